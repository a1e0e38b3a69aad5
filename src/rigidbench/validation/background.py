"""BGDrift under coherent translation versus independent jitter (paper, appendix "Controlled Metric
Perturbations").

C background corners, drawn uniformly over a W x H image, are followed across T frames. At every
frame t >= 1 the corners are displaced from their frame-0 positions either all by one vector of
length m in a random direction (coherent translation: a camera pan) or each by its own isotropic
Gaussian vector, rescaled so that the frame's mean displacement length is exactly m (independent
jitter). The two conditions therefore have matched raw displacement; every confidence is 1.
"""

from __future__ import annotations

import numpy as np

from ..metrics.background import bgdrift

MOTIONS = ("translation", "jitter")
N_CORNERS = 200
N_FRAMES = 49
IMAGE_SIZE_WH = (1280, 704)


def corner_tracks(magnitude_px: float, motion: str, rng: np.random.Generator, n_corners: int = N_CORNERS,
                  n_frames: int = N_FRAMES, size_wh: tuple[int, int] = IMAGE_SIZE_WH) -> np.ndarray:
    """Returns (C,T,2) float64 px corner tracks whose displacement from frame 0 has mean length
    magnitude_px at every frame t >= 1, coherent ("translation") or independent ("jitter")."""
    if motion not in MOTIONS:
        raise ValueError(f"motion must be one of {MOTIONS}, got '{motion}'")
    w, h = size_wh
    x0 = rng.uniform((0.0, 0.0), (w - 1.0, h - 1.0), size=(n_corners, 2))
    if motion == "translation":
        angle = rng.uniform(0.0, 2 * np.pi, size=n_frames)
        step = np.stack([np.cos(angle), np.sin(angle)], axis=-1)[None].repeat(n_corners, axis=0)
    else:
        step = rng.standard_normal((n_corners, n_frames, 2))
        step /= np.linalg.norm(step, axis=-1).mean(axis=0)[None, :, None]
    step[:, 0] = 0.0
    return x0[:, None, :] + magnitude_px * step


def mean_displacement(tracks: np.ndarray) -> float:
    """tracks: (C,T,2) px. Returns the mean over corners and frames t >= 1 of ||x_t - x_0|| in px."""
    return float(np.linalg.norm(tracks[:, 1:] - tracks[:, :1], axis=-1).mean())


def motion_sweep(magnitudes_px: np.ndarray, trials: int, seed: int, n_corners: int = N_CORNERS,
                 n_frames: int = N_FRAMES, size_wh: tuple[int, int] = IMAGE_SIZE_WH) -> dict[str, np.ndarray]:
    """Returns {"<motion>/bgdrift", "<motion>/displacement"}: (len(magnitudes_px), trials) float, BGDrift
    (real metric, 1/H units) and the raw mean displacement / H of the same tracks."""
    rng = np.random.default_rng(seed)
    height = size_wh[1]
    out = {f"{m}/{k}": np.full((len(magnitudes_px), trials), np.nan)
           for m in MOTIONS for k in ("bgdrift", "displacement")}
    confidence = np.ones((n_corners, n_frames))
    for i, magnitude in enumerate(magnitudes_px):
        for trial in range(trials):
            for motion in MOTIONS:
                tracks = corner_tracks(float(magnitude), motion, rng, n_corners, n_frames, size_wh)
                out[f"{motion}/bgdrift"][i, trial] = bgdrift(tracks, confidence, height).value
                out[f"{motion}/displacement"][i, trial] = mean_displacement(tracks) / height
    return out
