"""Time the metric stage on one synthetic paper-size clip and print JSON.

One 49-frame 1280x704 clip with 4 actors, 80 tracks (20 per actor) and up to 200 background
corners, with perception arrays (masks, tracks, disparity, corner tracks) given. Reports
seconds and memory for the eight array metrics together and one by one, then LPIPS (the
torchvision-free AlexNet, random weights) and IdDrift separately.

Wall seconds and process CPU seconds (user + system, all threads) are both reported: on a
shared machine the wall time includes waiting for the CPU, the CPU time does not.

Memory is reported three ways, because each misses something:
  tracemalloc_peak_mb  numpy/Python allocations only (OpenCV and torch buffers are invisible);
  rss_peak_delta_mb    peak resident set during the stage (VmHWM after resetting it through
                       /proc/self/clear_refs, or a 2 ms RSS sampler if that is not permitted)
                       minus the resident set at its start: everything, including native code;
  ru_maxrss_delta_mb   growth of getrusage's peak over the stage; where clear_refs works it is
                       reset with VmHWM (so it matches rss_peak_delta_mb), otherwise it is 0
                       whenever an earlier step peaked higher, i.e. only a lower bound.

IdDrift with a real DINOv2 ViT-L/14 is far too slow on a CPU to run on a whole clip, so the
script (a) times the full IdDrift computation with a small convolutional feature net, which
measures patch extraction, resizing and bookkeeping, and (b) times a randomly initialised
ViT-L/14-sized transformer (plain torch, same widths and depth as DINOv2-L: 24 blocks, width
1024, 16 heads, MLP 4096, 14-pixel patches, 257 tokens) on a few patches and extrapolates to
the clip's patch count.

Every metric is called the way the evaluator calls it: through the registry
(``METRICS[name].load()``) on one ``MetricInputs`` per example, so ATE-3D and SI-MSE share one
disparity alignment in ``array_metrics_total`` (the one-by-one rows refit it, each on fresh inputs).
``--repeat N`` times the array metrics N times and reports the fastest (min of N wall and, separately,
of N CPU seconds; the runs are interleaved with the one-by-one rows); only the first run has
tracemalloc on, so with N >= 2 the times are free of its overhead. ``ssim_filter_floor`` is the cost of the filtering alone: the
five separable 11-tap Gaussian filters per frame (cv2.sepFilter2D on float32 (H, W, 3)), frames split
over the same threads as SSIM; SSIM cannot cost less than that.

Printed JSON: ``machine`` (cpus, torch_threads, python), ``clip`` (frames, width, height, actors,
tracks, corners, build_seconds, iddrift_pairs), ``timings`` (per row: seconds, cpu_seconds and the
three memory figures), ``values`` (the ten metric values, rounded to 1e-6), ``target``.

Usage: .venv/bin/python benchmarks/metrics.py [--frames 49] [--repeat 3] [--skip-vit] [--vit-patches 8]
       .venv/bin/python benchmarks/metrics.py --quick      # 4 frames at 320x176, no ViT (seconds)
"""

from __future__ import annotations

import argparse
import gc
import json
import os
import resource
import sys
import threading
import time
import tracemalloc
from contextlib import contextmanager

import numpy as np

WIDTH, HEIGHT, N_ACTORS, POINTS_PER_ACTOR = 1280, 704, 4, 20


def _rss_mb() -> float:
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2**20


def _hwm_mb() -> float | None:
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) / 1024
    return None


def _reset_hwm() -> bool:
    try:
        with open("/proc/self/clear_refs", "w") as f:
            f.write("5")
        return True
    except OSError:
        return False


@contextmanager
def measure(results: dict, name: str, trace: bool = True):
    """Record seconds and the three memory figures of the enclosed block under results[name].

    ``trace=False`` leaves tracemalloc off (its hook on every Python allocation slows code that makes
    many small numpy calls, such as SSIM's strips, by a third): timed repeats run without it."""
    gc.collect()
    rss0 = _rss_mb()
    hwm_reset = _reset_hwm()  # also lowers getrusage's peak to the current RSS on Linux
    usage0 = resource.getrusage(resource.RUSAGE_SELF)
    maxrss0 = usage0.ru_maxrss / 1024
    samples = [rss0]
    stop = threading.Event()

    def sample():
        while not stop.wait(0.002):
            samples.append(_rss_mb())

    sampler = threading.Thread(target=sample, daemon=True)
    if not hwm_reset:  # VmHWM gives the peak where clear_refs works; sample only where it does not
        sampler.start()
    if trace:
        tracemalloc.start()
    t0 = time.perf_counter()
    try:
        yield
    finally:
        seconds = time.perf_counter() - t0
        usage = resource.getrusage(resource.RUSAGE_SELF)
        cpu = usage.ru_utime + usage.ru_stime - usage0.ru_utime - usage0.ru_stime
        peak = tracemalloc.get_traced_memory()[1] if trace else None
        if trace:
            tracemalloc.stop()
        stop.set()
        if sampler.is_alive():
            sampler.join()
        hwm = _hwm_mb() if hwm_reset else None
        peak_rss = max(max(samples), hwm or 0.0)
        results[name] = {
            "seconds": round(seconds, 3),
            "cpu_seconds": round(cpu, 3),
            "tracemalloc_peak_mb": None if peak is None else round(peak / 2**20, 1),
            "rss_peak_delta_mb": round(peak_rss - rss0, 1),
            "rss_peak_method": "VmHWM reset via clear_refs" if hwm_reset else "2 ms RSS sampling",
            "ru_maxrss_delta_mb": round(usage.ru_maxrss / 1024 - maxrss0, 1),
        }


def camera():
    """K (3,3), Blender camera-to-world R_c, t_c: 35 mm lens on a 36 mm sensor, 2.5 m from the scene."""
    f = 35.0 / 36.0 * WIDTH
    K = np.array([[f, 0.0, WIDTH / 2], [0.0, f, HEIGHT / 2], [0.0, 0.0, 1.0]])
    cam = np.array([0.0, -2.5, 0.45])
    forward = np.array([0.0, 1.0, -0.18])
    forward /= np.linalg.norm(forward)
    right = np.cross(forward, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    up = np.cross(right, forward)
    return K, np.column_stack([right, up, -forward]), cam


def build_clip(frames: int, seed: int = 0) -> dict:
    """Synthetic reference and generated clips with perception arrays."""
    import cv2

    from rigidbench.metrics.common import project

    rng = np.random.default_rng(seed)
    K, R_c, t_c = camera()
    t = np.arange(frames) / 24.0
    start = np.array([[-0.5, 0.0, 0.3], [-0.15, 0.2, 0.35], [0.2, -0.1, 0.3], [0.5, 0.3, 0.4]])
    velocity = np.array([[0.4, 0.0, 0.0], [0.0, -0.3, 0.0], [-0.2, 0.2, 0.0], [0.0, 0.0, 0.0]])
    fall = np.zeros((frames, 3))
    fall[:, 2] = -0.5 * 9.81 * np.minimum(t, 0.25) ** 2
    ref_pos = start[:, None] + velocity[:, None] * t[None, :, None] + fall[None]
    gen_pos = ref_pos + np.array([0.0, 0.05, 0.01]) * t[None, :, None] * 2  # drifts away over time
    radius_m = 0.06
    right, up = R_c[:, 0], R_c[:, 1]
    offsets = rng.uniform(-1, 1, (N_ACTORS, POINTS_PER_ACTOR, 2)) * radius_m * 0.6
    body = offsets[..., :1] * right + offsets[..., 1:] * up  # (N, 20, 3) points facing the camera
    actor_index = np.repeat(np.arange(N_ACTORS), POINTS_PER_ACTOR)

    def tracks_for(pos):
        pts = pos[:, None] + body[:, :, None]  # (N, 20, T, 3)
        xy, _ = project(pts.reshape(-1, 3), K, R_c, t_c)
        return xy.reshape(N_ACTORS * POINTS_PER_ACTOR, frames, 2)

    texture = cv2.GaussianBlur(rng.integers(0, 256, (HEIGHT, WIDTH, 3), dtype=np.uint8), (0, 0), 2)
    rows = (np.arange(HEIGHT, dtype=np.float32)[:, None] + 0.5) / HEIGHT
    background_depth = np.broadcast_to(6.0 - 3.5 * rows, (HEIGHT, WIDTH)).astype(np.float32)
    colours = rng.integers(30, 230, (N_ACTORS, 3))

    def render(pos, rgb, masks, depth):
        centres, z = project(pos.reshape(-1, 3), K, R_c, t_c)
        centres = centres.reshape(N_ACTORS, frames, 2)
        z = z.reshape(N_ACTORS, frames)
        for f in range(frames):
            rgb[f] = texture
            depth[f] = background_depth
            for a in np.argsort(-z[:, f]):  # far to near
                r_px = int(round(K[0, 0] * radius_m / z[a, f]))
                c = tuple(int(v) for v in np.round(centres[a, f] - 0.5))
                layer = np.zeros((HEIGHT, WIDTH), np.uint8)
                cv2.circle(layer, c, r_px, 1, -1)
                m = layer.astype(bool)
                masks[f, a] = m
                rgb[f][m] = colours[a]
                depth[f][m] = z[a, f]

    shape = (frames, HEIGHT, WIDTH)
    ref_rgb, gen_rgb = np.empty(shape + (3,), np.uint8), np.empty(shape + (3,), np.uint8)
    ref_masks, gen_masks = np.zeros((frames, N_ACTORS, HEIGHT, WIDTH), bool), np.zeros((frames, N_ACTORS, HEIGHT, WIDTH), bool)
    ref_depth, gen_depth = np.empty(shape, np.float32), np.empty(shape, np.float32)
    render(ref_pos, ref_rgb, ref_masks, ref_depth)
    render(gen_pos, gen_rgb, gen_masks, gen_depth)
    for f in range(frames):  # appearance drift and noise in the generated clip
        noise = rng.integers(-6, 7, (HEIGHT, WIDTH, 3), dtype=np.int16)
        gen_rgb[f] = np.clip(gen_rgb[f].astype(np.int16) + noise + f // 8, 0, 255).astype(np.uint8)
    disparity = np.empty(shape, np.float32)
    for f in range(frames):  # affine-ambiguous disparity with multiplicative noise
        disparity[f] = 0.8 / gen_depth[f] * rng.uniform(0.97, 1.03, (HEIGHT, WIDTH)).astype(np.float32) + 0.05
    del gen_depth
    ref_depth[:, :40] = np.inf  # a strip of invalid reference depth, as behind a window

    ref_tracks, gen_tracks = tracks_for(ref_pos), tracks_for(gen_pos) + rng.normal(0, 1.0, (80, frames, 2))
    inside = lambda xy: (xy[..., 0] > 0) & (xy[..., 0] < WIDTH) & (xy[..., 1] > 0) & (xy[..., 1] < HEIGHT)
    ref_vis = inside(ref_tracks) & (rng.random((80, frames)) > 0.05)
    gen_vis = inside(gen_tracks) & (rng.random((80, frames)) > 0.05)

    return dict(K=K, R_c=R_c, t_c=t_c, ref_pos=ref_pos, actor_index=actor_index,
                ref_rgb=ref_rgb, gen_rgb=gen_rgb, ref_masks=ref_masks, gen_masks=gen_masks,
                ref_depth=ref_depth, disparity=disparity, ref_tracks=ref_tracks, gen_tracks=gen_tracks,
                ref_vis=ref_vis, gen_vis=gen_vis)


def corner_tracks(clip: dict, seed: int = 1):
    """Detect corners on generated frame 0 and follow them with a slow drift plus 0.5 px jitter."""
    from rigidbench.metrics.background import detect_background_corners

    rng = np.random.default_rng(seed)
    x0 = detect_background_corners(clip["gen_rgb"][0], clip["gen_masks"][0]).astype(np.float64)
    frames = clip["gen_rgb"].shape[0]
    drift = np.outer(np.arange(frames), [0.3, -0.1])
    tracks = x0[:, None] + drift[None] + rng.normal(0, 0.5, (len(x0), frames, 2))
    tracks[:, 0] = x0
    conf = rng.uniform(0.3, 1.0, (len(x0), frames))
    return tracks, conf


ARRAY_METRICS = ("iou", "centroid_l2", "chamfer", "ate", "ate3d", "si_mse", "ssim", "bgdrift")


def metric_inputs(clip: dict, corners, conf, lpips_net=None, identity_net=None):
    """One ``MetricInputs`` of the synthetic clip, as the evaluator builds it for an example."""
    from rigidbench.metrics import MetricInputs

    c2w = np.eye(4)
    c2w[:3, :3], c2w[:3, 3] = clip["R_c"], clip["t_c"]
    n_points, frames = clip["ref_tracks"].shape[:2]
    return MetricInputs(
        ref_rgb=clip["ref_rgb"], gen_rgb=clip["gen_rgb"], ref_masks=clip["ref_masks"], gen_masks=clip["gen_masks"],
        ref_tracks=clip["ref_tracks"], gen_tracks=clip["gen_tracks"], ref_visibility=clip["ref_vis"],
        gen_visibility=clip["gen_vis"], track_actor=clip["actor_index"], ref_depth_m=clip["ref_depth"],
        gen_disparity=clip["disparity"], K=clip["K"], camera_to_world=c2w, actor_positions_m=clip["ref_pos"],
        ref_points_m=np.zeros((n_points, frames, 3)), bg_tracks=corners, bg_confidence=conf,
        lpips_net=lpips_net, identity_net=identity_net)


def array_metrics(clip: dict, corners, conf) -> dict:
    """The eight metrics that need no neural network, through the registry on one MetricInputs."""
    from rigidbench.metrics import METRICS

    inputs = metric_inputs(clip, corners, conf)
    return {name: METRICS[name].load()(inputs) for name in ARRAY_METRICS}


def ssim_filter_floor(clip: dict) -> None:
    """The five separable Gaussian filters of SSIM on every frame, frames split over SSIM's threads."""
    import cv2

    from rigidbench.metrics import appearance

    win = appearance.gaussian_window()
    frames = clip["ref_rgb"].shape[0]
    shape = clip["ref_rgb"].shape[1:]
    ssim_workers = getattr(appearance, "ssim_workers", lambda n: min(4, os.cpu_count() or 1, n))  # older trees

    def run(part: range) -> None:
        src, dst = np.empty(shape, np.float32), np.empty(shape, np.float32)
        for t in part:
            for _ in range(5):
                cv2.sepFilter2D(src, cv2.CV_32F, win, win, dst=dst, borderType=cv2.BORDER_REFLECT)

    workers = ssim_workers(frames)
    threads = [threading.Thread(target=run, args=(range(i, frames, workers),)) for i in range(workers)]
    for th in threads:
        th.start()
    for th in threads:
        th.join()


def vit_l14():
    """A randomly initialised ViT-L/14-sized image encoder (DINOv2-L widths), plain torch."""
    import torch
    from torch import nn

    class ViT(nn.Module):
        def __init__(self):
            super().__init__()
            self.patch = nn.Conv2d(3, 1024, kernel_size=14, stride=14)
            self.cls = nn.Parameter(torch.zeros(1, 1, 1024))
            self.pos = nn.Parameter(torch.zeros(1, 257, 1024))
            layer = nn.TransformerEncoderLayer(1024, 16, 4096, activation="gelu", batch_first=True, norm_first=True)
            self.blocks = nn.TransformerEncoder(layer, 24, enable_nested_tensor=False)
            self.norm = nn.LayerNorm(1024)

        def forward(self, x):
            tokens = self.patch(x).flatten(2).transpose(1, 2)
            tokens = torch.cat([self.cls.expand(len(x), -1, -1), tokens], dim=1) + self.pos
            return self.norm(self.blocks(tokens))[:, 0]

    return ViT().eval()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=49)
    parser.add_argument("--repeat", type=int, default=1, help="time the array metrics N times; report the fastest")
    parser.add_argument("--skip-vit", action="store_true", help="do not time the ViT-L/14-sized encoder")
    parser.add_argument("--vit-patches", type=int, default=8, help="patches in the timed ViT forward")
    parser.add_argument("--lpips-batch", type=int, default=4)
    parser.add_argument("--quick", action="store_true", help="4 frames at 320x176, no ViT: a smoke run (seconds)")
    parser.add_argument("--array-only", action="store_true",
                        help="only the eight array metrics and the SSIM floor (no LPIPS, IdDrift or ViT)")
    args = parser.parse_args()
    global WIDTH, HEIGHT
    if args.quick:
        WIDTH, HEIGHT = 320, 176
        args.frames, args.skip_vit, args.repeat = min(args.frames, 4), True, 1

    import torch

    from rigidbench.metrics import appearance, identity, lpips_net

    results: dict = {"machine": {"cpus": os.cpu_count(), "torch_threads": torch.get_num_threads(),
                                 "python": sys.version.split()[0]},
                     "clip": {"frames": args.frames, "width": WIDTH, "height": HEIGHT, "actors": N_ACTORS,
                              "tracks": N_ACTORS * POINTS_PER_ACTOR}}
    t0 = time.perf_counter()
    clip = build_clip(args.frames)
    corners, conf = corner_tracks(clip)
    results["clip"]["corners"] = int(len(corners))
    results["clip"]["build_seconds"] = round(time.perf_counter() - t0, 1)
    timings: dict = {}

    from rigidbench.metrics import METRICS

    values: dict = {}
    runs: dict = {}
    repeats = max(1, args.repeat)
    for r in range(repeats):  # interleaved: whole stage, floor, then each metric alone
        trace = r == 0  # the first run measures memory (tracemalloc on); the others time without it
        with measure(runs, f"array_metrics_total#{r}", trace):
            values = array_metrics(clip, corners, conf)
        with measure(runs, f"ssim_filter_floor#{r}", trace):
            ssim_filter_floor(clip)
        for name in ARRAY_METRICS:  # one by one, each on fresh inputs (the alignment is refitted)
            inputs = metric_inputs(clip, corners, conf)
            with measure(runs, f"{name}#{r}", trace):
                METRICS[name].load()(inputs)
    for key in sorted({k.split("#")[0] for k in runs}, key=lambda k: list(runs).index(f"{k}#0")):
        row = dict(runs[f"{key}#0"])  # memory figures from the traced run
        row["seconds"] = min(runs[f"{key}#{r}"]["seconds"] for r in range(repeats))
        row["cpu_seconds"] = min(runs[f"{key}#{r}"]["cpu_seconds"] for r in range(repeats))
        row["rss_peak_delta_mb"] = max(runs[f"{key}#{r}"]["rss_peak_delta_mb"] for r in range(repeats))
        row["runs"] = repeats
        timings[key] = row
    timings["ssim_filter_floor"]["ssim_over_floor_cpu"] = round(
        timings["ssim"]["cpu_seconds"] / max(timings["ssim_filter_floor"]["cpu_seconds"], 1e-9), 2)
    with measure(timings, "corner_detection"):
        from rigidbench.metrics.background import detect_background_corners
        detect_background_corners(clip["gen_rgb"][0], clip["gen_masks"][0])

    if args.array_only:
        results["timings"] = timings
        results["values"] = {k: (None if not np.isfinite(v.value) else round(float(v.value), 6))
                             for k, v in values.items()}
        print(json.dumps(results, indent=1))
        return
    torch.manual_seed(0)
    net = lpips_net.build_lpips_alex(random_backbone=True)
    with measure(timings, "lpips_alexnet_random_weights"):
        values["lpips"] = appearance.lpips(clip["ref_rgb"], clip["gen_rgb"], net, batch_size=args.lpips_batch)

    small = torch.nn.Sequential(torch.nn.Conv2d(3, 16, 8, stride=8), torch.nn.ReLU(),
                                torch.nn.AdaptiveAvgPool2d(4), torch.nn.Flatten()).eval()
    p_idx, _ = identity.patch_pairs(clip["ref_tracks"], clip["gen_tracks"], clip["ref_vis"], clip["gen_vis"],
                                    HEIGHT, WIDTH)
    results["clip"]["iddrift_pairs"] = int(len(p_idx))
    with measure(timings, "iddrift_pipeline_small_convnet"):
        values["iddrift"] = identity.iddrift(clip["ref_rgb"], clip["gen_rgb"], clip["ref_tracks"],
                                             clip["gen_tracks"], clip["ref_vis"], clip["gen_vis"],
                                             clip["actor_index"], small)
    if not args.skip_vit:
        vit = vit_l14()
        x = torch.randn(args.vit_patches, 3, 224, 224)
        with torch.inference_mode():
            vit(x[:1])  # warm-up
            with measure(timings, f"vit_l14_forward_{args.vit_patches}_patches_fp32"):
                vit(x)
        per_patch = timings[f"vit_l14_forward_{args.vit_patches}_patches_fp32"]["seconds"] / args.vit_patches
        results["iddrift_vit_l14_extrapolated"] = {
            "patches": 2 * int(len(p_idx)),
            "seconds_per_patch_fp32_cpu": round(per_patch, 3),
            "estimated_seconds_fp32_cpu": round(per_patch * 2 * len(p_idx), 1),
            "note": "random ViT-L/14-sized plain-torch encoder; transformers not used",
        }

    results["timings"] = timings
    results["target"] = {"array_metrics_seconds_lt": 5.0, "array_metrics_memory_mb_lt": 2048,
                         "met_seconds": timings["array_metrics_total"]["seconds"] < 5.0,
                         "met_memory_rss": timings["array_metrics_total"]["rss_peak_delta_mb"] < 2048}
    results["values"] = {k: (None if not np.isfinite(v.value) else round(float(v.value), 6)) for k, v in values.items()}
    print(json.dumps(results, indent=1))


if __name__ == "__main__":
    main()
