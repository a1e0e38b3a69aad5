"""Evaluate a model's predictions against the reference bundles (paper, section 3.4 and appendix B).

For every reference example in ``data_dir`` the evaluator decodes ``pred_dir/<id>.<ext>``,
resizes it to the reference resolution, runs a perception backend on it (cached by content
hash), aligns the video and the perception outputs to the reference timestamps t_k = k/24,
computes the ten measurements and writes

- ``out/examples/<id>.json``: the ten scalars (null for non-finite), task, partition, input hash;
- ``out/examples/<id>.npz``: the per-frame arrays of each measurement;
- ``out/results.json``: mean, population standard deviation and finite count per metric,
  overall, per task and per partition, and whether the result is official;
- ``out/run.json``: model, data and prediction hashes, versions, backend, settings, timings,
  skipped measurements and failed examples with reasons.

A rerun skips examples whose inputs (video, world state, reference, backend, settings) are
unchanged and recomputes the others; an interrupted run resumes. One bad example is recorded
with its reason and never stops the others.
"""

from __future__ import annotations

import hashlib
import json
import logging
import math
import platform
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np

log = logging.getLogger(__name__)

METRICS = ("iou", "centroid_l2", "chamfer", "ate", "ate3d", "si_mse", "ssim", "lpips", "iddrift", "bgdrift")
EVAL_SIZE = 100
SCORE_VERSION = "1"


class EvaluationError(Exception):
    """An example could not be evaluated; the message names it and the reason."""


@dataclass
class FeatureNets:
    """Optional learned feature networks; a missing one skips its measurement with a reason."""

    lpips: Callable | None = None
    identity: Callable | None = None
    skipped: dict[str, str] = field(default_factory=dict)
    device: str = "cpu"

    @property
    def key(self) -> str:
        return ",".join(f"{m}={'yes' if getattr(self, n) else 'no'}" for m, n in (("lpips", "lpips"), ("iddrift", "identity")))


def load_feature_nets(device: str | None = None, allow_download: bool = False) -> FeatureNets:
    """LPIPS-AlexNet and DINOv2-L identity features from local weights (see ``perception.weights``) on
    ``device`` (None: CUDA when available); a network whose weights are absent is skipped with the reason."""
    from .perception import weights
    from .perception.device import resolve_device
    from .perception.features import WeightsUnavailable, load_identity_features

    nets = FeatureNets(device=resolve_device(device))
    try:
        nets.lpips = _load_lpips(allow_download).to(nets.device)
    except WeightsUnavailable as exc:
        nets.skipped["lpips"] = str(exc)
    try:
        nets.identity = load_identity_features(device=nets.device, path=weights.locate("dinov2"),
                                               allow_download=allow_download)
    except WeightsUnavailable as exc:
        nets.skipped["iddrift"] = str(exc)
    return nets


def _load_lpips(allow_download: bool):
    """LPIPS-AlexNet with the lpips package's linear layers and the AlexNet backbone from $RIGIDBENCH_ALEXNET
    or the torch hub cache; raises WeightsUnavailable naming what is missing."""
    from .metrics import lpips_net
    from .perception import weights
    from .perception.features import WeightsUnavailable

    lin = weights.locate("lpips-lin")
    if lin is None:
        raise WeightsUnavailable(weights.missing_message("lpips-lin"))
    backbone = weights.locate("alexnet")
    if backbone is None and not allow_download:
        raise WeightsUnavailable(weights.missing_message("alexnet"))
    try:
        return lpips_net.build_lpips_alex(backbone_weights=backbone, lin_weights=lin, allow_download=allow_download)
    except (OSError, KeyError, ValueError) as exc:
        raise WeightsUnavailable(f"{weights.missing_message('alexnet')} (loading failed: {exc})") from None


# ---------------------------------------------------------------------------------------------
# Scoring one example


def score_example(sample, gen_rgb: np.ndarray, perception, nets: FeatureNets) -> dict[str, object]:
    """Compute the ten measurements for aligned inputs of equal length T'.

    gen_rgb (T',H,W,3) uint8 and ``perception`` already aligned to the first T' reference
    timestamps. Returns name -> MetricResult, or None for a skipped measurement.
    """
    from .metrics import appearance, background, depth, identity, masks, tracks

    n = gen_rgb.shape[0]
    active = sample.active_indices
    ref_rgb = sample.frames[:n]
    ref_masks = sample.masks[:n][:, active]
    ref_depth = sample.depth[:n]
    gt_tracks = sample.tracks
    ref_tracks = gt_tracks["tracks"][:, :n]
    ref_vis = gt_tracks["visibility"][:, :n]
    actor = sample.track_active_index
    h = ref_rgb.shape[1]
    K = sample.K
    c2w = sample.camera_to_world
    positions = sample.trajectory.positions_m[active, :n]
    p = perception
    results: dict[str, object] = {
        "iou": masks.iou(ref_masks, p.masks),
        "centroid_l2": masks.centroid_l2(ref_masks, p.masks),
        "chamfer": masks.chamfer(ref_masks, p.masks),
        "ate": tracks.ate(ref_tracks, p.tracks, ref_vis, p.visibility, h),
    }
    alignment = depth.fit_disparity_alignment(p.disparity, ref_depth)
    results["ate3d"] = depth.ate3d(p.tracks, ref_vis, p.visibility, actor, p.disparity, ref_depth, K,
                                   c2w[:3, :3], c2w[:3, 3], positions, alignment=alignment,
                                   ref_points_m=tracked_points_world(sample, n))
    results["si_mse"] = depth.si_mse(p.disparity, ref_depth, alignment=alignment)
    results["ssim"] = appearance.ssim(ref_rgb, gen_rgb)
    results["lpips"] = appearance.lpips(ref_rgb, gen_rgb, nets.lpips) if nets.lpips else None
    results["iddrift"] = (identity.iddrift(ref_rgb, gen_rgb, ref_tracks, p.tracks, ref_vis, p.visibility, actor,
                                           nets.identity) if nets.identity else None)
    results["bgdrift"] = background.bgdrift(p.bg_tracks, p.bg_confidence, h)
    return results


def tracked_points_world(sample, n_frames: int) -> np.ndarray:
    """Simulator world positions (P,T,3) of the ground-truth query points: R_{a,t} p^b + t_{a,t}."""
    from .groundtruth.contacts import quat_to_matrix

    tracks = sample.tracks
    traj = sample.trajectory
    body = np.asarray(tracks["points_body_m"], np.float64)
    actor = np.asarray(tracks["actor_index"])
    out = np.empty((body.shape[0], n_frames, 3))
    for t in range(n_frames):
        rot = quat_to_matrix(traj.quat_wxyz[actor, t])  # (P,3,3)
        out[:, t] = np.einsum("pij,pj->pi", rot, body) + traj.positions_m[actor, t]
    return out


# ---------------------------------------------------------------------------------------------
# Hashing and files


def file_hash(path: Path, chunk: int = 1 << 20) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as fh:
        while block := fh.read(chunk):
            digest.update(block)
    return digest.hexdigest()


REFERENCE_FILES = ("metadata.json", "masks.npz", "depth.npz", "tracks.npz", "trajectories.npz", "video.mp4")


def reference_hash(sample_dir: Path) -> str:
    digest = hashlib.sha256()
    for name in REFERENCE_FILES:
        path = sample_dir / name
        digest.update(name.encode())
        digest.update(file_hash(path).encode() if path.exists() else b"missing")
    return digest.hexdigest()


def _write_json(path: Path, doc: dict) -> None:
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(json.dumps(doc, indent=2, allow_nan=False))
    tmp.replace(path)


def _finite_or_none(x: float) -> float | None:
    return float(x) if x is not None and math.isfinite(x) else None


def find_prediction(pred_dir: Path, sample_id: str) -> Path | None:
    from .video import VIDEO_EXTENSIONS

    found = [pred_dir / f"{sample_id}{ext}" for ext in VIDEO_EXTENSIONS if (pred_dir / f"{sample_id}{ext}").exists()]
    if len(found) > 1:
        raise EvaluationError(f"{sample_id}: several predictions ({', '.join(p.name for p in found)}); keep one")
    return found[0] if found else None


def reference_dirs(data_dir: Path) -> list[Path]:
    """Complete reference bundles (directories with metadata.json), sorted by id."""
    if not data_dir.is_dir():
        raise EvaluationError(f"{data_dir}: reference data directory does not exist; render it with "
                              "`rigidbench render --split eval --data ...`")
    return sorted(p for p in data_dir.iterdir() if p.is_dir() and (p / "metadata.json").exists())


# ---------------------------------------------------------------------------------------------
# Aggregation


def summarise(values: list[float | None]) -> dict:
    arr = np.array([v for v in values if v is not None and math.isfinite(v)], dtype=np.float64)
    return {"mean": float(arr.mean()) if arr.size else None, "std": float(arr.std()) if arr.size else None,
            "finite": int(arr.size), "n": len(values)}


def aggregate(records: list[dict]) -> dict:
    """Mean, population std and finite count per metric overall, per task and per partition."""
    def block(rs: list[dict]) -> dict:
        return {m: summarise([r["metrics"].get(m) for r in rs]) for m in METRICS}

    out = {"overall": block(records), "by_task": {}, "by_partition": {}}
    for key, name in (("task", "by_task"), ("partition", "by_partition")):
        for value in sorted({r[key] for r in records}):
            out[name][value] = block([r for r in records if r[key] == value])
    return out


# ---------------------------------------------------------------------------------------------
# The run


@dataclass
class EvaluationSummary:
    out_dir: Path
    evaluated: list[str]
    reused: list[str]
    failed: dict[str, str]
    skipped_metrics: dict[str, str]
    official: bool
    results: dict


def ready_backend(perception: str, options: dict | None = None):
    """The perception backend, after checking it has every network weight it needs (EvaluationError
    listing each missing one, where it was looked for and how to fetch it, before any work starts)."""
    from .perception.base import get_backend

    backend = get_backend(perception, **(options or {}))
    missing = backend.missing_weights() if hasattr(backend, "missing_weights") else []
    if missing:
        raise EvaluationError(f"{backend.name} perception cannot run: " + "\n  ".join(missing)
                              + "\n  (`rigidbench weights --list` shows every weight and where it is looked for)")
    return backend


def evaluate(pred_dir: str | Path, data_dir: str | Path, out_dir: str | Path, *, perception: str = "gt",
             ids: list[str] | None = None, limit: int | None = None, nets: FeatureNets | None = None,
             model: str | None = None, progress: bool = True,
             perception_options: dict | None = None) -> EvaluationSummary:
    """Score every selected example; see the module docstring for the files written.

    ``perception_options`` go to the backend's constructor (neural: depth_model, device, weights,
    allow_download, models); a backend with ``use_cache_dir`` caches its model outputs under
    ``out/cache/<backend>/``."""
    from .groundtruth.bundle import Sample
    from .perception.base import Perception, PerceptionError
    from .perception.gt import state_path
    from .video import VideoError, align_video, read_video, reference_times, resize_frames

    pred_dir, data_dir, out_dir = Path(pred_dir), Path(data_dir), Path(out_dir)
    if not pred_dir.is_dir():
        raise EvaluationError(f"{pred_dir}: predictions directory does not exist")
    model = model or pred_dir.name
    refs = reference_dirs(data_dir)
    all_ids = [p.name for p in refs]
    if ids:
        unknown = sorted(set(ids) - set(all_ids))
        if unknown:
            raise EvaluationError(f"unknown example id(s) {', '.join(unknown)} in {data_dir}")
        refs = [p for p in refs if p.name in set(ids)]
    refs = refs[:limit] if limit is not None else refs
    backend = ready_backend(perception, perception_options)
    if hasattr(backend, "use_cache_dir"):
        backend.use_cache_dir(out_dir / "cache" / backend.name)
    nets = nets if nets is not None else load_feature_nets()
    (out_dir / "examples").mkdir(parents=True, exist_ok=True)
    (out_dir / "cache").mkdir(exist_ok=True)
    started = time.time()
    evaluated, reused, failed, records = [], [], {}, []
    timings: dict[str, float] = {"decode_s": 0.0, "perception_s": 0.0, "metrics_s": 0.0}
    pred_hashes, ref_hashes = {}, {}
    bar = _progress(len(refs), progress)
    for ref_dir in refs:
        sample_id = ref_dir.name
        bar.set_postfix_str(sample_id)
        try:
            pred = find_prediction(pred_dir, sample_id)
            if pred is None:
                raise EvaluationError(f"{sample_id}: no prediction {sample_id}.mp4 (or .webm/.mov/...) in {pred_dir}")
            state = state_path(pred)
            pred_key = file_hash(pred) + (file_hash(state) if state.exists() else "")
            ref_key = reference_hash(ref_dir)
            pred_hashes[sample_id], ref_hashes[sample_id] = pred_key, ref_key
            input_key = hashlib.sha256(f"{pred_key}|{ref_key}|{backend.name}:{backend.version}|{nets.key}|"
                                       f"{SCORE_VERSION}".encode()).hexdigest()
            record_path = out_dir / "examples" / f"{sample_id}.json"
            if record_path.exists():
                old = json.loads(record_path.read_text())
                if old.get("input_key") == input_key:
                    records.append(old)
                    reused.append(sample_id)
                    bar.update(1)
                    continue
            sample = Sample(ref_dir)
            t0 = time.time()
            video = read_video(pred)
            w, h = sample.resolution
            if video.size != (w, h):
                video.frames = resize_frames(video.frames, (w, h))
            timings["decode_s"] += time.time() - t0
            t0 = time.time()
            cache = out_dir / "cache" / f"{sample_id}-{backend.name}-{input_key[:16]}.npz"
            if cache.exists():
                perceived = Perception.load(cache)
            else:
                perceived = backend.perceive(sample, video, pred)
                for old_cache in (out_dir / "cache").glob(f"{sample_id}-{backend.name}-*.npz"):
                    old_cache.unlink()
                perceived.save(cache)
            timings["perception_s"] += time.time() - t0
            ref_times = reference_times(sample.n_frames, sample.fps)
            aligned = perceived.aligned(ref_times)
            gen_rgb = align_video(video, ref_times)
            t0 = time.time()
            scores = score_example(sample, gen_rgb, aligned, nets)
            timings["metrics_s"] += time.time() - t0
            record = {"id": sample_id, "model": model, "task": sample.task, "partition": sample.partition,
                      "frames_compared": int(gen_rgb.shape[0]), "input_key": input_key,
                      "perception": backend.name,
                      "metrics": {m: (_finite_or_none(r.value) if r is not None else None) for m, r in scores.items()},
                      "skipped": {m: nets.skipped.get(m, "not computed") for m, r in scores.items() if r is None}}
            arrays = {m: np.asarray(r.per_frame, np.float64) for m, r in scores.items()
                      if r is not None and r.per_frame is not None}
            tmp = out_dir / "examples" / f"{sample_id}.tmp.npz"
            np.savez_compressed(tmp, **arrays)
            tmp.replace(out_dir / "examples" / f"{sample_id}.npz")
            _write_json(record_path, record)
            records.append(record)
            evaluated.append(sample_id)
        except (EvaluationError, PerceptionError, VideoError, OSError, ValueError, KeyError) as exc:
            failed[sample_id] = str(exc)
            log.warning("example %s failed: %s", sample_id, exc)
        bar.update(1)
    bar.close()
    complete_ids = {r["id"] for r in records}
    missing_metrics = sorted({m for r in records for m in r.get("skipped", {})})
    official = (len(all_ids) == EVAL_SIZE and complete_ids == set(all_ids) and not failed and not missing_metrics)
    results = {"model": model, "perception": backend.name, "official": official,
               "n_examples": len(records), "n_reference": len(all_ids), "failed": failed,
               "skipped_metrics": {m: nets.skipped.get(m, "not computed") for m in missing_metrics},
               **aggregate(records)}
    if not official:
        results["why_not_official"] = _why_not_official(all_ids, complete_ids, failed, missing_metrics)
    _write_json(out_dir / "results.json", results)
    _write_json(out_dir / "run.json", _run_info(model, pred_dir, data_dir, backend, nets, pred_hashes, ref_hashes,
                                                timings, time.time() - started, evaluated, reused, failed))
    return EvaluationSummary(out_dir, evaluated, reused, failed, results["skipped_metrics"], official, results)


def _why_not_official(all_ids, complete_ids, failed, missing_metrics) -> list[str]:
    reasons = []
    if len(all_ids) != EVAL_SIZE:
        reasons.append(f"the reference directory holds {len(all_ids)} examples, not the {EVAL_SIZE} of the eval split")
    if set(all_ids) - complete_ids:
        reasons.append(f"{len(set(all_ids) - complete_ids)} examples were not scored")
    if failed:
        reasons.append(f"{len(failed)} examples failed")
    if missing_metrics:
        reasons.append(f"measurements skipped: {', '.join(missing_metrics)}")
    return reasons


def _digest(mapping: dict[str, str]) -> str:
    return hashlib.sha256(json.dumps(mapping, sort_keys=True).encode()).hexdigest()


def _versions() -> dict[str, str]:
    import importlib.metadata as md

    out = {"python": platform.python_version()}
    for pkg in ("rigidbench", "numpy", "scipy", "opencv-python-headless", "av", "torch", "pytorch-msssim"):
        try:
            out[pkg] = md.version(pkg)
        except md.PackageNotFoundError:
            out[pkg] = "not installed"
    return out


def _run_info(model, pred_dir, data_dir, backend, nets, pred_hashes, ref_hashes, timings, total_s,
              evaluated, reused, failed) -> dict:
    return {"model": model, "predictions": str(pred_dir), "data": str(data_dir),
            "predictions_hash": _digest(pred_hashes), "data_hash": _digest(ref_hashes),
            "perception": {"backend": backend.name, "version": backend.version,
                           "settings": getattr(backend, "settings", {})},
            "feature_nets": {"lpips": nets.lpips is not None, "iddrift": nets.identity is not None,
                             "device": nets.device, "skipped": nets.skipped},
            "settings": {"reference_fps": 24, "score_version": SCORE_VERSION},
            "versions": _versions(), "timings_s": {**{k: round(v, 3) for k, v in timings.items()},
                                                  "total_s": round(total_s, 3)},
            "evaluated": evaluated, "reused": reused, "failed": failed,
            "finished_at": time.strftime("%Y-%m-%dT%H:%M:%S%z")}


class _NoBar:
    def update(self, n: int = 1) -> None:
        pass

    def set_postfix_str(self, s: str) -> None:
        pass

    def close(self) -> None:
        pass


def _progress(total: int, enabled: bool):
    if not enabled:
        return _NoBar()
    from tqdm import tqdm

    return tqdm(total=total, unit="example", desc="evaluate")
