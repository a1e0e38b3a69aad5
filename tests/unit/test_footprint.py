import math

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from rigidbench.scene_spec import footprint

sizes = st.floats(0.01, 3.0)


def _grid_has_fit(task_lw, support_lw, n=20001):
    psi = np.linspace(0, math.pi / 2, n)
    c, s = np.cos(psi), np.sin(psi)
    ok = (task_lw[0] * c + task_lw[1] * s <= support_lw[0]) & (task_lw[0] * s + task_lw[1] * c <= support_lw[1])
    return bool(ok.any())


@settings(max_examples=300, deadline=None)
@given(lt=sizes, wt=sizes, ls=sizes, ws=sizes, angle=st.floats(-180, 180), seed=st.integers(0, 2**32 - 1))
def test_every_sampled_angle_satisfies_both_inequalities(lt, wt, ls, ws, angle, seed):
    support = (max(ls, ws), min(ls, ws))
    intervals = footprint.fit_intervals((lt, wt), support, math.radians(angle))
    rng = np.random.default_rng(seed)
    for _ in range(20 if intervals else 0):
        psi_world = footprint.sample_rotation(rng, intervals)
        assert 0 <= psi_world < 2 * math.pi
        assert footprint.fits((lt, wt), support, psi_world - math.radians(angle), tol=1e-9)


@settings(max_examples=300, deadline=None)
@given(lt=sizes, wt=sizes, ls=sizes, ws=sizes)
def test_sampler_finds_angles_whenever_any_exist(lt, wt, ls, ws):
    support = (max(ls, ws), min(ls, ws))
    intervals = footprint.fit_intervals((lt, wt), support)
    if _grid_has_fit((lt, wt), support):
        assert intervals, "a fitting angle exists on a fine grid but no interval was found"
        footprint.sample_rotation(np.random.default_rng(0), intervals)
    # Conversely, every interval found must actually fit (check its midpoint and ends).
    for lo, hi in intervals:
        for psi in (lo, hi, (lo + hi) / 2):
            assert footprint.fits((lt, wt), support, psi, tol=1e-9)


def test_square_support_tight_fit_only_axis_aligned():
    # A 1 x 0.5 task on a 1 x 0.5 support fits exactly at 0 and pi only: zero-length intervals.
    intervals = footprint.fit_intervals((1.0, 0.5), (1.0, 0.5))
    assert intervals and all(hi - lo < 1e-6 for lo, hi in intervals)
    psi = footprint.sample_rotation(np.random.default_rng(3), intervals)
    assert min(abs(psi), abs(psi - math.pi), abs(psi - 2 * math.pi)) < 1e-6


def test_small_task_on_large_support_fits_everywhere():
    intervals = footprint.fit_intervals((0.1, 0.1), (2.0, 1.0))
    assert abs(sum(hi - lo for lo, hi in intervals) - 2 * math.pi) < 1e-9


def test_sampling_is_proportional_to_interval_length():
    intervals = [(0.0, 0.1), (1.0, 1.3)]
    rng = np.random.default_rng(0)
    draws = np.array([footprint.sample_rotation(rng, intervals) for _ in range(20000)])
    frac = np.mean(draws >= 1.0)
    assert abs(frac - 0.75) < 0.015
    assert np.all(((draws >= 0) & (draws <= 0.1)) | ((draws >= 1.0) & (draws <= 1.3)))


def test_symmetry_tiling_covers_four_quadrants():
    quadrant = footprint.fit_intervals_first_quadrant((1.2, 0.2), (1.3, 0.6))
    tiled = footprint.tile_symmetries(quadrant)
    assert len(tiled) == 4 * len(quadrant)
    for lo, hi in tiled:
        assert footprint.fits((1.2, 0.2), (1.3, 0.6), (lo + hi) / 2)


def test_too_large_task_has_no_rotation():
    assert footprint.fit_intervals((3.0, 1.0), (2.0, 1.0)) == []
