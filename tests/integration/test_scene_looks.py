"""Scene looks: each scene's signature feature is there, where the benchmark's cameras look.

Cheap checks on the built environments (no full renders): the beach has a blue daytime sky and
a sea below the horizon, the mural covers the walls the cameras see behind the low table at
the height they see, the japandi table has chairs round it, and the reworked rooms are not lit
to white.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

bpy = pytest.importorskip("bpy", reason="bpy (Blender as a Python module) is not installed; "
                                        "install the 'blender' extra")

from rigidbench.blender.assets.scenes import build_environment  # noqa: E402
from rigidbench.config import registry  # noqa: E402

pytestmark = pytest.mark.integration

REG = registry()


def _world_vertices(ob) -> np.ndarray:
    co = np.empty(len(ob.data.vertices) * 3, np.float32)
    ob.data.vertices.foreach_get("co", co)
    m = np.array(ob.matrix_world)
    return co.reshape(-1, 3).astype(float) @ m[:3, :3].T + m[:3, 3]


def _by_kind(env, kind: str) -> list:
    return [ob for ob in env.occluders if ob.name.rsplit("_", 1)[0].endswith(f"_{kind}")]


def test_beach_has_a_blue_sky_and_a_sea_to_the_horizon(empty_scene):
    env = build_environment(REG.scenes["beach_gazebo"])
    nodes = env.world.node_tree.nodes
    sky = [n for n in nodes if n.bl_idname == "ShaderNodeTexSky"]
    assert sky and sky[0].sky_type == "NISHITA", "the beach needs a daytime sky, not an interior HDRI"
    assert 10.0 < math.degrees(sky[0].sun_elevation) < 80.0, "a daytime sun, above the horizon"
    # A physical sky is blue: Rayleigh scattering. Check the material the sea uses is blue-dominant too.
    sea = _by_kind(env, "sea")
    assert len(sea) == 1
    v = _world_vertices(sea[0])
    assert v[:, 2].max() < 0.0 and np.ptp(v[:, 0]) > 1000.0, "a wide sea below the deck"
    sand = _by_kind(env, "sand")
    assert len(sand) == 1
    s = _world_vertices(sand[0])
    centre = np.mean([o.location[:2] for o in env.supports.values()], axis=0)
    top = s[s[:, 2] > s[:, 2].max() - 1e-6]
    reach = np.linalg.norm(top[:, :2] - centre, axis=1)
    # the beach ends within ~8-18 m so the sea shows between it and the horizon from a 1-2 m high camera
    assert 6.0 < reach.min() < 12.0 and reach.max() < 20.0, (reach.min(), reach.max())
    assert s[:, 2].max() > v[:, 2].max(), "the sand stands above the water"
    bsdf = next(n for n in sea[0].active_material.node_tree.nodes if n.bl_idname == "ShaderNodeBsdfPrincipled")
    r, g, b, _ = bsdf.inputs["Base Color"].default_value
    assert b > r and b > 0.05, "the sea is blue"
    assert any(l.data.type == "SUN" for l in env.lights), "sunlight casts shadows on the deck"


def test_beach_sky_renders_blue(empty_scene):
    """A tiny render of the sky just above the horizon: blue, not sunset orange or grey."""
    env = build_environment(REG.scenes["beach_gazebo"])
    scene = bpy.context.scene
    cam_data = bpy.data.cameras.new("look")
    cam_data.lens = 35.0
    cam = bpy.data.objects.new("look", cam_data)
    scene.collection.objects.link(cam)
    cam.location = (0.0, 0.0, 1.5)
    cam.rotation_euler = (math.radians(100.0), 0.0, 0.0)  # 10 degrees above the horizon, toward +y
    scene.camera = cam
    for ob in env.occluders:  # only the sky
        ob.hide_render = True
    scene.render.engine = "CYCLES"
    scene.cycles.samples = 4
    scene.cycles.use_denoising = False
    scene.render.resolution_x, scene.render.resolution_y = 32, 18
    scene.view_settings.view_transform = "Standard"
    bpy.ops.render.render()
    out = bpy.data.images["Render Result"]
    path = bpy.app.tempdir + "sky.png"
    out.save_render(path)
    img = bpy.data.images.load(path)
    px = np.array(img.pixels[:]).reshape(18, 32, 4)[..., :3]
    mean = px.mean((0, 1))
    assert mean[2] > mean[0] + 0.05, f"sky colour {mean} is not blue"
    assert 0.25 < mean.mean() < 0.97, f"sky brightness {mean} (not black, not clipped)"


def test_mural_is_on_every_wall_at_camera_height(empty_scene):
    """The benchmark's cameras circle the low table: whatever wall is behind it must carry butterflies."""
    from rigidbench.blender.assets import _paint

    env = build_environment(REG.scenes["butterfly_mural_room"])
    walls = [ob for ob in env.occluders if "_wall_" in ob.name]
    assert len(walls) == 4
    for ob in walls:
        assert ob.active_material is not None and ob.active_material.name.endswith("_mural"), ob.name
    # most butterflies fly at 0.25-1.7 m on the 2.8 m wall: the lower-middle rows are the most colourful
    img = _paint.butterfly_mural()
    sat = img.max(-1) - img.min(-1)
    h = img.shape[0]
    low = (sat[int(h * 0.4):int(h * 0.92)] > 0.4).mean()
    high = (sat[:int(h * 0.3)] > 0.4).mean()
    assert low > 0.12 and low > 2 * high, (low, high)


def test_japandi_table_has_chairs_round_it(empty_scene):
    scene = REG.scenes["modern_japandi_dining"]
    env = build_environment(scene)
    table = scene.support("table")
    L, W = table.size_m
    cx, cy, top = table.centre_m
    chairs = _by_kind(env, "chair")
    near = []
    for ob in chairs:
        v = _world_vertices(ob)
        # distance of the chair's footprint from the table's rectangle (table axis-aligned)
        dx = max(abs(ob.location.x - cx) - L / 2, 0.0)
        dy = max(abs(ob.location.y - cy) - W / 2, 0.0)
        if math.hypot(dx, dy) < 1.2:
            near.append(ob)
            assert v[:, 2].max() > top + 0.05, f"{ob.name}: its back shows above the table top"
    assert len(near) >= 4, [ob.name for ob in chairs]
    sides = {(np.sign(round(ob.location.x - cx, 2)) if abs(ob.location.y - cy) < 0.01 else 0,
              np.sign(round(ob.location.y - cy, 2))) for ob in near}
    assert len(sides) >= 3, "chairs on at least three sides"


@pytest.mark.parametrize("scene_id", ["minimal_white_kitchen", "modular_flat", "modern_japandi_dining",
                                      "butterfly_mural_room"])
def test_reworked_rooms_have_directional_light_and_no_white_walls(empty_scene, scene_id):
    env = build_environment(REG.scenes[scene_id])
    assert any(l.data.type == "SUN" for l in env.lights), "a sun through the open top gives shadows"
    fill = [l for l in env.lights if "_fill_" in l.name]
    sun = next(l for l in env.lights if l.data.type == "SUN")
    assert all(f.data.energy <= 150.0 for f in fill), "a soft fill, not a flat wash"
    assert sun.data.energy >= 0.5
    for ob in (o for o in env.occluders if "_wall_" in o.name):
        mat = ob.active_material
        bsdf = next((n for n in mat.node_tree.nodes if n.bl_idname == "ShaderNodeBsdfPrincipled"), None)
        base = bsdf.inputs["Base Color"]
        if base.is_linked:  # a tone mix: check the brighter end
            mix = base.links[0].from_node
            cols = [i.default_value for i in mix.inputs if i.type == "RGBA" and not i.is_linked]
            lum = max(0.2126 * c[0] + 0.7152 * c[1] + 0.0722 * c[2] for c in cols) if cols else 0.0
        else:
            c = base.default_value
            lum = 0.2126 * c[0] + 0.7152 * c[1] + 0.0722 * c[2]
        assert lum < 0.75, f"{ob.name}: wall albedo {lum:.2f} (linear) reads as blown-out white"


def test_white_kitchen_counter_wall_has_decor_at_eye_height(empty_scene):
    """Over the counter only flat things may hang (the clear column): a rail and prints at 1.1-1.6 m."""
    env = build_environment(REG.scenes["minimal_white_kitchen"])
    hung = [ob for ob in env.occluders if any(k in ob.name for k in ("_rail_", "_art_", "_shelf_"))]
    heights = [(_world_vertices(ob)[:, 2].min(), _world_vertices(ob)[:, 2].max()) for ob in hung]
    assert sum(1 for lo, hi in heights if lo < 1.6 and hi > 1.0) >= 3, heights


def _window_hiders(env, scene_id: str, reach_m: float, cover: float) -> list[tuple[str, str]]:
    """(window, item) pairs where a furnishing item within ``reach_m`` of a window's wall spans more than
    ``cover`` of the opening's height and overlaps it along the wall (curtains, plants and the like excepted)."""
    from rigidbench.blender.assets.scenes import WINDOW_DRESSING

    def kind(ob) -> str:
        return ob.name[len(scene_id) + 1:].rsplit("_", 1)[0]

    boxes = {ob.name: (_world_vertices(ob).min(0), _world_vertices(ob).max(0)) for ob in env.occluders}
    found = []
    for win in (ob for ob in env.occluders if kind(ob) == "window"):
        lo, hi = boxes[win.name]
        normal = int(np.argmin((hi - lo)[:2]))  # the frame is thin across its wall
        along = 1 - normal
        for ob in env.occluders:
            k = kind(ob)
            if k in WINDOW_DRESSING or k.startswith(("wall", "floor")) or ob.name == win.name:
                continue
            a, b = boxes[ob.name]
            near = a[normal] < hi[normal] + reach_m and b[normal] > lo[normal] - reach_m
            overlap_along = min(b[along], hi[along]) - max(a[along], lo[along])
            overlap_up = min(b[2], hi[2]) - max(a[2], lo[2])
            if near and overlap_along > 0.05 and overlap_up > cover * (hi[2] - lo[2]):
                found.append((win.name, ob.name))
    return found


@pytest.mark.parametrize("scene_id", sorted(REG.scenes))
def test_no_bookcase_or_picture_hides_a_window(empty_scene, scene_id):
    """A bookcase stood in front of the mural room's window, and a print hung over one in the luxury kitchen
    and two bookcases over the loft's: wall items now slide beside the windows (Kit.on_wall)."""
    from rigidbench.blender.assets.scenes import WINDOW_COVER, WINDOW_REACH_M

    env = build_environment(REG.scenes[scene_id])
    assert _window_hiders(env, scene_id, WINDOW_REACH_M - 0.05, WINDOW_COVER + 0.05) == []
