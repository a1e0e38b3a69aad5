"""Camera model: intrinsics, orbit pose, projection and unprojection (hand-computed values)."""

import math

import numpy as np
import pytest

from rigidbench.groundtruth import camera_model as cm


def test_intrinsics_paper_camera():
    K = cm.intrinsics(35.0, 36.0, 1280, 704)
    f = 35.0 / 36.0 * 1280  # 1244.44 px
    np.testing.assert_allclose(K, [[f, 0, 639.5], [0, f, 351.5], [0, 0, 1]])


def test_camera_position_azimuth_and_elevation():
    p = cm.camera_position((1.0, 2.0, 0.5), azimuth_deg=90.0, elevation_deg=30.0, distance_m=2.0)
    np.testing.assert_allclose(p, [1.0, 2.0 + 2 * math.cos(math.radians(30)), 0.5 + 1.0], atol=1e-12)


def test_look_at_axes_from_plus_x():
    R, t = cm.camera_pose((0, 0, 0), azimuth_deg=0.0, elevation_deg=0.0, distance_m=2.0)
    np.testing.assert_allclose(t, [2, 0, 0])
    # standing at +x looking towards -x with z up: right is +y, up is +z, camera -z looks at -x
    np.testing.assert_allclose(R[:, 0], [0, 1, 0], atol=1e-12)
    np.testing.assert_allclose(R[:, 1], [0, 0, 1], atol=1e-12)
    np.testing.assert_allclose(R[:, 2], [1, 0, 0], atol=1e-12)
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(R) == pytest.approx(1.0)


def test_project_hand_values():
    K = cm.intrinsics(35.0, 36.0, 1280, 704)
    f = K[0, 0]
    R, t = cm.camera_pose((0, 0, 0), 0.0, 0.0, 2.0)
    uv, z = cm.project(np.array([[0.0, 0.1, 0.0], [0.0, 0.0, 0.1], [-1.0, 0.0, 0.0]]), K, R, t)
    np.testing.assert_allclose(z, [2.0, 2.0, 3.0])
    np.testing.assert_allclose(uv[0], [639.5 + f * 0.05, 351.5])  # +y world is to the right
    np.testing.assert_allclose(uv[1], [639.5, 351.5 - f * 0.05])  # +z world is up (smaller v)
    np.testing.assert_allclose(uv[2], [639.5, 351.5])


def test_target_projects_to_principal_point_at_elevation():
    K = cm.intrinsics(35.0, 36.0, 256, 144)
    target = np.array([0.3, -0.2, 0.9])
    R, t = cm.camera_pose(target, 137.0, 10.0, 1.7)
    uv, z = cm.project(target, K, R, t)
    np.testing.assert_allclose(uv, [127.5, 71.5], atol=1e-9)
    assert z == pytest.approx(1.7)


def test_unproject_inverts_project():
    rng = np.random.default_rng(0)
    K = cm.intrinsics(35.0, 36.0, 320, 176)
    R, t = cm.camera_pose((0, 0, 1), 200.0, 10.0, 1.5)
    pts = rng.uniform(-0.3, 0.3, size=(50, 3)) + [0, 0, 1]
    uv, z = cm.project(pts, K, R, t)
    np.testing.assert_allclose(cm.unproject(uv, z, K, R, t), pts, atol=1e-12)
    rays = cm.pixel_rays(K, R, uv)
    np.testing.assert_allclose(t + z[:, None] * rays, pts, atol=1e-12)


def test_world_to_camera_cv_is_inverse_pose_with_flip():
    R, t = cm.camera_pose((0.5, 0.5, 0.8), 33.0, 10.0, 2.0)
    w2c = cm.world_to_camera_cv(R, t)
    c2w = cm.pose_matrix(R, t)
    flip = np.diag([1.0, -1.0, -1.0, 1.0])
    np.testing.assert_allclose(w2c @ c2w, flip, atol=1e-12)
    p = np.array([0.1, 0.2, 0.3])
    np.testing.assert_allclose((w2c @ np.r_[p, 1])[:3], cm.to_camera_cv(p, R, t), atol=1e-12)
