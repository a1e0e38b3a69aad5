"""The demo behind `make demo`: render one evaluation example per task, run the reference and a set of
failure modes, score them, write the report and print the model x metric table.

Everything runs on this machine's CPU with no network: the reference clips are rendered at the
`demo` preset (the `preview` clip at half its samples), the failure modes make their predictions from them (image-space ones in
milliseconds, physics counterfactuals by re-simulating and re-rendering), and `gt` perception
scores them exactly. Measurements whose networks are not available locally are skipped and the
reason is printed.

How sure a score is (docs/statistics.md): one failure mode (``SAMPLED_MODE``, a random camera shake) is
generated ``SAMPLES`` times per example, so its line shows each measurement's seed spread; and before the
predictors run, a geometry-only physical envelope of ``TWINS`` twins per example is made
(``flows.envelope``), against which every run is scored (the share of examples inside it is printed).
"""

from __future__ import annotations

import math
import time
from pathlib import Path
from typing import Sequence

from ..context import RunContext
from ..errors import UserError
from ..manifest import eval_rows
from ..metrics import METRICS
from ..perception.features import load_feature_nets
from ..predictors import PREDICTORS, PredictContext
from ..readouts.records import load_run_readouts, one_line
from ..report import build_report
from ..stages.evaluate import evaluate, ready_backend
from ..stages.predict import predict
from ..stages.render import render_rows
from .envelope import make_envelope

# Image-space modes cost milliseconds; `gravity` re-renders every example once more.
DEMO_MODES = ("reference", "static", "slow", "delayed", "gamma", "camera-shake", "background-wobble", "gravity")
SAMPLED_MODE, SAMPLES = "camera-shake", 2  # generated twice per example: the seed spread of a random failure
TWINS = 4  # geometry-only twins per example in the demo's envelope
ENVELOPE_METRICS = ("iou", "ate", "ate3d")  # the shares inside the envelope the demo prints


def first_of_each_task(rows):
    """The first manifest row of every task, in task order."""
    chosen = {}
    for row in rows:
        chosen.setdefault(row.task, row)
    return [chosen[t] for t in sorted(chosen)]


def format_table(table: dict[str, list[float | None]]) -> str:
    """Model x metric means (in registry order) as fixed-width text; missing or non-finite values print as n/a."""
    lines = [f"{'model':18s}" + "".join(f"{info.display_name:>9s}" for info in METRICS.values())]
    for mode, values in table.items():
        cells = ("n/a" if v is None or not math.isfinite(v) else f"{v:.4f}" for v in values)
        lines.append(f"{mode:18s}" + "".join(f"{c:>9s}" for c in cells))
    return "\n".join(lines)


def _stage(number: int, total: int, text: str, started: float) -> None:
    print(f"[{number}/{total}] {text}  ({time.time() - started:.0f} s elapsed)", flush=True)


def _envelope(split_dir: Path, envelope_dir: Path, twins: int, ctx: RunContext) -> dict[str, str]:
    """Make the demo's geometry-only envelope; returns what failed in it ("envelope/<item>": reason)."""
    made = make_envelope(split_dir, envelope_dir, twins=twins, ctx=ctx)
    return {f"envelope/{item}": why for stage_report in (made.predicted, made.scored) if stage_report is not None
            for item, why in stage_report.failed.items()}


def _print_spread(samples: dict[str, dict], inside: dict[str, dict], twins: int) -> None:
    """The seed std of the sampled mode (per measurement) and each model's share of examples inside the envelope."""
    for mode, spread in samples.items():
        print(f"\n{mode}: {SAMPLES} samples per example; seed std (of the whole-set mean over sample indices):")
        print(format_table({f"  {mode} ± ": [spread.get(m) for m in METRICS]}).split("\n", 1)[1])
    if inside:
        print(f"\nshare of examples inside the physical envelope ({twins} geometry-only twins; docs/statistics.md):")
        print("  " + f"{'model':16s}" + "".join(f"{m:>9s}" for m in ENVELOPE_METRICS))
        for mode, shares in inside.items():
            print("  " + f"{mode:16s}" + "".join(f"{'n/a' if v is None else format(v, '.2f'):>9s}"
                                                  for v in shares.values()))


def run_demo(out_dir: Path, quality: str = "demo", severity: float = 0.5, perception: str = "gt",
             modes: Sequence[str] = DEMO_MODES, report: bool = True, resamples: int = 20000,
             ctx: RunContext | None = None, twins: int = TWINS) -> int:
    """Render, make the envelope (``twins`` per example; 0: none), predict, evaluate and report; returns the
    process exit status."""
    ctx = ctx or RunContext()
    for mode in modes:
        if mode not in PREDICTORS:
            raise UserError(f"demo mode: {PREDICTORS.unknown_message(mode)}")
    if perception != "gt":  # check the networks before spending minutes on rendering
        ready_backend(perception)
    started = time.time()
    out_dir = Path(out_dir)
    reg = ctx.registry
    rows = first_of_each_task(eval_rows(reg))
    data = out_dir / "data"
    stages = (4 if report else 3) + (1 if twins else 0)
    _stage(1, stages, f"rendering {len(rows)} evaluation examples (one per task) at the '{quality}' preset "
                      f"into {data}", started)
    render_failures = {i: why for report in render_rows(rows, reg, data, quality=quality, config_dirs=ctx.config_dirs)
                       for i, why in report.failed.items()}
    for sample_id, reason in render_failures.items():
        print(f"  render FAILED {sample_id}: {reason}", flush=True)
    if len(render_failures) == len(rows):
        print("every example failed to render; nothing to evaluate", flush=True)
        return 1
    split_dir = data / "eval"
    step, envelope_dir, problems = 2, None, {}
    if twins:
        envelope_dir = out_dir / "envelope"
        _stage(step, stages, f"making the physical envelope: {twins} geometry-only twins per example into "
                             f"{envelope_dir}", started)
        problems.update(_envelope(split_dir, envelope_dir, twins, ctx))
        step += 1
    nets = load_feature_nets(ctx.device)
    table, run_dirs, samples, inside = {}, [], {}, {}
    _stage(step, stages, f"predicting and evaluating {len(modes)} built-in predictors (severity {severity}, "
                         f"{perception} perception; {SAMPLED_MODE} {SAMPLES} samples per example)", started)
    for mode in modes:
        preds = out_dir / "predictions" / mode
        k = SAMPLES if mode == SAMPLED_MODE else 1
        run = predict(mode, split_dir, preds, PredictContext(ctx, 0.0 if mode == "reference" else severity),
                      samples=k)
        scored = evaluate(preds, split_dir, out_dir / "runs" / mode, nets=nets, model=mode, perception=perception,
                          envelope=envelope_dir)
        problems.update({f"{mode}/{item}": v for item, v in {**run.failed, **scored.failed}.items()})
        results = scored.facts.results
        table[mode] = [results["overall"][m]["mean"] for m in METRICS]
        if k > 1:
            samples[mode] = {m: (v or {}).get("seed_std") for m, v in (results.get("samples") or {}).get("metrics", {}).items()}
        if "envelope" in results:
            inside[mode] = {m: (results["envelope"]["overall"].get(m) or {}).get("inside") for m in ENVELOPE_METRICS}
        run_dirs.append(scored.root)
    step += 1
    report_html = None
    if report:
        _stage(step, stages, f"writing the report ({resamples} bootstrap resamples)", started)
        report_html = build_report(run_dirs, out_dir / "report", resamples=resamples, seed=0)
    _stage(stages, stages, f"results: means over {len(rows)} examples, {perception} perception", started)
    print("\n" + format_table(table))
    _print_spread(samples, inside, twins)
    print("\nphysics readouts (median over examples; docs/physics.md):")
    for run_dir in run_dirs:  # issue 28: one line per model below the ten measurements
        print("  " + one_line(*load_run_readouts(run_dir)[:2]))
    if nets.skipped:
        print("\nskipped measurements:")
        for metric, reason in nets.skipped.items():
            print(f"  {metric}: {reason}")
    for key, reason in problems.items():
        print(f"  FAILED {key}: {reason}")
    print(f"\nper-example results: {out_dir / 'runs'}")
    if report_html is not None:
        print(f"report: {Path(report_html).resolve()}")
    print(f"total time: {time.time() - started:.0f} s")
    return 1 if problems else 0
