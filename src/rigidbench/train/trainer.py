"""``rigidbench train``: LoRA (DDP) or full (FSDP2) fine-tuning of the Wan transformer on a cache.

One update (``step``) is ``grad_accum`` local batches of ``batch_size`` cached examples on each of the
``world_size`` processes. For each local batch the objective (``objective.py``) draws one timestep
index and the noise from a generator seeded by (seed, step, local batch, rank) with
``objective.draws: per_rank``, or by (seed, step, local batch, 0) on every rank with ``shared`` (the
release: its ranks were seeded alike, so all drew the same timestep and noise); the examples are
read in a seeded random order, a fresh permutation per pass over the cache, dealt out by global
position (rank r takes positions r*B .. r*B+B-1 of each group of world_size*B). The data position
is therefore the number of examples seen, and a resumed run draws exactly what an uninterrupted one
draws.

LoRA (``mode: lora``): peft adapters of rank ``lora.rank`` on ``lora.target_modules`` of every
block; the base weights are frozen. Full (``mode: full``): every transformer weight except
``frozen_modules`` trains. ``master_weights: bfloat16`` (the packaged ``lora`` and ``full``, which
reproduce the published runs) is the release's: the whole transformer (adapters too), its gradients
and AdamW's moments are stored and updated in bfloat16, and FSDP2 reduces gradients in bfloat16; at
the full run's lr 2e-5 an update smaller than half a weight's bfloat16 spacing leaves it unchanged.
``master_weights: float32``: float32 adapters / float32 full weights (the frozen LoRA base bfloat16 on
a GPU), which FSDP2 casts to bfloat16 for compute on a GPU. Both run the forward pass under bf16 autocast on a GPU and in float32 on the
CPU (``run.json`` records which), compute the loss in float32, clip the gradient norm, and step a
(fused where available) AdamW and the warm-up + cosine learning rate (``schedules.lr_factor``; update
k runs at schedule index k - 1 + ``schedule.first_step``). The text context is the cache's
``text.prompt`` with ``text.padding`` (``cache.LatentCache.batch``).
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import logging
import platform
import time
import warnings
from dataclasses import dataclass, field
from datetime import datetime, timezone
from pathlib import Path
from typing import Any, Callable

import torch

from ..errors import ConfigError
from . import checkpoint as ckpt
from .cache import LatentCache
from .config import TrainConfig, model_spec
from .distributed import DistInfo, init_distributed, mean_across, shutdown, wrap_ddp, wrap_fsdp
from .models import load_transformer
from .objective import FlowMatchingObjective, transformer_prediction
from .schedules import lr_factor

log = logging.getLogger(__name__)


@dataclass
class TrainSummary:
    run_dir: Path
    start_step: int
    end_step: int
    losses: list[float] = field(default_factory=list)
    checkpoints: list[Path] = field(default_factory=list)
    facts: dict[str, Any] = field(default_factory=dict)


def stream_seed(*parts: int) -> int:
    """A 63-bit seed for the generator of one (seed, step, local batch, rank)."""
    digest = hashlib.sha256("/".join(str(int(p)) for p in parts).encode()).digest()
    return int.from_bytes(digest[:8], "little") & ((1 << 63) - 1)


def draw_seed(cfg: TrainConfig, step: int, micro: int, rank: int) -> int:
    """The seed of the timestep and noise draw of (step, local batch) on ``rank``: rank 0's on every rank
    with ``objective.draws: shared`` (the release), each rank its own with ``per_rank``."""
    return stream_seed(cfg.seed, step, micro, rank if cfg.objective_draws == "per_rank" else 0)


class DataOrder:
    """Global example position -> cache index: a seeded permutation of the cache per pass."""

    def __init__(self, n: int, seed: int):
        self.n, self.seed = n, seed
        self._epoch, self._perm = -1, None

    def __call__(self, position: int) -> int:
        epoch = position // self.n
        if epoch != self._epoch:
            g = torch.Generator().manual_seed(stream_seed(self.seed, epoch, 0xDA7A))
            self._epoch, self._perm = epoch, torch.randperm(self.n, generator=g).tolist()
        return self._perm[position % self.n]


def build_model(cfg: TrainConfig, info: DistInfo, use_bf16: bool):
    """The transformer with its trainable parameters chosen (and LoRA adapters added), on the device."""
    lora = cfg.mode == "lora"
    bf16_master = cfg.master_weights == "bfloat16"
    base_dtype = torch.bfloat16 if ((lora and use_bf16) or bf16_master) else torch.float32
    torch.manual_seed(cfg.seed)
    model = load_transformer(cfg.model, cfg.model_path, cfg.init, dtype=base_dtype, device=info.device)
    if bf16_master:  # the release: DiffSynth loaded every DiT tensor in bfloat16
        model = model.to(torch.bfloat16)
    if lora:
        from peft import LoraConfig

        model.requires_grad_(False)
        torch.manual_seed(cfg.seed)  # the adapters' initial A matrices
        model.add_adapter(LoraConfig(r=cfg.lora_rank, lora_alpha=cfg.lora_alpha, lora_dropout=cfg.lora_dropout,
                                     target_modules=list(cfg.lora_target_modules), init_lora_weights=True))
        for p in model.parameters():
            if p.requires_grad:
                p.data = p.data.to(torch.bfloat16 if bf16_master else torch.float32)
    else:
        model.requires_grad_(True)
        for prefix in cfg.frozen_modules:
            try:
                model.get_submodule(prefix).requires_grad_(False)
            except AttributeError:
                raise ConfigError(f"{cfg.source}: frozen_modules: the transformer has no module '{prefix}'") from None
    if cfg.gradient_checkpointing:
        model.enable_gradient_checkpointing()
    model.train()
    return model


def mixed_precision(cfg: TrainConfig, device: torch.device) -> tuple[bool, str]:
    """(bf16 autocast on?, what the run records): bf16 on a GPU when asked; the CPU runs fp32."""
    if cfg.precision == "bf16" and device.type == "cuda":
        return True, "bf16 mixed precision"
    if cfg.precision == "bf16":
        return False, "fp32 (bf16 asked for, but this run is on the CPU)"
    return False, "fp32"


def make_optimizer(params, cfg: TrainConfig) -> tuple[torch.optim.Optimizer, str]:
    """AdamW with the config's settings; fused when asked and supported, else PyTorch's default
    implementation. Returns (optimizer, a description of the implementation used)."""
    kwargs = dict(lr=cfg.optimizer_lr, betas=cfg.optimizer_betas, weight_decay=cfg.optimizer_weight_decay,
                  eps=cfg.optimizer_eps)
    if cfg.optimizer_fused:
        try:
            return torch.optim.AdamW(params, fused=True, **kwargs), "AdamW (fused)"
        except (RuntimeError, TypeError, ValueError) as exc:
            reason = str(exc).splitlines()[0]
            return torch.optim.AdamW(params, **kwargs), f"AdamW (not fused: {reason})"
    return torch.optim.AdamW(params, **kwargs), "AdamW (fused: false in the config)"


def _grad_norm(params, max_norm: float) -> float:
    norm = torch.nn.utils.clip_grad_norm_(params, max_norm)
    if hasattr(norm, "full_tensor"):
        norm = norm.full_tensor()
    return float(norm)


def _versions() -> dict[str, str]:
    import importlib.metadata as md

    out = {"python": platform.python_version()}
    for name in ("torch", "diffusers", "peft", "transformers"):
        try:
            out[name] = md.version(name)
        except md.PackageNotFoundError:
            pass
    return out


def train(cfg: TrainConfig, cache_dir: str | Path, run_dir: str | Path, *, device: str | None = None,
          progress: bool = True, on_step: Callable[[dict[str, Any]], None] | None = None,
          save_final: bool = True) -> TrainSummary:
    """Train (or resume) the run in ``run_dir`` on the cache ``cache_dir``; every process of a torchrun
    launch calls this. ``on_step(record)`` is called after each update with its metrics record;
    ``save_final=False`` skips the checkpoint at ``max_steps`` (benchmarks)."""
    info = init_distributed(device)
    try:
        with warnings.catch_warnings():
            # FSDP2 warns that the transformer's output is a view; the loss only slices it (no in-place op)
            warnings.filterwarnings("ignore", message="FSDP2-wrapped module .* returned a view tensor")
            return _train(cfg, Path(cache_dir), Path(run_dir), info, progress, on_step, save_final)
    finally:
        shutdown(info)


def _check_cache(cache: LatentCache, cfg: TrainConfig, model) -> None:
    made_with = cache.manifest.get("model")
    if made_with != cfg.model:
        raise ConfigError(f"{cache.dir} was preprocessed for model '{made_with}', the configuration trains "
                          f"'{cfg.model}'; preprocess with --model {cfg.model} or choose a matching configuration")
    channels, text_dim = model.config.in_channels, model.config.text_dim
    if cache.latent_shape[0] != channels or cache.text_dim != text_dim:
        raise ConfigError(f"{cache.dir}: latents with {cache.latent_shape[0]} channels and text of width "
                          f"{cache.text_dim}, but the transformer takes {channels} and {text_dim}")


def _recipe_facts(cfg: TrainConfig, per_step: int) -> dict:
    """What run.json records of the configuration's recipe."""
    return {"mode": cfg.mode, "model": cfg.model, "init": cfg.init, "examples_per_update": per_step,
            "paper_examples_per_update": cfg.effective_batch, "master_weights": cfg.master_weights,
            "recipe": {"text": {"prompt": cfg.text_prompt, "padding": cfg.text_padding},
                       "objective": {"clean_slot_timestep": cfg.objective_clean_slot_timestep,
                                     "draws": cfg.objective_draws, "dtype": cfg.objective_dtype},
                       "schedule_first_step": cfg.schedule_first_step}}


def _accumulate(model, cache: LatentCache, objective: FlowMatchingObjective, order: DataOrder, cfg: TrainConfig,
                info: DistInfo, step: int, first: int, use_bf16: bool, input_dtype) -> tuple[list[float], list]:
    """The gradients of one update: ``cfg.grad_accum`` micro-batches of this rank's examples, starting at
    example ``first`` of the data order (gradients synchronised on the last one only). Returns each
    micro-batch's loss and timestep."""
    losses, timesteps = [], []
    for micro in range(cfg.grad_accum):
        last = micro == cfg.grad_accum - 1
        start = first + micro * info.world_size * cfg.batch_size + info.rank * cfg.batch_size
        indices = [order(start + j) for j in range(cfg.batch_size)]
        latents, text = cache.batch(indices, device=info.device, prompt=cfg.text_prompt, padding=cfg.text_padding)
        g = torch.Generator().manual_seed(draw_seed(cfg, step, micro, info.rank))
        index, noise = objective.draw(g, latents.shape)
        batch = objective.prepare(latents, noise.to(info.device), index)
        if hasattr(model, "set_requires_gradient_sync"):  # FSDP2
            model.set_requires_gradient_sync(last)
        sync = model.no_sync() if (hasattr(model, "no_sync") and not last) else contextlib.nullcontext()
        with sync:
            with torch.autocast(info.device.type, dtype=torch.bfloat16, enabled=use_bf16):
                pred = transformer_prediction(model, batch, text if input_dtype is None else text.to(input_dtype),
                                              input_dtype=input_dtype)
            loss = objective.loss(pred, batch)
            (loss / cfg.grad_accum).backward()
        losses.append(float(loss.detach()))
        timesteps.append(batch.timestep)
    return losses, timesteps


def _train(cfg: TrainConfig, cache_dir: Path, run_dir: Path, info: DistInfo, progress: bool,
           on_step, save_final: bool) -> TrainSummary:
    from tqdm import tqdm

    model_spec(cfg.model)
    cache = LatentCache(cache_dir)
    ckpt.prepare_run_dir(run_dir, cfg, info)
    use_bf16, precision = mixed_precision(cfg, info.device)

    model = build_model(cfg, info, use_bf16)
    _check_cache(cache, cfg, model)
    cache.check_text(cfg.text_prompt, cfg.text_padding)
    patch_size = model.config.patch_size
    n_trainable = sum(p.numel() for p in model.parameters() if p.requires_grad)
    wrapper = "none (one process)"
    if info.distributed:
        if cfg.wrapper == "fsdp":
            model = wrap_fsdp(model, info, bf16=use_bf16,
                              reduce_dtype=torch.bfloat16 if cfg.master_weights == "bfloat16" else torch.float32)
            wrapper = "FSDP2 fully_shard per block, then root"
        else:
            model = wrap_ddp(model, info)
            wrapper = "DDP"
    params = [p for p in model.parameters() if p.requires_grad]
    optimizer, optimizer_impl = make_optimizer(params, cfg)
    scheduler = torch.optim.lr_scheduler.LambdaLR(
        optimizer, lambda e: lr_factor(e + cfg.schedule_first_step, cfg.schedule_warmup_steps,
                                       cfg.schedule_horizon_steps))

    start_step, seen = 0, 0
    latest = ckpt.latest_checkpoint(run_dir)
    if latest is not None:
        record = ckpt.load_checkpoint(latest[1], model, optimizer, scheduler, cfg, info)
        start_step, seen = latest[0], int(record["examples_seen"])
        if info.is_main:
            ckpt.truncate_metrics(run_dir, start_step)
            log.info("resuming %s from %s", run_dir, latest[1])

    per_step = info.world_size * cfg.batch_size * cfg.grad_accum
    facts = {"device": str(info.device), "world_size": info.world_size, "precision": precision,
             "optimizer": optimizer_impl, "wrapper": wrapper, **_recipe_facts(cfg, per_step),
             "trainable_parameters": n_trainable, "cache": str(cache_dir.resolve()), "cache_examples": len(cache)}
    if info.is_main:
        if per_step != cfg.effective_batch:
            log.warning("%d examples per update on %d process(es); the paper's configuration has %d "
                        "(%d GPUs)", per_step, info.world_size, cfg.effective_batch, cfg.gpus)
        ckpt.append_run_record(run_dir, {"started": datetime.now(timezone.utc).isoformat(timespec="seconds"),
                                         "start_step": start_step, **facts, "versions": _versions()})

    objective = FlowMatchingObjective(cfg.objective_num_train_timesteps, cfg.objective_shift, patch_size,
                                      clean_slot_timestep=cfg.objective_clean_slot_timestep, dtype=cfg.objective_dtype)
    input_dtype = torch.bfloat16 if cfg.master_weights == "bfloat16" else None
    order = DataOrder(len(cache), cfg.seed)
    summary = TrainSummary(run_dir, start_step, start_step, facts=facts)
    bar = tqdm(total=cfg.max_steps, initial=start_step, unit="step", desc="train",
               disable=not (progress and info.is_main))
    metrics = (run_dir / ckpt.METRICS_FILE).open("a") if info.is_main else None
    try:
        for step in range(start_step, cfg.max_steps):
            if info.device.type == "cuda":
                torch.cuda.synchronize(info.device)
            t0 = time.perf_counter()
            first = seen + (step - start_step) * per_step
            losses, timesteps = _accumulate(model, cache, objective, order, cfg, info, step, first, use_bf16,
                                            input_dtype)
            grad_norm = _grad_norm(params, cfg.optimizer_grad_clip)
            lr = scheduler.get_last_lr()[0]
            optimizer.step()
            scheduler.step()
            optimizer.zero_grad(set_to_none=True)
            loss_mean = mean_across(info, sum(losses) / len(losses))
            if info.device.type == "cuda":
                torch.cuda.synchronize(info.device)
            dt = time.perf_counter() - t0
            done = step + 1
            record = {"step": done, "loss": loss_mean, "lr": lr, "grad_norm": grad_norm, "s_per_step": dt,
                      "examples_per_s": per_step / dt, "examples_seen": seen + (done - start_step) * per_step,
                      "timestep": sum(timesteps) / len(timesteps)}
            if info.device.type == "cuda":
                record["peak_memory_gib"] = torch.cuda.max_memory_allocated(info.device) / 2**30
            summary.losses.append(loss_mean)
            summary.end_step = done
            if metrics is not None and (done % cfg.log_every == 0 or done == cfg.max_steps):
                metrics.write(json.dumps(record) + "\n")
                metrics.flush()
            bar.update(1)
            bar.set_postfix(loss=f"{loss_mean:.4f}", lr=f"{lr:.2e}")
            if done % cfg.checkpoint_every == 0 or (save_final and done == cfg.max_steps):
                summary.checkpoints.append(ckpt.save_checkpoint(
                    run_dir, done, model, optimizer, scheduler, cfg, info,
                    {"examples_seen": record["examples_seen"], "precision": precision, "optimizer": optimizer_impl,
                     "wrapper": wrapper}))
            if on_step is not None:
                on_step(record)
    finally:
        bar.close()
        if metrics is not None:
            metrics.close()
    return summary
