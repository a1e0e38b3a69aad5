"""The report's figures as PNG and PDF (matplotlib `Figure` objects, no pyplot state, Agg rendering).

- ssim_vs_ate3d: model means on SSIM and ATE-3D (ATE-3D axis reversed) with the correlation of SSIM
  and negative ATE-3D across models in the title (paper figure "Model and task results", left);
- ate3d_by_task: one horizontal bar per model within each task, with 95% intervals (right panel);
- metric_intervals: mean and 95% interval of every model on all ten measurements;
- poi_heatmaps: probability that the row model beats the column model on matched examples, one
  panel per measurement, rows and columns ordered by model mean, best first; bold entries have an
  interval excluding 0.5;
- envelope_<metric>: where a run was scored against a physical envelope, each example's envelope (the
  twins' 5th to 95th percentile and median) with every model's samples and sample mean on it, for one
  measurement (`build_report(envelope_metric=...)`, ATE-3D by default).
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from rigidbench.metrics import METRICS
from rigidbench.report.analysis import ReportData, best_first_order, task_label
from rigidbench.report.tables import display_scale, metric_label

log = logging.getLogger(__name__)

DPI = 150


@dataclass(frozen=True)
class FigureFile:
    """One written figure: `png` and `pdf` paths, with the title and caption the HTML shows."""

    key: str
    title: str
    caption: str
    png: Path
    pdf: Path
    width_in: float


def new_figure(width_in: float, height_in: float):
    """A matplotlib Figure of this size with the constrained layout, on an Agg canvas (no pyplot state)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(width_in, height_in), layout="constrained")
    FigureCanvasAgg(fig)  # an Agg canvas, so text can be measured before saving (place_labels)
    return fig


def save_figure(fig, out_dir: Path, key: str, title: str, caption: str) -> FigureFile:
    """Write ``fig`` as ``out_dir/<key>.png`` (at DPI) and ``.pdf`` (no creation date, so reruns match)."""
    png, pdf = out_dir / f"{key}.png", out_dir / f"{key}.pdf"
    fig.savefig(png, dpi=DPI)
    # The constrained layout is resolution-independent: keep the one just computed for the PDF
    # instead of solving it again (the solve is most of the drawing time).
    fig.set_layout_engine("none")
    fig.savefig(pdf, metadata={"CreationDate": None})
    return FigureFile(key, title, caption, png, pdf, float(fig.get_figwidth()))


def model_colors(n_models: int) -> list:
    """One distinct colour per model, the same in every figure."""
    import matplotlib

    cmap = matplotlib.colormaps["tab10" if n_models <= 10 else "tab20"]
    return [cmap(i % cmap.N) for i in range(n_models)]


def _errors(mean: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """mean, lo, hi: (M,). Returns (2, M) non-negative error-bar lengths, 0 where the interval is undefined."""
    err = np.stack([mean - lo, hi - mean])
    return np.where(np.isfinite(err), np.maximum(err, 0.0), 0.0)


def correlation_title(corr: dict | None) -> str:
    """Figure title text for the SSIM / negative ATE-3D correlation across model means."""
    if corr is None:
        return "correlation needs at least 2 models with finite SSIM and ATE-3D"

    def one(name: str, key: str) -> str:
        value = corr[key]
        if not math.isfinite(value):
            return f"{name} undefined"
        text = f"{name} = {value:+.2f}"
        lo, hi = corr[f"{key}_ci"]
        if corr.get("has_ci") and math.isfinite(lo) and math.isfinite(hi):
            text += f" [{lo:+.2f}, {hi:+.2f}]"
        return text

    suffix = "" if corr.get("has_ci") else " (no interval with < 3 models)"
    return (f"SSIM vs −ATE-3D across {corr['n_models']} model means\n{one('Pearson r', 'pearson')}, "
            f"{one('Spearman ρ', 'spearman')}{suffix}")


LABEL_OFFSETS_PT = [(5, 5)] + [(5, dy) for k in range(1, 8) for dy in (5 - 12 * k, 5 + 12 * k)] \
    + [(-5, 5 - 12 * k) for k in range(-3, 4)]  # nearest first; the last ones sit left of the point


def place_labels(ax, points, fontsize: float = 8) -> list:
    """Name each point ``(x, y, text)`` beside it without covering another name: each label takes the
    first offset of LABEL_OFFSETS_PT (points, right of and then above or below its point, then to its left)
    whose box overlaps none placed before, top points first; if none is free it keeps the nearest. Call
    after the axes' limits are final. Returns the annotations."""
    fig = ax.figure
    fig.canvas.draw()  # lays out the figure, so the boxes are measured where they will be drawn
    renderer = fig.canvas.get_renderer()
    placed, out = [], []
    for x, y, text in sorted(points, key=lambda p: -p[1]):
        for dx, dy in LABEL_OFFSETS_PT:
            label = ax.annotate(text, (x, y), textcoords="offset points", xytext=(dx, dy), fontsize=fontsize,
                                ha="left" if dx >= 0 else "right", va="bottom")
            box = label.get_window_extent(renderer).expanded(1.05, 1.1)
            if not any(box.overlaps(b) for b in placed):
                break
            label.remove()
        else:
            dx, dy = LABEL_OFFSETS_PT[0]
            label = ax.annotate(text, (x, y), textcoords="offset points", xytext=(dx, dy), fontsize=fontsize)
            box = label.get_window_extent(renderer)
        placed.append(box)
        out.append(label)
    return out


def ssim_vs_ate3d(data: ReportData, out_dir: Path) -> FigureFile:
    """Scatter of model means, SSIM against ATE-3D with the ATE-3D axis reversed."""
    t = data.table
    ks, ka = t.metric_index("ssim"), t.metric_index("ate3d")
    o = data.overall
    colors = model_colors(len(t.models))
    fig = new_figure(7.0, 5.0)
    ax = fig.add_subplot()
    labelled = []
    for m, model in enumerate(t.models):
        x, y = o.mean[m, ka], o.mean[m, ks]
        if not (math.isfinite(x) and math.isfinite(y)):
            continue
        xerr = _errors(o.mean[m:m + 1, ka], o.lo[m:m + 1, ka], o.hi[m:m + 1, ka])
        yerr = _errors(o.mean[m:m + 1, ks], o.lo[m:m + 1, ks], o.hi[m:m + 1, ks])
        ax.errorbar([x], [y], xerr=xerr, yerr=yerr, fmt="o", color=colors[m], capsize=3, label=model)
        labelled.append((x, y, model))
    ax.invert_xaxis()
    ax.set_xlabel("ATE-3D ↓ (axis reversed: better to the right)")
    ax.set_ylabel("SSIM ↑")
    ax.grid(alpha=0.3)
    ax.set_title(correlation_title(data.correlation), fontsize=9)
    place_labels(ax, labelled)
    caption = ("Model means with 95% bootstrap intervals over examples. The ATE-3D axis is reversed, and the "
               "correlation is computed against negative ATE-3D; its interval resamples models "
               f"({data.resamples:,} resamples, shown with at least 3 models).")
    return save_figure(fig, out_dir, "ssim_vs_ate3d", "SSIM against ATE-3D", caption)


def ate3d_by_task(data: ReportData, out_dir: Path, metric: str = "ate3d") -> FigureFile:
    """Horizontal bars: one per model within each task, mean with 95% interval."""
    t = data.table
    k = t.metric_index(metric)
    n_models, n_tasks = len(t.models), len(data.tasks)
    colors = model_colors(n_models)
    fig = new_figure(7.5, 1.2 + 0.16 * n_tasks * (n_models + 1))
    ax = fig.add_subplot()
    iv = data.by_task
    for m, model in enumerate(t.models):
        y = np.arange(n_tasks) * (n_models + 1) + m
        mean = iv.mean[m, :, k]
        ok = np.isfinite(mean)
        ax.barh(y[ok], mean[ok], xerr=_errors(mean, iv.lo[m, :, k], iv.hi[m, :, k])[:, ok], color=colors[m],
                height=0.85, capsize=2, label=model, error_kw={"elinewidth": 0.8})
    ax.set_yticks(np.arange(n_tasks) * (n_models + 1) + (n_models - 1) / 2, [task_label(x) for x in data.tasks])
    ax.invert_yaxis()
    name = METRICS[metric].display_name
    ax.set_xlabel(f"{name} {'↑' if METRICS[metric].higher_is_better else '↓'}")
    ax.grid(axis="x", alpha=0.3)
    ax.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.01, 1.0), frameon=False)
    caption = (f"Mean {name} for each model and task with 95% bootstrap intervals; bars within each task follow "
               "the order of the key.")
    return save_figure(fig, out_dir, f"{metric}_by_task", f"{name} by task", caption)


def metric_intervals(data: ReportData, out_dir: Path) -> FigureFile:
    """One panel per measurement: every model's mean with its 95% interval, models in a fixed order."""
    t = data.table
    n_models, n_metrics = len(t.models), len(t.metrics)
    ncols = min(5, n_metrics)
    nrows = math.ceil(n_metrics / ncols)
    colors = model_colors(n_models)
    fig = new_figure(2.6 * ncols + 1.2, nrows * (0.9 + 0.28 * n_models))
    axes = fig.subplots(nrows, ncols, squeeze=False, sharey=True)
    from matplotlib.ticker import MaxNLocator

    o = data.overall
    y = np.arange(n_models)
    for k, metric in enumerate(t.metrics):
        ax = axes.flat[k]
        scale = display_scale(metric)
        mean = o.mean[:, k] * scale
        err = _errors(mean, o.lo[:, k] * scale, o.hi[:, k] * scale)
        for m in range(n_models):
            if math.isfinite(mean[m]):
                ax.errorbar([mean[m]], [y[m]], xerr=err[:, m:m + 1], fmt="o", color=colors[m], capsize=3, ms=4)
        if not np.isfinite(mean).any():
            ax.text(0.5, 0.5, "skipped" if t.skipped[:, k].all() else "no finite values", transform=ax.transAxes,
                    ha="center", va="center", color="0.4")
        arrow = "↑" if METRICS[metric].higher_is_better else "↓"
        ax.set_title(f"{metric_label(metric)} {arrow}", fontsize=10)
        ax.grid(axis="x", alpha=0.3)
        ax.xaxis.set_major_locator(MaxNLocator(nbins=4))
        ax.tick_params(axis="x", labelsize=7)
        ax.tick_params(axis="y", labelsize=8)
    for ax in axes.flat[n_metrics:]:
        ax.set_visible(False)
    axes[0, 0].set_yticks(y, list(t.models))
    axes[0, 0].set_ylim(n_models - 0.5, -0.5)
    caption = ("Points are model means and bars 95% percentile bootstrap intervals over evaluation examples "
               f"({data.resamples:,} resamples). Models follow the same row order in every panel."
               + (" BGDrift is multiplied by 10³." if "bgdrift" in t.metrics else ""))
    return save_figure(fig, out_dir, "metric_intervals", "Uncertainty across all measurements", caption)


def poi_heatmaps(data: ReportData, out_dir: Path) -> FigureFile | None:
    """Grid of (M, M) probability-of-improvement panels, one per measurement; None with one model."""
    t = data.table
    n_models, n_metrics = len(t.models), len(t.metrics)
    if n_models < 2:
        return None
    import matplotlib

    ncols = 5 if n_models <= 3 else 3 if n_models <= 8 else 2
    nrows = math.ceil(n_metrics / ncols)
    side = max(2.6, 0.45 * n_models + 1.4)
    fig = new_figure(side * ncols + 0.8, side * nrows)
    axes = fig.subplots(nrows, ncols, squeeze=False)
    cmap = matplotlib.colormaps["RdBu"].with_extremes(bad="0.9")
    image = None
    font = max(5.0, 9.0 - 0.4 * n_models)
    for k, (metric, pm) in enumerate(zip(t.metrics, data.poi_matrices)):
        ax = axes.flat[k]
        order = best_first_order(data.overall.mean[:, k], METRICS[metric].higher_is_better)
        est = pm.estimate[np.ix_(order, order)].copy()
        np.fill_diagonal(est, np.nan)
        image = ax.imshow(est, cmap=cmap, vmin=0.0, vmax=1.0)
        for i in range(n_models):
            for j in range(n_models):
                if i != j and math.isfinite(est[i, j]):
                    sig = bool(pm.significant[order[i], order[j]])
                    ax.text(j, i, f"{est[i, j]:.2f}", ha="center", va="center", fontsize=font,
                            fontweight="bold" if sig else "normal",
                            color="white" if abs(est[i, j] - 0.5) > 0.3 else "black")
        labels = [t.models[i] for i in order]
        ax.set_xticks(range(n_models), labels, rotation=60, ha="right", fontsize=font)
        ax.set_yticks(range(n_models), labels, fontsize=font)
        arrow = "↑" if METRICS[metric].higher_is_better else "↓"
        title = f"{METRICS[metric].display_name} {arrow}"
        if t.skipped[:, k].all():
            title += " (skipped)"
        ax.set_title(title, fontsize=10)
    for ax in axes.flat[n_metrics:]:
        ax.set_visible(False)
    if image is not None:
        fig.colorbar(image, ax=list(axes.flat[:n_metrics]), shrink=0.6, label="P(row model better than column)")
    caption = ("Each cell is the probability that the row model is better than the column model on the same "
               "example (ties count one half). Rows and columns are ordered by the model mean, best first. Bold "
               f"entries have a paired bootstrap 95% interval ({data.resamples:,} resamples) that excludes 0.5.")
    return save_figure(fig, out_dir, "poi_heatmaps", "Matched probability of improvement", caption)


def envelope_order(data: ReportData, k: int, q05: np.ndarray, median: np.ndarray, q95: np.ndarray) -> np.ndarray:
    """Indices of the examples with an envelope on metric k, grouped by task (report order) and sorted by the
    envelope's median within each task."""
    t = data.table
    ok = np.flatnonzero(np.isfinite(q05) & np.isfinite(q95))
    rank = {task: i for i, task in enumerate(data.tasks)}
    return np.array(sorted(ok, key=lambda j: (rank.get(t.tasks[j], len(rank)), median[j], t.example_ids[j])),
                    dtype=np.int64)


def envelope_band(data: ReportData, k: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(q05, median, q95), each (N,), of metric k per example: from the first run whose envelope has it."""
    env = data.envelope
    out = [np.full(len(data.table.example_ids), np.nan) for _ in range(3)]
    for m in range(len(data.table.models)):
        fill = ~np.isfinite(out[0]) & np.isfinite(env.q05[m, :, k]) & np.isfinite(env.q95[m, :, k])
        for arr, source in zip(out, (env.q05, env.median, env.q95)):
            arr[fill] = source[m, fill, k]
    return out[0], out[1], out[2]


def envelope_spread(data: ReportData, out_dir: Path) -> FigureFile | None:
    """One measurement per example: the envelope's 5th-95th percentile band and median, with each model's samples
    (small dots) and their mean (large marker) beside it; None without an envelope on that measurement."""
    env, t, metric = data.envelope, data.table, data.envelope_metric
    if env is None or metric not in env.metrics:
        return None
    k, scale = t.metric_index(metric), display_scale(metric)
    q05, median, q95 = (a * scale for a in envelope_band(data, k))
    order = envelope_order(data, k, q05, median, q95)
    if order.size == 0:
        return None
    n_models, n = len(t.models), len(order)
    x = np.arange(n)
    colors = model_colors(n_models)
    fig = new_figure(min(16.0, max(7.0, 2.5 + 0.14 * n * max(1.0, n_models / 3))), 4.6)
    ax = fig.add_subplot()
    ax.bar(x, q95[order] - q05[order], bottom=q05[order], width=0.8, color="0.85", edgecolor="none",
           label="envelope: twins' 5th-95th percentile")
    ax.scatter(x, median[order], marker="_", s=90, color="0.25", linewidths=1.5, label="envelope median", zorder=3)
    samples = data.samples.values[..., k] if data.samples is not None else t.scores[:, :, None, k]
    width = 0.7 / max(n_models, 1)
    shown = [q05[order], q95[order]]
    for m, model in enumerate(t.models):
        dx = (m - (n_models - 1) / 2) * width
        per = samples[m][order] * scale  # (n, S)
        rows, cols = np.nonzero(np.isfinite(per))
        if per.shape[1] > 1 and rows.size:
            ax.scatter(x[rows] + dx, per[rows, cols], s=9, color=colors[m], alpha=0.55, linewidths=0, zorder=4)
        mean = t.scores[m, order, k] * scale
        ok = np.isfinite(mean)
        ax.scatter(x[ok] + dx, mean[ok], s=30, color=colors[m], edgecolors="black", linewidths=0.5, zorder=5,
                   label=model)
        shown += [per[np.isfinite(per)], mean[ok]]
    values = np.concatenate([v.ravel() for v in shown])
    values = values[np.isfinite(values)]
    if values.size and values.min() > 0 and values.max() / values.min() > 100:
        ax.set_yscale("log")
    tasks = [t.tasks[j] for j in order]
    starts = [i for i in range(n) if i == 0 or tasks[i] != tasks[i - 1]]
    for i in starts[1:]:
        ax.axvline(i - 0.5, color="0.6", lw=0.8)
    for i, end in zip(starts, starts[1:] + [n]):
        ax.text((i + end - 1) / 2, 1.01, task_label(tasks[i]), transform=ax.get_xaxis_transform(), ha="center",
                va="bottom", fontsize=8)
    if n <= 40:
        ax.set_xticks(x, [t.example_ids[j] for j in order], rotation=90, fontsize=6)
    else:
        ax.set_xticks([])
    ax.set_xlim(-0.6, n - 0.4)
    ax.set_xlabel("examples, by task, sorted by the envelope's median")
    name = metric_label(metric)
    ax.set_ylabel(f"{name} {'↑' if METRICS[metric].higher_is_better else '↓'}")
    ax.grid(axis="y", alpha=0.3)
    ax.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.01, 1.0), frameon=False)
    several = data.samples is not None
    caption = (f"{METRICS[metric].display_name} on each example against the physical envelope: grey bars span the "
               "5th to 95th percentile of the physical twins (the reference re-simulated with its initial state and "
               "materials perturbed within what one frame cannot resolve), the dark tick is their median. "
               + ("Small dots are each model's samples, large markers their mean, the value the envelope columns "
                  "compare. " if several else "Markers are each model's score on the example. ")
               + "A mean inside the grey bar, or beyond it on the better side, is as close to the reference as "
               "physics allows; choose the measurement with --envelope-metric." + (f" {METRICS[metric].display_name} is multiplied by {scale:g}."
                                            if scale != 1.0 else ""))
    return save_figure(fig, out_dir, f"envelope_{metric}", f"{METRICS[metric].display_name} against the physical "
                       "envelope, example by example", caption)


def build_figures(data: ReportData, out_dir: Path) -> list[FigureFile]:
    """Write every figure as PNG and PDF into out_dir. Returns them in display order."""
    out_dir.mkdir(parents=True, exist_ok=True)
    figures = [ssim_vs_ate3d(data, out_dir), ate3d_by_task(data, out_dir), metric_intervals(data, out_dir)]
    heatmaps = poi_heatmaps(data, out_dir)
    if heatmaps is not None:
        figures.append(heatmaps)
    spread = envelope_spread(data, out_dir)
    if spread is not None:
        figures.append(spread)
    log.info("wrote %d figures to %s", len(figures), out_dir)
    return figures
