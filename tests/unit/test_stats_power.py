"""Unit tests for rigidbench.stats.power: variance components, detectable differences, sample sizes."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy import stats as sps

from rigidbench.stats.power import (
    PairedVarianceComponents,
    examples_needed,
    minimum_detectable_difference,
    paired_test_power,
    paired_variance_components,
    power_table,
)
from rigidbench.stats.samples import paired_difference_samples


def _components(between: float, within_a: float, within_b: float) -> PairedVarianceComponents:
    return PairedVarianceComponents(between, within_a, within_b, 100, float("nan"), None)


def _paired_experiments(rng, n_experiments, n_examples, k, difference, between, within_a, within_b):
    """Scores (X, E, K) of models A and B: shared example effect, a per-example difference effect, sample noise."""
    shared = rng.normal(size=(n_experiments, n_examples, 1))
    effect = math.sqrt(between) * rng.normal(size=(n_experiments, n_examples, 1))
    a = shared + difference + effect + math.sqrt(within_a) * rng.normal(size=(n_experiments, n_examples, k))
    b = shared + math.sqrt(within_b) * rng.normal(size=(n_experiments, n_examples, k))
    return a, b


def test_power_is_alpha_at_zero_and_matches_the_normal_formula_for_large_samples():
    assert paired_test_power(0.0, 2.0, 100) == pytest.approx(0.05, abs=1e-12)
    # Large E: the t-test becomes the z-test, MDE -> (z_0.975 + z_0.8) * tau / sqrt(E).
    z = sps.norm.ppf(0.975) + sps.norm.ppf(0.8)
    assert minimum_detectable_difference(2.0, n_examples=100000) == pytest.approx(z * math.sqrt(2.0 / 100000), rel=1e-3)
    mde = minimum_detectable_difference(1.5, n_examples=100)
    assert paired_test_power(mde, 1.5, 100) == pytest.approx(0.8, abs=1e-9)
    # The t-test at 99 degrees of freedom needs a little more than the z-test.
    assert z * math.sqrt(1.5 / 100) < mde < 1.01 * z * math.sqrt(1.5 / 100)
    assert minimum_detectable_difference(0.0) == 0.0 and math.isnan(minimum_detectable_difference(float("nan")))


def test_examples_needed_is_the_smallest_sufficient_count():
    var = 1.5
    mde = minimum_detectable_difference(var, n_examples=100)
    assert examples_needed(mde * 1.000001, var) == 100
    for diff in (0.05, 0.3, 1.0, 3.0):
        n = examples_needed(diff, var)
        assert paired_test_power(diff, var, n) >= 0.8
        assert n == 2 or paired_test_power(diff, var, n - 1) < 0.8
    assert examples_needed(0.0, var) is None and examples_needed(0.5, 0.0) == 2


def test_difference_variance_by_components_and_at_the_measured_k():
    comp = _components(0.5, 1.0, 3.0)
    assert comp.difference_variance(1) == 4.5 and comp.difference_variance(4) == 1.5
    k1_only = PairedVarianceComponents(float("nan"), float("nan"), float("nan"), 100, 2.5, (1, 1))
    assert k1_only.difference_variance(1) == 2.5 and math.isnan(k1_only.difference_variance(2))
    with pytest.raises(ValueError):
        comp.difference_variance(0)


def test_variance_components_recover_the_simulated_ones():
    rng = np.random.default_rng(5)
    a, b = _paired_experiments(rng, 1, 4000, 4, 0.2, between=0.5, within_a=1.0, within_b=2.0)
    b[0, 10, :2] = np.nan  # an example with fewer samples
    comp = paired_variance_components(a[0], b[0])
    assert comp.n_examples == 4000 and comp.measured_samples is None
    assert comp.within_a == pytest.approx(1.0, rel=0.05) and comp.within_b == pytest.approx(2.0, rel=0.05)
    # var(d_e) = 0.5 + 1/4 + 2/4 = 1.25 with s.e. 1.25 * sqrt(2 / 4000) = 0.028; the estimate of between is
    # var(d_e) minus the within parts, so its error is about that s.e.
    assert comp.between == pytest.approx(0.5, abs=0.1)
    assert comp.measured_variance == pytest.approx(1.25, rel=0.1)
    single = paired_variance_components(a[0, :, :1], b[0, :, :1])
    assert math.isnan(single.between) and single.measured_samples == (1, 1)
    d = a[0, :, 0] - b[0, :, 0]
    assert single.n_examples == 3999
    assert single.difference_variance(1) == pytest.approx(np.var(d[np.isfinite(d)], ddof=1), rel=1e-12)


def test_power_table_rows():
    comps = {"ate": _components(0.5, 1.0, 1.0), "iou": _components(0.01, 0.0, 0.0)}
    rows = power_table(comps, samples_per_example=(1, 4), differences={"ate": 0.3})
    assert [(r.measurement, r.samples_per_example) for r in rows] == [("ate", 1), ("ate", 4), ("iou", 1), ("iou", 4)]
    ate1, ate4, iou1, _ = rows
    assert ate1.difference_variance == 2.5 and ate4.difference_variance == 1.0
    assert ate1.min_detectable_difference == pytest.approx(minimum_detectable_difference(2.5, 100))
    assert ate4.min_detectable_difference < ate1.min_detectable_difference
    assert ate4.examples_needed == examples_needed(0.3, 1.0) and ate4.samples_needed == 4 * ate4.examples_needed
    assert iou1.examples_needed is None and math.isnan(iou1.difference)


@pytest.mark.parametrize("k, between, within", [(1, 1.0, 0.5), (4, 1.0, 1.0), (8, 0.2, 2.0)])
def test_stated_detectable_difference_is_detected_80_percent_of_the_time(k, between, within):
    n_examples, n_experiments = 100, 1000
    comp = _components(between, within, within)
    mde = power_table({"m": comp}, n_examples=n_examples, samples_per_example=(k,))[0].min_detectable_difference
    rng = np.random.default_rng([17, k])
    a, b = _paired_experiments(rng, n_experiments, n_examples, k, mde, between, within, within)
    d = a.mean(axis=-1) - b.mean(axis=-1)
    t_detected = sps.ttest_1samp(d, 0.0, axis=-1).pvalue < 0.05
    # The library's paired bootstrap interval, in batches with their own seeds (see simulated_coverage).
    boot_detected = []
    for g, (pa, pb) in enumerate(zip(np.array_split(a, 20), np.array_split(b, 20))):
        _, lo, hi = paired_difference_samples(pa, pb, n_resamples=2000, seed=g)
        boot_detected.append((lo > 0) | (hi < 0))
    assert 0.75 <= t_detected.mean() <= 0.85
    assert 0.75 <= np.concatenate(boot_detected).mean() <= 0.85


def test_a_difference_out_of_reach_needs_no_number_of_examples():
    # a difference that is a rounding error of the spread (a perfect score's 10%, 1e-16) asks for ~1e32 examples:
    # None, as for a zero difference, not an endless search (the demo's report met this on the reference's L2)
    from rigidbench.stats.power import MAX_EXAMPLES, examples_needed

    assert examples_needed(1e-16, 0.01) is None
    assert examples_needed(0.0, 0.01) is None
    # just past the bound (normal approximation (z_a/2 + z_p)^2 var / d^2 = 7.85 var / d^2): None; just inside: a number
    assert examples_needed(0.01, 2 * 0.01 ** 2 * MAX_EXAMPLES / 7.85) is None
    assert 0.49 * MAX_EXAMPLES < examples_needed(0.01, 0.5 * 0.01 ** 2 * MAX_EXAMPLES / 7.85) < 0.51 * MAX_EXAMPLES
    assert 2 <= examples_needed(0.1, 0.01) < 20  # an ordinary case still answers a small number
