"""The ``probe-bases`` stage (paper section 5.3, appendix E): per block x tau cell, the position basis by INLP
on all the activation store's rows (``probe.inlp``), a random orthonormal basis of the same rank, and the
variance-matched top-K principal components with their alpha, into ``bases/bNN_tauT.npz``.

On the stage driver: an item is a block x tau cell, its key the store's content (every clip's extraction key and
the store's settings) and INLP's settings (``BASES_VERSION``, ridge, stopping R^2, iterations, dtype, procedure);
so a store that gained or changed clips has its bases fitted again, and bases files made before ledgers existed
(or copied from another output folder of the same store) are reused when they say they were fitted this way.
Bases fitted by an older INLP (``BASES_VERSION``) are refitted, not reused. ``probe intervene`` runs this stage
first (``stages.probe_intervene``).
"""

from __future__ import annotations

import csv
import hashlib
import json
from pathlib import Path
from typing import Any

import numpy as np
import torch

from ..driver import Adopted, ItemResult, RunOptions, Stage, StageReport, StageWorker, read_ledger, run_stage
from ..errors import UserError
from ..hashing import digest
from ..perception.device import resolve_device
from ..probe.inlp import (MAX_ITER, MIN_R2, RIDGE, inlp, random_orthonormal, removed_variance, total_variance,
                          variance_matched_pcs)
from ..probe.store import ActivationStore, tau_name


BASES_VERSION = 2  # 2: the release's INLP (uncentred ridge scaled by rows, pooled R^2), controls on its training rows


def fit_bases(x: np.ndarray, position: np.ndarray, ridge: float = RIDGE, min_r2: float = MIN_R2,
              max_iter: int = MAX_ITER, seed: int = 0, device=None, dtype=torch.float64,
              procedure: str = "stable") -> dict:
    """The three bases of one cell: {"position", "random", "pc": (D, r) arrays, "alpha_pc", facts...}.
    INLP (``procedure``) on all rows (80/20 split inside); the controls from the INLP training rows, as the
    release."""
    res = inlp(x, position, ridge=ridge, min_r2=min_r2, max_iter=max_iter, seed=seed, device=device, dtype=dtype,
               keep_covariance=True, procedure=procedure)
    cov = res.covariance
    pc = variance_matched_pcs(None, res.basis, cov, device=res.device)
    rand = random_orthonormal(res.basis.shape[0], res.rank, seed + 1)
    return {"position": res.basis, "random": rand, "pc": pc.basis, "alpha_pc": pc.alpha, "rank": res.rank,
            "k_pc": pc.k, "removed_variance": pc.target_variance, "top_k_variance": pc.top_variance,
            "random_removed_variance": removed_variance(None, rand, cov), "total_variance": total_variance(None, cov),
            "iterations": len(res.train_r2), "rounds": res.rounds, "procedure": res.procedure,
            "stopped": res.stopped, "train_r2": res.train_r2,
            "heldout_r2": res.heldout_r2, "train_rows": res.train_rows, "heldout_rows": res.heldout_rows,
            "inlp_seconds": res.seconds, "inlp_device": res.device, "inlp_dtype": res.dtype,
            "version": BASES_VERSION}


def _bases_digest(cell: dict) -> str:
    """A digest of one cell's three bases as stored (float32)."""
    h = hashlib.sha256()
    for k in ("position", "random", "pc"):
        a = np.ascontiguousarray(np.asarray(cell[k], dtype=np.float32))
        h.update(f"{k}{a.shape}".encode())
        h.update(a.tobytes())
    return h.hexdigest()


def cell_id(block: int, tau: float) -> str:
    return f"b{block:02d}_{tau_name(tau)}"


def bases_path(root: Path, block: int, tau: float) -> Path:
    return Path(root) / "bases" / f"{cell_id(block, tau)}.npz"


def load_bases(path: Path) -> tuple[dict, dict]:
    """(arrays {"position", "random", "pc"}, facts) of a bases file."""
    with np.load(path, allow_pickle=False) as z:
        cell = {k: z[k] for k in z.files}
    return cell, json.loads(str(cell.pop("facts")))


def bases_key(store_digest: str, inlp_dtype: str, block: int, tau: float, procedure: str = "stable") -> str:
    """What determines a cell's bases: the store's rows and activations, the cell, INLP's settings (the
    release's procedure has its own precision; the stable one keeps the keys of bases made before it)."""
    if procedure == "release":
        return digest("inlp-bases", BASES_VERSION, store_digest, int(block), float(tau), RIDGE, MIN_R2, MAX_ITER, 0,
                      "release")
    return digest("inlp-bases", BASES_VERSION, store_digest, int(block), float(tau), RIDGE, MIN_R2, MAX_ITER, 0,
                  str(inlp_dtype))


def rounds_of(facts: dict) -> int:
    """Regressors a cell's INLP added (bases facts of any version: the rounds run, less a last one that
    stopped on R^2)."""
    if "rounds" in facts:
        return int(facts["rounds"])
    return len(facts.get("train_r2") or []) - (facts.get("stopped") == "r2")


class BasesStage(Stage):
    """The block x tau cells -> ``bases/bNN_tauT.npz``: INLP on all the store's rows of the cell, and its two
    controls (``fit_bases``). A cell's key is the store's content and INLP's settings, so a store that
    gained clips has its bases fitted again; bases made before ledgers existed (or copied from another
    output folder of the same store) are reused."""

    name = "probe-bases"
    worker = "rigidbench.stages.probe_bases:BasesWorker"
    unit = "cell"

    def __init__(self, store: ActivationStore, out: Path, cells: list[tuple[int, float]], device: str,
                 inlp_dtype: str, procedure: str = "stable"):
        self.store, self.out, self.cells = store, Path(out), cells
        self.device, self.inlp_dtype, self.procedure = device, inlp_dtype, procedure
        self.store_digest = digest(store.identity)

    @property
    def root(self) -> Path:
        return self.out

    def items(self) -> dict[str, Any]:
        return {cell_id(b, tau): {"block": b, "tau": tau} for b, tau in self.cells}

    def key(self, item_id: str, payload: Any) -> str:
        return bases_key(self.store_digest, self.inlp_dtype, payload["block"], payload["tau"], self.procedure)

    def job(self) -> dict:
        return {"acts": str(self.store.dir.resolve()), "store_digest": self.store_digest, "device": self.device,
                "inlp_dtype": self.inlp_dtype, "procedure": self.procedure}

    def intact(self, item_id: str) -> bool:
        """The cell's bases file is there and says it was fitted with the ledger's key (not, e.g., copied over
        from another store's output)."""
        path = self.out / "bases" / f"{item_id}.npz"
        try:
            with np.load(path, allow_pickle=False) as z:
                made_with = json.loads(str(z["facts"])).get("key")
        except (OSError, ValueError, KeyError):
            return False
        return made_with is None or made_with == (read_ledger(self.out, self.name, item_id) or {}).get("key")

    def adopt(self, item_id: str, payload: Any, key: str) -> Adopted | None:
        path = self.out / "bases" / f"{item_id}.npz"
        if not path.is_file():
            return None
        try:
            cell, facts = load_bases(path)
        except (OSError, ValueError, KeyError):
            return None
        if facts.get("key", key) != key or facts.get("version") != BASES_VERSION:
            return None  # fitted for another store, with other settings, or by an older INLP: fitted again
        return Adopted({**facts, "digest": _bases_digest(cell)}, f"a bases file fitted this way ({path})")


class BasesWorker(StageWorker):
    def __init__(self, job: dict):
        super().__init__(job)
        self.store = ActivationStore(job["acts"])
        self.position = self.store.rows["position"].astype(np.float64)
        self.device = torch.device(resolve_device(job["device"]))
        self.dtype = getattr(torch, job["inlp_dtype"])

    def run(self, item_id: str, payload: Any, staging: Path, progress) -> ItemResult:
        b, tau = int(payload["block"]), float(payload["tau"])
        procedure = self.job.get("procedure", "stable")
        fitted = fit_bases(self.store.cell(b, tau), self.position, device=self.device, dtype=self.dtype,
                           procedure=procedure)
        info = {k: v for k, v in fitted.items() if k not in ("position", "random", "pc")}
        info["key"] = bases_key(self.job["store_digest"], self.job["inlp_dtype"], b, tau, procedure)
        cell = {k: fitted[k].astype(np.float32) for k in ("position", "random", "pc")}
        rel = f"bases/{item_id}.npz"
        (staging / "bases").mkdir()
        np.savez(staging / rel, facts=json.dumps(info), **cell)
        return ItemResult(outputs=[rel], result={**info, "digest": _bases_digest(cell)})


BASES_COLUMNS = ["block", "tau", "procedure", "rank", "rounds", "rounds_x3", "iterations", "stopped", "k_pc", "alpha_pc",
                 "removed_variance", "top_k_variance", "random_removed_variance", "total_variance", "final_train_r2",
                 "first_heldout_r2", "last_heldout_r2", "train_rows", "heldout_rows", "inlp_seconds", "inlp_device",
                 "inlp_dtype"]


def fit_cells(store: ActivationStore, out: Path, cells: list[tuple[int, float]], device: str, inlp_dtype: str,
              procedure: str = "stable", progress: bool = True) -> tuple[StageReport, list[dict]]:
    """Run the ``probe-bases`` stage on ``cells`` into ``out`` and write ``out/bases.csv``: (the stage's
    report, each cell's facts in cell order). UserError when any cell could not be fitted."""
    fitted = run_stage(BasesStage(store, out, cells, device, inlp_dtype, procedure), RunOptions(progress=progress))
    if fitted.failed:
        raise UserError(f"{store.dir}: the bases of {len(fitted.failed)} cell(s) could not be fitted ("
                        + "; ".join(f"{k}: {v}" for k, v in list(fitted.failed.items())[:3]) + ")")
    facts = []
    for b, tau in cells:
        info = {k: v for k, v in fitted.results[cell_id(b, tau)].items() if k not in ("key", "digest")}
        facts.append({"block": b, "tau": tau, **info})
    with (Path(out) / "bases.csv").open("w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=BASES_COLUMNS, extrasaction="ignore")
        w.writeheader()
        for f in facts:
            w.writerow({**f, "procedure": f.get("procedure", "stable"), "rounds": rounds_of(f),
                        "rounds_x3": 3 * rounds_of(f), "final_train_r2": f["train_r2"][-1] if f["train_r2"] else "",
                        "first_heldout_r2": f["heldout_r2"][0] if f["heldout_r2"] else "",
                        "last_heldout_r2": f["heldout_r2"][-1] if f["heldout_r2"] else ""})
    return fitted, facts


__all__ = ["BASES_VERSION", "BasesStage", "BasesWorker", "bases_key", "bases_path", "cell_id", "fit_bases",
           "fit_cells", "load_bases", "rounds_of"]
