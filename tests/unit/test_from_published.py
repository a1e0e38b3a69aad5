"""A SceneSpec rebuilt from published metadata (scene_spec.from_published) and the measurements and comparison that
re-simulating the published set uses (datasets.resimulate), without bpy."""

from __future__ import annotations

import math

import numpy as np
import pytest

from fixtures import published_from_sim as pfs
from fixtures import published_set as ps
from rigidbench.config import registry as load_registry
from rigidbench.datasets.resimulate import (RESIM_TOLERANCE_M, ResimRow, ResimTable, compare, measure_ramp,
                                            support_top, support_top_from_contacts)
from rigidbench.groundtruth import camera_model as cm
from rigidbench.groundtruth.trajectory import Contact, Trajectory
from rigidbench.rotations import quat_to_matrix
from rigidbench.scene_spec.from_published import Cannot, RebuiltSpec, ramp_from_published, spec_from_published


@pytest.fixture(scope="module")
def reg():
    return load_registry()


def quat_z(deg: float) -> np.ndarray:
    a = math.radians(deg)
    return np.array([math.cos(a / 2), 0.0, 0.0, math.sin(a / 2)])


def published_meta(actors: dict, *, scene="modern_loft", surface="Counter", center=(3.9, -5.92, 0.55),
                   task="free_fall", angle=30.0, cam=((4.5, -7.5, 1.0), (3.9, -5.9, 0.7)), width=1280, fx=1244.4):
    """A published metadata.json with a camera at cam[0] looking at cam[1]."""
    R_c = ps._look_at(np.array(cam[0]), np.array(cam[1]))
    return {"task_type": task, "scene_id": scene, "seed": 7, "surface": surface, "center": list(center),
            "task_angle": angle, "camera_azimuth": 40.0, "footprint": [0.2, 0.1], "frames": 49, "split": "ood-scene",
            "prompt": "An apple is dropping.",
            "actors": {n: {"object_id": oid, "role": role, "position": list(pos)}
                       for n, (oid, role, pos, _) in actors.items()},
            "camera": {"intrinsics": {"fx": fx, "fy": fx, "cx": width / 2, "cy": 352, "width": width, "height": 704},
                       "extrinsics": {"location": list(cam[0]), "rotation": list(ps._quat_from_matrix(R_c))}},
            "render": {"resolution": [width, 704], "fps": 24}}


def poses(actors: dict) -> dict:
    return {n: (np.array(pos), np.array(q)) for n, (_, _, pos, q) in actors.items()}


def test_the_rebuilt_spec_puts_every_actor_back_at_its_published_pose(reg):
    q = np.array([0.9, 0.1, -0.3, 0.2]) / np.linalg.norm([0.9, 0.1, -0.3, 0.2])
    actors = {"falling": ("apple", "active", (4.0, -5.8, 1.2), q)}
    rebuilt = spec_from_published(published_meta(actors), poses(actors), reg, sample_id="00007")
    assert isinstance(rebuilt, RebuiltSpec)
    spec = rebuilt.spec
    (body,) = spec.world_bodies()
    assert np.allclose(body.position_m, (4.0, -5.8, 1.2), atol=1e-12)
    same = abs(np.dot(body.quat_wxyz, q))  # q and -q are one rotation
    assert same == pytest.approx(1.0, abs=1e-12)
    assert spec.task_rotation_deg == 30.0 and spec.sample_id == "00007" and spec.task == "free_fall"
    # the body in the task frame: its offset from the support centre turned back by 30 degrees
    off = np.array([4.0 - 3.9, -5.8 + 5.92])
    a = math.radians(-30)
    assert np.allclose(spec.bodies[0].position_m[:2], [math.cos(a) * off[0] - math.sin(a) * off[1],
                                                       math.sin(a) * off[0] + math.cos(a) * off[1]], atol=1e-12)
    assert spec.bodies[0].position_m[2] == pytest.approx(1.2 - 0.55)
    apple = reg.object("apple")
    assert spec.bodies[0].size_m == tuple(apple.size_m) and spec.bodies[0].physics.mass_kg == apple.physics.mass_kg
    # the support: the published centre, the first release's size and long axis for (modern_loft, Counter)
    assert spec.support.centre_m == (3.9, -5.92, 0.55)
    assert spec.support.size_m == (2.688, 0.925) and spec.support.long_axis_deg == 1.53
    assert rebuilt.notes["support_size_from"] == "first release's surface table"
    assert spec.sim.fps == 24 and spec.sim.frames == 49 and spec.sim.substeps == reg.sim.substeps
    assert spec.partition == "ood_scene"


def test_the_support_top_and_physics_follow_the_measurement_and_the_task(reg):
    actors = {"bouncing": ("bouncy_ball", "active", (0.1, 0.0, 1.5), (1.0, 0.0, 0.0, 0.0))}
    meta = published_meta(actors, scene="modern_loft", surface="counter", center=(0.0, 0.0, 0.92), task="bounce")
    rebuilt = spec_from_published(meta, poses(actors), reg, support_top_m=0.93)
    spec = rebuilt.spec
    assert spec.support.centre_m == (0.0, 0.0, 0.93) and rebuilt.notes["support_top_from"] == "contacts"
    assert spec.world_bodies()[0].position_m[2] == pytest.approx(1.5, abs=1e-12)
    catalogue = reg.scene("modern_loft").support("counter")
    assert spec.support.size_m == tuple(catalogue.size_m)  # not in the release's table: our catalogue's
    override = reg.task("bounce").support_override
    physics = spec.support.physics
    assert (physics.friction, physics.restitution) == (override.friction, override.restitution)


def test_a_published_ramp_becomes_our_wedge_in_the_same_place(reg):
    L, H, W = 0.5, 0.3, 0.35
    p, q = np.array([1.0, 2.0, 0.8]), quat_z(130.0)
    centre, ours = ramp_from_published(p, q, L, H)
    # the release's wedge (origin at the bottom edge of the high end, length along +y), written from its facts
    theirs = np.array([[x, y, z] for x in (-W / 2, W / 2) for y, z in ((0, 0), (0, H), (L, 0))])
    theirs = theirs @ quat_to_matrix(q).T + p
    from rigidbench.blender.assets.standin import ramp_mesh

    mine = ramp_mesh(L, H, W).vertices @ quat_to_matrix(np.asarray(ours)).T + centre
    key = lambda v: tuple(np.round(v, 9))  # noqa: E731
    assert sorted(map(key, mine)) == sorted(map(key, theirs))
    # and through spec_from_published, with the measured size
    actors = {"ramp": ("ramp", "passive", tuple(p), q), "rolling": ("orange", "active", (1.1, 2.2, 1.2), quat_z(0))}
    spec = spec_from_published(published_meta(actors), poses(actors), reg, ramp_sizes={"ramp": (L, H, W)}).spec
    ramp = spec.world_bodies()[0]
    assert ramp.ramp.length_m == L and ramp.ramp.height_m == H and ramp.size_m == (L, W, H)
    assert np.allclose(ramp.position_m, centre, atol=1e-12)
    assert spec.bodies[0].physics.mass_kg == 0.0 and spec.bodies[0].role == "passive"


def test_the_camera_spec_reproduces_the_published_camera(reg):
    actors = {"falling": ("apple", "active", (3.9, -5.9, 1.1), quat_z(0))}
    meta = published_meta(actors, cam=((5.2, -7.0, 1.3), (3.8, -5.8, 0.8)))
    rebuilt = spec_from_published(meta, poses(actors), reg)
    cam = rebuilt.spec.camera
    R_c, t_c = cm.camera_pose(cam.target_m, cam.azimuth_deg, cam.elevation_deg, cam.distance_m)
    R_pub = ps._look_at(np.array([5.2, -7.0, 1.3]), np.array([3.8, -5.8, 0.8]))
    assert np.allclose(t_c, [5.2, -7.0, 1.3], atol=1e-9) and np.allclose(R_c, R_pub, atol=1e-9)
    assert cam.lens_mm / cam.sensor_width_mm * 1280 == pytest.approx(1244.4)
    assert rebuilt.notes["camera_orientation_error_deg"] < 1e-5
    assert cam.relative_azimuth_deg == pytest.approx((cam.azimuth_deg - 30.0) % 360)


@pytest.mark.parametrize("change, words", [
    (lambda m, p: m["actors"]["falling"].update(object_id="unobtainium"), "object id 'unobtainium' is not in our"),
    (lambda m, p: p.pop("falling"), "no pose at frame 0"),
    (lambda m, p: m.update(surface="Sofa"), "support 'Sofa' of scene 'modern_loft'"),
    (lambda m, p: m.update(task_type="juggling"), "task 'juggling' is not in our catalogue"),
    (lambda m, p: m.pop("center"), "no support centre"),
    (lambda m, p: m["actors"]["falling"].update(position=[4.0, -5.8, 1.25]), "differ by 5.0 cm"),
    (lambda m, p: m["actors"]["falling"].update(role="decor"), "role 'decor'"),
    (lambda m, p: m["actors"].update(ramp={"object_id": "ramp", "role": "passive", "position": [4, -6, 0.55]})
     or p.update(ramp=(np.array([4, -6, 0.55]), quat_z(0))), "ramp 'ramp': its length, height and width"),
])
def test_what_the_metadata_lacks_is_a_reason_not_an_exception(reg, change, words):
    actors = {"falling": ("apple", "active", (4.0, -5.8, 1.2), quat_z(10))}
    meta, p = published_meta(actors), poses(actors)
    change(meta, p)
    rebuilt = spec_from_published({"sample_id": "00003", "source": {"original_metadata": meta}}, p, reg)
    assert isinstance(rebuilt, Cannot) and rebuilt.sample_id == "00003"
    assert words in rebuilt.reason, rebuilt.reason


def test_support_top_from_contacts_uses_upward_points_on_the_named_surface():
    def contact(b, zs, nz):
        return Contact(frame=3, a="ball", b=b, points_m=tuple((0.0, 0.0, z) for z in zs),
                       normals=tuple((0.0, math.sqrt(1 - nz * nz), nz) for _ in zs), distances_m=(0.0,) * len(zs))

    contacts = [contact("Counter", [0.551, 0.552, 0.549], 1.0), contact("Counter", [0.3, 0.3, 0.3], 0.2),
                contact("ramp", [0.9, 0.9, 0.9], 1.0), contact("Counter", [0.556], 0.95)]
    assert support_top_from_contacts(contacts, "Counter") == pytest.approx(np.median([0.551, 0.552, 0.549, 0.556]))
    assert support_top_from_contacts(contacts[:2], "Counter") == pytest.approx(0.551)
    assert support_top_from_contacts(contacts[1:3], "Counter") is None  # side points only: too few upward ones
    assert support_top(0.55, 0.553) is None and support_top(0.55, None) is None  # agrees: the centre stays
    assert support_top(0.55, 0.62) == 0.62


@pytest.mark.parametrize("azimuth, width, footprints", [(70.0, 320, 0.02), (160.0, 256, 0.02), (-110.0, 256, 2.0),
                                                        (-130.0, 256, 2.0), (-90.0, 256, None)])
def test_measure_ramp_recovers_the_wedge_from_its_depth(azimuth, width, footprints):
    """The wedge is ray-cast (fixtures.published_from_sim) into depth and mask with the published pixel
    convention. With its slope in view the size is measured to a fiftieth of a pixel's footprint (depth / fx, 5 mm
    at 320 px and 6.4 mm at 256 px here); seen from behind, from a side face's edge, to two footprints; straight
    from behind (no slope, no side) not at all."""
    from rigidbench.blender.assets.standin import ramp_mesh

    L, H, W = 0.56, 0.37, 0.33
    p_pub, q_pub = np.array([0.2, -0.1, 0.902]), quat_z(25.0)
    centre, q_ours = ramp_from_published(p_pub, q_pub, L, H)
    height = width * 3 // 4
    R_c, t_c = cm.camera_pose(centre, azimuth + 25.0, 10.0, 1.6)
    fx = 35 / 36 * width
    K = np.array([[fx, 0, width / 2], [0, fx, height / 2], [0, 0, 1.0]])
    dirs = pfs.blender_rays(K, R_c, width, height)
    mesh = ramp_mesh(L, H, W)
    s = pfs.cast_mesh(t_c, dirs, mesh.vertices, mesh.faces, centre, q_ours).reshape(height, width)
    depth = np.where(np.isfinite(s), s, np.inf)
    got = measure_ramp(depth, np.isfinite(s), K, R_c, t_c, p_pub, q_pub)
    if footprints is None:
        assert got is None
        return
    assert got == pytest.approx((L, H, W), abs=footprints * 1.6 / fx)
    assert measure_ramp(depth, np.zeros_like(np.isfinite(s)), K, R_c, t_c, p_pub, q_pub) is None


def trajectory(positions, quats=None) -> Trajectory:
    positions = np.asarray(positions, float)
    quats = np.tile([1.0, 0, 0, 0], positions.shape[:2] + (1,)) if quats is None else quats
    return Trajectory(names=("a", "b"), roles=("active", "active"), fps=24.0, positions_m=positions, quat_wxyz=quats)


def test_compare_measures_metres_pixels_and_degrees_over_the_first_second():
    T = 49
    t = np.arange(T) / 24.0
    base = np.zeros((2, T, 3))
    base[0, :, 2] = 1.0 - 0.5 * 9.81 * np.minimum(t, 0.4) ** 2
    base[1, :, 0] = 0.3
    moved = base.copy()
    moved[1, 12:, 0] += 0.05  # actor b 5 cm off from frame 12
    moved[0, 30:, 1] += 0.2  # actor a off only after the window
    quats = np.tile([1.0, 0, 0, 0], (2, T, 1))
    quats[0, 24:] = quat_z(10.0)
    R_c, t_c = cm.camera_pose((0, 0, 0.5), 0.0, 10.0, 2.0)
    K = cm.intrinsics(35, 36, 640, 352)
    d = compare(trajectory(base), trajectory(moved, quats), ["a", "b"], K, R_c, t_c)
    assert d.window_frames == 25 and d.clip_frames == 49
    assert d.max_m == pytest.approx(0.05) and d.final_m == pytest.approx(0.05) and d.first_frame_over == 12
    assert d.worst_actor == "b" and d.clip_max_m == pytest.approx(0.2)
    uv0, _ = cm.project(base[1, 12:25], K, R_c, t_c)
    uv1, _ = cm.project(moved[1, 12:25], K, R_c, t_c)
    assert d.max_px == pytest.approx(np.linalg.norm(uv1 - uv0, axis=-1).max())
    assert d.max_deg == pytest.approx(10.0) and d.final_deg == pytest.approx(10.0)
    same = compare(trajectory(base), trajectory(base), ["a", "b"], K, R_c, t_c)
    assert same.max_m == 0.0 and same.first_frame_over is None and same.max_deg == 0.0
    assert 0.05 > RESIM_TOLERANCE_M  # the 5 cm shift above is beyond the tolerance


def test_the_table_counts_envelopes_and_summarises_each_task():
    def row(sid, task, outcome, max_m=None):
        from rigidbench.datasets.resimulate import Drift

        drift = None if max_m is None else Drift(25, max_m, max_m, 10 * max_m, 10 * max_m, 1.0, 1.0, 49, max_m, max_m,
                                                 float("nan"), 1.0, "a", None)
        return ResimRow(sid, task, "in_distribution", outcome, "ok" if outcome == "reproduced" else "no envelope",
                        None if outcome == "reproduced" else "why", drift)

    table = ResimTable([row("1", "bounce", "reproduced", 0.001), row("2", "bounce", "drifts", 0.05),
                        row("3", "bounce", "reproduced", 0.002), row("4", "free_fall", "cannot"),
                        row("5", "free_fall", "failed")])
    doc = table.to_dict()
    assert doc["examples"] == 5 and doc["with_envelope"] == 2 and table.with_envelope == ["1", "3"]
    bounce, free_fall, total = doc["by_task"]
    assert bounce["task"] == "bounce" and bounce["count"] == 3 and bounce["with_envelope"] == 2
    assert bounce["share_within_tolerance"] == pytest.approx(2 / 3) and bounce["median_max_m"] == pytest.approx(0.002)
    assert free_fall["cannot"] == 1 and free_fall["failed"] == 1 and free_fall["median_max_m"] is None
    assert total["count"] == 5 and total["share_within_tolerance"] == pytest.approx(0.4)
    assert doc["rows"][0]["drift"]["clip_max_px"] is None  # NaN written as null
    assert table.envelope_examples()["2"] == {"status": "no envelope", "reason": "why"}
