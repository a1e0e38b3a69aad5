"""IdDrift: patch geometry, validity, and the actor-then-pair averaging with known features."""

import math

import numpy as np
import pytest

from rigidbench.metrics.identity import (IMAGENET_MEAN, IMAGENET_STD, extract_patches, iddrift, patch_is_valid,
                                         patch_origins)

torch = pytest.importorskip("torch")

H, W = 160, 320


def test_patch_origin_and_validity_by_hand():
    # centre 32.0 -> columns 0..63; centre 0.5 rounds half to even to 0 -> columns -32..31 (32 inside);
    # centre 100.5 rounds to 100 -> rows 68..131
    np.testing.assert_array_equal(patch_origins(np.array([[32.0, 32.0], [0.5, 100.5]])), [[0, 0], [-32, 68]])
    centres = np.array([
        [0.5, 80.0],     # 32 columns inside: kept
        [-0.5, 80.0],    # exactly 32 columns inside: kept
        [-1.0, 80.0],    # 31 columns inside: dropped
        [160.0, -1.0],   # 31 rows inside: dropped
        [160.0, 192.0],  # rows 160..223 -> 0 inside an image of height 160: dropped
        [np.nan, 5.0],
    ])
    np.testing.assert_array_equal(patch_is_valid(centres, H, W), [True, True, False, False, False, False])


def test_extract_patches_copies_the_part_inside_the_image():
    frame = (np.arange(H * W * 3) % 251 + 1).reshape(H, W, 3).astype(np.uint8)  # no zeros inside
    patches = extract_patches(frame, np.array([[32.0, 32.0], [0.5, 40.0]]))
    assert [p.shape for p in patches] == [(64, 64, 3), (64, 32, 3)]
    np.testing.assert_array_equal(patches[0], frame[:64, :64])
    # centre 0.5 -> 0: columns -32..31 requested, -32..-1 lie outside and are cut off (no padding)
    np.testing.assert_array_equal(patches[1], frame[8:72, :32])


def mean_colour(x):
    """Feature = per-channel mean of the normalised patch (B, 3)."""
    return x.mean(dim=(2, 3))


def normalised(rgb):
    v = (np.asarray(rgb, float) / 255 - IMAGENET_MEAN) / IMAGENET_STD
    return v / np.linalg.norm(v)


def test_identical_clips_give_zero_for_any_feature_net():
    rng = np.random.default_rng(0)
    rgb = rng.integers(0, 256, (4, H, W, 3), dtype=np.uint8)
    tracks = np.stack([rng.uniform([40, 40], [W - 40, H - 40], (4, 2)) for _ in range(6)])
    vis = np.ones((6, 4), bool)
    torch.manual_seed(0)
    net = torch.nn.Sequential(torch.nn.Conv2d(3, 8, 7, stride=4), torch.nn.ReLU(), torch.nn.Flatten())
    r = iddrift(rgb, rgb.copy(), tracks, tracks.copy(), vis, vis, np.array([0, 0, 0, 1, 1, 1]), net)
    assert r.value == pytest.approx(0.0, abs=1e-6)
    assert math.isnan(r.per_frame[0])


def test_actor_then_pair_mean_by_hand():
    # Reference frames are uniformly grey; generated frames are red on the left half and
    # blue on the right half from frame 1 on. Actor 0 (left) has three valid pairs, actor 1
    # (right) one, so the actor-weighted mean differs from pooling the four pairs.
    ref = np.full((3, H, W, 3), 128, np.uint8)
    gen = ref.copy()
    gen[1:, :, : W // 2] = (200, 40, 40)
    gen[1:, :, W // 2:] = (40, 40, 200)
    gen[0] = 0  # frame 0 differs completely but never counts
    left, right = [80.0, 80.0], [240.0, 80.0]
    tracks = np.array([[left] * 3, [left] * 3, [right] * 3, [right] * 3])
    ref_vis = np.ones((4, 3), bool)
    gen_vis = ref_vis.copy()
    gen_vis[1, 2] = True
    gen_vis[3, 1:] = [False, True]  # actor 1: point 3 only at frame 2
    gen_vis[2, 1:] = False          # point 2 of actor 1 never jointly visible after frame 0
    gen_tracks = tracks.copy()
    gen_tracks[1, 1] = [-100.0, 80.0]  # patch outside the generated image: pair dropped
    actor = np.array([0, 0, 1, 1])
    r = iddrift(ref, gen, tracks, gen_tracks, ref_vis, gen_vis, actor, mean_colour)
    s_red = normalised([128] * 3) @ normalised([200, 40, 40])
    s_blue = normalised([128] * 3) @ normalised([40, 40, 200])
    # actor 0 pairs: (p0, t1), (p0, t2), (p1, t2); actor 1: (p3, t2)
    assert r.value == pytest.approx(1 - (s_red + s_blue) / 2, abs=1e-5)
    assert abs(r.value - (1 - (3 * s_red + s_blue) / 4)) > 1e-3
    np.testing.assert_allclose(r.per_frame[1:], [1 - s_red, 1 - (s_red + s_blue) / 2], atol=1e-5)
    batched = iddrift(ref, gen, tracks, gen_tracks, ref_vis, gen_vis, actor, mean_colour, batch_size=1)
    assert batched.value == pytest.approx(r.value, abs=1e-7)


def test_no_valid_pairs_is_nan():
    rgb = np.zeros((2, H, W, 3), np.uint8)
    tracks = np.full((1, 2, 2), 80.0)
    vis = np.array([[True, False]])  # visible only at frame 0, which never counts
    r = iddrift(rgb, rgb, tracks, tracks, vis, vis, np.array([0]), mean_colour)
    assert math.isnan(r.value)


def test_feature_input_is_224_and_imagenet_normalised():
    seen = {}

    def spy(x):
        seen["shape"] = tuple(x.shape)
        seen["mean"] = x.mean(dim=(0, 2, 3)).numpy()
        return x.mean(dim=(2, 3))

    rgb = np.full((2, H, W, 3), 255, np.uint8)
    tracks = np.full((1, 2, 2), 80.0)
    vis = np.ones((1, 2), bool)
    iddrift(rgb, rgb, tracks, tracks, vis, vis, np.array([0]), spy)
    assert seen["shape"] == (1, 3, 224, 224)
    np.testing.assert_allclose(seen["mean"], (1 - np.array(IMAGENET_MEAN)) / IMAGENET_STD, rtol=1e-5)
