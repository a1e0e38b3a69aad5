"""Extending RigidBench: a metric or a predictor is one module plus one registration, and then it is
everywhere (evaluate's output, the demo table, the report); a bug inside a metric stops the run."""

import json

import numpy as np
import pytest
from fixtures.blender import render_eval_examples, requires_bpy

from rigidbench.driver import RunOptions
from rigidbench.flows.demo import format_table
from rigidbench.metrics import METRICS, MetricInfo, MetricResult
from rigidbench.perception.features import FeatureNets
from rigidbench.predictors import PREDICTORS, Kind, PredictContext, Predictor, PredictorInfo
from rigidbench.predictors.image_space import reference
from rigidbench.report import build_report
from rigidbench.stages.evaluate import evaluate
from rigidbench.stages.predict import predict

pytestmark = [pytest.mark.integration, requires_bpy]


# -- a toy metric and a toy predictor, as a user would write them in their own module ---------------


def mean_abs_difference(x) -> MetricResult:
    """Mean absolute RGB difference in [0, 1], per frame and overall."""
    diff = np.abs(x.ref_rgb.astype(np.float64) - x.gen_rgb.astype(np.float64)).mean(axis=(1, 2, 3)) / 255.0
    return MetricResult(float(diff.mean()), diff)


def broken_metric(x) -> MetricResult:
    return MetricResult(len(x), None)  # a bug: MetricInputs has no len()


def inverted(sample, ctx):
    """The reference with inverted colours after its first frame; the world state it shows is the reference's."""
    pred = reference(sample, 0.0)
    pred.frames[1:] = 255 - pred.frames[1:]
    return pred


TOY_METRIC = MetricInfo("mad", f"{__name__}:mean_abs_difference", "MAD", False, "appearance",
                        "mean absolute RGB difference", ("gamma",))
TOY_PREDICTOR = PredictorInfo("inverted", f"{__name__}:inverted", "colours inverted", Kind.PLUGIN, writes_state=True)


@pytest.fixture(scope="module")
def data_dir(tmp_path_factory):
    return render_eval_examples(tmp_path_factory.mktemp("data"), ("00015",))


def test_a_registered_metric_and_predictor_appear_in_every_output(data_dir, tmp_path):
    with METRICS.added(TOY_METRIC), PREDICTORS.added(TOY_PREDICTOR):
        runs, table = [], {}
        for name in ("reference", "inverted"):
            preds = tmp_path / "predictions" / name
            run = predict(name, data_dir, preds, PredictContext(severity=0.0), run=RunOptions(progress=False))
            assert run.succeeded == ["00015"] and not run.failed
            summary = evaluate(preds, data_dir, tmp_path / "runs" / name, nets=FeatureNets(),
                               protocol="lossless", run=RunOptions(progress=False))  # the toy metric is hand-computed on the decoded frames
            assert not summary.failed
            table[name] = [summary.facts.results["overall"][m]["mean"] for m in METRICS]
            runs.append(summary.root)
        record = json.loads((tmp_path / "runs" / "inverted" / "examples" / "00015.json").read_text())
        frames = np.load(tmp_path / "runs" / "inverted" / "examples" / "00015.npz")["mad"]
        # Hand-computed: inverting colours moves every channel value v to 255 - v, |v - (255 - v)| = |2v - 255|
        # (frame 0 is left as given, so the prediction passes the first-frame check).
        from rigidbench.groundtruth.bundle import Sample

        ref = Sample(data_dir / "00015").frames.astype(np.float64)
        expected = (np.abs(2 * ref - 255).mean(axis=(1, 2, 3)) / 255.0)
        expected[0] = 0.0
        assert record["metrics"]["mad"] == pytest.approx(expected.mean(), rel=1e-9)
        np.testing.assert_allclose(frames, expected, rtol=1e-9)
        assert json.loads((tmp_path / "runs" / "reference" / "results.json").read_text())["overall"]["mad"]["mean"] == 0
        text = format_table(table)
        assert text.splitlines()[0].split()[-1] == "MAD" and text.splitlines()[2].startswith("inverted")
        page = build_report(runs, tmp_path / "report", resamples=200, seed=0)
        html = page.read_text()
        assert "MAD" in html and "inverted" in html  # the model-comparison table's new column and row
    assert "mad" not in METRICS and "inverted" not in PREDICTORS


def test_a_bug_inside_a_metric_stops_evaluate(data_dir, tmp_path):
    preds = tmp_path / "predictions" / "reference"
    predict("reference", data_dir, preds, PredictContext(severity=0.0), run=RunOptions(progress=False))
    with METRICS.added(MetricInfo("broken", f"{__name__}:broken_metric", "Broken", False, "appearance", "a bug")):
        with pytest.raises(TypeError, match="has no len"):
            evaluate(preds, data_dir, tmp_path / "runs" / "reference", nets=FeatureNets(), run=RunOptions(progress=False))


def test_a_bad_example_is_recorded_and_the_run_goes_on(data_dir, tmp_path):
    preds = tmp_path / "predictions" / "broken-video"
    preds.mkdir(parents=True)
    (preds / "00015.mp4").write_bytes(b"not a video")
    summary = evaluate(preds, data_dir, tmp_path / "runs" / "broken", nets=FeatureNets(), run=RunOptions(progress=False))
    assert list(summary.failed) == ["00015"] and "00015.mp4" in summary.failed["00015"]


def test_the_readme_plugin_example_runs_as_written(data_dir, tmp_path, monkeypatch, capsys):
    """The 'Your own model' example of README.md, copied verbatim into a module and run through the CLI."""
    import re
    from pathlib import Path

    from rigidbench.cli import main
    from rigidbench.preflight import validate_predictions
    from rigidbench.video import read_video

    readme = (Path(__file__).parents[2] / "README.md").read_text()
    section = readme.split("### Your own model", 1)[1]
    code = re.search(r"```python\n(.*?)```", section, re.S).group(1)
    (tmp_path / "my_model.py").write_text(code)
    monkeypatch.syspath_prepend(str(tmp_path))
    out = tmp_path / "predictions" / "still"
    assert main(["predict", "my_model:StillModel", "--data", str(data_dir), "--out", str(out)]) == 0, \
        capsys.readouterr().err
    video = read_video(out / "00015.mp4")
    assert video.frames.shape[0] == 49 and np.allclose(np.diff(video.times_s), 1 / 24)
    generation = json.loads((out / "generation.json").read_text())
    assert generation["kind"] == "user plug-in" and generation["examples"]["00015"]["status"] == "succeeded"
    assert generation["examples"]["00015"]["prompt"].endswith("Motion begins on the first frame.")
    assert validate_predictions(out, data_dir).ok


class PaidReference(Predictor):
    """A stand-in for a hosted model: every example is a paid call; it shows the reference."""

    paid = True
    calls = 0

    def predict(self, sample, ctx):
        PaidReference.calls += 1
        return reference(sample, 0.0)


def test_audit_stops_before_paid_calls_then_predicts_evaluates_and_reports(data_dir, tmp_path, capsys):
    from rigidbench.cli import main

    paid = PredictorInfo("paid-reference", f"{__name__}:PaidReference", "a paid stand-in", Kind.HOSTED,
                         writes_state=True)
    argv = ["audit", "--models", "static,paid-reference", "--data", str(data_dir), "--out", str(tmp_path / "audit"),
            "--perception", "gt", "--resamples", "200"]
    with PREDICTORS.added(paid):
        PaidReference.calls = 0
        assert main(argv) == 2  # not confirmed: nothing is sent or written
        assert "paid-reference: 1" in capsys.readouterr().out and PaidReference.calls == 0
        assert not (tmp_path / "audit" / "predictions" / "static" / "00015.mp4").exists()
        assert main(argv + ["--yes"]) == 0
        out = capsys.readouterr().out
        assert PaidReference.calls == 1 and "report: " in out
        for model in ("static", "paid-reference"):
            results = json.loads((tmp_path / "audit" / "runs" / model / "results.json").read_text())
            assert results["n_examples"] == 1 and not results["failed"]
        assert (tmp_path / "audit" / "report" / "report.html").exists()
        assert main(argv) == 0  # everything is there: no paid call left, nothing to confirm
        assert PaidReference.calls == 1
