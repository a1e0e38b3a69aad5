"""Training-run directory, checkpoints and resume.

::

    RUN/config.yaml                  the resolved settings (a restart must agree, see TrainConfig.identity)
    RUN/run.json                     one record per launch: start step, processes, device, precision,
                                     optimizer implementation, library versions
    RUN/metrics.jsonl                one line per logged update: step, loss (mean over local batches and
                                     processes), lr, grad_norm (before clipping), s_per_step,
                                     examples_per_s, examples_seen, timestep (rank 0's mean), and
                                     peak_memory_gib on a GPU
    RUN/checkpoints/step-500/        what the predictor loads; every ``checkpoint_every`` updates and at
                                     the last one:
        adapter_config.json          LoRA: a PEFT adapter directory (PeftModel.save_pretrained layout:
        adapter_model.safetensors      keys base_model.model.<module>.lora_A.weight / lora_B.weight)
        config.json                  full: WanTransformer3DModel.save_pretrained
        diffusion_pytorch_model.safetensors
        checkpoint.json              step, mode, base model, examples seen, config digest (written last)
    RUN/training_state/step-500/     the resumable state of the same update, removed from all but the
                                     newest ``keep_training_states`` (1 in the packaged configurations:
                                     a full fine-tuning state is ~30 GB with bf16 masters, ~60 GB
                                     with float32; 0 keeps every one):
        dcp/                         torch.distributed.checkpoint: the trainable weights (``master_weights``) and
                                     the AdamW state, one file per process (reshardable on load)
        scheduler.pt                 the learning-rate scheduler's state
        rng-rank<r>.pt               torch CPU/CUDA and Python RNG states of process r
        state.json                   step, examples seen, processes (written last)

``rigidbench predict wan-2.2 --checkpoint RUN/checkpoints/step-500`` loads either kind (the LoRA
directory as a PEFT adapter, the full one as a transformer directory); the exported weights are in
``export_dtype``. ``load.py`` reads the authors' release's formats too (DiffSynth-named LoRA and full
state dicts, Lightning ``.ckpt``). The training state lives beside the export, not in it, so removing it never
changes the files the predictor fingerprints. Both directories are written as ``step-N.tmp`` and
renamed when complete (the state first), so a directory without ``.tmp`` is finished. Restarting
``train`` with the same ``--out`` loads the highest step that has both: weights, optimizer,
scheduler, RNG and data position (the data order and every noise draw are functions of the seed,
the step and the examples seen), and drops the metric lines after it, so the resumed run writes
the loss curve of an uninterrupted one.
"""

from __future__ import annotations

import json
import logging
import os
import random
import shutil
import warnings
from pathlib import Path
from typing import Any

import torch

from ..atomic import write_text
from ..errors import ConfigError, UserError
from .config import RESUMABLE_CHANGES, TrainConfig, model_spec
from .distributed import DistInfo, barrier, broadcast_object

log = logging.getLogger(__name__)

CHECKPOINTS = "checkpoints"
STATE_DIR = "training_state"
CHECKPOINT_FILE = "checkpoint.json"
STATE_FILE = "state.json"
METRICS_FILE = "metrics.jsonl"
PEFT_PREFIX = "base_model.model."


def checkpoint_dir(run_dir: Path, step: int) -> Path:
    return Path(run_dir) / CHECKPOINTS / f"step-{step}"


def state_dir(run_dir: Path, step: int) -> Path:
    return Path(run_dir) / STATE_DIR / f"step-{step}"


def _steps(root: Path, marker: str) -> dict[int, Path]:
    found = {}
    for d in root.glob("step-*") if root.is_dir() else []:
        step = d.name.removeprefix("step-")
        if d.is_dir() and step.isdigit() and (d / marker).is_file():
            found[int(step)] = d
    return found


def finished_checkpoints(run_dir: str | Path) -> list[tuple[int, Path]]:
    """(step, checkpoint directory) of every finished checkpoint of the run, by step."""
    return sorted(_steps(Path(run_dir) / CHECKPOINTS, CHECKPOINT_FILE).items())


def latest_checkpoint(run_dir: str | Path) -> tuple[int, Path] | None:
    """(step, checkpoint directory) of the newest checkpoint a run can resume from (its training state
    is there too), or None."""
    states = _steps(Path(run_dir) / STATE_DIR, STATE_FILE)
    found = [(step, d) for step, d in finished_checkpoints(run_dir) if step in states]
    return found[-1] if found else None


def unwrap(model):
    """The transformer inside a DDP wrapper (FSDP2 shards in place: the model is the transformer)."""
    return getattr(model, "module", model)


def trainable_names(model) -> set[str]:
    return {n for n, p in unwrap(model).named_parameters() if p.requires_grad}


# -- run directory ------------------------------------------------------------------------------


def prepare_run_dir(run_dir: Path, cfg: TrainConfig, info: DistInfo) -> None:
    """Create RUN/ and its config.yaml, or check that an existing run has the same settings
    (ConfigError on every process when not)."""
    import yaml

    error = None
    if info.is_main:
        run_dir.mkdir(parents=True, exist_ok=True)
        path = run_dir / "config.yaml"
        if path.is_file():
            try:
                old = yaml.safe_load(path.read_text()) or {}
            except yaml.YAMLError:
                old = {}
            old = {k: v for k, v in old.items() if k not in RESUMABLE_CHANGES}
            new = cfg.identity()
            if json.dumps(old, sort_keys=True) != json.dumps(new, sort_keys=True):
                changed = sorted(k for k in set(old) | set(new) if old.get(k) != new.get(k))
                error = (f"{run_dir} holds a run with other settings (changed: {', '.join(changed)}); "
                         "resume it with its own settings or train into a new --out")
        if error is None:
            write_text(path, f"# {cfg.source}\n" + yaml.safe_dump(cfg.to_dict(), sort_keys=False))
    error = broadcast_object(info, error)
    if error:
        raise ConfigError(error)


def append_run_record(run_dir: Path, record: dict[str, Any]) -> None:
    path = run_dir / "run.json"
    runs = json.loads(path.read_text()) if path.is_file() else []
    runs.append(record)
    write_text(path, json.dumps(runs, indent=1))


def truncate_metrics(run_dir: Path, step: int) -> None:
    """Keep the metric lines of updates up to ``step`` (a killed run may have logged past its last checkpoint)."""
    path = run_dir / METRICS_FILE
    if not path.is_file():
        return
    kept = []
    for line in path.read_text().splitlines():
        try:
            if json.loads(line)["step"] <= step:
                kept.append(line)
        except (ValueError, KeyError, TypeError):
            continue  # a line cut short by the kill
    write_text(path, "".join(f"{line}\n" for line in kept))


# -- export (what the predictor loads) ------------------------------------------------------------


def lora_state_dict(model) -> dict[str, torch.Tensor]:
    """The trainable LoRA tensors, unsharded, keyed as peft saves them (adapter name removed). Every
    process must call this: under FSDP each tensor is gathered from its shards."""
    state = {}
    for name, p in unwrap(model).named_parameters():
        if p.requires_grad:
            full = p.full_tensor() if hasattr(p, "full_tensor") else p
            key = name.replace(".lora_A.default.", ".lora_A.").replace(".lora_B.default.", ".lora_B.")
            state[key] = full.detach().cpu()
    return state


def export_lora(state: dict[str, torch.Tensor], model, out: Path, cfg: TrainConfig, dtype: torch.dtype) -> None:
    """Write the LoRA tensors ``state`` (``lora_state_dict``) as a PEFT adapter directory (rank 0)."""
    from safetensors.torch import save_file

    save_file({PEFT_PREFIX + k: v.to(dtype).contiguous() for k, v in state.items()},
              str(out / "adapter_model.safetensors"), metadata={"format": "pt"})
    config = unwrap(model).peft_config["default"]
    config.base_model_name_or_path = cfg.model_path or model_spec(cfg.model).hub_id or "rigidbench.train.tiny"
    config.save_pretrained(str(out))


def full_state_dict(model, info: DistInfo) -> dict[str, torch.Tensor]:
    """Every transformer tensor, unsharded, on the CPU of rank 0 (empty on the other ranks)."""
    from torch.distributed.checkpoint.state_dict import StateDictOptions, get_model_state_dict

    if info.distributed:
        return get_model_state_dict(model, options=StateDictOptions(full_state_dict=True, cpu_offload=True))
    return {k: v.detach().cpu() for k, v in unwrap(model).state_dict().items()}


def export_transformer(state: dict[str, torch.Tensor], config, out: Path, dtype: torch.dtype) -> None:
    """``WanTransformer3DModel.save_pretrained`` of the weights in ``state`` (no second copy on a device:
    the model is built on the meta device and takes the tensors as they are)."""
    from diffusers import WanTransformer3DModel

    with torch.device("meta"):
        shell = WanTransformer3DModel.from_config(config)
    shell.load_state_dict({k: v.to(dtype) for k, v in state.items()}, assign=True, strict=True)
    shell.save_pretrained(str(out), safe_serialization=True)


# -- resumable state ------------------------------------------------------------------------------


def _state_dicts(model, optimizer):
    from torch.distributed.checkpoint.state_dict import get_model_state_dict, get_optimizer_state_dict

    names = trainable_names(model)
    model_sd = {k: v for k, v in get_model_state_dict(model).items() if k in names}
    return {"model": model_sd, "optim": get_optimizer_state_dict(model, optimizer)}


def _rng_state() -> dict[str, Any]:
    state = {"torch": torch.get_rng_state(), "python": random.getstate()}
    if torch.cuda.is_available():
        state["cuda"] = torch.cuda.get_rng_state_all()
    return state


def save_checkpoint(run_dir: Path, step: int, model, optimizer, scheduler, cfg: TrainConfig, info: DistInfo,
                    facts: dict[str, Any]) -> Path:
    """Write checkpoint ``step`` (every process takes part) and return its directory."""
    import torch.distributed.checkpoint as dcp

    final, state_final = checkpoint_dir(run_dir, step), state_dir(run_dir, step)
    tmp, state_tmp = (d.with_name(d.name + ".tmp") for d in (final, state_final))
    if info.is_main:
        for d in (tmp, state_tmp):
            shutil.rmtree(d, ignore_errors=True)
            d.mkdir(parents=True)
    barrier(info)
    export_dtype = getattr(torch, cfg.export_dtype)
    if cfg.mode == "lora":
        state = lora_state_dict(model)
        if info.is_main:
            export_lora(state, model, tmp, cfg, export_dtype)
    else:
        state = full_state_dict(model, info)
        if info.is_main:
            export_transformer(state, unwrap(model).config, tmp, export_dtype)
        del state
    with warnings.catch_warnings():  # one process: DCP warns that it saves without a process group
        warnings.filterwarnings("ignore", message="torch.distributed is disabled")
        dcp.save(_state_dicts(model, optimizer), checkpoint_id=str(state_tmp / "dcp"), no_dist=not info.distributed)
    torch.save(_rng_state(), state_tmp / f"rng-rank{info.rank}.pt")
    if info.is_main:
        torch.save(scheduler.state_dict(), state_tmp / "scheduler.pt")
    barrier(info)
    if info.is_main:
        record = {"step": step, "mode": cfg.mode, "model": cfg.model, "config_digest": cfg.digest(),
                  "world_size": info.world_size, **facts}
        (state_tmp / STATE_FILE).write_text(json.dumps(record, indent=1))
        (tmp / CHECKPOINT_FILE).write_text(json.dumps(record, indent=1))
        for d, done in ((state_tmp, state_final), (tmp, final)):
            shutil.rmtree(done, ignore_errors=True)
            os.replace(d, done)
        if cfg.keep_training_states:
            states = sorted(_steps(Path(run_dir) / STATE_DIR, STATE_FILE).items())
            for _, older in states[:-cfg.keep_training_states]:
                shutil.rmtree(older, ignore_errors=True)
    barrier(info)
    return final


def load_checkpoint(path: Path, model, optimizer, scheduler, cfg: TrainConfig, info: DistInfo) -> dict[str, Any]:
    """Restore weights, optimizer, scheduler and this process's RNG from the training state of checkpoint
    ``path`` (RUN/checkpoints/step-N); returns its checkpoint.json record."""
    import torch.distributed.checkpoint as dcp
    from torch.distributed.checkpoint.state_dict import StateDictOptions, set_model_state_dict, \
        set_optimizer_state_dict

    record = json.loads((path / CHECKPOINT_FILE).read_text())
    if record.get("config_digest") != cfg.digest() or record.get("mode") != cfg.mode:
        raise ConfigError(f"{path}: written by a run with other settings; train into a new --out")
    saved = state_dir(path.parent.parent, int(record["step"]))
    state = _state_dicts(model, optimizer)
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message="torch.distributed is disabled")
        dcp.load(state, checkpoint_id=str(saved / "dcp"), no_dist=not info.distributed)
    set_model_state_dict(model, state["model"], options=StateDictOptions(strict=False))
    set_optimizer_state_dict(model, optimizer, state["optim"])
    scheduler.load_state_dict(torch.load(saved / "scheduler.pt", weights_only=True))
    rng_path = saved / f"rng-rank{info.rank}.pt"
    if rng_path.is_file():
        rng = torch.load(rng_path, weights_only=False)
        torch.set_rng_state(rng["torch"])
        random.setstate(rng["python"])
        if "cuda" in rng and torch.cuda.is_available():
            torch.cuda.set_rng_state_all(rng["cuda"])
    elif info.world_size == record.get("world_size"):
        raise UserError(f"{rng_path} is missing; the checkpoint is incomplete")
    return record
