"""The evaluate stage: every reference example's prediction perceived, aligned, scored and written.

``EvaluateStage`` puts evaluation on the stage driver (``rigidbench.driver``): the driver selects the
examples, keeps a ledger entry per example (``out/.stages/evaluate/<id>.json``) keyed by the example's
inputs and rules, skips those whose key and committed record are unchanged, runs the rest through an
executor and records failures; ``EvaluateWorker`` scores one example into a staging folder, and
``EvaluateStage.finish`` writes results.json and run.json from every selected example's record.

Several samples (generations) per example (``folders.find_samples``: ``<id>.s<k>.mp4`` beside ``<id>.mp4``) make
one item per (example, sample), each with its own ledger entry, key and record (``examples/<id>.s<k>.json``);
``--ids`` and ``--limit`` choose examples with all their samples. results.json's numbers are over examples, each
the mean of its samples, plus a ``samples`` block (seed spread, within-example std, best of K) and the
``variance`` components; one sample per example gives the numbers it gave before samples existed.
"""

from __future__ import annotations

import glob
import logging
import math
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ..driver import (Adopted, ItemResult, Key, Progress, RunOptions, Stage, StageReport, StageWorker,
                      ledger_outcomes, outputs_intact, read_ledger, run_stage)
from ..errors import EXAMPLE_ERRORS, EvaluationError
from ..evaluation.aggregation import (EVAL_SIZE, aggregate, coverage_summary, example_notes, sample_index,
                                      samples_summary, variance_components, why_not_official)
from ..evaluation.envelope import Envelope, check_envelope, envelope_block, read_envelope
from ..evaluation.keys import file_hash, input_key, reference_hash
from ..evaluation.protocol import Protocol, get_protocol
from ..evaluation.provenance import run_info
from ..evaluation.reference_side import ReferenceSide
from ..evaluation.scoring import metric_inputs, score_inputs, skip_reasons
from ..executors import Resources, Shard
from ..firstframe import compare_first_frames, mismatch_message
from ..folders import RunFolder, check_prediction, sample_files, sample_item, state_path
from ..groundtruth.bundle import Sample, bundle_dirs, resolve_split_dir, set_identity, unverified_reason
from ..hashing import digest
from ..jsonio import read_json, write_json
from ..metrics import METRICS
from ..perception.base import Perception, get_backend
from ..perception.features import FeatureNets, feature_nets_key, load_feature_nets
from ..readouts.records import aggregate_readouts, example_readouts, read_example_readouts, record_problem
from ..video import align_video, aligned_length, resize_frames

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class EvaluateFacts:
    """What ``evaluate`` adds to its ``StageReport`` (``report.facts``): results.json's content, the skipped
    measurements (name -> reason) and whether the run is official."""

    results: dict
    skipped_metrics: dict[str, str]
    official: bool


def short_clip_message(pred: Path, coverage: dict, fps: float) -> str:
    """Why a clip that does not cover the reference span is refused, and what to do."""
    return (f"{pred}: the clip's last frame is at {coverage['clip_last_s']:.3f} s, so it covers "
            f"{coverage['frames']} of the {coverage['reference_frames']} reference frames (0 to "
            f"{coverage['seconds']:.3f} s); it must cover the reference span 0 to {coverage['span_s']:.3f} s "
            f"({coverage['reference_frames']} frames at {fps:g} fps), as the published evaluator requires. "
            "Generate the whole span, or pass --allow-short to score it on the frames it has (marked in "
            "results.json; not an official result)")


def refusal(facts: dict, pred: Path, ref_dir: Path, first_frame_check: bool, allow_short: bool) -> str | None:
    """Why an example is refused under these rules, from its facts (``first_frame``, ``coverage``), or None.
    A first frame that is not the reference's (another set's inputs) is named before a short clip. Used for
    a fresh score, and for a record from before ledgers, which is adopted only when these rules accept it."""
    first = facts.get("first_frame") or {}
    if first_frame_check and first.get("matches") is False:
        try:
            metadata = Sample(ref_dir).metadata
        except EXAMPLE_ERRORS:
            metadata = {}
        return mismatch_message(pred, ref_dir.name, ref_dir.parent, metadata, float(first.get("correlation", 0.0)),
                                first.get("orientation"), first.get("turned_correlation"))
    coverage = facts.get("coverage") or {}
    if coverage.get("short") and not allow_short:
        return short_clip_message(pred, coverage, float(coverage.get("fps", 24.0)))
    return None


def ready_backend(perception: str, options: dict | None = None, backend=None):
    """The perception backend (``backend``, or a new one), after checking it has every network weight it needs
    (EvaluationError listing each missing one, where it was looked for and how to fetch it, before any work
    starts)."""
    backend = backend if backend is not None else get_backend(perception, **(options or {}))
    missing = backend.missing_weights() if hasattr(backend, "missing_weights") else []
    if missing:
        raise EvaluationError(f"{backend.name} perception cannot run: " + "\n  ".join(missing)
                              + "\n  (`rigidbench weights --list` shows every weight and where it is looked for)")
    return backend


def _finite_or_none(x: float | None) -> float | None:
    return float(x) if x is not None and math.isfinite(x) else None


def evaluate(pred_dir: str | Path, data_dir: str | Path, out_dir: str | Path, *, perception: str = "gt",
             run: RunOptions = RunOptions(), nets: FeatureNets | None = None,
             model: str | None = None, perception_options: dict | None = None, device: str | None = None,
             protocol: str | None = None, first_frame_check: bool = True,
             allow_short: bool = False, envelope: str | Path | None = None) -> StageReport:
    """Score every selected example of the reference split ``data_dir`` (a split directory, or a data root
    holding one split); writes out/examples/<id>.json, .npz and .readouts.json, out/results.json and
    out/run.json.

    ``perception_options`` go to the backend's constructor (neural: depth_model, device, weights,
    allow_download, models); a backend with ``use_cache_dir`` caches its model outputs under
    ``out/cache/<backend>/``. A rerun reuses examples whose inputs and rules are unchanged (the stage
    driver's ledger, ``out/.stages/evaluate/``; ``EvaluateStage.key``) and scores the others; a killed run
    resumes. ``run`` selects the examples and runs them (default: all, in this process); a selection with a
    shard scores only its part (its results.json covers that part; a final run without one reuses every
    example and aggregates). The weights are checked, and the feature networks loaded, only when an
    example is to be scored. ``protocol`` names the evaluation protocol (``evaluation.protocol``; default
    ``rigidbench-v1``, the published evaluator's rules). ``first_frame_check`` (default on) fails an
    example whose prediction does not start from its reference's first frame (generated from another set's
    inputs); turning it off is recorded in results.json. A clip that does not cover the reference span
    (``video.aligned_length``, the rule ``validate`` uses) fails its example, as the published evaluator
    refuses it; ``allow_short`` scores it on the frames it has instead, marked short in its record and
    results.json (not official). Both rules are part of each example's key: changing one scores the
    examples again. Every record and results.json hold each example's coverage (seconds and fraction of
    the span scored). ``envelope``: a physical envelope folder (``rigidbench envelope``; read and checked to
    be for this set before any example is scored): results.json gains an "envelope" block
    (``evaluation.envelope.envelope_block``); it is not part of any example's key, so changing it rewrites
    results.json only. Returns the driver's report, its ``facts`` an ``EvaluateFacts``."""
    pred_dir, out_dir = Path(pred_dir), Path(out_dir)
    if not pred_dir.is_dir():
        raise EvaluationError(f"{pred_dir}: predictions directory does not exist")
    data_dir = resolve_split_dir(data_dir)
    rules = get_protocol(protocol)
    backend = get_backend(perception, **(perception_options or {}))
    stage = EvaluateStage(pred_dir, data_dir, out_dir, model=model or pred_dir.name, backend=backend, nets=nets,
                          rules=rules, perception=perception, perception_options=perception_options or {},
                          device=device, first_frame_check=first_frame_check, allow_short=allow_short,
                          shard=run.selection.shard)
    if envelope is not None:  # --envelope: read and checked before anything is scored
        stage.envelope = read_envelope(envelope)
        check_envelope(stage.envelope, stage.all_ids, set_identity(bundle_dirs(data_dir)))
    return run_stage(stage, run)


def evaluation_resources(perception: str, device: str | None) -> Resources:
    """One GPU per worker for neural perception (unless the device is the CPU); one CPU otherwise."""
    return Resources(num_cpus=1, num_gpus=1 if perception == "neural" and device != "cpu" else 0)


def read_record(path: Path) -> dict | None:
    """The score record at ``path``, or None when there is none or it is damaged (a truncated or foreign file,
    a field of another type: not an error, the example is simply scored again and the file replaced)."""
    doc = read_json(path, "scoring this example again", expect=dict)
    problem = None if doc is None else record_problem(doc)
    if problem is not None:
        log.warning("%s: %s; scoring this example again", path, problem)
    return doc if problem is None else None


class EvaluateStage(Stage):
    """The evaluate stage as the driver sees it. Root: the run folder; items: one per (example, sample) of the
    reference examples of the split (``items``; one sample per example: the example ids), payload ``{"example":
    id, "sample": k}``; key: a ``Key`` whose facts hold what the worker and run.json need (the example's
    ``input_key``, its prediction file and the content hashes); its digest covers the example's input key (prediction video and world state, reference bundle, perception backend and version,
    feature networks, metric list, protocol, score version; ``cache.input_key``, also stored in its record)
    together with the rules ``first_frame_check`` and ``allow_short``; its output: ``examples/<id>.npz``,
    ``<id>.readouts.json`` and ``<id>.json`` (the record, committed last), named by the sample's item
    (``<id>.s<k>.json`` for sample k >= 1). ``finish`` aggregates per example (its samples' mean)."""

    name = "evaluate"
    worker = "rigidbench.stages.evaluate:EvaluateWorker"

    def __init__(self, pred_dir: Path, data_dir: Path, out_dir: Path, *, model: str, backend, nets: FeatureNets | None,
                 rules: Protocol, perception: str, perception_options: dict, device: str | None,
                 first_frame_check: bool, allow_short: bool, shard: Shard = Shard()):
        self.pred_dir, self.data_dir, self.folder = Path(pred_dir), Path(data_dir), RunFolder(out_dir)
        self.model, self.backend, self.nets, self.rules = model, backend, nets, rules
        self.perception, self.perception_options, self.device = perception, perception_options, device
        self.first_frame_check, self.allow_short, self.shard = first_frame_check, allow_short, shard
        self.resources = evaluation_resources(perception, device)
        self.metrics = tuple(METRICS)
        self.nets_key = nets.key if nets is not None else feature_nets_key()
        self.all_ids = [p.name for p in bundle_dirs(self.data_dir)]
        # filled by items(): item -> payload; sample item -> its video; example -> why its samples cannot be listed;
        # example -> its items
        self.payloads: dict[str, dict] = {}
        self.found: dict[str, Path] = {}
        self.unlisted: dict[str, str] = {}
        self.example_items: dict[str, list[str]] = {}
        self.results: dict | None = None
        self.skipped: dict[str, str] = {}
        self.started = time.time()
        self.envelope: Envelope | None = None  # evaluate --envelope: results.json's "envelope" block

    @property
    def root(self) -> Path:
        return self.folder.path

    @property
    def where(self) -> str:
        return str(self.data_dir)

    def items(self) -> dict[str, Any]:
        """One item per (example, sample): every sample of every reference example under the naming rule
        (``folders.find_samples``), named ``sample_item(id, k)``, payload ``{"example": id, "sample": k}``, in
        example then sample order. An example with no prediction, or whose samples clash (``<id>.mp4`` beside
        ``<id>.s0.mp4``), is the single item ``<id>`` whose key fails with the reason; each sample's file is
        checked by its own key, so one that is not a regular file fails alone."""
        out: dict[str, Any] = {}
        self.found, self.unlisted, self.example_items = {}, {}, {}
        for example in self.all_ids:
            try:
                found = sample_files(self.pred_dir, example)
            except EXAMPLE_ERRORS as exc:
                found, self.unlisted[example] = {}, str(exc)
            for k, path in (found or {0: None}).items():
                item = sample_item(example, k)
                out[item] = {"example": example, "sample": k}
                self.example_items.setdefault(example, []).append(item)
                if path is not None:
                    self.found[item] = path
        if any(len(items) > 1 for items in self.example_items.values()):
            self.unit = "sample"  # the driver's counts are of samples
        self.payloads = out
        return out

    def example_of(self, item_id: str) -> str:
        """The example of an item (``items``' payloads); ``--ids`` and ``--limit`` choose examples."""
        return self.payloads.get(item_id, {}).get("example", item_id)

    def key(self, item_id: str, payload: dict) -> Key:
        """The sample's key: its prediction's hash (and its world state's), with the reference example's."""
        example = payload.get("example", item_id)
        if example in self.unlisted:
            raise EvaluationError(self.unlisted[example])
        pred = self.found.get(item_id)
        if pred is None:
            raise EvaluationError(f"{example}: no prediction {example}.mp4 (or .webm/.mov/..., or samples "
                                  f"{example}.s<k>.mp4) in {self.pred_dir}")
        state = state_path(check_prediction(pred))
        pred_key = file_hash(pred) + (file_hash(state) if state.exists() else "")  # both checked regular
        ref_key = reference_hash(self.data_dir / example)
        key = input_key(pred_key, ref_key, f"{self.backend.name}:{self.backend.version}", self.nets_key,
                        self.metrics, f"protocol={self.rules.key()}")
        return Key(digest(key, {"first_frame_check": self.first_frame_check, "allow_short": self.allow_short}),
                   {"input_key": key, "prediction": str(pred), "pred_hash": pred_key, "ref_hash": ref_key})

    def intact(self, item_id: str) -> bool:
        """Every output the worker listed (the .npz, the .readouts.json and the record) is still there as it was
        committed (the driver's check), the readouts file still reads as one, and the record was scored from
        these inputs (its ``input_key`` is the ledger entry's, which the driver found to hold this key)."""
        entry = read_ledger(self.root, self.name, item_id)
        if not outputs_intact(self.root, entry) or read_example_readouts(self.folder.readouts(item_id),
                                                                         "the example is scored again") is None:
            return False
        record = read_record(self.folder.record(item_id))
        scored = ((entry.get("result") or {}).get("record") or {}).get("input_key")
        return record is not None and scored is not None and record.get("input_key") == scored

    def adopt(self, item_id: str, payload: dict, key: Key) -> Adopted | None:
        """A record from before ledgers scored from these inputs, and accepted by these rules (it may have
        been scored under others: its facts say whether it would be refused now)."""
        record = read_record(self.folder.record(item_id))
        if record is None or record.get("input_key") != key.facts["input_key"]:
            return None
        if refusal(record, Path(key.facts["prediction"]), self.data_dir / payload.get("example", item_id),
                   self.first_frame_check, self.allow_short) is not None:
            return None
        return Adopted({"record": record, "timings": {}}, "a record scored from these inputs before ledgers")

    def job(self) -> dict:
        return {"pred_dir": str(self.pred_dir.resolve()), "data_dir": str(self.data_dir.resolve()),
                "out_dir": str(self.root.resolve()), "model": self.model, "perception": self.perception,
                "perception_options": self.perception_options, "device": self.device, "protocol": self.rules.name,
                "first_frame_check": self.first_frame_check, "allow_short": self.allow_short}

    def worker_instance(self) -> "EvaluateWorker":
        """In this process: a worker around this backend and the feature networks (loaded now, once)."""
        if self.nets is None:
            self.nets = load_feature_nets(self.device)
        return EvaluateWorker(self.job(), backend=self.backend, nets=self.nets)

    def prepare(self, todo: list[str]) -> None:
        """Before any example is scored: every weight the backend needs is there (one error naming each)."""
        ready_backend(self.perception, backend=self.backend)
        self.folder.cache_dir.mkdir(parents=True, exist_ok=True)

    def _outcomes(self, selected: list[str], done: dict[str, dict], failed_items: dict[str, str]
                  ) -> tuple[list[dict], dict[str, str]]:
        """Per example, from the ledger's outcomes of its selected samples (``driver.ledger_outcomes``): the score
        records, sorted by (example, sample), of every complete example (each of its selected samples scored), and
        example -> why it failed for each example with a failed sample (an example of one sample: its reason as
        it is; else each failed sample's, "sample k: ..."). An example with a sample not attempted yet (or being
        scored elsewhere) is in neither."""
        chosen: dict[str, list[str]] = {}
        for item in selected:
            chosen.setdefault(self.example_of(item), []).append(item)
        records, failed = [], {}
        for example, items in chosen.items():
            failures = [(item, failed_items[item]) for item in items if item in failed_items]
            if failures:
                if self.example_items.get(example, [example]) == [example]:
                    failed[example] = failures[0][1]
                else:
                    failed[example] = "; ".join(f"sample {self.index_of(item)}: {why}" for item, why in failures)
            elif all(item in done for item in items):
                for item in items:
                    record = read_record(self.folder.record(item))
                    records.append(record if record is not None else done[item]["result"]["record"])
        records.sort(key=lambda r: (r["id"], sample_index(r)))
        return records, failed

    def index_of(self, item_id: str) -> int:
        """The sample index of an item (``items``' payloads; 0 for an example's own item)."""
        return int(self.payloads.get(item_id, {}).get("sample", 0))

    def finish(self, report: StageReport) -> None:
        """results.json and run.json from the records of every selected example scored now or earlier, by this
        process or another on the same folder (the ledger: ``driver.ledger_outcomes``; a failure counts while
        it is the example's latest entry); nothing when the run did not complete (an interrupt or a bug: the
        rerun writes them). The driver runs this under the run-level lock, so of processes finishing at once
        the last writes results.json from everything done by then."""
        if not report.completed:
            return
        self.folder.examples_dir.mkdir(parents=True, exist_ok=True)
        self.folder.cache_dir.mkdir(exist_ok=True)
        done, failed_items = ledger_outcomes(self, report)
        records, failed = self._outcomes(report.selected, done, failed_items)
        complete_ids = {r["id"] for r in records}
        missing_metrics = sorted({m for r in records for m in r.get("skipped", {})})
        coverage = coverage_summary(records)
        selected_examples = list(dict.fromkeys(self.example_of(i) for i in report.selected))
        dataset = set_identity([self.data_dir / i for i in selected_examples])
        unverified = unverified_reason(dataset)  # a published set whose MD5 nobody checked is never official
        official = (len(self.all_ids) == EVAL_SIZE and set(report.selected) == set(self.payloads)
                    and complete_ids == set(self.all_ids) and not failed and not missing_metrics
                    and not coverage["short"] and unverified is None)
        self.skipped = {m: _skip_reason(records, m, self.nets) for m in missing_metrics}
        results = {"model": self.model, "perception": self.backend.name,
                   "protocol": {**self.rules.facts(), "first_frame_check": self.first_frame_check,
                                "allow_short": self.allow_short},
                   "dataset": dataset, "official": official, "metrics": list(self.metrics),
                   "n_examples": len(complete_ids), "n_reference": len(self.all_ids), "failed": failed,
                   "skipped_metrics": self.skipped, "coverage": coverage, **aggregate(records, self.metrics),
                   "readouts": aggregate_readouts(records, self.root)}
        higher = {m: METRICS[m].higher_is_better for m in self.metrics}
        # several samples per example: the headline above is over per-example sample means; the spreads, the
        # best of K (labelled, never the headline) and the variance components for the report's power table
        results["samples"] = samples_summary(records, self.metrics, higher)
        results["variance"] = variance_components(records, self.metrics)
        notes = example_notes(records)
        if notes:  # values the protocol's rules leave undefined, with the reason (e.g. the release would stop)
            results["notes"] = notes
        if self.shard.count > 1:
            results["shard"] = str(self.shard)
        if not official:
            results["why_not_official"] = why_not_official(self.all_ids, complete_ids, failed, missing_metrics,
                                                           coverage["short"]) + ([unverified] if unverified else [])
        # -- evaluate --envelope: the records against the physical envelope (not part of any example's key) --
        if self.envelope is not None:
            results["envelope"] = envelope_block(self.envelope, records)
        # -- end of the envelope block --
        write_json(self.folder.results, results, indent=2, allow_nan=False)
        timings: dict[str, float] = {"decode_s": 0.0, "perception_s": 0.0, "metrics_s": 0.0}
        for sample_id in report.ran:
            for k, v in report.results[sample_id].get("timings", {}).items():
                timings[k] = timings.get(k, 0.0) + v
        feature_nets = self.nets if self.nets is not None else FeatureNets(skipped=dict(self.skipped))
        facts = {i: k.facts for i, k in report.keys.items() if isinstance(k, Key)}
        info = run_info(self.model, self.pred_dir, self.data_dir, self.backend, feature_nets, self.metrics,
                        {i: f["pred_hash"] for i, f in facts.items()}, {i: f["ref_hash"] for i, f in facts.items()}, timings, time.time() - self.started, sorted(report.ran),
                        list(report.reused), failed)
        write_json(self.folder.run, {**info, "protocol": self.rules.facts(), "dataset": results["dataset"]},
                   indent=2, allow_nan=False)
        self.results = results
        report.facts = EvaluateFacts(results, dict(self.skipped), bool(official))

def _skip_reason(records: list[dict], metric: str, nets: FeatureNets | None) -> str:
    if nets is not None and metric in nets.skipped:
        return nets.skipped[metric]
    return next((r["skipped"][metric] for r in records if metric in r.get("skipped", {})), "not computed")


class EvaluateWorker(StageWorker):
    """Scores one example per call into the staging folder; keeps its perception backend and feature
    networks loaded between calls (built from the job on a Ray actor or a child process, handed over
    ready in this process). Its facts hold the example's ``input_key`` (``EvaluateStage.key``)."""

    STEPS = 3  # decode, perceive, measure

    def __init__(self, job: dict, backend=None, nets: FeatureNets | None = None):
        super().__init__(job)
        self.pred_dir, self.data_dir, self.out_dir = (Path(job[k]) for k in ("pred_dir", "data_dir", "out_dir"))
        self.model = job["model"]
        self.cache_dir = RunFolder(self.out_dir).cache_dir
        self.cache_dir.mkdir(parents=True, exist_ok=True)
        self.backend = backend or ready_backend(job["perception"], job.get("perception_options"))
        if hasattr(self.backend, "use_cache_dir"):
            self.backend.use_cache_dir(self.cache_dir / self.backend.name)
        self.nets = nets if nets is not None else load_feature_nets(job.get("device"))
        self.protocol = get_protocol(job.get("protocol"))
        self.first_frame_check = bool(job.get("first_frame_check", True))
        self.allow_short = bool(job.get("allow_short", False))
        #: the reference side of the last example scored: items come example by example, so the next samples of
        #: that example reuse its reference files and everything derived from them (``reference_side``)
        self.reference: ReferenceSide | None = None
        self._reference_lock = threading.Lock()

    def reference_side(self, example: str, ref_hash: str | None) -> ReferenceSide:
        """The reference side of ``example``: the last one when it is of the same bundle content (``ref_hash``,
        the key's reference hash), else a new one (which replaces it), told how many samples the example has."""
        path = self.data_dir / example
        with self._reference_lock:  # (a local executor may call one worker from several threads)
            if self.reference is None or not self.reference.serves(path, ref_hash):
                self.reference = None  # the previous example's arrays are freed before the next are read
                try:
                    samples = len(sample_files(self.pred_dir, example))
                except EXAMPLE_ERRORS:  # clashing names: that sample's key failed already; the others are scored
                    samples = 1
                self.reference = ReferenceSide.read(path, ref_hash, samples)
            return self.reference

    def run(self, item_id: str, payload: dict, staging: Path, progress: Progress, facts: dict) -> ItemResult:
        timings: dict[str, float] = {"decode_s": 0.0, "perception_s": 0.0, "metrics_s": 0.0}
        example, index = payload.get("example", item_id), int(payload.get("sample", 0))  # item_id: their name
        pred = Path(facts["prediction"])
        if not (pred.exists() or pred.is_symlink()):
            raise EvaluationError(f"{item_id}: its prediction {pred.name} disappeared from {self.pred_dir}")
        reference = self.reference_side(example, facts.get("ref_hash"))
        record = _score_one(reference.sample, pred, self.backend, self.nets, self.model,
                            facts["input_key"], staging, self.cache_dir, timings, self.protocol,
                            self.first_frame_check, self.allow_short, progress, index=index, reference=reference)
        out = RunFolder(Path())  # the paths under the run folder, as written under staging
        outputs = [out.arrays(item_id), out.readouts(item_id), out.record(item_id)]  # the record last: done
        return ItemResult(outputs=[p.as_posix() for p in outputs], result={"record": record, "timings": timings})


def clip_coverage(clip_times_s: np.ndarray, ref_times_s: np.ndarray, fps: float) -> dict:
    """How much of the reference span a clip with frame times clip_times_s (T,) s covers: reference frames
    covered (``aligned_length``), the seconds and fraction of the span (0 to ref_times_s[-1]) they reach,
    the clip's last timestamp, and ``short`` when it misses any reference frame."""
    n = aligned_length(clip_times_s, ref_times_s)
    span_s = float(ref_times_s[-1]) if len(ref_times_s) else 0.0
    seconds = float(ref_times_s[n - 1]) if n else 0.0
    return {"frames": int(n), "reference_frames": int(len(ref_times_s)), "seconds": round(seconds, 6),
            "span_s": round(span_s, 6), "fraction": round(seconds / span_s, 6) if span_s > 0 else float(n > 0),
            "clip_last_s": round(float(clip_times_s[-1]), 6) if len(clip_times_s) else 0.0, "fps": float(fps),
            "short": bool(n < len(ref_times_s))}


def _perceive(backend, sample: Sample, video, pred: Path, cache_dir: Path, item: str, key: str) -> Perception:
    """The backend's perception of the sample's video, cached in ``cache_dir`` as ``<item>-<backend>-<key>.npz``
    (an older cache of the item is replaced) unless the backend says recomputing is cheaper (gt)."""
    cache = cache_dir / f"{item}-{backend.name}-{key[:16]}.npz"
    if not getattr(backend, "cache", True):
        return backend.perceive(sample, video, pred)
    if cache.exists():
        return Perception.load(cache)
    perceived = backend.perceive(sample, video, pred)
    for old_cache in cache_dir.glob(f"{glob.escape(item)}-{backend.name}-*.npz"):
        old_cache.unlink()
    perceived.save(cache)
    return perceived


def _score_one(sample: Sample, pred: Path, backend, nets: FeatureNets, model: str, key: str, staging: Path,
               cache_dir: Path, timings: dict[str, float], protocol: Protocol, first_frame_check: bool = True,
               allow_short: bool = False, progress: Progress = lambda done, total: None, index: int = 0,
               reference: ReferenceSide | None = None) -> dict:
    """Decode, check coverage, perceive (cached under ``cache_dir`` by input key ``key``), align and score
    sample ``index`` of one example (``pred``: its video); writes its .npz, .readouts.json and .json under
    ``staging/examples/`` (a run folder's layout), named by the sample's item (``folders.sample_item``: the
    example id for sample 0), and returns the record (``id``: the example, ``sample``: ``index``). A clip short
    of the reference span is refused (EvaluationError) unless ``allow_short``. ``reference``: the example's
    ``ReferenceSide`` of ``sample`` (the worker keeps it for the example's samples, so that the reference side is
    read and derived once per example; the scores are the same without it); its large files are read on a
    background thread while the video is decoded, as is the world state of a backend with ``prefetch`` (gt).
    ``timings`` gains decode_s, reference_s (waiting for the reference's files), perception_s, metrics_s,
    readouts_s and write_s."""
    if reference is None or reference.sample is not sample:
        reference = ReferenceSide(sample)
    reference.prefetch()
    if hasattr(backend, "prefetch"):  # gt: the world state is read while the video is decoded
        backend.prefetch(pred)
    sample_id = sample.sample_id
    item = sample_item(sample_id, index)
    steps = EvaluateWorker.STEPS
    t0 = time.time()
    ref_times = reference.times_s
    # Decode only up to the last reference time unless the backend needs every generated frame (neural:
    # CoTracker3 offline and VDA see the whole clip, as in the published runs).
    video = protocol.decode(pred, until_s=None if getattr(backend, "whole_clip", True) else float(ref_times[-1]))
    w, h = sample.resolution
    if video.size != (w, h):
        video.frames = resize_frames(video.frames, (w, h))
    facts = {"first_frame": compare_first_frames(video.frames[0], reference.first_frame).facts(),
             "coverage": clip_coverage(video.times_s, ref_times, sample.fps)}
    why = refusal(facts, pred, sample.path, first_frame_check, allow_short)
    if why is not None:  # another set's inputs, or short of the span: refused rather than scored
        raise EvaluationError(why)
    video.frames = protocol.prepare(video.frames, in_place=True)
    timings["decode_s"] += time.time() - t0
    progress(1, steps)
    t0 = time.time()
    perceived = _perceive(backend, sample, video, pred, cache_dir, item, key)
    timings["perception_s"] += time.time() - t0
    t0 = time.time()
    reference.wait()
    timings["reference_s"] = timings.get("reference_s", 0.0) + time.time() - t0
    progress(2, steps)
    aligned = perceived.aligned(ref_times)
    gen_rgb = align_video(video, ref_times, copy=False)
    t0 = time.time()
    inputs = metric_inputs(sample, gen_rgb, aligned, nets, edge_rules=protocol.edge_rules,  # metrics and readouts
                           reference=reference)
    out = RunFolder(staging)
    out.examples_dir.mkdir(parents=True, exist_ok=True)
    readouts: dict = {}  # the summary for the record and the seconds it took

    def with_readouts(partial: dict) -> None:  # the readouts (IdDrift feeds one) while SSIM may still compute
        started = time.time()
        readouts["summary"] = example_readouts(sample, inputs, partial, staging, item)
        readouts["seconds"] = time.time() - started

    scores = score_inputs(inputs, after=with_readouts)
    timings["metrics_s"] += time.time() - t0 - readouts["seconds"]
    timings["readouts_s"] = timings.get("readouts_s", 0.0) + readouts["seconds"]
    record = {"id": sample_id, "sample": int(index), "model": model, "task": sample.task, "partition": sample.partition,
              "protocol": protocol.name,
              "frames_compared": int(gen_rgb.shape[0]), **facts, "input_key": key,
              "perception": backend.name,
              "metrics": {m: (_finite_or_none(r.value) if r is not None else None) for m, r in scores.items()},
              "skipped": skip_reasons(scores, inputs, nets),
              "notes": {m: r.note for m, r in scores.items() if r is not None and r.note}}
    record["readouts"] = readouts["summary"]
    t0 = time.time()
    arrays = {m: np.asarray(r.per_frame, np.float64) for m, r in scores.items()
              if r is not None and r.per_frame is not None}
    np.savez_compressed(out.arrays(item), **arrays)
    write_json(out.record(item), record, indent=2, allow_nan=False)  # NaN refused: null is written
    timings["write_s"] = timings.get("write_s", 0.0) + time.time() - t0
    progress(3, steps)
    return record
