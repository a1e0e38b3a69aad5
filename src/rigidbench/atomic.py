"""Atomic writes: a file or a directory is built under a temporary name beside its final one and renamed
into place when complete, so a reader (or a rerun after a kill) never sees half of it.

- ``atomic_file(path)``: yields the temporary path for any writer (text, bytes, ``np.savez``, an encoder);
  on a normal exit it is renamed onto ``path``, on an exception it is removed. ``write_text`` and
  ``write_bytes`` are the two common cases; ``jsonio.write_json`` is the JSON one.
- ``atomic_dir(path)``: the same for a directory.
- ``replace_path(src, dst)``: put a finished file or directory in place of whatever is at ``dst``.

Temporaries are hidden siblings, ``.<name>.tmp<suffix>`` (``unique``: ``.<name>.<random>.tmp<suffix>``,
for paths that several threads or processes may write at once; the last rename wins). A writer that
appends an extension (``np.savez`` adds ``.npz``) gets a temporary ending in it through ``suffix``.
Standard library only: ``rigidbench.benchmark`` (imported by ``import rigidbench``) uses it.
"""

from __future__ import annotations

import os
import shutil
import tempfile
from contextlib import contextmanager
from pathlib import Path
from typing import Iterator


def fsync_file(path: str | Path) -> None:
    """Flush a file's data to disk (before a rename that must survive a crash)."""
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


@contextmanager
def atomic_file(path: str | Path, *, suffix: str = "", tmp: str | Path | None = None, unique: bool = False,
                mode: int | None = None, durable: bool = False) -> Iterator[Path]:
    """Yield a temporary path beside ``path`` to write; rename it onto ``path`` when the block ends, remove
    it when the block raises. ``tmp``: the temporary's own name (a stage whose leftovers are cleaned up by
    name); ``mode``: chmod before the rename (``unique`` temporaries are created private to their owner);
    ``durable``: fsync before the rename (state that must survive a crash)."""
    path = Path(path)
    if tmp is not None:
        tmp = Path(tmp)
    elif unique:
        fd, name = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=f".tmp{suffix}")
        os.close(fd)
        tmp = Path(name)
    else:
        tmp = path.with_name(f".{path.name}.tmp{suffix}")
    try:
        yield tmp
        if durable:
            fsync_file(tmp)
        if mode is not None:
            os.chmod(tmp, mode)
        tmp.replace(path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def write_text(path: str | Path, text: str, *, encoding: str | None = None, **options) -> Path:
    """Write ``text`` to ``path`` atomically (``options``: those of ``atomic_file``)."""
    with atomic_file(path, **options) as tmp:
        tmp.write_text(text, encoding=encoding)
    return Path(path)


def write_bytes(path: str | Path, data: bytes, **options) -> Path:
    """Write ``data`` to ``path`` atomically (``options``: those of ``atomic_file``)."""
    with atomic_file(path, **options) as tmp:
        tmp.write_bytes(data)
    return Path(path)


def replace_path(src: str | Path, dst: str | Path) -> None:
    """Rename ``src`` (a complete file or directory) onto ``dst``, replacing whatever is there: a file in one
    atomic rename; a directory whole (the old one is moved aside first and removed once the new one is in
    place, so ``dst`` is never half of either). A file is fsynced first."""
    src, dst = Path(src), Path(dst)
    if src.is_file() and not src.is_symlink():
        fsync_file(src)
    if not (dst.exists() or dst.is_symlink()):
        src.rename(dst)
    elif dst.is_dir() and not dst.is_symlink():
        old = dst.with_name(f".{dst.name}.old-{os.getpid()}")
        shutil.rmtree(old, ignore_errors=True)
        dst.rename(old)
        src.rename(dst)
        shutil.rmtree(old, ignore_errors=True)
    else:
        src.replace(dst)


@contextmanager
def atomic_dir(path: str | Path, *, tmp: str | Path | None = None, unique: bool = False,
               replace: bool = False) -> Iterator[Path]:
    """Yield a fresh temporary directory beside ``path`` to fill; rename it to ``path`` when the block ends,
    remove it when the block raises. A leftover at ``tmp`` (a killed run's) is removed first. ``replace``:
    an existing ``path`` is moved aside and removed once the new one is in place; otherwise the rename
    fails on a non-empty ``path``."""
    path = Path(path)
    if unique:
        tmp = Path(tempfile.mkdtemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent))
    else:
        tmp = Path(tmp) if tmp is not None else path.with_name(f".{path.name}.tmp")
        if tmp.exists():
            shutil.rmtree(tmp)
        tmp.mkdir(parents=True)
    try:
        yield tmp
        if replace:
            replace_path(tmp, path)
        else:
            tmp.replace(path)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
