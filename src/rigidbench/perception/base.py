"""The perception interface: what the metrics need to know about a generated clip.

A backend turns one generated video (decoded, resized to the reference resolution, at its own
frame times) into a ``Perception``; the evaluator then aligns it to the reference timestamps
(linear in time for tracks, disparity and track confidences; nearest for masks and visibility
flags, the background corners' 0/1 weights included) and passes the arrays to the metric
functions. Background corners carry their own timestamps (``bg_times_s``): the neural backend
tracks them on the clip already resampled to the reference times, as the published runs did.
Backends:

- ``gt``: exact, from the world state a built-in predictor wrote beside its video;
- ``neural``: SAM 2.1, CoTracker3 and Video Depth Anything on the generated clip (``neural``).

Adding a backend is one module exposing a class with ``name``, ``version`` and ``perceive``,
plus one ``BACKENDS.add(BackendInfo(...))``.
"""

from __future__ import annotations

from dataclasses import MISSING, dataclass, fields, replace
from pathlib import Path
from typing import Protocol

import numpy as np

from ..atomic import atomic_file
from ..errors import PerceptionError
from ..registry import LazyRegistry
from ..video import aligned_length, interpolate_linear, interpolate_nearest


#: Key prefixes of the cache format: a bool array stored bit-packed (np.packbits, flat) with its shape.
_PACKED, _SHAPE = "__packbits__", "__shape__"


def save_arrays(obj, path: str | Path, compress: bool = True) -> None:
    """Write every field of an array dataclass to an .npz, atomically.

    ``compress=False`` is the perception cache's format (measured in docs/performance.md): an
    uncompressed .npz with every bool array bit-packed (8x smaller, packed and unpacked exactly) and
    every other array as it is. Deflate cost 15 s per paper-size example for a 2.6x smaller file, and
    float16 disparity would move SI-MSE and ATE-3D, so numbers keep their dtype: cached and recomputed
    scores are identical."""
    path = Path(path)
    arrays = {}
    for f in fields(obj):
        value = np.asarray(getattr(obj, f.name))
        if not compress and value.dtype == bool and value.ndim >= 1:
            # One packed row per index along axis 0 (per frame for masks), so frames stay readable one by one.
            arrays[_PACKED + f.name] = np.packbits(value.reshape(len(value), -1), axis=1)
            arrays[_SHAPE + f.name] = np.asarray(value.shape, np.int64)
        else:
            arrays[f.name] = value
    with atomic_file(path, suffix=".npz") as tmp:
        (np.savez_compressed if compress else np.savez)(tmp, **arrays)


def load_arrays(cls, path: str | Path):
    """Read an array dataclass written by ``save_arrays`` (either format; no pickles). A field with a default
    (a flag such as ``geometry_only``) is read back as a Python value, and takes its default in a file written
    before it existed."""
    values = {}
    with np.load(path, allow_pickle=False) as z:
        for f in fields(cls):
            if f.default is not MISSING:
                if f.name in z.files:
                    values[f.name] = z[f.name].item()
            elif f.name in z.files:
                values[f.name] = z[f.name]
            else:
                shape = tuple(int(n) for n in z[_SHAPE + f.name])
                bits = np.unpackbits(z[_PACKED + f.name], axis=1, count=int(np.prod(shape[1:], dtype=np.int64)))
                values[f.name] = bits.view(bool).reshape(shape)
    return cls(**values)


def packed_frames(path: str | Path, key: str, indices) -> dict[int, np.ndarray] | None:
    """Entries ``indices`` along axis 0 of the bool array ``key`` that ``save_arrays(..., compress=False)``
    stored bit-packed in the .npz at ``path``, unpacking only those rows; None if ``key`` is not stored packed."""
    with np.load(path, allow_pickle=False) as z:
        if _PACKED + key not in z.files:
            return None
        shape = tuple(int(n) for n in z[_SHAPE + key])
        rows = z[_PACKED + key]  # an uncompressed member: about an eighth of the bool array
    count = int(np.prod(shape[1:], dtype=np.int64))
    return {int(i): np.unpackbits(rows[int(i)], count=count).view(bool).reshape(shape[1:])
            for i in sorted(set(indices)) if 0 <= int(i) < shape[0]}


@dataclass
class Perception:
    """Per-frame quantities recovered from a generated clip (T frames at ``times_s``).

    masks (T,N,H,W) bool for the N active actors (reference order); tracks (P,T,2) float32 pixel
    (x, y) of the reference query points, visibility (P,T) bool, confidence (P,T) float32 in
    [0, 1] (the tracker's own confidence, kept apart from the visibility decision; 1 where a
    known point is visible and 0 elsewhere for exact backends), track_actor (P,) int index into
    the active actors; disparity (T,H,W) float32 (affine-invariant inverse depth). Background
    corners at their own times bg_times_s (Tb,) float64 seconds: bg_tracks (C,Tb,2) float32,
    bg_confidence (C,Tb) float32 BGDrift weights (the tracker's 0/1 visibility). geometry_only: the clip is no
    render (a geometry-only twin, from its world state): the appearance measurements are not computed.
    """

    times_s: np.ndarray
    masks: np.ndarray
    tracks: np.ndarray
    visibility: np.ndarray
    confidence: np.ndarray
    track_actor: np.ndarray
    disparity: np.ndarray
    bg_times_s: np.ndarray
    bg_tracks: np.ndarray
    bg_confidence: np.ndarray
    geometry_only: bool = False

    @property
    def n_frames(self) -> int:
        return int(self.times_s.shape[0])

    def save(self, path: str | Path) -> None:
        """Write the evaluator's perception cache: uncompressed .npz, masks bit-packed (``save_arrays``)."""
        save_arrays(self, path, compress=False)

    @classmethod
    def load(cls, path: str | Path) -> "Perception":
        return load_arrays(cls, path)

    def aligned(self, ref_times_s: np.ndarray) -> "Perception":
        """Resample to the reference timestamps that fall within this clip (paper, appendix B.1).

        The background arrays are resampled from ``bg_times_s`` to the same timestamps (exact
        copies where those are the reference times already); reference times the background
        arrays do not reach get NaN tracks and zero weight. Where the clip's times are the reference
        times already, the masks and the disparity are views of this perception's (the same values).
        """

        n = aligned_length(self.times_s, ref_times_s)
        dst = np.asarray(ref_times_s[:n], dtype=np.float64)

        def lin(x: np.ndarray, axis: int, src: np.ndarray, to: np.ndarray) -> np.ndarray:
            y = np.moveaxis(interpolate_linear(np.moveaxis(x, axis, 0), src, to), 0, axis)
            # Along axis 0 the result is already a new C-contiguous array of x's dtype (a float one): no second
            # copy of the clip-sized disparity; elsewhere astype lays the moved axes out in memory as before.
            return y if axis == 0 and y.dtype == x.dtype else y.astype(x.dtype)

        def near(x: np.ndarray, axis: int, src: np.ndarray, to: np.ndarray) -> np.ndarray:
            return np.moveaxis(interpolate_nearest(np.moveaxis(x, axis, 0), src, to), 0, axis)

        src, bg_src = self.times_s, np.asarray(self.bg_times_s, dtype=np.float64)
        # Frames already at the reference times, bit for bit: resampling returns the first n frames as they are,
        # so the clip-sized arrays (frames on axis 0, C-contiguous as a fresh copy is) are taken as views of them.
        on_time = (np.array_equal(np.asarray(src[:n], np.float64), dst)
                   and bool(np.all(np.diff(np.asarray(src, np.float64)) > 0)))

        def frames(x: np.ndarray, resample) -> np.ndarray:
            if on_time and x.flags.c_contiguous and (resample is near or np.issubdtype(x.dtype, np.floating)):
                return x[:n]
            return resample(x, 0, src, dst)

        nb = aligned_length(bg_src, dst)
        bg_tracks = np.full((self.bg_tracks.shape[0], n, 2), np.nan, dtype=self.bg_tracks.dtype)
        bg_confidence = np.zeros((self.bg_confidence.shape[0], n), dtype=self.bg_confidence.dtype)
        if nb:
            bg_tracks[:, :nb] = lin(self.bg_tracks, 1, bg_src, dst[:nb])
            bg_confidence[:, :nb] = near(self.bg_confidence, 1, bg_src, dst[:nb])
        return replace(self, times_s=dst, masks=frames(self.masks, near), tracks=lin(self.tracks, 1, src, dst),
                       visibility=near(self.visibility, 1, src, dst), confidence=lin(self.confidence, 1, src, dst),
                       disparity=frames(self.disparity, lin), bg_times_s=dst.copy(), bg_tracks=bg_tracks,
                       bg_confidence=bg_confidence)


class Backend(Protocol):
    """``cache`` (optional class attribute, default True): whether the evaluator stores this backend's
    perception between runs; False for a backend cheaper to recompute than to write and read (``gt``)."""

    name: str
    version: str

    def perceive(self, sample, video, prediction_path: Path) -> Perception:
        """sample: the reference ``Sample``; video: the generated ``Video`` resized to the
        reference resolution (native frame times); prediction_path: the video file."""


@dataclass(frozen=True)
class BackendInfo:
    """Registry entry of a perception backend: ``target`` is "module:Class" constructed with the options."""

    name: str
    target: str
    description: str
    aliases: tuple[str, ...] = ()


BACKENDS: LazyRegistry[BackendInfo] = LazyRegistry("perception backend", [
    BackendInfo("gt", "rigidbench.perception.gt:GroundTruthBackend",
                "exact masks, tracks, depth and background motion from the world state a predictor wrote"),
    BackendInfo("neural", "rigidbench.perception.neural:NeuralBackend",
                "SAM 2.1, CoTracker3 offline, Video Depth Anything (or Depth Anything V2) on the generated clip"),
])


def get_backend(name: str, **options) -> Backend:
    """The backend registered as ``name``, constructed with ``options``."""
    return BACKENDS.load(name)(**options)
