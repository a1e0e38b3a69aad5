"""2D ATE against hand-computed values."""

import math

import numpy as np
import pytest

from rigidbench.metrics.tracks import ate

H = 100


def test_identical_tracks_give_zero():
    rng = np.random.default_rng(0)
    tracks = rng.random((6, 4, 2)) * 50
    vis = rng.random((6, 4)) > 0.3
    vis[0, 0] = True
    assert ate(tracks, tracks.copy(), vis, vis.copy(), H).value == 0.0


def test_every_point_frame_has_equal_weight():
    ref = np.zeros((2, 2, 2))
    gen = np.zeros((2, 2, 2))
    gen[0, 1] = [18.0, 24.0]  # 30 px error at frame 1
    vis = np.array([[True, True], [True, False]])
    r = ate(ref, gen, vis, vis, H)
    # three visible point-frames with errors 0, 0, 30 px
    assert r.value == pytest.approx(30 / 3 / H)
    assert r.value != pytest.approx((0 + 30 / H) / 2)  # not the mean of frame means
    np.testing.assert_allclose(r.per_frame, [0.0, 0.3])


def test_requires_both_visibilities():
    ref = np.zeros((2, 1, 2))
    gen = np.array([[[3.0, 4.0]], [[300.0, 400.0]]])
    ref_vis = np.array([[True], [True]])
    gen_vis = np.array([[True], [False]])  # point 1's huge error is not jointly visible
    assert ate(ref, gen, ref_vis, gen_vis, H).value == pytest.approx(5 / H)
    assert ate(ref, gen, gen_vis, ref_vis, H).value == pytest.approx(5 / H)


def test_all_invisible_is_nan():
    tracks = np.zeros((3, 4, 2))
    vis = np.zeros((3, 4), bool)
    r = ate(tracks, tracks, vis, vis, H)
    assert math.isnan(r.value)
    assert np.isnan(r.per_frame).all()


def test_non_finite_coordinates_are_omitted():
    ref = np.zeros((2, 1, 2))
    gen = np.array([[[6.0, 8.0]], [[np.nan, 0.0]]])
    vis = np.ones((2, 1), bool)
    assert ate(ref, gen, vis, vis, H).value == pytest.approx(10 / H)


def test_shape_mismatch_raises():
    with pytest.raises(ValueError, match="shape"):
        ate(np.zeros((2, 3, 2)), np.zeros((2, 4, 2)), np.ones((2, 3), bool), np.ones((2, 3), bool), H)
