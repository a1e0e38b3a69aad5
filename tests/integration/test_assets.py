"""Procedural assets in Blender: objects fit their configured boxes, supports sit exactly where
the scene YAML says, user meshes load and fit, ramps are the physics wedge, and one object
renders in Cycles with its material."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

bpy = pytest.importorskip("bpy", reason="bpy (Blender as a Python module) is not installed; "
                                        "install the 'sim' extra to run the asset tests")

from rigidbench.blender.assets import _paint  # noqa: E402
from rigidbench.blender.assets.objects import build_object, build_ramp  # noqa: E402
from rigidbench.blender.assets.scenes import build_environment  # noqa: E402
from rigidbench.blender.assets.standin import ramp_mesh  # noqa: E402
from rigidbench.config import registry  # noqa: E402
from rigidbench.scene_spec.types import RampShape  # noqa: E402

pytestmark = pytest.mark.integration

REG = registry()


def local_vertices(ob) -> np.ndarray:
    """Mesh vertices in the object's frame. Returns (V,3) float64 m."""
    co = np.empty(len(ob.data.vertices) * 3, np.float32)
    ob.data.vertices.foreach_get("co", co)
    return co.reshape(-1, 3).astype(float)


def world_vertices(ob) -> np.ndarray:
    v = local_vertices(ob)
    m = np.array(ob.matrix_world)
    return v @ m[:3, :3].T + m[:3, 3]


def _uses_nodes(mat) -> bool:
    out = [n for n in mat.node_tree.nodes if n.bl_idname == "ShaderNodeOutputMaterial"]
    return bool(out) and out[0].inputs["Surface"].is_linked


@pytest.mark.parametrize("object_id", sorted(REG.objects))
def test_object_fits_its_configured_box(empty_scene, object_id):
    cfg = REG.object(object_id)
    ob = build_object(cfg, f"{object_id}_0")
    assert ob.name in empty_scene.objects and ob.type == "MESH"
    v = local_vertices(ob)
    lo, hi = v.min(0), v.max(0)
    size = np.asarray(cfg.size_m)
    np.testing.assert_allclose(hi - lo, size, rtol=0.10)
    np.testing.assert_allclose((lo + hi) / 2, 0.0, atol=0.01 * size.max())
    assert tuple(ob.location) == (0.0, 0.0, 0.0) and tuple(ob.scale) == (1.0, 1.0, 1.0)
    assert len(v) < 3000
    assert not ob.data.validate(), "mesh needed repairs"
    assert ob.data.materials and all(m is not None and _uses_nodes(m) for m in ob.data.materials)


def test_die_pips_are_on_the_right_faces():
    # opposite faces sum to 7, and the painted atlas tile of each face shows that many pips
    from scipy import ndimage

    pips = _paint.DIE_PIPS
    assert {pips["+x"] + pips["-x"], pips["+y"] + pips["-y"], pips["+z"] + pips["-z"]} == {7}
    img = _paint.die()
    tile = img.shape[0] // 2
    order = ("+x", "-x", "+y", "-y", "+z", "-z")
    for i, face in enumerate(order):
        r, c = divmod(i, 3)
        dark = img[r * tile:(r + 1) * tile, c * tile:(c + 1) * tile].mean(-1) < 0.4
        _, count = ndimage.label(dark)
        assert count == pips[face], face


def test_painters_are_deterministic():
    a = _paint.baseball.__wrapped__()
    b = _paint.baseball.__wrapped__()
    assert np.array_equal(a, b) and a.shape[-1] == 3 and 0.0 <= a.min() and a.max() <= 1.0


@pytest.mark.parametrize("scene_id", sorted(REG.scenes))
def test_scene_supports_are_exact(empty_scene, scene_id):
    scene = REG.scene(scene_id)
    env = build_environment(scene)
    assert set(env.supports) == {s.name for s in scene.supports}
    assert env.occluders and not set(map(id, env.occluders)) & set(map(id, env.supports.values()))
    assert env.lights and empty_scene.world is env.world
    for s in scene.supports:
        ob = env.supports[s.name]
        v = world_vertices(ob)
        top = v[:, 2].max()
        assert top == pytest.approx(s.centre_m[2], abs=1e-4)
        on_top = v[np.abs(v[:, 2] - top) < 1e-5]
        yaw = math.radians(s.long_axis_deg)
        rel = on_top[:, :2] - np.asarray(s.centre_m[:2])
        local = rel @ np.array([[math.cos(yaw), -math.sin(yaw)], [math.sin(yaw), math.cos(yaw)]])
        half = np.asarray(s.size_m) / 2
        np.testing.assert_allclose(local.min(0), -half, atol=1e-3)
        np.testing.assert_allclose(local.max(0), half, atol=1e-3)


@pytest.mark.parametrize("scene_id", ["hallway_interior", "modern_luxury_kitchen", "cozy_living_room"])
def test_supports_are_visible_from_many_azimuths(empty_scene, scene_id):
    # the benchmark camera stands 1.4-3 m away at 10 degrees elevation: most azimuths must see the support
    from mathutils import Vector

    scene = REG.scene(scene_id)
    build_environment(scene)
    depsgraph = bpy.context.evaluated_depsgraph_get()
    for s in scene.supports:
        goal = Vector((s.centre_m[0], s.centre_m[1], s.centre_m[2] + 0.04))
        clear = 0
        for k in range(24):
            az, el = math.radians(15 * k), math.radians(10)
            cam = goal + Vector((math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), math.sin(el))) * 2.2
            hit, *_ = empty_scene.ray_cast(depsgraph, cam, (goal - cam).normalized(),
                                           distance=(goal - cam).length - 0.05)
            clear += not hit
        assert clear >= 10, f"{scene_id}/{s.name}: only {clear} of 24 azimuths see the support"


def test_scene_style_hdri_override(empty_scene):
    scene = REG.scene("modern_loft")
    env = build_environment(dataclasses.replace(scene, style={**scene.style, "hdri": "forest.exr"}))
    images = [n.image for n in env.world.node_tree.nodes if n.bl_idname == "ShaderNodeTexEnvironment"]
    assert images and images[0].filepath.endswith("forest.exr")
    with pytest.raises(ValueError, match="style.hdri"):
        build_environment(dataclasses.replace(scene, style={**scene.style, "hdri": "moon.exr"}))


def test_user_obj_mesh_is_loaded_and_fitted(empty_scene, tmp_path):
    # a pyramid with its apex along the OBJ +y (up) axis, far from the origin
    path = tmp_path / "pyramid.obj"
    path.write_text("v 9 0 9\nv 13 0 9\nv 13 0 11\nv 9 0 11\nv 11 3 10\n"
                    "f 1 2 3 4\nf 1 5 2\nf 2 5 3\nf 3 5 4\nf 4 5 1\n")
    cfg = dataclasses.replace(REG.object("large_dice"), mesh_path=str(path), size_m=(0.12, 0.06, 0.09))
    before = set(bpy.data.objects)
    ob = build_object(cfg, "user_pyramid")
    assert set(bpy.data.objects) - before == {ob}, "imported helper objects must be removed"
    v = local_vertices(ob)
    assert len(v) == 5 and len(ob.data.polygons) == 5
    np.testing.assert_allclose(v.max(0) - v.min(0), cfg.size_m, rtol=1e-5)
    np.testing.assert_allclose((v.max(0) + v.min(0)) / 2, 0.0, atol=1e-6)
    apex = v[np.argmax(v[:, 2])]
    np.testing.assert_allclose(apex, [0.0, 0.0, 0.045], atol=1e-6)  # +y up in OBJ became +z up
    assert ob.data.materials[0] is not None
    # The collision hull comes from the same fitted vertices, and the import leaves nothing behind.
    from rigidbench.blender.assets.objects import object_vertices

    np.testing.assert_allclose(np.sort(object_vertices(cfg), axis=0), np.sort(v, axis=0), atol=1e-6)
    assert set(bpy.data.objects) - before == {ob}


def test_missing_user_mesh_names_the_config(empty_scene, tmp_path):
    cfg = dataclasses.replace(REG.object("apple"), mesh_path=str(tmp_path / "nope.glb"))
    with pytest.raises(FileNotFoundError, match="apple.yaml"):
        build_object(cfg, "missing")


@pytest.mark.parametrize("material_id", sorted(REG.materials))
def test_ramp_is_the_physics_wedge_with_metric_uvs(empty_scene, material_id):
    shape = RampShape(length_m=0.6, height_m=0.35, width_m=0.32, material=material_id)
    ob = build_ramp(shape, REG.material(material_id), "ramp_0")
    ref = ramp_mesh(0.6, 0.35, 0.32)
    np.testing.assert_allclose(local_vertices(ob), ref.vertices, atol=1e-6)
    faces = np.array([list(p.vertices) for p in ob.data.polygons])
    np.testing.assert_array_equal(faces, ref.faces)
    assert ob.data.materials[0].name == f"rb_ramp_{material_id}" and _uses_nodes(ob.data.materials[0])
    # UVs are an isometric unwrap in metres, so a texture keeps its real-world scale on every face
    uv = np.empty(len(ob.data.loops) * 2, np.float32)
    ob.data.uv_layers.active.data.foreach_get("uv", uv)
    uv = uv.reshape(-1, 3, 2)
    xyz = ref.vertices[ref.faces]
    for a, b in ((0, 1), (1, 2), (2, 0)):
        np.testing.assert_allclose(np.linalg.norm(uv[:, a] - uv[:, b], axis=1),
                                   np.linalg.norm(xyz[:, a] - xyz[:, b], axis=1), atol=1e-5)


def test_tomato_renders_red_in_cycles(empty_scene, tmp_path):
    scene = empty_scene
    ob = build_object(REG.object("tomato"), "tomato_0")
    world = bpy.data.worlds.new("w")
    world.use_nodes = True
    world.node_tree.nodes["Background"].inputs["Color"].default_value = (1.0, 1.0, 1.0, 1.0)
    scene.world = world
    cam = bpy.data.objects.new("cam", bpy.data.cameras.new("cam"))
    cam.location = (0.0, -0.3, 0.05)
    cam.rotation_euler = (math.radians(80), 0.0, 0.0)
    scene.collection.objects.link(cam)
    scene.camera = cam
    scene.render.engine = "CYCLES"
    scene.cycles.device = "CPU"
    scene.cycles.samples = 4
    scene.cycles.use_denoising = False
    scene.render.resolution_x = scene.render.resolution_y = 32
    scene.render.filepath = str(tmp_path / "tomato.png")
    bpy.ops.render.render(write_still=True)
    img = bpy.data.images.load(str(tmp_path / "tomato.png"))
    px = np.empty(32 * 32 * 4, np.float32)
    img.pixels.foreach_get(px)
    centre = px.reshape(32, 32, 4)[12:20, 12:20, :3].mean((0, 1))
    corner = px.reshape(32, 32, 4)[:3, :3, :3].mean((0, 1))
    assert centre[0] > centre[1] + 0.15 and centre[0] > centre[2] + 0.15, centre  # red tomato in the middle
    assert corner.min() > 0.6, corner  # white background around it
    del ob


def test_object_without_builder_gets_a_fitted_stand_in(empty_scene):
    cfg = dataclasses.replace(REG.object("food_can"), id="mug", name="Mug", size_m=(0.09, 0.08, 0.1))
    ob = build_object(cfg, "mug_0")
    v = local_vertices(ob)
    np.testing.assert_allclose(v.max(0) - v.min(0), cfg.size_m, rtol=1e-5)
    assert ob.data.materials[0].name == "rb_generic_mug"


def test_new_scene_id_uses_its_layout_style(empty_scene):
    base = REG.scene("modern_warm_kitchen")
    support = dataclasses.replace(base.supports[0], name="worktop", centre_m=(1.0, 2.0, 0.88), long_axis_deg=90.0)
    scene = dataclasses.replace(base, id="my_kitchen", supports=(support,), style={"layout": "kitchen"})
    env = build_environment(scene)
    v = world_vertices(env.supports["worktop"])
    assert v[:, 2].max() == pytest.approx(0.88, abs=1e-4)
    np.testing.assert_allclose(v[:, :2].max(0) - v[:, :2].min(0), [0.65, 3.0], atol=1e-3)  # long axis along y
    assert len(env.occluders) > 5


def test_user_scene_mesh_becomes_occluders(empty_scene, tmp_path):
    path = tmp_path / "room.obj"
    path.write_text("v -3 0 -3\nv 3 0 -3\nv 3 0 3\nv -3 0 3\nf 1 2 3 4\n")  # a 6 m floor quad (y up)
    scene = dataclasses.replace(REG.scene("modern_loft"), id="my_room", mesh_path=str(path), style={})
    env = build_environment(scene)
    names = [ob.name for ob in env.occluders]
    assert any(n.startswith("room") for n in names), names
    assert env.supports["counter"].matrix_world.translation.z == pytest.approx(0.92 - 0.02, abs=1e-6)


@pytest.mark.parametrize("scene_id", sorted(REG.scenes))
def test_space_above_every_support_is_clear(empty_scene, scene_id):
    # Upward rays from just above each top face (inset by the rule's margin) on a 4 cm grid must not hit
    # any scene geometry within CLEAR_ABOVE_M: nothing hangs over a drop zone (the japandi pendant once did).
    from mathutils import Vector

    from rigidbench.blender.assets.scenes import CLEAR_ABOVE_M, CLEAR_INSET_M

    scene = REG.scene(scene_id)
    build_environment(scene)
    depsgraph = bpy.context.evaluated_depsgraph_get()
    for s in scene.supports:
        yaw = math.radians(s.long_axis_deg)
        axis_long, axis_short = np.array([math.cos(yaw), math.sin(yaw)]), np.array([-math.sin(yaw), math.cos(yaw)])
        half = np.asarray(s.size_m) / 2 - CLEAR_INSET_M - 1e-3
        hits = []
        for u in np.linspace(-half[0], half[0], max(2, int(2 * half[0] / 0.04) + 1)):
            for w in np.linspace(-half[1], half[1], max(2, int(2 * half[1] / 0.04) + 1)):
                x, y = np.asarray(s.centre_m[:2]) + u * axis_long + w * axis_short
                start = Vector((x, y, s.centre_m[2] + 0.002))
                hit, loc, _, _, ob, _ = empty_scene.ray_cast(depsgraph, start, Vector((0.0, 0.0, 1.0)),
                                                             distance=CLEAR_ABOVE_M - 0.002)
                if hit:
                    hits.append((ob.name, round(loc.z - s.centre_m[2], 3)))
        assert not hits, f"{scene_id}/{s.name}: geometry above the support: {sorted(set(hits))[:5]}"


def test_japandi_pendant_hangs_above_the_clear_column(empty_scene):
    from rigidbench.blender.assets.scenes import CLEAR_ABOVE_M

    scene = REG.scene("modern_japandi_dining")
    env = build_environment(scene)
    table = scene.support("table")
    pendants = [ob for ob in env.occluders if "pendant" in ob.name]
    assert pendants, "the dining table keeps its pendant lamp"
    lowest = min(world_vertices(ob)[:, 2].min() for ob in pendants)
    assert lowest >= table.centre_m[2] + CLEAR_ABOVE_M - 1e-6
    bulbs = [ob for ob in env.lights if "bulb" in ob.name]
    assert bulbs and all(ob.location.z > table.centre_m[2] + CLEAR_ABOVE_M - 0.1 for ob in bulbs)


@pytest.mark.parametrize("object_id", sorted(REG.objects))
def test_collision_hull_is_the_decimated_hull_of_the_rendered_mesh(empty_scene, object_id):
    from scipy.spatial import ConvexHull

    from rigidbench.blender.assets.collision import MAX_HULL_VERTICES, hull_mesh
    from rigidbench.blender.assets.objects import object_vertices

    cfg = REG.object(object_id)
    rendered = local_vertices(build_object(cfg, f"{object_id}_0"))
    np.testing.assert_allclose(object_vertices(cfg), rendered, atol=1e-6)  # same geometry, no Blender needed
    hull = hull_mesh(rendered)
    assert len(hull.vertices) <= MAX_HULL_VERTICES
    # every kept vertex is a rendered vertex, and the hull's box is the configured box exactly
    d = np.linalg.norm(hull.vertices[:, None, :] - rendered[None, :, :], axis=2).min(1)
    assert d.max() < 1e-9
    np.testing.assert_allclose(hull.vertices.max(0) - hull.vertices.min(0), cfg.size_m, atol=1e-9)
    # closed and outward: each edge is shared by two faces, and the signed volume is the hull's volume
    edges = np.sort(np.concatenate([hull.faces[:, [0, 1]], hull.faces[:, [1, 2]], hull.faces[:, [2, 0]]]), axis=1)
    _, counts = np.unique(edges, axis=0, return_counts=True)
    assert np.all(counts == 2)
    a, b, c = (hull.vertices[hull.faces[:, k]] for k in range(3))
    volume = np.einsum("ij,ij->i", a, np.cross(b, c)).sum() / 6
    assert volume == pytest.approx(ConvexHull(hull.vertices).volume, rel=1e-9)
    # decimation loses little: the full hull's vertices lie at most 2.5% of the longest side outside it
    full = rendered[ConvexHull(rendered).vertices]
    eq = ConvexHull(hull.vertices).equations
    assert (full @ eq[:, :3].T + eq[:, 3]).max() <= 0.025 * max(cfg.size_m)
