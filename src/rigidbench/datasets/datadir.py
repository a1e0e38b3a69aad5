"""The ``--data`` folder of ``download`` and ``import``: made usable (a file there is one clear error), and
held by one run at a time (an advisory lock file, so two runs never write the same bundles at once)."""

from __future__ import annotations

import contextlib
from pathlib import Path
from typing import Iterator

from ..errors import UserError

#: the lock file ``download`` and ``import`` hold in DATA while they run
LOCK_FILE = ".import.lock"

_HELD: dict[str, int] = {}  # lock files this process holds -> depth (the lock is re-entrant within a process)


class DataBusyError(UserError):
    """Another run is downloading or importing into the same ``--data``."""


def format_bytes(n: float) -> str:
    """A byte count for people: "812 bytes", "3.4 MB", "18.2 GB" (powers of 1000)."""
    for unit in ("bytes", "kB", "MB", "GB", "TB"):
        if abs(n) < 1000 or unit == "TB":
            return f"{n:,.0f} {unit}" if unit == "bytes" else f"{n:,.1f} {unit}"
        n /= 1000
    return ""  # unreachable


def prepare_data_dir(data: str | Path) -> Path:
    """``data`` as a folder, created when missing; UserError (one line) when it, or a folder above it, is a
    file, or it cannot be created."""
    data = Path(data)
    if data.exists() and not data.is_dir():
        raise UserError(f"--data {data}: this is a file, not a folder; pass a folder (it is created if missing)")
    try:
        data.mkdir(parents=True, exist_ok=True)
    except (FileExistsError, NotADirectoryError):
        raise UserError(f"--data {data}: a part of this path is a file, not a folder; pass another folder") from None
    except OSError as exc:
        raise UserError(f"--data {data}: cannot create it ({exc.strerror or exc})") from None
    return data


@contextlib.contextmanager
def hold_lock(path: Path, error: UserError, reentrant: bool = False) -> Iterator[None]:
    """Hold an exclusive advisory lock on the file ``path`` (created if missing) for the duration; raise
    ``error`` when another process (or another open of the file) holds it. ``reentrant``: a nested hold in
    this process passes. No lock where ``fcntl`` is missing (Windows)."""
    try:
        import fcntl
    except ImportError:  # Windows: no lock
        yield
        return
    key = str(path.resolve())
    if reentrant and _HELD.get(key):
        _HELD[key] += 1
        try:
            yield
        finally:
            _HELD[key] -= 1
        return
    with open(path, "a") as fh:
        try:
            fcntl.flock(fh.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            raise error from None
        _HELD[key] = _HELD.get(key, 0) + 1
        try:
            yield
        finally:
            _HELD[key] -= 1
            fcntl.flock(fh.fileno(), fcntl.LOCK_UN)


def data_lock(data: str | Path) -> contextlib.AbstractContextManager[None]:
    """Hold ``DATA/.import.lock`` (``data`` must exist; re-entrant: ``download`` holds it and then imports):
    DataBusyError when another download or import holds it."""
    path = Path(data) / LOCK_FILE
    return hold_lock(path, DataBusyError(
        f"--data {data}: another rigidbench download or import is writing there (it holds {path}); wait for it "
        "to finish, or choose another --data"), reentrant=True)


__all__ = ["DataBusyError", "LOCK_FILE", "data_lock", "format_bytes", "hold_lock", "prepare_data_dir"]
