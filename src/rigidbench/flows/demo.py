"""The demo behind `make demo`: render one evaluation example per task, run the reference and a set of
failure modes, score them, write the report and print the model x metric table.

Everything runs on this machine's CPU with no network: the reference clips are rendered at the
`demo` preset (the `preview` clip at half its samples), the failure modes make their predictions from them (image-space ones in
milliseconds, physics counterfactuals by re-simulating and re-rendering), and `gt` perception
scores them exactly. Measurements whose networks are not available locally are skipped and the
reason is printed.
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

# Image-space modes cost milliseconds; `gravity` re-renders every example once more.
DEMO_MODES = ("reference", "static", "slow", "delayed", "gamma", "camera-shake", "background-wobble", "gravity")


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


def run_demo(out_dir: Path, quality: str = "demo", severity: float = 0.5, perception: str = "gt",
             modes: Sequence[str] = DEMO_MODES, report: bool = True, resamples: int = 20000,
             ctx: RunContext | None = None) -> int:
    """Render, predict, evaluate and report; returns the process exit status."""
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
    stages = 4 if report else 3
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
    nets = load_feature_nets(ctx.device)
    table, run_dirs, problems = {}, [], {}
    _stage(2, stages, f"predicting and evaluating {len(modes)} built-in predictors (severity {severity}, "
                      f"{perception} perception)", started)
    for mode in modes:
        preds = out_dir / "predictions" / mode
        run = predict(mode, split_dir, preds, PredictContext(ctx, 0.0 if mode == "reference" else severity))
        scored = evaluate(preds, split_dir, out_dir / "runs" / mode, nets=nets, model=mode, perception=perception)
        problems.update({f"{mode}/{k}": v for k, v in {**run.failed, **scored.failed}.items()})
        table[mode] = [scored.facts.results["overall"][m]["mean"] for m in METRICS]
        run_dirs.append(scored.root)
    report_html = None
    if report:
        _stage(3, stages, f"writing the report ({resamples} bootstrap resamples)", started)
        report_html = build_report(run_dirs, out_dir / "report", resamples=resamples, seed=0)
    _stage(stages, stages, f"results: means over {len(rows)} examples, {perception} perception", started)
    print("\n" + format_table(table))
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
