"""Scoring one example: the reference bundle and the perceived generated clip -> every registered metric."""

from __future__ import annotations

import numpy as np

from ..metrics import METRICS, MetricInputs
from ..metrics.common import PAPER_RULES, EdgeRules
from ..rotations import quat_to_matrix


def metric_inputs(sample, gen_rgb: np.ndarray, perception, nets,
                  edge_rules: EdgeRules = PAPER_RULES) -> MetricInputs:
    """The MetricInputs of reference ``sample`` and a generated clip gen_rgb (T',H,W,3) uint8 whose
    ``perception`` is already aligned to the first T' reference timestamps; ``nets``: FeatureNets;
    ``edge_rules``: the metrics' edge-case rules (the evaluation protocol's ``edge_rules``)."""
    n = gen_rgb.shape[0]
    active = sample.active_indices
    gt_tracks = sample.tracks
    return MetricInputs(
        ref_rgb=sample.frames[:n], gen_rgb=gen_rgb,
        ref_masks=sample.masks[:n][:, active], gen_masks=perception.masks,
        ref_tracks=gt_tracks["tracks"][:, :n], gen_tracks=perception.tracks,
        ref_visibility=gt_tracks["visibility"][:, :n], gen_visibility=perception.visibility,
        track_actor=sample.track_active_index,
        ref_depth_m=sample.depth[:n], gen_disparity=perception.disparity,
        K=sample.K, camera_to_world=sample.camera_to_world,
        actor_positions_m=sample.trajectory.positions_m[active, :n],
        ref_points_m=tracked_points_world(sample, n),
        bg_tracks=perception.bg_tracks, bg_confidence=perception.bg_confidence,
        lpips_net=nets.lpips, identity_net=nets.identity, edge_rules=edge_rules)


def score_inputs(inputs: MetricInputs, metrics=None) -> dict[str, object]:
    """name -> MetricResult (None: skipped) for every registered metric (or the names in ``metrics``)."""
    names = tuple(METRICS) if metrics is None else tuple(metrics)
    return {name: METRICS.load(name)(inputs) for name in names}


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
