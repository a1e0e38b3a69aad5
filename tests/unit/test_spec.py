import math
import subprocess
import sys

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from rigidbench import manifest
from rigidbench.config import registry
from rigidbench.scene_spec import cluster, footprint
from rigidbench.scene_spec.build import SpecError, body_aabb, build_scene_spec, indefinite, make_prompt
from rigidbench.scene_spec.types import SceneSpec


@pytest.fixture(scope="module")
def reg():
    return registry()


@pytest.fixture(scope="module")
def rows(reg):
    return manifest.eval_rows(reg)


def test_every_eval_row_builds_and_round_trips_through_json(rows, reg):
    for row in rows:
        spec = build_scene_spec(row, reg)
        assert SceneSpec.from_json(spec.to_json()) == spec
        assert SceneSpec.from_json(spec.to_json()).to_json() == spec.to_json()


def test_same_seed_same_spec_in_another_process(rows, reg):
    code = ("from rigidbench import manifest; from rigidbench.config import registry; "
            "from rigidbench.scene_spec.build import build_scene_spec; r = registry(); "
            "print(build_scene_spec(manifest.eval_rows(r)[42], r).to_json())")
    out = subprocess.run([sys.executable, "-c", code], check=True, capture_output=True, text=True).stdout
    assert out.strip() == build_scene_spec(rows[42], reg).to_json()


def test_task_structure(rows, reg):
    expected = {"free_fall": (1, 0), "bounce": (1, 0), "ramp_collision": (2, 2), "ball_chain": (4, 1),
                "drop_into_cluster": (4, 0)}
    for row in rows:
        spec = build_scene_spec(row, reg)
        n_active = len(spec.active)
        n_ramps = sum(b.asset == "ramp" for b in spec.bodies)
        assert (n_active, n_ramps) == expected[row.task], row
        assert all(b.asset in row.allowed_objects for b in spec.active)
        assert len({b.name for b in spec.bodies}) == len(spec.bodies)


def test_tags_and_bounce_override(rows, reg):
    for row in rows:
        spec = build_scene_spec(row, reg)
        if row.task == "bounce":
            assert all("bouncy" in reg.object(b.asset).tags for b in spec.active)
            assert (spec.support.physics.restitution, spec.support.physics.friction) == (0.6, 0.3)
        else:
            assert (spec.support.physics.restitution, spec.support.physics.friction) == (0.3, 0.4)
        if row.task == "ramp_collision":
            assert all("rolling" in reg.object(b.asset).tags for b in spec.active)
        if row.task == "drop_into_cluster":
            assert all("stackable" in reg.object(b.asset).tags for b in spec.active if b.step == "cluster")


def test_drop_heights_and_resting_objects(rows, reg):
    for row in rows:
        spec = build_scene_spec(row, reg)
        for b in spec.active:
            bottom = body_aabb(b)[0][2]
            if b.step in ("object", "faller"):
                assert 0.50 <= bottom - 0.001 <= 0.70 + 1e-9
            if b.step in ("cluster", "row"):
                assert bottom == pytest.approx(0.001)


def test_ramp_placement_quarter_down_and_on_slope(rows, reg):
    for row in rows:
        if row.task != "ramp_collision":
            continue
        spec = build_scene_spec(row, reg)
        left, right = spec.body("ramp_a"), spec.body("ramp_b")
        gap = (right.position_m[0] - right.ramp.length_m / 2) - (left.position_m[0] + left.ramp.length_m / 2)
        assert 0.10 <= gap <= 0.15
        for ramp_name, obj in (("ramp_a", spec.active[0]), ("ramp_b", spec.active[1])):
            ramp = spec.body(ramp_name)
            shape = ramp.ramp
            sign = 1 if ramp_name == "ramp_a" else -1
            top_x = ramp.position_m[0] - sign * shape.length_m / 2
            theta = math.atan2(shape.height_m, shape.length_m)
            normal = np.array([sign * math.sin(theta), 0, math.cos(theta)])
            rel = np.array(obj.position_m) - np.array([top_x, ramp.position_m[1], shape.height_m])
            along = np.array([sign * math.cos(theta), 0, -math.sin(theta)]) @ rel
            assert along / math.hypot(shape.length_m, shape.height_m) == pytest.approx(0.25, abs=0.01)
            assert normal @ rel == pytest.approx(reg.object(obj.asset).size_m[2] / 2 + 0.001, abs=1e-9)


def test_ball_chain_row_spacing(rows, reg):
    for row in rows:
        if row.task != "ball_chain":
            continue
        spec = build_scene_spec(row, reg)
        ramp = spec.body("ramp")
        foot = ramp.position_m[0] + ramp.ramp.length_m / 2
        members = [b for b in spec.bodies if b.step == "row"]
        spans = [body_aabb(b) for b in members]
        assert 0.08 - 1e-9 <= spans[0][0][0] - foot <= 0.12 + 1e-9
        for (lo0, hi0), (lo1, hi1) in zip(spans, spans[1:]):
            assert 0.02 - 1e-9 <= lo1[0] - hi0[0] <= 0.04 + 1e-9


def test_footprint_fits_support_at_every_candidate_rotation(rows, reg):
    for row in rows:
        spec = build_scene_spec(row, reg)
        assert len(spec.rotation_candidates_deg) == 8
        for deg in spec.rotation_candidates_deg:
            rel = math.radians(deg - spec.support.long_axis_deg)
            assert footprint.fits(spec.footprint_m, spec.support.size_m, rel, tol=1e-7)
        world = spec.world_bodies()
        lo = np.min([body_aabb(b)[0] for b in spec.bodies], 0)
        hi = np.max([body_aabb(b)[1] for b in spec.bodies], 0)
        assert np.allclose((lo[:2] + hi[:2]) / 2, 0, atol=1e-9)
        assert world[0].position_m[2] == pytest.approx(spec.bodies[0].position_m[2] + spec.support.centre_m[2])


def test_azimuth_candidates_respect_task_ranges(rows, reg):
    for row in rows:
        spec = build_scene_spec(row, reg)
        ranges = reg.task(row.task).azimuth_ranges_deg
        assert all(any(lo <= a <= hi or lo <= a + 360 <= hi for lo, hi in ranges) for a in spec.azimuth_candidates_deg)
        assert all(a % 15 == 0 for a in spec.azimuth_candidates_deg)
    assert len(build_scene_spec(rows[0], reg).azimuth_candidates_deg) in (14,)  # ball chain: 7 + 7 angles


def test_prompt_articles():
    assert indefinite("Apple") == "an apple" and indefinite("Large die") == "a large die"
    assert indefinite("Energy-drink can") == "an energy-drink can"
    assert make_prompt("{object} is dropping.", {"object": "Apple"}) == "An apple is dropping."
    assert make_prompt("{a} and {b} are rolling down two ramps facing each other.",
                       {"a": "Orange", "b": "Toy duck"}) == \
        "An orange and a toy duck are rolling down two ramps facing each other."


def test_unfittable_task_reports_example(rows, reg, monkeypatch):
    import dataclasses

    row = next(r for r in rows if r.task == "ball_chain")
    scene = reg.scene(row.scene)
    tiny = dataclasses.replace(scene, supports=tuple(dataclasses.replace(s, size_m=(0.3, 0.2)) for s in scene.supports))
    small_reg = dataclasses.replace(reg, scenes={**reg.scenes, row.scene: tiny})
    with pytest.raises(SpecError, match=rf"example {row.sample_id}: task 'ball_chain'.*never fits support"):
        build_scene_spec(row, small_reg)


@settings(max_examples=60, deadline=None)
@given(n=st.integers(2, 6), seed=st.integers(0, 10_000), squeeze=st.floats(0.3, 1.0))
def test_cluster_relaxation_leaves_no_overlap(n, seed, squeeze):
    rng = np.random.default_rng(seed)
    radii = rng.uniform(0.02, 0.11, n)
    start = cluster.ring_positions(n, cluster.ring_radius(radii.max(), 0.005, n), rng.uniform(0, 6.28)) * squeeze
    relaxed = cluster.relax(start, radii)
    # Deliberately squeezed rings (down to 30% of the radius, overlaps of several cm) are pushed
    # apart to within pymunk's residual contact penetration, far below Bullet's 1 mm margin.
    assert cluster.max_overlap_m(relaxed, radii) <= 5e-4


@settings(max_examples=60, deadline=None)
@given(n=st.integers(2, 6), seed=st.integers(0, 10_000), gap=st.floats(0.003, 0.008))
def test_cluster_on_paper_ring_has_no_overlap(n, seed, gap):
    rng = np.random.default_rng(seed)
    radii = rng.uniform(0.02, 0.11, n)
    start = cluster.ring_positions(n, cluster.ring_radius(radii.max(), gap, n), rng.uniform(0, 6.28))
    relaxed = cluster.relax(start, radii)
    assert cluster.max_overlap_m(relaxed, radii) <= 2e-6  # pymunk's collision slop (1 micrometre)


def test_ring_radius_spacing():
    r, g = 0.04, 0.006
    for n in (3, 4, 5):
        pos = cluster.ring_positions(n, cluster.ring_radius(r, g, n), 0.0)
        assert np.linalg.norm(pos[0] - pos[1]) == pytest.approx(2 * r + g)
