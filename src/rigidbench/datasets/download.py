"""Download a published dataset: resumable parts, the MD5 of the whole, a safe extraction, a completion marker.

Everything lives in ``<data>/.download/<id>/``::

    <part>.part      a part still being fetched (HTTP Range continues it from its size)
    <part>           a complete part (the right size; never fetched again)
    verified.json    the MD5 of the whole matched (with each part's size and mtime, so it is not recomputed)
    extracted.tmp/   an extraction in progress (removed and redone if a run stopped during it)
    extracted/       the complete extraction (renamed from extracted.tmp)
    complete.json    id, version, md5, time: the download is done (written last, atomically)
    imported.json    the samples a complete import made (``rigidbench download``, commands/data.py)

A run stopped at any moment (mid-part, between parts, during the MD5, during the extraction, before or while
the parts are deleted) is finished by running it again, without fetching what is already on disk. Only one
run at a time may use the folder (a lock file). Network failures (connection errors, timeouts, a server that
trickles below ``min_bytes_per_s``, HTTP 429 and 5xx) are retried with exponential backoff, a bounded number
of times per part; then the error names the part and its URL and says to rerun to resume.

The free-disk check counts, at the fullest moment, what is still to download, the extraction and the import's
own files (up to the archive's size, written after the parts are deleted unless they are kept). Once the
download is complete, ``extracted/`` may be deleted (the imported bundles hold their own files): nothing is
fetched again for it (``ExtractionDeletedError`` says how to download afresh; kept parts are extracted again).
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import logging
import os
import shutil
import sys
import time
from dataclasses import dataclass
from datetime import datetime, timezone
from importlib import metadata
from pathlib import Path
from typing import Any

from ..errors import RigidBenchError, UserError
from ..extras import require
from ..jsonio import write_json
from ..logsafe import install_filter, public_url
from .datadir import format_bytes, hold_lock, prepare_data_dir
from .describe import DatasetDescription, DatasetPart
from .extract import safe_extract

# httpx logs every request's full URL at INFO: its records are scrubbed even where the command line's logging
# (logsafe.configure_logging) is not in use, e.g. a download called from Python.
install_filter(("httpx", "httpcore.connection", "httpcore.http11", __name__))

log = logging.getLogger(__name__)

DOWNLOAD_DIR = ".download"
MARKER = "complete.json"
VERIFIED = "verified.json"
_CHUNK = 1 << 20


class DownloadError(RigidBenchError):
    """A part could not be fetched (retries exhausted, or an answer that cannot be used); names the part, the
    URL and what to do next."""


class DiskSpaceError(UserError):
    """Not enough free disk space for what is still to download plus the extraction."""


class ChecksumError(RigidBenchError):
    """The downloaded archive's MD5 is not the one its description gives."""


class DownloadBusyError(UserError):
    """Another run is downloading into the same folder."""


class ExtractionDeletedError(UserError):
    """A finished download whose extraction was deleted (and whose parts are gone): never fetched again
    silently."""


@dataclass(frozen=True)
class TransferSettings:
    """Network and disk limits of a download (the defaults suit a large archive over a slow link)."""

    connect_timeout_s: float = 30.0
    read_timeout_s: float = 60.0  # longest wait for the next bytes of an answer
    retries: int = 5  # failed requests in a row for one part with no byte received, before giving up
    max_requests_per_part: int = 50  # requests for one part in all (progress or not), before giving up
    backoff_s: float = 2.0  # the wait after the first failure; doubles after each failure in a row
    backoff_max_s: float = 60.0  # and never exceeds this (a Retry-After is honoured up to it)
    min_bytes_per_s: float = 16 * 1024  # an answer slower than this over a whole window is dropped and resumed
    throughput_window_s: float = 60.0
    disk_margin_bytes: int = 512 * 1024 * 1024  # free space kept beyond the download and the extraction
    disk_margin_fraction: float = 0.02  # ... or this fraction of the archive, whichever is larger
    #: what the import writes (its own depth, masks, tracks; frames and video are hard-linked), as a fraction of
    #: the archive: an upper bound (it rewrites at most what the archive holds besides frames and video)
    import_fraction: float = 1.0


#: what the import measured (benchmarks/published_import.py; 2-core machine, CPU time), said by the disk check
IMPORT_MEASURED = ("on a synthetic paper-size sample (1280x704, 49 frames) the import wrote 10% of the sample's "
                   "bytes in 4.8 s of CPU")


def download_dir(desc: DatasetDescription, data: str | Path) -> Path:
    """The folder that holds the dataset's parts, markers and extraction: ``<data>/.download/<id>``."""
    return Path(data) / DOWNLOAD_DIR / desc.id


def extracted_dir(desc: DatasetDescription, data: str | Path) -> Path:
    """Where the archive's content lands: ``<data>/.download/<id>/extracted``."""
    return download_dir(desc, data) / "extracted"


def read_marker(desc: DatasetDescription, data: str | Path) -> dict[str, Any] | None:
    """The completion marker of a finished download (None when there is none); DownloadError when it records
    another archive than ``desc`` describes."""
    path = download_dir(desc, data) / MARKER
    try:
        marker = json.loads(path.read_text())
    except FileNotFoundError:
        return None
    except (OSError, ValueError) as exc:
        raise DownloadError(f"{path}: unreadable completion marker ({exc}); delete it and run again") from None
    if marker.get("id") != desc.id or marker.get("md5") != desc.md5:
        raise DownloadError(f"{path}: records {marker.get('id')} with MD5 {marker.get('md5')}, but {desc.source} "
                            f"describes {desc.id} with MD5 {desc.md5}; delete {path.parent} to download it afresh")
    return marker


def download_dataset(desc: DatasetDescription, data: str | Path, *, keep_archive: bool = False, verify: bool = True,
                     progress: bool = True, client: Any = None, settings: TransferSettings | None = None) -> Path:
    """Fetch, verify and extract ``desc`` under ``data``; returns the extracted folder
    (``<data>/.download/<id>/extracted``). Resumes whatever an earlier run left; a finished download is
    returned at once without any request. ``keep_archive`` keeps the parts after extraction; ``verify=False``
    skips the MD5; ``client`` is an ``httpx.Client`` to use (else one is made, honouring proxy variables).
    Raises DiskSpaceError, DownloadError, ChecksumError, extract.ArchiveError, DownloadBusyError."""
    settings = settings or TransferSettings()
    prepare_data_dir(data)
    root = download_dir(desc, data)
    root.mkdir(parents=True, exist_ok=True)
    extracted = extracted_dir(desc, data)
    with _lock(root):
        marker = read_marker(desc, data)
        if marker is not None and extracted.is_dir():
            if not marker.get("archive_kept"):
                _delete_parts(desc, root)  # finishes a deletion that was interrupted
            return extracted
        if marker is not None and not _parts_on_disk(desc, root):
            raise ExtractionDeletedError(
                f"{extracted}: deleted after the download finished, and its parts are gone; nothing is fetched "
                f"again on its own. To download {desc.id} afresh ({_size(desc.size_bytes)}), delete "
                f"{root / MARKER} and run again")
        if extracted.is_dir():  # extracted, but stopped before the marker was written
            verified = _verified_record_matches(desc, root)
        else:  # (with a marker: the extraction was deleted but the parts were kept: extracted again from them)
            _check_disk(desc, root, settings, keep_archive)
            _fetch_parts(desc, root, client, settings, progress)
            paths = [root / p.name for p in desc.parts]
            verified = _verify(desc, root, progress) if verify else _verified_record_matches(desc, root)
            with _bar(desc.size_bytes, 0, f"extract {desc.archive}", progress) as bar:
                safe_extract(paths, extracted, archive=desc.archive, on_read=bar.update)
        write_json(root / MARKER, {
            "id": desc.id, "name": desc.name, "version": desc.version, "archive": desc.archive, "md5": desc.md5,
            "md5_verified": verified, "size_bytes": desc.size_bytes, "archive_kept": keep_archive,
            "completed_at": datetime.now(timezone.utc).isoformat(timespec="seconds"), "source": desc.source,
        }, durable=True)
        if not keep_archive:
            _delete_parts(desc, root)
        log.info("%s %s is in %s", desc.name, desc.version, extracted)
        return extracted


# ---------------------------------------------------------------------------------------------
# Fetching


class _Retryable(Exception):
    def __init__(self, reason: str, after_s: float | None = None):
        super().__init__(reason)
        self.reason, self.after_s = reason, after_s


def _fetch_parts(desc: DatasetDescription, root: Path, client: Any, settings: TransferSettings,
                 progress: bool) -> None:
    todo = []
    have_bytes = 0
    for part in desc.parts:
        final = root / part.name
        if final.exists():
            size = final.stat().st_size
            if size == part.size_bytes:
                have_bytes += size
                continue
            if size > part.size_bytes:
                raise DownloadError(f"{final}: {size:,} bytes, but {desc.source} gives this part {part.size_bytes:,}; "
                                    "delete it (or fix the description) and run again")
            os.replace(final, root / f"{part.name}.part")  # short: resume it
        tmp = root / f"{part.name}.part"
        have_bytes += min(tmp.stat().st_size, part.size_bytes) if tmp.exists() else 0
        todo.append(part)
    if not todo:
        return
    owned = client is None
    if owned:
        client = _make_client(settings)
    try:
        with _bar(desc.size_bytes, have_bytes, f"download {desc.archive}", progress) as bar:
            for part in todo:
                _fetch_part(client, desc, part, root, settings, bar)
    finally:
        if owned:
            client.close()


def _httpx():
    return require("httpx", "downloading a dataset")


def _make_client(settings: TransferSettings):
    httpx = _httpx()
    try:
        version = metadata.version("rigidbench")
    except metadata.PackageNotFoundError:
        version = "dev"
    return httpx.Client(follow_redirects=True, headers={"User-Agent": f"rigidbench/{version}"},
                        timeout=_timeout(settings))


def _timeout(settings: TransferSettings):
    httpx = _httpx()
    return httpx.Timeout(connect=settings.connect_timeout_s, read=settings.read_timeout_s,
                         write=settings.read_timeout_s, pool=settings.connect_timeout_s)


def _fetch_part(client: Any, desc: DatasetDescription, part: DatasetPart, root: Path, settings: TransferSettings,
                bar: Any) -> None:
    """Fetch one part into ``<part>.part`` (continuing it) and rename it to ``<part>`` when complete."""
    tmp, final = root / f"{part.name}.part", root / part.name
    failures = requests = 0
    while True:
        have = tmp.stat().st_size if tmp.exists() else 0
        if have > part.size_bytes:  # not ours to keep: longer than the part can be
            log.warning("%s: %d bytes, more than the part's %d; fetching it again", tmp, have, part.size_bytes)
            bar.update(-part.size_bytes)
            tmp.unlink()
            have = 0
        if have == part.size_bytes:
            with open(tmp, "rb+") as fh:
                os.fsync(fh.fileno())
            os.replace(tmp, final)
            log.info("%s: complete (%d bytes, %d requests)", part.name, part.size_bytes, requests)
            return
        requests += 1
        received = [0]
        try:
            _request_part(client, desc, part, tmp, have, settings, bar, received)
            continue  # the loop checks the size (an answer that ended early raises _Retryable)
        except _Retryable as exc:
            failures = 0 if received[0] else failures + 1
            where = f"part {part.name} of {desc.archive} ({public_url(part.url)})"
            if failures > settings.retries or requests >= settings.max_requests_per_part:
                raise DownloadError(f"{where}: {exc.reason}; gave up after {requests} requests. What is downloaded "
                                    f"is kept in {root}: run the same command again to resume") from None
            pause = min(settings.backoff_max_s, settings.backoff_s * 2 ** max(failures - 1, 0))
            if exc.after_s is not None:
                pause = min(settings.backoff_max_s, max(pause, exc.after_s))
            log.warning("%s: %s; retrying in %.1f s", where, exc.reason, pause)
            time.sleep(pause)


def _request_part(client: Any, desc: DatasetDescription, part: DatasetPart, tmp: Path, have: int,
                  settings: TransferSettings, bar: Any, received: list[int]) -> None:
    """One GET of the part from byte ``have`` on, appended to ``tmp``; ``received[0]`` counts the bytes
    written. Raises _Retryable for what another request may fix, DownloadError for what it cannot."""
    httpx = _httpx()
    where = f"part {part.name} of {desc.archive} ({public_url(part.url)})"
    headers = {"Accept-Encoding": "identity"}
    if have:
        headers["Range"] = f"bytes={have}-"
    try:
        with client.stream("GET", part.url, headers=headers, timeout=_timeout(settings)) as response:
            status = response.status_code
            if status == 429 or status >= 500:
                raise _Retryable(f"HTTP {status}", _retry_after(response.headers.get("retry-after")))
            if status == 416 and have:  # the server's file is shorter than what we have: start over
                log.warning("%s: the server refused to resume at byte %d (HTTP 416); fetching it again", where, have)
                tmp.unlink()
                bar.update(-have)
                raise _Retryable("HTTP 416 (range not satisfiable)")
            if status not in (200, 206):
                raise DownloadError(f"{where}: HTTP {status}; check the URL in {desc.source}")
            start = 0
            if status == 206:
                start, total = _content_range(response.headers.get("content-range"))
                if total is not None and total != part.size_bytes:
                    raise DownloadError(f"{where}: the server has {total:,} bytes, but {desc.source} gives this part "
                                        f"{part.size_bytes:,}; is the description for this server's release?")
                if start not in (have, 0):
                    raise _Retryable(f"the server answered from byte {start}, not {have}")
            else:
                length = response.headers.get("content-length")
                if length is not None and length.isdigit() and int(length) != part.size_bytes:
                    raise DownloadError(f"{where}: the server has {int(length):,} bytes, but {desc.source} gives "
                                        f"this part {part.size_bytes:,}; is the description for this server's release?")
            if start == 0 and have:  # the server ignored Range (200) or restarted: this part starts over
                log.info("%s: the server did not resume at byte %d; fetching the part from its start", where, have)
                bar.update(-have)
                have = 0
            left = part.size_bytes - have
            window_start, window_bytes = time.monotonic(), 0
            with open(tmp, "ab" if have else "wb") as fh:
                for chunk in response.iter_raw():
                    if len(chunk) > left:
                        fh.write(chunk[:left])
                        bar.update(left)
                        raise DownloadError(f"{where}: the server sent more than the {part.size_bytes:,} bytes "
                                            f"{desc.source} gives this part; is the description for this release?")
                    fh.write(chunk)
                    left -= len(chunk)
                    received[0] += len(chunk)
                    bar.update(len(chunk))
                    now = time.monotonic()
                    if now - window_start >= settings.throughput_window_s:
                        rate = (received[0] - window_bytes) / (now - window_start)
                        if rate < settings.min_bytes_per_s:
                            raise _Retryable(f"too slow ({rate:,.0f} bytes/s over {now - window_start:.0f} s, below "
                                             f"{settings.min_bytes_per_s:,.0f})")
                        window_start, window_bytes = now, received[0]
            if left:
                raise _Retryable(f"the answer ended {left:,} bytes before the end of the part")
    except httpx.TransportError as exc:  # connection refused or reset, timeouts, a body cut short
        raise _Retryable(f"{type(exc).__name__}: {exc}" if str(exc) else type(exc).__name__) from None


def _retry_after(value: str | None) -> float | None:
    try:
        return max(0.0, float(value)) if value is not None else None
    except ValueError:
        return None  # an HTTP date: use our own backoff


def _content_range(value: str | None) -> tuple[int, int | None]:
    """(first byte, total size or None) of a ``Content-Range: bytes a-b/total`` header."""
    try:
        unit, _, rest = (value or "").partition(" ")
        span, _, total = rest.partition("/")
        if unit != "bytes":
            raise ValueError
        return int(span.partition("-")[0]), (None if total == "*" else int(total))
    except ValueError:
        raise _Retryable(f"an unusable Content-Range {value!r}") from None


# ---------------------------------------------------------------------------------------------
# Disk, verification, clean-up


_size = format_bytes


def _tree_bytes(path: Path) -> int:
    total = 0
    for dirpath, _, files in os.walk(path):
        for f in files:
            with contextlib.suppress(OSError):
                total += os.lstat(os.path.join(dirpath, f)).st_size
    return total


def _parts_on_disk(desc: DatasetDescription, root: Path) -> bool:
    """Every part is on disk, complete."""
    return all((root / p.name).is_file() and (root / p.name).stat().st_size == p.size_bytes for p in desc.parts)


def _check_disk(desc: DatasetDescription, root: Path, settings: TransferSettings, keep_archive: bool = False) -> None:
    """Refuse to start when the disk cannot hold, at its fullest, what is still to download, the extraction
    (taken as the archive's size) and the import's own files (``settings.import_fraction`` of the archive,
    written after the parts are deleted unless they are kept), plus a margin."""
    to_fetch = 0
    for part in desc.parts:
        final, tmp = root / part.name, root / f"{part.name}.part"
        if final.exists() and final.stat().st_size == part.size_bytes:
            continue
        have = final.stat().st_size if final.exists() else tmp.stat().st_size if tmp.exists() else 0
        to_fetch += max(part.size_bytes - have, 0)
    extraction = desc.size_bytes
    imported = int(settings.import_fraction * desc.size_bytes)
    # the parts are deleted before the import (unless kept): its files then reuse their space first
    import_extra = imported if keep_archive else max(0, imported - desc.size_bytes)
    margin = max(settings.disk_margin_bytes, int(settings.disk_margin_fraction * desc.size_bytes))
    stale = root / "extracted.tmp"  # removed before extracting again: its space counts as free
    free = shutil.disk_usage(root).free + (_tree_bytes(stale) if stale.exists() else 0)
    need = to_fetch + extraction + import_extra + margin
    if free < need:
        data = root.parent.parent
        where = "beside the kept parts" if keep_archive else "in the space the deleted parts free"
        raise DiskSpaceError(
            f"not enough free disk space in {data} for {desc.id}: it needs {_size(need)} ({_size(to_fetch)} still to "
            f"download, {_size(extraction)} to extract, {_size(import_extra)} more to import: the import writes up to "
            f"{_size(imported)} {where} ({IMPORT_MEASURED}), {_size(margin)} to spare) and {_size(free)} is free; "
            f"free {_size(need - free)} there or choose another --data directory")


def _part_stamps(desc: DatasetDescription, root: Path) -> list[list[Any]]:
    stamps = []
    for part in desc.parts:
        st = (root / part.name).stat()
        stamps.append([part.name, st.st_size, st.st_mtime_ns])
    return stamps


def _verified_record_matches(desc: DatasetDescription, root: Path) -> bool:
    try:
        record = json.loads((root / VERIFIED).read_text())
        return record.get("md5") == desc.md5 and record.get("parts") == _part_stamps(desc, root)
    except (OSError, ValueError):
        return False


def _verify(desc: DatasetDescription, root: Path, progress: bool) -> bool:
    """Check the MD5 of the parts read in order (and each part's own MD5 where the description gives one);
    recorded in verified.json so a rerun does not read them again. Raises ChecksumError, deleting nothing."""
    if _verified_record_matches(desc, root):
        return True
    whole = hashlib.md5(usedforsecurity=False)
    bad_parts = []
    buffer = bytearray(_CHUNK)
    view = memoryview(buffer)
    with _bar(desc.size_bytes, 0, f"verify {desc.archive}", progress) as bar:
        for part in desc.parts:
            own = hashlib.md5(usedforsecurity=False) if part.md5 else None
            with open(root / part.name, "rb") as fh:
                while n := fh.readinto(buffer):
                    whole.update(view[:n])
                    if own is not None:
                        own.update(view[:n])
                    bar.update(n)
            if own is not None and own.hexdigest() != part.md5:
                bad_parts.append(part.name)
    actual = whole.hexdigest()
    if actual != desc.md5:
        if bad_parts:
            todo = (f"the parts {', '.join(bad_parts)} do not match their own MD5: delete them from {root} and run "
                    "again to fetch them afresh")
        else:
            todo = (f"nothing was deleted: delete the parts in {root} (or the whole folder) and run again to download "
                    f"them afresh, or check the MD5 in {desc.source}")
        raise ChecksumError(f"{desc.archive}: MD5 mismatch (expected {desc.md5}, got {actual}); {todo}")
    write_json(root / VERIFIED, {"md5": desc.md5, "parts": _part_stamps(desc, root)})
    return True


def _delete_parts(desc: DatasetDescription, root: Path) -> None:
    for part in desc.parts:
        (root / part.name).unlink(missing_ok=True)
        (root / f"{part.name}.part").unlink(missing_ok=True)
    (root / VERIFIED).unlink(missing_ok=True)


# ---------------------------------------------------------------------------------------------
# Progress and locking


class _NoBar:
    def update(self, n: int = 1) -> None:
        pass

    def __enter__(self) -> "_NoBar":
        return self

    def __exit__(self, *exc: Any) -> None:
        pass


def _bar(total: int, initial: int, desc: str, progress: bool) -> Any:
    """A progress bar in bytes on stderr, or one that shows nothing (progress off, not a terminal, no tqdm)."""
    if not progress or not sys.stderr.isatty():
        return _NoBar()
    try:
        from tqdm import tqdm
    except ImportError:
        return _NoBar()
    return tqdm(total=total, initial=initial, desc=desc, unit="B", unit_scale=True, unit_divisor=1024,
                file=sys.stderr, dynamic_ncols=True)


def _lock(root: Path) -> contextlib.AbstractContextManager[None]:
    """Hold ``<root>/.lock`` for the duration (POSIX advisory lock; no lock where fcntl is missing)."""
    return hold_lock(root / ".lock", DownloadBusyError(f"another run is downloading into {root}; wait for it to "
                                                        "finish"))
