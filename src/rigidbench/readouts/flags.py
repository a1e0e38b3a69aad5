"""Failure flags: per actor and per example, each with a stated threshold and the evidence kept.

A flag is True (raised), False (checked, not raised) or None (undefined, with a reason). Per-actor
flags are raised for the example when any actor raises them, False when every defined actor is
False, None when no actor defines them.

- ``disappears``: the generated mask of an actor is empty (< DISAPPEAR_MIN_PX pixels) on at least
  MIN_FRAMES frames at which the reference mask of that actor has at least IN_VIEW_MIN_PX pixels;
- ``duplicates``: the generated mask splits into at least two 8-connected components each of at
  least DUPLICATE_MIN_PX pixels and DUPLICATE_MIN_SHARE of the largest one, on at least MIN_FRAMES
  frames at which the reference mask of that actor does not split the same way (occlusion);
  both compare generated frame k with the reference frame nearest the matched instant s t_k + d of the
  speed readout (``reference_frames``), so a clip played slower or later is not flagged where it hides
  an actor behind something later than the reference does (eval 00020's kiwi behind a ramp under
  ``slow``); generated frames matched past the reference's last frame are not checked;
- ``frozen``: the generated actor's world displacement from frame 0 stays below FROZEN_M at every frame
  while the reference actor moves more than FROZEN_M (undefined when the reference does not move);
- ``through_support``: the generated actor's anchored height (readouts.physics) falls below
  min(lowest reference height of that actor, support top + its half smallest side) by more than
  max(THROUGH_TOL_M, THROUGH_TOL_RADII x that half side) on at least THROUGH_MIN_FRAMES frames. The
  tolerance is the object's whole thickness (2 half sides: its top below the support's): the height
  read from a clip is the median of the visible surface points, which wanders by up to a radius as the
  object turns or is occluded, so a smaller tolerance flagged the reference itself (demo examples
  00010 and 00020, by 0.6-1.6 cm; an occluded kiwi by 14 cm on 2 frames, frames the reconstruction now
  leaves out: readouts.physics.off_own_mask);
- ``through_actor``: two generated actors' anchored centres come closer than
  THROUGH_ACTOR_SHARE x (sum of their half smallest sides) on at least MIN_FRAMES frames (undefined
  without actor sizes);
- ``identity``: the example's IdDrift exceeds IDENTITY_IDDRIFT (undefined when IdDrift was not computed);
- ``camera``: the background's coherent image motion, the RANSAC similarity (3 px, as BGDrift) from
  frame-0 to frame-t background corners, moves a 3 x 3 grid of image points by more than
  CAMERA_SHIFT_H x H (RMS over the grid) at some frame; the prompt asked for a locked camera.
"""

from __future__ import annotations

import math

import numpy as np

from rigidbench.readouts.physics import MIN_MOTION_M, anchored_positions, generated_displacements, time_warp

MIN_FRAMES = 2
IN_VIEW_MIN_PX = 20
DISAPPEAR_MIN_PX = 1
DUPLICATE_MIN_PX = 10
DUPLICATE_MIN_SHARE = 0.25
FROZEN_M = MIN_MOTION_M
THROUGH_TOL_M = 0.02
THROUGH_TOL_RADII = 2.0
THROUGH_MIN_FRAMES = 3
THROUGH_ACTOR_SHARE = 0.4
IDENTITY_IDDRIFT = 0.35
CAMERA_SHIFT_H = 0.01
CAMERA_MIN_CORNERS = 4
RANSAC_THRESHOLD_PX = 3.0

THRESHOLDS = {
    "disappears": f"empty generated mask (< {DISAPPEAR_MIN_PX} px) on >= {MIN_FRAMES} frames where the reference "
                  f"mask at the matched instant has >= {IN_VIEW_MIN_PX} px",
    "duplicates": f">= 2 components of >= {DUPLICATE_MIN_PX} px and >= {DUPLICATE_MIN_SHARE:g} of the largest on >= "
                  f"{MIN_FRAMES} frames where the reference at the matched instant does not split",
    "frozen": f"generated displacement < {FROZEN_M * 100:g} cm at every frame while the reference moves more",
    "through_support": f"anchored height below the lowest allowed by > max({THROUGH_TOL_M * 100:g} cm, "
                       f"{THROUGH_TOL_RADII:g} half-sides) on >= {THROUGH_MIN_FRAMES} frames",
    "through_actor": f"centres closer than {THROUGH_ACTOR_SHARE:g} x the summed half-sides on >= {MIN_FRAMES} frames",
    "identity": f"IdDrift > {IDENTITY_IDDRIFT:g}",
    "camera": f"coherent background motion > {CAMERA_SHIFT_H:g} H (RMS over a 3x3 grid of image points)",
}
ACTOR_FLAGS = ("disappears", "duplicates", "frozen", "through_support", "through_actor")
EXAMPLE_FLAGS = ("identity", "camera")
FLAGS = ACTOR_FLAGS + EXAMPLE_FLAGS


def _frames(mask: np.ndarray) -> list[int]:
    return [int(k) for k in np.flatnonzero(mask)]


def _components(mask: np.ndarray) -> np.ndarray:
    """Sizes of the 8-connected components of a (H,W) bool mask, largest first."""
    from scipy import ndimage

    labels, n = ndimage.label(mask, structure=np.ones((3, 3), bool))
    if n == 0:
        return np.zeros(0, int)
    return np.sort(np.bincount(labels.ravel())[1:])[::-1]


def _splits(mask: np.ndarray) -> bool:
    sizes = _components(mask)
    big = sizes[(sizes >= DUPLICATE_MIN_PX) & (sizes >= DUPLICATE_MIN_SHARE * (sizes[0] if sizes.size else 0))]
    return big.size >= 2


def reference_frames(ctx) -> np.ndarray:
    """(T,) int: the reference frame each generated frame's masks are compared with, the one nearest the
    matched instant s t + d of the speed readout (frame 0 before the reference starts, -1 past its last
    mask frame: not compared); the same frame when the speed is undefined (a reference that does not move)."""
    w = time_warp(ctx)
    n_ref = ctx.inputs.ref_masks.shape[0]
    k = np.arange(ctx.n_frames)
    if not (math.isfinite(w.speed) and math.isfinite(w.offset_s)):
        return np.where(k < n_ref, k, -1)
    matched = np.maximum(np.rint((w.speed * ctx.times_s + w.offset_s) * ctx.fps).astype(int), 0)
    return np.where(matched < n_ref, matched, -1)


def disappears(ctx, a: int) -> dict:
    x = ctx.inputs
    ref_k = reference_frames(ctx)
    ref_area = ctx.reference_shared(f"mask_area:{a}", lambda: x.ref_masks[:, a].reshape(x.ref_masks.shape[0], -1)
                                    .sum(axis=1))[ref_k]
    gen_area = x.gen_masks[:, a].reshape(x.gen_masks.shape[0], -1).sum(axis=1)
    hit = (ref_k >= 0) & (gen_area < DISAPPEAR_MIN_PX) & (ref_area >= IN_VIEW_MIN_PX)
    return {"raised": bool(hit.sum() >= MIN_FRAMES), "frames": _frames(hit), "reference_frames": ref_k[hit]}


def duplicates(ctx, a: int) -> dict:
    x = ctx.inputs
    ref_k = reference_frames(ctx)
    ref_splits = ctx.reference_shared(f"splits:{a}", dict)  # reference frame -> whether its mask splits

    def splits_in_reference(k: int) -> bool:
        if k not in ref_splits:
            ref_splits[k] = _splits(x.ref_masks[k, a])
        return ref_splits[k]

    hit = np.array([k >= 0 and _splits(x.gen_masks[t, a]) and not splits_in_reference(int(k))
                    for t, k in enumerate(ref_k)], bool)
    return {"raised": bool(hit.sum() >= MIN_FRAMES), "frames": _frames(hit), "reference_frames": ref_k[hit]}


def frozen(ctx, a: int) -> dict:
    ref = np.asarray(ctx.ref_positions_m, np.float64)[a, :ctx.n_frames]
    ref_motion = float(np.linalg.norm(ref - ref[:1], axis=-1).max())
    gen = generated_displacements(ctx)[a]
    ok = np.isfinite(gen).all(axis=-1)
    if ref_motion <= FROZEN_M:
        return {"raised": None, "reason": f"the reference actor moves {ref_motion * 100:.2g} cm, not more than "
                f"{FROZEN_M * 100:g} cm", "reference_motion_m": ref_motion}
    if not ok.any():
        return {"raised": None, "reason": "no reconstruction of the generated actor", "reference_motion_m": ref_motion}
    gen_motion = float(np.linalg.norm(gen[ok], axis=-1).max())
    return {"raised": gen_motion < FROZEN_M, "generated_motion_m": gen_motion, "reference_motion_m": ref_motion,
            "frames_reconstructed": int(ok.sum())}


def through_support(ctx, a: int) -> dict:
    z = anchored_positions(ctx)[a, :, 2]
    if not np.isfinite(z).any():
        return {"raised": None, "reason": "no reconstruction of the generated actor"}
    r = float(ctx.actor_radius_m[a])
    floor = float(np.nanmin(np.asarray(ctx.ref_positions_m, np.float64)[a, :, 2]))
    if math.isfinite(ctx.support_top_m) and math.isfinite(r):
        floor = min(floor, ctx.support_top_m + r)
    tol = max(THROUGH_TOL_M, THROUGH_TOL_RADII * r) if math.isfinite(r) else THROUGH_TOL_M
    with np.errstate(invalid="ignore"):
        hit = z < floor - tol
    return {"raised": bool(hit.sum() >= THROUGH_MIN_FRAMES), "frames": _frames(hit), "lowest_allowed_m": floor - tol,
            "lowest_generated_m": float(np.nanmin(z))}


def through_actor(ctx, a: int) -> dict:
    p = anchored_positions(ctx)
    r = np.asarray(ctx.actor_radius_m, np.float64)
    if ctx.n_actors < 2:
        return {"raised": False, "frames": [], "others": []}
    if not np.isfinite(r).all():
        return {"raised": None, "reason": "actor sizes unknown (no scene spec)"}
    frames, others = np.zeros(ctx.n_frames, bool), []
    for b in range(ctx.n_actors):
        if b == a:
            continue
        with np.errstate(invalid="ignore"):
            close = np.linalg.norm(p[a] - p[b], axis=-1) < THROUGH_ACTOR_SHARE * (r[a] + r[b])
        if close.sum() >= MIN_FRAMES:
            others.append(ctx.actor_names[b])
        frames |= close
    return {"raised": bool(others), "frames": _frames(frames), "others": others}


def camera_motion(ctx) -> dict:
    """Per-frame RMS image shift (fraction of H) of a 3x3 grid of image points under the background's
    RANSAC similarity from frame 0; NaN at frames with fewer than 4 corners."""
    import cv2

    x = ctx.inputs
    h, w = x.ref_rgb.shape[1:3]
    grid = np.array([(gx, gy) for gx in (0.1 * w, 0.5 * w, 0.9 * w) for gy in (0.1 * h, 0.5 * h, 0.9 * h)])
    tracks = np.asarray(x.bg_tracks, np.float64)
    conf = np.asarray(x.bg_confidence, np.float64)
    shift = np.full(ctx.n_frames, np.nan)
    if tracks.size == 0:
        return {"per_frame": shift, "max": float("nan")}
    shift[0] = 0.0
    for t in range(1, min(ctx.n_frames, tracks.shape[1])):
        use = (conf[:, 0] > 0) & (conf[:, t] > 0) & np.isfinite(tracks[:, 0]).all(-1) & np.isfinite(tracks[:, t]).all(-1)
        if use.sum() < CAMERA_MIN_CORNERS:
            continue
        A, _ = cv2.estimateAffinePartial2D(tracks[use, 0].astype(np.float32).reshape(-1, 1, 2),
                                           tracks[use, t].astype(np.float32).reshape(-1, 1, 2), method=cv2.RANSAC,
                                           ransacReprojThreshold=RANSAC_THRESHOLD_PX)
        if A is None:
            continue
        moved = grid @ A[:, :2].T + A[:, 2]
        shift[t] = float(np.sqrt(np.mean(np.sum((moved - grid) ** 2, axis=1)))) / h
    finite = shift[np.isfinite(shift)]
    return {"per_frame": shift, "max": float(finite.max()) if finite.size > 1 else float("nan")}


def readout_flags(ctx) -> dict:
    """Every flag per actor and for the example, with its threshold and evidence."""
    actors = []
    for a in range(ctx.n_actors):
        actors.append({"actor": ctx.actor_names[a], "disappears": disappears(ctx, a), "duplicates": duplicates(ctx, a),
                       "frozen": frozen(ctx, a), "through_support": through_support(ctx, a),
                       "through_actor": through_actor(ctx, a)})
    example: dict[str, bool | None] = {}
    for flag in ACTOR_FLAGS:
        values = [r[flag]["raised"] for r in actors if r[flag]["raised"] is not None]
        example[flag] = (True if any(values) else False) if values else None
    if ctx.iddrift is None:
        identity = {"raised": None, "reason": "IdDrift was not computed (its feature network is missing) or is NaN"}
    else:
        identity = {"raised": ctx.iddrift > IDENTITY_IDDRIFT, "iddrift": ctx.iddrift}
    cam = camera_motion(ctx)
    if math.isfinite(cam["max"]):
        camera = {"raised": cam["max"] > CAMERA_SHIFT_H, "max_shift_h": cam["max"],
                  "frames": _frames(np.nan_to_num(cam["per_frame"]) > CAMERA_SHIFT_H)}
    else:
        camera = {"raised": None, "reason": f"no frame has {CAMERA_MIN_CORNERS} background corners at frame 0 and t"}
    example["identity"], example["camera"] = identity["raised"], camera["raised"]
    raised = [f for f in FLAGS if example[f]]
    return {"value": float(len(raised)), "raised": raised, "example": example, "actors": actors,
            "identity": identity, "camera": camera, "thresholds": THRESHOLDS, "reason": None}
