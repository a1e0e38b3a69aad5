"""One test per edge-case rule of docs/metrics.md ("Edge cases"), against hand-computed values.

1. IdDrift border patch: the feature network sees the part of the patch inside the image,
   resized on its own to 224 x 224 (no zero padding).
2. Half-pixel track centres: patch placement rounds half to even.
3. Non-finite positions flagged visible: not visible (ATE, ATE-3D, IdDrift, BGDrift alike).
4. ATE-3D generated points outside the image: excluded (no clamped border depth).
5. ATE-3D with no actor moving more than 1 cm: NaN, without a warning or an exception.
"""

import math
import warnings

import numpy as np
import pytest

from rigidbench.metrics.background import bgdrift
from rigidbench.metrics.common import finite_and_visible, inside_image
from rigidbench.metrics.depth import ate3d
from rigidbench.metrics.identity import (IMAGENET_MEAN, IMAGENET_STD, extract_patches, iddrift, patch_is_valid,
                                         patch_origins)
from rigidbench.metrics.tracks import ate

torch = pytest.importorskip("torch")
pytest.importorskip("cv2")

H, W = 160, 320
RGB = [0, 1, 2]


def normalised_input(value, channel):
    """What the feature network sees for a pixel value in [0, 255] of a channel (or values of channels)."""
    mean, std = np.asarray(IMAGENET_MEAN)[channel], np.asarray(IMAGENET_STD)[channel]
    return (np.asarray(value, float) / 255 - mean) / std


def stretched_ramp(n):
    """A crop whose pixel k holds the value k (k = 0..n-1), resized to 224 with half-pixel
    centres: output pixel j samples source position (j + 0.5) n / 224 - 0.5, held at the edges,
    and a linear ramp interpolates to that position itself."""
    return np.clip((np.arange(224) + 0.5) * n / 224 - 0.5, 0, n - 1)


def recording_features():
    """A stand-in feature network: returns the per-channel mean and keeps every input it saw."""
    seen = []

    def features(x):
        seen.append(x.clone())
        return x.mean(dim=(2, 3))

    return features, seen


# ------------------------------------------------------------------ 1. border patch: crop and resize


def test_border_patch_feature_input_is_the_inside_crop_resized():
    # Channel 0 holds the column, channel 1 the row, channel 2 a constant 90.
    rows, cols = np.mgrid[0:H, 0:W]
    frame = np.stack([np.minimum(cols, 255), rows, np.full((H, W), 90)], axis=-1).astype(np.uint8)
    rgb = np.stack([frame, frame])
    # Centre (8, 10): the patch requests columns -24..39 and rows -22..41; inside are columns
    # 0..39 (40 >= 32) and rows 0..41 (42 >= 32), so it is kept and the crop is 42 x 40.
    tracks = np.array([[[8.0, 10.0], [8.0, 10.0]]])
    vis = np.ones((1, 2), bool)
    features, seen = recording_features()
    r = iddrift(rgb, rgb.copy(), tracks, tracks.copy(), vis, vis, np.array([0]), features)
    assert r.value == pytest.approx(0.0, abs=1e-6)
    assert len(seen) == 2  # reference and generated patch of the one pair (frame 1)
    for x in seen:
        x = x.numpy()
        assert x.shape == (1, 3, 224, 224)
        # columns stretch 40 -> 224 along the width, rows 42 -> 224 along the height
        np.testing.assert_allclose(x[0, 0], np.broadcast_to(normalised_input(stretched_ramp(40), 0), (224, 224)),
                                   atol=1e-5)
        np.testing.assert_allclose(x[0, 1], np.broadcast_to(normalised_input(stretched_ramp(42), 1)[:, None],
                                                            (224, 224)), atol=1e-5)
        # no black padding anywhere: the constant channel stays constant
        np.testing.assert_allclose(x[0, 2], normalised_input(90, 2), atol=1e-5)


def test_border_crop_is_compared_to_the_border_crop_of_the_other_clip():
    # Reference grey; generated frame black outside the first 40 columns, red inside. The patch
    # centred at (8, 80) only ever sees the red strip, so with the mean-colour feature the
    # similarity is that of grey and pure red: zero padding would have mixed black into it.
    ref = np.full((2, H, W, 3), 128, np.uint8)
    gen = np.zeros((2, H, W, 3), np.uint8)
    gen[:, :, :40] = (200, 40, 40)
    tracks = np.full((1, 2, 2), [8.0, 80.0])
    vis = np.ones((1, 2), bool)
    r = iddrift(ref, gen, tracks, tracks.copy(), vis, vis, np.array([0]), lambda x: x.mean(dim=(2, 3)))
    grey = normalised_input([128] * 3, RGB)
    red = normalised_input([200, 40, 40], RGB)
    expected = 1 - grey @ red / (np.linalg.norm(grey) * np.linalg.norm(red))
    assert r.value == pytest.approx(expected, abs=1e-5)


# ------------------------------------------------------------------ 2. half-pixel centres


def test_half_pixel_centres_round_half_to_even():
    # rint: 40.5 -> 40, 41.5 -> 42, -0.5 -> 0, 2.5 -> 2, 319.5 -> 320, 159.5 -> 160; origin = rint - 32
    centres = np.array([[40.5, 41.5], [-0.5, 2.5], [319.5, 159.5]])
    np.testing.assert_array_equal(patch_origins(centres), [[8, 10], [-32, -30], [288, 128]])
    # float32 tracks round the same way
    np.testing.assert_array_equal(patch_origins(centres.astype(np.float32)), [[8, 10], [-32, -30], [288, 128]])
    # the crop starts where the rounded centre says
    rows, cols = np.mgrid[0:H, 0:W]
    frame = np.stack([cols % 256, rows, rows], axis=-1).astype(np.uint8)
    a, b = extract_patches(frame, np.array([[40.5, 80.5], [41.5, 81.5]]))
    np.testing.assert_array_equal(a[0, :, 0], np.arange(8, 72))   # columns 8..71
    np.testing.assert_array_equal(a[:, 0, 1], np.arange(48, 112))  # 80.5 -> 80: rows 48..111
    np.testing.assert_array_equal(b[0, :, 0], np.arange(10, 74))   # columns 10..73
    np.testing.assert_array_equal(b[:, 0, 1], np.arange(50, 114))  # 81.5 -> 82: rows 50..113


def test_half_pixel_rounding_decides_validity_at_the_border():
    centres = np.array([
        [320.5, 80.0],  # -> 320: columns 288..351, 32 inside: kept (half up would give 31)
        [321.5, 80.0],  # -> 322: columns 290..353, 30 inside: dropped
        [-0.5, 80.0],   # -> 0: columns -32..31, 32 inside: kept
        [-1.5, 80.0],   # -> -2: columns -34..29, 30 inside: dropped
        [160.0, 160.5],  # -> 160: rows 128..191, 32 inside an image of height 160: kept
    ])
    np.testing.assert_array_equal(patch_is_valid(centres, H, W), [True, False, True, False, True])


# ------------------------------------------------------------------ 3. non-finite positions


def test_shared_rule_non_finite_is_not_visible():
    vis = np.array([[True, True, False], [True, True, True]])
    a = np.zeros((2, 3, 2))
    b = np.zeros((2, 3, 2))
    a[0, 1, 0] = np.nan
    b[1, 2, 1] = -np.inf
    a[0, 2] = np.nan  # already invisible
    np.testing.assert_array_equal(finite_and_visible(vis, a, b), [[True, False, False], [True, True, False]])
    np.testing.assert_array_equal(finite_and_visible(vis), vis)


def test_ate_drops_non_finite_positions_flagged_visible():
    ref = np.zeros((3, 2, 2))
    gen = np.zeros((3, 2, 2))
    gen[0] = [3.0, 4.0]                  # 5 px at both frames
    gen[1] = [[6.0, 8.0], [np.inf, 0.0]]  # 10 px at frame 0; infinite at frame 1
    gen[2] = [[np.nan, 1.0], [0.0, 0.0]]  # NaN at frame 0; 0 px at frame 1 ...
    ref[2, 1] = [np.nan, np.nan]          # ... but the reference is NaN there
    vis = np.ones((3, 2), bool)
    r = ate(ref, gen, vis, vis, 100)
    # Q = {(0,0), (0,1), (1,0)} with errors 5, 5, 10 px
    assert r.value == pytest.approx(20 / 3 / 100)
    np.testing.assert_allclose(r.per_frame, [15 / 2 / 100, 5 / 100])


def mean_colour(x):
    return x.mean(dim=(2, 3))


def cosine(a, b):
    return a @ b / (np.linalg.norm(a) * np.linalg.norm(b))


def test_iddrift_drops_non_finite_positions_flagged_visible():
    # Reference grey; generated red on the left half, blue on the right half.
    ref = np.full((3, H, W, 3), 128, np.uint8)
    gen = ref.copy()
    gen[:, :, : W // 2] = (200, 40, 40)
    gen[:, :, W // 2:] = (40, 40, 200)
    left, right = [80.0, 80.0], [240.0, 80.0]
    ref_tracks = np.array([[left] * 3, [right] * 3])
    gen_tracks = ref_tracks.copy()
    gen_tracks[0, 1] = [np.nan, 80.0]  # actor 0: NaN at frame 1, still flagged visible
    gen_tracks[1, 2] = [np.inf, 80.0]  # actor 1: infinite at frame 2
    vis = np.ones((2, 3), bool)
    actor = np.array([0, 1])
    grey = normalised_input([128] * 3, RGB)
    s_red = cosine(grey, normalised_input([200, 40, 40], RGB))
    s_blue = cosine(grey, normalised_input([40, 40, 200], RGB))
    r = iddrift(ref, gen, ref_tracks, gen_tracks, vis, vis, actor, mean_colour)
    # pairs left: actor 0 at frame 2 (red), actor 1 at frame 1 (blue)
    assert r.value == pytest.approx(1 - (s_red + s_blue) / 2, abs=1e-5)
    np.testing.assert_allclose(r.per_frame[1:], [1 - s_blue, 1 - s_red], atol=1e-5)
    # a non-finite reference position is dropped the same way: actor 0 loses its last pair
    ref_nan = ref_tracks.copy()
    ref_nan[0, 2] = [80.0, np.nan]
    r = iddrift(ref, gen, ref_nan, gen_tracks, vis, vis, actor, mean_colour)
    assert r.value == pytest.approx(1 - s_blue, abs=1e-5)
    assert math.isnan(r.per_frame[2])


def test_bgdrift_gives_non_finite_corners_zero_weight():
    # Five corners move by (10, 0); corner 4 moves 30 px more and has confidence 0.5 at frame 0.
    x0 = np.array([[100.0, 100.0], [300.0, 120.0], [180.0, 400.0], [500.0, 350.0], [250.0, 250.0]])
    tracks = np.stack([x0, x0 + [10.0, 0.0]], axis=1)
    tracks[4, 1] += [0.0, 30.0]
    conf = np.ones((5, 2))
    conf[4, 0] = 0.5
    expected = 0.5 * 30 / 4.5 / 100  # only corner 4 has a residual, 30 px with weight 0.5 of 4.5
    assert bgdrift(tracks, conf, 100).value == pytest.approx(expected, rel=1e-4)
    # Three more corners, each confident but non-finite somewhere, with wild positions otherwise.
    extra = np.array([[[400.0, 200.0], [np.nan, 200.0]],     # NaN at frame 1
                      [[np.inf, 300.0], [700.0, 500.0]],     # infinite at frame 0
                      [[600.0, 100.0], [650.0, 180.0]]])     # finite, but NaN confidence at frame 1
    extra_conf = np.array([[1.0, 1.0], [1.0, 1.0], [1.0, np.nan]])
    r = bgdrift(np.concatenate([tracks, extra]), np.concatenate([conf, extra_conf]), 100)
    assert r.value == pytest.approx(expected, rel=1e-4)
    assert r.per_frame[1] == pytest.approx(expected, rel=1e-4)
    # non-finite corners do not count towards the four a frame needs
    few = np.concatenate([tracks[:3], extra[:1]])
    r = bgdrift(few, np.ones((4, 2)), 100)
    assert math.isnan(r.value) and np.isnan(r.per_frame).all()


# ------------------------------------------------------------------ ATE-3D scene for rules 3-5
# A 10 x 8 image, focal length 10 px, principal point (4.5, 3.5), camera at the origin with the
# identity camera-to-world rotation (Blender: looking down -Z, +Y up). A pixel (u, v) at depth Z
# is the world point (Z (u - 4.5) / 10, -Z (v - 3.5) / 10, -Z). Reference depth is 2 + 0.1 j m
# in column j at both frames and the predicted disparity is exactly 1 / depth, so the clip
# alignment is the identity and the depth at an integer pixel is exact.

SH, SW, FOCAL = 8, 10, 10.0
SK = np.array([[FOCAL, 0.0, 4.5], [0.0, FOCAL, 3.5], [0.0, 0.0, 1.0]])
SR, ST = np.eye(3), np.zeros(3)
OFFSET = np.array([0.1, 0.0, 0.0])  # the reference position is 0.1 m beside the reconstruction


def world(u, v, z):
    return np.array([z * (u - 4.5) / FOCAL, -z * (v - 3.5) / FOCAL, -z])


def scene_depth():
    depth = np.broadcast_to(2.0 + 0.1 * np.arange(SW), (2, SH, SW)).copy()
    return depth, 1.0 / depth


A0, A1 = world(3, 4, 2.3), world(6, 4, 2.6)  # point 0 at pixel (3, 4) at frame 0, (6, 4) at frame 1


def scene_ate3d(p1_frame1, p0_visible_at_1=True, positions=None):
    """One actor, two points; point 1 is visible only at frame 1, at p1_frame1."""
    tracks = np.array([[[3.0, 4.0], [6.0, 4.0]], [[5.0, 4.0], p1_frame1]])
    vis = np.array([[True, p0_visible_at_1], [False, True]])
    depth, disparity = scene_depth()
    if positions is None:
        positions = np.stack([A0 + OFFSET, A1 + OFFSET])[None]
    return ate3d(tracks, vis, vis.copy(), np.array([0, 0]), disparity, depth, SK, SR, ST, positions)


def test_scene_inside_points_by_hand():
    # Point 1 at (9.5, 4): the right edge of the image's last pixel column, still inside; bilinear
    # sampling uses column 9 (depth 2.9). The median of two points is their mean.
    assert inside_image(np.array([[9.5, 4.0], [9.6, 4.0], [-0.5, -0.5]]), SH, SW).tolist() == [True, False, True]
    r = scene_ate3d([9.5, 4.0])
    recon1 = (A1 + world(9.5, 4, 2.9)) / 2
    err1 = np.linalg.norm(recon1 - (A1 + OFFSET))
    expected = math.sqrt((0.1 ** 2 + err1 ** 2) / 2) / np.linalg.norm(A1 - A0)
    assert r.value == pytest.approx(expected, rel=1e-9)


# ------------------------------------------------------------------ 3 (ATE-3D) non-finite


@pytest.mark.parametrize("bad", [[np.nan, 4.0], [np.inf, np.inf], [3.0, -np.inf]])
def test_ate3d_drops_non_finite_positions_flagged_visible(bad):
    r = scene_ate3d(bad)
    # point 1 is dropped: both frames reconstruct point 0 exactly, 0.1 m from the reference
    assert r.value == pytest.approx(0.1 / np.linalg.norm(A1 - A0), rel=1e-9)


# ------------------------------------------------------------------ 4. ATE-3D points outside the image


def test_ate3d_excludes_generated_points_outside_the_image():
    disp = np.linalg.norm(A1 - A0)
    for outside in ([12.0, 4.0], [9.6, 4.0], [5.0, -3.0]):
        r = scene_ate3d(outside)
        # point 1 is excluded, so frame 1 reconstructs point 0 alone: 0.1 m at both frames
        assert r.value == pytest.approx(0.1 / disp, rel=1e-9)
        np.testing.assert_allclose(r.per_frame, [0.1 / disp, 0.1 / disp], rtol=1e-9)
    # The clamped-border alternative (depth of column 9, 2.9 m, unprojected at u = 12) would give
    # a different score; the test tells the two rules apart.
    clamped1 = (A1 + world(12, 4, 2.9)) / 2
    clamped = math.sqrt((0.1 ** 2 + np.linalg.norm(clamped1 - A1 - OFFSET) ** 2) / 2) / disp
    assert abs(clamped - 0.1 / disp) > 0.1
    # With point 0 not visible at frame 1, the actor has no point left there: (0, 1) leaves V3.
    r = scene_ate3d([12.0, 4.0], p0_visible_at_1=False)
    assert r.value == pytest.approx(0.1 / disp, rel=1e-9)
    assert r.per_frame[0] == pytest.approx(0.1 / disp, rel=1e-9)
    assert math.isnan(r.per_frame[1])


# ------------------------------------------------------------------ 5. ATE-3D with no moving actor


@pytest.mark.parametrize("move_m", [0.0, 0.005, 0.0099])
def test_ate3d_without_a_moving_actor_is_nan(move_m):
    # The reconstruction is perfectly finite; only the denominator is empty (A_m needs > 0.01 m).
    positions = np.stack([A0, A0 + [move_m, 0.0, 0.0]])[None]
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no "mean of empty slice" or division warnings either
        r = scene_ate3d([6.0, 4.0], positions=positions)
    assert math.isnan(r.value)
    assert r.per_frame.shape == (2,) and np.isnan(r.per_frame).all()


def test_ate3d_one_centimetre_is_the_threshold():
    # Just over 1 cm moves: A_m = {0}, and the value is finite again.
    positions = np.stack([A0, A0 + [0.0101, 0.0, 0.0]])[None]
    r = scene_ate3d([6.0, 4.0], positions=positions)
    # frame 0: point 0 is exact (error 0); frame 1: mean of A1 and the second point at (6, 4)
    err1 = np.linalg.norm(A1 - (A0 + [0.0101, 0.0, 0.0]))
    assert r.value == pytest.approx(math.sqrt(err1 ** 2 / 2) / 0.0101, rel=1e-6)
