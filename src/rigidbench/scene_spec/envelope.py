"""The physical envelope's perturbation: a reference SceneSpec -> one physical twin (pure; no bpy).

A twin is the reference with its initial state and material parameters drawn within what one frame
cannot resolve. How far is data, ``configs/envelope.yaml`` (each number with its reason), read by
``load_envelope`` into an ``EnvelopeConfig``: the standard deviations of zero-mean Gaussians for the
position (m), the orientation (degrees) and, relative, the restitution, friction and mass.

``perturb_spec(spec, registry, config, seed, scale)`` draws every number from
``numpy.random.default_rng(seed)`` in a fixed order, so one seed gives one twin on every machine;
``scale`` multiplies every standard deviation, and ``scale = 0`` returns the reference's spec and
registry themselves. What is drawn, in the task frame (where the SceneSpec lays the bodies out):

- each active actor, in spec order: a position offset and a rotation vector (each three standard
  normals times the config's deviation), then relative changes of its friction, restitution and mass.
  An actor resting on something at frame 0 keeps resting on it: its offset is projected onto the plane
  it rests on and its rotation onto that plane's normal (it slides and turns in the plane). The plane
  follows from the task step that placed it (``resting_normals``): the support's top face for
  ``on_support``, ``line`` and ``cluster`` steps, the ramp's slope for ``on_ramp``; a ``drop`` step's
  actor is free in all six directions. A body whose step the task does not name (a hand-made spec)
  rests on the support when its bounding box is within ``RESTING_TOLERANCE_M`` of its top face;
- then each passive surface, the ramps in spec order, the support and the floor (the registry's
  passive friction and restitution): relative changes of friction and restitution.

Relative changes multiply by (1 + sigma z): friction and mass stay positive (clipped at 0 and at
``MIN_MASS_FRACTION`` of the reference's mass), restitution stays in [0, 1]. The rotation turns the
actor about its own origin: q' = exp(omega / 2) q.

``admissible(twin_spec) -> bool``, when given, may refuse a draw (the twins predictor refuses those that
bring two actors into contact where the reference's are apart); a refused draw is followed by the next
one from the same generator, up to ``MAX_DRAWS``.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Mapping

import numpy as np

from ..config import Registry, config_file, read_config_yaml
from ..errors import ConfigError, SpecError, UserError
from ..rotations import quat_mul, quat_to_matrix
from .build import body_aabb
from .types import Body, BodyPhysics, SceneSpec

ENVELOPE_FILE = "envelope.yaml"
MAX_DRAWS = 100  # draws refused by ``admissible`` before a twin is given up
MIN_MASS_FRACTION = 0.05  # a relative mass change never leaves less than this of the reference's mass
RESTING_TOLERANCE_M = 0.005  # bottom this close to the support's top face: resting on it (drops start >= 0.5 m up)
SUPPORT_STEPS = ("on_support", "line", "cluster")  # task-step ops whose actors rest on the support at frame 0
UP = np.array([0.0, 0.0, 1.0])


@dataclass(frozen=True)
class Noise:
    """One standard deviation of the envelope and why it is what it is."""

    value: float
    reason: str


@dataclass(frozen=True)
class EnvelopeConfig:
    """Standard deviations of a twin's perturbation (``configs/envelope.yaml``); ``source``: the file read."""

    position_m: Noise
    orientation_deg: Noise
    restitution_rel: Noise
    friction_rel: Noise
    mass_rel: Noise
    source: str = ""

    def numbers(self) -> dict[str, float]:
        """{entry: value}: what makes twins differ (a predictor's settings)."""
        return {f.name: getattr(self, f.name).value for f in dataclasses.fields(self) if f.name != "source"}

    def to_dict(self) -> dict[str, Any]:
        """{entry: {"value", "reason"}} and the source file (``envelope.json``'s "config")."""
        out: dict[str, Any] = {f.name: dataclasses.asdict(getattr(self, f.name))
                               for f in dataclasses.fields(self) if f.name != "source"}
        out["source"] = self.source
        return out


ENTRIES = tuple(f.name for f in dataclasses.fields(EnvelopeConfig) if f.name != "source")
RELATIVE = tuple(name for name in ENTRIES if name.endswith("_rel"))


def _bad(path: Path, key: str, message: str) -> UserError:
    return UserError(f"{path}: key '{key}': {message}; fix the envelope configuration (see {ENVELOPE_FILE} "
                     "in rigidbench/configs for the expected form)")


def _noise(path: Path, key: str, entry: Any) -> Noise:
    if not isinstance(entry, Mapping):
        raise _bad(path, key, f"expected a mapping with 'value' and 'reason', got {entry!r}")
    extra = sorted(set(entry) - {"value", "reason"})
    if extra:
        raise _bad(path, f"{key}.{extra[0]}", "unknown field; an entry has only 'value' and 'reason'")
    value, reason = entry.get("value"), entry.get("reason")
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value) or value < 0:
        raise _bad(path, f"{key}.value", f"expected a finite number >= 0, got {value!r}")
    if key in RELATIVE and value >= 1:
        raise _bad(path, f"{key}.value", f"a relative deviation must be below 1, got {value!r}")
    if not isinstance(reason, str) or not reason.strip():
        raise _bad(path, f"{key}.reason", "every number needs its reason (a non-empty string)")
    return Noise(float(value), " ".join(reason.split()))


def load_envelope(path: str | Path | None = None, config_dirs=()) -> EnvelopeConfig:
    """The envelope configuration in ``path``, or (None) the ``envelope.yaml`` of the last configuration
    directory that has one (``config_dirs`` over the packaged ``configs/``). A UserError naming the file and
    the key when it cannot be used."""
    try:
        path = Path(path).expanduser() if path is not None else config_file(ENVELOPE_FILE, config_dirs)
        data = read_config_yaml(path)
    except ConfigError as exc:
        raise UserError(str(exc)) from None
    if not isinstance(data, Mapping):
        raise _bad(path, "<root>", f"expected a mapping of {', '.join(ENTRIES)}, got {type(data).__name__}")
    for key in data:
        if key not in ENTRIES:
            raise _bad(path, str(key), f"unknown entry; the entries are {', '.join(ENTRIES)}")
    for key in ENTRIES:
        if key not in data:
            raise _bad(path, key, "is missing")
    return EnvelopeConfig(**{key: _noise(path, key, data[key]) for key in ENTRIES}, source=str(path))


# -- what each actor rests on ------------------------------------------------------------------------------


def ramp_normal(ramp: Body) -> np.ndarray:
    """Unit normal (3,) of a ramp body's slope in the task frame (its model frame descends toward +x)."""
    shape = ramp.ramp
    if shape is None:
        raise SpecError(f"body '{ramp.name}' is not a ramp")
    local = np.array([shape.height_m, 0.0, shape.length_m]) / math.hypot(shape.height_m, shape.length_m)
    return quat_to_matrix(np.asarray(ramp.quat_wxyz, np.float64)) @ local


def resting_normals(spec: SceneSpec, registry: Registry) -> dict[str, np.ndarray | None]:
    """Active actor name -> unit normal (3,) of the plane it rests on at frame 0, None for a free actor."""
    steps = {s.name: s for s in registry.tasks[spec.task].steps} if spec.task in registry.tasks else {}
    out: dict[str, np.ndarray | None] = {}
    for body in spec.active:
        step = steps.get(body.step)
        if step is None:  # a hand-made spec: resting on the support if it starts on it
            out[body.name] = UP if body_aabb(body)[0][2] <= RESTING_TOLERANCE_M else None
        elif step.op in SUPPORT_STEPS:
            out[body.name] = UP
        elif step.op == "on_ramp":
            out[body.name] = ramp_normal(spec.body(step.params["ramp"]))
        else:
            out[body.name] = None
    return out


# -- the draw ----------------------------------------------------------------------------------------------


def quat_from_rotation_vector(omega: np.ndarray) -> np.ndarray:
    """(w, x, y, z) of the turn by |omega| radians about omega (3,)."""
    angle = float(np.linalg.norm(omega))
    if angle == 0.0:
        return np.array([1.0, 0.0, 0.0, 0.0])
    return np.concatenate([[math.cos(angle / 2)], math.sin(angle / 2) * np.asarray(omega, np.float64) / angle])


def _relative(value: float, sigma: float, z: float, lo: float = 0.0, hi: float = math.inf) -> float:
    return float(min(max(value * (1.0 + sigma * z), lo), hi))


def _surface(physics: BodyPhysics, config: EnvelopeConfig, scale: float, z: np.ndarray) -> BodyPhysics:
    """Friction and restitution of a surface changed by standard normals z (2,)."""
    return dataclasses.replace(
        physics, friction=_relative(physics.friction, config.friction_rel.value * scale, z[0]),
        restitution=_relative(physics.restitution, config.restitution_rel.value * scale, z[1], hi=1.0))


def _draw(spec: SceneSpec, registry: Registry, config: EnvelopeConfig, scale: float, rng: np.random.Generator,
          normals: Mapping[str, np.ndarray | None]) -> tuple[SceneSpec, Registry]:
    sigma_p = config.position_m.value * scale
    sigma_r = math.radians(config.orientation_deg.value) * scale
    bodies = []
    for body in spec.bodies:
        if body.role == "active":
            z_pos, z_rot, z_mat = rng.standard_normal(3), rng.standard_normal(3), rng.standard_normal(3)
            n = normals[body.name]
            if n is not None:  # slide within the resting plane, turn about its normal
                z_pos = z_pos - n * float(n @ z_pos)
                z_rot = n * float(n @ z_rot)
            quat = quat_mul(quat_from_rotation_vector(sigma_r * z_rot), np.asarray(body.quat_wxyz, np.float64))
            mass = body.physics.mass_kg
            physics = dataclasses.replace(_surface(body.physics, config, scale, z_mat[:2]), mass_kg=_relative(
                mass, config.mass_rel.value * scale, z_mat[2], lo=MIN_MASS_FRACTION * mass))
            position = np.asarray(body.position_m, np.float64) + sigma_p * z_pos
            body = dataclasses.replace(body, position_m=tuple(float(v) for v in position),
                                       quat_wxyz=tuple(float(v) for v in quat), physics=physics)
        bodies.append(body)
    for k, body in enumerate(bodies):
        if body.role != "active":
            bodies[k] = dataclasses.replace(body, physics=_surface(body.physics, config, scale, rng.standard_normal(2)))
    support = dataclasses.replace(spec.support, physics=_surface(spec.support.physics, config, scale,
                                                                 rng.standard_normal(2)))
    floor = _surface(BodyPhysics(0.0, registry.sim.passive_friction, registry.sim.passive_restitution), config, scale,
                     rng.standard_normal(2))
    sim = dataclasses.replace(registry.sim, passive_friction=floor.friction, passive_restitution=floor.restitution)
    return (dataclasses.replace(spec, bodies=tuple(bodies), support=support), dataclasses.replace(registry, sim=sim))


def perturb_spec(spec: SceneSpec, registry: Registry, config: EnvelopeConfig, seed: int, scale: float,
                 admissible: Callable[[SceneSpec], bool] | None = None) -> tuple[SceneSpec, Registry]:
    """One physical twin of ``spec``: (twin spec, registry with the twin's floor physics); see the module
    docstring. ``scale`` >= 0 multiplies every deviation; 0 returns ``(spec, registry)`` unchanged. A
    SpecError naming the example when ``MAX_DRAWS`` draws in a row are refused by ``admissible``."""
    scale = float(scale)
    if not math.isfinite(scale) or scale < 0:
        raise ValueError(f"the perturbation scale must be a finite number >= 0, got {scale}")
    if scale == 0.0:
        return spec, registry
    rng = np.random.default_rng(int(seed))
    normals = resting_normals(spec, registry)
    for _ in range(MAX_DRAWS):
        twin = _draw(spec, registry, config, scale, rng, normals)
        if admissible is None or admissible(twin[0]):
            return twin
    raise SpecError(f"example {spec.sample_id}: {MAX_DRAWS} twins drawn at scale {scale:g} (seed {seed}) all put "
                    "actors into contact that are apart in the reference; lower the scale or the envelope's "
                    "position_m and orientation_deg")


__all__ = ["ENVELOPE_FILE", "ENTRIES", "EnvelopeConfig", "MAX_DRAWS", "Noise", "load_envelope", "perturb_spec",
           "quat_from_rotation_vector", "ramp_normal", "resting_normals"]
