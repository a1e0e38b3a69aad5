"""What ``rigidbench probe extract|fit|intervene|report`` runs (declared in ``commands.probing``) (paper sections 5.2-5.3,
appendix E; docs/probing.md). Light: torch and the models are imported only when a command runs."""

from __future__ import annotations

import sys

from ..context import RunContext
from ..argtypes import selected_ids
from ..errors import UserError
from ..perception.device import resolve_device
from ..registry import load_target

PAPER_TAUS = "0.1,0.3,0.5,0.7,0.9"
INTERVENTION_TAUS = "0.3,0.5,0.7"
#: command-line destination -> ``recipe.Conditioning`` field
CONDITIONING_OPTIONS = {"prompt": "prompt", "text_padding": "padding", "clean_slot_timestep": "clean_slot_timestep",
                        "dtype": "dtype", "objective_dtype": "objective_dtype", "noise": "noise"}


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
    run_extract = load_target("rigidbench.probe.extract:run_extract", "command")
    summary = run_extract(args.backbone, args.cache, args.data, args.out, model=args.model,
                          model_path=None if args.model_path is None else str(args.model_path),
                          taus=parse_floats(args.taus, "--taus"), device=args.net_device or ctx.device,
                          limit=args.limit, progress=not args.no_progress, backbone_seed=args.random_seed,
                          ids=selected_ids(args), recipe=args.recipe, overrides=conditioning_overrides(args))
    print(f"probe extract ({args.backbone}): {len(summary.extracted)} clips, {summary.rows} actor-slot rows into "
          f"{summary.out} ({len(summary.skipped)} already there, {len(summary.failed)} failed) in "
          f"{summary.seconds:.1f} s")
    _print_redone(summary.redone, summary.report.ran if summary.report else [])
    for clip, reason in summary.failed.items():
        print(f"  FAILED {clip}: {reason}", file=sys.stderr)
    return 1 if summary.failed and not summary.extracted and not summary.skipped else 0


def _print_redone(redone: dict[str, str], ran) -> None:
    """One line for the clips made again this run and why (the first few)."""
    again = [i for i in ran if i in redone]
    if again:
        print(f"  made again: {len(again)} clips ({'; '.join(f'{i}: {redone[i]}' for i in again[:5])}"
              f"{' ...' if len(again) > 5 else ''})")


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
                 inlp_dtype=args.inlp_dtype, clip_split=args.clip_split, recipe=args.recipe,
                 overrides=conditioning_overrides(args), inlp_procedure=args.inlp_procedure)
    print(f"probe intervene: {len(result['clips'])} clips ({result['clips_this_run']} run now), "
          f"{len(result['bases'])} cells ({result['bases_fitted_this_run']} fitted now) into {args.out}")
    _print_redone(result.get("redone", {}), result["clips"])
    for row in result["summary"]:
        print(f"  {row['variant']:>8} {row['readout']:>6}: dL = {row['mean']:.4g} [{row['lo']:.4g}, {row['hi']:.4g}]")
    for clip, reason in result.get("failed", {}).items():
        print(f"  FAILED {clip}: {reason}", file=sys.stderr)
    return 0


def cmd_report(args, ctx: RunContext) -> int:
    report = load_target("rigidbench.probe.report:write_report", "command")
    page = report(args.probes or [], args.intervene, args.out)
    print(f"probe report: {page}")
    return 0
