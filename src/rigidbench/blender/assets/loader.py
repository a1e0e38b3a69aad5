"""Load user mesh files (glTF .glb/.gltf, Wavefront .obj, Blender .blend) as one fitted mesh object.

The file's mesh objects are imported, their world transforms and modifiers applied, and their
polygons, UVs and materials merged into one mesh whose bounding box is centred on the origin
and scaled to ``ObjectConfig.size_m`` (the model frame: +z up, +x the long axis). glTF is
+y-up by convention and converted by its importer; OBJ files are read as +y-up (the format's
usual convention) and converted to +z-up. Rotate the model in the file if it lies differently.
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from ...config import ObjectConfig
from . import materials as M
from ._mesh import Part, fit, join, to_object

log = logging.getLogger(__name__)

MAX_VERTICES = 20000  # above this the convex hull and the render still work, but slowly


def import_objects(path: str | Path, what: str) -> list:
    """Import every object of a mesh file into the current scene; returns the new bpy objects.

    ``what`` names the config entry for error messages (e.g. 'objects/mug.yaml').
    """
    import bpy

    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{what}: field 'mesh': {path} does not exist; fix the path (relative to the YAML)")
    before = set(bpy.data.objects)
    suffix = path.suffix.lower()
    if suffix in (".glb", ".gltf"):
        _ensure_gltf_addon()
        bpy.ops.import_scene.gltf(filepath=str(path))
    elif suffix == ".obj":
        bpy.ops.wm.obj_import(filepath=str(path), forward_axis="NEGATIVE_Z", up_axis="Y")
    elif suffix == ".blend":
        with bpy.data.libraries.load(str(path), link=False) as (src, dst):
            dst.objects = list(src.objects)
        for ob in dst.objects:
            if ob is not None and ob.name not in bpy.context.scene.collection.objects:
                bpy.context.scene.collection.objects.link(ob)
    else:
        raise ValueError(f"{what}: field 'mesh': unsupported file type '{path.suffix}'; use .glb, .gltf, .obj "
                         "or .blend")
    bpy.context.view_layer.update()
    return [ob for ob in bpy.data.objects if ob not in before]


def _ensure_gltf_addon() -> None:
    import addon_utils
    import bpy

    if not hasattr(bpy.ops.import_scene, "gltf") or "io_scene_gltf2" not in bpy.context.preferences.addons:
        addon_utils.enable("io_scene_gltf2", default_set=True)


def merge_meshes(objects: list) -> tuple[Part, list]:
    """World-space union of the mesh objects (modifiers applied). Returns (part, materials)."""
    import bpy

    depsgraph = bpy.context.evaluated_depsgraph_get()
    parts, materials = [], []
    for ob in objects:
        if ob.type != "MESH":
            continue
        evaluated = ob.evaluated_get(depsgraph)
        mesh = evaluated.to_mesh()
        try:
            n_v, n_c, n_f = len(mesh.vertices), len(mesh.loops), len(mesh.polygons)
            if n_f == 0:
                continue
            co = np.empty(n_v * 3, np.float32)
            mesh.vertices.foreach_get("co", co)
            m = np.array(ob.matrix_world)
            verts = co.reshape(-1, 3).astype(float) @ m[:3, :3].T + m[:3, 3]
            corners = np.empty(n_c, np.int32)
            mesh.loops.foreach_get("vertex_index", corners)
            sizes = np.empty(n_f, np.int32)
            mesh.polygons.foreach_get("loop_total", sizes)
            mat_idx = np.empty(n_f, np.int32)
            mesh.polygons.foreach_get("material_index", mat_idx)
            smooth = np.empty(n_f, bool)
            mesh.polygons.foreach_get("use_smooth", smooth)
            uvs = np.zeros(n_c * 2, np.float32)
            if mesh.uv_layers.active is not None:
                mesh.uv_layers.active.data.foreach_get("uv", uvs)
            slots = [s.material for s in ob.material_slots] or [None]
            remap = []
            for mat in slots:
                if mat not in materials:
                    materials.append(mat)
                remap.append(materials.index(mat))
            mat_idx = np.asarray(remap)[np.clip(mat_idx, 0, len(remap) - 1)]
            parts.append(Part(verts, corners.astype(np.int64), sizes.astype(np.int64),
                              uvs.reshape(-1, 2).astype(float), mat_idx.astype(np.int64), smooth))
        finally:
            evaluated.to_mesh_clear()
    if not parts:
        return None, []
    return join(parts), materials


def remove_objects(objects: list) -> None:
    """Delete imported objects and the mesh data only they used."""
    import bpy

    meshes = [ob.data for ob in objects if ob.type == "MESH"]
    for ob in objects:
        bpy.data.objects.remove(ob, do_unlink=True)
    for mesh in meshes:
        if mesh.users == 0:
            bpy.data.meshes.remove(mesh)


def load_mesh_vertices(obj: ObjectConfig) -> np.ndarray:
    """Vertices (V,3) float64 m of the user's mesh file for ``obj``, fitted as ``load_mesh_object`` fits
    them (for the collision hull); the imported objects are removed again."""
    part, _, _ = _merged_user_mesh(obj)
    return np.asarray(fit(part, obj.size_m).vertices, dtype=np.float64)


def _merged_user_mesh(obj: ObjectConfig):
    """(mesh part, materials, description) merged from the user's mesh file; the imports are removed."""
    what = obj.source or f"object '{obj.id}'"
    imported = import_objects(obj.mesh_path, what)
    try:
        part, mats = merge_meshes(imported)
    finally:
        remove_objects(imported)
    if part is None:
        raise ValueError(f"{what}: field 'mesh': {obj.mesh_path} contains no mesh with faces; export the model "
                         "as a mesh (not curves or points)")
    return part, mats, what


def load_mesh_object(obj: ObjectConfig, name: str):
    """The user's mesh file for ``obj`` as one mesh object named ``name`` fitted to obj.size_m."""
    part, mats, what = _merged_user_mesh(obj)
    if len(part.vertices) > MAX_VERTICES:
        log.warning("%s: mesh %s has %d vertices; consider decimating it below %d for faster hulls and renders",
                    what, obj.mesh_path, len(part.vertices), MAX_VERTICES)
    lo, hi = part.vertices.min(0), part.vertices.max(0)
    extent = hi - lo
    ratio = (extent / max(extent.max(), 1e-12)) / (np.asarray(obj.size_m) / max(obj.size_m))
    if np.any(ratio > 1.25) or np.any(ratio < 0.8):
        log.warning("%s: mesh %s has proportions %s but size_m is %s; it will be stretched to fit. Rotate the "
                    "model (+z up, +x long axis) or correct size_m", what, obj.mesh_path,
                    np.round(extent, 4).tolist(), list(obj.size_m))
    fallback = M.plain(f"rb_user_{obj.id}", (0.7, 0.7, 0.7), roughness=0.5, noise_scale=150, bump=0.1,
                       variation=0.3)
    mats = [m if m is not None else fallback for m in mats]
    ob = to_object(fit(part, obj.size_m), name, mats)
    ob["rb_asset"] = obj.id
    return ob
