"""Metric registry and shared helpers (nested mean, bilinear sampling, camera, geometric median)."""

import math
import subprocess
import sys

import numpy as np
import pytest

from rigidbench.metrics import METRICS, MetricResult, get_metric
from rigidbench.metrics.common import geometric_median, nested_mean, project, sample_bilinear, unproject


def test_registry_order_names_and_directions():
    assert list(METRICS) == ["iou", "centroid_l2", "chamfer", "ate", "ate3d", "si_mse", "ssim", "lpips",
                             "iddrift", "bgdrift"]
    assert [m.display_name for m in METRICS.values()] == ["IoU", "L2", "Cham.", "ATE", "ATE-3D", "SI-MSE",
                                                          "SSIM", "LPIPS", "IdDrift", "BGDrift"]
    assert {n for n, m in METRICS.items() if m.higher_is_better} == {"iou", "ssim"}
    assert METRICS["ssim"].direction == "higher" and METRICS["ate3d"].direction == "lower"


def test_every_entry_loads_a_function():
    for info in METRICS.values():
        assert callable(info.load()), info.name


def test_lookup_by_display_name_and_typo_hint():
    assert get_metric("ATE-3D").name == "ate3d"
    assert get_metric("Cham.").name == "chamfer"
    with pytest.raises(KeyError, match="Did you mean 'bgdrift'"):
        get_metric("bgdrfit")


def test_package_import_is_light():
    code = "import sys, rigidbench.metrics; print('torch' in sys.modules, 'cv2' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.split() == ["False", "False"]


def test_nested_mean_skips_undefined():
    q = np.array([[1.0, 3.0], [5.0, np.nan], [np.nan, np.inf]])
    r = nested_mean(q)
    assert isinstance(r, MetricResult)
    assert r.value == pytest.approx((2.0 + 5.0) / 2)
    np.testing.assert_array_equal(np.isnan(r.per_frame), [False, False, True])


def test_bilinear_sampling_convention():
    img = np.add.outer(10.0 * np.arange(4), np.arange(5))  # value = 10 * row + col
    # pixel (row 1, col 2) has its centre at x = 2, y = 1 (OpenCV / CoTracker convention)
    np.testing.assert_allclose(sample_bilinear(img, np.array([[2.0, 1.0], [2.5, 1.5], [-0.4, -0.3]])),
                               [12.0, 17.5, 0.0])  # the last is within half a pixel of the corner
    assert np.isnan(sample_bilinear(img, np.array([[4.6, 1.0], [-0.6, 1.0]]))).all()
    img[1, 3] = np.nan
    assert sample_bilinear(img, np.array([[2.0, 1.0]]))[0] == 12.0  # NaN neighbour with zero weight
    assert np.isnan(sample_bilinear(img, np.array([[2.5, 1.0]]))[0])


def test_blender_camera_convention():
    K = np.array([[100.0, 0, 50], [0, 100.0, 40], [0, 0, 1]])
    R_c, t_c = np.eye(3), np.zeros(3)  # Blender camera at the origin looks down world -Z, +Y up
    xy, depth = project(np.array([[0.0, 0, -5], [1.0, 0, -5], [0.0, 1, -5]]), K, R_c, t_c)
    np.testing.assert_allclose(depth, 5.0)
    np.testing.assert_allclose(xy, [[50, 40], [70, 40], [50, 20]])  # right is +x, up is -y
    np.testing.assert_allclose(unproject(xy, depth, K, R_c, t_c), [[0, 0, -5], [1, 0, -5], [0, 1, -5]], atol=1e-12)


def test_geometric_median():
    np.testing.assert_allclose(geometric_median(np.array([[0.0, 0, 0], [1, 0, 0], [10, 0, 0]])), [1, 0, 0], atol=1e-4)
    square = np.array([[1.0, 1, 0], [-1, 1, 0], [1, -1, 0], [-1, -1, 0]]) + 2.0
    np.testing.assert_allclose(geometric_median(square), [2, 2, 2], atol=1e-12)
    assert math.isnan(geometric_median(np.zeros((0, 3)))[0])
    # robust to an outlier, unlike the mean
    pts = np.vstack([np.random.default_rng(0).normal(0, 0.01, (9, 3)), [[100.0, 0, 0]]])
    assert np.linalg.norm(geometric_median(pts)) < 0.05


def test_infer_device_follows_the_network():
    torch = pytest.importorskip("torch")
    from rigidbench.metrics.common import infer_device

    assert infer_device(torch.nn.Linear(2, 2)) == torch.device("cpu")
    assert infer_device(lambda x: x) is None
    assert infer_device(torch.nn.Linear(2, 2), "meta") == "meta"
