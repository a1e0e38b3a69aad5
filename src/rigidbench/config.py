"""Load and validate the YAML registry (tasks, objects, scenes, materials, presets, splits).

Every file is validated when it is loaded and cross-referenced against the others, so a typo
fails early with a message naming the file, the field and the values that would be accepted.
Extra directories (``extra_dirs``; the command line builds them from ``--config`` and
``RIGIDBENCH_CONFIG_PATH``, ``os.pathsep``-separated) are layered over the packaged ``configs/``: a file with the same ``id`` replaces the packaged
one, a new ``id`` adds an object, scene, task or material.
"""

from __future__ import annotations

import dataclasses
import difflib
import functools
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterable, Mapping, Sequence

import yaml

from .errors import ConfigError

PACKAGE_CONFIG_DIR = Path(__file__).resolve().parent / "configs"

OBJECT_PARTITIONS = ("train", "held_out")
SCENE_PARTITIONS = ("train", "held_out")
SHAPES = ("ellipsoid", "cylinder", "box", "banana")
STEP_OPS = ("drop", "on_support", "ramp", "on_ramp", "line", "cluster")
DIRECTIONS = ("+x", "-x")
MESH_SUFFIXES = (".glb", ".gltf", ".obj", ".blend")


def _fail(path: Path | str, field_name: str, message: str) -> ConfigError:
    return ConfigError(f"{path}: field '{field_name}': {message}")


def _suggest(value: str, known: Iterable[str]) -> str:
    known = sorted(known)
    close = difflib.get_close_matches(str(value), known, n=1)
    hint = f" (did you mean '{close[0]}'?)" if close else ""
    return f"{hint}; known values: {', '.join(known)}"


# ---------------------------------------------------------------------------------------------
# Typed field readers: each names the file and field on failure.


class _Reader:
    def __init__(self, path: Path, data: Any, prefix: str = ""):
        if not isinstance(data, Mapping):
            raise _fail(path, prefix or "<root>", f"expected a mapping, got {type(data).__name__}")
        self.path, self.data, self.prefix = path, data, prefix

    def _name(self, key: str) -> str:
        return f"{self.prefix}{key}"

    def has(self, key: str) -> bool:
        return key in self.data and self.data[key] is not None

    def raw(self, key: str, default: Any = ...) -> Any:
        if key not in self.data or self.data[key] is None:
            if default is ...:
                raise _fail(self.path, self._name(key), "is required but missing")
            return default
        return self.data[key]

    def str(self, key: str, default: Any = ..., choices: Iterable[str] | None = None) -> str:
        value = self.raw(key, default)
        if value is None:
            return value
        if not isinstance(value, str):
            raise _fail(self.path, self._name(key), f"expected a string, got {value!r}")
        if choices is not None and value not in choices:
            raise _fail(self.path, self._name(key), f"unknown value '{value}'" + _suggest(value, choices))
        return value

    def float(self, key: str, default: Any = ..., lo: float | None = None, hi: float | None = None,
              positive: bool = False) -> float:
        value = self.raw(key, default)
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise _fail(self.path, self._name(key), f"expected a number, got {value!r}")
        value = float(value)
        if positive and not value > 0:
            raise _fail(self.path, self._name(key), f"must be > 0, got {value}")
        if lo is not None and hi is None and value < lo:
            raise _fail(self.path, self._name(key), f"must be >= {lo:g}, got {value}")
        if lo is not None and value < lo or hi is not None and value > hi:
            raise _fail(self.path, self._name(key), f"must lie in [{lo}, {hi}], got {value}")
        return value

    def int(self, key: str, default: Any = ..., lo: int | None = None) -> int:
        value = self.raw(key, default)
        if isinstance(value, bool) or not isinstance(value, int):
            raise _fail(self.path, self._name(key), f"expected an integer, got {value!r}")
        if lo is not None and value < lo:
            raise _fail(self.path, self._name(key), f"must be >= {lo}, got {value}")
        return value

    def bool(self, key: str, default: Any = ...) -> bool:
        value = self.raw(key, default)
        if not isinstance(value, bool):
            raise _fail(self.path, self._name(key), f"expected true or false, got {value!r}")
        return value

    def vector(self, key: str, n: int, default: Any = ..., positive: bool = False) -> tuple[float, ...]:
        value = self.raw(key, default)
        if (not isinstance(value, (list, tuple)) or len(value) != n
                or not all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in value)):
            raise _fail(self.path, self._name(key), f"expected a list of {n} numbers, got {value!r}")
        if positive and not all(v > 0 for v in value):
            raise _fail(self.path, self._name(key), f"all entries must be > 0, got {value!r}")
        return tuple(float(v) for v in value)

    def interval(self, key: str, default: Any = ..., positive: bool = False) -> tuple[float, float]:
        """A [lo, hi] range sampled uniformly; a single number means a fixed value."""
        value = self.raw(key, default)
        if isinstance(value, (int, float)) and not isinstance(value, bool):
            value = [value, value]
        lo, hi = _Reader(self.path, {key: value}, self.prefix).vector(key, 2)
        if lo > hi:
            raise _fail(self.path, self._name(key), f"lower bound {lo} exceeds upper bound {hi}")
        if positive and lo <= 0:
            raise _fail(self.path, self._name(key), f"must be > 0, got {value!r}")
        return (lo, hi)

    def str_list(self, key: str, default: Any = ..., choices: Iterable[str] | None = None) -> tuple[str, ...]:
        value = self.raw(key, default)
        if not isinstance(value, (list, tuple)) or not all(isinstance(v, str) for v in value):
            raise _fail(self.path, self._name(key), f"expected a list of strings, got {value!r}")
        if choices is not None:
            for v in value:
                if v not in choices:
                    raise _fail(self.path, self._name(key), f"unknown value '{v}'" + _suggest(v, choices))
        return tuple(value)

    def text(self, key: str, default: Any = ...) -> str | None:
        """A non-empty string (or ``default``, which may be None)."""
        value = self.str(key, default)
        if value is not None and not value:
            raise _fail(self.path, self._name(key), "expected a non-empty string")
        return value

    def numbers(self, cls: type, lows: Mapping[str, float]) -> Any:
        """A dataclass of numbers from this mapping, each field optional (the dataclass default);
        integer defaults make integer fields. ``lows`` gives a lower bound per field (else 0)."""
        names = list(cls.__dataclass_fields__)
        self.reject_unknown(names)
        values = {}
        for n in names:
            if self.has(n):
                lo = lows.get(n, 0)
                default = cls.__dataclass_fields__[n].default
                values[n] = self.int(n, lo=int(lo)) if isinstance(default, int) else self.float(n, lo=float(lo))
        return cls(**values)

    def sub(self, key: str, default: Any = ...) -> "_Reader":
        return _Reader(self.path, self.raw(key, default), self._name(key) + ".")

    def items(self, key: str) -> list["_Reader"]:
        value = self.raw(key)
        if not isinstance(value, list) or not value:
            raise _fail(self.path, self._name(key), "expected a non-empty list")
        return [_Reader(self.path, v, f"{self._name(key)}[{i}].") for i, v in enumerate(value)]

    def reject_unknown(self, allowed: Iterable[str]) -> None:
        allowed = set(allowed)
        for key in self.data:
            if key not in allowed:
                raise _fail(self.path, self._name(str(key)), "unknown field" + _suggest(str(key), allowed))


FieldReader = _Reader  # the public name, for config files outside this module (predictors/hosted.py)


# ---------------------------------------------------------------------------------------------
# Frozen specs


@dataclass(frozen=True)
class Physics:
    """Bullet material of one body: mass (kg; 0 for passive), friction and restitution."""

    mass_kg: float
    friction: float
    restitution: float


@dataclass(frozen=True)
class ObjectConfig:
    id: str
    name: str
    partition: str
    tags: tuple[str, ...]
    size_m: tuple[float, float, float]  # bounding box x (long axis), y, z (up) at rest
    physics: Physics
    shape: str  # stand-in primitive and footprint rule
    mesh_path: str | None = None  # user mesh (glTF, OBJ, .blend) replacing the procedural builder
    description: str = ""
    source: str = ""

    @property
    def footprint_radius_m(self) -> float:
        """Radius of the circle that encloses the resting footprint (used by clusters)."""
        sx, sy, _ = self.size_m
        if self.shape == "box":
            return 0.5 * (sx * sx + sy * sy) ** 0.5
        return 0.5 * max(sx, sy)


@dataclass(frozen=True)
class SupportConfig:
    name: str
    centre_m: tuple[float, float, float]  # centre of the top face; z is its height
    size_m: tuple[float, float]  # (long, short)
    long_axis_deg: float


@dataclass(frozen=True)
class SceneConfig:
    id: str
    name: str
    partition: str
    supports: tuple[SupportConfig, ...]
    floor_z_m: float = 0.0
    style: Mapping[str, Any] = field(default_factory=dict)
    mesh_path: str | None = None
    description: str = ""
    source: str = ""

    def support(self, name: str) -> SupportConfig:
        for s in self.supports:
            if s.name == name:
                return s
        raise ConfigError(f"{self.source}: field 'supports': scene '{self.id}' has no support '{name}'"
                          + _suggest(name, [s.name for s in self.supports]))


@dataclass(frozen=True)
class TaskStep:
    """One placement operation of a task; ``params`` holds op-specific validated values."""

    op: str
    name: str
    params: Mapping[str, Any]


@dataclass(frozen=True)
class TaskConfig:
    id: str
    name: str
    prompt: str
    azimuth_ranges_deg: tuple[tuple[float, float], ...]
    steps: tuple[TaskStep, ...]
    support_override: Physics | None = None
    source: str = ""


@dataclass(frozen=True)
class MaterialConfig:
    id: str
    name: str
    params: Mapping[str, Any]
    source: str = ""


@dataclass(frozen=True)
class RenderPreset:
    name: str
    resolution: tuple[int, int]  # (width, height)
    frames: int
    samples: int
    adaptive_threshold: float | None
    denoise: bool
    max_bounces: int
    diffuse_bounces: int
    glossy_bounces: int
    transmission_bounces: int
    persistent_data: bool
    # "full": path traced to the bounce limits with the light tree and bump mapping (the paper);
    # "fast": Cycles fast GI past the first bounce, lights sampled by power, no bump mapping.
    light_transport: str = "full"
    # OpenImageDenoise quality: "high" (prefilter ACCURATE, the paper), "balanced" or "fast" (prefilter FAST).
    denoise_quality: str = "high"


LIGHT_TRANSPORTS = ("full", "fast")
DENOISE_QUALITIES = ("high", "balanced", "fast")


@dataclass(frozen=True)
class SimSettings:
    fps: int = 24
    frames: int = 49
    substeps: int = 30
    solver_iterations: int = 20
    gravity_m_s2: float = 9.81
    linear_damping: float = 0.1
    angular_damping: float = 0.5
    active_margin_m: float = 0.001
    passive_margin_m: float = 0.0001
    passive_friction: float = 0.4
    passive_restitution: float = 0.3
    contact_tolerance_m: float = 0.003
    max_contact_points: int = 5


@dataclass(frozen=True)
class CameraSettings:
    lens_mm: float = 35.0
    sensor_width_mm: float = 36.0
    elevation_deg: float = 10.0
    min_distance_m: float = 1.4
    framing_multiplier: float = 1.4
    bbox_padding_m: float = 0.2
    azimuth_step_deg: float = 15.0
    visibility_threshold: float = 0.5
    rotation_attempts: int = 8
    points_per_target: int = 16
    view_grid_cols: int = 16  # rays across the image for the clearance and background checks
    view_grid_rows: int = 9
    max_obstruction: float = 0.02  # largest fraction of those rays that may hit something nearer than the framed box
    # the furnished-background preference applies only among views this close to the best visibility
    background_visibility_margin: float = 0.1


@dataclass(frozen=True)
class EvalPartition:
    id: str
    scenes: str  # "train" or "held_out"
    objects: str


@dataclass(frozen=True)
class SplitConfig:
    train_seed: int
    train_per_scene: int
    train_task_counts: Mapping[str, int]
    eval_seed: int
    eval_per_task: int
    eval_partitions: tuple[EvalPartition, ...]


@dataclass(frozen=True)
class Registry:
    """Everything the configs declare, validated and cross-referenced."""

    objects: Mapping[str, ObjectConfig]
    scenes: Mapping[str, SceneConfig]
    tasks: Mapping[str, TaskConfig]
    materials: Mapping[str, MaterialConfig]
    presets: Mapping[str, RenderPreset]
    sim: SimSettings
    camera: CameraSettings
    splits: SplitConfig
    tags: tuple[str, ...]

    def object(self, key: str) -> ObjectConfig:
        return _lookup(self.objects, key, "object")

    def scene(self, key: str) -> SceneConfig:
        return _lookup(self.scenes, key, "scene")

    def task(self, key: str) -> TaskConfig:
        return _lookup(self.tasks, key, "task")

    def material(self, key: str) -> MaterialConfig:
        return _lookup(self.materials, key, "ramp material")

    def preset(self, key: str) -> RenderPreset:
        return _lookup(self.presets, key, "render preset")

    def objects_in(self, partition: str) -> tuple[str, ...]:
        return tuple(sorted(o.id for o in self.objects.values() if o.partition == partition))

    def scenes_in(self, partition: str) -> tuple[str, ...]:
        return tuple(sorted(s.id for s in self.scenes.values() if s.partition == partition))


def _lookup(table: Mapping[str, Any], key: str, what: str) -> Any:
    try:
        return table[key]
    except KeyError:
        raise ConfigError(f"unknown {what} '{key}'" + _suggest(key, table)) from None


# ---------------------------------------------------------------------------------------------
# Parsers


def _read_yaml(path: Path) -> Any:
    try:
        with open(path, encoding="utf-8") as fh:
            return yaml.safe_load(fh)
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f" at line {mark.line + 1}, column {mark.column + 1}" if mark else ""
        raise ConfigError(f"{path}: not valid YAML{where}: {getattr(exc, 'problem', exc)}") from None
    except UnicodeDecodeError as exc:
        raise ConfigError(f"{path}: not UTF-8 text (byte {exc.start} is 0x{exc.object[exc.start]:02x}); save the file "
                          "as UTF-8") from None
    except OSError as exc:
        raise ConfigError(f"{path}: cannot be read: {exc.strerror}") from None


def _physics(r: _Reader, passive: bool = False) -> Physics:
    r.reject_unknown(("mass_kg", "friction", "restitution"))
    mass = 0.0 if passive else r.float("mass_kg", positive=True)
    return Physics(mass, r.float("friction", lo=0.0, hi=2.0), r.float("restitution", lo=0.0, hi=1.0))


def _resolve_mesh(path: Path, r: _Reader, key: str) -> str | None:
    value = r.str(key, None)
    if value is None:
        return None
    mesh = (path.parent / value).resolve() if not os.path.isabs(value) else Path(value)
    if mesh.suffix.lower() not in MESH_SUFFIXES:
        raise _fail(path, key, f"unsupported mesh format '{mesh.suffix}'; use one of {', '.join(MESH_SUFFIXES)}")
    if not mesh.exists():
        raise _fail(path, key, f"mesh file {mesh} does not exist")
    return str(mesh)


def parse_object(path: Path, data: Any, tags: tuple[str, ...]) -> ObjectConfig:
    r = _Reader(path, data)
    r.reject_unknown(("id", "name", "partition", "tags", "size_m", "physics", "shape", "mesh", "description"))
    return ObjectConfig(
        id=r.str("id"),
        name=r.str("name"),
        partition=r.str("partition", choices=OBJECT_PARTITIONS),
        tags=r.str_list("tags", choices=tags),
        size_m=r.vector("size_m", 3, positive=True),  # type: ignore[arg-type]
        physics=_physics(r.sub("physics")),
        shape=r.str("shape", choices=SHAPES),
        mesh_path=_resolve_mesh(path, r, "mesh"),
        description=r.str("description", ""),
        source=str(path),
    )


def parse_scene(path: Path, data: Any) -> SceneConfig:
    r = _Reader(path, data)
    r.reject_unknown(("id", "name", "partition", "supports", "floor_z_m", "style", "mesh", "description"))
    supports = []
    for s in r.items("supports"):
        s.reject_unknown(("name", "centre_m", "size_m", "long_axis_deg"))
        supports.append(SupportConfig(
            name=s.str("name"), centre_m=s.vector("centre_m", 3),  # type: ignore[arg-type]
            size_m=s.vector("size_m", 2, positive=True),  # type: ignore[arg-type]
            long_axis_deg=s.float("long_axis_deg", 0.0)))
        if supports[-1].size_m[0] < supports[-1].size_m[1]:
            raise _fail(path, f"supports[{len(supports) - 1}].size_m", "give (long, short): long must be >= short")
    names = [s.name for s in supports]
    if len(set(names)) != len(names):
        raise _fail(path, "supports", f"support names must be unique, got {names}")
    style = r.raw("style", {})
    if not isinstance(style, Mapping):
        raise _fail(path, "style", f"expected a mapping, got {style!r}")
    return SceneConfig(
        id=r.str("id"), name=r.str("name"), partition=r.str("partition", choices=SCENE_PARTITIONS),
        supports=tuple(supports), floor_z_m=r.float("floor_z_m", 0.0), style=dict(style),
        mesh_path=_resolve_mesh(path, r, "mesh"), description=r.str("description", ""), source=str(path))


_STEP_FIELDS: dict[str, dict[str, str]] = {
    # field -> kind; "interval+" positive range, "tag", "ref" (earlier step), "dir", "int"
    "drop": {"tag": "tag", "height_m": "interval+", "over": "ref?"},
    "on_support": {"tag": "tag"},
    "ramp": {"length_m": "interval+", "height_m": "interval+", "width_m": "interval+", "descends": "dir",
             "gap_m": "interval?", "facing": "ref?"},
    "on_ramp": {"tag": "tag", "ramp": "ref"},
    "line": {"tag": "tag", "count": "int", "after": "ref", "offset_m": "interval+", "gap_m": "interval+"},
    "cluster": {"tag": "tag", "count": "int", "gap_m": "interval+"},
}


def parse_task(path: Path, data: Any, tags: tuple[str, ...]) -> TaskConfig:
    r = _Reader(path, data)
    r.reject_unknown(("id", "name", "prompt", "camera_azimuth_deg", "support_override", "steps"))
    ranges = r.raw("camera_azimuth_deg")
    if not isinstance(ranges, list) or not ranges:
        raise _fail(path, "camera_azimuth_deg", "expected a list of [lo, hi] ranges in degrees")
    az = tuple(_Reader(path, {"r": v}, f"camera_azimuth_deg[{i}].").interval("r") for i, v in enumerate(ranges))
    override = _physics(r.sub("support_override"), passive=True) if r.has("support_override") else None
    steps: list[TaskStep] = []
    for s in r.items("steps"):
        op = s.str("op", choices=STEP_OPS)
        fields = _STEP_FIELDS[op]
        s.reject_unknown(("op", "name", "role", *fields))
        name = s.str("name")
        if name in [p.name for p in steps]:
            raise _fail(path, f"{s.prefix}name", f"step name '{name}' is used twice")
        params: dict[str, Any] = {}
        for key, kind in fields.items():
            optional = kind.endswith("?")
            kind = kind.rstrip("?")
            if optional and not s.has(key):
                continue
            if kind == "tag":
                params[key] = s.str(key, choices=tags)
            elif kind == "interval+":
                params[key] = s.interval(key, positive=True)
            elif kind == "interval":
                params[key] = s.interval(key)
            elif kind == "int":
                params[key] = s.int(key, lo=1)
            elif kind == "dir":
                params[key] = s.str(key, choices=DIRECTIONS)
            elif kind == "ref":
                params[key] = s.str(key, choices=[p.name for p in steps])
        steps.append(TaskStep(op=op, name=name, params=params))
    prompt = r.str("prompt")
    object_steps = [s.name for s in steps if s.op in ("drop", "on_support", "on_ramp")]
    try:
        prompt.format(**{n: "x" for n in object_steps})
    except (KeyError, IndexError, ValueError) as exc:
        raise _fail(path, "prompt", f"placeholder {exc} is not a single-object step; "
                                    f"use one of {{{'}, {'.join(object_steps)}}}") from None
    return TaskConfig(id=r.str("id"), name=r.str("name"), prompt=prompt, azimuth_ranges_deg=az,
                      steps=tuple(steps), support_override=override, source=str(path))


def parse_material(path: Path, data: Any) -> MaterialConfig:
    r = _Reader(path, data)
    r.reject_unknown(("id", "name", "params"))
    params = r.raw("params", {})
    if not isinstance(params, Mapping):
        raise _fail(path, "params", f"expected a mapping, got {params!r}")
    return MaterialConfig(id=r.str("id"), name=r.str("name"), params=dict(params), source=str(path))


def parse_presets(path: Path, data: Any) -> dict[str, RenderPreset]:
    r = _Reader(path, data)
    r.reject_unknown(("presets",))
    out = {}
    raw = r.raw("presets")
    if not isinstance(raw, Mapping):
        raise _fail(path, "presets", "expected a mapping of preset name to settings")
    for name in raw:
        p = r.sub("presets").sub(name)
        p.reject_unknown(("resolution", "frames", "samples", "adaptive_threshold", "denoise", "max_bounces",
                          "diffuse_bounces", "glossy_bounces", "transmission_bounces", "persistent_data",
                          "light_transport", "denoise_quality"))
        w, h = p.vector("resolution", 2, positive=True)
        if w != int(w) or h != int(h) or int(w) % 2 or int(h) % 2:
            raise _fail(path, f"presets.{name}.resolution", "width and height must be even integers (H.264)")
        out[name] = RenderPreset(
            name=name, resolution=(int(w), int(h)), frames=p.int("frames", lo=2), samples=p.int("samples", lo=1),
            adaptive_threshold=p.float("adaptive_threshold", None) if p.has("adaptive_threshold") else None,
            denoise=p.bool("denoise"), max_bounces=p.int("max_bounces", lo=0),
            diffuse_bounces=p.int("diffuse_bounces", lo=0), glossy_bounces=p.int("glossy_bounces", lo=0),
            transmission_bounces=p.int("transmission_bounces", lo=0), persistent_data=p.bool("persistent_data"),
            light_transport=p.str("light_transport", "full", choices=LIGHT_TRANSPORTS),
            denoise_quality=p.str("denoise_quality", "high", choices=DENOISE_QUALITIES))
    return out


def _parse_flat(path: Path, data: Any, cls: type) -> Any:
    r = _Reader(path, data)
    names = list(cls.__dataclass_fields__)
    r.reject_unknown(names)
    kwargs = {}
    for n in names:
        default = cls.__dataclass_fields__[n].default
        kwargs[n] = r.int(n, default) if isinstance(default, int) else r.float(n, default)
    return cls(**kwargs)


def parse_splits(path: Path, data: Any, task_ids: Iterable[str]) -> SplitConfig:
    r = _Reader(path, data)
    r.reject_unknown(("train", "eval"))
    t, e = r.sub("train"), r.sub("eval")
    t.reject_unknown(("seed", "per_scene", "task_counts"))
    e.reject_unknown(("seed", "per_task", "partitions"))
    counts_raw = t.raw("task_counts")
    if not isinstance(counts_raw, Mapping):
        raise _fail(path, "train.task_counts", "expected a mapping of task id to count")
    task_ids = tuple(task_ids)
    counts = {}
    for k in counts_raw:
        if k not in task_ids:
            raise _fail(path, f"train.task_counts.{k}", f"unknown task '{k}'" + _suggest(k, task_ids))
        counts[k] = t.sub("task_counts").int(k, lo=0)
    parts = []
    for p in e.items("partitions"):
        p.reject_unknown(("id", "scenes", "objects"))
        parts.append(EvalPartition(p.str("id"), p.str("scenes", choices=SCENE_PARTITIONS),
                                   p.str("objects", choices=OBJECT_PARTITIONS)))
    return SplitConfig(train_seed=t.int("seed", lo=0), train_per_scene=t.int("per_scene", lo=1),
                       train_task_counts=counts, eval_seed=e.int("seed", lo=0), eval_per_task=e.int("per_task", lo=1),
                       eval_partitions=tuple(parts))


# ---------------------------------------------------------------------------------------------
# Loading


def config_dirs(extra_dirs: Iterable[str | Path] = ()) -> list[Path]:
    """The packaged config directory followed by ``extra_dirs`` (later directories override earlier ones)."""
    dirs = [PACKAGE_CONFIG_DIR] + [Path(p) for p in extra_dirs]
    for d in dirs[1:]:
        if not d.is_dir():
            raise ConfigError(f"{d}: configuration directory does not exist (from RIGIDBENCH_CONFIG_PATH or --config)")
    return dirs


def _collect(dirs: list[Path], sub: str, parse) -> dict[str, Any]:
    table: dict[str, Any] = {}
    for d in dirs:
        for path in sorted((d / sub).glob("*.yaml")) if (d / sub).is_dir() else []:
            item = parse(path, _read_yaml(path))
            if path.stem != item.id:
                raise _fail(path, "id", f"id '{item.id}' must match the file name '{path.stem}'")
            table[item.id] = item
    return table


def _last_file(dirs: list[Path], name: str) -> Path:
    found = [d / name for d in dirs if (d / name).is_file()]
    if not found:
        raise ConfigError(f"{dirs[0] / name}: required configuration file is missing")
    return found[-1]


def config_file(name: str, extra_dirs: Iterable[str | Path] = ()) -> Path:
    """The file ``name`` (e.g. "models.yaml") from the last configuration directory that has it: a copy in
    an extra directory replaces the packaged one as a whole. ConfigError when none has it."""
    return _last_file(config_dirs(extra_dirs), name)


def read_config_yaml(path: str | Path) -> Any:
    """Parse one YAML configuration file; ConfigError names the file (and line) when it cannot be read."""
    return _read_yaml(Path(path))


def load_registry(extra_dirs: Iterable[str | Path] = ()) -> Registry:
    """Read and validate every configuration file; raises ConfigError naming file and field."""
    dirs = config_dirs(extra_dirs)
    tags_path = _last_file(dirs, "tags.yaml")
    tags_reader = _Reader(tags_path, _read_yaml(tags_path))
    tags_reader.reject_unknown(("tags",))
    tags = tags_reader.str_list("tags")
    objects = _collect(dirs, "objects", lambda p, d: parse_object(p, d, tags))
    scenes = _collect(dirs, "scenes", parse_scene)
    tasks = _collect(dirs, "tasks", lambda p, d: parse_task(p, d, tags))
    materials = _collect(dirs, "materials", parse_material)
    presets_path = _last_file(dirs, "render.yaml")
    presets = parse_presets(presets_path, _read_yaml(presets_path))
    sim_path = _last_file(dirs, "simulation.yaml")
    sim = _parse_flat(sim_path, _read_yaml(sim_path), SimSettings)
    cam_path = _last_file(dirs, "camera.yaml")
    camera = _parse_flat(cam_path, _read_yaml(cam_path), CameraSettings)
    splits_path = _last_file(dirs, "splits.yaml")
    splits = parse_splits(splits_path, _read_yaml(splits_path), tasks)
    for what, table in (("objects", objects), ("scenes", scenes), ("tasks", tasks), ("materials", materials)):
        if not table:
            raise ConfigError(f"{dirs[0] / what}: no {what} are configured")
    for task in tasks.values():
        for step in task.steps:
            tag = step.params.get("tag")
            if tag is not None and not any(tag in o.tags for o in objects.values()):
                raise _fail(task.source, f"steps.{step.name}.tag", f"no object carries the tag '{tag}'")
    return Registry(objects=objects, scenes=scenes, tasks=tasks, materials=materials, presets=presets,
                    sim=sim, camera=camera, splits=splits, tags=tags)


@functools.lru_cache(maxsize=4)
def _cached(key: tuple[str, ...]) -> Registry:
    return load_registry(key)


def registry(extra_dirs: Iterable[str | Path] = ()) -> Registry:
    """The registry for the packaged configs plus any extra directories (cached per process).

    The environment is not consulted here: the command line turns ``$RIGIDBENCH_CONFIG_PATH`` and
    ``--config`` into the directories of its ``RunContext``, which passes them down."""
    return _cached(tuple(str(Path(d).resolve()) for d in extra_dirs))


# -- configuration values as parts of a stage's key ----------------------------------------------------------

#: Configuration fields that do not change what is rendered or simulated (where the entry was read from).
UNKEYED_CONFIG_FIELDS = ("source", "description")


def plain(value: Any, skip: Sequence[str] = UNKEYED_CONFIG_FIELDS) -> Any:
    """A configuration value as JSON types (dataclasses as dicts without the ``skip`` fields), for a key."""
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return {f.name: plain(getattr(value, f.name), skip) for f in dataclasses.fields(value) if f.name not in skip}
    if isinstance(value, Mapping):
        return {str(k): plain(v, skip) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [plain(v, skip) for v in value]
    return value
