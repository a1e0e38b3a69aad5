"""The report with several samples per example and a physical envelope (issue 34).

Run folders are written here as `rigidbench evaluate` writes them: one record per (example, sample)
(``examples/<id>.json`` sample 0, ``examples/<id>.s<k>.json`` sample k, each with its ``sample`` index),
results.json from `evaluation.aggregate`, and, for a run scored against an envelope, a hand-written
results.json "envelope" block. Every expected number is computed here from the test's own arrays with
numpy (means, seed std, best of K, envelope shares) or by calling rigidbench.stats on them (the
bootstrap intervals and the power table), never read back from the report's own intermediate values.
"""

from __future__ import annotations

import json
import math
from html.parser import HTMLParser
from pathlib import Path

import numpy as np
import pytest
from fixtures.report_files import read_csv, row_for

import rigidbench.report as report_pkg
from rigidbench.errors import ReportError
from rigidbench.evaluation import aggregate
from rigidbench.folders import sample_item
from rigidbench.metrics import METRICS
from rigidbench.report import build_report
from rigidbench.report.tables import column_decimals, fmt
from rigidbench.stats import (
    PairedVarianceComponents,
    bootstrap_ci,
    paired_difference,
    paired_variance_components,
    power_table,
    probability_of_improvement,
)

RESAMPLES = 400
N = 12
IDS = [f"{i:05d}" for i in range(N)]
TASKS = ["free_fall", "ball_chain", "bounce"] * 4
PARTITIONS = ["in_distribution"] * 6 + ["ood_scene"] * 6
MEASURED = ("ate3d", "iou")  # the hand-written envelope covers these two
MISSING_ENTRY = "00003"      # the envelope block has no entry for this example


def sample_values(seed: int, k: int, shift: float = 0.0) -> dict[str, np.ndarray]:
    """metric -> (N, k) scores: an example effect plus sample noise, positive, different per metric."""
    rng = np.random.default_rng(seed)
    out = {}
    for i, metric in enumerate(METRICS):
        example = rng.uniform(0.5, 2.0, size=(N, 1)) * (1 + i % 3)
        out[metric] = example + shift + rng.normal(0.0, 0.15, size=(N, k)) ** 2 + 0.05 * rng.uniform(size=(N, k))
    out["iou"] = np.clip(out["iou"] / out["iou"].max(), 0.0, 1.0)
    return out


def write_run(root: Path, model: str, values: dict[str, np.ndarray], envelope: dict | None = None,
              sample_field: bool = True) -> Path:
    """runs/<model>/ with one record per (example, sample); values: metric -> (N, K)."""
    run_dir = root / model
    (run_dir / "examples").mkdir(parents=True)
    records = []
    k_count = next(iter(values.values())).shape[1]
    for j, sample_id in enumerate(IDS):
        for k in range(k_count):
            record = {"id": sample_id, "model": model, "task": TASKS[j], "partition": PARTITIONS[j],
                      "frames_compared": 49, "perception": "gt",
                      "metrics": {m: float(values[m][j, k]) for m in METRICS}, "skipped": {}}
            if sample_field:
                record["sample"] = k
            (run_dir / "examples" / f"{sample_item(sample_id, k)}.json").write_text(json.dumps(record))
            records.append(record)
    results = {"model": model, "perception": "gt", "official": False, "n_examples": N, "n_reference": N,
               "failed": {}, "skipped_metrics": {}, **aggregate(records, tuple(METRICS)),
               "why_not_official": ["a test set"]}
    if envelope is not None:
        results["envelope"] = envelope
    (run_dir / "results.json").write_text(json.dumps(results))
    (run_dir / "run.json").write_text(json.dumps({"model": model, "perception": {"backend": "gt", "version": "1"}}))
    return run_dir


def envelope_block(values: dict[str, np.ndarray]) -> tuple[dict, dict[str, np.ndarray]]:
    """A hand-written results.json "envelope" block for a run with these values, and per metric its (N,) arrays
    of inside (1/0, NaN where the block has no entry), excess, q05, median and q95."""
    rng = np.random.default_rng(99)
    per_example: dict[str, dict] = {i: {} for i in IDS if i != MISSING_ENTRY}
    arrays = {}
    for metric in MEASURED:
        mean = values[metric].mean(axis=1)
        q05 = mean * rng.uniform(0.6, 1.1, N)
        q95 = q05 + rng.uniform(0.05, 0.6, N)
        median = (q05 + q95) / 2
        higher = METRICS[metric].higher_is_better
        excess = np.maximum(0.0, q05 - mean) if higher else np.maximum(0.0, mean - q95)
        inside = (excess == 0).astype(float)  # one-sided: better than every twin is inside (docs/statistics.md)
        for j, sample_id in enumerate(IDS):
            if sample_id in per_example:
                per_example[sample_id][metric] = {"q05": q05[j], "median": median[j], "q95": q95[j], "position": 0.5,
                                                  "excess": excess[j], "inside": bool(inside[j]), "twins": 4}
        missing = np.array([i == MISSING_ENTRY for i in IDS])
        arrays[metric] = {"inside": np.where(missing, np.nan, inside), "excess": np.where(missing, np.nan, excess),
                          "q05": q05, "median": median, "q95": q95}
    widths = {task: {m: 0.1 * (t + 1) * (k + 1) for k, m in enumerate(MEASURED)}
              for t, task in enumerate(("free_fall", "ball_chain", "bounce"))}
    block = {"source": "/envelopes/test", "twins": 4, "geometry_only": True, "scale": 1.0, "metrics": list(MEASURED),
             "overall": {}, "by_task": {}, "by_partition": {}, "per_example": per_example, "widths": widths}
    return block, arrays


@pytest.fixture(scope="module")
def world(tmp_path_factory) -> dict:
    """Two runs with two samples per example, 'alt' scored against a hand-written envelope; one report."""
    root = tmp_path_factory.mktemp("samples")
    base, alt = sample_values(1, 2), sample_values(2, 2, shift=0.1)
    block, env = envelope_block(alt)
    runs = [write_run(root / "runs", "base", base), write_run(root / "runs", "alt", alt, envelope=block)]
    page = build_report(runs, root / "out", resamples=RESAMPLES, seed=0, examples=0)
    return {"root": root, "runs": runs, "values": {"base": base, "alt": alt}, "env": env, "page": page,
            "out": page.parent}




def md_rows(path: Path) -> dict[str, list[str]]:
    """A Markdown table's body rows by their first cell."""
    out = {}
    for line in path.read_text().splitlines():
        if line.startswith("| ") and not line.startswith("| :--"):
            cells = [c.strip() for c in line.strip("|").split(" | ")]
            out.setdefault(cells[0], cells)
    return out


# ------------------------------------------------------------------------------ one sample per example


def test_one_sample_per_example_report_is_unchanged_by_the_samples_layer(tmp_path, monkeypatch):
    """K = 1 without an envelope: every file is byte-identical to the report built without the samples layer
    (read_samples returning None is the report as it was before samples existed)."""
    plain = [write_run(tmp_path / "a", "m1", sample_values(5, 1), sample_field=False),
             write_run(tmp_path / "a", "m2", sample_values(6, 1))]

    def files(out: Path) -> dict[str, bytes]:
        return {p.relative_to(out).as_posix(): p.read_bytes() for p in sorted(out.rglob("*")) if p.is_file()}

    def report(runs, out: Path) -> dict[str, bytes]:
        build_report(runs, out, resamples=RESAMPLES, seed=0, examples=0)
        return files(out)

    new = report(plain, tmp_path / "new")
    monkeypatch.setattr(report_pkg, "read_samples", lambda table: None)
    old = report(plain, tmp_path / "old")
    monkeypatch.undo()
    assert new.keys() == old.keys()
    assert [name for name in new if new[name] != old[name]] == []
    for name in ("tables/samples.csv", "tables/power.csv", "tables/best_of_k.md", "tables/envelope.md"):
        assert name not in new
    assert "±" not in new["report.html"].decode() and "Best of K" not in new["report.html"].decode()


# ------------------------------------------------------------------------------ several samples per example


def test_main_table_shows_mean_of_sample_means_and_seed_std(world):
    out, values = world["out"], world["values"]
    rows = read_csv(out / "tables" / "model_metrics.csv")
    samples = read_csv(out / "tables" / "samples.csv")
    md = md_rows(out / "tables" / "model_metrics.md")
    for k, metric in enumerate(METRICS):
        means = {}
        for model, arr in values.items():
            y = arr[metric]
            m_e = y.mean(axis=1)  # each example's sample mean
            mean, lo, hi = bootstrap_ci(m_e, n_resamples=RESAMPLES, seed=0)
            assert math.isclose(float(m_e.mean()), mean, rel_tol=1e-12)
            row = row_for(rows, model=model, metric=metric)
            assert math.isclose(float(row["mean"]), m_e.mean(), rel_tol=1e-12)
            assert math.isclose(float(row["ci_low"]), lo, rel_tol=1e-9)
            assert math.isclose(float(row["ci_high"]), hi, rel_tol=1e-9)
            seed_std = float(np.std(y.mean(axis=0), ddof=1))  # std over k of the whole-set mean of sample k
            within = math.sqrt(((y - m_e[:, None]) ** 2).sum() / N)  # K - 1 = 1 degree of freedom per example
            srow = row_for(samples, model=model, metric=metric)
            assert math.isclose(float(srow["seed_std"]), seed_std, rel_tol=1e-9)
            assert math.isclose(float(srow["within_example_std"]), within, rel_tol=1e-9)
            assert (srow["samples_min"], srow["samples_max"]) == ("2", "2")
            means[model] = (float(m_e.mean()), seed_std)
        scale = METRICS[metric].display_scale
        decimals = column_decimals(np.array([v[0] for v in means.values()]), metric)
        for model, (mean, std) in means.items():
            cell = md[model][1 + k]
            # the std keeps at least one significant digit where it is below the mean's last printed digit
            std_decimals = max(decimals, min(6, -math.floor(math.log10(std * scale))))
            assert f"{fmt(mean * scale, decimals)} ± {fmt(std * scale, std_decimals)}" in cell, (metric, cell)
    assert "seed std" in (out / "tables" / "model_metrics.md").read_text()


def test_best_of_k_is_a_separate_labelled_table(world):
    out, values = world["out"], world["values"]
    assert "best of" not in (out / "tables" / "model_metrics.md").read_text().lower().replace("the best of k samples "
                                                                                            "is in a table", "")
    text = (out / "tables" / "best_of_k.md").read_text()
    assert text.startswith("### Best of K samples per example (optimistic; not the headline)")
    samples = read_csv(out / "tables" / "samples.csv")
    headline = read_csv(out / "tables" / "model_metrics.csv")
    for model, arr in values.items():
        for metric in METRICS:
            y = arr[metric]
            best = y.max(axis=1) if METRICS[metric].higher_is_better else y.min(axis=1)
            _, lo, hi = bootstrap_ci(best, n_resamples=RESAMPLES, seed=0)
            row = row_for(samples, model=model, metric=metric)
            assert math.isclose(float(row["best_of_k_mean"]), best.mean(), rel_tol=1e-12)
            assert math.isclose(float(row["best_of_k_ci_low"]), lo, rel_tol=1e-9)
            assert math.isclose(float(row["best_of_k_ci_high"]), hi, rel_tol=1e-9)
            # never the headline: the model table's mean is the mean of sample means, which differs here
            assert float(row_for(headline, model=model, metric=metric)["mean"]) != pytest.approx(best.mean())
    html = world["page"].read_text()
    models_section = html.split('<section id="models">')[1].split("</section>")[0]
    samples_section = html.split('<section id="samples">')[1].split("</section>")[0]
    assert 'id="table-best_of_k"' not in models_section and 'id="table-best_of_k"' in samples_section
    assert "not the headline" in samples_section


def test_paired_comparisons_resample_examples_on_sample_means(world):
    out, values = world["out"], world["values"]
    rows = read_csv(out / "tables" / "paired_changes.csv")
    for metric in METRICS:
        a, b = values["alt"][metric].mean(axis=1), values["base"][metric].mean(axis=1)
        diff = paired_difference(a, b, n_resamples=RESAMPLES, seed=0)
        poi = probability_of_improvement(a, b, METRICS[metric].higher_is_better, n_resamples=RESAMPLES, seed=0)
        row = row_for(rows, model="alt", metric=metric)
        assert [float(row[c]) for c in ("diff_mean", "diff_ci_low", "diff_ci_high")] == pytest.approx(diff, rel=1e-9)
        assert [float(row[c]) for c in ("poi", "poi_ci_low", "poi_ci_high")] == pytest.approx(poi, rel=1e-9)


# ----------------------------------------------------------------------------------------------- envelope


def test_envelope_columns_from_the_hand_written_block(world):
    out, env = world["out"], world["env"]
    rows = read_csv(out / "tables" / "envelope.csv")
    assert {r["model"] for r in rows} == {"alt"}  # base was not scored against an envelope
    for metric in MEASURED:
        inside, excess = env[metric]["inside"], env[metric]["excess"]
        row = row_for(rows, model="alt", grouping="overall", group="all", metric=metric)
        assert float(row["inside"]) == pytest.approx(np.nanmean(inside), rel=1e-12)
        assert float(row["excess"]) == pytest.approx(np.nanmean(excess), rel=1e-12)
        assert int(row["n_examples"]) == N - 1
        for task in set(TASKS):
            sel = np.array([t == task for t in TASKS])
            row = row_for(rows, model="alt", grouping="task", group=task, metric=metric)
            assert float(row["inside"]) == pytest.approx(np.nanmean(inside[sel]), rel=1e-12)
            assert float(row["excess"]) == pytest.approx(np.nanmean(excess[sel]), rel=1e-12)
    md = md_rows(out / "tables" / "envelope.md")
    header = next(line for line in (out / "tables" / "envelope.md").read_text().splitlines() if line.startswith("| "))
    assert header.count(" inside") == len(MEASURED) and "ATE-3D excess" in header
    for i, metric in enumerate(m for m in METRICS if m in MEASURED):  # the columns follow the registry's order
        inside = np.nanmean(env[metric]["inside"])
        assert md["alt"][2 + 3 * i] == f"{100 * inside:.0f}% (n={N - 1})"
        assert md["base"][2 + 3 * i] == "—" and md["base"][3 + 3 * i] == "—"
    widths = read_csv(out / "tables" / "envelope_widths.csv")
    assert float(row_for(widths, task="ball_chain", metric="iou")["width"]) == pytest.approx(0.4)


def test_envelope_figure_is_a_valid_png_with_the_chosen_measurement(world, tmp_path):
    from matplotlib.image import imread

    png = world["out"] / "figures" / "envelope_ate3d.png"
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    image = imread(png)
    assert image.ndim == 3 and image.shape[0] > 100 and image.shape[1] > 100
    assert (world["out"] / "figures" / "envelope_ate3d.pdf").read_bytes()[:5] == b"%PDF-"
    assert "figures/envelope_ate3d.png" in world["page"].read_text()
    page = build_report(world["runs"][1:], tmp_path / "ssim", resamples=100, seed=0, examples=0,
                        envelope_metric="ssim")
    assert not list((page.parent / "figures").glob("envelope_*"))
    assert "does not measure" in (page.parent / "tables" / "envelope.md").read_text()
    with pytest.raises(ReportError, match="--envelope-metric 'speed' is not a measurement"):
        build_report(world["runs"], tmp_path / "bad", resamples=100, examples=0, envelope_metric="speed")


class _Refs(HTMLParser):
    def __init__(self):
        super().__init__()
        self.refs = []

    def handle_starttag(self, tag, attrs):
        self.refs += [v for k, v in attrs if k in ("href", "src") and v and not v.startswith("#")]


def test_every_file_the_page_references_exists(world):
    parser = _Refs()
    parser.feed(world["page"].read_text())
    for name in ("tables/power.csv", "tables/samples.csv", "tables/envelope.csv", "figures/envelope_ate3d.png"):
        assert name in parser.refs
    assert [r for r in parser.refs if not (world["out"] / r).is_file()] == []


# -------------------------------------------------------------------------------------------- power table


def _check_power_rows(rows: list[dict], model: str, components: dict, differences: dict) -> None:
    expected = power_table(components, n_examples=100, samples_per_example=(1, 2, 4, 8), differences=differences)
    assert len(expected) == 4 * len(components)
    for exp in expected:
        row = row_for(rows, model=model, metric=exp.measurement, samples_per_example=str(exp.samples_per_example))
        assert float(row["difference_variance"]) == pytest.approx(exp.difference_variance, rel=1e-12)
        assert float(row["min_detectable_difference"]) == pytest.approx(exp.min_detectable_difference, rel=1e-9)
        assert float(row["difference"]) == pytest.approx(exp.difference, rel=1e-12)
        assert int(row["examples_needed"]) == exp.examples_needed
        assert int(row["samples_needed"]) == exp.examples_needed * exp.samples_per_example


def test_power_table_between_two_runs_matches_stats_power(world):
    out, values = world["out"], world["values"]
    rows = read_csv(out / "tables" / "power.csv")
    components = {m: paired_variance_components(values["alt"][m], values["base"][m]) for m in METRICS}
    differences = {m: 0.10 * abs(values["base"][m].mean(axis=1).mean()) for m in METRICS}
    _check_power_rows(rows, "alt", components, differences)
    assert {r["assumption"] for r in rows} == {"paired"} and {r["baseline"] for r in rows} == {"base"}
    text = (out / "tables" / "power.md").read_text()
    assert "alt vs base" in text and "100 examples" in text and "10% of the baseline's mean" in text
    assert 'id="table-power"' in world["page"].read_text()


def test_power_table_of_one_run_doubles_its_own_variances(tmp_path):
    values = sample_values(7, 3)
    run = write_run(tmp_path / "runs", "solo", values)
    page = build_report([run], tmp_path / "out", resamples=100, seed=0, examples=0,
                        power_differences={"ate3d": 0.05})
    rows = read_csv(page.parent / "tables" / "power.csv")
    components, differences = {}, {}
    for metric in METRICS:
        y = values[metric]
        m_e = y.mean(axis=1)
        within = ((y - m_e[:, None]) ** 2).sum() / (N * 2)  # pooled, K - 1 = 2 per example
        between = max(np.var(m_e, ddof=1) - within / 3, 0.0)
        components[metric] = PairedVarianceComponents(2 * between, within, within, N, 2 * np.var(m_e, ddof=1),
                                                      (3, 3))
        differences[metric] = 0.05 if metric == "ate3d" else 0.10 * abs(m_e.mean())
    _check_power_rows(rows, "solo", components, differences)
    assert {r["assumption"] for r in rows} == {"one run doubled"}
    text = (page.parent / "tables" / "power.md").read_text()
    assert "solo, doubled" in text and "independent" in text and "--power-difference for ate3d" in text


def test_power_table_pairing_runs_of_one_and_two_samples_says_n_a(tmp_path):
    """A run of one sample per example has no within-example variance, and its variance of differences with a run
    of two samples holds at neither K = 1 nor K = 2 for both: every entry of that comparison is n/a."""
    runs = [write_run(tmp_path / "runs", "one", sample_values(3, 1)),
            write_run(tmp_path / "runs", "two", sample_values(4, 2))]
    page = build_report(runs, tmp_path / "out", resamples=100, seed=0, examples=0)
    rows = read_csv(page.parent / "tables" / "power.csv")
    assert len(rows) == 4 * len(METRICS) and {r["model"] for r in rows} == {"two"}
    assert {r["min_detectable_difference"] for r in rows} == {""} and {r["examples_needed"] for r in rows} == {""}
    assert "n/a" in (page.parent / "tables" / "power.md").read_text()


def test_cmd_report_power_difference_and_envelope_metric_options(world, tmp_path):
    import argparse

    from matplotlib.image import imread

    from rigidbench.commands.scoring import _report_arguments, cmd_report

    parser = argparse.ArgumentParser()
    _report_arguments(parser)
    args = parser.parse_args([str(world["runs"][1]), "--out", str(tmp_path / "cli"), "--resamples", "100",
                              "--examples", "0", "--envelope-metric", "iou", "--power-difference", "ate3d=0.2"])
    assert cmd_report(args) == 0
    rows = read_csv(tmp_path / "cli" / "tables" / "power.csv")
    assert float(row_for(rows, metric="ate3d", samples_per_example="1")["difference"]) == 0.2
    assert imread(tmp_path / "cli" / "figures" / "envelope_iou.png").ndim == 3
    assert not (tmp_path / "cli" / "figures" / "envelope_ate3d.png").exists()
    for bad, message in (("ate3d", "write METRIC=VALUE"), ("ate3d=-1", "positive number"),
                         ("speed=1", "not a measurement")):
        args.power_difference = [bad]
        with pytest.raises(ReportError, match=message):
            cmd_report(args)
