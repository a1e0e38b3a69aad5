"""Unit tests for rigidbench.stats: bootstrap intervals, paired comparisons, correlations."""

from __future__ import annotations

import math
import warnings

import numpy as np
import pytest
from scipy import stats as sps

import rigidbench.stats.correlation as correlation_module
from rigidbench.stats import (
    bootstrap_ci,
    correlation_across_models,
    improvement_indicators,
    paired_difference,
    paired_difference_matrix,
    probability_of_improvement,
    probability_of_improvement_matrix,
)

B = 20000


# ---------------------------------------------------------------- bootstrap_ci


def _percentile_mc_se(data: np.ndarray, q: float, n_resamples: int) -> float:
    """Monte-Carlo s.e. of the q-quantile of n_resamples bootstrap means (normal approximation).

    The q-quantile of B draws has s.e. sqrt(q(1-q)/B) / f(x_q); the bootstrap distribution of the
    mean is close to N(mean, sd_pop^2 / N), whose density at its q-quantile is phi(z_q) / se_mean.
    """
    se_mean = data.std() / math.sqrt(len(data))
    z = sps.norm.ppf(q)
    return math.sqrt(q * (1 - q) / n_resamples) * se_mean / sps.norm.pdf(z)


@pytest.mark.parametrize(
    "name, n",
    [("normal", 100), ("exponential", 100), ("lognormal", 40)],
)
def test_bootstrap_ci_agrees_with_scipy_percentile_within_monte_carlo_error(name, n):
    rng = np.random.default_rng(7)
    data = {
        "normal": lambda: rng.normal(2.0, 0.5, n),
        "exponential": lambda: rng.exponential(0.3, n),
        "lognormal": lambda: rng.lognormal(0.0, 0.6, n),
    }[name]()
    mean, lo, hi = bootstrap_ci(data, n_resamples=B, confidence=0.95, seed=0)
    ref = sps.bootstrap(
        (data,), np.mean, n_resamples=B, method="percentile", confidence_level=0.95, rng=np.random.default_rng(99)
    ).confidence_interval
    assert mean == pytest.approx(data.mean(), rel=1e-12)
    # Two independent Monte-Carlo estimates: the difference has sqrt(2) times one s.e.
    tol = 3 * math.sqrt(2) * _percentile_mc_se(data, 0.025, B)
    assert abs(lo - ref.low) < tol
    assert abs(hi - ref.high) < tol
    assert lo < mean < hi


def test_bootstrap_ci_equals_explicit_index_gather_with_documented_stream():
    data = np.array([0.3, -1.2, 4.0, 2.5, 0.0, 7.1, -0.4])
    seed, n_res = 3, 501
    idx = np.random.default_rng(seed).integers(0, len(data), size=(n_res, len(data)), dtype=np.int32)
    means = data[idx].mean(axis=1)
    lo_ref, hi_ref = np.quantile(means, [0.05, 0.95])
    mean, lo, hi = bootstrap_ci(data, n_resamples=n_res, confidence=0.9, seed=seed)
    assert mean == pytest.approx(data.mean(), abs=1e-12)
    assert lo == pytest.approx(lo_ref, abs=1e-12)
    assert hi == pytest.approx(hi_ref, abs=1e-12)


def test_bootstrap_ci_does_not_depend_on_chunk_size():
    values = np.random.default_rng(0).normal(size=(6, 37))
    full = bootstrap_ci(values, n_resamples=3001, seed=5)
    chunked = bootstrap_ci(values, n_resamples=3001, seed=5, chunk_elements=37 * 13)
    for x, y in zip(full, chunked):
        np.testing.assert_allclose(x, y, rtol=0, atol=1e-12)


def test_two_point_data_gives_hand_computed_percentiles():
    # Means of 2 draws from {0, 1}: 0 w.p. 1/4, 0.5 w.p. 1/2, 1 w.p. 1/4. The 2.5% and 97.5%
    # quantiles are then 0 and 1; the 30% and 70% quantiles both fall inside the 0.5 mass.
    assert bootstrap_ci([0.0, 1.0], seed=1) == (0.5, 0.0, 1.0)
    assert bootstrap_ci([0.0, 1.0], confidence=0.4, seed=1) == (0.5, 0.5, 0.5)


@pytest.mark.parametrize("value", [0.3, 1e6 + 0.1, -2.7e-9])
def test_constant_data_gives_degenerate_interval(value):
    mean, lo, hi = bootstrap_ci(np.full(100, value))
    assert mean == lo == hi == value


def test_non_finite_values_are_omitted_per_row():
    rng = np.random.default_rng(11)
    clean = rng.normal(size=(3, 50))
    dirty = clean.copy()
    dirty[1, [4, 17]] = np.nan
    dirty[2, 9] = np.inf
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        mean, lo, hi = bootstrap_ci(dirty, n_resamples=2000, seed=2)
    for row in range(3):
        finite = dirty[row][np.isfinite(dirty[row])]
        alone = bootstrap_ci(finite, n_resamples=2000, seed=2)
        assert (mean[row], lo[row], hi[row]) == pytest.approx(alone, abs=1e-12)
    assert mean[1] == pytest.approx(np.delete(clean[1], [4, 17]).mean(), rel=1e-12)
    # Rows 0 and 1 have different finite counts, so their intervals differ from the clean data.
    assert bootstrap_ci(clean[0], n_resamples=2000, seed=2) == pytest.approx((mean[0], lo[0], hi[0]), abs=1e-12)


def test_rows_with_fewer_than_two_finite_values_give_nan_intervals():
    values = np.array(
        [
            [np.nan, np.nan, np.nan],
            [np.nan, 4.0, np.inf],
            [1.0, 2.0, np.nan],
        ]
    )
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        mean, lo, hi = bootstrap_ci(values, n_resamples=500)
    assert np.isnan(mean[0]) and np.isnan(lo[0]) and np.isnan(hi[0])
    assert mean[1] == 4.0 and np.isnan(lo[1]) and np.isnan(hi[1])
    assert mean[2] == 1.5 and 1.0 <= lo[2] <= hi[2] <= 2.0
    empty = bootstrap_ci(np.zeros((2, 0)))
    assert all(np.isnan(v).all() and v.shape == (2,) for v in empty)


def test_bootstrap_ci_shapes_and_determinism():
    values = np.random.default_rng(4).normal(size=(10, 8, 30))
    mean, lo, hi = bootstrap_ci(values, n_resamples=1000, seed=9)
    assert mean.shape == lo.shape == hi.shape == (10, 8)
    np.testing.assert_allclose(mean, values.mean(axis=-1), rtol=1e-12)
    assert np.all(lo <= mean) and np.all(mean <= hi)
    again = bootstrap_ci(values, n_resamples=1000, seed=9)
    np.testing.assert_array_equal(lo, again[1])
    other = bootstrap_ci(values, n_resamples=1000, seed=10)
    assert not np.array_equal(lo, other[1])
    single = bootstrap_ci(values[3, 5], n_resamples=1000, seed=9)
    assert all(isinstance(v, float) for v in single)
    assert single == pytest.approx((mean[3, 5], lo[3, 5], hi[3, 5]), abs=1e-12)


def test_interval_narrows_with_lower_confidence():
    data = np.random.default_rng(5).normal(size=60)
    _, lo95, hi95 = bootstrap_ci(data, confidence=0.95)
    _, lo50, hi50 = bootstrap_ci(data, confidence=0.5)
    assert lo95 < lo50 < hi50 < hi95


@pytest.mark.parametrize("kwargs", [{"confidence": 1.0}, {"confidence": 0.0}, {"n_resamples": 0}, {"n_resamples": 2.5}])
def test_bootstrap_ci_rejects_bad_options(kwargs):
    with pytest.raises(ValueError):
        bootstrap_ci([1.0, 2.0, 3.0], **kwargs)


# ---------------------------------------------------------------- paired differences


def test_paired_difference_of_identical_arrays_is_exactly_zero():
    a = np.random.default_rng(8).normal(3.0, 2.0, 100)
    assert paired_difference(a, a.copy()) == (0.0, 0.0, 0.0)


def test_paired_difference_drops_unmatched_examples():
    a = np.array([1.0, 2.0, np.nan, 5.0, 4.0])
    b = np.array([0.0, 0.5, 3.0, np.inf, 1.0])
    mean, lo, hi = paired_difference(a, b, n_resamples=2000, seed=1)
    # Matched examples 0, 1, 4 with differences 1, 1.5, 3.
    assert mean == pytest.approx(5.5 / 3)
    assert (mean, lo, hi) == pytest.approx(bootstrap_ci([1.0, 1.5, 3.0], n_resamples=2000, seed=1))
    assert 1.0 <= lo < hi <= 3.0


def test_paired_difference_matrix_matches_pairwise_calls_and_is_antisymmetric():
    rng = np.random.default_rng(12)
    values = rng.normal(size=(4, 40)) + np.arange(4)[:, None] * 0.3
    values[2, 5] = np.nan
    res = paired_difference_matrix(values, n_resamples=3000, seed=4)
    for i in range(4):
        for j in range(4):
            if i == j:
                assert (res.estimate[i, i], res.lo[i, i], res.hi[i, i]) == (0.0, 0.0, 0.0)
                continue
            ref = paired_difference(values[i], values[j], n_resamples=3000, seed=4)
            assert (res.estimate[i, j], res.lo[i, j], res.hi[i, j]) == pytest.approx(ref, abs=1e-12)
    np.testing.assert_allclose(res.estimate, -res.estimate.T, atol=1e-15)
    assert res.n_matched[0, 2] == res.n_matched[2, 0] == 39 and res.n_matched[0, 1] == 40
    assert res.null_value == 0.0
    assert res.significant[3, 0] and res.significant[0, 3]
    assert not res.significant.diagonal().any()


# ---------------------------------------------------------------- probability of improvement


def test_poi_hand_built_case_with_ties():
    a = [1.0, 2.0, 3.0, 4.0]
    b = [1.0, 3.0, 2.0, 0.0]
    np.testing.assert_array_equal(improvement_indicators(a, b, True), [0.5, 0.0, 1.0, 1.0])
    poi, lo, hi = probability_of_improvement(a, b, higher_is_better=True, n_resamples=B, seed=0)
    assert poi == 0.625
    assert (poi, lo, hi) == pytest.approx(bootstrap_ci([0.5, 0.0, 1.0, 1.0], n_resamples=B, seed=0))
    # Lower is better: the wins swap, the tie stays a half.
    np.testing.assert_array_equal(improvement_indicators(a, b, False), [0.5, 1.0, 0.0, 0.0])
    assert probability_of_improvement(a, b, higher_is_better=False)[0] == 0.375


@pytest.mark.parametrize("higher", [True, False])
def test_poi_of_reversed_pair_is_complement(higher):
    rng = np.random.default_rng(21)
    a = np.round(rng.normal(size=80), 1)  # rounding creates ties
    b = np.round(rng.normal(size=80), 1)
    poi_ab, lo_ab, hi_ab = probability_of_improvement(a, b, higher, n_resamples=5000, seed=3)
    poi_ba, lo_ba, hi_ba = probability_of_improvement(b, a, higher, n_resamples=5000, seed=3)
    assert poi_ab + poi_ba == pytest.approx(1.0, abs=1e-12)
    assert lo_ab + hi_ba == pytest.approx(1.0, abs=1e-12)
    assert hi_ab + lo_ba == pytest.approx(1.0, abs=1e-12)


def test_poi_drops_unmatched_examples():
    a = np.array([1.0, np.nan, 3.0, 0.0, 2.0])
    b = np.array([0.0, 1.0, np.inf, 1.0, 2.0])
    w = improvement_indicators(a, b, True)
    np.testing.assert_array_equal(w[[0, 3, 4]], [1.0, 0.0, 0.5])
    assert np.isnan(w[[1, 2]]).all()
    assert probability_of_improvement(a, b, True)[0] == pytest.approx(0.5)


def test_poi_matrix_values_direction_and_significance():
    x = np.random.default_rng(30).normal(size=60)
    shift = np.where(np.arange(60) % 2 == 0, 0.5, -0.5)
    values = np.stack([x + 1.0, x, x + shift, x])
    values[1, 0] = np.nan
    res = probability_of_improvement_matrix(values, higher_is_better=True, n_resamples=4000, seed=6)
    assert res.estimate[0, 1] == 1.0 and res.lo[0, 1] == 1.0 and res.hi[0, 1] == 1.0
    assert res.estimate[1, 0] == 0.0 and res.significant[0, 1] and res.significant[1, 0]
    # Model 2 beats model 3 on exactly half the examples: PoI 0.5 and not significant.
    assert res.estimate[2, 3] == 0.5 and not res.significant[2, 3]
    # Model 1 and model 3 are identical where matched: every example is a tie.
    assert res.estimate[1, 3] == 0.5 and res.lo[1, 3] == res.hi[1, 3] == 0.5 and not res.significant[1, 3]
    np.testing.assert_array_equal(res.estimate.diagonal(), 0.5)
    assert not res.significant.diagonal().any()
    assert res.n_matched[0, 1] == 59 and res.n_matched[0, 2] == 60 and res.n_matched[1, 1] == 59
    np.testing.assert_allclose(res.estimate + res.estimate.T, 1.0, atol=1e-12)
    for i, j in [(0, 2), (2, 0), (1, 2), (3, 1)]:
        ref = probability_of_improvement(values[i], values[j], True, n_resamples=4000, seed=6)
        assert (res.estimate[i, j], res.lo[i, j], res.hi[i, j]) == pytest.approx(ref, abs=1e-12)
    lower = probability_of_improvement_matrix(values, higher_is_better=False, n_resamples=4000, seed=6)
    np.testing.assert_allclose(lower.estimate, res.estimate.T, atol=1e-12)


# ---------------------------------------------------------------- correlation across models


def test_correlation_point_estimates_match_scipy():
    rng = np.random.default_rng(40)
    x = rng.normal(size=8)
    y = -0.8 * x + 0.3 * rng.normal(size=8)
    y[3] = y[5]  # a tie for the rank correlation
    res = correlation_across_models(x, y, n_resamples=2000)
    assert res["pearson"] == pytest.approx(sps.pearsonr(x, y).statistic, abs=1e-12)
    assert res["spearman"] == pytest.approx(sps.spearmanr(x, y).statistic, abs=1e-12)
    assert res["pearson_ci"][0] <= res["pearson"] <= res["pearson_ci"][1]
    assert res["spearman_ci"][0] <= res["spearman"] <= res["spearman_ci"][1]
    assert -1.0 <= res["pearson_ci"][0] and res["pearson_ci"][1] <= 1.0


def test_correlation_bootstrap_equals_brute_force_over_resampled_models():
    x = np.array([0.2, 0.9, 0.4, 0.7])
    y = np.array([1.0, 1.0, 2.0, 3.0])
    seed, n_res = 5, 400
    idx = np.random.default_rng(seed).integers(0, 4, size=(n_res, 4))
    pearson, spearman, degenerate = [], [], 0
    for row in idx:
        xs, ys = x[row], y[row]
        if np.ptp(xs) == 0 or np.ptp(ys) == 0:
            degenerate += 1
            continue
        pearson.append(sps.pearsonr(xs, ys).statistic)
        spearman.append(sps.spearmanr(xs, ys).statistic)
    res = correlation_across_models(x, y, n_resamples=n_res, confidence=0.9, seed=seed)
    assert degenerate > 0 and res["n_degenerate"] == degenerate
    np.testing.assert_allclose(res["pearson_ci"], np.quantile(pearson, [0.05, 0.95]), atol=1e-12)
    np.testing.assert_allclose(res["spearman_ci"], np.quantile(spearman, [0.05, 0.95]), atol=1e-12)


def test_correlation_degenerate_count_matches_probability_of_single_model_draw():
    # With 3 distinct models a resample is constant only if one model is drawn 3 times: p = 3/27.
    res = correlation_across_models([1.0, 2.0, 4.0], [3.0, 1.0, 2.0], n_resamples=B, seed=0)
    expected = B / 9
    sd = math.sqrt(B * (1 / 9) * (8 / 9))
    assert abs(res["n_degenerate"] - expected) < 5 * sd


def _assert_same_correlation(res: dict, ref: dict) -> None:
    assert res.keys() == ref.keys()
    for key, value in ref.items():
        np.testing.assert_allclose(res[key], value, rtol=0, atol=1e-12, err_msg=key)


def test_correlation_chunking_and_non_finite_models(monkeypatch):
    rng = np.random.default_rng(41)
    x, y = rng.normal(size=6), rng.normal(size=6)
    full = correlation_across_models(x, y, n_resamples=3000, seed=2)
    monkeypatch.setattr(correlation_module, "_CHUNK_RESAMPLES", 257)
    chunked = correlation_across_models(x, y, n_resamples=3000, seed=2)
    _assert_same_correlation(chunked, full)
    x_nan = np.append(x, np.nan)
    y_nan = np.append(y, 0.5)
    _assert_same_correlation(correlation_across_models(x_nan, y_nan, n_resamples=3000, seed=2), full)
    undefined = correlation_across_models([1.0, np.nan], [2.0, 3.0])
    assert math.isnan(undefined["pearson"]) and math.isnan(undefined["spearman_ci"][0])
    constant = correlation_across_models([1.0, 1.0, 1.0], [2.0, 3.0, 4.0])
    assert math.isnan(constant["pearson"])
