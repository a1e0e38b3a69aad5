"""Commands that score and report: validate, evaluate, report, readouts, validate-metrics, weights, demo."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from ..argtypes import IdList, input_folder, int_at_least, non_negative_int, positive_int, writable
from ..context import RunContext
from ..errors import UserError
from . import Command, output_dir, report_stage, run_options, split_dir, split_ids


def _validate_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("predictions", type=Path, help="directory with <id>.mp4 files")


def cmd_validate(args, ctx: RunContext) -> int:
    from ..preflight import main as validate_main

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
    p.add_argument("--envelope", type=Path, metavar="ENV",
                   help="a physical envelope folder (made by `rigidbench envelope` for this set): results.json also "
                        "says, per measurement, task and partition, the share of examples inside the twins' 5-95%% "
                        "band and the mean excess beyond it (docs/statistics.md); changes no score")


def cmd_evaluate(args, ctx: RunContext) -> int:
    from ..stages.evaluate import evaluate

    input_folder(args.predictions, "predictions", "the folder of <id>.mp4 files")
    out = output_dir(args.out or Path("runs") / args.predictions.name)
    options = ({"depth_model": args.depth_model, "device": ctx.device} if args.perception == "neural" else None)
    report = evaluate(args.predictions, split_dir(args), out, perception=args.perception, run=run_options(args),
                      model=args.model, perception_options=options, device=ctx.device, protocol=args.protocol,
                      first_frame_check=not args.no_first_frame_check,
                      allow_short=args.allow_short, envelope=args.envelope)
    status = report_stage(report)  # the words every stage uses; then evaluate's own lines
    facts = report.facts
    dataset = facts.results.get("dataset", {})
    print(f"reference set: {dataset.get('dataset')} {dataset.get('version') or ''}; protocol "
          f"{facts.results['protocol']['name']}; model {facts.results['model']}")
    samples = facts.results.get("samples") or {}
    counts = samples.get("samples_per_example") or {}
    several = (counts.get("max") or 1) > 1  # then each measurement's mean ± the spread between seeds
    if several:
        span = str(counts["min"]) if counts["min"] == counts["max"] else f"{counts['min']} to {counts['max']}"
        print(f"samples per example: {span} ({samples.get('n_items')} scored); each example's value is the mean of "
              "its samples; ± is the seed std (of the whole-set mean over sample indices)")
    for name, stats in facts.results["overall"].items():
        mean = "n/a" if stats["mean"] is None else f"{stats['mean']:.4f}"
        if several:
            seed_std = ((samples.get("metrics") or {}).get(name) or {}).get("seed_std")
            mean += " ± " + ("n/a" if seed_std is None else f"{seed_std:.4f}")
        print(f"  {name:12s} {mean:>10s}  (finite {stats['finite']}/{stats['n']})")
    for metric, reason in facts.skipped_metrics.items():
        print(f"  skipped {metric}: {reason}")
    if "envelope" in facts.results:
        _print_envelope(facts.results["envelope"])
    print("official result" if facts.official else
          "not an official result: " + "; ".join(facts.results.get("why_not_official", [])))
    return status


def _print_envelope(block: dict) -> None:
    """evaluate --envelope's lines: per measurement the share inside the envelope and the mean excess."""
    print(f"against the envelope {block['source']} ({block['twins']} twins"
          f"{', geometry only' if block['geometry_only'] else ''}):")
    for name, stats in block["overall"].items():
        if stats["n"]:
            print(f"  {name:12s} inside {stats['inside']:6.1%}  mean excess {stats['excess']:.4g}  (n {stats['n']})")
    if block["no_envelope"]:
        ids = list(block["no_envelope"])
        print(f"  {block['n_no_envelope']} examples without an envelope: {', '.join(ids[:10])}"
              f"{' ...' if len(ids) > 10 else ''}")


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
    p.add_argument("--envelope-metric", default="ate3d", metavar="METRIC",
                   help="the measurement of the figure of each model's samples against the physical envelope "
                        "(default ate3d; runs scored with `evaluate --envelope`)")
    p.add_argument("--power-difference", action="append", default=[], metavar="METRIC=VALUE",
                   help="a difference the power table says how many examples and samples need (repeatable; in "
                        "the measurement's unit; default 10%% of the baseline's mean)")


def cmd_report(args, ctx=None) -> int:
    """CLI entry: args.runs (list of run dirs), args.out, args.baseline, args.resamples, args.seed; optional
    args.examples (filmstrip examples, default 3), args.no_clips, args.outlines ("reference" or "perceived"),
    args.probe_report (a probe report to link), args.envelope_metric, args.power_difference (METRIC=VALUE)."""
    from ..metrics import METRICS
    from ..report import build_report
    from ..report.samples import parse_differences

    writable(args.out)
    page = build_report(args.runs, args.out, resamples=args.resamples, seed=args.seed, baseline=args.baseline,
                        examples=getattr(args, "examples", 3), clips=not getattr(args, "no_clips", False),
                        outlines=getattr(args, "outlines", "reference"),
                        probe_report=getattr(args, "probe_report", None),
                        envelope_metric=getattr(args, "envelope_metric", "ate3d"),
                        power_differences=parse_differences(getattr(args, "power_difference", None), tuple(METRICS)))
    print(f"report for {len(args.runs)} run(s): {page}")
    return 0


def _readouts_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("runs", nargs="+", type=Path, help="run directories (runs/MODEL)")
    p.add_argument("--examples", action="store_true", help="also one line per example")


def cmd_readouts(args, ctx=None) -> int:
    """CLI: rigidbench readouts RUN [RUN ...] [--examples]: print each run's readouts."""
    from ..folders import RunFolder
    from ..readouts.records import DISTRIBUTIONS, format_block, load_run_readouts, summary

    for run in args.runs:
        run = Path(run)
        if not RunFolder(run).examples_dir.is_dir():
            raise UserError(f"{run}: not a run folder (no examples/); run `rigidbench evaluate` first")
        model, block, examples = load_run_readouts(run)
        for line in format_block(model, block):
            print(line)
        if getattr(args, "examples", False):
            for e in examples:
                s = summary(e["readouts"])
                raised = [k for k, v in s["flags"].items() if v]
                vals = ", ".join(f"{k} {('-' if s[k] is None else format(s[k], '.3g'))}" for k in DISTRIBUTIONS)
                which = f"{e['id']} sample {e['sample']}" if e.get("sample") else e["id"]
                print(f"    {which} ({e.get('task', '')}): {vals}; flags: {', '.join(raised) or 'none'}")
    return 0


def _validate_metrics_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--out", type=Path, default=Path("validation"), help="output directory (default validation/)")
    p.add_argument("--examples", type=positive_int, default=10, help="reference examples to perturb (default 10)")
    p.add_argument("--severities", type=int_at_least(2), default=6, help="levels per sweep, >= 2")
    p.add_argument("--seed", type=non_negative_int, default=0)
    p.add_argument("--with-rendered", action="store_true",
                   help="also use the failure modes that re-render with Blender (depth-offset, identity-swap; slow)")


def cmd_validate_metrics(args, ctx=None) -> int:
    """CLI: rigidbench validate-metrics --data DIR --out DIR [--examples N] [--severities K] [--seed S]
    [--with-rendered]."""
    from ..groundtruth.bundle import resolve_split_dir
    from ..validation.run import TABLE_STEM, validate_metrics

    writable(args.out)
    try:
        out = validate_metrics(resolve_split_dir(args.data, args.split), args.out, examples=args.examples, severities=args.severities,
                               seed=args.seed, with_rendered=getattr(args, "with_rendered", False))
    except ValueError as exc:  # an option out of range (BundleError, a RigidBenchError, reaches the CLI as is)
        raise UserError(str(exc)) from None
    summary = json.loads((out / "summary.json").read_text())
    print(f"metric validation on {len(summary['examples'])} examples: {', '.join(summary['examples'])}")
    for line in summary["lines"]:
        print(f"  {line}")
    for metric, reason in summary["skipped"].items():
        print(f"  skipped {metric}: {reason}")
    print(f"table: {out / (TABLE_STEM + '.md')} and .csv; figure: {out / (TABLE_STEM + '.png')} and .pdf")
    return 0


def _weights_arguments(p: argparse.ArgumentParser) -> None:
    """--list and --download [NAME ...]."""
    from ..perception.weights import WEIGHTS  # light: no torch or transformers at import

    group = p.add_mutually_exclusive_group()
    group.add_argument("--list", action="store_true", help="show every weight, where it is looked for and whether "
                                                           "it is present (the default)")
    group.add_argument("--download", nargs="*", metavar="NAME",
                       help=f"fetch weights into the standard caches for offline use; names: {', '.join(WEIGHTS)} "
                            "(none: everything the default neural perception and feature metrics need)")
    p.add_argument("--json", action="store_true", help="with --list: print JSON instead of a table")


def cmd_weights(args, ctx=None) -> int:
    """`rigidbench weights`: args.list (bool), args.download (None or list of names; [] = defaults),
    args.json (bool). Returns 0 on success, 1 if a download failed; an unknown name is a UserError."""
    from ..errors import WeightsUnavailable
    from ..perception.weights import WEIGHTS, download, format_listing, locate, missing_message, spec, status

    if args.download is None:
        rows = [status(name) for name in WEIGHTS]
        print(json.dumps(rows, indent=2) if getattr(args, "json", False) else format_listing(rows))
        return 0
    names = args.download or [n for n, w in WEIGHTS.items() if w.default]
    try:
        for name in names:
            spec(name)
    except KeyError as exc:
        raise UserError(f"--download: {exc.args[0]}") from None
    failed = 0
    for name in names:
        w = WEIGHTS[name]
        if w.kind == "package":
            found = locate(name)
            print(f"{name}: {'present at ' + str(found) if found else missing_message(name)}")
            failed += found is None
            continue
        try:
            print(f"{name}: downloaded to {download(name)}")
        except WeightsUnavailable as exc:
            print(f"{name}: {exc}", file=sys.stderr)
            failed += 1
    return 1 if failed else 0


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
    p.add_argument("--twins", type=non_negative_int, default=4, metavar="N",
                   help="geometry-only physical twins per example in the demo's envelope (default 4; 0: no envelope)")


def cmd_demo(args, ctx: RunContext) -> int:
    from ..flows.demo import run_demo

    output_dir(args.out)
    modes = split_ids(args.modes) or None
    kwargs = {"modes": modes} if modes else {}
    return run_demo(args.out, quality=args.quality, severity=args.severity, perception=args.perception,
                    report=not args.no_report, ctx=ctx, twins=args.twins, **kwargs)


COMMANDS = (
    Command("validate", "fast preflight of a predictions directory before evaluation",
            "rigidbench.commands.scoring:cmd_validate", _validate_arguments, groups=("data",)),
    Command("evaluate", "score predictions against the reference with the ten measurements; reruns rescore only "
                        "examples whose prediction, reference or settings changed",
            "rigidbench.commands.scoring:cmd_evaluate", _evaluate_arguments, groups=("data", "executor", "selection")),
    Command("report", "tables, figures and report.html from evaluation runs",
            "rigidbench.commands.scoring:cmd_report", _report_arguments),
    Command("readouts", "physics readouts of evaluation runs: playback speed, gravity, restitution, failure flags "
                        "(docs/physics.md)",
            "rigidbench.commands.scoring:cmd_readouts", _readouts_arguments),
    Command("validate-metrics", "controlled metric perturbations and one failure-mode response curve per metric "
                                "(figure + table)",
            "rigidbench.commands.scoring:cmd_validate_metrics", _validate_metrics_arguments, groups=("data",)),
    Command("weights", "list the perception/feature network weights, or download them for offline use",
            "rigidbench.commands.scoring:cmd_weights", _weights_arguments),
    Command("demo", "the whole loop on this machine: render, predict, evaluate (CPU, minutes)",
            "rigidbench.commands.scoring:cmd_demo", _demo_arguments),
)
