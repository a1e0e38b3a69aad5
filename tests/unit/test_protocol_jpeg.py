"""The protocols' JPEG step is PIL's JPEG at quality 95 with 4:4:4 chroma, exactly: a frame with fine colour
detail comes back byte for byte as PIL's own encode and decode at those settings, and not as 4:2:0 chroma or
another quality would return it (an SSIM range cannot tell those apart)."""

from __future__ import annotations

import io

import numpy as np
import pytest
from PIL import Image, JpegImagePlugin

from rigidbench.evaluation.protocol import PROTOCOLS, jpeg_roundtrip


def colour_detail(seed: int, h: int = 48, w: int = 64) -> np.ndarray:
    """A frame whose colour changes every pixel (red/blue columns over a smooth ramp): 4:2:0 halves the
    chroma resolution and visibly changes it."""
    rng = np.random.default_rng(seed)
    y, x = np.mgrid[0:h, 0:w]
    frame = np.stack([x * 255 // w, y * 255 // h, np.full((h, w), 128)], -1).astype(np.int32)
    frame[:, ::2, 0] = 230
    frame[:, 1::2, 2] = 230
    frame += rng.integers(-8, 9, frame.shape)
    return np.clip(frame, 0, 255).astype(np.uint8)


def pil_roundtrip(frame: np.ndarray, **options) -> tuple[np.ndarray, Image.Image]:
    buffer = io.BytesIO()
    Image.fromarray(frame).save(buffer, format="JPEG", **options)
    buffer.seek(0)
    im = Image.open(buffer)
    return np.asarray(im.convert("RGB")), im


def test_the_round_trip_is_pils_quality_95_with_444_chroma_exactly():
    frames = np.stack([colour_detail(seed) for seed in range(3)])
    out = jpeg_roundtrip(frames)
    assert out.shape == frames.shape and out.dtype == np.uint8
    for t, frame in enumerate(frames):
        expected, im = pil_roundtrip(frame, quality=95, subsampling=0)
        assert JpegImagePlugin.get_sampling(im) == 0  # the reference itself is 4:4:4
        assert np.array_equal(out[t], expected)
        assert not np.array_equal(out[t], frame)  # it is lossy: the step really ran
    assert np.array_equal(jpeg_roundtrip(frames[0]), out[0])  # one (H,W,3) frame as in a batch


@pytest.mark.parametrize("options", [{"quality": 95, "subsampling": 2}, {"quality": 95, "subsampling": 1},
                                     {"quality": 95}, {"quality": 90, "subsampling": 0}, {"quality": 75}])
def test_other_chroma_subsampling_or_quality_would_be_told_apart(options):
    frame = colour_detail(0)
    other, _ = pil_roundtrip(frame, **options)
    ours = jpeg_roundtrip(frame)
    assert not np.array_equal(ours, other)
    if options.get("subsampling", 2) != 0:  # PIL's default at these qualities is 4:2:0
        # subsampled chroma loses the per-pixel colour columns: a large error where 4:4:4 keeps them
        err = np.abs(other.astype(int) - frame).mean()
        assert err > 3 * np.abs(ours.astype(int) - frame).mean()


@pytest.mark.parametrize("name", ["rigidbench-v1", "paper-rules"])
def test_the_jpeg_protocols_prepare_frames_with_that_round_trip(name):
    protocol = PROTOCOLS[name]
    frames = np.stack([colour_detail(seed) for seed in range(2)])
    assert protocol.jpeg_quality == 95
    prepared = protocol.prepare(frames)
    for t, frame in enumerate(frames):
        assert np.array_equal(prepared[t], pil_roundtrip(frame, quality=95, subsampling=0)[0])


def test_the_lossless_protocol_leaves_frames_as_decoded():
    frames = np.stack([colour_detail(seed) for seed in range(2)])
    assert PROTOCOLS["lossless"].prepare(frames) is frames
