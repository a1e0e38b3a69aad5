"""Iterative nullspace projection (INLP) of position and its two controls (paper appendix E,
"Position-Aligned Interventions"). Pure numpy.

INLP: rows split 80/20 (seed 0). Repeat: project the training activations onto the orthogonal
complement of the basis so far, fit ridge regression (coefficient 0.05, centred, closed form) to the
target, and stop when its training R^2 < 0.05 (that regressor is not added) or after 30 iterations;
otherwise add the regressor's row space (its k weight vectors) to the basis, re-orthonormalised.

Controls: a random orthonormal basis of the same rank (seed 0), and the variance-matched top-K
principal components: V_p = ||X_c B_p||_F^2 / (n - 1), K the smallest with sum_{i<=K} lambda_i >= V_p,
alpha = 1 - sqrt(1 - V_p / sum_{i<=K} lambda_i), since removing alpha of the top-K subspace removes
alpha (2 - alpha) sum_{i<=K} lambda_i variance.
The intervention applies h - alpha (h B) B^T (alpha = 1 for INLP and random).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .fit import r2_score


@dataclass
class INLPResult:
    basis: np.ndarray                       # (D, r) orthonormal columns
    train_r2: list[float] = field(default_factory=list)    # every fitted regressor's training R^2
    heldout_r2: list[float] = field(default_factory=list)  # ... and on the held-out 20%
    stopped: str = ""                       # "r2" or "iterations"

    @property
    def rank(self) -> int:
        return int(self.basis.shape[1])


def ridge_fit(x: np.ndarray, y: np.ndarray, lam: float = 0.05) -> tuple[np.ndarray, np.ndarray]:
    """Centred ridge regression: (W (D, k), b (k,)) minimising ||x W + b - y||^2 + lam ||W||^2."""
    xm, ym = x.mean(axis=0), y.mean(axis=0)
    xc, yc = x - xm, y - ym
    d = x.shape[1]
    if len(x) < d:  # the dual form is cheaper
        w = xc.T @ np.linalg.solve(xc @ xc.T + lam * np.eye(len(x)), yc)
    else:
        w = np.linalg.solve(xc.T @ xc + lam * np.eye(d), xc.T @ yc)
    return w, ym - xm @ w


def project_out(x: np.ndarray, basis: np.ndarray, alpha: float = 1.0) -> np.ndarray:
    """x - alpha (x B) B^T."""
    if basis.shape[1] == 0:
        return x
    return x - alpha * (x @ basis) @ basis.T


def _extend(basis: np.ndarray, directions: np.ndarray, tol: float = 1e-8) -> np.ndarray:
    """Orthonormal basis of span(basis, directions) (directions (D, k)), dropping dependent ones."""
    new = directions - basis @ (basis.T @ directions) if basis.shape[1] else directions.copy()
    q, r = np.linalg.qr(new)
    keep = np.abs(np.diag(r)) > tol * max(1.0, float(np.abs(r).max()))
    q = q[:, keep]
    q = q - basis @ (basis.T @ q) if basis.shape[1] else q  # one more pass for numerical orthogonality
    q, _ = np.linalg.qr(q)
    return np.concatenate([basis, q], axis=1)


def split_rows(n: int, train_fraction: float = 0.8, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    order = np.random.default_rng(seed).permutation(n)
    cut = int(round(train_fraction * n))
    return np.sort(order[:cut]), np.sort(order[cut:])


def inlp(x: np.ndarray, y: np.ndarray, ridge: float = 0.05, min_r2: float = 0.05, max_iter: int = 30,
         train_fraction: float = 0.8, seed: int = 0) -> INLPResult:
    """INLP basis of the target ``y`` (n, k) in the activations ``x`` (n, D)."""
    x = np.asarray(x, dtype=np.float64)
    y = np.asarray(y, dtype=np.float64).reshape(len(y), -1)
    tr, ho = split_rows(len(x), train_fraction, seed)
    basis = np.zeros((x.shape[1], 0))
    result = INLPResult(basis=basis, stopped="iterations")
    for _ in range(max_iter):
        xt = project_out(x[tr], basis)
        w, b = ridge_fit(xt, y[tr], ridge)
        r2 = r2_score(y[tr], xt @ w + b)
        result.train_r2.append(r2)
        result.heldout_r2.append(r2_score(y[ho], project_out(x[ho], basis) @ w + b) if len(ho) > 1 else float("nan"))
        if not r2 >= min_r2:  # also stops on NaN (a constant target)
            result.stopped = "r2"
            break
        basis = _extend(basis, w)
    result.basis = basis
    return result


def random_orthonormal(d: int, rank: int, seed: int = 0) -> np.ndarray:
    """(d, rank) random orthonormal basis (QR of a Gaussian matrix)."""
    if rank == 0:
        return np.zeros((d, 0))
    q, r = np.linalg.qr(np.random.default_rng(seed).standard_normal((d, rank)))
    return q * np.sign(np.diag(r))


def removed_variance(x: np.ndarray, basis: np.ndarray) -> float:
    """V_p = ||X_c B||_F^2 / (n - 1)."""
    xc = x - x.mean(axis=0)
    return float(np.sum((xc @ basis) ** 2) / (len(x) - 1))


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


def variance_matched_pcs(x: np.ndarray, basis: np.ndarray) -> PCControl:
    """The variance-matched top-K principal-component control of the basis ``basis``."""
    x = np.asarray(x, dtype=np.float64)
    v_p = removed_variance(x, basis)
    xc = x - x.mean(axis=0)
    cov = xc.T @ xc / (len(x) - 1)
    lam, vec = np.linalg.eigh(cov)
    order = np.argsort(lam)[::-1]
    lam, vec = lam[order], vec[:, order]
    alpha, k, top = variance_matched_alpha(v_p, lam)
    return PCControl(basis=vec[:, :k], alpha=alpha, k=k, target_variance=v_p, top_variance=top)


def total_variance(x: np.ndarray) -> float:
    xc = x - x.mean(axis=0)
    return float(np.sum(xc ** 2) / (len(x) - 1))
