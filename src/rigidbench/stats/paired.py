"""Paired model comparisons on matched examples (paper appendix C, "Paired Model Comparisons").

Every model is scored on the same examples, so a comparison is made per example before
averaging. Example k counts for a pair only when both models have a finite score on it.
Probability of improvement: w_k = 1 if model i is better on example k, 0.5 for a tie, else 0;
PoI(i, j) = mean_k w_k with a paired percentile bootstrap of the matched w_k.
All-pairs matrices bootstrap the pairs i < j in one vectorised call and fill j > i by symmetry
(PoI(j, i) = 1 - PoI(i, j); diff(j, i) = -diff(i, j)), which is what bootstrapping the
reversed pair with the same seed gives.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from rigidbench.stats.bootstrap import bootstrap_ci


@dataclass(frozen=True)
class PairwiseMatrix:
    """Row model i versus column model j; every field (M, M). `significant`: interval excludes `null_value`."""

    estimate: np.ndarray
    lo: np.ndarray
    hi: np.ndarray
    n_matched: np.ndarray
    significant: np.ndarray
    null_value: float


def improvement_indicators(a, b, higher_is_better: bool) -> np.ndarray:
    """a, b: (..., N) float scores. Returns (..., N) float64 w in {0, 0.5, 1}, NaN where either is non-finite."""
    a_arr = np.asarray(a, dtype=np.float64)
    b_arr = np.asarray(b, dtype=np.float64)
    if a_arr.shape != b_arr.shape:
        raise ValueError(f"scores must be matched example by example, got shapes {a_arr.shape} and {b_arr.shape}")
    better = a_arr > b_arr if higher_is_better else a_arr < b_arr
    w = np.where(better, 1.0, np.where(a_arr == b_arr, 0.5, 0.0))
    w[~(np.isfinite(a_arr) & np.isfinite(b_arr))] = np.nan
    return w


def probability_of_improvement(
    a, b, higher_is_better: bool, n_resamples: int = 20000, confidence: float = 0.95, seed: int = 0
) -> tuple[float, float, float]:
    """a, b: (N,) float scores of two models on the same examples. Returns (PoI of a over b, lo, hi)."""
    a_arr = np.asarray(a, dtype=np.float64)
    if a_arr.ndim != 1:
        raise ValueError(f"probability_of_improvement needs (N,) arrays, got shape {a_arr.shape}")
    return bootstrap_ci(improvement_indicators(a_arr, b, higher_is_better), n_resamples, confidence, seed)


def pairwise_matrix(
    pair_stats: np.ndarray,
    n_matched_pairs: np.ndarray,
    n_finite: np.ndarray,
    null_value: float,
    n_resamples: int,
    confidence: float,
    seed: int,
) -> PairwiseMatrix:
    """pair_stats: (P, N) per-example statistic for pairs i < j (NaN unmatched). Returns the full (M, M) matrix."""
    m = len(n_finite)
    iu, ju = np.triu_indices(m, k=1)
    est_p, lo_p, hi_p = bootstrap_ci(pair_stats, n_resamples, confidence, seed)
    estimate = np.full((m, m), np.nan)
    lo = np.full((m, m), np.nan)
    hi = np.full((m, m), np.nan)
    estimate[iu, ju], lo[iu, ju], hi[iu, ju] = est_p, lo_p, hi_p
    # Reflecting about the null value: the reversed pair's statistic is 2*null - w per example.
    estimate[ju, iu] = 2 * null_value - est_p
    lo[ju, iu] = 2 * null_value - hi_p
    hi[ju, iu] = 2 * null_value - lo_p
    diag = np.arange(m)
    estimate[diag, diag] = np.where(n_finite >= 1, null_value, np.nan)
    lo[diag, diag] = np.where(n_finite >= 2, null_value, np.nan)
    hi[diag, diag] = lo[diag, diag]
    n_matched = np.zeros((m, m), dtype=np.int64)
    n_matched[iu, ju] = n_matched_pairs
    n_matched[ju, iu] = n_matched_pairs
    n_matched[diag, diag] = n_finite
    with np.errstate(invalid="ignore"):
        significant = (lo > null_value) | (hi < null_value)
    return PairwiseMatrix(estimate, lo, hi, n_matched, significant, float(null_value))


def _check_models(values) -> np.ndarray:
    """values: (M, N) scores of M models on N shared examples. Returns it as float64, or raises ValueError."""
    arr = np.asarray(values, dtype=np.float64)
    if arr.ndim != 2:
        raise ValueError(f"expected (models, examples) scores with shape (M, N), got shape {arr.shape}")
    return arr


def paired_difference_matrix(
    values, n_resamples: int = 20000, confidence: float = 0.95, seed: int = 0
) -> PairwiseMatrix:
    """values: (M, N) float scores. Returns PairwiseMatrix of mean(row - column) over matched examples, null 0."""
    arr = _check_models(values)
    iu, ju = np.triu_indices(arr.shape[0], k=1)
    # Non-finite in either model makes the difference non-finite, so the pair drops that example.
    with np.errstate(invalid="ignore"):
        diffs = arr[iu] - arr[ju]
    return pairwise_matrix(
        diffs, np.isfinite(diffs).sum(axis=1), np.isfinite(arr).sum(axis=1), 0.0, n_resamples, confidence, seed
    )


def probability_of_improvement_matrix(
    values, higher_is_better: bool, n_resamples: int = 20000, confidence: float = 0.95, seed: int = 0
) -> PairwiseMatrix:
    """values: (M, N) float scores. Returns PairwiseMatrix of PoI(row model over column model), null 0.5."""
    arr = _check_models(values)
    iu, ju = np.triu_indices(arr.shape[0], k=1)
    w = improvement_indicators(arr[iu], arr[ju], higher_is_better)
    return pairwise_matrix(
        w, np.isfinite(w).sum(axis=1), np.isfinite(arr).sum(axis=1), 0.5, n_resamples, confidence, seed
    )


__all__ = [
    "PairwiseMatrix",
    "improvement_indicators",
    "paired_difference_matrix",
    "probability_of_improvement",
    "probability_of_improvement_matrix",
]
