"""Linear and MLP probes (paper table "Probe configuration") and the shuffled-label control.

One cell is fit per block x tau x target x probe class x label condition:

* linear: one affine map D -> k; mlp: D -> 64 -> k with a ReLU hidden layer;
* Adam, 20 epochs, batch 4,096, learning rate 1e-3, seed 0 (the batch order and the initial weights);
* continuous targets: MSE loss, test R^2; contact: binary cross-entropy, test ROC-AUC;
* the shuffled control permutes the training labels once (seed 0); validation and test keep theirs.

As in the authors' release (``probe/fit.py``), which produced the paper's tables, the probe is fit on
the raw activations and raw targets, and R^2 is pooled over the target's dimensions:
1 - sum of squared residuals over all dimensions / sum of squared deviations from each dimension's
test-set mean (``r2_score``). Two choices of ours stay available as explicit options, recorded in
``fit.json``: ``standardize=True`` (inputs and continuous targets z-scored with training statistics,
an affine change of variables that keeps the linear probe affine) and ``r2="mean"`` (the uniform
average of per-dimension R^2).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from ..errors import UserError
from ..jsonio import write_json
from .store import ActivationStore

PROBES = ("linear", "mlp")
LABELS = ("trained", "shuffled")
R2_KINDS = ("pooled", "mean")


@dataclass(frozen=True)
class ProbeSettings:
    epochs: int = 20
    batch_size: int = 4096
    lr: float = 1e-3
    seed: int = 0
    hidden: int = 64
    device: str = "cpu"  # where the probe trains (the batch order is drawn on the CPU either way)
    standardize: bool = False  # the release fits raw activations and targets; True: z-score both (ours)
    r2: str = "pooled"         # "pooled" over the target's dimensions (the release) or "mean" per dimension


def r2_score(y: np.ndarray, pred: np.ndarray, kind: str = "pooled") -> float:
    """R^2 of ``pred`` for ``y`` (n, k). ``pooled`` (the release's, the default): 1 - SS_res / SS_tot with
    both sums over every row and dimension, SS_tot about each dimension's mean; NaN when SS_tot is 0.
    ``mean``: the uniform average over dimensions of each one's R^2 (dimensions with zero variance
    left out). NaN for fewer than two rows."""
    if kind not in R2_KINDS:
        raise ValueError(f"unknown R^2 {kind!r}; use one of {R2_KINDS}")
    y = np.asarray(y, dtype=np.float64).reshape(len(y), -1)
    pred = np.asarray(pred, dtype=np.float64).reshape(len(pred), -1)
    if len(y) < 2:
        return float("nan")
    ss_tot = ((y - y.mean(axis=0)) ** 2).sum(axis=0)
    ss_res = ((y - pred) ** 2).sum(axis=0)
    if kind == "pooled":
        total = float(ss_tot.sum())
        return 1.0 - float(ss_res.sum()) / total if total > 0 else float("nan")
    ok = ss_tot > 1e-12 * max(1.0, float(np.abs(y).max()) ** 2)
    if not ok.any():
        return float("nan")
    return float(np.mean(1.0 - ss_res[ok] / ss_tot[ok]))


def roc_auc(y: np.ndarray, score: np.ndarray) -> float:
    """ROC-AUC of ``score`` for binary ``y`` (NaN when only one class is present)."""
    y = np.asarray(y).reshape(-1) > 0.5
    if y.all() or not y.any():
        return float("nan")
    from sklearn.metrics import roc_auc_score

    return float(roc_auc_score(y, np.asarray(score, dtype=np.float64).reshape(-1)))


def make_probe(kind: str, d_in: int, d_out: int, hidden: int = 64) -> torch.nn.Module:
    if kind == "linear":
        return torch.nn.Linear(d_in, d_out)
    if kind == "mlp":
        return torch.nn.Sequential(torch.nn.Linear(d_in, hidden), torch.nn.ReLU(), torch.nn.Linear(hidden, d_out))
    raise ValueError(f"unknown probe kind {kind!r}; use one of {PROBES}")


def shuffled(y: np.ndarray, seed: int = 0) -> np.ndarray:
    """The training labels permuted once (rows): ``torch.randperm`` with a CPU generator seeded ``seed``,
    the release's permutation."""
    return y[torch.randperm(len(y), generator=torch.Generator().manual_seed(int(seed))).numpy()]


def _stats(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    mean = x.mean(axis=0)
    std = x.std(axis=0)
    return mean, np.where(std > 1e-6, std, 1.0)


class FittedProbe:
    """A trained probe with its input (and target) standardisation; ``predict`` returns target units
    (continuous) or logits (binary)."""

    def __init__(self, net, x_stats, y_stats, binary: bool, r2: str = "pooled"):
        self.net, self.x_stats, self.y_stats, self.binary, self.r2 = net, x_stats, y_stats, binary, r2

    @torch.no_grad()
    def predict(self, x: np.ndarray) -> np.ndarray:
        device = next(self.net.parameters()).device
        xs = torch.as_tensor(((x - self.x_stats[0]) / self.x_stats[1]).astype(np.float32), device=device)
        out = self.net(xs).cpu().numpy().astype(np.float64)
        return out if self.binary else out * self.y_stats[1] + self.y_stats[0]


def train_probe(x: np.ndarray, y: np.ndarray, kind: str, binary: bool,
                settings: ProbeSettings = ProbeSettings()) -> tuple[FittedProbe, float]:
    """Fit one probe on rows ``x`` (n, D), labels ``y`` (n, k) (raw, or z-scored when
    ``settings.standardize``); returns it and its last-epoch mean loss."""
    x = np.asarray(x, dtype=np.float32)
    y = np.asarray(y, dtype=np.float32).reshape(len(y), -1)
    identity = (np.zeros(x.shape[1], np.float32), np.ones(x.shape[1], np.float32))
    x_stats = _stats(x) if settings.standardize else identity
    y_stats = _stats(y) if settings.standardize and not binary else (np.zeros(y.shape[1]), np.ones(y.shape[1]))
    device = torch.device(settings.device)
    xs = torch.as_tensor((x - x_stats[0]) / x_stats[1], dtype=torch.float32, device=device)
    ys = torch.as_tensor((y - y_stats[0]) / y_stats[1], dtype=torch.float32, device=device)
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(settings.seed)
        net = make_probe(kind, x.shape[1], y.shape[1], settings.hidden).to(device)
    gen = torch.Generator().manual_seed(settings.seed)
    opt = torch.optim.Adam(net.parameters(), lr=settings.lr)
    loss_fn = torch.nn.BCEWithLogitsLoss() if binary else torch.nn.MSELoss()
    last = float("nan")
    for _ in range(settings.epochs):
        order = torch.randperm(len(xs), generator=gen)
        total, count = 0.0, 0
        for start in range(0, len(xs), settings.batch_size):
            idx = order[start:start + settings.batch_size].to(device)
            opt.zero_grad(set_to_none=True)
            loss = loss_fn(net(xs[idx]), ys[idx])
            loss.backward()
            opt.step()
            total += float(loss.detach()) * len(idx)
            count += len(idx)
        last = total / max(count, 1)
    return FittedProbe(net.eval(), x_stats, y_stats, binary, settings.r2), last


def score(probe: FittedProbe, x: np.ndarray, y: np.ndarray) -> float:
    """Test score: ROC-AUC for a binary probe, R^2 otherwise (NaN for no rows)."""
    if len(x) == 0:
        return float("nan")
    pred = probe.predict(np.asarray(x, dtype=np.float32))
    return roc_auc(y, pred) if probe.binary else r2_score(y, pred, probe.r2)


def fit_cell(train: tuple[np.ndarray, np.ndarray], val: tuple[np.ndarray, np.ndarray],
             test: tuple[np.ndarray, np.ndarray], kind: str, binary: bool, labels: str = "trained",
             settings: ProbeSettings = ProbeSettings()) -> dict:
    """One probe cell: {"test", "val" (scores), "train_loss", "metric"}; ``labels="shuffled"`` is the control."""
    x, y = train
    y = np.asarray(y).reshape(len(y), -1)
    if labels == "shuffled":
        y = shuffled(y, settings.seed)
    elif labels != "trained":
        raise ValueError(f"unknown label condition {labels!r}; use one of {LABELS}")
    probe, loss = train_probe(x, y, kind, binary, settings)
    return {"test": score(probe, *test), "val": score(probe, *val), "train_loss": loss,
            "metric": "roc_auc" if binary else ("r2" if settings.r2 == "pooled" else "r2_mean")}


# -- the sweep (``rigidbench probe fit``) ------------------------------------------------------------

SCORE_COLUMNS = ("backbone", "block", "tau", "target", "probe", "labels", "metric", "test", "val", "train_loss",
                 "n_train", "n_val", "n_test", "seconds")


def cell_key(r: dict) -> tuple:
    return (int(r["block"]), round(float(r["tau"]), 6), r["target"], r["probe"], r["labels"])


def run_fit(acts, out, *, targets=None, probes=PROBES, blocks=None, taus=None,
            settings: ProbeSettings = ProbeSettings(), progress: bool = True) -> list[dict]:
    """Fit every block x tau x target x probe x label cell of the store ``acts`` into ``out``:
    scores.jsonl (one line per cell, appended as it is done: a rerun skips done cells), then
    scores.csv and fit.json (settings, row counts). Returns the score records."""
    import csv
    import json
    import time
    from pathlib import Path

    from tqdm import tqdm

    store = ActivationStore(acts)
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    known = store.targets
    targets = list(targets or known)
    for t in targets:
        if t not in known:
            raise UserError(f"unknown target {t!r}; the store has {', '.join(known)}")
    blocks = list(range(store.blocks)) if blocks is None else list(blocks)
    taus = store.taus if taus is None else [float(t) for t in taus]
    rows = store.rows
    split = rows["split"]
    masks = {s: split == s for s in ("train", "val", "test")}
    if not masks["train"].any():
        raise UserError(f"{acts}: no training rows; extract more clips")
    backbone = store.manifest["backbone"]
    path = out / "scores.jsonl"
    records = [json.loads(line) for line in path.read_text().splitlines() if line.strip()] if path.is_file() else []
    done = {cell_key(r) for r in records}
    write_json(out / "fit.json", {"acts": str(Path(acts).resolve()), "backbone": backbone,
                                   "settings": settings.__dict__, "targets": targets, "probes": list(probes),
                                   "rows": {s: int(m.sum()) for s, m in masks.items()},
                                   "clips": {s: int(len(set(rows["clip"][m]))) for s, m in masks.items()},
                                   "token_grid": store.manifest["token_grid"],
                                   "schedule": store.manifest["schedule"]}, sort_keys=True)
    todo = [(b, tau) for b in blocks for tau in taus]
    bar = tqdm(total=len(todo) * len(targets) * len(probes) * 2, unit="cell", desc=f"fit {backbone}",
               disable=not progress)
    with path.open("a") as fh:
        for b, tau in todo:
            x = None
            for target in targets:
                dim, kind = known[target]
                y = rows[target].reshape(len(split), -1).astype(np.float32)
                for probe in probes:
                    for labels in LABELS:
                        key = (b, round(tau, 6), target, probe, labels)
                        if key in done:
                            bar.update(1)
                            continue
                        if x is None:
                            x = store.cell(b, tau)
                        t0 = time.perf_counter()
                        res = fit_cell(*((x[m], y[m]) for m in (masks["train"], masks["val"], masks["test"])),
                                       probe, kind == "binary", labels, settings)
                        rec = {"backbone": backbone, "block": b, "tau": tau, "target": target, "probe": probe,
                               "labels": labels, **res, "n_train": int(masks["train"].sum()),
                               "n_val": int(masks["val"].sum()), "n_test": int(masks["test"].sum()),
                               "seconds": time.perf_counter() - t0}
                        fh.write(json.dumps(rec) + "\n")
                        fh.flush()
                        records.append(rec)
                        bar.update(1)
    bar.close()
    with (out / "scores.csv").open("w", newline="") as fh:
        writer = csv.DictWriter(fh, fieldnames=SCORE_COLUMNS, extrasaction="ignore")
        writer.writeheader()
        writer.writerows(sorted(records, key=cell_key))
    return records
