"""Does a prediction start from its reference's first frame? (No silent mixing of evaluation sets.)

A video model is given the reference's first frame, so the first frame of its clip shows the same
scene from the same camera. A clip generated from another set's inputs (our rendered set against
the published one, or the other way round: the same ids name different scenes) does not, and
would be scored against the wrong reference without any error. This module compares the two
first frames cheaply and tolerantly:

- both are reduced to grayscale (Rec. 601 luma) and resized by area averaging to a common small
  size, ``COMPARE_WIDTH`` pixels wide with the reference's aspect ratio, which removes what codecs,
  resizing and a model's slight blur change;
- each thumbnail has its own mean subtracted, and the statistic is their normalised
  cross-correlation (Pearson correlation over pixels), which ignores exposure offsets and gain;
- the frames match when the correlation is at least ``MIN_CORRELATION`` and no turned version of
  the prediction (rotated 180 degrees, mirrored left to right, upside down: ``ORIENTATIONS``) fits
  better by more than ``ORIENTATION_MARGIN``. A turned frame keeps the scene's coarse layout, so
  the correlation alone can pass it; the turned-back frame then fits as well as an honest one.

The threshold was chosen by measurement on the first frames of the 17 paper-preset examples of
docs/gallery (1280x704) and on synthetic frames (tests/unit/test_firstframe.py). The same frame
through JPEG q50 or q20, a 1280x704 -> 832x480 Lanczos resize, H.264 (crf 28, or crf 40 at half
size), a Gaussian blur of sigma 2 px (or 6 px), +10 % brightness or a colour cast keeps the
correlation at or above 0.99; +30 % brightness gives 0.97, the gamma 2.5 failure mode 0.94, and a
3 % zoom, a centre crop to 16:9 or an 8 px shift at 1280 px stay above 0.86. The 136 pairs of
different examples give at most 0.685, and that pair is the same room seen from almost the same
camera (azimuth 1.6 degrees and distance 5 cm apart); the next is 0.61, the mean 0.07, the lowest
-0.72 (so the sign counts: an anti-correlated frame is not taken for a match). 0.8 leaves about 0.06
below the worst same-frame case and 0.12 above the worst different-example case. Two examples that
share a room and nearly share a camera can still pass one by one; mixing whole sets still shows up
as mismatches on nearly every example.

Turned frames, measured on the first frames of the 17 gallery sheets (docs/gallery, 636x352
crops): as given, a mirrored frame correlates up to 0.81 with its reference (scene_beach_gazebo,
so the correlation alone passed it), an upside-down one up to 0.23 and a rotated one up to 0.19;
under a strong lens vignette (brightness times max(0, 1 - 0.7 r^2), r the distance from the
centre with x over half the width and y over half the height) up to 0.90, 0.83 and 0.84. Turned
back, raw or through H.264 crf 28, they correlate at least 0.999. The honest variants above (JPEG
q20 and q50, H.264 crf 28 and crf 40 at half size, a Lanczos resize, blur sigma 2 and 6 px, +30 %
brightness, gamma 2.5, a colour cast, a 3 % zoom, a 16:9 crop, an 8 px shift at 1280 px) keep the
frame as given the best fit by at least 0.14 on the same frames (a 3 % zoom of
scene_beach_gazebo), far above ``ORIENTATION_MARGIN``. A scene so symmetric that its mirror image
correlates within ``ORIENTATION_MARGIN`` of it cannot be told from its mirror image, and is not.

The comparison functions are pure functions of numpy arrays; ``read_first_frame`` and
``read_reference_first_frame`` read files for validate.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from .folders import BundleFolder, inputs_path
from .video import iter_video

#: Width in pixels of the thumbnails that are compared; the height follows the reference's aspect.
COMPARE_WIDTH = 64
#: Normalised cross-correlation of the mean-subtracted thumbnails at or above which the frames match.
MIN_CORRELATION = 0.8
#: A thumbnail whose standard deviation is below this (grey levels of 0..255) is treated as flat.
FLAT_STD = 1.0
#: What validate and evaluate record for an example whose first frame does not match.
MISMATCH_KIND = "first_frame_mismatch"
#: The ways a prediction's first frame may be turned, each as the index that turns a (H, W) thumbnail back
#: (each turn is its own inverse; a thumbnail of a turned frame is the turned thumbnail, the cells being symmetric).
ORIENTATIONS: dict[str, tuple[slice, slice]] = {
    "rotated 180 degrees": (slice(None, None, -1), slice(None, None, -1)),
    "mirrored left to right": (slice(None), slice(None, None, -1)),
    "upside down": (slice(None, None, -1), slice(None)),
}
#: A turned version of the prediction that correlates better than the frame as given by more than this names
#: the prediction turned (and refuses it).
ORIENTATION_MARGIN = 0.02

_LUMA = (0.299, 0.587, 0.114)  # Rec. 601


def to_gray(image: np.ndarray) -> np.ndarray:
    """image (H,W,3) RGB or (H,W) gray, any numeric dtype on the 0..255 scale; returns (H,W) float32 luma."""
    a = np.asarray(image, dtype=np.float32)
    if a.ndim == 3 and a.shape[-1] in (3, 4):
        return a[..., 0] * _LUMA[0] + a[..., 1] * _LUMA[1] + a[..., 2] * _LUMA[2]
    if a.ndim == 3 and a.shape[-1] == 1:
        return a[..., 0]
    if a.ndim == 2:
        return a
    raise ValueError(f"expected an (H,W,3) RGB or (H,W) gray image, got shape {a.shape}")


def _area_weights(n_in: int, n_out: int) -> np.ndarray:
    """(n_out, n_in) matrix whose row j averages the input cells that output cell j covers (by overlap)."""
    edges = np.linspace(0.0, n_in, n_out + 1)
    lo, hi = edges[:-1, None], edges[1:, None]
    cells = np.arange(n_in)[None, :]
    overlap = np.clip(np.minimum(hi, cells + 1) - np.maximum(lo, cells), 0.0, None)
    return overlap / overlap.sum(axis=1, keepdims=True)


def area_resize(gray: np.ndarray, width: int, height: int) -> np.ndarray:
    """gray (H,W) float; returns (height, width) by area averaging (each output pixel the mean of what it covers)."""
    h, w = gray.shape
    rows = _area_weights(h, height).astype(np.float32) @ np.asarray(gray, np.float32)
    return rows.astype(np.float64) @ _area_weights(w, width).T


def compare_size(reference_shape: tuple[int, ...], width: int = COMPARE_WIDTH) -> tuple[int, int]:
    """(width, height) of the thumbnails for a reference of shape (H, W, ...): ``width`` wide, its aspect."""
    h, w = reference_shape[:2]
    width = min(width, w)
    return width, max(1, round(width * h / w))


def thumbnail(image: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """image (H,W,3) or (H,W); returns the (size[1], size[0]) grayscale area-averaged thumbnail, mean subtracted."""
    small = area_resize(to_gray(image), *size)
    return small - small.mean()


def _correlation(a: np.ndarray, b: np.ndarray) -> float:
    """Normalised cross-correlation of two mean-subtracted thumbnails; 1.0 for two flat ones, 0.0 for one."""
    sa, sb = a.std(), b.std()
    if sa < FLAT_STD and sb < FLAT_STD:
        return 1.0
    if sa < FLAT_STD or sb < FLAT_STD:
        return 0.0
    return float(np.clip((a * b).mean() / (sa * sb), -1.0, 1.0))


def _thumbnails(pred_first_rgb: np.ndarray, ref_first_rgb: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    size = compare_size(np.shape(ref_first_rgb))
    return thumbnail(pred_first_rgb, size), thumbnail(ref_first_rgb, size)


def first_frame_correlation(pred_first_rgb: np.ndarray, ref_first_rgb: np.ndarray) -> float:
    """Normalised cross-correlation in [-1, 1] of the two frames' mean-subtracted thumbnails.

    The prediction is resized to the reference's thumbnail size whatever its own size. Two flat
    frames (no structure to compare) give 1.0; a flat frame against a structured one gives 0.0.
    """
    return _correlation(*_thumbnails(pred_first_rgb, ref_first_rgb))


@dataclass(frozen=True)
class FirstFrameComparison:
    """How a prediction's first frame compares with its reference's."""

    correlation: float  # the frame as given
    orientation: str | None = None  # a key of ORIENTATIONS when the frame is the reference's turned
    turned_correlation: float | None = None  # the correlation once turned back (with ``orientation``)

    @property
    def matches(self) -> bool:
        return self.correlation >= MIN_CORRELATION and self.orientation is None

    def facts(self) -> dict[str, Any]:
        """What a run records: correlation and matches, and the orientation when the frame is turned."""
        out: dict[str, Any] = {"correlation": round(self.correlation, 4), "matches": self.matches}
        if self.orientation is not None:
            out.update(orientation=self.orientation, turned_correlation=round(float(self.turned_correlation), 4))
        return out


def compare_first_frames(pred_first_rgb: np.ndarray, ref_first_rgb: np.ndarray) -> FirstFrameComparison:
    """pred_first_rgb, ref_first_rgb: (H,W,3) uint8 RGB first frames (sizes may differ).

    The correlation of the frame as given, and the orientation (rotated 180 degrees, mirrored, upside
    down) whose turned-back frame correlates at least ``MIN_CORRELATION`` and better than the frame as
    given by more than ``ORIENTATION_MARGIN``, if any (the best such one).
    """
    pred, ref = _thumbnails(pred_first_rgb, ref_first_rgb)
    straight = _correlation(pred, ref)
    turned = {name: _correlation(pred[index], ref) for name, index in ORIENTATIONS.items()}
    name = max(turned, key=turned.__getitem__)
    if turned[name] >= MIN_CORRELATION and turned[name] > straight + ORIENTATION_MARGIN:
        return FirstFrameComparison(straight, name, turned[name])
    return FirstFrameComparison(straight)


def check_first_frame(pred_first_rgb: np.ndarray, ref_first_rgb: np.ndarray) -> tuple[bool, float]:
    """pred_first_rgb, ref_first_rgb: (H,W,3) uint8 RGB first frames (sizes may differ).

    Returns (matches, correlation): matches is True when the prediction starts from the reference's
    first frame, allowing for codecs, resizing, slight blur and exposure changes, and not rotated or
    mirrored (see the module doc); correlation is that of the frame as given.
    """
    result = compare_first_frames(pred_first_rgb, ref_first_rgb)
    return result.matches, result.correlation


def describe_reference_set(data_dir: str | Path, metadata: Mapping[str, Any] | None) -> str:
    """Names the set a reference bundle belongs to: its folder and where the bundle came from.

    An imported bundle carries ``metadata["source"]`` (dataset name, version); our renders do not.
    """
    source = (metadata or {}).get("source")
    if isinstance(source, Mapping) and source.get("dataset"):
        version = source.get("version")
        origin = f"dataset {source['dataset']}" + (f" version {version}" if version else "")
        origin += ", imported by rigidbench import"
    else:
        origin = "rendered by rigidbench render"
    return f"{data_dir} ({origin})"


def mismatch_message(pred_path: str | Path, example_id: str, data_dir: str | Path,
                     ref_metadata: Mapping[str, Any] | None, score: float, orientation: str | None = None,
                     turned_correlation: float | None = None) -> str:
    """The error for a prediction whose first frame is not its reference's: names both sets and the fix.

    data_dir: the reference split directory. With ``orientation`` (``FirstFrameComparison``), the frame is
    the reference's turned, and the message says so."""
    pred_path = Path(pred_path)
    if orientation is not None:
        turned = f"{turned_correlation:.2f} turned back, " if turned_correlation is not None else ""
        return (f"{pred_path.name}: its first frame is the first frame of reference example {example_id} in "
                f"{describe_reference_set(data_dir, ref_metadata)} {orientation} (correlation {turned}"
                f"{score:.2f} as given). The clip was generated from, or written as, a turned image; check "
                f"how the generation script reads the input image and writes the frames, then regenerate it")
    inputs = inputs_path(data_dir)
    return (f"{pred_path.name}: its first frame does not match the first frame of reference example {example_id} "
            f"in {describe_reference_set(data_dir, ref_metadata)} (correlation {score:.2f}, needs at "
            f"least {MIN_CORRELATION:.2f}). The predictions in {pred_path.parent} were probably generated from "
            f"another set's inputs (the same ids name different scenes in our rendered set and the published "
            f"one); regenerate them from this set's inputs (`rigidbench inputs --data {data_dir}` writes "
            f"{inputs}), or pass the --data they were generated from")


def read_reference_first_frame(bundle_dir: str | Path) -> np.ndarray | None:
    """(H,W,3) uint8 RGB first frame of a reference bundle (frames/00000.png, else video.mp4), or None."""
    folder = BundleFolder(Path(bundle_dir))
    png = folder.frame(0)
    if png.is_file():
        from PIL import Image

        with Image.open(png) as image:
            return np.asarray(image.convert("RGB"))
    video = folder.video
    if video.is_file():
        return read_first_frame(video)
    return None


def read_first_frame(path: str | Path) -> np.ndarray:
    """(H,W,3) uint8 RGB first decoded frame of a video file; VideoError when there is none."""
    frames = iter_video(path)
    try:
        return next(frames)[1]  # iter_video yields at least one frame or raises VideoError
    finally:
        frames.close()
