"""Build a Bullet rigid-body scene in Blender from a SceneSpec, simulate it, and record the result.

Scene (paper appendix A, table "Simulation and rendering configuration"):
- fps and frame count from ``spec.sim``; Blender frame f is sample frame f-1 at time (f-1)/fps;
  a rigid-body world with ``spec.sim`` substeps per frame, solver iterations and gravity
  (0, 0, -g), its point cache covering frames 1..frames;
- every actor in spec order (world poses from ``spec.world_bodies()``): active objects as
  convex-hull rigid bodies (the hull of the rendered procedural mesh, decimated to at most
  ``MAX_HULL_VERTICES`` vertices, see ``body_mesh``) with their own mass, friction and
  restitution, linear and angular damping and collision margin from ``spec.sim``, never deactivated; passive ramps as
  triangle-mesh colliders with the passive margin and the ramp body's friction and restitution;
- then the support, a passive triangle-mesh box whose top face is at ``support.centre_m`` (size
  ``support.size_m`` along ``long_axis_deg``, ``SUPPORT_THICKNESS_M`` thick) with the support's
  physics (the bounce task's override included), and, unless the support lies on the floor,
  a large passive floor box with its top at z = 0 and the registry's passive friction and
  restitution, so objects leaving the support land somewhere. The floor collides as a Bullet
  box rather than a triangle mesh: its triangles would be tens of metres long, which Bullet's
  triangle-mesh collision handles poorly against centimetre-sized hulls.

Stepping calls ``scene.frame_set(f)`` for f = 1..frames in order and reads every body's
``matrix_world``; the point cache is then marked baked (see ``freeze_cache``). Contacts come
from ``rigidbench.groundtruth.contacts`` on the convex hulls of the same meshes.

Bounces: Bullet multiplies the two restitutions, and at these impact speeds (3-4 m/s, 5-6 mm
per 1/720 s substep) a hull is first seen already penetrating the support by up to one substep
of travel; without split impulse the solver's Baumgarte term then adds ERP * depth / dt
(ERP = 0.2) to the rebound. So rebound speed = e_obj * e_support * v + 0.2 * depth / dt, which
lies between the restitution product and that product + 0.2 v (tests check this to ~5%).
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from ..atomic import atomic_dir
from ..config import Registry, registry as load_registry
from ..errors import SpecError
from ..groundtruth.contacts import contact_pairs, convex_hull, detect_contacts
from ..groundtruth.trajectory import Contact, Trajectory, save_contacts
from ..rotations import quat_about_z
from ..scene_spec.types import Body, BodyPhysics, SceneSpec
from .assets.collision import MAX_HULL_VERTICES, hull_mesh
from .assets.objects import object_vertices
from .assets.standin import Mesh, box, ramp_mesh
from .session import import_bpy, link_object, reset_scene

log = logging.getLogger(__name__)

SUPPORT_NAME = "support"
FLOOR_NAME = "floor"
SUPPORT_THICKNESS_M = 0.05
FLOOR_THICKNESS_M = 0.5
FLOOR_PADDING_M = 25.0  # floor extends this far beyond the support: objects launched at ~10 m/s stay on it
FLOOR_SKIP_HEIGHT_M = 1e-4  # a support whose top face is this close to z = 0 is the floor itself

SCENE_SPEC_FILE = "scene_spec.json"
TRAJECTORIES_FILE = "trajectories.npz"
CONTACTS_FILE = "contacts.json"


@dataclass(frozen=True)
class SceneBody:
    """One rigid body as Blender builds it: mesh in the model frame and its world pose."""

    name: str
    role: str  # "active" or "passive"
    kind: str  # "object", "ramp", "support" or "floor"
    mesh: Mesh
    position_m: tuple[float, float, float]
    quat_wxyz: tuple[float, float, float, float]
    physics: BodyPhysics
    collision_shape: str  # Blender rigid-body shape: "CONVEX_HULL" (active), "MESH" (passive), "BOX" (floor)
    margin_m: float


@dataclass
class SimulationResult:
    """Trajectory of every actor (active objects and ramps) and per-frame contacts."""

    trajectory: Trajectory
    contacts: list[Contact]
    tolerance_m: float
    timings_s: dict[str, float] = field(default_factory=dict)  # wall seconds: build, frames, contacts

    @property
    def frames(self) -> int:
        return int(self.trajectory.positions_m.shape[1])


# -- scene description (no bpy) ----------------------------------------------------------------


_HULLS: dict[tuple, Mesh] = {}  # collision hulls by (asset id, mesh file, asset size, body size)


def body_mesh(body: Body, registry: Registry) -> Mesh:
    """Collision mesh of one actor in its model frame (the single mesh source for Bullet and contacts):
    the exact wedge for a ramp; for an object, the convex hull (at most MAX_HULL_VERTICES vertices) of
    the mesh ``assets.objects.build_object`` renders, its bounding box centred on the origin and
    equal to ``body.size_m``. Hulls are cached per process."""
    if body.ramp is not None:
        return ramp_mesh(body.ramp.length_m, body.ramp.height_m, body.ramp.width_m)
    obj = registry.object(body.asset)
    key = (obj.id, str(obj.mesh_path or ""), tuple(obj.size_m), tuple(body.size_m))
    if key not in _HULLS:
        scale = np.asarray(body.size_m, float) / np.asarray(obj.size_m, float)
        _HULLS[key] = hull_mesh(object_vertices(obj) * scale, MAX_HULL_VERTICES)
    return _HULLS[key]


def support_body(spec: SceneSpec) -> SceneBody:
    """The support as a passive box whose top face is centred at ``spec.support.centre_m``."""
    s = spec.support
    cx, cy, cz = s.centre_m
    return SceneBody(name=SUPPORT_NAME, role="passive", kind="support",
                     mesh=box().fitted((s.size_m[0], s.size_m[1], SUPPORT_THICKNESS_M)),
                     position_m=(cx, cy, cz - SUPPORT_THICKNESS_M / 2),
                     quat_wxyz=quat_about_z(math.radians(s.long_axis_deg)), physics=s.physics,
                     collision_shape="MESH", margin_m=spec.sim.passive_margin_m)


def floor_body(spec: SceneSpec, registry: Registry) -> SceneBody | None:
    """A passive floor box with its top at z = 0 under the support, or None if the support is the floor."""
    s = spec.support
    if abs(s.centre_m[2]) <= FLOOR_SKIP_HEIGHT_M:
        return None
    side = s.size_m[0] + 2 * FLOOR_PADDING_M
    physics = BodyPhysics(0.0, registry.sim.passive_friction, registry.sim.passive_restitution)
    return SceneBody(name=FLOOR_NAME, role="passive", kind="floor",
                     mesh=box().fitted((side, side, FLOOR_THICKNESS_M)),
                     position_m=(s.centre_m[0], s.centre_m[1], -FLOOR_THICKNESS_M / 2),
                     quat_wxyz=(1.0, 0.0, 0.0, 0.0), physics=physics, collision_shape="BOX",
                     margin_m=spec.sim.passive_margin_m)


def scene_bodies(spec: SceneSpec, registry: Registry) -> tuple[SceneBody, ...]:
    """Every rigid body in build order: actors in spec order, then the support and the floor."""
    out = []
    for b in spec.world_bodies():
        if b.name in (SUPPORT_NAME, FLOOR_NAME):
            raise SpecError(f"example {spec.sample_id}: actor name '{b.name}' is reserved for scene geometry; "
                             "rename the body in the spec")
        active = b.role == "active"
        if not active and b.role != "passive":
            raise SpecError(f"example {spec.sample_id}: body '{b.name}' has role '{b.role}'; "
                             "expected 'active' or 'passive'")
        out.append(SceneBody(name=b.name, role=b.role, kind="object" if b.ramp is None else "ramp",
                             mesh=body_mesh(b, registry), position_m=b.position_m, quat_wxyz=b.quat_wxyz,
                             physics=b.physics, collision_shape="CONVEX_HULL" if active else "MESH",
                             margin_m=spec.sim.active_margin_m if active else spec.sim.passive_margin_m))
    out.append(support_body(spec))
    floor = floor_body(spec, registry)
    if floor is not None:
        out.append(floor)
    names = [b.name for b in out]
    if len(set(names)) != len(names):
        raise SpecError(f"example {spec.sample_id}: body names must be unique, got {names}")
    return tuple(out)


# -- Blender -------------------------------------------------------------------------------------


def _configure_world(scene: Any, spec: SceneSpec) -> Any:
    bpy = _bpy()
    sim = spec.sim
    scene.render.fps = int(sim.fps)
    scene.render.fps_base = 1.0
    scene.frame_start = 1
    scene.frame_end = int(sim.frames)
    scene.use_gravity = True
    scene.gravity = (0.0, 0.0, -float(sim.gravity_m_s2))
    bpy.ops.rigidbody.world_add()
    world = scene.rigidbody_world
    world.enabled = True
    world.time_scale = 1.0
    world.substeps_per_frame = int(sim.substeps)
    world.solver_iterations = int(sim.solver_iterations)
    world.use_split_impulse = False
    world.point_cache.frame_start = 1
    world.point_cache.frame_end = int(sim.frames)
    return world


def _add_rigid_body(obj: Any, body: SceneBody, spec: SceneSpec) -> None:
    bpy = _bpy()
    with bpy.context.temp_override(object=obj, active_object=obj, selected_objects=[obj],
                                   selected_editable_objects=[obj]):
        bpy.ops.rigidbody.object_add(type="ACTIVE" if body.role == "active" else "PASSIVE")
    rb = obj.rigid_body
    rb.collision_shape = body.collision_shape
    rb.friction = float(body.physics.friction)
    rb.restitution = float(body.physics.restitution)
    rb.use_margin = True
    rb.collision_margin = float(body.margin_m)
    if body.role == "active":
        rb.mass = float(body.physics.mass_kg)
        rb.linear_damping = float(spec.sim.linear_damping)
        rb.angular_damping = float(spec.sim.angular_damping)
        rb.use_deactivation = False
        rb.use_start_deactivated = False
    rb.kinematic = False


def _bpy() -> Any:
    return import_bpy()


def build_rigid_scene(spec: SceneSpec, bodies: Sequence[SceneBody]) -> tuple[Any, list[Any]]:
    """Reset Blender and build the rigid-body scene; returns (bpy Scene, bpy Objects in ``bodies`` order)."""
    scene = reset_scene()
    _configure_world(scene, spec)
    objects = []
    for body in bodies:
        obj = link_object(scene, body.name, body.mesh.vertices, body.mesh.faces)
        obj.rotation_mode = "QUATERNION"
        obj.location = body.position_m
        obj.rotation_quaternion = body.quat_wxyz
        _add_rigid_body(obj, body, spec)
        objects.append(obj)
    return scene, objects


def run_frames(scene: Any, objects: Sequence[Any], frames: int) -> tuple[np.ndarray, np.ndarray]:
    """Step Blender frames 1..frames in order. Returns world positions (N,T,3) m and quaternions (N,T,4) w,x,y,z."""
    positions = np.zeros((len(objects), frames, 3))
    quats = np.zeros((len(objects), frames, 4))
    for f in range(frames):
        scene.frame_set(f + 1)
        for i, obj in enumerate(objects):
            loc, rot, _ = obj.matrix_world.decompose()
            positions[i, f] = tuple(loc)
            quats[i, f] = (rot.w, rot.x, rot.y, rot.z)
    return positions, quats


def _hulls(meshes: Sequence[Mesh]) -> list:
    """Convex hull of each mesh, computed once per distinct vertex array (repeated objects share one)."""
    cache: dict[bytes, Any] = {}
    out = []
    for mesh in meshes:
        key = np.ascontiguousarray(mesh.vertices, dtype=np.float64).tobytes()
        if key not in cache:
            cache[key] = convex_hull(mesh.vertices)
        out.append(cache[key])
    return out


def freeze_cache(scene: Any) -> None:
    """Mark the rigid-body point cache as baked, so later edits to the scene (materials, parenting,
    visibility, a camera) cannot invalidate it: revisiting a frame then replays the simulated pose
    instead of re-simulating from the last valid frame, which would give a different result."""
    bpy = _bpy()
    with bpy.context.temp_override(scene=scene, point_cache=scene.rigidbody_world.point_cache):
        bpy.ops.ptcache.bake_from_cache()
    if not scene.rigidbody_world.point_cache.is_baked:
        raise RuntimeError("could not bake Blender's rigid-body point cache after simulation")


def simulate(spec: SceneSpec, registry: Registry | None = None) -> SimulationResult:
    """Simulate one example in Blender's Bullet; returns the actors' trajectory and all contacts.

    Blender's current scene is left holding the simulated bodies (named as in the spec, plus
    "support" and "floor") with a baked cache, so a renderer can dress it and step the frames."""
    if registry is None:
        registry = load_registry()
    t0 = time.perf_counter()
    bodies = scene_bodies(spec, registry)
    scene, objects = build_rigid_scene(spec, bodies)
    t1 = time.perf_counter()
    positions, quats = run_frames(scene, objects, spec.sim.frames)
    freeze_cache(scene)
    if not np.isfinite(positions).all() or not np.isfinite(quats).all():
        raise RuntimeError(f"example {spec.sample_id}: Bullet produced non-finite poses; check the spec's "
                           "masses, sizes and initial overlaps")
    t2 = time.perf_counter()
    tolerance = registry.sim.contact_tolerance_m
    hulls = _hulls([b.mesh for b in bodies])
    contacts = detect_contacts([b.name for b in bodies], hulls, positions, quats,
                               contact_pairs([b.role for b in bodies]), tolerance, registry.sim.max_contact_points)
    t3 = time.perf_counter()
    n = len(spec.bodies)
    trajectory = Trajectory(names=tuple(b.name for b in bodies[:n]), roles=tuple(b.role for b in bodies[:n]),
                            fps=float(spec.sim.fps), positions_m=positions[:n], quat_wxyz=quats[:n])
    timings = {"build": t1 - t0, "frames": t2 - t1, "contacts": t3 - t2}
    log.debug("example %s: build %.3f s, %d frames %.3f s, contacts %.3f s", spec.sample_id, t1 - t0,
              spec.sim.frames, t2 - t1, t3 - t2)
    return SimulationResult(trajectory=trajectory, contacts=contacts, tolerance_m=tolerance, timings_s=timings)


def write_simulation(out_dir: str | Path, spec: SceneSpec, result: SimulationResult, overwrite: bool = False) -> Path:
    """Write scene_spec.json, trajectories.npz and contacts.json into ``out_dir`` atomically
    (a temporary sibling directory renamed into place); returns the directory."""
    out = Path(out_dir)
    if out.exists() and not overwrite:
        raise FileExistsError(f"{out}: already exists; remove it or pass overwrite=True")
    out.parent.mkdir(parents=True, exist_ok=True)
    with atomic_dir(out, unique=True, replace=True) as tmp:
        (tmp / SCENE_SPEC_FILE).write_text(spec.to_json())
        result.trajectory.save(tmp / TRAJECTORIES_FILE)
        save_contacts(tmp / CONTACTS_FILE, result.contacts, frames=result.frames, tolerance_m=result.tolerance_m)
    return out


def simulate_to_dir(spec: SceneSpec, out_dir: str | Path, registry: Registry | None = None,
                    overwrite: bool = False) -> SimulationResult:
    """Simulate ``spec`` and write its files into ``out_dir`` (see ``write_simulation``)."""
    result = simulate(spec, registry)
    write_simulation(out_dir, spec, result, overwrite=overwrite)
    return result


__all__ = ["SimulationResult", "SceneBody", "body_mesh", "support_body", "floor_body", "scene_bodies",
           "build_rigid_scene", "run_frames", "freeze_cache", "simulate", "write_simulation", "simulate_to_dir",
           "SUPPORT_NAME", "FLOOR_NAME", "SUPPORT_THICKNESS_M"]
