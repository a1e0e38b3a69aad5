"""render.dress_scene: every actor is its procedural model over a hidden physics body, in the scene's room."""

from __future__ import annotations

import dataclasses

import pytest

pytest.importorskip("bpy", reason="bpy (Blender as a Python module) is not installed; "
                           "run `make test`, which installs it")

from fixtures.scenes import free_fall_spec, ramp_collision_spec  # noqa: E402

from rigidbench.blender.physics import FLOOR_NAME, SUPPORT_NAME  # noqa: E402
from rigidbench.blender.render import build_search_scene  # noqa: E402


def test_every_actor_is_its_model_parented_to_its_hidden_physics_body(reg):
    spec = ramp_collision_spec(reg)  # two ramps (passive task geometry) and two objects
    scene, objects, dressing = build_search_scene(spec, reg)
    for k, body in enumerate(spec.bodies, start=1):
        shown, phys = dressing.render_objects[body.name], objects[body.name]
        assert shown is not phys and shown.parent is phys, body.name
        assert phys.hide_render and not shown.hide_render, body.name
        assert shown.pass_index == k and phys.pass_index == 0, body.name
        assert len(shown.data.materials) >= 1, body.name  # the model's own materials
    assert dressing.environment.scene_id == spec.scene and spec.support.name in dressing.environment.supports
    # the room provides the support and the floor, so their physics boxes are hidden as well
    assert set(dressing.hidden) == {b.name for b in spec.bodies} | {SUPPORT_NAME, FLOOR_NAME}
    assert objects[SUPPORT_NAME].hide_render and objects[FLOOR_NAME].hide_render
    assert scene.world is dressing.environment.world


def test_a_support_the_room_lacks_stays_visible_in_a_plain_material(reg):
    spec = free_fall_spec(reg)
    spec = dataclasses.replace(spec, support=dataclasses.replace(spec.support, name="not_in_this_room"))
    scene, objects, dressing = build_search_scene(spec, reg)
    support = objects[SUPPORT_NAME]
    assert not support.hide_render and SUPPORT_NAME not in dressing.hidden
    assert [m.name for m in support.data.materials] == ["rb_support"] and support.pass_index == 0
    assert objects[FLOOR_NAME].hide_render  # the room's floor still replaces the physics floor
