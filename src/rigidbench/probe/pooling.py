"""Actor-aligned pooling of residual-stream tokens (paper appendix E, equation "actor-time-pooling").

Wan's VAE is causal with 4x temporal compression (4n+1 frames -> n+1 latent slots): slot 0 holds
pixel frame 0 and slot s > 0 holds frames 4s-3 .. 4s. For each slot, the simulator masks of each
actor are merged (logical or) over the slot's frames and max-pooled to the token grid (a token is
covered when any pixel of its cell is); the probe input of actor a at slot s is the mean of the
block's output over the covered tokens. A (slot, actor) with no covered token gives no row.

The token grid follows the model: frames resized (stretched, as ``preprocess`` resizes them) to the
encoding size, 16x spatial VAE compression, 2x2 patchify. For Wan 2.2 at 640x352 that is 22x40
latents and an 11x20 token grid per slot (13 slots), not the 22x40 token grid the paper's text says.
Pure numpy; the pooled rows are a matrix product, so it works on torch tensors as well.
"""

from __future__ import annotations

import numpy as np

TEMPORAL_COMPRESSION = 4


def slot_frames(slot: int, temporal: int = TEMPORAL_COMPRESSION) -> list[int]:
    """Pixel frames of latent slot ``slot``: [0] for slot 0, [4s-3 .. 4s] otherwise."""
    if slot < 0:
        raise ValueError(f"slot must be at least 0, got {slot}")
    if slot == 0:
        return [0]
    return list(range(temporal * slot - temporal + 1, temporal * slot + 1))


def n_slots(frames: int, temporal: int = TEMPORAL_COMPRESSION) -> int:
    """Latent slots of a clip of ``frames`` (4n+1) frames."""
    return (frames - 1) // temporal + 1


def max_pool_to_grid(mask: np.ndarray, grid: tuple[int, int]) -> np.ndarray:
    """mask (..., H, W) bool -> (..., gh, gw) bool: token (i, j) covers the pixel rows
    [floor(i H/gh), ceil((i+1) H/gh)) and columns likewise (the cells of a stretched resize)."""
    mask = np.asarray(mask, dtype=bool)
    h, w = mask.shape[-2:]
    gh, gw = int(grid[0]), int(grid[1])
    out = np.zeros(mask.shape[:-2] + (gh, gw), dtype=bool)
    rows = [(int(np.floor(i * h / gh)), max(int(np.ceil((i + 1) * h / gh)), int(np.floor(i * h / gh)) + 1))
            for i in range(gh)]
    cols = [(int(np.floor(j * w / gw)), max(int(np.ceil((j + 1) * w / gw)), int(np.floor(j * w / gw)) + 1))
            for j in range(gw)]
    for i, (r0, r1) in enumerate(rows):
        band = mask[..., r0:r1, :].any(axis=-2)
        for j, (c0, c1) in enumerate(cols):
            out[..., i, j] = band[..., c0:c1].any(axis=-1)
    return out


def slot_token_masks(masks: np.ndarray, slots: int, grid: tuple[int, int],
                     temporal: int = TEMPORAL_COMPRESSION) -> np.ndarray:
    """masks (T, N, H, W) bool per pixel frame -> (slots, N, gh, gw) bool: per slot, the masks merged
    over the slot's frames (those < T) and max-pooled to ``grid``."""
    masks = np.asarray(masks, dtype=bool)
    t, n = masks.shape[:2]
    out = np.zeros((slots, n) + tuple(grid), dtype=bool)
    for s in range(slots):
        frames = [f for f in slot_frames(s, temporal) if f < t]
        if frames:
            out[s] = max_pool_to_grid(masks[frames].any(axis=0), grid)
    return out


def pooling_matrix(token_masks: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """token_masks (S, N, gh, gw) bool -> (W (R, S*gh*gw) float32, index (R, 2) int64 of (slot, actor)).

    Row r of W averages the tokens of one covered (slot, actor), in the order Wan flattens its tokens
    (slot, row, column); (slot, actor) pairs with no covered token are omitted. ``W @ tokens`` (tokens
    (S*gh*gw, D)) gives the actor-pooled rows."""
    s, n, gh, gw = token_masks.shape
    per_slot = gh * gw
    rows, index = [], []
    for slot in range(s):
        for actor in range(n):
            cover = token_masks[slot, actor].reshape(-1)
            count = int(cover.sum())
            if count == 0:
                continue
            w = np.zeros(s * per_slot, dtype=np.float32)
            w[slot * per_slot:(slot + 1) * per_slot] = cover / count
            rows.append(w)
            index.append((slot, actor))
    if not rows:
        return np.zeros((0, s * per_slot), dtype=np.float32), np.zeros((0, 2), dtype=np.int64)
    return np.stack(rows), np.asarray(index, dtype=np.int64)


def pool_actors(tokens, token_masks: np.ndarray):
    """tokens (S*gh*gw, D) (numpy or torch) -> (rows (R, D), index (R, 2)) per ``pooling_matrix``."""
    w, index = pooling_matrix(token_masks)
    if hasattr(tokens, "new_tensor"):  # torch
        return tokens.new_tensor(w) @ tokens, index
    return w.astype(np.result_type(tokens.dtype, np.float32)) @ tokens, index
