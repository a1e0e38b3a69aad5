"""Depth metrics: clip-level disparity alignment, SI-MSE and ATE-3D (paper eqs. appendix-depth-fit,
appendix-reconstruction, appendix-ate3d, appendix-si-mse).

Reference depth is the Cycles Z pass, float32 (T, H, W) metres along the optical axis; a
pixel is valid when its depth is finite and in (0, 100) m. Predicted disparity (T, h, w) is
bilinearly resized to (H, W) when the grids differ (OpenCV INTER_LINEAR, half-pixel centres).
One scale and shift map predicted disparity to reference inverse depth over every valid
pixel of the clip; aligned disparities that are positive are inverted to depth. Frames are
processed one at a time so a 49 x 704 x 1280 clip never needs a float64 copy of the clip.

Which track points ATE-3D uses: the generated track of every point that is visible in both
the generated and the reference clip at frame t (the perception rule "generated and
reference visibility must both be true"), assigned to its actor by the actor index, and
whose generated position is

- finite: a NaN or infinite position counts as not visible (`common.finite_and_visible`, the
  rule shared with ATE, IdDrift and BGDrift);
- inside the image, i.e. within the area the pixels cover, [-0.5, W - 0.5] x [-0.5, H - 0.5]
  (`common.inside_image`): a generated point that has left the image has no predicted depth
  Z^_t(u^), so it is excluded, not given the depth of the nearest border pixel (within the
  outer half pixel the edge pixels are used, as bilinear sampling does at any image edge);
- on a pixel with a valid aligned depth (positive aligned disparity, finite prediction).

An actor-frame none of whose points passes these tests has no reconstruction and is not in V3.

Under the published evaluator's rules (``rules="published"``, its ``eval/score/trajectory.py`` and
``depth.py``) ATE-3D differs in exactly these places:

- every jointly visible generated point is used: a point outside the image is clamped to
  [0, W - 1.0001] x [0, H - 1.0001] for the depth lookup (it takes the depth of the border pixels)
  and unprojected at its unclamped position; an infinite position makes its actor-frame's
  reconstruction non-finite (so the actor-frame leaves V3); a NaN position stops the release
  (``IndexError``), which is recorded here as NaN with that reason;
- the bilinear depth sample blends all four neighbours, so a neighbour without depth (NaN) drops
  the point even where its weight is 0;
- the geometric median clamps distances at 1e-5 and, on convergence, returns the estimate before
  the last step;
- with no actor moving more than 1 cm the denominator is 1 (the raw RMSE in metres), not NaN;
- a constant predicted disparity gets the minimum-norm least-squares fit (``numpy.linalg.lstsq``),
  scale d0 y / (d0^2 + 1) and shift y / (d0^2 + 1), instead of scale 0 and shift y (the same depth on
  the valid pixels; it differs on pixels without valid reference depth). SI-MSE shares this fit.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from rigidbench.metrics.common import (PAPER_RULES, PUBLISHED_RULES, EdgeRules, MetricResult,
                                       check_rules, finite_and_visible, finite_mean, geometric_median, inside_image,
                                       sample_bilinear, sample_bilinear_clamped, unproject)

log = logging.getLogger(__name__)

#: Reference depths at or beyond this many metres are background/sky and invalid.
MAX_VALID_DEPTH_M = 100.0
#: Actors whose reference start-to-end displacement exceeds this count as moving (A_m).
MIN_DISPLACEMENT_M = 0.01


@dataclass(frozen=True)
class DepthAlignment:
    """Least-squares fit scale * disparity + shift ~= 1 / Z_ref over `n_pixels` valid pixels."""

    scale: float
    shift: float
    n_pixels: int


def valid_reference_depth(depth_ref_m: np.ndarray) -> np.ndarray:
    """depth_ref_m: (..., H, W) float metres. Returns bool of the same shape: finite and in (0, 100) m."""
    with np.errstate(invalid="ignore"):
        return np.isfinite(depth_ref_m) & (depth_ref_m > 0) & (depth_ref_m < MAX_VALID_DEPTH_M)


def disparity_frame(disparity: np.ndarray, t: int, shape_hw: tuple[int, int]) -> np.ndarray:
    """disparity: (T, h, w) float. Returns frame t on the (H, W) grid (bilinearly resized if needed), dtype kept."""
    frame = np.asarray(disparity[t])
    if frame.shape != tuple(shape_hw):
        import cv2

        frame = cv2.resize(frame.astype(np.float32), (shape_hw[1], shape_hw[0]),
                           interpolation=cv2.INTER_LINEAR)
    return frame


def _check_depth_inputs(disparity: np.ndarray, depth_ref_m: np.ndarray) -> None:
    if depth_ref_m.ndim != 3 or disparity.ndim != 3 or disparity.shape[0] != depth_ref_m.shape[0]:
        raise ValueError(f"disparity {disparity.shape} and reference depth {depth_ref_m.shape} must both be "
                         "(T, H, W) with the same T; cut them to the common length first")


def depth_validity(disparity: np.ndarray, depth_ref_m: np.ndarray,
                   valid_ref: np.ndarray | None = None) -> np.ndarray:
    """disparity: (T, h, w); depth_ref_m: (T, H, W) m. Returns (T, H, W) bool: the pixels the disparity
    alignment and SI-MSE use, finite predicted disparity and reference depth in (0, 100) m. Computed once
    per example and shared by both (``score_si_mse``, ``score_ate3d``). ``valid_ref``: the reference's part,
    ``reference_depth_validity(depth_ref_m)``, when already known (once for all the samples of an example)."""
    _check_depth_inputs(disparity, depth_ref_m)
    shape_hw = depth_ref_m.shape[1:]
    out = reference_depth_validity(depth_ref_m) if valid_ref is None else np.empty(depth_ref_m.shape, bool)
    tmp = np.empty(shape_hw, bool)
    for t in range(depth_ref_m.shape[0]):
        np.isfinite(disparity_frame(disparity, t, shape_hw), out=tmp)
        np.logical_and(out[t] if valid_ref is None else valid_ref[t], tmp, out=out[t])
    return out


def reference_depth_validity(depth_ref_m: np.ndarray) -> np.ndarray:
    """depth_ref_m: (T, H, W) m. Returns (T, H, W) bool: reference depth in (0, 100) m (``valid_reference_depth``,
    frame by frame without clip-sized temporaries): the reference's part of ``depth_validity``."""
    out = np.empty(depth_ref_m.shape, bool)
    tmp = np.empty(depth_ref_m.shape[1:], bool)
    with np.errstate(invalid="ignore"):
        for t in range(depth_ref_m.shape[0]):
            z = depth_ref_m[t]
            # 0 < z < 100 excludes NaN and +-inf, so no separate isfinite(z) is needed.
            np.greater(z, 0, out=out[t])
            out[t] &= np.less(z, MAX_VALID_DEPTH_M, out=tmp)
    return out


def _valid_pairs(disparity: np.ndarray, depth_ref_m: np.ndarray, valid: np.ndarray | None, t: int):
    """Frame t's valid pixels as float64 (disparity, reference depth), or None when there are none."""
    d = disparity_frame(disparity, t, depth_ref_m.shape[1:])
    z = depth_ref_m[t]
    if valid is None:
        keep = valid_reference_depth(z) & np.isfinite(d)
    else:
        keep = valid[t]
    if not keep.any():
        return None
    return d[keep].astype(np.float64), z[keep].astype(np.float64)


def fit_disparity_alignment(disparity: np.ndarray, depth_ref_m: np.ndarray,
                            valid: np.ndarray | None = None, rules: EdgeRules = PAPER_RULES) -> DepthAlignment:
    """disparity: (T, h, w); depth_ref_m: (T, H, W) m. Returns the clip-level least-squares
    (scale, shift) with scale * d + shift ~= 1/Z over pixels with finite d and Z in (0, 100) m.
    ``valid``: those pixels as (T, H, W) bool when already known (``depth_validity``). A constant
    prediction d0 gets scale 0 (``rules="published"``: the minimum-norm fit, see the module)."""
    _check_depth_inputs(disparity, depth_ref_m)
    rules = check_rules(rules)
    # Shifted one-pass sums in float64: the pivot (first frame's means) removes cancellation.
    n = 0
    pivot_d = pivot_y = None
    s_d = s_y = s_dd = s_dy = 0.0
    for t in range(depth_ref_m.shape[0]):
        pair = _valid_pairs(disparity, depth_ref_m, valid, t)
        if pair is None:
            continue
        dv, yv = pair
        np.divide(1.0, yv, out=yv)
        if pivot_d is None:
            pivot_d, pivot_y = float(dv.mean()), float(yv.mean())
        dv -= pivot_d
        yv -= pivot_y
        n += dv.size
        s_d += float(dv.sum())
        s_y += float(yv.sum())
        # numpy's pairwise sums, not BLAS dot products: BLAS splits long sums across its threads, so the
        # last bits would depend on the thread count (a Ray worker runs with one).
        yv *= dv
        s_dy += float(np.sum(yv))
        dv *= dv
        s_dd += float(np.sum(dv))
    if n == 0:
        log.warning("no pixel has both finite predicted disparity and valid reference depth; "
                    "depth metrics are undefined for this clip")
        return DepthAlignment(float("nan"), float("nan"), 0)
    mean_d, mean_y = s_d / n, s_y / n
    var_d = s_dd / n - mean_d * mean_d
    cov_dy = s_dy / n - mean_d * mean_y
    if not var_d > 0:
        # Constant prediction: every scale fits equally well; the minimum-norm answer is scale 0.
        log.warning("predicted disparity is constant over the valid pixels; aligned depth is constant")
        if rules == PUBLISHED_RULES:  # numpy.linalg.lstsq's minimum-norm solution of s d0 + c = mean(1/Z)
            d0, y = mean_d + pivot_d, mean_y + pivot_y
            return DepthAlignment(d0 * y / (d0 * d0 + 1.0), y / (d0 * d0 + 1.0), n)
        return DepthAlignment(0.0, mean_y + pivot_y, n)
    scale = cov_dy / var_d
    shift = (mean_y + pivot_y) - scale * (mean_d + pivot_d)
    return DepthAlignment(float(scale), float(shift), n)


def aligned_depth(disparity_hw: np.ndarray, alignment: DepthAlignment) -> np.ndarray:
    """disparity_hw: (...) float disparity. Returns (...) float64 depth 1/(s d + c) where that is positive, else NaN."""
    aligned = alignment.scale * np.asarray(disparity_hw, dtype=np.float64) + alignment.shift
    out = np.full(aligned.shape, np.nan)
    positive = np.isfinite(aligned) & (aligned > 0)
    np.divide(1.0, aligned, out=out, where=positive)
    return out


def si_mse(disparity: np.ndarray, depth_ref_m: np.ndarray,
           alignment: DepthAlignment | None = None, valid: np.ndarray | None = None) -> MetricResult:
    """disparity: (T, h, w); depth_ref_m: (T, H, W) m. Returns the mean over frames with >= 1 valid
    pixel of var(log Z^ - log Z) (mean of squares minus squared mean) and (T,) per-frame values.
    ``valid``: (T, H, W) bool from ``depth_validity`` when already computed (shared with the alignment)."""
    _check_depth_inputs(disparity, depth_ref_m)
    if valid is None:
        valid = depth_validity(disparity, depth_ref_m)
    if alignment is None:
        alignment = fit_disparity_alignment(disparity, depth_ref_m, valid=valid)
    t_len = depth_ref_m.shape[0]
    per_frame = np.full(t_len, np.nan)
    if alignment.n_pixels == 0:
        return MetricResult(float("nan"), per_frame)
    for t in range(t_len):
        pair = _valid_pairs(disparity, depth_ref_m, valid, t)
        if pair is None:
            continue
        aligned, zv = pair
        aligned *= alignment.scale
        aligned += alignment.shift
        positive = aligned > 0  # where the aligned depth 1/aligned exists
        n_positive = int(np.count_nonzero(positive))
        if n_positive == 0:
            continue
        if n_positive < aligned.size:
            aligned, zv = aligned[positive], zv[positive]
        # log(Z^) - log(Z) = -log(aligned * Z)
        aligned *= zv
        delta = np.log(aligned, out=aligned)
        np.negative(delta, out=delta)
        mean = np.mean(delta)
        per_frame[t] = float(np.mean(np.square(delta, out=delta)) - mean ** 2)
    return MetricResult(finite_mean(per_frame), per_frame)


def reconstruct_actor_positions(gen_tracks: np.ndarray, visible: np.ndarray, actor_index: np.ndarray,
                                n_actors: int, disparity: np.ndarray, shape_hw: tuple[int, int],
                                alignment: DepthAlignment, K: np.ndarray, R_c: np.ndarray,
                                t_c: np.ndarray, ref_points_m: np.ndarray | None = None,
                                rules: EdgeRules = PAPER_RULES) -> tuple[np.ndarray, np.ndarray | None]:
    """gen_tracks: (P, T, 2) px; visible: (P, T) bool; actor_index: (P,) int; disparity: (T, h, w).
    Returns (N, T, 3) world positions in m: geometric median of each actor's unprojected visible
    points, with depth sampled bilinearly from the aligned depth map; points with a non-finite
    position, outside the image or on invalid depth are left out; NaN where no point is left.
    With ``ref_points_m`` (P, T, 3), the simulator positions of the same tracked points, also
    returns the geometric median of exactly the points used at each actor-frame (else None).
    ``rules="published"``: every visible point, the clamped depth lookup, the unclamped unprojection and
    the release's median (module docstring); gen_tracks must then hold no NaN at a visible point-frame
    (the release stops there; `ate3d` checks first)."""
    published = check_rules(rules) == PUBLISHED_RULES
    t_len = gen_tracks.shape[1]
    actor_index = np.asarray(actor_index)
    out = np.full((n_actors, t_len, 3), np.nan)
    ref = None if ref_points_m is None else np.full((n_actors, t_len, 3), np.nan)
    if alignment.n_pixels == 0:
        return out, ref
    usable = visible if published else finite_and_visible(visible, gen_tracks) & inside_image(gen_tracks, *shape_hw)
    sample, median = ((sample_bilinear_clamped, geometric_median_published) if published
                      else (sample_bilinear, geometric_median))
    for t in range(t_len):
        points_t = np.flatnonzero(usable[:, t])
        if points_t.size == 0:
            continue
        xy = np.asarray(gen_tracks[points_t, t], dtype=np.float64)
        # Aligned depth is evaluated only at the four pixels each sample reads.
        depth_m = sample(disparity_frame(disparity, t, shape_hw), xy, transform=lambda d: aligned_depth(d, alignment))
        with np.errstate(invalid="ignore", over="ignore"):
            world = unproject(xy, depth_m, K, R_c, t_c)
            # The release keeps a point with a positive depth, even where its world position is not finite.
            kept = np.isfinite(depth_m) & (depth_m > 0) if published else np.isfinite(world).all(axis=1)
        for a in range(n_actors):
            mine = kept & (actor_index[points_t] == a)
            if mine.any():
                out[a, t] = median(world[mine])
                if ref is not None:
                    ref[a, t] = median(np.asarray(ref_points_m, np.float64)[points_t[mine], t])
    return out, ref


def geometric_median_published(points: np.ndarray, tol: float = 1e-5, max_iter: int = 100) -> np.ndarray:
    """The published evaluator's Weiszfeld iteration: points (M, D), M >= 1. One point is returned as it
    is; otherwise started at the mean, distances clamped at ``tol``, and when a step moves less than
    ``tol`` the estimate before that step is returned. Non-finite points give a non-finite result."""
    points = np.asarray(points, dtype=np.float64)
    if len(points) == 1:
        return points[0]
    estimate = points.mean(axis=0)
    with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
        for _ in range(max_iter):
            weights = 1.0 / np.maximum(np.linalg.norm(points - estimate, axis=1, keepdims=True), tol)
            new = (points * weights).sum(axis=0) / weights.sum()
            if np.linalg.norm(new - estimate) < tol:
                break
            estimate = new
    return estimate


def _published_stop(gen_tracks: np.ndarray, visible: np.ndarray) -> str:
    """Why the published evaluator stops on these tracks ('' when it does not): a NaN coordinate of a
    visible generated point reaches an integer index in its ``bilinear_sample``."""
    bad = visible & np.isnan(np.asarray(gen_tracks, dtype=np.float64)).any(axis=-1)
    if not bad.any():
        return ""
    p, t = (int(i[0]) for i in np.nonzero(bad))
    return ("undefined under the published evaluator's rules: it stops with IndexError "
            f"(trajectory.bilinear_sample) on a NaN generated track position flagged visible (point {p}, frame {t})")


def ate3d(gen_tracks: np.ndarray, ref_visible: np.ndarray, gen_visible: np.ndarray,
          actor_index: np.ndarray, disparity: np.ndarray, depth_ref_m: np.ndarray, K: np.ndarray,
          R_c: np.ndarray, t_c: np.ndarray, positions_m: np.ndarray,
          alignment: DepthAlignment | None = None, ref_points_m: np.ndarray | None = None,
          rules: EdgeRules = PAPER_RULES) -> MetricResult:
    """gen_tracks: (P, T, 2) px; visibilities (P, T) bool; actor_index (P,) int in [0, N);
    disparity (T, h, w); depth_ref_m (T, H, W) m; K (3,3); camera-to-world R_c (3,3), t_c (3,)
    (Blender convention); positions_m (N, T, 3) reference actor positions over the same T.
    ref_points_m (P, T, 3), optional: simulator world positions of the tracked points; when given,
    the reference position of an actor-frame is the geometric median of the same points used for
    the reconstruction (so a perfect prediction scores exactly zero, rather than the offset between
    a surface-point median and the body origin), while the displacement scale still uses
    positions_m. Returns RMSE over finite actor-frames / mean start-to-end displacement of actors moving
    > 0.01 m (NaN if either set is empty), and (T,) per-frame RMS over actors / the same denominator.
    ``rules="published"``: the published evaluator's rules (module docstring); ref_points_m is not used."""
    _check_depth_inputs(disparity, depth_ref_m)
    rules = check_rules(rules)
    positions_m = np.asarray(positions_m, dtype=np.float64)
    n_actors, t_len = positions_m.shape[:2]
    if gen_tracks.shape[1] != t_len or depth_ref_m.shape[0] != t_len:
        raise ValueError(f"tracks ({gen_tracks.shape[1]} frames), depth ({depth_ref_m.shape[0]}) and reference "
                         f"positions ({t_len}) must cover the same frames; cut them to the common length first")
    actor_index = np.asarray(actor_index)
    if actor_index.size and (actor_index.min() < 0 or actor_index.max() >= n_actors):
        raise ValueError(f"actor_index must lie in [0, {n_actors}) to match positions_m; got "
                         f"[{actor_index.min()}, {actor_index.max()}]")
    visible = np.asarray(ref_visible, bool) & np.asarray(gen_visible, bool)
    per_frame = np.full(t_len, np.nan)
    if rules == PUBLISHED_RULES:
        stop = _published_stop(gen_tracks, visible)
        if stop:
            return MetricResult(float("nan"), per_frame, stop)
    if alignment is None:
        alignment = fit_disparity_alignment(disparity, depth_ref_m, rules=rules)
    if rules == PUBLISHED_RULES:
        ref_points_m = None
    recon, ref_points_median = reconstruct_actor_positions(gen_tracks, visible, actor_index, n_actors, disparity,
                                                           depth_ref_m.shape[1:], alignment, K, R_c, t_c,
                                                           ref_points_m, rules=rules)
    target = positions_m if ref_points_median is None else ref_points_median
    with np.errstate(invalid="ignore", over="ignore"):
        sq_err = np.sum((recon - target) ** 2, axis=-1)  # (N, T), NaN outside V3
    displacement = np.linalg.norm(positions_m[:, -1] - positions_m[:, 0], axis=-1)
    moving = displacement > MIN_DISPLACEMENT_M
    in_v3 = np.isfinite(recon).all(axis=-1)
    if not in_v3.any() or (rules == PAPER_RULES and not moving.any()):
        return MetricResult(float("nan"), per_frame)
    # The published evaluator divides by 1 (metres) when no actor moves more than 1 cm.
    scale = float(displacement[moving].mean()) if moving.any() else 1.0
    value = float(np.sqrt(sq_err[in_v3].mean())) / scale
    counts = in_v3.sum(axis=0)
    np.divide(np.where(in_v3, sq_err, 0.0).sum(axis=0), counts, out=per_frame, where=counts > 0)
    per_frame = np.sqrt(per_frame) / scale
    return MetricResult(value, per_frame)


# -- registry adapters: compute(MetricInputs) -> MetricResult -----------------------------------------


def _validity(x) -> np.ndarray:
    """The (T, H, W) pixels with valid reference depth and finite disparity, shared by the fit and SI-MSE (the
    reference's part shared by the samples of an example)."""
    valid_ref = x.reference_shared("valid_depth", lambda: reference_depth_validity(x.ref_depth_m))
    return x.shared("depth_validity", lambda: depth_validity(x.gen_disparity, x.ref_depth_m, valid_ref))


def _alignment(x) -> DepthAlignment:
    """The disparity-to-depth fit of one example, shared by ATE-3D and SI-MSE."""
    return x.shared("disparity_alignment",
                    lambda: fit_disparity_alignment(x.gen_disparity, x.ref_depth_m, valid=_validity(x),
                                                    rules=x.edge_rules))


def score_ate3d(x) -> MetricResult:
    """ATE-3D against the simulated actor positions p_{a,t} (the paper's equation)."""
    c2w = np.asarray(x.camera_to_world, np.float64)
    return ate3d(x.gen_tracks, x.ref_visibility, x.gen_visibility, x.track_actor, x.gen_disparity, x.ref_depth_m,
                 x.K, c2w[:3, :3], c2w[:3, 3], x.actor_positions_m, alignment=_alignment(x), rules=x.edge_rules)


def score_si_mse(x) -> MetricResult:
    return si_mse(x.gen_disparity, x.ref_depth_m, alignment=_alignment(x), valid=_validity(x))
