"""Time fine-tuning steps and print JSON.

    python benchmarks/train.py [--quick] [--cpu-steps 20] [--gpu-steps 4] [--no-gpu] [--modes lora,full]

CPU: the ``tiny`` configuration (LoRA and full) on a synthetic cache of tiny latents: seconds per
optimizer step (median over the steps after the first) and the process's peak resident memory.

GPU (when torch sees one): the paper's ``lora`` and ``full`` configurations at real size with random
weights (``init: random``: Wan 2.2 TI2V-5B's transformer configuration, so no download) on one GPU,
on a synthetic cache of real-shape latents (48 x 13 x 22 x 40) and text (4096 wide, 120 real tokens
padded to 512): seconds per optimizer step (LoRA: 8 accumulated batches of 2; full: one batch of 16
with gradient checkpointing) and peak GPU memory. Full fine-tuning with the packaged bfloat16 master
weights keeps weights, gradients and AdamW state (8 bytes x 4.9 billion trainable parameters, 39 GB)
unsharded on one GPU, plus the activations; with ``--set master_weights=float32`` that is 79 GB, more
than an H100 holds. The eight-GPU FSDP run shards them.

From the measured GPU numbers it projects the hours for the paper's 3,000 steps on eight GPUs. That
number is a projection, not a measurement: under DDP and FSDP each of the eight GPUs does the same
per-GPU work per update as the one measured GPU (LoRA 16 examples, full 16 examples), so the
projection is 3,000 x the measured step time, assuming the gradient all-reduce (LoRA, ~0.1 GB) and
FSDP's all-gathers and reduce-scatters (full) overlap with compute and that the sharded optimizer
step costs no more than the unsharded one measured here.

Each measurement runs in its own process so peak memory belongs to it alone.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

PAPER_STEPS = 3000
PAPER_GPUS = 8
REAL_TEXT_TOKENS = 120  # about the UMT5 token count of a task prompt with the paper's suffix


def synthetic_cache(root: Path, model: str, n: int, latent_shape, text_dim: int, tokens: int, text_len: int) -> Path:
    import torch

    from rigidbench.train.cache import CacheWriter, prompt_key

    writer = CacheWriter(root, {"model": model, "width": 0, "height": 0, "frames": 0, "text_len": text_len,
                                "prompt_format": "synthetic (benchmark)"})
    g = torch.Generator().manual_seed(0)
    key = prompt_key("benchmark")
    # UMT5's output at all text_len positions, `tokens` of them real (what preprocess stores)
    writer.add_text({key: torch.randn(text_len, text_dim, generator=g)}, {key: "benchmark"}, {key: tokens})
    writer.set(text_dim=text_dim, latent_shape=list(latent_shape))
    latents = {f"{i:05d}": torch.randn(tuple(latent_shape), generator=g) for i in range(n)}
    writer.add_latents(latents, {k: {"prompt": key, "prompt_task": key} for k in latents})
    return root


def worker(kind: str, mode: str, steps: int) -> dict:
    """One measurement in this process: kind "cpu" (tiny) or "gpu" (real size, random weights)."""
    import torch

    from rigidbench.train.config import load_train_config
    from rigidbench.train.trainer import train

    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        if kind == "cpu":
            torch.set_num_threads(max(1, min(2, os.cpu_count() or 1)))
            cache = synthetic_cache(tmp / "cache", "tiny", 4, (48, 3, 4, 8), 32, REAL_TEXT_TOKENS, 512)
            cfg = load_train_config("tiny", overrides=[f"mode={mode}", f"max_steps={steps}",
                                                       f"checkpoint_every={steps + 1}"])
            device = "cpu"
        else:
            cfg = load_train_config(mode, overrides=["init=random", f"max_steps={steps}",
                                                     f"checkpoint_every={steps + 1}"])
            n = cfg.batch_size * cfg.grad_accum
            cache = synthetic_cache(tmp / "cache", "wan-2.2", n, (48, 13, 22, 40), 4096, REAL_TEXT_TOKENS, 512)
            device = "cuda"
        summary = train(cfg, cache, tmp / "run", device=device, progress=False, save_final=False)
        records = [json.loads(line) for line in (tmp / "run" / "metrics.jsonl").read_text().splitlines()]
    times = [r["s_per_step"] for r in records[1:]] or [records[0]["s_per_step"]]
    out = {"config": mode if kind == "gpu" else f"tiny --set mode={mode}", "steps_timed": len(times),
           "s_per_step": statistics.median(times), "s_per_step_min": min(times),
           "first_step_s": records[0]["s_per_step"],
           "examples_per_step": cfg.batch_size * cfg.grad_accum, "precision": summary.facts["precision"],
           "optimizer": summary.facts["optimizer"], "trainable_parameters": summary.facts["trainable_parameters"],
           "gradient_checkpointing": cfg.gradient_checkpointing}
    if kind == "cpu":
        out["peak_rss_mib"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
        out["threads"] = torch.get_num_threads()
    else:
        out["peak_gpu_memory_gib"] = torch.cuda.max_memory_allocated() / 2**30
        out["gpu"] = torch.cuda.get_device_name()
    return out


def run_worker(kind: str, mode: str, steps: int, timeout: int) -> dict:
    cmd = [sys.executable, __file__, "--worker", kind, mode, str(steps)]
    done = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout)
    if done.returncode != 0:
        return {"error": done.stderr.strip().splitlines()[-1] if done.stderr.strip() else f"exit {done.returncode}",
                "stderr_tail": done.stderr[-2000:]}
    return json.loads(done.stdout.strip().splitlines()[-1])


def projection(gpu: dict) -> dict:
    out = {"what": f"PROJECTED, not measured: hours for the paper's {PAPER_STEPS} optimizer steps on {PAPER_GPUS} "
                   "GPUs, = steps x the one-GPU step time measured above (each GPU does the same per-GPU work per "
                   "update under DDP/FSDP; communication assumed overlapped with compute)",
           "measured_on": None}
    for mode, result in gpu.items():
        if "s_per_step" in result:
            out[f"{mode}_hours"] = PAPER_STEPS * result["s_per_step"] / 3600
            out[f"{mode}_examples_per_s_all_gpus"] = PAPER_GPUS * result["examples_per_step"] / result["s_per_step"]
            out["measured_on"] = result.get("gpu")
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cpu-steps", type=int, default=20)
    ap.add_argument("--gpu-steps", type=int, default=4)
    ap.add_argument("--modes", default="lora,full")
    ap.add_argument("--no-gpu", action="store_true")
    ap.add_argument("--no-cpu", action="store_true")
    ap.add_argument("--timeout", type=int, default=900, help="seconds per measurement")
    ap.add_argument("--worker", nargs=3, metavar=("KIND", "MODE", "STEPS"), help=argparse.SUPPRESS)
    ap.add_argument("--quick", action="store_true", help="smoke run: 2 LoRA steps of the tiny configuration on the CPU")
    args = ap.parse_args()
    if args.quick:
        args.cpu_steps = 2
        args.no_gpu = True
        args.modes = 'lora'
    if args.worker:
        kind, mode, steps = args.worker
        print(json.dumps(worker(kind, mode, int(steps))))
        return
    import torch

    modes = [m.strip() for m in args.modes.split(",") if m.strip()]
    report = {"cpu_tiny": None, "gpu_real_size_random_weights": None, "projection": None}
    if not args.no_cpu:
        report["cpu_tiny"] = {m: run_worker("cpu", m, args.cpu_steps, args.timeout) for m in modes}
    if torch.cuda.is_available() and not args.no_gpu:
        gpu = {m: run_worker("gpu", m, args.gpu_steps, args.timeout) for m in modes}
        report["gpu_real_size_random_weights"] = gpu
        report["projection"] = projection(gpu)
    else:
        report["gpu_real_size_random_weights"] = "no CUDA device here (or --no-gpu)"
    print(json.dumps(report, indent=1))


if __name__ == "__main__":
    main()
