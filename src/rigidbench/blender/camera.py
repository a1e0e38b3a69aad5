"""Camera framing, the visibility search over task rotations and azimuths, and the bpy camera.

Paper, appendix "Scene Layout and Camera Selection":
- the camera looks at the padded (0.2 m) joint bounding box of the actors and the support, from
  10 degrees elevation with a 35 mm lens, at 1.4 x the box's largest extent (at least 1.4 m);
  depth of field is off;
- for each candidate task rotation in order, azimuths every 15 degrees inside the task's range
  (task-relative, in the spec's seeded order) are tried; about 16 surface points per target mesh
  (the active actors) are sampled and a ray is cast from the camera to each; the first
  (rotation, azimuth) that sees at least 50% of the points is accepted, otherwise the best pair.

Our addition (docs/camera.md), which keeps the paper's lens, elevation, distance and candidate
order: within the first rotation that has an accepted azimuth, every azimuth is checked with a
16 x 9 grid of rays through the image. A position is rejected when more than 2% of those rays
first hit geometry that is nearer than the framed box and above the support's top face (a wall
beside the camera, a chair or cabinet in front of the action); among the accepted positions whose
visibility is within 0.1 of the best accepted one, the one whose background (rays beyond the box,
above the top face) hits the most furnishing rather than bare wall, floor or sky is taken, ties
going to the seeded order. Without the room
(``environment`` None) only the clearance check runs.

"The support" in the framed box is the part of the support the task uses: the actors' footprint
at the support's top-face height (the whole support can be a 2.6 m counter or a floor patch,
which would shrink the objects to a few pixels). Rays see only geometry that renders: objects
hidden from render are passed through (physics stand-ins under dressed meshes are also hidden in
the view layer, which ``scene.ray_cast`` skips, so a coincident dressed surface is not missed).

Only the functions that take a bpy scene or object import bpy (inside the function).
"""

from __future__ import annotations

import dataclasses
import logging
import math
from typing import Any, Callable, Sequence

import numpy as np

from ..config import CameraSettings
from ..groundtruth import camera_model as cm
from ..scene_spec.build import body_aabb
from ..scene_spec.types import CameraSpec, SceneSpec

log = logging.getLogger(__name__)

CLIP_START_M = 0.01
CLIP_END_M = 1000.0
RAY_EPSILON_M = 1e-4  # a hit this close before the sampled point counts as reaching it
MAX_PASS_THROUGH = 16  # render-hidden objects a ray may pass through


# -- pure geometry ------------------------------------------------------------------------------


def framing_box(spec: SceneSpec, padding_m: float) -> tuple[np.ndarray, np.ndarray]:
    """(lo (3,), hi (3,)) m: world AABB of the actors (frame 0) joined with their footprint on the
    support's top face, padded by ``padding_m`` on every side."""
    boxes = [body_aabb(b) for b in spec.world_bodies()]
    lo = np.min([b[0] for b in boxes], axis=0)
    hi = np.max([b[1] for b in boxes], axis=0)
    top = spec.support.centre_m[2]
    lo[2], hi[2] = min(lo[2], top), max(hi[2], top)
    return lo - padding_m, hi + padding_m


def framing(spec: SceneSpec, settings: CameraSettings) -> tuple[np.ndarray, float]:
    """(target (3,) m, distance m): centre of the padded framing box and framing_multiplier x its
    largest extent, at least min_distance_m."""
    lo, hi = framing_box(spec, settings.bbox_padding_m)
    distance = max(settings.framing_multiplier * float(np.max(hi - lo)), settings.min_distance_m)
    return (lo + hi) / 2, distance


def camera_spec(spec: SceneSpec, relative_azimuth_deg: float, settings: CameraSettings,
                visibility: float) -> CameraSpec:
    """The CameraSpec framing ``spec`` (at its task rotation) from a task-relative azimuth."""
    target, distance = framing(spec, settings)
    return CameraSpec(azimuth_deg=float((spec.task_rotation_deg + relative_azimuth_deg) % 360.0),
                      relative_azimuth_deg=float(relative_azimuth_deg), elevation_deg=settings.elevation_deg,
                      distance_m=float(distance), target_m=tuple(float(v) for v in target),
                      lens_mm=settings.lens_mm, sensor_width_mm=settings.sensor_width_mm,
                      visibility=float(visibility))


def camera_pose(camera: CameraSpec) -> tuple[np.ndarray, np.ndarray]:
    """(R_c (3,3), t_c (3,) m): Blender camera-to-world pose of a CameraSpec."""
    return cm.camera_pose(camera.target_m, camera.azimuth_deg, camera.elevation_deg, camera.distance_m)


def sample_surface(vertices: np.ndarray, triangles: np.ndarray, count: int, rng: np.random.Generator) -> np.ndarray:
    """vertices (V,3) m, triangles (F,3) int. Returns (count,3) area-weighted uniform surface points."""
    tri = vertices[triangles]
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    if not np.isfinite(area).all() or area.sum() <= 0:
        raise ValueError(f"cannot sample a surface with total area {area.sum()}")
    face = rng.choice(len(tri), size=count, p=area / area.sum())
    r1, r2 = rng.random(count), rng.random(count)
    s = np.sqrt(r1)
    w = np.stack([1 - s, s * (1 - r2), s * r2], axis=1)
    return np.einsum("pk,pkj->pj", w, tri[face])


STRUCTURE_WORDS = frozenset({"wall", "floor", "skirting", "wainscot", "backsplash", "sand", "shore", "sea",
                             "platform", "steps", "support"})  # scene items that are room, not furnishing
ABOVE_TOP_M = 0.02  # hits this far above the support's top face can obstruct or count as background


def view_grid_uv(cols: int, rows: int, width: float, height: float) -> np.ndarray:
    """(rows*cols, 2) pixel centres of a regular grid of cells over a width x height image."""
    u = (np.arange(cols) + 0.5) / cols * width
    v = (np.arange(rows) + 0.5) / rows * height
    return np.stack(np.meshgrid(u, v), -1).reshape(-1, 2)


def box_distance(point: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> float:
    """Euclidean distance (m) from ``point`` to the axis-aligned box [lo, hi] (0 inside)."""
    p = np.asarray(point, float)
    return float(np.linalg.norm(np.maximum(np.maximum(lo - p, 0.0), p - hi)))


@dataclasses.dataclass(frozen=True)
class ViewCheck:
    """What a grid of rays through one candidate view hit."""

    obstruction: float  # fraction of rays stopped above the support top, nearer than the framed box
    furnishing: float  # fraction of rays that reach past the box above the top face and hit furnishing

    def clear(self, settings: CameraSettings) -> bool:
        return self.obstruction <= settings.max_obstruction


def summarise_view(distance_m: np.ndarray, hit_z_m: np.ndarray, kind: Sequence[str], near_m: float,
                   top_z_m: float) -> ViewCheck:
    """Pure core of the view check. Per ray: first-hit distance (inf: nothing), hit height and what
    was hit ('actor', 'structure', 'furnishing' or 'none'); ``near_m`` is the camera's distance to
    the framed box, ``top_z_m`` the support's top face."""
    d, z = np.asarray(distance_m, float), np.asarray(hit_z_m, float)
    k = np.asarray(kind)
    above = np.isfinite(d) & (z > top_z_m + ABOVE_TOP_M) & (k != "actor")
    blocked = above & (d < near_m)
    furnished = above & (d >= near_m) & (k == "furnishing")
    n = max(len(d), 1)
    return ViewCheck(obstruction=float(blocked.sum() / n), furnishing=float(furnished.sum() / n))


def choose_view(accepted: Sequence[tuple[float, float, float]], visibility_margin: float) -> tuple[float, float, float]:
    """Pick among accepted views ``(furnishing, relative azimuth, visibility)`` (seeded order): the
    most furnished background among the views that see the actors within ``visibility_margin`` of
    the best accepted visibility; ties keep the seeded order. Without the margin a bare table
    behind the action could win over a view that sees every actor (a ramp seen from behind with
    its striker hidden on the far slope)."""
    if not accepted:
        raise ValueError("choose_view needs at least one accepted view")
    best_visibility = max(a[2] for a in accepted)
    near_best = [a for a in accepted if a[2] >= best_visibility - visibility_margin - 1e-12]
    return max(near_best, key=lambda a: a[0])  # max keeps the first of ties


def item_kind(name: str, scene_id: str) -> str:
    """'structure' for the room itself (walls, floor, support slabs, sand and sea), else 'furnishing'.
    Environment objects are named ``<scene id>_<item>_<count>``; supports ``support_<name>``."""
    core = name[len(scene_id) + 1:] if name.startswith(scene_id + "_") else name
    return "structure" if STRUCTURE_WORDS & set(core.split("_")) else "furnishing"


# -- bpy ------------------------------------------------------------------------------------------


def mesh_arrays(obj: Any) -> tuple[np.ndarray, np.ndarray]:
    """Evaluated mesh of a bpy object in its local frame: vertices (V,3) m, triangles (F,3) int."""
    import bpy

    depsgraph = bpy.context.evaluated_depsgraph_get()
    evaluated = obj.evaluated_get(depsgraph)
    mesh = evaluated.to_mesh()
    try:
        mesh.calc_loop_triangles()
        verts = np.zeros(len(mesh.vertices) * 3)
        mesh.vertices.foreach_get("co", verts)
        tris = np.zeros(len(mesh.loop_triangles) * 3, dtype=np.int64)
        mesh.loop_triangles.foreach_get("vertices", tris)
    finally:
        evaluated.to_mesh_clear()
    return verts.reshape(-1, 3), tris.reshape(-1, 3)


def target_points(objects: Sequence[Any], count: int, seed: int) -> list[np.ndarray]:
    """Local-frame surface points (count,3) per object, sampled with ``default_rng(seed)`` in order."""
    rng = np.random.default_rng(seed)
    out = []
    for obj in objects:
        verts, tris = mesh_arrays(obj)
        out.append(sample_surface(verts, tris, count, rng))
    return out


def _world(obj: Any, local: np.ndarray) -> np.ndarray:
    m = np.array(obj.matrix_world)
    return local @ m[:3, :3].T + m[:3, 3]


def first_render_hit(scene: Any, depsgraph: Any, origin: np.ndarray, direction: np.ndarray,
                     distance_m: float) -> tuple[Any, float]:
    """First object that renders along a ray (unit ``direction``) within ``distance_m``:
    (bpy Object or None, hit distance m or inf). Objects hidden from render are passed through."""
    from mathutils import Vector

    travelled = 0.0
    start = np.asarray(origin, dtype=np.float64)
    for _ in range(MAX_PASS_THROUGH):
        hit, loc, _n, _i, obj, _m = scene.ray_cast(depsgraph, Vector(start), Vector(direction),
                                                    distance=distance_m - travelled)
        if not hit:
            return None, math.inf
        step = float(np.dot(np.array(loc) - start, direction))
        travelled += step
        if not obj.original.hide_render:
            return obj.original, travelled
        start = np.array(loc) + direction * 1e-6
        travelled += 1e-6
    return None, math.inf


def visible_fraction(scene: Any, position_m: np.ndarray, targets: Sequence[Any],
                     points_local: Sequence[np.ndarray]) -> float:
    """Fraction of all targets' sample points (local (P,3) per target) reached by a ray from
    ``position_m``: the first rendered hit is the target itself or lies beyond the point."""
    import bpy

    depsgraph = bpy.context.evaluated_depsgraph_get()
    seen = total = 0
    for obj, local in zip(targets, points_local):
        for p in _world(obj, local):
            d = p - position_m
            dist = float(np.linalg.norm(d))
            total += 1
            hit, at = first_render_hit(scene, depsgraph, position_m, d / dist, dist + 1.0)
            if hit is None or hit == obj or at >= dist - RAY_EPSILON_M:
                seen += 1
    return seen / max(total, 1)


def pose_bodies(spec: SceneSpec, objects: dict[str, Any]) -> None:
    """Place every actor's bpy object at its frame-0 world pose for ``spec.task_rotation_deg``."""
    import bpy

    for b in spec.world_bodies():
        obj = objects[b.name]
        obj.rotation_mode = "QUATERNION"
        obj.location = b.position_m
        obj.rotation_quaternion = b.quat_wxyz
    bpy.context.view_layer.update()


def check_view(scene: Any, spec: SceneSpec, relative_azimuth_deg: float, settings: CameraSettings,
               actors: set, scene_id: str | None) -> ViewCheck:
    """Cast the view grid from the camera of ``spec`` (at its task rotation) at ``relative_azimuth_deg``."""
    import bpy

    cam = camera_spec(spec, relative_azimuth_deg, settings, 0.0)
    R_c, t_c = camera_pose(cam)
    W, H = 1280.0, 704.0  # only the aspect matters: the paper's frame
    K = cm.intrinsics(settings.lens_mm, settings.sensor_width_mm, int(W), int(H))
    rays = cm.pixel_rays(K, R_c, view_grid_uv(settings.view_grid_cols, settings.view_grid_rows, W, H))
    lo, hi = framing_box(spec, settings.bbox_padding_m)
    depsgraph = bpy.context.evaluated_depsgraph_get()
    dist, z, kind = [], [], []
    for ray in rays:
        direction = ray / np.linalg.norm(ray)
        obj, at = first_render_hit(scene, depsgraph, t_c, direction, CLIP_END_M)
        dist.append(at)
        z.append(float(t_c[2] + direction[2] * at) if obj is not None else -math.inf)
        kind.append("none" if obj is None else "actor" if obj.name in actors else
                    "structure" if scene_id is None else item_kind(obj.name, scene_id))
    return summarise_view(np.array(dist), np.array(z), kind, box_distance(t_c, lo, hi), spec.support.centre_m[2])


def search_camera(spec: SceneSpec, settings: CameraSettings, scene: Any, posed: dict[str, Any],
                  targets: Callable[[], Sequence[Any]] | Sequence[Any], actors: Sequence[Any] = (),
                  scene_id: str | None = None) -> SceneSpec:
    """Visibility search (paper A.3) with our clearance check and background preference (module
    docstring). ``posed`` maps actor name -> bpy object that ``pose_bodies`` moves; ``targets`` are
    the rendered bpy objects of the active actors (in spec order); ``actors`` all rendered actor
    objects (their hits never obstruct); ``scene_id`` names the built environment whose items count
    as furnishing (None: no preference). Returns ``spec`` with ``task_rotation_deg`` and ``camera``
    filled. Leaves the actors at the chosen pose."""
    target_objs = list(targets() if callable(targets) else targets)
    points = target_points(target_objs, settings.points_per_target, spec.seed)
    actor_names = {o.name for o in [*target_objs, *actors]}
    best: tuple[float, SceneSpec, float] | None = None  # best visibility of all
    least_blocked: tuple[float, SceneSpec, float, float] | None = None  # visible, least obstructed
    tried = 0
    for rotation in spec.rotation_candidates_deg[:settings.rotation_attempts]:
        candidate = dataclasses.replace(spec, task_rotation_deg=float(rotation))
        pose_bodies(candidate, posed)
        target, distance = framing(candidate, settings)
        accepted: list[tuple[float, float, float]] = []  # (furnishing, relative azimuth, visibility)
        for relative in candidate.azimuth_candidates_deg:
            position = cm.camera_position(target, rotation + relative, settings.elevation_deg, distance)
            fraction = visible_fraction(scene, position, target_objs, points)
            tried += 1
            if best is None or fraction > best[0]:
                best = (fraction, candidate, relative)
            if fraction < settings.visibility_threshold:
                continue
            view = check_view(scene, candidate, relative, settings, actor_names, scene_id)
            if view.clear(settings):
                accepted.append((view.furnishing, relative, fraction))
            elif least_blocked is None or view.obstruction < least_blocked[0]:
                least_blocked = (view.obstruction, candidate, relative, fraction)
        if accepted:
            furnishing, relative, fraction = choose_view(accepted, settings.background_visibility_margin)
            log.debug("example %s: camera at rotation %.1f, azimuth %+.0f sees %.0f%%, background %.0f%% "
                      "furnished (%d tried)", spec.sample_id, rotation, relative, 100 * fraction,
                      100 * furnishing, tried)
            return dataclasses.replace(candidate, camera=camera_spec(candidate, relative, settings, fraction))
    if least_blocked is not None:
        obstruction, candidate, relative, fraction = least_blocked
        log.warning("example %s: every camera that sees the actors has something nearer than them in view; using "
                    "the least obstructed (%.0f%% of the image, rotation %.1f, azimuth %+.0f)", spec.sample_id,
                    100 * obstruction, candidate.task_rotation_deg, relative)
        pose_bodies(candidate, posed)
        return dataclasses.replace(candidate, camera=camera_spec(candidate, relative, settings, fraction))
    if best is None:
        raise ValueError(f"example {spec.sample_id}: no rotation or azimuth candidates to search; "
                         "check the task's camera_azimuth_deg ranges")
    fraction, candidate, relative = best
    log.warning("example %s: no camera reaches %.0f%% visibility; using the best pair (%.0f%%, rotation %.1f, "
                "azimuth %+.0f)", spec.sample_id, 100 * settings.visibility_threshold, 100 * fraction,
                candidate.task_rotation_deg, relative)
    pose_bodies(candidate, posed)
    return dataclasses.replace(candidate, camera=camera_spec(candidate, relative, settings, fraction))


def add_camera(scene: Any, camera: CameraSpec, name: str = "camera") -> Any:
    """Create the bpy camera for a CameraSpec (sensor fit horizontal, no depth of field) and make it
    the scene camera; returns the camera object."""
    import bpy
    from mathutils import Matrix

    data = bpy.data.cameras.new(name)
    data.type = "PERSP"
    data.lens = camera.lens_mm
    data.sensor_width = camera.sensor_width_mm
    data.sensor_fit = "HORIZONTAL"
    data.shift_x = data.shift_y = 0.0
    data.clip_start = CLIP_START_M
    data.clip_end = CLIP_END_M
    data.dof.use_dof = False
    obj = bpy.data.objects.new(name, data)
    scene.collection.objects.link(obj)
    R, t = camera_pose(camera)
    obj.matrix_world = Matrix(cm.pose_matrix(R, t).tolist())
    scene.camera = obj
    return obj


__all__ = ["framing_box", "framing", "camera_spec", "camera_pose", "sample_surface", "mesh_arrays", "target_points",
           "STRUCTURE_WORDS", "view_grid_uv", "box_distance", "ViewCheck", "summarise_view", "choose_view", "item_kind",
           "first_render_hit", "visible_fraction", "pose_bodies", "check_view", "search_camera", "add_camera"]
