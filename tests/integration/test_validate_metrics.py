"""rigidbench validate-metrics on one rendered free-fall example at the `test` preset."""

import csv
import json

import pytest
from fixtures.blender import render_eval_examples, requires_bpy

from rigidbench.perception.features import FeatureNets
from rigidbench.validation import validate_metrics

pytestmark = [pytest.mark.integration, requires_bpy]

NO_WEIGHTS = "test: no DINOv2 weights on this machine"


@pytest.fixture(scope="module")
def data_dir(tmp_path_factory):
    return render_eval_examples(tmp_path_factory.mktemp("data"), ("00015",))  # free fall


@pytest.fixture(scope="module")
def validation(data_dir, tmp_path_factory):
    out = tmp_path_factory.mktemp("validation")
    nets = FeatureNets(skipped={"lpips": "test: no AlexNet weights", "iddrift": NO_WEIGHTS})
    assert validate_metrics(data_dir, out, examples=10, severities=3, seed=0, nets=nets, trials=4, bg_trials=2,
                            progress=False) == out
    with open(out / "metric_validation.csv") as fh:
        rows = list(csv.DictReader(fh))
    return out, rows


def curve(rows, experiment, metric, condition):
    """(severity, mean) pairs of one curve in severity order."""
    picked = [r for r in rows if r["experiment"] == experiment and r["metric"] == metric
              and r["condition"] == condition]
    return sorted((float(r["severity"]), float(r["mean"]) if r["mean"] else float("nan")) for r in picked)


def test_writes_table_figure_and_summary(validation):
    out, rows = validation
    for name in ("metric_validation.csv", "metric_validation.md", "metric_validation.png", "metric_validation.pdf",
                 "summary.json"):
        assert (out / name).stat().st_size > 0, name
    summary = json.loads((out / "summary.json").read_text())
    assert summary["examples"] == ["00015 (free_fall)"]
    markdown = (out / "metric_validation.md").read_text()
    assert "ATE-3D" in markdown and "BGDrift" in markdown and NO_WEIGHTS in markdown


def test_ate3d_rises_equally_along_and_across_the_ray_while_2d_ate_stays_zero_along_it(validation):
    _, rows = validation
    along = curve(rows, "ate3d_ray", "ate3d", "along")
    across = curve(rows, "ate3d_ray", "ate3d", "across")
    assert [s for s, _ in along] == [0.0, 0.25, 0.5]
    assert along[0][1] == pytest.approx(0.0, abs=5e-3)
    assert along[0][1] < along[1][1] < along[2][1] and across[0][1] < across[1][1] < across[2][1]
    assert along[2][1] == pytest.approx(across[2][1], rel=0.1)
    assert all(abs(v) < 1e-9 for _, v in curve(rows, "ate3d_ray", "ate", "along"))
    ate_across = curve(rows, "ate3d_ray", "ate", "across")
    assert ate_across[0][1] == 0.0 < ate_across[1][1] < ate_across[2][1]


def test_bgdrift_follows_jitter_and_wobble_but_not_coherent_motion(validation):
    _, rows = validation
    jitter = [v for _, v in curve(rows, "bgdrift_motion", "bgdrift", "jitter")]
    translation = [v for _, v in curve(rows, "bgdrift_motion", "bgdrift", "translation")]
    assert jitter[0] < jitter[1] < jitter[2] and max(translation) < 1e-6
    wobble = [v for _, v in curve(rows, "metric_curve", "bgdrift", "main")]
    shake = [v for _, v in curve(rows, "metric_curve", "bgdrift", "control")]
    assert wobble[0] < wobble[1] < wobble[2] and wobble[2] > 10 * max(shake[2], 1e-4)


def test_skipped_iddrift_is_reported_and_pixel_l2_is_still_measured(validation):
    out, rows = validation
    swap = [r for r in rows if r["experiment"] == "iddrift_swap" and r["metric"] == "iddrift"]
    assert swap and all(r["mean"] == "" and r["note"] == f"skipped: {NO_WEIGHTS}" for r in swap)
    l2 = curve(rows, "iddrift_swap", "pixel_l2", "swap")
    assert l2[0][1] == 0.0 and l2[2][1] > 0.0
    assert json.loads((out / "summary.json").read_text())["skipped"]["iddrift"] == NO_WEIGHTS
    # One curve per measured metric, each saying which failure mode drove it (image-space only here).
    modes = {r["metric"]: r["mode"] for r in rows if r["experiment"] == "metric_curve" and r["condition"] == "main"}
    assert modes["ate3d"] == "slow" and modes["ssim"] == "gamma" and modes["bgdrift"] == "background-wobble"
    iou = [v for _, v in curve(rows, "metric_curve", "iou", "main")]
    assert iou[0] == 1.0 and iou[2] < iou[0]


def test_readout_curves_are_written_with_their_truths(validation):
    """validate-metrics adds the physics readouts under the failure modes that set them (issue 28): the
    playback-speed curve of `slow` follows 1 / (1 + s), and the flag cases name the flags they expect."""
    out, _ = validation
    with open(out / "readout_curves.csv") as fh:
        rows = list(csv.DictReader(fh))
    slow = [r for r in rows if r["mode"] == "slow" and r["readout"] == "speed"]
    assert [float(r["severity"]) for r in slow] == [0.0, 0.5, 1.0]
    for r in slow:
        assert float(r["truth"]) == pytest.approx(1 / (1 + float(r["severity"])))
    flags = {r["mode"]: r["truth"] for r in rows if r["readout"] == "flags"}
    assert flags == {"reference": "none", "static": "frozen", "camera-drift": "camera"}
    assert (out / "readout_curves.png").stat().st_size > 0
    summary = json.loads((out / "summary.json").read_text())
    assert summary["readouts"]["rows"] == len(rows) and any(line.startswith("readout speed under slow")
                                                            for line in summary["lines"])
