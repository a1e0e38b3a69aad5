"""The report's fine-tuned checkpoint section (paper appendix D) and its link to a probe report.

Run directories are written in the exact format `rigidbench evaluate` writes (example records, results.json
from `evaluate.aggregate`, run.json with the predictions directory); each predictions directory holds the
generation.json `rigidbench predict` writes, and each training checkpoint directory the checkpoint.json
`rigidbench train` writes. Scores are chosen so the paired changes against base Wan are known by hand.
"""

from __future__ import annotations

import csv
import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest

from rigidbench.cli import build_parser
from rigidbench.evaluation import aggregate
from rigidbench.metrics import METRICS
from rigidbench.report import build_report, load_runs
from rigidbench.report.analysis import analyse
from rigidbench.report.checkpoints import (
    checkpoint_tables,
    find_checkpoints,
    selected_breakdown_table,
    selected_paired_table,
)
from rigidbench.report.tables import fmt, interval_text
from rigidbench.stats import paired_difference

RESAMPLES = 300
N = 6
IDS = [f"{i:05d}" for i in range(N)]
TASKS = ["free_fall", "bounce", "ball_chain"] * 2
PARTITIONS = ["in_distribution"] * 3 + ["ood_scene"] * 3
BASE_ATE3D = [2.0, 3.0, 1.0, 4.0, 2.5, 1.5]
# Per-example ATE-3D change of each checkpoint against base; the means are the paired changes.
ATE3D_CHANGE = {"lora-500": [-0.5, -0.5, -0.2, -0.8, -0.3, -0.5],      # mean -0.4667
                "lora-1000": [-1.0, -0.6, -0.4, -1.2, -0.6, -0.2],     # mean -0.6667
                "full-500": [0.1, -0.1, 0.3, 0.0, 0.2, 0.1],           # mean +0.1
                "full-1000": [-0.3, -0.3, -0.3, -0.3, -0.3, -0.3]}     # mean -0.3
IOU_CHANGE = {"lora-500": 0.01, "lora-1000": 0.03, "full-500": -0.02, "full-1000": 0.02}


def write_run(root: Path, model: str, scores: dict[str, list], predictions: Path | None) -> Path:
    """runs/<model>/ as evaluate writes it, run.json recording the predictions directory."""
    run_dir = root / "runs" / model
    (run_dir / "examples").mkdir(parents=True)
    records = []
    for j, sample_id in enumerate(IDS):
        record = {"id": sample_id, "model": model, "task": TASKS[j], "partition": PARTITIONS[j],
                  "frames_compared": 49, "input_key": "k" * 64, "perception": "gt",
                  "metrics": {m: scores[m][j] for m in METRICS}, "skipped": {}}
        (run_dir / "examples" / f"{sample_id}.json").write_text(json.dumps(record, indent=2, allow_nan=False))
        records.append(record)
    results = {"model": model, "perception": "gt", "official": False, "n_examples": N, "n_reference": N,
               "failed": {}, "skipped_metrics": {}, **aggregate(records, tuple(METRICS)),
               "why_not_official": ["the reference directory holds 6 examples, not the 100 of the eval split"]}
    (run_dir / "results.json").write_text(json.dumps(results, indent=2, allow_nan=False))
    run = {"model": model, "predictions": str(predictions) if predictions else "", "data": str(root / "data"),
           "perception": {"backend": "gt", "version": "1"}, "finished_at": "2026-01-01T00:00:00"}
    (run_dir / "run.json").write_text(json.dumps(run, indent=2))
    return run_dir


def write_predictions(root: Path, name: str, predictor: str, checkpoint: dict | None) -> Path:
    """predictions/<name>/generation.json as predict writes it (settings and model both name the checkpoint)."""
    pred = root / "predictions" / name
    pred.mkdir(parents=True)
    settings_ckpt = None if checkpoint is None else {k: checkpoint[k] for k in ("kind", "path", "files")}
    doc = {"predictor": predictor, "target": "rigidbench.predictors.wan:Wan22", "kind": "local",
           "settings": {"predictor": predictor, "seed": 0, "source": "hub", "model": "Wan-AI/Wan2.2-TI2V-5B-Diffusers",
                        "steps": 50, "checkpoint": settings_ckpt},
           "model": {"source": "hub", "pipeline_class": "diffusers.WanImageToVideoPipeline",
                     "checkpoint": None if checkpoint is None else {**checkpoint, "description": "x"}},
           "versions": {}, "examples": {}}
    (pred / "generation.json").write_text(json.dumps(doc, indent=1))
    return pred


def write_checkpoint(root: Path, run: str, step: int, mode: str, with_json: bool = True) -> dict:
    """RUN/checkpoints/step-N/ with checkpoint.json (as train writes it); returns the predictor's record."""
    ckpt = root / "train" / run / "checkpoints" / f"step-{step}"
    ckpt.mkdir(parents=True)
    if with_json:
        (ckpt / "checkpoint.json").write_text(json.dumps(
            {"step": step, "mode": mode, "model": "wan-2.2", "config_digest": "d" * 16, "world_size": 8,
             "examples_seen": step * 128}, indent=1))
    kind = "lora-peft" if mode == "lora" else "transformer-dir"
    return {"kind": kind, "path": str(ckpt.resolve()), "weights": str(ckpt.resolve()),
            "files": {"adapter_model.safetensors": {"sha256": "0" * 64}}}


def scores_for(name: str) -> dict[str, list]:
    rng = np.random.default_rng(sum(map(ord, name)))
    scores = {m: [float(v) for v in rng.uniform(0.2, 0.6, N)] for m in METRICS}
    scores["ate3d"] = list(BASE_ATE3D)
    scores["iou"] = [0.5] * N
    if name in ATE3D_CHANGE:
        scores["ate3d"] = [b + d for b, d in zip(BASE_ATE3D, ATE3D_CHANGE[name])]
        scores["iou"] = [0.5 + IOU_CHANGE[name]] * N
    return scores


@pytest.fixture(scope="module")
def sweep_root(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("sweep")
    write_run(root, "wan-2.2", scores_for("base"), write_predictions(root, "wan-2.2", "wan-2.2", None))
    for name, run, step, mode, with_json in (("lora-500", "lora", 500, "lora", True),
                                             ("lora-1000", "lora", 1000, "lora", True),
                                             ("full-1000", "full", 1000, "full", True),
                                             ("full-500", "full", 500, "full", False)):  # step from the name
        record = write_checkpoint(root, run, step, mode, with_json)
        write_run(root, name, scores_for(name), write_predictions(root, name, "wan-2.2", record))
    # Another model whose predictions directory is not on this machine: left unclassified.
    write_run(root, "cosmos", scores_for("cosmos"), root / "elsewhere" / "cosmos")
    return root


def run_dirs(root: Path, names) -> list[Path]:
    return [root / "runs" / n for n in names]


ALL = ["wan-2.2", "lora-500", "lora-1000", "full-1000", "full-500", "cosmos"]


def test_find_checkpoints_steps_runs_and_paired_changes(sweep_root):
    data = analyse(load_runs(run_dirs(sweep_root, ALL)), resamples=RESAMPLES, seed=0)
    sweep = find_checkpoints(data)
    assert sweep is not None
    assert sweep.runs == ("LoRA", "Full FT")
    assert [(c.run, c.step, c.name, c.mode) for c in sweep.checkpoints] == [
        ("LoRA", 500, "lora-500", "lora"), ("LoRA", 1000, "lora-1000", "lora"),
        ("Full FT", 500, "full-500", "full"), ("Full FT", 1000, "full-1000", "full")]
    assert data.table.models[sweep.base] == "wan-2.2"
    k, ki = data.table.metric_index("ate3d"), data.table.metric_index("iou")
    want = {"lora-500": -0.4666667, "lora-1000": -0.6666667, "full-500": 0.1, "full-1000": -0.3}
    for i, c in enumerate(sweep.checkpoints):
        assert sweep.diff.mean[i, k] == pytest.approx(want[c.name], abs=1e-6)
        assert sweep.diff.mean[i, ki] == pytest.approx(IOU_CHANGE[c.name], abs=1e-9)
        # The same interval as the stats package's paired difference on these examples.
        a = np.array([b + d for b, d in zip(BASE_ATE3D, ATE3D_CHANGE[c.name])])
        mean, lo, hi = paired_difference(a, np.array(BASE_ATE3D), n_resamples=RESAMPLES, seed=0)
        assert (sweep.diff.mean[i, k], sweep.diff.lo[i, k], sweep.diff.hi[i, k]) == pytest.approx((mean, lo, hi))
    # Lowest ATE-3D per run: LoRA step 1000, full step 1000.
    assert [sweep.checkpoints[i].name for i in sweep.selected] == ["lora-1000", "full-1000"]
    assert any("cosmos" in n for n in sweep.notes)


def test_report_shows_checkpoint_section(sweep_root, tmp_path):
    page = build_report(run_dirs(sweep_root, ALL), tmp_path / "report", resamples=RESAMPLES, examples=0)
    text = page.read_text()
    assert '<section id="checkpoints">' in text and 'href="#checkpoints"' in text
    assert "figures/metric_vs_step.png" in text
    assert (tmp_path / "report" / "figures" / "metric_vs_step.png").stat().st_size > 0
    assert (tmp_path / "report" / "figures" / "metric_vs_step.pdf").exists()
    assert 'id="table-checkpoint_sweep"' in text and 'id="table-checkpoint_paired"' in text
    section = text[text.index('<section id="checkpoints">'):]
    section = section[:section.index("</section>")]
    assert "1,000" in section and "Full FT" in section and "LoRA" in section
    # Paired ATE-3D changes as printed (two decimals at this magnitude) with their intervals.
    paired = section[section.index('id="table-checkpoint_paired"'):]
    for printed in ("-0.467", "-0.667", "+0.100", "-0.300"):
        assert printed in paired, printed
    with open(tmp_path / "report" / "tables" / "checkpoint_sweep.csv", newline="") as fh:
        rows = list(csv.DictReader(fh))
    got = {(r["training_run"], r["step"]): float(r["diff_mean"]) for r in rows if r["metric"] == "ate3d"
           and r["diff_mean"]}
    assert got == pytest.approx({("LoRA", "500"): -0.4666667, ("LoRA", "1000"): -0.6666667,
                                 ("Full FT", "500"): 0.1, ("Full FT", "1000"): -0.3}, abs=1e-6)
    assert {r["model"] for r in rows if r["training_run"] == "base"} == {"wan-2.2"}
    md = (tmp_path / "report" / "report.md").read_text()
    assert "Complete checkpoint sweep" in md and "Paired changes against base Wan" in md
    # The selected checkpoints' tables land on the page, in report.md and as .md/.tex files.
    for key, title in (("checkpoint_selected_paired", "Paired changes for the selected checkpoints"),
                       ("checkpoint_selected_tasks", "Selected checkpoints by task"),
                       ("checkpoint_selected_partitions", "Selected checkpoints by evaluation partition")):
        assert f'id="table-{key}"' in section, key
        assert title in md
        assert (tmp_path / "report" / "tables" / f"{key}.md").read_text().startswith(f"### {title}")
        assert f"label{{tab:{key.replace('_', '-')}}}" in (tmp_path / "report" / "tables" / f"{key}.tex").read_text()


def test_no_checkpoint_runs_no_section(sweep_root, tmp_path):
    page = build_report(run_dirs(sweep_root, ["wan-2.2", "cosmos"]), tmp_path / "report", resamples=RESAMPLES,
                        examples=0)
    text = page.read_text()
    assert 'id="checkpoints"' not in text and "metric_vs_step" not in text
    assert not (tmp_path / "report" / "tables" / "checkpoint_sweep.csv").exists()


def test_checkpoints_without_base_have_curves_but_no_paired_table(sweep_root, tmp_path):
    page = build_report(run_dirs(sweep_root, ["lora-500", "lora-1000"]), tmp_path / "report", resamples=RESAMPLES,
                        examples=0)
    text = page.read_text()
    assert '<section id="checkpoints">' in text and "metric_vs_step.png" in text
    assert 'id="table-checkpoint_paired"' not in text
    assert "No base run" in text
    # One selected checkpoint and no base: nothing to pair, but its task and partition means are shown.
    assert 'id="table-checkpoint_selected_paired"' not in text
    assert 'id="table-checkpoint_selected_tasks"' in text and 'id="table-checkpoint_selected_partitions"' in text


def test_probe_report_link(sweep_root, tmp_path):
    probe = tmp_path / "probe"
    probe.mkdir()
    (probe / "report.html").write_text("<html></html>")
    out = tmp_path / "report"
    page = build_report(run_dirs(sweep_root, ["wan-2.2", "cosmos"]), out, resamples=RESAMPLES, examples=0,
                        probe_report=probe)
    text = page.read_text()
    assert 'Probe report: <a href="../probe/report.html">' in text
    assert (out / "../probe/report.html").resolve() == (probe / "report.html").resolve()
    assert "Probe report: [../probe/report.html]" in (out / "report.md").read_text()
    page = build_report(run_dirs(sweep_root, ["wan-2.2", "cosmos"]), tmp_path / "plain", resamples=RESAMPLES,
                        examples=0)
    assert "Probe report" not in page.read_text()


def test_cli_probe_report_option(tmp_path):
    args = build_parser().parse_args(["report", "runs/a", "--probe-report", str(tmp_path / "probe.html")])
    assert args.probe_report == tmp_path / "probe.html"
    assert build_parser().parse_args(["report", "runs/a"]).probe_report is None


# ------------------------------------------------------------------ the selected checkpoints' tables
# Selected: lora-1000 and full-1000 (lowest mean ATE-3D of each run). Their ATE-3D per example:
LORA_1000 = [b + d for b, d in zip(BASE_ATE3D, ATE3D_CHANGE["lora-1000"])]   # 1.0 2.4 0.6 2.8 1.9 1.3
FULL_1000 = [b + d for b, d in zip(BASE_ATE3D, ATE3D_CHANGE["full-1000"])]   # 1.7 2.7 0.7 3.7 2.2 1.2


@pytest.fixture(scope="module")
def all_data(sweep_root):
    data = analyse(load_runs(run_dirs(sweep_root, ALL)), resamples=RESAMPLES, seed=0)
    return data, find_checkpoints(data)


def _row(table, label: str):
    return next(row for row in table.rows if row[0].text == label)


def test_selected_paired_table_columns_and_checkpoint_difference(all_data):
    data, sweep = all_data
    tb = selected_paired_table(data, sweep)
    assert tb.key == "checkpoint_selected_paired"
    assert tb.header == ("Metric", "LoRA 1,000 − base", "Full FT 1,000 − base", "Full FT − LoRA")
    # Metrics are the rows, in the table's metric order.
    assert [row[0].text.rsplit(" ", 1)[0] for row in tb.rows][:2] == ["IoU", "L2"]
    ate = _row(tb, "ATE-3D ↓")
    # Against base: the same numbers as the every-checkpoint table (means -0.6667 and -0.3).
    assert [c.text for c in ate[1:3]] == ["-0.667", "-0.300"]
    # Full FT - LoRA per example: 0.7 0.3 0.1 0.9 0.3 -0.1, mean 2.2 / 6.
    per_example = np.array(FULL_1000) - np.array(LORA_1000)
    assert per_example.mean() == pytest.approx(2.2 / 6)
    mean, lo, hi = paired_difference(np.array(FULL_1000), np.array(LORA_1000), n_resamples=RESAMPLES, seed=0)
    assert mean == pytest.approx(2.2 / 6)
    assert ate[3].text == "+0.367" == fmt(2.2 / 6, 3, signed=True)
    assert ate[3].detail == interval_text(lo, hi, 3, signed=True)
    assert lo > 0 and ate[3].mark == "significant"
    # IoU: constant per-example changes +0.03 and +0.02, so Full FT - LoRA is exactly -0.01 and significant.
    iou = _row(tb, "IoU ↑")
    assert [c.text for c in iou[1:]] == ["+0.0300", "+0.0200", "-0.0100"]
    assert all(c.mark == "significant" for c in iou[1:])
    # Bold exactly where the interval excludes 0 (the "- base" columns are the sweep's paired intervals).
    for k, row in enumerate(tb.rows):
        for col, i in enumerate(sweep.selected, start=1):
            excludes = sweep.diff.lo[i, k] > 0 or sweep.diff.hi[i, k] < 0
            assert (row[col].mark == "significant") == excludes, (row[0].text, col)
    assert any(row[1].mark == "" for row in tb.rows)   # some intervals straddle 0 in this fixture

    # Swapping the two selections swaps the column's label and flips the sign (and mirrors the interval).
    swapped = selected_paired_table(data, dataclasses.replace(sweep, selected=tuple(reversed(sweep.selected))))
    assert swapped.header[-1] == "LoRA − Full FT"
    back = _row(swapped, "ATE-3D ↓")[-1]
    assert back.text == "-0.367"
    assert back.detail == interval_text(-hi, -lo, 3, signed=True)


def test_selected_paired_table_one_run_or_no_base(sweep_root):
    # One training run: only its "- base" column, no checkpoint-vs-checkpoint column.
    data = analyse(load_runs(run_dirs(sweep_root, ["wan-2.2", "lora-500", "lora-1000"])), resamples=RESAMPLES, seed=0)
    tb = selected_paired_table(data, find_checkpoints(data))
    assert tb.header == ("Metric", "LoRA 1,000 − base")
    assert _row(tb, "ATE-3D ↓")[1].text == "-0.667"
    # Two runs without a base: only the checkpoint-vs-checkpoint column.
    data = analyse(load_runs(run_dirs(sweep_root, ["lora-500", "lora-1000", "full-500", "full-1000"])),
                   resamples=RESAMPLES, seed=0)
    tb = selected_paired_table(data, find_checkpoints(data))
    assert tb.header == ("Metric", "Full FT − LoRA")
    assert _row(tb, "ATE-3D ↓")[1].text == "+0.367"
    # One run without a base: no table.
    data = analyse(load_runs(run_dirs(sweep_root, ["lora-500", "lora-1000"])), resamples=RESAMPLES, seed=0)
    sweep = find_checkpoints(data)
    assert selected_paired_table(data, sweep) is None
    tasks = selected_breakdown_table(data, sweep, "task")
    assert [row[0].text for row in tasks.rows] == ["LoRA 1,000"]
    assert all(c.mark == "" for c in tasks.rows[0][1:])  # a single row is never marked


def test_selected_tasks_table_means_and_marks(all_data):
    data, sweep = all_data
    tb = selected_breakdown_table(data, sweep, "task")
    assert tb.key == "checkpoint_selected_tasks"
    # Report task order; the examples are free_fall, bounce, ball_chain twice (indices j and j + 3).
    assert tb.header == ("Model", "Ball chain", "Bounce", "Free fall")
    assert tb.groups == (("ATE-3D ↓", 3),)
    # Ball chain (examples 2, 5): base (1.0 + 1.5) / 2, LoRA (0.6 + 1.3) / 2, full (0.7 + 1.2) / 2, and so on.
    want = {"Base": ["1.25", "2.75", "3.00"], "LoRA 1,000": ["0.95", "2.15", "1.90"],
            "Full FT 1,000": ["0.95", "2.45", "2.70"]}
    assert {row[0].text: [c.text for c in row[1:]] for row in tb.rows} == want
    assert np.mean([LORA_1000[2], LORA_1000[5]]) == pytest.approx(0.95)
    assert np.mean([FULL_1000[0], FULL_1000[3]]) == pytest.approx(2.7)
    marks = {row[0].text: [c.mark for c in row[1:]] for row in tb.rows}
    # Ball chain: LoRA and full tie at 0.95 as printed, so nothing is marked (not even base below them).
    assert marks == {"Base": ["", "", ""], "LoRA 1,000": ["", "best", "best"],
                     "Full FT 1,000": ["", "second", "second"]}


def test_selected_partitions_table_means_and_marks(all_data):
    data, sweep = all_data
    tb = selected_breakdown_table(data, sweep, "partition")
    assert tb.key == "checkpoint_selected_partitions"
    assert tb.header == ("Model", "ID", "Scene", "ID", "Scene")
    assert tb.groups == (("ATE-3D ↓", 2), ("SSIM ↑", 2))
    rows = {row[0].text: row[1:] for row in tb.rows}
    assert list(rows) == ["Base", "LoRA 1,000", "Full FT 1,000"]
    # ATE-3D: ID is examples 0-2, Scene 3-5.
    assert [c.text for c in rows["Base"][:2]] == ["2.00", "2.67"]            # 6 / 3, 8 / 3
    assert [c.text for c in rows["LoRA 1,000"][:2]] == ["1.33", "2.00"]      # 4 / 3, 6 / 3
    assert [c.text for c in rows["Full FT 1,000"][:2]] == ["1.70", "2.37"]   # 5.1 / 3, 7.1 / 3
    assert [c.mark for c in rows["LoRA 1,000"][:2]] == ["best", "best"]
    assert [c.mark for c in rows["Full FT 1,000"][:2]] == ["second", "second"]
    assert [c.mark for c in rows["Base"][:2]] == ["", ""]
    # SSIM: the mean of each partition's examples from the fixture's scores; the highest is bold.
    names = {"Base": "base", "LoRA 1,000": "lora-1000", "Full FT 1,000": "full-1000"}
    for g, part in enumerate((slice(0, 3), slice(3, 6))):
        means = {label: float(np.mean(scores_for(name)["ssim"][part])) for label, name in names.items()}
        for label, value in means.items():
            assert rows[label][2 + g].text == f"{value:.3f}"
        ordered = sorted(means, key=means.get, reverse=True)
        assert len({round(v, 3) for v in means.values()}) == 3   # no tie as printed in this fixture
        assert rows[ordered[0]][2 + g].mark == "best" and rows[ordered[1]][2 + g].mark == "second"
        assert rows[ordered[2]][2 + g].mark == ""


def test_selected_tables_drop_a_skipped_metric(all_data):
    data, _ = all_data
    t = data.table
    k = t.metric_index("ssim")
    skipped = t.skipped.copy()
    skipped[:, k] = True
    scores = t.scores.copy()
    scores[:, :, k] = np.nan
    data = analyse(dataclasses.replace(t, skipped=skipped, scores=scores), resamples=RESAMPLES, seed=0)
    sweep = find_checkpoints(data)
    tb = selected_breakdown_table(data, sweep, "partition")
    assert tb.groups == (("ATE-3D ↓", 2),) and tb.header == ("Model", "ID", "Scene")
    assert [c.text for c in _row(selected_paired_table(data, sweep), "SSIM ↑")[1:]] == ["skipped"] * 3


def test_selected_tables_absent_without_selected_checkpoints(all_data):
    data, sweep = all_data
    none = dataclasses.replace(sweep, selected=())
    assert selected_paired_table(data, none) is None
    assert selected_breakdown_table(data, none, "task") is None
    assert selected_breakdown_table(data, none, "partition") is None
    assert [tb.key for tb in checkpoint_tables(data, none)] == ["checkpoint_sweep", "checkpoint_paired"]
    assert [tb.key for tb in checkpoint_tables(data, sweep)] == [
        "checkpoint_sweep", "checkpoint_paired", "checkpoint_selected_paired", "checkpoint_selected_tasks",
        "checkpoint_selected_partitions"]
