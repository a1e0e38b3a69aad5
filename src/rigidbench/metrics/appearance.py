"""Full-frame metrics: SSIM and LPIPS (paper eqs. appendix-ssim, appendix-lpips), both averaged
over every frame including frame 0.

SSIM reproduces `pytorch_msssim.ssim(X, Y, data_range=255, size_average=False)` on (1, 3, H, W)
float32 frames: an 11-tap Gaussian (sigma 1.5) built exactly as pytorch_msssim builds it,
applied separably with 'valid' support (the border of 5 pixels is dropped), K = (0.01, 0.03),
SSIM map averaged per channel and then over channels. The filtering runs in float32 with
OpenCV, one frame at a time in a small thread pool (frames split over the cores this process may
use), so a 49 x 704 x 1280 clip needs a few hundred MB instead of the ~11 GB of a whole-clip torch
call; the per-pixel formula then runs on cache-sized strips of rows and each strip's map is summed
in float64 by OpenCV. Values agree with pytorch_msssim to float32 rounding (~1e-7); the cost is
within about 1.5x of the five Gaussian filters alone (`benchmarks/metrics.py`, ssim_filter_floor).
"""

from __future__ import annotations

import threading
from concurrent.futures import ThreadPoolExecutor
from typing import Callable

import numpy as np

from rigidbench.executors import usable_cores
from rigidbench.metrics.common import MetricResult, check_same_shape, finite_mean, infer_device

SSIM_WIN_SIZE = 11
SSIM_WIN_SIGMA = 1.5
SSIM_K = (0.01, 0.03)


def _check_rgb(ref_rgb: np.ndarray, gen_rgb: np.ndarray) -> None:
    check_same_shape("reference RGB", ref_rgb, "generated RGB", gen_rgb)
    if ref_rgb.ndim != 4 or ref_rgb.shape[-1] != 3:
        raise ValueError(f"RGB clips must be (T, H, W, 3), got shape {ref_rgb.shape}")


def gaussian_window(size: int = SSIM_WIN_SIZE, sigma: float = SSIM_WIN_SIGMA) -> np.ndarray:
    """Returns the (size,) float32 Gaussian window, normalised in float32 like pytorch_msssim's."""
    coords = np.arange(size, dtype=np.float32) - np.float32(size // 2)
    g = np.exp(-(coords ** 2) / np.float32(2 * sigma ** 2)).astype(np.float32)
    return (g / g.sum(dtype=np.float32)).astype(np.float32)


#: Rows of the SSIM map combined at a time: the per-pixel formula runs on strips whose temporaries
#: stay in the core's cache instead of streaming five full-frame float32 maps through memory.
SSIM_STRIP_ROWS = 32


class _SSIMWorkspace:
    """Reusable float32 buffers: (H, W, C) for the two inputs, a product and the five filtered maps,
    and (SSIM_STRIP_ROWS, W, C) strip temporaries; reusing them avoids page-faulting ~90 MB per frame."""

    def __init__(self, shape: tuple[int, ...]) -> None:
        self.shape = shape
        self.x, self.y, self.tmp, self.mu1, self.mu2, self.s11, self.s22, self.s12 = (
            np.empty(shape, np.float32) for _ in range(8))
        strip = (min(SSIM_STRIP_ROWS, shape[0]),) + tuple(shape[1:])
        self.m11, self.m22, self.m12, self.den = (np.empty(strip, np.float32) for _ in range(4))


#: Workspaces kept between ``ssim`` calls (those of the last clip's shape, at most this many: 87 MB each at
#: 1280 x 704), so that the next clip, often the next sample of the same example, faults in no new memory.
SSIM_SPARE_WORKSPACES = 4
_SPARE: list[_SSIMWorkspace] = []
_SPARE_LOCK = threading.Lock()


def _spare_workspace(shape: tuple[int, ...]) -> _SSIMWorkspace:
    """A kept workspace for frames of ``shape`` (removed from the spares), else a new one."""
    with _SPARE_LOCK:
        for k, ws in enumerate(_SPARE):
            if ws.shape == shape:
                return _SPARE.pop(k)
    return _SSIMWorkspace(shape)


def _workspace(store: threading.local, shape: tuple[int, ...]) -> _SSIMWorkspace:
    """The calling thread's workspace in `store`, (re)allocated when the frame shape changes."""
    ws = getattr(store, "ws", None)
    if ws is None or ws.shape != shape:
        ws = store.ws = _SSIMWorkspace(shape)
    return ws


def _ssim_valid_mean(ws: "_SSIMWorkspace", s11_full: np.ndarray, valid_box: tuple[int, int, int, int],
                     channels: int, data_range: float) -> np.ndarray:
    """The per-channel mean of the SSIM map over the valid rows r0:r1 and columns c0:c1 (``valid_box``), from
    the filtered maps in ``ws`` (mu1, mu2, s22, s12; overwritten) and the reference's filtered square
    ``s11_full`` (read only)."""
    import cv2

    r0, r1, c0, c1 = valid_box
    # Same operations, in the same order and float32 precision, as pytorch_msssim._ssim, on strips of
    # the valid rows; each strip's map is summed in float64 by OpenCV (no copy of the strided interior).
    c1_ = np.float32((SSIM_K[0] * data_range) ** 2)
    c2_ = np.float32((SSIM_K[1] * data_range) ** 2)
    total = np.zeros(max(4, channels))
    for top in range(r0, r1, SSIM_STRIP_ROWS):
        n = min(SSIM_STRIP_ROWS, r1 - top)
        rows = slice(top, top + n)
        mu1, mu2 = ws.mu1[rows], ws.mu2[rows]
        s11, s22, s12 = s11_full[rows], ws.s22[rows], ws.s12[rows]
        m11, m22, m12, den = ws.m11[:n], ws.m22[:n], ws.m12[:n], ws.den[:n]
        np.multiply(mu1, mu1, out=m11)
        np.multiply(mu2, mu2, out=m22)
        np.multiply(mu1, mu2, out=m12)
        # cs = (2 (s12 - mu1 mu2) + C2) / ((s11 - mu1^2) + (s22 - mu2^2) + C2)
        s12 -= m12
        s12 *= 2
        s12 += c2_
        np.subtract(s11, m11, out=den)
        s22 -= m22
        den += s22
        den += c2_
        s12 /= den
        # luminance = (2 mu1 mu2 + C1) / (mu1^2 + mu2^2 + C1)
        m12 *= 2
        m12 += c1_
        m11 += m22
        m11 += c1_
        m12 /= m11
        m12 *= s12
        valid = m12[:, c0:c1]
        if channels <= 4:
            total[:channels] += cv2.sumElems(valid)[:channels]
        else:  # OpenCV's sum takes at most four channels
            total += valid.reshape(-1, channels).sum(axis=0, dtype=np.float64)
    return total[:channels] / float((r1 - r0) * (c1 - c0))


def ssim_frame(ref: np.ndarray, gen: np.ndarray, data_range: float = 255.0,
               store: threading.local | None = None, ref_maps: dict | None = None) -> float:
    """ref, gen: (H, W, C) uint8 or float. Returns single-scale SSIM (mean over channels of the mean
    SSIM map); `store` lets consecutive calls in one thread reuse their buffers. ``ref_maps``: a dict where the
    reference frame's filtered square (the costliest of its two maps: a float32 product and filter; its mean
    is filtered from the uint8 frame, cheaply, each time) is kept ("sq") and found, so that the samples of one
    example compute it once: the same numbers."""
    import cv2

    ref, gen = np.asarray(ref), np.asarray(gen)
    shape = ref.shape if ref.ndim == 3 else ref.shape + (1,)
    ws = _workspace(store if store is not None else threading.local(), shape)
    np.copyto(ws.x, np.asarray(ref).reshape(shape), casting="unsafe")
    np.copyto(ws.y, np.asarray(gen).reshape(shape), casting="unsafe")
    h, w, channels = shape
    win = gaussian_window()
    half = SSIM_WIN_SIZE // 2
    one = np.ones(1, dtype=np.float32)
    # pytorch_msssim skips smoothing along a dimension shorter than the window.
    kx, (c0, c1) = (win, (half, w - half)) if w >= SSIM_WIN_SIZE else (one, (0, w))
    ky, (r0, r1) = (win, (half, h - half)) if h >= SSIM_WIN_SIZE else (one, (0, h))

    def blur(src: np.ndarray, dst: np.ndarray) -> None:
        # Filtered over the whole frame; only the 'valid' interior is used in the end,
        # so the border mode never reaches the result.
        out = cv2.sepFilter2D(src, cv2.CV_32F, kx, ky, dst=dst, borderType=cv2.BORDER_REFLECT)
        if not np.shares_memory(out, dst):  # OpenCV reallocated (e.g. a single-channel frame)
            dst[...] = out.reshape(dst.shape)

    x, y, tmp = ws.x, ws.y, ws.tmp
    # OpenCV filters uint8 frames with the same float32 arithmetic as their float32 copies (bit for
    # bit), reading a quarter of the bytes.
    as_u8 = [np.ascontiguousarray(v).reshape(shape) if v.dtype == np.uint8 and shape[2] <= 4 else None
             for v in (ref, gen)]
    blur(x if as_u8[0] is None else as_u8[0], ws.mu1)
    kept = None if ref_maps is None else ref_maps.get("sq")
    if kept is not None and kept.shape == shape:
        s11_full = kept  # not written below
    else:
        s11_full = ws.s11 if ref_maps is None else np.empty(shape, np.float32)
        np.multiply(x, x, out=tmp)
        blur(tmp, s11_full)
        if ref_maps is not None:
            s11_full.flags.writeable = False
            ref_maps["sq"] = s11_full
    blur(y if as_u8[1] is None else as_u8[1], ws.mu2)
    np.multiply(y, y, out=tmp)
    blur(tmp, ws.s22)
    np.multiply(x, y, out=tmp)
    blur(tmp, ws.s12)
    per_channel = _ssim_valid_mean(ws, s11_full, (r0, r1, c0, c1), channels, data_range)
    return float(per_channel.mean())


def ssim_workers(frames: int) -> int:
    """Threads SSIM splits `frames` frames over: the cores this process may use, at most 4 and at most `frames`."""
    return usable_cores(min(4, max(frames, 1)))


def ssim(ref_rgb: np.ndarray, gen_rgb: np.ndarray, workers: int | None = None,
         ref_maps: dict | None = None) -> MetricResult:
    """ref_rgb, gen_rgb: (T, H, W, 3) uint8. Returns mean SSIM (data range 255) over all frames and (T,) per frame.
    ``ref_maps``: frame index -> that reference frame's kept map (``ssim_frame``), kept between calls with the
    same ``ref_rgb`` (the samples of one example: one of the five filters per frame, the costliest, and one
    product are not done again)."""
    _check_rgb(ref_rgb, gen_rgb)
    workers = workers or ssim_workers(ref_rgb.shape[0])
    frames = range(ref_rgb.shape[0])
    store = threading.local()  # one workspace per thread, given back for the next call when this one returns
    shape = tuple(ref_rgb.shape[1:])
    taken: list[_SSIMWorkspace] = []

    def one(t: int) -> float:
        if getattr(store, "ws", None) is None:
            store.ws = _spare_workspace(shape)
            taken.append(store.ws)
        maps = None if ref_maps is None else ref_maps.setdefault(t, {})  # (dict.setdefault: atomic under the GIL)
        return ssim_frame(ref_rgb[t], gen_rgb[t], store=store, ref_maps=maps)

    try:
        if workers == 1:
            values = [one(t) for t in frames]
        else:
            # OpenCV and numpy release the GIL, so frames run in parallel without copies.
            with ThreadPoolExecutor(max_workers=workers) as pool:
                values = list(pool.map(one, frames))
    finally:
        with _SPARE_LOCK:
            _SPARE[:] = (taken + [ws for ws in _SPARE if ws.shape == shape])[:SSIM_SPARE_WORKSPACES]
    per_frame = np.asarray(values, dtype=np.float64)
    return MetricResult(finite_mean(per_frame), per_frame)


def rgb_to_lpips_input(rgb: np.ndarray, device: str | None = None):
    """rgb: (B, H, W, 3) uint8. Returns a (B, 3, H, W) float32 torch tensor in [-1, 1]."""
    import torch

    rgb = np.ascontiguousarray(rgb)
    if not rgb.flags.writeable:  # a shared read-only view (the example's reference side): torch wants its own
        rgb = rgb.copy()
    x = torch.from_numpy(rgb).to(device=device)
    return x.permute(0, 3, 1, 2).float().div_(127.5).sub_(1.0)


def lpips(ref_rgb: np.ndarray, gen_rgb: np.ndarray, net: Callable, batch_size: int = 4,
          device: str | None = None) -> MetricResult:
    """ref_rgb, gen_rgb: (T, H, W, 3) uint8; net(x, y) on (B, 3, H, W) in [-1, 1] returns (B,) or
    (B, 1, 1, 1) distances; inputs go to `device`, by default the device of net's parameters.
    Returns the mean LPIPS over all frames and (T,) per frame."""
    import torch

    _check_rgb(ref_rgb, gen_rgb)
    device = infer_device(net, device)
    if batch_size < 1:
        raise ValueError(f"batch_size must be >= 1, got {batch_size}")
    values = []
    with torch.inference_mode():
        for start in range(0, ref_rgb.shape[0], batch_size):
            x = rgb_to_lpips_input(ref_rgb[start:start + batch_size], device)
            y = rgb_to_lpips_input(gen_rgb[start:start + batch_size], device)
            d = net(x, y)
            values.append(d.reshape(d.shape[0], -1)[:, 0].float().cpu().numpy())
    per_frame = np.concatenate(values).astype(np.float64) if values else np.zeros(0)
    return MetricResult(finite_mean(per_frame), per_frame)


# -- registry adapters: compute(MetricInputs) -> MetricResult | None (None: network unavailable) ------


#: The most memory SSIM's reference maps may take to be kept for the other samples of an example (one float32
#: map per frame: 530 MB for 49 frames of 1280 x 704).
SSIM_MAPS_MAX_BYTES = 1024 ** 3


def score_ssim(x) -> MetricResult:
    """SSIM; the reference's filtered maps are kept for the next samples of the example when there are more
    (``MetricInputs.reference_samples``) and they fit in ``SSIM_MAPS_MAX_BYTES``."""
    keep = x.reference_samples > 1 and 4 * x.ref_rgb.size <= SSIM_MAPS_MAX_BYTES
    return ssim(x.ref_rgb, x.gen_rgb, ref_maps=x.reference_shared("ssim_maps", dict) if keep else None)


def score_lpips(x) -> MetricResult | None:
    return lpips(x.ref_rgb, x.gen_rgb, x.lpips_net) if x.lpips_net is not None else None
