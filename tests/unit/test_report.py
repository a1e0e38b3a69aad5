"""Unit tests for rigidbench.report: run loading, marks, intervals, CSV round trip, HTML references.

Run directories are written here in the exact format `rigidbench evaluate` writes (example
records, results.json from `evaluate.aggregate`, run.json), with hand-chosen scores whose means,
ranks and probabilities of improvement are known in advance.
"""

from __future__ import annotations

import argparse
import json
from html.parser import HTMLParser
from pathlib import Path

import numpy as np
import pytest

from rigidbench.commands.scoring import cmd_report
from rigidbench.evaluation import aggregate
from rigidbench.metrics import METRICS
from rigidbench.report import ReportError, build_report, load_runs
from rigidbench.report.analysis import analyse, choose_baseline, rank_marks
from rigidbench.report.tables import to_latex, to_markdown
from rigidbench.stats import bootstrap_ci, paired_difference, probability_of_improvement
from fixtures.report_files import read_csv, row_for

RESAMPLES = 2000
N = 8
IDS = [f"{i:05d}" for i in range(N)]
TASKS = ["free_fall", "bounce"] * 4
PARTITIONS = ["in_distribution"] * 4 + ["ood_scene"] * 4
# Zero-sum spread, so each model's mean on a metric is the chosen value.
SPREAD = np.linspace(-0.04, 0.04, N)
IOU_MEANS = {"reference": 1.0, "alpha": 0.9, "beta": 0.7, "gamma_run": 0.8, "delta": 0.1}
L2_MEANS = {"reference": 0.0, "alpha": 0.3, "beta": 0.1, "gamma_run": 0.2, "delta": 0.4}
ATE3D = {"alpha": [1, 2, 3, 4, 1, 2, 3, 4], "beta": [2, 2, 1, 5, 1, 2, 3, 4]}
DELTA_IDDRIFT_NONE = (1, 4, 6)  # examples where delta's IdDrift is non-finite -> n=5


def write_run(root: Path, model: str, scores: dict[str, list], ids=IDS, skipped: dict[str, str] | None = None,
              failed: dict[str, str] | None = None, dir_name: str | None = None) -> Path:
    """Write runs/<model>/ as evaluate.py does. scores: metric -> per-example value (None = non-finite)."""
    skipped = skipped or {}
    run_dir = root / (dir_name or model)
    (run_dir / "examples").mkdir(parents=True)
    records = []
    for j, sample_id in enumerate(ids):
        i = int(sample_id)
        record = {"id": sample_id, "model": model, "task": TASKS[i % len(TASKS)],
                  "partition": PARTITIONS[i % len(PARTITIONS)], "frames_compared": 49, "input_key": "k" * 64,
                  "perception": "gt",
                  "metrics": {m: (None if m in skipped else scores[m][j]) for m in METRICS},
                  "skipped": {m: reason for m, reason in skipped.items()}}
        (run_dir / "examples" / f"{sample_id}.json").write_text(json.dumps(record, indent=2, allow_nan=False))
        records.append(record)
    results = {"model": model, "perception": "gt", "official": False, "n_examples": len(records),
               "n_reference": len(ids), "failed": failed or {}, "skipped_metrics": skipped, **aggregate(records, tuple(METRICS)),
               "why_not_official": [f"the reference directory holds {len(ids)} examples, not the 100 of the eval "
                                    "split"]}
    (run_dir / "results.json").write_text(json.dumps(results, indent=2, allow_nan=False))
    run = {"model": model, "perception": {"backend": "gt", "version": "1"}, "finished_at": "2025-01-01T00:00:00"}
    (run_dir / "run.json").write_text(json.dumps(run, indent=2))
    return run_dir


def model_scores(model: str, seed: int, n: int = N) -> dict[str, list]:
    """Per-example scores of one synthetic model: IoU and L2 at fixed means, the rest seeded noise."""
    rng = np.random.default_rng(seed)
    scores = {m: list(rng.uniform(0.2, 0.6, n)) for m in METRICS}
    scores["iou"] = list(IOU_MEANS[model] + SPREAD[:n])
    scores["centroid_l2"] = list(np.abs(L2_MEANS[model] + SPREAD[:n]))
    scores["ate3d"] = [float(v) for v in ATE3D.get(model, rng.uniform(0.5, 5.0, n))]
    if model == "reference":
        scores["ate3d"] = [0.0] * n
    if model == "delta":
        scores["iddrift"] = [None if j in DELTA_IDDRIFT_NONE else v for j, v in enumerate(scores["iddrift"])]
    return {m: [None if v is None else float(v) for v in vals] for m, vals in scores.items()}


@pytest.fixture(scope="module")
def runs(tmp_path_factory) -> list[Path]:
    root = tmp_path_factory.mktemp("runs")
    order = ["reference", "alpha", "beta", "gamma_run", "delta"]
    dirs = []
    for seed, model in enumerate(order):
        skipped = {"lpips": "LPIPS weights not found in the torch hub cache"} if model == "gamma_run" else None
        dirs.append(write_run(root, model, model_scores(model, seed), skipped=skipped))
    return dirs


@pytest.fixture(scope="module")
def report(runs, tmp_path_factory) -> Path:
    return build_report(runs, tmp_path_factory.mktemp("report") / "out", resamples=RESAMPLES, seed=0)




def example_scores(run_dir: Path, metric: str, ids=IDS) -> np.ndarray:
    """(N,) float64 per-example scores read back from the run's example records, NaN for null."""
    out = []
    for sample_id in ids:
        value = json.loads((run_dir / "examples" / f"{sample_id}.json").read_text())["metrics"][metric]
        out.append(np.nan if value is None else value)
    return np.array(out, dtype=np.float64)


# ----------------------------------------------------------------------------------- marks


def test_rank_marks_unique_values_only_with_direction_ties_and_eligibility():
    # Higher is better: 0.9 best, 0.8 second.
    assert rank_marks(np.array([0.9, 0.7, 0.8, 0.1]), True, np.ones(4, bool)) == ["best", "", "second", ""]
    # Lower is better: 0.1 best, 0.2 second.
    assert rank_marks(np.array([0.3, 0.1, 0.2, 0.4]), False, np.ones(4, bool)) == ["", "best", "second", ""]
    # A tie takes no mark: not for the tied best (two zeros), and nothing below it.
    assert rank_marks(np.array([0.0, 0.0, 2.0]), False, np.ones(3, bool)) == ["", "", ""]
    # A unique best keeps its mark when the next two tie; the tie for second is unmarked.
    assert rank_marks(np.array([0.5, 1.0, 1.0, 2.0]), False, np.ones(4, bool)) == ["best", "", "", ""]
    # Two models: the worse one is not 'second-best'; an all-tied column has no marks.
    assert rank_marks(np.array([1.0, 2.0]), False, np.ones(2, bool)) == ["best", ""]
    assert rank_marks(np.array([1.0, 1.0]), False, np.ones(2, bool)) == ["", ""]
    # With decimals, means that print the same tie: 0.00002 and 0.00003 both read 0.000.
    assert rank_marks(np.array([2e-5, 3e-5, 0.4]), False, np.ones(3, bool)) == ["best", "second", ""]
    assert rank_marks(np.array([2e-5, 3e-5, 0.4]), False, np.ones(3, bool), decimals=3) == ["", "", ""]
    # ... after the display scale (BGDrift x 1000): 0.020 and 0.030 differ.
    assert rank_marks(np.array([2e-5, 3e-5, 0.4]), False, np.ones(3, bool), 3, 1000.0) == ["best", "second", ""]
    # Ineligible (e.g. the reference) and NaN means take no mark and do not push others down.
    assert rank_marks(np.array([0.0, np.nan, 0.3, 0.2, 0.5]), False,
                      np.array([False, True, True, True, True])) == ["", "", "second", "best", ""]


def test_best_and_second_marks_in_csv_markdown_and_latex(report):
    rows = read_csv(report.parent / "tables" / "model_metrics.csv")
    # IoU, higher is better: alpha 0.9 best, gamma_run 0.8 second; the reference (1.0) is not ranked.
    assert [row_for(rows, model=m, metric="iou")["mark"] for m in IOU_MEANS] == ["", "best", "", "second", ""]
    # L2, lower is better: beta 0.1 best, gamma_run 0.2 second; the reference (0.0) is not ranked.
    assert [row_for(rows, model=m, metric="centroid_l2")["mark"] for m in L2_MEANS] == ["", "", "best", "second", ""]
    md = (report.parent / "tables" / "model_metrics.md").read_text()
    tex = (report.parent / "tables" / "model_metrics.tex").read_text()
    beta_md = next(line for line in md.splitlines() if line.startswith("| beta |"))
    assert beta_md.split(" | ")[2].startswith("**0.100**")  # L2 column: bold
    gamma_md = next(line for line in md.splitlines() if line.startswith("| gamma_run |"))
    assert gamma_md.split(" | ")[1].startswith("<u>0.800</u>")  # IoU column: underlined
    assert r"\textbf{0.900}" in tex and r"\underline{0.800}" in tex
    assert r"\textbf{0.100}" in tex and r"\underline{0.200}" in tex
    assert r"gamma\_run" in tex and r"\toprule" in tex and r"\bottomrule" in tex
    assert r"\textbf{1.000}" not in tex  # the reference's IoU is not marked


# ------------------------------------------------------------------- intervals and CSV


def test_ci_columns_match_stats_bootstrap_ci(report, runs):
    rows = read_csv(report.parent / "tables" / "model_metrics.csv")
    for run_dir in runs:
        for metric in ("iou", "ate3d", "ssim", "bgdrift", "iddrift"):
            values = example_scores(run_dir, metric)
            mean, lo, hi = bootstrap_ci(values, n_resamples=RESAMPLES, seed=0)
            row = row_for(rows, model=run_dir.name, metric=metric)
            assert float(row["mean"]) == pytest.approx(np.nanmean(values), rel=1e-12, abs=1e-15)
            # Equal up to rounding: batching rows through one matrix product may change the last bit.
            got = (float(row["mean"]), float(row["ci_low"]), float(row["ci_high"]))
            assert got == pytest.approx((mean, lo, hi), rel=1e-12, abs=1e-15, nan_ok=True)
    by_task = read_csv(report.parent / "tables" / "by_task.csv")
    beta = example_scores(runs[2], "ate3d")
    mask = np.array(TASKS) == "bounce"
    mean, lo, hi = bootstrap_ci(beta[mask], n_resamples=RESAMPLES, seed=0)
    row = row_for(by_task, model="beta", task="bounce", metric="ate3d")
    got = (float(row["mean"]), float(row["ci_low"]), float(row["ci_high"]))
    assert got == pytest.approx((mean, lo, hi), rel=1e-12)
    assert int(row["n_examples"]) == 4


def test_csv_round_trips_to_the_computed_statistics(report, runs):
    data = analyse(load_runs(runs), resamples=RESAMPLES, seed=0)
    rows = read_csv(report.parent / "tables" / "model_metrics.csv")
    for m, model in enumerate(data.table.models):
        for k, metric in enumerate(data.table.metrics):
            row = row_for(rows, model=model, metric=metric)
            for field, arr in (("mean", data.overall.mean), ("ci_low", data.overall.lo), ("ci_high", data.overall.hi)):
                expected = arr[m, k]
                assert (row[field] == "") if np.isnan(expected) else float(row[field]) == expected
            assert int(row["n_finite"]) == data.overall.n_finite[m, k]
    partitions = read_csv(report.parent / "tables" / "by_partition.csv")
    g = data.partitions.index("ood_scene")
    k = data.table.metric_index("ssim")
    row = row_for(partitions, model="delta", partition="ood_scene", metric="ssim")
    assert float(row["mean"]) == data.by_partition.mean[4, g, k]


def test_finite_counts_reported_where_values_are_non_finite(report, runs):
    rows = read_csv(report.parent / "tables" / "model_metrics.csv")
    row = row_for(rows, model="delta", metric="iddrift")
    assert int(row["n_finite"]) == N - len(DELTA_IDDRIFT_NONE) == 5
    values = example_scores(runs[4], "iddrift")
    assert float(row["mean"]) == pytest.approx(np.nanmean(values), rel=1e-12)
    md = (report.parent / "tables" / "model_metrics.md").read_text()
    delta_line = next(line for line in md.splitlines() if line.startswith("| delta |"))
    assert delta_line.count("(n=5)") == 1
    assert "(n=" not in next(line for line in md.splitlines() if line.startswith("| alpha |"))
    assert "(n=5)" in (report.parent / "report.html").read_text()


def test_metric_skipped_for_one_model_is_shown_as_skipped_and_not_ranked(report):
    rows = read_csv(report.parent / "tables" / "model_metrics.csv")
    row = row_for(rows, model="gamma_run", metric="lpips")
    assert row["skipped"] == "1" and row["mean"] == "" and row["mark"] == "" and row["n_finite"] == "0"
    md = (report.parent / "tables" / "model_metrics.md").read_text()
    gamma_cells = next(line for line in md.splitlines() if line.startswith("| gamma_run |")).split(" | ")
    assert gamma_cells[8] == "skipped"  # LPIPS is the 8th metric
    page = (report.parent / "report.html").read_text()
    # The reason appears once, in a note naming the run it applies to.
    assert page.count("LPIPS weights not found in the torch hub cache") == 1
    assert "LPIPS not computed for gamma_run: LPIPS weights not found in the torch hub cache" in page


# --------------------------------------------------------------------- paired comparisons


def test_paired_changes_and_probability_of_improvement_with_ties(report, runs):
    rows = read_csv(report.parent / "tables" / "paired_changes.csv")
    row = row_for(rows, model="beta", metric="ate3d")
    assert row["baseline"] == "alpha"  # the first run that is not the reference
    # Lower is better. beta vs alpha per example: worse, tie, better, worse, tie x4 -> (0+.5+1+0+4*.5)/8.
    wins = np.array([0, 0.5, 1, 0, 0.5, 0.5, 0.5, 0.5])
    assert float(row["poi"]) == pytest.approx(3.5 / 8, abs=1e-12)
    _, lo, hi = bootstrap_ci(wins, n_resamples=RESAMPLES, seed=0)
    assert (float(row["poi_ci_low"]), float(row["poi_ci_high"])) == pytest.approx((lo, hi), abs=1e-12)
    alpha, beta = np.array(ATE3D["alpha"], float), np.array(ATE3D["beta"], float)
    assert probability_of_improvement(beta, alpha, False, n_resamples=RESAMPLES)[0] == pytest.approx(3.5 / 8)
    diff = paired_difference(beta, alpha, n_resamples=RESAMPLES, seed=0)
    assert (float(row["diff_mean"]), float(row["diff_ci_low"]), float(row["diff_ci_high"])) == pytest.approx(diff)
    matrix = read_csv(report.parent / "tables" / "poi_matrix.csv")
    assert float(row_for(matrix, metric="ate3d", model="alpha", opponent="beta")["poi"]) == pytest.approx(4.5 / 8)
    # The baseline has no row against itself; IdDrift pairs count only examples finite for both.
    assert not [r for r in rows if r["model"] == "alpha"]
    assert int(row_for(rows, model="delta", metric="iddrift")["n_matched"]) == 5


def test_baseline_choice(runs):
    models = ("reference", "alpha", "beta")
    assert choose_baseline(models, None) == 1
    assert choose_baseline(models, "beta") == 2
    assert choose_baseline(("reference",), None) == 0
    with pytest.raises(ReportError, match="'nope' is not one of the runs"):
        choose_baseline(models, "nope")


# ------------------------------------------------------------------------------ outputs


class _Refs(HTMLParser):
    def __init__(self):
        super().__init__()
        self.refs = []

    def handle_starttag(self, tag, attrs):
        # In-page anchors (the contents line) are not files.
        self.refs += [value for key, value in attrs if key in ("src", "href") and value and not value.startswith("#")]


def html_refs(page: Path) -> list[str]:
    parser = _Refs()
    parser.feed(page.read_text())
    return parser.refs


def test_every_file_referenced_from_report_html_exists(report):
    refs = html_refs(report)
    assert refs, "report.html references no files"
    for ref in refs:
        assert not ref.startswith(("http:", "https:", "/")), ref
        assert (report.parent / ref).is_file(), ref
    images = [r for r in refs if r.endswith(".png")]
    assert {Path(r).stem for r in images} == {"ssim_vs_ate3d", "ate3d_by_task", "metric_intervals", "poi_heatmaps"}
    for stem in ("ssim_vs_ate3d", "ate3d_by_task", "metric_intervals", "poi_heatmaps"):
        assert (report.parent / "figures" / f"{stem}.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
        assert (report.parent / "figures" / f"{stem}.pdf").read_bytes()[:5] == b"%PDF-"
    for key in ("model_metrics", "by_task", "all_by_task", "by_partition", "all_by_partition", "paired_changes",
                "poi_ate3d", "poi_ssim"):
        for ext in ("md", "tex"):
            assert f"tables/{key}.{ext}" in refs
    page = report.read_text()
    assert "<style>" in page and "<script" not in page
    assert "gt (v1)" in page  # perception backend from run.json


def test_ssim_ate3d_correlation_matches_stats_over_model_means(report, runs):
    from rigidbench.stats import correlation_across_models

    row = read_csv(report.parent / "tables" / "correlation.csv")[0]
    ssim = [np.nanmean(example_scores(r, "ssim")) for r in runs]
    ate3d = [np.nanmean(example_scores(r, "ate3d")) for r in runs]
    expected = correlation_across_models(ssim, -np.array(ate3d), n_resamples=RESAMPLES, seed=0)
    assert float(row["pearson"]) == pytest.approx(expected["pearson"], abs=1e-12)
    assert float(row["spearman"]) == pytest.approx(expected["spearman"], abs=1e-12)
    assert float(row["pearson_ci_low"]) == pytest.approx(expected["pearson_ci"][0], abs=1e-12)
    assert int(row["n_models"]) == 5


def test_single_run_report_through_cmd_report(tmp_path, capsys):
    run = write_run(tmp_path / "runs", "alpha", model_scores("alpha", 0))
    args = argparse.Namespace(runs=[run], out=tmp_path / "out", baseline=None, resamples=RESAMPLES, seed=0)
    assert cmd_report(args) == 0
    page = tmp_path / "out" / "report.html"
    assert str(page) in capsys.readouterr().out
    for ref in html_refs(page):
        assert (page.parent / ref).is_file(), ref
    assert not (page.parent / "tables" / "paired_changes.csv").exists()
    assert not (page.parent / "figures" / "poi_heatmaps.png").exists()
    assert "Only one run was given" in page.read_text()
    # One model: nothing to rank against.
    assert "**" not in (page.parent / "tables" / "model_metrics.md").read_text().split("\n\n")[1]


def test_runs_with_different_examples_use_the_intersection(tmp_path):
    a = write_run(tmp_path / "runs", "alpha", model_scores("alpha", 0))
    b = write_run(tmp_path / "runs", "beta", model_scores("beta", 1, n=6), ids=IDS[2:])
    table = load_runs([a, b])
    assert table.example_ids == tuple(IDS[2:])
    assert table.scores.shape == (2, 6, len(METRICS))
    np.testing.assert_array_equal(table.scores[0, :, table.metric_index("iou")], example_scores(a, "iou", IDS[2:]))
    assert any("6 examples that all runs share" in n and "2 from alpha" in n for n in table.notes)


def test_runs_with_the_same_model_name_get_their_directory_appended(tmp_path):
    a = write_run(tmp_path / "runs", "alpha", model_scores("alpha", 0), dir_name="alpha_seed0")
    b = write_run(tmp_path / "runs", "alpha", model_scores("alpha", 1), dir_name="alpha_seed1")
    assert load_runs([a, b]).models == ("alpha (alpha_seed0)", "alpha (alpha_seed1)")


def test_failed_examples_are_left_out(tmp_path):
    run = write_run(tmp_path / "runs", "alpha", model_scores("alpha", 0), failed={IDS[0]: "decode error"})
    assert load_runs([run]).example_ids == tuple(IDS[1:])


def test_clear_errors_name_the_run_directory(tmp_path):
    empty = tmp_path / "runs" / "unfinished"
    empty.mkdir(parents=True)
    with pytest.raises(ReportError, match=r"unfinished: no results\.json"):
        load_runs([empty])
    with pytest.raises(ReportError, match="missing_dir: run directory does not exist"):
        load_runs([tmp_path / "missing_dir"])
    a = write_run(tmp_path / "runs", "alpha", model_scores("alpha", 0), ids=IDS[:4])
    b = write_run(tmp_path / "runs", "beta", model_scores("beta", 1, n=4), ids=IDS[4:])
    with pytest.raises(ReportError, match="share no example ids"):
        load_runs([a, b])


def test_explicit_baseline(runs):
    from rigidbench.report.tables import paired_table

    data = analyse(load_runs(runs), resamples=200, seed=0, baseline="beta")
    assert data.table.models[data.baseline] == "beta"
    assert np.isnan(data.paired_diff.mean[2]).all()  # no comparison of beta with itself
    k = data.table.metric_index("iou")
    assert data.paired_diff.mean[1, k] == pytest.approx(IOU_MEANS["alpha"] - IOU_MEANS["beta"])
    table = paired_table(data)
    assert table.title == "Paired comparisons with beta" and table.header[2] == "IoU"
    # Two rows per model, Δ then PoI, every model but the baseline.
    assert [row[0].text for row in table.rows if row[0].text] == ["reference", "alpha", "gamma_run", "delta"]
    assert [row[1].text for row in table.rows[:2]] == ["Δ", "PoI"]
    assert table.rows[2][2 + k].text == "+0.200"  # alpha's IoU change against beta


def test_cmd_report_errors_are_rigidbench_errors(tmp_path):
    from rigidbench.errors import RigidBenchError as UserError

    bad = argparse.Namespace(runs=[tmp_path / "nothing"], out=tmp_path / "out", baseline=None, resamples=200, seed=0)
    with pytest.raises(UserError, match="nothing: run directory does not exist"):
        cmd_report(bad)


def test_table_renderers_escape_model_names():
    from rigidbench.report.tables import Cell, Table

    table = Table("t", "T", "caption 100%", ("Model", "x"), ("", "down"),
                  ((Cell("a|b_c&d"), Cell("1.0", "[0.9, 1.1]", "n=3", "best")),))
    md, tex = to_markdown(table), to_latex(table)
    assert "a\\|b_c&d" in md and "**1.0** [0.9, 1.1] (n=3)" in md
    assert r"a|b\_c\&d" in tex and r"caption 100\%" in tex and r"\textbf{1.0}" in tex


def test_decimals_ignore_numerical_noise_beside_real_values():
    from rigidbench.report.tables import decimals_for

    assert decimals_for([8.2, 3e-5, 1e-9, 2e-12, 0.0]) == 2  # 8.20, not eight places for the noise
    assert decimals_for([0.9, 0.8, 1.0]) == 3  # 0.900
    assert decimals_for([0.0048, 0.0016, 0.0012]) == 5  # median 0.0016 -> 0.00160
    assert decimals_for([1e-12]) == 6 and decimals_for([0.0, float("nan")]) == 3


def test_scatter_labels_of_coinciding_models_do_not_overlap():
    """The demo's gamma and background-wobble share their means; their names must still be readable."""
    from rigidbench.report.figures import new_figure, place_labels

    fig = new_figure(7.0, 5.0)
    ax = fig.add_subplot()
    points = [(0.129, 0.807, "gamma"), (0.129, 0.804, "background-wobble"), (0.129, 0.805, "reference-like"),
              (0.188, 0.991, "slow"), (0.227, 0.991, "gravity"), (0.35, 0.989, "static")]
    ax.scatter([p[0] for p in points], [p[1] for p in points])
    ax.invert_xaxis()
    labels = place_labels(ax, points)
    assert sorted(a.get_text() for a in labels) == sorted(p[2] for p in points)
    renderer = fig.canvas.get_renderer()
    boxes = [a.get_window_extent(renderer) for a in labels]
    for i in range(len(boxes)):
        for j in range(i + 1, len(boxes)):
            assert not boxes[i].overlaps(boxes[j]), (labels[i].get_text(), labels[j].get_text())
    # a lone point keeps the nearest place: right of and above it
    assert next(a for a in labels if a.get_text() == "static").xyann == (5, 5)
