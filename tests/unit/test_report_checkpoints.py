"""The report's fine-tuned checkpoint section (paper appendix D) and its link to a probe report.

Run directories are written in the exact format `rigidbench evaluate` writes (example records, results.json
from `evaluate.aggregate`, run.json with the predictions directory); each predictions directory holds the
generation.json `rigidbench predict` writes, and each training checkpoint directory the checkpoint.json
`rigidbench train` writes. Scores are chosen so the paired changes against base Wan are known by hand.
"""

from __future__ import annotations

import csv
import json
from pathlib import Path

import numpy as np
import pytest

from rigidbench.cli import build_parser
from rigidbench.evaluation import aggregate
from rigidbench.metrics import METRICS
from rigidbench.report import build_report, load_runs
from rigidbench.report.analysis import analyse
from rigidbench.report.checkpoints import find_checkpoints
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
