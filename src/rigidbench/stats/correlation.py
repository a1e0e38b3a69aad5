"""Correlation of two metrics across model means (paper section 4, "Model Comparison").

The bootstrap resamples MODELS, not examples: resample b draws M model indices with replacement
from ``np.random.default_rng(seed).integers(0, M, size=(n_resamples, M))``. A resample in which
either metric is constant (for example one model drawn M times) has no defined correlation; it is
dropped from both intervals and counted in ``n_degenerate``.
"""

from __future__ import annotations

import logging

import numpy as np

from .bootstrap import check_options

logger = logging.getLogger(__name__)

# Resamples per chunk; the Spearman ranks use a (chunk, M, M) comparison array.
_CHUNK_RESAMPLES = 4096


def average_ranks(x: np.ndarray) -> np.ndarray:
    """x: (B, M) float. Returns (B, M) float64 1-based ranks within each row, ties given their average rank."""
    less = (x[:, None, :] < x[:, :, None]).sum(axis=2)
    equal = (x[:, None, :] == x[:, :, None]).sum(axis=2)
    return less + (equal + 1) / 2.0


def pearson_rows(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """x, y: (B, M) float, neither constant within a row. Returns (B,) float64 Pearson r per row."""
    xc = x - x.mean(axis=1, keepdims=True)
    yc = y - y.mean(axis=1, keepdims=True)
    r = (xc * yc).sum(axis=1) / np.sqrt((xc * xc).sum(axis=1) * (yc * yc).sum(axis=1))
    return np.clip(r, -1.0, 1.0)


def _constant_rows(x: np.ndarray) -> np.ndarray:
    """x: (B, M). Returns (B,) bool, True where every entry of the row equals its first."""
    return np.all(x == x[:, :1], axis=1)


def correlation_across_models(
    x, y, n_resamples: int = 20000, confidence: float = 0.95, seed: int = 0
) -> dict:
    """x, y: (M,) float model means on two metrics. Returns dict of pearson, spearman, their (lo, hi) CIs and counts."""
    check_options(n_resamples, confidence)
    x_arr = np.asarray(x, dtype=np.float64)
    y_arr = np.asarray(y, dtype=np.float64)
    if x_arr.ndim != 1 or x_arr.shape != y_arr.shape:
        raise ValueError(f"need two (M,) arrays of model means, got shapes {x_arr.shape} and {y_arr.shape}")
    keep = np.isfinite(x_arr) & np.isfinite(y_arr)
    if not keep.all():
        logger.warning("dropping %d model(s) with a non-finite mean from the correlation", int((~keep).sum()))
    x_arr, y_arr = x_arr[keep], y_arr[keep]
    m = len(x_arr)
    result = {
        "pearson": float("nan"),
        "spearman": float("nan"),
        "pearson_ci": (float("nan"), float("nan")),
        "spearman_ci": (float("nan"), float("nan")),
        "n_models": m,
        "n_resamples": int(n_resamples),
        "n_degenerate": 0,
    }
    if m < 2 or _constant_rows(x_arr[None])[0] or _constant_rows(y_arr[None])[0]:
        logger.warning("correlation undefined for %d model(s) or a constant metric; returning NaN", m)
        return result
    result["pearson"] = float(pearson_rows(x_arr[None], y_arr[None])[0])
    result["spearman"] = float(pearson_rows(average_ranks(x_arr[None]), average_ranks(y_arr[None]))[0])

    rng = np.random.default_rng(seed)
    pearson_b, spearman_b = [], []
    n_degenerate = 0
    for start in range(0, int(n_resamples), _CHUNK_RESAMPLES):
        b = min(_CHUNK_RESAMPLES, int(n_resamples) - start)
        idx = rng.integers(0, m, size=(b, m))
        xs, ys = x_arr[idx], y_arr[idx]
        ok = ~(_constant_rows(xs) | _constant_rows(ys))
        n_degenerate += int(b - ok.sum())
        xs, ys = xs[ok], ys[ok]
        pearson_b.append(pearson_rows(xs, ys))
        spearman_b.append(pearson_rows(average_ranks(xs), average_ranks(ys)))
    result["n_degenerate"] = n_degenerate
    if n_degenerate:
        logger.debug("dropped %d of %d degenerate model resamples", n_degenerate, n_resamples)
    pearson_b = np.concatenate(pearson_b)
    spearman_b = np.concatenate(spearman_b)
    if len(pearson_b) == 0:
        return result
    alpha = 1.0 - confidence
    q = [alpha / 2.0, 1.0 - alpha / 2.0]
    result["pearson_ci"] = tuple(float(v) for v in np.quantile(pearson_b, q))
    result["spearman_ci"] = tuple(float(v) for v in np.quantile(spearman_b, q))
    return result
