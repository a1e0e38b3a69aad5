"""Iterative nullspace projection (INLP) of position and its two controls (paper appendix E,
"Position-Aligned Interventions"), as the authors' release (``probe/inlp.py``) computes them.

INLP: the cell's rows are split 80/20 (``torch.randperm`` seeded 0, the first int(0.8 n) train).
Repeat: fit ridge regression to the target on the training activations projected onto the
orthogonal complement of the basis so far, with the release's ridge: no intercept, uncentred inputs,
penalty ``ridge`` x (number of training rows) (W = (X^T X + 0.05 n I)^-1 X^T y); score it by the
training R^2 pooled over the target's dimensions (``fit.r2_score``); stop when that R^2 < 0.05 (the
regressor is not added) or after 30 iterations; otherwise add the regressor's row space (singular
values above 1e-6 of its largest) to the basis. The basis returned is the row space of all added
regressors stacked (the same 1e-6 rule), whose dimension is the rank the paper reports.

Computation: one pass over the training rows forms G = X^T X and X^T y in ``dtype`` (float64 by
default, as the release's ridge). Because every regressor lies in the complement of the basis so
far, the projected problem needs only G: with P = I - B B^T, (P X^T X P + lam n I) W = P X^T y, and the
projected predictions are X W. Each iteration is then one D x D solve plus one pass of X W for the
R^2 values; the release instead projects the (n, D) matrix and re-forms its Gram every iteration.
In exact arithmetic the two are the same, and this one equals the release's steps computed in
float64 up to rounding (tested); it is not what the release's float32 steps give (below). Torch on
``device`` (default CUDA when available, else the CPU); activations stay float32 and are cast chunk by
chunk (``chunk_rows``).

Procedures (``procedure``): ``"stable"`` (the default) is the computation above. ``"release"``
follows the authors' release literally (``inlp_release``): the training rows in the permutation's
order (not sorted), float32 on ``device``; each round solves the ridge in float64 from the float32
projected rows, casts the regressor W (k, D) to float32, scores it by the pooled R^2 computed in
float32 (stopping when R^2 < 0.05, so a NaN R^2 does not stop it), takes the null space of W by a
float32 SVD (singular values above 1e-6 of the largest count as its rank) and replaces the rows by
their float32 projection (X B) B^T onto that null space; at the end the stacked regressors' null
space N (same rule, float32), the float32 projector P = N N^T, and the basis is the null space of P
by the same rule, so its rank is D minus the number of P's singular values above 1e-6 of the
largest. Float32 rounding accumulates over the rounds and the last two steps count rounding noise
of P as rank, so the two procedures part on real activations (docs/probing.md, "INLP procedures").
The held-out R^2 of each round is ours (the rows projected the same way; R^2 in float64).

Controls: a random orthonormal basis of the same rank (the release's: a float32 Gaussian (D, rank)
matrix from a torch generator seeded ``seed + 1``, then QR; drawn on the CPU here, on the GPU in the
release), and the variance-matched top-K principal components of the training rows:
V_p = ||X_c B_p||_F^2 / (n - 1), K the smallest with sum_{i<=K} lambda_i >= V_p,
alpha = 1 - sqrt(1 - V_p / sum_{i<=K} lambda_i), since removing alpha of the top-K subspace removes
alpha (2 - alpha) sum_{i<=K} lambda_i variance. The intervention applies h - alpha (h B) B^T
(alpha = 1 for INLP and random).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np
import torch

from ..perception.device import resolve_device

RIDGE = 0.05        # ridge coefficient per training row (the release's reg * N)
MIN_R2 = 0.05       # stop when a new regressor's training R^2 falls below this
MAX_ITER = 30
PROCEDURES = ("stable", "release")  # ours (the default) | the release's float32 steps, literally
RANK_TOL = 1e-6     # singular values above RANK_TOL x the largest count towards a row space
TRAIN_FRACTION = 0.8


def split_rows(n: int, train_fraction: float = TRAIN_FRACTION, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """(training, held-out) row indices, each sorted: the release's ``torch.randperm(n)`` with a CPU
    generator seeded ``seed``, the first int(train_fraction n) for training."""
    order = torch.randperm(n, generator=torch.Generator().manual_seed(int(seed))).numpy()
    cut = int(train_fraction * n)
    return np.sort(order[:cut]), np.sort(order[cut:])


class Rows:
    """Rows ``index`` of the activations ``x`` (n, D) (numpy or torch, any float dtype), read in chunks
    of ``chunk_rows`` cast to ``dtype`` on ``device``. On the CPU each chunk is gathered when it is
    read (no copy of the rows is kept); on another device the selected rows are copied there once in
    their own dtype (float32: 4 n D bytes)."""

    def __init__(self, x, index, device, dtype=torch.float64, chunk_rows: int = 16384):
        self.device, self.dtype, self.chunk_rows = torch.device(device), dtype, int(chunk_rows)
        self.x = torch.as_tensor(x) if not torch.is_tensor(x) else x
        self.index = torch.as_tensor(np.asarray(index, dtype=np.int64))
        if self.device.type != "cpu":
            self.x = torch.cat([self.x[self.index[s:s + self.chunk_rows]].to(self.device)
                                for s in range(0, len(self.index), self.chunk_rows)]) if len(self.index) \
                else self.x[:0].to(self.device)
            self.index = None
        self.n, self.d = len(index), int(self.x.shape[1])

    def chunks(self):
        for start in range(0, self.n, self.chunk_rows):
            c = self.x[start:start + self.chunk_rows] if self.index is None else \
                self.x[self.index[start:start + self.chunk_rows]]
            yield start, c.to(device=self.device, dtype=self.dtype)

    def gram(self, y: torch.Tensor | None = None):
        """(X^T X, column sums of X, X^T y or None)."""
        g = torch.zeros((self.d, self.d), device=self.device, dtype=self.dtype)
        s = torch.zeros(self.d, device=self.device, dtype=self.dtype)
        xty = None if y is None else torch.zeros((self.d, y.shape[1]), device=self.device, dtype=self.dtype)
        for start, c in self.chunks():
            g.addmm_(c.T, c)
            s += c.sum(dim=0)
            if y is not None:
                xty.addmm_(c.T, y[start:start + len(c)])
        return g, s, xty

    def matmul(self, w: torch.Tensor) -> torch.Tensor:
        """X w, (n, k)."""
        return torch.cat([c @ w for _, c in self.chunks()]) if self.n else w.new_zeros((0, w.shape[1]))


def _pooled_r2(y: torch.Tensor, pred: torch.Tensor) -> float:
    """The release's R^2: 1 - sum (y - pred)^2 / sum (y - column mean)^2 over all dimensions."""
    if len(y) < 2:
        return float("nan")
    ss_tot = float(((y - y.mean(dim=0)) ** 2).sum())
    return 1.0 - float(((y - pred) ** 2).sum()) / ss_tot if ss_tot > 0 else float("nan")


def row_space(w: torch.Tensor | np.ndarray, tol: float = RANK_TOL):
    """Orthonormal basis (D, r) of the span of the columns of ``w`` (D, k): left singular vectors whose
    singular values exceed ``tol`` x the largest (the release's rank rule)."""
    as_numpy = not torch.is_tensor(w)
    wt = torch.as_tensor(w)
    if wt.numel() == 0:
        out = wt.new_zeros((wt.shape[0], 0))
    else:
        u, s, _ = torch.linalg.svd(wt, full_matrices=False)
        smax = float(s.max()) if s.numel() else 0.0
        out = u[:, s > tol * smax] if smax > 0 else wt.new_zeros((wt.shape[0], 0))
    return out.numpy() if as_numpy else out


def ridge_fit(x: np.ndarray, y: np.ndarray, coef: float = RIDGE) -> np.ndarray:
    """The release's ridge (numpy, float64): W (D, k) = (X^T X + coef n I)^-1 X^T y, no intercept."""
    x = np.asarray(x, dtype=np.float64)
    y = np.asarray(y, dtype=np.float64).reshape(len(x), -1)
    return np.linalg.solve(x.T @ x + coef * len(x) * np.eye(x.shape[1]), x.T @ y)


@dataclass
class INLPResult:
    basis: np.ndarray                       # (D, r) orthonormal columns (float64)
    train_r2: list[float] = field(default_factory=list)    # every fitted regressor's training R^2 (pooled)
    heldout_r2: list[float] = field(default_factory=list)  # ... and on the held-out 20%
    stopped: str = ""                       # "r2" or "iterations"
    train_rows: int = 0
    heldout_rows: int = 0
    device: str = "cpu"
    dtype: str = "float64"
    seconds: float = 0.0
    procedure: str = "stable"
    rounds: int = 0                         # regressors added to the basis
    covariance: np.ndarray | None = None    # (D, D) covariance of the training rows (keep_covariance=True)

    @property
    def rank(self) -> int:
        return int(self.basis.shape[1])


def inlp(x, y, ridge: float = RIDGE, min_r2: float = MIN_R2, max_iter: int = MAX_ITER,
         train_fraction: float = TRAIN_FRACTION, seed: int = 0, device=None, dtype=torch.float64,
         chunk_rows: int = 16384, keep_covariance: bool = False, procedure: str = "stable") -> INLPResult:
    """INLP basis of the target ``y`` (n, k) in the activations ``x`` (n, D); see the module docstring.
    ``keep_covariance`` also returns the training rows' covariance (for the PC control).
    ``procedure="release"``: the release's float32 steps (``inlp_release``; ``dtype`` does not apply)."""
    if procedure == "release":
        return inlp_release(x, y, ridge=ridge, min_r2=min_r2, max_iter=max_iter, train_fraction=train_fraction,
                            seed=seed, device=device, chunk_rows=chunk_rows, keep_covariance=keep_covariance)
    if procedure != "stable":
        raise ValueError(f"unknown INLP procedure {procedure!r}; use one of {PROCEDURES}")
    t0 = time.perf_counter()
    dev = torch.device(resolve_device(None if device is None else str(device)))
    n = len(x)
    y = torch.as_tensor(np.asarray(y, dtype=np.float64).reshape(n, -1))
    tr, ho = split_rows(n, train_fraction, seed)
    train = Rows(x, tr, dev, dtype, chunk_rows)
    held = Rows(x, ho, dev, dtype, chunk_rows)
    y_tr = y[torch.as_tensor(tr)].to(device=dev, dtype=dtype)
    y_ho = y[torch.as_tensor(ho)].to(device=dev, dtype=dtype)
    d = train.d
    g, col_sum, xty = train.gram(y_tr)
    lam = ridge * train.n
    eye = torch.eye(d, device=dev, dtype=dtype)
    basis = torch.zeros((d, 0), device=dev, dtype=dtype)
    added: list[torch.Tensor] = []
    result = INLPResult(basis=np.zeros((d, 0)), stopped="iterations", train_rows=train.n, heldout_rows=held.n,
                        device=str(dev), dtype=str(dtype).replace("torch.", ""))
    for _ in range(max_iter):
        if basis.shape[1]:
            gb = g @ basis
            a = g - basis @ gb.T - gb @ basis.T + basis @ (basis.T @ gb) @ basis.T
            rhs = xty - basis @ (basis.T @ xty)
        else:
            a, rhs = g, xty
        a = (a + a.T) / 2 + lam * eye
        chol, info = torch.linalg.cholesky_ex(a)
        w = torch.cholesky_solve(rhs, chol) if int(info) == 0 else torch.linalg.solve(a, rhs)
        if basis.shape[1]:  # exactly in the complement already; remove rounding
            w = w - basis @ (basis.T @ w)
        r2 = _pooled_r2(y_tr, train.matmul(w))
        result.train_r2.append(r2)
        result.heldout_r2.append(_pooled_r2(y_ho, held.matmul(w)) if held.n > 1 else float("nan"))
        if not r2 >= min_r2:  # also stops on NaN (a constant target)
            result.stopped = "r2"
            break
        added.append(w)
        new = row_space(w)
        if basis.shape[1]:
            new = new - basis @ (basis.T @ new)
            new, _ = torch.linalg.qr(new)
        basis = torch.cat([basis, new], dim=1)
    result.rounds = len(added)
    if added:
        result.basis = row_space(torch.cat(added, dim=1)).to(torch.float64).cpu().numpy()
    if keep_covariance:
        result.covariance = _covariance(g, col_sum, train.n)
    return _finish(result, dev, t0)


def _covariance(g: torch.Tensor, col_sum: torch.Tensor, n: int) -> np.ndarray:
    """The (D, D) float64 covariance of n rows from their Gram matrix and column sums."""
    mean = col_sum / max(n, 1)
    cov = (g - n * torch.outer(mean, mean)) / max(n - 1, 1)
    return ((cov + cov.T) / 2).to(torch.float64).cpu().numpy()


def _finish(result: INLPResult, dev: torch.device, t0: float) -> INLPResult:
    if dev.type == "cuda":
        torch.cuda.synchronize(dev)
    result.seconds = time.perf_counter() - t0
    return result


def _null_space(w: torch.Tensor, tol: float = RANK_TOL) -> torch.Tensor:
    """The release's null-space rule: rows r.. of Vh of a full SVD of ``w`` (m, D), r the number of singular
    values above ``tol`` x the largest; (D, D - r), in ``w``'s dtype."""
    _, s, vh = torch.linalg.svd(w, full_matrices=True)
    smax = float(s.max()) if s.numel() else 0.0
    r = int((s > tol * smax).sum()) if smax > 0 else 0
    return vh[r:].T


def _release_r2(w: torch.Tensor, x: torch.Tensor, y: torch.Tensor) -> float:
    """The release's pooled R^2 of ``x @ w.T`` for ``y``, in the tensors' precision (float32)."""
    pred = x @ w.T
    ss_res = float(((y - pred) ** 2).sum())
    ss_tot = float(((y - y.mean(0)) ** 2).sum())
    return 1.0 - ss_res / ss_tot if ss_tot > 0 else float("nan")


def inlp_release(x, y, ridge: float = RIDGE, min_r2: float = MIN_R2, max_iter: int = MAX_ITER,
                 train_fraction: float = TRAIN_FRACTION, seed: int = 0, device=None, chunk_rows: int = 16384,
                 keep_covariance: bool = False, rows_dtype=torch.float32) -> INLPResult:
    """INLP as the release computes it (module docstring, "Procedures"): float32 rows re-projected one
    regressor at a time, the rank of the stacked regressors, the basis from the float32 projector. Holds
    the n training rows in float32 on ``device`` and a float64 copy while a round's ridge is solved, or two
    float32 copies while they are projected, and the held-out rows: about 13 n D bytes at the peak.
    ``rows_dtype=torch.float64`` runs the same steps in float64 (a measurement aid:
    ``benchmarks/inlp_procedures.py``)."""
    t0 = time.perf_counter()
    dev = torch.device(resolve_device(None if device is None else str(device)))
    n = len(x)
    xt = torch.as_tensor(x) if not torch.is_tensor(x) else x
    yt = torch.as_tensor(np.asarray(y, dtype=np.float64).reshape(n, -1))
    order = torch.randperm(n, generator=torch.Generator().manual_seed(int(seed)))
    cut = int(train_fraction * n)
    tr, ho = order[:cut], order[cut:]  # the permutation's order, as the release indexes them
    x_tr = xt[tr].to(device=dev, dtype=rows_dtype)
    x_ho = xt[ho].to(device=dev, dtype=rows_dtype)
    y_tr, y_ho = yt[tr].to(device=dev, dtype=rows_dtype), yt[ho].to(device=dev, dtype=rows_dtype)
    d = int(x_tr.shape[1])
    precision = str(rows_dtype).replace("torch.", "")
    result = INLPResult(basis=np.zeros((d, 0)), stopped="iterations", train_rows=len(tr), heldout_rows=len(ho),
                        device=str(dev), dtype=f"{precision} (ridge solved in float64)", procedure="release")
    x_proj, h_proj = x_tr, x_ho  # replaced, never changed in place (the release clones)
    del x_tr, x_ho
    eye = torch.eye(d, device=dev, dtype=torch.float64)
    collected: list[torch.Tensor] = []
    for _ in range(max_iter):
        xd = x_proj.double()
        w = torch.linalg.solve(xd.T @ xd + ridge * len(xd) * eye, xd.T @ y_tr.double()).T.to(rows_dtype)
        del xd
        r2 = _release_r2(w, x_proj, y_tr)
        result.train_r2.append(r2)
        result.heldout_r2.append(_pooled_r2(y_ho.double(), (h_proj @ w.T).double()) if len(ho) > 1
                                 else float("nan"))
        if r2 < min_r2:
            result.stopped = "r2"
            break
        collected.append(w)
        null = _null_space(w)
        x_proj = (x_proj @ null) @ null.T
        h_proj = (h_proj @ null) @ null.T
    result.rounds = len(collected)
    if collected:
        joint = _null_space(torch.cat(collected, dim=0))
        result.basis = _null_space(joint @ joint.T).to(torch.float64).cpu().numpy()
    if keep_covariance:
        g, col_sum, _ = Rows(xt, np.sort(tr.numpy()), dev, torch.float64, chunk_rows).gram()
        result.covariance = _covariance(g, col_sum, len(tr))
    return _finish(result, dev, t0)


def project_out(x: np.ndarray, basis: np.ndarray, alpha: float = 1.0) -> np.ndarray:
    """x - alpha (x B) B^T."""
    if basis.shape[1] == 0:
        return x
    return x - alpha * (x @ basis) @ basis.T


def random_orthonormal(d: int, rank: int, seed: int = 1) -> np.ndarray:
    """(d, rank) random orthonormal basis as the release draws it: a float32 standard normal (d, rank)
    matrix from a torch generator seeded ``seed`` (the release passes its seed + 1), then reduced QR."""
    if rank == 0:
        return np.zeros((d, 0))
    g = torch.randn(d, rank, generator=torch.Generator().manual_seed(int(seed)), dtype=torch.float32)
    q, _ = torch.linalg.qr(g.double(), mode="reduced")
    return q.numpy()


def covariance(x: np.ndarray) -> np.ndarray:
    xc = np.asarray(x, dtype=np.float64)
    xc = xc - xc.mean(axis=0)
    return xc.T @ xc / (len(xc) - 1)


def removed_variance(x: np.ndarray | None, basis: np.ndarray, cov: np.ndarray | None = None) -> float:
    """V_p = ||X_c B||_F^2 / (n - 1) = trace(B^T C B) (from ``cov`` when given)."""
    c = covariance(x) if cov is None else cov
    return float(np.trace(basis.T @ c @ basis)) if basis.shape[1] else 0.0


@dataclass
class PCControl:
    basis: np.ndarray   # (D, K) top-K principal directions
    alpha: float
    k: int
    target_variance: float     # V_p
    top_variance: float        # sum of the top-K eigenvalues


def variance_matched_alpha(v_p: float, eigenvalues: np.ndarray) -> tuple[float, int, float]:
    """(alpha, K, sum of the top K) for eigenvalues in any order: the smallest K whose top-K sum >= v_p."""
    lam = np.sort(np.asarray(eigenvalues, dtype=np.float64))[::-1]
    cum = np.cumsum(lam)
    if v_p <= 0:
        return 0.0, 0, 0.0
    k = int(np.searchsorted(cum, v_p * (1 - 1e-12)) + 1)
    k = min(k, len(lam))
    top = float(cum[k - 1])
    return float(1.0 - np.sqrt(max(0.0, 1.0 - v_p / top))), k, top


def variance_matched_pcs(x: np.ndarray | None, basis: np.ndarray, cov: np.ndarray | None = None,
                         device=None) -> PCControl:
    """The variance-matched top-K principal-component control of ``basis``, from the rows ``x`` or their
    covariance ``cov`` (the release uses the cell's INLP training rows); the eigendecomposition runs in
    float64 on ``device`` (default: the CPU)."""
    c = covariance(x) if cov is None else np.asarray(cov, dtype=np.float64)
    v_p = removed_variance(None, basis, c)
    lam_t, vec_t = torch.linalg.eigh(torch.as_tensor(c, device=torch.device(device or "cpu")))
    lam, vec = lam_t.cpu().numpy(), vec_t.cpu().numpy()
    order = np.argsort(lam)[::-1]
    lam, vec = lam[order], vec[:, order]
    alpha, k, top = variance_matched_alpha(v_p, lam)
    return PCControl(basis=vec[:, :k], alpha=alpha, k=k, target_variance=v_p, top_variance=top)


def total_variance(x: np.ndarray | None, cov: np.ndarray | None = None) -> float:
    c = covariance(x) if cov is None else cov
    return float(np.trace(c))
