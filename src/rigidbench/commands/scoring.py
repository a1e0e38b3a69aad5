"""Commands that score and report: validate, evaluate, report, readouts, validate-metrics, weights, demo."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from ..argtypes import IdList, input_folder, int_at_least, non_negative_int, positive_int
from ..context import RunContext
from . import Command, executor_from, output_dir, selected_ids, split_dir, split_ids


def _validate_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("predictions", type=Path, help="directory with <id>.mp4 files")


def cmd_validate(args, ctx: RunContext) -> int:
    from ..validate import main as validate_main

    input_folder(args.predictions, "predictions", "the folder of <id>.mp4 files")
    return validate_main(args.predictions, split_dir(args))


def _evaluate_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("predictions", type=Path, help="directory with <id>.mp4 files (predictions/MODEL)")
    p.add_argument("--perception", choices=("gt", "neural"), default="gt",
                   help="gt: exact world state written by built-in predictors; neural: SAM 2.1 masks, CoTracker3 "
                        "tracks, Video Depth Anything disparity (for any model's videos; weights: rigidbench weights)")
    p.add_argument("--depth-model", choices=("vda", "dav2"), default="vda",
                   help="neural disparity: Video Depth Anything Large (the paper's) or Depth Anything V2 per frame")
    p.add_argument("--device", dest="net_device",
                   help="neural perception device, e.g. cuda or cpu (default: CUDA when available)")
    p.add_argument("--out", type=Path, help="run directory (default runs/<predictions dir name>)")
    p.add_argument("--model", help="model name in the results (default: the predictions directory name)")
    p.add_argument("--protocol", default=None, metavar="NAME",
                   help="evaluation protocol (default rigidbench-v1): rigidbench-v1: the published evaluator's rules, "
                        "comparable with the paper (OpenCV decoding, JPEG q95 4:4:4 after resizing, the release's "
                        "edge rules in the metrics); paper-rules: the same JPEG round trip with PyAV decoding and "
                        "our edge rules; lossless: paper-rules without the JPEG round trip (docs/metrics.md)")
    p.add_argument("--no-first-frame-check", action="store_true",
                   help="score predictions whose first frame is not their reference's (normally refused as made from "
                        "another set's inputs); recorded in results.json")
    p.add_argument("--allow-short", action="store_true",
                   help="score clips that do not cover the reference span (normally refused, as by the published "
                        "evaluator) on the frames they have; marked short in results.json, never official")


def cmd_evaluate(args, ctx: RunContext) -> int:
    from ..evaluation import evaluate

    input_folder(args.predictions, "predictions", "the folder of <id>.mp4 files")
    out = output_dir(args.out or Path("runs") / args.predictions.name)
    options = ({"depth_model": args.depth_model, "device": ctx.device} if args.perception == "neural" else None)
    executor, shard = executor_from(args)
    summary = evaluate(args.predictions, split_dir(args), out, perception=args.perception, ids=selected_ids(args),
                       limit=args.limit, model=args.model, perception_options=options, executor=executor, shard=shard,
                       device=ctx.device, protocol=args.protocol, first_frame_check=not args.no_first_frame_check,
                       allow_short=args.allow_short)
    overall = summary.results["overall"]
    dataset = summary.results.get("dataset", {})
    print(f"reference set: {dataset.get('dataset')} {dataset.get('version') or ''}; protocol "
          f"{summary.results['protocol']['name']}")
    print(f"{summary.results['model']}: {len(summary.evaluated)} evaluated, {len(summary.reused)} unchanged "
          f"(reused), {len(summary.failed)} failed"
          + (f", {len(summary.elsewhere)} being evaluated by another process" if summary.elsewhere else "")
          + f" -> {out}")
    for name, stats in overall.items():
        mean = "n/a" if stats["mean"] is None else f"{stats['mean']:.4f}"
        print(f"  {name:12s} {mean:>10s}  (finite {stats['finite']}/{stats['n']})")
    for metric, reason in summary.skipped_metrics.items():
        print(f"  skipped {metric}: {reason}")
    for sample_id, reason in summary.failed.items():
        print(f"  FAILED {sample_id}: {reason}", file=sys.stderr)
    print("official result" if summary.official else
          "not an official result: " + "; ".join(summary.results.get("why_not_official", [])))
    return 1 if summary.failed else 0


def _report_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("runs", nargs="+", type=Path, help="run directories (runs/*)")
    p.add_argument("--out", type=Path, default=Path("report"), help="output directory (default report/)")
    p.add_argument("--baseline", help="model for paired changes (default: first run not named 'reference')")
    p.add_argument("--resamples", type=positive_int, default=20000, help="bootstrap resamples (default 20000)")
    p.add_argument("--seed", type=non_negative_int, default=0)
    p.add_argument("--examples", type=non_negative_int, default=3,
                   help="examples shown as filmstrips (default 3; 0: none)")
    p.add_argument("--no-clips", action="store_true", help="no looping video clips beside the filmstrips")
    p.add_argument("--outlines", choices=("reference", "perceived"), default="reference",
                   help="object outlines drawn on the filmstrips: the reference masks, or each run's perceived masks")
    p.add_argument("--probe-report", type=Path, metavar="PATH",
                   help="a probe report (the report.html `rigidbench probe report` wrote, or its directory) to link")


def _readouts_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("runs", nargs="+", type=Path, help="run directories (runs/MODEL)")
    p.add_argument("--examples", action="store_true", help="also one line per example")


def _validate_metrics_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--out", type=Path, default=Path("validation"), help="output directory (default validation/)")
    p.add_argument("--examples", type=positive_int, default=10, help="reference examples to perturb (default 10)")
    p.add_argument("--severities", type=int_at_least(2), default=6, help="levels per sweep, >= 2")
    p.add_argument("--seed", type=non_negative_int, default=0)
    p.add_argument("--with-rendered", action="store_true",
                   help="also use the failure modes that re-render with Blender (depth-offset, identity-swap; slow)")


def _weights_arguments(p: argparse.ArgumentParser) -> None:
    from ..perception.weights import add_arguments  # light: no torch or transformers at import

    add_arguments(p)


def _demo_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--out", type=Path, default=Path("demo_out"), help="output directory (default demo_out)")
    p.add_argument("--quality", choices=("demo", "preview", "test"), default="demo",
                   help="render preset for the reference clips (default demo: the preview clip, 320x176, 49 frames, "
                        "at 4 samples denoised; preview: 8 samples)")
    p.add_argument("--severity", type=float, default=0.5, help="severity of every failure mode, in [0, 1]")
    p.add_argument("--perception", choices=("gt", "neural"), default="gt",
                   help="gt: exact world state (no networks); neural: SAM 2.1, CoTracker3, Video Depth Anything")
    p.add_argument("--modes", nargs="+", action=IdList, metavar="NAME",
                   help="built-in predictors to run (default: a set of "
                   "image-space failure modes plus gravity)")
    p.add_argument("--no-report", action="store_true", help="skip the report (tables, figures, report.html)")


def cmd_demo(args, ctx: RunContext) -> int:
    from ..pipeline.demo import run_demo

    output_dir(args.out)
    modes = split_ids(args.modes) or None
    kwargs = {"modes": modes} if modes else {}
    return run_demo(args.out, quality=args.quality, severity=args.severity, perception=args.perception,
                    report=not args.no_report, ctx=ctx, **kwargs)


COMMANDS = (
    Command("validate", "fast preflight of a predictions directory before evaluation",
            "rigidbench.commands.scoring:cmd_validate", _validate_arguments, groups=("data",)),
    Command("evaluate", "score predictions against the reference with the ten measurements; reruns rescore only "
                        "examples whose prediction, reference or settings changed",
            "rigidbench.commands.scoring:cmd_evaluate", _evaluate_arguments, groups=("data", "executor", "selection")),
    Command("report", "tables, figures and report.html from evaluation runs",
            "rigidbench.report:cmd_report", _report_arguments),
    Command("readouts", "physics readouts of evaluation runs: playback speed, gravity, restitution, failure flags "
                        "(docs/physics.md)",
            "rigidbench.readouts.records:cmd_readouts", _readouts_arguments),
    Command("validate-metrics", "controlled metric perturbations and one failure-mode response curve per metric "
                                "(figure + table)",
            "rigidbench.validation:cmd_validate_metrics", _validate_metrics_arguments, groups=("data",)),
    Command("weights", "list the perception/feature network weights, or download them for offline use",
            "rigidbench.perception.weights:cmd_weights", _weights_arguments),
    Command("demo", "the whole loop on this machine: render, predict, evaluate (CPU, minutes)",
            "rigidbench.commands.scoring:cmd_demo", _demo_arguments),
)
