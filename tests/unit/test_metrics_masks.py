"""Mask metrics against hand-computed values: IoU, centroid L2, Chamfer, nested averaging."""

import math

import numpy as np
import pytest

from rigidbench.metrics.masks import centroid_l2, chamfer, chamfer_pair, iou, mask_centroids

H, W = 10, 12


def box(r0, r1, c0, c1, h=H, w=W):
    m = np.zeros((h, w), bool)
    m[r0:r1, c0:c1] = True
    return m


def clip(*frames):
    """frames: lists of (H, W) masks, one list per frame. Returns (T, N, H, W) bool."""
    return np.stack([np.stack(f) for f in frames])


def test_identical_masks_are_perfect():
    rng = np.random.default_rng(0)
    masks = rng.random((3, 2, H, W)) > 0.6
    assert iou(masks, masks.copy()).value == 1.0
    assert centroid_l2(masks, masks.copy()).value == 0.0
    assert chamfer(masks, masks.copy()).value == 0.0


def test_one_pixel_shift_by_hand():
    ref = clip([box(2, 4, 2, 4)])  # 2x2 square, columns 2-3
    gen = clip([box(2, 4, 3, 5)])  # shifted one column right
    # intersection 2 pixels, union 6 pixels
    assert iou(ref, gen).value == pytest.approx(2 / 6)
    # centroids x = 3.0 and 4.0 (pixel centres at +0.5), distance 1 pixel, divided by H
    assert centroid_l2(ref, gen).value == pytest.approx(1 / H)
    # each set: half its pixels at distance 1, half at 0 -> 0.5 + 0.5
    assert chamfer(ref, gen).value == pytest.approx(1.0 / H)


def test_centroid_uses_pixel_centres():
    m = clip([box(0, 1, 0, 1)])
    np.testing.assert_allclose(mask_centroids(m)[0, 0], [0.0, 0.0])  # pixel centres at integers
    assert np.isnan(mask_centroids(clip([box(0, 0, 0, 0)]))).all()


def test_chamfer_is_euclidean_and_asymmetric_terms_add():
    a = np.zeros((8, 8), bool)
    b = np.zeros((8, 8), bool)
    a[0, 0] = True
    b[3, 4] = True
    assert chamfer_pair(a, b) == pytest.approx(10.0)  # 5 + 5
    b[0, 0] = True
    # d(a, b) = 0; d(b, a) = (0 + 5) / 2
    assert chamfer_pair(a, b) == pytest.approx(2.5)


def test_chamfer_crop_matches_brute_force():
    from scipy.spatial.distance import cdist

    rng = np.random.default_rng(1)
    for _ in range(5):
        a = np.zeros((40, 50), bool)
        b = np.zeros((40, 50), bool)
        a[rng.integers(0, 40, 15), rng.integers(0, 50, 15)] = True
        b[rng.integers(5, 20, 9), rng.integers(30, 45, 9)] = True
        pa, pb = np.argwhere(a), np.argwhere(b)
        d = cdist(pa, pb)
        expected = d.min(axis=1).mean() + d.min(axis=0).mean()
        assert chamfer_pair(a, b) == pytest.approx(expected, rel=1e-12)


def test_empty_masks():
    empty = box(0, 0, 0, 0)
    full = box(2, 4, 2, 4)
    both_empty = clip([empty])
    # empty union counts as 1; L2 and Chamfer undefined -> NaN for the clip
    assert iou(both_empty, both_empty).value == 1.0
    assert math.isnan(centroid_l2(both_empty, both_empty).value)
    assert math.isnan(chamfer(both_empty, both_empty).value)
    # generated mask missing: IoU 0, distances omitted
    assert iou(clip([full]), clip([empty])).value == 0.0
    assert math.isnan(chamfer(clip([full]), clip([empty])).value)


def test_actor_leaving_the_frame():
    # Actor 0 moves right and leaves the image at frame 2 in both clips; actor 1 is a static
    # square the generated clip shifts by one column.
    ref = clip([box(2, 4, 6, 8), box(6, 8, 2, 4)],
               [box(2, 4, 10, 12), box(6, 8, 2, 4)],
               [box(0, 0, 0, 0), box(6, 8, 2, 4)])
    gen = clip([box(2, 4, 6, 8), box(6, 8, 3, 5)],
               [box(2, 4, 10, 12), box(6, 8, 3, 5)],
               [box(0, 0, 0, 0), box(6, 8, 3, 5)])
    r = iou(ref, gen)
    # frames 0, 1: mean(1, 1/3); frame 2: actor 0 empty union -> 1, so also mean(1, 1/3)
    np.testing.assert_allclose(r.per_frame, [2 / 3] * 3)
    l2 = centroid_l2(ref, gen)
    # frame 2 only has actor 1 defined: mean over actors differs per frame
    np.testing.assert_allclose(l2.per_frame, [0.5 / H, 0.5 / H, 1.0 / H])
    assert l2.value == pytest.approx((0.5 + 0.5 + 1.0) / 3 / H)


def test_nested_mean_differs_from_pooled():
    # frame 0: two actors with L2 of 1 and 3 pixels; frame 1: actor 0 with 5 pixels, actor 1 empty
    ref = clip([box(0, 2, 0, 2), box(5, 7, 0, 2)],
               [box(0, 2, 0, 2), box(0, 0, 0, 0)])
    gen = clip([box(0, 2, 1, 3), box(5, 7, 3, 5)],
               [box(0, 2, 5, 7), box(0, 0, 0, 0)])
    r = centroid_l2(ref, gen)
    nested = ((1 + 3) / 2 + 5) / 2 / H
    pooled = (1 + 3 + 5) / 3 / H
    assert r.value == pytest.approx(nested)
    assert abs(r.value - pooled) > 1e-3
    np.testing.assert_allclose(r.per_frame, [2 / H, 5 / H])


def test_shape_and_dtype_errors():
    m = np.zeros((2, 1, H, W), bool)
    with pytest.raises(ValueError, match="shape"):
        iou(m, m[:1])
    with pytest.raises(ValueError, match="bool"):
        iou(m.astype(np.uint8), m.astype(np.uint8))
