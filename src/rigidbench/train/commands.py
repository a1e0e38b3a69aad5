"""The ``preprocess`` and ``train`` subcommands. Light: the stages (torch, diffusers, peft) are imported
only when a command runs, through ``registry.load_target`` (a missing package names the extra)."""

from __future__ import annotations

import os
import sys
from pathlib import Path

from ..context import RunContext
from ..errors import UserError
from ..executors import Resources, Shard, make_executor
from ..registry import load_target
from ..argtypes import positive_int
from .config import MODEL_SPECS, NAMED_CONFIGS, load_train_config


def cmd_preprocess(args, ctx: RunContext) -> int:
    run_preprocess = load_target("rigidbench.train.preprocess:run_preprocess", "command")
    if args.limit is not None and args.limit < 0:
        raise UserError(f"--limit must be at least 0, got {args.limit}")
    if args.shard_size < 1:
        raise UserError(f"--shard-size must be at least 1, got {args.shard_size}")
    model_path = None if args.model_path is None else str(args.model_path)
    device = args.net_device or ctx.device
    if args.executor == "ray":
        return _preprocess_on_ray(args, model_path, device)
    summary = run_preprocess(args.data, args.out, model=args.model, split=args.split, limit=args.limit,
                             model_path=model_path, device=device, shard_size=args.shard_size,
                             progress=not args.no_progress, shard=Shard.parse(args.shard), resize=args.resize,
                             vae_dtype=args.vae_dtype)
    print(f"preprocess ({args.model}, {summary.device}): {len(summary.encoded)} clips and {summary.prompts_encoded} "
          f"prompts encoded into {summary.cache} ({len(summary.skipped)} clips already there), "
          f"{len(summary.failed)} failed")
    for sample_id, reason in summary.failed.items():
        print(f"  FAILED {sample_id}: {reason}", file=sys.stderr)
    return 1 if summary.failed else 0


def _preprocess_on_ray(args, model_path: str | None, device: str | None) -> int:
    """One Ray actor per shard (a GPU each unless --device cpu), each writing its part of the cache."""
    executor = make_executor("ray", ray_address=args.ray_address)
    shards = args.ray_shards or executor.default_workers(Resources(num_gpus=0 if device == "cpu" else 1))
    job = {"data": str(Path(args.data).resolve()), "out": str(Path(args.out).resolve()), "model": args.model,
           "split": args.split, "limit": args.limit, "model_path": model_path, "device": device,
           "shard_size": args.shard_size, "shards": shards, "resize": args.resize, "vae_dtype": args.vae_dtype}
    results = executor.map("rigidbench.train.preprocess:PreprocessWorker", job, list(range(shards)),
                           Resources(num_cpus=1, num_gpus=0 if device == "cpu" else 1))
    encoded = sum(len(r.get("encoded", [])) for _, r in results)
    failed = {k: v for _, r in results for k, v in r.get("failed", {}).items()}
    print(f"preprocess ({args.model}) on Ray in {shards} parts: {encoded} clips encoded into {args.out}, "
          f"{len(failed)} failed")
    for sample_id, reason in failed.items():
        print(f"  FAILED {sample_id}: {reason}", file=sys.stderr)
    return 1 if failed else 0


def cmd_train(args, ctx: RunContext) -> int:
    cfg = load_train_config(args.train_config, ctx.config_dirs, args.set or ())
    train = load_target("rigidbench.train.trainer:train", "command")
    summary = train(cfg, args.cache, args.out, device=args.net_device or ctx.device, progress=not args.no_progress)
    if os.environ.get("RANK", "0") != "0":  # torchrun: rank 0 reports
        return 0
    last = f", last loss {summary.losses[-1]:.4f}" if summary.losses else ""
    print(f"train ({cfg.mode}, {cfg.model}): steps {summary.start_step} -> {summary.end_step}{last}; "
          f"{summary.facts.get('precision')}, {summary.facts.get('optimizer')}; run in {args.out}")
    for path in summary.checkpoints:
        print(f"  checkpoint {path}")
    return 0


def add_commands(subparsers) -> None:
    """Register ``preprocess`` and ``train`` on the ``rigidbench`` subparsers."""
    p = subparsers.add_parser("preprocess", help="encode a training split for fine-tuning Wan 2.2: prompts with "
                                                 "UMT5, clips with the VAE, into float16 shards (resumable)")
    p.add_argument("--data", type=Path, required=True,
                   help="reference bundles: the training split directory (data/train) or a data root")
    p.add_argument("--split", choices=("train", "eval"), default="train",
                   help="split under a data root (default: train)")
    p.add_argument("--out", type=Path, required=True, help="cache directory (created; a rerun skips done clips)")
    p.add_argument("--model", choices=tuple(MODEL_SPECS), default="wan-2.2",
                   help="wan-2.2 (640x352, 49 frames; the paper) or tiny (random tiny models, CPU tests)")
    p.add_argument("--model-path", type=Path, help="a local diffusers pipeline directory instead of the hub")
    p.add_argument("--limit", type=positive_int, help="only the first N bundles (sorted by id)")
    p.add_argument("--shard-size", type=int, default=64, help="clips per latent shard (default 64)")
    p.add_argument("--resize", choices=("bicubic", "lanczos"), default="bicubic",
                   help="frame resize filter: bicubic (PIL's default, the authors' release; default) or lanczos")
    p.add_argument("--vae-dtype", choices=("auto", "bfloat16", "float32"), default="auto",
                   help="VAE precision: auto (bfloat16 on a GPU, as the release; float32 on the CPU)")
    p.add_argument("--device", dest="net_device", help="e.g. cuda or cpu (default: CUDA when available)")
    p.add_argument("--no-progress", action="store_true", help="no progress bars")
    p.add_argument("--executor", choices=("local", "ray"), default="local",
                   help="ray: the split in parts, one Ray actor (a GPU each) per part, into CACHE/part-I-of-N")
    p.add_argument("--ray-address", help="Ray cluster to join (default: $RAY_ADDRESS, else a local Ray)")
    p.add_argument("--ray-shards", type=int, help="parts for --executor ray (default: the cluster's GPUs)")
    p.add_argument("--shard", metavar="I/N", help="only the I-th of N parts of the clips, into CACHE/part-I-of-N "
                                                  "(job arrays; training reads the parts as one cache)")
    p.set_defaults(func=cmd_preprocess)

    p = subparsers.add_parser("train", help="fine-tune Wan 2.2 on a preprocessed cache: LoRA (DDP) or full "
                                            "(FSDP); launch with torchrun for several GPUs; resumes from RUN")
    p.add_argument("--config", dest="train_config", required=True, metavar="NAME|PATH",
                   help=f"{'|'.join(NAMED_CONFIGS)} (configs/train/NAME.yaml) or a YAML file")
    p.add_argument("--set", action="append", metavar="KEY=VALUE",
                   help="override one setting, e.g. --set max_steps=100 --set optimizer.lr=5e-5 (repeatable)")
    p.add_argument("--cache", type=Path, required=True, help="the directory `rigidbench preprocess` wrote")
    p.add_argument("--out", type=Path, required=True,
                   help="run directory: metrics.jsonl, checkpoints/step-N; rerunning continues from the last")
    p.add_argument("--device", dest="net_device", help="e.g. cuda or cpu (default: CUDA when available)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.set_defaults(func=cmd_train)
