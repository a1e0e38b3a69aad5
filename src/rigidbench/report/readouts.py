"""The report's physics-readout section (issue 28): a table of each model's readouts and flag rates,
and one figure with a panel per readout showing each model's per-example values against the true
value. Readouts sit beside the ten measurements, never inside them; runs scored before readouts
existed simply have none (the section is left out when no run has any).
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from rigidbench.readouts.flags import FLAGS
from rigidbench.readouts.records import load_run_readouts
from rigidbench.report.figures import FigureFile, new_figure, save_figure
from rigidbench.report.tables import Cell, Table

#: panel key -> (title, per-example value from the readouts file, the true value it is compared with)
PANELS = {
    "speed": ("playback speed s^ (true 1)", lambda r: r["speed"].get("value"), lambda r: 1.0),
    "gravity": ("gravity g^ / simulated g", lambda r: r["gravity"].get("value"),
                lambda r: r["gravity"].get("simulated")),
    "gravity_per_speed2": ("g^ s^-2 / simulated g", lambda r: r["gravity"].get("per_speed2"),
                           lambda r: r["gravity"].get("simulated")),
    "restitution": ("restitution e^ - simulated rebound", lambda r: r["restitution"].get("value"),
                    lambda r: r["restitution"].get("reference")),
}


def _finite(x) -> bool:
    return x is not None and isinstance(x, (int, float)) and math.isfinite(x)


def panel_values(examples: list[dict], key: str) -> np.ndarray:
    """Per-example readout of one panel relative to its true value: a ratio for speed and gravity, a
    difference for restitution (NaN-free; examples where either is undefined are left out)."""
    _, value, truth = PANELS[key]
    out = []
    for e in examples:
        r = e.get("readouts", {})
        try:
            v, t = value(r), truth(r)
        except (KeyError, TypeError, AttributeError):
            continue
        if not (_finite(v) and _finite(t)):
            continue
        out.append(v - t if key == "restitution" else v / t if t else math.nan)
    arr = np.asarray(out, np.float64)
    return arr[np.isfinite(arr)]


def _median_cell(d: dict | None) -> Cell:
    if not d or d.get("median") is None:
        return Cell("-", note=f"0/{(d or {}).get('n', 0)}")
    return Cell(f"{d['median']:.3g}", detail=f"[{d['q25']:.3g}, {d['q75']:.3g}]", note=f"{d['finite']}/{d['n']}")


def readout_table(runs: list[tuple[str, dict, list[dict]]]) -> Table | None:
    """Model x (median and quartiles of s^, g^, g^ s^-2, e^; the rate of each flag)."""
    runs = [r for r in runs if r[1] and r[1].get("n")]
    if not runs:
        return None
    header = ("Model", "s^", "g^ (m/s^2)", "g^ s^-2", "e^", *FLAGS)
    rows = []
    for model, block, _ in runs:
        overall = block["overall"]
        flags = overall.get("flags", {})
        rows.append((Cell(model), *(_median_cell(overall.get(k)) for k in
                                    ("speed", "gravity", "gravity_per_speed2", "restitution")),
                     *(Cell("-" if flags.get(f, {}).get("rate") is None else f"{flags[f]['rate']:.0%}",
                            note=f"{flags.get(f, {}).get('raised', 0)}/{flags.get(f, {}).get('defined', 0)}")
                       for f in FLAGS)))
    return Table("readouts", "Physics readouts",
                 "Median [quartiles] (finite/n) over examples of playback speed, gravity, gravity over speed "
                 "squared and restitution read from each generated clip, and how often each failure flag is "
                 "raised (raised/defined). Readouts are not among the ten measurements: docs/physics.md.",
                 header, ("",) * len(header), tuple(rows))


def readout_figure(runs: list[tuple[str, dict, list[dict]]], out_dir: Path) -> FigureFile | None:
    """One panel per readout: each model's per-example values (relative to the truth) and their median."""
    runs = [r for r in runs if r[2]]
    if not runs:
        return None
    fig = new_figure(10.0, 1.2 + 0.35 * len(runs) * 2)
    axes = fig.subplots(1, len(PANELS), sharey=True)
    for ax, (key, (title, _, _)) in zip(axes, PANELS.items()):
        truth = 0.0 if key == "restitution" else 1.0
        ax.axvline(truth, color="0.3", linestyle="--", linewidth=1)
        for y, (_, _, examples) in enumerate(runs):
            values = panel_values(examples, key)
            if values.size:
                jitter = (np.arange(values.size) % 5 - 2) * 0.06
                ax.scatter(values, y + jitter, s=10, alpha=0.6, color="tab:blue")
                ax.plot([np.median(values)], [y], marker="|", markersize=16, color="black")
        ax.set_title(title, fontsize=9)
    axes[0].set_yticks(range(len(runs)), [model for model, _, _ in runs])
    axes[0].invert_yaxis()
    return save_figure(fig, out_dir, "readouts", "Physics readouts against the truth",
                       "Each dot is one example's readout relative to the true value (dashed): playback speed "
                       "(true 1), gravity and gravity over speed squared as fractions of the simulated g, "
                       "restitution minus the simulated rebound; the bar is the median. Examples where a readout "
                       "is undefined (no ballistic window, no bounce) are left out.")


def readout_section(run_dirs, figures_dir: Path) -> tuple[list[Table], list[FigureFile]]:
    """The section's tables and figures for the report (empty when no run has readouts)."""
    runs = [load_run_readouts(d) for d in run_dirs]
    table = readout_table(runs)
    figure = readout_figure(runs, Path(figures_dir))
    return ([table] if table is not None else []), ([figure] if figure is not None else [])


__all__ = ["PANELS", "panel_values", "readout_table", "readout_figure", "readout_section"]
