"""Rows, table files (CSV and Markdown) and the figure (PNG and PDF) of the metric validation."""

from __future__ import annotations

import csv
import math
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from ..atomic import atomic_file, write_text
from ..metrics import METRICS

#: the validation's own quantities that are not metrics
EXTRA_DISPLAY = {"pixel_l2": "pixel L2", "displacement": "raw displacement"}


def display(name: str) -> str:
    """Display name of a metric (its registry entry) or of a validation quantity."""
    return METRICS[name].display_name if name in METRICS else EXTRA_DISPLAY.get(name, name)
EXPERIMENTS = {"ate3d_ray": "ATE-3D: equal 3D offsets along vs across the viewing ray",
               "bgdrift_motion": "BGDrift: coherent translation vs independent jitter (matched displacement)",
               "iddrift_swap": "IdDrift: identity swap vs gamma change, with pixel L2",
               "metric_curve": "Response curves: each metric under the failure mode meant to move it"}
CSV_FIELDS = ("experiment", "metric", "condition", "mode", "severity", "severity_unit", "mean", "se", "n", "note")


@dataclass(frozen=True)
class Row:
    """One point of a response curve: mean and standard error over examples or trials (n finite values)."""

    experiment: str
    metric: str
    condition: str
    mode: str
    severity: float
    severity_unit: str
    mean: float
    se: float
    n: int
    note: str = ""


def mean_se(values: np.ndarray) -> tuple[float, float, int]:
    """values: (K,) float. Returns mean, standard error (std ddof=1 / sqrt(n); NaN if n < 2) and n of finite values."""
    v = np.asarray(values, np.float64)
    v = v[np.isfinite(v)]
    if v.size == 0:
        return float("nan"), float("nan"), 0
    se = float(v.std(ddof=1) / math.sqrt(v.size)) if v.size > 1 else float("nan")
    return float(v.mean()), se, int(v.size)


def curve_rows(experiment: str, metric: str, condition: str, mode: str, severities: np.ndarray, unit: str,
               values: np.ndarray, note: str = "") -> list[Row]:
    """values: (S, K) float, K examples or trials per severity. Returns one Row per severity."""
    return [Row(experiment, metric, condition, mode, float(s), unit, *mean_se(values[i]), note)
            for i, s in enumerate(severities)]


def skipped_rows(experiment: str, metric: str, condition: str, mode: str, severities: np.ndarray, unit: str,
                 reason: str) -> list[Row]:
    """Rows of NaN with the skip reason, one per severity (so the table shows what was not measured)."""
    return [Row(experiment, metric, condition, mode, float(s), unit, float("nan"), float("nan"), 0,
                f"skipped: {reason}") for s in severities]


def select(rows: list[Row], **match) -> list[Row]:
    """Rows whose fields equal every keyword given, in severity order."""
    return sorted((r for r in rows if all(getattr(r, k) == v for k, v in match.items())), key=lambda r: r.severity)


def _fmt(x: float) -> str:
    if not math.isfinite(x):
        return ""
    return f"{x:.6g}"


def write_csv(rows: list[Row], path: Path) -> Path:
    """All rows as CSV (empty cells for NaN)."""
    with atomic_file(path) as tmp, open(tmp, "w", newline="") as fh:
        writer = csv.DictWriter(fh, fieldnames=CSV_FIELDS)
        writer.writeheader()
        for row in rows:
            d = asdict(row)
            writer.writerow({k: (_fmt(v) if isinstance(v, float) else v) for k, v in d.items()})
    return path


def _cell(row: Row | None) -> str:
    if row is None:
        return ""
    if row.n == 0:
        return "skipped"
    if math.isfinite(row.se):
        return f"{row.mean:.4g} ± {row.se:.2g}"
    return f"{row.mean:.4g}"


def experiment_table(rows: list[Row], experiment: str) -> list[str]:
    """Markdown lines: one line per severity, one column per (metric, condition) of the experiment."""
    mine = [r for r in rows if r.experiment == experiment]
    if not mine:
        return []
    columns = list(dict.fromkeys((r.metric, r.condition, r.mode) for r in mine))
    severities = sorted({r.severity for r in mine})
    unit = mine[0].severity_unit
    head = [f"{unit}"] + [f"{display(m)} {c}" + (f" ({mode})" if mode and experiment == "metric_curve"
                                                         else "") for m, c, mode in columns]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    index = {(r.metric, r.condition, r.mode, r.severity): r for r in mine}
    for s in severities:
        lines.append("| " + " | ".join([f"{s:.3g}"] + [_cell(index.get((m, c, mode, s))) for m, c, mode in columns])
                     + " |")
    return lines


def write_markdown(rows: list[Row], summary: dict, path: Path) -> Path:
    """The summary, one table per experiment, the mode behind each curve and the skipped measurements."""
    lines = ["# Metric validation", "", f"Examples: {', '.join(summary['examples']) or 'none'}", ""]
    lines += ["## Summary", ""] + [f"- {line}" for line in summary["lines"]] + [""]
    for experiment, title in EXPERIMENTS.items():
        table = experiment_table(rows, experiment)
        if table:
            lines += [f"## {title}", ""] + table + [""]
    curves = summary.get("curves", [])
    if curves:
        lines += ["## Which failure mode drove each curve", "", "| metric | failure mode | role | note |",
                  "|---|---|---|---|"]
        lines += [f"| {display(c['metric'])} | {c['mode']} | {c['role']} | {c['note']} |"
                  for c in curves] + [""]
    if summary["skipped"]:
        lines += ["## Skipped", ""] + [f"- {name}: {reason}" for name, reason in summary["skipped"].items()] + [""]
    write_text(path, "\n".join(lines))
    return path


def _plot_curves(ax, curves: list[tuple[str, list[Row]]], xlabel: str, ylabel: str, title: str) -> None:
    drawn = False
    for label, rs in curves:
        rs = [r for r in rs if r.n > 0]
        if not rs:
            continue
        x = np.array([r.severity for r in rs])
        y = np.array([r.mean for r in rs])
        se = np.nan_to_num(np.array([r.se for r in rs]))
        line, = ax.plot(x, y, marker="o", ms=3, label=label)
        ax.fill_between(x, y - se, y + se, color=line.get_color(), alpha=0.2, linewidth=0)
        drawn = True
    ax.set_title(title, fontsize=9)
    ax.set_xlabel(xlabel, fontsize=8)
    ax.set_ylabel(ylabel, fontsize=8)
    ax.tick_params(labelsize=7)
    if drawn:
        ax.legend(fontsize=7)


def _skip_panel(ax, title: str, reason: str) -> None:
    import textwrap

    ax.set_title(title, fontsize=9)
    ax.text(0.5, 0.5, "skipped:\n" + textwrap.fill(reason, 40), ha="center", va="center", fontsize=7,
            transform=ax.transAxes, wrap=True)
    ax.set_xticks([])
    ax.set_yticks([])


def write_figure(rows: list[Row], skipped: dict[str, str], out_stem: Path) -> tuple[Path, Path]:
    """Top row: the three controlled perturbations (ATE-3D and 2D ATE along/across, BGDrift
    translation/jitter, IdDrift and pixel L2 swap/gamma); then one panel per metric curve.
    Shading is one standard error. Returns the PNG and PDF paths."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(3, 5, figsize=(20, 11), constrained_layout=True)
    top = axes[0]
    _plot_curves(top[0], [(c, select(rows, experiment="ate3d_ray", metric="ate3d", condition=c))
                          for c in ("along", "across")], "3D offset (m)", "ATE-3D", "ATE-3D: along vs across the ray")
    _plot_curves(top[1], [(c, select(rows, experiment="ate3d_ray", metric="ate", condition=c))
                          for c in ("along", "across")], "3D offset (m)", "2D ATE", "2D ATE: along vs across the ray")
    _plot_curves(top[2], [(c, select(rows, experiment="bgdrift_motion", metric="bgdrift", condition=c))
                          for c in ("translation", "jitter")], "mean displacement (px)", "BGDrift",
                 "BGDrift: translation vs jitter")
    id_rows = [r for r in rows if r.experiment == "iddrift_swap" and r.metric == "iddrift" and r.n > 0]
    if id_rows:
        _plot_curves(top[3], [(c, select(rows, experiment="iddrift_swap", metric="iddrift", condition=c))
                              for c in ("swap", "gamma")], "severity q", "IdDrift", "IdDrift: swap vs gamma")
    else:
        _skip_panel(top[3], "IdDrift: swap vs gamma", skipped.get("iddrift", "no feature network"))
    _plot_curves(top[4], [(c, select(rows, experiment="iddrift_swap", metric="pixel_l2", condition=c))
                          for c in ("swap", "gamma")], "severity q", "pixel L2 (RMS, [0,1])", "pixel L2: swap vs gamma")
    for ax, metric in zip(axes[1:].ravel(), METRICS):
        mine = [r for r in rows if r.experiment == "metric_curve" and r.metric == metric]
        title = display(metric)
        if not mine or all(r.n == 0 for r in mine):
            reason = next((r.note for r in mine if r.note), skipped.get(metric, "no usable failure mode"))
            _skip_panel(ax, title, reason.removeprefix("skipped: "))
            continue
        modes = list(dict.fromkeys(r.mode for r in mine))
        _plot_curves(ax, [(m, select(rows, experiment="metric_curve", metric=metric, mode=m)) for m in modes],
                     "severity", display(metric), f"{title} ({', '.join(modes)})")
    png, pdf = out_stem.with_suffix(".png"), out_stem.with_suffix(".pdf")
    fig.savefig(png, dpi=120)
    fig.savefig(pdf)
    plt.close(fig)
    return png, pdf
