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


# -- framing and camera search geometry (pure parts of rigidbench.blender.camera) ---------------------

from rigidbench.blender import camera as bcam  # noqa: E402  (imports no bpy)
from rigidbench.config import CameraSettings  # noqa: E402
from rigidbench.scene_spec.types import Body, BodyPhysics, SceneSpec, SimSpec, SupportSpec  # noqa: E402


def _spec(positions, rotation_deg=0.0, size=(0.1, 0.1, 0.1)):
    phys = BodyPhysics(0.1, 0.5, 0.5)
    bodies = tuple(Body(name=f"b{i}", asset="apple", role="active", step="s", position_m=p, quat_wxyz=(1, 0, 0, 0),
                        size_m=size, physics=phys) for i, p in enumerate(positions))
    return SceneSpec(sample_id="x", split="eval", task="free_fall", scene="s", surface="top", seed=1,
                     partition="p", allowed_objects=("apple",), prompt="p",
                     support=SupportSpec("top", (1.0, 2.0, 0.9), (2.0, 1.0), 0.0, BodyPhysics(0, 0.4, 0.3)),
                     bodies=bodies, footprint_m=(0.1, 0.1), rotation_candidates_deg=(rotation_deg,),
                     task_rotation_deg=rotation_deg, azimuth_candidates_deg=(0.0,),
                     sim=SimSpec(24, 49, 30, 20, 9.81, 0.1, 0.5, 0.001, 0.0001))


def test_framing_box_joins_actors_and_support_top():
    lo, hi = bcam.framing_box(_spec([(0.0, 0.0, 0.55)]), padding_m=0.2)
    # body centre (1, 2, 1.45) +- 0.05, extended down to the support top 0.9, padded by 0.2
    np.testing.assert_allclose(lo, [0.75, 1.75, 0.70])
    np.testing.assert_allclose(hi, [1.25, 2.25, 1.70])


def test_framing_distance_rule():
    cfg = CameraSettings()
    target, d = bcam.framing(_spec([(0.0, 0.0, 0.55)]), cfg)
    np.testing.assert_allclose(target, [1.0, 2.0, 1.2])
    assert d == pytest.approx(1.4)  # 1.4 x 1.0 m tall box = 1.4, the minimum
    target, d = bcam.framing(_spec([(-0.6, 0.0, 0.05), (0.6, 0.0, 0.05)]), cfg)
    assert d == pytest.approx(1.4 * (1.2 + 0.1 + 0.4))  # widest extent along x
    _, d = bcam.framing(_spec([(0.0, 0.0, 0.05)]), cfg)
    assert d == pytest.approx(1.4)  # small layouts keep the 1.4 m minimum


def test_framing_follows_task_rotation():
    _, d0 = bcam.framing(_spec([(-0.6, 0.0, 0.05), (0.6, 0.0, 0.05)], rotation_deg=0.0), CameraSettings())
    lo, hi = bcam.framing_box(_spec([(-0.6, 0.0, 0.05), (0.6, 0.0, 0.05)], rotation_deg=90.0), 0.2)
    np.testing.assert_allclose(hi - lo, [0.5, 1.7, 0.5], atol=1e-9)  # the row now runs along y


def test_camera_spec_world_azimuth_is_rotation_plus_relative():
    cam = bcam.camera_spec(_spec([(0.0, 0.0, 0.55)], rotation_deg=300.0), 90.0, CameraSettings(), 0.75)
    assert cam.azimuth_deg == pytest.approx(30.0) and cam.relative_azimuth_deg == 90.0
    assert cam.elevation_deg == 10.0 and cam.lens_mm == 35.0 and cam.visibility == 0.75
    R, t = bcam.camera_pose(cam)
    np.testing.assert_allclose(t, cm.camera_position(cam.target_m, 30.0, 10.0, cam.distance_m))


def test_sample_surface_is_on_the_mesh_and_area_weighted():
    # two triangles in the z=0 plane: areas 0.5 (x in [0,1]) and 4.5 (x in [2,5])
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [2, 0, 0], [5, 0, 0], [2, 3, 0]], float)
    f = np.array([[0, 1, 2], [3, 4, 5]])
    p = bcam.sample_surface(v, f, 4000, np.random.default_rng(0))
    assert p.shape == (4000, 3) and (p[:, 2] == 0).all()
    small = p[:, 0] <= 1
    assert (p[small].sum(1) <= 1 + 1e-12).all()  # inside the first triangle
    big = p[~small]
    assert ((big[:, 0] >= 2) & (big[:, 1] >= 0) & (big[:, 0] - 2 + big[:, 1] <= 3 + 1e-12)).all()
    assert small.mean() == pytest.approx(0.1, abs=0.02)
