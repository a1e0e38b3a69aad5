"""The faster metric code (issue 27) gives the values of the code it replaced.

Each reference below is a copy of the implementation before the change (SSIM's per-frame map and mean,
IoU by counts over axes, centroids by row and column sums, the disparity fit and SI-MSE each with its own
validity mask and gathers, IdDrift's patch preparation); the new code must agree within 1e-6 on random
inputs, including the awkward cases (frames narrower than the window, empty masks, invalid depth,
negative aligned disparity, border crops).
"""

from __future__ import annotations

import threading

import numpy as np
import pytest

from rigidbench.metrics import METRICS, MetricInputs, appearance, depth, identity, masks

# -- references: the implementations before issue 27 ------------------------------------------------


def ref_ssim_frame(ref, gen, data_range=255.0):
    import cv2

    shape = ref.shape if ref.ndim == 3 else ref.shape + (1,)
    x = np.asarray(ref, np.float32).reshape(shape).copy()
    y = np.asarray(gen, np.float32).reshape(shape).copy()
    h, w = shape[:2]
    win = appearance.gaussian_window()
    one = np.ones(1, np.float32)
    kx, cx = (win, slice(5, w - 5)) if w >= 11 else (one, slice(None))
    ky, cy = (win, slice(5, h - 5)) if h >= 11 else (one, slice(None))

    def blur(src):
        return cv2.sepFilter2D(src, cv2.CV_32F, kx, ky, borderType=cv2.BORDER_REFLECT).reshape(shape)

    mu1, mu2 = blur(x), blur(y)
    s11, s22, s12 = blur(x * x), blur(y * y), blur(x * y)
    c1 = np.float32((0.01 * data_range) ** 2)
    c2 = np.float32((0.03 * data_range) ** 2)
    s11 = s11 - mu1 * mu1
    s22 = s22 - mu2 * mu2
    s12 = s12 - mu1 * mu2
    cs = (s12 * 2 + c2) / (s11 + s22 + c2)
    lum = (mu1 * mu2 * 2 + c1) / (mu1 * mu1 + mu2 * mu2 + c1)
    per_channel = (lum * cs)[cy, cx].reshape(-1, shape[2]).mean(axis=0, dtype=np.float64)
    return float(per_channel.mean())


def ref_iou_per_actor(r, g):
    inter = np.count_nonzero(r & g, axis=(2, 3))
    union = np.count_nonzero(r | g, axis=(2, 3))
    return np.where(union > 0, inter / np.maximum(union, 1), 1.0)


def ref_centroids(m):
    rows = np.add.reduce(m, axis=3, dtype=np.int64)
    cols = np.add.reduce(m, axis=2, dtype=np.int64)
    area = rows.sum(axis=-1).astype(np.float64)
    y = rows @ np.arange(rows.shape[-1], dtype=np.float64)
    x = cols @ np.arange(cols.shape[-1], dtype=np.float64)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.stack([x / area, y / area], axis=-1)


def ref_fit(d, z):
    n, pivot_d, pivot_y = 0, None, None
    s_d = s_y = s_dd = s_dy = 0.0
    for t in range(z.shape[0]):
        with np.errstate(invalid="ignore"):
            valid = np.isfinite(z[t]) & (z[t] > 0) & (z[t] < 100) & np.isfinite(d[t])
        if not valid.any():
            continue
        dv = d[t][valid].astype(np.float64)
        yv = 1.0 / z[t][valid].astype(np.float64)
        if pivot_d is None:
            pivot_d, pivot_y = float(dv.mean()), float(yv.mean())
        dv -= pivot_d
        yv -= pivot_y
        n += dv.size
        s_d += float(dv.sum())
        s_y += float(yv.sum())
        s_dd += float(np.sum(dv * dv))
        s_dy += float(np.sum(dv * yv))
    mean_d, mean_y = s_d / n, s_y / n
    scale = (s_dy / n - mean_d * mean_y) / (s_dd / n - mean_d * mean_d)
    return scale, (mean_y + pivot_y) - scale * (mean_d + pivot_d)


def ref_si_mse(d, z, scale, shift):
    per_frame = np.full(z.shape[0], np.nan)
    for t in range(z.shape[0]):
        with np.errstate(invalid="ignore"):
            valid = np.isfinite(z[t]) & (z[t] > 0) & (z[t] < 100) & np.isfinite(d[t])
        if not valid.any():
            continue
        aligned = scale * d[t][valid].astype(np.float64) + shift
        positive = aligned > 0
        if not positive.any():
            continue
        delta = -np.log(aligned[positive] * z[t][valid][positive].astype(np.float64))
        per_frame[t] = float(np.mean(delta * delta) - np.mean(delta) ** 2)
    return per_frame


def ref_preprocess(patches):
    import torch
    import torch.nn.functional as F

    out = torch.empty((len(patches), 3, 224, 224))
    for i, patch in enumerate(patches):
        x = torch.from_numpy(np.ascontiguousarray(patch)).permute(2, 0, 1)[None].float() / 255.0
        out[i] = F.interpolate(x, size=(224, 224), mode="bilinear", align_corners=False, antialias=True)[0]
    mean = torch.tensor(identity.IMAGENET_MEAN).view(1, 3, 1, 1)
    std = torch.tensor(identity.IMAGENET_STD).view(1, 3, 1, 1)
    return (out - mean) / std


# -- comparisons ---------------------------------------------------------------------------------------


def _clip(rng, t, h, w):
    ref = rng.integers(0, 256, (t, h, w, 3), dtype=np.uint8)
    noise = rng.integers(-40, 41, ref.shape)
    return ref, np.clip(ref.astype(int) + noise, 0, 255).astype(np.uint8)


@pytest.mark.parametrize("shape", [(3, 90, 130), (2, 11, 11), (2, 8, 40), (2, 40, 7), (1, 75, 33)])
def test_ssim_matches_the_previous_implementation(shape):
    rng = np.random.default_rng(sum(shape))
    ref, gen = _clip(rng, *shape)
    got = appearance.ssim(ref, gen)
    want = np.array([ref_ssim_frame(ref[t], gen[t]) for t in range(shape[0])])
    np.testing.assert_allclose(got.per_frame, want, rtol=0, atol=1e-6)
    assert got.value == pytest.approx(want.mean(), abs=1e-6)


def test_ssim_float_and_single_channel_frames_match_the_previous_implementation():
    rng = np.random.default_rng(3)
    a = rng.uniform(0, 255, (50, 70)).astype(np.float32)
    b = np.clip(a + rng.normal(0, 20, a.shape), 0, 255).astype(np.float32)
    store = threading.local()
    assert appearance.ssim_frame(a, b, store=store) == pytest.approx(ref_ssim_frame(a, b), abs=1e-6)
    # and a frame taller than one strip, so several strips are summed
    tall_a = rng.integers(0, 256, (appearance.SSIM_STRIP_ROWS * 3 + 17, 23, 3), dtype=np.uint8)
    tall_b = rng.integers(0, 256, tall_a.shape, dtype=np.uint8)
    assert appearance.ssim_frame(tall_a, tall_b, store=store) == pytest.approx(ref_ssim_frame(tall_a, tall_b),
                                                                               abs=1e-6)


def _masks(rng, t=5, n=3, h=37, w=53):
    yy, xx = np.mgrid[:h, :w]
    out = np.zeros((t, n, h, w), bool)
    for i in range(t):
        for a in range(n):
            if rng.random() < 0.2:
                continue  # an empty actor-frame
            cx, cy, r = rng.uniform(0, w), rng.uniform(0, h), rng.uniform(2, 12)
            out[i, a] = (xx - cx) ** 2 + (yy - cy) ** 2 < r * r
    return out


def test_iou_and_centroids_match_the_previous_implementation():
    rng = np.random.default_rng(7)
    for _ in range(5):
        r, g = _masks(rng), _masks(rng)
        np.testing.assert_array_equal(masks.iou_per_actor(r, g), ref_iou_per_actor(r, g))
        np.testing.assert_array_equal(masks.mask_centroids(r), ref_centroids(r))
        want = np.linalg.norm(ref_centroids(r) - ref_centroids(g), axis=-1) / r.shape[2]
        np.testing.assert_array_equal(masks.centroid_l2_per_actor(r, g), want)


def _depth(rng, t=6, h=30, w=40):
    z = rng.uniform(0.5, 8.0, (t, h, w)).astype(np.float32)
    z[:, :, :3] = np.inf
    z[:, 0] = 150.0  # beyond the valid range
    z[:, 1, :5] = np.nan
    z[2] = np.inf  # a frame without valid depth
    d = (0.8 / z * rng.uniform(0.9, 1.1, z.shape) + 0.05).astype(np.float32)
    d[:, 5, 5:9] = np.nan
    d[-1, 10:20] = -5.0  # aligned disparity <= 0 there
    return d, z


def test_disparity_fit_and_si_mse_match_the_previous_implementation():
    rng = np.random.default_rng(11)
    d, z = _depth(rng)
    scale, shift = ref_fit(d, z)
    fit = depth.fit_disparity_alignment(d, z)
    assert fit.scale == pytest.approx(scale, rel=1e-9) and fit.shift == pytest.approx(shift, rel=1e-9)
    valid = depth.depth_validity(d, z)
    assert depth.fit_disparity_alignment(d, z, valid=valid) == fit
    want = ref_si_mse(d, z, fit.scale, fit.shift)
    for got in (depth.si_mse(d, z, alignment=fit), depth.si_mse(d, z, alignment=fit, valid=valid), depth.si_mse(d, z)):
        np.testing.assert_allclose(got.per_frame, want, rtol=0, atol=1e-12)
    assert np.isnan(want[2])


def test_registry_shares_one_validity_mask_between_si_mse_and_ate3d():
    rng = np.random.default_rng(5)
    d, z = _depth(rng, t=4)
    n_pts, t_len = 6, 4
    tracks = rng.uniform(0, 30, (n_pts, t_len, 2))
    vis = np.ones((n_pts, t_len), bool)
    x = MetricInputs(ref_rgb=np.zeros((t_len, 30, 40, 3), np.uint8), gen_rgb=np.zeros((t_len, 30, 40, 3), np.uint8),
                     ref_masks=np.zeros((t_len, 2, 30, 40), bool), gen_masks=np.zeros((t_len, 2, 30, 40), bool),
                     ref_tracks=tracks, gen_tracks=tracks, ref_visibility=vis, gen_visibility=vis,
                     track_actor=np.repeat([0, 1], 3), ref_depth_m=z, gen_disparity=d, K=np.diag([40.0, 40.0, 1.0]),
                     camera_to_world=np.eye(4), actor_positions_m=rng.normal(size=(2, t_len, 3)),
                     ref_points_m=np.zeros((n_pts, t_len, 3)), bg_tracks=np.zeros((0, t_len, 2)),
                     bg_confidence=np.zeros((0, t_len)))
    si = METRICS["si_mse"].load()(x)
    METRICS["ate3d"].load()(x)
    assert set(x._shared) == {"depth_validity", "disparity_alignment"}
    scale, shift = ref_fit(d, z)
    np.testing.assert_allclose(si.per_frame, ref_si_mse(d, z, scale, shift), rtol=0, atol=1e-12)


def test_patch_preparation_matches_the_previous_implementation():
    rng = np.random.default_rng(2)
    frame = rng.integers(0, 256, (90, 120, 3), dtype=np.uint8)
    centres = np.array([[60.0, 45.0], [33.4, 50.6], [2.0, 40.0], [119.0, 89.0], [60.0, 1.0], [80.5, 44.5]])
    patches = identity.extract_patches(frame, centres)
    assert len({p.shape for p in patches}) > 1  # border crops of several shapes
    got = identity.preprocess_patches(patches).numpy()
    np.testing.assert_allclose(got, ref_preprocess(patches).numpy(), rtol=0, atol=1e-6)
    same = [p for p in patches if p.shape == (64, 64, 3)]
    np.testing.assert_allclose(identity.preprocess_patches(np.stack(same)).numpy(), ref_preprocess(same).numpy(),
                               rtol=0, atol=1e-6)
