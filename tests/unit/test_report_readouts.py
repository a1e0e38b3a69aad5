"""The report's readout section: a table of each model's readouts and flag rates and a figure, from
runs evaluated on the synthetic published set (no Blender)."""

from __future__ import annotations

import json

import numpy as np
import pytest


from fixtures import published_set as ps  # noqa: E402

from rigidbench.driver import RunOptions  # noqa: E402
from rigidbench.perception.features import FeatureNets  # noqa: E402
from rigidbench.predictors import PredictContext  # noqa: E402
from rigidbench.report import build_report  # noqa: E402
from rigidbench.report.readouts import panel_values, readout_section  # noqa: E402
from rigidbench.stages.evaluate import evaluate  # noqa: E402
from rigidbench.stages.import_set import import_published  # noqa: E402
from rigidbench.stages.predict import predict  # noqa: E402


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    root = tmp_path_factory.mktemp("readout-report")
    ps.write_set(root / "src", n_frames=25)
    assert import_published(root / "src", root / "data", run=RunOptions(progress=False)).exit_status() == 0
    out = []
    for mode in ("reference", "static"):
        preds = root / "predictions" / mode
        predict(mode, root / "data" / "eval", preds, PredictContext(severity=1.0), run=RunOptions(progress=False))
        summary = evaluate(preds, root / "data", root / "runs" / mode, nets=FeatureNets(), run=RunOptions(progress=False))
        assert not summary.failed, summary.failed
        out.append(summary.root)
    return root, out


def test_the_section_has_a_row_per_model_and_the_flags_it_raised(runs, tmp_path):
    _, run_dirs = runs
    tables, figures = readout_section(run_dirs, tmp_path)
    (table,) = tables
    rows = {row[0].text: row for row in table.rows}
    assert set(rows) == {"reference", "static"}
    frozen = table.header.index("frozen")
    assert rows["static"][frozen].note.startswith("3/") and rows["reference"][frozen].note.startswith("0/")
    speed = table.header.index("s^")
    per_example = [json.loads(p.read_text())["readouts"]["speed"]["value"]
                   for p in sorted((run_dirs[0] / "examples").glob("*.readouts.json"))]
    assert float(rows["reference"][speed].text) == pytest.approx(np.median(per_example), rel=1e-2)
    (figure,) = figures
    assert figure.png.stat().st_size > 1000 and figure.pdf.exists()


def test_panel_values_are_relative_to_the_truth(runs):
    _, run_dirs = runs
    examples = [json.loads(p.read_text()) for p in sorted((run_dirs[0] / "examples").glob("*.readouts.json"))]
    speeds = panel_values(examples, "speed")
    raw = [e["readouts"]["speed"]["value"] for e in examples]
    np.testing.assert_allclose(np.sort(speeds), np.sort([v for v in raw if v is not None]))
    gravity = panel_values(examples, "gravity")
    assert gravity.size and np.all(np.abs(gravity - 1.0) < 0.1)  # the synthetic balls fall at 9.81 m/s^2


def test_panel_values_on_hand_built_examples():
    """Ratios against the simulated g, differences against the simulated rebound; undefined ones left out."""
    def example(speed, g, g_sim, per_speed2, e, e_sim):
        return {"readouts": {"speed": {"value": speed},
                             "gravity": {"value": g, "simulated": g_sim, "per_speed2": per_speed2},
                             "restitution": {"value": e, "reference": e_sim}}}

    examples = [example(0.5, 3.0, 2.0, 12.0, 0.4, 0.3), example(None, None, 2.0, None, 0.1, None)]
    np.testing.assert_allclose(panel_values(examples, "speed"), [0.5])
    np.testing.assert_allclose(panel_values(examples, "gravity"), [1.5])
    np.testing.assert_allclose(panel_values(examples, "gravity_per_speed2"), [6.0])
    np.testing.assert_allclose(panel_values(examples, "restitution"), [0.1])


def test_the_report_page_shows_the_section(runs, tmp_path):
    _, run_dirs = runs
    page = build_report(run_dirs, tmp_path / "report", resamples=200, examples=0).read_text()
    assert "Physics readouts" in page and "readouts.png" in page
