"""Statistics over several generations (samples) per example; formulas in docs/statistics.md.

Scores arrive as ``(..., E, K)`` float arrays: E examples, K samples each. Missing-value rule,
the per-example rule of ``bootstrap_ci`` carried one level down: a non-finite sample is omitted, an
example's mean is the mean of its K_e finite samples, and an example with no finite sample is
omitted from every estimate. Every example that remains weighs the same, whatever its K_e.

Headline: the mean over examples of per-example sample means, with a percentile bootstrap.
Two resampling schemes are implemented:

- ``"examples"`` (the default and the one reported): resample examples with replacement, each
  keeping all its samples. Its stream is ``bootstrap_ci``'s on the per-example means, so with
  K = 1 every number equals today's single-sample numbers exactly.
- ``"both"``: resample examples, then, inside each drawn example, resample its K_e finite samples
  with replacement. It counts the within-example variance twice (once through the spread of the
  per-example means, once through the second-level draws) and overstates the variance; it is
  kept for the coverage comparison in docs/statistics.md. Streams: example indices exactly as
  ``bootstrap_ci`` draws them from ``default_rng(seed)``; sample positions
  ``floor(u * K_e)`` with ``u = default_rng([seed, 1]).random((b, E, K))`` per chunk of b resamples.

Comparisons (paired difference and probability of improvement) use the ``"examples"`` scheme.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from rigidbench.stats.bootstrap import (
    MAX_CHUNK_ELEMENTS,
    bootstrap_ci,
    check_options,
    resampled_row_means,
    unpack_rows,
)
from rigidbench.stats.paired import PairwiseMatrix, improvement_indicators, paired_difference_matrix, pairwise_matrix

SCHEMES = ("examples", "both")


def _check_scores(scores, name: str = "scores") -> np.ndarray:
    """scores: (..., E, K) array-like. Returns float64 array, or raises ValueError naming the shape."""
    arr = np.asarray(scores, dtype=np.float64)
    if arr.ndim < 2:
        raise ValueError(
            f"{name} must have shape (..., examples, samples), got shape {arr.shape}; "
            "for one sample per example pass values[:, None]"
        )
    return arr


def _check_one(scores, what: str) -> np.ndarray:
    """scores: (E, K) for one model and measurement. Returns float64, or raises ValueError naming `what`."""
    arr = _check_scores(scores)
    if arr.ndim != 2:
        raise ValueError(f"{what} takes one measurement with shape (E, K), got {arr.shape}")
    return arr


def _check_scheme(scheme: str) -> None:
    if scheme not in SCHEMES:
        raise ValueError(f"scheme must be one of {SCHEMES}, got {scheme!r}")


def per_example_means(scores) -> np.ndarray:
    """scores: (..., E, K) float. Returns (..., E) float64 mean of finite samples, NaN where an example has none."""
    arr = _check_scores(scores)
    finite = np.isfinite(arr)
    k_e = finite.sum(axis=-1)
    total = np.where(finite, arr, 0.0).sum(axis=-1)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(k_e > 0, total / k_e, np.nan)


def _compact_rows(arr: np.ndarray, rows: np.ndarray, has: np.ndarray, n: int):
    """arr: (R, E, K). Returns values (r, n, K) with each example's finite samples first, and k_e (r, n)."""
    sub = arr[rows]
    finite = np.isfinite(sub)
    order = np.argsort(~finite, axis=-1, kind="stable")
    sub = np.take_along_axis(sub, order, axis=-1)
    finite = np.take_along_axis(finite, order, axis=-1)
    keep = has[rows]
    k = arr.shape[-1]
    values = sub[keep].reshape(len(rows), n, k)
    k_e = finite[keep].reshape(len(rows), n, k).sum(axis=-1)
    return np.where(np.isfinite(values), values, 0.0), k_e


def _two_level_means(
    deviations: np.ndarray, k_e: np.ndarray, n_resamples: int, seed: int, chunk_elements: int
) -> np.ndarray:
    """deviations: (R, n, K), finite, zero beyond k_e; k_e: (R, n) >= 1. Returns (n_resamples, R) resampled means."""
    n_rows, n, k = deviations.shape
    chunk_rows = max(1, min(n_resamples, chunk_elements // (n * k)))
    rng_examples = np.random.default_rng(seed)
    rng_samples = np.random.default_rng([seed, 1])
    out = np.empty((n_resamples, n_rows), dtype=np.float64)
    slot = np.arange(k)
    for start in range(0, n_resamples, chunk_rows):
        b = min(chunk_rows, n_resamples - start)
        idx = rng_examples.integers(0, n, size=(b, n), dtype=np.int32)
        u = rng_samples.random(size=(b, n, k))
        for r in range(n_rows):
            drawn_k = k_e[r][idx][..., None]  # (b, n, 1)
            pos = np.minimum((u * drawn_k).astype(np.int64), drawn_k - 1)
            vals = deviations[r][idx[..., None], pos]
            sums = np.where(slot < drawn_k, vals, 0.0).sum(axis=-1)
            out[start : start + b, r] = (sums / drawn_k[..., 0]).mean(axis=-1)
    return out


def _resampled_rows(
    arr: np.ndarray, scheme: str, n_resamples: int, seed: int, chunk_elements: int
):
    """arr: (R, E, K). Per group of rows with n examples: yields rows, n, center (r,), mean deviation (r,), replicates (B, r)."""
    finite = np.isfinite(arr)
    has = finite.any(axis=-1)
    n_examples = has.sum(axis=-1)
    for n in np.unique(n_examples):
        rows = np.flatnonzero(n_examples == n)
        if n == 0:
            continue
        values, k_e = _compact_rows(arr, rows, has, int(n))
        m_e = per_example_means(arr[rows])[has[rows]].reshape(len(rows), int(n))
        # Shift by the first example's mean, as bootstrap_ci does: same point estimate, no cancellation.
        center = m_e[:, 0].copy()
        if scheme == "examples":
            means = resampled_row_means(m_e - center[:, None], n_resamples, seed, chunk_elements)
        else:
            in_range = np.arange(arr.shape[-1]) < k_e[..., None]
            deviations = np.where(in_range, values - center[:, None, None], 0.0)
            means = _two_level_means(deviations, k_e, n_resamples, seed, chunk_elements)
        yield rows, int(n), center, (m_e - center[:, None]).mean(axis=-1), means


def resampled_means(
    scores, scheme: str = "examples", n_resamples: int = 20000, seed: int = 0, *, chunk_elements: int = MAX_CHUNK_ELEMENTS
) -> np.ndarray:
    """scores: (E, K) float. Returns (n_resamples,) float64 bootstrap replicates of the headline mean (NaN if no example)."""
    check_options(n_resamples, 0.5)
    _check_scheme(scheme)
    arr = _check_one(scores, "resampled_means")
    out = np.full(int(n_resamples), np.nan)
    for _, _, center, _, means in _resampled_rows(arr[None], scheme, int(n_resamples), seed, int(chunk_elements)):
        out = center[0] + means[:, 0]
    return out


def hierarchical_bootstrap_ci(
    scores,
    scheme: str = "examples",
    n_resamples: int = 20000,
    confidence: float = 0.95,
    seed: int = 0,
    *,
    chunk_elements: int = MAX_CHUNK_ELEMENTS,
):
    """scores: (..., E, K) float. Returns (mean of per-example means, lo, hi): floats for (E, K), else (...) arrays.

    The interval is the percentile interval of the resampled headline under `scheme`; it is NaN when
    fewer than two examples have a finite sample. With scheme="examples" the result equals
    ``bootstrap_ci(per_example_means(scores), ...)`` exactly.
    """
    check_options(n_resamples, confidence)
    _check_scheme(scheme)
    arr = _check_scores(scores)
    shape = arr.shape[:-2]
    if scheme == "examples":
        return bootstrap_ci(per_example_means(arr), n_resamples, confidence, seed, chunk_elements=chunk_elements)
    rows_arr = arr.reshape(int(np.prod(shape, dtype=np.int64)), *arr.shape[-2:])
    n_rows = rows_arr.shape[0]
    mean, lo, hi = np.full(n_rows, np.nan), np.full(n_rows, np.nan), np.full(n_rows, np.nan)
    alpha = 1.0 - confidence
    for rows, n, center, mean_dev, means in _resampled_rows(rows_arr, scheme, int(n_resamples), seed, int(chunk_elements)):
        mean[rows] = center + mean_dev
        if n < 2:
            continue
        q = np.quantile(means, [alpha / 2.0, 1.0 - alpha / 2.0], axis=0)
        lo[rows] = center + q[0]
        hi[rows] = center + q[1]
    return unpack_rows(mean, lo, hi, shape)


def sample_index_means(scores) -> np.ndarray:
    """scores: (E, K) float. Returns (K,) float64: for each sample index k, the mean over examples with a finite sample k."""
    arr = _check_one(scores, "sample_index_means")
    finite = np.isfinite(arr)
    count = finite.sum(axis=-2)
    total = np.where(finite, arr, 0.0).sum(axis=-2)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(count > 0, total / count, np.nan)


def seed_spread(scores) -> float:
    """scores: (E, K) float. Returns the std (ddof=1) over sample indices of the whole-set mean of sample k; NaN if < 2."""
    col = sample_index_means(scores)
    col = col[np.isfinite(col)]
    return float(np.std(col, ddof=1)) if len(col) >= 2 else float("nan")


def within_example_std(scores) -> float:
    """scores: (E, K) float. Returns sqrt(sum_e sum_k (y_ek - m_e)^2 / sum_e (K_e - 1)) over examples with K_e >= 2; NaN if none."""
    arr = _check_one(scores, "within_example_std")
    finite = np.isfinite(arr)
    k_e = finite.sum(axis=-1)
    m_e = per_example_means(arr)
    resid = np.where(finite, arr - np.where(k_e > 0, m_e, 0.0)[..., None], 0.0)
    dof = np.maximum(k_e - 1, 0).sum()
    return float(np.sqrt((resid**2).sum() / dof)) if dof > 0 else float("nan")


def best_of_k_per_example(scores, higher_is_better: bool) -> np.ndarray:
    """scores: (..., E, K) float. Returns (..., E) float64 best finite sample per example (max or min), NaN if none."""
    arr = _check_scores(scores)
    finite = np.isfinite(arr)
    fill = -np.inf if higher_is_better else np.inf
    masked = np.where(finite, arr, fill)
    best = masked.max(axis=-1) if higher_is_better else masked.min(axis=-1)
    return np.where(finite.any(axis=-1), best, np.nan)


@dataclass(frozen=True)
class BestOfK:
    """Mean over examples of each example's best sample; optimistic by construction, never the headline."""

    label: str
    mean: float
    lo: float
    hi: float


@dataclass(frozen=True)
class SampleSummary:
    """One measurement of one model over (E, K) scores; `mean`, `lo`, `hi` are the headline and its interval."""

    mean: float
    lo: float
    hi: float
    scheme: str
    n_examples: int
    n_samples: int
    samples_per_example: int
    sample_index_means: tuple[float, ...]
    seed_spread: float
    within_example_std: float
    best_of_k: BestOfK


def summarize_samples(
    scores,
    higher_is_better: bool,
    n_resamples: int = 20000,
    confidence: float = 0.95,
    seed: int = 0,
    scheme: str = "examples",
) -> SampleSummary:
    """scores: (E, K) float for one model and measurement. Returns SampleSummary (headline, spreads, labelled best-of-K)."""
    arr = _check_one(scores, "summarize_samples")
    mean, lo, hi = hierarchical_bootstrap_ci(arr, scheme, n_resamples, confidence, seed)
    k = arr.shape[1]
    direction = "max" if higher_is_better else "min"
    best = bootstrap_ci(best_of_k_per_example(arr, higher_is_better), n_resamples, confidence, seed)
    label = f"best of {k} samples per example ({direction} over samples; optimistic, not the headline)"
    return SampleSummary(
        mean=mean,
        lo=lo,
        hi=hi,
        scheme=scheme,
        n_examples=int(np.isfinite(arr).any(axis=1).sum()),
        n_samples=int(np.isfinite(arr).sum()),
        samples_per_example=k,
        sample_index_means=tuple(float(v) for v in sample_index_means(arr)),
        seed_spread=seed_spread(arr),
        within_example_std=within_example_std(arr),
        best_of_k=BestOfK(label, *best),
    )


# ---------------------------------------------------------------- comparisons between two models


def check_pair(a, b) -> tuple[np.ndarray, np.ndarray]:
    """a: (..., E, K1), b: (..., E, K2) with equal leading shapes. Returns both as float64."""
    a_arr, b_arr = _check_scores(a, "a"), _check_scores(b, "b")
    if a_arr.shape[:-1] != b_arr.shape[:-1]:
        raise ValueError(
            f"models must be scored on the same examples: shapes {a_arr.shape} and {b_arr.shape} "
            "differ before the samples axis"
        )
    return a_arr, b_arr


def paired_example_differences(a, b) -> np.ndarray:
    """a: (..., E, K1), b: (..., E, K2) float. Returns (..., E) m_a - m_b of per-example means; NaN unless both have a sample."""
    a_arr, b_arr = check_pair(a, b)
    return per_example_means(a_arr) - per_example_means(b_arr)


def improvement_fractions(a, b, higher_is_better: bool) -> np.ndarray:
    """a: (..., E, K1), b: (..., E, K2) float. Returns (..., E) share of finite sample pairs (j, l) where a_j beats b_l (ties 1/2).

    NaN where either model has no finite sample of that example. With K1 = K2 = 1 this is
    ``improvement_indicators`` of the single samples.
    """
    a_arr, b_arr = check_pair(a, b)
    w = improvement_indicators(
        np.broadcast_to(a_arr[..., :, None], (*a_arr.shape, b_arr.shape[-1])),
        np.broadcast_to(b_arr[..., None, :], (*a_arr.shape, b_arr.shape[-1])),
        higher_is_better,
    )
    finite = np.isfinite(w)
    count = finite.sum(axis=(-2, -1))
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(count > 0, np.where(finite, w, 0.0).sum(axis=(-2, -1)) / count, np.nan)


def paired_difference_samples(a, b, n_resamples: int = 20000, confidence: float = 0.95, seed: int = 0):
    """a: (..., E, K1), b: (..., E, K2). Returns (mean over examples of m_a - m_b, lo, hi), the examples bootstrap."""
    return bootstrap_ci(paired_example_differences(a, b), n_resamples, confidence, seed)


def probability_of_improvement_samples(
    a, b, higher_is_better: bool, n_resamples: int = 20000, confidence: float = 0.95, seed: int = 0
):
    """a: (..., E, K1), b: (..., E, K2). Returns (PoI of a over b, lo, hi): mean of improvement_fractions, examples bootstrap."""
    return bootstrap_ci(improvement_fractions(a, b, higher_is_better), n_resamples, confidence, seed)


def _check_model_samples(models) -> list[np.ndarray]:
    """models: sequence of M (E, K_m) arrays on the same E examples."""
    arrs = [_check_scores(m, f"model {i}") for i, m in enumerate(models)]
    if any(a.ndim != 2 for a in arrs) or len({a.shape[0] for a in arrs}) > 1:
        raise ValueError(f"need M arrays of shape (E, K_m) on the same examples, got shapes {[a.shape for a in arrs]}")
    return arrs


def paired_difference_matrix_samples(
    models, n_resamples: int = 20000, confidence: float = 0.95, seed: int = 0
) -> PairwiseMatrix:
    """models: M arrays (E, K_m). Returns PairwiseMatrix of mean(m_row - m_col) over matched examples, null 0."""
    arrs = _check_model_samples(models)
    return paired_difference_matrix(np.stack([per_example_means(a) for a in arrs]), n_resamples, confidence, seed)


def probability_of_improvement_matrix_samples(
    models, higher_is_better: bool, n_resamples: int = 20000, confidence: float = 0.95, seed: int = 0
) -> PairwiseMatrix:
    """models: M arrays (E, K_m). Returns PairwiseMatrix of PoI(row over column) from improvement_fractions, null 0.5."""
    arrs = _check_model_samples(models)
    iu, ju = np.triu_indices(len(arrs), k=1)
    e = arrs[0].shape[0] if arrs else 0
    w = np.empty((len(iu), e))
    for p, (i, j) in enumerate(zip(iu, ju)):
        w[p] = improvement_fractions(arrs[i], arrs[j], higher_is_better)
    n_finite = np.array([np.isfinite(a).any(axis=1).sum() for a in arrs], dtype=np.int64)
    return pairwise_matrix(w, np.isfinite(w).sum(axis=1), n_finite, 0.5, n_resamples, confidence, seed)


__all__ = [
    "SCHEMES",
    "BestOfK",
    "SampleSummary",
    "best_of_k_per_example",
    "hierarchical_bootstrap_ci",
    "improvement_fractions",
    "paired_difference_matrix_samples",
    "paired_difference_samples",
    "paired_example_differences",
    "per_example_means",
    "probability_of_improvement_matrix_samples",
    "probability_of_improvement_samples",
    "resampled_means",
    "sample_index_means",
    "seed_spread",
    "summarize_samples",
    "within_example_std",
]
