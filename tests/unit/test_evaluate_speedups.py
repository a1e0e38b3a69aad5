"""The pieces that make scoring K samples cheaper give exactly the numbers of the plain computation: each is
compared, bit for bit, with an independent straightforward version (or with itself without the shortcut)."""

from __future__ import annotations

import io

import numpy as np
import pytest

from rigidbench.evaluation import protocol, scoring
from rigidbench.metrics import MetricInputs, MetricResult
from rigidbench.metrics import appearance, depth, masks
from rigidbench.perception.gt import disparity_from_depth
from rigidbench.readouts.fits import fit_time_warp


def test_disparity_from_depth_is_one_over_depth_on_the_valid_pixels_only():
    z = np.array([[[0.5, 2.0, 99.9, 100.0], [np.inf, -np.inf, np.nan, 0.0], [-1.0, 1e-30, 3.0, 150.0]]], np.float32)
    z = np.concatenate([z, 2 * z])  # two frames
    want = np.full(z.shape, np.nan, np.float32)
    valid = np.isfinite(z) & (z > 0) & (z < 100)
    want[valid] = np.float32(1) / z[valid]
    got = disparity_from_depth(z)
    assert got.dtype == np.float32 and got.tobytes() == want.tobytes()
    assert disparity_from_depth(z.astype(np.float64)).tobytes() == want.tobytes()  # converted to float32 first
    assert disparity_from_depth(z[0, 0]).tobytes() == want[0, 0].tobytes()  # one row: any shape


def test_the_reference_part_of_depth_validity_can_be_given():
    rng = np.random.default_rng(0)
    z = rng.uniform(-5, 120, (3, 7, 9)).astype(np.float32)
    z[0, 0, :3] = (np.nan, np.inf, 0.0)
    d = rng.normal(size=(3, 7, 9)).astype(np.float32)
    d[1, 2, :4] = np.nan
    want = np.isfinite(z) & (z > 0) & (z < 100) & np.isfinite(d)
    assert np.array_equal(depth.depth_validity(d, z), want)
    ref = depth.reference_depth_validity(z)
    assert np.array_equal(ref, depth.valid_reference_depth(z))
    assert np.array_equal(depth.depth_validity(d, z, valid_ref=ref), want)
    assert np.array_equal(ref, depth.valid_reference_depth(z))  # the given part is not written into


def test_centroid_l2_with_known_reference_centroids():
    rng = np.random.default_rng(1)
    ref, gen = rng.random((4, 2, 12, 15)) < 0.2, rng.random((4, 2, 12, 15)) < 0.2
    ref[2, 1] = False  # an empty reference mask: NaN
    plain = masks.centroid_l2(ref, gen)
    given = masks.centroid_l2(ref, gen, masks.mask_centroids(ref))
    assert plain.value == given.value and plain.per_frame.tobytes() == given.per_frame.tobytes()


def test_time_warp_with_a_memo_is_the_same_fit():
    fps = 24.0
    t = np.arange(30) / fps
    ref = np.stack([0.3 * t, 0 * t, -0.5 * 9.81 * t ** 2], -1)[None]
    memo: dict = {}
    for speed in (1.0, 0.7):  # two samples against one reference
        gen = np.interp(speed * t, t, ref[0, :, 2])
        gen = np.stack([np.interp(speed * t, t, ref[0, :, 0]), 0 * t, gen], -1)[None]
        plain, shared = fit_time_warp(gen, ref, fps), fit_time_warp(gen, ref, fps, memo=memo)
        assert (plain.speed, plain.offset_s, plain.rmse_m, plain.speed_se) == (shared.speed, shared.offset_s,
                                                                                shared.rmse_m, shared.speed_se)
    assert len(memo) == 1  # one grid, used by both


def test_ssim_with_the_reference_maps_kept_is_the_same():
    rng = np.random.default_rng(2)
    ref = rng.integers(0, 256, (3, 20, 24, 3), dtype=np.uint8)
    maps: dict = {}
    for shift in (0, 5):
        gen = np.clip(ref.astype(int) + shift + rng.integers(-9, 10, ref.shape), 0, 255).astype(np.uint8)
        plain, kept = appearance.ssim(ref, gen, workers=1), appearance.ssim(ref, gen, workers=2, ref_maps=maps)
        assert plain.per_frame.tobytes() == kept.per_frame.tobytes()
    assert sorted(maps) == [0, 1, 2] and not maps[0]["sq"].flags.writeable


def test_threaded_jpeg_round_trip_is_the_frame_by_frame_one():
    from PIL import Image

    rng = np.random.default_rng(3)
    frames = rng.integers(0, 256, (5, 16, 24, 3), dtype=np.uint8)
    want = []
    for frame in frames:
        buffer = io.BytesIO()
        Image.fromarray(frame).save(buffer, format="JPEG", quality=95, subsampling=0)
        want.append(np.asarray(Image.open(io.BytesIO(buffer.getvalue())).convert("RGB")))
    assert np.array_equal(protocol.jpeg_roundtrip(frames), np.stack(want))
    assert np.array_equal(protocol.jpeg_roundtrip(frames[0]), want[0])
    own = frames.copy()  # written over, as the evaluator does with its decoded clip
    assert protocol.get_protocol(None).prepare(own, in_place=True) is own and np.array_equal(own, np.stack(want))


def test_aligning_frames_already_at_the_reference_times_can_skip_the_copy():
    from rigidbench.video import Video, align_video, reference_times

    rng = np.random.default_rng(5)
    frames = rng.integers(0, 256, (6, 8, 10, 3), dtype=np.uint8)
    ref = reference_times(5, 24.0)
    on_time = Video(frames=frames, times_s=reference_times(6, 24.0))
    view = align_video(on_time, ref, copy=False)
    assert np.shares_memory(view, frames) and np.array_equal(view, align_video(on_time, ref))
    late = Video(frames=frames, times_s=reference_times(6, 24.0) + 0.01)  # blended: a new array, as before
    assert not np.shares_memory(align_video(late, ref, copy=False), frames)
    assert np.array_equal(align_video(late, ref, copy=False), align_video(late, ref))


def _inputs(t=3, h=12, w=16):
    rng = np.random.default_rng(4)
    rgb = rng.integers(0, 256, (t, h, w, 3), dtype=np.uint8)
    m = rng.random((t, 1, h, w)) < 0.3
    tracks = rng.uniform(2, 10, (4, t, 2))
    vis = np.ones((4, t), bool)
    z = rng.uniform(1, 5, (t, h, w)).astype(np.float32)
    return MetricInputs(ref_rgb=rgb, gen_rgb=rgb[::-1].copy(), ref_masks=m, gen_masks=m[::-1].copy(),
                        ref_tracks=tracks, gen_tracks=tracks + 0.5, ref_visibility=vis, gen_visibility=vis,
                        track_actor=np.zeros(4, int), ref_depth_m=z, gen_disparity=1 / z,
                        K=np.diag([16.0, 16.0, 1.0]), camera_to_world=np.eye(4),
                        actor_positions_m=rng.normal(size=(1, t, 3)), ref_points_m=np.zeros((4, t, 3)),
                        bg_tracks=np.zeros((0, t, 2)), bg_confidence=np.zeros((0, t)))


@pytest.mark.parametrize("cores", [1, 2])
def test_score_inputs_on_a_background_thread_keeps_values_and_order(monkeypatch, cores):
    monkeypatch.setattr(scoring, "usable_cores", lambda *a: cores)
    seen = {}

    def after(scores):
        seen.update(scores)

    scores = scoring.score_inputs(_inputs(), after=after)
    plain = {name: info.load()(_inputs()) for name, info in scoring.METRICS.items()}
    assert list(scores) == list(plain)
    assert "ssim" not in seen and set(seen) == set(plain) - {"ssim"}  # `after` runs before SSIM is awaited
    for name, result in scores.items():
        if result is None:
            assert plain[name] is None
        else:
            assert isinstance(result, MetricResult) and np.array_equal(result.value, plain[name].value, equal_nan=True)
