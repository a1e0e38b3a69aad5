"""A reduced `rigidbench demo`: the `test` preset and three predictors, end to end through the report."""

import json
import re
from pathlib import Path

import pytest
from fixtures.blender import requires_bpy

from rigidbench.cli import main

pytestmark = [pytest.mark.integration, requires_bpy]

TASKS = ("ball_chain", "bounce", "drop_into_cluster", "free_fall", "ramp_collision")


def _row(text: str, model: str) -> list[str]:
    line = next(line for line in text.splitlines() if line.startswith(model + " "))
    return line.split()[1:]


def test_reduced_demo_renders_scores_and_reports(tmp_path, capsys):
    out = tmp_path / "demo"
    status = main(["demo", "--out", str(out), "--quality", "test", "--modes", "reference", "static", "gamma",
                   "camera-shake"])
    text = capsys.readouterr().out
    assert status == 0, text
    # One rendered example per task.
    metas = [json.loads(p.read_text()) for p in sorted((out / "data" / "eval").glob("*/metadata.json"))]
    assert sorted(m["task"] for m in metas) == list(TASKS)
    # The printed table: the reference scores perfectly; the frozen clip loses IoU, gamma loses SSIM only.
    ref, static, gamma = (_row(text, m) for m in ("reference", "static", "gamma"))
    # IoU exact; SSIM just below 1: the default protocol (rigidbench-v1, the published evaluator's) passes
    # generated frames through JPEG q95 4:4:4, the reference's own included
    assert float(ref[0]) == 1.0 and 0.99 < float(ref[6]) < 1.0
    assert float(static[0]) < 0.9
    assert float(gamma[0]) == 1.0 and float(gamma[6]) < float(ref[6]) - 0.05
    for mode in ("reference", "static", "gamma", "camera-shake"):
        results = json.loads((out / "runs" / mode / "results.json").read_text())
        assert results["n_examples"] == 5 and not results["failed"]
    # camera-shake is generated twice per example (different shakes), and its seed spread is printed
    shaken = json.loads((out / "runs" / "camera-shake" / "results.json").read_text())
    assert shaken["samples"]["samples_per_example"] == {"min": 2, "max": 2} and shaken["n_examples"] == 5
    assert len(list((out / "predictions" / "camera-shake").glob("*.s1.mp4"))) == 5
    assert shaken["samples"]["metrics"]["ate"]["seed_std"] > 0  # two different shakes, not one copied
    assert "camera-shake: 2 samples per example" in text
    # The 4-twin geometry-only envelope: the reference inside on every example, the frozen clip outside on most
    envelope = json.loads((out / "envelope" / "envelope.json").read_text())
    assert envelope["twins"] == 4 and envelope["geometry_only"] and len(envelope["examples"]) == 5
    ref_env = json.loads((out / "runs" / "reference" / "results.json").read_text())["envelope"]["overall"]
    static_env = json.loads((out / "runs" / "static" / "results.json").read_text())["envelope"]["overall"]
    assert all(ref_env[m]["inside"] == 1.0 for m in ("iou", "ate", "ate3d")), ref_env
    assert all(static_env[m]["inside"] < 0.5 for m in ("iou", "ate")), static_env
    assert re.search(r"^\s+reference\s+1\.00\s+1\.00\s+1\.00$", text, re.M), text
    # Skipped measurements are explained, and the report's path is printed and exists.
    for metric in json.loads((out / "runs" / "reference" / "results.json").read_text())["skipped_metrics"]:
        assert re.search(rf"^\s+{metric}: \S", text, re.M), f"no reason printed for skipped {metric}"
    report = re.search(r"^report: (.+)$", text, re.M)
    assert report and (out / "report" / "report.html").samefile(report.group(1))
    # The demo's runs are no submission (issue 35): `submit --validate-only` names gt perception and the 5 examples
    capsys.readouterr()
    card = Path(__file__).resolve().parents[2] / "docs" / "card.example.yaml"
    assert main(["submit", str(out / "runs" / "reference"), "--card", str(card), "--validate-only"]) == 2
    refused = capsys.readouterr().err
    assert ": gt perception: " in refused and ": missing examples: 5 of the 100 examples" in refused, refused


def test_demo_rejects_an_unknown_mode(tmp_path, capsys):
    status = main(["demo", "--out", str(tmp_path), "--quality", "test", "--modes", "gravitee"])
    err = capsys.readouterr().err
    assert status == 2 and "gravitee" in err


def test_neural_demo_without_weights_stops_before_rendering(tmp_path, monkeypatch, capsys):
    hub_constants = pytest.importorskip("huggingface_hub.constants")
    torch = pytest.importorskip("torch")
    from rigidbench.perception import weights

    monkeypatch.setattr(hub_constants, "HF_HUB_CACHE", str(tmp_path / "hf"))
    monkeypatch.setattr(torch.hub, "_hub_dir", str(tmp_path / "torch_hub"))
    for w in weights.WEIGHTS.values():
        if w.env:
            monkeypatch.delenv(w.env, raising=False)
    out = tmp_path / "demo"
    status = main(["demo", "--out", str(out), "--quality", "test", "--perception", "neural"])
    err = capsys.readouterr().err
    assert status == 2 and "rigidbench weights --download sam2" in err
    assert not out.exists()  # nothing rendered
