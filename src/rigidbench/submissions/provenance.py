"""What a run knows about itself, for a submission card's ``provenance:`` mapping (filled in, never typed).

``read_run_files(run_dir)`` reads the run folder ``rigidbench evaluate`` wrote (results.json, run.json, the
per-example records); ``run_provenance`` gathers, from them and from the predictions folder when it can be
reached: the reference set's identity and whether its MD5 was verified, the protocol, the perception backend
with the SHA-256 of each network weight file it names, the feature networks, the skipped measurements, the
RigidBench version that scored the run (and the version and git commit that made the bundle), the seeds
(from the predictions' generation.json), and the SHA-256 of every per-example file and video that goes into
the bundle.
"""

from __future__ import annotations

import subprocess
import time
from dataclasses import dataclass
from pathlib import Path

import rigidbench

from ..errors import UserError
from ..folders import GENERATION_FILE, RunFolder, split_sample_item
from ..hashing import digest, file_digest
from ..jsonio import DamagedJSON, load_json, read_json


@dataclass(frozen=True)
class RunFiles:
    """A run folder read back: results.json, run.json, and per example id its record's and (when there is one)
    its readouts file's path."""

    path: Path
    results: dict
    run: dict
    records: dict[str, Path]
    readouts: dict[str, Path]


def _run_json(path: Path, run_dir: Path) -> dict:
    try:
        return load_json(path, expect=dict)
    except FileNotFoundError:
        raise UserError(f"{path}: missing; {run_dir} is not a finished run folder (run `rigidbench evaluate "
                        f"PREDICTIONS --out {run_dir}` to the end)") from None
    except DamagedJSON as exc:
        raise UserError(f"{exc}; rerun `rigidbench evaluate` with --out {run_dir} to write it again") from None


def read_run_files(run_dir: str | Path) -> RunFiles:
    """The run folder ``run_dir`` read back; UserError naming a missing or damaged results.json or run.json."""
    run_dir = Path(run_dir)
    if not run_dir.is_dir():
        raise UserError(f"{run_dir}: no such run folder; pass the --out folder of `rigidbench evaluate`")
    folder = RunFolder(run_dir)
    results, run = _run_json(folder.results, run_dir), _run_json(folder.run, run_dir)
    records = {i: folder.record(i) for i in counted_ids(results, folder)}
    missing = [i for i, p in records.items() if not p.is_file()]
    if missing:
        raise UserError(f"{folder.record(missing[0])}: missing, but results.json counts it; rerun `rigidbench "
                        f"evaluate` with --out {run_dir} to score it again")
    readouts = {i: folder.readouts(i) for i in records if folder.readouts(i).is_file()}
    return RunFiles(run_dir, results, run, records, readouts)


def counted_ids(results: dict, folder: RunFolder) -> list[str]:
    """The examples results.json aggregates: those of its coverage block (a later `evaluate --ids` run may
    leave records of other examples in examples/), else every record there (a run from before coverage)."""
    per_example = (results.get("coverage") or {}).get("per_example") if isinstance(results.get("coverage"),
                                                                                   dict) else None
    if isinstance(per_example, dict):
        return sorted(per_example)
    return list(dict.fromkeys(split_sample_item(p.stem)[0] for p in folder.records()))  # examples, not samples


# -- the pieces ------------------------------------------------------------------------------------------------


def path_digest(path: Path) -> str:
    """SHA-256 of a file; of a folder, of its files' relative paths and digests (links followed, as the hub's
    cache folders are made of links to blobs)."""
    if path.is_file():
        return file_digest(path)
    files = sorted(p for p in path.rglob("*") if p.is_file())
    return digest({p.relative_to(path).as_posix(): file_digest(p.resolve()) for p in files})


def weight_digests(settings: dict) -> dict:
    """Per perception model role, the identity run.json records for it and the SHA-256 of each weight file or
    folder that identity names (None where the path is no longer there; injected models name none)."""
    out = {}
    for role, identity in sorted((settings.get("models") or {}).items()):
        files: dict[str, str | None] = {}
        for part in str(identity).split(":")[1:]:
            if part.startswith(("/", "~", ".")):
                path = Path(part).expanduser()
                files[part] = path_digest(path) if path.exists() else None
        out[role] = {"identity": identity, "sha256": files}
    return out


def git_commit() -> dict:
    """The git commit of the RigidBench source in use, and whether it has uncommitted changes (both None when
    it is not a git checkout, e.g. an installed wheel)."""
    source = Path(rigidbench.__file__).resolve().parent

    def git(*args: str) -> str | None:
        try:
            out = subprocess.run(["git", "-C", str(source), *args], capture_output=True, text=True, timeout=20)
        except (OSError, subprocess.SubprocessError):
            return None
        return out.stdout.strip() if out.returncode == 0 else None

    commit = git("rev-parse", "HEAD")
    status = git("status", "--porcelain", "--untracked-files=no", "--", ".") if commit else None
    return {"commit": commit, "dirty": None if status is None else bool(status)}


def seeds(predictions: Path | None, ids: list[str]) -> dict:
    """The seeds behind the videos, from the predictions folder's generation.json: the base seed, the rule that
    derives each example's seed, and each scored example's seed; ``found`` False with ``why`` when there is
    no generation.json to read (videos made outside rigidbench, or the folder is not here)."""
    if predictions is None:
        return {"found": False, "why": "the predictions folder is not known"}
    path = predictions / GENERATION_FILE
    doc = read_json(path, "the seeds are recorded as unknown", expect=dict)
    if doc is None:
        return {"found": False, "why": f"no readable {GENERATION_FILE} in {predictions}"}
    settings = doc.get("settings") if isinstance(doc.get("settings"), dict) else {}
    examples = doc.get("examples") if isinstance(doc.get("examples"), dict) else {}
    per = {i: examples[i].get("seed") for i in ids if isinstance(examples.get(i), dict)}
    return {"found": True, "predictor": doc.get("predictor"), "base": settings.get("seed"),
            "rule": settings.get("seeds"), "per_example": per}


def predictions_dir(run: dict, given: Path | None) -> Path | None:
    """The run's predictions folder: the one given (``--videos``), else the one run.json names when it is here."""
    if given is not None:
        return given
    recorded = run.get("predictions")
    return Path(recorded) if recorded and Path(recorded).is_dir() else None


def run_provenance(files: RunFiles, *, predictions: Path | None = None, published: dict | None = None,
                   videos: dict[str, Path] | None = None) -> dict:
    """The ``provenance:`` mapping of a card for the run ``files``; ``published``: the published set the run's
    reference set is (``validate.published_set``), ``videos``: id -> the clip going into the bundle."""
    results, run = files.results, files.run
    perception = dict(run.get("perception") or {"backend": results.get("perception")})
    perception["weights"] = weight_digests(perception.get("settings") or {})
    ids = sorted(files.records)
    return {
        "model": results.get("model"),
        "dataset": {**(results.get("dataset") or {}), "published": published},
        "protocol": results.get("protocol"),
        "perception": perception,
        "feature_nets": run.get("feature_nets"),
        "metrics": results.get("metrics"),
        "skipped_metrics": results.get("skipped_metrics") or {},
        "examples": {"scored": results.get("n_examples"), "reference": results.get("n_reference"),
                     "failed": results.get("failed") or {}},
        "official": results.get("official"),
        "why_not_official": results.get("why_not_official", []),
        "rigidbench": {"scored_with": (run.get("versions") or {}).get("rigidbench"),
                       "score_version": (run.get("settings") or {}).get("score_version"),
                       "bundled_with": rigidbench.__version__, **git_commit()},
        "versions": run.get("versions"),
        "hashes": {"predictions": run.get("predictions_hash"), "data": run.get("data_hash")},
        "seeds": seeds(predictions_dir(run, predictions), ids),
        "records": {i: file_digest(files.records[i]) for i in ids},
        "readouts": {i: file_digest(p) for i, p in sorted(files.readouts.items())},
        "videos": {i: file_digest(p) for i, p in sorted((videos or {}).items())},
        "finished_at": run.get("finished_at"),
        "bundled_at": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
    }


__all__ = ["RunFiles", "git_commit", "read_run_files", "run_provenance", "seeds",
           "weight_digests"]
