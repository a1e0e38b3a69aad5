"""One way to write a JSON file so that a reader never sees half of it: a unique temporary file in
the same directory, then an atomic rename. Safe when several threads or processes write the same
path (the last rename wins, and each rename is of a complete file). And one way to read back a JSON
file that a killed run or a user may have damaged: ``read_json`` treats it as absent, saying so."""

from __future__ import annotations

import json
import logging
from pathlib import Path
from typing import Any

from .atomic import write_text

log = logging.getLogger(__name__)


def write_json(path: str | Path, doc: Any, *, durable: bool = False, **dumps: Any) -> Path:
    """Write ``doc`` to ``path`` atomically; ``dumps`` go to ``json.dumps`` (default ``indent=1``).
    ``durable``: fsync before the rename (state that must survive a crash, e.g. a paid prediction's id)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    text = json.dumps(doc, **{"indent": 1, **dumps}) + "\n"
    # unique: several writers may write one path; mode: outputs are meant to be shared
    return write_text(path, text, unique=True, mode=0o644, durable=durable)


def read_json(path: str | Path, then: str = "ignored") -> Any:
    """The JSON document at ``path``; None when there is none, or when it cannot be read or parsed (a
    truncated or foreign file: logged as a warning ending in ``then``, what happens instead)."""
    path = Path(path)
    try:
        return json.loads(path.read_text())
    except FileNotFoundError:
        return None
    except (OSError, ValueError) as exc:
        log.warning("%s: unreadable (%s); %s", path, type(exc).__name__, then)
        return None
