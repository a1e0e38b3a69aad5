"""IdDrift under an identity swap versus a gamma change, with pixel L2 beside it (paper, appendix
"Controlled Metric Perturbations").

M frame-0 patches (64 x 64 px, centred on ground-truth track points of the reference examples)
are tested over several trials. At severity q each patch is picked with probability q; the
target replaces every picked patch with a donor patch showing another actor (or another
example's actor), the foil changes the same picked patches with gamma = 1 + 1.5 q. IdDrift is the
real metric: the reference and generated patches are laid out as a mosaic in frame 1 of a
two-frame clip, with one track per patch at its centre, so patch extraction, resizing and
normalisation are those of ``metrics.identity.iddrift``. Pixel L2 is the root-mean-square
difference of the patch pixels scaled to [0, 1], averaged over the patches.
"""

from __future__ import annotations

import logging
from typing import Callable

import numpy as np

from ..metrics.identity import PATCH_SIZE_PX, extract_patches, iddrift, patch_is_valid

log = logging.getLogger(__name__)

CHANGES = ("swap", "gamma")
GAMMA_PER_SEVERITY = 1.5  # gamma = 1 + 1.5 q, as the failure mode ``gamma``
MOSAIC_COLUMNS = 5


def apply_gamma(patches: np.ndarray, gamma: float) -> np.ndarray:
    """patches: (...,3) uint8. Returns uint8 255 (x/255)^gamma, rounded (the ``gamma`` failure mode's LUT)."""
    lut = np.clip(np.rint(255.0 * (np.arange(256) / 255.0) ** gamma), 0, 255).astype(np.uint8)
    return lut[patches]


def pixel_l2(ref_patches: np.ndarray, gen_patches: np.ndarray) -> float:
    """ref_patches, gen_patches: (M,S,S,3) uint8. Returns the mean over patches of the RMS pixel difference, 0-1."""
    diff = (ref_patches.astype(np.float64) - gen_patches.astype(np.float64)) / 255.0
    return float(np.sqrt((diff ** 2).reshape(len(diff), -1).mean(axis=1)).mean())


def mosaic(patches: np.ndarray, columns: int = MOSAIC_COLUMNS) -> tuple[np.ndarray, np.ndarray]:
    """patches: (M,S,S,3) uint8. Returns an (R*S, C*S, 3) uint8 image of the patches in rows of
    `columns` and (M,2) px patch centres (x, y) such that extract_patches gives them back exactly."""
    m, s = patches.shape[:2]
    cols = min(columns, m)
    rows = -(-m // cols)
    image = np.zeros((rows * s, cols * s, 3), np.uint8)
    centres = np.empty((m, 2))
    for k in range(m):
        r, c = divmod(k, cols)
        image[r * s:(r + 1) * s, c * s:(c + 1) * s] = patches[k]
        centres[k] = (c * s + s // 2, r * s + s // 2)  # patch_origins(c) = c - s/2 for integer c
    return image, centres


def patch_iddrift(ref_patches: np.ndarray, gen_patches: np.ndarray, feature_fn: Callable) -> float:
    """ref_patches, gen_patches: (M,64,64,3) uint8. Returns IdDrift (metrics.identity.iddrift) of the
    pairs, each patch its own actor, so the value is 1 - the mean patch cosine similarity."""
    ref_image, centres = mosaic(ref_patches)
    gen_image, _ = mosaic(gen_patches)
    ref_clip = np.stack([ref_image, ref_image])
    gen_clip = np.stack([ref_image, gen_image])  # frame 0 never counts
    tracks = np.repeat(centres[:, None, :], 2, axis=1)
    visible = np.ones(tracks.shape[:2], bool)
    return iddrift(ref_clip, gen_clip, tracks, tracks.copy(), visible, visible.copy(),
                   np.arange(len(centres)), feature_fn).value


def swap_vs_gamma(patches: np.ndarray, donors: np.ndarray, severities: np.ndarray, trials: int, seed: int,
                  feature_fn: Callable | None) -> dict[str, np.ndarray]:
    """patches, donors: (M,64,64,3) uint8 (donors[k] replaces patch k in a swap). Returns
    {"<change>/pixel_l2"} and, with a feature_fn, {"<change>/iddrift"}: (len(severities), trials) float."""
    if patches.shape != donors.shape:
        raise ValueError(f"patches {patches.shape} and donors {donors.shape} must have the same shape")
    rng = np.random.default_rng(seed)
    metrics = ("pixel_l2", "iddrift") if feature_fn is not None else ("pixel_l2",)
    out = {f"{c}/{m}": np.full((len(severities), trials), np.nan) for c in CHANGES for m in metrics}
    for i, q in enumerate(severities):
        gamma = 1.0 + GAMMA_PER_SEVERITY * float(q)
        for trial in range(trials):
            picked = rng.random(len(patches)) < q
            generated = {"swap": np.where(picked[:, None, None, None], donors, patches),
                         "gamma": np.where(picked[:, None, None, None], apply_gamma(patches, gamma), patches)}
            for change, gen in generated.items():
                out[f"{change}/pixel_l2"][i, trial] = pixel_l2(patches, gen)
                if feature_fn is not None:
                    out[f"{change}/iddrift"][i, trial] = patch_iddrift(patches, gen, feature_fn)
    return out


def square_patch(frame: np.ndarray, centres_xy: np.ndarray, size: int = PATCH_SIZE_PX) -> list[np.ndarray]:
    """frame (H,W,3) uint8, centres (M,2) px with valid patches. Returns M (size,size,3) uint8 patches: the
    part inside the image (``metrics.identity.extract_patches``), resized to size x size where the border
    cut it (the metric resizes every crop to the network's input anyway), so patches can be tiled."""
    import cv2

    return [crop if crop.shape[:2] == (size, size) else
            cv2.resize(np.ascontiguousarray(crop), (size, size), interpolation=cv2.INTER_LINEAR)
            for crop in extract_patches(frame, centres_xy, size)]


def frame0_candidates(sample) -> list[tuple[str, np.ndarray]]:
    """Returns one (group, centres (K,2) px) per active actor of `sample`: its track points that are
    visible at frame 0 and whose patch is valid; the group names the example and actor."""
    tracks = sample.tracks
    h = sample.resolution[1]
    w = sample.resolution[0]
    xy = np.asarray(tracks["tracks"][:, 0], np.float64)
    ok = tracks["visibility"][:, 0] & patch_is_valid(xy, h, w)
    actor = np.asarray(sample.track_active_index)
    return [(f"{sample.sample_id}/actor{a}", xy[ok & (actor == a)]) for a in np.unique(actor)
            if (ok & (actor == a)).any()]


def background_centres(actor_masks0: np.ndarray, size: int = PATCH_SIZE_PX) -> np.ndarray:
    """actor_masks0: (A,H,W) bool frame-0 masks. Returns (K,2) px centres of fully inside patches
    that overlap the fewest actor pixels (the donors when only one actor is available)."""
    covered = np.asarray(actor_masks0, bool).any(axis=0)
    h, w = covered.shape
    integral = np.pad(covered.cumsum(0).cumsum(1), ((1, 0), (1, 0)))
    ys, xs = np.mgrid[0:h - size + 1, 0:w - size + 1]
    overlap = integral[ys + size, xs + size] - integral[ys, xs + size] - integral[ys + size, xs] + integral[ys, xs]
    best = overlap == overlap.min()
    return np.stack([xs[best] + size // 2, ys[best] + size // 2], axis=-1).astype(np.float64)


def collect_patches(samples: list, n_patches: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, str]:
    """Frame-0 patches of the reference examples and a donor for each. Returns patches (M,64,64,3),
    donors (M,64,64,3) uint8 (M <= n_patches, spread over the actors) and a note on the donors' origin."""
    frames0 = {s.sample_id: s.frame(0) for s in samples}
    groups = [(s.sample_id, name, centres) for s in samples for name, centres in frame0_candidates(s)]
    if not groups:
        raise ValueError("no reference example has a valid frame-0 patch around a visible track point; "
                         "render examples whose actors are visible at frame 0")
    order = rng.permutation(len(groups))
    picks: list[tuple[int, np.ndarray]] = []
    pools = {g: list(rng.permutation(len(groups[g][2]))) for g in order}
    while len(picks) < n_patches and any(pools.values()):
        for g in order:  # round-robin over actors, so each actor gives about as many patches
            if pools[g] and len(picks) < n_patches:
                picks.append((int(g), groups[g][2][pools[g].pop()]))
    patches = np.stack([square_patch(frames0[groups[g][0]], centre[None])[0] for g, centre in picks])
    if len(groups) > 1:
        donors = []
        for g, _ in picks:
            other = int(rng.choice([k for k in range(len(groups)) if k != g]))
            centres = groups[other][2]
            donors.append(square_patch(frames0[groups[other][0]], centres[rng.integers(len(centres))][None])[0])
        note = f"donors: patches of another actor ({len(groups)} actors in {len(samples)} examples)"
    else:
        sample = samples[0]
        masks0 = sample.masks[0][sample.active_indices]
        centres = background_centres(masks0)
        chosen = centres[rng.integers(len(centres), size=len(picks))]
        donors = [square_patch(frames0[sample.sample_id], c[None])[0] for c in chosen]
        note = "donors: background patches of frame 0 (only one actor available to swap with)"
        log.info("only one actor in the validation examples; identity swaps use background patches")
    return patches, np.stack(donors), note
