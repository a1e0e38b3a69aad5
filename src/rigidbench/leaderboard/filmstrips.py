"""Filmstrips of the clips a submission includes: a few frames across the reference span, side by side, as one
small JPEG per clip for the site's example viewer.

Frames are decoded with ``video.iter_video`` (real timestamps, stopping after the span) and the one nearest each
of ``STRIP_TIMES_S`` is kept; a time past the clip's last frame (a short clip) is a grey tile. PyAV and Pillow
are imported when a strip is made.
"""

from __future__ import annotations

import io
import logging
from pathlib import Path

import numpy as np

from rigidbench.atomic import write_bytes
from rigidbench.errors import RigidBenchError
from rigidbench.video import REFERENCE_FPS, REFERENCE_FRAMES, iter_video, resize_frames

log = logging.getLogger(__name__)

SPAN_S = (REFERENCE_FRAMES - 1) / REFERENCE_FPS  # 2.0 s: the span every clip is scored over
STRIP_TIMES_S = tuple(float(t) for t in np.linspace(0.0, SPAN_S, 5))  # 0, 0.5, 1, 1.5, 2 s
TILE_HEIGHT = 96  # px of each frame in the strip
GAP = 2  # px between tiles
MISSING_GREY = 200
#: what decoding a damaged or foreign clip may raise
DECODE_ERRORS = (RigidBenchError, OSError, ValueError)


def nearest_frames(path: Path, times_s=STRIP_TIMES_S) -> list[np.ndarray | None]:
    """The decoded frame (H,W,3 uint8) nearest each time of ``times_s`` (seconds from the first frame), None
    for a time more than half a reference frame past the clip's last frame."""
    best: list[tuple[float, np.ndarray] | None] = [None] * len(times_s)
    last_t = -1.0
    for t, frame in iter_video(path, until_s=max(times_s)):
        last_t = t
        for k, want in enumerate(times_s):
            if best[k] is None or abs(t - want) < best[k][0]:
                best[k] = (abs(t - want), frame)
    late = 0.5 / REFERENCE_FPS
    return [None if b is None or want > last_t + late else b[1] for b, want in zip(best, times_s)]


def compose(frames: list[np.ndarray | None], tile_height: int = TILE_HEIGHT) -> np.ndarray:
    """(H, W*n + gaps, 3) uint8: each frame scaled to ``tile_height`` px high, a grey tile for None."""
    shape = next((f.shape for f in frames if f is not None), None)
    if shape is None:
        raise ValueError("no frame to show")
    width = max(1, round(shape[1] * tile_height / shape[0]))
    tiles = [np.full((tile_height, width, 3), MISSING_GREY, np.uint8) if f is None
             else resize_frames(f[None], (width, tile_height))[0] for f in frames]
    out = np.full((tile_height, len(tiles) * width + GAP * (len(tiles) - 1), 3), 255, np.uint8)
    for k, tile in enumerate(tiles):
        out[:, k * (width + GAP):k * (width + GAP) + width] = tile
    return out


def write_filmstrip(video: Path, out: Path) -> Path:
    """A JPEG filmstrip of ``video`` at ``out``; VideoError (a RigidBenchError) when it cannot be decoded."""
    from PIL import Image

    strip = compose(nearest_frames(video))
    buffer = io.BytesIO()
    Image.fromarray(strip).save(buffer, format="JPEG", quality=85)
    out.parent.mkdir(parents=True, exist_ok=True)
    return write_bytes(out, buffer.getvalue())


def filmstrips(videos: dict[str, Path | None], out_dir: Path) -> dict[str, Path | str]:
    """Example id -> its filmstrip ``out_dir/<id>.jpg``, or why there is none (a clip that cannot be decoded:
    logged and named); ids without a clip are left out."""
    out: dict[str, Path | str] = {}
    for sample_id, video in sorted(videos.items()):
        if video is None:
            continue
        try:
            out[sample_id] = write_filmstrip(video, out_dir / f"{sample_id}.jpg")
        except DECODE_ERRORS as exc:
            log.warning("%s: no filmstrip (%s)", video, exc)
            out[sample_id] = f"the clip could not be decoded ({exc})"
    return out


__all__ = ["STRIP_TIMES_S", "compose", "filmstrips", "nearest_frames", "write_filmstrip"]
