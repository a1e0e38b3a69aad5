"""The report's tables as one cell model, rendered to Markdown, LaTeX (booktabs) and HTML, plus tidy CSV.

Tables mirror the paper: model x ten metrics (mean and 95% bootstrap interval, best bold and
second-best underlined in each column, a tie as printed taking no mark), ATE-3D and SSIM by task
and by evaluation partition (every metric in a second, means-only table for each), paired changes
and probabilities of improvement against a baseline, and the model x model probability-of-
improvement matrix for ATE-3D and SSIM. Numbers print to about three significant figures at the
column's typical magnitude. A mean taken over fewer than all examples carries its finite count
("0.123 (n=97)"). CSV files hold the unrounded, unscaled numbers in long form (one row per model
and metric) and round-trip exactly. When the runs are comparable with the paper (report/paper.py), the
model, task and partition tables and their CSV files also carry the paper's rows, in a block of their own
marked "reported in the paper, not re-scored here", as the paper prints them and never ranked.
"""

from __future__ import annotations

import csv
import html
import math
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from rigidbench.metrics import GROUPS, METRICS
from rigidbench.report.analysis import (
    TASK_ORDER,
    ReportData,
    best_first_order,
    partition_label,
    rank_marks,
    task_label,
)
from rigidbench.report.paper import PaperNumbers
from rigidbench.report.samples import (
    DEFAULT_RELATIVE_DIFFERENCE,
    DOUBLED_ASSUMPTION,
    PAIRED_ASSUMPTION,
    POWER_ALPHA,
    POWER_EXAMPLES,
    POWER_SAMPLES,
    POWER_TARGET,
    PowerComparison,
    envelope_metric_note,
    finite,
)
from rigidbench.stats.power import PowerRow

# Display-only scale factors (the paper prints BGDrift x 10^3); CSV files stay unscaled.
# The paper's two column groups of the model table: six object measurements, four image measurements.
_SUPERSCRIPT = str.maketrans("0123456789-", "⁰¹²³⁴⁵⁶⁷⁸⁹⁻")


def metric_groups(metrics: tuple[str, ...]) -> tuple[tuple[str, int], ...]:
    """(heading, number of columns) for each run of consecutive metrics of one registry group."""
    groups: list[list] = []
    for m in metrics:
        heading = GROUPS.get(METRICS[m].group, METRICS[m].group)
        if groups and groups[-1][0] == heading:
            groups[-1][1] += 1
        else:
            groups.append([heading, 1])
    return tuple((h, n) for h, n in groups)


def display_scale(metric: str) -> float:
    return METRICS[metric].display_scale


@dataclass(frozen=True)
class Cell:
    """One table entry: main `text`, optional interval `detail` and count `note`; `mark` best/second/significant;
    `shade` a probability in [0, 1] that HTML shows as a blue (above 0.5) or red (below) background."""

    text: str
    detail: str = ""
    note: str = ""
    mark: str = ""
    shade: float = math.nan


@dataclass(frozen=True)
class Table:
    """A rendered-agnostic table; `groups` span the header columns after the first `n_label_columns`."""

    key: str
    title: str
    caption: str
    header: tuple[str, ...]
    arrows: tuple[str, ...]
    rows: tuple[tuple[Cell, ...], ...]
    n_label_columns: int = 1
    groups: tuple[tuple[str, int], ...] = ()
    row_breaks: tuple[int, ...] = field(default=())
    vertical_header: bool = False  # HTML: column headings after the label columns run bottom to top
    blocks: tuple[tuple[int, str], ...] = ()  # (row index, heading): a full-width heading before that row


# ------------------------------------------------------------------------------- number formats


def decimals_for(values) -> int:
    """values: array-like float. Returns decimals giving ~3 significant digits at their median magnitude,
    ignoring values below 1e-3 of the largest (numerical noise next to real errors) and at most 6."""
    arr = np.abs(np.asarray(values, dtype=np.float64).ravel())
    arr = arr[np.isfinite(arr) & (arr > 0)]
    if arr.size == 0:
        return 3
    arr = arr[arr >= 1e-3 * arr.max()]
    return int(np.clip(2 - math.floor(math.log10(float(np.median(arr)))), 0, 6))


def fmt(x: float, decimals: int, signed: bool = False) -> str:
    """x to `decimals` places; signed keeps the sign of a tiny change ('-0.000', as the paper prints it)."""
    if not math.isfinite(x):
        return "n/a"
    if signed:
        return f"{x:+.{decimals}f}"
    return f"{abs(x) if float(f'{x:.{decimals}f}') == 0.0 else x:.{decimals}f}"


def interval_text(lo: float, hi: float, decimals: int, signed: bool = False) -> str:
    """'[lo, hi]' at `decimals` places, or '' when the interval is undefined (fewer than two examples)."""
    if not (math.isfinite(lo) and math.isfinite(hi)):
        return ""
    return f"[{fmt(lo, decimals, signed)}, {fmt(hi, decimals, signed)}]"


def metric_label(metric: str) -> str:
    """Display name with its display scale, e.g. 'BGDrift×10³'."""
    info = METRICS[metric]
    if info.display_scale == 1.0:
        return info.display_name
    power = round(math.log10(info.display_scale))
    return f"{info.display_name}\u00d710{str(power).translate(_SUPERSCRIPT)}"


def metric_arrow(metric: str) -> str:
    return "up" if METRICS[metric].higher_is_better else "down"


def value_cell(mean: float, lo: float, hi: float, n_finite: int, n_total: int, decimals: int, mark: str = "",
               skipped: bool = False, with_interval: bool = True, scale: float = 1.0) -> Cell:
    """One mean with its interval and, when some examples were non-finite, its finite count."""
    if skipped:
        return Cell("skipped")
    note = f"n={n_finite}" if n_finite < n_total else ""
    if n_finite == 0:
        return Cell("n/a", note=note)
    detail = interval_text(lo * scale, hi * scale, decimals) if with_interval else ""
    return Cell(fmt(mean * scale, decimals), detail, note, mark)


# ------------------------------------------------------------------------------------- builders

# The paper's two headline measurements, the ones its task and partition tables and its
# probability-of-improvement figure show: 3D trajectory error against image similarity.
HEADLINE = ("ate3d", "ssim")


def headline_metrics(metrics: tuple[str, ...]) -> tuple[str, ...]:
    """The headline measurements present in `metrics` (the first two metrics if neither is)."""
    return tuple(m for m in HEADLINE if m in metrics) or tuple(metrics[:2])


def column_decimals(means: np.ndarray, metric: str) -> int:
    """Decimals for one metric's column of means (any shape), after its display scale."""
    return decimals_for(np.asarray(means, dtype=np.float64) * display_scale(metric))


def marks_for(means: np.ndarray, metric: str, eligible: np.ndarray, decimals: int) -> list[str]:
    """Best / second marks of one column, comparing the means as printed (see `rank_marks`)."""
    return rank_marks(means, METRICS[metric].higher_is_better, eligible, decimals, display_scale(metric))


def scale_note(metrics) -> str:
    return "".join(f" {METRICS[m].display_name} is multiplied by {METRICS[m].display_scale:g}."
                   for m in metrics if METRICS[m].display_scale != 1.0)


def _unranked_note(data: ReportData) -> str:
    unranked = [name for name, r in zip(data.table.models, data.ranked) if not r]
    return f" {', '.join(unranked)} is shown for comparison and not ranked." if unranked else ""


MARKS_NOTE = "Bold: best, underlined: second best, among unique values as printed (ties take no mark)."


def reported_rows(paper: PaperNumbers | None, by: str, columns: list[tuple[str, str | None]],
                  n_label_columns: int = 1) -> tuple[list[tuple[Cell, ...]], str, str]:
    """The paper's rows for a report table whose value columns are `columns` ((metric, task or partition id or
    None) each), from its tables by `by`: (rows, block heading, caption sentence); no rows when `paper` is None
    or has nothing for these columns. A row repeated by a later table (base Wan in the fine-tuning tables)
    is shown once; a column the paper does not report reads "—"."""
    rows: list[tuple[Cell, ...]] = []
    seen, used = set(), []
    for source in (paper.tables_by(by) if paper is not None else ()):
        found = False
        for row in source.rows:
            cells = [source.cell(row, metric, group) for metric, group in columns]
            if all(c is None for c in cells):
                continue
            label = f"{row.name} (paper)"
            texts = tuple(c.text if c is not None else "—" for c in cells)
            if (label, texts) in seen:
                continue
            seen.add((label, texts))
            found = True
            rows.append((Cell(label),) + (Cell(""),) * (n_label_columns - 1) + tuple(
                Cell("—") if c is None else Cell(c.text, note=f"n={c.n_finite}" if c.n_finite < c.n_examples
                                                 else "") for c in cells))
        if found:
            used.append(source)
    if not rows:
        return [], "", ""
    names = "; ".join(f"{t.title} ({t.label}, {t.cell_examples} examples per cell)" for t in used)
    heading = f"{paper.marker[0].upper()}{paper.marker[1:]}: {names}"
    missing = any(c.text == "—" for row in rows for c in row[n_label_columns:])
    caption = (f" Rows marked (paper) are {paper.marker}: the paper's means as it prints them (its precision and "
               f"scale), with no interval and no rank mark. Non-finite values in the paper's means: "
               f"{paper.non_finite[0].lower()}{paper.non_finite[1:]}" + (" —: not in the paper." if missing else ""))
    return rows, heading, caption


def model_table(data: ReportData, reported: PaperNumbers | None = None) -> Table:
    """Model x ten metrics: mean [95% CI], best / second-best per metric marked; `reported`: the paper's
    numbers, added below the runs (only for runs comparable with them, report/paper.py)."""
    t = data.table
    n = len(t.example_ids)
    columns = []
    for k, metric in enumerate(t.metrics):
        scale = display_scale(metric)
        decimals = column_decimals(data.overall.mean[:, k], metric)
        marks = marks_for(data.overall.mean[:, k], metric, data.ranked & ~t.skipped[:, k], decimals)
        columns.append([with_seed_std(value_cell(data.overall.mean[m, k], data.overall.lo[m, k],
                                                 data.overall.hi[m, k], int(data.overall.n_finite[m, k]), n, decimals,
                                                 marks[m], bool(t.skipped[m, k]), scale=scale),
                                      data, m, k, decimals) for m in range(len(t.models))])
    rows = tuple((Cell(model),) + tuple(col[m] for col in columns) for m, model in enumerate(t.models))
    paper_rows, heading, paper_note = reported_rows(reported, "model", [(m, None) for m in t.metrics])
    caption = (f"Means over the {n} evaluation examples, 95% percentile bootstrap interval below "
               f"({data.resamples:,} resamples over examples); non-finite measurements are left out and n= gives "
               f"the finite count where there were some. Arrows give the better direction. {MARKS_NOTE}"
               + scale_note(t.metrics) + _unranked_note(data) + samples_note(data) + paper_note)
    return Table("model_metrics", "Model comparison", caption, ("Model",) + tuple(metric_label(m) for m in t.metrics),
                 ("",) + tuple(metric_arrow(m) for m in t.metrics), rows + tuple(paper_rows),
                 groups=metric_groups(t.metrics), row_breaks=(len(rows),) if paper_rows else (),
                 blocks=((len(rows), heading),) if paper_rows else ())


def grouping(data: ReportData, by: str):
    """(per-example labels, group ids in display order, Intervals (M, G, K), label function) for 'task' or
    'partition'."""
    t = data.table
    if by == "task":
        return t.tasks, data.tasks, data.by_task, task_label
    if by == "partition":
        return t.partitions, data.partitions, data.by_partition, partition_label
    raise ValueError(f"unknown grouping {by!r}; use 'task' or 'partition'")


#: grouping ('task' or 'partition') -> (its word in captions, the CSV file of its per-group means)
GROUP_WORDS = {"task": ("task", "by_task.csv"),
                "partition": ("evaluation partition", "by_partition.csv")}
#: the caption sentence that explains the evaluation partitions' labels
PARTITION_NOTE = ("ID: training scenes and objects; Scene, Object, Both: held-out scenes, objects, or both.")


def breakdown_table(data: ReportData, by: str, metrics: tuple[str, ...] | None = None,
                    reported: PaperNumbers | None = None) -> Table:
    """Model x (metric, group) for a few metrics (default the headline ATE-3D and SSIM), as the paper's task
    and partition tables: mean [95% CI] per cell, best / second-best within each group; `reported`: the
    paper's numbers by that grouping, added below the runs."""
    t = data.table
    labels, groups, iv, label = grouping(data, by)
    metrics = metrics or headline_metrics(t.metrics)
    counts = [int(np.sum(labels == g)) for g in groups]
    columns, header, spans = [], [], []
    for metric in metrics:
        k = t.metric_index(metric)
        decimals = column_decimals(iv.mean[:, :, k], metric)
        for g in range(len(groups)):
            marks = marks_for(iv.mean[:, g, k], metric, data.ranked & ~t.skipped[:, k], decimals)
            columns.append([value_cell(iv.mean[m, g, k], iv.lo[m, g, k], iv.hi[m, g, k], int(iv.n_finite[m, g, k]),
                                       counts[g], decimals, marks[m], bool(t.skipped[m, k]),
                                       scale=display_scale(metric)) for m in range(len(t.models))])
        header += [label(g) for g in groups]
        spans.append((f"{metric_label(metric)}{ARROW_TEXT[metric_arrow(metric)]}", len(groups)))
    rows = tuple((Cell(model),) + tuple(col[m] for col in columns) for m, model in enumerate(t.models))
    paper_rows, heading, paper_note = reported_rows(reported, by, [(m, g) for m in metrics for g in groups])
    word, csv_name = GROUP_WORDS[by]
    names = " and ".join(METRICS[m].display_name for m in metrics)
    sizes = ", ".join(f"{label(g)} {c}" for g, c in zip(groups, counts))
    caption = (f"{names} by {word}: the mean over that {word}'s examples ({sizes}) with its 95% bootstrap interval. "
               + (PARTITION_NOTE + " " if by == "partition" else "") + MARKS_NOTE
               + f" Every measurement by {word} is in the table below and in {csv_name}." + scale_note(metrics)
               + paper_note)
    return Table(f"by_{by}", f"By {word}", caption, ("Model",) + tuple(header), ("",) * (1 + len(header)),
                 rows + tuple(paper_rows), groups=tuple(spans), row_breaks=(len(rows),) if paper_rows else (),
                 blocks=((len(rows), heading),) if paper_rows else ())


def all_metrics_table(data: ReportData, by: str) -> Table:
    """(group, model) x every metric: means only (intervals in the CSV), marks within each group."""
    t = data.table
    labels, groups, iv, label = grouping(data, by)
    decimals = [column_decimals(iv.mean[:, :, k], metric) for k, metric in enumerate(t.metrics)]
    rows, breaks = [], []
    for g, group in enumerate(groups):
        n = int(np.sum(labels == group))
        breaks.append(len(rows))
        marks = [marks_for(iv.mean[:, g, k], metric, data.ranked & ~t.skipped[:, k], decimals[k])
                 for k, metric in enumerate(t.metrics)]
        for m, model in enumerate(t.models):
            cells = tuple(value_cell(iv.mean[m, g, k], iv.lo[m, g, k], iv.hi[m, g, k], int(iv.n_finite[m, g, k]), n,
                                     decimals[k], marks[k][m], bool(t.skipped[m, k]), with_interval=False,
                                     scale=display_scale(metric))
                          for k, metric in enumerate(t.metrics))
            rows.append((Cell(f"{label(group)} ({n})" if m == 0 else ""), Cell(model)) + cells)
    word, csv_name = GROUP_WORDS[by]
    caption = (f"Every measurement by {word} (examples in parentheses), means only; the 95% intervals are in "
               f"{csv_name}. " + (PARTITION_NOTE + " " if by == "partition" else "") + MARKS_NOTE
               + scale_note(t.metrics))
    return Table(f"all_by_{by}", f"All measurements by {word}", caption,
                 (word.split()[-1].capitalize(), "Model") + tuple(metric_label(m) for m in t.metrics),
                 ("", "") + tuple(metric_arrow(m) for m in t.metrics), tuple(rows), n_label_columns=2,
                 row_breaks=tuple(breaks[1:]), groups=metric_groups(t.metrics))


def paired_table(data: ReportData) -> Table | None:
    """Two rows per model (Δ and PoI against the baseline) x every metric, each with its paired 95% CI; None for
    one run."""
    t = data.table
    if len(t.models) < 2:
        return None
    base = t.models[data.baseline]
    n = len(t.example_ids)
    d, p = data.paired_diff, data.paired_poi
    rows, breaks = [], []
    decimals = [column_decimals(np.array([d.mean[:, k], d.lo[:, k], d.hi[:, k]]), metric)
                for k, metric in enumerate(t.metrics)]
    for m in (m for m in range(len(t.models)) if m != data.baseline):
        breaks.append(len(rows))
        diffs, pois = [], []
        for k, metric in enumerate(t.metrics):
            scale, matched = display_scale(metric), int(d.n_finite[m, k])
            if t.skipped[m, k] or t.skipped[data.baseline, k]:
                diffs.append(Cell("skipped"))
                pois.append(Cell("skipped"))
                continue
            if matched == 0:
                diffs.append(Cell("n/a"))
                pois.append(Cell("n/a"))
                continue
            note = f"n={matched}" if matched < n else ""
            diff_sig = "significant" if (d.lo[m, k] > 0 or d.hi[m, k] < 0) else ""
            poi_sig = "significant" if (p.lo[m, k] > 0.5 or p.hi[m, k] < 0.5) else ""
            diffs.append(Cell(fmt(d.mean[m, k] * scale, decimals[k], signed=True),
                              interval_text(d.lo[m, k] * scale, d.hi[m, k] * scale, decimals[k], signed=True),
                              note, diff_sig))
            pois.append(Cell(fmt(p.mean[m, k], 2), interval_text(p.lo[m, k], p.hi[m, k], 2), "", poi_sig,
                             shade=float(p.mean[m, k])))
        rows.append((Cell(t.models[m]), Cell("Δ")) + tuple(diffs))
        rows.append((Cell(""), Cell("PoI")) + tuple(pois))
    caption = (f"Paired comparisons with {base} on matched examples (choose another baseline with --baseline NAME). "
               f"Δ: mean of (model − {base}); PoI: the probability of improvement, the fraction of examples on "
               f"which the model is better than {base}, ties counting one half (shaded blue above 0.5, red below). "
               f"Each has a paired 95% bootstrap interval ({data.resamples:,} resamples); bold entries have an "
               "interval that excludes 0 (Δ) or 0.5 (PoI). The arrows say which sign of Δ is better; n= counts "
               "the examples finite for both where some were not." + scale_note(t.metrics))
    return Table("paired_changes", f"Paired comparisons with {base}", caption,
                 ("Model", "") + tuple(metric_label(m) for m in t.metrics),
                 ("", "") + tuple(metric_arrow(m) for m in t.metrics), tuple(rows), n_label_columns=2,
                 groups=metric_groups(t.metrics), row_breaks=tuple(breaks[1:]))


def poi_table(data: ReportData, metric: str) -> Table | None:
    """The (M, M) matched probability-of-improvement matrix for one metric, models ordered best first, as in the
    paper's figure; None with one model or when no model has the metric."""
    t = data.table
    k = t.metric_index(metric)
    if len(t.models) < 2 or len(data.poi_matrices) <= k or t.skipped[:, k].all():
        return None
    pm = data.poi_matrices[k]
    order = best_first_order(data.overall.mean[:, k], METRICS[metric].higher_is_better)
    rows = []
    for i in order:
        cells = []
        for j in order:
            est = pm.estimate[i, j]
            if i == j:
                cells.append(Cell("·"))
            elif not math.isfinite(est):
                cells.append(Cell("n/a"))
            else:
                cells.append(Cell(fmt(est, 2), mark="significant" if pm.significant[i, j] else "", shade=float(est)))
        rows.append((Cell(t.models[i]),) + tuple(cells))
    name = METRICS[metric].display_name
    caption = (f"{name}: the probability that the row model is better than the column model on the same example "
               f"(ties count one half), over the examples finite for both. Rows and columns are ordered by the "
               f"model mean, best first; bold entries have a paired 95% bootstrap interval ({data.resamples:,} "
               "resamples) that excludes 0.5 (on the HTML page, cells shade blue above 0.5 and red below). Every "
               "measurement's matrix is in poi_matrix.csv.")
    return Table(f"poi_{metric}", f"{name}{ARROW_TEXT[metric_arrow(metric)]}: probability of improvement", caption,
                 ("Row beats column",) + tuple(t.models[j] for j in order), ("",) * (1 + len(order)), tuple(rows),
                 vertical_header=True)


# ------------------------------------------------------------- several samples, envelope, power


def samples_text(fewest: int, most: int) -> str:
    """Samples per example of one run: '4', or '2-4' where examples differ."""
    return f"{fewest}" if fewest == most else f"{fewest}-{most}"


def with_seed_std(cell: Cell, data: ReportData, m: int, k: int, decimals: int) -> Cell:
    """`cell` (run m's mean of metric k) as 'mean ± seed std' when the run has several samples per example."""
    s = data.samples
    if s is None or not s.several(m) or cell.text in ("skipped", "n/a") or not math.isfinite(s.seed_std[m, k]):
        return cell
    std = s.seed_std[m, k] * display_scale(data.table.metrics[k])
    return replace(cell, text=f"{cell.text} ± {fmt(std, std_decimals(std, decimals))}")


def std_decimals(std: float, decimals: int) -> int:
    """Decimals for a seed std beside a mean printed at `decimals`: as many, or more so that a std below the mean's
    last digit still shows one significant digit (at most 6)."""
    if not (math.isfinite(std) and std > 0):
        return decimals
    return max(decimals, min(6, -math.floor(math.log10(std))))


def samples_note(data: ReportData) -> str:
    """The model table's caption sentence on several samples per example ("" when every run has one)."""
    s = data.samples
    if s is None:
        return ""
    counts = "; ".join(f"{model} {samples_text(*s.samples[m])}" for m, model in enumerate(data.table.models))
    return (f" Samples per example: {counts}. An example counts once, with the mean of its samples; the "
            "interval resamples examples, each keeping its samples. ± is the seed std: the standard deviation "
            "(ddof 1) over sample indices k of the mean over examples of sample k, the mean ± std over runs that "
            "Physics-IQ reports. The best of K samples is in a table of its own and never here.")


def best_of_k_table(data: ReportData) -> Table | None:
    """Runs with several samples x every metric: the mean over examples of each example's best sample, with its
    95% interval; None when every run has one sample per example."""
    s, t = data.samples, data.table
    if s is None:
        return None
    n = len(t.example_ids)
    shown = [m for m in range(len(t.models)) if s.several(m)]
    columns = []
    for k, metric in enumerate(t.metrics):
        decimals = column_decimals(data.overall.mean[:, k], metric)
        columns.append([value_cell(s.best_mean[m, k], s.best_lo[m, k], s.best_hi[m, k], int(s.best_n[m, k]), n,
                                   decimals, skipped=bool(t.skipped[m, k]), scale=display_scale(metric))
                        for m in shown])
    rows = tuple((Cell(t.models[m]), Cell(samples_text(*s.samples[m]))) + tuple(col[i] for col in columns)
                 for i, m in enumerate(shown))
    caption = ("Best of K, optimistic by construction and not the headline: for each example, its best sample (the "
               "highest where ↑ is better, the lowest where ↓), averaged over the examples, with its 95% "
               f"percentile bootstrap interval over examples ({data.resamples:,} resamples). Choosing the best "
               "sample needs the reference, which a model does not have; the model comparison (each example's "
               "sample mean) is the score. K: samples per example. Also in samples.csv."
               + scale_note(t.metrics))
    return Table("best_of_k", "Best of K samples per example (optimistic; not the headline)", caption,
                 ("Model", "K") + tuple(metric_label(m) for m in t.metrics),
                 ("", "") + tuple(metric_arrow(m) for m in t.metrics), rows, n_label_columns=2,
                 groups=metric_groups(t.metrics))


def _envelope_words(data: ReportData) -> str:
    """The envelope(s) the runs were scored against, in a few words."""
    env = data.envelope
    blocks = [b for b in env.blocks if b is not None]
    twins = sorted({str(b.get("twins", "?")) for b in blocks})
    geometry = {bool(b.get("geometry_only")) for b in blocks}
    kind = ("geometry-only twins (no rendering)" if geometry == {True} else "rendered twins" if geometry == {False}
            else "twins, geometry-only for some runs")
    return f"{' or '.join(twins)} {kind} per example, from {'; '.join(env.sources) or 'an unrecorded folder'}"


def envelope_table(data: ReportData) -> Table | None:
    """Model x (metric: mean, share inside the envelope, mean excess) for the measurements the envelope covers;
    None when no run was scored against an envelope."""
    env, t = data.envelope, data.table
    if env is None or not env.metrics:
        return None
    n = len(t.example_ids)
    columns = []
    for metric in env.metrics:
        k, scale = t.metric_index(metric), display_scale(metric)
        decimals = column_decimals(data.overall.mean[:, k], metric)
        excess_decimals = column_decimals(env.excess[:, k], metric)
        means, inside, excess = [], [], []
        for m in range(len(t.models)):
            means.append(with_seed_std(value_cell(data.overall.mean[m, k], data.overall.lo[m, k],
                                                  data.overall.hi[m, k], int(data.overall.n_finite[m, k]), n,
                                                  decimals, skipped=bool(t.skipped[m, k]), with_interval=False,
                                                  scale=scale), data, m, k, decimals))
            counted = int(env.n[m, k])
            if not env.has(m) or counted == 0:
                inside.append(Cell("—"))
                excess.append(Cell("—"))
                continue
            note = f"n={counted}" if counted < n else ""
            inside.append(Cell(f"{100 * env.inside[m, k]:.0f}%", note=note))
            excess.append(Cell(fmt(env.excess[m, k] * scale, excess_decimals)))
        columns += [means, inside, excess]
    rows = tuple((Cell(model),) + tuple(col[m] for col in columns) for m, model in enumerate(t.models))
    header = ("Model",) + tuple(f"{metric_label(m)} {part}" for m in env.metrics for part in ("mean", "inside",
                                                                                               "excess"))
    different = (f" The runs were scored against different envelopes ({'; '.join(env.sources)}), so their shares "
                 "are not comparable." if len(env.sources) > 1 else "")
    caption = (f"Each run against the physical envelope: {_envelope_words(data)}. A twin is the reference "
               "re-simulated with its initial state and materials perturbed within what one frame cannot resolve "
               "(configs/envelope.yaml), scored against the reference like a model. Excess: the mean over examples "
               "of how far the run's value (the mean of its samples) lies beyond the envelope on the worse side, "
               "max(0, value − q95) where ↓ is better and max(0, q05 − value) where ↑ is. Inside: the share of "
               "examples with no excess, so a value better than every twin counts as inside. Mean: the "
               "run's score as in the model comparison. —: the run was not scored against an envelope "
               "(`rigidbench evaluate --envelope ENV`). By task and partition: envelope.csv." + different
               + envelope_figure_note(data) + scale_note(env.metrics))
    arrows = ("",) + tuple(a for m in env.metrics for a in (metric_arrow(m), "up", "down"))
    return Table("envelope", "Inside the physical envelope", caption, header, arrows, rows)


def envelope_figure_note(data: ReportData) -> str:
    """Why the envelope figure is missing for the chosen measurement ("" when it is drawn)."""
    return (" " + envelope_metric_note(data.envelope, data.envelope_metric)).rstrip()


def envelope_widths(data: ReportData) -> tuple[list[str], dict[str, dict]]:
    """(tasks in display order, task -> metric -> width) from the first envelope block with widths."""
    widths = next((b.get("widths") for b in data.envelope.blocks if b is not None and isinstance(b.get("widths"),
                                                                                                  dict)), None) or {}
    widths = {str(task): row for task, row in widths.items() if isinstance(row, dict)}
    order = [g for g in TASK_ORDER if g in widths] + sorted(set(widths) - set(TASK_ORDER))
    return order, widths


def envelope_widths_table(data: ReportData) -> Table | None:
    """Task x envelope metric: the envelope's median width (q95 − q05) over the task's examples; None without."""
    env = data.envelope
    if env is None or not env.metrics:
        return None
    tasks, widths = envelope_widths(data)
    if not tasks:
        return None
    cells = {metric: [finite(widths[task].get(metric)) for task in tasks] for metric in env.metrics}
    decimals = {metric: column_decimals(np.array(values), metric) for metric, values in cells.items()}
    rows = tuple((Cell(task_label(task)),) + tuple(
        Cell(fmt(cells[metric][i] * display_scale(metric), decimals[metric])) for metric in env.metrics)
        for i, task in enumerate(tasks))
    caption = ("How much room physics leaves, by task: the median over the task's examples of the envelope's width, "
               "the twins' 95th minus 5th percentile of each measurement against the reference. A wide envelope "
               "means the outcome is sensitive to what one frame cannot pin down; a model is not asked to be "
               f"closer than that. Twins: {_envelope_words(data)}. Also in envelope_widths.csv."
               + scale_note(env.metrics))
    return Table("envelope_widths", "Envelope width by task", caption,
                 ("Task",) + tuple(metric_label(m) for m in env.metrics), ("",) * (1 + len(env.metrics)), rows)


def comparison_label(cmp: PowerComparison) -> str:
    """'alpha vs base', or 'base, doubled' for one run's own components."""
    return f"{cmp.model} vs {cmp.baseline}" if cmp.assumption == PAIRED_ASSUMPTION else f"{cmp.model}, doubled"


def power_view(data: ReportData, differences: dict[str, float] | None = None) -> Table | None:
    """(comparison, metric) x (smallest detectable difference at 100 examples x K, the difference δ, examples
    needed for δ at each K); None when every run has one sample per example."""
    if not data.power:
        return None
    t = data.table
    rows, breaks = [], []
    for cmp in data.power:
        breaks.append(len(rows))
        by_metric: dict[str, list[PowerRow]] = {}
        for row in cmp.rows:
            by_metric.setdefault(row.measurement, []).append(row)
        for i, (metric, prs) in enumerate(by_metric.items()):
            scale = display_scale(metric)
            values = np.array([r.min_detectable_difference for r in prs] + [prs[0].difference]) * scale
            decimals = decimals_for(values)
            cells = [Cell(fmt(r.min_detectable_difference * scale, decimals)) for r in prs]
            cells.append(Cell(fmt(prs[0].difference * scale, decimals)))
            cells += [Cell(f"{r.examples_needed:,}", f"({r.samples_needed:,} samples)")
                      if r.examples_needed is not None else Cell("n/a") for r in prs]
            rows.append((Cell(comparison_label(cmp) if i == 0 else ""),
                         Cell(f"{metric_label(metric)}{ARROW_TEXT[metric_arrow(metric)]}")) + tuple(cells))
    assumptions = {cmp.assumption for cmp in data.power}
    words = []
    if PAIRED_ASSUMPTION in assumptions:
        words.append("A row 'A vs B' measures σ_D² and both σ_w² on the runs A and B (B the baseline).")
    if DOUBLED_ASSUMPTION in assumptions:
        words.append("With no second run to pair with, a row 'A, doubled' assumes a second model with A's variances "
                     "and example effects independent of A's: σ_D² is twice A's between-example variance and each "
                     "σ_w² is A's. That is pessimistic when two models find the same examples hard, which makes "
                     "their per-example differences vary less.")
    given = sorted(differences or {})
    delta = (f"δ: the difference given with --power-difference for {', '.join(given)}, else "
             if given else "δ: ") + f"{100 * DEFAULT_RELATIVE_DIFFERENCE:.0f}% of the baseline's mean."
    caption = (f"How sure a comparison of two models can be: the smallest mean difference that {POWER_EXAMPLES} "
               f"examples with K samples per example of each model detect with probability {POWER_TARGET:g}, and "
               f"how many examples a difference δ needs, in a two-sided paired t-test at level {POWER_ALPHA:g} on "
               "the per-example differences of sample means. At K samples the variance of one example's "
               "difference is τ²(K) = σ_D² + (σ_w,A² + σ_w,B²) / K, σ_D² the between-example variance of the true "
               "per-example difference and σ_w² each model's within-example variance, measured on this report's "
               f"{len(t.example_ids)} examples (rigidbench.stats.power). " + " ".join(words) + " " + delta
               + " Examples needed is per model, with the samples that makes (examples x K) below. n/a: that K "
               "needs a within-example variance, which a run with one sample per example does not measure, or "
               "the difference is zero. Every number is also in power.csv." + scale_note(t.metrics))
    header = (("Comparison", "Measurement") + tuple(f"detectable at K={k}" for k in POWER_SAMPLES) + ("δ",)
              + tuple(f"examples at K={k}" for k in POWER_SAMPLES))
    groups = ((f"Smallest detectable difference, {POWER_EXAMPLES} examples", len(POWER_SAMPLES)), ("", 1),
              ("Examples needed for δ", len(POWER_SAMPLES)))
    return Table("power", "Power: examples and samples a comparison needs", caption, header, ("",) * len(header),
                 tuple(rows), n_label_columns=2, groups=groups, row_breaks=tuple(breaks[1:]))


def sample_tables(data: ReportData, differences: dict[str, float] | None = None) -> list[Table]:
    """The tables of several samples per example and of the physical envelope that apply (none for a report of
    one sample per example without an envelope)."""
    return [tb for tb in (envelope_table(data), envelope_widths_table(data), best_of_k_table(data),
                          power_view(data, differences)) if tb is not None]


def build_tables(data: ReportData, reported: PaperNumbers | None = None,
                 differences: dict[str, float] | None = None) -> list[Table]:
    """Every table of the report, in display order; `reported`: the paper's numbers to show beside the runs
    (None: the runs are not comparable with them); differences: the --power-difference values."""
    tables = [model_table(data, reported), breakdown_table(data, "task", reported=reported),
              all_metrics_table(data, "task"), breakdown_table(data, "partition", reported=reported),
              all_metrics_table(data, "partition")]
    paired = paired_table(data)
    if paired is not None:
        tables.append(paired)
    tables += [tb for tb in (poi_table(data, m) for m in headline_metrics(data.table.metrics)) if tb is not None]
    return tables + sample_tables(data, differences)


# ------------------------------------------------------------------------------------ renderers

#: a metric's better direction (``metric_arrow``) as text after its label
ARROW_TEXT = {"up": " ↑", "down": " ↓", "": ""}
_ARROW_TEX = {"up": r"$\uparrow$", "down": r"$\downarrow$", "": ""}


def _md_escape(text: str) -> str:
    return text.replace("|", "\\|")


def _md_cell(cell: Cell) -> str:
    text = _md_escape(cell.text)
    if cell.mark in ("best", "significant"):
        text = f"**{text}**"
    elif cell.mark == "second":
        text = f"<u>{text}</u>"
    parts = [text] + ([cell.detail] if cell.detail else []) + ([f"({cell.note})"] if cell.note else [])
    return " ".join(parts)


def to_markdown(table: Table) -> str:
    """GitHub-flavoured Markdown: bold best, <u>underlined</u> second-best, caption below."""
    header = [_md_escape(h) + ARROW_TEXT[a] for h, a in zip(table.header, table.arrows)]
    align = [":--"] * table.n_label_columns + ["--:"] * (len(header) - table.n_label_columns)
    lines = [f"### {table.title}", "", "| " + " | ".join(header) + " |", "| " + " | ".join(align) + " |"]
    blocks = dict(table.blocks)
    for i, row in enumerate(table.rows):
        if i in blocks:
            lines.append(f"| *{_md_escape(blocks[i])}* |" + " |" * (len(header) - 1))
        lines.append("| " + " | ".join(_md_cell(c) for c in row) + " |")
    lines += ["", table.caption, ""]
    return "\n".join(lines)


_TEX_SPECIAL = {"\\": r"\textbackslash{}", "&": r"\&", "%": r"\%", "$": r"\$", "#": r"\#", "_": r"\_",
                "{": r"\{", "}": r"\}", "~": r"\textasciitilde{}", "^": r"\textasciicircum{}",
                "×": r"$\times$", "³": r"$^3$", "−": "$-$", "Δ": r"$\Delta$", "↑": r"$\uparrow$",
                "↓": r"$\downarrow$", "·": r"$\cdot$", "—": "---", "±": r"$\pm$", "δ": r"$\delta$",
                "σ": r"$\sigma$", "τ": r"$\tau$", "²": r"$^2$"}


def tex_escape(text: str) -> str:
    """Escape LaTeX specials and map the few non-ASCII symbols the report uses to math."""
    return "".join(_TEX_SPECIAL.get(ch, ch) for ch in text)


def _tex_cell(cell: Cell) -> str:
    text = tex_escape(cell.text)
    if cell.mark in ("best", "significant"):
        text = rf"\textbf{{{text}}}"
    elif cell.mark == "second":
        text = rf"\underline{{{text}}}"
    if cell.detail:
        text += rf"\,{{\scriptsize {tex_escape(cell.detail)}}}"
    if cell.note:
        text += rf"\,{{\scriptsize ({tex_escape(cell.note)})}}"
    return text


def to_latex(table: Table) -> str:
    """A booktabs `table` environment (needs \\usepackage{booktabs,graphicx}); \\textbf best, \\underline second."""
    n_cols = len(table.header)
    spec = "l" * table.n_label_columns + "r" * (n_cols - table.n_label_columns)
    lines = [r"\begin{table}[t]", r"  \centering", r"  \footnotesize", r"  \resizebox{\linewidth}{!}{%",
             rf"  \begin{{tabular}}{{{spec}}}", r"    \toprule"]
    if table.groups:
        first = table.n_label_columns + 1
        spans, rules = [], []
        for label, width in table.groups:
            spans.append(rf"\multicolumn{{{width}}}{{c}}{{{tex_escape(label)}}}")
            rules.append(rf"\cmidrule(lr){{{first}-{first + width - 1}}}")
            first += width
        lines.append("    " + " & " * table.n_label_columns + " & ".join(spans) + r" \\")
        lines.append("    " + "".join(rules))
    lines.append("    " + " & ".join(tex_escape(h) + _ARROW_TEX[a] for h, a in zip(table.header, table.arrows))
                 + r" \\")
    lines.append(r"    \midrule")
    blocks = dict(table.blocks)
    for i, row in enumerate(table.rows):
        if i in table.row_breaks:
            lines.append(r"    \midrule")
        if i in blocks:
            lines.append(rf"    \multicolumn{{{n_cols}}}{{l}}{{\emph{{{tex_escape(blocks[i])}}}}} \\")
        lines.append("    " + " & ".join(_tex_cell(c) for c in row) + r" \\")
    lines += [r"    \bottomrule", r"  \end{tabular}%", r"  }",
              rf"  \caption{{\textbf{{{tex_escape(table.title)}.}} {tex_escape(table.caption)}}}",
              rf"  \label{{tab:{table.key.replace('_', '-')}}}", r"\end{table}", ""]
    return "\n".join(lines)


def shade_color(p: float) -> str:
    """A probability in [0, 1] as a light background: white at 0.5, blue towards 1, red towards 0 (text stays
    black on every shade)."""
    strength = min(abs(p - 0.5) * 2.0, 1.0) * 0.62
    end = (33, 102, 172) if p > 0.5 else (178, 24, 43)  # the ends of matplotlib's RdBu, as in the heatmaps
    r, g, b = (round(255 + (c - 255) * strength) for c in end)
    return f"#{r:02x}{g:02x}{b:02x}"


def _html_cell(cell: Cell, tag: str = "td") -> str:
    text = html.escape(cell.text)
    if cell.mark in ("best", "significant"):
        text = f"<strong>{text}</strong>"
    elif cell.mark == "second":
        text = f"<u>{text}</u>"
    if cell.detail:
        text += f' <span class="ci">{html.escape(cell.detail)}</span>'
    if cell.note:
        text += f' <span class="n">({html.escape(cell.note)})</span>'
    css = ' class="skipped"' if cell.text in ("skipped", "n/a") else ""
    style = f' style="background:{shade_color(cell.shade)}"' if math.isfinite(cell.shade) else ""
    return f"<{tag}{css}{style}>{text}</{tag}>"


def to_html(table: Table) -> str:
    """An HTML <table> (classes for the page's inline CSS) followed by its caption."""
    css = "results vertical" if table.vertical_header else "results"
    lines = [f'<table class="{css}" id="table-{table.key}">', "<thead>"]
    if table.groups:
        cells = [f'<th colspan="{table.n_label_columns}"></th>']
        cells += [f'<th colspan="{w}" class="group">{html.escape(label)}</th>' for label, w in table.groups]
        lines.append("<tr>" + "".join(cells) + "</tr>")
    heads = []
    for i, (h, a) in enumerate(zip(table.header, table.arrows)):
        text = html.escape(h + ARROW_TEXT[a])
        if i < table.n_label_columns:
            heads.append(f"<th class=label>{text}</th>")
        else:
            heads.append(f'<th><span class="vh">{text}</span></th>' if table.vertical_header else f"<th>{text}</th>")
    lines.append("<tr>" + "".join(heads) + "</tr>")
    lines += ["</thead>", "<tbody>"]
    blocks = dict(table.blocks)
    for i, row in enumerate(table.rows):
        if i in blocks:
            lines.append(f'<tr class="block{" break" if i in table.row_breaks else ""}">'
                         f'<th colspan="{len(table.header)}" scope="colgroup">{html.escape(blocks[i])}</th></tr>')
        css = ' class="break"' if i in table.row_breaks and i not in blocks else ""
        label_cells = "".join(f'<th scope="row">{html.escape(c.text)}</th>' for c in row[:table.n_label_columns])
        lines.append(f"<tr{css}>" + label_cells + "".join(_html_cell(c) for c in row[table.n_label_columns:])
                     + "</tr>")
    lines += ["</tbody>", "</table>", f'<p class="caption">{html.escape(table.caption)}</p>']
    return "\n".join(lines)


# ------------------------------------------------------------------------------------------ CSV


def csv_number(x) -> str:
    """Float as its shortest round-tripping repr; NaN as an empty field."""
    x = float(x)
    return repr(x) if math.isfinite(x) else ""


def write_csv(path: Path, header: list[str], rows: list[list]) -> Path:
    """Write one CSV file (header row, then ``rows``); returns ``path``."""
    with open(path, "w", newline="") as fh:
        writer = csv.writer(fh)
        writer.writerow(header)
        writer.writerows(rows)
    return path


#: the `source` column of model_metrics.csv, by_task.csv and by_partition.csv for a row of the runs
SCORED_HERE = "scored here"


def reported_csv_rows(paper: PaperNumbers | None, by: str) -> list[list]:
    """The paper's numbers by `by` as rows of model_metrics.csv ("model") or by_<by>.csv: unscaled, without
    intervals or marks, `source` = the paper's marker; none when `paper` is None."""
    rows: list[list] = []
    for source in (paper.tables_by(by) if paper is not None else ()):
        for c in source.cells():
            model = f"{c.row} (paper)"
            if by == "model":
                row = [model, c.metric, int(c.higher_is_better), csv_number(c.value), "", "", c.n_finite,
                       c.n_examples, 0, "", paper.marker]
            else:
                row = [model, c.group, c.metric, csv_number(c.value), "", "", c.n_finite, c.n_examples, "",
                       paper.marker]
            if row not in rows:  # base Wan is in the task table and again in the fine-tuning one
                rows.append(row)
    return rows


def write_csvs(data: ReportData, out_dir: Path, reported: PaperNumbers | None = None) -> list[Path]:
    """Long-form CSV files of every statistic (unscaled, full precision); `reported`: the paper's numbers to add
    to model_metrics.csv and the by-task and by-partition files. Returns the paths written."""
    t = data.table
    n = len(t.example_ids)
    hib = [METRICS[m].higher_is_better for m in t.metrics]
    paths = []
    rows = []
    for k, metric in enumerate(t.metrics):
        decimals = column_decimals(data.overall.mean[:, k], metric)
        marks = marks_for(data.overall.mean[:, k], metric, data.ranked & ~t.skipped[:, k], decimals)
        for m, model in enumerate(t.models):
            o = data.overall
            rows.append([model, metric, int(hib[k]), csv_number(o.mean[m, k]), csv_number(o.lo[m, k]),
                         csv_number(o.hi[m, k]), int(o.n_finite[m, k]), n, int(t.skipped[m, k]), marks[m],
                         SCORED_HERE])
    paths.append(write_csv(out_dir / "model_metrics.csv", ["model", "metric", "higher_is_better", "mean", "ci_low",
                                                           "ci_high", "n_finite", "n_examples", "skipped", "mark",
                                                           "source"], rows + reported_csv_rows(reported, "model")))
    for key, labels, names, iv in (("by_task", t.tasks, data.tasks, data.by_task),
                                   ("by_partition", t.partitions, data.partitions, data.by_partition)):
        rows = []
        for g, group in enumerate(names):
            n_group = int(np.sum(labels == group))
            for k, metric in enumerate(t.metrics):
                decimals = column_decimals(iv.mean[:, :, k], metric)
                marks = marks_for(iv.mean[:, g, k], metric, data.ranked & ~t.skipped[:, k], decimals)
                for m, model in enumerate(t.models):
                    rows.append([model, group, metric, csv_number(iv.mean[m, g, k]), csv_number(iv.lo[m, g, k]),
                                 csv_number(iv.hi[m, g, k]), int(iv.n_finite[m, g, k]), n_group, marks[m],
                                 SCORED_HERE])
        column = key.removeprefix("by_")
        paths.append(write_csv(out_dir / f"{key}.csv", ["model", column, "metric", "mean", "ci_low", "ci_high",
                                                        "n_finite", "n_examples", "mark", "source"],
                               rows + reported_csv_rows(reported, column)))
    if len(t.models) >= 2:
        d, p = data.paired_diff, data.paired_poi
        rows = [[t.models[m], t.models[data.baseline], metric, int(hib[k]), csv_number(d.mean[m, k]),
                 csv_number(d.lo[m, k]), csv_number(d.hi[m, k]), csv_number(p.mean[m, k]), csv_number(p.lo[m, k]),
                 csv_number(p.hi[m, k]), int(d.n_finite[m, k])]
                for m in range(len(t.models)) if m != data.baseline for k, metric in enumerate(t.metrics)]
        paths.append(write_csv(out_dir / "paired_changes.csv",
                               ["model", "baseline", "metric", "higher_is_better", "diff_mean", "diff_ci_low",
                                "diff_ci_high", "poi", "poi_ci_low", "poi_ci_high", "n_matched"], rows))
        rows = [[metric, t.models[i], t.models[j], csv_number(pm.estimate[i, j]), csv_number(pm.lo[i, j]),
                 csv_number(pm.hi[i, j]), int(pm.n_matched[i, j]), int(bool(pm.significant[i, j]))]
                for metric, pm in zip(t.metrics, data.poi_matrices)
                for i in range(len(t.models)) for j in range(len(t.models)) if i != j]
        paths.append(write_csv(out_dir / "poi_matrix.csv", ["metric", "model", "opponent", "poi", "ci_low", "ci_high",
                                                            "n_matched", "significant"], rows))
    c = data.correlation
    if c is not None:
        ci_p = c["pearson_ci"] if c["has_ci"] else (math.nan, math.nan)
        ci_s = c["spearman_ci"] if c["has_ci"] else (math.nan, math.nan)
        paths.append(write_csv(out_dir / "correlation.csv",
                               ["x", "y", "n_models", "pearson", "pearson_ci_low", "pearson_ci_high", "spearman",
                                "spearman_ci_low", "spearman_ci_high"],
                               [["ssim", "-ate3d", c["n_models"], csv_number(c["pearson"]), csv_number(ci_p[0]),
                                 csv_number(ci_p[1]), csv_number(c["spearman"]), csv_number(ci_s[0]),
                                 csv_number(ci_s[1])]]))
    return paths + write_sample_csvs(data, out_dir)


def write_sample_csvs(data: ReportData, out_dir: Path) -> list[Path]:
    """samples.csv (several samples per example), envelope.csv and envelope_widths.csv (an envelope), power.csv
    (the power table), each only when it applies. Unscaled, full precision. Returns the paths written."""
    t, paths = data.table, []
    s = data.samples
    if s is not None:
        rows = [[model, metric, int(s.samples[m, 0]), int(s.samples[m, 1]), csv_number(data.overall.mean[m, k]),
                 csv_number(data.overall.lo[m, k]), csv_number(data.overall.hi[m, k]), csv_number(s.seed_std[m, k]),
                 csv_number(s.within_std[m, k]), csv_number(s.best_mean[m, k]), csv_number(s.best_lo[m, k]),
                 csv_number(s.best_hi[m, k]), int(data.overall.n_finite[m, k])]
                for m, model in enumerate(t.models) for k, metric in enumerate(t.metrics)]
        paths.append(write_csv(out_dir / "samples.csv",
                               ["model", "metric", "samples_min", "samples_max", "mean", "ci_low", "ci_high",
                                "seed_std", "within_example_std", "best_of_k_mean", "best_of_k_ci_low",
                                "best_of_k_ci_high", "n_finite"], rows))
    env = data.envelope
    if env is not None and env.metrics:
        rows = []
        for grouping, names, (inside, excess, n) in (
                ("overall", ("all",), (env.inside[:, None], env.excess[:, None], env.n[:, None])),
                ("task", data.tasks, env.by_task), ("partition", data.partitions, env.by_partition)):
            for g, group in enumerate(names):
                for metric in env.metrics:
                    k = t.metric_index(metric)
                    rows += [[model, str(env.blocks[m].get("source", "")), grouping, group, metric,
                              csv_number(inside[m, g, k]), csv_number(excess[m, g, k]), int(n[m, g, k])]
                             for m, model in enumerate(t.models) if env.has(m)]
        paths.append(write_csv(out_dir / "envelope.csv", ["model", "envelope", "grouping", "group", "metric",
                                                          "inside", "excess", "n_examples"], rows))
        tasks, widths = envelope_widths(data)
        if tasks:
            paths.append(write_csv(out_dir / "envelope_widths.csv", ["task", "metric", "width"],
                                   [[task, metric, csv_number(finite(widths[task].get(metric)))]
                                    for task in tasks for metric in env.metrics]))
    if data.power:
        rows = [[cmp.model, cmp.baseline, cmp.assumption, r.measurement, r.samples_per_example, r.n_examples,
                 csv_number(r.difference_variance), csv_number(r.min_detectable_difference), csv_number(r.difference),
                 "" if r.examples_needed is None else r.examples_needed,
                 "" if r.samples_needed is None else r.samples_needed,
                 csv_number(cmp.components[r.measurement].between), csv_number(cmp.components[r.measurement].within_a),
                 csv_number(cmp.components[r.measurement].within_b), cmp.components[r.measurement].n_examples,
                 POWER_ALPHA, POWER_TARGET]
                for cmp in data.power for r in cmp.rows]
        paths.append(write_csv(out_dir / "power.csv",
                               ["model", "baseline", "assumption", "metric", "samples_per_example", "n_examples",
                                "difference_variance", "min_detectable_difference", "difference", "examples_needed",
                                "samples_needed", "between_variance", "within_variance_model",
                                "within_variance_baseline", "measured_examples", "alpha", "power"], rows))
    return paths


def write_tables(tables: list[Table], out_dir: Path) -> dict[str, dict[str, Path]]:
    """Write each table as <key>.md and <key>.tex. Returns key -> {'md': path, 'tex': path}."""
    written = {}
    for table in tables:
        md = out_dir / f"{table.key}.md"
        tex = out_dir / f"{table.key}.tex"
        md.write_text(to_markdown(table))
        tex.write_text(to_latex(table))
        written[table.key] = {"md": md, "tex": tex}
    return written
