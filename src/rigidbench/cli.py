"""The ``rigidbench`` command. Subcommands import their stage lazily so ``--help`` is instant."""

from __future__ import annotations

import argparse
import logging
import os
import sys
from pathlib import Path

DEFAULT_DATA = Path("data")


class UserError(Exception):
    """An error caused by the user's input: printed as one line, exit status 2."""


def _ids(value: str) -> list[str]:
    return [v.strip() for v in value.replace(",", " ").split() if v.strip()]


def _split_rows(args):
    from . import manifest
    from .config import registry

    reg = registry()
    rows = manifest.rows(args.split, reg)
    ids = [i for chunk in (args.ids or []) for i in _ids(chunk)]
    try:
        return reg, manifest.select(rows, ids or None, args.limit)
    except KeyError as exc:
        raise UserError(exc.args[0]) from None


# -- subcommands ---------------------------------------------------------------------------------


def cmd_manifest(args) -> int:
    from . import manifest
    from .config import registry

    rows = manifest.rows(args.split, registry())
    out = args.out or Path("manifests") / f"{args.split}.jsonl"
    manifest.write(out, rows)
    print(f"wrote {len(rows)} {args.split} rows to {out}")
    return 0


def cmd_simulate(args) -> int:
    from .pipeline.simulate import simulate_rows

    reg, rows = _split_rows(args)
    out = args.out or DEFAULT_DATA / args.split
    failures, skipped = simulate_rows(rows, reg, Path(out))
    print(f"simulated {len(rows) - len(failures) - len(skipped)} of {len(rows)} examples into {out} "
          f"({len(skipped)} already done)")
    for sample_id, reason in failures:
        print(f"  FAILED {sample_id}: {reason}", file=sys.stderr)
    return 1 if failures else 0


def cmd_inputs(args) -> int:
    from .benchmark import write_inputs

    try:
        out = write_inputs(args.data, args.out)
    except FileNotFoundError as exc:
        raise UserError(str(exc)) from None
    print(f"wrote {out}")
    return 0


def cmd_validate(args) -> int:
    from .validate import main as validate_main

    return validate_main(args.predictions, args.data)


def cmd_evaluate(args) -> int:
    from .evaluate import EvaluationError, evaluate

    ids = [i for chunk in (args.ids or []) for i in _ids(chunk)]
    out = args.out or Path("runs") / args.predictions.name
    try:
        options = ({"depth_model": args.depth_model, "device": args.device}
                   if args.perception == "neural" else None)
        summary = evaluate(args.predictions, args.data, out, perception=args.perception, ids=ids or None,
                           limit=args.limit, model=args.model, perception_options=options)
    except EvaluationError as exc:
        raise UserError(str(exc)) from None
    overall = summary.results["overall"]
    print(f"{summary.results['model']}: {len(summary.evaluated)} evaluated, {len(summary.reused)} unchanged "
          f"(reused), {len(summary.failed)} failed -> {out}")
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


def cmd_predict(args) -> int:
    from .evaluate import EvaluationError
    from .pipeline.predict import predict

    ids = [i for chunk in (args.ids or []) for i in _ids(chunk)]
    out = args.out or Path("predictions") / args.name
    try:
        written, failed = predict(args.name, args.data, out, args.severity, ids or None, args.limit)
    except (KeyError, ValueError, EvaluationError) as exc:
        raise UserError(exc.args[0]) from None
    print(f"{args.name} (severity {args.severity}): wrote {len(written)} predictions to {out}")
    for sample_id, reason in failed.items():
        print(f"  FAILED {sample_id}: {reason}", file=sys.stderr)
    return 1 if failed else 0


def cmd_demo(args) -> int:
    from .pipeline.demo import run_demo

    modes = [m for chunk in (args.modes or []) for m in _ids(chunk)] or None
    kwargs = {"modes": modes} if modes else {}
    from .evaluate import EvaluationError

    try:
        return run_demo(args.out, quality=args.quality, severity=args.severity, perception=args.perception,
                        report=not args.no_report, **kwargs)
    except KeyError as exc:
        raise UserError(exc.args[0]) from None
    except EvaluationError as exc:
        raise UserError(str(exc)) from None


def _add_weights_arguments(parser) -> None:
    from .perception.weights import add_arguments  # light: no torch or transformers at import

    add_arguments(parser)


def _lazy(target: str):
    """A subcommand function imported only when that subcommand runs (keeps --help instant)."""
    def run(args):
        import importlib

        module, attr = target.split(":")
        return getattr(importlib.import_module(module), attr)(args)

    return run


def _add_render_commands(subparsers) -> None:
    """Register ``render`` and ``show`` on the ``rigidbench`` subparsers."""
    p = subparsers.add_parser("render", help="simulate and render examples into sample bundles "
                                             "(DATA/<split>/<id>/); reruns skip complete bundles")
    p.add_argument("--split", choices=("train", "eval"), default="eval", help="manifest to draw examples from")
    p.add_argument("--ids", nargs="+", metavar="ID", help="sample ids, e.g. 00000 00007 (default: all)")
    p.add_argument("--limit", type=int, help="only the first N selected examples")
    p.add_argument("--quality", default="paper", help="render preset: paper, preview or test (configs/render.yaml)")
    p.add_argument("--data", type=Path, default=DEFAULT_DATA, help="data directory (default: data)")
    p.add_argument("--workers", type=int, default=1, help="examples rendered at once, one process each (default 1)")
    p.add_argument("--device", choices=("auto", "cpu", "gpu"), default="auto",
                   help="Cycles device: auto picks OptiX, then CUDA, then the CPU (default auto)")
    p.add_argument("--no-progress", action="store_true", help="no progress bars")
    p.set_defaults(func=_lazy("rigidbench.pipeline.render:cmd_render"))

    p = subparsers.add_parser("show", help="write a PNG contact sheet of a rendered example "
                                           "(frames, masks, depth, ground-truth tracks)")
    p.add_argument("id", help="sample id, e.g. 00000")
    p.add_argument("--split", choices=("train", "eval"), default="eval")
    p.add_argument("--data", type=Path, default=DEFAULT_DATA, help="data directory (default: data)")
    p.add_argument("--out", type=Path, help="output PNG (default: <split>_<id>_contact_sheet.png)")
    p.set_defaults(func=_lazy("rigidbench.pipeline.render:cmd_show"))



# -- parser --------------------------------------------------------------------------------------


def _add_selection(p: argparse.ArgumentParser, split_default: str = "eval") -> None:
    p.add_argument("--split", choices=("train", "eval"), default=split_default, help="manifest to draw examples from")
    p.add_argument("--ids", nargs="+", metavar="ID", help="sample ids, e.g. 00000 00007 (default: all)")
    p.add_argument("--limit", type=int, help="only the first N selected examples")


def layer_config_dirs(dirs) -> None:
    """Make ``--config`` directories apply to every registry this process and its workers load (predictors,
    evaluation and counterfactual re-renders load it deep inside) by appending them to
    $RIGIDBENCH_CONFIG_PATH; raises ConfigError naming a directory that does not exist."""
    from .config import config_dirs

    env = [p for p in os.environ.get("RIGIDBENCH_CONFIG_PATH", "").split(os.pathsep) if p]
    os.environ["RIGIDBENCH_CONFIG_PATH"] = os.pathsep.join(env + [str(Path(d).resolve()) for d in dirs])
    config_dirs()


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="rigidbench",
        description="RigidBench: simulator-grounded evaluation of rigid-body physics in video generation models.")
    parser.add_argument("--config", action="append", default=[], metavar="DIR",
                        help="extra configuration directory layered over the packaged configs and "
                             "$RIGIDBENCH_CONFIG_PATH, for every stage of the command (repeatable)")
    parser.add_argument("-v", "--verbose", action="store_true", help="log debug messages")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")

    p = sub.add_parser("manifest", help="write the fixed train (5,000) or eval (100) manifest as JSON Lines")
    p.add_argument("--split", choices=("train", "eval"), required=True)
    p.add_argument("--out", type=Path, help="output file (default manifests/<split>.jsonl)")
    p.set_defaults(func=cmd_manifest)

    p = sub.add_parser("simulate", help="simulate examples with Bullet (no rendering): scene_spec.json, "
                                        "trajectories.npz, contacts.json per example")
    _add_selection(p)
    p.add_argument("--out", type=Path, help="output directory (default data/<split>)")
    p.set_defaults(func=cmd_simulate)

    _add_render_commands(sub)

    p = sub.add_parser("inputs", help="write inputs.jsonl: first frame, prompt and negative prompt per example")
    p.add_argument("--data", type=Path, default=DEFAULT_DATA / "eval", help="rendered split directory (default data/eval)")
    p.add_argument("--out", type=Path, help="output file (default DATA/inputs.jsonl)")
    p.set_defaults(func=cmd_inputs)

    p = sub.add_parser("predict", help="run a built-in predictor (failure mode) over the reference examples")
    p.add_argument("name", help="image space: reference, static, slow, fast, delayed, gamma, camera-shake, "
                                "camera-drift, background-wobble, identity-swap; re-simulated and re-rendered: "
                                "gravity, restitution, friction, mass, depth-offset")
    p.add_argument("--data", type=Path, default=DEFAULT_DATA / "eval", help="rendered split directory")
    p.add_argument("--out", type=Path, help="output directory (default predictions/NAME)")
    p.add_argument("--severity", type=float, default=1.0, help="0 = the reference, 1 = strong (default 1)")
    p.add_argument("--ids", nargs="+", metavar="ID")
    p.add_argument("--limit", type=int)
    p.set_defaults(func=cmd_predict)

    p = sub.add_parser("validate", help="fast preflight of a predictions directory before evaluation")
    p.add_argument("predictions", type=Path, help="directory with <id>.mp4 files")
    p.add_argument("--data", type=Path, default=DEFAULT_DATA / "eval", help="rendered split directory")
    p.set_defaults(func=cmd_validate)

    p = sub.add_parser("evaluate", help="score predictions against the reference with the ten measurements")
    p.add_argument("predictions", type=Path, help="directory with <id>.mp4 files (predictions/MODEL)")
    p.add_argument("--data", type=Path, default=DEFAULT_DATA / "eval", help="rendered split directory")
    p.add_argument("--perception", choices=("gt", "neural"), default="gt",
                   help="gt: exact world state written by built-in predictors; neural: SAM 2.1 masks, CoTracker3 "
                        "tracks, Video Depth Anything disparity (for any model's videos; weights: rigidbench weights)")
    p.add_argument("--depth-model", choices=("vda", "dav2"), default="vda",
                   help="neural disparity: Video Depth Anything Large (the paper's) or Depth Anything V2 per frame")
    p.add_argument("--device", help="neural perception device, e.g. cuda or cpu (default: CUDA when available)")
    p.add_argument("--out", type=Path, help="run directory (default runs/<predictions dir name>)")
    p.add_argument("--model", help="model name in the results (default: the predictions directory name)")
    p.add_argument("--ids", nargs="+", metavar="ID")
    p.add_argument("--limit", type=int)
    p.set_defaults(func=cmd_evaluate)
    p = sub.add_parser("report", help="tables, figures and report.html from evaluation runs")
    p.add_argument("runs", nargs="+", type=Path, help="run directories (runs/*)")
    p.add_argument("--out", type=Path, default=Path("report"), help="output directory (default report/)")
    p.add_argument("--baseline", help="model for paired changes (default: first run not named 'reference')")
    p.add_argument("--resamples", type=int, default=20000, help="bootstrap resamples (default 20000)")
    p.add_argument("--seed", type=int, default=0)
    p.set_defaults(func=_lazy("rigidbench.report:cmd_report"))
    p = sub.add_parser("validate-metrics", help="controlled metric perturbations and one failure-mode response "
                       "curve per metric (figure + table)")
    p.add_argument("--data", type=Path, default=DEFAULT_DATA / "eval", help="rendered reference bundles")
    p.add_argument("--out", type=Path, default=Path("validation"), help="output directory (default validation/)")
    p.add_argument("--examples", type=int, default=10, help="reference examples to perturb (default 10)")
    p.add_argument("--severities", type=int, default=6, help="levels per sweep, >= 2")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--with-rendered", action="store_true",
                   help="also use the failure modes that re-render with Blender (depth-offset, identity-swap; slow)")
    p.set_defaults(func=_lazy("rigidbench.validation:cmd_validate_metrics"))
    p = sub.add_parser("weights", help="list the perception/feature network weights, or download them for "
                       "offline use")
    _add_weights_arguments(p)
    p.set_defaults(func=_lazy("rigidbench.perception.weights:cmd_weights"))
    p = sub.add_parser("demo", help="the whole loop on this machine: render, predict, evaluate (CPU, minutes)")
    p.add_argument("--out", type=Path, default=Path("demo_out"), help="output directory (default demo_out)")
    p.add_argument("--quality", choices=("preview", "test"), default="preview",
                   help="render preset for the reference clips (default preview: 320x176, 49 frames)")
    p.add_argument("--severity", type=float, default=0.5, help="severity of every failure mode, in [0, 1]")
    p.add_argument("--perception", choices=("gt", "neural"), default="gt",
                   help="gt: exact world state (no networks); neural: SAM 2.1, CoTracker3, Video Depth Anything")
    p.add_argument("--modes", nargs="+", metavar="NAME", help="built-in predictors to run (default: a set of "
                   "image-space failure modes plus gravity)")
    p.add_argument("--no-report", action="store_true", help="skip the report (tables, figures, report.html)")
    p.set_defaults(func=cmd_demo)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.DEBUG if args.verbose else logging.INFO,
                        format="%(levelname)s %(name)s: %(message)s")
    if not getattr(args, "func", None):
        parser.print_help()
        return 0
    from .config import ConfigError

    try:
        if args.config:
            layer_config_dirs(args.config)
        return int(args.func(args) or 0)
    except (UserError, ConfigError) as exc:
        print(f"rigidbench {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"rigidbench {args.command}: interrupted; rerun the same command to resume", file=sys.stderr)
        return 130
