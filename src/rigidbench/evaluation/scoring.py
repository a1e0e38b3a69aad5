"""Scoring one example: the reference bundle and the perceived generated clip -> every registered metric."""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from typing import Callable

import numpy as np

from ..executors import usable_cores
from ..metrics import METRICS, MetricInputs
from ..metrics.common import PAPER_RULES, EdgeRules
from ..rotations import quat_to_matrix


#: Why a geometry-only twin (``predictors.twins``) has no appearance measurements.
NO_RGB_REASON = "geometry-only twin: no RGB"


def metric_inputs(sample, gen_rgb: np.ndarray, perception, nets,
                  edge_rules: EdgeRules = PAPER_RULES, reference=None) -> MetricInputs:
    """The MetricInputs of reference ``sample`` and a generated clip gen_rgb (T',H,W,3) uint8 whose
    ``perception`` is already aligned to the first T' reference timestamps; ``nets``: FeatureNets;
    ``edge_rules``: the metrics' edge-case rules (the evaluation protocol's ``edge_rules``). A geometry-only
    perception (``Perception.geometry_only``) skips the appearance group with ``NO_RGB_REASON``. ``reference``: the
    example's ``reference_side.ReferenceSide`` (of ``sample``), whose reference-only arrays and cache the samples
    of the example share (None: computed for these inputs alone; the values are the same)."""
    n = gen_rgb.shape[0]
    active = sample.active_indices
    gt_tracks = sample.tracks
    if reference is not None:
        ref_masks, ref_points, cache = reference.active_masks(n), reference.tracked_points(n), reference.cache
    else:
        ref_masks, ref_points, cache = sample.masks[:n][:, active], tracked_points_world(sample, n), None
    samples = reference.samples if reference is not None else 1
    return MetricInputs(
        ref_rgb=sample.frames[:n], gen_rgb=gen_rgb,
        ref_masks=ref_masks, gen_masks=perception.masks,
        ref_tracks=gt_tracks["tracks"][:, :n], gen_tracks=perception.tracks,
        ref_visibility=gt_tracks["visibility"][:, :n], gen_visibility=perception.visibility,
        track_actor=sample.track_active_index,
        ref_depth_m=sample.depth[:n], gen_disparity=perception.disparity,
        K=sample.K, camera_to_world=sample.camera_to_world,
        actor_positions_m=sample.trajectory.positions_m[active, :n],
        ref_points_m=ref_points,
        bg_tracks=perception.bg_tracks, bg_confidence=perception.bg_confidence,
        lpips_net=nets.lpips, identity_net=nets.identity, edge_rules=edge_rules, reference_cache=cache,
        reference_samples=samples,
        skipped={name: NO_RGB_REASON for name, info in METRICS.items() if info.group == "appearance"}
        if getattr(perception, "geometry_only", False) else {})


#: Measurements computed on a background thread while the others run (where the process may use two cores or
#: more): they spend their time in OpenCV, which releases the GIL (SSIM's Gaussian filters on its own threads),
#: so the rest, mostly single-threaded, overlaps them. Each value is the same wherever it is computed.
BACKGROUND_METRICS = ("ssim",)


def score_inputs(inputs: MetricInputs, metrics=None,
                 after: Callable[[dict[str, object]], None] | None = None) -> dict[str, object]:
    """name -> MetricResult (None: skipped) for every registered metric (or the names in ``metrics``), in that
    order; those in ``inputs.skipped`` are not computed. ``after(scores)``, when given, runs once every
    measurement but those of ``BACKGROUND_METRICS`` is in (``scores`` holds those), while they may still be
    computing (the evaluator computes the readouts there)."""
    names = tuple(METRICS) if metrics is None else tuple(metrics)

    def score(name: str):
        return None if name in inputs.skipped else METRICS.load(name)(inputs)

    background = [name for name in names if name in BACKGROUND_METRICS and name not in inputs.skipped]
    if not background or usable_cores() < 2:
        scores = {name: score(name) for name in names if name not in background}
        if after is not None:
            after(scores)
        scores.update((name, score(name)) for name in background)
        return {name: scores[name] for name in names}
    with ThreadPoolExecutor(max_workers=1) as pool:
        pending = {name: pool.submit(score, name) for name in background}
        scores = {name: score(name) for name in names if name not in pending}
        if after is not None:
            after(scores)
        scores.update((name, future.result()) for name, future in pending.items())
    return {name: scores[name] for name in names}


def skip_reasons(scores: dict[str, object], inputs: MetricInputs, nets) -> dict[str, str]:
    """metric -> why it was not computed, for each skipped (None) entry of ``scores``: the example's own reason
    (``inputs.skipped``), else the feature networks' (``nets.skipped``), else "not computed"."""
    return {m: inputs.skipped.get(m) or nets.skipped.get(m, "not computed") for m, r in scores.items() if r is None}


def score_example(sample, gen_rgb: np.ndarray, perception, nets, metrics=None) -> dict[str, object]:
    """Every registered measurement of one example; see ``metric_inputs`` for the arguments."""
    return score_inputs(metric_inputs(sample, gen_rgb, perception, nets), metrics)


def tracked_points_world(sample, n_frames: int) -> np.ndarray:
    """Simulator world positions (P,T,3) of the ground-truth query points: R_{a,t} p^b + t_{a,t}."""
    tracks = sample.tracks
    traj = sample.trajectory
    body = np.asarray(tracks["points_body_m"], np.float64)
    actor = np.asarray(tracks["actor_index"])
    out = np.empty((body.shape[0], n_frames, 3))
    for t in range(n_frames):
        rot = quat_to_matrix(traj.quat_wxyz[actor, t])  # (P,3,3)
        out[:, t] = np.einsum("pij,pj->pi", rot, body) + traj.positions_m[actor, t]
    return out
