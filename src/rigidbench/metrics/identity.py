"""IdDrift: one minus the cosine similarity of features of track-centred patches (paper eq. appendix-iddrift).

Patches: 64 x 64 pixels requested around the reference track in the reference frame and
around the generated track in the generated frame, at every frame t >= 1 where the point is
visible in both clips and both positions are finite (a NaN or infinite position counts as not
visible, `common.finite_and_visible`, the rule shared with ATE, ATE-3D and BGDrift). With
pixel centres at integers, a patch centred at (x, y) requests columns rint(x) - 32 ...
rint(x) + 31 and likewise for rows, where rint rounds half to even (40.5 -> 40, 41.5 -> 42,
-0.5 -> 0), as Python's and numpy's round do in the authors' release. A patch is kept only
if at least 32 of its columns and at least 32 of its rows lie inside the image; a pair counts
only if both patches are kept. The feature network sees the part of the patch inside the
image (no padding), resized on its own to 224 x 224 (bilinear, half-pixel centres; a border
crop of w x h pixels is stretched to the full input), scaled to [0, 1] and normalised with
the ImageNet mean and std. Features are L2-normalised before their dot product. Similarities
are averaged within each actor and then across actors that have at least one pair.

Under the published evaluator's rules (``rules="published"``) the one difference is a non-finite
position: a reference or generated track position with a NaN or infinite coordinate at a frame t >= 1
where the point is visible in both clips stops the release (``int(round(x))`` raises in its
``extract_patch``), so IdDrift is NaN for the example, with that reason in ``MetricResult.note``.
"""

from __future__ import annotations

from typing import Callable

import numpy as np

from rigidbench.metrics.common import (PAPER_RULES, PUBLISHED_RULES, EdgeRules, MetricResult, check_rules,
                                       finite_and_visible, finite_mean, infer_device)
from rigidbench.metrics.tracks import check_tracks

PATCH_SIZE_PX = 64
FEATURE_INPUT_SIZE_PX = 224
IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)


def patch_origins(centers_xy: np.ndarray, size: int = PATCH_SIZE_PX) -> np.ndarray:
    """centers_xy: (M, 2) finite px (centres at integers). Returns (M, 2) int64 (col, row) of the requested
    patch's first pixel: rint(centre) - size // 2, rounding half to even."""
    return np.rint(np.asarray(centers_xy, dtype=np.float64)).astype(np.int64) - size // 2


def patch_boxes(centers_xy: np.ndarray, height: int, width: int, size: int = PATCH_SIZE_PX) -> np.ndarray:
    """centers_xy: (M, 2) px. Returns (M, 4) int64 (col0, col1, row0, row1), the half-open part of each
    requested patch inside the image (empty, col1 <= col0 or row1 <= row0, for a non-finite centre)."""
    centers_xy = np.asarray(centers_xy, dtype=np.float64).reshape(-1, 2)
    finite = np.isfinite(centers_xy).all(axis=1)
    # Far-off finite centres are clipped first so the integer conversion cannot overflow.
    limit = float(max(height, width) + 2 * size)
    safe = np.where(finite[:, None], np.clip(centers_xy, -limit, limit), -limit)
    origin = patch_origins(safe, size)
    col0, row0 = np.maximum(origin[:, 0], 0), np.maximum(origin[:, 1], 0)
    col1, row1 = np.minimum(origin[:, 0] + size, width), np.minimum(origin[:, 1] + size, height)
    return np.stack([col0, col1, row0, row1], axis=1)


def patch_is_valid(centers_xy: np.ndarray, height: int, width: int, size: int = PATCH_SIZE_PX) -> np.ndarray:
    """centers_xy: (M, 2) px. Returns (M,) bool: finite centre and >= half the patch width and height inside."""
    box = patch_boxes(centers_xy, height, width, size)
    return (2 * (box[:, 1] - box[:, 0]) >= size) & (2 * (box[:, 3] - box[:, 2]) >= size)


def extract_patches(frame: np.ndarray, centers_xy: np.ndarray, size: int = PATCH_SIZE_PX) -> list[np.ndarray]:
    """frame: (H, W, 3) uint8; centers_xy: (M, 2) px with valid patches. Returns M (h, w, 3) uint8 crops, the
    part of each patch inside the image (views into frame; 64 x 64 away from the border)."""
    h, w = frame.shape[:2]
    return [frame[r0:r1, c0:c1] for c0, c1, r0, r1 in patch_boxes(centers_xy, h, w, size)]


def preprocess_patches(patches, device: str | None = None):
    """patches: B (h_i, w_i, 3) uint8 crops (a list, or a (B, s, s, 3) array). Returns (B, 3, 224, 224)
    float32 torch tensor: each crop resized on its own to 224 x 224, scaled to [0, 1], ImageNet-normalised.

    The affine normalisation runs on the crops before resizing (bilinear weights sum to one, so it
    commutes with the resize up to float32 rounding, ~1e-7): 12x fewer values than after. The resize
    keeps torch's antialiased kernel: for an enlargement it computes the same bilinear weights (and is
    faster on a contiguous batch than the plain kernel on a permuted one), whereas ``antialias=False``
    moves the network's input by up to 2e-6 (benchmarks/metrics.py, docs/performance.md)."""
    import torch
    import torch.nn.functional as F

    size = (FEATURE_INPUT_SIZE_PX, FEATURE_INPUT_SIZE_PX)
    mean = torch.tensor(IMAGENET_MEAN, device=device).view(1, 3, 1, 1)
    std = torch.tensor(IMAGENET_STD, device=device).view(1, 3, 1, 1)

    def resized(crops: np.ndarray):
        x = torch.from_numpy(np.ascontiguousarray(crops)).to(device=device)
        x = x.permute(0, 3, 1, 2).to(torch.float32).contiguous()  # (b, 3, h, w)
        x /= 255.0
        x -= mean
        x /= std
        return F.interpolate(x, size=size, mode="bilinear", align_corners=False, antialias=True)

    if isinstance(patches, np.ndarray):
        return resized(patches)
    by_shape: dict[tuple[int, ...], list[int]] = {}
    for i, patch in enumerate(patches):
        by_shape.setdefault(tuple(patch.shape), []).append(i)
    if len(by_shape) == 1:  # the usual case: every crop 64 x 64, no reordering needed
        return resized(np.stack(patches))
    out = torch.empty((len(patches), 3) + size, device=device)
    for idx in by_shape.values():  # crops of one shape are resized together
        out[torch.as_tensor(idx, device=out.device)] = resized(np.stack([patches[i] for i in idx]))
    return out


def _normalized_features(feature_fn: Callable, patches: list[np.ndarray], device: str | None):
    import torch

    f = feature_fn(preprocess_patches(patches, device)).float()
    f = f.reshape(f.shape[0], -1)
    return f / torch.linalg.vector_norm(f, dim=1, keepdim=True).clamp_min(1e-12)


def patch_pairs(ref_tracks: np.ndarray, gen_tracks: np.ndarray, ref_visible: np.ndarray,
                gen_visible: np.ndarray, height: int, width: int) -> tuple[np.ndarray, np.ndarray]:
    """Tracks (P, T, 2), visibilities (P, T). Returns point and frame indices (K,) of the valid
    pairs: t >= 1, visible in both clips, both positions finite, and both patches kept."""
    ok = finite_and_visible(ref_visible & gen_visible, ref_tracks, gen_tracks)
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
                ref_patches += extract_patches(ref_rgb[t], ref_tracks[p_idx[here], t])
                gen_patches += extract_patches(gen_rgb[t], gen_tracks[p_idx[here], t])
            f_ref = _normalized_features(feature_fn, ref_patches, device)
            f_gen = _normalized_features(feature_fn, gen_patches, device)
            sims[sel] = (f_ref * f_gen).sum(dim=1).double().cpu().numpy()
    return sims


def iddrift(ref_rgb: np.ndarray, gen_rgb: np.ndarray, ref_tracks: np.ndarray, gen_tracks: np.ndarray,
            ref_visible: np.ndarray, gen_visible: np.ndarray, actor_index: np.ndarray,
            feature_fn: Callable, batch_size: int = 256, device: str | None = None,
            rules: EdgeRules = PAPER_RULES) -> MetricResult:
    """RGB (T, H, W, 3) uint8; tracks (P, T, 2) px; visibilities (P, T) bool; actor_index (P,) int;
    feature_fn maps (B, 3, 224, 224) ImageNet-normalised float to (B, D); patches are prepared on
    `device`, by default the device of feature_fn's parameters if it is a torch module. Returns 1 - mean over
    actors of the actor's mean patch cosine similarity (NaN if no actor has a pair), and (T,)
    per frame: 1 - the same actor-then-pair mean restricted to frame t (NaN at t = 0).
    ``rules="published"``: NaN with a note where the published evaluator stops (module docstring)."""
    check_tracks(ref_tracks, gen_tracks, ref_visible, gen_visible)
    if ref_rgb.shape != gen_rgb.shape or ref_rgb.shape[0] != ref_tracks.shape[1]:
        raise ValueError(f"RGB clips {ref_rgb.shape} / {gen_rgb.shape} must match each other and the "
                         f"{ref_tracks.shape[1]} track frames")
    t_len, height, width = ref_rgb.shape[:3]
    actor_index = np.asarray(actor_index)
    if check_rules(rules) == PUBLISHED_RULES:
        stop = _published_stop(ref_tracks, gen_tracks, ref_visible & gen_visible)
        if stop:
            return MetricResult(float("nan"), np.full(t_len, np.nan), stop)
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


def _published_stop(ref_tracks: np.ndarray, gen_tracks: np.ndarray, visible: np.ndarray) -> str:
    """Why the published evaluator stops on these tracks ('' when it does not): a non-finite coordinate
    of either clip's position at a jointly visible point-frame with t >= 1."""
    bad = visible & ~(np.isfinite(np.asarray(ref_tracks, dtype=np.float64)).all(axis=-1)
                      & np.isfinite(np.asarray(gen_tracks, dtype=np.float64)).all(axis=-1))
    bad[:, 0] = False
    if not bad.any():
        return ""
    p, t = (int(i[0]) for i in np.nonzero(bad))
    return ("undefined under the published evaluator's rules: it stops with ValueError/OverflowError "
            f"(identity.extract_patch, int(round(x))) on a non-finite track position flagged visible (point {p}, "
            f"frame {t})")


def score_iddrift(x) -> MetricResult | None:
    """Registry adapter: IdDrift of the MetricInputs ``x`` (None without the DINOv2 network)."""
    if x.identity_net is None:
        return None
    return iddrift(x.ref_rgb, x.gen_rgb, x.ref_tracks, x.gen_tracks, x.ref_visibility, x.gen_visibility,
                   x.track_actor, x.identity_net, rules=x.edge_rules)
