"""SSIM against pytorch_msssim, and the LPIPS frame loop with a tiny network."""

import numpy as np
import pytest

from rigidbench.metrics.appearance import gaussian_window, lpips, ssim

torch = pytest.importorskip("torch")
pytorch_msssim = pytest.importorskip("pytorch_msssim")


def reference_ssim(x, y):
    """(T, H, W, 3) uint8 -> (T,) pytorch_msssim values on NCHW float32."""
    tx = torch.from_numpy(x).permute(0, 3, 1, 2).float()
    ty = torch.from_numpy(y).permute(0, 3, 1, 2).float()
    return pytorch_msssim.ssim(tx, ty, data_range=255, size_average=False).numpy()


def test_window_matches_pytorch_msssim():
    from pytorch_msssim.ssim import _fspecial_gauss_1d

    np.testing.assert_allclose(gaussian_window(), _fspecial_gauss_1d(11, 1.5).numpy().ravel(), rtol=1e-6)


@pytest.mark.parametrize("shape", [(3, 24, 40), (2, 37, 29), (1, 64, 96)])
def test_ssim_equals_pytorch_msssim_on_random_frames(shape):
    rng = np.random.default_rng(sum(shape))
    x = rng.integers(0, 256, shape + (3,), dtype=np.uint8)
    y = np.clip(x.astype(int) + rng.integers(-60, 61, x.shape), 0, 255).astype(np.uint8)
    expected = reference_ssim(x, y)
    r = ssim(x, y)
    np.testing.assert_allclose(r.per_frame, expected, atol=1e-6)
    assert r.value == pytest.approx(expected.mean(), abs=1e-6)


def test_ssim_on_smooth_frames_matches_to_float32_rounding():
    import cv2

    rng = np.random.default_rng(3)
    x = np.stack([cv2.GaussianBlur(rng.integers(0, 256, (48, 64, 3), dtype=np.uint8), (0, 0), 4)
                  for _ in range(2)])
    y = np.clip(x.astype(int) + rng.integers(-3, 4, x.shape), 0, 255).astype(np.uint8)
    np.testing.assert_allclose(ssim(x, y).per_frame, reference_ssim(x, y), atol=1e-5)


def test_ssim_frame_smaller_than_window_in_one_dimension():
    rng = np.random.default_rng(4)
    x = rng.integers(0, 256, (1, 8, 40, 3), dtype=np.uint8)
    y = rng.integers(0, 256, (1, 8, 40, 3), dtype=np.uint8)
    with pytest.warns(UserWarning):  # pytorch_msssim skips smoothing along the short axis
        expected = reference_ssim(x, y)
    np.testing.assert_allclose(ssim(x, y).per_frame, expected, atol=1e-6)


def test_ssim_identical_is_one_and_threads_do_not_change_values():
    rng = np.random.default_rng(5)
    x = rng.integers(0, 256, (4, 30, 40, 3), dtype=np.uint8)
    y = rng.integers(0, 256, (4, 30, 40, 3), dtype=np.uint8)
    assert ssim(x, x.copy()).value == pytest.approx(1.0, abs=1e-7)
    np.testing.assert_array_equal(ssim(x, y, workers=1).per_frame, ssim(x, y, workers=3).per_frame)


class MeanAbsDiff(torch.nn.Module):
    """Tiny stand-in for LPIPS: mean |x - y| per image, returned as (B, 1, 1, 1)."""

    def forward(self, x, y):
        return (x - y).abs().mean(dim=(1, 2, 3)).view(-1, 1, 1, 1)


def test_lpips_maps_rgb_to_unit_range_and_averages_frames():
    ref = np.zeros((5, 6, 7, 3), np.uint8)
    gen = np.zeros((5, 6, 7, 3), np.uint8)
    gen[0] = 255  # -1 vs +1 everywhere: distance 2
    gen[1, :3] = 255  # half the image: distance 1
    r = lpips(ref, gen, MeanAbsDiff(), batch_size=2)
    np.testing.assert_allclose(r.per_frame, [2.0, 1.0, 0.0, 0.0, 0.0], atol=1e-6)
    assert r.value == pytest.approx(3.0 / 5, abs=1e-6)
    np.testing.assert_allclose(lpips(ref, gen, MeanAbsDiff(), batch_size=8).per_frame, r.per_frame)
    assert lpips(gen, gen.copy(), MeanAbsDiff()).value == 0.0


def test_lpips_accepts_flat_outputs():
    ref = np.zeros((3, 4, 4, 3), np.uint8)
    r = lpips(ref, ref + 51, lambda x, y: (y - x).mean(dim=(1, 2, 3)))
    np.testing.assert_allclose(r.per_frame, 0.4, atol=1e-6)  # 51 / 127.5
