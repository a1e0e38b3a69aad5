"""Time the neural perception networks on one synthetic clip and print JSON.

Each network is built at its real size with random weights (no downloads) and run the way the
neural backend runs it, on the best device at the backend's precision:

- sam2: SAM 2.1 Hiera Large (``Sam2VideoModel`` with the released config, 1024 px input), one
  frame-0 mask prompt per actor, propagated through the clip;
- cotracker: the CoTracker3 offline hub entry with ``pretrained=False`` when $RIGIDBENCH_COTRACKER
  names a real co-tracker checkout (real size); otherwise the tests' tiny stand-in, which has the
  interface but NOT the size of CoTracker3 (reported as ``"real_size": false``); 20 points per
  actor plus 200 background corners, one call;
- vda: Video Depth Anything Large (ViT-L), input size 384 (32-frame windows, so even a short clip
  runs one full window);
- dinov2: DINOv2 ViT-L/14 (``Dinov2Model``, 224 px, batches of 256) on the IdDrift patch count of
  the clip, 2 x points x (frames - 1);
- lpips: LPIPS with an AlexNet backbone on every frame pair, batches of 4.

The paper clip is 49 frames at 1280x704 with up to 4 actors; on a CPU shrink it with --frames,
--size, --actors and the input-size options (the JSON records what ran). Reported per network:
wall seconds, process CPU seconds, parameters (millions) and the peak GPU memory (CUDA only).

Usage: .venv/bin/python benchmarks/perception.py [--quick] [--frames 49] [--size 1280x704] [--actors 4]
       [--device cuda|cpu] [--models sam2,cotracker,vda,dinov2,lpips] [--sam2-input 1024]
       [--vda-input 384] [--dinov2-patches N] [--repeats 1]
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
MODELS = ("sam2", "cotracker", "vda", "dinov2", "lpips")


def synthetic_clip(frames: int, width: int, height: int, actors: int, seed: int = 0):
    """Textured wall with ``actors`` boxes sliding right. Returns frames (T,H,W,3) uint8 and masks0 (N,H,W) bool."""
    rng = np.random.default_rng(seed)
    cell = max(4, width // 80)
    wall = (rng.random((height // cell + 1, width // cell + 1, 3)) * 255).astype(np.uint8)
    wall = wall.repeat(cell, 0).repeat(cell, 1)[:height, :width]
    clip = np.repeat(wall[None], frames, axis=0)
    masks0 = np.zeros((actors, height, width), bool)
    bw, bh = width // 10, height // 6
    for a in range(actors):
        x0, y0 = (a + 1) * width // (actors + 2), height // 3
        masks0[a, y0:y0 + bh, x0:x0 + bw] = True
        for t in range(frames):
            dx = t * max(1, width // 200)
            clip[t, y0:y0 + bh, x0 + dx:x0 + dx + bw] = rng.integers(0, 255, 3)
    return clip, masks0


def query_points(masks0: np.ndarray, per_actor: int = 20, seed: int = 0) -> np.ndarray:
    from rigidbench.groundtruth.tracks import sample_query_pixels

    rng = np.random.default_rng(seed)
    return np.concatenate([sample_query_pixels(m, per_actor, rng) for m in masks0]).astype(np.float32)


class Timer:
    def __init__(self, device: str):
        self.device = device

    def __enter__(self):
        import torch

        if self.device.startswith("cuda"):
            torch.cuda.synchronize()
            torch.cuda.reset_peak_memory_stats()
        self.wall, self.cpu = time.perf_counter(), time.process_time()
        return self

    def __exit__(self, *exc):
        import torch

        if self.device.startswith("cuda"):
            torch.cuda.synchronize()
            self.peak_gpu_mb = torch.cuda.max_memory_allocated() / 2**20
        else:
            self.peak_gpu_mb = None
        self.wall_s = time.perf_counter() - self.wall
        self.cpu_s = time.process_time() - self.cpu


def params_m(model) -> float:
    return round(sum(p.numel() for p in model.parameters()) / 1e6, 2)


def bench_sam2(clip, masks0, device, args) -> dict:
    from transformers import Sam2VideoModel

    from rigidbench.perception.device import inference_dtype
    from rigidbench.perception.sam2 import hiera_large_config, propagate_masks

    cfg = hiera_large_config()
    if args.sam2_input != 1024:
        s = args.sam2_input
        cfg.image_size = s
        cfg.vision_config.backbone_config.image_size = [s, s]
        cfg.vision_config.backbone_feature_sizes = [[s // 4, s // 4], [s // 8, s // 8], [s // 16, s // 16]]
        cfg.prompt_encoder_config.image_size = s
        cfg.memory_attention_rope_feat_sizes = [s // 16, s // 16]
    model = Sam2VideoModel(cfg).to(device=device, dtype=inference_dtype("sam2", device)).eval()
    with Timer(device) as tm:
        masks = propagate_masks(model, clip, masks0)
    assert masks.shape == (clip.shape[0],) + masks0.shape
    return {"model": "SAM 2.1 Hiera Large", "input_px": args.sam2_input, "prompts": len(masks0), "real_size": True,
            "params_m": params_m(model), "seconds": tm.wall_s, "cpu_seconds": tm.cpu_s, "peak_gpu_mb": tm.peak_gpu_mb}


def bench_cotracker(clip, masks0, device, args) -> dict:
    from rigidbench.metrics.background import detect_background_corners
    from rigidbench.perception.cotracker import load_cotracker, track_points

    repo = os.environ.get("RIGIDBENCH_COTRACKER")
    real = bool(repo) and Path(repo, "cotracker").is_dir()
    model = load_cotracker(repo_dir=repo if real else ROOT / "tests" / "fixtures" / "cotracker_hub",
                           pretrained=False, device=device)
    points = np.concatenate([query_points(masks0), detect_background_corners(clip[0], masks0)])
    with Timer(device) as tm:
        tracks, _, _ = track_points(model, clip, points)
    assert tracks.shape == (len(points), clip.shape[0], 2)
    return {"model": "CoTracker3 offline" if real else "CoTracker stand-in (tests/fixtures; NOT real size)",
            "real_size": real, "points": int(len(points)), "params_m": params_m(model), "seconds": tm.wall_s,
            "cpu_seconds": tm.cpu_s, "peak_gpu_mb": tm.peak_gpu_mb}


def bench_vda(clip, device, args) -> dict:
    from rigidbench.perception.video_depth import build_video_depth_anything, video_disparity

    model = build_video_depth_anything("vitl", device=device)
    with Timer(device) as tm:
        disparity = video_disparity(model, clip, input_size=args.vda_input)
    assert disparity.shape == clip.shape[:3]
    return {"model": "Video Depth Anything Large", "input_size": args.vda_input, "real_size": True,
            "params_m": params_m(model), "seconds": tm.wall_s, "cpu_seconds": tm.cpu_s, "peak_gpu_mb": tm.peak_gpu_mb}


def bench_dinov2(clip, masks0, device, args) -> dict:
    import torch
    from transformers import Dinov2Config, Dinov2Model

    from rigidbench.perception.features import load_identity_features

    cfg = Dinov2Config(hidden_size=1024, num_hidden_layers=24, num_attention_heads=16, intermediate_size=4096,
                       patch_size=14, image_size=518, layerscale_value=1.0)
    model = Dinov2Model(cfg)
    features = load_identity_features(device=device, model=model)
    n_points = 20 * len(masks0)
    n_patches = args.dinov2_patches or 2 * n_points * max(clip.shape[0] - 1, 1)
    x = torch.randn(min(n_patches, 256), 3, 224, 224)
    with Timer(device) as tm:
        for start in range(0, n_patches, 256):
            features(x[: min(256, n_patches - start)])
    return {"model": "DINOv2 ViT-L/14", "patches": n_patches, "batch": 256, "real_size": True,
            "params_m": params_m(model), "seconds": tm.wall_s, "cpu_seconds": tm.cpu_s,
            "peak_gpu_mb": tm.peak_gpu_mb}


def bench_lpips(clip, device, args) -> dict:
    from rigidbench.metrics.appearance import lpips
    from rigidbench.metrics.lpips_net import build_lpips_alex

    net = build_lpips_alex(random_backbone=True).to(device)
    other = clip[:, :, ::-1].copy()
    with Timer(device) as tm:
        lpips(clip, other, net)
    return {"model": "LPIPS AlexNet", "frames": int(clip.shape[0]), "real_size": True, "params_m": params_m(net),
            "seconds": tm.wall_s, "cpu_seconds": tm.cpu_s, "peak_gpu_mb": tm.peak_gpu_mb}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=49)
    parser.add_argument("--size", default="1280x704", help="WIDTHxHEIGHT of the clip")
    parser.add_argument("--actors", type=int, default=4)
    parser.add_argument("--device", default=None, help="cuda or cpu (default: cuda when available)")
    parser.add_argument("--models", default=",".join(MODELS))
    parser.add_argument("--sam2-input", type=int, default=1024, help="SAM 2 input size (1024 = paper)")
    parser.add_argument("--vda-input", type=int, default=384, help="VDA input size (384 = paper)")
    parser.add_argument("--dinov2-patches", type=int, default=None, help="patches to embed (default: the clip's count)")
    parser.add_argument("--repeats", type=int, default=1,
                        help="time each network this many times and report the fastest (the first run on a GPU "
                             "includes kernel selection and allocator warm-up)")
    parser.add_argument("--quick", action="store_true", help="smoke run: LPIPS on 4 frames at 64x48 on the CPU")
    args = parser.parse_args(argv)
    if args.quick:
        args.frames = 4
        args.size = '64x48'
        args.actors = 1
        args.device = 'cpu'
        args.models = 'lpips'

    import torch

    from rigidbench.perception.device import resolve_device

    device = resolve_device(args.device)
    width, height = (int(v) for v in args.size.lower().split("x"))
    clip, masks0 = synthetic_clip(args.frames, width, height, args.actors)
    torch.manual_seed(0)
    results = {}
    for name in args.models.split(","):
        if name not in MODELS:
            parser.error(f"unknown model {name!r}; choose from {', '.join(MODELS)}")
        run = {"sam2": lambda: bench_sam2(clip, masks0, device, args),
               "cotracker": lambda: bench_cotracker(clip, masks0, device, args),
               "vda": lambda: bench_vda(clip, device, args),
               "dinov2": lambda: bench_dinov2(clip, masks0, device, args),
               "lpips": lambda: bench_lpips(clip, device, args)}[name]
        runs = [run() for _ in range(max(1, args.repeats))]
        best = min(runs, key=lambda r: r["seconds"])
        best["seconds_each"] = [round(r["seconds"], 3) for r in runs]
        results[name] = {k: (round(v, 3) if isinstance(v, float) else v) for k, v in best.items()}
        print(f"{name}: {results[name]['seconds']:.1f} s", file=sys.stderr)
    paper = (args.frames, width, height, args.sam2_input, args.vda_input) == (49, 1280, 704, 1024, 384)
    doc = {"device": device, "torch": torch.__version__, "threads": torch.get_num_threads(),
           "clip": {"frames": args.frames, "width": width, "height": height, "actors": args.actors},
           "paper_size": paper, "models": results,
           "total_seconds": round(sum(r["seconds"] for r in results.values()), 3),
           "peak_gpu_mb": (max(r["peak_gpu_mb"] for r in results.values()) if device.startswith("cuda") else None)}
    print(json.dumps(doc, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
