"""The perception interface: what the metrics need to know about a generated clip.

A backend turns one generated video (decoded, resized to the reference resolution, at its own
frame times) into a ``Perception``; the evaluator then aligns it to the reference timestamps
(linear in time for tracks, disparity and confidences; nearest for masks and visibility) and
passes the arrays to the metric functions. Backends:

- ``gt``: exact, from the world state a built-in predictor wrote beside its video;
- ``neural``: SAM 2.1, CoTracker3 and Video Depth Anything on the generated clip (``neural``).

Adding a backend is one module exposing a class with ``name``, ``version`` and ``perceive``,
registered in ``BACKENDS``.
"""

from __future__ import annotations

from dataclasses import dataclass, fields, replace
from pathlib import Path
from typing import Protocol

import numpy as np


class PerceptionError(Exception):
    """Perception could not run for an example; names the example and what to do."""


def save_arrays(obj, path: str | Path) -> None:
    """Write every field of an array dataclass to a compressed .npz, atomically."""
    path = Path(path)
    tmp = path.with_name(path.name + ".tmp.npz")
    np.savez_compressed(tmp, **{f.name: getattr(obj, f.name) for f in fields(obj)})
    tmp.replace(path)


def load_arrays(cls, path: str | Path):
    """Read an array dataclass written by ``save_arrays`` (no pickles)."""
    with np.load(path, allow_pickle=False) as z:
        return cls(**{f.name: z[f.name] for f in fields(cls)})


@dataclass
class Perception:
    """Per-frame quantities recovered from a generated clip (T frames at ``times_s``).

    masks (T,N,H,W) bool for the N active actors (reference order); tracks (P,T,2) float32 pixel
    (x, y) of the reference query points, visibility (P,T) bool, track_actor (P,) int index into
    the active actors; disparity (T,H,W) float32 (affine-invariant inverse depth); bg_tracks
    (C,T,2) float32 background corners, bg_confidence (C,T) float32 in [0, 1].
    """

    times_s: np.ndarray
    masks: np.ndarray
    tracks: np.ndarray
    visibility: np.ndarray
    track_actor: np.ndarray
    disparity: np.ndarray
    bg_tracks: np.ndarray
    bg_confidence: np.ndarray

    @property
    def n_frames(self) -> int:
        return int(self.times_s.shape[0])

    def save(self, path: str | Path) -> None:
        save_arrays(self, path)

    @classmethod
    def load(cls, path: str | Path) -> "Perception":
        return load_arrays(cls, path)

    def aligned(self, ref_times_s: np.ndarray) -> "Perception":
        """Resample to the reference timestamps that fall within this clip (paper, appendix B.1)."""
        from ..video import aligned_length, interpolate_linear, interpolate_nearest

        n = aligned_length(self.times_s, ref_times_s)
        dst = np.asarray(ref_times_s[:n], dtype=np.float64)
        src = self.times_s

        def lin(x: np.ndarray, axis: int) -> np.ndarray:
            return np.moveaxis(interpolate_linear(np.moveaxis(x, axis, 0), src, dst), 0, axis).astype(x.dtype)

        def near(x: np.ndarray, axis: int) -> np.ndarray:
            return np.moveaxis(interpolate_nearest(np.moveaxis(x, axis, 0), src, dst), 0, axis)

        return replace(self, times_s=dst, masks=near(self.masks, 0), tracks=lin(self.tracks, 1),
                       visibility=near(self.visibility, 1), disparity=lin(self.disparity, 0),
                       bg_tracks=lin(self.bg_tracks, 1), bg_confidence=lin(self.bg_confidence, 1))


class Backend(Protocol):
    name: str
    version: str

    def perceive(self, sample, video, prediction_path: Path) -> Perception:
        """sample: the reference ``Sample``; video: the generated ``Video`` resized to the
        reference resolution (native frame times); prediction_path: the video file."""


BACKENDS = {
    "gt": "rigidbench.perception.gt:GroundTruthBackend",
    "neural": "rigidbench.perception.neural:NeuralBackend",
}


def get_backend(name: str, **options) -> Backend:
    import importlib

    try:
        module_name, attr = BACKENDS[name].split(":")
    except KeyError:
        raise PerceptionError(f"unknown perception backend '{name}'; choose one of {', '.join(BACKENDS)}") from None
    try:
        module = importlib.import_module(module_name)
    except ModuleNotFoundError as exc:
        raise PerceptionError(f"perception backend '{name}' needs the package '{exc.name}'; "
                              f"install it with: pip install -e '.[neural]'") from None
    return getattr(module, attr)(**options)
