"""Ground-truth point tracks on a synthetic scene with hand-computed projections and occlusion.

Camera at (0, -5, 0) looking along +y: a world point (x, y, z) lands at u = 31.5 + 40 x / (5 + y),
v = 23.5 - 40 z / (5 + y). Actor A is a flat patch at depth 5 m that slides +x by 0.125 m
(one pixel) per frame; passive actor B is a static wall at depth 4 m covering columns 40..47.
"""

import math

import numpy as np

from rigidbench.groundtruth import camera_model as cm
from rigidbench.groundtruth import tracks as gt

W, H, T = 64, 48, 30
K = np.array([[40.0, 0, 31.5], [0, 40.0, 23.5], [0, 0, 1]])
R_C, T_C = cm.look_at((0, -5, 0), (0, 0, 0)), np.array([0.0, -5.0, 0.0])


def _scene(occlude_mask: bool = True):
    masks = np.zeros((T, 2, H, W), bool)
    depth = np.full((T, H, W), 10.0, np.float32)
    for t in range(T):
        a = np.zeros((H, W), bool)
        a[18:30, 20 + t:min(32 + t, W)] = True
        depth[t][a] = 5.0
        masks[t, 1, :, 40:48] = True
        depth[t, :, 40:48] = 4.0
        masks[t, 0] = a & ~masks[t, 1] if occlude_mask else a
    rotations = np.broadcast_to(np.eye(3), (2, T, 3, 3)).copy()
    positions = np.zeros((2, T, 3))
    positions[0, :, 0] = 0.125 * np.arange(T)
    positions[1] = [0.0, -1.0, 0.0]
    return masks, depth, rotations, positions


def test_erode_square_by_three_pixels():
    m = np.zeros((20, 20), bool)
    m[5:14, 6:15] = True  # 9x9
    e = gt.erode(m, 3)
    expected = np.zeros_like(m)
    expected[8:11, 9:12] = True  # 3x3 core
    np.testing.assert_array_equal(e, expected)


def test_erode_treats_border_as_background():
    m = np.ones((10, 10), bool)
    e = gt.erode(m, 3)
    assert e[3:7, 3:7].all() and e.sum() == 16


def test_sample_query_pixels_without_replacement_inside_erosion():
    m = np.zeros((30, 30), bool)
    m[5:20, 5:20] = True
    rng = np.random.default_rng(1)
    q = gt.sample_query_pixels(m, 20, rng)
    assert q.shape == (20, 2)
    assert len({tuple(p) for p in q}) == 20
    assert ((q >= 8) & (q < 17)).all()  # eroded square 8..16


def test_small_mask_gives_all_pixels():
    m = np.zeros((30, 30), bool)
    m[10:17, 10:18] = True  # 7x8 -> eroded to 1x2
    q = gt.sample_query_pixels(m, 20, np.random.default_rng(0))
    assert sorted(map(tuple, q)) == [(13, 13), (14, 13)]


def test_body_point_hand_value():
    depth0 = np.full((H, W), 5.0)
    # pixel (u=39.5 is not a centre; take u=39, v=15): x = (39-31.5)*5/40, z = -(15-23.5)*5/40
    pb = gt.body_points(np.array([[39, 15]]), depth0, K, R_C, T_C, np.eye(3), np.array([1.0, 0.0, 0.0]))
    np.testing.assert_allclose(pb, [[(39 - 31.5) * 5 / 40 - 1.0, 0.0, 8.5 * 5 / 40]], atol=1e-12)


def test_tracks_follow_translation_and_turn_off_behind_occluder():
    masks, depth, rotations, positions = _scene()
    out = gt.ground_truth_tracks(masks, depth, K, R_C, T_C, rotations, positions, np.array([True, False]), seed=7)
    assert out.tracks_px.shape == (20, T, 2) and out.tracks_px.dtype == np.float32
    assert out.visibility.shape == (20, T) and out.visibility.dtype == bool
    np.testing.assert_array_equal(out.points_per_actor, [20, 0])
    assert (out.actor_index == 0).all()
    q = out.query_pixels
    assert ((q[:, 0] >= 23) & (q[:, 0] < 29) & (q[:, 1] >= 21) & (q[:, 1] < 27)).all()
    t = np.arange(T)
    np.testing.assert_allclose(out.tracks_px[..., 0], q[:, :1] + t[None], atol=1e-4)
    np.testing.assert_allclose(out.tracks_px[..., 1], np.broadcast_to(q[:, 1:], (20, T)), atol=1e-4)
    col = q[:, :1] + t[None]
    expected = ~((col >= 40) & (col < 48)) & (col <= W - 1)
    np.testing.assert_array_equal(out.visibility, expected)
    assert out.visibility[:, 0].all()
    assert not out.visibility[:, 17].any()  # columns 40..45: every point is behind the wall
    assert out.visibility[:, -1].all()  # columns 52..57: past the wall again


def test_depth_test_alone_hides_points_behind_occluder():
    masks, depth, rotations, positions = _scene(occlude_mask=False)  # A's mask ignores the wall
    out = gt.ground_truth_tracks(masks, depth, K, R_C, T_C, rotations, positions, np.array([True, False]), seed=7)
    col = out.query_pixels[:, :1] + np.arange(T)[None]
    behind = (col >= 40) & (col < 48)
    assert behind.any()
    assert not out.visibility[behind].any()  # 5 m > 1.01 x 4 m


def test_rotation_about_vertical_axis_hand_projection():
    theta = math.radians(60)
    R1 = np.array([[math.cos(theta), -math.sin(theta), 0], [math.sin(theta), math.cos(theta), 0], [0, 0, 1]])
    pb = np.array([[0.4, 0.0, 0.2]])
    world = gt.carry(pb, np.stack([np.eye(3), R1]), np.zeros((2, 3)))
    uv, z = cm.project(world, K, R_C, T_C)
    x0, z0 = 0.4, 0.2
    d = 5 + x0 * math.sin(theta)
    np.testing.assert_allclose(z[0], [5.0, d])
    np.testing.assert_allclose(uv[0, 1], [31.5 + 40 * x0 * math.cos(theta) / d, 23.5 - 40 * z0 / d])


def test_point_behind_camera_is_invisible():
    uv = np.array([[[10.0, 10.0], [10.0, 10.0]]])
    z = np.array([[3.0, -3.0]])
    mask = np.ones((2, H, W), bool)
    depth = np.full((2, H, W), 5.0)
    np.testing.assert_array_equal(gt.visibility(uv, z, mask, depth), [[True, False]])


def test_same_seed_same_tracks():
    masks, depth, rotations, positions = _scene()
    a = gt.ground_truth_tracks(masks, depth, K, R_C, T_C, rotations, positions, np.array([True, False]), seed=3)
    b = gt.ground_truth_tracks(masks, depth, K, R_C, T_C, rotations, positions, np.array([True, False]), seed=3)
    np.testing.assert_array_equal(a.query_pixels, b.query_pixels)
    c = gt.ground_truth_tracks(masks, depth, K, R_C, T_C, rotations, positions, np.array([True, False]), seed=4)
    assert not np.array_equal(a.query_pixels, c.query_pixels)


def test_tracks_save_load_roundtrip(tmp_path):
    masks, depth, rotations, positions = _scene()
    a = gt.ground_truth_tracks(masks, depth, K, R_C, T_C, rotations, positions, np.array([True, False]), seed=3)
    a.save(tmp_path / "tracks.npz")
    b = gt.Tracks.load(tmp_path / "tracks.npz")
    np.testing.assert_array_equal(a.tracks_px, b.tracks_px)
    np.testing.assert_array_equal(a.visibility, b.visibility)
    assert b.actor_index.dtype == np.int64


def test_published_rule_erodes_by_a_diamond_and_falls_back_to_the_mask():
    m = np.zeros((30, 30), bool)
    m[5:20, 5:20] = True  # 15x15: the cross eroded 3 times keeps the 9x9 core
    pool = gt.erode_cross(m, 3)
    assert pool[8:17, 8:17].all() and pool.sum() == 81
    assert gt.erode_cross(np.abs(np.indices((30, 30)) - 15).sum(0) <= 5, 3).sum() == 13  # L1 ball 5 -> L1 ball 2
    rule = gt.TRACK_RULES["published"]
    q = gt.sample_query_pixels(m, 20, np.random.default_rng(42), rule=rule)
    assert pool[q[:, 1], q[:, 0]].all() and len(q) == 20
    small = np.zeros((30, 30), bool)
    small[10:15, 10:15] = True  # 5x5: nothing survives, so all 20 points come from the mask itself
    q = gt.sample_query_pixels(small, 20, np.random.default_rng(42), rule=rule)
    assert len(q) == 20 and small[q[:, 1], q[:, 0]].all()
    assert len(gt.sample_query_pixels(small, 20, np.random.default_rng(42))) == 0  # our earlier rule: none


def test_published_rule_seeds_every_actor_afresh():
    m = np.zeros((40, 40), bool)
    m[5:25, 5:25] = True
    masks = np.stack([m, m])[None].repeat(2, axis=0)  # (T=2, N=2, H, W): two actors with the same mask
    depth = np.full((2, 40, 40), 2.0, np.float32)
    K = np.array([[40.0, 0, 20], [0, 40.0, 20], [0, 0, 1]])
    rot = np.broadcast_to(np.eye(3), (2, 2, 3, 3))
    pos = np.zeros((2, 2, 3))
    pub = gt.ground_truth_tracks(masks, depth, K, np.eye(3), np.array([0, 0, 5.0]), rot, pos, np.array([True, True]),
                                 seed=7, rule=gt.TRACK_RULES["published"])
    a, b = pub.query_pixels[pub.actor_index == 0], pub.query_pixels[pub.actor_index == 1]
    np.testing.assert_array_equal(a, b)  # a fresh generator seeded 42 per actor draws the same pixels
    ours = gt.ground_truth_tracks(masks, depth, K, np.eye(3), np.array([0, 0, 5.0]), rot, pos, np.array([True, True]),
                                  seed=7)
    assert not np.array_equal(ours.query_pixels[ours.actor_index == 0], ours.query_pixels[ours.actor_index == 1])
