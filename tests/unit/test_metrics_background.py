"""BGDrift and the background corner detector."""

import math

import numpy as np
import pytest

from rigidbench.metrics.background import bgdrift, detect_background_corners

pytest.importorskip("cv2")

H, W, T = 704, 1280, 49


def random_corners(rng, n=200):
    return rng.uniform([20, 20], [W - 20, H - 20], (n, 2))


def test_static_and_coherent_motion_give_zero():
    rng = np.random.default_rng(0)
    x0 = random_corners(rng)
    conf = rng.uniform(0.2, 1.0, (200, T))
    static = np.repeat(x0[:, None], T, axis=1)
    assert bgdrift(static, conf, H).value == pytest.approx(0.0, abs=1e-9)
    # coherent translation plus a slow rotation and zoom about the image centre
    tracks = np.empty((200, T, 2))
    centre = np.array([W / 2, H / 2])
    for t in range(T):
        a, s = 0.002 * t, 1 + 0.001 * t
        rot = s * np.array([[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]])
        tracks[:, t] = (x0 - centre) @ rot.T + centre + [0.8 * t, -0.5 * t]
    assert bgdrift(tracks, conf, H).value < 1e-5


def test_independent_jitter_is_not_absorbed():
    rng = np.random.default_rng(1)
    x0 = random_corners(rng)
    conf = np.ones((200, T))
    mean_disp = 20.0
    sigma = mean_disp / math.sqrt(math.pi / 2)  # 2D Gaussian with this mean displacement
    angle = np.linspace(0, np.pi, T)  # direction changes over time, magnitude fixed
    coherent = x0[:, None] + mean_disp * np.stack([np.cos(angle), np.sin(angle)], axis=-1)[None]
    coherent[:, 0] = x0
    jitter = np.repeat(x0[:, None], T, axis=1) + rng.normal(0.0, sigma, (200, T, 2))
    jitter[:, 0] = x0
    assert np.mean(np.linalg.norm(coherent[:, 1:] - x0[:, None], axis=-1)) == pytest.approx(mean_disp)
    assert bgdrift(coherent, conf, H).value < 1e-5
    # the fit cannot remove independent motion: residual ~ the jitter itself
    assert bgdrift(jitter, conf, H).value > 0.5 * mean_disp / H


def test_weights_and_outlier_by_hand():
    x0 = np.array([[100.0, 100.0], [300.0, 120.0], [180.0, 400.0], [500.0, 350.0], [250.0, 250.0]])
    tracks = np.stack([x0, x0 + [10.0, 0.0]], axis=1)
    tracks[4, 1] += [0.0, 30.0]  # one corner moves 30 px against the others
    conf = np.ones((5, 2))
    conf[4, 0] = 0.5
    r = bgdrift(tracks, conf, 100)
    assert r.value == pytest.approx(0.5 * 30 / 4.5 / 100, rel=1e-4)
    assert math.isnan(r.per_frame[0])
    assert r.per_frame[1] == pytest.approx(r.value)


def test_frames_with_too_few_corners_are_skipped():
    rng = np.random.default_rng(2)
    x0 = random_corners(rng, 6)
    tracks = np.stack([x0, x0 + rng.normal(0, 5, x0.shape), x0 + 1.0], axis=1)
    conf = np.ones((6, 3))
    conf[:3, 1] = 0.0  # frame 1 keeps 3 corners: skipped
    r = bgdrift(tracks, conf, H)
    assert math.isnan(r.per_frame[1])
    assert r.value == pytest.approx(0.0, abs=1e-6)  # only the coherent frame 2 counts
    conf[:, 2] = 0.0
    assert math.isnan(bgdrift(tracks, conf, H).value)


def test_raw_displacement_when_ransac_gives_no_transform():
    # All corners at one point: no similarity can be estimated, so the residual is ||x_t - x_0||.
    tracks = np.zeros((5, 2, 2))
    tracks[:, 1] = [3.0, 4.0]
    assert bgdrift(tracks, np.ones((5, 2)), 10).value == pytest.approx(0.5)


def test_corner_detector_respects_eroded_background_and_pixel_convention():
    import cv2

    yy, xx = np.mgrid[0:240, 0:320]
    board = (((yy // 20) + (xx // 20)) % 2 * 255).astype(np.uint8)
    rgb = np.repeat(board[..., None], 3, axis=2)
    masks = np.zeros((2, 240, 320), bool)
    masks[0, 60:140, 100:180] = True
    masks[1, 150:200, 220:300] = True
    corners = detect_background_corners(rgb, masks)
    assert 0 < len(corners) <= 200
    # every corner lies in the background eroded by the 31x31 ellipse
    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (31, 31))
    allowed = cv2.erode((~masks.any(0)).astype(np.uint8), kernel).astype(bool)
    cols, rows = np.floor(corners).astype(int).T
    assert allowed[rows, cols].all()
    # checker corners sit on pixel boundaries, multiples of 20 in continuous coordinates
    off = np.abs((corners + 10) % 20 - 10)
    assert np.all(off <= 1.0)
    d = np.linalg.norm(corners[:, None] - corners[None], axis=-1) + np.eye(len(corners)) * 1e9
    assert d.min() >= 10 - 1e-6
