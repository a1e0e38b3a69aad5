"""One way to write a JSON file so that a reader never sees half of it: a unique temporary file in
the same directory, then an atomic rename. Safe when several threads or processes write the same
path (the last rename wins, and each rename is of a complete file). And one way to read back a JSON
file that a killed run or a user may have damaged: ``load_json`` says why it cannot be used (DamagedJSON),
``read_json`` treats it as absent, saying so."""

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
    # unique: several writers may write one path (its file gets the umask's mode, as every output)
    return write_text(path, text, unique=True, durable=durable)


class DamagedJSON(ValueError):
    """A JSON file that is there but cannot be used: the message says why (empty, truncated or not JSON, not
    UTF-8 text, a directory, or a document of another type than expected)."""


_TYPE_NAMES = {dict: "a JSON object", list: "a JSON list", str: "a JSON string", bool: "a JSON boolean",
               int: "a JSON number", float: "a JSON number", type(None): "JSON null"}


def load_json(path: str | Path, expect: type | None = None) -> Any:
    """The JSON document at ``path``, checked to be an ``expect`` (e.g. ``dict``) when given.
    FileNotFoundError when there is none; DamagedJSON saying why when it cannot be used (what a killed run,
    a full disk or a user may leave: an empty or cut file, foreign bytes, a directory, another document)."""
    path = Path(path)
    try:
        raw = path.read_bytes()
    except FileNotFoundError:
        raise
    except IsADirectoryError:
        raise DamagedJSON(f"{path}: a directory, not a JSON file") from None
    except OSError as exc:
        raise DamagedJSON(f"{path}: cannot be read ({exc.strerror or type(exc).__name__})") from None
    if not raw.strip():
        raise DamagedJSON(f"{path}: empty")
    try:
        doc = json.loads(raw.decode("utf-8"))
    except UnicodeDecodeError:
        raise DamagedJSON(f"{path}: not UTF-8 text") from None
    except ValueError as exc:
        raise DamagedJSON(f"{path}: truncated or not JSON ({exc})") from None
    if expect is not None and not isinstance(doc, expect):
        want = _TYPE_NAMES.get(expect, expect.__name__)
        raise DamagedJSON(f"{path}: holds {_TYPE_NAMES.get(type(doc), type(doc).__name__)}, not {want}")
    return doc


def read_json(path: str | Path, then: str = "ignored", expect: type | None = None) -> Any:
    """The JSON document at ``path`` (an ``expect``, when given); None when there is none, or when it cannot be
    used (``load_json``'s DamagedJSON, logged as a warning saying why and ending in ``then``, what happens
    instead)."""
    try:
        return load_json(path, expect)
    except FileNotFoundError:
        return None
    except (OSError, ValueError) as exc:  # DamagedJSON; OSError: e.g. a file where a parent folder should be
        reason = str(exc) if isinstance(exc, DamagedJSON) else f"{path}: unreadable ({type(exc).__name__})"
        log.warning("%s; %s", reason, then)
        return None
