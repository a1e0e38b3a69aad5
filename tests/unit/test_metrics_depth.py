"""Depth alignment, SI-MSE and ATE-3D on synthetic cameras, depth maps and tracks.

The test camera is written with its own basis vectors (right, down, forward) rather than
K, R_c and S, so the library's camera convention is checked against an independent form.
"""

import math

import numpy as np
import pytest

from rigidbench.metrics.depth import (DepthAlignment, aligned_depth, ate3d, fit_disparity_alignment,
                                      si_mse, valid_reference_depth)
from rigidbench.metrics.tracks import ate

# ---------------------------------------------------------------- SI-MSE and the fit


def test_valid_reference_depth_rule():
    z = np.array([[0.0, -1.0, 0.5, 99.9, 100.0, np.inf, np.nan, 150.0]], np.float32)
    np.testing.assert_array_equal(valid_reference_depth(z), [[False, False, True, True, False, False, False, False]])


def test_fit_recovers_affine_disparity_and_ignores_invalid_pixels():
    rng = np.random.default_rng(0)
    z = rng.uniform(1.0, 20.0, (3, 8, 9)).astype(np.float32)
    disparity = (2.5 / z.astype(np.float64) - 0.3)  # d = 2.5 / Z - 0.3  ->  1/Z = 0.4 d + 0.12
    z[0, 0, :4] = [0.0, np.inf, np.nan, 150.0]
    disparity[0, 0, :4] = 1e6  # garbage where the reference is invalid
    disparity[1, 2, 3] = np.nan
    fit = fit_disparity_alignment(disparity, z)
    assert fit.scale == pytest.approx(0.4, rel=1e-6)
    assert fit.shift == pytest.approx(0.12, rel=1e-6)
    assert fit.n_pixels == 3 * 8 * 9 - 5


def test_aligned_depth_only_where_positive():
    z_hat = aligned_depth(np.array([[0.25, 0.5, 1.0, np.nan]]), DepthAlignment(2.0, -1.0, 4))
    assert np.isnan(z_hat[0, [0, 1, 3]]).all()
    assert z_hat[0, 2] == 1.0


def test_si_mse_identical_is_zero():
    rng = np.random.default_rng(1)
    z = rng.uniform(0.5, 50.0, (4, 6, 7)).astype(np.float32)
    r = si_mse(1.0 / z.astype(np.float64), z)
    assert abs(r.value) < 1e-12
    assert r.per_frame.shape == (4,)


def test_si_mse_by_hand_with_invalid_pixels():
    # Residuals of 1/Z against d are orthogonal to [d, 1], so the fit is exactly identity:
    # frame 0: d = (1, 1), 1/Z = (1.1, 0.9); frame 1: d = (2, 2), 1/Z = (2.1, 1.9).
    # A third column holds pixels that must be ignored; frame 2 has no valid pixel at all.
    z = np.array([[[1 / 1.1, 1 / 0.9, 0.0]],
                  [[1 / 2.1, 1 / 1.9, np.inf]],
                  [[np.nan, 0.0, 200.0]]], np.float64)
    d = np.array([[[1.0, 1.0, 5.0]],
                  [[2.0, 2.0, 7.0]],
                  [[1.0, 1.0, 1.0]]])
    r = si_mse(d, z)
    frame0 = ((math.log(1.1) - math.log(0.9)) / 2) ** 2  # variance of two values = (half difference)^2
    frame1 = ((math.log(2.1) - math.log(1.9)) / 2) ** 2
    np.testing.assert_allclose(r.per_frame[:2], [frame0, frame1], rtol=1e-9)
    assert math.isnan(r.per_frame[2])
    assert r.value == pytest.approx((frame0 + frame1) / 2, rel=1e-9)
    # a NaN disparity pixel removes that pixel only
    d_nan = d.copy()
    d_nan[1, 0, 1] = np.nan
    d_nan[1, 0, 0] = 2.0
    r2 = si_mse(d_nan, z)
    assert r2.per_frame[1] == pytest.approx(0.0, abs=1e-9)  # one valid pixel left: zero variance


def test_si_mse_invariant_to_depth_scale_and_disparity_affinity():
    rng = np.random.default_rng(2)
    z = rng.uniform(1.0, 10.0, (3, 12, 10))
    d = (1.0 / z) * rng.uniform(0.8, 1.2, z.shape)  # imperfect prediction
    base = si_mse(d, z).value
    assert base > 1e-4
    assert si_mse(d, 3.0 * z).value == pytest.approx(base, rel=1e-9)
    assert si_mse(7.0 * d + 0.2, z).value == pytest.approx(base, rel=1e-9)


def test_disparity_is_resized_to_the_reference_grid():
    z = np.stack([np.full((8, 12), 2.0), np.full((8, 12), 4.0)]).astype(np.float32)
    d_small = np.stack([np.full((4, 6), 0.5), np.full((4, 6), 0.25)])  # exact 1/Z at half size
    fit = fit_disparity_alignment(d_small, z)
    assert (fit.scale, fit.n_pixels) == (pytest.approx(1.0), 2 * 8 * 12)
    assert abs(si_mse(d_small, z).value) < 1e-12


# ---------------------------------------------------------------- ATE-3D scene

W, H, F = 320, 240, 300.0
K = np.array([[F, 0.0, W / 2], [0.0, F, H / 2], [0.0, 0.0, 1.0]])
CAM = np.array([0.0, -4.0, 1.2])
_fwd = np.array([0.0, 4.0, -0.8])
FORWARD = _fwd / np.linalg.norm(_fwd)
RIGHT = np.cross(FORWARD, [0.0, 0.0, 1.0])
RIGHT /= np.linalg.norm(RIGHT)
DOWN = np.cross(FORWARD, RIGHT)
# Blender camera: +X right, +Y up, looking down -Z; columns are those axes in world coordinates.
R_C = np.column_stack([RIGHT, -DOWN, -FORWARD])
T_LEN = 5
OFFSET_M = 0.15


def project(points):
    """(..., 3) world -> (..., 2) pixels (centres at +0.5) and (...) depth along FORWARD."""
    v = points - CAM
    z = v @ FORWARD
    return np.stack([W / 2 + F * (v @ RIGHT) / z, H / 2 + F * (v @ DOWN) / z], axis=-1), z


def positions():
    """(2, T, 3): actor 0 moves 0.24 m sideways, actor 1 moves 0.4 m away from the camera."""
    t = np.arange(T_LEN)
    a0 = np.stack([-0.4 + 0.06 * t, np.zeros(T_LEN), np.full(T_LEN, 0.5)], axis=-1)
    a1 = np.stack([np.full(T_LEN, 0.5), 0.2 + 0.1 * t, np.full(T_LEN, 0.7)], axis=-1)
    return np.stack([a0, a1])


def body_points(pos):
    """(N, T, 3) centres -> (4N, T, 3) points at +-OFFSET along RIGHT and DOWN (median = centre) and actor index."""
    offsets = OFFSET_M * np.array([RIGHT, -RIGHT, DOWN, -DOWN])
    pts = pos[:, None] + offsets[None, :, None]  # (N, 4, T, 3)
    return pts.reshape(-1, pos.shape[1], 3), np.repeat(np.arange(pos.shape[0]), 4)


def background_depth():
    """(H, W) tilted floor-like depth, linear in the pixel row, 5-9 m."""
    rows = np.arange(H)[:, None] + 0.5
    return np.broadcast_to(9.0 - 4.0 * rows / H, (H, W)).copy()


def render(points):
    """(P, T, 3) world points -> (T, H, W) depth with a 4x4 block of each point's depth around
    its pixel (covering every neighbour bilinear sampling reads) over the background, and the
    (T, H, W) bool mask of those blocks."""
    xy, z = project(points)
    depth = np.repeat(background_depth()[None], points.shape[1], axis=0)
    blocks = np.zeros(depth.shape, bool)
    for p in range(points.shape[0]):
        for t in range(points.shape[1]):
            c0, r0 = np.floor(xy[p, t] - 0.5).astype(int) - 1
            depth[t, r0:r0 + 4, c0:c0 + 4] = z[p, t]
            blocks[t, r0:r0 + 4, c0:c0 + 4] = True
    return depth, blocks


def score(gen_points, ref_points, actor, pos, exact_fit=True, ref_vis=None):
    """ATE-3D and 2D ATE of a generated clip whose points are gen_points."""
    ref_depth, ref_blocks = render(ref_points)
    gen_depth, gen_blocks = render(gen_points)
    if exact_fit:
        # Where the generated disparity shows an actor somewhere the reference does not (or the
        # reverse), mark the reference depth invalid so the clip-level fit stays exactly the
        # identity and the test isolates unprojection and the median.
        ref_depth[ref_blocks | gen_blocks] = np.inf
    ref_xy, _ = project(ref_points)
    gen_xy, _ = project(gen_points)
    vis = np.ones(ref_xy.shape[:2], bool)
    ref_vis = vis if ref_vis is None else ref_vis
    r3 = ate3d(gen_xy, ref_vis, vis, actor, 1.0 / gen_depth, ref_depth.astype(np.float32), K, R_C, CAM, pos)
    r2 = ate(ref_xy, gen_xy, ref_vis, vis, H)
    return r3, r2


def test_camera_convention_matches_independent_projection():
    from rigidbench.metrics.common import project as lib_project, unproject

    pts = positions().reshape(-1, 3)
    xy, z = project(pts)
    lib_xy, lib_z = lib_project(pts, K, R_C, CAM)
    np.testing.assert_allclose(lib_xy, xy, atol=1e-9)
    np.testing.assert_allclose(lib_z, z, atol=1e-12)
    np.testing.assert_allclose(unproject(xy, z, K, R_C, CAM), pts, atol=1e-9)


def test_identical_clip_gives_zero():
    pos = positions()
    pts, actor = body_points(pos)
    ref_depth, _ = render(pts)
    xy, _ = project(pts)
    vis = np.ones(xy.shape[:2], bool)
    disparity = (1.0 / ref_depth).astype(np.float32)  # exact 1/Z, float32 like a real prediction
    r = ate3d(xy, vis, vis, actor, disparity, ref_depth.astype(np.float32), K, R_C, CAM, pos)
    assert r.value < 1e-5
    assert r.per_frame.shape == (T_LEN,)
    assert np.all(r.per_frame < 1e-5)


def test_offset_along_viewing_ray_is_seen_like_perpendicular_offset():
    pos = positions()
    pts, actor = body_points(pos)
    mean_displacement = (0.24 + 0.4) / 2
    rays = (pts - CAM) / np.linalg.norm(pts - CAM, axis=-1, keepdims=True)
    centre_rays = (pos - CAM) / np.linalg.norm(pos - CAM, axis=-1, keepdims=True)
    perp = np.cross(centre_rays, [0.0, 0.0, 1.0])
    perp /= np.linalg.norm(perp, axis=-1, keepdims=True)
    along_scores = []
    for delta in (0.1, 0.2, 0.4):
        along3, along2 = score(pts + delta * rays, pts, actor, pos)
        perp3, perp2 = score(pts + delta * np.repeat(perp, 4, axis=0), pts, actor, pos)
        assert along2.value < 1e-9  # each point stays on its pixel: invisible to 2D ATE
        assert perp2.value > 0.01
        # a rigid perpendicular shift moves the median by exactly delta
        assert perp3.value == pytest.approx(delta / mean_displacement, rel=1e-6)
        # the four points' rays diverge by ~2 degrees, so along-ray matches to well under 1 %
        assert along3.value == pytest.approx(perp3.value, rel=1e-2)
        along_scores.append(along3.value)
    np.testing.assert_allclose(np.array(along_scores) / along_scores[0], [1, 2, 4], rtol=1e-3)


def test_offset_along_viewing_ray_with_the_fit_over_all_pixels():
    # Without excluding actor pixels the fit moves a little; the response stays close.
    pos = positions()
    pts, actor = body_points(pos)
    rays = (pts - CAM) / np.linalg.norm(pts - CAM, axis=-1, keepdims=True)
    along3, _ = score(pts + 0.2 * rays, pts, actor, pos, exact_fit=False)
    assert along3.value == pytest.approx(0.2 / 0.32, rel=0.05)


def test_denominator_uses_moving_actors_only_and_v3_by_hand():
    pos = positions()
    pos[1] = pos[1, :1]  # actor 1 static: not in A_m
    pts, actor = body_points(pos)
    gen = pts.copy()
    gen[actor == 1] += 0.1 * RIGHT  # actor 1 reconstructed 0.1 m off at every frame
    r3, _ = score(gen, pts, actor, pos)
    assert r3.value == pytest.approx(math.sqrt(0.01 / 2) / 0.24, rel=1e-6)
    np.testing.assert_allclose(r3.per_frame, math.sqrt(0.01 / 2) / 0.24, rtol=1e-6)
    # actor 1 not visible in the reference at frames 0-2: those actor-frames leave V3
    ref_vis = np.ones(pts.shape[:2], bool)
    ref_vis[actor == 1, :3] = False
    r3, _ = score(gen, pts, actor, pos, ref_vis=ref_vis)
    assert r3.value == pytest.approx(math.sqrt(2 * 0.01 / 7) / 0.24, rel=1e-6)
    np.testing.assert_allclose(r3.per_frame[:3], 0.0, atol=1e-6)  # float32 depth rounding


def test_nan_disparity_at_an_actor_removes_its_points():
    pos = positions()
    pts, actor = body_points(pos)
    gen = pts.copy()
    gen[actor == 0] += 0.1 * RIGHT
    ref_depth, ref_blocks = render(pts)
    gen_depth, gen_blocks = render(gen)
    ref_depth[ref_blocks | gen_blocks] = np.inf
    disparity = 1.0 / gen_depth
    xy, _ = project(gen)
    # actor 0's blocks at frame 1 have no prediction
    cols = np.clip(np.floor(xy[actor == 0, 1] - 0.5).astype(int), 0, None)
    for c, r in cols:
        disparity[1, r - 1:r + 3, c - 1:c + 3] = np.nan
    vis = np.ones(xy.shape[:2], bool)
    r = ate3d(xy, vis, vis, actor, disparity, ref_depth, K, R_C, CAM, pos)
    # V3: actor 0 at 4 frames (error 0.1) and actor 1 at 5 frames (error 0)
    assert r.value == pytest.approx(math.sqrt(4 * 0.01 / 9) / 0.32, rel=1e-6)
    assert r.per_frame[1] == pytest.approx(0.0, abs=1e-9)


def test_undefined_cases_are_nan():
    pos = positions()
    pts, actor = body_points(pos)
    depth, _ = render(pts)
    xy, _ = project(pts)
    vis = np.ones(xy.shape[:2], bool)
    static = np.repeat(pos[:, :1], T_LEN, axis=1)
    assert math.isnan(ate3d(xy, vis, vis, actor, 1 / depth, depth, K, R_C, CAM, static).value)
    none = np.zeros_like(vis)
    r = ate3d(xy, none, vis, actor, 1 / depth, depth, K, R_C, CAM, pos)
    assert math.isnan(r.value) and np.isnan(r.per_frame).all()
    with pytest.raises(ValueError, match="actor_index"):
        ate3d(xy, vis, vis, actor + 5, 1 / depth, depth, K, R_C, CAM, pos)


def test_body_origin_offset_counts_unless_reference_points_are_given():
    # The simulator position is the body origin, here 0.05 m behind the tracked surface
    # points. The paper's ATE-3D compares against it, so even a perfect prediction keeps a
    # floor of 0.05 m; with ref_points_m the target is the median of the same tracked points.
    pos = positions()
    pts, actor = body_points(pos)
    origin = pos + 0.05 * FORWARD
    depth, _ = render(pts)
    xy, _ = project(pts)
    vis = np.ones(xy.shape[:2], bool)
    paper = ate3d(xy, vis, vis, actor, 1.0 / depth, depth, K, R_C, CAM, origin)
    assert paper.value == pytest.approx(0.05 / 0.32, rel=1e-6)
    same_points = ate3d(xy, vis, vis, actor, 1.0 / depth, depth, K, R_C, CAM, origin, ref_points_m=pts)
    assert same_points.value == pytest.approx(0.0, abs=1e-9)
