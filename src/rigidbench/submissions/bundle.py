"""A submission bundle: its layout, its SHA-256 manifest, reading it back (``load_submission``) and writing it.

A bundle is one ``.tar.gz`` archive whose single top folder ``submission/`` holds

- ``card.yaml``: the submitter's card (``submissions.card``) plus a ``provenance:`` mapping filled from the run
  (``submissions.provenance``), never typed by hand;
- ``results.json``: the run's results, as ``rigidbench evaluate`` wrote them;
- ``examples/<id>.json`` and, when the run has one, ``examples/<id>.readouts.json``: the per-example records;
- ``videos/<id>.mp4`` (optional): the generated clips that were scored;
- ``MANIFEST.sha256``: one line ``<sha256>  <relative path>`` for every other file (sorted by path).

``load_submission`` accepts the archive or an extracted ``submission/`` folder (or the folder holding it) and
checks the manifest first: a file whose hash differs, a listed file that is missing, or a file that is not
listed is a ``SubmissionError`` naming it. An archive is extracted (safely: ``datasets.extract``) into a
temporary folder that lives until the process exits, so the ``videos`` paths stay readable.
"""

from __future__ import annotations

import atexit
import re
import shutil
import tarfile
import tempfile
from dataclasses import dataclass, field
from pathlib import Path, PurePosixPath

import yaml

from ..atomic import atomic_file
from ..datasets.extract import ArchiveError, safe_extract
from ..errors import UserError
from ..folders import EXAMPLES_DIR, READOUTS_SUFFIX, RESULTS_FILE
from ..hashing import file_digest
from ..jsonio import DamagedJSON, load_json

TOP = "submission"
CARD_FILE = "card.yaml"
MANIFEST_FILE = "MANIFEST.sha256"
VIDEOS_DIR = "videos"
VIDEO_SUFFIX = ".mp4"
PROVENANCE_KEY = "provenance"
ARCHIVE_SUFFIXES = (".tar.gz", ".tgz")
_MANIFEST_LINE = re.compile(r"^([0-9a-f]{64})  (\S(?:.*\S)?)$")
_ID = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_-]*$")


class SubmissionError(UserError):
    """A submission bundle that cannot be used: the message names the file and what is wrong with it."""


@dataclass(frozen=True)
class Submission:
    """One submission, read back and checked against its manifest.

    ``name``: the entry's display name (the card's ``name``, else its ``model.name``); ``card``: the
    submitter's card without ``provenance``; ``provenance``: what the run recorded (``submissions.provenance``);
    ``results``: results.json; ``records``: id -> ``examples/<id>.json``; ``readouts``: id ->
    ``examples/<id>.readouts.json`` (only the ids that have one); ``videos``: id -> the clip's path, or None
    when the bundle holds none for it (every id of ``records`` is a key); ``path``: the archive or folder
    given; ``manifest``: relative path -> SHA-256 of every file but the manifest, as checked."""

    name: str
    card: dict
    provenance: dict
    results: dict
    records: dict[str, dict]
    readouts: dict[str, dict]
    videos: dict[str, Path | None]
    path: Path
    manifest: dict[str, str] = field(default_factory=dict)

    def record_digest(self, sample_id: str) -> str | None:
        """The SHA-256 of ``examples/<id>.json`` as bundled (from the checked manifest)."""
        return self.manifest.get(f"{EXAMPLES_DIR}/{sample_id}.json")


# -- the manifest ----------------------------------------------------------------------------------------


def bundle_files(root: Path) -> list[str]:
    """The relative POSIX paths of every regular file under ``root`` except the manifest, sorted; a link or
    anything other than a file or folder is a SubmissionError naming it."""
    out = []
    for p in sorted(root.rglob("*")):
        rel = p.relative_to(root).as_posix()
        if p.is_symlink() or not (p.is_file() or p.is_dir()):
            raise SubmissionError(f"{root / rel}: not a regular file (links and special files are refused)")
        if p.is_file() and rel != MANIFEST_FILE:
            out.append(rel)
    return out


def manifest_text(root: Path) -> str:
    """``MANIFEST.sha256``'s content for the folder ``root``: ``<sha256>  <path>`` per file, sorted by path."""
    return "".join(f"{file_digest(root / rel)}  {rel}\n" for rel in bundle_files(root))


def read_manifest(root: Path, where: str) -> dict[str, str]:
    """Relative path -> sha256 of ``root/MANIFEST.sha256`` (``where`` names the bundle in messages)."""
    path = root / MANIFEST_FILE
    try:
        lines = path.read_text(encoding="utf-8").splitlines()
    except FileNotFoundError:
        raise SubmissionError(f"{where}: no {MANIFEST_FILE}; a bundle is written by `rigidbench submit`") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise SubmissionError(f"{where}: {MANIFEST_FILE} cannot be read ({type(exc).__name__})") from None
    entries: dict[str, str] = {}
    for k, line in enumerate(lines, 1):
        match = _MANIFEST_LINE.match(line)
        if not match:
            raise SubmissionError(f"{where}: {MANIFEST_FILE} line {k} is not '<sha256>  <path>'")
        rel = match.group(2)
        parts = PurePosixPath(rel).parts
        if rel.startswith("/") or ".." in parts or rel == MANIFEST_FILE or rel in entries:
            raise SubmissionError(f"{where}: {MANIFEST_FILE} line {k} lists '{rel}', which is not a file a bundle "
                                  "may list (absolute, '..', the manifest itself or listed twice)")
        entries[rel] = match.group(1)
    return entries


def manifest_problems(root: Path, where: str) -> list[str]:
    """One line per file of the folder ``root`` that disagrees with its manifest: its hash differs, it is listed
    but missing, or it is there but not listed (empty: the manifest holds)."""
    listed = read_manifest(root, where)
    present = set(bundle_files(root))
    problems = []
    for rel, sha in sorted(listed.items()):
        if rel not in present:
            problems.append(f"{where}: {rel}: listed in {MANIFEST_FILE} but missing")
        elif file_digest(root / rel) != sha:
            problems.append(f"{where}: {rel}: its SHA-256 is not the one {MANIFEST_FILE} lists (the file was "
                            "changed after the bundle was made)")
    problems += [f"{where}: {rel}: not listed in {MANIFEST_FILE} (a file added after the bundle was made)"
                 for rel in sorted(present - set(listed))]
    return problems


# -- reading -----------------------------------------------------------------------------------------------


_EXTRACTED: list[Path] = []


def _remove_extracted() -> None:
    for folder in _EXTRACTED:
        shutil.rmtree(folder, ignore_errors=True)


atexit.register(_remove_extracted)


def is_archive(path: Path) -> bool:
    return path.name.endswith(ARCHIVE_SUFFIXES)


def submission_root(path: str | Path) -> Path:
    """The ``submission/`` folder of a bundle: the archive extracted into a temporary folder (removed when the
    process exits), or the folder given (``submission/`` itself, or a folder holding it)."""
    path = Path(path)
    if not path.exists():
        raise SubmissionError(f"{path}: no such file or folder; pass a bundle (.tar.gz) `rigidbench submit` wrote, "
                              "or its extracted folder")
    if path.is_dir():
        root = path / TOP if (path / TOP).is_dir() and not (path / MANIFEST_FILE).exists() else path
        return root
    if not is_archive(path):
        raise SubmissionError(f"{path}: not a .tar.gz bundle or a folder")
    tmp = Path(tempfile.mkdtemp(prefix="rigidbench-submission-"))
    _EXTRACTED.append(tmp)
    try:
        safe_extract([path], tmp / "x", archive=str(path),
                     remedy="the bundle is damaged or incomplete: copy it again or ask its submitter")
    except ArchiveError as exc:
        raise SubmissionError(str(exc)) from None
    tops = [p for p in (tmp / "x").iterdir()]
    if [p.name for p in tops] != [TOP] or not tops[0].is_dir():
        raise SubmissionError(f"{path}: the archive's top level must be one folder '{TOP}/' (it holds "
                              f"{', '.join(sorted(p.name for p in tops))})")
    return tops[0]


def _json(root: Path, rel: str, where: str) -> dict:
    try:
        return load_json(root / rel, expect=dict)
    except FileNotFoundError:
        raise SubmissionError(f"{where}: {rel}: missing") from None
    except DamagedJSON as exc:
        raise SubmissionError(f"{where}: {rel}: {str(exc).split(': ', 1)[-1]}") from None


def read_card_file(path: Path, where: str | None = None) -> dict:
    """A card YAML file as a mapping; SubmissionError naming it when it is not one."""
    where = where or str(path)
    try:
        doc = yaml.safe_load(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise SubmissionError(f"{where}: no such file") from None
    except (OSError, UnicodeDecodeError, yaml.YAMLError) as exc:
        raise SubmissionError(f"{where}: not a readable YAML file ({type(exc).__name__})") from None
    if not isinstance(doc, dict):
        raise SubmissionError(f"{where}: holds {type(doc).__name__}, not a mapping of card fields")
    return doc


def card_name(card: dict) -> str:
    """The display name of an entry: the card's ``name``, else ``model.name``."""
    if isinstance(card.get("name"), str) and card["name"].strip():
        return card["name"].strip()
    model = card.get("model")
    return str(model.get("name")) if isinstance(model, dict) and model.get("name") else "unnamed"


def load_submission(path: str | Path) -> Submission:
    """Read a bundle (``.tar.gz`` or extracted folder), after checking every file against ``MANIFEST.sha256``
    (SubmissionError naming the first file that disagrees: changed, missing or not listed)."""
    path = Path(path)
    root = submission_root(path)
    where = str(path)
    problems = manifest_problems(root, where)
    if problems:
        raise SubmissionError(problems[0] + (f" (and {len(problems) - 1} more)" if len(problems) > 1 else ""))
    card = read_card_file(root / CARD_FILE, f"{where}: {CARD_FILE}")
    provenance = card.pop(PROVENANCE_KEY, None)
    if not isinstance(provenance, dict):
        raise SubmissionError(f"{where}: {CARD_FILE}: no '{PROVENANCE_KEY}' mapping; a bundle is written by "
                              "`rigidbench submit`")
    results = _json(root, RESULTS_FILE, where)
    records: dict[str, dict] = {}
    readouts: dict[str, dict] = {}
    examples = root / EXAMPLES_DIR
    for p in sorted(examples.glob("*.json")) if examples.is_dir() else []:
        rel = f"{EXAMPLES_DIR}/{p.name}"
        if p.name.endswith(READOUTS_SUFFIX):
            readouts[p.name[:-len(READOUTS_SUFFIX)]] = _json(root, rel, where)
        elif _ID.match(p.stem):
            records[p.stem] = _json(root, rel, where)
    stray = sorted(set(readouts) - set(records))
    if stray:
        raise SubmissionError(f"{where}: {EXAMPLES_DIR}/{stray[0]}{READOUTS_SUFFIX}: readouts of an example "
                              "with no record")
    videos: dict[str, Path | None] = {i: None for i in records}
    for p in sorted((root / VIDEOS_DIR).glob("*")) if (root / VIDEOS_DIR).is_dir() else []:
        if p.suffix != VIDEO_SUFFIX or p.stem not in records:
            raise SubmissionError(f"{where}: {VIDEOS_DIR}/{p.name}: not the .mp4 of an example of the bundle")
        videos[p.stem] = p
    return Submission(name=card_name(card), card=card, provenance=provenance, results=results, records=records,
                      readouts=readouts, videos=videos, path=path, manifest=read_manifest(root, where))


# -- writing -----------------------------------------------------------------------------------------------


def write_archive(folder: Path, out: Path) -> Path:
    """Write ``folder`` (a complete ``submission/`` tree, manifest included) as the archive ``out``: its files
    under ``submission/``, sorted, with fixed owner and mode (atomic: a failed write leaves nothing)."""
    with atomic_file(out, suffix=".tar.gz", unique=True) as tmp:
        with tarfile.open(tmp, "w:gz") as tar:
            tar.add(folder, arcname=TOP, recursive=False, filter=_plain)
            for p in sorted(folder.rglob("*")):
                tar.add(p, arcname=f"{TOP}/{p.relative_to(folder).as_posix()}", recursive=False, filter=_plain)
    return out


def _plain(info: tarfile.TarInfo) -> tarfile.TarInfo:
    info.uid = info.gid = 0
    info.uname = info.gname = ""
    info.mode = 0o755 if info.isdir() else 0o644
    return info
