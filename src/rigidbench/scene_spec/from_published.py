"""A SceneSpec rebuilt from the metadata of one published example (pure Python; no bpy).

The published evaluation set ships no scene spec, only what its renderer recorded (``metadata.json``:
``task_type``, ``scene_id``, ``surface``, ``center``, ``task_angle``, ``footprint``, ``frames``,
``actors{name: {object_id, role, position}}``, ``camera{intrinsics, extrinsics}``, ``render{fps}``) and each
actor's pose per frame (``trajectories.npz``). ``spec_from_published`` rebuilds a spec our Bullet simulation
can run, or says why it cannot (a ``Cannot`` value, never an exception, for anything the data lacks):

- actors: each published actor becomes a body of the same name and role, at its published pose of frame 0
  (the metadata records positions only; orientations come from the trajectory's first frame, which the
  caller passes). An object actor takes our catalogue's object of the same ``object_id`` (its size, mass,
  friction and restitution; the mesh is our procedural one, not the published asset). A published ramp
  (``object_id`` "ramp", a five-face wedge whose origin is the bottom edge of its high end, running along its
  local +y) becomes our ``RampShape`` once its length, height and width are known: the metadata does not hold
  them, so the caller measures them (``rigidbench.datasets.resimulate.measure_ramp``) or the example cannot be
  rebuilt;
- support: a box whose top face is centred at the published ``center`` (x, y), its top at
  ``support_top_m`` when the caller has a measurement (contacts with the surface) or else ``center``'s z;
  its size and long axis from the first release's surface table below (``PUBLISHED_SURFACES``), or else our
  catalogue's scene of the same id with a support of the same name; the support's friction and restitution
  are our task's support override or the registry's passive values (the release used the same numbers);
- task frame: ``task_rotation_deg`` is the published ``task_angle``; bodies are stored in the task frame
  (``SceneSpec.world_bodies`` puts them back at their published world poses);
- simulation: the registry's Bullet settings (the release's: 30 substeps, 20 solver iterations, damping 0.1
  and 0.5, margins 1 mm and 0.1 mm) at the published fps and frame count;
- camera: a ``CameraSpec`` (our orbit convention) that reproduces the published camera's position and
  orientation: its target is the point of the optical axis nearest the actors' centroid at frame 0, its
  lens ``fx * sensor_width / W`` on the registry's sensor width. ``visibility`` is 0.0: not measured for a
  published camera.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from typing import Any, Mapping

import numpy as np

from ..config import Registry
from ..rotations import quat_about_z, quat_to_matrix
from .types import Body, BodyPhysics, CameraSpec, RampShape, SceneSpec, SimSpec, SupportSpec, quat_mul

#: The first release's supports (``scenes/configs/scenes/*.yaml`` of swarnim-j/RigidBench, commit f0b8f29):
#: (scene id, surface name) -> (long side m, short side m, long-axis angle in degrees). Each published example
#: names its surface and records its ``center`` but not its size. Round tables (equal sides) become squares.
PUBLISHED_SURFACES: dict[tuple[str, str], tuple[float, float, float]] = {
    ("beach_gazebo", "Cylinder"): (1.065, 1.065, 80.94),
    ("butterfly_mural_room", "carpet"): (3.147, 2.366, 90.01),
    ("coastal_living_room", "Object014"): (1.219, 0.711, 0.0),
    ("cozy_living_room", "Cylinder.016"): (1.338, 1.338, 0.0),
    ("dining_room_set", "Table.002"): (1.6, 0.978, 0.0),
    ("hallway_interior", "Circle"): (3.056, 3.056, 90.0),
    ("minimal_white_kitchen", "Box013"): (1.603, 1.183, 9.49),
    ("modern_japandi_dining", "Table.005"): (1.699, 0.861, 0.0),
    ("modern_loft", "Counter"): (2.688, 0.925, 1.53),
    ("modern_luxury_kitchen", "handle"): (2.922, 1.102, 84.09),
    ("modern_warm_kitchen", "Desk"): (2.22, 1.058, 90.0),
    ("modular_flat", "Cube.006"): (1.272, 0.886, 0.0),
}
RAMP_ASSET = "ramp"  # the published object_id of a ramp actor
STEP = "published"  # the task step recorded on every rebuilt body
#: The largest gap (m) allowed between an actor's metadata position and its trajectory's frame 0; both are the
#: pose before the first simulation step, so they differ only by the trajectory's float32 rounding.
POSITION_AGREEMENT_M = 1e-3


@dataclass(frozen=True)
class Cannot:
    """Why no spec can be rebuilt for one example (one line, naming what is missing)."""

    sample_id: str
    reason: str

    def __str__(self) -> str:
        return f"example {self.sample_id}: cannot rebuild a scene spec: {self.reason}"


@dataclass(frozen=True)
class RebuiltSpec:
    """A spec rebuilt from published metadata, with where its less certain numbers came from."""

    spec: SceneSpec
    notes: dict[str, Any] = field(default_factory=dict)


def published_metadata(metadata: Mapping[str, Any]) -> dict[str, Any]:
    """The published ``metadata.json`` of an example: an imported bundle's ``source.original_metadata``, or
    ``metadata`` itself when it is the published file."""
    source = metadata.get("source")
    if isinstance(source, Mapping) and isinstance(source.get("original_metadata"), Mapping):
        return dict(source["original_metadata"])
    return dict(metadata)


def ramp_from_published(position_m, quat_wxyz, length_m: float, height_m: float) -> tuple[np.ndarray, tuple]:
    """(position (3,), quaternion w,x,y,z) of our ramp model (centred; high end at -x, descending toward +x) that
    occupies the published ramp whose origin is ``position_m``/``quat_wxyz`` (origin at the bottom edge of the
    high end, length along local +y, height along local +z). Our model axes (x, y, z) are the published
    (y, -x, z): a turn of +90 degrees about z; our centre is the published local (0, L/2, H/2)."""
    R = quat_to_matrix(np.asarray(quat_wxyz, float))
    centre = np.asarray(position_m, float) + R @ np.array([0.0, length_m / 2, height_m / 2])
    return centre, quat_mul(tuple(quat_wxyz), quat_about_z(math.pi / 2))


def _support_size(scene_id: str, surface: str, registry: Registry) -> tuple[tuple[float, float], float, str] | None:
    """((long, short) m, long-axis degrees, where from) of a named support, or None when unknown."""
    if (scene_id, surface) in PUBLISHED_SURFACES:
        long_m, short_m, axis = PUBLISHED_SURFACES[(scene_id, surface)]
        return (long_m, short_m), axis, "first release's surface table"
    scene = registry.scenes.get(scene_id)
    for s in (scene.supports if scene is not None else ()):
        if s.name == surface:
            return tuple(s.size_m), s.long_axis_deg, f"our catalogue (scene {scene_id})"
    return None


def _camera(meta: Mapping[str, Any], centroid: np.ndarray, registry: Registry) -> tuple[CameraSpec, float] | None:
    """(CameraSpec, the angle in degrees between its orientation and the published one) or None when the
    published camera block is incomplete."""
    try:
        intr, extr = meta["camera"]["intrinsics"], meta["camera"]["extrinsics"]
        fx, width = float(intr["fx"]), float(intr["width"])
        t_c = np.asarray(extr["location"], float)
        q = np.asarray(extr["rotation"], float)
    except (KeyError, TypeError, ValueError):
        return None
    if t_c.shape != (3,) or q.shape != (4,) or not (np.isfinite(t_c).all() and np.isfinite(q).all()) or width <= 0:
        return None
    R_c = quat_to_matrix(q)
    forward = -R_c[:, 2]  # a Blender camera looks along its -z
    distance = float(max(np.dot(centroid - t_c, forward), 1e-3))
    target = t_c + distance * forward
    offset = (t_c - target) / distance
    elevation = math.degrees(math.asin(float(np.clip(offset[2], -1.0, 1.0))))
    azimuth = math.degrees(math.atan2(offset[1], offset[0])) % 360.0
    # our orbit camera (groundtruth.camera_model.look_at): right = forward x z, up = right x forward
    right = np.cross(forward, [0.0, 0.0, 1.0])
    right /= max(np.linalg.norm(right), 1e-12)
    rebuilt = np.stack([right, np.cross(right, forward), -forward], axis=1)
    cos = (np.trace(rebuilt.T @ R_c) - 1.0) / 2.0
    roll_deg = math.degrees(math.acos(float(np.clip(cos, -1.0, 1.0))))
    task_angle = float(meta.get("task_angle") or 0.0)
    sensor = registry.camera.sensor_width_mm
    return CameraSpec(azimuth_deg=azimuth, relative_azimuth_deg=(azimuth - task_angle) % 360.0,
                      elevation_deg=elevation, distance_m=distance, target_m=tuple(float(v) for v in target),
                      lens_mm=fx * sensor / width, sensor_width_mm=sensor, visibility=0.0), roll_deg


def _support(meta: Mapping[str, Any], task_id: str, registry: Registry,
             support_top_m: float | None) -> tuple[SupportSpec, dict[str, Any]] | str:
    """The support box and notes on where its numbers came from, or why there is none."""
    centre = meta.get("center")
    try:
        cx, cy, cz = (float(v) for v in centre)
    except (TypeError, ValueError):
        return f"the published metadata has no support centre ('center' is {centre!r})"
    scene_id, surface = str(meta.get("scene_id", "")), str(meta.get("surface", meta.get("surface_name", "")))
    size = _support_size(scene_id, surface, registry)
    if size is None:
        return (f"support '{surface}' of scene '{scene_id}' is neither in the first release's surface table nor in "
                "our catalogue, so its size is unknown")
    (long_m, short_m), long_axis, size_source = size
    top = float(support_top_m) if support_top_m is not None else cz
    override = registry.task(task_id).support_override
    physics = BodyPhysics(0.0, override.friction if override else registry.sim.passive_friction,
                          override.restitution if override else registry.sim.passive_restitution)
    notes = {"support_size_from": size_source,
             "support_top_from": "contacts" if support_top_m is not None else "metadata center",
             "support_top_m": top, "support_center_z_m": cz}
    return SupportSpec(name=surface, centre_m=(cx, cy, top), size_m=(long_m, short_m), long_axis_deg=long_axis,
                       physics=physics), notes


def _world_body(name: str, actor: Any, pose: tuple[Any, Any] | None, registry: Registry,
                ramp_sizes: Mapping[str, tuple[float, float, float]]) -> tuple[Body, np.ndarray, np.ndarray] | str:
    """(the body with its fields but its pose, world position (3,), world quaternion (4,)) of one published actor,
    or why there is none."""
    if not isinstance(actor, Mapping):
        return f"actor '{name}' has no metadata"
    role, object_id = str(actor.get("role") or ""), actor.get("object_id")
    if role not in ("active", "passive"):
        return f"actor '{name}' has role {role!r}; expected 'active' or 'passive'"
    if pose is None:
        return f"actor '{name}' has no pose at frame 0 in the published trajectories"
    position, quat = (np.asarray(v, float) for v in pose)
    if position.shape != (3,) or quat.shape != (4,) or not (np.isfinite(position).all() and np.isfinite(quat).all()) \
            or np.linalg.norm(quat) < 0.5:
        return (f"actor '{name}' has a malformed pose at frame 0 (position {position.tolist()}, "
                f"rotation {quat.tolist()})")
    quat = quat / np.linalg.norm(quat)
    recorded = actor.get("position")
    if recorded is not None:
        gap = float(np.linalg.norm(np.asarray(recorded, float) - position))
        if not gap <= POSITION_AGREEMENT_M:
            return f"actor '{name}': its metadata position and its trajectory's frame 0 differ by {gap * 100:.1f} cm"
    identity = (0.0, 0.0, 0.0), (1.0, 0.0, 0.0, 0.0)
    if object_id == RAMP_ASSET:
        if name not in ramp_sizes:
            return (f"ramp '{name}': its length, height and width are not in the published metadata and were not "
                    "measured from its depth")
        length, height, width = (float(v) for v in ramp_sizes[name])
        position, turned = ramp_from_published(position, quat, length, height)
        material = sorted(registry.materials)[0] if registry.materials else "none"  # (rendering only)
        body = Body(name=str(name), asset=RAMP_ASSET, role=role, step=STEP, position_m=identity[0],
                    quat_wxyz=identity[1], size_m=(length, width, height),
                    physics=BodyPhysics(0.0, registry.sim.passive_friction, registry.sim.passive_restitution),
                    ramp=RampShape(length_m=length, height_m=height, width_m=width, material=material))
        return body, position, np.asarray(turned, float)
    if not object_id or object_id not in registry.objects:
        return f"actor '{name}': object id {object_id!r} is not in our catalogue (configs/objects)"
    obj = registry.objects[object_id]
    physics = BodyPhysics(obj.physics.mass_kg if role == "active" else 0.0, obj.physics.friction,
                          obj.physics.restitution)
    return Body(name=str(name), asset=obj.id, role=role, step=STEP, position_m=identity[0], quat_wxyz=identity[1],
                size_m=tuple(obj.size_m), physics=physics), position, quat


def _sim_spec(meta: Mapping[str, Any], bundle: Mapping[str, Any], registry: Registry) -> SimSpec:
    """The registry's Bullet settings at the published fps and frame count."""
    render = meta.get("render") if isinstance(meta.get("render"), Mapping) else {}
    sim = registry.sim
    return SimSpec(fps=int(round(float(render.get("fps", bundle.get("fps", sim.fps))))),
                   frames=int(meta.get("frames") or bundle.get("frames") or sim.frames), substeps=sim.substeps,
                   solver_iterations=sim.solver_iterations, gravity_m_s2=sim.gravity_m_s2,
                   linear_damping=sim.linear_damping, angular_damping=sim.angular_damping,
                   active_margin_m=sim.active_margin_m, passive_margin_m=sim.passive_margin_m)


def _placed_bodies(actors: Mapping[str, Any], initial_poses: Mapping[str, tuple[Any, Any]], registry: Registry,
                   ramp_sizes: Mapping[str, tuple[float, float, float]], centre_m, task_angle_deg: float):
    """Every actor as a body placed relative to the support's centre and top, in the task's frame (the world
    offset turned back by the task angle); with their world positions. A str says why one cannot be placed."""
    yaw = math.radians(task_angle_deg)
    c, s = math.cos(yaw), math.sin(yaw)
    cx, cy, top = centre_m
    bodies, world_positions = [], []
    for name, actor in actors.items():
        made = _world_body(str(name), actor, initial_poses.get(name), registry, ramp_sizes)
        if isinstance(made, str):
            return made
        body, position, quat = made
        world_positions.append(position)
        dx, dy, dz = position[0] - cx, position[1] - cy, position[2] - top
        local = (c * dx + s * dy, -s * dx + c * dy, dz)
        bodies.append(replace(body, position_m=tuple(float(v) for v in local),
                              quat_wxyz=quat_mul(quat_about_z(-yaw), tuple(float(v) for v in quat))))
    return bodies, world_positions


def spec_from_published(metadata: Mapping[str, Any], initial_poses: Mapping[str, tuple[Any, Any]], registry: Registry,
                        *, sample_id: str | None = None, support_top_m: float | None = None,
                        ramp_sizes: Mapping[str, tuple[float, float, float]] | None = None) -> RebuiltSpec | Cannot:
    """A SceneSpec for one published example, or ``Cannot`` naming what is missing.

    ``metadata``: the published metadata.json (or an imported bundle's metadata.json, which keeps it under
    ``source.original_metadata``); ``initial_poses``: actor name -> (position (3,) m, quaternion (4,) w,x,y,z)
    at frame 0 (the published trajectory's first frame); ``support_top_m``: a measured height of the support's
    top face (else the published ``center``'s z); ``ramp_sizes``: ramp actor name -> (length, height, width) m,
    measured by the caller (the metadata does not hold them)."""
    bundle = dict(metadata)
    meta = published_metadata(bundle)
    sid = str(sample_id or bundle.get("sample_id") or meta.get("sample_id") or "?")
    task_id = str(meta.get("task_type") or bundle.get("task") or "")
    if task_id not in registry.tasks:
        return Cannot(sid, f"task '{task_id}' is not in our catalogue (configs/tasks)")
    actors = meta.get("actors")
    if not isinstance(actors, Mapping) or not actors:
        return Cannot(sid, "the published metadata lists no actors")
    support = _support(meta, task_id, registry, support_top_m)
    if isinstance(support, str):
        return Cannot(sid, support)
    support_spec, notes = support
    task_angle = float(meta.get("task_angle") or 0.0)
    placed = _placed_bodies(actors, initial_poses, registry, ramp_sizes or {}, support_spec.centre_m, task_angle)
    if isinstance(placed, str):
        return Cannot(sid, placed)
    bodies, world_positions = placed
    if not any(b.role == "active" for b in bodies):
        return Cannot(sid, "no actor is active")
    camera = _camera(meta, np.mean(world_positions, axis=0), registry)
    if camera is not None:
        notes["camera_orientation_error_deg"] = camera[1]
    row = (bundle.get("source") or {}).get("manifest_row")
    objects = [str(o) for o in row.get("objects", [])] if isinstance(row, Mapping) else []
    spec = SceneSpec(
        sample_id=sid, split=str(bundle.get("split", "eval")), task=task_id, scene=str(meta.get("scene_id", "")),
        surface=support_spec.name, seed=int(meta.get("seed") or 0),
        partition=str(bundle.get("partition") or meta.get("split", "")).replace("-", "_"),
        allowed_objects=tuple(objects or sorted({b.asset for b in bodies if b.ramp is None})),
        prompt=str(bundle.get("prompt") or meta.get("prompt") or ""), support=support_spec, bodies=tuple(bodies),
        footprint_m=tuple(float(v) for v in (meta.get("footprint") or (0.0, 0.0)))[:2],
        rotation_candidates_deg=(task_angle,), task_rotation_deg=task_angle,
        azimuth_candidates_deg=(camera[0].relative_azimuth_deg,) if camera else (),
        sim=_sim_spec(meta, bundle, registry), camera=camera[0] if camera else None)
    return RebuiltSpec(spec=spec, notes=notes)


__all__ = ["Cannot", "RebuiltSpec", "PUBLISHED_SURFACES", "RAMP_ASSET", "POSITION_AGREEMENT_M", "published_metadata",
           "ramp_from_published", "spec_from_published"]
