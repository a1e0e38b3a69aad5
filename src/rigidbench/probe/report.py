"""``rigidbench probe report``: the probing and intervention figures and tables of the paper (sections
5.2-5.3, appendix E) from ``probe fit`` directories (one per backbone) and a ``probe intervene`` directory.

OUT/index.html                      the page (figures and tables)
OUT/probe_by_block.png|pdf          linear and MLP test score by block per backbone (mean over tau,
                                    shaded min..max; dashed: shuffled-label control)
OUT/probe_by_noise_<probe>.png|pdf  score by block at every tau, per target and backbone
OUT/probe_heatmap_<probe>.png|pdf   block x tau heat maps per backbone and target
OUT/intervention_by_block.png|pdf   mean loss change by block per tau and readout, bootstrap 95% CI,
                                    symmetric-log axis (linear within +-0.01)
OUT/probe_summary.csv               mean test score over cells per backbone x target x probe, trained and shuffled
OUT/probe_state_summary.csv         mean and best cell per backbone x target x probe (trained labels)
OUT/intervention_summary.csv        the aggregate intervention table (mean [lo, hi] per variant x readout)
"""

from __future__ import annotations

import csv
import html
import json
from pathlib import Path

import numpy as np

from ..errors import UserError

CHANCE = {"r2": 0.0, "r2_mean": 0.0, "roc_auc": 0.5}
VARIANT_LABELS = {"position": "Position (INLP)", "pc": "Variance-matched PC", "random": "Random subspace"}


def _figure(rows: int, cols: int, w: float = 3.2, h: float = 2.4):
    from matplotlib.figure import Figure

    fig = Figure(figsize=(w * cols, h * rows), layout="constrained")
    axes = np.atleast_2d(fig.subplots(rows, cols, squeeze=False))
    return fig, axes


def _save(fig, out: Path, stem: str) -> list[str]:
    from matplotlib.ticker import MaxNLocator

    for ax in fig.axes:
        if ax.get_xlabel() == "block" or ax.get_title().startswith(("position", "contact")):
            ax.xaxis.set_major_locator(MaxNLocator(integer=True))
    for ext in ("png", "pdf"):
        fig.savefig(out / f"{stem}.{ext}", dpi=130)
    return [f"{stem}.png"]


def load_scores(dirs) -> list[dict]:
    records = []
    for d in dirs:
        path = Path(d) / "scores.jsonl"
        if not path.is_file():
            raise UserError(f"{d}: no scores.jsonl; run `rigidbench probe fit --out {d}` first")
        records += [json.loads(x) for x in path.read_text().splitlines() if x.strip()]
    return records


def _values(records, **match) -> list[dict]:
    return [r for r in records if all(r[k] == v for k, v in match.items())]


def probe_tables(records: list[dict]) -> tuple[list[dict], list[dict]]:
    summary, state = [], []
    backbones = sorted({r["backbone"] for r in records})
    targets = list(dict.fromkeys(r["target"] for r in records))
    for bb in backbones:
        for t in targets:
            row = {"backbone": bb, "target": t}
            for probe in ("linear", "mlp"):
                tr = np.array([r["test"] for r in _values(records, backbone=bb, target=t, probe=probe,
                                                          labels="trained")], dtype=float)
                sh = np.array([r["test"] for r in _values(records, backbone=bb, target=t, probe=probe,
                                                          labels="shuffled")], dtype=float)
                if not len(tr):
                    continue
                metric = _values(records, backbone=bb, target=t, probe=probe)[0]["metric"]
                row[f"{probe}_metric"] = metric
                row[f"{probe}_mean"] = float(np.nanmean(tr)) if np.isfinite(tr).any() else float("nan")
                row[f"{probe}_shuffled_mean"] = float(np.nanmean(sh)) if np.isfinite(sh).any() else float("nan")
                state.append({"backbone": bb, "target": t, "probe": probe, "metric": metric,
                              "mean": row[f"{probe}_mean"],
                              "best_cell": float(np.nanmax(tr)) if np.isfinite(tr).any() else float("nan"),
                              "cells": int(len(tr))})
            summary.append(row)
    return summary, state


def _curves(records, bb, target, probe, labels):
    """blocks, taus, matrix (blocks x taus) of test scores."""
    sel = _values(records, backbone=bb, target=target, probe=probe, labels=labels)
    blocks = sorted({r["block"] for r in sel})
    taus = sorted({r["tau"] for r in sel})
    m = np.full((len(blocks), len(taus)), np.nan)
    for r in sel:
        m[blocks.index(r["block"]), taus.index(r["tau"])] = r["test"]
    return blocks, taus, m


def probe_figures(records: list[dict], out: Path) -> list[str]:
    import matplotlib

    files = []
    backbones = sorted({r["backbone"] for r in records})
    targets = list(dict.fromkeys(r["target"] for r in records))
    colors = {bb: matplotlib.colormaps["tab10"](i % 10) for i, bb in enumerate(backbones)}
    probes = [p for p in ("linear", "mlp") if _values(records, probe=p)]
    main_targets = [t for t in ("position", "contact") if t in targets] or targets[:2]
    fig, axes = _figure(len(probes), len(main_targets))
    for i, probe in enumerate(probes):
        for j, target in enumerate(main_targets):
            ax = axes[i, j]
            metric = None
            for bb in backbones:
                blocks, _, m = _curves(records, bb, target, probe, "trained")
                if not blocks:
                    continue
                metric = _values(records, backbone=bb, target=target)[0]["metric"]
                with np.errstate(all="ignore"):
                    ax.plot(blocks, np.nanmean(m, axis=1), color=colors[bb], label=bb)
                    ax.fill_between(blocks, np.nanmin(m, axis=1), np.nanmax(m, axis=1), color=colors[bb], alpha=0.2)
                    sb, _, sm = _curves(records, bb, target, probe, "shuffled")
                    if sb:
                        ax.plot(sb, np.nanmean(sm, axis=1), color=colors[bb], ls="--", lw=0.8)
            if metric:
                ax.axhline(CHANCE[metric], color="0.6", lw=0.6)
            ax.set_title(f"{target} ({probe})", fontsize=9)
            ax.set_xlabel("block")
            ax.set_ylabel("test AUC" if metric == "roc_auc" else "test $R^2$")
    axes[0, 0].legend(fontsize=7)
    files += _save(fig, out, "probe_by_block")

    for probe in probes:
        taus = sorted({r["tau"] for r in records})
        fig, axes = _figure(len(targets), len(taus), 2.4, 1.9)
        for i, target in enumerate(targets):
            for j, tau in enumerate(taus):
                ax = axes[i, j]
                for bb in backbones:
                    sel = sorted(_values(records, backbone=bb, target=target, probe=probe, labels="trained", tau=tau),
                                 key=lambda r: r["block"])
                    if sel:
                        ax.plot([r["block"] for r in sel], [r["test"] for r in sel], "o-", ms=2, color=colors[bb],
                                label=bb)
                        ax.axhline(CHANCE[sel[0]["metric"]], color="0.7", lw=0.5)
                ax.set_title(f"{target}, tau={tau:g}", fontsize=7)
                ax.tick_params(labelsize=6)
        axes[0, 0].legend(fontsize=6)
        files += _save(fig, out, f"probe_by_noise_{probe}")

        fig, axes = _figure(len(backbones), len(targets), 2.2, 2.0)
        for i, bb in enumerate(backbones):
            for j, target in enumerate(targets):
                ax = axes[i, j]
                blocks, ts, m = _curves(records, bb, target, probe, "trained")
                if blocks:
                    im = ax.imshow(m.T, aspect="auto", origin="lower", cmap="viridis",
                                   extent=(min(blocks) - 0.5, max(blocks) + 0.5, -0.5, len(ts) - 0.5))
                    ax.set_yticks(range(len(ts)), [f"{t:g}" for t in ts])
                    ax.figure.colorbar(im, ax=ax, shrink=0.8)
                ax.set_title(f"{bb}: {target}", fontsize=7)
                ax.tick_params(labelsize=6)
                ax.set_xlabel("block", fontsize=6)
                ax.set_ylabel("tau", fontsize=6)
        files += _save(fig, out, f"probe_heatmap_{probe}")
    return files


def intervention_figure(by_cell: list[dict], out: Path) -> list[str]:
    import matplotlib

    taus = sorted({float(r["tau"]) for r in by_cell})
    readouts = [r for r in ("full", "direct") if any(c["readout"] == r for c in by_cell)]
    colors = {v: matplotlib.colormaps["tab10"](i) for i, v in enumerate(VARIANT_LABELS)}
    fig, axes = _figure(len(readouts), len(taus))
    for i, readout in enumerate(readouts):
        for j, tau in enumerate(taus):
            ax = axes[i, j]
            for v, label in VARIANT_LABELS.items():
                sel = sorted((r for r in by_cell if r["variant"] == v and r["readout"] == readout
                              and float(r["tau"]) == tau), key=lambda r: int(r["block"]))
                if not sel:
                    continue
                b = [int(r["block"]) for r in sel]
                ax.plot(b, [float(r["mean"]) for r in sel], "o-", ms=2, color=colors[v], label=label)
                ax.fill_between(b, [float(r["lo"]) for r in sel], [float(r["hi"]) for r in sel], color=colors[v],
                                alpha=0.2)
            ax.set_yscale("symlog", linthresh=0.01)
            ax.axhline(0, color="0.6", lw=0.5)
            ax.set_title(f"{'full model' if readout == 'full' else 'direct head'}, tau={tau:g}", fontsize=8)
            ax.set_xlabel("block")
            ax.set_ylabel(r"$\Delta\mathcal{L}$")
    axes[0, 0].legend(fontsize=7)
    return _save(fig, out, "intervention_by_block")


def _read_csv(path: Path) -> list[dict]:
    with path.open() as fh:
        return list(csv.DictReader(fh))


def _write_csv(path: Path, rows: list[dict]) -> None:
    cols = list(dict.fromkeys(k for r in rows for k in r))
    with path.open("w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=cols)
        w.writeheader()
        w.writerows(rows)


def _fmt(v) -> str:
    try:
        f = float(v)
    except (TypeError, ValueError):
        return html.escape(str(v))
    return "nan" if not np.isfinite(f) else f"{f:.3f}"


def _table(rows: list[dict]) -> str:
    if not rows:
        return "<p>(none)</p>"
    cols = list(dict.fromkeys(k for r in rows for k in r))
    head = "".join(f"<th>{html.escape(c)}</th>" for c in cols)
    body = "".join("<tr>" + "".join(f"<td>{_fmt(r.get(c, ''))}</td>" for c in cols) + "</tr>" for r in rows)
    return f"<table><tr>{head}</tr>{body}</table>"


def write_report(probe_dirs, intervene_dir, out) -> Path:
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    if not probe_dirs and intervene_dir is None:
        raise UserError("probe report needs --probes DIR... and/or --intervene DIR")
    sections = ["<h1>RigidBench: probing Wan's transformer</h1>"]
    grids = []
    if probe_dirs:
        records = load_scores(probe_dirs)
        if not records:
            raise UserError(f"{', '.join(map(str, probe_dirs))}: no fitted cells")
        for d in probe_dirs:
            meta = Path(d) / "fit.json"
            if meta.is_file():
                m = json.loads(meta.read_text())
                grids.append(f"{html.escape(str(m['backbone']))}: token grid {m['token_grid']} "
                             "(slots x rows x columns),"
                             f" rows {m['rows']}, clips {m['clips']}")
        summary, state = probe_tables(records)
        _write_csv(out / "probe_summary.csv", summary)
        _write_csv(out / "probe_state_summary.csv", state)
        figs = probe_figures(records, out)
        sections += ["<h2>Probe scores</h2>", "<ul>" + "".join(f"<li>{g}</li>" for g in grids) + "</ul>",
                     "<p>Mean test score over block x tau cells (R<sup>2</sup>; ROC-AUC for contact); "
                     "shuffled-label control alongside (probe_summary.csv).</p>", _table(summary),
                     "<h3>Mean and best cell (probe_state_summary.csv)</h3>", _table(state)]
        sections += [f'<figure><img src="{f}" style="max-width:100%"><figcaption>{f}</figcaption></figure>'
                     for f in figs]
    if intervene_dir is not None:
        d = Path(intervene_dir)
        if not (d / "summary.csv").is_file():
            raise UserError(f"{d}: no summary.csv; run `rigidbench probe intervene --out {d}` first")
        summary = _read_csv(d / "summary.csv")
        _write_csv(out / "intervention_summary.csv", summary)
        figs = intervention_figure(_read_csv(d / "effects_by_cell.csv"), out)
        bases = _read_csv(d / "bases.csv")
        ranks = [int(b["rank"]) for b in bases]
        procedures = ", ".join(sorted({b.get("procedure") or "stable" for b in bases}))
        sections += ["<h2>Position-aligned interventions</h2>",
                     f"<p>INLP position basis rank {min(ranks)}-{max(ranks)} (mean {np.mean(ranks):.1f}) over "
                     f"{len(bases)} cells, INLP procedure {procedures}. Loss change: mean over clips of each clip's "
                     "mean over blocks and taus, bootstrap 95% CI over clips.</p>", _table(summary)]
        sections += [f'<figure><img src="{f}" style="max-width:100%"><figcaption>{f}</figcaption></figure>'
                     for f in figs]
    page = out / "index.html"
    style = "body{font-family:sans-serif;max-width:1100px;margin:auto}table{border-collapse:collapse}" \
            "td,th{border:1px solid #ccc;padding:2px 6px;font-size:12px}"
    page.write_text(f"<!doctype html><html><head><meta charset='utf-8'><title>RigidBench probes</title>"
                    f"<style>{style}</style></head><body>{''.join(sections)}</body></html>")
    return page
