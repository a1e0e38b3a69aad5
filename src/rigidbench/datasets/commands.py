"""``rigidbench download`` and ``rigidbench import``: the published evaluation set, from a URL or a file
you already have, to bundles in ``DATA/eval`` and ``DATA/inputs.jsonl``."""

from __future__ import annotations

import re
from pathlib import Path

from ..argtypes import selected_ids
from ..benchmark import write_inputs
from ..errors import UserError
from .describe import load_dataset
from .download import download_dataset, read_marker
from .extract import safe_extract
from .importer import import_published

PART_NAME = re.compile(r"\.part(\d+)-of-(\d+)$")
ARCHIVE_SUFFIXES = (".tar.gz", ".tgz")


def _identity(desc, verified: bool) -> dict:
    return {**desc.identity(), "md5_verified": bool(verified)}


def _finish(summary, data: Path) -> int:
    """Print what the import did, write DATA/inputs.jsonl; exit status 1 when a sample failed."""
    print(f"imported {len(summary.imported)} samples, {len(summary.unchanged)} unchanged, {len(summary.failed)} failed "
          f"-> {summary.split_dir}")
    for sample_id, reason in summary.failed.items():
        print(f"  FAILED {sample_id}: {reason}")
    if summary.imported or summary.unchanged:
        inputs = write_inputs(data)
        print(f"model inputs: {inputs}")
        print(f"next: generate one video per line of {inputs} into predictions/MODEL/<id>.mp4, then "
              f"`rigidbench validate predictions/MODEL --data {data}` and "
              f"`rigidbench evaluate predictions/MODEL --data {data} --perception neural`")
    return 1 if summary.failed else 0


def cmd_download(args, ctx) -> int:
    desc = load_dataset(args.dataset, ctx.config_dirs)
    print(f"{desc.name} {desc.version}: {desc.size_bytes / 1e9:.1f} GB in {len(desc.parts)} parts ({desc.licence}"
          f"{', doi:' + desc.doi if desc.doi else ''})")
    extracted = download_dataset(desc, args.data, keep_archive=args.keep_archive, verify=not args.no_verify)
    verified = bool((read_marker(desc, args.data) or {}).get("md5_verified"))
    summary = import_published(extracted, args.data, dataset=_identity(desc, verified),
                               registry=ctx.registry, config_dirs=ctx.config_dirs)
    return _finish(summary, Path(args.data))


def archive_parts(src: Path) -> list[Path] | None:
    """The archive file(s) ``src`` names: a .tar.gz, one of its parts, or a folder of parts (in order);
    None when ``src`` is an extracted folder. UserError for a gap in the parts."""
    if src.is_file():
        match = PART_NAME.search(src.name)
        if match is None:
            if not src.name.endswith(ARCHIVE_SUFFIXES):
                raise UserError(f"{src}: not a .tar.gz archive, one of its parts or an extracted folder")
            return [src]
        folder, stem = src.parent, src.name[:match.start()]
    else:
        parts = [p for p in src.iterdir() if p.is_file() and PART_NAME.search(p.name)]
        if not parts:
            archives = [p for p in src.iterdir() if p.is_file() and p.name.endswith(ARCHIVE_SUFFIXES)]
            return archives[:1] if len(archives) == 1 and not any(p.is_dir() for p in src.iterdir()) else None
        folder, stem = src, parts[0].name[:PART_NAME.search(parts[0].name).start()]
    found = sorted((int(PART_NAME.search(p.name).group(1)), int(PART_NAME.search(p.name).group(2)), p)
                   for p in folder.iterdir() if p.name.startswith(stem) and PART_NAME.search(p.name))
    count = found[0][1]
    numbers = [n for n, _, _ in found]
    expected = list(range(numbers[0], numbers[0] + count))
    if numbers != expected:
        missing = sorted(set(expected) - set(numbers))
        raise UserError(f"{folder}: parts of {stem} missing: {', '.join(str(n) for n in missing[:10])} of {count}; "
                        "download them (rigidbench download resumes) or pass the extracted folder")
    return [p for _, _, p in found]


def cmd_import(args, ctx) -> int:
    src = Path(args.src)
    if not src.exists():
        raise UserError(f"{src}: no such file or folder")
    desc = load_dataset(args.dataset, ctx.config_dirs)
    parts = archive_parts(src)
    if parts is not None:
        name = PART_NAME.sub("", parts[0].name)
        for suffix in ARCHIVE_SUFFIXES:
            name = name.removesuffix(suffix)
        dest = Path(args.data) / ".import" / name
        if not dest.exists():
            print(f"extracting {len(parts)} file(s) of {parts[0].name} into {dest}")
            safe_extract(parts, dest, archive=PART_NAME.sub("", parts[0].name))
        src = dest
    summary = import_published(src, args.data, dataset=_identity(desc, False), registry=ctx.registry,
                               config_dirs=ctx.config_dirs, ids=selected_ids(args), limit=args.limit)
    return _finish(summary, Path(args.data))


__all__ = ["cmd_download", "cmd_import", "archive_parts"]
