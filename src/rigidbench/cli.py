"""The ``rigidbench`` command. Subcommands import their stage lazily so ``--help`` is instant."""

from __future__ import annotations

import argparse
import logging
import os
import sys
from pathlib import Path

from .argtypes import positive_int
from .context import RunContext
from .errors import RigidBenchError, UserError
from .train.commands import add_commands as add_train_commands
from .probe.commands import add_commands as add_probe_commands

DEFAULT_DATA = Path("data")
CONFIG_PATH_ENV = "RIGIDBENCH_CONFIG_PATH"


def _output_dir(path: Path, option: str = "--out") -> Path:
    """A directory to write into: UserError when ``path`` is an existing file (not a folder)."""
    if path.exists() and not path.is_dir():
        raise UserError(f"{option} {path}: is a file, not a folder; pass a folder for the outputs")
    return path


def _ids(value: str) -> list[str]:
    return [v.strip() for v in value.replace(",", " ").split() if v.strip()]


def _selected_ids(args) -> list[str] | None:
    return [i for chunk in (args.ids or []) for i in _ids(chunk)] or None


def _split_dir(args) -> Path:
    """The reference split directory ``--data`` (and ``--split``) name; BundleError with a did-you-mean, or
    naming `rigidbench import` when ``--data`` is in the published archive's own layout."""
    from .groundtruth.bundle import resolve_split_dir

    return resolve_split_dir(args.data, getattr(args, "split", None))


def _split_rows(args, ctx: RunContext):
    from . import manifest

    reg = ctx.registry
    try:
        return reg, manifest.select(manifest.rows(args.split, reg), _selected_ids(args), args.limit)
    except KeyError as exc:
        raise UserError(exc.args[0]) from None


def build_context(args) -> RunContext:
    """The run context of one command: $RIGIDBENCH_CONFIG_PATH, then each --config, layered over the packaged
    configs (the only place the environment variable is read); ConfigError names a missing directory."""
    from .config import config_dirs

    env = [Path(p) for p in os.environ.get(CONFIG_PATH_ENV, "").split(os.pathsep) if p]
    dirs = tuple(p.resolve() for p in env + [Path(d) for d in args.config])
    config_dirs(dirs)  # check they exist before any work starts
    return RunContext(config_dirs=dirs, device=getattr(args, "net_device", None))


def load_plugins(modules) -> None:
    """Import each plug-in module (it registers its entries when imported); a missing one is a UserError."""
    import importlib

    for name in modules:
        try:
            importlib.import_module(name)
        except ModuleNotFoundError as exc:
            if exc.name and name.startswith(exc.name):
                raise UserError(f"--plugin {name}: no module named '{exc.name}' (is it installed or on "
                                "PYTHONPATH?)") from None
            raise


# -- subcommands ---------------------------------------------------------------------------------


def cmd_manifest(args, ctx: RunContext) -> int:
    from . import manifest

    rows = manifest.rows(args.split, ctx.registry)
    out = args.out or Path("manifests") / f"{args.split}.jsonl"
    manifest.write(out, rows)
    print(f"wrote {len(rows)} {args.split} rows to {out}")
    return 0


def cmd_simulate(args, ctx: RunContext) -> int:
    from .pipeline.simulate import simulate_rows

    reg, rows = _split_rows(args, ctx)
    out = args.out or DEFAULT_DATA / args.split
    failures, skipped = simulate_rows(rows, reg, Path(out))
    print(f"simulated {len(rows) - len(failures) - len(skipped)} of {len(rows)} examples into {out} "
          f"({len(skipped)} already done)")
    for sample_id, reason in failures:
        print(f"  FAILED {sample_id}: {reason}", file=sys.stderr)
    return 1 if failures else 0


def cmd_inputs(args, ctx: RunContext) -> int:
    from .benchmark import write_inputs

    try:
        out = write_inputs(_split_dir(args), args.out)
    except FileNotFoundError as exc:
        raise UserError(str(exc)) from None
    print(f"wrote {out}")
    return 0


def cmd_validate(args, ctx: RunContext) -> int:
    from .validate import main as validate_main

    return validate_main(args.predictions, _split_dir(args))


def cmd_evaluate(args, ctx: RunContext) -> int:
    from .evaluation import evaluate

    out = _output_dir(args.out or Path("runs") / args.predictions.name)
    options = ({"depth_model": args.depth_model, "device": ctx.device} if args.perception == "neural" else None)
    executor, shard = executor_from(args)
    summary = evaluate(args.predictions, _split_dir(args), out, perception=args.perception, ids=_selected_ids(args),
                       limit=args.limit, model=args.model, perception_options=options, executor=executor, shard=shard,
                       device=ctx.device, protocol=args.protocol, first_frame_check=not args.no_first_frame_check,
                       allow_short=args.allow_short)
    overall = summary.results["overall"]
    dataset = summary.results.get("dataset", {})
    print(f"reference set: {dataset.get('dataset')} {dataset.get('version') or ''}; protocol "
          f"{summary.results['protocol']['name']}")
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


def format_predictors() -> str:
    """The predictor registry as a table: name, kind, what it needs and writes, description."""
    from .predictors import PREDICTORS, load_entry_points

    load_entry_points()
    lines = [f"{'name':18s} {'kind':13s} {'needs':8s} {'writes':12s} description"]
    for name, info in PREDICTORS.items():
        needs = "Blender" if info.needs_blender else "-"
        writes = "video+state" if info.writes_state else "video"
        lines.append(f"{name:18s} {info.kind.value:13s} {needs:8s} {writes:12s} {info.description}")
    lines.append("\nyour own model: rigidbench predict package.module:MyModel (a Predictor subclass or a function "
                 "f(sample, ctx) -> Prediction)")
    return "\n".join(lines)


def _predict_context(args, ctx: RunContext):
    """The PredictContext of ``predict`` and ``audit``: severity, seed and the model options given."""
    from types import MappingProxyType

    from .predictors import PredictContext

    options = {"concurrency": args.concurrency, "offload": args.offload or None, "tiled_vae": args.tiled_vae or None,
               "checkpoint": args.checkpoint, "no_guardrail": args.no_guardrail or None, "model_path": args.model_path,
               "repay_expired": args.repay_expired or None, "sampler": args.sampler}
    return PredictContext(ctx, args.severity, args.seed,
                          options=MappingProxyType({k: v for k, v in options.items() if v is not None}))


def cmd_predict(args, ctx: RunContext) -> int:
    from .pipeline.predict import predict
    from .predictors import predictor_info

    if args.list:
        print(format_predictors())
        return 0
    if not args.name:
        raise UserError("name a predictor (rigidbench predict --list shows them)")
    info = predictor_info(args.name)
    out = _output_dir(args.out or Path("predictions") / info.name)
    executor, shard = executor_from(args)
    summary = predict(args.name, _split_dir(args), out, _predict_context(args, ctx), _selected_ids(args), args.limit,
                      dry_run=args.dry_run, executor=executor, shard=shard)
    if args.dry_run:
        print(f"{info.name}: would generate {len(summary.planned)} videos ({len(summary.skipped)} already there), "
              f"{summary.paid_calls} paid API calls; nothing was sent")
        return 0
    print(f"{info.name}: {len(summary.written)} predictions in {out} "
          f"({len(summary.skipped)} already there), {len(summary.failed)} failed")
    for sample_id, reason in summary.failed.items():
        print(f"  FAILED {sample_id}: {reason}", file=sys.stderr)
    return 1 if summary.failed else 0


def cmd_audit(args, ctx: RunContext) -> int:
    from .pipeline.audit import audit

    models = [m for chunk in args.models for m in _ids(chunk)]
    options = ({"depth_model": args.depth_model, "device": ctx.device} if args.perception == "neural" else None)
    summary = audit(models, _split_dir(args), args.out, _predict_context(args, ctx), yes=args.yes,
                    perception=args.perception, perception_options=options, ids=_selected_ids(args), limit=args.limit,
                    resamples=args.resamples)
    if summary.stopped_for_confirmation:
        return 2
    for model, failures in summary.failed.items():
        for sample_id, reason in failures.items():
            print(f"  FAILED {model}/{sample_id}: {reason}", file=sys.stderr)
    if summary.report is not None:
        print(f"report: {summary.report}")
    return 1 if summary.failed or summary.blocked else 0


def cmd_demo(args, ctx: RunContext) -> int:
    from .pipeline.demo import run_demo

    modes = [m for chunk in (args.modes or []) for m in _ids(chunk)] or None
    kwargs = {"modes": modes} if modes else {}
    return run_demo(args.out, quality=args.quality, severity=args.severity, perception=args.perception,
                    report=not args.no_report, ctx=ctx, **kwargs)


def _add_weights_arguments(parser) -> None:
    from .perception.weights import add_arguments  # light: no torch or transformers at import

    add_arguments(parser)


def _lazy(target: str):
    """A subcommand function ``f(args, ctx)`` imported only when that subcommand runs (keeps --help instant)."""
    def run(args, ctx: RunContext):
        from .registry import load_target

        return load_target(target, "command")(args, ctx)

    return run


def _add_render_commands(subparsers) -> None:
    """Register ``render`` and ``show`` on the ``rigidbench`` subparsers."""
    p = subparsers.add_parser("render", help="simulate and render examples into sample bundles "
                                             "(DATA/<split>/<id>/); reruns skip bundles that are complete and "
                                             "rendered at the preset asked for")
    p.add_argument("--split", choices=("train", "eval"), default="eval", help="manifest to draw examples from")
    p.add_argument("--ids", nargs="+", metavar="ID", help="sample ids, e.g. 00000 00007 (default: all)")
    p.add_argument("--limit", type=positive_int, help="only the first N selected examples")
    p.add_argument("--quality", default="paper", help="render preset: paper, preview or test (configs/render.yaml)")
    p.add_argument("--data", type=Path, default=DEFAULT_DATA, help="data directory (default: data)")
    p.add_argument("--workers", type=positive_int, default=1, help="examples rendered at once, one process each (default 1)")
    p.add_argument("--device", choices=("auto", "cpu", "gpu"), default="auto",
                   help="Cycles device: auto picks OptiX, then CUDA, then the CPU (default auto)")
    p.add_argument("--no-progress", action="store_true", help="no progress bars")
    add_executor_arguments(p)
    p.set_defaults(func=_lazy("rigidbench.pipeline.render:cmd_render"))

    p = subparsers.add_parser("show", help="write a PNG contact sheet of a rendered example "
                                           "(frames, masks, depth, ground-truth tracks)")
    p.add_argument("ids", nargs="+", metavar="ID", help="sample id(s), e.g. 00000 00007")
    _add_data(p)
    p.add_argument("--out", type=Path, help="output PNG for one id, or a folder for the sheets (default: "
                                            "<split>_<id>_contact_sheet.png here)")
    p.set_defaults(func=_lazy("rigidbench.pipeline.render:cmd_show"))



# -- parser --------------------------------------------------------------------------------------


def _add_selection(p: argparse.ArgumentParser, split_default: str = "eval") -> None:
    p.add_argument("--split", choices=("train", "eval"), default=split_default, help="manifest to draw examples from")
    p.add_argument("--ids", nargs="+", metavar="ID", help="sample ids, e.g. 00000 00007 (default: all)")
    p.add_argument("--limit", type=positive_int, help="only the first N selected examples")


def _add_model_options(p: argparse.ArgumentParser) -> None:
    """Options of video models (each model uses the ones that apply to it and records them)."""
    p.add_argument("--severity", type=float, default=1.0,
                   help="failure modes: 0 = the reference, 1 = strong (default 1)")
    p.add_argument("--seed", type=int, default=0, help="base seed for video models: each example gets its own, "
                                                       "derived from this and its id (default 0)")
    p.add_argument("--concurrency", type=int, help="hosted models: predictions in flight at once (default 8)")
    p.add_argument("--repay-expired", action="store_true",
                   help="hosted models: pay for a new prediction when a paid one's output has expired at the API")
    p.add_argument("--device", dest="net_device", help="local models and networks: cuda or cpu (default: CUDA "
                                                       "when available)")
    p.add_argument("--offload", action="store_true", help="local models: model CPU offload (smaller GPUs)")
    p.add_argument("--tiled-vae", action="store_true", help="local models: tiled VAE decoding (smaller GPUs)")
    p.add_argument("--checkpoint", type=Path, help="wan-2.2: a LoRA adapter or a full fine-tuned transformer")
    p.add_argument("--sampler", choices=("flow-euler", "unipc"),
                   help="wan-2.2: flow-euler (default; the paper's runs: DiffSynth's flow-matching Euler schedule, "
                        "shift 5) or unipc (the Diffusers repository's scheduler)")
    p.add_argument("--model-path", type=Path, help="local models: weights from this directory instead of the hub")
    p.add_argument("--no-guardrail", action="store_true",
                   help="cosmos-2.5: replace the Cosmos guardrail with a pass-through (you take on its licence terms)")


def add_executor_arguments(p: argparse.ArgumentParser) -> None:
    """--executor, --ray-address and --shard: how and which part of a stage's examples run."""
    p.add_argument("--executor", choices=("local", "ray"), default="local",
                   help="local: this machine; ray: one task per example on a Ray cluster (outputs go to a directory "
                        "every node sees)")
    p.add_argument("--ray-address", help="Ray cluster to join (default: $RAY_ADDRESS, else a local Ray)")
    p.add_argument("--shard", metavar="I/N", help="only the I-th of N deterministic parts of the examples "
                                                  "(0-based; for job arrays), e.g. --shard 0/4")


def executor_from(args):
    """(Executor, Shard) from --executor, --ray-address and --shard."""
    from .executors import Shard, make_executor

    return make_executor(args.executor, ray_address=args.ray_address), Shard.parse(args.shard)


def _add_data(p: argparse.ArgumentParser) -> None:
    """--data and --split for a command that reads reference bundles (one convention for all of them)."""
    p.add_argument("--data", type=Path, default=DEFAULT_DATA,
                   help="reference bundles: a split directory (data/eval) or a data root (data) with --split "
                        "(default: data)")
    p.add_argument("--split", choices=("train", "eval"),
                   help="split under a data root (default: the only split present)")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="rigidbench",
        description="RigidBench: simulator-grounded evaluation of rigid-body physics in video generation models.")
    parser.add_argument("--config", action="append", default=[], metavar="DIR",
                        help="extra configuration directory layered over the packaged configs and "
                             "$RIGIDBENCH_CONFIG_PATH, for every stage of the command (repeatable)")
    parser.add_argument("--plugin", action="append", default=[], metavar="MODULE",
                        help="import MODULE first, so the metrics, predictors or perception backends it registers "
                             "are available to the command (repeatable)")
    parser.add_argument("-v", "--verbose", action="store_true", help="log debug messages")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")

    p = sub.add_parser("download", help="the paper's published evaluation set: download (resumable), verify, extract "
                                        "and import into DATA/eval (about 40 GB of free disk while it runs)")
    p.add_argument("--data", type=Path, default=DEFAULT_DATA, help="data root (default: data); bundles go to DATA/eval")
    p.add_argument("--dataset", help="dataset id or name from configs/datasets (default: the newest published set)")
    p.add_argument("--keep-archive", action="store_true", help="keep the downloaded parts after extraction")
    p.add_argument("--no-verify", action="store_true", help="skip the archive's MD5 check (not recommended)")
    p.set_defaults(func=_lazy("rigidbench.datasets.commands:cmd_download"))

    p = sub.add_parser("import", help="import a published evaluation set you downloaded by hand (the .tar.gz, its "
                                      "parts' folder, or the extracted folder) into DATA/eval")
    p.add_argument("src", type=Path, help="the archive (.tar.gz), or the folder it was extracted into")
    p.add_argument("--data", type=Path, default=DEFAULT_DATA, help="data root (default: data); bundles go to DATA/eval")
    p.add_argument("--dataset", help="which published set this is, for the record (default: the newest described)")
    p.add_argument("--ids", nargs="+", metavar="ID", help="import only these sample ids")
    p.set_defaults(func=_lazy("rigidbench.datasets.commands:cmd_import"))

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
    _add_data(p)
    p.add_argument("--out", type=Path, help="output file (default <split directory>/inputs.jsonl)")
    p.set_defaults(func=cmd_inputs)

    p = sub.add_parser("predict", help="make one video per reference example with a registered predictor or "
                                       "your own model (--list shows the registry)")
    p.add_argument("name", nargs="?", help="a registered predictor (see --list) or package.module:Attr for your own")
    p.add_argument("--list", action="store_true", help="list the registered predictors and exit")
    _add_data(p)
    p.add_argument("--out", type=Path, help="output directory (default predictions/NAME)")
    _add_model_options(p)
    p.add_argument("--dry-run", action="store_true",
                   help="print the request each example would send and the number of paid calls; send nothing")
    add_executor_arguments(p)
    p.add_argument("--ids", nargs="+", metavar="ID")
    p.add_argument("--limit", type=positive_int)
    p.set_defaults(func=cmd_predict)

    p = sub.add_parser("audit", help="several video models end to end: predict (resuming), validate, evaluate, "
                                     "then one report; stops before paid API calls unless --yes")
    p.add_argument("--models", nargs="+", required=True, metavar="NAME",
                   help="comma- or space-separated predictor names, e.g. wan-2.2,veo-3.1")
    _add_data(p)
    p.add_argument("--out", type=Path, default=Path("audit"), help="output directory (default audit/)")
    p.add_argument("--perception", choices=("gt", "neural"), default="neural",
                   help="neural for video models (default); gt only for predictors that write world state")
    p.add_argument("--depth-model", choices=("vda", "dav2"), default="vda")
    p.add_argument("--yes", action="store_true", help="make the paid API calls the audit counted")
    p.add_argument("--resamples", type=int, default=20000, help="bootstrap resamples in the report")
    p.add_argument("--ids", nargs="+", metavar="ID")
    p.add_argument("--limit", type=positive_int)
    _add_model_options(p)
    p.set_defaults(func=cmd_audit)

    p = sub.add_parser("validate", help="fast preflight of a predictions directory before evaluation")
    p.add_argument("predictions", type=Path, help="directory with <id>.mp4 files")
    _add_data(p)
    p.set_defaults(func=cmd_validate)

    p = sub.add_parser("evaluate", help="score predictions against the reference with the ten measurements")
    p.add_argument("predictions", type=Path, help="directory with <id>.mp4 files (predictions/MODEL)")
    _add_data(p)
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
                   help="evaluation protocol (default rigidbench-v1): rigidbench-v1: the published evaluator's rules, comparable with the paper (generated frames "
                        "go through JPEG q95 4:4:4 after resizing); lossless: no JPEG round trip (docs/metrics.md)")
    p.add_argument("--no-first-frame-check", action="store_true",
                   help="score predictions whose first frame is not their reference's (normally refused as made from "
                        "another set's inputs); recorded in results.json")
    p.add_argument("--allow-short", action="store_true",
                   help="score clips that do not cover the reference span (normally refused, as by the published "
                        "evaluator) on the frames they have; marked short in results.json, never official")
    add_executor_arguments(p)
    p.add_argument("--ids", nargs="+", metavar="ID")
    p.add_argument("--limit", type=positive_int)
    p.set_defaults(func=cmd_evaluate)
    p = sub.add_parser("report", help="tables, figures and report.html from evaluation runs")
    p.add_argument("runs", nargs="+", type=Path, help="run directories (runs/*)")
    p.add_argument("--out", type=Path, default=Path("report"), help="output directory (default report/)")
    p.add_argument("--baseline", help="model for paired changes (default: first run not named 'reference')")
    p.add_argument("--resamples", type=int, default=20000, help="bootstrap resamples (default 20000)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--examples", type=int, default=3, help="examples shown as filmstrips (default 3; 0: none)")
    p.add_argument("--no-clips", action="store_true", help="no looping video clips beside the filmstrips")
    p.add_argument("--outlines", choices=("reference", "perceived"), default="reference",
                   help="object outlines drawn on the filmstrips: the reference masks, or each run's perceived masks")
    p.add_argument("--probe-report", type=Path, metavar="PATH",
                   help="a probe report (the report.html `rigidbench probe report` wrote, or its directory) to link")
    p.set_defaults(func=_lazy("rigidbench.report:cmd_report"))
    p = sub.add_parser("readouts", help="physics readouts of evaluation runs: playback speed, gravity, restitution, "
                       "failure flags (docs/physics.md)")
    p.add_argument("runs", nargs="+", type=Path, help="run directories (runs/MODEL)")
    p.add_argument("--examples", action="store_true", help="also one line per example")
    p.set_defaults(func=_lazy("rigidbench.readouts.records:cmd_readouts"))
    p = sub.add_parser("validate-metrics", help="controlled metric perturbations and one failure-mode response "
                       "curve per metric (figure + table)")
    _add_data(p)
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
    p.add_argument("--quality", choices=("demo", "preview", "test"), default="demo",
                   help="render preset for the reference clips (default demo: the preview clip, 320x176, 49 frames, "
                        "at 4 samples denoised; preview: 8 samples)")
    p.add_argument("--severity", type=float, default=0.5, help="severity of every failure mode, in [0, 1]")
    p.add_argument("--perception", choices=("gt", "neural"), default="gt",
                   help="gt: exact world state (no networks); neural: SAM 2.1, CoTracker3, Video Depth Anything")
    p.add_argument("--modes", nargs="+", metavar="NAME", help="built-in predictors to run (default: a set of "
                   "image-space failure modes plus gravity)")
    p.add_argument("--no-report", action="store_true", help="skip the report (tables, figures, report.html)")
    p.set_defaults(func=cmd_demo)
    add_train_commands(sub)  # preprocess, train (fine-tuning Wan 2.2)
    add_probe_commands(sub)  # probe extract|fit|intervene|report (paper sections 5.2-5.3)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.DEBUG if args.verbose else logging.INFO,
                        format="%(levelname)s %(name)s: %(message)s")
    if not getattr(args, "func", None):
        parser.print_help()
        return 0
    try:
        ctx = build_context(args)
        load_plugins(args.plugin)
        return int(args.func(args, ctx) or 0)
    except RigidBenchError as exc:
        print(f"rigidbench {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"rigidbench {args.command}: interrupted; rerun the same command to resume", file=sys.stderr)
        return 130
