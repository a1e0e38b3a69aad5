"""The archives behind ``rigidbench download`` and ``rigidbench import`` (their commands: ``commands.data``): the
published evaluation set, from a URL or a file you already have, to bundles in ``DATA/eval`` and ``DATA/inputs.jsonl``.

Both hold DATA's lock while they run (``datadir.data_lock``: a second run is one line, exit 2) and record in
every bundle whether the archive's MD5 was checked, and how: ``download`` checks the parts it fetched (unless
``--no-verify``), ``import`` hashes the archive or parts it is given while it extracts them (and refuses a
mismatch). An extracted folder cannot be checked: bundles imported from one are recorded unverified, and a
result on them is never official. After a complete import the extraction may be deleted: the bundles hold
their own files (frames and video hard-linked), and ``download`` does not fetch the archive again for it.
"""

from __future__ import annotations

import hashlib
import json
import os
import re
from pathlib import Path

from ..errors import UserError
from ..jsonio import write_json
from .download import extracted_dir, read_marker
from .extract import md5_of, safe_extract

PART_NAME = re.compile(r"\.part(\d+)-of-(\d+)$")
ARCHIVE_SUFFIXES = (".tar.gz", ".tgz")
#: in DATA/.download/<id>/: the samples a complete import of the download made (so deleting the extraction
#: afterwards never makes ``download`` fetch the archive again)
IMPORTED = "imported.json"
IMPORT_DIR = ".import"  # DATA/.import/<archive>/: where ``import`` extracts an archive it is given

BY_DOWNLOAD = "rigidbench download checked the MD5 of the parts it fetched"
BY_IMPORT = "rigidbench import checked the MD5 of the archive it was given"
NO_VERIFY = "downloaded with --no-verify"
FROM_FOLDER = "imported from an extracted folder, whose archive's MD5 cannot be checked"
IMPORT_REMEDY = ("the file is damaged or incomplete: fetch it again (`rigidbench download` resumes and checks the MD5) "
                 "or compare its MD5 with the dataset's description")


def dataset_identity(desc, verified: bool, verification: str) -> dict:
    """What each imported bundle records about its set: the description's identity, whether the archive's
    MD5 was checked, and how (or why not)."""
    return {**desc.identity(), "verified": bool(verified), "verification": verification}


def unshared_bytes(folder: Path) -> int:
    """Bytes of the files under ``folder`` that nothing else links to (what deleting it frees)."""
    total = 0
    for dirpath, _, files in os.walk(folder):
        for name in files:
            st = os.lstat(os.path.join(dirpath, name))
            total += st.st_size if st.st_nlink == 1 else 0
    return total


def _part(path: Path) -> tuple[str, int, int] | None:
    """(archive stem, part number, part count) of a part's file name, or None."""
    match = PART_NAME.search(path.name)
    return None if match is None else (path.name[:match.start()], int(match.group(1)), int(match.group(2)))


def archive_parts(src: Path) -> list[Path] | None:
    """The archive file(s) ``src`` names: a .tar.gz, one of its parts, or a folder of parts (in order);
    None when ``src`` is an extracted folder. UserError for a missing, stray or ambiguous part."""
    if src.is_file():
        named = _part(src)
        if named is None:
            if not src.name.endswith(ARCHIVE_SUFFIXES):
                raise UserError(f"{src}: not a .tar.gz archive, one of its parts or an extracted folder")
            return [src]
        folder, stem = src.parent, named[0]
    else:
        stems = sorted({named[0] for p in src.iterdir() if p.is_file() and (named := _part(p))})
        if not stems:
            archives = [p for p in src.iterdir() if p.is_file() and p.name.endswith(ARCHIVE_SUFFIXES)]
            return archives[:1] if len(archives) == 1 and not any(p.is_dir() for p in src.iterdir()) else None
        if len(stems) > 1:
            raise UserError(f"{src}: holds the parts of {len(stems)} archives ({', '.join(stems)}); pass the path "
                            "of one part of the archive to import")
        folder, stem = src, stems[0]
    found = sorted((named[1], named[2], p) for p in folder.iterdir()
                   if p.is_file() and (named := _part(p)) and named[0] == stem)
    counts = sorted({count for _, count, _ in found})
    if len(counts) > 1:
        names = ", ".join(p.name for *_, p in found)
        raise UserError(f"{folder}: the parts of {stem} disagree on how many there are ({names}); delete the ones "
                        "that do not belong")
    count = counts[0]
    stray = [p.name for n, _, p in found if not 1 <= n <= count]
    if stray:
        raise UserError(f"{folder}: {', '.join(stray)} cannot be a part of the {count}-part archive {stem}; delete it "
                        "(or fetch the archive again)")
    numbers = [n for n, _, _ in found]
    if len(set(numbers)) != len(numbers):
        twice = sorted({n for n in numbers if numbers.count(n) > 1})
        raise UserError(f"{folder}: part {', '.join(map(str, twice))} of {stem} is there under two names; keep one")
    missing = sorted(set(range(1, count + 1)) - set(numbers))
    if missing:
        shown = ", ".join(str(n) for n in missing[:10]) + (" ..." if len(missing) > 10 else "")
        raise UserError(f"{folder}: parts of {stem} missing: {shown} of {count}; download them (rigidbench download "
                        "resumes) or pass the extracted folder")
    return [p for _, _, p in found]


def _stamps(paths: list[Path]) -> list[list]:
    return [[p.name, p.stat().st_size, p.stat().st_mtime_ns] for p in paths]


def extract_checked(parts: list[Path], desc, data: Path) -> Path:
    """Extract the archive ``parts`` make into DATA/.import/<archive>/ (once), hashing it in the same read,
    and check its MD5 against ``desc``; returns the extracted folder. A later run on the same, unchanged files
    takes the MD5 from ``<archive>.md5.json`` beside it. UserError on a mismatch (the extraction is kept)."""
    archive = PART_NAME.sub("", parts[0].name)
    name = archive
    for suffix in ARCHIVE_SUFFIXES:
        name = name.removesuffix(suffix)
    dest = data / IMPORT_DIR / name
    record = dest.parent / f"{name}.md5.json"
    try:
        known = json.loads(record.read_text())
    except (OSError, ValueError):
        known = {}
    if dest.exists() and known.get("parts") == _stamps(parts):
        actual = known.get("md5")
    elif dest.exists():
        print(f"checking the MD5 of {len(parts)} file(s) of {archive}")
        actual = md5_of(parts)
    else:
        print(f"extracting {len(parts)} file(s) of {archive} into {dest}, checking its MD5")
        digest = hashlib.md5(usedforsecurity=False)
        safe_extract(parts, dest, archive=archive, digest=digest, remedy=IMPORT_REMEDY)
        actual = digest.hexdigest()
    write_json(record, {"md5": actual, "parts": _stamps(parts)})
    if actual != desc.md5:
        given = parts[0] if len(parts) == 1 else parts[0].parent
        raise UserError(f"{given}: the archive's MD5 is {actual}, but {desc.source} gives {desc.id} the MD5 "
                        f"{desc.md5}: it is damaged, incomplete or another release. Fetch it again (rigidbench "
                        f"download resumes) or name its description with --dataset; its extraction stays in {dest}")
    return dest


def folder_verification(src: Path, desc, data: Path) -> tuple[bool, str]:
    """Whether the extracted folder ``src`` is known to come from an archive whose MD5 was checked: the
    extraction of a verified ``download``, or of an archive ``import`` checked."""
    where = src.resolve()
    extracted = extracted_dir(desc, data).resolve()
    if where == extracted or extracted in where.parents:
        verified = bool((read_marker(desc, data) or {}).get("md5_verified"))
        return verified, BY_DOWNLOAD if verified else NO_VERIFY
    if where.parent == (data / IMPORT_DIR).resolve():
        try:
            if json.loads((where.parent / f"{where.name}.md5.json").read_text()).get("md5") == desc.md5:
                return True, BY_IMPORT
        except (OSError, ValueError):
            pass
    return False, FROM_FOLDER


__all__ = ["archive_parts", "dataset_identity", "extract_checked", "folder_verification", "unshared_bytes"]
