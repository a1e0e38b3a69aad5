"""Decoding only up to the reference length (``read_video(until_s=...)``) and antialiased resizing.

The published evaluation resized generated frames with PIL's Lanczos (RigidBench release,
``eval/prepare.py``, ``extract_frames``), which widens its kernel when shrinking; OpenCV's
INTER_LANCZOS4 does not, so a 1080p output shrunk to 1280x704 aliases fine texture into moire.
"""

from __future__ import annotations

import numpy as np
import pytest

from rigidbench.video import (align_video, frames_until, read_video, reference_times, resize_frames,
                              write_video)

pytest.importorskip("av")
cv2 = pytest.importorskip("cv2")
Image = pytest.importorskip("PIL.Image")


def ramp_frames(n: int, size=(64, 36)) -> np.ndarray:
    """(n,H,W,3) uint8 frames whose brightness encodes the frame index (10 levels per frame)."""
    w, h = size
    values = (20 + 10 * np.arange(n)).clip(0, 255).astype(np.uint8)
    return np.broadcast_to(values[:, None, None, None], (n, h, w, 3)).copy()


# -- read_video(until_s) -----------------------------------------------------------------------------

@pytest.mark.parametrize("fps, until_s, expected", [
    (24.0, 0.11, 4),        # between 2/24 and 3/24: decodes up to 3/24 s, the frame after it
    (24.0, 0.125, 4),       # exactly on frame 3: that frame, nothing after it
    (16.0, 4 / 24, 4),      # a 5-frame 24 Hz reference against a 16 Hz clip: 0 .. 3/16 s
    (16.0, 2.0, 33),        # the paper's 2 s at 16 Hz
    (24.0, 10.0, 60),       # past the end: the whole clip
])
def test_read_video_until_decodes_the_frames_up_to_the_closing_one(tmp_path, fps, until_s, expected):
    n = 60 if fps == 24.0 else 40
    path = write_video(tmp_path / "clip.mp4", ramp_frames(n), fps=fps)
    full = read_video(path)
    cut = read_video(path, until_s=until_s)
    assert cut.n_frames == expected == frames_until(full.times_s, until_s)
    np.testing.assert_array_equal(cut.times_s, full.times_s[:expected])
    np.testing.assert_array_equal(cut.frames, full.frames[:expected])
    assert (cut.times_s[:-1] < until_s).all()
    assert cut.times_s[-1] >= until_s - 1e-6 or expected == n


def test_alignment_of_a_clip_decoded_until_the_reference_end_equals_the_whole_clips(tmp_path):
    ref = reference_times(49, 24.0)
    path = write_video(tmp_path / "cosmos.mp4", ramp_frames(40), fps=16.0)  # 2.44 s at 16 Hz
    cut = read_video(path, until_s=ref[-1])
    assert cut.n_frames == 33  # 0 .. 2.0 s
    np.testing.assert_array_equal(align_video(cut, ref), align_video(read_video(path), ref))
    path = write_video(tmp_path / "veo.mp4", ramp_frames(97, size=(32, 18)), fps=24.0)
    cut = read_video(path, until_s=ref[-1])
    assert cut.n_frames == 49
    np.testing.assert_array_equal(align_video(cut, ref), align_video(read_video(path), ref))


def test_read_video_until_applies_to_overridden_and_png_timestamps(tmp_path):
    path = write_video(tmp_path / "clip.mp4", ramp_frames(20), fps=24.0)
    video = read_video(path, fps=12.0, until_s=0.25)  # times k / 12: 0, 1/12, 2/12, 3/12
    assert video.n_frames == 4
    np.testing.assert_allclose(video.times_s, np.arange(4) / 12.0)
    folder = tmp_path / "frames"
    folder.mkdir()
    frames = ramp_frames(10)
    for k, frame in enumerate(frames):
        cv2.imwrite(str(folder / f"{k:05d}.png"), frame[..., ::-1])
    video = read_video(folder, fps=24.0, until_s=0.1)  # 0, 1/24, 2/24, 3/24
    assert video.n_frames == 4
    np.testing.assert_array_equal(video.frames, frames[:4])
    assert read_video(folder, fps=24.0, until_s=5.0).n_frames == 10


def test_frames_until_by_hand():
    times = np.arange(10) / 16.0
    assert frames_until(times, 0.0) == 1
    assert frames_until(times, 0.0625) == 2
    assert frames_until(times, 0.07) == 3
    assert frames_until(times, 99.0) == 10


# -- antialiased resizing ---------------------------------------------------------------------------

def stripes(height: int, width: int, period_px: float) -> np.ndarray:
    """(H,W,3) uint8 vertical cosine stripes around 127.5, amplitude 100."""
    x = np.arange(width)
    row = 127.5 + 100 * np.cos(2 * np.pi * x / period_px)
    return np.repeat(np.rint(row).astype(np.uint8)[None, :, None], height, 0).repeat(3, 2)


def moire_energy(image: np.ndarray) -> float:
    """RMS of an image's deviation from its mean (what aliasing leaves of detail that cannot be shown)."""
    gray = image.astype(np.float64).mean(axis=-1)
    return float(np.sqrt(np.mean((gray - gray.mean()) ** 2)))


@pytest.mark.parametrize("period_px", [2.0, 3.0, 2.4])
def test_shrinking_4x_does_not_alias_fine_stripes(period_px):
    src = stripes(384, 384, period_px)
    out = resize_frames(src, (96, 96))
    assert out.shape == (96, 96, 3) and out.dtype == np.uint8
    assert abs(out.astype(np.float64).mean() - src.astype(np.float64).mean()) < 1.0  # mean preserved
    assert moire_energy(out) < 2.0  # detail beyond the new Nyquist is removed, not folded down
    spectrum = np.abs(np.fft.rfft(out[..., 0].astype(np.float64).mean(axis=0) - out[..., 0].mean()))
    assert spectrum.max() / 96 < 1.0
    if period_px == 3.0:  # OpenCV's Lanczos keeps the stripes as a full-contrast moire
        assert moire_energy(cv2.resize(src, (96, 96), interpolation=cv2.INTER_LANCZOS4)) > 30


def test_a_one_pixel_checkerboard_shrinks_to_its_mean():
    board = ((np.indices((256, 256)).sum(axis=0) % 2) * 255).astype(np.uint8)[..., None].repeat(3, 2)
    out = resize_frames(board, (64, 64))
    assert np.abs(out.astype(np.float64) - 127.5).max() <= 1.0


def test_resize_is_pils_lanczos_exactly_at_the_papers_sizes():
    rng = np.random.default_rng(0)
    frame = rng.integers(0, 256, (1080, 1920, 3), dtype=np.uint8)
    out = resize_frames(frame[None], (1280, 704))
    assert out.shape == (1, 704, 1280, 3)
    expected = np.asarray(Image.fromarray(frame).resize((1280, 704), Image.Resampling.LANCZOS))
    np.testing.assert_array_equal(out[0], expected)


def test_enlarging_stays_sensible():
    x = np.linspace(0, 255, 32)
    ramp = np.repeat(np.rint(x).astype(np.uint8)[None, :, None], 18, 0).repeat(3, 2)
    up = resize_frames(ramp, (64, 36))
    assert up.shape == (36, 64, 3)
    # Interior of a linear ramp stays linear (Lanczos reproduces linear functions away from the borders).
    expected = np.interp((np.arange(64) + 0.5) / 2 - 0.5, np.arange(32), x)
    np.testing.assert_allclose(up[18, 6:-6, 0], expected[6:-6], atol=1.5)
    constant = np.full((18, 32, 3), 77, np.uint8)
    assert (resize_frames(constant, (64, 36)) == 77).all()
    frames = np.stack([ramp, ramp[:, ::-1]])
    both = resize_frames(frames, (64, 36))
    np.testing.assert_array_equal(both[0], up)
    np.testing.assert_array_equal(both[1], resize_frames(ramp[:, ::-1].copy(), (64, 36)))


def test_non_uint8_frames_are_antialiased_too():
    src = stripes(384, 384, 3.0).astype(np.float32)
    out = resize_frames(src, (96, 96))
    assert out.shape == (96, 96, 3) and out.dtype == np.float32
    assert abs(out.mean() - src.mean()) < 1.0 and moire_energy(out) < 2.0
