"""Fine-tuned checkpoints in the report: metric-versus-step curves, paired changes against base Wan and the
selected checkpoints by task and evaluation partition (paper appendix D, "Complete Checkpoint Results" and
"Task and Evaluation-Partition Breakdowns").

A run is a checkpoint run when the ``generation.json`` of the predictions directory its run.json records
(written by ``rigidbench predict``) names a checkpoint: ``model.checkpoint`` (or ``settings.checkpoint``)
with its ``path`` and ``kind``. The checkpoint directory's ``checkpoint.json`` (written by
``rigidbench train``, see ``rigidbench.train.checkpoint``) gives its ``step`` and ``mode`` (lora / full);
when that file is not on this machine the step is read from the directory name (``step-N``) and the mode
from the checkpoint kind. The training run is ``RUN`` in ``RUN/checkpoints/step-N``. Base Wan is a run of
the same predictor without a checkpoint.

The paired change of each checkpoint is (checkpoint - base) per example with the same percentile bootstrap
as the report's baseline comparison (`analysis.paired_vs_baseline`), over the examples shared by all runs.
The selected checkpoints (per training run, the lowest mean ATE-3D) get the appendix's three further tables:
their paired changes against base and, with exactly two training runs, against each other (second run minus
first, paired over the same examples), and their mean ATE-3D by task and ATE-3D / SSIM by evaluation
partition beside base Wan, from the report's per-group means and marked as its other per-group tables are.
Anything missing (no predictions directory, no generation.json) leaves that run unclassified; the section
appears only when at least one checkpoint run is found.
"""

from __future__ import annotations

import json
import logging
import math
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from rigidbench.folders import GENERATION_FILE, PredictionsFolder
from rigidbench.metrics import METRICS
from rigidbench.report.analysis import Intervals, ReportData, higher_is_better, paired_vs_baseline
from rigidbench.report.examples import resolve_dir
from rigidbench.report.figures import FigureFile, model_colors, new_figure, save_figure
from rigidbench.report.tables import (
    ARROW_TEXT,
    GROUP_WORDS,
    MARKS_NOTE,
    PARTITION_NOTE,
    Cell,
    Table,
    column_decimals,
    csv_number,
    display_scale,
    fmt,
    grouping,
    headline_metrics,
    interval_text,
    marks_for,
    metric_arrow,
    metric_groups,
    metric_label,
    scale_note,
    value_cell,
    write_csv,
)

log = logging.getLogger(__name__)

CHECKPOINT_FILE = "checkpoint.json"   # rigidbench.train.checkpoint.CHECKPOINT_FILE
MODE_LABELS = {"lora": "LoRA", "full": "Full FT"}
_STEP = re.compile(r"^step-(\d+)$")


@dataclass(frozen=True)
class CheckpointModel:
    """One evaluation run of a fine-tuned checkpoint: its row in the ScoreTable and where it came from."""

    index: int
    name: str
    run: str            # training-run label ("LoRA", "Full FT", or with the run directory when ambiguous)
    run_dir: str        # the training run directory (RUN of RUN/checkpoints/step-N)
    mode: str           # lora | full (or what checkpoint.json says)
    step: int | None
    kind: str           # the predictor's checkpoint kind (lora-peft, transformer-dir, ...)
    path: str


@dataclass(frozen=True)
class CheckpointSweep:
    """Every checkpoint run (ordered by training run, then step), base Wan and the paired changes against it.

    diff, poi: Intervals (C, K), checkpoint minus base and PoI over base, in `checkpoints` order; None without
    a base run. selected: per training run, the index (into `checkpoints`) of the lowest mean ATE-3D."""

    checkpoints: tuple[CheckpointModel, ...]
    runs: tuple[str, ...]
    base: int | None
    diff: Intervals | None
    poi: Intervals | None
    selected: tuple[int, ...]
    notes: tuple[str, ...]


def _read_generation(run) -> tuple[dict | None, str]:
    """(generation.json of the run's predictions directory or None, why not)."""
    pred_dir = resolve_dir(run.predictions, run.path)
    if pred_dir is None:
        return None, f"predictions directory '{run.predictions}' not found" if run.predictions else \
            "no predictions directory in run.json"
    path = PredictionsFolder(pred_dir).generation
    if not path.is_file():
        return None, f"no {GENERATION_FILE} in {pred_dir}"
    try:
        doc = json.loads(path.read_text())
    except (OSError, ValueError) as exc:
        return None, f"{path} unreadable ({exc})"
    return (doc if isinstance(doc, dict) else None), ("" if isinstance(doc, dict) else f"{path} is not an object")


def checkpoint_record(generation: dict) -> dict | None:
    """The checkpoint a generation.json names ({"path", "kind", ...}), or None for a base model."""
    for section in ("model", "settings"):
        record = (generation.get(section) or {}).get("checkpoint")
        if isinstance(record, dict) and record.get("path"):
            return record
    return None


def predictor_name(generation: dict) -> str:
    return str(generation.get("predictor") or (generation.get("settings") or {}).get("predictor") or "")


def describe_checkpoint(record: dict) -> tuple[str, str, int | None]:
    """(training run directory, mode, step) of a checkpoint record, from checkpoint.json when it is readable,
    else from the path (``RUN/checkpoints/step-N``) and the kind."""
    path = Path(str(record["path"]))
    ckpt_dir = path if path.suffix != ".safetensors" else path.parent
    run_dir = ckpt_dir.parent.parent if ckpt_dir.parent.name == "checkpoints" else ckpt_dir.parent
    kind = str(record.get("kind") or "")
    mode = "lora" if kind.startswith("lora") else "full" if kind.startswith("transformer") else kind or "unknown"
    match = _STEP.match(ckpt_dir.name)
    step = int(match.group(1)) if match else None
    meta_path = ckpt_dir / CHECKPOINT_FILE
    if meta_path.is_file():
        try:
            meta = json.loads(meta_path.read_text())
            step = int(meta["step"]) if meta.get("step") is not None else step
            mode = str(meta.get("mode") or mode)
        except (OSError, ValueError, TypeError, KeyError) as exc:
            log.warning("%s unreadable (%s); step and mode taken from the path", meta_path, exc)
    return str(run_dir), mode, step


def _run_labels(found: list[tuple[str, str]]) -> dict[tuple[str, str], str]:
    """(run_dir, mode) -> label: the mode's name, with the run directory's name where two runs share a mode."""
    labels = {}
    for run_dir, mode in found:
        base = MODE_LABELS.get(mode, mode)
        same = [r for r, m in found if MODE_LABELS.get(m, m) == base]
        labels[(run_dir, mode)] = base if len(same) == 1 else f"{base} ({Path(run_dir).name})"
    return labels


def find_checkpoints(data: ReportData, resamples: int | None = None, seed: int | None = None) -> CheckpointSweep | None:
    """Classify the report's runs; None when none of them is a fine-tuned checkpoint."""
    t = data.table
    generations = {}
    for m, run in enumerate(t.runs):
        doc, why = _read_generation(run)
        if doc is not None:
            generations[m] = doc
        else:
            log.debug("%s: %s; not classified as a checkpoint run", run.name, why)
    found = {m: checkpoint_record(doc) for m, doc in generations.items()}
    ckpt_rows = [m for m, rec in found.items() if rec is not None]
    if not ckpt_rows:
        return None
    notes = []
    predictors = {predictor_name(generations[m]) for m in ckpt_rows}
    bases = [m for m, rec in found.items() if rec is None and predictor_name(generations[m]) in predictors]
    base = bases[0] if bases else None
    if len(bases) > 1:
        notes.append(f"Several runs are base {'/'.join(sorted(predictors))} without a checkpoint "
                     f"({', '.join(t.models[m] for m in bases)}); the paired changes use {t.models[base]}.")
    if base is None:
        notes.append(f"No base run ({'/'.join(sorted(predictors))} without a checkpoint) is among the runs, so "
                     "there are no paired changes; add its run directory to compare.")
    unclassified = [t.runs[m].name for m in range(len(t.runs)) if m not in generations]
    if unclassified:
        notes.append(f"No {GENERATION_FILE} found for {', '.join(unclassified)}, so whether "
                     f"{'it is' if len(unclassified) == 1 else 'they are'} a checkpoint or base run is unknown.")
    described = {m: describe_checkpoint(found[m]) for m in ckpt_rows}
    keys = list(dict.fromkeys((run_dir, mode) for run_dir, mode, _ in described.values()))
    labels = _run_labels(keys)
    mode_order = {mode: i for i, mode in enumerate(MODE_LABELS)}
    keys.sort(key=lambda k: (mode_order.get(k[1], len(mode_order)), labels[k]))
    models = []
    for key in keys:
        rows = [m for m in ckpt_rows if described[m][:2] == key]
        rows.sort(key=lambda m: (described[m][2] is None, described[m][2] or 0, t.models[m]))
        models += [CheckpointModel(m, t.models[m], labels[key], key[0], key[1], described[m][2],
                                   str(found[m].get("kind") or ""), str(found[m]["path"])) for m in rows]
    if any(c.step is None for c in models):
        notes.append("No step is known for " + ", ".join(c.name for c in models if c.step is None)
                     + f" (no {CHECKPOINT_FILE} and no step-N directory name); it is left out of the curves.")
    diff = poi = None
    resamples = data.resamples if resamples is None else resamples
    seed = data.seed if seed is None else seed
    if base is not None:
        rows = [base] + [c.index for c in models]
        d, p = paired_vs_baseline(t.scores[rows], 0, higher_is_better(t.metrics), resamples, seed)
        diff, poi = (Intervals(*(getattr(iv, f)[1:] for f in ("mean", "lo", "hi", "n_finite"))) for iv in (d, p))
    selected = []
    if "ate3d" in t.metrics:
        k = t.metric_index("ate3d")
        for label in dict.fromkeys(c.run for c in models):
            idx = [i for i, c in enumerate(models) if c.run == label and math.isfinite(data.overall.mean[c.index, k])]
            if idx:
                selected.append(min(idx, key=lambda i: data.overall.mean[models[i].index, k]))
    return CheckpointSweep(tuple(models), tuple(dict.fromkeys(c.run for c in models)), base, diff, poi,
                           tuple(selected), tuple(notes))


def _step_text(step: int | None) -> str:
    return "—" if step is None else f"{step:,}"


def sweep_table(data: ReportData, sweep: CheckpointSweep) -> Table:
    """Base and every checkpoint x every metric, means only, best / second marked among them (the paper's
    complete checkpoint sweep); the step of each run's lowest-ATE-3D checkpoint is bold."""
    t = data.table
    rows_idx = ([sweep.base] if sweep.base is not None else []) + [c.index for c in sweep.checkpoints]
    eligible = np.zeros(len(t.models), dtype=bool)
    eligible[rows_idx] = True
    n = len(t.example_ids)
    columns = []
    for k, metric in enumerate(t.metrics):
        decimals = column_decimals(data.overall.mean[rows_idx, k], metric)
        means = np.where(eligible, data.overall.mean[:, k], np.nan)
        marks = marks_for(means, metric, eligible & ~t.skipped[:, k], decimals)
        columns.append({m: (Cell("skipped") if t.skipped[m, k] else
                            Cell(fmt(data.overall.mean[m, k] * display_scale(metric), decimals),
                                 note=f"n={int(data.overall.n_finite[m, k])}" if data.overall.n_finite[m, k] < n
                                 else "", mark=marks[m]))
                        for m in rows_idx})
    rows, breaks = [], []
    if sweep.base is not None:
        rows.append((Cell("Base"), Cell("—")) + tuple(col[sweep.base] for col in columns))
    previous = None
    for i, c in enumerate(sweep.checkpoints):
        if c.run != previous and rows:
            breaks.append(len(rows))
        previous = c.run
        rows.append((Cell(c.run), Cell(_step_text(c.step), mark="best" if i in sweep.selected else ""))
                    + tuple(col[c.index] for col in columns))
    caption = (f"Means over the {n} shared evaluation examples for base Wan"
               + (f" ({t.models[sweep.base]})" if sweep.base is not None else " (not among the runs)")
               + " and every evaluated checkpoint of each training run. A bold step marks the lowest mean ATE-3D "
               f"within its run. {MARKS_NOTE} Intervals are in checkpoint_sweep.csv." + scale_note(t.metrics))
    return Table("checkpoint_sweep", "Complete checkpoint sweep", caption,
                 ("Regime", "Step") + tuple(metric_label(m) for m in t.metrics),
                 ("", "") + tuple(metric_arrow(m) for m in t.metrics), tuple(rows), n_label_columns=2,
                 groups=metric_groups(t.metrics), row_breaks=tuple(breaks))


def paired_checkpoint_table(data: ReportData, sweep: CheckpointSweep) -> Table | None:
    """Every checkpoint x every metric: mean paired change against base Wan with its 95% bootstrap interval."""
    if sweep.base is None or sweep.diff is None:
        return None
    t = data.table
    n = len(t.example_ids)
    d = sweep.diff
    decimals = [column_decimals(np.array([d.mean[:, k], d.lo[:, k], d.hi[:, k]]), metric)
                for k, metric in enumerate(t.metrics)]
    rows, breaks, previous = [], [], None
    for i, c in enumerate(sweep.checkpoints):
        if c.run != previous and rows:
            breaks.append(len(rows))
        previous = c.run
        cells = []
        for k, metric in enumerate(t.metrics):
            scale, matched = display_scale(metric), int(d.n_finite[i, k])
            if t.skipped[c.index, k] or t.skipped[sweep.base, k]:
                cells.append(Cell("skipped"))
            elif matched == 0:
                cells.append(Cell("n/a"))
            else:
                sig = "significant" if (d.lo[i, k] > 0 or d.hi[i, k] < 0) else ""
                cells.append(Cell(fmt(d.mean[i, k] * scale, decimals[k], signed=True),
                                  interval_text(d.lo[i, k] * scale, d.hi[i, k] * scale, decimals[k], signed=True),
                                  f"n={matched}" if matched < n else "", sig))
        rows.append((Cell(c.run), Cell(_step_text(c.step), mark="best" if i in sweep.selected else ""))
                    + tuple(cells))
    base = t.models[sweep.base]
    caption = (f"Mean paired change of each checkpoint against base Wan ({base}), checkpoint − base on the "
               f"matched examples, with its 95% percentile bootstrap interval ({data.resamples:,} resamples over "
               "examples). Bold changes have an interval that excludes 0; a bold step marks the run's lowest "
               "mean ATE-3D. Positive is better where the arrow points up, negative where it points down; n= "
               "counts the examples finite for both where some were not." + scale_note(t.metrics))
    return Table("checkpoint_paired", "Paired changes against base Wan", caption,
                 ("Regime", "Step") + tuple(metric_label(m) for m in t.metrics),
                 ("", "") + tuple(metric_arrow(m) for m in t.metrics), tuple(rows), n_label_columns=2,
                 groups=metric_groups(t.metrics), row_breaks=tuple(breaks))


# ------------------------------------------------------------------------- the selected checkpoints


def _selected_label(c: CheckpointModel) -> str:
    """'LoRA 1,000': the training run and step (the model name when no step is known)."""
    return f"{c.run} {c.step:,}" if c.step is not None else f"{c.run} ({c.name})"


def selected_paired_table(data: ReportData, sweep: CheckpointSweep) -> Table | None:
    """Metric x comparison for the selected checkpoints (the paper's transposed table): each selected checkpoint
    minus base Wan and, when exactly two training runs have one, the second minus the first, each a mean paired
    change with its 95% bootstrap interval. None when there is no column (no base and not two selected)."""
    t = data.table
    n = len(t.example_ids)
    chosen = [sweep.checkpoints[i] for i in sweep.selected]
    # (heading, mean, lo, hi, n_finite arrays over metrics, the two ScoreTable rows compared)
    columns = []
    if sweep.base is not None and sweep.diff is not None:
        d = sweep.diff
        columns += [(f"{_selected_label(c)} − base", d.mean[i], d.lo[i], d.hi[i], d.n_finite[i],
                     (c.index, sweep.base)) for i, c in zip(sweep.selected, chosen)]
    if len(chosen) == 2:
        first, second = chosen
        d, _ = paired_vs_baseline(t.scores[[first.index, second.index]], 0, higher_is_better(t.metrics),
                                  data.resamples, data.seed)
        columns.append((f"{second.run} − {first.run}", d.mean[1], d.lo[1], d.hi[1], d.n_finite[1],
                        (second.index, first.index)))
    if not columns:
        return None
    rows = []
    for k, metric in enumerate(t.metrics):
        scale = display_scale(metric)
        decimals = column_decimals(np.array([[col[f][k] for f in (1, 2, 3)] for col in columns]), metric)
        cells = []
        for _, mean, lo, hi, n_finite, (a, b) in columns:
            matched = int(n_finite[k])
            if t.skipped[a, k] or t.skipped[b, k]:
                cells.append(Cell("skipped"))
            elif matched == 0:
                cells.append(Cell("n/a"))
            else:
                cells.append(Cell(fmt(mean[k] * scale, decimals, signed=True),
                                  interval_text(lo[k] * scale, hi[k] * scale, decimals, signed=True),
                                  f"n={matched}" if matched < n else "",
                                  "significant" if (lo[k] > 0 or hi[k] < 0) else ""))
        rows.append((Cell(metric_label(metric) + ARROW_TEXT[metric_arrow(metric)]),) + tuple(cells))
    names = ", ".join(f"{_selected_label(c)} ({c.name})" for c in chosen)
    against = ([f"against base Wan ({t.models[sweep.base]})"] if sweep.base is not None else []) + (
        [f"between the two runs' selections ({chosen[1].run} − {chosen[0].run})"] if len(chosen) == 2 else [])
    caption = (f"Mean paired change of the selected checkpoints ({names}: the lowest mean ATE-3D of each training "
               f"run) {' and '.join(against)}, on the matched examples, with its 95% percentile bootstrap interval "
               f"({data.resamples:,} resamples over examples). Bold changes have an interval that excludes 0. "
               "Positive is better where the arrow points up, negative where it points down; n= counts the examples "
               "finite for both where some were not." + scale_note(t.metrics))
    return Table("checkpoint_selected_paired", "Paired changes for the selected checkpoints", caption,
                 ("Metric",) + tuple(col[0] for col in columns), ("",) * (1 + len(columns)), tuple(rows))


def selected_breakdown_table(data: ReportData, sweep: CheckpointSweep, by: str) -> Table | None:
    """Base Wan and the selected checkpoints x (metric, group): means over each task's (by="task": ATE-3D) or
    evaluation partition's (by="partition": ATE-3D and SSIM) examples, from the report's per-group means
    (`data.by_task`, `data.by_partition`), best / second marked among these rows as in the report's other
    per-group tables. A metric no shown row has drops its group; None without selected checkpoints."""
    t = data.table
    if not sweep.selected:
        return None
    labels, groups, iv, label = grouping(data, by)
    chosen = [sweep.checkpoints[i] for i in sweep.selected]
    entries = ([("Base", sweep.base)] if sweep.base is not None else []) + [(_selected_label(c), c.index)
                                                                            for c in chosen]
    rows_idx = [m for _, m in entries]
    shown = np.zeros(len(t.models), dtype=bool)
    shown[rows_idx] = True
    wanted = ("ate3d",) if by == "task" else headline_metrics(t.metrics)
    metrics = tuple(m for m in wanted if m in t.metrics and not t.skipped[rows_idx, t.metric_index(m)].all())
    if not metrics:
        return None
    counts = [int(np.sum(labels == g)) for g in groups]
    columns, header, spans = [], [], []
    for metric in metrics:
        k = t.metric_index(metric)
        decimals = column_decimals(iv.mean[rows_idx, :, k], metric)
        for g in range(len(groups)):
            marks = marks_for(iv.mean[:, g, k], metric, shown & data.ranked & ~t.skipped[:, k], decimals)
            columns.append({m: value_cell(iv.mean[m, g, k], iv.lo[m, g, k], iv.hi[m, g, k],
                                          int(iv.n_finite[m, g, k]), counts[g], decimals, marks[m],
                                          bool(t.skipped[m, k]), with_interval=False, scale=display_scale(metric))
                            for m in rows_idx})
        header += [label(g) for g in groups]
        spans.append((f"{metric_label(metric)}{ARROW_TEXT[metric_arrow(metric)]}", len(groups)))
    rows = tuple((Cell(text),) + tuple(col[m] for col in columns) for text, m in entries)
    word, csv_name = GROUP_WORDS[by]
    names = " and ".join(METRICS[m].display_name for m in metrics)
    sizes = ", ".join(f"{label(g)} {c}" for g, c in zip(groups, counts))
    who = ", ".join(f"{text} ({t.models[m]})" for text, m in entries)
    caption = (f"Mean {names} over each {word}'s examples ({sizes}) for "
               + ("base Wan and " if sweep.base is not None else "")
               + f"the selected checkpoints (the lowest mean ATE-3D of each training run): {who}. Non-finite "
               "measurements are left out and n= gives the finite count where there were some. "
               + (PARTITION_NOTE + " " if by == "partition" else "") + MARKS_NOTE
               + f" The 95% intervals are in {csv_name}." + scale_note(metrics))
    title = "Selected checkpoints by task" if by == "task" else "Selected checkpoints by evaluation partition"
    return Table(f"checkpoint_selected_{'tasks' if by == 'task' else 'partitions'}", title, caption,
                 ("Model",) + tuple(header), ("",) * (1 + len(header)), rows, groups=tuple(spans))


def checkpoint_tables(data: ReportData, sweep: CheckpointSweep) -> list[Table]:
    """The section's tables in display order: the sweep, paired changes of every checkpoint against base, then
    the selected checkpoints' paired changes, by task and by evaluation partition (each where it exists)."""
    tables = [sweep_table(data, sweep), paired_checkpoint_table(data, sweep), selected_paired_table(data, sweep),
              selected_breakdown_table(data, sweep, "task"), selected_breakdown_table(data, sweep, "partition")]
    return [tb for tb in tables if tb is not None]


def write_checkpoint_csv(data: ReportData, sweep: CheckpointSweep, out_dir: Path) -> Path:
    """checkpoint_sweep.csv: one row per (run, metric), unscaled: mean with interval, and the paired change and
    PoI against base with intervals (empty on the base row or without a base)."""
    t = data.table
    o = data.overall
    rows = []
    entries = ([("base", "", "", sweep.base, None)] if sweep.base is not None else []) + [
        (c.run, c.mode, "" if c.step is None else c.step, c.index, i) for i, c in enumerate(sweep.checkpoints)]
    for run, mode, step, m, i in entries:
        for k, metric in enumerate(t.metrics):
            paired = ["", "", "", "", "", "", ""]
            if i is not None and sweep.diff is not None:
                d, p = sweep.diff, sweep.poi
                paired = [csv_number(d.mean[i, k]), csv_number(d.lo[i, k]), csv_number(d.hi[i, k]),
                          csv_number(p.mean[i, k]), csv_number(p.lo[i, k]), csv_number(p.hi[i, k]), int(d.n_finite[i, k])]
            rows.append([run, mode, step, t.models[m], metric, int(METRICS[metric].higher_is_better),
                         csv_number(o.mean[m, k]), csv_number(o.lo[m, k]), csv_number(o.hi[m, k]),
                         int(o.n_finite[m, k]), *paired, int(i is not None and i in sweep.selected)])
    return write_csv(out_dir / "checkpoint_sweep.csv",
                     ["training_run", "mode", "step", "model", "metric", "higher_is_better", "mean", "ci_low",
                      "ci_high", "n_finite", "diff_mean", "diff_ci_low", "diff_ci_high", "poi", "poi_ci_low",
                      "poi_ci_high", "n_matched", "selected"], rows)


def checkpoint_figure(data: ReportData, sweep: CheckpointSweep, out_dir: Path) -> FigureFile | None:
    """metric_vs_step: one panel per measurement, one line per training run (mean with its 95% band) against the
    step, base Wan as a dashed horizontal line with its band. None when no checkpoint has a step."""
    t = data.table
    if not any(c.step is not None for c in sweep.checkpoints):
        return None
    from matplotlib.ticker import MaxNLocator

    order = [m for m in ("ate3d", "iou", "ssim") if m in t.metrics] + [m for m in t.metrics
                                                                        if m not in ("ate3d", "iou", "ssim")]
    ncols = min(5, len(order))
    nrows = math.ceil(len(order) / ncols)
    fig = new_figure(2.9 * ncols, 2.3 * nrows + 0.4)
    axes = fig.subplots(nrows, ncols, squeeze=False)
    colors = model_colors(len(sweep.runs))
    o = data.overall
    all_steps = sorted({c.step for c in sweep.checkpoints if c.step is not None})
    for panel, metric in enumerate(order):
        k = t.metric_index(metric)
        ax = axes.flat[panel]
        scale = display_scale(metric)
        for r, label in enumerate(sweep.runs):
            pts = [c for c in sweep.checkpoints if c.run == label and c.step is not None]
            steps = np.array([c.step for c in pts], dtype=float)
            idx = [c.index for c in pts]
            mean, lo, hi = (o.mean[idx, k] * scale, o.lo[idx, k] * scale, o.hi[idx, k] * scale)
            ok = np.isfinite(mean)
            if not ok.any():
                continue
            ax.plot(steps[ok], mean[ok], "o-", color=colors[r], ms=3.5, lw=1.4, label=label)
            band = ok & np.isfinite(lo) & np.isfinite(hi)
            if band.any():
                ax.fill_between(steps[band], lo[band], hi[band], color=colors[r], alpha=0.15, lw=0)
        if sweep.base is not None and math.isfinite(o.mean[sweep.base, k]):
            ax.axhline(o.mean[sweep.base, k] * scale, color="0.25", ls="--", lw=1.1, label="Base Wan")
            if math.isfinite(o.lo[sweep.base, k]) and math.isfinite(o.hi[sweep.base, k]):
                ax.axhspan(o.lo[sweep.base, k] * scale, o.hi[sweep.base, k] * scale, color="0.5", alpha=0.1, lw=0)
        arrow = "↑" if METRICS[metric].higher_is_better else "↓"
        ax.set_title(f"{metric_label(metric)} {arrow}", fontsize=10)
        ax.set_xlabel("step", fontsize=8)
        ax.grid(alpha=0.3)
        if len(all_steps) <= 7:
            ax.set_xticks(all_steps, [f"{x:,}" for x in all_steps])
        else:
            ax.xaxis.set_major_locator(MaxNLocator(nbins=5, integer=True))
        ax.tick_params(labelsize=7)
        if t.skipped[:, k].all():
            ax.text(0.5, 0.5, "skipped", transform=ax.transAxes, ha="center", va="center", color="0.4")
    for ax in axes.flat[len(order):]:
        ax.set_visible(False)
    handles, labels = axes.flat[0].get_legend_handles_labels()
    if handles:
        fig.legend(handles, labels, loc="outside upper center", ncols=len(handles), frameon=False, fontsize=9)
    caption = ("Mean of each measurement against the training step, one line per training run with its 95% "
               f"bootstrap band over examples ({data.resamples:,} resamples); the dashed line and grey band are base "
               "Wan." + (" BGDrift is multiplied by 10³." if "bgdrift" in t.metrics else ""))
    return save_figure(fig, out_dir, "metric_vs_step", "Measurements against the training step", caption)
