"""Read evaluation run directories (runs/<model>/, written by `rigidbench evaluate`) into one array.

A run directory holds ``results.json`` (aggregates, official flag, skipped measurements),
``run.json`` (model, perception backend, settings, the predictions and reference directories) and
``examples/<id>.json`` (the ten scalars of one example, null where non-finite, with its task and
partition). `load_runs` aligns every run on
the example ids that all runs share and returns scores (models, examples, metrics) with NaN for
a non-finite or skipped measurement.
"""

from __future__ import annotations

import json
import logging
import math
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from rigidbench.errors import ReportError
from rigidbench.folders import RunFolder
from rigidbench.metrics import METRICS

log = logging.getLogger(__name__)



@dataclass(frozen=True)
class RunInfo:
    """One run directory: its model name, provenance and the measurements it skipped (metric -> reason)."""

    name: str
    path: Path
    perception: str
    perception_version: str
    official: bool
    why_not_official: tuple[str, ...]
    skipped_metrics: dict[str, str]
    failed: dict[str, str]
    n_examples: int
    n_reference: int | None
    finished_at: str
    predictions: str = ""  # the predictions directory and reference split as run.json recorded them
    data: str = ""
    coverage: dict = field(default_factory=dict)  # results.json "coverage": fractions of the reference span

    @property
    def coverage_text(self) -> str:
        """Mean coverage of the reference span as a percentage, with the short clips scored; "—" if unknown."""
        mean = self.coverage.get("mean_fraction")
        if mean is None:
            return "—"
        short = self.coverage.get("short") or []
        return f"{100 * mean:.0f}%" + (f" ({len(short)} short: {', '.join(short[:3])}"
                                       f"{' ...' if len(short) > 3 else ''})" if short else "")


@dataclass(frozen=True)
class ScoreTable:
    """scores: (M, N, K) float64, NaN where non-finite or skipped; tasks, partitions: (N,) str."""

    runs: tuple[RunInfo, ...]
    example_ids: tuple[str, ...]
    tasks: np.ndarray
    partitions: np.ndarray
    metrics: tuple[str, ...]
    scores: np.ndarray
    skipped: np.ndarray  # (M, K) bool: the run did not compute this measurement at all
    notes: tuple[str, ...] = field(default=())

    @property
    def models(self) -> tuple[str, ...]:
        return tuple(run.name for run in self.runs)

    def metric_index(self, metric: str) -> int:
        """Position of `metric` along the last axis of `scores`."""
        return self.metrics.index(metric)


def _read_json(path: Path, run_dir: Path) -> dict:
    """Parse one JSON file of a run; a malformed file raises ReportError naming it."""
    try:
        return json.loads(path.read_text())
    except json.JSONDecodeError as exc:
        raise ReportError(f"{path}: not valid JSON ({exc}); rerun `rigidbench evaluate` for {run_dir}") from None


def _score(value) -> float:
    """A stored scalar (float or null) as float64, NaN for null or non-finite."""
    if value is None:
        return math.nan
    value = float(value)
    return value if math.isfinite(value) else math.nan


def read_run(run_dir: str | Path) -> tuple[RunInfo, dict[str, dict]]:
    """Read one run directory. Returns its RunInfo and example id -> example record."""
    run_dir = Path(run_dir)
    if not run_dir.is_dir():
        what = "is a file, not a run directory" if run_dir.exists() else "run directory does not exist"
        raise ReportError(f"{run_dir}: {what}; pass directories written by "
                          "`rigidbench evaluate predictions/MODEL --out runs/MODEL`")
    folder = RunFolder(run_dir)
    results_path = folder.results
    if not results_path.exists():
        raise ReportError(f"{run_dir}: no results.json, so this is not a finished evaluation run; run "
                          f"`rigidbench evaluate predictions/MODEL --out {run_dir}` first (it resumes)")
    results = _read_json(results_path, run_dir)
    run = _read_json(folder.run, run_dir) if folder.run.exists() else {}
    failed = dict(results.get("failed") or {})
    records = {}
    for path in folder.records():  # <id>.json, not <id>.x.json
        record = _read_json(path, run_dir)
        sample_id = str(record.get("id", path.stem))
        if sample_id in failed:
            continue  # a stale record from an earlier run of an example that failed this time
        for key in ("task", "partition", "metrics"):
            if key not in record:
                raise ReportError(f"{path}: example record has no '{key}'; rerun `rigidbench evaluate` for {run_dir}")
        records[sample_id] = record
    if not records:
        raise ReportError(f"{run_dir}: no scored examples in {folder.examples_dir}; every example failed or the "
                          "run was interrupted before scoring one. Rerun `rigidbench evaluate` for it")
    perception = run.get("perception") or {}
    info = RunInfo(
        name=str(run.get("model") or results.get("model") or run_dir.name),
        path=run_dir,
        perception=str(perception.get("backend") or results.get("perception") or "unknown"),
        perception_version=str(perception.get("version", "")),
        official=bool(results.get("official", False)),
        why_not_official=tuple(results.get("why_not_official") or ()),
        skipped_metrics=dict(results.get("skipped_metrics") or {}),
        failed=failed,
        n_examples=len(records),
        n_reference=results.get("n_reference"),
        finished_at=str(run.get("finished_at", "")),
        predictions=str(run.get("predictions") or ""),
        data=str(run.get("data") or ""),
        coverage=dict(results.get("coverage") or {}),
    )
    return info, records


def _unique_names(infos: list[RunInfo]) -> list[RunInfo]:
    """Runs with the same model name get their directory name appended, so every row is distinct."""
    names = [info.name for info in infos]
    out = []
    for info in infos:
        if names.count(info.name) > 1:
            renamed = f"{info.name} ({info.path.name})"
            log.warning("two runs are named %s; calling the one in %s '%s'", info.name, info.path, renamed)
            info = replace(info, name=renamed)
        out.append(info)
    if len({info.name for info in out}) != len(out):
        raise ReportError("several runs have the same model name and directory name: "
                          + ", ".join(str(i.path) for i in infos) + "; pass each run once")
    return out


def load_runs(run_dirs) -> ScoreTable:
    """run_dirs: sequence of run directories. Returns a ScoreTable over the example ids all runs share."""
    run_dirs = [Path(p) for p in run_dirs]
    if not run_dirs:
        raise ReportError("no run directories given; pass e.g. runs/* (directories written by `rigidbench evaluate`)")
    loaded = [read_run(p) for p in run_dirs]
    infos = _unique_names([info for info, _ in loaded])
    id_sets = [set(records) for _, records in loaded]
    shared = sorted(set.intersection(*id_sets))
    if not shared:
        raise ReportError("the runs share no example ids, so they cannot be compared: "
                          + "; ".join(f"{i.path}: {len(s)} examples" for i, s in zip(infos, id_sets)))
    notes = []
    extra = {info.name: len(ids) - len(shared) for info, ids in zip(infos, id_sets) if len(ids) > len(shared)}
    if extra:
        notes.append(f"The runs cover different examples; every table and figure uses the {len(shared)} examples "
                     "that all runs share (left out: "
                     + ", ".join(f"{n} from {name}" for name, n in extra.items()) + ").")
        log.warning("%s", notes[-1])
    first = loaded[0][1]
    tasks = np.array([str(first[i]["task"]) for i in shared])
    partitions = np.array([str(first[i]["partition"]) for i in shared])
    for info, (_, records) in zip(infos[1:], loaded[1:]):
        for j, sample_id in enumerate(shared):
            rec = records[sample_id]
            if str(rec["task"]) != tasks[j] or str(rec["partition"]) != partitions[j]:
                raise ReportError(
                    f"{info.path}: example {sample_id} is {rec['task']}/{rec['partition']} here but "
                    f"{tasks[j]}/{partitions[j]} in {infos[0].path}; the runs were scored on different data")
    metric_names = tuple(METRICS)  # the registry at call time: a metric registered later is reported too
    scores = np.full((len(infos), len(shared), len(metric_names)), np.nan)
    skipped = np.zeros((len(infos), len(metric_names)), dtype=bool)
    for m, (info, (_, records)) in enumerate(zip(infos, loaded)):
        for j, sample_id in enumerate(shared):
            stored = records[sample_id]["metrics"]
            scores[m, j] = [_score(stored.get(name)) for name in metric_names]
        for k, name in enumerate(metric_names):
            # Skipped = not computed on any shared example (a missing network), not merely non-finite.
            skipped[m, k] = bool(np.isnan(scores[m, :, k]).all()) and (
                name in info.skipped_metrics or all(name in records[i].get("skipped", {}) for i in shared))
    return ScoreTable(tuple(infos), tuple(shared), tasks, partitions, metric_names, scores, skipped, tuple(notes))
