"""Mask metrics: IoU, centroid L2 and bidirectional Chamfer distance (paper eqs. appendix-iou/l2/chamfer).

All three use the nested mean: actors defined at a frame are averaged first, then frames
with at least one defined actor. IoU is always defined (an empty union counts as 1); L2 and
Chamfer are undefined where either mask is empty. Distances are in pixels divided by H.
"""

from __future__ import annotations

import numpy as np

from rigidbench.metrics.common import MetricResult, check_same_shape, nested_mean


def _check_masks(ref_masks: np.ndarray, gen_masks: np.ndarray) -> None:
    check_same_shape("reference masks", ref_masks, "generated masks", gen_masks)
    if ref_masks.ndim != 4:
        raise ValueError(f"masks must be (T, N, H, W), got shape {ref_masks.shape}")
    if ref_masks.dtype != bool or gen_masks.dtype != bool:
        raise ValueError(f"masks must be bool, got {ref_masks.dtype} and {gen_masks.dtype}")


def iou_per_actor(ref_masks: np.ndarray, gen_masks: np.ndarray) -> np.ndarray:
    """ref_masks, gen_masks: (T, N, H, W) bool. Returns (T, N) IoU, 1 where the union is empty."""
    _check_masks(ref_masks, gen_masks)
    t_len, n = ref_masks.shape[:2]
    out = np.empty((t_len, n))
    both = np.empty(ref_masks.shape[2:], bool)
    for t in range(t_len):
        for a in range(n):
            # Flat counts of one contiguous (H, W) plane: numpy's popcount path, many times faster than
            # count_nonzero over axes (a bool-to-int reduction); |A u B| = |A| + |B| - |A n B|.
            r, g = ref_masks[t, a], gen_masks[t, a]
            inter = np.count_nonzero(np.logical_and(r, g, out=both))
            union = np.count_nonzero(r) + np.count_nonzero(g) - inter
            out[t, a] = inter / union if union > 0 else 1.0
    return out


def iou(ref_masks: np.ndarray, gen_masks: np.ndarray) -> MetricResult:
    """ref_masks, gen_masks: (T, N, H, W) bool. Returns nested-mean IoU and (T,) per-frame IoU."""
    return nested_mean(iou_per_actor(ref_masks, gen_masks))


def mask_centroids(masks: np.ndarray) -> np.ndarray:
    """masks: (T, N, H, W) bool. Returns (T, N, 2) pixel centroids (x, y), centres at integers; NaN if empty."""
    t_len, n, _, width = masks.shape
    out = np.full((t_len, n, 2), np.nan)
    for t in range(t_len):
        for a in range(n):
            # Flat indices of the foreground: exact integer sums of rows and columns, no (H,)/(W,) reductions.
            idx = np.flatnonzero(masks[t, a])
            if idx.size:
                rows, cols = np.divmod(idx, width)
                out[t, a] = (int(cols.sum()) / idx.size, int(rows.sum()) / idx.size)
    return out


def centroid_l2_per_actor(ref_masks: np.ndarray, gen_masks: np.ndarray,
                          ref_centroids: np.ndarray | None = None) -> np.ndarray:
    """ref_masks, gen_masks: (T, N, H, W) bool. Returns (T, N) centroid distance / H, NaN if either mask is empty.
    ``ref_centroids``: ``mask_centroids(ref_masks)`` when already known."""
    _check_masks(ref_masks, gen_masks)
    height = ref_masks.shape[2]
    if ref_centroids is None:
        ref_centroids = mask_centroids(ref_masks)
    dist = np.linalg.norm(ref_centroids - mask_centroids(gen_masks), axis=-1)
    return dist / height


def centroid_l2(ref_masks: np.ndarray, gen_masks: np.ndarray, ref_centroids: np.ndarray | None = None) -> MetricResult:
    """ref_masks, gen_masks: (T, N, H, W) bool. Returns nested-mean centroid L2 / H and (T,) per frame."""
    return nested_mean(centroid_l2_per_actor(ref_masks, gen_masks, ref_centroids))


def _mean_distance_to(src: np.ndarray, dst: np.ndarray) -> float:
    """src, dst: (h, w) bool, both non-empty. Mean over src pixels of the Euclidean distance to the nearest dst pixel."""
    from scipy.ndimage import distance_transform_edt

    # The EDT of ~dst is, at every pixel, the exact distance to the nearest dst pixel.
    return float(distance_transform_edt(~dst)[src].mean())


def chamfer_pair(ref_mask: np.ndarray, gen_mask: np.ndarray) -> float:
    """ref_mask, gen_mask: (H, W) bool. Returns d(S, S^) + d(S^, S) in pixels; NaN if either is empty."""
    if not ref_mask.any() or not gen_mask.any():
        return float("nan")
    union = ref_mask | gen_mask
    rows = np.flatnonzero(union.any(axis=1))
    cols = np.flatnonzero(union.any(axis=0))
    # Both sets lie inside the union's bounding box, so the EDT on the crop is still exact.
    crop = (slice(rows[0], rows[-1] + 1), slice(cols[0], cols[-1] + 1))
    a, b = ref_mask[crop], gen_mask[crop]
    return _mean_distance_to(a, b) + _mean_distance_to(b, a)


def chamfer_per_actor(ref_masks: np.ndarray, gen_masks: np.ndarray) -> np.ndarray:
    """ref_masks, gen_masks: (T, N, H, W) bool. Returns (T, N) Chamfer distance / H, NaN if either mask is empty."""
    _check_masks(ref_masks, gen_masks)
    t_len, n, height = ref_masks.shape[:3]
    out = np.full((t_len, n), np.nan)
    for t in range(t_len):
        for a in range(n):
            out[t, a] = chamfer_pair(ref_masks[t, a], gen_masks[t, a]) / height
    return out


def chamfer(ref_masks: np.ndarray, gen_masks: np.ndarray) -> MetricResult:
    """ref_masks, gen_masks: (T, N, H, W) bool. Returns nested-mean Chamfer / H and (T,) per frame."""
    return nested_mean(chamfer_per_actor(ref_masks, gen_masks))


# -- registry adapters: compute(MetricInputs) -> MetricResult -----------------------------------------


def score_iou(x) -> MetricResult:
    return iou(x.ref_masks, x.gen_masks)


def score_centroid_l2(x) -> MetricResult:
    ref_centroids = x.reference_shared("mask_centroids", lambda: mask_centroids(x.ref_masks))
    return centroid_l2(x.ref_masks, x.gen_masks, ref_centroids)


def score_chamfer(x) -> MetricResult:
    return chamfer(x.ref_masks, x.gen_masks)
