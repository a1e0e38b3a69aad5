"""The audit: several video models over the same reference split, in one command.

For each model: predict (resuming: finished videos are kept, failed ones retried), validate,
evaluate; then one report comparing them. Hosted models cost money per call, so the audit first
counts the paid calls each one still needs (a dry run that sends nothing) and stops there unless
the user confirmed with ``yes``.

Layout under ``out``: ``predictions/<model>/``, ``runs/<model>/``, ``report/``.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Sequence

from ..driver import RunOptions
from ..errors import UserError
from ..perception.features import FeatureNets, load_feature_nets
from ..predictors import PredictContext, predictor_info
from ..preflight import format_report, validate_predictions
from ..report import build_report
from ..stages.evaluate import evaluate
from ..stages.predict import predict

log = logging.getLogger(__name__)


@dataclass
class AuditSummary:
    paid_calls: dict[str, int] = field(default_factory=dict)  # hosted model -> calls it still needs
    stopped_for_confirmation: bool = False
    failed: dict[str, dict[str, str]] = field(default_factory=dict)  # model -> example -> reason
    blocked: dict[str, int] = field(default_factory=dict)  # model -> validation errors
    runs: list[Path] = field(default_factory=list)
    report: Path | None = None


def audit(models: Sequence[str], split_dir: Path, out: Path, ctx: PredictContext, *, yes: bool = False,
          perception: str = "gt", perception_options: dict | None = None,
          run: RunOptions = RunOptions(), nets: FeatureNets | None = None, report: bool = True,
          resamples: int = 20000) -> AuditSummary:
    """Predict, validate and evaluate every model in ``models`` on ``split_dir``, then report them together."""
    if not models:
        raise UserError("name at least one model, e.g. --models wan-2.2,veo-3.1 (rigidbench predict --list)")
    infos = [predictor_info(m) for m in models]  # unknown names fail before any work
    out = Path(out)
    summary = AuditSummary()
    for name, info in zip(models, infos):
        preds = out / "predictions" / info.name
        planned = predict(name, split_dir, preds, ctx, replace(run, progress=False), dry_run=True)
        if planned.facts.paid_calls:
            summary.paid_calls[info.name] = planned.facts.paid_calls
    if summary.paid_calls:
        lines = ", ".join(f"{m}: {n}" for m, n in summary.paid_calls.items())
        print(f"paid API calls this audit needs: {lines} ({sum(summary.paid_calls.values())} in all)", flush=True)
        if not yes:
            summary.stopped_for_confirmation = True
            print("nothing was sent; rerun with --yes to make these calls", flush=True)
            return summary
    nets = nets if nets is not None else load_feature_nets(ctx.run.device)
    for name, info in zip(models, infos):
        preds = out / "predictions" / info.name
        print(f"[{info.name}] predict into {preds}", flush=True)
        made = predict(name, split_dir, preds, ctx, run)
        if made.failed:
            summary.failed[info.name] = dict(made.failed)
        checked = validate_predictions(preds, split_dir)
        if not checked.ok:
            summary.blocked[info.name] = len(checked.errors)
            print(format_report(checked), flush=True)
        print(f"[{info.name}] evaluate ({perception} perception)", flush=True)
        result = evaluate(preds, split_dir, out / "runs" / info.name, perception=perception, run=run,
                          nets=nets, model=info.name, perception_options=perception_options)
        for sample_id, reason in result.failed.items():
            summary.failed.setdefault(info.name, {}).setdefault(sample_id, reason)
        summary.runs.append(result.root)
    if report and summary.runs:
        summary.report = build_report(summary.runs, out / "report", resamples=resamples, seed=0)
    return summary
