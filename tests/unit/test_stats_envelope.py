"""rigidbench.stats.envelope: the twins' quantiles, a model's position, excess and inside, their summaries and
the width table, on hand-computed cases and against a re-implementation of the type-7 quantile."""

from __future__ import annotations

import math

import numpy as np
import pytest

from rigidbench.stats.envelope import (excess, inside, positions, score_against_envelope, summarize, summarize_by,
                                       twin_quantiles, width_table)

NAN = math.nan


def type7(values: list[float], p: float) -> float:
    """Hyndman and Fan's type 7 quantile, written out: h = (n - 1) p on the sorted values."""
    x = sorted(values)
    h = (len(x) - 1) * p
    j = math.floor(h)
    return x[j] if j + 1 >= len(x) else x[j] + (h - j) * (x[j + 1] - x[j])


def test_quantiles_by_hand():
    q05, med, q95, n = twin_quantiles([[1, 2, 3, 4, 5], [2, 1, NAN, NAN, NAN], [5, 5, 5, 5, 5]])
    # [1..5]: h = 0.2 -> 1.2; h = 2 -> 3; h = 3.8 -> 4.8. [1, 2]: h = 0.05 -> 1.05; 1.5; h = 0.95 -> 1.95.
    np.testing.assert_allclose(q05, [1.2, 1.05, 5.0])
    np.testing.assert_allclose(med, [3.0, 1.5, 5.0])
    np.testing.assert_allclose(q95, [4.8, 1.95, 5.0])
    assert n.tolist() == [5, 2, 5]


def test_quantiles_match_the_written_out_formula():
    rng = np.random.default_rng(3)
    twins = rng.normal(size=(20, 8))
    twins[rng.random(twins.shape) < 0.2] = NAN
    q05, med, q95, n = twin_quantiles(twins)
    for e in range(20):
        finite = [v for v in twins[e] if math.isfinite(v)]
        assert n[e] == len(finite)
        if len(finite) < 2:
            assert math.isnan(q05[e]) and math.isnan(med[e]) and math.isnan(q95[e])
            continue
        assert q05[e] == pytest.approx(type7(finite, 0.05))
        assert med[e] == pytest.approx(type7(finite, 0.5))
        assert q95[e] == pytest.approx(type7(finite, 0.95))


def test_non_finite_twins_are_omitted_and_fewer_than_two_give_no_envelope():
    q05, med, q95, n = twin_quantiles([[1, NAN, 3, math.inf], [NAN, 4, -math.inf, NAN], [NAN] * 4])
    assert n.tolist() == [2, 1, 0]
    assert q05[0] == pytest.approx(1.1) and q95[0] == pytest.approx(2.9)
    assert np.isnan([q05[1], med[1], q95[1], q05[2]]).all()
    scores = score_against_envelope([[1, NAN, 3, math.inf], [NAN, 4, -math.inf, NAN]], [[2.0], [4.0]], False)
    assert scores.has_envelope.tolist() == [True, False]
    assert np.isnan([scores.position[1], scores.excess[1], scores.inside[1]]).all()
    assert scores.inside[0] == 1.0 and scores.position[0] == 0.5  # beats 3, loses to 1


def test_excess_in_both_directions():
    # the envelope [1.2, 4.8] of twins 1..5
    v = [5.0, 3.0, 0.5, NAN]
    np.testing.assert_allclose(excess(v, 1.2, 4.8, higher_is_better=False), [0.2, 0.0, 0.0, NAN])
    np.testing.assert_allclose(excess(v, 1.2, 4.8, higher_is_better=True), [0.0, 0.0, 0.7, NAN])
    assert np.isnan(excess(3.0, NAN, NAN, False))


def test_inside_means_no_worse_than_the_envelope_allows():
    # lower is better: inside up to q95 (closed), and below q05 too (better than every twin: excess 0)
    np.testing.assert_array_equal(inside([1.2, 4.8, 3.0, 1.19, 4.81], 1.2, 4.8, False), [1, 1, 1, 1, 0])
    # higher is better: the mirror
    np.testing.assert_array_equal(inside([1.2, 4.8, 3.0, 1.19, 4.81], 1.2, 4.8, True), [1, 1, 1, 0, 1])
    v = np.array([0.0, 1.19, 3.0, 4.81, 9.0])
    for hib in (False, True):  # inside exactly where the excess is 0
        np.testing.assert_array_equal(inside(v, 1.2, 4.8, hib) == 1, excess(v, 1.2, 4.8, hib) == 0)
    assert np.isnan(inside([NAN], 1.0, 2.0, False)).all() and np.isnan(inside([1.0], NAN, 2.0, True)).all()


def test_positions_count_ties_as_half_and_follow_the_direction():
    twins = [[1, 2, 3, 4, 5]]
    # lower is better: a value beats the twins above it
    np.testing.assert_allclose(positions(twins, [3.0], False), [2.5 / 5])
    np.testing.assert_allclose(positions(twins, [0.0], False), [1.0])
    np.testing.assert_allclose(positions(twins, [5.0], False), [0.5 / 5])
    # higher is better: the mirror
    np.testing.assert_allclose(positions(twins, [3.0], True), [2.5 / 5])
    np.testing.assert_allclose(positions(twins, [0.0], True), [0.0])
    np.testing.assert_allclose(positions(twins, [6.0], True), [1.0])
    # one position per sample, NaN for a missing sample
    got = positions([[1, 2, 3, NAN]], [[0.0, 2.0, NAN]], False)
    np.testing.assert_allclose(got, [[1.0, 0.5, NAN]])


def test_score_against_envelope_uses_the_mean_of_finite_samples():
    twins = [[1, 2, 3, 4, 5], [1, 2, 3, 4, 5], [10, 11, 12, 13, 14]]
    samples = [[4.0, 6.0], [5.0, NAN], [NAN, NAN]]  # means 5, 5, none
    s = score_against_envelope(twins, samples, higher_is_better=False)
    np.testing.assert_allclose(s.value, [5.0, 5.0, NAN])
    np.testing.assert_allclose(s.excess, [0.2, 0.2, NAN])
    np.testing.assert_allclose(s.inside, [0.0, 0.0, NAN])
    np.testing.assert_allclose(s.sample_positions, [[1.5 / 5, 0.0], [0.5 / 5, NAN], [NAN, NAN]])
    assert s.scored.tolist() == [True, True, False]
    np.testing.assert_allclose(s.q05, [1.2, 1.2, 10.2])
    with pytest.raises(ValueError, match="same examples"):
        score_against_envelope(twins, samples[:2], False)
    with pytest.raises(ValueError, match="shape"):
        score_against_envelope([1, 2, 3], samples, False)


def test_summaries_overall_and_by_group():
    twins = np.tile(np.arange(1.0, 6.0), (5, 1))  # every envelope [1.2, 4.8]
    values = np.array([[3.0], [6.0], [5.0], [NAN], [2.0]])  # inside, excess 1.2, excess 0.2, none, inside
    s = score_against_envelope(twins, values, higher_is_better=False)
    overall = summarize(s)
    assert overall == {"inside": pytest.approx(2 / 4), "excess": pytest.approx((0 + 1.2 + 0.2 + 0) / 4), "n": 4}
    by = summarize_by(s, ["a", "b", "a", "b", "c"])
    assert list(by) == ["a", "b", "c"]
    assert by["a"] == {"inside": 0.5, "excess": pytest.approx(0.1), "n": 2}
    assert by["b"] == {"inside": 0.0, "excess": pytest.approx(1.2), "n": 1}  # the missing value does not count
    assert by["c"] == {"inside": 1.0, "excess": 0.0, "n": 1}
    assert summarize(s, np.zeros(5, bool)) == {"inside": None, "excess": None, "n": 0}


def test_width_table_is_the_median_width_per_task():
    q05 = np.array([0.0, 1.0, 0.0, NAN, 2.0])
    q95 = np.array([1.0, 4.0, 2.0, NAN, 2.5])  # widths 1, 3, 2, none, 0.5
    tasks = ["fall", "chain", "fall", "fall", "chain"]
    table = width_table({"ate": (q05, q95), "iou": (q05 * 0, q05 * 0 + 0.1)}, tasks)
    assert table["fall"]["ate"] == pytest.approx(1.5)  # median of 1 and 2 (the example with no envelope left out)
    assert table["chain"]["ate"] == pytest.approx(1.75)  # median of 3 and 0.5
    assert table["fall"]["iou"] == pytest.approx(0.1)
    assert width_table({"ate": (np.array([NAN]), np.array([NAN]))}, ["x"]) == {"x": {"ate": None}}


def test_the_floor_raises_the_worse_bound_to_what_the_reference_itself_scores():
    # ATE-3D-like: twins 1..5 (q95 4.8); the reference scored as a model gives 6 on this example (its own
    # reconstruction error), so a value of 5.5 is no worse than a perfect prediction: inside, excess 0
    twins = np.tile(np.arange(1.0, 6.0), (3, 1))
    values = np.array([[5.5], [6.5], [5.5]])
    floor = np.array([6.0, 6.0, NAN])  # the third example's floor is unknown: q95 alone
    s = score_against_envelope(twins, values, higher_is_better=False, floor=floor)
    np.testing.assert_allclose(s.bound, [6.0, 6.0, 4.8])
    np.testing.assert_allclose(s.excess, [0.0, 0.5, 0.7])
    np.testing.assert_array_equal(s.inside, [1.0, 0.0, 0.0])
    np.testing.assert_allclose(s.q95, [4.8, 4.8, 4.8])  # the twins' quantiles are reported as they are
    # a floor better than q95 changes nothing; higher is better: the floor lowers q05
    low = score_against_envelope(twins, values, higher_is_better=False, floor=np.zeros(3))
    np.testing.assert_allclose(low.bound, [4.8, 4.8, 4.8])
    high = score_against_envelope(twins, [[0.5], [0.5], [1.1]], higher_is_better=True, floor=[0.4, 2.0, NAN])
    np.testing.assert_allclose(high.bound, [0.4, 1.2, 1.2])
    np.testing.assert_allclose(high.excess, [0.0, 0.7, 0.1])
