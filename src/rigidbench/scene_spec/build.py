"""Manifest row -> SceneSpec (pure Python; no bpy).

A single seed drives one NumPy generator that samples, in order: every task step's numbers and
objects, the cluster phase, the eight candidate task rotations (footprint fit) and the order in
which camera azimuths are searched. The same row therefore always gives the same spec.

Placement operations (task YAML ``steps``):
- ``drop`` / ``on_support``: one object at a sampled height above the support (bottom of its
  bounding box ``height_m`` above the top face), or resting on it; ``over`` centres it above an
  earlier group;
- ``ramp``: a passive five-face wedge; ``facing`` + ``gap_m`` puts its foot ``gap_m`` from the
  foot of an earlier ramp that descends the other way;
- ``on_ramp``: an object a quarter of the way down a ramp's slope, aligned with the slope and
  turned so its long axis runs across the slope (so it rolls);
- ``line``: objects in a row beyond a ramp's foot, spaced by their bounding boxes;
- ``cluster``: objects on a ring of radius (r + g/2)/sin(pi/n), relaxed with pymunk.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from ..errors import SpecError
from ..config import ObjectConfig, Registry, TaskStep
from ..rotations import quat_about_y, quat_about_z, quat_to_matrix
from . import cluster as cluster_ops
from . import footprint
from .types import Body, BodyPhysics, RampShape, SceneSpec, SimSpec, SupportSpec, quat_mul

PLACEMENT_CLEARANCE_M = 0.001  # gap left between a placed object and the surface below it
MAX_LAYOUT_ATTEMPTS = 20
RAMP_START_FRACTION = 0.25  # objects start a quarter of the way down the slope


def _box_corners(size_m: tuple[float, float, float]) -> np.ndarray:
    h = np.asarray(size_m) / 2
    return np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)]) * h


def body_aabb(body: Body) -> tuple[np.ndarray, np.ndarray]:
    """Axis-aligned bounds (min, max) of a body's rotated bounding box in its parent frame."""
    pts = _box_corners(body.size_m) @ quat_to_matrix(body.quat_wxyz, normalize=False).T + np.asarray(body.position_m)
    return pts.min(0), pts.max(0)


def indefinite(name: str) -> str:
    """'Apple' -> 'an apple'; 'Large die' -> 'a large die'."""
    lower = name[0].lower() + name[1:]
    return ("an " if lower[0] in "aeiou" else "a ") + lower


def make_prompt(template: str, names: dict[str, str]) -> str:
    """Fill ``{step}`` placeholders with object names with indefinite articles; capitalise."""
    text = template.format(**{k: indefinite(v) for k, v in names.items()})
    return text[0].upper() + text[1:]


@dataclass
class _Layout:
    """Bodies placed so far (task frame, before centring), keyed by step name."""

    bodies: list[Body]
    groups: dict[str, list[Body]]


def _uniform(rng: np.random.Generator, interval: tuple[float, float]) -> float:
    lo, hi = interval
    return float(lo + (hi - lo) * rng.random())


def _pick(rng: np.random.Generator, candidates: list[ObjectConfig]) -> ObjectConfig:
    return candidates[int(rng.integers(len(candidates)))]


def _physics(obj: ObjectConfig) -> BodyPhysics:
    return BodyPhysics(obj.physics.mass_kg, obj.physics.friction, obj.physics.restitution)


class _Builder:
    def __init__(self, registry: Registry, row: Any, rng: np.random.Generator):
        self.reg = registry
        self.row = row
        self.rng = rng
        self.allowed = [registry.object(o) for o in row.allowed_objects]
        self.counter = 0
        self.prompt_names: dict[str, str] = {}

    def candidates(self, tag: str, step: TaskStep) -> list[ObjectConfig]:
        found = [o for o in self.allowed if tag in o.tags]
        if not found:
            raise SpecError(f"example {self.row.sample_id}: task step '{step.name}' needs an object tagged "
                            f"'{tag}' but none of the allowed objects ({', '.join(o.id for o in self.allowed)}) has it")
        return found

    def new_body(self, obj: ObjectConfig, step: TaskStep, position, quat) -> Body:
        body = Body(name=f"{obj.id}_{self.counter}", asset=obj.id, role="active", step=step.name,
                    position_m=tuple(float(v) for v in position), quat_wxyz=tuple(float(v) for v in quat),
                    size_m=obj.size_m, physics=_physics(obj))
        self.counter += 1
        return body

    # -- operations ----------------------------------------------------------------------------

    def op_drop(self, step: TaskStep, layout: _Layout) -> None:
        obj = _pick(self.rng, self.candidates(step.params["tag"], step))
        height = _uniform(self.rng, step.params["height_m"]) if step.op == "drop" else 0.0
        yaw = 2 * math.pi * float(self.rng.random())
        xy = np.zeros(2)
        if "over" in step.params:
            group = layout.groups[step.params["over"]]
            lo = np.min([body_aabb(b)[0] for b in group], axis=0)
            hi = np.max([body_aabb(b)[1] for b in group], axis=0)
            xy = (lo[:2] + hi[:2]) / 2
        body = self.new_body(obj, step, (xy[0], xy[1], 0.0), quat_about_z(yaw))
        bottom = body_aabb(body)[0][2]
        body = _with_position(body, (xy[0], xy[1], height + PLACEMENT_CLEARANCE_M - bottom))
        layout.bodies.append(body)
        layout.groups[step.name] = [body]
        self.prompt_names[step.name] = obj.name

    op_on_support = op_drop

    def op_ramp(self, step: TaskStep, layout: _Layout) -> None:
        p = step.params
        length, height, width = (_uniform(self.rng, p[k]) for k in ("length_m", "height_m", "width_m"))
        material = self.reg.material(sorted(self.reg.materials)[int(self.rng.integers(len(self.reg.materials)))]).id
        if "facing" in p:
            other = layout.groups[p["facing"]][0]
            material = other.ramp.material  # a facing pair is one set of ramps
            gap = _uniform(self.rng, p.get("gap_m", (0.0, 0.0)))
            other_foot = other.position_m[0] + (other.ramp.length_m / 2 if _descends_plus(other) else -other.ramp.length_m / 2)
            foot = other_foot + (gap if _descends_plus(other) else -gap)
        else:
            foot = 0.0
        plus = p["descends"] == "+x"
        centre_x = foot - length / 2 if plus else foot + length / 2
        quat = (1.0, 0.0, 0.0, 0.0) if plus else quat_about_z(math.pi)
        body = Body(name=step.name, asset="ramp", role="passive", step=step.name,
                    position_m=(centre_x, 0.0, height / 2), quat_wxyz=quat, size_m=(length, width, height),
                    physics=BodyPhysics(0.0, self.reg.sim.passive_friction, self.reg.sim.passive_restitution),
                    ramp=RampShape(length_m=length, height_m=height, width_m=width, material=material))
        layout.bodies.append(body)
        layout.groups[step.name] = [body]

    def op_on_ramp(self, step: TaskStep, layout: _Layout) -> None:
        ramp = layout.groups[step.params["ramp"]][0]
        obj = _pick(self.rng, self.candidates(step.params["tag"], step))
        shape = ramp.ramp
        theta = math.atan2(shape.height_m, shape.length_m)
        sign = 1.0 if _descends_plus(ramp) else -1.0
        top_x = ramp.position_m[0] - sign * shape.length_m / 2
        # A quarter of the way down the slope, measured along the slope from its top edge.
        x = top_x + sign * RAMP_START_FRACTION * shape.length_m
        z = shape.height_m * (1 - RAMP_START_FRACTION)
        normal = np.array([sign * math.sin(theta), 0.0, math.cos(theta)])
        # Long axis across the slope (so elongated objects roll), then tilt onto the slope.
        quat = quat_mul(quat_about_y(sign * theta), quat_about_z(math.pi / 2))
        lift = obj.size_m[2] / 2 + PLACEMENT_CLEARANCE_M
        centre = np.array([x, ramp.position_m[1], z]) + normal * lift
        body = self.new_body(obj, step, centre, quat)
        layout.bodies.append(body)
        layout.groups[step.name] = [body]
        self.prompt_names[step.name] = obj.name

    def op_line(self, step: TaskStep, layout: _Layout) -> None:
        p = step.params
        after = layout.groups[p["after"]][0]
        sign = 1.0 if _descends_plus(after) else -1.0
        foot = after.position_m[0] + sign * after.size_m[0] / 2
        cursor = foot + sign * _uniform(self.rng, p["offset_m"])
        candidates = self.candidates(p["tag"], step)
        group = []
        for i in range(p["count"]):
            if i:
                cursor += sign * _uniform(self.rng, p["gap_m"])
            obj = _pick(self.rng, candidates)
            yaw = 2 * math.pi * float(self.rng.random())
            body = self.new_body(obj, step, (0.0, 0.0, 0.0), quat_about_z(yaw))
            lo, hi = body_aabb(body)
            near = lo[0] if sign > 0 else hi[0]
            far = hi[0] if sign > 0 else lo[0]
            body = _with_position(body, (cursor - near, 0.0, PLACEMENT_CLEARANCE_M - lo[2]))
            cursor += far - near
            group.append(body)
        layout.bodies.extend(group)
        layout.groups[step.name] = group

    def op_cluster(self, step: TaskStep, layout: _Layout) -> None:
        p = step.params
        candidates = self.candidates(p["tag"], step)
        objs = [_pick(self.rng, candidates) for _ in range(p["count"])]
        gap = _uniform(self.rng, p["gap_m"])
        radii = np.array([o.footprint_radius_m for o in objs])
        radius = cluster_ops.ring_radius(float(radii.max()), gap, len(objs))
        phase = 2 * math.pi * float(self.rng.random())
        start = cluster_ops.ring_positions(len(objs), radius, phase)
        relaxed = cluster_ops.relax(start, radii)
        group = []
        for obj, (x, y) in zip(objs, relaxed):
            yaw = 2 * math.pi * float(self.rng.random())
            body = self.new_body(obj, step, (0.0, 0.0, 0.0), quat_about_z(yaw))
            bottom = body_aabb(body)[0][2]
            group.append(_with_position(body, (float(x), float(y), PLACEMENT_CLEARANCE_M - bottom)))
        layout.bodies.extend(group)
        layout.groups[step.name] = group


def _descends_plus(ramp: Body) -> bool:
    return abs(ramp.quat_wxyz[0]) > abs(ramp.quat_wxyz[3])  # yaw 0 -> +x, yaw pi -> -x


def _with_position(body: Body, position) -> Body:
    return replace(body, position_m=tuple(float(v) for v in position))


def _footprint(bodies: list[Body]) -> tuple[np.ndarray, np.ndarray]:
    lo = np.min([body_aabb(b)[0] for b in bodies], axis=0)
    hi = np.max([body_aabb(b)[1] for b in bodies], axis=0)
    return lo, hi


def azimuth_candidates(ranges_deg: tuple[tuple[float, float], ...], step_deg: float) -> list[float]:
    """Task-relative azimuths every ``step_deg`` inside the allowed ranges (inclusive), deduplicated mod 360."""
    out: list[float] = []
    for lo, hi in ranges_deg:
        a = math.ceil(lo / step_deg - 1e-9) * step_deg
        while a <= hi + 1e-9:
            v = round(a % 360.0, 9)
            if v not in out:
                out.append(v)
            a += step_deg
    return out


def build_scene_spec(row: Any, registry: Registry) -> SceneSpec:
    """Turn a manifest row (sample_id, split, task, scene, surface, seed, partition, allowed_objects)
    into a SceneSpec. Raises SpecError naming the example when the task cannot be laid out."""
    task = registry.task(row.task)
    scene = registry.scene(row.scene)
    support_cfg = scene.support(row.surface)
    rng = np.random.default_rng(row.seed)
    builder = _Builder(registry, row, rng)
    support_lw = support_cfg.size_m
    for attempt in range(MAX_LAYOUT_ATTEMPTS):
        builder.counter = 0
        builder.prompt_names = {}
        layout = _Layout(bodies=[], groups={})
        for step in task.steps:
            getattr(builder, f"op_{step.op}")(step, layout)
        lo, hi = _footprint(layout.bodies)
        size = hi - lo
        task_lw = (float(size[0]), float(size[1]))
        intervals = footprint.fit_intervals(task_lw, support_lw, math.radians(support_cfg.long_axis_deg))
        if intervals:
            break
    else:
        raise SpecError(f"example {row.sample_id}: task '{row.task}' (last footprint {task_lw[0]:.3f} x "
                        f"{task_lw[1]:.3f} m) never fits support '{row.surface}' of scene '{row.scene}' "
                        f"({support_lw[0]} x {support_lw[1]} m) in {MAX_LAYOUT_ATTEMPTS} attempts; "
                        "enlarge the support in the scene YAML or narrow the task's ranges")
    centre = (lo + hi) / 2
    bodies = tuple(_with_position(b, (b.position_m[0] - centre[0], b.position_m[1] - centre[1], b.position_m[2]))
                   for b in layout.bodies)
    rotations = tuple(round(math.degrees(footprint.sample_rotation(rng, intervals)), 9)
                      for _ in range(registry.camera.rotation_attempts))
    azimuths = azimuth_candidates(task.azimuth_ranges_deg, registry.camera.azimuth_step_deg)
    order = rng.permutation(len(azimuths))
    override = task.support_override
    support_physics = BodyPhysics(0.0, override.friction if override else registry.sim.passive_friction,
                                  override.restitution if override else registry.sim.passive_restitution)
    sim = registry.sim
    return SceneSpec(
        sample_id=row.sample_id, split=row.split, task=row.task, scene=row.scene, surface=row.surface,
        seed=int(row.seed), partition=row.partition, allowed_objects=tuple(row.allowed_objects),
        prompt=make_prompt(task.prompt, builder.prompt_names),
        support=SupportSpec(name=support_cfg.name, centre_m=support_cfg.centre_m, size_m=support_cfg.size_m,
                            long_axis_deg=support_cfg.long_axis_deg, physics=support_physics),
        bodies=bodies, footprint_m=task_lw, rotation_candidates_deg=rotations, task_rotation_deg=rotations[0],
        azimuth_candidates_deg=tuple(float(azimuths[i]) for i in order),
        sim=SimSpec(fps=sim.fps, frames=sim.frames, substeps=sim.substeps, solver_iterations=sim.solver_iterations,
                    gravity_m_s2=sim.gravity_m_s2, linear_damping=sim.linear_damping,
                    angular_damping=sim.angular_damping, active_margin_m=sim.active_margin_m,
                    passive_margin_m=sim.passive_margin_m),
    )
