"""Unit tests for rigidbench.stats.samples: statistics over K samples per example."""

from __future__ import annotations

import itertools
import math
import warnings

import numpy as np
import pytest

from rigidbench.stats import (
    bootstrap_ci,
    paired_difference,
    paired_difference_matrix,
    probability_of_improvement,
    probability_of_improvement_matrix,
)
from rigidbench.stats.samples import (
    best_of_k_per_example,
    hierarchical_bootstrap_ci,
    improvement_fractions,
    paired_difference_matrix_samples,
    paired_difference_samples,
    per_example_means,
    probability_of_improvement_matrix_samples,
    probability_of_improvement_samples,
    resampled_means,
    sample_index_means,
    seed_spread,
    summarize_samples,
    within_example_std,
)


def _dirty_vector(n: int, seed: int) -> np.ndarray:
    x = np.random.default_rng(seed).normal(2.0, 1.5, n)
    x[[3, 11]] = np.nan
    x[7] = np.inf
    return x


# ---------------------------------------------------------------- K = 1 is today's numbers


def test_k1_headline_and_interval_equal_bootstrap_ci_exactly():
    x = _dirty_vector(60, 0)
    for seed in (0, 5):
        today = bootstrap_ci(x, n_resamples=3000, seed=seed)
        assert hierarchical_bootstrap_ci(x[:, None], n_resamples=3000, seed=seed) == today
        s = summarize_samples(x[:, None], higher_is_better=False, n_resamples=3000, seed=seed)
        assert (s.mean, s.lo, s.hi) == today
        # With one sample the best sample is the sample: best-of-1 is the headline.
        assert (s.best_of_k.mean, s.best_of_k.lo, s.best_of_k.hi) == today
        assert s.n_examples == 57 and s.n_samples == 57 and math.isnan(s.seed_spread)
        assert math.isnan(s.within_example_std)
    # Batched rows too.
    rows = np.stack([x, _dirty_vector(60, 1)])
    for got, want in zip(hierarchical_bootstrap_ci(rows[..., None], n_resamples=500), bootstrap_ci(rows, n_resamples=500)):
        np.testing.assert_array_equal(got, want)


def test_k1_two_level_scheme_equals_examples_scheme():
    x = _dirty_vector(40, 2)
    both = hierarchical_bootstrap_ci(x[:, None], scheme="both", n_resamples=2000, seed=3)
    assert both == pytest.approx(bootstrap_ci(x, n_resamples=2000, seed=3), abs=1e-12)


@pytest.mark.parametrize("higher", [True, False])
def test_k1_comparisons_equal_todays_exactly(higher):
    rng = np.random.default_rng(9)
    a = np.round(rng.normal(size=50), 1)  # ties
    b = np.round(rng.normal(size=50), 1)
    a[4], b[9], b[12] = np.nan, np.inf, np.nan
    assert paired_difference_samples(a[:, None], b[:, None], n_resamples=2000, seed=1) == paired_difference(
        a, b, n_resamples=2000, seed=1
    )
    assert probability_of_improvement_samples(
        a[:, None], b[:, None], higher, n_resamples=2000, seed=1
    ) == probability_of_improvement(a, b, higher, n_resamples=2000, seed=1)
    c = rng.normal(size=50)
    models = np.stack([a, b, c])
    for got, want in [
        (paired_difference_matrix_samples(models[..., None], n_resamples=1000), paired_difference_matrix(models, 1000)),
        (
            probability_of_improvement_matrix_samples(models[..., None], higher, n_resamples=1000),
            probability_of_improvement_matrix(models, higher, 1000),
        ),
    ]:
        for field in ("estimate", "lo", "hi", "n_matched", "significant"):
            np.testing.assert_array_equal(getattr(got, field), getattr(want, field), err_msg=field)


# ---------------------------------------------------------------- estimators on hand-built cases

HAND = np.array(
    [
        [1.0, 3.0, np.nan],  # mean 2, residuals -1, 1
        [4.0, 4.0, 7.0],  # mean 5, residuals -1, -1, 2
        [np.nan, np.inf, np.nan],  # no finite sample: omitted
        [0.0, np.nan, 6.0],  # mean 3, residuals -3, 3
    ]
)


def test_per_example_means_and_headline_follow_the_missing_sample_rule():
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        means = per_example_means(HAND)
        mean, lo, hi = hierarchical_bootstrap_ci(HAND, n_resamples=500)
    np.testing.assert_array_equal(means[[0, 1, 3]], [2.0, 5.0, 3.0])
    assert np.isnan(means[2])
    # Every example weighs the same whatever its number of finite samples: (2 + 5 + 3) / 3, not 21 / 7.
    assert mean == pytest.approx(10.0 / 3.0, abs=1e-15)
    assert 2.0 <= lo <= mean <= hi <= 5.0


def test_seed_spread_and_within_example_std_by_hand():
    # Sample-index means: k=0 over (1, 4, 0) = 5/3; k=1 over (3, 4) = 7/2; k=2 over (7, 6) = 13/2.
    np.testing.assert_allclose(sample_index_means(HAND), [5 / 3, 7 / 2, 13 / 2], rtol=1e-15)
    assert seed_spread(HAND) == pytest.approx(np.std([5 / 3, 7 / 2, 13 / 2], ddof=1), rel=1e-14)
    # Pooled: squared residuals 2 + 6 + 18 = 26 over (1 + 2 + 1) degrees of freedom.
    assert within_example_std(HAND) == pytest.approx(math.sqrt(26 / 4), rel=1e-14)
    assert math.isnan(within_example_std(np.array([[1.0, np.nan], [2.0, np.nan]])))


def test_best_of_k_follows_direction_and_is_labelled_apart_from_the_headline():
    np.testing.assert_array_equal(best_of_k_per_example(HAND, True)[[0, 1, 3]], [3.0, 7.0, 6.0])
    np.testing.assert_array_equal(best_of_k_per_example(HAND, False)[[0, 1, 3]], [1.0, 4.0, 0.0])
    assert np.isnan(best_of_k_per_example(HAND, True)[2])
    lower = summarize_samples(HAND, higher_is_better=False, n_resamples=500)
    higher = summarize_samples(HAND, higher_is_better=True, n_resamples=500)
    assert lower.best_of_k.mean == pytest.approx(5 / 3) and higher.best_of_k.mean == pytest.approx(16 / 3)
    assert lower.mean == higher.mean == pytest.approx(10 / 3)
    assert "best of 3" in lower.best_of_k.label and "min" in lower.best_of_k.label
    assert "not the headline" in higher.best_of_k.label and "max" in higher.best_of_k.label
    assert higher.n_examples == 3 and higher.n_samples == 7 and higher.samples_per_example == 3


def test_improvement_fractions_count_all_finite_sample_pairs():
    a = np.array([[1.0, 3.0], [2.0, np.nan], [np.nan, np.nan]])
    b = np.array([[2.0, 2.0, 0.0], [2.0, 1.0, 5.0], [1.0, 1.0, 1.0]])
    # Example 0: 1 beats only 0; 3 beats all three -> 4 of 6. Example 1: 2 vs (2, 1, 5) -> (0.5 + 1 + 0) / 3.
    w = improvement_fractions(a, b, higher_is_better=True)
    np.testing.assert_allclose(w[:2], [4 / 6, 1.5 / 3], rtol=1e-15)
    assert np.isnan(w[2])
    np.testing.assert_allclose(improvement_fractions(b, a, True)[:2], 1 - w[:2], rtol=1e-15)
    np.testing.assert_allclose(improvement_fractions(a, b, False)[:2], [2 / 6, 1.5 / 3], rtol=1e-15)
    poi = probability_of_improvement_samples(a, b, True, n_resamples=500)
    assert poi[0] == pytest.approx((4 / 6 + 0.5) / 2)
    diff = paired_difference_samples(a, b, n_resamples=500)
    assert diff[0] == pytest.approx(((2 - 4 / 3) + (2 - 8 / 3)) / 2)


def test_pairwise_matrix_with_samples_matches_pair_calls_and_symmetry():
    rng = np.random.default_rng(3)
    models = [rng.normal(size=(30, 2)), rng.normal(0.4, 1, size=(30, 4)), np.round(rng.normal(size=(30, 1)), 1)]
    models[1][5] = np.nan
    res = probability_of_improvement_matrix_samples(models, higher_is_better=False, n_resamples=1500, seed=2)
    for i, j in [(0, 1), (1, 2), (2, 0)]:
        ref = probability_of_improvement_samples(models[i], models[j], False, n_resamples=1500, seed=2)
        assert (res.estimate[i, j], res.lo[i, j], res.hi[i, j]) == pytest.approx(ref, abs=1e-12)
    np.testing.assert_allclose(res.estimate + res.estimate.T, 1.0, atol=1e-12)
    assert res.n_matched[0, 1] == 29 and res.n_matched[1, 1] == 29 and res.n_matched[0, 2] == 30
    diff = paired_difference_matrix_samples(models, n_resamples=1500, seed=2)
    ref = paired_difference_samples(models[1], models[2], n_resamples=1500, seed=2)
    assert (diff.estimate[1, 2], diff.lo[1, 2], diff.hi[1, 2]) == pytest.approx(ref, abs=1e-12)


@pytest.mark.parametrize(
    "call",
    [
        lambda: hierarchical_bootstrap_ci(np.zeros(5)),
        lambda: hierarchical_bootstrap_ci(np.zeros((5, 2)), scheme="samples"),
        lambda: summarize_samples(np.zeros((2, 5, 2)), True),
        lambda: paired_difference_samples(np.zeros((5, 2)), np.zeros((6, 2))),
        lambda: probability_of_improvement_matrix_samples([np.zeros((5, 2)), np.zeros(5)], True),
    ],
)
def test_bad_shapes_and_schemes_raise_value_error(call):
    with pytest.raises(ValueError):
        call()


# ---------------------------------------------------------------- hierarchical bootstrap vs brute force

SMALL = np.array(
    [
        [0.0, np.nan, 1.0],  # K_e = 2
        [10.0, 20.0, 40.0],  # K_e = 3
        [np.nan, 100.0, np.nan],  # K_e = 1
        [np.nan, np.nan, np.nan],  # omitted
    ]
)


def _brute_force_replicates(scores: np.ndarray, scheme: str, n_resamples: int, seed: int) -> np.ndarray:
    """Explicit loops over the documented streams: example indices, then sample positions floor(u * K_e)."""
    examples = [row[np.isfinite(row)] for row in scores if np.isfinite(row).any()]
    n, k = len(examples), scores.shape[1]
    idx = np.random.default_rng(seed).integers(0, n, size=(n_resamples, n), dtype=np.int32)
    u = np.random.default_rng([seed, 1]).random(size=(n_resamples, n, k))
    out = []
    for b in range(n_resamples):
        total = 0.0
        for i in range(n):
            samples = examples[idx[b, i]]
            if scheme == "examples":
                total += samples.mean()
            else:
                total += np.mean([samples[int(u[b, i, j] * len(samples))] for j in range(len(samples))])
        out.append(total / n)
    return np.array(out)


@pytest.mark.parametrize("scheme", ["examples", "both"])
def test_replicates_equal_explicit_loops_over_the_documented_stream(scheme):
    reps = resampled_means(SMALL, scheme, n_resamples=300, seed=4)
    brute = _brute_force_replicates(SMALL, scheme, 300, 4)
    np.testing.assert_allclose(reps, brute, rtol=0, atol=1e-12)
    mean, lo, hi = hierarchical_bootstrap_ci(SMALL, scheme, n_resamples=300, confidence=0.9, seed=4)
    assert mean == pytest.approx((0.5 + 70 / 3 + 100) / 3, abs=1e-12)
    np.testing.assert_allclose([lo, hi], np.quantile(brute, [0.05, 0.95]), rtol=0, atol=1e-12)
    # Chunking the resamples leaves the stream, hence the replicates, unchanged.
    chunked = resampled_means(SMALL, scheme, n_resamples=300, seed=4, chunk_elements=3 * 3 * 7)
    np.testing.assert_allclose(chunked, reps, rtol=0, atol=1e-12)


def _exact_bootstrap_distribution(scores: np.ndarray, scheme: str) -> dict[float, float]:
    """Enumerate every equally likely resampling outcome; returns value -> probability of the headline."""
    examples = [row[np.isfinite(row)] for row in scores if np.isfinite(row).any()]
    n = len(examples)
    # Outcomes for one drawn example: its possible resampled means, each with its probability.
    per_draw = []
    for samples in examples:
        if scheme == "examples":
            per_draw.append([(samples.mean(), 1.0)])
        else:
            k = len(samples)
            per_draw.append([(np.mean(c), k**-k) for c in itertools.product(samples, repeat=k)])
    dist: dict[float, float] = {}
    for drawn in itertools.product(range(n), repeat=n):
        for combo in itertools.product(*(per_draw[e] for e in drawn)):
            value = round(sum(v for v, _ in combo) / n, 9)
            dist[value] = dist.get(value, 0.0) + n**-n * math.prod(p for _, p in combo)
    return dist


@pytest.mark.parametrize("scheme", ["examples", "both"])
def test_replicates_follow_the_enumerated_bootstrap_distribution(scheme):
    exact = _exact_bootstrap_distribution(SMALL, scheme)
    assert sum(exact.values()) == pytest.approx(1.0, abs=1e-12)
    n_res = 20000
    reps = np.round(resampled_means(SMALL, scheme, n_resamples=n_res, seed=11), 9)
    assert set(np.unique(reps)) <= set(exact)
    support = np.array(sorted(exact))
    cdf_exact = np.cumsum([exact[v] for v in support])
    cdf_reps = np.searchsorted(np.sort(reps), support, side="right") / n_res
    # Kolmogorov-Smirnov distance: 1.63 / sqrt(B) is the 1% critical value.
    assert np.max(np.abs(cdf_reps - cdf_exact)) < 1.63 / math.sqrt(n_res)


def test_two_level_scheme_adds_the_within_variance_a_second_time():
    rng = np.random.default_rng(8)
    scores = 0.3 * rng.normal(size=(30, 1)) + rng.normal(size=(30, 4))
    scores[2, 1] = scores[7, [0, 3]] = np.nan
    m = per_example_means(scores)
    n = len(m)
    var_examples = np.var(m) / n
    pop_within = np.array([np.var(r[np.isfinite(r)]) / np.isfinite(r).sum() for r in scores])
    var_both = (np.var(m) + pop_within.mean()) / n
    for scheme, expected in [("examples", var_examples), ("both", var_both)]:
        reps = resampled_means(scores, scheme, n_resamples=20000, seed=1)
        assert reps.mean() == pytest.approx(m.mean(), abs=4 * math.sqrt(expected / 20000))
        # Relative s.e. of a variance from B normal-ish replicates is sqrt(2 / B) = 1%.
        assert np.var(reps) == pytest.approx(expected, rel=0.05)
    assert var_both > 1.3 * var_examples


def test_constant_scores_give_a_degenerate_interval_in_both_schemes():
    scores = np.full((20, 3), 1e6 + 0.1)
    scores[4, 2] = np.nan
    for scheme in ("examples", "both"):
        assert hierarchical_bootstrap_ci(scores, scheme, n_resamples=200) == (1e6 + 0.1,) * 3


def test_fewer_than_two_examples_leave_the_interval_nan():
    mean, lo, hi = hierarchical_bootstrap_ci(SMALL[2:], "both", n_resamples=100)
    assert mean == 100.0 and math.isnan(lo) and math.isnan(hi)
    mean, lo, hi = hierarchical_bootstrap_ci(np.full((3, 2), np.nan), "both", n_resamples=100)
    assert math.isnan(mean) and math.isnan(lo)


# ---------------------------------------------------------------- coverage on synthetic data


def simulated_coverage(k: int, seed: int, scheme: str = "examples", n_experiments: int = 1000, n_examples: int = 100,
                       between_sd: float = 1.0, within_sd: float = 1.0, n_resamples: int = 2000, groups: int = 20):
    """Share of experiments whose 95% interval covers the true mean; returns (coverage, mean interval width).

    Scores y_ek = mu + a_e + eps_ek with a_e ~ N(0, between_sd^2), eps_ek ~ N(0, within_sd^2). The
    experiments are bootstrapped in `groups` batches with different seeds, so that the Monte-Carlo
    error of one shared index matrix does not move every experiment's interval together.
    """
    mu = 0.3
    rng = np.random.default_rng([seed, k])
    y = mu + between_sd * rng.normal(size=(n_experiments, n_examples, 1))
    y = y + within_sd * rng.normal(size=(n_experiments, n_examples, k))
    covered, width = [], []
    for g, part in enumerate(np.array_split(y, groups)):
        _, lo, hi = hierarchical_bootstrap_ci(part, scheme, n_resamples=n_resamples, seed=seed * 1000 + g)
        covered.append((lo <= mu) & (mu <= hi))
        width.append(hi - lo)
    return float(np.concatenate(covered).mean()), float(np.concatenate(width).mean())


@pytest.mark.parametrize("k", [1, 2, 8])
def test_examples_bootstrap_covers_the_true_mean_95_percent_of_the_time(k):
    # Seed 1 of seeds 0-19: 58 of those 60 (seed, K) runs lie in [0.93, 0.97] (docs/statistics.md).
    coverage, _ = simulated_coverage(k, seed=1)
    assert 0.93 <= coverage <= 0.97
