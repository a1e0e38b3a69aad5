"""Shared pieces of the metrics: result type, nested means, pixel convention, camera geometry.

Pixel convention (used by every metric, track and corner in RigidBench, and by the bundle's
K, whose principal point is (W/2 - 0.5, H/2 - 0.5)): image coordinates are (x, y) in pixels
with pixel (row i, column j) centred at x = j, y = i, as in OpenCV and CoTracker. The
ground-truth tracks, the rendered masks and depth, and predicted tracks all use it.

Camera convention: the pose (R_c, t_c) is camera-to-world in Blender's convention (the
camera looks down its -Z axis, +Y is up). S = diag(1, -1, -1) converts computer-vision
camera coordinates (X right, Y down, Z forward) to Blender camera coordinates, so a pixel
(u, v) with depth d along the optical axis lies at world R_c S d K^-1 [u, v, 1] + t_c.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np

#: Converts computer-vision camera coordinates to Blender camera coordinates (and back).
CV_TO_BLENDER = np.diag([1.0, -1.0, -1.0])

#: The two rule sets for the edge cases of docs/metrics.md ("Edge cases"): ``paper`` follows the paper's
#: wording (non-finite positions count as not visible, generated points outside the image are left out of
#: ATE-3D, ATE-3D is NaN without a moving actor); ``published`` follows the authors' released evaluator
#: wherever it differs, and records NaN with a reason where that evaluator stops with an exception. The
#: evaluation protocol chooses one (``evaluation.protocol``); every metric takes it as a parameter.
EdgeRules = Literal["paper", "published"]
PAPER_RULES: EdgeRules = "paper"
PUBLISHED_RULES: EdgeRules = "published"
EDGE_RULES: tuple[EdgeRules, ...] = (PAPER_RULES, PUBLISHED_RULES)


def check_rules(rules: str) -> EdgeRules:
    """``rules`` if it names an edge-rule set, else a ValueError naming the known ones."""
    if rules not in EDGE_RULES:
        raise ValueError(f"unknown edge rules {rules!r}; known: {', '.join(EDGE_RULES)}")
    return rules  # type: ignore[return-value]


@dataclass(frozen=True)
class MetricResult:
    """A clip-level score and, where one makes sense, its per-frame values (NaN = undefined); ``note``: why
    the value is NaN where the published evaluator's rules stop with an exception (empty otherwise)."""

    value: float
    per_frame: np.ndarray | None = None
    note: str = ""


def finite_mean(x: np.ndarray) -> float:
    """Mean of the finite entries of x; NaN when there are none."""
    x = np.asarray(x, dtype=np.float64)
    keep = np.isfinite(x)
    return float(x[keep].mean()) if keep.any() else float("nan")


def finite_and_visible(visible: np.ndarray, *tracks: np.ndarray) -> np.ndarray:
    """visible: (P, T) bool; tracks: any number of (P, T, 2) px. Returns (P, T) bool: visible and
    both coordinates of every given track finite. The one rule for non-finite positions (ATE,
    ATE-3D, IdDrift, BGDrift): a NaN or infinite position counts as not visible at that frame,
    whatever its visibility flag or confidence says, so it adds nothing to any sum or count."""
    keep = np.asarray(visible, dtype=bool).copy()
    for xy in tracks:
        keep &= np.isfinite(np.asarray(xy, dtype=np.float64)).all(axis=-1)
    return keep


def inside_image(xy: np.ndarray, height: int, width: int) -> np.ndarray:
    """xy: (..., 2) px (centres at integers). Returns (...) bool: finite and within the area the
    pixels cover, [-0.5, W - 0.5] x [-0.5, H - 0.5] (where `sample_bilinear` gives a value)."""
    xy = np.asarray(xy, dtype=np.float64)
    x, y = xy[..., 0], xy[..., 1]
    with np.errstate(invalid="ignore"):
        return (np.isfinite(x) & np.isfinite(y) & (x >= -0.5) & (x <= width - 0.5)
                & (y >= -0.5) & (y <= height - 0.5))


def nested_mean(q: np.ndarray) -> MetricResult:
    """q: (T, N) per-frame, per-actor values, non-finite = undefined. Returns the mean over
    frames with >= 1 defined actor of the mean over that frame's defined actors, and the
    (T,) per-frame actor means (NaN where no actor is defined)."""
    q = np.asarray(q, dtype=np.float64)
    if q.ndim != 2:
        raise ValueError(f"nested_mean expects a (T, N) array, got shape {q.shape}")
    defined = np.isfinite(q)
    counts = defined.sum(axis=1)
    sums = np.where(defined, q, 0.0).sum(axis=1)
    per_frame = np.full(q.shape[0], np.nan)
    np.divide(sums, counts, out=per_frame, where=counts > 0)
    return MetricResult(finite_mean(per_frame), per_frame)


def infer_device(net, device=None):
    """`device` if given, else the device of a torch module's first parameter, else None (CPU)."""
    if device is not None:
        return device
    parameters = getattr(net, "parameters", None)
    if callable(parameters):
        for p in parameters():
            return p.device
    return None


def check_same_shape(name_a: str, a: np.ndarray, name_b: str, b: np.ndarray) -> None:
    """Raise a ValueError naming both arrays when their shapes differ."""
    if a.shape != b.shape:
        raise ValueError(f"{name_a} has shape {a.shape} but {name_b} has shape {b.shape}; "
                         "cut both clips to the common length and resolution before scoring")


def sample_bilinear(image: np.ndarray, xy: np.ndarray, transform=None) -> np.ndarray:
    """image: (H, W) float; xy: (M, 2) pixel coordinates (x, y), centres at integers. Returns (M,)
    float64 bilinear samples; NaN outside [-0.5, W-0.5] x [-0.5, H-0.5] or where a used neighbour is NaN.

    Within half a pixel of the border the nearest edge pixels are used (edge clamping).
    `transform`, if given, maps the gathered float64 pixel values before interpolation, so
    a per-pixel function of the image is sampled without computing it on the whole image."""
    h, w = image.shape
    xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
    out = np.full(len(xy), np.nan)
    x, y = xy[:, 0], xy[:, 1]
    inside = inside_image(xy, h, w)
    if not inside.any():
        return out
    col = np.clip(x[inside], 0.0, w - 1.0)
    row = np.clip(y[inside], 0.0, h - 1.0)
    c0 = np.minimum(np.floor(col).astype(np.int64), max(w - 2, 0))
    r0 = np.minimum(np.floor(row).astype(np.int64), max(h - 2, 0))
    c1 = np.minimum(c0 + 1, w - 1)
    r1 = np.minimum(r0 + 1, h - 1)
    fc = col - c0
    fr = row - r0
    taps = [np.asarray(image[r, c], dtype=np.float64) for r, c in ((r0, c0), (r0, c1), (r1, c0), (r1, c1))]
    if transform is not None:
        taps = [transform(v) for v in taps]
    v00, v01, v10, v11 = taps
    # A neighbour with zero weight must not poison the sample with its NaN.
    top = _lerp(v00, v01, fc)
    bottom = _lerp(v10, v11, fc)
    out[inside] = _lerp(top, bottom, fr)
    return out


def sample_bilinear_clamped(image: np.ndarray, xy: np.ndarray, transform=None) -> np.ndarray:
    """The published evaluator's sampling (its ``trajectory.bilinear_sample``). image: (H, W) float; xy: (M, 2)
    pixel coordinates without NaN (an infinite one is clamped like any other). Returns (M,) float64.

    Coordinates are clamped to [0, W - 1.0001] x [0, H - 1.0001] first, so a point outside the image takes
    the value of the nearest border pixels; the four neighbours are blended with all four weights, so a NaN
    neighbour makes the sample NaN even where its weight is 0. ``transform`` as in `sample_bilinear`."""
    h, w = image.shape
    xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
    col = np.clip(xy[:, 0], 0.0, w - 1.0001)
    row = np.clip(xy[:, 1], 0.0, h - 1.0001)
    c0, r0 = np.floor(col).astype(np.int64), np.floor(row).astype(np.int64)
    c1, r1 = np.minimum(c0 + 1, w - 1), np.minimum(r0 + 1, h - 1)
    fc, fr = col - c0, row - r0
    taps = [np.asarray(image[r, c], dtype=np.float64) for r, c in ((r0, c0), (r0, c1), (r1, c0), (r1, c1))]
    if transform is not None:
        taps = [transform(v) for v in taps]
    v00, v01, v10, v11 = taps
    return v00 * (1 - fc) * (1 - fr) + v01 * fc * (1 - fr) + v10 * (1 - fc) * fr + v11 * fc * fr


def _lerp(a: np.ndarray, b: np.ndarray, f: np.ndarray) -> np.ndarray:
    """(1-f) a + f b, exact at f = 0 and f = 1 even when the unused end is NaN."""
    res = (1.0 - f) * a + f * b
    res = np.where(f == 0.0, a, res)
    return np.where(f == 1.0, b, res)


def unproject(xy: np.ndarray, depth_m: np.ndarray, K: np.ndarray, R_c: np.ndarray,
              t_c: np.ndarray) -> np.ndarray:
    """xy: (M, 2) pixels; depth_m: (M,) along the optical axis; K (3,3); camera-to-world
    R_c (3,3), t_c (3,) in Blender's camera convention. Returns (M, 3) world points in metres."""
    xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
    homog = np.concatenate([xy, np.ones((len(xy), 1))], axis=1)
    rays_cv = np.linalg.solve(np.asarray(K, dtype=np.float64), homog.T).T
    points_cv = rays_cv * np.asarray(depth_m, dtype=np.float64)[:, None]
    world_from_cv = np.asarray(R_c, dtype=np.float64) @ CV_TO_BLENDER
    return points_cv @ world_from_cv.T + np.asarray(t_c, dtype=np.float64)


def project(points_m: np.ndarray, K: np.ndarray, R_c: np.ndarray,
            t_c: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """points_m: (M, 3) world points; K, R_c, t_c as in `unproject`. Returns (M, 2) pixel
    coordinates and (M,) depth along the optical axis (positive in front of the camera)."""
    points = np.asarray(points_m, dtype=np.float64).reshape(-1, 3)
    cv_from_world = CV_TO_BLENDER @ np.asarray(R_c, dtype=np.float64).T
    cam = (points - np.asarray(t_c, dtype=np.float64)) @ cv_from_world.T
    pix = cam @ np.asarray(K, dtype=np.float64).T
    depth = cam[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        xy = pix[:, :2] / pix[:, 2:3]
    return xy, depth


def geometric_median(points: np.ndarray, tol: float = 1e-5, max_iter: int = 100) -> np.ndarray:
    """points: (M, D) float. Returns the (D,) geometric median by Weiszfeld's algorithm started
    at the mean, stopping when a step moves less than `tol` or after `max_iter` steps; NaN for M=0."""
    points = np.asarray(points, dtype=np.float64)
    if len(points) == 0:
        return np.full(points.shape[1], np.nan)
    estimate = points.mean(axis=0)
    for _ in range(max_iter):
        dist = np.linalg.norm(points - estimate, axis=1)
        # A point at the estimate gets a large finite weight instead of an infinite one.
        weights = 1.0 / np.maximum(dist, 1e-12)
        new = weights @ points / weights.sum()
        step = np.linalg.norm(new - estimate)
        estimate = new
        if step < tol:
            break
    return estimate
