"""Video decoding and encoding, real timestamps, Lanczos resizing and temporal alignment.

Scoring keeps the reference timestamps t_k = k / 24 (paper, appendix B.1). A generated clip is
decoded with its real presentation timestamps (pts * time_base, relative to the first frame, so
variable frame rate is handled), resized with antialiased Lanczos (PIL) to the reference resolution, and sampled at
t_k: RGB, track coordinates and disparity linearly in physical time between the two neighbouring
generated frames; masks and visibility flags by nearest neighbour. Reference timestamps after the
last generated frame are discarded, so each comparison stops at the shorter sequence; a longer
clip is cut at the reference length.

PyAV (``av``), Pillow (``PIL``) and OpenCV (``cv2``) are imported inside the functions that need them.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from fractions import Fraction
from pathlib import Path
from typing import Iterable, Iterator

import numpy as np

from .atomic import atomic_file
from .errors import VideoError
from .folders import MAX_VIDEO_BYTES, VIDEO_EXTENSIONS, check_video_file  # noqa: F401 (re-exported)

log = logging.getLogger(__name__)

#: Reference clip: 49 frames at 24 fps, 1280x704 (paper, section 3 and appendix B.1).
REFERENCE_FPS = 24.0
REFERENCE_FRAMES = 49
REFERENCE_SIZE = (1280, 704)

#: Seconds within which two timestamps are the same instant (a reference time that coincides with a
#: generated frame takes that frame unchanged).
TIME_TOLERANCE_S = 1e-6

#: Seconds by which a reference time may lie outside a clip's first-to-last-frame span and still count as
#: covered (it is then sampled at that end frame): half a frame of the 24 fps reference, i.e. the nearest
#: generated frame is at most half a reference frame away. The one coverage rule: ``aligned_length``
#: (what ``evaluate`` compares and the span it records), the resampling here, and ``validate``'s
#: too-short check all use it, so a clip whose last timestamp is a fraction of a millisecond early is
#: neither refused by one nor cut short by the other.
COVERAGE_TOLERANCE_S = 0.5 / REFERENCE_FPS

# MAX_VIDEO_BYTES (largest prediction file read; a bigger one is refused before it is hashed or decoded),
# VIDEO_EXTENSIONS (extensions read as videos) and check_video_file live with the predictions folder.

_FORMAT_BY_SUFFIX = {".mp4": "mp4", ".mov": "mov", ".mkv": "matroska", ".webm": "webm"}


@dataclass
class Video:
    """frames: (T,H,W,3) uint8 RGB; times_s: (T,) float64 seconds from the first frame, increasing."""

    frames: np.ndarray
    times_s: np.ndarray
    fps_nominal: float | None = None

    def __post_init__(self) -> None:
        self.times_s = np.asarray(self.times_s, dtype=np.float64)
        if self.frames.dtype != np.uint8 or self.frames.ndim != 4 or self.frames.shape[-1] != 3:
            raise ValueError(f"Video frames must be uint8 (T,H,W,3), got {self.frames.dtype} {self.frames.shape}")
        if self.times_s.shape != (self.frames.shape[0],):
            raise ValueError(f"Video has {self.frames.shape[0]} frames but times_s has shape {self.times_s.shape}")
        if self.frames.shape[0] == 0:
            raise ValueError("Video has no frames")
        if np.any(np.diff(self.times_s) <= 0):
            raise ValueError("Video times_s must be strictly increasing")

    @property
    def n_frames(self) -> int:
        return int(self.frames.shape[0])

    @property
    def size(self) -> tuple[int, int]:
        """(W, H) in pixels."""
        return int(self.frames.shape[2]), int(self.frames.shape[1])

    @property
    def duration_s(self) -> float:
        """Seconds spanned by the timestamps, first to last frame (49 frames at 24 fps span 2.0 s)."""
        return float(self.times_s[-1] - self.times_s[0])

    @property
    def fps_measured(self) -> float | None:
        """Mean frame rate from the timestamps, (T-1) / duration; None for a single frame."""
        return (self.n_frames - 1) / self.duration_s if self.n_frames > 1 else None

    def at(self, times_s: np.ndarray, mode: str = "linear") -> np.ndarray:
        """times_s: (K,) seconds within the clip. Returns (K,H,W,3) uint8, linear blend or nearest frame."""
        times_s = np.asarray(times_s, dtype=np.float64)
        if mode == "nearest":
            return interpolate_nearest(self.frames, self.times_s, times_s)
        if mode != "linear":
            raise ValueError(f"unknown resampling mode {mode!r}; use 'linear' or 'nearest'")
        i0, i1, w = _bracket(self.times_s, times_s)
        out = np.empty((len(times_s),) + self.frames.shape[1:], dtype=np.uint8)
        for k in range(len(times_s)):
            out[k] = _blend_uint8(self.frames[i0[k]], self.frames[i1[k]], w[k])
        return out


@dataclass(frozen=True)
class VideoInfo:
    """Container metadata and packet timestamps of one video, read without decoding it to RGB."""

    path: Path
    codec: str
    width: int
    height: int
    times_s: np.ndarray
    fps_nominal: float | None

    @property
    def n_frames(self) -> int:
        return int(len(self.times_s))

    @property
    def duration_s(self) -> float:
        """Seconds from the first to the last frame timestamp."""
        return float(self.times_s[-1] - self.times_s[0]) if len(self.times_s) else 0.0

    @property
    def fps_measured(self) -> float | None:
        """Mean frame rate from the timestamps, (T-1) / duration; None for fewer than two frames."""
        return (self.n_frames - 1) / self.duration_s if self.n_frames > 1 and self.duration_s > 0 else None


# ---------------------------------------------------------------------------------------------
# Timestamps and interpolation (pure numpy)
# ---------------------------------------------------------------------------------------------


def reference_times(n_frames: int = REFERENCE_FRAMES, fps: float = REFERENCE_FPS) -> np.ndarray:
    """Returns (n_frames,) float64 reference timestamps t_k = k / fps in seconds."""
    if n_frames < 0 or fps <= 0:
        raise ValueError(f"need n_frames >= 0 and fps > 0, got {n_frames} and {fps}")
    return np.arange(n_frames, dtype=np.float64) / float(fps)


def aligned_length(gen_times_s: np.ndarray, ref_times_s: np.ndarray, tol_s: float = COVERAGE_TOLERANCE_S) -> int:
    """gen_times_s (T,), ref_times_s (K,) seconds. Returns how many leading reference times the clip covers:
    those within ``tol_s`` (COVERAGE_TOLERANCE_S, the one coverage rule) of its first-to-last-frame span."""
    gen_times_s = np.asarray(gen_times_s, dtype=np.float64)
    ref_times_s = np.asarray(ref_times_s, dtype=np.float64)
    if len(gen_times_s) == 0 or len(ref_times_s) == 0:
        return 0
    inside = (ref_times_s >= gen_times_s[0] - tol_s) & (ref_times_s <= gen_times_s[-1] + tol_s)
    # Count the leading run only: scoring stops at the first reference time the clip cannot cover.
    return int(len(inside)) if inside.all() else int(np.argmin(inside))


def frames_until(times_s: np.ndarray, until_s: float, tol_s: float = TIME_TOLERANCE_S) -> int:
    """times_s (T,) increasing seconds. Returns how many leading frames a comparison up to ``until_s``
    needs: every frame before it and the first at or after it (what ``read_video(until_s=...)`` decodes)."""
    times_s = np.asarray(times_s, dtype=np.float64)
    return int(min(np.searchsorted(times_s, until_s - tol_s, side="left") + 1, len(times_s)))


def _bracket(src_times_s: np.ndarray, dst_times_s: np.ndarray,
             tol_s: float = COVERAGE_TOLERANCE_S) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """src (T,) increasing, dst (K,) seconds. Returns i0, i1 (K,) int and w (K,) float64 in [0, 1]; a dst
    time within ``tol_s`` outside the source span (``aligned_length``'s rule) takes the end sample."""
    src = np.asarray(src_times_s, dtype=np.float64)
    dst = np.asarray(dst_times_s, dtype=np.float64)
    if src.ndim != 1 or len(src) == 0:
        raise ValueError(f"source times must be a non-empty 1-D array, got shape {src.shape}")
    if len(src) > 1 and np.any(np.diff(src) <= 0):
        raise ValueError("source times must be strictly increasing")
    outside = (dst < src[0] - tol_s) | (dst > src[-1] + tol_s)
    if np.any(outside):
        bad = dst[outside]
        raise ValueError(
            f"{len(bad)} target times (first {bad[0]:.6f} s) lie outside the source span "
            f"[{src[0]:.6f}, {src[-1]:.6f}] s; cut them first with aligned_length()")
    if len(src) == 1:
        zeros = np.zeros(len(dst), dtype=np.int64)
        return zeros, zeros, np.zeros(len(dst))
    i0 = np.clip(np.searchsorted(src, dst, side="right") - 1, 0, len(src) - 2)
    i1 = i0 + 1
    w = np.clip((dst - src[i0]) / (src[i1] - src[i0]), 0.0, 1.0)
    return i0, i1, w


def interpolate_linear(values: np.ndarray, src_times_s: np.ndarray, dst_times_s: np.ndarray,
                       axis: int = 0) -> np.ndarray:
    """values (..., T along axis, ...); times in seconds. Returns values at dst times, float, T -> K on axis."""
    values = np.asarray(values)
    moved = np.moveaxis(values, axis, 0)
    if moved.shape[0] != len(src_times_s):
        raise ValueError(f"values have {moved.shape[0]} samples on axis {axis} but {len(src_times_s)} source times")
    i0, i1, w = _bracket(src_times_s, dst_times_s)
    dtype = values.dtype if np.issubdtype(values.dtype, np.floating) else np.dtype(np.float64)
    out = np.empty((len(w),) + moved.shape[1:], dtype=dtype)
    for k in range(len(w)):  # one output sample at a time: no float copy of the whole input
        if w[k] <= 0.0:
            out[k] = moved[i0[k]]
        elif w[k] >= 1.0:
            out[k] = moved[i1[k]]
        else:
            a = moved[i0[k]].astype(dtype, copy=False)
            b = moved[i1[k]].astype(dtype, copy=False)
            out[k] = a * dtype.type(1.0 - w[k]) + b * dtype.type(w[k])
    return np.moveaxis(out, 0, axis)


def interpolate_nearest(values: np.ndarray, src_times_s: np.ndarray, dst_times_s: np.ndarray,
                        axis: int = 0) -> np.ndarray:
    """values (..., T along axis, ...), any dtype (bool masks stay bool). Returns the nearest samples; ties go earlier."""
    values = np.asarray(values)
    if np.moveaxis(values, axis, 0).shape[0] != len(src_times_s):
        raise ValueError(f"values have {values.shape[axis]} samples on axis {axis} but {len(src_times_s)} source times")
    i0, i1, w = _bracket(src_times_s, dst_times_s)
    index = np.where(w > 0.5, i1, i0)
    return np.take(values, index, axis=axis)


def _blend_uint8(a: np.ndarray, b: np.ndarray, w: float) -> np.ndarray:
    """a, b: (H,W,3) uint8; w in [0, 1]. Returns (1-w)*a + w*b rounded half-to-even, uint8."""
    if w <= 1e-9:
        return a
    if w >= 1.0 - 1e-9:
        return b
    mixed = a.astype(np.float32) * np.float32(1.0 - w) + b.astype(np.float32) * np.float32(w)
    return np.rint(mixed).clip(0, 255).astype(np.uint8)


# ---------------------------------------------------------------------------------------------
# Resizing
# ---------------------------------------------------------------------------------------------


def _resize_image(image: np.ndarray, width: int, height: int) -> np.ndarray:
    """image (H,W,C); returns (height,width,C) of the same dtype, PIL Lanczos (antialiased when shrinking).
    uint8 with 1, 3 or 4 channels is resized as one PIL image; anything else channel by channel in
    PIL's 32-bit float mode (rounded back for integer dtypes)."""
    from PIL import Image

    lanczos = Image.Resampling.LANCZOS
    if image.dtype == np.uint8 and image.shape[-1] in (1, 3, 4):
        pil = Image.fromarray(image[..., 0] if image.shape[-1] == 1 else np.ascontiguousarray(image))
        return np.asarray(pil.resize((width, height), lanczos)).reshape(height, width, -1)
    out = np.stack([np.asarray(Image.fromarray(np.ascontiguousarray(image[..., c], dtype=np.float32))
                               .resize((width, height), lanczos)) for c in range(image.shape[-1])], axis=-1)
    if np.issubdtype(image.dtype, np.integer):
        info = np.iinfo(image.dtype)
        out = np.rint(out).clip(info.min, info.max)
    return out.astype(image.dtype)


def resize_frames(frames: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """frames (T,H,W,C) or (H,W,C) uint8; size (W,H). Returns the Lanczos-resized frames, uint8 (input if same size).

    Resized as the published evaluation resized generated frames (RigidBench release,
    ``eval/prepare.py``, ``extract_frames``): PIL ``Image.resize(size, LANCZOS)`` per RGB frame.
    PIL widens the Lanczos-3 kernel by the shrink factor, so shrinking (e.g. 1920x1080 outputs to
    1280x704) is antialiased; OpenCV's INTER_LANCZOS4 keeps a fixed 8-tap kernel and aliases
    there. Enlarging is ordinary Lanczos-3 interpolation.
    """
    width, height = int(size[0]), int(size[1])
    if frames.shape[-3:-1] == (height, width):
        return frames
    if frames.ndim == 3:
        return _resize_image(frames, width, height)
    out = np.empty((frames.shape[0], height, width) + frames.shape[3:], dtype=frames.dtype)
    for t in range(frames.shape[0]):
        out[t] = _resize_image(frames[t], width, height).reshape(out.shape[1:])
    return out


def resize_maps(maps: np.ndarray, size: tuple[int, int], method: str = "bilinear") -> np.ndarray:
    """maps (T,H,W) or (H,W), float (bool only with 'nearest'); size (W,H). Returns resized maps, same dtype."""
    import cv2

    flags = {"bilinear": cv2.INTER_LINEAR, "lanczos": cv2.INTER_LANCZOS4, "nearest": cv2.INTER_NEAREST}
    if method not in flags:
        raise ValueError(f"unknown resize method {method!r}; use one of {sorted(flags)}")
    width, height = int(size[0]), int(size[1])
    if maps.shape[-2:] == (height, width):
        return maps
    if maps.dtype == np.bool_:
        if method != "nearest":
            raise ValueError("boolean maps (masks) can only be resized with method='nearest'")
        return resize_maps(maps.astype(np.uint8), size, "nearest").astype(bool)
    if not (np.issubdtype(maps.dtype, np.floating) or maps.dtype == np.uint8):
        raise ValueError(f"resize_maps takes float, uint8 or bool maps, got {maps.dtype}")
    work = maps.astype(np.float32) if maps.dtype == np.float16 else maps  # cv2 has no float16 resize
    if work.ndim == 2:
        return cv2.resize(work, (width, height), interpolation=flags[method]).astype(maps.dtype, copy=False)
    out = np.empty((work.shape[0], height, width), dtype=maps.dtype)
    for t in range(work.shape[0]):
        out[t] = cv2.resize(work[t], (width, height), interpolation=flags[method])
    return out


# ---------------------------------------------------------------------------------------------
# Temporal alignment
# ---------------------------------------------------------------------------------------------


def align_frames(frames: Iterable[tuple[float, np.ndarray]], ref_times_s: np.ndarray,
                 size: tuple[int, int] | None = None) -> np.ndarray:
    """frames: (time s, (H,W,3) uint8) in increasing time; ref_times_s (K,) increasing. Returns (K',H,W,3) uint8.

    Streaming form of the alignment: only the two neighbouring generated frames are held, each
    resized with antialiased Lanczos (``resize_frames``: PIL, as the paper's pipeline does), then
    blended linearly in physical time in float32 and rounded half-to-even back to uint8. A
    reference time that coincides with a generated frame (within TIME_TOLERANCE_S) returns that
    resized frame unchanged. Reference times after the last generated frame are dropped (K' <= K), so a
    longer clip is cut at the reference length and a shorter one stops at its last frame; those within
    COVERAGE_TOLERANCE_S of it are covered (``aligned_length``) and take the last frame.
    """
    ref = np.asarray(ref_times_s, dtype=np.float64)
    out: np.ndarray | None = None
    k = 0
    prev: np.ndarray | None = None
    t_prev = 0.0
    for t, frame in frames:
        if k == len(ref):
            break
        if size is None:
            size = (frame.shape[1], frame.shape[0])
        if out is None:
            out = np.empty((len(ref), size[1], size[0], 3), dtype=np.uint8)
        cur = resize_frames(frame, size)
        if prev is None:
            if ref[0] < t - COVERAGE_TOLERANCE_S:
                break  # the clip starts after the first reference time: nothing can be scored
            while k < len(ref) and ref[k] <= t + TIME_TOLERANCE_S:
                out[k] = cur
                k += 1
        else:
            while k < len(ref) and ref[k] <= t + TIME_TOLERANCE_S:
                w = min(max((ref[k] - t_prev) / (t - t_prev), 0.0), 1.0)
                out[k] = _blend_uint8(prev, cur, w)
                k += 1
        prev, t_prev = cur, t
    else:  # the clip ended: reference times within the coverage tolerance of its last frame take that frame
        while prev is not None and k < len(ref) and ref[k] <= t_prev + COVERAGE_TOLERANCE_S:
            out[k] = prev
            k += 1
    if out is None:
        width, height = size if size is not None else (0, 0)
        return np.empty((0, height, width, 3), dtype=np.uint8)
    return out if k == len(ref) else out[:k].copy()


def align_video(video: Video, ref_times_s: np.ndarray, size: tuple[int, int] | None = None,
                copy: bool = True) -> np.ndarray:
    """video: decoded clip; ref_times_s (K,) s; size (W,H) or None (keep). Returns (K',H,W,3) uint8; see align_frames.
    ``copy=False``: where the clip's first K frame times are the reference times, bit for bit, at the size asked
    for (alignment then returns its frames unchanged), the first K of ``video.frames`` themselves (a view)."""
    ref = np.asarray(ref_times_s, dtype=np.float64)
    frames = video.frames
    if (not copy and size in (None, (frames.shape[2], frames.shape[1])) and 0 < len(ref) <= len(video.times_s)
            and np.array_equal(np.asarray(video.times_s[:len(ref)], np.float64), ref)):
        return frames[:len(ref)]
    return align_frames(zip(video.times_s.tolist(), frames), ref_times_s, size)


def read_aligned(path: str | Path, ref_times_s: np.ndarray,
                 size: tuple[int, int] | None = REFERENCE_SIZE) -> tuple[np.ndarray, np.ndarray]:
    """path: a generated clip; ref_times_s (K,) s; size (W,H). Returns frames (K',H,W,3) uint8, times (K',) s.

    Decodes and aligns in one pass, holding only the output and two neighbouring frames.
    """
    ref_times_s = np.asarray(ref_times_s, dtype=np.float64)
    frames = align_frames(iter_video(path), ref_times_s, size)
    return frames, ref_times_s[: len(frames)].copy()


# ---------------------------------------------------------------------------------------------
# Decoding
# ---------------------------------------------------------------------------------------------


def _snap_to_rate(t_s: float, index: int, fps: float | None, quantum_s: float) -> float:
    """t_s: time of frame number index from pts; quantum_s: the time base. Returns index / fps if within one tick."""
    # Containers such as Matroska store times in whole milliseconds, so 1/24 s becomes 0.042 s;
    # a timestamp within one tick of the constant-rate grid is that grid time after rounding.
    if fps is None or fps <= 0 or quantum_s * fps > 0.1:
        return t_s
    grid_s = index / fps
    return grid_s if abs(t_s - grid_s) <= quantum_s + 1e-9 else t_s


def _nominal_fps(stream) -> float | None:
    """stream: a PyAV video stream. Returns its average (or guessed) frame rate in Hz, None if unknown."""
    for rate in (stream.average_rate, stream.guessed_rate):
        if rate is not None and rate > 0:
            return float(rate)
    return None


def _open(path: Path):
    """Opens a container with PyAV; raises VideoError for a missing, unreadable or non-regular file."""
    import av

    check_video_file(path)
    try:
        container = av.open(str(path))
    except av.error.FFmpegError as exc:
        raise VideoError(path, f"cannot open as a video ({exc.strerror or exc}); re-encode it as H.264 mp4") from exc
    if not container.streams.video:
        container.close()
        raise VideoError(path, "contains no video stream")
    return container


class _FrameBuffer:
    """Growable (T,H,W,3) uint8 buffer: frames are copied in once, no list-then-stack double copy."""

    def __init__(self, capacity_hint: int):
        self.capacity_hint = max(int(capacity_hint), 1)
        self.data: np.ndarray | None = None
        self.n = 0

    def append(self, frame: np.ndarray) -> None:
        self.slot(frame.shape)[...] = frame

    def slot(self, shape: tuple[int, ...]) -> np.ndarray:
        """The next frame's place, (H,W,3) uint8, counted as appended: the caller writes the frame into it."""
        if self.data is None:
            self.data = np.empty((self.capacity_hint,) + tuple(shape), dtype=np.uint8)
        elif self.n == len(self.data):
            grown = np.empty((2 * len(self.data),) + self.data.shape[1:], dtype=np.uint8)
            grown[: self.n] = self.data
            self.data = grown
        self.n += 1
        return self.data[self.n - 1]

    def result(self) -> np.ndarray:
        if self.data is None:
            raise ValueError("no frames were appended")
        return self.data if self.n == len(self.data) else self.data[: self.n].copy()


def iter_video(path: str | Path, *, until_s: float | None = None) -> Iterator[tuple[float, np.ndarray]]:
    """path: a video file. Yields (time s from the first frame, (H,W,3) uint8 RGB) in increasing time.

    Times are pts * time_base relative to the first frame, so variable frame rate is kept; a time
    within one time-base tick of index / nominal fps is snapped to it (see _snap_to_rate). Frames
    whose time does not increase are dropped with a warning. Decoding stops after the first frame
    at or after ``until_s``.
    """
    import av

    path = Path(path)
    container = _open(path)
    try:
        stream = container.streams.video[0]
        stream.thread_type = "AUTO"
        fps_nominal = _nominal_fps(stream)
        first_pts: int | None = None
        index = 0
        t_last = -math.inf
        try:
            for frame in container.decode(stream):
                if frame.pts is None:
                    if fps_nominal is None:
                        raise VideoError(path, "frames carry no timestamps and the stream has no frame rate")
                    t = index / fps_nominal
                else:
                    if first_pts is None:
                        first_pts = frame.pts
                    time_base = frame.time_base or stream.time_base
                    t = _snap_to_rate(float((frame.pts - first_pts) * time_base), index, fps_nominal,
                                      float(time_base))
                if t <= t_last:
                    log.warning("%s: dropping frame %d, its timestamp %.6f s does not increase", path, index, t)
                    continue
                yield t, frame.to_ndarray(format="rgb24")
                index += 1
                t_last = t
                if until_s is not None and t >= until_s - TIME_TOLERANCE_S:
                    return
        except av.error.FFmpegError as exc:
            if index == 0:
                raise VideoError(path, f"cannot decode ({exc.strerror or exc}); re-encode it as H.264 mp4") from exc
            log.warning("%s: decoding stopped after %d frames: %s", path, index, exc)
        if index == 0:
            raise VideoError(path, "contains no decodable frames")
    finally:
        container.close()


#: The decoders ``read_video`` offers. ``pyav`` converts YUV to RGB with the matrix the stream's colour
#: tag names (BT.709 for most hosted models' output), frame times from the container; ``opencv`` decodes
#: as the published evaluator did (``cv2.VideoCapture``): BT.601 whatever the tag, frame k at k / the
#: header's frame rate. Untagged streams decode to the same pixels with both.
DECODERS = ("pyav", "opencv")


def read_video(path: str | Path, *, fps: float | None = None, until_s: float | None = None,
               decoder: str = "pyav") -> Video:
    """path: a video file or a directory of PNG frames (needs fps). Returns Video, RGB uint8, real timestamps.

    Timestamps come from iter_video. ``fps`` overrides them with k / fps (required for PNG
    directories). ``until_s`` (seconds from the first frame) decodes only what a comparison up to
    that time needs: every frame with a timestamp before it, and the first frame at or after it
    (within TIME_TOLERANCE_S), which is the frame at ``until_s`` itself or the later neighbour that
    linear and nearest alignment need at the end; nothing after that frame is decoded. It applies
    to the returned timestamps (k / fps when ``fps`` is given). ``decoder``: one of DECODERS
    (``read_video_opencv`` for ``opencv``).
    """
    path = Path(path)
    if decoder not in DECODERS:
        raise ValueError(f"unknown decoder {decoder!r}; known: {', '.join(DECODERS)}")
    if path.is_dir():
        if fps is None:
            raise VideoError(path, "a directory of PNG frames needs an explicit fps")
        return _read_png_dir(path, fps, until_s)
    if decoder == "opencv":
        return read_video_opencv(path, fps=fps, until_s=until_s)
    fps_nominal, hint = _stream_header(path)
    rate = fps if fps is not None else fps_nominal
    if rate and until_s is not None:
        hint = min(hint or math.inf, max(int(math.ceil(until_s * rate)), 0) + 2)
    buffer = _FrameBuffer(hint or 64)
    times: list[float] = []
    frames = iter_video(path, until_s=until_s if fps is None else None)
    try:
        for t, frame in frames:
            buffer.append(frame)
            times.append(t)
            if fps is not None and until_s is not None and _reached(len(times) - 1, fps, until_s):
                break
    finally:
        frames.close()
    times_s = np.arange(len(times)) / fps if fps is not None else np.asarray(times, dtype=np.float64)
    return Video(frames=buffer.result(), times_s=times_s, fps_nominal=fps if fps is not None else fps_nominal)


def read_video_opencv(path: str | Path, *, fps: float | None = None, until_s: float | None = None) -> Video:
    """path: a video file. Returns Video decoded as the published evaluator decoded predictions (its
    ``eval/prepare.py``): ``cv2.VideoCapture`` frames in decoding order, BGR -> RGB, the YUV matrix
    OpenCV's FFmpeg backend applies (BT.601) whatever colour matrix the stream is tagged with, and frame
    k at k / fps (``fps``, else the header's rate, ``CAP_PROP_FPS``). ``until_s`` as in read_video."""
    import cv2

    path = Path(path)
    check_video_file(path)
    capture = cv2.VideoCapture(str(path))
    try:
        if not capture.isOpened():
            raise VideoError(path, "OpenCV cannot open it as a video; re-encode it as H.264 mp4")
        rate = float(fps) if fps is not None else float(capture.get(cv2.CAP_PROP_FPS))
        if not (math.isfinite(rate) and rate > 0):
            raise VideoError(path, "OpenCV reads no frame rate from its header; re-encode it with a constant "
                                   "frame rate (e.g. 24 fps)")
        hint = max(int(capture.get(cv2.CAP_PROP_FRAME_COUNT) or 0), 1)
        if until_s is not None:
            hint = min(hint, max(int(math.ceil(until_s * rate)), 0) + 2)
        buffer = _FrameBuffer(hint)
        while True:
            ok, bgr = capture.read()
            if not ok or bgr is None:
                break
            if buffer.data is not None and bgr.shape != buffer.data.shape[1:]:
                raise VideoError(path, f"frame {buffer.n} is {bgr.shape[1]}x{bgr.shape[0]}, unlike the first frame")
            slot = buffer.slot(bgr.shape)
            converted = cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB, dst=slot)  # into the buffer, without a copy
            if converted is not slot:  # (OpenCV allocated its own)
                slot[...] = converted
            if until_s is not None and _reached(buffer.n - 1, rate, until_s):
                break
    finally:
        capture.release()
    if buffer.n == 0:
        raise VideoError(path, "OpenCV decodes no frames from it; re-encode it as H.264 mp4")
    return Video(frames=buffer.result(), times_s=np.arange(buffer.n) / rate, fps_nominal=rate)


def _stream_header(path: Path) -> tuple[float | None, int]:
    """path: a video file. Returns the header's nominal frame rate (Hz, None if unknown) and frame count (0 if unknown)."""
    container = _open(path)
    try:
        stream = container.streams.video[0]
        return _nominal_fps(stream), int(stream.frames or 0)
    finally:
        container.close()


def _reached(index: int, fps: float, until_s: float) -> bool:
    """Whether frame ``index`` at index / fps is the first one a read up to ``until_s`` must end with."""
    return index / float(fps) >= until_s - TIME_TOLERANCE_S


def _read_png_dir(path: Path, fps: float, until_s: float | None = None) -> Video:
    """path: a directory of PNG frames, sorted by name; fps in Hz. Returns Video with times k / fps
    (with ``until_s``: up to the first frame at or after it, as read_video)."""
    import cv2

    files = sorted(p for p in path.iterdir() if p.suffix.lower() == ".png")
    if not files:
        raise VideoError(path, "directory holds no .png frames")
    if until_s is not None:
        last = next((k for k in range(len(files)) if _reached(k, fps, until_s)), len(files) - 1)
        files = files[: last + 1]
    buffer = _FrameBuffer(len(files))
    for file in files:
        bgr = cv2.imread(str(file), cv2.IMREAD_COLOR)
        if bgr is None:
            raise VideoError(file, "cannot read PNG frame")
        if buffer.data is not None and bgr.shape != buffer.data.shape[1:]:
            raise VideoError(file, f"frame size {bgr.shape[1]}x{bgr.shape[0]} differs from the first frame")
        buffer.append(bgr[..., ::-1])
    return Video(frames=buffer.result(), times_s=np.arange(len(files)) / float(fps), fps_nominal=float(fps))


def probe_video(path: str | Path) -> VideoInfo:
    """path: a video file. Returns VideoInfo from container metadata and demuxed packet pts (no RGB decode)."""
    import av

    path = Path(path)
    container = _open(path)
    try:
        stream = container.streams.video[0]
        codec = stream.codec_context
        pts: list[int] = []
        for packet in container.demux(stream):
            if packet.size == 0 or packet.is_discard:
                continue
            stamp = packet.pts if packet.pts is not None else packet.dts
            if stamp is not None:
                pts.append(stamp)
        fps_nominal = _nominal_fps(stream)
        quantum_s = float(stream.time_base)
        unique_pts = sorted(set(pts))
        times_s = np.array([_snap_to_rate((p - unique_pts[0]) * quantum_s, j, fps_nominal, quantum_s)
                            for j, p in enumerate(unique_pts)], dtype=np.float64)
        if len(times_s) == 0 and stream.frames and fps_nominal:
            times_s = np.arange(stream.frames, dtype=np.float64) / fps_nominal
        return VideoInfo(path=path, codec=codec.name, width=int(codec.width), height=int(codec.height),
                         times_s=times_s, fps_nominal=fps_nominal)
    except av.error.FFmpegError as exc:
        raise VideoError(path, f"cannot read packets ({exc}); re-encode it as H.264 mp4") from exc
    finally:
        container.close()


def check_decodable(path: str | Path) -> None:
    """path: a video file. Decodes its first frame only; raises VideoError when that fails."""
    import av

    container = _open(Path(path))
    try:
        stream = container.streams.video[0]
        for _ in container.decode(stream):
            return
        raise VideoError(path, "contains no decodable frames")
    except av.error.FFmpegError as exc:
        raise VideoError(path, f"cannot decode ({exc}); re-encode it as H.264 mp4") from exc
    finally:
        container.close()


# ---------------------------------------------------------------------------------------------
# Encoding
# ---------------------------------------------------------------------------------------------


def write_video(path: str | Path, frames: np.ndarray, fps: float = REFERENCE_FPS, *, crf: int = 18,
                times_s: np.ndarray | None = None, preset: str = "medium", lossless: bool = False) -> Path:
    """frames (T,H,W,3) uint8 RGB, H and W even; fps in Hz. Writes H.264 yuv420p (VP9 for .webm) atomically.

    ``lossless`` writes H.264 in RGB with crf 0 (libx264rgb), which decodes to exactly ``frames``.

    With ``times_s`` (T,) seconds, strictly increasing, each frame gets that presentation time on
    a 1/90000 s time base (a variable-frame-rate file); otherwise frame k is shown at k / fps.
    """
    import av

    path = Path(path)
    frames = np.asarray(frames)
    if frames.dtype != np.uint8 or frames.ndim != 4 or frames.shape[-1] != 3 or frames.shape[0] == 0:
        raise ValueError(f"{path}: frames must be uint8 (T,H,W,3) with T >= 1, got {frames.dtype} {frames.shape}")
    height, width = frames.shape[1:3]
    if height % 2 or width % 2:
        raise ValueError(f"{path}: H.264 yuv420p needs even dimensions, got {width}x{height}; "
                         f"resize first, e.g. resize_frames(frames, ({width + width % 2}, {height + height % 2}))")
    suffix = path.suffix.lower()
    if suffix not in _FORMAT_BY_SUFFIX:
        raise ValueError(f"{path}: cannot write '{suffix}'; use one of {', '.join(_FORMAT_BY_SUFFIX)}")
    if times_s is not None:
        times_s = np.asarray(times_s, dtype=np.float64)
        if times_s.shape != (frames.shape[0],) or np.any(np.diff(times_s) <= 0):
            raise ValueError(f"{path}: times_s must be (T,) strictly increasing, got shape {times_s.shape}")
    codec_name = "libvpx-vp9" if suffix == ".webm" else ("libx264rgb" if lossless else "libx264")
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_file(path, suffix=suffix, unique=True) as tmp_name:
        with av.open(str(tmp_name), mode="w", format=_FORMAT_BY_SUFFIX[suffix]) as container:
            stream = container.add_stream(codec_name, rate=Fraction(fps).limit_denominator(100_000))
            stream.width, stream.height = width, height
            stream.pix_fmt = "rgb24" if codec_name == "libx264rgb" else "yuv420p"
            options = {"crf": "0" if lossless else str(int(crf))}
            options.update({"preset": preset} if codec_name.startswith("libx264") else {"b": "0"})
            stream.options = options
            time_base = Fraction(1, 90_000) if times_s is not None else None
            if time_base is not None:
                stream.codec_context.time_base = time_base
                stream.time_base = time_base
            for index, frame in enumerate(_iter_frames(frames)):
                video_frame = av.VideoFrame.from_ndarray(frame, format="rgb24")
                if time_base is not None:
                    video_frame.pts = round((times_s[index] - times_s[0]) * 90_000)
                    video_frame.time_base = time_base
                container.mux(stream.encode(video_frame))
            container.mux(stream.encode(None))
    return path


def _iter_frames(frames: np.ndarray) -> Iterator[np.ndarray]:
    """frames (T,H,W,3) uint8. Yields C-contiguous (H,W,3) frames for the encoder."""
    for frame in frames:
        yield np.ascontiguousarray(frame)
