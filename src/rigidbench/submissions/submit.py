"""Making a bundle from a run folder and a card (``rigidbench submit``).

``prepare(run_dir, card_path, config_dirs, videos_dir)`` reads the run and the card and returns a ``Prepared``:
the run's files, the card, the clips to include and every ``problem`` (one line each: the run's and the card's,
``submissions.validate``, and the clips'). ``write_bundle(prepared, out)`` fills in the card's provenance and
writes the archive (``submissions.bundle`` gives its layout) when there is no problem.
"""

from __future__ import annotations

import shutil
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Iterable

import yaml

from ..errors import RigidBenchError
from ..evaluation.keys import digest as keys_digest
from ..folders import EXAMPLES_DIR, RESULTS_FILE, find_prediction, state_path
from ..hashing import file_digest
from .bundle import (CARD_FILE, MANIFEST_FILE, PROVENANCE_KEY, TOP, VIDEO_SUFFIX, VIDEOS_DIR, SubmissionError,
                     manifest_text, read_card_file, write_archive)
from .provenance import RunFiles, read_run_files, run_provenance
from .validate import published_set, submission_problems


@dataclass(frozen=True)
class Prepared:
    """A run and a card read, checked and filled in: ``problems`` empty means it can be bundled."""

    files: RunFiles
    card: dict
    videos: dict[str, Path]
    videos_dir: Path | None
    published: dict | None  # the dataset description that names the run's set (id, examples, DOI)
    problems: list[str]

    def provenance(self) -> dict:
        """The card's ``provenance:`` (hashes every weight file the run names: only when bundling)."""
        return run_provenance(self.files, predictions=self.videos_dir, published=self.published,
                              videos=self.videos)


def video_problems(files: RunFiles, videos_dir: Path) -> tuple[dict[str, Path], list[str]]:
    """The clip of each scored example in ``videos_dir`` and one line per problem: a clip missing, not an .mp4,
    or the clips not being the ones the run scored (their hashes against run.json's ``predictions_hash``)."""
    where = f"--videos {videos_dir}"
    if not videos_dir.is_dir():
        return {}, [f"{where}: no such folder; pass the predictions folder the run scored"]
    found, missing, other = {}, [], []
    hashes = {}
    for sample_id in sorted(files.records):
        try:
            path = find_prediction(videos_dir, sample_id)
        except RigidBenchError as exc:  # several clips, or not a regular file
            return {}, [f"{where}: {exc}"]
        if path is None:
            missing.append(sample_id)
            continue
        if path.suffix != VIDEO_SUFFIX:
            other.append(path.name)
        found[sample_id] = path
        state = state_path(path)
        hashes[sample_id] = file_digest(path) + (file_digest(state) if state.exists() else "")
    problems = []
    if missing:
        problems.append(f"{where}: no clip for {len(missing)} scored examples ({', '.join(missing[:5])}"
                        f"{' ...' if len(missing) > 5 else ''})")
    if other:
        problems.append(f"{where}: a bundle holds .mp4 clips; convert {', '.join(other[:5])} to .mp4")
    recorded = files.run.get("predictions_hash")
    if not problems and recorded and keys_digest(hashes) != recorded:
        problems.append(f"{where}: these clips are not the ones the run scored (their hashes differ from run.json's "
                        "predictions_hash); pass the folder `rigidbench evaluate` read")
    return found, problems


def prepare(run_dir: str | Path, card_path: str | Path, config_dirs: Iterable[str | Path] = (),
            videos_dir: str | Path | None = None) -> Prepared:
    """Read and check the run ``run_dir`` and the card ``card_path``; with ``videos_dir``, its clips too."""
    files = read_run_files(run_dir)
    card = read_card_file(Path(card_path))
    problems = submission_problems(files, card, str(card_path), config_dirs)
    videos: dict[str, Path] = {}
    if videos_dir is not None:
        videos, more = video_problems(files, Path(videos_dir))
        problems += more
    described = published_set(files.results.get("dataset") or {}, config_dirs)
    published = None if described is None else {"id": described.id, "examples": described.examples,
                                                 "doi": described.doi}
    return Prepared(files, card, videos, None if videos_dir is None else Path(videos_dir), published, problems)


def write_bundle(prepared: Prepared, out: str | Path) -> Path:
    """The archive ``out`` of a prepared run: card.yaml (the card and its provenance), results.json, the records
    and readouts, the clips, and the manifest. SubmissionError when the run has problems."""
    if prepared.problems:
        raise SubmissionError(f"{prepared.files.path}: not bundled: {len(prepared.problems)} problem(s)")
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(prefix=".rigidbench-submit-", dir=out.parent) as tmp:
        root = Path(tmp) / TOP
        (root / EXAMPLES_DIR).mkdir(parents=True)
        card = {**prepared.card, PROVENANCE_KEY: prepared.provenance()}
        (root / CARD_FILE).write_text(yaml.safe_dump(card, sort_keys=False, allow_unicode=True), encoding="utf-8")
        shutil.copyfile(prepared.files.path / RESULTS_FILE, root / RESULTS_FILE)
        for sample_id, path in prepared.files.records.items():
            shutil.copyfile(path, root / EXAMPLES_DIR / path.name)
        for sample_id, path in prepared.files.readouts.items():
            shutil.copyfile(path, root / EXAMPLES_DIR / path.name)
        if prepared.videos:
            (root / VIDEOS_DIR).mkdir()
            for sample_id, path in prepared.videos.items():
                shutil.copyfile(path, root / VIDEOS_DIR / f"{sample_id}{VIDEO_SUFFIX}")
        (root / MANIFEST_FILE).write_text(manifest_text(root), encoding="utf-8")
        write_archive(root, out)
    return out
