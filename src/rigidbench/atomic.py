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

Permissions: every file and directory these write gets the mode the user's umask gives a new one
(``umask_mode``), whatever its writer made it (``mkstemp`` and some libraries make files private), so all
kinds of output are alike: 0644 files under umask 022, 0600 under 077.

Write failures: an ``OSError`` that means the output cannot be written there (``WRITE_ERRNOS``: a full disk,
a read-only file system, no permission, a file or folder in the way) comes out of ``atomic_file`` as a
``WriteError`` naming the final path and what to do, also where the writer's own error named no file (a
failed ``write()``). Standard library only: ``rigidbench.benchmark`` (imported by ``import rigidbench``)
uses it.
"""

from __future__ import annotations

import contextlib
import errno
import os
import shutil
import stat
import tempfile
import threading
import zipfile
from contextlib import contextmanager
from pathlib import Path
from typing import Iterator

#: errno values meaning "this output cannot be written here", as opposed to a bad input or a bug
WRITE_ERRNOS = frozenset({errno.ENOSPC, errno.EDQUOT, errno.EROFS, errno.EACCES, errno.EPERM, errno.ENOTDIR,
                          errno.EISDIR, errno.EFBIG})
_WHAT_TO_DO = {
    errno.ENOSPC: "free some space and rerun (finished work is kept)",
    errno.EDQUOT: "free some space (a disk quota is full) and rerun (finished work is kept)",
    errno.EROFS: "the file system is read-only; write somewhere else",
    errno.EACCES: "no permission to write there; write somewhere else or change its permissions",
    errno.EPERM: "no permission to write there; write somewhere else or change its permissions",
    errno.ENOTDIR: "a file is in the way where a folder should be; move it aside",
    errno.EISDIR: "a folder is in the way where a file should be; move it aside",
    errno.EFBIG: "the file is too large for this file system; write somewhere else",
}


_ONLY_IN_WRITING = frozenset({errno.ENOSPC, errno.EDQUOT, errno.EROFS, errno.EFBIG})


class WriteError(OSError):
    """An output that cannot be written: ``str()`` is one line naming the file, the reason and what to do.
    An ``OSError`` (per-example loops record it as that example's failure; the command line prints it)."""

    def __str__(self) -> str:
        hint = _WHAT_TO_DO.get(self.errno)
        return f"cannot write {self.filename}: {self.strerror}" + (f"; {hint}" if hint else "")


def describe_os_error(exc: OSError) -> str:
    """One line for an ``OSError``: the path it names (the target of a rename), the reason and, for
    ``WRITE_ERRNOS``, what to do."""
    if isinstance(exc, WriteError):
        return str(exc)
    path = exc.filename2 if exc.filename2 is not None else exc.filename
    reason = exc.strerror or str(exc) or type(exc).__name__
    hint = _WHAT_TO_DO.get(exc.errno) if exc.errno in _ONLY_IN_WRITING else None  # others: reading, too
    return (f"{path}: " if path is not None else "") + reason + (f"; {hint}" if hint else "")


def as_write_error(exc: OSError, path: str | Path) -> OSError:
    """``exc`` as a ``WriteError`` naming ``path`` when it is one of ``WRITE_ERRNOS``; otherwise ``exc``."""
    if exc.errno not in WRITE_ERRNOS or isinstance(exc, WriteError):
        return exc
    return WriteError(exc.errno, exc.strerror or os.strerror(exc.errno), str(path))


_umask_lock = threading.Lock()


def current_umask() -> int:
    """The process's umask, read without changing it where the system says it (Linux: /proc/self/status)."""
    with contextlib.suppress(OSError, ValueError, IndexError):
        with open("/proc/self/status", encoding="ascii", errors="replace") as fh:
            for line in fh:
                if line.startswith("Umask:"):
                    return int(line.split()[1], 8)
    with _umask_lock:  # elsewhere: set and restore it (a moment in which other threads' new files get 022)
        mask = os.umask(0o022)
        os.umask(mask)
    return mask


def umask_mode(path: str | Path) -> None:
    """Give ``path`` the mode the umask gives a new file (0666 less the umask) or directory (0777 less it),
    keeping a file's execute bits only when it had some. A symbolic link is left alone. The one place our
    outputs' permissions are set: temporaries from ``mkstemp``/``mkdtemp`` and files some libraries create
    are private to their owner, and an output's kind must not decide who may read it."""
    st = os.lstat(path)
    if stat.S_ISLNK(st.st_mode):
        return
    full = 0o777 if stat.S_ISDIR(st.st_mode) or st.st_mode & 0o111 else 0o666
    mode = full & ~current_umask()
    if stat.S_IMODE(st.st_mode) != mode:
        with contextlib.suppress(OSError):  # a file system without Unix modes (vfat, some network mounts) refuses
            os.chmod(path, mode)


def release_open_writers(exc: BaseException, where: str | Path) -> None:
    """Close, quietly, the zip files a failed writer left open at or under ``where`` (``np.savez`` leaves
    its ZipFile to the garbage collector, whose close fails again on a full disk and prints "Exception
    ignored in ZipFile.__del__"); closed here, they are never closed again."""
    where = os.path.abspath(where)

    def writing_there(value) -> bool:
        if not (isinstance(value, zipfile.ZipFile) and value.fp is not None and value.mode != "r"
                and isinstance(value.filename, str)):
            return False
        name = os.path.abspath(value.filename)
        return name == where or name.startswith(os.path.join(where, ""))

    tb = exc.__traceback__
    while tb is not None:
        for value in list(tb.tb_frame.f_locals.values()):
            if writing_there(value):
                with contextlib.suppress(Exception):
                    value.close()
                if value.fp is not None:  # close refused (a member still open): drop the file unfinished
                    with contextlib.suppress(Exception):
                        value.fp.close()
                    value.fp = None
        tb = tb.tb_next


def fsync_file(path: str | Path) -> None:
    """Flush a file's data to disk (before a rename that must survive a crash)."""
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


@contextmanager
def atomic_file(path: str | Path, *, suffix: str = "", tmp: str | Path | None = None, unique: bool = False,
                durable: bool = False) -> Iterator[Path]:
    """Yield a temporary path beside ``path`` to write; rename it onto ``path`` when the block ends, remove
    it when the block raises. ``tmp``: the temporary's own name (a stage whose leftovers are cleaned up by
    name); ``durable``: fsync before the rename (state that must survive a crash). The file gets the
    umask's mode (``umask_mode``); a write failure of ``WRITE_ERRNOS`` about the temporary (or about no file:
    a failed ``write()``) is raised as a ``WriteError`` naming ``path``."""
    path = Path(path)
    try:
        if tmp is not None:
            tmp = Path(tmp)
        elif unique:
            fd, name = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=f".tmp{suffix}")
            os.close(fd)
            tmp = Path(name)
        else:
            tmp = path.with_name(f".{path.name}.tmp{suffix}")
    except OSError as exc:
        raise as_write_error(exc, path) from None
    try:
        yield tmp
        if durable:
            fsync_file(tmp)
        umask_mode(tmp)
        tmp.replace(path)
    except BaseException as exc:
        release_open_writers(exc, tmp)
        with contextlib.suppress(OSError):  # e.g. on a read-only file system: the first error is the one to show
            tmp.unlink(missing_ok=True)
        if (isinstance(exc, OSError) and exc.errno in WRITE_ERRNOS and _names(exc.filename, None, tmp)
                and _names(exc.filename2, None, path)):  # about our temporary (or no file): name the output
            raise WriteError(exc.errno, exc.strerror or os.strerror(exc.errno), str(path)) from None
        raise


def _names(filename, *paths) -> bool:
    """Whether an OSError's ``filename`` is one of ``paths`` (None: it names none)."""
    return any(filename is None if p is None else filename is not None and os.fspath(filename) == os.fspath(p)
               for p in paths)


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
    elif (dst.is_dir() and not dst.is_symlink()) or src.is_dir():  # (a directory onto a file: the same way)
        old = dst.with_name(f".{dst.name}.old-{os.getpid()}")
        shutil.rmtree(old, ignore_errors=True)
        dst.rename(old)
        src.rename(dst)
        shutil.rmtree(old, ignore_errors=True) if old.is_dir() and not old.is_symlink() else old.unlink()
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
        umask_mode(tmp)  # mkdtemp makes it private
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
