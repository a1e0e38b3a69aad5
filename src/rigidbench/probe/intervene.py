"""``rigidbench probe intervene``: remove a fitted subspace at one block and measure Wan's loss change
(paper appendix E, "Position-Aligned Interventions").

Per block x tau cell: the position basis by INLP on all the store's rows (``inlp.inlp``: the
release's ridge and pooled R^2, 80/20 row split inside, torch on CUDA when available), a random
orthonormal basis of the same rank, and the variance-matched top-K principal components with their
alpha (variances from INLP's training rows, as in the release). The clips are the first ``clips`` of
the store's clips sorted by id (``clip_split="all"``, the release's: its first 100 ids of the
training corpus, whatever their probe split), or of its training-split clips (``"train"``). Bases
fitted by an older INLP (``BASES_VERSION``) are refitted, not reused. For each chosen clip, under the
same noised latent as
extraction: the baseline forward (recording every block's output and the time embedding), then per
block and variant

* full model: the block's output h is replaced by h - alpha (h B) B^T on every token and the forward
  continues through the remaining blocks and the head (``full_readout="resume"``, the default: from
  the recorded block output, with the arguments the blocks were called with; ``"hook"``: a forward
  hook and a whole forward pass, the same numbers at about twice the cost);
* direct head: Wan's time-conditioned output stage applied to the modified state at once
  (``model.direct_head``); the baseline of this readout is the head applied to the unmodified state.

Loss: unweighted MSE to the velocity target over slots 1.. (slot 0 is the clean conditioning slot).
At the last block both readouts are the same computation. Clip-level means over blocks and taus are
bootstrapped over clips (``rigidbench.stats.bootstrap_ci``, 20,000 resamples, seed 0).

Outputs: bases/b00_tau0.3.npz, bases.csv (rank, K, alpha, variances, INLP R^2 path), effects.jsonl
(one line per clip x block x tau x variant x readout; a rerun skips done clips), effects_by_cell.csv,
summary.csv and intervene.json.
"""

from __future__ import annotations

import csv
import json
import time
from pathlib import Path

import numpy as np
import torch

from ..atomic import atomic_file
from ..errors import UserError
from ..perception.device import resolve_device
from ..stats.bootstrap import bootstrap_ci
from ..train.cache import LatentCache
from ..train.objective import FlowMatchingObjective
from . import model as wan
from .inlp import (MAX_ITER, MIN_R2, RIDGE, inlp, random_orthonormal, removed_variance, resolve_device as inlp_device,
                   total_variance, variance_matched_pcs)
from .store import ActivationStore, atomic_json, tau_name

VARIANTS = ("position", "pc", "random")
READOUTS = ("full", "direct")
DEFAULT_TAUS = (0.3, 0.5, 0.7)


BASES_VERSION = 2  # 2: the release's INLP (uncentred ridge scaled by rows, pooled R^2), controls on its training rows


def fit_bases(x: np.ndarray, position: np.ndarray, ridge: float = RIDGE, min_r2: float = MIN_R2,
              max_iter: int = MAX_ITER, seed: int = 0, device=None, dtype=torch.float64) -> dict:
    """The three bases of one cell: {"position", "random", "pc": (D, r) arrays, "alpha_pc", facts...}.
    INLP on all rows (80/20 split inside); the controls from the INLP training rows, as the release."""
    res = inlp(x, position, ridge=ridge, min_r2=min_r2, max_iter=max_iter, seed=seed, device=device, dtype=dtype,
               keep_covariance=True)
    cov = res.covariance
    pc = variance_matched_pcs(None, res.basis, cov, device=res.device)
    rand = random_orthonormal(res.basis.shape[0], res.rank, seed + 1)
    return {"position": res.basis, "random": rand, "pc": pc.basis, "alpha_pc": pc.alpha, "rank": res.rank,
            "k_pc": pc.k, "removed_variance": pc.target_variance, "top_k_variance": pc.top_variance,
            "random_removed_variance": removed_variance(None, rand, cov), "total_variance": total_variance(None, cov),
            "iterations": len(res.train_r2), "stopped": res.stopped, "train_r2": res.train_r2,
            "heldout_r2": res.heldout_r2, "train_rows": res.train_rows, "heldout_rows": res.heldout_rows,
            "inlp_seconds": res.seconds, "inlp_device": res.device, "inlp_dtype": res.dtype,
            "version": BASES_VERSION}


def run_intervene(acts, cache_dir, out, *, taus=DEFAULT_TAUS, clips: int = 100, blocks=None,
                  n_resamples: int = 20000, device: str | None = None, progress: bool = True,
                  dtype=torch.float32, full_readout: str = "resume", inlp_dtype=torch.float64,
                  clip_split: str = "all") -> dict:
    from tqdm import tqdm

    store = ActivationStore(acts)
    man = store.manifest
    taus = [float(t) for t in taus]
    for t in taus:
        if not any(abs(t - s) < 1e-9 for s in store.taus):
            raise UserError(f"tau {t} was not extracted into {acts} (it has {store.taus})")
    blocks = list(range(store.blocks)) if blocks is None else list(blocks)
    if full_readout not in ("resume", "hook"):
        raise UserError(f"full readout must be resume or hook, got {full_readout!r}")
    out = Path(out)
    (out / "bases").mkdir(parents=True, exist_ok=True)
    rows = store.rows
    position = rows["position"].astype(np.float64)
    inlp_dev = inlp_device(None if device is None else resolve_device(device))
    inlp_dtype = getattr(torch, inlp_dtype) if isinstance(inlp_dtype, str) else inlp_dtype

    # 1. bases per cell (on the full activation corpus)
    bases, alphas, facts = {}, {}, []
    for b in blocks:
        for tau in taus:
            path = out / "bases" / f"b{b:02d}_{tau_name(tau)}.npz"
            info = None
            if path.is_file():
                with np.load(path, allow_pickle=False) as z:
                    cell = {k: z[k] for k in z.files}
                info = json.loads(str(cell.pop("facts")))
                if info.get("version") != BASES_VERSION:  # fitted by an older INLP: refit
                    info = None
            if info is None:
                fitted = fit_bases(store.cell(b, tau), position, device=inlp_dev, dtype=inlp_dtype)
                info = {k: v for k, v in fitted.items() if k not in ("position", "random", "pc")}
                cell = {k: fitted[k] for k in ("position", "random", "pc")}
                with atomic_file(path, suffix=".npz") as tmp:
                    np.savez(tmp, facts=json.dumps(info), **{k: v.astype(np.float32) for k, v in cell.items()})
            bases[(b, tau)] = cell
            alphas[(b, tau)] = float(info["alpha_pc"])
            facts.append({"block": b, "tau": tau, **info})
    with (out / "bases.csv").open("w", newline="") as fh:
        cols = ["block", "tau", "rank", "iterations", "stopped", "k_pc", "alpha_pc", "removed_variance",
                "top_k_variance", "random_removed_variance", "total_variance", "final_train_r2", "first_heldout_r2",
                "last_heldout_r2", "train_rows", "heldout_rows", "inlp_seconds", "inlp_device", "inlp_dtype"]
        w = csv.DictWriter(fh, fieldnames=cols, extrasaction="ignore")
        w.writeheader()
        for f in facts:
            w.writerow({**f, "final_train_r2": f["train_r2"][-1] if f["train_r2"] else "",
                        "first_heldout_r2": f["heldout_r2"][0] if f["heldout_r2"] else "",
                        "last_heldout_r2": f["heldout_r2"][-1] if f["heldout_r2"] else ""})

    # 2. the loss changes on the first ``clips`` training clips
    cache = LatentCache(cache_dir)
    if clip_split not in ("all", "train"):
        raise UserError(f"clip split must be all or train, got {clip_split!r}")
    present = set(rows["clip"])
    pool = sorted(i for i, s in man["splits"].items() if i in present and (clip_split == "all" or s == "train"))
    chosen = [i for i in pool if i in cache.manifest["examples"]][:clips]
    if not chosen:
        raise UserError(f"{acts}: no {'training-split ' if clip_split == 'train' else ''}clips of the store are in "
                        f"the cache {cache_dir}")
    dev = torch.device(resolve_device(device))
    transformer = wan.load_backbone(man["backbone"], man["model"], man.get("model_path"), dev, dtype)
    obj = FlowMatchingObjective(wan.NUM_TRAIN_TIMESTEPS, wan.SHIFT, transformer.config.patch_size)
    eff_path = out / "effects.jsonl"
    effects = [json.loads(x) for x in eff_path.read_text().splitlines() if x.strip()] if eff_path.is_file() else []
    done = {e["clip"] for e in effects}
    start = time.perf_counter()
    todo = [c for c in chosen if c not in done]
    bar = tqdm(total=len(todo), unit="clip", desc="intervene", disable=not progress)
    with eff_path.open("a") as fh:
        for clip in todo:
            latent, text = cache.batch([cache.ids.index(clip)], dtype=torch.float32)
            lines = []
            for tau in taus:
                batch = obj.prepare(latent, wan.clip_noise(clip, latent.shape, man["seed"]), wan.tau_index(tau))
                captured: dict = {}
                with torch.no_grad(), wan.capture_blocks(transformer, captured), \
                        wan.capture_block_inputs(transformer, captured):
                    base = wan.forward(transformer, batch, text, dev, dtype)
                loss0 = wan.flow_loss(base, batch)
                for b in blocks:
                    h = captured[b].float()
                    with torch.no_grad():
                        direct0 = wan.flow_loss(wan.direct_head(transformer, captured[b], captured["temb"],
                                                                batch.noisy.shape), batch)
                    for variant in VARIANTS:
                        basis = torch.as_tensor(bases[(b, tau)][variant], device=dev, dtype=torch.float32)
                        alpha = alphas[(b, tau)] if variant == "pc" else 1.0
                        with torch.no_grad():
                            mod = (h - alpha * (h @ basis) @ basis.T).to(captured[b].dtype)
                            if full_readout == "hook":
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
            for line in lines:
                fh.write(json.dumps(line) + "\n")
            fh.flush()
            effects += lines
            bar.update(1)
    bar.close()
    seconds = time.perf_counter() - start
    return summarize(effects, facts, out, n_resamples, {"acts": str(Path(acts).resolve()), "backbone": man["backbone"],
                                                        "model": man["model"], "taus": taus, "blocks": blocks,
                                                        "clips": chosen, "seconds_this_run": seconds,
                                                        "full_readout": full_readout, "clip_split": clip_split,
                                                        "inlp": {"ridge_per_row": RIDGE, "min_r2": MIN_R2,
                                                                 "max_iter": MAX_ITER, "intercept": False,
                                                                 "centred": False, "r2": "pooled",
                                                                 "dtype": str(inlp_dtype).replace("torch.", ""),
                                                                 "device": str(inlp_dev)},
                                                        "clips_this_run": len(todo)})


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
    atomic_json(out / "intervene.json", result)
    return result
