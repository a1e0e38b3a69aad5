"""The evaluate stage: every reference example's prediction perceived, aligned, scored and written."""

from __future__ import annotations

import json
import logging
import math
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from tqdm import tqdm

from ..atomic import atomic_file
from ..errors import EXAMPLE_ERRORS, EvaluationError, UserError
from ..executors import Executor, LocalExecutor, Resources, Shard, failure_record
from ..firstframe import check_first_frame, mismatch_message
from ..folders import RunFolder, find_prediction, state_path
from ..groundtruth.bundle import Sample, bundle_dirs, resolve_split_dir, set_identity
from ..metrics import METRICS
from ..perception.base import Perception, get_backend
from ..perception.features import FeatureNets, feature_nets_key, load_feature_nets
from ..video import align_video, aligned_length, read_video, reference_times, resize_frames
from ..readouts.records import aggregate_readouts, example_readouts
from .aggregation import EVAL_SIZE, aggregate, coverage_summary, why_not_official
from .cache import file_hash, input_key, reference_hash, write_json
from .protocol import Protocol, get_protocol
from .provenance import run_info
from .scoring import metric_inputs, score_inputs

log = logging.getLogger(__name__)


@dataclass
class EvaluationSummary:
    out_dir: Path
    evaluated: list[str]
    reused: list[str]
    failed: dict[str, str]
    skipped_metrics: dict[str, str]
    official: bool
    results: dict


def short_clip_message(pred: Path, coverage: dict, fps: float) -> str:
    """Why a clip that does not cover the reference span is refused, and what to do."""
    return (f"{pred}: the clip's last frame is at {coverage['clip_last_s']:.3f} s, so it covers "
            f"{coverage['frames']} of the {coverage['reference_frames']} reference frames (0 to "
            f"{coverage['seconds']:.3f} s); it must cover the reference span 0 to {coverage['span_s']:.3f} s "
            f"({coverage['reference_frames']} frames at {fps:g} fps), as the published evaluator requires. "
            "Generate the whole span, or pass --allow-short to score it on the frames it has (marked in "
            "results.json; not an official result)")


def refusal(facts: dict, pred: Path, ref_dir: Path, first_frame_check: bool, allow_short: bool) -> str | None:
    """Why an example is refused under these rules, from its record's facts (``first_frame``, ``coverage``), or
    None: one rule for a fresh score and for a record reused from a run under other rules. A first frame that
    is not the reference's (another set's inputs) is named before a short clip."""
    first = facts.get("first_frame") or {}
    if first_frame_check and first.get("matches") is False:
        try:
            metadata = Sample(ref_dir).metadata
        except EXAMPLE_ERRORS:
            metadata = {}
        return mismatch_message(pred, ref_dir.name, ref_dir.parent, metadata, float(first.get("correlation", 0.0)))
    coverage = facts.get("coverage") or {}
    if coverage.get("short") and not allow_short:
        return short_clip_message(pred, coverage, float(coverage.get("fps", 24.0)))
    return None


def ready_backend(perception: str, options: dict | None = None):
    """The perception backend, after checking it has every network weight it needs (EvaluationError
    listing each missing one, where it was looked for and how to fetch it, before any work starts)."""
    backend = get_backend(perception, **(options or {}))
    missing = backend.missing_weights() if hasattr(backend, "missing_weights") else []
    if missing:
        raise EvaluationError(f"{backend.name} perception cannot run: " + "\n  ".join(missing)
                              + "\n  (`rigidbench weights --list` shows every weight and where it is looked for)")
    return backend


def _finite_or_none(x: float | None) -> float | None:
    return float(x) if x is not None and math.isfinite(x) else None


def evaluate(pred_dir: str | Path, data_dir: str | Path, out_dir: str | Path, *, perception: str = "gt",
             ids: list[str] | None = None, limit: int | None = None, nets: FeatureNets | None = None,
             model: str | None = None, progress: bool = True, perception_options: dict | None = None,
             executor: Executor | None = None, shard: Shard = Shard(), device: str | None = None,
             protocol: str | None = None, first_frame_check: bool = True,
             allow_short: bool = False) -> EvaluationSummary:
    """Score every selected example of the reference split ``data_dir`` (a split directory, or a data root
    holding one split); writes out/examples/<id>.json and .npz, out/results.json and out/run.json.

    ``perception_options`` go to the backend's constructor (neural: depth_model, device, weights,
    allow_download, models); a backend with ``use_cache_dir`` caches its model outputs under
    ``out/cache/<backend>/``. A rerun reuses examples whose inputs are unchanged. ``executor`` runs
    the examples (default: in this process); ``shard`` scores only its part of the selection (its
    results.json covers that part; a final run without ``shard`` reuses every example and aggregates).
    ``protocol`` names the evaluation protocol (``evaluation.protocol``; default ``rigidbench-v1``, the
    published evaluator's rules). ``first_frame_check`` (default on) fails an example whose prediction does
    not start from its reference's first frame (generated from another set's inputs); turning it off is
    recorded in results.json. A clip that does not cover the reference span (``video.aligned_length``, the
    rule ``validate`` uses) fails its example, as the published evaluator refuses it; ``allow_short``
    scores it on the frames it has instead, marked short in its record and results.json (not official).
    Every record and results.json hold each example's coverage (seconds and fraction of the span scored)."""
    pred_dir, out_dir = Path(pred_dir), Path(out_dir)
    if not pred_dir.is_dir():
        raise EvaluationError(f"{pred_dir}: predictions directory does not exist")
    data_dir = resolve_split_dir(data_dir)
    model = model or pred_dir.name
    refs = bundle_dirs(data_dir)
    all_ids = [p.name for p in refs]
    if ids:
        unknown = sorted(set(ids) - set(all_ids))
        if unknown:
            raise UserError(f"unknown example id(s) {', '.join(unknown)} in {data_dir}")
        refs = [p for p in refs if p.name in set(ids)]
    refs = shard.select(refs[:limit] if limit is not None else refs)
    executor = executor or LocalExecutor()
    metrics = tuple(METRICS)
    rules = get_protocol(protocol)
    backend = ready_backend(perception, perception_options)
    local = isinstance(executor, LocalExecutor)
    if local and nets is None:
        nets = load_feature_nets(device)
    nets_key = nets.key if nets is not None else feature_nets_key()
    run_folder = RunFolder(out_dir)
    run_folder.examples_dir.mkdir(parents=True, exist_ok=True)
    run_folder.cache_dir.mkdir(exist_ok=True)
    started = time.time()
    evaluated, reused, failed, records = [], [], {}, []
    timings: dict[str, float] = {"decode_s": 0.0, "perception_s": 0.0, "metrics_s": 0.0}
    pred_hashes, ref_hashes = {}, {}
    todo = []
    for ref_dir in refs:  # what needs scoring: the input keys are computed here, on the driver
        sample_id = ref_dir.name
        try:
            pred = find_prediction(pred_dir, sample_id)
            if pred is None:
                raise EvaluationError(f"{sample_id}: no prediction {sample_id}.mp4 (or .webm/.mov/...) in {pred_dir}")
            state = state_path(pred)
            pred_key = file_hash(pred) + (file_hash(state) if state.exists() else "")  # both checked regular
            ref_key = reference_hash(ref_dir)
        except EXAMPLE_ERRORS as exc:
            failed[sample_id] = str(exc)
            log.warning("example %s failed: %s", sample_id, exc)
            continue
        pred_hashes[sample_id], ref_hashes[sample_id] = pred_key, ref_key
        key = input_key(pred_key, ref_key, f"{backend.name}:{backend.version}", nets_key, metrics,
                        f"protocol={rules.name}")
        old = previous_record(run_folder.record(sample_id))
        why = refusal(old, pred, ref_dir, first_frame_check, allow_short) if old.get("input_key") == key else None
        if why is not None:  # scored earlier under looser rules: the same refusal as a fresh score
            failed[sample_id] = why
            log.warning("example %s failed: %s", sample_id, why)
        elif old.get("input_key") == key:
            records.append(old)
            reused.append(sample_id)
        else:
            todo.append({"id": sample_id, "key": key})
    job = {"pred_dir": str(pred_dir.resolve()), "data_dir": str(data_dir.resolve()), "out_dir": str(out_dir.resolve()),
           "model": model, "perception": perception, "perception_options": perception_options or {}, "device": device,
           "protocol": rules.name, "first_frame_check": first_frame_check, "allow_short": allow_short}
    bar = tqdm(total=len(todo), unit="example", desc="evaluate", disable=not progress or not todo)

    def collect(item: dict, result: dict) -> None:
        if result.get("status") == "succeeded":
            records.append(result["record"])
            evaluated.append(item["id"])
            for k, v in result.get("timings", {}).items():
                timings[k] = timings.get(k, 0.0) + v
        else:
            failed[item["id"]] = result.get("error", "failed")
            log.warning("example %s failed: %s", item["id"], failed[item["id"]])
        bar.update(1)

    worker = EvaluateWorker(job, backend=backend, nets=nets) if local else None
    try:
        executor.map(WORKER, job, todo, evaluation_resources(perception, device), on_result=collect, instance=worker)
    finally:
        bar.close()
    records.sort(key=lambda r: r["id"])
    evaluated.sort()
    complete_ids = {r["id"] for r in records}
    selected = [p.name for p in refs]
    missing_metrics = sorted({m for r in records for m in r.get("skipped", {})})
    coverage = coverage_summary(records)
    official = (len(all_ids) == EVAL_SIZE and len(selected) == len(all_ids) and complete_ids == set(all_ids)
                and not failed and not missing_metrics and not coverage["short"])
    skipped = {m: _skip_reason(records, m, nets) for m in missing_metrics}
    results = {"model": model, "perception": backend.name,
               "protocol": {**rules.facts(), "first_frame_check": first_frame_check, "allow_short": allow_short},
               "dataset": set_identity(refs), "official": official, "metrics": list(metrics),
               "n_examples": len(records), "n_reference": len(all_ids), "failed": failed,
               "skipped_metrics": skipped, "coverage": coverage, **aggregate(records, metrics),
               "readouts": aggregate_readouts(records, out_dir)}
    if shard.count > 1:
        results["shard"] = str(shard)
    if not official:
        results["why_not_official"] = why_not_official(all_ids, complete_ids, failed, missing_metrics,
                                                       coverage["short"])
    write_json(run_folder.results, results)
    feature_nets = nets if nets is not None else FeatureNets(skipped={m: skipped[m] for m in skipped})
    info = run_info(model, pred_dir, data_dir, backend, feature_nets, metrics, pred_hashes, ref_hashes, timings,
                    time.time() - started, evaluated, reused, failed)
    write_json(run_folder.run, {**info, "protocol": rules.facts(), "dataset": results["dataset"]})
    return EvaluationSummary(out_dir, evaluated, reused, failed, skipped, official, results)


def previous_record(path: Path) -> dict:
    """The score record an earlier run left at ``path``, or {} when there is none or it is damaged (a
    truncated or foreign file is not an error: the example is simply scored again and the file replaced)."""
    if not path.exists():
        return {}
    try:
        doc = json.loads(path.read_text())
    except (OSError, ValueError) as exc:
        log.warning("%s: cannot be read (%s); scoring this example again", path, exc)
        return {}
    return doc if isinstance(doc, dict) else {}


def _skip_reason(records: list[dict], metric: str, nets: FeatureNets | None) -> str:
    if nets is not None and metric in nets.skipped:
        return nets.skipped[metric]
    return next((r["skipped"][metric] for r in records if metric in r.get("skipped", {})), "not computed")


def evaluation_resources(perception: str, device: str | None) -> Resources:
    """One GPU per worker for neural perception (unless the device is the CPU); one CPU otherwise."""
    return Resources(num_cpus=1, num_gpus=1 if perception == "neural" and device != "cpu" else 0)


WORKER = "rigidbench.evaluation.runner:EvaluateWorker"


class EvaluateWorker:
    """Scores one example per call, ``{"id", "key"}`` -> a record (``status`` succeeded or failed); keeps
    its perception backend and feature networks loaded between calls (a Ray actor holds one)."""

    def __init__(self, job: dict, backend=None, nets: FeatureNets | None = None):
        self.pred_dir, self.data_dir, self.out_dir = (Path(job[k]) for k in ("pred_dir", "data_dir", "out_dir"))
        self.model = job["model"]
        self.backend = backend or ready_backend(job["perception"], job.get("perception_options"))
        if hasattr(self.backend, "use_cache_dir"):
            self.backend.use_cache_dir(RunFolder(self.out_dir).cache_dir / self.backend.name)
        self.nets = nets if nets is not None else load_feature_nets(job.get("device"))
        self.protocol = get_protocol(job.get("protocol"))
        self.first_frame_check = bool(job.get("first_frame_check", True))
        self.allow_short = bool(job.get("allow_short", False))

    def __call__(self, item: dict) -> dict:
        timings: dict[str, float] = {"decode_s": 0.0, "perception_s": 0.0, "metrics_s": 0.0}
        sample_id = item["id"]
        try:
            pred = find_prediction(self.pred_dir, sample_id)
            if pred is None:
                raise EvaluationError(f"{sample_id}: its prediction disappeared from {self.pred_dir}")
            record = _score_one(Sample(self.data_dir / sample_id), pred, self.backend, self.nets, self.model,
                                item["key"], self.out_dir, timings, self.protocol, self.first_frame_check,
                                self.allow_short)
        except EXAMPLE_ERRORS as exc:
            return failure_record(exc)
        return {"status": "succeeded", "record": record, "timings": timings}


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


def _score_one(sample: Sample, pred: Path, backend, nets: FeatureNets, model: str, key: str, out_dir: Path,
               timings: dict[str, float], protocol: Protocol, first_frame_check: bool = True,
               allow_short: bool = False) -> dict:
    """Decode, check coverage, perceive (cached by input key), align and score one example; writes its .npz
    and .json. A clip short of the reference span is refused (EvaluationError) unless ``allow_short``."""
    sample_id = sample.sample_id
    t0 = time.time()
    ref_times = reference_times(sample.n_frames, sample.fps)
    # Decode only up to the last reference time unless the backend needs every generated frame (neural:
    # CoTracker3 offline and VDA see the whole clip, as in the published runs).
    video = read_video(pred, until_s=None if getattr(backend, "whole_clip", True) else float(ref_times[-1]))
    w, h = sample.resolution
    if video.size != (w, h):
        video.frames = resize_frames(video.frames, (w, h))
    matches, correlation = check_first_frame(video.frames[0], sample.frame(0))
    facts = {"first_frame": {"correlation": round(correlation, 4), "matches": bool(matches)},
             "coverage": clip_coverage(video.times_s, ref_times, sample.fps)}
    why = refusal(facts, pred, sample.path, first_frame_check, allow_short)
    if why is not None:  # another set's inputs, or short of the span: refused rather than scored
        raise EvaluationError(why)
    video.frames = protocol.prepare(video.frames)
    timings["decode_s"] += time.time() - t0
    t0 = time.time()
    run_folder = RunFolder(out_dir)
    cache = run_folder.cache_dir / f"{sample_id}-{backend.name}-{key[:16]}.npz"
    if not getattr(backend, "cache", True):  # cheaper to recompute than to store (gt)
        perceived = backend.perceive(sample, video, pred)
    elif cache.exists():
        perceived = Perception.load(cache)
    else:
        perceived = backend.perceive(sample, video, pred)
        for old_cache in run_folder.cache_dir.glob(f"{sample_id}-{backend.name}-*.npz"):
            old_cache.unlink()
        perceived.save(cache)
    timings["perception_s"] += time.time() - t0
    aligned = perceived.aligned(ref_times)
    gen_rgb = align_video(video, ref_times)
    t0 = time.time()
    inputs = metric_inputs(sample, gen_rgb, aligned, nets)  # one adapter for the metrics and the readouts
    scores = score_inputs(inputs)
    timings["metrics_s"] += time.time() - t0
    record = {"id": sample_id, "model": model, "task": sample.task, "partition": sample.partition,
              "protocol": protocol.name,
              "frames_compared": int(gen_rgb.shape[0]), **facts, "input_key": key,
              "perception": backend.name,
              "metrics": {m: (_finite_or_none(r.value) if r is not None else None) for m, r in scores.items()},
              "skipped": {m: nets.skipped.get(m, "not computed") for m, r in scores.items() if r is None}}
    record["readouts"] = example_readouts(sample, inputs, scores, out_dir)
    arrays = {m: np.asarray(r.per_frame, np.float64) for m, r in scores.items()
              if r is not None and r.per_frame is not None}
    with atomic_file(run_folder.arrays(sample_id), suffix=".npz") as tmp:
        np.savez_compressed(tmp, **arrays)
    write_json(run_folder.record(sample_id), record)
    return record
