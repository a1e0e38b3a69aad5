"""The ``preprocess`` and ``train`` commands (fine-tuning Wan 2.2): their arguments and what they run. Light: the
stages (torch, diffusers, peft) are imported only when a command runs, through ``registry.load_target`` (a
missing package names the extra)."""

from __future__ import annotations

import os
from pathlib import Path

from ..argtypes import existing_folder, output_folder, positive_int
from ..context import RunContext
from ..errors import UserError
from ..registry import load_target
from ..train.config import MODEL_SPECS, NAMED_CONFIGS, RESIZES, VAE_DTYPES, load_train_config
from . import Command, report_stage, run_options


def _preprocess_arguments(p) -> None:
    p.add_argument("--data", type=existing_folder, required=True,
                   help="reference bundles: the training split directory (data/train) or a data root")
    p.add_argument("--split", choices=("train", "eval"), default="train",
                   help="split under a data root (default: train)")
    p.add_argument("--out", type=output_folder, required=True,
                   help="cache directory (created; a rerun skips done clips)")
    p.add_argument("--model", choices=tuple(MODEL_SPECS), default="wan-2.2",
                   help="wan-2.2 (640x352, 49 frames; the paper) or tiny (random tiny models, CPU tests)")
    p.add_argument("--model-path", type=Path, help="a local diffusers pipeline directory instead of the hub")
    p.add_argument("--shard-size", type=int, default=64,
                   help="ignored, kept so older scripts run: the cache now keeps one latent file per clip")
    p.add_argument("--resize", choices=RESIZES, default="bicubic",
                   help="frame resize filter: bicubic (PIL's default, the authors' release; default) or lanczos")
    p.add_argument("--vae-dtype", choices=VAE_DTYPES, default="auto",
                   help="VAE precision: auto (bfloat16 on a GPU, as the release; float32 on the CPU)")
    p.add_argument("--device", dest="net_device", help="e.g. cuda or cpu (default: CUDA when available)")
    p.add_argument("--ray-shards", type=positive_int, metavar="N",
                   help="--executor ray: Ray actors encoding clips (default: the cluster's GPUs)")


def _train_arguments(p) -> None:
    p.add_argument("--config", dest="train_config", required=True, metavar="NAME|PATH",
                   help=f"{'|'.join(NAMED_CONFIGS)} (configs/train/NAME.yaml) or a YAML file")
    p.add_argument("--set", action="append", metavar="KEY=VALUE",
                   help="override one setting, e.g. --set max_steps=100 --set optimizer.lr=5e-5 (repeatable)")
    p.add_argument("--cache", type=existing_folder, required=True, help="the directory `rigidbench preprocess` wrote")
    p.add_argument("--out", type=output_folder, required=True,
                   help="run directory: metrics.jsonl, checkpoints/step-N; rerunning continues from the last")
    p.add_argument("--device", dest="net_device", help="e.g. cuda or cpu (default: CUDA when available)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")


def cmd_preprocess(args, ctx: RunContext) -> int:
    run_preprocess = load_target("rigidbench.stages.preprocess:run_preprocess", "command")
    if args.limit is not None and args.limit < 0:
        raise UserError(f"--limit must be at least 0, got {args.limit}")
    model_path = None if args.model_path is None else str(args.model_path)
    device = args.net_device or ctx.device
    # --executor ray: a Ray actor per GPU (per CPU with --device cpu), each encoding clips
    report = run_preprocess(args.data, args.out, model=args.model, split=args.split,
                            run=run_options(args, actors=args.ray_shards), model_path=model_path, device=device,
                            resize=args.resize, vae_dtype=args.vae_dtype)
    status = report_stage(report)  # the words every stage uses; then the prompts this run encoded
    where = " on Ray" if args.executor == "ray" else ""
    print(f"  prompts encoded: {report.facts.prompts_encoded} ({args.model} on {report.facts.device}{where})")
    return status


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


COMMANDS = (
    Command("preprocess", "encode a training split for fine-tuning Wan 2.2: prompts with UMT5, clips with the VAE, "
                          "one file per clip (reruns encode only clips whose inputs or settings changed)",
            "rigidbench.commands.training:cmd_preprocess", _preprocess_arguments,
            groups=("selection", "executor", "progress")),
    Command("train", "fine-tune Wan 2.2 on a preprocessed cache: LoRA (DDP) or full (FSDP); launch with torchrun "
                     "for several GPUs; resumes from RUN",
            "rigidbench.commands.training:cmd_train", _train_arguments),
)
