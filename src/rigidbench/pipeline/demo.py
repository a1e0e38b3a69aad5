"""The demo behind `make demo`: render one evaluation example per task, run the reference and a
set of failure modes, score them with exact (gt) perception and print the model x metric table."""

from __future__ import annotations

import math
from pathlib import Path

DEMO_MODES = ("reference", "static", "slow", "delayed", "gamma", "camera-shake", "background-wobble")
DISPLAY = ("IoU", "L2", "Cham.", "ATE", "ATE-3D", "SI-MSE", "SSIM", "LPIPS", "IdDrift", "BGDrift")


def first_of_each_task(rows):
    chosen = {}
    for row in rows:
        chosen.setdefault(row.task, row)
    return [chosen[t] for t in sorted(chosen)]


def run_demo(out_dir: Path, quality: str = "preview", severity: float = 0.5) -> int:
    from ..config import registry
    from ..evaluate import METRICS, evaluate, load_feature_nets
    from ..manifest import eval_rows
    from .predict import predict
    from .render import render_rows

    reg = registry()
    rows = first_of_each_task(eval_rows(reg))
    data = out_dir / "data"
    print(f"[1/3] rendering {len(rows)} evaluation examples (one per task) at the '{quality}' preset")
    render_rows(rows, reg, data, quality=quality)
    split_dir = data / "eval"
    nets = load_feature_nets()
    table = {}
    print(f"[2/3] predicting and evaluating {len(DEMO_MODES)} built-in predictors (severity {severity})")
    for mode in DEMO_MODES:
        preds = out_dir / "predictions" / mode
        predict(mode, split_dir, preds, 0.0 if mode == "reference" else severity)
        summary = evaluate(preds, split_dir, out_dir / "runs" / mode, nets=nets, model=mode)
        table[mode] = [summary.results["overall"][m]["mean"] for m in METRICS]
    print("[3/3] results (means over the examples; gt perception)\n")
    print(f"{'model':18s}" + "".join(f"{d:>9s}" for d in DISPLAY))
    for mode, values in table.items():
        print(f"{mode:18s}" + "".join(f"{'n/a' if v is None or not math.isfinite(v) else f'{v:.4f}':>9s}"
                                      for v in values))
    for metric, reason in nets.skipped.items():
        print(f"\nskipped {metric}: {reason}")
    print(f"\nper-example results: {out_dir / 'runs'}")
    return 0
