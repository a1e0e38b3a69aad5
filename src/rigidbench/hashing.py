"""The content hashes of stage keys: ``digest`` of JSON-serialisable parts and ``file_digest`` of a file's bytes
(base layer: whatever computes a key imports this, not the stage driver)."""

from __future__ import annotations

import hashlib
import json
from pathlib import Path
from typing import Any


def digest(*parts: Any) -> str:
    """A stable hex key of JSON-serialisable parts (sorted keys; paths and other objects as text)."""
    text = json.dumps(parts, sort_keys=True, default=str, separators=(",", ":"))
    return hashlib.sha256(text.encode()).hexdigest()


def file_digest(path: str | Path, chunk: int = 1 << 20) -> str:
    """The sha256 hex digest of a file's content (read in chunks): the one content hash of keys."""
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        while block := fh.read(chunk):
            h.update(block)
    return h.hexdigest()


__all__ = ["digest", "file_digest"]
