"""Reading a split archive as one stream, its MD5, and a safe extraction of it.

The parts are never joined on disk: ``ConcatenatedFiles`` reads them in order as one file, ``md5_of`` hashes
that stream, and ``safe_extract`` feeds it to ``tarfile`` in streaming mode (``r|gz``). Every member is
checked before anything of it is written: an absolute path, a ``..`` component, a symbolic or hard link, a
device or FIFO (or any type other than a regular file or a directory) aborts the extraction with an error
naming the member. Extraction goes into ``<dest>.tmp`` and is renamed to ``dest`` only when complete, so a
failed or interrupted extraction never leaves a folder that looks done.
"""

from __future__ import annotations

import contextlib
import hashlib
import io
import logging
import os
import shutil
import tarfile
import zlib
from pathlib import Path, PurePosixPath
from typing import Callable, Sequence

from ..atomic import atomic_dir, umask_mode
from ..errors import RigidBenchError

log = logging.getLogger(__name__)

_CHUNK = 1 << 20


class ArchiveError(RigidBenchError):
    """An archive that cannot be extracted: corrupt, truncated, or with an unsafe member (named)."""


class UnsafeMemberError(ArchiveError):
    """An archive member that would write outside the destination or is a link, device or FIFO."""


class ConcatenatedFiles(io.RawIOBase):
    """A read-only file over several files read one after another (the parts of a split archive).
    ``on_read(n)`` is called with the number of bytes each read returned (for a progress bar); ``digest``
    (a hashlib object) is updated with every byte read."""

    def __init__(self, paths: Sequence[str | Path], on_read: Callable[[int], None] | None = None, digest=None):
        super().__init__()
        self._paths = [Path(p) for p in paths]
        self._index = 0
        self._fh: io.BufferedReader | None = None
        self._on_read = on_read
        self._digest = digest
        self.position = 0

    def readable(self) -> bool:
        return True

    def readinto(self, buffer) -> int:  # type: ignore[override]
        view = memoryview(buffer).cast("B")
        while self._index < len(self._paths):
            if self._fh is None:
                self._fh = open(self._paths[self._index], "rb")
            n = self._fh.readinto(view)
            if n:
                self.position += n
                if self._digest is not None:
                    self._digest.update(view[:n])
                if self._on_read is not None:
                    self._on_read(n)
                return n
            self._fh.close()
            self._fh = None
            self._index += 1
        return 0

    def close(self) -> None:
        if self._fh is not None:
            self._fh.close()
            self._fh = None
        super().close()


def md5_of(paths: Sequence[str | Path], on_read: Callable[[int], None] | None = None) -> str:
    """The MD5 (hex) of the files' contents concatenated in order."""
    digest = hashlib.md5(usedforsecurity=False)
    with ConcatenatedFiles(paths, on_read) as stream:
        buffer = bytearray(_CHUNK)
        view = memoryview(buffer)
        while n := stream.readinto(buffer):
            digest.update(view[:n])
    return digest.hexdigest()


def member_path(member: tarfile.TarInfo, archive: str) -> PurePosixPath | None:
    """The member's relative path inside the destination (None for the archive's root, "." or "./"), or
    UnsafeMemberError when it is absolute, climbs with '..', or is not a regular file or a directory."""
    name = member.name
    what = f"{archive}: member '{name}'"
    if member.issym() or member.islnk():
        kind = "a symbolic link" if member.issym() else "a hard link"
        raise UnsafeMemberError(f"{what} is {kind} (to '{member.linkname}'); links are refused, nothing was kept")
    if member.ischr() or member.isblk() or member.isfifo():
        raise UnsafeMemberError(f"{what} is a device or FIFO; refused, nothing was kept")
    if not (member.isreg() or member.isdir()):
        raise UnsafeMemberError(f"{what} has an unsupported type {member.type!r}; refused, nothing was kept")
    if "\\" in name or name.startswith("/") or (len(name) > 1 and name[1] == ":"):
        raise UnsafeMemberError(f"{what} has an absolute path; refused, nothing was kept")
    parts = [p for p in name.split("/") if p not in ("", ".")]
    if ".." in parts:
        raise UnsafeMemberError(f"{what} climbs out of the destination with '..'; refused, nothing was kept")
    return PurePosixPath(*parts) if parts else None


#: what to do about an archive that is not a readable .tar.gz, after a download
DOWNLOAD_REMEDY = ("the download may be corrupt: verify it (do not pass --no-verify) or delete its parts and "
                   "download again")


def safe_extract(paths: Sequence[str | Path], dest: str | Path, *, archive: str | None = None,
                 on_read: Callable[[int], None] | None = None, digest=None,
                 remedy: str = DOWNLOAD_REMEDY) -> Path:
    """Extract the gzip'd tar made of ``paths`` (one archive, or its parts in order) into ``dest``, which must
    not exist: members go to ``<dest>.tmp`` (removed first if an earlier run left it), renamed to ``dest``
    when all are written. Only regular files (mode 0644) and directories are created. ``digest`` (a hashlib
    object) is updated with every byte of the archive, to its end (the MD5 in the same read). Raises
    ArchiveError (UnsafeMemberError for an unsafe member; ``remedy`` says what to do about an unreadable
    archive) and removes ``<dest>.tmp``; returns ``dest``."""
    dest = Path(dest)
    archive = archive or Path(paths[0]).name
    if dest.exists():
        raise ArchiveError(f"{dest}: already exists; remove it to extract {archive} again")
    tmp = dest.with_name(dest.name + ".tmp")  # the name download's free-space check and cleanup know
    if tmp.exists():
        log.info("removing %s left by an interrupted extraction", tmp)
    with atomic_dir(dest, tmp=tmp) as root:
        _extract_members(paths, root, archive, on_read, digest, remedy)
    return dest


def _extract_members(paths: Sequence[str | Path], root: Path, archive: str,
                     on_read: Callable[[int], None] | None, digest, remedy: str) -> None:
    files = 0
    try:
        with ConcatenatedFiles(paths, on_read, digest) as stream, tarfile.open(fileobj=stream, mode="r|gz") as tar:
            for member in tar:
                rel = member_path(member, archive)
                if rel is None:
                    continue
                target = root.joinpath(*rel.parts)
                # no link is ever created, so no path under root can lead outside it; checked anyway
                if os.path.commonpath([os.path.normpath(root), os.path.normpath(target)]) != os.path.normpath(root):
                    raise UnsafeMemberError(f"{archive}: member '{member.name}' would be written outside the "
                                            "destination; refused, nothing was kept")
                if member.isdir():
                    _mkdirs(target, root, archive, member.name)
                    continue
                _mkdirs(target.parent, root, archive, member.name)
                if target.is_dir():
                    raise ArchiveError(f"{archive}: member '{member.name}' is a file where the archive already "
                                       "made a directory; nothing was kept")
                source = tar.extractfile(member)
                assert source is not None  # a regular file
                with open(target, "wb") as out:
                    shutil.copyfileobj(source, out, _CHUNK)
                umask_mode(target)  # a member's own mode is not kept: as every other file we write
                with contextlib.suppress(OverflowError, ValueError, OSError):  # an odd mtime is not worth failing
                    os.utime(target, (member.mtime, member.mtime))
                files += 1
            if digest is not None:  # the tar's end marker may come before the file's end: hash the rest
                buffer = bytearray(_CHUNK)
                while stream.readinto(buffer):
                    pass
    except (tarfile.TarError, zlib.error, EOFError) as exc:
        raise ArchiveError(f"{archive}: not a readable .tar.gz ({type(exc).__name__}: {exc}); {remedy}") from None
    if not files:
        raise ArchiveError(f"{archive}: the archive holds no files")


def _mkdirs(path: Path, root: Path, archive: str, member: str) -> None:
    try:
        path.mkdir(parents=True, exist_ok=True)
    except (FileExistsError, NotADirectoryError):
        raise ArchiveError(f"{archive}: member '{member}' needs a directory where the archive already wrote a "
                           "file; nothing was kept") from None
