"""Video ingestion, encoding and temporal alignment (paper appendix B.1)."""

from __future__ import annotations

import os

import numpy as np
import pytest

from rigidbench.video import (Video, VideoError, align_video, aligned_length, interpolate_linear,
                              interpolate_nearest, probe_video, read_aligned, read_video, reference_times,
                              resize_frames, resize_maps, write_video)

pytest.importorskip("av")
pytest.importorskip("cv2")

REF_TIMES = reference_times(49, 24.0)


# ---------------------------------------------------------------------------------------------
# Synthetic clips whose content encodes time
# ---------------------------------------------------------------------------------------------

def ramp_value(t_s):
    """Uniform brightness of the ramp clip at time t_s: 20 + 100 t, saturating at 255."""
    return np.clip(20.0 + 100.0 * np.asarray(t_s, dtype=np.float64), 0.0, 255.0)


def ramp_frames(times_s, size=(64, 36)) -> np.ndarray:
    """(T,H,W,3) uint8 uniform frames, brightness ramp_value(t) rounded."""
    width, height = size
    values = np.rint(ramp_value(times_s)).astype(np.uint8)
    return np.broadcast_to(values[:, None, None, None], (len(values), height, width, 3)).copy()


SQUARE_SIDE_PX = 10.0
SQUARE_SPEED_PX_S = 25.0


def square_center_x(t_s):
    """Analytic x of the square's centre (pixel c spans [c, c+1)) at time t_s."""
    return 14.0 + SQUARE_SPEED_PX_S * np.asarray(t_s, dtype=np.float64)


def square_frames(times_s, size=(128, 72)) -> np.ndarray:
    """(T,H,W,3) uint8: a bright anti-aliased square (exact pixel coverage) moving right at constant speed."""
    width, height = size
    edges_x = np.arange(width + 1, dtype=np.float64)
    edges_y = np.arange(height + 1, dtype=np.float64)
    y0 = height / 2 - SQUARE_SIDE_PX / 2
    cover_y = np.clip(np.minimum(edges_y[1:], y0 + SQUARE_SIDE_PX) - np.maximum(edges_y[:-1], y0), 0, 1)
    frames = np.empty((len(times_s), height, width, 3), dtype=np.uint8)
    for k, t in enumerate(times_s):
        x0 = square_center_x(t) - SQUARE_SIDE_PX / 2
        cover_x = np.clip(np.minimum(edges_x[1:], x0 + SQUARE_SIDE_PX) - np.maximum(edges_x[:-1], x0), 0, 1)
        gray = 30.0 + 200.0 * cover_y[:, None] * cover_x[None, :]
        frames[k] = np.rint(gray).astype(np.uint8)[..., None]
    return frames


def centroid_x(frame: np.ndarray) -> float:
    """frame (H,W,3) uint8. Returns the intensity-weighted x centre of the bright square (pixel c at c + 0.5)."""
    gray = frame.astype(np.float64).mean(axis=-1)
    weights = np.clip(gray - 30.0 - 3.0, 0.0, None)  # drop codec noise around the background level
    xs = np.arange(frame.shape[1]) + 0.5
    return float((weights.sum(axis=0) * xs).sum() / weights.sum())


def fps_times(n_frames: int, fps: float) -> np.ndarray:
    return np.arange(n_frames) / fps


# ---------------------------------------------------------------------------------------------
# Timestamps and interpolation (no codec)
# ---------------------------------------------------------------------------------------------

def test_reference_times_are_k_over_fps():
    times = reference_times(49)
    assert times.shape == (49,) and times.dtype == np.float64
    assert times[0] == 0.0 and times[-1] == 2.0
    np.testing.assert_array_equal(reference_times(3, 24.0), [0.0, 1 / 24, 2 / 24])
    with pytest.raises(ValueError):
        reference_times(5, fps=0.0)


@pytest.mark.parametrize("gen_times, expected", [
    (fps_times(33, 16.0), 49),   # Cosmos: 33 frames at 16 Hz end exactly at 2.0 s
    (fps_times(97, 24.0), 49),   # Veo: 4 s at 24 Hz, cut at the reference length
    (fps_times(25, 24.0), 25),   # a 1.0 s clip
    (fps_times(17, 16.0), 25),   # also 1.0 s
    (fps_times(48, 24.0), 48),   # one frame short
    (np.array([0.0, 0.5, 1.0 - 1e-7]), 25),  # within the tolerance of t = 1.0
    (np.array([0.0, 0.5, 1.0 - 3e-4]), 25),  # 0.3 ms early (ms-rounded VFR times): still covers t = 1.0
    (np.array([0.0, 0.5, 1.0 - 0.02]), 25),  # within half a reference frame (1/48 s): the nearest frame
    (np.array([0.0, 0.5, 1.0 - 0.022]), 24),  # beyond it: t = 1.0 is discarded
    (np.array([0.0]), 1),
    (np.array([]), 0),
])
def test_aligned_length_stops_at_the_shorter_sequence(gen_times, expected):
    assert aligned_length(gen_times, REF_TIMES) == expected


def test_interpolate_linear_matches_hand_values():
    values = np.array([0.0, 10.0, 30.0])
    out = interpolate_linear(values, np.array([0.0, 1.0, 3.0]), np.array([0.0, 0.5, 2.0, 3.0]))
    np.testing.assert_allclose(out, [0.0, 5.0, 20.0, 30.0])


def test_interpolate_linear_on_track_axis_and_dtypes():
    # Tracks (P,T,2): point 0 moves +1 px/frame in x at 12 Hz; sample at 24 Hz times.
    tracks = np.zeros((2, 3, 2), dtype=np.float32)
    tracks[0, :, 0] = [0.0, 1.0, 2.0]
    tracks[1, :, 1] = [4.0, 4.0, 10.0]
    out = interpolate_linear(tracks, fps_times(3, 12.0), fps_times(5, 24.0), axis=1)
    assert out.shape == (2, 5, 2) and out.dtype == np.float32
    np.testing.assert_allclose(out[0, :, 0], [0.0, 0.5, 1.0, 1.5, 2.0])
    np.testing.assert_allclose(out[1, :, 1], [4.0, 4.0, 4.0, 7.0, 10.0])
    ints = interpolate_linear(np.array([0, 3]), np.array([0.0, 1.0]), np.array([1 / 3]))
    assert ints.dtype == np.float64
    np.testing.assert_allclose(ints, [1.0])


def test_interpolate_linear_refuses_to_extrapolate():
    with pytest.raises(ValueError, match="aligned_length"):  # more than half a frame past the last sample
        interpolate_linear(np.zeros(3), fps_times(3, 24.0), np.array([0.0, 0.11]))
    with pytest.raises(ValueError):
        interpolate_linear(np.zeros(3), np.array([0.0, 0.2, 0.1]), np.array([0.05]))


def test_interpolate_nearest_16_to_24_hz_keeps_bool():
    # 16 Hz frames at 0, 62.5, 125 ms; 24 Hz targets 0, 41.7, 83.3, 125 ms -> nearest 0, 1, 1, 2.
    masks = np.zeros((3, 2, 2), dtype=bool)
    masks[0, 0, 0] = masks[1, 0, 1] = masks[2, 1, 1] = True
    out = interpolate_nearest(masks, fps_times(3, 16.0), fps_times(4, 24.0))
    assert out.dtype == np.bool_
    np.testing.assert_array_equal(out, masks[[0, 1, 1, 2]])
    # Exact midpoint ties go to the earlier frame; visibility (P,T) on axis 1.
    vis = np.array([[True, False]])
    np.testing.assert_array_equal(interpolate_nearest(vis, np.array([0.0, 1.0]), np.array([0.5, 0.51]), axis=1),
                                  [[True, False]])


def test_video_at_linear_rounds_half_to_even_and_nearest():
    frames = np.zeros((2, 1, 3, 3), dtype=np.uint8)
    frames[0, 0] = [[0, 1, 100], [0, 0, 0], [0, 0, 0]]
    frames[1, 0] = [[1, 2, 200], [0, 0, 0], [0, 0, 0]]
    video = Video(frames, np.array([0.0, 1.0]), fps_nominal=1.0)
    mid = video.at(np.array([0.5]))[0, 0, 0]
    np.testing.assert_array_equal(mid, [0, 2, 150])  # 0.5 -> 0 and 1.5 -> 2 (half to even)
    quarter = video.at(np.array([0.25]))[0, 0, 0]
    np.testing.assert_array_equal(quarter, [0, 1, 125])
    np.testing.assert_array_equal(video.at(np.array([0.2, 0.9]), mode="nearest"), frames[[0, 1]])
    with pytest.raises(ValueError):
        video.at(np.array([1.5]))
    with pytest.raises(ValueError):
        video.at(np.array([0.5]), mode="cubic")


def test_video_rejects_bad_inputs():
    with pytest.raises(ValueError):
        Video(np.zeros((2, 4, 4, 3), dtype=np.float32), np.array([0.0, 1.0]))
    with pytest.raises(ValueError):
        Video(np.zeros((2, 4, 4, 3), dtype=np.uint8), np.array([0.0, 0.0]))
    video = Video(np.zeros((3, 4, 6, 3), dtype=np.uint8), np.array([0.0, 0.5, 2.0]))
    assert video.duration_s == 2.0 and video.size == (6, 4) and video.fps_measured == 1.0


def test_align_video_in_memory_is_exact_at_shared_timestamps():
    rng = np.random.default_rng(0)
    frames = rng.integers(0, 256, size=(60, 6, 8, 3), dtype=np.uint8)
    aligned = align_video(Video(frames, fps_times(60, 24.0)), REF_TIMES)
    np.testing.assert_array_equal(aligned, frames[:49])
    # 12 Hz: even reference frames are generated frames, odd ones the rounded mean of the two neighbours.
    aligned12 = align_video(Video(frames[:25], fps_times(25, 12.0)), REF_TIMES)
    assert aligned12.shape == (49, 6, 8, 3)
    np.testing.assert_array_equal(aligned12[0::2], frames[:25])
    mean = (frames[:24].astype(np.float64) + frames[1:25]) / 2
    np.testing.assert_array_equal(aligned12[1::2], np.rint(mean).astype(np.uint8))


# ---------------------------------------------------------------------------------------------
# Resizing
# ---------------------------------------------------------------------------------------------

def test_resize_frames_lanczos_shapes_and_constant_image():
    frames = np.full((2, 36, 64, 3), 77, dtype=np.uint8)
    out = resize_frames(frames, (32, 18))
    assert out.shape == (2, 18, 32, 3) and out.dtype == np.uint8
    assert np.all(out == 77)
    assert resize_frames(frames, (64, 36)) is frames
    assert resize_frames(frames[0], (128, 72)).shape == (72, 128, 3)


def test_resize_maps_bilinear_keeps_a_linear_gradient():
    # Disparity equal to the x coordinate of each pixel centre; halving the width keeps it linear.
    xs = np.arange(64, dtype=np.float32) + 0.5
    maps = np.broadcast_to(xs, (3, 36, 64)).copy()
    out = resize_maps(maps, (32, 18))
    assert out.shape == (3, 18, 32) and out.dtype == np.float32
    expected = (np.arange(32) + 0.5) * 2.0
    np.testing.assert_allclose(out[1, 5], expected, atol=1e-4)
    masks = np.zeros((2, 4, 4), dtype=bool)
    masks[:, :2, :2] = True
    small = resize_maps(masks, (2, 2), method="nearest")
    assert small.dtype == np.bool_
    np.testing.assert_array_equal(small[0], [[True, False], [False, False]])
    with pytest.raises(ValueError):
        resize_maps(masks, (2, 2))


# ---------------------------------------------------------------------------------------------
# Encoding and decoding
# ---------------------------------------------------------------------------------------------

@pytest.mark.parametrize("suffix", [".mp4", ".mkv", ".mov", ".webm"])
def test_write_read_roundtrip(tmp_path, suffix):
    frames = square_frames(fps_times(30, 24.0), size=(64, 36))
    path = write_video(tmp_path / f"clip{suffix}", frames, fps=24)
    video = read_video(path)
    assert video.frames.shape == frames.shape and video.frames.dtype == np.uint8
    np.testing.assert_allclose(video.times_s, fps_times(30, 24.0), atol=1e-9)
    assert video.fps_nominal == pytest.approx(24.0)
    assert np.abs(video.frames.astype(int) - frames).mean() < 2.0
    info = probe_video(path)
    assert (info.width, info.height, info.n_frames) == (64, 36, 30)
    np.testing.assert_allclose(info.times_s, video.times_s, atol=1e-9)
    assert sorted(os.listdir(tmp_path)) == [f"clip{suffix}"]  # no temporary left behind


def test_write_video_rejects_odd_sizes_and_leaves_nothing(tmp_path):
    with pytest.raises(ValueError, match="even"):
        write_video(tmp_path / "odd.mp4", np.zeros((3, 35, 64, 3), dtype=np.uint8))
    with pytest.raises(ValueError):
        write_video(tmp_path / "float.mp4", np.zeros((3, 36, 64, 3), dtype=np.float32))
    assert os.listdir(tmp_path) == []


def test_write_video_replaces_existing_file(tmp_path):
    path = tmp_path / "clip.mp4"
    write_video(path, ramp_frames(fps_times(5, 24.0)))
    write_video(path, ramp_frames(fps_times(9, 24.0)))
    assert read_video(path).n_frames == 9


def test_read_gif_uses_real_frame_delays(tmp_path):
    from PIL import Image

    images = [Image.fromarray(np.full((36, 64, 3), 40 * i, dtype=np.uint8)) for i in range(4)]
    images[0].save(tmp_path / "a.gif", save_all=True, append_images=images[1:], duration=[40, 60, 100, 40], loop=0)
    video = read_video(tmp_path / "a.gif")
    np.testing.assert_allclose(video.times_s, [0.0, 0.04, 0.10, 0.20], atol=1e-9)
    np.testing.assert_array_equal(video.frames[:, 10, 10, 0], [0, 40, 80, 120])


def test_read_png_directory_needs_fps(tmp_path):
    import cv2

    frames = square_frames(fps_times(4, 24.0), size=(64, 36))
    frames[..., 0] = 0  # make RGB order observable
    for k, frame in enumerate(frames):
        cv2.imwrite(str(tmp_path / f"{k:04d}.png"), frame[..., ::-1])
    video = read_video(tmp_path, fps=24.0)
    np.testing.assert_array_equal(video.frames, frames)
    np.testing.assert_allclose(video.times_s, fps_times(4, 24.0))
    with pytest.raises(VideoError, match="fps"):
        read_video(tmp_path)


def test_read_video_errors_name_the_file(tmp_path):
    with pytest.raises(VideoError, match="not found") as missing:
        read_video(tmp_path / "nope.mp4")
    assert missing.value.path == tmp_path / "nope.mp4"
    (tmp_path / "empty.mp4").write_bytes(b"")
    with pytest.raises(VideoError, match="empty"):
        read_video(tmp_path / "empty.mp4")
    (tmp_path / "noise.mp4").write_bytes(np.random.default_rng(1).bytes(4096))
    with pytest.raises(VideoError, match="noise.mp4"):
        read_video(tmp_path / "noise.mp4")
    with pytest.raises(VideoError):
        probe_video(tmp_path / "noise.mp4")


def test_read_video_until_stops_after_the_needed_frame(tmp_path):
    path = write_video(tmp_path / "veo.mp4", ramp_frames(fps_times(97, 24.0)), fps=24)
    video = read_video(path, until_s=1.0)
    assert video.n_frames == 25 and video.times_s[-1] == pytest.approx(1.0)


# ---------------------------------------------------------------------------------------------
# Temporal alignment through a real codec
# ---------------------------------------------------------------------------------------------

@pytest.mark.parametrize("n_frames, fps, expected", [
    (33, 16.0, 49),   # Cosmos-like: 2.0 s at 16 Hz, resampled to 24 Hz
    (97, 24.0, 49),   # Veo-like: 4 s at 24 Hz, first 49 frames
    (25, 24.0, 25),   # a 1.0 s clip stops scoring at t = 1.0 s
    (17, 16.0, 25),
])
def test_align_ramp_video_matches_content_at_reference_times(tmp_path, n_frames, fps, expected):
    gen_times = fps_times(n_frames, fps)
    path = write_video(tmp_path / "ramp.mp4", ramp_frames(gen_times), fps=fps)
    frames, times = read_aligned(path, REF_TIMES, size=(32, 18))
    assert frames.shape == (expected, 18, 32, 3)
    np.testing.assert_array_equal(times, REF_TIMES[:expected])
    brightness = frames.reshape(expected, -1).mean(axis=1)
    # Content check: the analytic ramp within codec tolerance (limited-range YUV costs up to
    # 1 level, integer content 0.5 more).
    np.testing.assert_allclose(brightness, ramp_value(REF_TIMES[:expected]), atol=2.0)
    # Timing check, free of codec bias: blending the decoded frames at the written times k / fps
    # (np.interp, independent of the code under test) agrees up to the final rounding. At 100
    # levels/s a slip of a quarter of a 24 Hz frame (about 1 level) would already exceed this.
    decoded = read_video(path).frames.reshape(n_frames, -1).mean(axis=1)
    np.testing.assert_allclose(brightness, np.interp(REF_TIMES[:expected], gen_times, decoded), atol=0.5 + 1e-6)


@pytest.mark.parametrize("n_frames, fps", [(33, 16.0), (97, 24.0)])
def test_align_moving_square_tracks_analytic_position(tmp_path, n_frames, fps):
    path = write_video(tmp_path / "square.mp4", square_frames(fps_times(n_frames, fps)), fps=fps, crf=12)
    video = read_video(path)
    aligned = align_video(video, REF_TIMES)
    assert aligned.shape == (49, 72, 128, 3)
    xs = np.array([centroid_x(frame) for frame in aligned])
    np.testing.assert_allclose(xs, square_center_x(REF_TIMES), atol=0.25)
    # Lanczos to half size halves the coordinates (pixel edges at integers).
    half = align_video(video, REF_TIMES, size=(64, 36))
    xs_half = np.array([centroid_x(frame) for frame in half])
    np.testing.assert_allclose(xs_half, square_center_x(REF_TIMES) / 2, atol=0.2)


def test_align_variable_frame_rate_uses_real_timestamps(tmp_path):
    # Ten frames 0.1 s apart, then 0.025 s apart up to 2.1 s: a uniform-rate reading would be far off.
    times = np.concatenate([np.arange(10) * 0.1, 1.0 + np.arange(45) * 0.025])
    path = write_video(tmp_path / "vfr.mp4", square_frames(times), fps=24, times_s=times, crf=12)
    video = read_video(path)
    np.testing.assert_allclose(video.times_s, times, atol=1e-6)
    np.testing.assert_allclose(probe_video(path).times_s, times, atol=1e-6)
    aligned = align_video(video, REF_TIMES)
    assert len(aligned) == 49
    xs = np.array([centroid_x(frame) for frame in aligned])
    np.testing.assert_allclose(xs, square_center_x(REF_TIMES), atol=0.25)
    # A VFR clip that ends before 2.0 s is scored only up to its last frame.
    short = write_video(tmp_path / "vfr_short.mp4", square_frames(times[:20]), times_s=times[:20])
    last_s = times[19]  # 1.25 s -> reference frames 0..30
    assert len(read_aligned(short, REF_TIMES, size=(128, 72))[0]) == int(np.floor(last_s * 24 + 1e-9)) + 1


def test_streaming_read_aligned_equals_decode_then_align(tmp_path):
    path = write_video(tmp_path / "c.mp4", square_frames(fps_times(33, 16.0)), fps=16)
    streamed, times = read_aligned(path, REF_TIMES, size=(64, 36))
    np.testing.assert_array_equal(streamed, align_video(read_video(path), REF_TIMES, size=(64, 36)))
    assert len(times) == 49
