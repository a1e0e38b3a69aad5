"""2D Absolute Trajectory Error over point tracks (paper eq. appendix-ate).

Tracks are (P, T, 2) pixel coordinates (x, y) with pixel centres at integers (see
`common`); a point-frame counts only when both the reference and the generated visibility
flags are true and both positions are finite (a NaN or infinite position counts as not
visible, `common.finite_and_visible`), and every such pair has equal weight (no per-actor or
per-frame averaging).

Under the published evaluator's rules (``rules="published"``) a point-frame counts when both visibility
flags are true, whatever its positions: a NaN or infinite position flagged visible makes that frame's
and the clip's ATE NaN (or infinite), as the release's plain mean over the visible pairs does.
"""

from __future__ import annotations

import numpy as np

from rigidbench.metrics.common import (PAPER_RULES, PUBLISHED_RULES, EdgeRules, MetricResult, check_rules,
                                       check_same_shape, finite_and_visible)


def check_tracks(ref_tracks: np.ndarray, gen_tracks: np.ndarray, ref_visible: np.ndarray,
                 gen_visible: np.ndarray) -> None:
    """Raise a ValueError unless tracks are (P, T, 2) and visibilities (P, T) bool of matching size."""
    check_same_shape("reference tracks", ref_tracks, "generated tracks", gen_tracks)
    check_same_shape("reference visibility", ref_visible, "generated visibility", gen_visible)
    if ref_tracks.ndim != 3 or ref_tracks.shape[2] != 2 or ref_visible.shape != ref_tracks.shape[:2]:
        raise ValueError(f"tracks must be (P, T, 2) with visibility (P, T); got {ref_tracks.shape} "
                         f"and {ref_visible.shape}")
    if ref_visible.dtype != bool or gen_visible.dtype != bool:
        raise ValueError(f"visibility must be bool, got {ref_visible.dtype} and {gen_visible.dtype}")


def joint_visibility(ref_visible: np.ndarray, gen_visible: np.ndarray) -> np.ndarray:
    """ref_visible, gen_visible: (P, T) bool. Returns (P, T) bool: visible in both clips."""
    return ref_visible & gen_visible


def ate(ref_tracks: np.ndarray, gen_tracks: np.ndarray, ref_visible: np.ndarray,
        gen_visible: np.ndarray, image_height: int, rules: EdgeRules = PAPER_RULES) -> MetricResult:
    """ref_tracks, gen_tracks: (P, T, 2) px; visibilities (P, T) bool. Returns the mean of
    ||u^ - u|| / H over jointly visible, finite point-frames (NaN if none) and (T,) per-frame means.
    ``rules="published"``: over every jointly visible point-frame, finite or not (see the module)."""
    check_tracks(ref_tracks, gen_tracks, ref_visible, gen_visible)
    keep = joint_visibility(ref_visible, gen_visible)
    if check_rules(rules) != PUBLISHED_RULES:
        keep = finite_and_visible(keep, ref_tracks, gen_tracks)
    with np.errstate(invalid="ignore"):
        err = np.linalg.norm(np.asarray(gen_tracks, np.float64) - np.asarray(ref_tracks, np.float64),
                             axis=-1) / float(image_height)
    total = float(err[keep].mean()) if keep.any() else float("nan")
    counts = keep.sum(axis=0)
    per_frame = np.full(err.shape[1], np.nan)
    np.divide(np.where(keep, err, 0.0).sum(axis=0), counts, out=per_frame, where=counts > 0)
    return MetricResult(total, per_frame)


def score_ate(x) -> MetricResult:
    """Registry adapter: ATE of the MetricInputs ``x``."""
    return ate(x.ref_tracks, x.gen_tracks, x.ref_visibility, x.gen_visibility, x.height, rules=x.edge_rules)
