"""Bullet simulation through bpy on hand-built specs: physical checks, contacts, files, determinism."""

from __future__ import annotations

import json
import math
import subprocess
import sys
import textwrap

import numpy as np
import pytest

from fixtures.blender import requires_bpy
from fixtures.scenes import (SUPPORT_TOP_M, ball_chain_spec, bounce_spec, drop_into_cluster_spec, free_fall_spec,
                             make_spec, ramp_collision_spec, resting)

from rigidbench.groundtruth.contacts import quat_to_matrix
from rigidbench.groundtruth.trajectory import Trajectory, load_contacts
from rigidbench.scene_spec.types import SceneSpec

pytestmark = pytest.mark.integration

BULLET_ERP = 0.2  # Bullet's default error-reduction parameter for penetration recovery


def _simulate(spec, reg):
    from rigidbench.blender.physics import simulate

    return simulate(spec, reg)


def _damped_fall_m(t: np.ndarray, g: float, k: float) -> np.ndarray:
    """Distance fallen from rest under gravity g with linear drag rate k (1/s)."""
    return (g / k) * (t - (1 - np.exp(-k * t)) / k)


def _damped_apex_m(v0: float, g: float, k: float) -> float:
    """Rise height of a body thrown up at v0 with linear drag rate k (1/s)."""
    return v0 / k - (g / k ** 2) * math.log(1 + k * v0 / g)


def _lowest_point_m(reg, spec, traj, name: str, frame: int) -> float:
    """World z of the lowest vertex of the collision hull of ``name`` at ``frame``."""
    from rigidbench.blender.physics import body_mesh

    i = traj.index(name)
    verts = body_mesh(spec.body(name), reg).vertices @ quat_to_matrix(traj.quat_wxyz[i, frame]).T
    return float((verts + traj.positions_m[i, frame])[:, 2].min())


@pytest.fixture(scope="module")
def free_fall(reg):
    """The apple free-fall spec and its simulation."""
    spec = free_fall_spec(reg, "apple", drop_m=0.6)
    return spec, _simulate(spec, reg)


@requires_bpy
def test_free_fall_follows_damped_gravity(reg, free_fall):
    spec, result = free_fall
    traj = result.trajectory
    t = traj.times_s
    early = t <= 0.3 + 1e-9
    z0 = traj.positions_m[0, 0, 2]
    assert z0 == pytest.approx(spec.world_bodies()[0].position_m[2], abs=1e-6)
    k = -math.log(1 - spec.sim.linear_damping)
    analytic = z0 - _damped_fall_m(t[early], spec.sim.gravity_m_s2, k)
    err = traj.positions_m[0, early, 2] - analytic
    assert np.abs(err).max() <= 0.002
    # Bullet integrates semi-implicitly (velocity first) at fps*substeps Hz, which lowers the body
    # by g*t*dt/2 relative to the exact solution: the error is that bias, not noise.
    dt = 1.0 / (spec.sim.fps * spec.sim.substeps)
    assert np.allclose(err, -spec.sim.gravity_m_s2 * t[early] * dt / 2, atol=1e-4)
    # Straight down, no spin.
    assert np.allclose(traj.positions_m[0, early, :2], traj.positions_m[0, 0, :2], atol=1e-6)
    assert np.allclose(np.abs(traj.quat_wxyz[0, early] @ traj.quat_wxyz[0, 0]), 1.0, atol=1e-6)


@requires_bpy
def test_free_fall_lands_on_support_with_upward_contact(reg, free_fall):
    spec, result = free_fall
    name = result.trajectory.names[0]
    gap = _lowest_point_m(reg, spec, result.trajectory, name, -1) - SUPPORT_TOP_M
    assert -0.0005 <= gap <= 0.003
    on_support = [c for c in result.contacts if c.a == name and c.b == "support"]
    assert on_support and on_support[-1].frame == spec.sim.frames - 1
    # Impact happens between frames; a small rebound can keep the first sampled contact a few frames later.
    impact_frame = math.ceil(math.sqrt(2 * 0.6 / spec.sim.gravity_m_s2) * spec.sim.fps)
    assert impact_frame <= on_support[0].frame <= impact_frame + 3
    last = on_support[-1]
    assert 1 <= len(last.points_m) <= 5
    assert np.allclose(last.normals, [0.0, 0.0, 1.0], atol=1e-3)
    assert np.all(np.abs(np.array(last.distances_m)) <= 0.003)
    assert not [c for c in result.contacts if c.b == "floor"]


@requires_bpy
@pytest.mark.parametrize("asset, drop_m", [("baseball", 0.6), ("tennis_ball", 0.55)])
def test_bounce_apex_matches_restitution_product_plus_penetration_recovery(reg, asset, drop_m):
    spec = bounce_spec(reg, asset, drop_m=drop_m)
    result = _simulate(spec, reg)
    traj = result.trajectory
    sim = spec.sim
    g, k = sim.gravity_m_s2, -math.log(1 - sim.linear_damping)
    z = traj.positions_m[0, :, 2]
    # Height of the centre when the hulls touch: top face + half height + both collision margins.
    z_contact = SUPPORT_TOP_M + reg.object(asset).size_m[2] / 2 + sim.active_margin_m + sim.passive_margin_m
    # Replay Bullet's substeps (gravity, damping, then position) up to the first penetrating one.
    dt, damp = 1.0 / (sim.fps * sim.substeps), (1 - sim.linear_damping) ** (1.0 / (sim.fps * sim.substeps))
    zz, v = z[0], 0.0
    while zz >= z_contact:
        v = (v - g * dt) * damp
        zz += v * dt
    impact_speed, penetration = -v, z_contact - zz
    e = reg.object(asset).physics.restitution * spec.support.physics.restitution
    # Bullet multiplies the restitutions; its Baumgarte push-out adds ERP * penetration / dt.
    rebound = e * impact_speed + BULLET_ERP * penetration / dt
    predicted_apex = _damped_apex_m(rebound, g, k)
    bounce = int(np.nonzero(np.diff(z) > 1e-3)[0][0])  # first frame that moves up
    flight = np.arange(bounce + 1, bounce + 1 + int(2 * rebound / g * sim.fps))  # frames surely airborne
    coeff = np.polyfit(traj.times_s[flight], z[flight], 2)
    apex = coeff[2] - coeff[1] ** 2 / (4 * coeff[0]) - z_contact
    assert apex == pytest.approx(predicted_apex, rel=0.15)
    # The pure restitution product is the floor of the rebound, never exceeded from below.
    assert apex >= 0.85 * _damped_apex_m(e * impact_speed, g, k)
    # Comes to rest on the support: lowest mesh point a hair above the top face.
    for f in range(sim.frames - 8, sim.frames):
        gap = _lowest_point_m(reg, spec, traj, traj.names[0], f) - SUPPORT_TOP_M
        assert -0.0005 <= gap <= 0.003
    assert np.abs(traj.linear_velocity_m_s[0, -1, 2]) < 0.05


def _slope_coordinate(spec, traj, name: str, descends_plus: bool) -> np.ndarray:
    """Signed distance (T,) m along the task's +x axis (or -x), from the support centre."""
    yaw = math.radians(spec.task_rotation_deg)
    axis = np.array([math.cos(yaw), math.sin(yaw), 0.0]) * (1 if descends_plus else -1)
    return (traj.positions_m[traj.index(name)] - np.array(spec.support.centre_m)) @ axis


@requires_bpy
def test_ramp_objects_roll_down_and_reach_the_foot(reg):
    spec = ramp_collision_spec(reg, task_rotation_deg=30.0)
    result = _simulate(spec, reg)
    traj = result.trajectory
    assert traj.roles == ("passive", "passive", "active", "active")
    for ramp_name, obj, plus in (("ramp_a", "orange_0", True), ("ramp_b", "apple_1", False)):
        ramp = spec.body(ramp_name)
        i = traj.index(ramp_name)
        assert np.allclose(traj.positions_m[i], traj.positions_m[i, 0], atol=1e-9)  # passive ramps stay put
        s = _slope_coordinate(spec, traj, obj, plus)
        theta = math.atan2(ramp.ramp.height_m, ramp.ramp.length_m)
        speed = np.diff(s) * spec.sim.fps
        assert np.all(np.diff(speed[:6]) > 0)  # speeds up downhill
        coeff = np.polyfit(traj.times_s[:6], s[:6] / math.cos(theta), 2)
        # A rolling ball accelerates at 5/7 g sin(theta), less a little for the damping; sliding
        # would give g sin(theta).
        rolling = 5 / 7 * spec.sim.gravity_m_s2 * math.sin(theta)
        assert 0.85 * rolling <= 2 * coeff[0] <= 1.02 * rolling
        foot = abs(ramp.position_m[0]) - ramp.ramp.length_m / 2  # the feet face each other
        assert s.max() > -foot, f"{obj} never reached the foot of {ramp_name}"
        # While on the slope, the contact normal is the slope's normal, leaning downhill.
        yaw = math.radians(spec.task_rotation_deg)
        sign = 1 if plus else -1
        slope_normal = np.array([sign * math.sin(theta) * math.cos(yaw), sign * math.sin(theta) * math.sin(yaw),
                                 math.cos(theta)])
        on_slope = [c for c in result.contacts if c.a == obj and c.b == ramp_name and c.frame < 6]
        assert [c.frame for c in on_slope] == list(range(6))
        for c in on_slope:
            assert np.allclose(c.normals, slope_normal, atol=1e-4)
    pairs = {(c.a, c.b) for c in result.contacts}
    assert ("orange_0", "apple_1") in pairs  # they meet between the ramps
    assert ("orange_0", "ramp_a") in pairs and ("apple_1", "ramp_b") in pairs


@requires_bpy
def test_ball_chain_striker_sets_first_row_object_moving(reg):
    spec = ball_chain_spec(reg, "baseball", "apple")
    result = _simulate(spec, reg)
    traj = result.trajectory
    first_hit = [c.frame for c in result.contacts if {c.a, c.b} == {"baseball_0", "apple_1"}]
    assert first_hit, "the striker never touched the first row object"
    hit = min(first_hit)
    row = traj.positions_m[traj.index("apple_1")]
    striker = traj.positions_m[traj.index("baseball_0")]
    # At rest (beyond settling onto the support from its 1 mm placement clearance) until the striker reaches
    # it: when it first moves, the two centres are no farther apart than the sum of their half sizes plus
    # a few millimetres (margins, hull facets and the striker's rebound within one frame).
    moved = int(np.nonzero(np.linalg.norm(row - row[0], axis=1) > 0.002)[0][0])
    reach = (reg.object("baseball").size_m[0] + reg.object("apple").size_m[0]) / 2
    assert np.linalg.norm(striker[moved] - row[moved]) <= reach + 0.005
    assert np.linalg.norm(striker[moved - 1] - row[moved - 1]) > reach
    # The contact is reported with the impact; frames sample it at 24 fps, so the impact itself may
    # fall between two frames and the bodies be a few millimetres apart again at the next ones.
    assert moved - 1 <= hit <= moved + 3
    assert row[-1, 0] - row[0, 0] > 0.02  # pushed along +x after it


@requires_bpy
def test_drop_into_cluster_faller_hits_a_member(reg):
    spec = drop_into_cluster_spec(reg, "food_can", "apple")
    result = _simulate(spec, reg)
    members = {"food_can_0", "food_can_1", "food_can_2"}
    hits = [c for c in result.contacts if "apple_3" in (c.a, c.b) and ({c.a, c.b} & members)]
    assert hits
    fall_frames = math.ceil(math.sqrt(2 * 0.6 / spec.sim.gravity_m_s2) * spec.sim.fps)
    assert fall_frames <= min(c.frame for c in hits) <= fall_frames + 3
    for c in hits:
        assert 1 <= len(c.points_m) <= 5
        assert np.allclose(np.linalg.norm(c.normals, axis=1), 1.0)
    # Members start on the support and are in contact with it from frame 0.
    for m in members:
        assert any(c.frame == 0 and c.a == m and c.b == "support" for c in result.contacts)


@requires_bpy
def test_write_simulation_round_trips(reg, free_fall, tmp_path):
    from rigidbench.blender.physics import write_simulation

    spec, result = free_fall
    out = write_simulation(tmp_path / "example", spec, result)
    assert sorted(p.name for p in out.iterdir()) == ["contacts.json", "scene_spec.json", "trajectories.npz"]
    assert [p.name for p in tmp_path.iterdir()] == ["example"]  # no temporary directory left behind
    assert SceneSpec.from_json((out / "scene_spec.json").read_text()) == spec
    traj = Trajectory.load(out / "trajectories.npz")
    assert np.array_equal(traj.positions_m, result.trajectory.positions_m)
    assert load_contacts(out / "contacts.json") == result.contacts
    doc = json.loads((out / "contacts.json").read_text())
    assert doc["frames"] == spec.sim.frames and doc["tolerance_m"] == reg.sim.contact_tolerance_m
    with pytest.raises(FileExistsError):
        write_simulation(out, spec, result)
    write_simulation(out, spec, result, overwrite=True)
    assert [p.name for p in tmp_path.iterdir()] == ["example"]


@requires_bpy
def test_no_state_leaks_between_examples(reg):
    spec = ball_chain_spec(reg, "baseball", "apple")
    first = _simulate(spec, reg).trajectory
    _simulate(drop_into_cluster_spec(reg), reg)
    again = _simulate(spec, reg).trajectory
    assert np.array_equal(first.positions_m, again.positions_m)
    assert np.array_equal(first.quat_wxyz, again.quat_wxyz)


@requires_bpy
def test_same_spec_is_bitwise_identical_across_processes(reg, tmp_path):
    spec = ramp_collision_spec(reg, task_rotation_deg=17.0)
    spec_path = tmp_path / "spec.json"
    spec_path.write_text(spec.to_json())
    script = textwrap.dedent("""
        import sys
        from pathlib import Path
        from rigidbench.blender.physics import simulate_to_dir
        from rigidbench.scene_spec.types import SceneSpec
        spec = SceneSpec.from_json(Path(sys.argv[1]).read_text())
        simulate_to_dir(spec, sys.argv[2])
    """)
    outs = []
    for k in range(2):
        out = tmp_path / f"run{k}"
        subprocess.run([sys.executable, "-c", script, str(spec_path), str(out)], check=True, timeout=120,
                       capture_output=True)
        outs.append(out)
    a, b = (Trajectory.load(o / "trajectories.npz") for o in outs)
    assert np.array_equal(a.positions_m, b.positions_m) and np.array_equal(a.quat_wxyz, b.quat_wxyz)
    assert (outs[0] / "contacts.json").read_bytes() == (outs[1] / "contacts.json").read_bytes()
    assert np.abs(a.positions_m[:, -1] - a.positions_m[:, 0]).max() > 0.05  # something actually moved


@requires_bpy
def test_scene_edits_after_simulation_do_not_resimulate(reg):
    import bpy

    spec = ball_chain_spec(reg, "baseball", "apple")
    traj = _simulate(spec, reg).trajectory
    scene = bpy.context.scene
    striker = bpy.data.objects["baseball_0"]
    # What a renderer does next: materials, a child model, hiding the physics stand-in.
    striker.data.materials.append(bpy.data.materials.new("paint"))
    child = bpy.data.objects.new("model", bpy.data.meshes.new("model"))
    scene.collection.objects.link(child)
    child.parent = striker
    striker.hide_render = True
    for f in (30, 49, 5, 20):
        scene.frame_set(f)
        assert np.array_equal(np.array(striker.matrix_world.translation), traj.positions_m[1, f - 1].astype(np.float32))


def test_scene_bodies_add_support_and_floor_below_the_actors(reg):
    from rigidbench.blender.physics import scene_bodies

    spec = ball_chain_spec(reg, task_rotation_deg=40.0)
    bodies = scene_bodies(spec, reg)
    assert [b.name for b in bodies] == [b.name for b in spec.bodies] + ["support", "floor"]
    assert [b.collision_shape for b in bodies] == ["MESH"] + ["CONVEX_HULL"] * 4 + ["MESH", "BOX"]
    for body in bodies:
        z = body.mesh.vertices[:, 2] + body.position_m[2]  # all rotations here are about +z
        if body.name == "support":
            assert z.max() == pytest.approx(SUPPORT_TOP_M) and body.physics == spec.support.physics
            corners = body.mesh.vertices[:, :2]
            assert np.ptp(corners[:, 0]) == pytest.approx(spec.support.size_m[0])
        elif body.name == "floor":
            assert z.max() == pytest.approx(0.0)
            assert (body.physics.friction, body.physics.restitution) == (reg.sim.passive_friction,
                                                                         reg.sim.passive_restitution)
        else:
            assert z.min() >= SUPPORT_TOP_M - 1e-9  # actors start on or above the support
    active = [b for b in bodies if b.role == "active"]
    assert all(b.margin_m == spec.sim.active_margin_m for b in active)
    assert all(b.margin_m == spec.sim.passive_margin_m for b in bodies if b.role == "passive")


def test_support_on_the_floor_has_no_separate_floor_and_names_are_reserved(reg):
    from rigidbench.blender.physics import scene_bodies

    spec = make_spec(reg, "free_fall", [resting(reg, "apple_0", "apple", 0.0, 0.0, "object")], support_top_m=0.0)
    assert [b.name for b in scene_bodies(spec, reg)] == ["apple_0", "support"]
    bad = make_spec(reg, "free_fall", [resting(reg, "support", "apple", 0.0, 0.0, "object")])
    with pytest.raises(ValueError, match="reserved"):
        scene_bodies(bad, reg)
