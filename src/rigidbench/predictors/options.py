"""Each predictor's own typed options, and how the command line's ``--model-args`` (and the older global
flags) become them.

A predictor declares its options as a frozen dataclass of ``ModelOptions`` whose fields are made with
``option(default, help, ...)``: the field's type (``bool``, ``int``, ``float``, ``str``, ``Path``, a
``Literal`` of choices, any of them ``| None``) says how a value given as text is read, the help text
and limits live with the field. The class is named by the predictor class (``options_type``) and by its
registry entry (``PredictorInfo.options``), so ``rigidbench predict --list`` shows every model's options
and the command line checks them without importing the model (no torch, no weights). The built-in
models' options are defined here, in a module that imports nothing heavy.

The command line (``model_options``) turns ``--model-args k=v,k=v`` and the older flags (``--offload``,
``--tiled-vae``, ``--checkpoint``, ``--model-path``, ``--sampler``, ``--no-guardrail``, ``--concurrency``,
``--repay-expired``: aliases of the options of the same name) into the mapping that goes into
``PredictContext.options``: only the options given, each checked and typed, JSON-serialisable (a path
as a string), so a worker process or a Ray node rebuilds the same options from it. A ``--model-args``
key the model does not have is an error; a flag that does not apply to the model is ignored, as it
always was. A predictor reads its options typed with ``Predictor.options(ctx)`` (``from_mapping``: a
value None counts as not given and keys of other models' options are ignored, so one mapping can serve
several models, as in ``audit``).

Values read from text: bool ``true/false, 1/0, yes/no, on/off`` (any case); int and float as Python
reads them; a path as written (``~`` is expanded where it is used); a choice exactly.
"""

from __future__ import annotations

import dataclasses
import math
import os
import typing
from dataclasses import dataclass
from pathlib import Path
from types import MappingProxyType, NoneType, UnionType
from typing import Any, Literal, Mapping

from ..errors import UserError
from ..registry import load_target
from .base import PredictorInfo

TRUE = ("true", "1", "yes", "on")
FALSE = ("false", "0", "no", "off")

#: the global flags of ``predict`` and ``audit`` that are aliases of the option of the same name
LEGACY_FLAGS = {"offload": "--offload", "tiled_vae": "--tiled-vae", "checkpoint": "--checkpoint",
                "model_path": "--model-path", "sampler": "--sampler", "no_guardrail": "--no-guardrail",
                "concurrency": "--concurrency", "repay_expired": "--repay-expired"}


def option(default: Any = None, help: str = "", *, minimum: float | None = None, positive: bool = False,
           internal: bool = False, shown: str | None = None) -> Any:
    """A field of a ``ModelOptions`` dataclass: its default, its help text, an inclusive ``minimum`` or
    ``positive`` (> 0) for numbers; ``internal``: settable from Python only (e.g. an injected pipeline),
    never listed or read from the command line; ``shown``: how ``predict --list`` shows the default."""
    return dataclasses.field(default=default, metadata={"help": help, "minimum": minimum, "positive": positive,
                                                        "internal": internal, "shown": shown})


@dataclass(frozen=True)
class OptionSpec:
    """One option as the command line sees it: how a value is read and checked, and its help."""

    name: str
    kind: type | None  # bool, int, float, str, Path; None for a choice (``choices``) or anything (internal)
    optional: bool  # None is a value (``X | None``): "not given, the model's own value"
    choices: tuple[str, ...] = ()
    default: Any = None
    help: str = ""
    minimum: float | None = None
    positive: bool = False
    internal: bool = False
    shown: str | None = None

    @property
    def flag(self) -> str | None:
        """The older global flag that is an alias of this option, if any."""
        return LEGACY_FLAGS.get(self.name)

    def type_label(self) -> str:
        if self.choices:
            return "|".join(self.choices)
        if self.kind is None:
            return "object"
        label = {bool: "bool", int: "int", float: "float", str: "text", Path: "path"}[self.kind]
        if self.minimum is not None:
            label += f" >= {self.minimum:g}"
        elif self.positive:
            label += " > 0"
        return label

    def default_label(self) -> str:
        if self.shown is not None:
            return self.shown
        if self.default is None:
            return "model's" if self.optional else "-"
        if isinstance(self.default, bool):
            return "true" if self.default else "false"
        return str(self.default)

    def convert(self, value: Any, model: str, source: str | None = None) -> Any:
        """``value`` (text from the command line, or already typed) as this option's type, checked; a
        UserError naming the model and the option (``source``: how it was given, default "option NAME")."""
        where = f"{model}: {source or f'option {self.name}'}"
        if value is None:
            if self.optional or self.internal:
                return None
            raise UserError(f"{where} needs a value")
        if self.internal or (self.kind is None and not self.choices):
            return value
        if self.choices:
            if not isinstance(value, str) or value not in self.choices:
                raise UserError(f"{where} must be one of {', '.join(self.choices)}, got {value!r}")
            return value
        if self.kind is bool:
            return _to_bool(value, where)
        if self.kind in (int, float):
            number = _to_number(value, self.kind, where)
            if self.minimum is not None and number < self.minimum:
                raise UserError(f"{where} must be at least {self.minimum:g}, got {number}")
            if self.positive and number <= 0:
                raise UserError(f"{where} must be positive, got {number}")
            return number
        if self.kind is Path:
            if isinstance(value, str) and value.strip():
                return Path(value.strip())
            if isinstance(value, os.PathLike) and str(value):
                return Path(value)
            raise UserError(f"{where} must be a path, got {value!r}")
        if not isinstance(value, str):
            raise UserError(f"{where} must be text, got {value!r}")
        return value


def _to_bool(value: Any, where: str) -> bool:
    if isinstance(value, bool):
        return value
    if isinstance(value, int) and value in (0, 1):
        return bool(value)
    if isinstance(value, str):
        text = value.strip().lower()
        if text in TRUE:
            return True
        if text in FALSE:
            return False
    raise UserError(f"{where} must be true or false ({'/'.join(TRUE)} or {'/'.join(FALSE)}), got {value!r}")


def _to_number(value: Any, kind: type, where: str) -> int | float:
    what = "a number (an integer)" if kind is int else "a number"
    if isinstance(value, bool):
        raise UserError(f"{where} must be {what}, got {value!r}")
    if isinstance(value, str):
        try:
            number = kind(value.strip())
        except ValueError:
            raise UserError(f"{where} must be {what}, got {value!r}") from None
    elif isinstance(value, (int, float)) and math.isfinite(value) and (kind is float or value == int(value)):
        number = kind(value)
    else:
        raise UserError(f"{where} must be {what}, got {value!r}")
    if not math.isfinite(number):
        raise UserError(f"{where} must be a finite number, got {value!r}")
    return number


_SPECS: dict[type, tuple[OptionSpec, ...]] = {}


def option_specs(cls: type) -> tuple[OptionSpec, ...]:
    """The options of the dataclass ``cls``, in field order (cached)."""
    if cls in _SPECS:
        return _SPECS[cls]
    if not dataclasses.is_dataclass(cls):
        raise TypeError(f"{cls!r}: model options are a dataclass (see rigidbench.predictors.options)")
    hints = typing.get_type_hints(cls)
    specs = []
    for f in dataclasses.fields(cls):
        kind, optional, choices = _read_type(hints[f.name], f"{cls.__name__}.{f.name}")
        meta = f.metadata
        specs.append(OptionSpec(f.name, kind, optional, choices,
                                f.default if f.default is not dataclasses.MISSING else None,
                                meta.get("help", ""), meta.get("minimum"), bool(meta.get("positive")),
                                bool(meta.get("internal")) or kind is None and not choices, meta.get("shown")))
    _SPECS[cls] = tuple(specs)
    return _SPECS[cls]


def _read_type(tp: Any, where: str) -> tuple[type | None, bool, tuple[str, ...]]:
    """(kind, optional, choices) of a field's annotation."""
    optional = False
    if typing.get_origin(tp) in (typing.Union, UnionType):
        args = [a for a in typing.get_args(tp) if a is not NoneType]
        optional = len(args) < len(typing.get_args(tp))
        if len(args) != 1:
            raise TypeError(f"{where}: an option has one type (or that type | None), got {tp!r}")
        tp = args[0]
    if typing.get_origin(tp) is Literal:
        choices = typing.get_args(tp)
        if not all(isinstance(c, str) for c in choices):
            raise TypeError(f"{where}: the choices of an option are strings, got {choices!r}")
        return None, optional, tuple(choices)
    if tp is Any:
        return None, True, ()
    if tp in (bool, int, float, str, Path):
        return tp, optional, ()
    raise TypeError(f"{where}: options are bool, int, float, str, Path or a Literal of strings, got {tp!r}")


@dataclass(frozen=True)
class ModelOptions:
    """Base of a predictor's options (a frozen dataclass whose fields are made with ``option``)."""

    @classmethod
    def specs(cls) -> tuple[OptionSpec, ...]:
        return option_specs(cls)

    @classmethod
    def from_mapping(cls, mapping: Mapping[str, Any], *, model: str = "model", strict: bool = False):
        """The options in ``mapping`` (typed values or text), checked. None counts as not given. Keys that
        are not options of ``cls`` are ignored, or, with ``strict``, a UserError (``unknown_option``)."""
        values = {}
        for spec in cls.specs():
            value = mapping.get(spec.name)
            if value is not None:
                values[spec.name] = spec.convert(value, model)
        if strict:
            names = {s.name for s in cls.specs()}
            for key in mapping:
                if key not in names:
                    raise UserError(unknown_option(model, key, cls))
        return cls(**values)

    def to_mapping(self) -> dict[str, Any]:
        """The options that differ from their defaults, as JSON values (a path as a string): a mapping for
        ``PredictContext.options`` that ``from_mapping`` reads back as these options (internal options are
        left out)."""
        out = {}
        for spec in self.specs():
            value = getattr(self, spec.name)
            if not spec.internal and value != spec.default:
                out[spec.name] = _json(value)
        return out


def unknown_option(model: str, key: str, cls: type | None) -> str:
    """The message for an option ``key`` that model ``model`` (options ``cls``) does not have."""
    names = [s.name for s in option_specs(cls) if not s.internal] if cls is not None else []
    if not names:
        return f"model '{model}' has no option '{key}'; it has no options"
    return f"model '{model}' has no option '{key}'; its options: {', '.join(names)}"


# -- the built-in predictors' options ---------------------------------------------------------------------

DTYPES = ("bfloat16", "float16", "float32")  # LocalOptions.dtype's choices (local.py re-exports it)


@dataclass(frozen=True)
class LocalOptions(ModelOptions):
    """What both locally run video models (``wan-2.2``, ``cosmos-2.5``) take. A number left out is the
    paper's (see each model); every value is recorded."""

    offload: bool = option(False, "model CPU offload: each component on the GPU only while it runs (smaller GPUs)")
    tiled_vae: bool = option(False, "tiled VAE encoding and decoding (less GPU memory)")
    model_path: Path | None = option(None, "weights from this diffusers pipeline directory instead of the hub",
                                             shown="the hub")
    revision: str | None = option(None, "the hub revision (default: the model's)")
    height: int | None = option(None, "frame height in pixels (a multiple of the model's size multiple)", minimum=1)
    width: int | None = option(None, "frame width in pixels (a multiple of the model's size multiple)", minimum=1)
    num_frames: int | None = option(None, "frames to generate (4k + 1)", minimum=1)
    steps: int | None = option(None, "inference steps", minimum=1)
    guidance_scale: float | None = option(None, "classifier-free guidance scale")
    fps: float | None = option(None, "frame rate the video is written at", positive=True)
    dtype: Literal["bfloat16", "float16", "float32"] | None = option(None, "weights' dtype when the pipeline is "
                                                                           "loaded (the paper: bfloat16)")
    pipeline: Any = option(None, "an already built pipeline of the model's class, used instead of loading one "
                                 "(tests and benchmarks)", internal=True)


@dataclass(frozen=True)
class WanOptions(LocalOptions):
    """``wan-2.2``: the local options, the sampler, a fine-tuned checkpoint and the sampling numerics
    (``recipe`` names a set of the last three; an option given beside it overrides the recipe's value)."""

    checkpoint: Path | None = option(None, "a fine-tuned model: a LoRA adapter (PEFT directory or safetensors) or a "
                                           "full fine-tuned transformer", shown="none")
    sampler: Literal["flow-euler", "unipc"] = option("flow-euler", "flow-euler (the paper's runs: DiffSynth's "
                                                                   "flow-matching Euler schedule, shift 5) or unipc "
                                                                   "(the Diffusers repository's scheduler)")
    recipe: Literal["ours", "release"] = option("ours", "ours (diffusers' numerics) or release (DiffSynth's, as the "
                                                        "paper's runs sampled: timestep_dtype and update_dtype "
                                                        "bfloat16, vae_codec diffsynth-tiled)")
    timestep_dtype: Literal["float32", "bfloat16"] | None = option(
        None, "the timestep the transformer sees: float32 or rounded to bfloat16 (DiffSynth)", shown="recipe's")
    update_dtype: Literal["float32", "bfloat16"] | None = option(
        None, "the Euler update: float32 (diffusers) or bfloat16 (DiffSynth: dt x v rounded, then added to "
              "bfloat16 latents); bfloat16 needs sampler flow-euler", shown="recipe's")
    vae_codec: Literal["diffusers", "diffsynth-tiled"] | None = option(
        None, "diffusers (untiled, or tiled_vae) or diffsynth-tiled (DiffSynth's tiled encode of the first frame "
              "and tiled decode, 30x52 latent tiles, stride 15x26, and its uint8 conversion)", shown="recipe's")


@dataclass(frozen=True)
class CosmosOptions(LocalOptions):
    """``cosmos-2.5``: the local options and the guardrail."""

    no_guardrail: bool = option(False, "replace the Cosmos guardrail with a pass-through (you take on its "
                                       "licence terms, printed when it runs)")


@dataclass(frozen=True)
class HostedOptions(ModelOptions):
    """The hosted models on Replicate."""

    concurrency: int = option(8, "predictions in flight at once", minimum=1)
    repay_expired: bool = option(False, "pay for a new prediction when a paid one's output has expired at the API")


@dataclass(frozen=True)
class TwinOptions(ModelOptions):
    """``twin``: a physical twin of the reference (``predictors.twins``)."""

    scale: float | None = option(None, "multiplies every deviation of the envelope (1: as configured, 0: the "
                                       "reference itself; may exceed 1)", minimum=0, shown="the severity")
    geometry_only: bool = option(False, "no path tracing: trajectories, masks, tracks and depth from the simulator "
                                        "and the data passes; the video shows the actors' silhouettes on the first "
                                        "frame and the appearance measurements are skipped")
    envelope: Path | None = option(None, "the envelope configuration file", shown="envelope.yaml of the configs")
    spec_dir: Path | None = option(None, "scene specs rebuilt for imported examples, <spec_dir>/<id>/scene_spec.json "
                                         "(the resimulation folder of `rigidbench envelope`); used where a bundle has "
                                         "none; such twins are geometry-only", shown="none")


# -- the command line -------------------------------------------------------------------------------------


def parse_model_args(text: str | None) -> dict[str, str]:
    """``"k=v,k=v"`` as {k: v} (values as text). Whitespace around keys, values and items is dropped; a
    value may contain '=' (a path); an empty item, an item without '=' or with no key, and a key given
    twice are UserErrors naming the item."""
    out: dict[str, str] = {}
    if text is None or not text.strip():
        return out
    for number, item in enumerate(text.split(","), 1):
        key, sep, value = item.partition("=")
        key = key.strip()
        if not item.strip():
            raise UserError(f"--model-args {text!r}: item {number} is empty (expected k=v,k=v)")
        if not sep or not key:
            raise UserError(f"--model-args: item {item.strip()!r} is not key=value (expected k=v,k=v)")
        if key in out:
            raise UserError(f"--model-args: option {key!r} is given twice")
        out[key] = value.strip()
    return out


def _external(info: PredictorInfo) -> bool:
    """A predictor of a plug-in (registered by it, an entry point or given by its path), not one of ours."""
    return not info.target.startswith("rigidbench.")


def options_type(info: PredictorInfo) -> type[ModelOptions] | None:
    """The options dataclass of predictor ``info``: its registry entry's, else, for a plug-in's predictor,
    its class's ``options_type`` (which imports the plug-in's module); None: it takes no options."""
    if info.options is not None or not _external(info):
        return info.options
    cls = getattr(load_target(info.target, f"predictor '{info.name}'"), "options_type", None)
    if cls is not None and not (isinstance(cls, type) and issubclass(cls, ModelOptions)):
        raise UserError(f"predictor '{info.name}': options_type must be a dataclass of "
                        f"rigidbench.predictors.options.ModelOptions, got {cls!r}")
    return cls


def resolve_options(info: PredictorInfo, raw: Mapping[str, Any]) -> ModelOptions | None:
    """The options instance of predictor ``info`` from ``raw`` (text or typed values; None: not given):
    every key must be one of its options (a UserError listing them otherwise), every value of its type.
    None for a predictor without options (``raw`` must then be empty)."""
    cls = options_type(info)
    if cls is None:
        for key in raw:
            raise UserError(unknown_option(info.name, key, None))
        return None
    return cls.from_mapping(raw, model=info.name, strict=True)


def legacy_flags(args) -> dict[str, Any]:
    """The older flags' values from parsed command-line ``args`` (a missing attribute counts as not given),
    for ``model_options``."""
    return {name: getattr(args, name, None) for name in LEGACY_FLAGS}


def _json(value: Any) -> Any:
    return str(value) if isinstance(value, os.PathLike) else value


def _public_names(cls: type | None) -> list[str]:
    return [s.name for s in option_specs(cls) if not s.internal] if cls is not None else []


def _options(info: PredictorInfo, given: Mapping[str, str], legacy: Mapping[str, Any] | None) -> dict[str, Any]:
    """``model_options`` with ``--model-args`` already parsed."""
    flags = {k: v for k, v in (legacy or {}).items() if v is not None and v is not False}  # left out: not given
    cls = options_type(info)
    if cls is None:
        for key in given:
            raise UserError(unknown_option(info.name, key, None) + (
                " (a plug-in declares its options with the class attribute options_type, a dataclass of "
                "rigidbench.predictors.options.ModelOptions)" if _external(info) else ""))
        return {k: _json(v) for k, v in flags.items()} if _external(info) else {}
    specs = {s.name: s for s in option_specs(cls) if not s.internal}
    for key in given:
        if key not in specs:
            raise UserError(unknown_option(info.name, key, cls))
    values = {k: specs[k].convert(v, info.name, f"--model-args {k}") for k, v in given.items()}
    for key, value in flags.items():
        if key not in specs:
            continue  # a flag of another model: ignored, as it always was
        flag = LEGACY_FLAGS.get(key, key)
        typed = specs[key].convert(value, info.name, flag)
        if key in values and values[key] != typed:
            raise UserError(f"{info.name}: {flag} and --model-args {key}={given[key]} disagree; give the option once")
        values[key] = typed
    resolve_options(info, values)  # the dataclass's own checks of the whole, if it has any
    return {k: _json(v) for k, v in values.items()}


def model_options(info: PredictorInfo, model_args: str | None = None,
                  legacy: Mapping[str, Any] | None = None) -> Mapping[str, Any]:
    """What goes into ``PredictContext.options`` for predictor ``info``: ``--model-args`` (``model_args``,
    "k=v,k=v") and the older flags (``legacy``: {option name: value}, e.g. ``legacy_flags(args)``; None and
    False mean not given), checked and typed, only those given, as JSON values (a path as a string).

    A ``--model-args`` key the model does not have is a UserError listing its options; a flag the model
    does not have is ignored (as it always was); a flag and ``--model-args`` giving one option different
    values is a UserError. A plug-in that declares no options gets the flags given as they are (paths as
    strings), and no ``--model-args``."""
    return MappingProxyType(_options(info, parse_model_args(model_args), legacy))


def audit_options(infos, model_args: str | None = None,
                  legacy: Mapping[str, Any] | None = None) -> Mapping[str, Any]:
    """``model_options`` for several models run with one context (``audit``): each model's options checked
    as there, merged into one mapping (each model reads only its own). A ``--model-args`` key must be an
    option of at least one of the models."""
    infos = list(infos)
    given = parse_model_args(model_args)
    types_ = [options_type(info) for info in infos]
    known = sorted({name for cls in types_ for name in _public_names(cls)})
    for key in given:
        if key not in known:
            raise UserError(f"none of {', '.join(i.name for i in infos)} has an option '{key}'"
                            + (f"; their options: {', '.join(known)}" if known else "; they have no options"))
    merged: dict[str, Any] = {}
    for info, cls in zip(infos, types_):
        names = set(_public_names(cls))
        merged.update(_options(info, {k: v for k, v in given.items() if k in names}, legacy))
    return MappingProxyType(merged)


def format_options(info: PredictorInfo, indent: str = "    ") -> str:
    """Predictor ``info``'s options for ``predict --list``: a head line, then one line each: name, type,
    default ("model's": the model's own value, see its description) and help (with the older flag that is
    its alias); "" for a predictor without options."""
    cls = options_type(info)
    specs = [s for s in option_specs(cls) if not s.internal] if cls is not None else []
    if not specs:
        return ""
    rows = [("option", "type", "default", "help")] + [
        (s.name, s.type_label(), s.default_label(), s.help + (f" (also {s.flag})" if s.flag else "")) for s in specs]
    widths = [max(len(row[i]) for row in rows) for i in range(3)]
    return "\n".join(f"{indent}{a:{widths[0]}s}  {b:{widths[1]}s}  {c:{widths[2]}s}  {d}".rstrip()
                     for a, b, c, d in rows)


__all__ = ["CosmosOptions", "HostedOptions", "LEGACY_FLAGS", "LocalOptions", "ModelOptions", "OptionSpec",
           "TwinOptions", "WanOptions", "audit_options", "format_options", "legacy_flags", "model_options", "option",
           "option_specs", "options_type", "parse_model_args", "resolve_options",
           "unknown_option"]
