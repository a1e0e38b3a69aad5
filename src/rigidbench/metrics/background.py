"""BGDrift: confidence-weighted residual of background corners after a per-frame RANSAC
similarity transform (paper eq. appendix-bgdrift), and the frame-0 corner detector.

For each frame t >= 1, C_t holds the corners with positive confidence at frames 0 and t. If
|C_t| >= 4, `cv2.estimateAffinePartial2D(x0, xt, method=cv2.RANSAC,
ransacReprojThreshold=3.0)` (OpenCV's default threshold, in pixels) fits translation,
rotation and uniform scale; if it returns no transform the raw displacement ||x_t - x_0|| is
the residual. Frames with fewer than 4 corners are skipped (they add nothing to either sum).
Residuals of all corners in C_t (inliers and outliers) are weighted by conf_0 * conf_t and
pooled over every frame and corner before dividing by H.

Non-finite values (the rule shared with ATE, ATE-3D and IdDrift, `common.finite_and_visible`):
a corner whose position or confidence is NaN or infinite at frame t counts as having zero
confidence there, so it is left out of C_t (and, if that happens at frame 0, out of every C_t);
it never reaches the RANSAC fit or either sum.

Under the published evaluator's rules (``rules="published"``) C_t holds the corners whose product of
confidences conf_0 * conf_t is positive (a NaN product is not; an infinite one is), whatever their
positions: a NaN or infinite position reaches the fit and the residuals, so that frame's value and
the clip's BGDrift are NaN (or infinite), as in the release.
"""

from __future__ import annotations

import numpy as np

from rigidbench.metrics.common import (PAPER_RULES, PUBLISHED_RULES, EdgeRules, MetricResult, check_rules,
                                       finite_and_visible)

MIN_CORNERS = 4
RANSAC_THRESHOLD_PX = 3.0
MAX_CORNERS = 200
CORNER_QUALITY = 0.01
CORNER_MIN_DISTANCE_PX = 10
BACKGROUND_EROSION_KERNEL_PX = 31  # elliptical, i.e. a 15-pixel erosion


def detect_background_corners(rgb0: np.ndarray, actor_masks0: np.ndarray, max_corners: int = MAX_CORNERS,
                              quality: float = CORNER_QUALITY,
                              min_distance_px: float = CORNER_MIN_DISTANCE_PX) -> np.ndarray:
    """rgb0: (H, W, 3) uint8 generated frame 0; actor_masks0: (N, H, W) bool generated frame-0
    masks. Returns (C, 2) float32 Shi-Tomasi corners (x, y) in the background eroded by a 31 x 31
    ellipse, in OpenCV's integer-centred pixel coordinates (the RigidBench convention)."""
    import cv2

    if rgb0.ndim != 3 or rgb0.shape[2] != 3 or actor_masks0.shape[1:] != rgb0.shape[:2]:
        raise ValueError(f"expected rgb0 (H, W, 3) and masks (N, H, W) on the same grid; "
                         f"got {rgb0.shape} and {actor_masks0.shape}")
    foreground = np.asarray(actor_masks0, bool).any(axis=0)
    background = np.where(foreground, 0, 255).astype(np.uint8)
    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE,
                                       (BACKGROUND_EROSION_KERNEL_PX, BACKGROUND_EROSION_KERNEL_PX))
    background = cv2.erode(background, kernel)
    gray = cv2.cvtColor(np.ascontiguousarray(rgb0, dtype=np.uint8), cv2.COLOR_RGB2GRAY)
    corners = cv2.goodFeaturesToTrack(gray, maxCorners=max_corners, qualityLevel=quality,
                                      minDistance=min_distance_px, mask=background)
    if corners is None:
        return np.zeros((0, 2), dtype=np.float32)
    return corners.reshape(-1, 2).astype(np.float32)


def frame_residuals(x0: np.ndarray, xt: np.ndarray, ransac_threshold_px: float = RANSAC_THRESHOLD_PX) -> np.ndarray:
    """x0, xt: (C, 2) px corner positions at frames 0 and t. Returns (C,) ||A_t(x0) - xt|| for the
    RANSAC similarity A_t, or ||xt - x0|| when RANSAC returns no transform."""
    import cv2

    src = np.ascontiguousarray(x0, dtype=np.float32).reshape(-1, 1, 2)
    dst = np.ascontiguousarray(xt, dtype=np.float32).reshape(-1, 1, 2)
    transform, _ = cv2.estimateAffinePartial2D(src, dst, method=cv2.RANSAC,
                                               ransacReprojThreshold=ransac_threshold_px)
    x0 = np.asarray(x0, dtype=np.float64)
    xt = np.asarray(xt, dtype=np.float64)
    if transform is None:
        return np.linalg.norm(xt - x0, axis=1)
    mapped = x0 @ transform[:, :2].T + transform[:, 2]
    return np.linalg.norm(mapped - xt, axis=1)


def bgdrift(corner_tracks: np.ndarray, confidences: np.ndarray, image_height: int,
            ransac_threshold_px: float = RANSAC_THRESHOLD_PX, min_corners: int = MIN_CORNERS,
            rules: EdgeRules = PAPER_RULES) -> MetricResult:
    """corner_tracks: (C, T, 2) px; confidences: (C, T) in [0, 1]. Returns (1/H) sum w r / sum w over
    frames t >= 1 with >= 4 usable corners (NaN if none), and (T,) per-frame weighted means / H
    (NaN at t = 0 and skipped frames); the clip value pools weights over frames, it is not the
    mean of the per-frame values. ``rules="published"``: the release's corner rule (module docstring)."""
    corner_tracks = np.asarray(corner_tracks, dtype=np.float64)
    confidences = np.asarray(confidences, dtype=np.float64)
    if corner_tracks.ndim != 3 or corner_tracks.shape[2] != 2 or confidences.shape != corner_tracks.shape[:2]:
        raise ValueError(f"corner tracks must be (C, T, 2) with confidences (C, T); got "
                         f"{corner_tracks.shape} and {confidences.shape}")
    t_len = corner_tracks.shape[1]
    per_frame = np.full(t_len, np.nan)
    published = check_rules(rules) == PUBLISHED_RULES
    with np.errstate(invalid="ignore", over="ignore"):
        # (C, T): positive finite confidence at a finite position; anything else weighs zero.
        weighted = finite_and_visible(np.isfinite(confidences) & (np.nan_to_num(confidences) > 0), corner_tracks)
        product = confidences * confidences[:, :1]  # conf_0 * conf_t
        total_wr = total_w = 0.0
        for t in range(1, t_len):
            usable = product[:, t] > 0 if published else weighted[:, 0] & weighted[:, t]
            if usable.sum() < min_corners:
                continue
            r = frame_residuals(corner_tracks[usable, 0], corner_tracks[usable, t], ransac_threshold_px)
            w = product[usable, t]
            total_wr += float(w @ r)
            total_w += float(w.sum())
            per_frame[t] = float(w @ r) / float(w.sum()) / image_height
        value = total_wr / total_w / image_height if total_w > 0 else float("nan")
    return MetricResult(value, per_frame)


def score_bgdrift(x) -> MetricResult:
    """Registry adapter: BGDrift of the MetricInputs ``x``."""
    return bgdrift(x.bg_tracks, x.bg_confidence, x.height, rules=x.edge_rules)
