"""The probe summaries that `probe intervene` and `probe report` write are recomputed here from the lines they
summarise: the intervention table from the per-clip effect lines, the probe tables from the fitted cells.

The effects are hand-built so that a summary over lines and one over clip means differ: clip "c2" has one
block x tau cell where the others have four, and its effect is far from theirs."""

from __future__ import annotations

import csv
import itertools

import numpy as np
import pytest

from rigidbench.probe.report import probe_tables, write_report
from rigidbench.stages.probe_intervene import READOUTS, VARIANTS, summarize
from fixtures.report_files import read_csv

CELLS = [(0, 0.3), (0, 0.7), (1, 0.3), (1, 0.7)]
CLIPS = {"c0": CELLS, "c1": CELLS, "c2": CELLS[:1], "c3": CELLS}
RESAMPLES = 400


def delta(clip: str, block: int, tau: float, variant: str, readout: str) -> float:
    """A distinct effect per line; c2's is ten times larger."""
    v = VARIANTS.index(variant) + 0.5 * READOUTS.index(readout) + 0.1 * block + tau + 0.01 * int(clip[1])
    return 10 * v if clip == "c2" else v


def effect_lines() -> list[dict]:
    return [{"clip": c, "block": b, "tau": tau, "variant": v, "readout": r, "loss_base": 1.0,
             "loss": 1.0 + delta(c, b, tau, v, r), "delta": delta(c, b, tau, v, r)}
            for c, cells in CLIPS.items() for (b, tau) in cells for v in VARIANTS for r in READOUTS]



@pytest.fixture(scope="module")
def intervened(tmp_path_factory):
    out = tmp_path_factory.mktemp("intervene")
    summarize(effect_lines(), [], out, RESAMPLES, {"clips": list(CLIPS)})
    with (out / "bases.csv").open("w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=["block", "tau", "rank", "procedure"])
        w.writeheader()
        w.writerows({"block": b, "tau": tau, "rank": 2 + b, "procedure": "stable"} for b, tau in CELLS)
    return out


def test_the_intervention_summary_is_the_mean_over_clips_of_each_clips_mean(intervened):
    rows = {(r["variant"], r["readout"]): r for r in read_csv(intervened / "summary.csv")}
    assert set(rows) == set(itertools.product(VARIANTS, READOUTS))
    for (variant, readout), row in rows.items():
        clip_means = [np.mean([delta(c, b, tau, variant, readout) for b, tau in cells]) for c, cells in CLIPS.items()]
        every_line = np.mean([delta(c, b, tau, variant, readout) for c, cells in CLIPS.items() for b, tau in cells])
        assert float(row["mean"]) == pytest.approx(np.mean(clip_means), rel=1e-12)
        assert abs(np.mean(clip_means) - every_line) > 0.4  # the two readings differ: the test tells them apart
        assert int(row["clips"]) == len(CLIPS)
        # a bootstrap over 4 clips: inside the range of the clip means and around their mean
        assert min(clip_means) <= float(row["lo"]) < float(row["mean"]) < float(row["hi"]) <= max(clip_means)


def test_the_by_cell_table_is_the_mean_over_the_clips_that_have_the_cell(intervened):
    rows = read_csv(intervened / "effects_by_cell.csv")
    assert len(rows) == len(VARIANTS) * len(READOUTS) * len(CELLS)
    for row in rows:
        b, tau, v, r = int(row["block"]), float(row["tau"]), row["variant"], row["readout"]
        have = [c for c, cells in CLIPS.items() if (b, tau) in cells]
        assert float(row["mean"]) == pytest.approx(np.mean([delta(c, b, tau, v, r) for c in have]), rel=1e-12)
        if len(have) == 3:  # c2 is not in the cell: its large effect does not widen the interval
            assert float(row["hi"]) < 10


def test_the_report_shows_the_intervention_summary_it_was_given(intervened, tmp_path):
    page = write_report([], intervened, tmp_path / "report")
    assert read_csv(tmp_path / "report" / "intervention_summary.csv") == read_csv(intervened / "summary.csv")
    text = page.read_text()
    for row in read_csv(intervened / "summary.csv"):
        assert f"<td>{float(row['mean']):.3f}</td><td>{float(row['lo']):.3f}</td>" in text
    assert "rank 2-3 (mean 2.5) over 4 cells" in text


def score_lines() -> list[dict]:
    """Fitted cells of two backbones: test = a distinct number per cell; one NaN cell (a probe that failed)."""
    lines = []
    for bb, target, probe, labels, block, tau in itertools.product(("base", "random"), ("position", "contact"),
                                                                   ("linear", "mlp"), ("trained", "shuffled"),
                                                                   (0, 1, 2), (0.3, 0.7)):
        test = 0.1 * block + tau + (0.05 if probe == "mlp" else 0) - (0.5 if labels == "shuffled" else 0)
        test += 0.2 if bb == "base" else 0
        if (bb, target, probe, labels, block, tau) == ("base", "position", "linear", "trained", 2, 0.7):
            test = float("nan")
        lines.append({"backbone": bb, "target": target, "probe": probe, "labels": labels, "block": block, "tau": tau,
                      "metric": "roc_auc" if target == "contact" else "r2", "test": test})
    return lines


def test_probe_tables_are_the_mean_and_best_cell_of_the_fitted_scores():
    lines = score_lines()
    summary, state = probe_tables(lines)
    assert [(r["backbone"], r["target"]) for r in summary] == [("base", "position"), ("base", "contact"),
                                                                ("random", "position"), ("random", "contact")]
    for row in summary:
        for probe in ("linear", "mlp"):
            for labels, key in (("trained", f"{probe}_mean"), ("shuffled", f"{probe}_shuffled_mean")):
                cells = [x["test"] for x in lines if (x["backbone"], x["target"], x["probe"], x["labels"]) ==
                         (row["backbone"], row["target"], probe, labels)]
                finite = [v for v in cells if np.isfinite(v)]
                assert len(cells) == 6 and row[key] == pytest.approx(sum(finite) / len(finite), rel=1e-12)
    for row in state:
        cells = [x["test"] for x in lines if (x["backbone"], x["target"], x["probe"], x["labels"]) ==
                 (row["backbone"], row["target"], row["probe"], "trained")]
        assert row["best_cell"] == pytest.approx(np.nanmax(cells)) and row["cells"] == 6
    nan_row = next(r for r in state if (r["backbone"], r["target"], r["probe"]) == ("base", "position", "linear"))
    assert nan_row["best_cell"] == pytest.approx(0.1 + 0.7 + 0.2)  # block 1, tau 0.7: block 2's (1.1) is NaN
