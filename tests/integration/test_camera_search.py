"""The camera search rejects views with something nearer than the action (docs/camera.md)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

bpy = pytest.importorskip("bpy", reason="bpy (Blender as a Python module) is not installed; "
                                        "run `make test`, which installs it")

from rigidbench import manifest  # noqa: E402
from rigidbench.blender.assets._mesh import box, to_object  # noqa: E402
from rigidbench.blender.camera import box_distance, camera_pose, check_view, framing_box, search_camera  # noqa: E402
from rigidbench.blender.render import build_search_scene  # noqa: E402
from rigidbench.groundtruth import camera_model as cm  # noqa: E402
from rigidbench.scene_spec.build import build_scene_spec  # noqa: E402


def _search(spec, settings, scene, objects, dressing):
    active = [dressing.render_objects[b.name] for b in spec.active]
    posed = {b.name: objects[b.name] for b in spec.bodies}
    return search_camera(spec, settings, scene, posed, active, actors=list(dressing.render_objects.values()),
                         scene_id=dressing.environment.scene_id)


def test_a_pillar_beside_the_camera_moves_it_elsewhere(reg):
    row = next(r for r in manifest.rows("eval", reg) if r.task == "free_fall")
    spec = build_scene_spec(row, reg)
    scene, objects, dressing = build_search_scene(spec, reg)
    unchecked = dataclasses.replace(reg.camera, max_obstruction=1.0)
    first = _search(spec, unchecked, scene, objects, dressing)
    view = check_view(scene, first, first.camera.relative_azimuth_deg, reg.camera,
                      {o.name for o in dressing.render_objects.values()}, dressing.environment.scene_id)
    assert view.obstruction <= reg.camera.max_obstruction  # the room alone leaves this view clear

    # a 3 m pillar 0.6 m in front of that camera, over the left quarter of the image
    R, t = camera_pose(first.camera)
    right, forward = R[:, 0], -R[:, 2]
    centre = t + 0.6 * forward - 0.25 * right
    pillar = to_object(box((0.15, 0.15, 3.0)), f"{dressing.environment.scene_id}_pillar_999", [])
    pillar.location = (float(centre[0]), float(centre[1]), 1.5)
    bpy.context.view_layer.update()
    blocked = check_view(scene, first, first.camera.relative_azimuth_deg, reg.camera,
                         {o.name for o in dressing.render_objects.values()}, dressing.environment.scene_id)
    assert blocked.obstruction > 0.05

    chosen = _search(spec, reg.camera, scene, objects, dressing)
    assert (chosen.task_rotation_deg, chosen.camera.azimuth_deg) != (first.task_rotation_deg, first.camera.azimuth_deg)
    # independently of the ray grid: no point of the pillar projects into the new image nearer than the action
    R2, t2 = camera_pose(chosen.camera)
    K = cm.intrinsics(chosen.camera.lens_mm, chosen.camera.sensor_width_mm, 1280, 704)
    g = np.linspace(-0.5, 0.5, 7)
    local = np.array([[x * 0.15, y * 0.15, z * 3.0] for x in g for y in g for z in g])
    uv, depth = cm.project(local + np.array(pillar.location), K, R2, t2)
    inside = (depth > 0) & (uv[:, 0] >= 0) & (uv[:, 0] < 1280) & (uv[:, 1] >= 0) & (uv[:, 1] < 704)
    lo, hi = framing_box(chosen, reg.camera.bbox_padding_m)
    assert not np.any(inside & (np.linalg.norm(local + np.array(pillar.location) - t2, axis=1) < box_distance(t2, lo, hi)))
