"""What ``rigidbench preprocess`` and ``rigidbench train`` run (declared in ``commands.training``). Light: the
stages (torch, diffusers, peft) are imported only when a command runs, through ``registry.load_target`` (a
missing package names the extra)."""

from __future__ import annotations

import os
import sys

from ..context import RunContext
from ..argtypes import selected_ids
from ..errors import UserError
from ..executors import Shard, make_executor
from ..registry import load_target
from .config import load_train_config


def cmd_preprocess(args, ctx: RunContext) -> int:
    run_preprocess = load_target("rigidbench.train.preprocess:run_preprocess", "command")
    if args.limit is not None and args.limit < 0:
        raise UserError(f"--limit must be at least 0, got {args.limit}")
    model_path = None if args.model_path is None else str(args.model_path)
    device = args.net_device or ctx.device
    executor = None
    if args.executor == "ray":  # a Ray actor per GPU (per CPU with --device cpu), each encoding clips
        executor = make_executor("ray", ray_address=args.ray_address, workers=args.ray_shards)
    summary = run_preprocess(args.data, args.out, model=args.model, split=args.split, limit=args.limit,
                             model_path=model_path, device=device, progress=not args.no_progress,
                             shard=Shard.parse(args.shard), resize=args.resize, vae_dtype=args.vae_dtype,
                             ids=selected_ids(args), executor=executor)
    where = " on Ray" if args.executor == "ray" else ""
    print(f"preprocess ({args.model}, {summary.device}){where}: {len(summary.encoded)} clips and "
          f"{summary.prompts_encoded} prompts encoded into {summary.cache} ({len(summary.skipped)} clips already "
          f"there), {len(summary.failed)} failed")
    changed = [i for i, why in summary.redone.items() if i in summary.encoded]
    if changed:
        print(f"  encoded again: {len(changed)} clips ({'; '.join(f'{i}: {summary.redone[i]}' for i in changed[:5])}"
              f"{' ...' if len(changed) > 5 else ''})")
    for sample_id, reason in summary.failed.items():
        print(f"  FAILED {sample_id}: {reason}", file=sys.stderr)
    return 1 if summary.failed else 0


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
