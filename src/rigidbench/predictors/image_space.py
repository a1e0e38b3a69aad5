"""Image-space failure modes: predictions made from the reference's own frames, in milliseconds.

Each maps a reference ``Sample`` and a severity in [0, 1] (0 = the reference itself) to a
``Prediction``: the frames, their timestamps and the exact ``WorldState`` they depict, so
``--perception gt`` can score them without any learned model.

- time: ``static`` (motion frozen at the first frame), ``slow`` / ``fast`` playback, ``delayed``
  start; the video shows the reference at remapped times s(t);
- camera: ``camera-shake`` (random per-frame translation and rotation) and ``camera-drift``
  (steady pan), coherent image motion of the whole frame;
- background: ``background-wobble``, a smooth non-rigid displacement of the background only;
- appearance: ``gamma`` (gamma 1 + 1.5 s, as in the paper's IdDrift check);
- ``reference``: the reference, losslessly re-encoded.

The failure modes that re-simulate and re-render with Blender live in ``counterfactuals``
(physics and depth offset) and ``identity_swap``; all are registered in ``predictors.PREDICTORS``.
"""

from __future__ import annotations

import math

import numpy as np

from ..perception.gt import WorldState, static_background
from ..video import interpolate_nearest
from .base import Prediction

MAX_DELAY_S = 0.5
SHAKE_AMPLITUDE = 0.03  # fraction of image height at severity 1
SHAKE_ROTATION_DEG = 1.5
DRIFT_FRACTION = 0.15  # fraction of image width panned over the clip at severity 1
WOBBLE_AMPLITUDE = 0.02  # fraction of image height at severity 1
WOBBLE_GRID = (12, 20)  # (rows, cols) of the coarse displacement grid stored in the state


def _reference(sample):
    active = sample.active_indices
    tracks = sample.tracks
    return (sample.frames, sample.masks[:, active], sample.depth, tracks["tracks"].astype(np.float32),
            tracks["visibility"].astype(bool))


def _times(sample) -> np.ndarray:
    return np.arange(sample.n_frames) / float(sample.fps)


def time_remap(sample, shown_s: np.ndarray) -> Prediction:
    """A video whose frame k shows the reference frame nearest to time shown_s[k] (clamped to the clip).

    Frames are repeated or dropped, never blended, so every pixel and every state array (masks,
    depth, tracks, visibility) depicts the same rendered instant exactly."""
    frames, masks, depth, tracks, vis = _reference(sample)
    src = _times(sample)
    shown = np.clip(np.asarray(shown_s, np.float64), 0.0, src[-1])
    rgb = interpolate_nearest(frames, src, shown)
    out_masks = interpolate_nearest(masks, src, shown)
    out_depth = interpolate_nearest(depth, src, shown).astype(np.float32)
    out_tracks = np.moveaxis(interpolate_nearest(np.moveaxis(tracks, 1, 0), src, shown), 0, 1).astype(np.float32)
    out_vis = np.moveaxis(interpolate_nearest(np.moveaxis(vis, 1, 0), src, shown), 0, 1)
    times = _times(sample)[: len(shown)]
    affine, flow = static_background(len(shown))
    return Prediction(rgb, times, WorldState(times, out_masks, out_depth, out_tracks, out_vis, affine, flow))


def reference(sample, severity: float) -> Prediction:
    return time_remap(sample, _times(sample))


def static(sample, severity: float) -> Prediction:
    return time_remap(sample, _times(sample) * (1.0 - severity))


def slow(sample, severity: float) -> Prediction:
    return time_remap(sample, _times(sample) / (1.0 + severity))


def fast(sample, severity: float) -> Prediction:
    """Playback (1 + s) times faster; the video ends when the reference runs out (a shorter clip)."""
    t = _times(sample)
    shown = t * (1.0 + severity)
    return time_remap(sample, shown[shown <= t[-1] + 1e-9])


def delayed(sample, severity: float) -> Prediction:
    return time_remap(sample, np.maximum(_times(sample) - MAX_DELAY_S * severity, 0.0))


def gamma(sample, severity: float) -> Prediction:
    pred = reference(sample, 0.0)
    g = 1.0 + 1.5 * severity
    lut = np.clip(np.rint(255.0 * (np.arange(256) / 255.0) ** g), 0, 255).astype(np.uint8)
    pred.frames = lut[pred.frames]
    return pred


def _warp_all(pred: Prediction, affines: np.ndarray) -> Prediction:
    """Apply per-frame 2x3 image affines to frames, masks, depth and tracks (coherent camera motion)."""
    import cv2

    t, h, w = pred.frames.shape[:3]
    frames = np.empty_like(pred.frames)
    masks = np.empty_like(pred.state.masks)
    depth = np.empty_like(pred.state.depth_m)
    for k in range(t):
        a = affines[k]
        frames[k] = cv2.warpAffine(pred.frames[k], a, (w, h), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)
        depth[k] = cv2.warpAffine(pred.state.depth_m[k], a, (w, h), flags=cv2.INTER_NEAREST,
                                  borderMode=cv2.BORDER_REFLECT)
        for n in range(masks.shape[1]):
            masks[k, n] = cv2.warpAffine(pred.state.masks[k, n].astype(np.uint8), a, (w, h),
                                         flags=cv2.INTER_NEAREST, borderValue=0).astype(bool)
    tr = pred.state.tracks
    moved = np.einsum("tij,ptj->pti", affines[:, :, :2], tr) + affines[None, :, :, 2]
    inside = (moved[..., 0] >= 0) & (moved[..., 0] < w) & (moved[..., 1] >= 0) & (moved[..., 1] < h)
    state = WorldState(pred.state.times_s, masks, depth, moved.astype(np.float32),
                       pred.state.visibility & inside, affines.astype(np.float64), pred.state.bg_flow)
    return Prediction(frames, pred.times_s, state)


def _affine(angle_deg: float, dx: float, dy: float, centre: tuple[float, float]) -> np.ndarray:
    """2x3 image affine: rotate by angle about ``centre`` then translate (integer pixel centres, as cv2)."""
    import cv2

    a = cv2.getRotationMatrix2D((centre[0], centre[1]), angle_deg, 1.0)
    a[:, 2] += (dx, dy)
    return a


def camera_shake(sample, severity: float, seed: int = 0) -> Prediction:
    pred = reference(sample, 0.0)
    t, h, w = pred.frames.shape[:3]
    rng = np.random.default_rng(seed + scene_seed(sample))
    amp = SHAKE_AMPLITUDE * h * severity
    affines = np.stack([_affine(0.0, 0.0, 0.0, (w / 2 - 0.5, h / 2 - 0.5))] + [
        _affine(SHAKE_ROTATION_DEG * severity * rng.uniform(-1, 1), amp * rng.uniform(-1, 1),
                amp * rng.uniform(-1, 1), (w / 2 - 0.5, h / 2 - 0.5)) for _ in range(t - 1)])
    return _warp_all(pred, affines)


def camera_drift(sample, severity: float) -> Prediction:
    pred = reference(sample, 0.0)
    t, h, w = pred.frames.shape[:3]
    shift = DRIFT_FRACTION * w * severity * np.arange(t) / max(t - 1, 1)
    return _warp_all(pred, np.stack([_affine(0.0, float(-dx), 0.0, (w / 2 - 0.5, h / 2 - 0.5)) for dx in shift]))


def background_wobble(sample, severity: float) -> Prediction:
    """Smoothly displace background pixels (actors untouched); the displacement is stored as bg_flow."""
    import cv2

    pred = reference(sample, 0.0)
    t, h, w = pred.frames.shape[:3]
    gh, gw = WOBBLE_GRID
    amp = WOBBLE_AMPLITUDE * h * severity
    gy, gx = np.meshgrid(np.linspace(0, 1, gh), np.linspace(0, 1, gw), indexing="ij")
    flow = np.zeros((t, gh, gw, 2), np.float32)
    for k in range(1, t):
        phase = 2 * math.pi * k / 12.0
        flow[k, ..., 0] = amp * np.sin(2 * math.pi * 2 * gy + phase)
        flow[k, ..., 1] = amp * np.cos(2 * math.pi * 3 * gx + 0.7 * phase)
    ys, xs = np.mgrid[0:h, 0:w].astype(np.float32)
    frames = pred.frames.copy()
    for k in range(1, t):
        dense = cv2.resize(flow[k], (w, h), interpolation=cv2.INTER_LINEAR)
        # Output pixel x shows the background point that moved there: sample the source at x - d(x).
        warped = cv2.remap(pred.frames[k], xs - dense[..., 0], ys - dense[..., 1], cv2.INTER_LINEAR,
                           borderMode=cv2.BORDER_REFLECT)
        actors = pred.state.masks[k].any(axis=0)
        warped[actors] = pred.frames[k][actors]
        frames[k] = warped
    pred.frames = frames
    pred.state.bg_flow = flow
    return pred


def scene_seed(sample) -> int:
    return int(sample.metadata.get("seed", 0))
