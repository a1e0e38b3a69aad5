"""Training and preprocessing settings: the YAML files of ``configs/train/`` read into a frozen
``TrainConfig``, and the per-model preprocessing sizes. Light: yaml only.

A training configuration is named (``lora``, ``full``, ``tiny``: ``configs/train/<name>.yaml``,
a copy in a ``--config`` directory's ``train/`` replacing the packaged one) or given as a path.
``--set key=value`` overrides one dotted key (``optimizer.lr=1e-3``, ``mode=full``); values are
parsed as YAML. Every key of the file is known and checked: a typo is a ConfigError naming the
file, the key and the nearest known key.
"""

from __future__ import annotations

import dataclasses
import difflib
import hashlib
import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterable, Mapping

import yaml

from ..config import config_file, read_config_yaml
from ..errors import ConfigError

MODES = ("lora", "full")
DISTRIBUTED = ("auto", "ddp", "fsdp")
PRECISIONS = ("bf16", "fp32")
INITS = ("pretrained", "random")
EXPORT_DTYPES = ("float32", "bfloat16", "float16")
NAMED_CONFIGS = ("lora", "full", "tiny")
#: preprocessing choices (``rigidbench preprocess --resize`` / ``--vae-dtype``; docs/finetuning.md)
RESIZES = ("bicubic", "lanczos")
VAE_DTYPES = ("auto", "bfloat16", "float32")
#: the recipe options where our trainer and the authors' release differ (docs/finetuning.md); the first
#: value of each is the release's behaviour
TEXT_PROMPTS = ("task", "task+suffix")            # text.prompt: the task prompt alone | with the paper's suffix
TEXT_PADDINGS = ("encoder", "zeros")              # text.padding: UMT5's outputs at the padding positions | zeros
CLEAN_SLOT_TIMESTEPS = ("noisy", "zero")          # objective.clean_slot_timestep: t on every token | 0 on slot 0
DRAWS = ("shared", "per_rank")                    # objective.draws: one timestep and noise for all ranks | per rank
OBJECTIVE_DTYPES = ("bfloat16", "float32")        # objective.dtype: timestep, noised latent and target precision
MASTER_WEIGHTS = ("bfloat16", "float32")          # master_weights: dtype of the trained weights, gradients, AdamW state


@dataclass(frozen=True)
class ModelSpec:
    """What preprocessing and training need to know about one base model.

    width, height: pixels each frame is resized to before VAE encoding; frames: how many frames
    of each clip are encoded (4n+1 for Wan's VAE); text_len: the padded text length the pipeline
    uses (``max_sequence_length``); hub_id: the diffusers repository (None: built locally)."""

    name: str
    width: int
    height: int
    frames: int
    text_len: int
    hub_id: str | None
    description: str


MODEL_SPECS: dict[str, ModelSpec] = {
    # paper appendix D: 49 frames resized from 1280x704 to 640x352 -> 13 latent slots on a 22x40 grid
    "wan-2.2": ModelSpec("wan-2.2", 640, 352, 49, 512, "Wan-AI/Wan2.2-TI2V-5B-Diffusers",
                         "Wan 2.2 TI2V-5B (UMT5-XXL, Wan 2.2 VAE, 5B DiT)"),
    # tiny.py: random models of the same classes; 9 frames at 128x64 -> 3 latent slots on a 4x8 grid
    "tiny": ModelSpec("tiny", 128, 64, 9, 512, None, "randomly initialised tiny Wan models (tests, CPU)"),
}


def model_spec(name: str) -> ModelSpec:
    if name not in MODEL_SPECS:
        close = difflib.get_close_matches(name, MODEL_SPECS, n=1)
        hint = f" (did you mean '{close[0]}'?)" if close else ""
        raise ConfigError(f"unknown model '{name}'{hint}; known models: {', '.join(MODEL_SPECS)}")
    return MODEL_SPECS[name]


@dataclass(frozen=True)
class TrainConfig:
    """One training run's settings (paper, table "Fine-tuning configurations"). Field names are the
    YAML's dotted keys with dots replaced by underscores (``optimizer.lr`` -> ``optimizer_lr``)."""

    mode: str                       # lora | full
    model: str                      # a MODEL_SPECS name
    model_path: str | None          # a local diffusers pipeline directory (None: the hub id / tiny builder)
    init: str                       # pretrained | random (benchmarks: random weights of the real shape)
    lora_rank: int
    lora_alpha: float
    lora_dropout: float
    lora_target_modules: tuple[str, ...]
    frozen_modules: tuple[str, ...]  # full mode: module prefixes kept fixed (condition_embedder)
    distributed: str                # ddp | fsdp | auto (lora: ddp, full: fsdp); used under torchrun
    gpus: int                       # the paper's GPU count; effective batch = gpus x batch_size x grad_accum
    batch_size: int                 # per process
    grad_accum: int
    optimizer_lr: float
    optimizer_fused: bool
    optimizer_betas: tuple[float, float]
    optimizer_weight_decay: float
    optimizer_eps: float
    optimizer_grad_clip: float
    schedule_warmup_steps: int
    schedule_horizon_steps: int
    schedule_first_step: int        # the schedule's index of the first update: 0 (the release: lr 0) or 1
    max_steps: int
    checkpoint_every: int
    keep_training_states: int       # training_state/ kept in the newest N checkpoints (0: all); exports stay
    master_weights: str             # bfloat16 (the release; packaged lora and full) | float32 (float32 masters)
    gradient_checkpointing: bool
    precision: str                  # bf16 (GPU; the CPU runs fp32 and records it) | fp32
    seed: int
    objective_num_train_timesteps: int
    objective_shift: float
    objective_clean_slot_timestep: str  # noisy (the release) | zero: the timestep of the clean first slot's tokens
    objective_draws: str            # shared (the release: every rank draws the same t and noise) | per_rank
    objective_dtype: str            # bfloat16 (the release) | float32: timestep, noised latent and target
    text_prompt: str                # task (the release) | task+suffix: which cached prompt conditions training
    text_padding: str               # encoder (the release) | zeros: the text context after the prompt's tokens
    export_dtype: str               # dtype of the exported LoRA adapter / transformer checkpoint
    log_every: int
    source: str = ""                # where the settings came from (file and overrides)

    @property
    def wrapper(self) -> str:
        """"ddp" or "fsdp": ``distributed``, with "auto" meaning the paper's pairing (LoRA: DDP, full: FSDP)."""
        if self.distributed != "auto":
            return self.distributed
        return "ddp" if self.mode == "lora" else "fsdp"

    @property
    def effective_batch(self) -> int:
        """Examples per update on the paper's ``gpus`` processes."""
        return self.gpus * self.batch_size * self.grad_accum

    def to_dict(self) -> dict[str, Any]:
        """The settings as a nested mapping, in the YAML's shape (``source`` left out)."""
        out: dict[str, Any] = {}
        for key, _ in KEYS.items():
            value = getattr(self, key.replace(".", "_"))
            node = out
            *parents, leaf = key.split(".")
            for p in parents:
                node = node.setdefault(p, {})
            node[leaf] = list(value) if isinstance(value, tuple) else value
        return out

    def identity(self) -> dict[str, Any]:
        """The settings a resumed run must share with the run it continues (all but the run length,
        checkpoint interval and logging)."""
        d = self.to_dict()
        for key in RESUMABLE_CHANGES:
            d.pop(key, None)
        return d

    def digest(self) -> str:
        return hashlib.sha256(json.dumps(self.identity(), sort_keys=True).encode()).hexdigest()[:16]


def _int(v, lo=None):
    if isinstance(v, bool) or not isinstance(v, int):
        raise ValueError(f"expected an integer, got {v!r}")
    if lo is not None and v < lo:
        raise ValueError(f"must be at least {lo}, got {v}")
    return v


def _float(v, lo=None, positive=False):
    if isinstance(v, str):  # YAML 1.1 reads 1e-4 (no dot) as a string
        try:
            v = float(v)
        except ValueError:
            pass
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        raise ValueError(f"expected a number, got {v!r}")
    v = float(v)
    if positive and v <= 0:
        raise ValueError(f"must be positive, got {v}")
    if lo is not None and v < lo:
        raise ValueError(f"must be at least {lo}, got {v}")
    return v


def _bool(v):
    if not isinstance(v, bool):
        raise ValueError(f"expected true or false, got {v!r}")
    return v


def _choice(choices):
    def check(v):
        if v not in choices:
            close = difflib.get_close_matches(str(v), choices, n=1)
            hint = f" (did you mean '{close[0]}'?)" if close else ""
            raise ValueError(f"unknown value {v!r}{hint}; known values: {', '.join(choices)}")
        return v
    return check


def _first_step(v):
    if _int(v, 0) not in (0, 1):
        raise ValueError(f"expected 0 (the release: the first update runs at the schedule's value at 0) or 1, got {v}")
    return v


def _str_list(v):
    if isinstance(v, str):
        v = [v]
    if not isinstance(v, (list, tuple)) or not all(isinstance(s, str) and s for s in v):
        raise ValueError(f"expected a list of names, got {v!r}")
    return tuple(v)


def _betas(v):
    if not isinstance(v, (list, tuple)) or len(v) != 2:
        raise ValueError(f"expected two numbers [beta1, beta2], got {v!r}")
    b = tuple(_float(x) for x in v)
    if not all(0.0 <= x < 1.0 for x in b):
        raise ValueError(f"betas must lie in [0, 1), got {v!r}")
    return b


def _optional_str(v):
    if v is not None and not isinstance(v, str):
        raise ValueError(f"expected a path or null, got {v!r}")
    return v


#: every key of a training YAML -> its checker (dotted keys are nested mappings in the file)
KEYS: dict[str, Any] = {
    "mode": _choice(MODES),
    "model": _choice(tuple(MODEL_SPECS)),
    "model_path": _optional_str,
    "init": _choice(INITS),
    "lora.rank": lambda v: _int(v, 1),
    "lora.alpha": lambda v: _float(v, positive=True),
    "lora.dropout": lambda v: _float(v, lo=0.0),
    "lora.target_modules": _str_list,
    "frozen_modules": lambda v: () if v in (None, []) else _str_list(v),
    "distributed": _choice(DISTRIBUTED),
    "gpus": lambda v: _int(v, 1),
    "batch_size": lambda v: _int(v, 1),
    "grad_accum": lambda v: _int(v, 1),
    "optimizer.lr": lambda v: _float(v, positive=True),
    "optimizer.fused": _bool,
    "optimizer.betas": _betas,
    "optimizer.weight_decay": lambda v: _float(v, lo=0.0),
    "optimizer.eps": lambda v: _float(v, positive=True),
    "optimizer.grad_clip": lambda v: _float(v, positive=True),
    "schedule.warmup_steps": lambda v: _int(v, 0),
    "schedule.horizon_steps": lambda v: _int(v, 1),
    "schedule.first_step": _first_step,
    "max_steps": lambda v: _int(v, 1),
    "checkpoint_every": lambda v: _int(v, 1),
    "keep_training_states": lambda v: _int(v, 0),
    "master_weights": _choice(MASTER_WEIGHTS),
    "gradient_checkpointing": _bool,
    "precision": _choice(PRECISIONS),
    "seed": lambda v: _int(v, 0),
    "objective.num_train_timesteps": lambda v: _int(v, 2),
    "objective.shift": lambda v: _float(v, positive=True),
    "objective.clean_slot_timestep": _choice(CLEAN_SLOT_TIMESTEPS),
    "objective.draws": _choice(DRAWS),
    "objective.dtype": _choice(OBJECTIVE_DTYPES),
    "text.prompt": _choice(TEXT_PROMPTS),
    "text.padding": _choice(TEXT_PADDINGS),
    "export_dtype": _choice(EXPORT_DTYPES),
    "log_every": lambda v: _int(v, 1),
}
RESUMABLE_CHANGES = ("max_steps", "checkpoint_every", "keep_training_states", "log_every")


def _flatten(data: Mapping, prefix: str = "") -> dict[str, Any]:
    out = {}
    for k, v in data.items():
        key = f"{prefix}{k}"
        if isinstance(v, Mapping) and not any(name == key for name in KEYS):
            out.update(_flatten(v, key + "."))
        else:
            out[key] = v
    return out


def parse_override(text: str) -> tuple[str, Any]:
    """``key=value`` (value parsed as YAML) -> (key, value); ConfigError when malformed."""
    key, sep, value = text.partition("=")
    key = key.strip()
    if not sep or not key:
        raise ConfigError(f"--set {text!r}: expected KEY=VALUE, e.g. --set optimizer.lr=1e-3")
    try:
        return key, yaml.safe_load(value)
    except yaml.YAMLError:
        raise ConfigError(f"--set {text!r}: the value is not valid YAML") from None


def config_from_mapping(data: Any, source: str, overrides: Iterable[str] = ()) -> TrainConfig:
    """Validate a parsed YAML mapping (plus ``key=value`` overrides) into a TrainConfig."""
    if not isinstance(data, Mapping):
        raise ConfigError(f"{source}: expected a mapping of training settings, got {type(data).__name__}")
    flat = _flatten(data)
    overrides = list(overrides)
    for text in overrides:
        key, value = parse_override(text)
        flat[key] = value
    values = {}
    for key, value in flat.items():
        if key not in KEYS:
            close = difflib.get_close_matches(key, KEYS, n=1)
            hint = f" (did you mean '{close[0]}'?)" if close else ""
            raise ConfigError(f"{source}: unknown key '{key}'{hint}")
        try:
            values[key] = KEYS[key](value)
        except ValueError as exc:
            raise ConfigError(f"{source}: field '{key}': {exc}") from None
    missing = [k for k in KEYS if k not in values]
    if missing:
        raise ConfigError(f"{source}: missing keys {', '.join(missing)}")
    where = source + "".join(f" --set {o}" for o in overrides)
    cfg = TrainConfig(**{k.replace(".", "_"): v for k, v in values.items()}, source=where)
    if cfg.schedule_warmup_steps >= cfg.schedule_horizon_steps:
        raise ConfigError(f"{where}: schedule.warmup_steps ({cfg.schedule_warmup_steps}) must be below "
                          f"schedule.horizon_steps ({cfg.schedule_horizon_steps})")
    if cfg.mode == "lora" and cfg.lora_dropout >= 1.0:
        raise ConfigError(f"{where}: lora.dropout must be below 1, got {cfg.lora_dropout}")
    return cfg


def config_path(name_or_path: str | Path, config_dirs: Iterable[str | Path] = ()) -> Path:
    """The YAML file ``--config`` names: a path to a file, else ``train/<name>.yaml`` from the
    packaged configs or the last extra configuration directory that has it."""
    text = str(name_or_path)
    path = Path(text).expanduser()
    if path.suffix in (".yaml", ".yml") or path.is_file():
        if not path.is_file():
            raise ConfigError(f"{path}: training configuration file does not exist")
        return path
    try:
        return config_file(f"train/{text}.yaml", config_dirs)
    except ConfigError:
        close = difflib.get_close_matches(text, NAMED_CONFIGS, n=1)
        hint = f" (did you mean '{close[0]}'?)" if close else ""
        raise ConfigError(f"unknown training configuration '{text}'{hint}; give one of "
                          f"{', '.join(NAMED_CONFIGS)} or a path to a YAML file") from None


def load_train_config(name_or_path: str | Path, config_dirs: Iterable[str | Path] = (),
                      overrides: Iterable[str] = ()) -> TrainConfig:
    """Read, override and validate a training configuration (see the module docstring)."""
    path = config_path(name_or_path, config_dirs)
    return config_from_mapping(read_config_yaml(path), str(path), overrides)


def replace(cfg: TrainConfig, **changes) -> TrainConfig:
    """A copy of ``cfg`` with fields changed (field names, e.g. ``max_steps=4``), validated again."""
    merged = dataclasses.replace(cfg, **changes)
    return config_from_mapping(merged.to_dict(), cfg.source + " (changed in code)")
