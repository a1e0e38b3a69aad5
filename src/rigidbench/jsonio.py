"""One way to write a JSON file so that a reader never sees half of it: a unique temporary file in
the same directory, then an atomic rename. Safe when several threads or processes write the same
path (the last rename wins, and each rename is of a complete file)."""

from __future__ import annotations

import json
import os
import tempfile
from pathlib import Path
from typing import Any


def write_json(path: str | Path, doc: Any, *, durable: bool = False, **dumps: Any) -> Path:
    """Write ``doc`` to ``path`` atomically; ``dumps`` go to ``json.dumps`` (default ``indent=1``).
    ``durable``: fsync before the rename (state that must survive a crash, e.g. a paid prediction's id)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    text = json.dumps(doc, **{"indent": 1, **dumps}) + "\n"
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "w") as fh:
            fh.write(text)
            if durable:
                fh.flush()
                os.fsync(fh.fileno())
        os.chmod(tmp, 0o644)  # mkstemp makes the file private to its owner; outputs are meant to be shared
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return path
