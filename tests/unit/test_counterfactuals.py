"""The pure parts of the re-rendered failure modes: what each severity changes, offsets, donors, blending."""

import numpy as np
import pytest

from rigidbench.config import registry
from rigidbench.predictors import PREDICTORS, FailureMode, Kind
from rigidbench.predictors.counterfactuals import (depth_offsets, friction_change, gravity_change, mass_change,
                                               restitution_change)
from rigidbench.predictors.identity_swap import DONORS, blend_inside_masks, donor_for
from rigidbench.scene_spec.types import Body, BodyPhysics, SceneSpec, SimSpec, SupportSpec

IDENTITY = (1.0, 0.0, 0.0, 0.0)


@pytest.fixture(scope="module")
def reg():
    return registry()


def _body(name, role, mass, friction, restitution):
    return Body(name=name, asset="ramp" if role == "passive" else "apple", role=role, step=name,
                position_m=(0.0, 0.0, 0.1), quat_wxyz=IDENTITY, size_m=(0.1, 0.1, 0.1),
                physics=BodyPhysics(mass, friction, restitution))


@pytest.fixture()
def spec():
    sim = SimSpec(fps=24, frames=49, substeps=30, solver_iterations=20, gravity_m_s2=9.81, linear_damping=0.1,
                  angular_damping=0.5, active_margin_m=0.001, passive_margin_m=0.0001)
    bodies = (_body("ramp", "passive", 0.0, 0.4, 0.3), _body("a", "active", 0.2, 0.5, 0.15),
              _body("b", "active", 0.1, 0.6, 0.1), _body("c", "active", 0.4, 0.2, 0.5))
    return SceneSpec(sample_id="x", split="test", task="ball_chain", scene="s", surface="counter", seed=0,
                     partition="test", allowed_objects=("apple",), prompt="p",
                     support=SupportSpec("counter", (0.0, 0.0, 0.9), (2.0, 1.0), 0.0, BodyPhysics(0.0, 0.3, 0.6)),
                     bodies=bodies, footprint_m=(1.0, 1.0), rotation_candidates_deg=(0.0,), task_rotation_deg=0.0,
                     azimuth_candidates_deg=(0.0,), sim=sim)


@pytest.mark.parametrize("change", [gravity_change, restitution_change, friction_change, mass_change])
def test_zero_severity_changes_nothing(change, spec, reg):
    new_spec, new_reg = change(spec, reg, 0.0)
    assert new_spec == spec and new_reg.sim == reg.sim


def test_gravity_scales_by_one_plus_severity(spec, reg):
    assert gravity_change(spec, reg, 1.0)[0].sim.gravity_m_s2 == pytest.approx(19.62)
    new, _ = gravity_change(spec, reg, 0.5)
    assert new.sim.gravity_m_s2 == pytest.approx(14.715)
    assert new.bodies == spec.bodies and new.camera == spec.camera


def test_restitution_moves_every_surface_toward_elastic(spec, reg):
    new, new_reg = restitution_change(spec, reg, 0.5)
    # e + s (1 - e): 0.3 -> 0.65, 0.15 -> 0.575, 0.1 -> 0.55, 0.5 -> 0.75; support 0.6 -> 0.8.
    assert [b.physics.restitution for b in new.bodies] == pytest.approx([0.65, 0.575, 0.55, 0.75])
    assert new.support.physics.restitution == pytest.approx(0.8)
    e_floor = reg.sim.passive_restitution
    assert new_reg.sim.passive_restitution == pytest.approx(e_floor + 0.5 * (1 - e_floor))
    assert [b.physics.friction for b in new.bodies] == [b.physics.friction for b in spec.bodies]
    assert [b.physics.mass_kg for b in new.bodies] == [b.physics.mass_kg for b in spec.bodies]
    full, full_reg = restitution_change(spec, reg, 1.0)
    assert all(b.physics.restitution == pytest.approx(1.0) for b in full.bodies)
    assert full.support.physics.restitution == pytest.approx(1.0)
    assert full_reg.sim.passive_restitution == pytest.approx(1.0)


def test_friction_scales_every_surface_down(spec, reg):
    new, new_reg = friction_change(spec, reg, 0.25)
    assert [b.physics.friction for b in new.bodies] == pytest.approx([0.3, 0.375, 0.45, 0.15])
    assert new.support.physics.friction == pytest.approx(0.225)
    assert new_reg.sim.passive_friction == pytest.approx(0.75 * reg.sim.passive_friction)
    full, full_reg = friction_change(spec, reg, 1.0)
    assert all(b.physics.friction == 0.0 for b in full.bodies) and full_reg.sim.passive_friction == 0.0


def test_mass_alternates_heavier_and_lighter_active_actors(spec, reg):
    new, new_reg = mass_change(spec, reg, 0.5)  # factor 1 + 4 * 0.5 = 3
    assert [b.physics.mass_kg for b in new.bodies] == pytest.approx([0.0, 0.6, 0.1 / 3, 1.2])
    assert new_reg is reg and new.support == spec.support
    # Scaling every mass by one factor would change nothing; the ratio of neighbours must change.
    full, _ = mass_change(spec, reg, 1.0)
    ratio = full.bodies[1].physics.mass_kg / full.bodies[2].physics.mass_kg
    assert ratio == pytest.approx(25 * 0.2 / 0.1)


def test_depth_offsets_point_along_the_viewing_ray_toward_the_camera():
    positions = np.array([[[3.0, 4.0, 0.0], [0.0, 0.0, 2.0]]])  # (A=1, T=2, 3)
    off = depth_offsets(positions, np.zeros(3), 0.5)
    assert off.shape == (1, 2, 3)
    np.testing.assert_allclose(off[0, 0], [-0.3, -0.4, 0.0])
    np.testing.assert_allclose(off[0, 1], [0.0, 0.0, -0.5])
    assert not depth_offsets(positions, np.array([1.0, 1.0, 1.0]), 0.0).any()


def test_donor_table_pairs_configured_objects_with_different_ones(reg):
    assert set(DONORS) == set(reg.objects)
    for recipient, donor in DONORS.items():
        assert donor in reg.objects and donor != recipient
        assert donor_for(recipient, reg.objects) == donor


def test_donor_fallback_is_the_next_object_id():
    assert donor_for("user_mug", ["apple", "user_mug", "zebra"]) == "zebra"
    assert donor_for("zebra", ["apple", "zebra"]) == "apple"  # wraps around
    assert donor_for("apple", ["apple", "kiwi"]) == "kiwi"  # the table's donor (lemon) is not configured
    with pytest.raises(ValueError, match="no other configured object"):
        donor_for("apple", ["apple"])


def test_blend_changes_only_actor_pixels_after_frame_zero():
    ref = np.full((2, 2, 3, 3), 100, np.uint8)
    swapped = np.full((2, 2, 3, 3), 200, np.uint8)
    masks = np.zeros((2, 1, 2, 3), bool)
    masks[:, 0, 1, 2] = True
    out = blend_inside_masks(ref, swapped, masks, 0.25)
    assert out[1, 1, 2].tolist() == [125, 125, 125]
    out[1, 1, 2] = 100
    assert (out == 100).all()  # frame 0 and every pixel outside the mask untouched
    assert (blend_inside_masks(ref, swapped, masks, 1.0)[1, 1, 2] == 200).all()


def test_new_modes_are_registered():
    for name in ("identity-swap", "gravity", "restitution", "friction", "mass", "depth-offset"):
        info = PREDICTORS[name]
        assert info.kind == Kind.FAILURE_MODE and info.needs_blender and info.writes_state
        assert isinstance(info.create(), FailureMode)
