"""Read evaluation run directories (runs/<model>/, written by `rigidbench evaluate`) into one array.

A run directory holds ``results.json`` (aggregates, official flag, skipped measurements),
``run.json`` (model, perception backend, settings, the predictions and reference directories) and
``examples/<id>.json`` (the ten scalars of one example, null where non-finite, with its task and
partition; with several samples per example, ``examples/<id>.s<k>.json`` too, one per sample). `load_runs`
aligns every run on the example ids that all runs share and returns scores (models, examples, metrics) with
NaN for a non-finite or skipped measurement: each example's mean over its samples (its value with one
sample), as results.json's numbers are; the samples themselves are in ``ScoreTable.samples``.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from rigidbench.errors import ReportError
from rigidbench.evaluation.aggregation import example_means, sample_index
from rigidbench.folders import RunFolder, split_sample_item
from rigidbench.groundtruth.bundle import unverified_reason
from rigidbench.jsonio import DamagedJSON, load_json
from rigidbench.metrics import METRICS
from rigidbench.readouts.records import record_problem, rewrite_hint

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
    unreadable: dict = field(default_factory=dict)  # example id -> why its record is left out (damaged)
    protocol: str = ""  # results.json "protocol" name (evaluation.protocol), "" when the run predates it
    dataset: dict = field(default_factory=dict)  # results.json "dataset": the reference set (bundle.set_identity)
    envelope: dict | None = None  # results.json "envelope" (`evaluate --envelope ENV`), None when it has none

    @property
    def dataset_text(self) -> str:
        """The reference set in a few words: its name and version and, for a published set, whether its MD5
        was checked."""
        d = self.dataset
        if not d or "sets" in d:
            return str(d.get("dataset", "mixed")) if d else "unrecorded"
        name = " ".join(str(d[k]) for k in ("dataset", "version") if d.get(k))
        if d.get("dataset") == "rendered":
            return name
        return f"{name} (MD5 {'verified' if unverified_reason(d) is None else 'not verified'})"

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
    """scores: (M, N, K) float64 (models, examples, metrics), each example's mean over its samples' finite
    values, NaN where none is finite or the measurement was skipped; tasks, partitions: (N,) str. ``samples``:
    (M, N, K, S) float64, sample s of the example in column s (S: the largest sample index + 1 of any run), NaN
    where non-finite or the example has no such sample; ``n_samples``: (M, N) int, the samples scored per example
    (1 for a run of one sample per example)."""

    runs: tuple[RunInfo, ...]
    example_ids: tuple[str, ...]
    tasks: np.ndarray
    partitions: np.ndarray
    metrics: tuple[str, ...]
    scores: np.ndarray
    skipped: np.ndarray  # (M, K) bool: the run did not compute this measurement at all
    notes: tuple[str, ...] = field(default=())
    samples: np.ndarray | None = None  # (M, N, K, S): see above; None only for a table built by hand
    n_samples: np.ndarray | None = None  # (M, N) int

    @property
    def models(self) -> tuple[str, ...]:
        return tuple(run.name for run in self.runs)

    def metric_index(self, metric: str) -> int:
        """Position of `metric` along the last axis of `scores`."""
        return self.metrics.index(metric)


def _rerun(run_dir: Path) -> str:
    return f"rerun `rigidbench evaluate` with --out {run_dir} (it keeps every scored example)"


def _read_json(path: Path, run_dir: Path) -> dict:
    """One run-level JSON file of a run (results.json, run.json) as a JSON object; a damaged one (truncated,
    empty, not UTF-8, a directory, another document) raises ReportError naming it and what to do."""
    try:
        return load_json(path, expect=dict)
    except DamagedJSON as exc:
        raise ReportError(f"{exc}; {rewrite_hint(run_dir, path)}") from None


def _score(value) -> float:
    """A stored scalar (float or null) as float64, NaN for null or non-finite."""
    if value is None:
        return math.nan
    value = float(value)
    return value if math.isfinite(value) else math.nan


def read_run(run_dir: str | Path) -> tuple[RunInfo, dict[str, dict]]:
    """Read one run directory. Returns its RunInfo and example id -> example record: with one sample, the
    record; with several, the first sample's record with ``metrics`` the mean over the samples
    (``evaluation.aggregation.example_means``); each has ``sample_records``, its samples' records by sample
    index. An example with a sample record that cannot be read is left out (``RunInfo.unreadable``)."""
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
    failed = results.get("failed") or {}
    if not isinstance(failed, dict):
        raise ReportError(f"{results_path}: its 'failed' is not a JSON object; {rewrite_hint(run_dir, results_path)}")
    records, unreadable = {}, {}
    sample_records: dict[str, list[dict]] = {}
    for path in folder.records():  # <id>.json and <id>.s<k>.json, not <id>.x.json
        if split_sample_item(path.stem)[0] in failed:
            continue  # a stale record from an earlier run of an example that failed this time
        try:
            record = load_json(path, expect=dict)
            problem = record_problem(record)
        except FileNotFoundError:
            continue  # removed since the listing
        except DamagedJSON as exc:
            record, problem = None, str(exc).removeprefix(f"{path}: ")
        if problem is not None:  # left out, counted in the report's header (load_runs)
            log.warning("%s: %s; the example is left out of the report; %s to score it again", path, problem,
                        _rerun(run_dir))
            unreadable[path.stem] = f"{path.relative_to(run_dir)}: {problem}"
            continue
        sample_id = str(record.get("id", path.stem))
        if sample_id in failed:
            continue
        sample_records.setdefault(sample_id, []).append(record)
    left_out = {split_sample_item(stem)[0] for stem in unreadable}  # left out whole: a sample cannot be read
    for example in example_means([r for i, rs in sample_records.items() if i not in left_out for r in rs],
                                 tuple(METRICS)):
        records[example["id"]] = {**example, "sample_records": sorted(sample_records[example["id"]], key=sample_index)}
    coverage = results.get("coverage")
    scored = coverage.get("per_example") if isinstance(coverage, dict) else None
    for sample_id in sorted(scored) if isinstance(scored, dict) else ():  # scored (results.json), record gone
        if sample_id not in records and sample_id not in left_out and sample_id not in failed:
            unreadable[sample_id] = f"{folder.record(sample_id).relative_to(run_dir)}: missing"
    if not records:
        damaged = f" ({len(unreadable)} example record(s) damaged: {'; '.join(unreadable.values())})" \
            if unreadable else ""
        raise ReportError(f"{run_dir}: no scored examples in {folder.examples_dir}{damaged}; every example failed "
                          "or the run was interrupted before scoring one. Rerun `rigidbench evaluate` for it")
    try:
        info = _run_info(run_dir, results, run, failed, records, unreadable)
    except (TypeError, ValueError, AttributeError) as exc:
        raise ReportError(f"{results_path} or {folder.run}: a field has another type than `rigidbench evaluate` "
                          f"writes ({type(exc).__name__}: {exc}); {rewrite_hint(run_dir, results_path)}") from None
    return info, records


def _envelope(block) -> dict | None:
    """results.json's "envelope" block, checked to be a JSON object whose "per_example" is one (TypeError if not)."""
    if block is not None and not (isinstance(block, dict) and isinstance(block.get("per_example", {}), dict)):
        raise TypeError("its 'envelope' is not the object `evaluate --envelope ENV` writes (with a 'per_example' "
                        "object)")
    return block


def _run_info(run_dir: Path, results: dict, run: dict, failed: dict, records: dict, unreadable: dict) -> RunInfo:
    """The RunInfo of a run from its results.json and run.json (TypeError, ValueError or AttributeError when a
    field has another type than evaluate writes)."""
    perception = run.get("perception") or {}
    dataset = dict(results.get("dataset") or {})
    unverified = unverified_reason(dataset)  # a results.json written before issue 32 may still say official
    reasons = tuple(results.get("why_not_official") or ())
    return RunInfo(
        name=str(run.get("model") or results.get("model") or run_dir.name),
        path=run_dir,
        perception=str(perception.get("backend") or results.get("perception") or "unknown"),
        perception_version=str(perception.get("version", "")),
        official=bool(results.get("official", False)) and unverified is None,
        why_not_official=reasons + ((unverified,) if unverified and unverified not in reasons else ()),
        skipped_metrics=dict(results.get("skipped_metrics") or {}),
        failed=failed,
        n_examples=len(records),
        n_reference=results.get("n_reference"),
        finished_at=str(run.get("finished_at", "")),
        predictions=str(run.get("predictions") or ""),
        data=str(run.get("data") or ""),
        coverage=dict(results.get("coverage") or {}),
        unreadable=unreadable,
        protocol=str((results.get("protocol") or {}).get("name") or ""),
        dataset=dataset,
        envelope=_envelope(results.get("envelope")),
    )


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
    for info in infos:
        if info.unreadable:
            notes.append(f"{len(info.unreadable)} example record(s) of {info.name} could not be read and are left "
                         f"out ({'; '.join(info.unreadable.values())}); {_rerun(info.path)} to score them again.")
    protocols = sorted({info.protocol or "unrecorded" for info in infos})
    if len(protocols) > 1:
        notes.append("The runs were scored under different evaluation protocols ("
                     + "; ".join(f"{info.name}: {info.protocol or 'unrecorded'}" for info in infos)
                     + "); their differences mix the protocols' rules with the models' (docs/metrics.md).")
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
    samples, n_samples = _sample_array(loaded, shared, metric_names)
    return ScoreTable(tuple(infos), tuple(shared), tasks, partitions, metric_names, scores, skipped, tuple(notes),
                      samples, n_samples)


def _sample_array(loaded: list[tuple[RunInfo, dict[str, dict]]], shared: list[str], metric_names: tuple[str, ...]
                  ) -> tuple[np.ndarray, np.ndarray]:
    """(samples (M, N, K, S) float64, n_samples (M, N) int) of the runs on the ``shared`` examples: sample s of an
    example in column s (S: the largest sample index + 1), NaN where non-finite or absent (``ScoreTable``)."""
    width = max((sample_index(r) + 1 for _, records in loaded for i in shared for r in records[i]["sample_records"]),
                default=1)
    samples = np.full((len(loaded), len(shared), len(metric_names), width), np.nan)
    n_samples = np.zeros((len(loaded), len(shared)), dtype=np.int64)
    for m, (_, records) in enumerate(loaded):
        for j, sample_id in enumerate(shared):
            for r in records[sample_id]["sample_records"]:
                samples[m, j, :, sample_index(r)] = [_score(r["metrics"].get(name)) for name in metric_names]
            n_samples[m, j] = len(records[sample_id]["sample_records"])
    return samples, n_samples
