"""SceneSpec: the plain-data description of one example, from which simulation and render follow.

Conventions (used everywhere in RigidBench):
- metres, seconds, kilograms; world +z is up; quaternions are (w, x, y, z) as Blender stores them;
- an object's model frame has its origin at the centre of its resting bounding box, +z up and +x
  along the long axis;
- bodies are laid out in the *task frame* (origin at the centre of the task footprint on the
  support's top face); ``SceneSpec.world_bodies()`` rotates them by the task rotation about +z and
  moves them onto the support. Changing ``task_rotation_deg`` therefore re-poses the whole layout.
"""

from __future__ import annotations

import dataclasses
import json
import math
import types
import typing
from dataclasses import dataclass
from typing import Any

import numpy as np

from .. import rotations

SPEC_VERSION = 1


@dataclass(frozen=True)
class BodyPhysics:
    mass_kg: float  # 0 for passive bodies
    friction: float
    restitution: float


@dataclass(frozen=True)
class RampShape:
    """A five-face wedge: bottom, back wall, slope and two triangular sides.

    In its model frame the ramp spans x in [-L/2, L/2], y in [-W/2, W/2], z in [-H/2, H/2], its
    high end (back wall) at x = -L/2 so the slope descends toward +x.
    """

    length_m: float
    height_m: float
    width_m: float
    material: str


@dataclass(frozen=True)
class Body:
    name: str  # unique actor name within the example, e.g. "apple_0", "ramp_a"
    asset: str  # object id, or "ramp"
    role: str  # "active" (simulated, scored) or "passive" (task geometry such as ramps)
    step: str  # the task step that placed it
    position_m: tuple[float, float, float]
    quat_wxyz: tuple[float, float, float, float]
    size_m: tuple[float, float, float]  # resting bounding box in the model frame
    physics: BodyPhysics
    ramp: RampShape | None = None


@dataclass(frozen=True)
class SupportSpec:
    name: str
    centre_m: tuple[float, float, float]  # top-face centre
    size_m: tuple[float, float]  # (long, short)
    long_axis_deg: float
    physics: BodyPhysics


@dataclass(frozen=True)
class CameraSpec:
    """A pinhole camera looking at ``target_m`` from ``azimuth_deg`` (world, about +z)."""

    azimuth_deg: float  # world azimuth of the camera position around the target
    relative_azimuth_deg: float  # azimuth relative to the task rotation
    elevation_deg: float
    distance_m: float
    target_m: tuple[float, float, float]
    lens_mm: float
    sensor_width_mm: float
    visibility: float  # fraction of sampled target points visible from this camera


@dataclass(frozen=True)
class SimSpec:
    fps: int
    frames: int
    substeps: int
    solver_iterations: int
    gravity_m_s2: float
    linear_damping: float
    angular_damping: float
    active_margin_m: float
    passive_margin_m: float


@dataclass(frozen=True)
class SceneSpec:
    sample_id: str
    split: str
    task: str
    scene: str
    surface: str
    seed: int
    partition: str
    allowed_objects: tuple[str, ...]
    prompt: str
    support: SupportSpec
    bodies: tuple[Body, ...]  # in the task frame
    footprint_m: tuple[float, float]  # axis-aligned (L_T, W_T) in the task frame
    rotation_candidates_deg: tuple[float, ...]  # world yaw angles sampled from the footprint fit
    task_rotation_deg: float  # the chosen candidate
    azimuth_candidates_deg: tuple[float, ...]  # task-relative azimuths to search, in seeded order
    sim: SimSpec
    camera: CameraSpec | None = None
    render_preset: str | None = None
    version: int = SPEC_VERSION

    # -- derived views -----------------------------------------------------------------------

    @property
    def active(self) -> tuple[Body, ...]:
        return tuple(b for b in self.bodies if b.role == "active")

    def body(self, name: str) -> Body:
        for b in self.bodies:
            if b.name == name:
                return b
        raise KeyError(f"example {self.sample_id}: no body named '{name}'")

    def world_bodies(self) -> tuple[Body, ...]:
        """Bodies posed in the world: task frame rotated by ``task_rotation_deg`` onto the support."""
        yaw = math.radians(self.task_rotation_deg)
        c, s = math.cos(yaw), math.sin(yaw)
        qz = (math.cos(yaw / 2), 0.0, 0.0, math.sin(yaw / 2))
        cx, cy, cz = self.support.centre_m
        out = []
        for b in self.bodies:
            x, y, z = b.position_m
            pos = (cx + c * x - s * y, cy + s * x + c * y, cz + z)
            out.append(dataclasses.replace(b, position_m=pos, quat_wxyz=quat_mul(qz, b.quat_wxyz)))
        return tuple(out)

    # -- serialisation -----------------------------------------------------------------------

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)

    def to_json(self, indent: int | None = 2) -> str:
        return json.dumps(self.to_dict(), indent=indent)

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> "SceneSpec":
        if data.get("version", SPEC_VERSION) != SPEC_VERSION:
            raise ValueError(f"SceneSpec version {data.get('version')} is not supported (expected {SPEC_VERSION})")
        return _from_data(cls, data)

    @classmethod
    def from_json(cls, text: str) -> "SceneSpec":
        return cls.from_dict(json.loads(text))


def quat_mul(a: tuple[float, ...], b: tuple[float, ...]) -> tuple[float, float, float, float]:
    """Hamilton product of two (w, x, y, z) quaternions, as a tuple of floats (``rotations.quat_mul``)."""
    return tuple(float(v) for v in rotations.quat_mul(np.asarray(a, np.float64), np.asarray(b, np.float64)))


def _from_data(tp: Any, value: Any) -> Any:
    """Rebuild a (nested) dataclass value from JSON data using its type hints."""
    origin = typing.get_origin(tp)
    if dataclasses.is_dataclass(tp):
        hints = typing.get_type_hints(tp)
        kwargs = {f.name: _from_data(hints[f.name], value[f.name]) for f in dataclasses.fields(tp) if f.name in value}
        return tp(**kwargs)
    if origin in (typing.Union, types.UnionType):
        args = typing.get_args(tp)
        if value is None:
            return None
        return _from_data(next(a for a in args if a is not type(None)), value)
    if origin is tuple:
        args = typing.get_args(tp)
        if len(args) == 2 and args[1] is Ellipsis:
            return tuple(_from_data(args[0], v) for v in value)
        return tuple(_from_data(a, v) for a, v in zip(args, value))
    if tp is float:
        return float(value)
    return value


__all__ = ["SceneSpec", "Body", "BodyPhysics", "RampShape", "SupportSpec", "CameraSpec", "SimSpec", "quat_mul",
           "SPEC_VERSION"]
