"""Percentile bootstrap over evaluation examples (paper appendix C, "Uncertainty Across Metrics").

The example is the resampling unit. Every row (one model on one metric, or one matched pair)
bootstraps its own finite examples. Rows with the same number ``n`` of finite examples share one
index matrix, and that matrix is always the one drawn by::

    np.random.default_rng(seed).integers(0, n, size=(n_resamples, n), dtype=np.int32)

(drawn in row chunks from that one generator, which gives the same stream), so a row's interval
does not depend on which other rows are computed with it. Resampled means are computed with
the multinomial-counts trick, ``counts (B, n) @ deviations (n, R) / n``, in bounded chunks.
"""

from __future__ import annotations

import logging

import numpy as np

logger = logging.getLogger(__name__)

# Largest resample chunk, in index-matrix elements (B_chunk * n); bounds peak memory to ~50 MB.
MAX_CHUNK_ELEMENTS = 1 << 21


def check_options(n_resamples: int, confidence: float) -> None:
    """Validate bootstrap options; raises ValueError naming the bad argument."""
    if int(n_resamples) != n_resamples or n_resamples < 1:
        raise ValueError(f"n_resamples must be a positive integer, got {n_resamples!r}")
    if not 0.0 < confidence < 1.0:
        raise ValueError(f"confidence must lie strictly between 0 and 1, got {confidence!r}")


def _resample_counts(n: int, n_resamples: int, seed: int, chunk_rows: int):
    """Yield counts (b, n) float64 of how often each example is drawn, b rows per chunk."""
    rng = np.random.default_rng(seed)
    for start in range(0, n_resamples, chunk_rows):
        b = min(chunk_rows, n_resamples - start)
        idx = rng.integers(0, n, size=(b, n), dtype=np.int32)
        flat = idx + (np.arange(b, dtype=np.int64) * n)[:, None]
        yield np.bincount(flat.ravel(), minlength=b * n).reshape(b, n).astype(np.float64)


def resampled_row_means(
    deviations: np.ndarray, n_resamples: int, seed: int, chunk_elements: int
) -> np.ndarray:
    """deviations: (R, n) float64, finite. Returns (n_resamples, R) float64 resampled means."""
    n_rows, n = deviations.shape
    chunk_rows = max(1, min(n_resamples, chunk_elements // n))
    out = np.empty((n_resamples, n_rows), dtype=np.float64)
    dev_t = np.ascontiguousarray(deviations.T)
    start = 0
    for counts in _resample_counts(n, n_resamples, seed, chunk_rows):
        out[start : start + len(counts)] = counts @ dev_t
        start += len(counts)
    out /= n
    return out


def _bootstrap_rows(
    values: np.ndarray, n_resamples: int, confidence: float, seed: int, chunk_elements: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """values: (R, N) float. Returns mean, lo, hi, each (R,) float64; NaN interval if < 2 finite."""
    finite = np.isfinite(values)
    n_finite = finite.sum(axis=1)
    n_rows = values.shape[0]
    mean = np.full(n_rows, np.nan)
    lo = np.full(n_rows, np.nan)
    hi = np.full(n_rows, np.nan)
    alpha = 1.0 - confidence
    for n in np.unique(n_finite):
        rows = np.flatnonzero(n_finite == n)
        if n == 0:
            continue
        compact = values[rows][finite[rows]].reshape(len(rows), int(n)).astype(np.float64)
        # Shift by one data value per row: constant rows then resample to exactly that value,
        # and the sums avoid cancellation when the values sit far from zero.
        center = compact[:, :1]
        deviations = compact - center
        mean[rows] = center[:, 0] + deviations.mean(axis=1)
        if n < 2:
            logger.debug("%d row(s) have a single finite example; interval left NaN", len(rows))
            continue
        means = resampled_row_means(deviations, n_resamples, seed, chunk_elements)
        q = np.quantile(means, [alpha / 2.0, 1.0 - alpha / 2.0], axis=0)
        lo[rows] = center[:, 0] + q[0]
        hi[rows] = center[:, 0] + q[1]
    return mean, lo, hi


def unpack_rows(mean: np.ndarray, lo: np.ndarray, hi: np.ndarray, shape: tuple[int, ...]):
    """Reshape flat row results to `shape`; 0-d results become Python floats."""
    if shape == ():
        return float(mean[0]), float(lo[0]), float(hi[0])
    return mean.reshape(shape), lo.reshape(shape), hi.reshape(shape)


def bootstrap_ci(
    values,
    n_resamples: int = 20000,
    confidence: float = 0.95,
    seed: int = 0,
    *,
    chunk_elements: int = MAX_CHUNK_ELEMENTS,
):
    """values: (..., N) float per-example scores. Returns (mean, lo, hi): floats for (N,), else (...) float64 arrays."""
    check_options(n_resamples, confidence)
    arr = np.asarray(values, dtype=np.float64)
    if arr.ndim == 0:
        raise ValueError("bootstrap_ci needs per-example values with shape (..., N), got a scalar")
    shape = arr.shape[:-1]
    rows = arr.reshape(int(np.prod(shape, dtype=np.int64)), arr.shape[-1])
    mean, lo, hi = _bootstrap_rows(rows, int(n_resamples), confidence, seed, int(chunk_elements))
    return unpack_rows(mean, lo, hi, shape)


def paired_difference(
    a, b, n_resamples: int = 20000, confidence: float = 0.95, seed: int = 0
) -> tuple[float, float, float]:
    """a, b: (N,) float scores on the same examples. Returns (mean of a-b, lo, hi) over examples finite in both."""
    a_arr = np.asarray(a, dtype=np.float64)
    b_arr = np.asarray(b, dtype=np.float64)
    if a_arr.ndim != 1 or a_arr.shape != b_arr.shape:
        raise ValueError(
            f"paired_difference needs two (N,) arrays over the same examples, got {a_arr.shape} and {b_arr.shape}"
        )
    both = np.isfinite(a_arr) & np.isfinite(b_arr)
    diff = np.where(both, a_arr - b_arr, np.nan)
    return bootstrap_ci(diff, n_resamples, confidence, seed)
