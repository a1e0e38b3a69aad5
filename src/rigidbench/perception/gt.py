"""Exact perception for predictions whose world state is known.

Built-in predictors (the reference itself and the failure-mode suite) write, beside each video
``<id>.mp4``, the world state it depicts as ``<id>.state.npz`` at the video's own frame times:

- ``times_s`` (T,): frame timestamps of the video;
- ``masks`` (T,N,H,W) bool: the N active actors of the reference, in reference order;
- ``depth_m`` (T,H,W) float32: depth along the camera axis of what each pixel shows
  (0, inf or >= 100 where there is none);
- ``tracks`` (P,T,2) float32 and ``visibility`` (P,T) bool: where the reference's ground-truth
  query points appear in the video;
- ``bg_affine`` (T,2,3) float64: image-space motion of the background, mapping frame-0 pixel
  coordinates to frame t (identity for a locked camera);
- ``bg_flow`` (T,h,w,2) float32: additional local background displacement in pixels on a coarse
  grid spanning the frame-0 image (zeros when the background moves rigidly);
- ``geometry_only`` (a 0-d bool, absent in older files: False): the video is no render (a geometry-only
  physical twin, ``predictors.twins``), so the appearance measurements are not computed for it.

A video decoded only up to some time (``read_video(until_s=...)``) uses the state's first frames.
The backend reads that file and returns the same quantities the neural models estimate:
disparity is 1/depth; the track confidence is 1 where a point is visible and 0 elsewhere;
background corners are detected on the video's frame 0 outside the frame-0 actor masks and carried
by the known background motion (at the video's frame times), with weight 1 while a corner is in
the image and not covered by an actor, else 0 (the neural backend's 0/1 tracker visibility).
"""

from __future__ import annotations

from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..folders import STATE_SUFFIX, state_path  # noqa: F401 (re-exported: the state file beside a video)
from ..metrics.background import detect_background_corners
from .base import Perception, PerceptionError, load_arrays, save_arrays


@dataclass
class WorldState:
    times_s: np.ndarray
    masks: np.ndarray
    depth_m: np.ndarray
    tracks: np.ndarray
    visibility: np.ndarray
    bg_affine: np.ndarray
    bg_flow: np.ndarray
    geometry_only: bool = False

    def save(self, path: str | Path) -> None:
        save_arrays(self, path)

    @classmethod
    def load(cls, path: str | Path) -> "WorldState":
        try:
            return load_arrays(cls, path)
        except (OSError, KeyError, ValueError) as exc:
            raise PerceptionError(f"{path}: not a readable world-state file ({exc}); rerun the predictor "
                                  "that wrote it") from None


def static_background(n_frames: int) -> tuple[np.ndarray, np.ndarray]:
    """Identity affine (T,2,3) and zero flow (T,2,2,2) for a locked camera and rigid background."""
    affine = np.zeros((n_frames, 2, 3))
    affine[:, 0, 0] = affine[:, 1, 1] = 1.0
    return affine, np.zeros((n_frames, 2, 2, 2), np.float32)


def reference_state(sample, frames: int | None = None) -> WorldState:
    """The reference bundle's own world state (what the ``reference`` predictor depicts)."""
    masks = sample.masks[:, sample.active_indices]
    t = masks.shape[0] if frames is None else frames
    tr = sample.tracks
    affine, flow = static_background(t)
    return WorldState(times_s=np.arange(t) / float(sample.fps), masks=masks[:t], depth_m=sample.depth[:t],
                      tracks=tr["tracks"][:, :t], visibility=tr["visibility"][:, :t],
                      bg_affine=affine, bg_flow=flow)


def disparity_from_depth(depth_m: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
    """1/depth where depth is in (0, 100) m, NaN elsewhere. (T,H,W) -> (T,H,W) float32, written into ``out`` when
    given (float32 of the same shape; the float32 depth itself may be: each frame is read before it is written)."""
    depth = np.asarray(depth_m, dtype=np.float32)
    if out is None:
        out = np.empty(depth.shape, np.float32)
    elif out.shape != depth.shape or out.dtype != np.float32:
        raise ValueError(f"out must be float32 {depth.shape}, got {out.dtype} {out.shape}")
    # Frame by frame, in place: the same float32 quotients as dividing the valid pixels alone, without the
    # clip-sized masks and gathers of that (0.08 instead of 0.13 CPU s for benchmarks/evaluate_samples.py's clip).
    n = depth.shape[0] if depth.ndim > 1 else 1
    rows = depth.reshape(n, depth.size // n if n else 0)
    quotients = out.reshape(rows.shape)
    invalid = np.empty(rows.shape[1], bool)
    nan = np.float32(np.nan)
    with np.errstate(divide="ignore", invalid="ignore"):
        for z, q in zip(rows, quotients):
            np.logical_not(np.greater(z, 0) & np.less(z, 100), out=invalid)  # 0 < z < 100 excludes NaN, +-inf
            np.divide(np.float32(1.0), z, out=q)
            np.copyto(q, nan, where=invalid)
    return out


def move_background_points(points: np.ndarray, affine: np.ndarray, flow: np.ndarray,
                           size_wh: tuple[int, int]) -> np.ndarray:
    """Carry frame-0 points (C,2) through background motion. Returns (C,T,2) pixel positions."""
    points = np.asarray(points, np.float64)
    moved = np.einsum("tij,cj->cti", affine[:, :, :2], points) + affine[None, :, :, 2]
    if np.any(flow):
        gh, gw = flow.shape[1:3]
        w, h = size_wh
        gx = np.clip(points[:, 0] / w * (gw - 1), 0, gw - 1)
        gy = np.clip(points[:, 1] / h * (gh - 1), 0, gh - 1)
        x0, y0 = np.floor(gx).astype(int), np.floor(gy).astype(int)
        x1, y1 = np.minimum(x0 + 1, gw - 1), np.minimum(y0 + 1, gh - 1)
        fx, fy = (gx - x0)[None, :, None], (gy - y0)[None, :, None]
        f = (flow[:, y0, x0] * (1 - fx) * (1 - fy) + flow[:, y0, x1] * fx * (1 - fy)
             + flow[:, y1, x0] * (1 - fx) * fy + flow[:, y1, x1] * fx * fy)  # (T,C,2)
        moved = moved + np.transpose(f, (1, 0, 2))
    return moved


def background_confidence(bg_tracks: np.ndarray, masks: np.ndarray) -> np.ndarray:
    """1 where a corner lies in the image and outside every actor mask, else 0. Returns (C,T)."""
    t, _, h, w = masks.shape
    any_actor = masks.any(axis=1)
    x = np.rint(bg_tracks[..., 0]).astype(int)  # pixel centres at integers
    y = np.rint(bg_tracks[..., 1]).astype(int)
    inside = (x >= 0) & (x < w) & (y >= 0) & (y < h)
    conf = np.zeros(bg_tracks.shape[:2], np.float32)
    for k in range(t):
        ok = inside[:, k]
        conf[ok, k] = (~any_actor[k, y[ok, k], x[ok, k]]).astype(np.float32)
    return conf


def _state_and_disparity(path: Path) -> tuple[WorldState, np.ndarray]:
    """The world state at ``path`` and the disparity of all its frames. The depth is not read again: where it is
    a float32 array of its own (as read from the file) the disparity takes its place, so the state's
    ``depth_m`` then holds the disparity (one clip-sized array less)."""
    state = WorldState.load(path)
    depth = state.depth_m
    own = isinstance(depth, np.ndarray) and depth.dtype == np.float32 and depth.flags.writeable and \
        depth.flags.c_contiguous and depth.base is None
    return state, disparity_from_depth(depth, out=depth if own else None)


class GroundTruthBackend:
    """Exact perception from the world state written by a built-in predictor."""

    name = "gt"
    whole_clip = False  # needs the generated clip only up to the last reference time
    cache = False  # recomputing from the world state costs less than writing and reading a cache
    version = "2"  # 2: Perception carries track confidences and background timestamps

    def __init__(self) -> None:
        self._read_ahead: tuple[Path, Future] | None = None

    def prefetch(self, prediction_path: Path) -> None:
        """Start reading the world state beside ``prediction_path``, and its disparity, on a background thread
        (zlib releases the GIL), so that it overlaps the decoding of the video; ``perceive`` of the same
        prediction takes the result (or the error reading it raised)."""
        path = state_path(prediction_path)
        self._read_ahead = None
        if path.exists():
            pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="world state")
            self._read_ahead = (path, pool.submit(_state_and_disparity, path))
            pool.shutdown(wait=False)  # its thread ends with the read

    def _state(self, path: Path) -> tuple[WorldState, np.ndarray]:
        ahead, self._read_ahead = self._read_ahead, None
        if ahead is not None and ahead[0] == path:
            return ahead[1].result()
        return _state_and_disparity(path)

    def perceive(self, sample, video, prediction_path: Path) -> Perception:

        path = state_path(prediction_path)
        if not path.exists():
            raise PerceptionError(
                f"{prediction_path}: no world state ({path.name}) beside the video. `--perception gt` scores only "
                "predictions from built-in predictors (rigidbench predict ...); use `--perception neural` "
                "for your own model's videos")
        state, disparity = self._state(path)
        n = state.times_s.shape[0]
        h, w = state.masks.shape[2:]
        if video.frames.shape[1:3] != (h, w):
            raise PerceptionError(f"{path}: world state is {w}x{h} but the video is "
                                  f"{video.frames.shape[2]}x{video.frames.shape[1]}; rerun the predictor")
        if video.n_frames < n and np.allclose(state.times_s[:video.n_frames], video.times_s, atol=1e-3):
            # the video was decoded only up to some time (read_video(until_s=...)): the state's first frames
            keep = video.n_frames
            state = WorldState(times_s=state.times_s[:keep], masks=state.masks[:keep], depth_m=state.depth_m[:keep],
                               tracks=state.tracks[:, :keep], visibility=state.visibility[:, :keep],
                               bg_affine=state.bg_affine[:keep], bg_flow=state.bg_flow[:keep],
                               geometry_only=state.geometry_only)
            n = keep
        if n != video.n_frames or not np.allclose(state.times_s, video.times_s, atol=1e-3):
            raise PerceptionError(f"{path}: world state has {n} frames but {prediction_path.name} decodes to "
                                  f"{video.n_frames} (or different timestamps); rerun the predictor")
        active = state.masks.shape[1]
        if active != len(sample.active_indices):
            raise PerceptionError(f"{path}: world state has {active} actors, reference {sample.sample_id} has "
                                  f"{len(sample.active_indices)} active actors")
        corners = detect_background_corners(video.frames[0], state.masks[0])
        bg_tracks = move_background_points(corners, state.bg_affine, state.bg_flow, (w, h)).astype(np.float32)
        return Perception(
            times_s=np.asarray(state.times_s, np.float64), masks=state.masks.astype(bool, copy=False),
            tracks=state.tracks.astype(np.float32), visibility=state.visibility.astype(bool),
            confidence=state.visibility.astype(np.float32),
            track_actor=np.asarray(sample.track_active_index, dtype=np.int64),
            disparity=disparity[:n],
            bg_times_s=np.asarray(state.times_s, np.float64),
            bg_tracks=bg_tracks, bg_confidence=background_confidence(bg_tracks, state.masks),
            geometry_only=bool(state.geometry_only))
