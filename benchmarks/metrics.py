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

Usage: .venv/bin/python benchmarks/metrics.py [--frames 49] [--skip-vit] [--vit-patches 8]
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
def measure(results: dict, name: str):
    """Record seconds and the three memory figures of the enclosed block under results[name]."""
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
    sampler.start()
    tracemalloc.start()
    t0 = time.perf_counter()
    try:
        yield
    finally:
        seconds = time.perf_counter() - t0
        usage = resource.getrusage(resource.RUSAGE_SELF)
        cpu = usage.ru_utime + usage.ru_stime - usage0.ru_utime - usage0.ru_stime
        _, peak = tracemalloc.get_traced_memory()
        tracemalloc.stop()
        stop.set()
        sampler.join()
        hwm = _hwm_mb() if hwm_reset else None
        peak_rss = max(max(samples), hwm or 0.0)
        results[name] = {
            "seconds": round(seconds, 3),
            "cpu_seconds": round(cpu, 3),
            "tracemalloc_peak_mb": round(peak / 2**20, 1),
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


def array_metrics(clip: dict, corners, conf) -> dict:
    """The eight metrics that need no neural network, as the evaluator would call them."""
    from rigidbench.metrics import appearance, background, depth, masks, tracks

    alignment = depth.fit_disparity_alignment(clip["disparity"], clip["ref_depth"])
    return {
        "iou": masks.iou(clip["ref_masks"], clip["gen_masks"]),
        "centroid_l2": masks.centroid_l2(clip["ref_masks"], clip["gen_masks"]),
        "chamfer": masks.chamfer(clip["ref_masks"], clip["gen_masks"]),
        "ate": tracks.ate(clip["ref_tracks"], clip["gen_tracks"], clip["ref_vis"], clip["gen_vis"], HEIGHT),
        "ate3d": depth.ate3d(clip["gen_tracks"], clip["ref_vis"], clip["gen_vis"], clip["actor_index"],
                             clip["disparity"], clip["ref_depth"], clip["K"], clip["R_c"], clip["t_c"],
                             clip["ref_pos"], alignment=alignment),
        "si_mse": depth.si_mse(clip["disparity"], clip["ref_depth"], alignment=alignment),
        "ssim": appearance.ssim(clip["ref_rgb"], clip["gen_rgb"]),
        "bgdrift": background.bgdrift(corners, conf, HEIGHT),
    }


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
    parser.add_argument("--skip-vit", action="store_true", help="do not time the ViT-L/14-sized encoder")
    parser.add_argument("--vit-patches", type=int, default=8, help="patches in the timed ViT forward")
    parser.add_argument("--lpips-batch", type=int, default=4)
    args = parser.parse_args()

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

    with measure(timings, "array_metrics_total"):
        values = array_metrics(clip, corners, conf)
    with measure(timings, "corner_detection"):
        from rigidbench.metrics.background import detect_background_corners
        detect_background_corners(clip["gen_rgb"][0], clip["gen_masks"][0])

    # One by one (the alignment is refitted inside ate3d and si_mse here).
    from rigidbench.metrics import METRICS
    calls = {
        "iou": lambda: METRICS["iou"].load()(clip["ref_masks"], clip["gen_masks"]),
        "centroid_l2": lambda: METRICS["centroid_l2"].load()(clip["ref_masks"], clip["gen_masks"]),
        "chamfer": lambda: METRICS["chamfer"].load()(clip["ref_masks"], clip["gen_masks"]),
        "ate": lambda: METRICS["ate"].load()(clip["ref_tracks"], clip["gen_tracks"], clip["ref_vis"],
                                             clip["gen_vis"], HEIGHT),
        "ate3d": lambda: METRICS["ate3d"].load()(clip["gen_tracks"], clip["ref_vis"], clip["gen_vis"],
                                                 clip["actor_index"], clip["disparity"], clip["ref_depth"],
                                                 clip["K"], clip["R_c"], clip["t_c"], clip["ref_pos"]),
        "si_mse": lambda: METRICS["si_mse"].load()(clip["disparity"], clip["ref_depth"]),
        "ssim": lambda: METRICS["ssim"].load()(clip["ref_rgb"], clip["gen_rgb"]),
        "bgdrift": lambda: METRICS["bgdrift"].load()(corners, conf, HEIGHT),
    }
    for name, call in calls.items():
        with measure(timings, name):
            call()

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
