"""Commands that run video models: predict and audit."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from ..argtypes import IdList, positive_int
from ..context import RunContext
from ..errors import RigidBenchError, UserError
from . import Command, output_dir, report_stage, run_options, split_dir, split_ids


def format_predictors() -> str:
    """The predictor registry as a table: name, kind, what it needs and writes, description, and each model's
    own options (``--model-args``)."""
    from ..predictors import PREDICTORS, format_options, load_entry_points

    load_entry_points()
    lines = [f"{'name':18s} {'kind':13s} {'needs':8s} {'writes':12s} description"]
    for name, info in PREDICTORS.items():
        needs = "Blender" if info.needs_blender else "-"
        writes = "video+state" if info.writes_state else "video"
        lines.append(f"{name:18s} {info.kind.value:13s} {needs:8s} {writes:12s} {info.description}")
        try:
            options = format_options(info, indent=" " * 20)
        except RigidBenchError as exc:  # a plug-in whose target cannot be loaded is still listed
            options = f"{'':20s}(its options cannot be shown: {exc})"
        if options:
            lines.append(options)
    lines.append("\nmodel options: --model-args KEY=VALUE,... (e.g. offload=true,checkpoint=lora.safetensors)")
    lines.append("your own model: rigidbench predict package.module:MyModel (a Predictor subclass or a function "
                 "f(sample, ctx) -> Prediction)")
    return "\n".join(lines)


def predict_context(args, ctx: RunContext, names: list[str]):
    """The PredictContext of ``predict`` (one model) and ``audit`` (several): severity, seed and the models' own
    options from --model-args and the flags that alias them, typed and checked against each model."""
    from ..predictors import PredictContext, audit_options, legacy_flags, model_options, predictor_info

    infos = [predictor_info(name) for name in names]
    options = (model_options(infos[0], args.model_args, legacy_flags(args)) if len(infos) == 1 else
               audit_options(infos, args.model_args, legacy_flags(args)))
    return PredictContext(ctx, args.severity, args.seed, options=options)


def _predict_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("name", nargs="?", help="a registered predictor (see --list) or package.module:Attr for your own")
    p.add_argument("--list", action="store_true", help="list the registered predictors and their options, and exit")
    p.add_argument("--out", type=Path, help="output directory (default predictions/NAME)")
    p.add_argument("--dry-run", action="store_true",
                   help="print the request each example would send and the number of paid calls; send nothing")
    p.add_argument("--samples", type=positive_int, default=1, metavar="K",
                   help="predictions per example (default 1), each with its own seed: sample 0 is <id>.mp4, sample "
                        "k <id>.s<k>.mp4; a hosted model is paid K times per example; raising K later makes only "
                        "the new samples")


def cmd_predict(args, ctx: RunContext) -> int:
    from ..stages.predict import predict
    from ..predictors import predictor_info

    if args.list:
        print(format_predictors())
        return 0
    if not args.name:
        raise UserError("name a predictor (rigidbench predict --list shows them)")
    info = predictor_info(args.name)
    ctx.registry  # a bad configuration file: one error now, not one failure per example
    out = output_dir(args.out or Path("predictions") / info.name, dry_run=args.dry_run)
    report = predict(args.name, split_dir(args), out, predict_context(args, ctx, [args.name]), run_options(args),
                     dry_run=args.dry_run, samples=args.samples)
    if args.dry_run:
        planned = report.facts
        print(f"{report.stage}: would make {len(planned.planned)}, {len(report.reused)} up to date, "
              f"{len(report.failed)} failed of {len(report.selected)} {report.unit}(s)")
        per = (f" ({planned.samples} samples per example, each a paid call of its own)"
               if planned.samples > 1 and planned.paid_calls else "")
        print(f"{info.name}: {planned.paid_calls} paid API calls{per}; nothing was sent")
        if planned.note:
            print(f"note: {planned.note}")
        return 0
    return report_stage(report)


def _audit_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--models", nargs="+", action=IdList, required=True, metavar="NAME",
                   help="comma- or space-separated predictor names, e.g. wan-2.2,veo-3.1")
    p.add_argument("--out", type=Path, default=Path("audit"), help="output directory (default audit/)")
    p.add_argument("--perception", choices=("gt", "neural"), default="neural",
                   help="neural for video models (default); gt only for predictors that write world state")
    p.add_argument("--depth-model", choices=("vda", "dav2"), default="vda")
    p.add_argument("--yes", action="store_true", help="make the paid API calls the audit counted")
    p.add_argument("--resamples", type=positive_int, default=20000, help="bootstrap resamples in the report")


def cmd_audit(args, ctx: RunContext) -> int:
    from ..flows.audit import audit

    models = split_ids(args.models)
    output_dir(args.out)
    ctx.registry  # a bad configuration file: one error now, not one failure per example and model
    options = ({"depth_model": args.depth_model, "device": ctx.device} if args.perception == "neural" else None)
    summary = audit(models, split_dir(args), args.out, predict_context(args, ctx, models), yes=args.yes,
                    perception=args.perception, perception_options=options, run=run_options(args),
                    resamples=args.resamples)
    if summary.stopped_for_confirmation:
        return 2
    for model, failures in summary.failed.items():
        for sample_id, reason in failures.items():
            print(f"  FAILED {model}/{sample_id}: {reason}", file=sys.stderr)
    if summary.report is not None:
        print(f"report: {summary.report}")
    return 1 if summary.failed or summary.blocked else 0


COMMANDS = (
    Command("predict", "make one video (K with --samples K) per reference example with a registered predictor or "
                       "your own model (--list shows the registry); reruns skip examples whose inputs and settings "
                       "are unchanged",
            "rigidbench.commands.models:cmd_predict", _predict_arguments,
            groups=("data", "model", "executor", "selection")),
    Command("audit", "several video models end to end: predict (resuming), validate, evaluate, then one report; "
                     "stops before paid API calls unless --yes",
            "rigidbench.commands.models:cmd_audit", _audit_arguments, groups=("data", "selection", "model")),
)
