"""``rigidbench probe intervene``: remove a fitted subspace at one block and measure Wan's loss change
(paper appendix E, "Position-Aligned Interventions").

Per block x tau cell: the position basis by INLP on all the store's rows (``inlp.inlp``: the
release's ridge and pooled R^2, 80/20 row split inside, torch on CUDA when available; ``procedure``
``stable``, ours, or ``release``, the release's float32 steps), a random
orthonormal basis of the same rank, and the variance-matched top-K principal components with their
alpha (variances from INLP's training rows, as in the release). The clips are the first ``clips`` of
the store's clips sorted by id (``clip_split="all"``, the release's: its first 100 ids of the
training corpus, whatever their probe split), or of its training-split clips (``"train"``). Bases
fitted by an older INLP (``BASES_VERSION``) are refitted, not reused. For each chosen clip, under the
same noised latent and text as extraction (the store's ``recipe.Conditioning``, unless the caller
names another recipe or choice; a conditioning other than the store's is logged): the baseline
forward (recording every block's output and the time embedding), then per block and variant

* full model: the block's output h is replaced by h - alpha (h B) B^T on every token and the forward
  continues through the remaining blocks and the head (``full_readout="resume"``, the default: from
  the recorded block output, with the arguments the blocks were called with; ``"hook"``: a forward
  hook and a whole forward pass, the same numbers at about twice the cost);
* direct head: Wan's time-conditioned output stage applied to the modified state at once
  (``model.direct_head``); the baseline of this readout is the head applied to the unmodified state.

Loss: unweighted MSE to the velocity target over slots 1.. (slot 0 is the clean conditioning slot).
At the last block both readouts are the same computation. Clip-level means over blocks and taus are
bootstrapped over clips (``rigidbench.stats.bootstrap_ci``, 20,000 resamples, seed 0).

Outputs: bases/b00_tau0.3.npz, bases.csv (procedure, rank, rounds and 3 x rounds, K, alpha, variances,
INLP R^2 path), effects/<clip>.jsonl and effects.jsonl (all of them: one line per clip x block x tau x
variant x readout), effects_by_cell.csv, summary.csv and intervene.json.

On the stage driver (``rigidbench.driver``), in two stages. ``probe-bases`` (``stages.probe_bases``, run
first): an item is a block x tau cell, keyed by the store's content and INLP's settings. ``probe-intervene``:
an item is a clip, its key the intervention settings (taus, blocks, readout, dtype, the conditioning
when it is not ours), the store, every
cell's bases (their digests), the clip's extraction key and its cache entry; a rerun skips the clips
done this way and redoes exactly those whose key changed, saying why. The summary tables are computed
after every run over the selected clips that are done (``--resamples`` alone redoes no clip). An
``effects.jsonl`` of an older RigidBench (no per-clip files) is not reused: its clips run again.
"""

from __future__ import annotations

import csv
import json
import logging
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from ..atomic import atomic_file
from ..driver import ItemResult, RunOptions, Selection, Stage, StageReport, StageWorker, run_stage, validate_selection
from ..errors import UserError
from ..hashing import digest
from ..jsonio import write_json
from ..perception.device import resolve_device
from ..probe import model as wan
from ..probe.inlp import MAX_ITER, MIN_R2, PROCEDURES, RIDGE
from ..probe.recipe import Conditioning, conditioning_with, recipe, recipe_label
from ..probe.store import ActivationStore
from ..stats.bootstrap import bootstrap_ci
from ..train.cache import LatentCache
from .probe_bases import bases_path, cell_id, fit_cells, load_bases

log = logging.getLogger(__name__)

VARIANTS = ("position", "pc", "random")
READOUTS = ("full", "direct")
DEFAULT_TAUS = (0.3, 0.5, 0.7)


@dataclass(frozen=True)
class InterveneFacts:
    """What ``run_intervene`` adds to the ``probe-intervene`` stage's ``StageReport`` (``report.facts``): the
    content of intervene.json (``results``: the bootstrap summary over the clips done, every cell's bases facts,
    the settings) and the report of the ``probe-bases`` stage it ran first (``bases``: the cells fitted now or up
    to date)."""

    results: dict
    bases: StageReport


class InterveneStage(Stage):
    """The chosen clips -> ``effects/<clip>.jsonl`` (one line per block x tau x variant x readout)."""

    name = "probe-intervene"
    worker = "rigidbench.stages.probe_intervene:InterveneWorker"
    unit = "clip"

    def __init__(self, store: ActivationStore, cache: LatentCache, out: Path, clips: list[str], *, taus, blocks,
                 full_readout: str, device: str, bases: dict[str, str] | None = None,
                 conditioning: Conditioning = Conditioning()):
        self.store, self.cache, self.out, self.clips = store, cache, Path(out), clips
        self.conditioning = conditioning
        man = store.manifest
        self.settings = {"taus": taus, "blocks": blocks, "full_readout": full_readout, "dtype": conditioning.dtype,
                         "variants": list(VARIANTS), "readouts": list(READOUTS)}
        if conditioning.key_part() is not None:  # ours: the keys of outputs made before the option
            self.settings["conditioning"] = conditioning.key_part()
        self.backbone = {"backbone": man["backbone"], "model": man["model"], "model_path": man.get("model_path"),
                         "backbone_seed": man.get("backbone_seed"), "seed": man["seed"]}
        self.device = device
        self.bases: dict[str, str] | None = None
        self.settings_key: str | None = None
        if bases is not None:
            self.use_bases(bases)

    def use_bases(self, bases: dict[str, str]) -> None:
        """The bases the clips are intervened with: every cell's bases digest, in cell order (known once the
        ``probe-bases`` stage has run; the selection is checked before, ``run_intervene``)."""
        self.bases = bases
        self.settings_key = digest(self.settings, digest(self.store.identity), bases)

    @property
    def root(self) -> Path:
        return self.out

    @property
    def where(self) -> str:
        return f"{self.store.dir} (clips also in {self.cache.dir})"

    def items(self) -> dict[str, Any]:
        return {c: {} for c in self.clips}

    def key(self, item_id: str, payload: Any) -> str:
        if self.settings_key is None:
            raise RuntimeError("InterveneStage: use_bases before its keys are computed")
        return digest(self.settings_key, self.store.clip_key(item_id),
                      self.cache.entry_key(item_id, self.conditioning.prompt))

    def job(self) -> dict:
        return {"root": str(self.out.resolve()), "cache": str(Path(self.cache.dir).resolve()), **self.settings,
                **self.backbone, "device": self.device, "conditioning": self.conditioning.as_dict()}

    def intact(self, item_id: str) -> bool:
        return (self.out / effects_file(item_id)).is_file()


def effects_file(clip: str) -> str:
    return f"effects/{clip}.jsonl"


class InterveneWorker(StageWorker):
    """One clip per call: the baseline forward at each tau, then per block and variant the two readouts with
    the block's output projected off the basis. The backbone and the bases load once, here."""

    def __init__(self, job: dict):
        super().__init__(job)
        self.cache = LatentCache(job["cache"])
        self.dev = torch.device(resolve_device(job["device"]))
        self.dtype = getattr(torch, job["dtype"])
        seed = wan.RANDOM_SEED if job.get("backbone_seed") is None else int(job["backbone_seed"])
        self.transformer = wan.load_backbone(job["backbone"], job["model"], job.get("model_path"), self.dev,
                                             self.dtype, seed=seed)
        self.conditioning = Conditioning.from_record(job.get("conditioning"))
        self.obj = wan.make_objective(self.conditioning, self.transformer.config.patch_size)
        self.bases, self.alphas = {}, {}
        for b in job["blocks"]:
            for tau in job["taus"]:
                cell, facts = load_bases(bases_path(Path(job["root"]), b, tau))
                self.bases[(b, tau)] = {k: torch.as_tensor(v, device=self.dev, dtype=torch.float32)
                                        for k, v in cell.items()}
                self.alphas[(b, tau)] = float(facts["alpha_pc"])

    def run(self, item_id: str, payload: Any, staging: Path, progress) -> ItemResult:
        transformer, dev, dtype, clip = self.transformer, self.dev, self.dtype, item_id
        cond = self.conditioning
        latent, text = self.cache.batch([self.cache.ids.index(clip)], dtype=torch.float32, prompt=cond.prompt,
                                        padding=cond.padding)
        lines = []
        taus = self.job["taus"]
        for n, tau in enumerate(taus):
            batch = wan.noised_batch(latent[0], clip, tau, self.obj, self.job["seed"], cond)
            captured: dict = {}
            with torch.no_grad(), wan.capture_blocks(transformer, captured), \
                    wan.capture_block_inputs(transformer, captured):
                base = wan.forward(transformer, batch, text, dev, dtype)
            loss0 = wan.flow_loss(base, batch)
            for b in self.job["blocks"]:
                h = captured[b].float()
                with torch.no_grad():
                    direct0 = wan.flow_loss(wan.direct_head(transformer, captured[b], captured["temb"],
                                                            batch.noisy.shape), batch)
                for variant in VARIANTS:
                    basis = self.bases[(b, tau)][variant]
                    alpha = self.alphas[(b, tau)] if variant == "pc" else 1.0
                    with torch.no_grad():
                        mod = (h - alpha * (h @ basis) @ basis.T).to(captured[b].dtype)
                        if self.job["full_readout"] == "hook":
                            with wan.intervene_block(transformer, b, basis, alpha):
                                full = wan.flow_loss(wan.forward(transformer, batch, text, dev, dtype), batch)
                        else:
                            full = wan.flow_loss(wan.resume_from(transformer, b, mod, captured["block_args"],
                                                                 captured["temb"], batch.noisy.shape), batch)
                        direct = wan.flow_loss(wan.direct_head(transformer, mod, captured["temb"],
                                                               batch.noisy.shape), batch)
                    for readout, l0, l1 in (("full", loss0, full), ("direct", direct0, direct)):
                        lines.append({"clip": clip, "block": b, "tau": tau, "variant": variant,
                                      "readout": readout, "loss_base": l0, "loss": l1, "delta": l1 - l0})
            progress(n + 1, len(taus))
        rel = effects_file(clip)
        (staging / "effects").mkdir()
        (staging / rel).write_text("".join(json.dumps(line) + "\n" for line in lines))
        return ItemResult(outputs=[rel], result={"lines": len(lines)})

    def close(self) -> None:
        self.transformer = None


def run_intervene(acts, cache_dir, out, *, taus=DEFAULT_TAUS, run: RunOptions = RunOptions(Selection(limit=100)),
                  blocks=None, n_resamples: int = 20000, device: str | None = None,
                  dtype=None, full_readout: str = "resume", inlp_dtype=torch.float64,
                  clip_split: str = "all", recipe: str | None = None, overrides: dict | None = None,
                  inlp_procedure: str | None = None) -> StageReport:
    """The bases of every block x tau cell (stage ``probe-bases``), then the loss changes on the first
    ``run.selection.limit`` clips (stage ``probe-intervene``; the command's ``--clips``), then the bootstrap
    tables over the clips done. An unknown id in ``run.selection`` fails before any bases are fitted. Returns
    the ``probe-intervene`` stage's report, its ``facts`` an ``InterveneFacts``.
    Conditioning and INLP procedure: those of ``recipe`` (default: the recipe the store was extracted with,
    and the store's own conditioning), with ``overrides`` of its choices (``dtype``, when given, is the
    forward precision) and ``inlp_procedure`` instead of the recipe's."""
    store = ActivationStore(acts)
    man = store.manifest
    cond, procedure, label = _intervention_recipe(store, recipe, overrides, dtype, inlp_procedure)
    taus = [float(t) for t in taus]
    for t in taus:
        if not any(abs(t - s) < 1e-9 for s in store.taus):
            raise UserError(f"tau {t} was not extracted into {acts} (it has {store.taus})")
    blocks = list(range(store.blocks)) if blocks is None else [int(b) for b in blocks]
    if full_readout not in ("resume", "hook"):
        raise UserError(f"full readout must be resume or hook, got {full_readout!r}")
    if clip_split not in ("all", "train"):
        raise UserError(f"clip split must be all or train, got {clip_split!r}")
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    inlp_dev = torch.device(resolve_device(device))
    inlp_dtype = str(inlp_dtype).replace("torch.", "")
    start = time.perf_counter()

    # the candidate clips: the store's (all, or its training split) that are in the cache
    cache = LatentCache(cache_dir)
    present = set(store.rows["clip"])
    pool = sorted(i for i, s in man["splits"].items() if i in present and (clip_split == "all" or s == "train"))
    candidates = [i for i in pool if i in cache.manifest["examples"]]
    if not candidates:
        raise UserError(f"{acts}: no {'training-split ' if clip_split == 'train' else ''}clips of the store are in "
                        f"the cache {cache_dir}")
    stage = InterveneStage(store, cache, out, candidates, taus=taus, blocks=blocks, full_readout=full_readout,
                           device=str(resolve_device(device)), conditioning=cond)
    validate_selection(stage, run)  # an unknown id fails now, before the bases are fitted

    # 1. bases per cell (on the full activation corpus); 2. the loss changes on the selected clips
    cells = [(b, tau) for b in blocks for tau in taus]
    fitted, facts = fit_cells(store, out, cells, str(inlp_dev), inlp_dtype, procedure, progress=run.progress)
    stage.use_bases({cell_id(b, tau): fitted.results[cell_id(b, tau)]["digest"] for b, tau in cells})
    report = run_stage(stage, run)
    done = report.succeeded
    if not done:
        raise UserError(f"{out}: no clip could be intervened on ("
                        + "; ".join(f"{k}: {v}" for k, v in list(report.failed.items())[:3]) + ")")
    effects = [json.loads(line) for clip in done for line in (out / effects_file(clip)).read_text().splitlines()
               if line.strip()]
    with atomic_file(out / "effects.jsonl") as tmp:
        tmp.write_text("".join(json.dumps(e) + "\n" for e in effects))
    inlp_record = {"procedure": procedure, "ridge_per_row": RIDGE, "min_r2": MIN_R2, "max_iter": MAX_ITER,
                   "intercept": False, "centred": False, "r2": "pooled",
                   "dtype": inlp_dtype if procedure == "stable" else "float32 (ridge solved in float64)",
                   "device": str(inlp_dev)}
    meta = {"acts": str(Path(acts).resolve()), "backbone": man["backbone"], "model": man["model"], "taus": taus,
            "blocks": blocks, "clips": done, "seconds_this_run": time.perf_counter() - start,
            "full_readout": full_readout, "clip_split": clip_split, "recipe": label, "conditioning": cond.as_dict(),
            "store_conditioning": store.conditioning.as_dict(), "inlp": inlp_record,
            "clips_this_run": len(report.ran), "bases_fitted_this_run": len(fitted.ran), "failed": report.failed,
            "redone": report.redone}
    report.facts = InterveneFacts(summarize(effects, facts, out, n_resamples, meta), fitted)
    return report


def _intervention_recipe(store: ActivationStore, name: str | None, overrides: dict | None, dtype,
                         inlp_procedure: str | None) -> tuple[Conditioning, str, str]:
    """(conditioning, INLP procedure, recipe label) of an intervention on ``store`` (``run_intervene``)."""
    if name is None:
        chosen = recipe(store.recipe.split("+")[0])
        base = store.conditioning
    else:
        chosen = recipe(name)
        base = chosen.conditioning
    if dtype is not None:
        overrides = {"dtype": str(dtype).replace("torch.", ""), **(overrides or {})}
    cond = conditioning_with(base, **(overrides or {}))
    procedure = inlp_procedure or chosen.inlp
    if procedure not in PROCEDURES:
        raise UserError(f"INLP procedure must be one of {', '.join(PROCEDURES)}, got {procedure!r}")
    if cond != store.conditioning:
        differ = {k: (v, store.conditioning.as_dict()[k]) for k, v in cond.as_dict().items()
                  if v != store.conditioning.as_dict()[k]}
        log.warning("%s: intervening with conditioning other than the store's extraction (%s)", store.dir,
                    ", ".join(f"{k} {a} instead of {b}" for k, (a, b) in differ.items()))
    return cond, procedure, recipe_label(chosen.name, cond, procedure)


def summarize(effects: list[dict], facts: list[dict], out: Path, n_resamples: int, meta: dict) -> dict:
    """Bootstrap tables from the effect lines: summary.csv (clip means over every block and tau) and
    effects_by_cell.csv (per block x tau, over clips); intervene.json with both."""
    clips = sorted({e["clip"] for e in effects})
    cindex = {c: i for i, c in enumerate(clips)}
    summary, by_cell = [], []
    cells = sorted({(e["block"], e["tau"]) for e in effects})
    for variant in VARIANTS:
        for readout in READOUTS:
            sel = [e for e in effects if e["variant"] == variant and e["readout"] == readout]
            sums, counts = np.zeros(len(clips)), np.zeros(len(clips))
            grid = np.full((len(cells), len(clips)), np.nan)
            cpos = {c: i for i, c in enumerate(cells)}
            for e in sel:
                sums[cindex[e["clip"]]] += e["delta"]
                counts[cindex[e["clip"]]] += 1
                grid[cpos[(e["block"], e["tau"])], cindex[e["clip"]]] = e["delta"]
            per_clip = np.where(counts > 0, sums / np.maximum(counts, 1), np.nan)
            mean, lo, hi = bootstrap_ci(per_clip, n_resamples=n_resamples, seed=0)
            summary.append({"variant": variant, "readout": readout, "mean": mean, "lo": lo, "hi": hi,
                            "clips": int(np.isfinite(per_clip).sum())})
            m, l, h = bootstrap_ci(grid, n_resamples=n_resamples, seed=0) if len(cells) else ([], [], [])
            for (b, tau), a, c, d in zip(cells, np.atleast_1d(m), np.atleast_1d(l), np.atleast_1d(h)):
                by_cell.append({"variant": variant, "readout": readout, "block": b, "tau": tau, "mean": float(a),
                                "lo": float(c), "hi": float(d)})
    with (out / "summary.csv").open("w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=["variant", "readout", "mean", "lo", "hi", "clips"], extrasaction="ignore")
        w.writeheader()
        w.writerows(summary)
    with (out / "effects_by_cell.csv").open("w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=["variant", "readout", "block", "tau", "mean", "lo", "hi"])
        w.writeheader()
        w.writerows(by_cell)
    result = {**meta, "n_resamples": n_resamples, "summary": summary,
              "bases": [{k: v for k, v in f.items()} for f in facts]}
    write_json(out / "intervene.json", result, sort_keys=True)
    return result
