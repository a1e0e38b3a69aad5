"""``rigidbench probe extract``: actor-aligned residual streams of every DiT block at five schedule
fractions (paper appendix E, "Actor-Aligned Residual Streams"); the layout is in ``store.py``.

For each clip of the preprocessing cache (its normalised reference latent and prompt embedding):
noise the latent at each tau (``model.noised_batch``: slot 0 kept clean, at timestep 0 by default), run
the DiT with the clip's text, record every block's output with forward hooks, pool it per actor and slot
(``pooling``; masks from the clip's bundle in ``--data``) and attach the simulator targets
(``targets``).

On the stage driver (``rigidbench.driver``): an item is a clip of the cache, its worker (which loads
the backbone once) writes the clip's activation file and row table. A clip's key is a digest of the
settings that determine them (the backbone and its weights, the random backbone's seed, the model,
the schedule fractions, the noise seed, the forward dtype, the conditioning of ``recipe.Conditioning``
when it is not ours: prompt, padding, slot-0 timestep, precisions, noise), of the clip's cache entry
(``LatentCache.entry_key``) and of its bundle's masks, trajectories and contacts; so a rerun skips the
clips extracted this way and extracts again exactly those whose key changed, saying why. The probe
split of every clip is assigned once (``store.assign_splits`` over the clips of the first run; clips
added later join the training split) and kept in the manifest, which is rebuilt from the ledger after
every run. A store of an older RigidBench (version 2, chunks) is still read by ``fit`` and
``intervene``; extracting into it is refused (use a new ``--out``).
"""

from __future__ import annotations

import json
import logging
from dataclasses import dataclass
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

import numpy as np
import torch

from ..driver import ItemResult, RunOptions, Stage, StageReport, StageWorker, read_ledger, run_stage, stage_dir
from ..errors import ConfigError, UserError
from ..folders import CONTACTS_FILE, MASKS_FILE, METADATA_FILE, TRAJECTORIES_FILE
from ..groundtruth.bundle import Sample, bundle_dirs, resolve_split_dir
from ..hashing import digest
from ..jsonio import read_json, write_json
from ..perception.device import resolve_device
from ..predictors.wan import detect_checkpoint, fingerprint
from ..probe import model as wan
from ..probe.pooling import pooling_matrix, slot_token_masks
from ..probe.recipe import Conditioning, conditioning_with, recipe, recipe_label
from ..probe.store import MANIFEST, STORE_VERSION, acts_file, assign_splits, cell_name, rows_file
from ..probe.targets import TARGETS, sample_targets
from ..train.cache import LatentCache, bundle_fingerprint, index_lock

log = logging.getLogger(__name__)

STAGE = "probe-extract"
#: the bundle files a clip's rows depend on
BUNDLE_FILES = (METADATA_FILE, MASKS_FILE, TRAJECTORIES_FILE, CONTACTS_FILE)
POOLING = ("per slot: masks merged over the slot's frames, max-pooled to the token grid; mean over an actor's "
           "covered tokens")


@dataclass(frozen=True)
class ExtractFacts:
    """What ``run_extract`` adds to its ``StageReport`` (``report.facts``): the actor-slot rows of the clips made
    this run (``rows``), those of them with no covered actor (``empty``: no rows), and the clips of the cache
    without a bundle in --data (``missing``: clip -> why; not candidates, so outside the report's counts; the
    store's manifest lists them as failed)."""

    rows: int
    empty: tuple[str, ...]
    missing: dict[str, str]


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


def backbone_identity(backbone: str, model: str, model_path: str | None, backbone_seed: int) -> dict:
    """What the backbone's weights are: base or random (with its seed) of the model's weights, or a checkpoint
    of ``rigidbench train`` by its files' content (``predictors.wan.fingerprint``), wherever it lies."""
    ident: dict[str, Any] = {"backbone": backbone if backbone in ("base", "random") else "checkpoint",
                             "model": model, "model_path": model_path}
    if backbone == "random":
        ident["seed"] = int(backbone_seed)
        ident["random_init"] = wan.RANDOM_INIT
    elif backbone != "base":
        found = detect_checkpoint(backbone)
        ident["checkpoint"] = {"kind": found["kind"], "files": fingerprint(found)}
    return ident


def _now() -> str:
    return datetime.now(timezone.utc).isoformat(timespec="seconds")


class ExtractStage(Stage):
    """The clips of a cache (with their bundles) -> the activation store ``out``."""

    name = STAGE
    worker = "rigidbench.stages.probe_extract:ExtractWorker"
    unit = "clip"

    def __init__(self, backbone: str, cache_dir, data, out, *, model: str | None = None,
                 model_path: str | None = None, taus=wan.DEFAULT_TAUS, device: str | None = None, seed: int = 0,
                 dtype=None, backbone_seed: int = wan.RANDOM_SEED, limit: int | None = None,
                 recipe_name: str | None = None, overrides: dict | None = None):
        self.cache = cache = LatentCache(cache_dir)
        model = model or str(cache.manifest["model"])
        if model != cache.manifest["model"]:
            raise UserError(f"{cache_dir}: the cache was encoded for {cache.manifest['model']}, not --model {model}")
        self.split_dir = resolve_split_dir(data)
        self.bundles = {d.name: d for d in bundle_dirs(self.split_dir)}
        self.out = Path(out)
        if (self.out / MANIFEST).is_file():
            try:
                version = json.loads((self.out / MANIFEST).read_text()).get("version")
            except ValueError:
                version = STORE_VERSION  # unreadable: rebuilt from the ledger
            if version != STORE_VERSION:
                raise UserError(f"{self.out}: an activation store of an older RigidBench (version {version}); "
                                "`probe fit` and `probe intervene` still read it, but extraction now keeps one file "
                                "per clip: extract into a new --out")
        self.device = str(torch.device(resolve_device(device)))
        chosen = recipe(recipe_name)
        if dtype is not None:
            overrides = {"dtype": str(dtype).replace("torch.", ""), **(overrides or {})}
        self.conditioning = cond = conditioning_with(chosen.conditioning, **(overrides or {}))
        try:
            cache.check_text(cond.prompt, cond.padding)
        except ConfigError as e:
            raise UserError(str(e).split("; ")[0] + "; preprocess again into a new directory, or extract with "
                            "--prompt task+suffix --text-padding zeros") from None
        self.dtype = cond.dtype
        self.taus = [float(t) for t in taus]
        self.seed, self.limit, self.backbone = int(seed), limit, str(backbone)
        self.backbone_seed = int(backbone_seed)
        random = {"backbone_seed": self.backbone_seed, "random_init": wan.RANDOM_INIT} if backbone == "random" \
            else {"backbone_seed": None}
        self.settings = {"version": STORE_VERSION, "backbone": self.backbone, **random, "model": model,
                         "model_path": model_path, "cache": str(Path(cache.dir).resolve()),
                         "data": str(self.split_dir.resolve()),
                         "schedule": wan.schedule_points(self.taus, wan.make_objective(cond)),
                         "recipe": recipe_label(chosen.name, cond), "conditioning": cond.as_dict(),
                         "tau_mapping": wan.TAU_MAPPING, "num_train_timesteps": wan.NUM_TRAIN_TIMESTEPS,
                         "shift": wan.SHIFT, "seed": self.seed, "latent_shape": list(cache.latent_shape),
                         "frames": int(cache.manifest["frames"]),
                         "targets": {k: list(v) for k, v in TARGETS.items()}, "dtype": "float16", "pooling": POOLING}
        self.model, self.model_path = model, model_path
        keyed = {k: v for k, v in self.settings.items()
                 if k not in ("backbone", "cache", "data", "recipe", "conditioning")}
        extra = [] if cond.key_part() is None else [cond.key_part()]  # ours: the keys of earlier stores
        self.settings_key = digest(keyed, backbone_identity(self.backbone, model, model_path, self.backbone_seed),
                                   self.dtype, *extra)
        #: clips of the cache without a bundle in --data (reported as failed, as before)
        self.missing = {i: f"no bundle {i} in {self.split_dir}" for i in cache.ids if i not in self.bundles}

    @property
    def root(self) -> Path:
        return self.out

    @property
    def where(self) -> str:
        return f"{self.cache.dir} (clips with a bundle in {self.split_dir})"

    def items(self) -> dict[str, Any]:
        return {i: {"dir": str(self.bundles[i].resolve())} for i in self.cache.ids if i in self.bundles}

    def key(self, item_id: str, payload: Any) -> str:
        return digest(self.settings_key, self.cache.entry_key(item_id, self.conditioning.prompt),
                      bundle_fingerprint(payload["dir"], BUNDLE_FILES))

    def job(self) -> dict:
        return {"root": str(self.out.resolve()), "cache": str(Path(self.cache.dir).resolve()),
                "backbone": self.backbone, "model": self.model, "model_path": self.model_path,
                "backbone_seed": self.backbone_seed, "device": self.device, "dtype": self.dtype, "taus": self.taus,
                "seed": self.seed, "settings_key": self.settings_key, "conditioning": self.conditioning.as_dict()}

    def intact(self, item_id: str) -> bool:
        result = (read_ledger(self.out, STAGE, item_id) or {}).get("result") or {}
        return _files_present(self.out, item_id, result)

    def prepare(self, todo: list[str]) -> None:
        self._write_index(todo)  # the splits are fixed before any clip runs (a killed run keeps them)

    def finish(self, report: StageReport) -> None:
        if stage_dir(self.out, STAGE).is_dir():
            self._write_index([], warn=True)

    def _population(self) -> list[str]:
        ids = list(self.items())
        return ids[:self.limit] if self.limit is not None else ids

    def _write_index(self, todo: list[str], warn: bool = False) -> dict:
        """The manifest: this run's settings, the clips extracted with them (from the ledger), their probe
        splits (kept; new clips join the training split) and the failures."""
        sdir = stage_dir(self.out, STAGE)
        with index_lock(sdir):
            previous = read_json(self.out / MANIFEST, "rebuilt") or {}
            clips, empty, failed, facts, other = {}, [], {}, {}, []
            for path in sorted(sdir.glob("*.json")):
                entry = read_ledger(self.out, STAGE, path.stem)
                if entry is None:
                    continue
                result = entry.get("result") or {}
                if entry.get("status") == "failed":
                    failed[path.stem] = entry.get("error") or "failed"
                    continue
                if entry.get("status") != "succeeded":
                    continue
                if result.get("settings") != self.settings_key:
                    other.append(path.stem)
                    continue
                if not _files_present(self.out, path.stem, result):
                    continue
                facts = {k: result[k] for k in ("token_grid", "blocks", "width")}
                if result["rows"]:
                    clips[path.stem] = {"rows": int(result["rows"]), "key": entry["key"]}
                else:
                    empty.append(path.stem)
            splits = previous.get("splits") if previous.get("seed") == self.seed else None
            candidates = self._population() + list(todo) + list(clips)
            if not splits:
                splits = assign_splits(list(dict.fromkeys(candidates)), self.seed)
            for c in candidates:  # clips added after the first run join the training split
                splits.setdefault(c, "train")
            for k in ("token_grid", "blocks", "width"):
                if k not in facts and previous.get("settings_key") == self.settings_key and k in previous:
                    facts[k] = previous[k]
            manifest = {**self.settings, **facts, "settings_key": self.settings_key,
                        "splits": dict(sorted(splits.items())),
                        "clips": clips, "empty": empty, "failed": {**failed, **self.missing},
                        "created": previous.get("created") or _now(), "updated": _now()}
            write_json(self.out / MANIFEST, manifest, sort_keys=True)
        if other and warn:
            log.warning("%s: %d clip(s) were extracted with other settings and are not in the store's index (%s)",
                        self.out, len(other), ", ".join(other[:10]) + (" ..." if len(other) > 10 else ""))
        return manifest


def _files_present(root: Path, clip: str, result: dict) -> bool:
    if "rows" not in result or not (root / rows_file(clip)).is_file():
        return False
    return not result["rows"] or (root / acts_file(clip)).is_file()


class ExtractWorker(StageWorker):
    """One clip per call: the backbone (loaded once, here) on its noised latent at every tau, every block's
    output pooled per actor and slot -> ``acts/<clip>.safetensors`` and ``rows/<clip>.npz``."""

    def __init__(self, job: dict):
        super().__init__(job)
        self.cache = LatentCache(job["cache"])
        self.dev = torch.device(resolve_device(job["device"]))
        self.dtype = getattr(torch, job["dtype"])
        self.transformer = wan.load_backbone(job["backbone"], job["model"], job["model_path"], self.dev, self.dtype,
                                             seed=job["backbone_seed"])
        self.conditioning = Conditioning.from_record(job.get("conditioning"))
        self.obj = wan.make_objective(self.conditioning, self.transformer.config.patch_size)
        self.grid = tuple(wan.token_grid(self.cache.latent_shape, self.transformer.config.patch_size))
        self.frames = int(self.cache.manifest["frames"])
        config = self.transformer.config
        self.facts = {"token_grid": list(self.grid), "blocks": len(self.transformer.blocks),
                      "width": int(config.num_attention_heads * config.attention_head_dim)}

    def run(self, item_id: str, payload: Any, staging: Path, progress) -> ItemResult:
        from safetensors.numpy import save_file

        w, table = clip_rows(Sample(payload["dir"]), self.grid, self.frames)
        table["clip"] = np.array([item_id] * len(w), dtype=str)
        outputs = []
        if len(w):
            cond = self.conditioning
            latent, text = self.cache.batch([self.cache.ids.index(item_id)], dtype=torch.float32, prompt=cond.prompt,
                                            padding=cond.padding)
            wt = torch.as_tensor(w, device=self.dev)
            acts = {}
            taus = self.job["taus"]
            for n, tau in enumerate(taus):
                batch = wan.noised_batch(latent[0], item_id, tau, self.obj, self.job["seed"], cond)
                store: dict = {}
                with torch.no_grad(), wan.capture_blocks(self.transformer, store):
                    wan.forward(self.transformer, batch, text, self.dev, self.dtype)
                for b in range(len(self.transformer.blocks)):
                    acts[cell_name(b, tau)] = np.ascontiguousarray(
                        (wt @ store[b][0].float()).cpu().numpy().astype(np.float16))
                progress(n + 1, len(taus))
            (staging / "acts").mkdir()
            save_file(acts, str(staging / acts_file(item_id)))
            outputs.append(acts_file(item_id))
        (staging / "rows").mkdir()
        np.savez(staging / rows_file(item_id), **table)
        outputs.append(rows_file(item_id))  # last: the clip's completion mark
        return ItemResult(outputs=outputs, result={"rows": int(len(w)), "settings": self.job["settings_key"],
                                                   **self.facts})

    def close(self) -> None:
        self.transformer = None


def run_extract(backbone: str, cache_dir, data, out, *, model: str | None = None, model_path: str | None = None,
                taus=wan.DEFAULT_TAUS, device: str | None = None, run: RunOptions = RunOptions(),
                chunk_size: int | None = None, seed: int = 0, dtype=None,
                backbone_seed: int = wan.RANDOM_SEED, recipe: str | None = None,
                overrides: dict | None = None) -> StageReport:
    """Extract the first ``limit`` clips of the cache (or the ``ids``; this ``shard``'s part) into the store
    ``out``, conditioned as the ``recipe`` (``ours`` or ``release``) with ``overrides`` of its choices
    (``recipe.Conditioning`` fields; ``dtype``, when given, is the forward precision). ``chunk_size`` is
    accepted for older callers and unused (version 3 keeps one file pair per clip). Returns the driver's
    report, its ``facts`` an ``ExtractFacts``."""
    stage = ExtractStage(backbone, cache_dir, data, out, model=model, model_path=model_path, taus=taus,
                         device=device, seed=seed, dtype=dtype, backbone_seed=backbone_seed, limit=run.selection.limit,
                         recipe_name=recipe, overrides=overrides)
    report = run_stage(stage, run)
    rows = {i: int(report.results[i].get("rows", 0)) for i in report.ran}
    report.facts = ExtractFacts(sum(rows.values()), tuple(i for i in report.ran if not rows[i]), dict(stage.missing))
    return report
