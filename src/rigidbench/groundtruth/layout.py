"""The published evaluation set's own layout, recognised wherever RigidBench reads --data.

The authors' archive is a root with ``manifest.json`` and ``samples/<id>/`` (or ``eval/<id>/``),
whose sample metadata.json has ``task_type`` and no ``sample_id``; our renders and the bundles
``rigidbench import`` makes from it carry ``sample_id``. Every reader refuses the published
layout with the one command that converts it, instead of a KeyError or an "OK".

Standard library only: ``rigidbench.benchmark`` (imported by ``import rigidbench``) uses it.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any, Iterator

from ..errors import BundleError
from ..folders import METADATA_FILE


class PublishedLayoutError(BundleError):
    """A folder in the published archive's own layout, which must go through `rigidbench import` first."""


SAMPLE_WHAT = "sample metadata.json with task_type and no sample_id"


def is_published_metadata(meta: Any) -> bool:
    """True for a sample metadata.json in the published layout: ``task_type`` but no ``sample_id``."""
    return isinstance(meta, dict) and "task_type" in meta and "sample_id" not in meta


def sample_dirs(folder: Path) -> Iterator[Path]:
    try:
        entries = sorted(folder.iterdir())
    except OSError:
        return
    for entry in entries:
        if entry.is_dir() and not entry.name.startswith(".") and (entry / METADATA_FILE).is_file():
            yield entry


def _holds_published_samples(folder: Path, probe: int = 3) -> bool:
    """Whether the first few sample folders of ``folder`` carry published-layout metadata."""
    for k, sample_dir in enumerate(sample_dirs(folder)):
        if k >= probe:
            break
        try:
            meta = json.loads((sample_dir / METADATA_FILE).read_text())
        except (OSError, ValueError):
            continue
        if is_published_metadata(meta):
            return True
    return False


def find_published_layout(path: str | Path) -> tuple[Path, str] | None:
    """(folder, what identifies it) when ``path`` is, holds or sits in the published archive's own layout.

    The published layout is a root with ``manifest.json`` and ``samples/<id>/``, or sample folders
    (in ``samples/``, ``eval/`` or ``path`` itself) whose metadata.json has ``task_type`` and no
    ``sample_id``; the archive's top folder (``rigidbench-eval-v1.1/``) may sit between. Our renders
    and imported bundles carry ``sample_id``: a folder of them (``path``, or its ``eval/`` or
    ``train/``) is not in the published layout, whatever else lies beside it. Returns None for
    anything but the published layout.
    """
    path = Path(path)
    if not path.is_dir():
        return None
    for split_dir in (path, path / "eval", path / "train"):
        if next(sample_dirs(split_dir), None) is not None:  # the folder the commands would read
            return (path, SAMPLE_WHAT) if _holds_published_samples(split_dir) else None
    candidates = [path] + sorted(p for p in path.iterdir() if p.is_dir() and not p.name.startswith("."))
    for folder in candidates:  # a published root, or the archive's top folder above one
        if (folder / "manifest.json").is_file() and (folder / "samples").is_dir():
            return folder, "manifest.json and samples/"
        for where in (folder / "samples", folder / "eval"):
            if _holds_published_samples(where):
                return folder, SAMPLE_WHAT
    return None


def published_layout_message(folder: Path, what: str) -> str:
    return (f"{folder} holds the published RigidBench evaluation set in its original layout ({what}), which "
            f"rigidbench does not read directly; convert it into bundles with `rigidbench import {folder} "
            f"--data DIR` (DIR: a new data folder, e.g. data-published) and pass --data DIR to this command")


def check_not_published_layout(path: str | Path) -> None:
    """PublishedLayoutError (a BundleError) naming `rigidbench import` when ``path`` is in the published layout."""
    found = find_published_layout(path)
    if found is not None:
        raise PublishedLayoutError(published_layout_message(*found))


__all__ = ["SAMPLE_WHAT", "sample_dirs", "PublishedLayoutError", "is_published_metadata", "find_published_layout",
           "published_layout_message", "check_not_published_layout"]
