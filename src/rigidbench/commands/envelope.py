"""The command that measures how much error physics itself allows: envelope (docs/statistics.md)."""

from __future__ import annotations

import argparse
import math
from pathlib import Path

from ..argtypes import int_at_least, non_negative_int, output_folder
from ..context import RunContext
from . import Command, report_stage, run_options, split_dir


def _scale(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number") from None
    if not math.isfinite(value) or value < 0:
        raise argparse.ArgumentTypeError(f"{text!r}: the scale must be a finite number >= 0")
    return value


def _envelope_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--out", type=output_folder, required=True, metavar="ENV",
                   help="the envelope folder (twins in ENV/predictions, their scores in ENV/run, ENV/envelope.json); "
                        "pass it to `rigidbench evaluate --envelope ENV`")
    p.add_argument("--twins", type=int_at_least(2), default=8, metavar="N",
                   help="physical twins per example (default 8)")
    p.add_argument("--scale", type=_scale, default=1.0,
                   help="multiplies every deviation of the envelope configuration (default 1: as configured; 0: the "
                        "reference itself)")
    p.add_argument("--full", action="store_true",
                   help="path trace every twin like the reference, so the appearance measurements get an envelope too "
                        "(a full render per twin); default: geometry only (simulator and data passes, no path "
                        "tracing; the six motion measurements)")
    p.add_argument("--envelope-config", type=Path, metavar="FILE",
                   help="the perturbation, as configs/envelope.yaml (default: the packaged one)")
    p.add_argument("--seed", type=non_negative_int, default=0, help="base seed of the twins' draws (default 0)")


def cmd_envelope(args, ctx: RunContext) -> int:
    """`rigidbench envelope --data DATA --out ENV [--twins N] [--scale S] [--full] [--envelope-config FILE]`."""
    from ..flows.envelope import make_envelope

    facts = make_envelope(split_dir(args), args.out, twins=args.twins, scale=args.scale, geometry_only=not args.full,
                          config=args.envelope_config, seed=args.seed, run=run_options(args), ctx=ctx)
    status = 0
    for report in facts.reports:
        status = max(status, report_stage(report))
    if not facts.written:
        print(f"envelope: shard {args.shard}: its twins are made and scored; run once more without --shard to write "
              f"{args.out / 'envelope.json'}")
        return status
    ok = sorted(i for i, e in facts.examples.items() if e.get("status") == "ok")
    print(f"envelope: {len(ok)} of {len(facts.examples)} examples have one ({args.twins} twins each, scale "
          f"{args.scale:g}, {'path traced' if args.full else 'geometry only'}); {args.out / 'envelope.json'}")
    for sample_id, entry in facts.examples.items():
        if entry.get("status") != "ok":
            print(f"  no envelope {sample_id}: {entry.get('reason')}")
        elif (entry.get("reconstruction") or {}).get("zero_twin"):
            floor = ", ".join(f"{m} {v:.4g}" for m, v in entry["reconstruction"]["zero_twin"].items())
            print(f"  imported {sample_id}: its twin at scale 0 against the published reference (the floor): {floor}")
    if facts.resimulation is not None:
        print(f"re-simulated imported examples: {facts.resimulation['with_envelope']} of "
              f"{facts.resimulation['examples']} reproduce the published trajectory (largest position error over "
              f"the first {facts.resimulation['tolerance']['window_s']:g} s at most "
              f"{facts.resimulation['tolerance']['max_position_error_m'] * 100:g} cm)")
        for row in facts.resimulation["by_task"]:
            error = row.get("median_max_m")
            print(f"  {row['task']:18s} {row['with_envelope']} of {row['count']} reproduced; median largest error "
                  + ("n/a" if error is None else f"{error * 100:.2f} cm"))
    if facts.widths:
        metrics = list(next(iter(facts.widths.values())))
        print("envelope width (median over examples of the twins' 95th - 5th percentile):")
        print(f"  {'task':18s}" + "".join(f"{m:>12s}" for m in metrics))
        for task, row in facts.widths.items():
            cells = ("n/a" if row.get(m) is None else f"{row[m]:.4g}" for m in metrics)
            print(f"  {task:18s}" + "".join(f"{c:>12s}" for c in cells))
    return status

COMMANDS = (
    Command("envelope", "the physical envelope of a reference set: N twins per example re-simulated within what one "
                        "frame cannot resolve, scored like a model (docs/statistics.md)",
            "rigidbench.commands.envelope:cmd_envelope", _envelope_arguments,
            groups=("data", "selection", "executor", "progress")),
)
