"""IdDrift: one minus the cosine similarity of features of track-centred patches (paper eq. appendix-iddrift).

Patches: 64 x 64 pixels centred on the reference track in the reference frame and on the
generated track in the generated frame, at every frame t >= 1 where the point is visible in
both clips. With pixel centres at integers, a patch centred at (x, y) covers columns
round(x) - 32 ... round(x) + 31 (rounding half up) and likewise for rows. A patch is
kept only if at least 32 of its columns and at least 32 of its rows lie inside the image; the
part outside the image is filled with zeros (black). A pair counts only if both patches are
kept. Patches are resized to 224 x 224 (bilinear, antialiased, half-pixel centres), scaled to
[0, 1] and normalised with the ImageNet mean and std before the feature function sees them.
Features are L2-normalised before their dot product. Similarities are averaged within each
actor and then across actors that have at least one pair.
"""

from __future__ import annotations

from typing import Callable

import numpy as np

from rigidbench.metrics.common import MetricResult, finite_mean, infer_device
from rigidbench.metrics.tracks import check_tracks

PATCH_SIZE_PX = 64
FEATURE_INPUT_SIZE_PX = 224
IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)


def patch_origins(centers_xy: np.ndarray, size: int = PATCH_SIZE_PX) -> np.ndarray:
    """centers_xy: (M, 2) px (centres at integers). Returns (M, 2) int64 (col, row) of each patch's first pixel."""
    return np.floor(np.asarray(centers_xy, dtype=np.float64) - size / 2 + 0.5).astype(np.int64)


def patch_is_valid(centers_xy: np.ndarray, height: int, width: int, size: int = PATCH_SIZE_PX) -> np.ndarray:
    """centers_xy: (M, 2) px. Returns (M,) bool: finite centre and >= half the patch width and height inside."""
    centers_xy = np.asarray(centers_xy, dtype=np.float64)
    finite = np.isfinite(centers_xy).all(axis=1)
    origin = patch_origins(np.where(finite[:, None], centers_xy, 0.0), size)
    inside_cols = np.minimum(origin[:, 0] + size, width) - np.maximum(origin[:, 0], 0)
    inside_rows = np.minimum(origin[:, 1] + size, height) - np.maximum(origin[:, 1], 0)
    return finite & (2 * inside_cols >= size) & (2 * inside_rows >= size)


def extract_patches(frame: np.ndarray, centers_xy: np.ndarray, size: int = PATCH_SIZE_PX) -> np.ndarray:
    """frame: (H, W, 3) uint8; centers_xy: (M, 2) px with valid patches. Returns (M, size, size, 3) uint8, zeros outside."""
    h, w = frame.shape[:2]
    padded = np.zeros((h + 2 * size, w + 2 * size, frame.shape[2]), dtype=frame.dtype)
    padded[size:size + h, size:size + w] = frame
    origin = patch_origins(centers_xy, size) + size
    # Valid patches overlap the image by >= size/2, so their padded origins lie in [size/2, W + size/2].
    origin[:, 0] = np.clip(origin[:, 0], 0, w + size)
    origin[:, 1] = np.clip(origin[:, 1], 0, h + size)
    offs = np.arange(size)
    rows = origin[:, 1, None, None] + offs[None, :, None]
    cols = origin[:, 0, None, None] + offs[None, None, :]
    return padded[rows, cols]


def preprocess_patches(patches: np.ndarray, device: str | None = None):
    """patches: (B, s, s, 3) uint8. Returns (B, 3, 224, 224) float32 torch tensor, ImageNet-normalised."""
    import torch
    import torch.nn.functional as F

    x = torch.from_numpy(np.ascontiguousarray(patches)).to(device=device).permute(0, 3, 1, 2).float() / 255.0
    x = F.interpolate(x, size=(FEATURE_INPUT_SIZE_PX, FEATURE_INPUT_SIZE_PX), mode="bilinear",
                      align_corners=False, antialias=True)
    mean = torch.tensor(IMAGENET_MEAN, device=x.device).view(1, 3, 1, 1)
    std = torch.tensor(IMAGENET_STD, device=x.device).view(1, 3, 1, 1)
    return (x - mean) / std


def _normalized_features(feature_fn: Callable, patches: np.ndarray, device: str | None):
    import torch

    f = feature_fn(preprocess_patches(patches, device)).float()
    f = f.reshape(f.shape[0], -1)
    return f / torch.linalg.vector_norm(f, dim=1, keepdim=True).clamp_min(1e-12)


def patch_pairs(ref_tracks: np.ndarray, gen_tracks: np.ndarray, ref_visible: np.ndarray,
                gen_visible: np.ndarray, height: int, width: int) -> tuple[np.ndarray, np.ndarray]:
    """Tracks (P, T, 2), visibilities (P, T). Returns point and frame indices (K,) of the valid
    pairs: t >= 1, visible in both clips, and both patches kept."""
    ok = ref_visible & gen_visible
    ok[:, 0] = False
    p_idx, t_idx = np.nonzero(ok)
    keep = (patch_is_valid(ref_tracks[p_idx, t_idx], height, width)
            & patch_is_valid(gen_tracks[p_idx, t_idx], height, width))
    return p_idx[keep], t_idx[keep]


def pair_similarities(ref_rgb: np.ndarray, gen_rgb: np.ndarray, ref_tracks: np.ndarray,
                      gen_tracks: np.ndarray, p_idx: np.ndarray, t_idx: np.ndarray,
                      feature_fn: Callable, batch_size: int = 256, device: str | None = None) -> np.ndarray:
    """RGB (T, H, W, 3) uint8; tracks (P, T, 2); pair indices (K,). Returns (K,) cosine similarities."""
    import torch

    sims = np.empty(len(p_idx))
    # Sorted by frame, so each batch is a few runs of one frame and `sel` stays in run order.
    order = np.argsort(t_idx, kind="stable")
    with torch.inference_mode():
        for start in range(0, len(order), batch_size):
            sel = order[start:start + batch_size]
            ref_patches, gen_patches = [], []
            for t in np.unique(t_idx[sel]):
                here = sel[t_idx[sel] == t]
                ref_patches.append(extract_patches(ref_rgb[t], ref_tracks[p_idx[here], t]))
                gen_patches.append(extract_patches(gen_rgb[t], gen_tracks[p_idx[here], t]))
            f_ref = _normalized_features(feature_fn, np.concatenate(ref_patches), device)
            f_gen = _normalized_features(feature_fn, np.concatenate(gen_patches), device)
            sims[sel] = (f_ref * f_gen).sum(dim=1).double().cpu().numpy()
    return sims


def iddrift(ref_rgb: np.ndarray, gen_rgb: np.ndarray, ref_tracks: np.ndarray, gen_tracks: np.ndarray,
            ref_visible: np.ndarray, gen_visible: np.ndarray, actor_index: np.ndarray,
            feature_fn: Callable, batch_size: int = 256, device: str | None = None) -> MetricResult:
    """RGB (T, H, W, 3) uint8; tracks (P, T, 2) px; visibilities (P, T) bool; actor_index (P,) int;
    feature_fn maps (B, 3, 224, 224) ImageNet-normalised float to (B, D); patches are prepared on
    `device`, by default the device of feature_fn's parameters if it is a torch module. Returns 1 - mean over
    actors of the actor's mean patch cosine similarity (NaN if no actor has a pair), and (T,)
    per frame: 1 - the same actor-then-pair mean restricted to frame t (NaN at t = 0)."""
    check_tracks(ref_tracks, gen_tracks, ref_visible, gen_visible)
    if ref_rgb.shape != gen_rgb.shape or ref_rgb.shape[0] != ref_tracks.shape[1]:
        raise ValueError(f"RGB clips {ref_rgb.shape} / {gen_rgb.shape} must match each other and the "
                         f"{ref_tracks.shape[1]} track frames")
    t_len, height, width = ref_rgb.shape[:3]
    actor_index = np.asarray(actor_index)
    p_idx, t_idx = patch_pairs(ref_tracks, gen_tracks, ref_visible, gen_visible, height, width)
    per_frame = np.full(t_len, np.nan)
    if len(p_idx) == 0:
        return MetricResult(float("nan"), per_frame)
    sims = pair_similarities(ref_rgb, gen_rgb, ref_tracks, gen_tracks, p_idx, t_idx, feature_fn,
                             batch_size, infer_device(feature_fn, device))
    finite = np.isfinite(sims)
    sims, t_idx, actors = sims[finite], t_idx[finite], actor_index[p_idx][finite]
    if len(sims) == 0:
        return MetricResult(float("nan"), per_frame)
    actor_means = [sims[actors == a].mean() for a in np.unique(actors)]
    for t in np.unique(t_idx):
        at_t = t_idx == t
        per_frame[t] = 1.0 - np.mean([sims[at_t & (actors == a)].mean() for a in np.unique(actors[at_t])])
    return MetricResult(1.0 - finite_mean(np.asarray(actor_means)), per_frame)
