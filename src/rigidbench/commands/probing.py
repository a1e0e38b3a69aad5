"""The ``probe`` command group: extract, fit, intervene, report (paper sections 5.2-5.3, appendix E;
docs/probing.md): their arguments and what they run. Light: torch and the models are imported only when a command
runs."""

from __future__ import annotations

import sys
from pathlib import Path

from ..argtypes import existing_folder, non_negative_int, output_folder, positive_int
from ..context import RunContext
from ..errors import UserError
from ..perception.device import resolve_device
from ..probe.recipe import CHOICES, INLP_PROCEDURES, RECIPE_NAMES
from ..registry import load_target
from ..train.config import MODEL_SPECS
from . import Command, report_stage, run_options

PAPER_TAUS = "0.1,0.3,0.5,0.7,0.9"
INTERVENTION_TAUS = "0.3,0.5,0.7"
#: command-line destination -> ``recipe.Conditioning`` field
CONDITIONING_OPTIONS = {"prompt": "prompt", "text_padding": "padding", "clean_slot_timestep": "clean_slot_timestep",
                        "dtype": "dtype", "objective_dtype": "objective_dtype", "noise": "noise"}


def _extract_arguments(p) -> None:
    p.add_argument("--backbone", required=True, metavar="base|random|CHECKPOINT",
                   help="base (pretrained), random (re-initialised DiT) or a `rigidbench train` checkpoint directory")
    p.add_argument("--cache", type=existing_folder, required=True, help="the cache `rigidbench preprocess` wrote")
    p.add_argument("--data", type=existing_folder, required=True,
                   help="the bundles the cache was made from (DIR/train)")
    p.add_argument("--out", type=output_folder, required=True,
                   help="activation store (created; a rerun skips done clips)")
    p.add_argument("--model", choices=tuple(MODEL_SPECS), help="default: the cache's model")
    p.add_argument("--model-path", type=Path, help="a local diffusers pipeline directory instead of the hub")
    p.add_argument("--taus", default=PAPER_TAUS, help=f"schedule fractions along the training schedule, 0.9 the "
                                                      f"least noisy (default {PAPER_TAUS})")
    p.add_argument("--random-seed", type=non_negative_int, default=0,
                   help="seed of --backbone random's re-initialisation (default 0, the release's); recorded")
    _conditioning_arguments(p, "default: ours (the options' first values)")
    p.add_argument("--chunk-size", type=int, default=64,
                   help="ignored, kept so older scripts run: the store now keeps one file pair per clip")
    p.add_argument("--device", dest="net_device", help="e.g. cuda or cpu (default: CUDA when available)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")


def _conditioning_arguments(p, default: str) -> None:
    """--recipe and one option per conditioning choice (docs/probing.md, "Recipes"); unset options take the
    recipe's value. The first value of each choice is ours, the second the release's."""
    p.add_argument("--recipe", choices=RECIPE_NAMES,
                   help=f"ours, or release: every choice of the authors' release ({default}); recorded")
    p.add_argument("--prompt", choices=CHOICES["prompt"], help="the evaluation prompt with the paper's suffix, or "
                                                              "the task prompt alone (the release)")
    p.add_argument("--text-padding", choices=CHOICES["padding"],
                   help="text context after the prompt's tokens: zeros, or UMT5's outputs (the release)")
    p.add_argument("--clean-slot-timestep", choices=CHOICES["clean_slot_timestep"],
                   help="timestep of the clean slot 0's tokens: 0, or the noisy t on every token (the release)")
    p.add_argument("--dtype", choices=CHOICES["dtype"], help="the transformer's forward precision")
    p.add_argument("--objective-dtype", choices=CHOICES["objective_dtype"],
                   help="bfloat16 (the release): timesteps rounded to bfloat16, bfloat16 noised latent and target")
    p.add_argument("--noise", choices=CHOICES["noise"],
                   help="noise drawn per clip, or one tensor shared by every clip (the release)")


def _fit_arguments(p) -> None:
    p.add_argument("--acts", type=existing_folder, required=True, help="the store `probe extract` wrote")
    p.add_argument("--out", type=output_folder, required=True,
                   help="directory for scores.csv (a rerun skips done cells)")
    p.add_argument("--targets", help="comma-separated targets (default: all: position, contact, orientation, ...)")
    p.add_argument("--probes", default="linear,mlp", help="linear,mlp (default both)")
    p.add_argument("--blocks", help="comma-separated block indices (default: all)")
    p.add_argument("--taus", help="comma-separated schedule fractions (default: all extracted)")
    p.add_argument("--epochs", type=positive_int, default=20)
    p.add_argument("--batch-size", type=positive_int, default=4096)
    p.add_argument("--lr", type=float, default=1e-3)
    p.add_argument("--seed", type=non_negative_int, default=0)
    p.add_argument("--standardize", action="store_true",
                   help="z-score activations and continuous targets with training statistics (ours; the release, "
                        "and the default, fit raw values)")
    p.add_argument("--r2", choices=("pooled", "mean"), default="pooled",
                   help="R^2 pooled over a target's dimensions (default, the release's) or the mean of per-dimension R^2")
    p.add_argument("--device", dest="net_device", help="where probes train, e.g. cuda or cpu (default: CUDA when "
                                                       "available)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")


def _intervene_arguments(p) -> None:
    p.add_argument("--acts", type=existing_folder, required=True,
                   help="the store `probe extract` wrote (its backbone is used)")
    p.add_argument("--cache", type=existing_folder, required=True, help="the cache the store was extracted from")
    p.add_argument("--out", type=output_folder, required=True, help="output directory (a rerun skips done clips)")
    p.add_argument("--taus", default=INTERVENTION_TAUS, help=f"schedule fractions (default {INTERVENTION_TAUS})")
    p.add_argument("--clips", type=positive_int, default=100, help="the first N clips by id (default 100)")
    p.add_argument("--clip-split", choices=("all", "train"), default="all",
                   help="choose them among all the store's clips (default, the release's) or its training split")
    p.add_argument("--blocks", help="comma-separated block indices (default: all)")
    p.add_argument("--resamples", type=positive_int, default=20000,
                   help="bootstrap resamples over clips (default 20,000)")
    p.add_argument("--full-readout", choices=("resume", "hook"), default="resume",
                   help="resume: run the remaining blocks from the recorded block output (default); hook: a "
                        "forward hook and a whole forward pass (same numbers, about twice the cost)")
    p.add_argument("--inlp-dtype", choices=("float64", "float32"), default="float64",
                   help="precision of the stable INLP's Gram matrix and solves (default float64, as the release's "
                        "ridge)")
    p.add_argument("--inlp-procedure", choices=INLP_PROCEDURES,
                   help="stable (ours) or release (the release's float32 steps, literally); default: the recipe's")
    _conditioning_arguments(p, "default: the recipe and conditioning the store was extracted with")
    p.add_argument("--device", dest="net_device", help="e.g. cuda or cpu (default: CUDA when available; INLP runs "
                                                       "there too)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")


def _report_arguments(p) -> None:
    p.add_argument("--probes", type=existing_folder, nargs="+",
                   help="`probe fit` output directories (one per backbone)")
    p.add_argument("--intervene", type=existing_folder, help="the `probe intervene` output directory")
    p.add_argument("--out", type=output_folder, required=True, help="report directory (index.html)")


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


def conditioning_overrides(args) -> dict:
    """The conditioning choices given on the command line (``commands.probing``), by ``Conditioning`` field."""
    return {field: getattr(args, dest) for dest, field in CONDITIONING_OPTIONS.items()
            if getattr(args, dest, None) is not None}


def cmd_extract(args, ctx: RunContext) -> int:
    run_extract = load_target("rigidbench.stages.probe_extract:run_extract", "command")
    report = run_extract(args.backbone, args.cache, args.data, args.out, model=args.model,
                         model_path=None if args.model_path is None else str(args.model_path),
                         taus=parse_floats(args.taus, "--taus"), device=args.net_device or ctx.device,
                         run=run_options(args), backbone_seed=args.random_seed, recipe=args.recipe,
                         overrides=conditioning_overrides(args))
    status = report_stage(report)  # the words every stage uses; then the rows this run extracted
    facts = report.facts
    empty = f"; no actor covered in {', '.join(facts.empty)}" if facts.empty else ""
    print(f"  actor-slot rows extracted: {facts.rows} ({args.backbone} backbone){empty}")
    for clip, reason in facts.missing.items():  # clips of the cache that --data lacks: failed, as the manifest says
        print(f"  FAILED {clip}: {reason}", file=sys.stderr)
    return 1 if facts.missing else status


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
    run = load_target("rigidbench.stages.probe_intervene:run_intervene", "command")
    if args.clips < 1:
        raise UserError(f"--clips must be at least 1, got {args.clips}")
    report = run(args.acts, args.cache, args.out, taus=parse_floats(args.taus, "--taus"),
                 run=run_options(args, limit=args.clips), blocks=parse_ints(args.blocks, "--blocks"),
                 n_resamples=args.resamples, device=args.net_device or ctx.device, full_readout=args.full_readout,
                 inlp_dtype=args.inlp_dtype, clip_split=args.clip_split, recipe=args.recipe,
                 overrides=conditioning_overrides(args), inlp_procedure=args.inlp_procedure)
    report_stage(report.facts.bases)  # the cells' bases (every one fitted, or the run stopped), then the clips
    status = report_stage(report)
    print(f"  loss change over the {len(report.facts.results['clips'])} clip(s) done, mean [95% CI]:")
    for row in report.facts.results["summary"]:
        print(f"  {row['variant']:>8} {row['readout']:>6}: dL = {row['mean']:.4g} [{row['lo']:.4g}, {row['hi']:.4g}]")
    return status


def cmd_report(args, ctx: RunContext) -> int:
    report = load_target("rigidbench.probe.report:write_report", "command")
    page = report(args.probes or [], args.intervene, args.out)
    print(f"probe report: {page}")
    return 0


COMMANDS = (Command("probe", "probe Wan's transformer for physical state and remove position subspaces "
                            "(paper sections 5.2-5.3)", subcommands=(
    Command("extract", "actor-pooled outputs of every DiT block at five noise levels (resumable)",
            "rigidbench.commands.probing:cmd_extract", _extract_arguments, groups=("selection",)),
    Command("fit", "linear and MLP probes with shuffled-label controls, per block x tau x target",
            "rigidbench.commands.probing:cmd_fit", _fit_arguments),
    Command("intervene", "INLP position subspace vs random and variance-matched PC controls: loss change through "
                         "the remaining blocks and the direct head",
            "rigidbench.commands.probing:cmd_intervene", _intervene_arguments),
    Command("report", "figures (PNG/PDF), CSV tables and an HTML page of probes and interventions",
            "rigidbench.commands.probing:cmd_report", _report_arguments),
)),)
