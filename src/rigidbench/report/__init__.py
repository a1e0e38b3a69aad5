"""`rigidbench report runs/* --out report/`: the paper's tables, figures and one HTML page from run directories.

Writes into the output directory::

    report.html                     every table, figure and example, the runs and their provenance
    report.md                       the same tables in Markdown, figures and filmstrips linked
    tables/<name>.md, .tex          model_metrics, by_task, all_by_task, by_partition, all_by_partition,
                                    paired_changes, poi_ate3d, poi_ssim
    tables/<name>.csv               model_metrics, by_task, by_partition, paired_changes, poi_matrix,
                                    correlation (long form, unrounded, unscaled)
    figures/<name>.png, .pdf        ssim_vs_ate3d, ate3d_by_task, metric_intervals, poi_heatmaps
    with several samples per example (report/samples.py): "mean ± seed std" in the model table,
                                    tables/best_of_k.md/.tex and power.md/.tex, tables/samples.csv and
                                    power.csv
    with runs scored against a physical envelope (`evaluate --envelope ENV`): tables/envelope.md/.tex,
                                    envelope_widths.md/.tex, envelope.csv, envelope_widths.csv and
                                    figures/envelope_<metric>.png/.pdf (ATE-3D unless envelope_metric says)
    with fine-tuned checkpoint runs (see report/checkpoints.py): tables/checkpoint_sweep.md/.tex/.csv,
                                    tables/checkpoint_paired.md/.tex (with a base run), for the selected
                                    checkpoints tables/checkpoint_selected_paired, _tasks, _partitions
                                    .md/.tex, and figures/metric_vs_step.png/.pdf
    examples/<id>/<row>.jpg, .mp4   filmstrips of a few examples: the reference and each prediction with
                                    mask outlines, and looping clips (where the reference bundles and
                                    predictions that run.json records are on this machine)

When every run is on the verified published set, scored under protocol rigidbench-v1 with neural perception
over all its examples, the model, task and partition tables (and model_metrics.csv, by_task.csv,
by_partition.csv, whose `source` column tells them apart) also show the paper's numbers
(configs/paper_numbers.yaml), marked "reported in the paper, not re-scored here"; otherwise one line under
"Model comparison" and in report.md says why they are not shown (report/paper.py).

A report whose runs all have one sample per example and no envelope is exactly what it was before samples
and envelopes existed, file for file. matplotlib is imported only when figures are drawn.
"""

from __future__ import annotations

import logging
import os
from dataclasses import dataclass
from pathlib import Path

from rigidbench.metrics import METRICS
from rigidbench.report.analysis import analyse
from rigidbench.report.checkpoints import checkpoint_figure, checkpoint_tables, find_checkpoints, write_checkpoint_csv
from rigidbench.report.examples import build_filmstrips
from rigidbench.report.figures import build_figures
from rigidbench.report.html import render_page
from rigidbench.report.load import ReportError, ScoreTable, load_runs
from rigidbench.report.paper import comparison_problem, load_paper_numbers
from rigidbench.report.readouts import readout_section
from rigidbench.report.samples import check_metric, read_samples
from rigidbench.report.tables import build_tables, to_markdown, write_csvs, write_tables

log = logging.getLogger(__name__)

__all__ = ["ReportError", "ReportNotes", "ScoreTable", "build_report", "load_runs"]

# Which CSV files the HTML offers beside each table.
_CSV_FOR_TABLE = {"model_metrics": ("model_metrics.csv", "correlation.csv", "samples.csv"), "by_task": ("by_task.csv",),
                  "all_by_task": ("by_task.csv",), "by_partition": ("by_partition.csv",),
                  "all_by_partition": ("by_partition.csv",), "paired_changes": ("paired_changes.csv",),
                  "poi_ate3d": ("poi_matrix.csv",), "poi_ssim": ("poi_matrix.csv",),
                  "checkpoint_sweep": ("checkpoint_sweep.csv",), "checkpoint_paired": ("checkpoint_sweep.csv",),
                  "checkpoint_selected_paired": ("checkpoint_sweep.csv",),
                  "checkpoint_selected_tasks": ("by_task.csv",),
                  "checkpoint_selected_partitions": ("by_partition.csv",),
                  "best_of_k": ("samples.csv",), "power": ("power.csv",), "envelope": ("envelope.csv",),
                  "envelope_widths": ("envelope_widths.csv",)}


@dataclass(frozen=True)
class ReportNotes:
    """What the report could not do as usual, said once each.

    status: whether the runs are official, with the reasons every unofficial run shares; extra_reasons:
    run name -> its reasons beyond those; general: short notes for the page header; skipped_summary and
    skipped: measurements not computed, one line and then one note per (measurement, reason).
    """

    status: str
    official: bool
    extra_reasons: dict[str, tuple[str, ...]]
    general: tuple[str, ...]
    skipped_summary: str
    skipped: tuple[str, ...]

    def lines(self) -> list[str]:
        """Every note as plain text, in page order (report.md)."""
        return [self.status, *self.general, *self.skipped]


def official_status(runs) -> tuple[str, bool, dict[str, tuple[str, ...]]]:
    """(one sentence on whether the runs are official, all official?, run -> reasons beyond the shared ones)."""
    unofficial = [r for r in runs if not r.official]
    if not unofficial:
        return (f"Official: {'every run covers' if len(runs) > 1 else 'the run covers'} the whole evaluation split "
                "with every measurement."), True, {}
    shared = [x for x in unofficial[0].why_not_official if all(x in r.why_not_official for r in unofficial)]
    extra = {r.name: tuple(x for x in r.why_not_official if x not in shared) for r in unofficial}
    who = ("Not an official result" if len(unofficial) == len(runs)
           else f"Not official for {', '.join(r.name for r in unofficial)}")
    reason = (": " + "; ".join(shared) + "." if shared else " (the reasons for each run are under Runs).")
    return who + reason, False, extra


def _and(items: list[str]) -> str:
    return items[0] if len(items) == 1 else ", ".join(items[:-1]) + " and " + items[-1]


def report_notes(data) -> ReportNotes:
    """Plain-language notes on what the report could not do as usual: official status, one run, skipped metrics."""
    t = data.table
    general = list(t.notes)
    for run in t.runs:
        short = run.coverage.get("short") or []
        if short:
            general.append(f"{run.name}: {len(short)} clips shorter than the reference span were scored on the "
                           f"frames they have (--allow-short; coverage {run.coverage_text}); its scores are not "
                           "comparable with full-length runs.")
    if len(t.models) == 1:
        general.append("Only one run was given: there are no paired comparisons or probability-of-improvement "
                       "matrices, and no correlation across models.")
    # One note per (measurement, reason), naming the runs it applies to: the reasons are long.
    groups: dict[tuple[str, str], list[str]] = {}
    for m, run in enumerate(t.runs):
        for k, s in zip(t.metrics, t.skipped[m]):
            if s:
                groups.setdefault((k, run.skipped_metrics.get(k, "")), []).append(run.name)

    def who(names) -> str:
        return f"all {len(names)} runs" if len(names) == len(t.runs) > 1 else ", ".join(names)

    skipped = [f"{METRICS[k].display_name} not computed for {who(names)}" + (f": {reason}" if reason else ".")
               for (k, reason), names in groups.items()]
    by_metric: dict[str, list[str]] = {}
    for (k, _), names in groups.items():
        by_metric.setdefault(k, []).extend(n for n in names if n not in by_metric.get(k, []))
    summary = ""
    if by_metric:
        names = [METRICS[k].display_name for k in by_metric]
        runs_sets = {tuple(v) for v in by_metric.values()}
        verb = "was" if len(names) == 1 else "were"
        if len(runs_sets) == 1:
            summary = f"{_and(names)} {verb} not computed for {who(next(iter(runs_sets)))}"
        else:
            summary = "Not computed: " + "; ".join(f"{METRICS[k].display_name} for {who(v)}"
                                                   for k, v in by_metric.items())
    status, official, extra = official_status(t.runs)
    return ReportNotes(status, official, extra, tuple(general), summary, tuple(skipped))


def probe_link(probe_report, out_dir: Path) -> tuple[str, str] | None:
    """(href relative to out_dir, note) for a probe report: its report.html, or the file given; None if none."""
    if probe_report is None:
        return None
    path = Path(probe_report)
    if path.is_dir() or not path.suffix:
        path = path / "report.html"
    href = Path(os.path.relpath(path.resolve(), out_dir.resolve())).as_posix()
    return href, "" if path.is_file() else f" (not found at {path} when this report was written)"


def build_report(run_dirs, out_dir, resamples: int = 20000, seed: int = 0, baseline: str | None = None,
                 examples: int = 3, clips: bool = True, outlines: str = "reference",
                 probe_report: Path | None = None, envelope_metric: str = "ate3d",
                 power_differences: dict[str, float] | None = None) -> Path:
    """Read run directories, write tables, figures, example filmstrips and report.html into out_dir.

    examples: how many examples get filmstrips (0: none); clips: also write their looping videos; outlines:
    what the prediction rows outline, "reference" (where the objects should be) or "perceived" (the run's
    perception cache). Runs of fine-tuned checkpoints add a checkpoint section (report/checkpoints.py);
    probe_report: the HTML `rigidbench probe report` wrote (or its directory), linked from the header.
    envelope_metric: the measurement of the envelope figure; power_differences: metric -> the difference the
    power table's "examples needed" aim at (default 10% of the baseline's mean). Returns the report.html path."""
    out_dir = Path(out_dir)
    table = load_runs(run_dirs)
    log.info("loaded %d runs over %d shared examples", len(table.models), len(table.example_ids))
    check_metric(envelope_metric, table.metrics, "--envelope-metric")
    for metric in power_differences or {}:
        check_metric(metric, table.metrics, "--power-difference")
    data = analyse(table, resamples=resamples, seed=seed, baseline=baseline, samples=read_samples(table),
                   power_differences=power_differences, envelope_metric=envelope_metric)
    tables_dir, figures_dir = out_dir / "tables", out_dir / "figures"
    tables_dir.mkdir(parents=True, exist_ok=True)
    figures_dir.mkdir(parents=True, exist_ok=True)
    paper = load_paper_numbers()
    paper_note = comparison_problem(table, paper) or ""  # the paper's rows only beside comparable runs
    reported = None if paper_note else paper
    tables = build_tables(data, reported, power_differences)
    sweep = find_checkpoints(data)
    if sweep is not None:
        tables += checkpoint_tables(data, sweep)
    readout_tables, readout_figures = readout_section(run_dirs, figures_dir)  # beside the ten measurements
    tables += readout_tables
    table_files = write_tables(tables, tables_dir)
    csv_paths = {p.name: p for p in write_csvs(data, tables_dir, reported)}
    if sweep is not None:
        path = write_checkpoint_csv(data, sweep, tables_dir)
        csv_paths[path.name] = path
    for key, files in table_files.items():
        files["csv"] = [csv_paths[name] for name in _CSV_FOR_TABLE.get(key, ()) if name in csv_paths]
    figures = build_figures(data, figures_dir)
    if sweep is not None:
        curve = checkpoint_figure(data, sweep, figures_dir)
        if curve is not None:
            figures.append(curve)
    figures += readout_figures
    probe = probe_link(probe_report, out_dir)
    strips = build_filmstrips(data, out_dir / "examples", n_examples=examples, clips=clips, outlines=outlines)
    notes = report_notes(data)
    markdown = ["# RigidBench report", ""] + [f"- {n}" for n in notes.lines() + ([paper_note] if paper_note else [])]
    if probe is not None:
        markdown.append(f"- Probe report: [{probe[0]}]({probe[0]}){probe[1]}")
    if sweep is not None:
        markdown += [f"- Fine-tuned checkpoints: {n}" for n in sweep.notes]
    markdown.append("")
    for tb in tables:
        markdown.append(to_markdown(tb))
    for fig in figures:
        markdown += [f"### {fig.title}", "", f"![{fig.title}]({fig.png.relative_to(out_dir).as_posix()})", "",
                     fig.caption, ""]
    if strips.note:
        markdown += [strips.note, ""]
    for ex in strips.examples:
        markdown += [f"### Example {ex.sample_id} ({ex.task}, {ex.partition})", ""]
        markdown += [f"- {row.label}: ![{row.label}]({row.image.relative_to(out_dir).as_posix()})"
                     if row.image is not None else f"- {row.label}: {row.note}" for row in ex.rows]
        markdown.append("")
    (out_dir / "report.md").write_text("\n".join(markdown))
    page = out_dir / "report.html"
    page.write_text(render_page(data, notes, tables, table_files, figures, out_dir, strips,
                                checkpoints=sweep, probe=probe, paper_note=paper_note))
    log.info("wrote %s", page)
    return page


