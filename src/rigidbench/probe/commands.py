"""The ``probe`` subcommand: ``rigidbench probe extract|fit|intervene|report`` (paper sections 5.2-5.3,
appendix E; docs/probing.md). Light: torch and the models are imported only when a command runs."""

from __future__ import annotations

import sys
from pathlib import Path

from ..context import RunContext
from ..errors import UserError
from ..perception.device import resolve_device
from ..registry import load_target
from ..argtypes import positive_int

PAPER_TAUS = "0.1,0.3,0.5,0.7,0.9"
INTERVENTION_TAUS = "0.3,0.5,0.7"


def parse_floats(text: str, what: str) -> list[float]:
    try:
        values = [float(v) for v in str(text).split(",") if v.strip()]
    except ValueError:
        raise UserError(f"{what}: expected comma-separated numbers, got {text!r}") from None
    if not values:
        raise UserError(f"{what}: no values in {text!r}")
    return values


def parse_ints(text: str | None, what: str) -> list[int] | None:
    if text is None:
        return None
    try:
        return [int(v) for v in str(text).split(",") if v.strip()]
    except ValueError:
        raise UserError(f"{what}: expected comma-separated integers, got {text!r}") from None


def cmd_extract(args, ctx: RunContext) -> int:
    run_extract = load_target("rigidbench.probe.extract:run_extract", "command")
    if args.chunk_size < 1:
        raise UserError(f"--chunk-size must be at least 1, got {args.chunk_size}")
    summary = run_extract(args.backbone, args.cache, args.data, args.out, model=args.model,
                          model_path=None if args.model_path is None else str(args.model_path),
                          taus=parse_floats(args.taus, "--taus"), device=args.net_device or ctx.device,
                          limit=args.limit, chunk_size=args.chunk_size, progress=not args.no_progress,
                          backbone_seed=args.random_seed)
    print(f"probe extract ({args.backbone}): {len(summary.extracted)} clips, {summary.rows} actor-slot rows into "
          f"{summary.out} ({len(summary.skipped)} already there, {len(summary.failed)} failed) in "
          f"{summary.seconds:.1f} s")
    for clip, reason in summary.failed.items():
        print(f"  FAILED {clip}: {reason}", file=sys.stderr)
    return 1 if summary.failed and not summary.extracted and not summary.skipped else 0


def cmd_fit(args, ctx: RunContext) -> int:
    fit = load_target("rigidbench.probe.fit:run_fit", "command")
    settings_cls = load_target("rigidbench.probe.fit:ProbeSettings", "command")
    device = resolve_device(args.net_device or ctx.device)
    settings = settings_cls(epochs=args.epochs, batch_size=args.batch_size, lr=args.lr, seed=args.seed, device=device,
                            standardize=args.standardize, r2=args.r2)
    records = fit(args.acts, args.out, targets=args.targets.split(",") if args.targets else None,
                  probes=tuple(args.probes.split(",")), blocks=parse_ints(args.blocks, "--blocks"),
                  taus=None if args.taus is None else parse_floats(args.taus, "--taus"), settings=settings,
                  progress=not args.no_progress)
    print(f"probe fit: {len(records)} cells in {args.out}/scores.csv")
    return 0


def cmd_intervene(args, ctx: RunContext) -> int:
    run = load_target("rigidbench.probe.intervene:run_intervene", "command")
    if args.clips < 1:
        raise UserError(f"--clips must be at least 1, got {args.clips}")
    result = run(args.acts, args.cache, args.out, taus=parse_floats(args.taus, "--taus"), clips=args.clips,
                 blocks=parse_ints(args.blocks, "--blocks"), n_resamples=args.resamples,
                 device=args.net_device or ctx.device, progress=not args.no_progress, full_readout=args.full_readout,
                 inlp_dtype=args.inlp_dtype, clip_split=args.clip_split)
    print(f"probe intervene: {len(result['clips'])} clips, {len(result['bases'])} cells into {args.out}")
    for row in result["summary"]:
        print(f"  {row['variant']:>8} {row['readout']:>6}: dL = {row['mean']:.4g} [{row['lo']:.4g}, {row['hi']:.4g}]")
    return 0


def cmd_report(args, ctx: RunContext) -> int:
    report = load_target("rigidbench.probe.report:write_report", "command")
    page = report(args.probes or [], args.intervene, args.out)
    print(f"probe report: {page}")
    return 0


def add_commands(subparsers) -> None:
    """Register ``probe`` (with extract, fit, intervene, report) on the ``rigidbench`` subparsers."""
    probe = subparsers.add_parser("probe", help="probe Wan's transformer for physical state and remove "
                                                "position subspaces (paper sections 5.2-5.3)")
    sub = probe.add_subparsers(dest="probe_command", required=True, metavar="{extract,fit,intervene,report}")

    p = sub.add_parser("extract", help="actor-pooled outputs of every DiT block at five noise levels (resumable)")
    p.add_argument("--backbone", required=True, metavar="base|random|CHECKPOINT",
                   help="base (pretrained), random (re-initialised DiT) or a `rigidbench train` checkpoint directory")
    p.add_argument("--cache", type=Path, required=True, help="the cache `rigidbench preprocess` wrote")
    p.add_argument("--data", type=Path, required=True, help="the bundles the cache was made from (DIR/train)")
    p.add_argument("--out", type=Path, required=True, help="activation store (created; a rerun skips done clips)")
    p.add_argument("--model", choices=("wan-2.2", "tiny"), help="default: the cache's model")
    p.add_argument("--model-path", type=Path, help="a local diffusers pipeline directory instead of the hub")
    p.add_argument("--taus", default=PAPER_TAUS, help=f"schedule fractions along the training schedule, 0.9 the "
                                                      f"least noisy (default {PAPER_TAUS})")
    p.add_argument("--random-seed", type=int, default=0,
                   help="seed of --backbone random's re-initialisation (default 0, the release's); recorded")
    p.add_argument("--limit", type=positive_int, help="only the first N clips of the cache (sorted by id)")
    p.add_argument("--chunk-size", type=int, default=64, help="clips per shard (default 64)")
    p.add_argument("--device", dest="net_device", help="e.g. cuda or cpu (default: CUDA when available)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.set_defaults(func=cmd_extract)

    p = sub.add_parser("fit", help="linear and MLP probes with shuffled-label controls, per block x tau x target")
    p.add_argument("--acts", type=Path, required=True, help="the store `probe extract` wrote")
    p.add_argument("--out", type=Path, required=True, help="directory for scores.csv (a rerun skips done cells)")
    p.add_argument("--targets", help="comma-separated targets (default: all: position, contact, orientation, ...)")
    p.add_argument("--probes", default="linear,mlp", help="linear,mlp (default both)")
    p.add_argument("--blocks", help="comma-separated block indices (default: all)")
    p.add_argument("--taus", help="comma-separated schedule fractions (default: all extracted)")
    p.add_argument("--epochs", type=int, default=20)
    p.add_argument("--batch-size", type=int, default=4096)
    p.add_argument("--lr", type=float, default=1e-3)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--standardize", action="store_true",
                   help="z-score activations and continuous targets with training statistics (ours; the release, "
                        "and the default, fit raw values)")
    p.add_argument("--r2", choices=("pooled", "mean"), default="pooled",
                   help="R^2 pooled over a target's dimensions (default, the release's) or the mean of per-dimension R^2")
    p.add_argument("--device", dest="net_device", help="where probes train, e.g. cuda or cpu (default: CUDA when "
                                                       "available)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.set_defaults(func=cmd_fit)

    p = sub.add_parser("intervene", help="INLP position subspace vs random and variance-matched PC controls: "
                                         "loss change through the remaining blocks and the direct head")
    p.add_argument("--acts", type=Path, required=True, help="the store `probe extract` wrote (its backbone is used)")
    p.add_argument("--cache", type=Path, required=True, help="the cache the store was extracted from")
    p.add_argument("--out", type=Path, required=True, help="output directory (a rerun skips done clips)")
    p.add_argument("--taus", default=INTERVENTION_TAUS, help=f"schedule fractions (default {INTERVENTION_TAUS})")
    p.add_argument("--clips", type=int, default=100, help="the first N clips by id (default 100)")
    p.add_argument("--clip-split", choices=("all", "train"), default="all",
                   help="choose them among all the store's clips (default, the release's) or its training split")
    p.add_argument("--blocks", help="comma-separated block indices (default: all)")
    p.add_argument("--resamples", type=int, default=20000, help="bootstrap resamples over clips (default 20,000)")
    p.add_argument("--full-readout", choices=("resume", "hook"), default="resume",
                   help="resume: run the remaining blocks from the recorded block output (default); hook: a "
                        "forward hook and a whole forward pass (same numbers, about twice the cost)")
    p.add_argument("--inlp-dtype", choices=("float64", "float32"), default="float64",
                   help="precision of INLP's Gram matrix and solves (default float64, as the release's ridge)")
    p.add_argument("--device", dest="net_device", help="e.g. cuda or cpu (default: CUDA when available; INLP runs "
                                                       "there too)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.set_defaults(func=cmd_intervene)

    p = sub.add_parser("report", help="figures (PNG/PDF), CSV tables and an HTML page of probes and interventions")
    p.add_argument("--probes", type=Path, nargs="+", help="`probe fit` output directories (one per backbone)")
    p.add_argument("--intervene", type=Path, help="the `probe intervene` output directory")
    p.add_argument("--out", type=Path, required=True, help="report directory (index.html)")
    p.set_defaults(func=cmd_report)
