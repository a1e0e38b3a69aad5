"""`rigidbench report runs/* --out report/`: the paper's tables, figures and one HTML page from run directories.

Writes into the output directory::

    report.html                     every table and figure, the runs and their provenance
    report.md                       the same tables in Markdown, figures linked
    tables/<name>.md, .tex          model_metrics, ate3d_by_task, by_partition, paired_changes
    tables/<name>.csv               model_metrics, by_task, by_partition, paired_changes, poi_matrix,
                                    correlation (long form, unrounded, unscaled)
    figures/<name>.png, .pdf        ssim_vs_ate3d, ate3d_by_task, metric_intervals, poi_heatmaps

matplotlib is imported only when figures are drawn.
"""

from __future__ import annotations

import logging
from pathlib import Path

from rigidbench.metrics import METRICS
from rigidbench.report.analysis import analyse
from rigidbench.report.figures import build_figures
from rigidbench.report.html import render_page
from rigidbench.report.load import ReportError, ScoreTable, load_runs
from rigidbench.report.tables import build_tables, to_markdown, write_csvs, write_tables

log = logging.getLogger(__name__)

__all__ = ["ReportError", "ScoreTable", "build_report", "cmd_report", "load_runs"]

# Which CSV files the HTML offers beside each table.
_CSV_FOR_TABLE = {"model_metrics": ("model_metrics.csv", "correlation.csv"), "ate3d_by_task": ("by_task.csv",),
                  "by_partition": ("by_partition.csv",), "paired_changes": ("paired_changes.csv", "poi_matrix.csv")}


def report_notes(data) -> list[str]:
    """Plain-language notes on what the report could not do as usual (one run, skipped metrics, baseline)."""
    t = data.table
    notes = list(t.notes)
    if len(t.models) == 1:
        notes.append("Only one run was given: there are no paired comparisons or probability-of-improvement "
                     "heatmaps, and no correlation across models.")
    else:
        base = t.models[data.baseline]
        notes.append(f"Paired changes are against '{base}' (choose another with --baseline NAME; the default is "
                     "the first run given that is not named 'reference': the reference scored against itself "
                     "is a measurement floor, not a baseline).")
    unranked = [name for name, r in zip(t.models, data.ranked) if not r]
    if unranked:
        notes.append(f"{', '.join(unranked)} is shown for comparison but takes no best / second-best marks.")
    # One note per (measurement, reason), naming the runs it applies to: the reasons are long.
    groups: dict[tuple[str, str], list[str]] = {}
    for m, run in enumerate(t.runs):
        for k, s in zip(t.metrics, t.skipped[m]):
            if s:
                groups.setdefault((k, run.skipped_metrics.get(k, "")), []).append(run.name)
    for (k, reason), names in groups.items():
        who = f"all {len(names)} runs" if len(names) == len(t.runs) > 1 else ", ".join(names)
        notes.append(f"{METRICS[k].display_name} not computed for {who}" + (f": {reason}" if reason else "."))
    if data.correlation is not None and not data.correlation.get("has_ci"):
        notes.append("The SSIM / ATE-3D correlation has no bootstrap interval with fewer than 3 models.")
    return notes


def build_report(run_dirs, out_dir, resamples: int = 20000, seed: int = 0, baseline: str | None = None) -> Path:
    """Read run directories, write tables, figures and report.html into out_dir. Returns the report.html path."""
    out_dir = Path(out_dir)
    table = load_runs(run_dirs)
    log.info("loaded %d runs over %d shared examples", len(table.models), len(table.example_ids))
    data = analyse(table, resamples=resamples, seed=seed, baseline=baseline)
    tables_dir, figures_dir = out_dir / "tables", out_dir / "figures"
    tables_dir.mkdir(parents=True, exist_ok=True)
    figures_dir.mkdir(parents=True, exist_ok=True)
    tables = build_tables(data)
    table_files = write_tables(tables, tables_dir)
    csv_paths = {p.name: p for p in write_csvs(data, tables_dir)}
    for key, files in table_files.items():
        files["csv"] = [csv_paths[name] for name in _CSV_FOR_TABLE.get(key, ()) if name in csv_paths]
    figures = build_figures(data, figures_dir)
    notes = report_notes(data)
    markdown = ["# RigidBench report", ""] + [f"- {n}" for n in notes] + [""]
    for tb in tables:
        markdown.append(to_markdown(tb))
    for fig in figures:
        markdown += [f"### {fig.title}", "", f"![{fig.title}]({fig.png.relative_to(out_dir).as_posix()})", "",
                     fig.caption, ""]
    (out_dir / "report.md").write_text("\n".join(markdown))
    page = out_dir / "report.html"
    page.write_text(render_page(data, notes, tables, table_files, figures, out_dir))
    log.info("wrote %s", page)
    return page


def cmd_report(args, ctx=None) -> int:
    """CLI entry: args.runs (list of run dirs), args.out, args.baseline, args.resamples, args.seed."""
    page = build_report(args.runs, args.out, resamples=args.resamples, seed=args.seed, baseline=args.baseline)
    print(f"report for {len(args.runs)} run(s): {page}")
    return 0
