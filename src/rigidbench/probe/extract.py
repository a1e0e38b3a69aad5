"""``rigidbench probe extract``: actor-aligned residual streams of every DiT block at five schedule
fractions (paper appendix E, "Actor-Aligned Residual Streams"); the layout is in ``store.py``.

For each clip of the preprocessing cache (its normalised reference latent and prompt embedding):
noise the latent at each tau (``model.noised_batch``: slot 0 kept clean at timestep 0), run the DiT
with the clip's text, record every block's output with forward hooks, pool it per actor and slot
(``pooling``; masks from the clip's bundle in ``--data``) and attach the simulator targets
(``targets``). Rows are buffered per chunk of clips and written as float16 shards per (block, tau).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from datetime import datetime, timezone
from pathlib import Path

import numpy as np
import torch

from ..atomic import atomic_file
from ..errors import EXAMPLE_ERRORS, UserError
from ..groundtruth.bundle import Sample, bundle_dirs, resolve_split_dir
from ..perception.device import resolve_device
from ..train.cache import LatentCache
from ..train.objective import FlowMatchingObjective
from . import model as wan
from .pooling import pooling_matrix, slot_token_masks
from .store import MANIFEST, STORE_VERSION, assign_splits, atomic_json, shard_path
from .targets import TARGETS, sample_targets

log = logging.getLogger(__name__)


@dataclass
class ExtractSummary:
    out: Path
    extracted: list[str] = field(default_factory=list)
    skipped: list[str] = field(default_factory=list)
    failed: dict[str, str] = field(default_factory=dict)
    rows: int = 0
    seconds: float = 0.0


def clip_rows(sample: Sample, grid: tuple[int, int, int], frames: int):
    """(pooling matrix W (R, L), row table) of one clip: its covered (slot, actor) pairs and their targets."""
    slots, gh, gw = grid
    tm = slot_token_masks(sample.masks[:frames], slots, (gh, gw))
    w, index = pooling_matrix(tm)
    targets, names, roles = sample_targets(sample, slots, frames)
    keep = np.array([np.isfinite(targets["position"][s, a]).all() for s, a in index], dtype=bool) \
        if len(index) else np.zeros(0, dtype=bool)
    w, index = w[keep], index[keep]
    table = {"slot": index[:, 0], "actor": index[:, 1],
             "actor_name": np.array([names[a] for a in index[:, 1]], dtype=str),
             "role": np.array([roles[a] for a in index[:, 1]], dtype=str)}
    for k in TARGETS:
        table[k] = targets[k][index[:, 0], index[:, 1]] if len(index) else np.zeros((0, TARGETS[k][0]), np.float32)
    return w, table


def _settings(backbone, model, model_path, cache: LatentCache, split_dir: Path, taus, seed, transformer,
              backbone_seed=None) -> dict:
    grid = wan.token_grid(cache.latent_shape, transformer.config.patch_size)
    random = {"backbone_seed": int(backbone_seed), "random_init": wan.RANDOM_INIT} if backbone == "random" else \
        {"backbone_seed": None}
    return {"version": STORE_VERSION, "backbone": str(backbone), **random, "model": model, "model_path": model_path,
            "cache": str(Path(cache.dir).resolve()), "data": str(split_dir.resolve()),
            "schedule": wan.schedule_points(taus), "tau_mapping": wan.TAU_MAPPING,
            "num_train_timesteps": wan.NUM_TRAIN_TIMESTEPS,
            "shift": wan.SHIFT, "seed": seed, "latent_shape": list(cache.latent_shape),
            "frames": int(cache.manifest["frames"]), "token_grid": list(grid),
            "blocks": len(transformer.blocks), "width": int(transformer.config.num_attention_heads
                                                            * transformer.config.attention_head_dim),
            "targets": {k: list(v) for k, v in TARGETS.items()}, "dtype": "float16",
            "pooling": "per slot: masks merged over the slot's frames, max-pooled to the token grid; "
                       "mean over an actor's covered tokens"}


def run_extract(backbone: str, cache_dir, data, out, *, model: str | None = None, model_path: str | None = None,
                taus=wan.DEFAULT_TAUS, device: str | None = None, limit: int | None = None, chunk_size: int = 64,
                seed: int = 0, progress: bool = True, dtype=torch.float32,
                backbone_seed: int = wan.RANDOM_SEED) -> ExtractSummary:
    import time

    from safetensors.numpy import save_file
    from tqdm import tqdm

    start = time.perf_counter()
    cache = LatentCache(cache_dir)
    model = model or str(cache.manifest["model"])
    if model != cache.manifest["model"]:
        raise UserError(f"{cache_dir}: the cache was encoded for {cache.manifest['model']}, not --model {model}")
    split_dir = resolve_split_dir(data)
    bundles = {d.name: d for d in bundle_dirs(split_dir)}
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    dev = torch.device(resolve_device(device))
    transformer = wan.load_backbone(backbone, model, model_path, dev, dtype, seed=backbone_seed)
    settings = _settings(backbone, model, model_path, cache, split_dir, taus, seed, transformer, backbone_seed)
    ids = [i for i in cache.ids if i in bundles][: limit if limit is not None else None]
    summary = ExtractSummary(out=out)
    for i in cache.ids:
        if i not in bundles:
            summary.failed[i] = f"no bundle {i} in {split_dir}"
    if (out / MANIFEST).is_file():
        import json

        manifest = json.loads((out / MANIFEST).read_text())
        differs = [k for k in ("version", "backbone", "backbone_seed", "model", "schedule", "seed", "latent_shape",
                               "blocks")
                   if manifest.get(k) != settings.get(k)]
        if differs:
            raise UserError(f"{out}: the store was extracted with other settings ({', '.join(differs)}); "
                            "use a new --out")
    else:
        manifest = {**settings, "splits": assign_splits(ids, seed), "chunks": [], "failed": {},
                    "created": datetime.now(timezone.utc).isoformat(timespec="seconds")}
        atomic_json(out / MANIFEST, manifest)
    done = {c for chunk in manifest["chunks"] for c in chunk["clips"]} | set(manifest.get("empty", []))
    todo = [i for i in ids if i not in done]
    summary.skipped = [i for i in ids if i in done]
    for i in todo:  # clips added to the cache after the first run join the training split
        manifest["splits"].setdefault(i, "train")
    obj = FlowMatchingObjective(wan.NUM_TRAIN_TIMESTEPS, wan.SHIFT, transformer.config.patch_size)
    grid = tuple(settings["token_grid"])
    frames = settings["frames"]
    bar = tqdm(total=len(todo), unit="clip", desc=f"extract {backbone}", disable=not progress)
    for c0 in range(0, len(todo), chunk_size):
        chunk_ids = todo[c0:c0 + chunk_size]
        acts: dict[tuple[int, float], list[np.ndarray]] = {}
        tables, written, empty = [], [], []
        for clip in chunk_ids:
            try:
                w, table = clip_rows(Sample(bundles[clip]), grid, frames)
            except EXAMPLE_ERRORS as exc:
                summary.failed[clip] = str(exc)
                bar.update(1)
                continue
            if len(w) == 0:
                empty.append(clip)
                bar.update(1)
                continue
            latent, text = cache.batch([cache.ids.index(clip)], dtype=torch.float32)
            wt = torch.as_tensor(w, device=dev)
            for tau in taus:
                batch = obj.prepare(latent, wan.clip_noise(clip, latent.shape, seed), wan.tau_index(tau))
                store: dict = {}
                with torch.no_grad(), wan.capture_blocks(transformer, store):
                    wan.forward(transformer, batch, text, dev, dtype)
                for b in range(len(transformer.blocks)):
                    acts.setdefault((b, tau), []).append((wt @ store[b][0].float()).cpu().numpy().astype(np.float16))
            table["clip"] = np.array([clip] * len(w), dtype=str)
            table["split"] = np.array([manifest["splits"][clip]] * len(w), dtype=str)
            tables.append(table)
            written.append(clip)
            summary.rows += len(w)
            bar.update(1)
        if written:
            name = f"chunk-{len(manifest['chunks']):05d}"
            for (b, tau), parts in acts.items():
                path = shard_path(out, b, tau, name)
                path.parent.mkdir(parents=True, exist_ok=True)
                with atomic_file(path) as tmp:
                    save_file({"h": np.ascontiguousarray(np.concatenate(parts))}, str(tmp))
            rows = {k: np.concatenate([t[k] for t in tables]) for k in tables[0]}
            (out / "rows").mkdir(exist_ok=True)
            with atomic_file(out / "rows" / f"{name}.npz", suffix=".npz") as tmp:
                np.savez(tmp, **rows)
            manifest["chunks"].append({"name": name, "clips": written, "rows": int(len(rows["clip"]))})
        manifest.setdefault("empty", []).extend(empty)
        manifest["failed"].update(summary.failed)
        manifest["updated"] = datetime.now(timezone.utc).isoformat(timespec="seconds")
        atomic_json(out / MANIFEST, manifest)
        summary.extracted += written
    bar.close()
    summary.seconds = time.perf_counter() - start
    return summary
