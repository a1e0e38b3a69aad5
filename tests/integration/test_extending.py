"""Extending RigidBench: a metric or a predictor is one module plus one registration, and then it is
everywhere (evaluate's output, the demo table, the report); a bug inside a metric stops the run."""

import json

import numpy as np
import pytest
from conftest import render_eval_examples, requires_bpy

from rigidbench.errors import RigidBenchError
from rigidbench.evaluation import evaluate
from rigidbench.metrics import METRICS, MetricInfo, MetricResult
from rigidbench.perception.features import FeatureNets
from rigidbench.pipeline.demo import format_table
from rigidbench.pipeline.predict import predict
from rigidbench.predictors import PREDICTORS, Kind, PredictContext, PredictorInfo
from rigidbench.predictors.image_space import reference
from rigidbench.report import build_report

pytestmark = [pytest.mark.integration, requires_bpy]


# -- a toy metric and a toy predictor, as a user would write them in their own module ---------------


def mean_abs_difference(x) -> MetricResult:
    """Mean absolute RGB difference in [0, 1], per frame and overall."""
    diff = np.abs(x.ref_rgb.astype(np.float64) - x.gen_rgb.astype(np.float64)).mean(axis=(1, 2, 3)) / 255.0
    return MetricResult(float(diff.mean()), diff)


def broken_metric(x) -> MetricResult:
    return MetricResult(len(x), None)  # a bug: MetricInputs has no len()


def inverted(sample, ctx):
    """The reference with inverted colours; the world state it shows is the reference's."""
    pred = reference(sample, 0.0)
    pred.frames = 255 - pred.frames
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
            run = predict(name, data_dir, preds, PredictContext(severity=0.0), progress=False)
            assert run.written == ["00015"] and not run.failed
            summary = evaluate(preds, data_dir, tmp_path / "runs" / name, nets=FeatureNets(), progress=False)
            assert not summary.failed
            table[name] = [summary.results["overall"][m]["mean"] for m in METRICS]
            runs.append(summary.out_dir)
        record = json.loads((tmp_path / "runs" / "inverted" / "examples" / "00015.json").read_text())
        frames = np.load(tmp_path / "runs" / "inverted" / "examples" / "00015.npz")["mad"]
        # Hand-computed: inverting colours moves every channel value v to 255 - v, |v - (255 - v)| = |2v - 255|.
        from rigidbench.groundtruth.bundle import Sample

        ref = Sample(data_dir / "00015").frames.astype(np.float64)
        expected = (np.abs(2 * ref - 255).mean(axis=(1, 2, 3)) / 255.0)
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
    predict("reference", data_dir, preds, PredictContext(severity=0.0), progress=False)
    with METRICS.added(MetricInfo("broken", f"{__name__}:broken_metric", "Broken", False, "appearance", "a bug")):
        with pytest.raises(TypeError, match="has no len"):
            evaluate(preds, data_dir, tmp_path / "runs" / "reference", nets=FeatureNets(), progress=False)


def test_a_bad_example_is_recorded_and_the_run_goes_on(data_dir, tmp_path):
    preds = tmp_path / "predictions" / "broken-video"
    preds.mkdir(parents=True)
    (preds / "00015.mp4").write_bytes(b"not a video")
    summary = evaluate(preds, data_dir, tmp_path / "runs" / "broken", nets=FeatureNets(), progress=False)
    assert list(summary.failed) == ["00015"] and "00015.mp4" in summary.failed["00015"]
    assert issubclass(type(RigidBenchError("x")), Exception)
