"""wan-2.2 and cosmos-2.5 end to end at the `test` preset: a rendered example -> the real predict stage with a
tiny randomly initialised pipeline of the model's class -> validate -> evaluate --perception neural with tiny
perception models. CPU, no network, no weights."""

import json
from types import MappingProxyType

import numpy as np
import pytest
from fixtures.blender import render_eval_examples, requires_bpy

torch = pytest.importorskip("torch")
pytest.importorskip("diffusers")
pytest.importorskip("transformers")

from fixtures import tiny_perception  # noqa: E402
from fixtures import tiny_video_models as tiny  # noqa: E402

from rigidbench.driver import RunOptions  # noqa: E402
from rigidbench.benchmark import NEGATIVE_PROMPT  # noqa: E402
from rigidbench.groundtruth.bundle import Sample  # noqa: E402
from rigidbench.metrics import METRICS  # noqa: E402
from rigidbench.perception.features import FeatureNets  # noqa: E402
from rigidbench.predictors import PredictContext, example_seed, model_inputs  # noqa: E402
from rigidbench.preflight import validate_predictions  # noqa: E402
from rigidbench.stages.evaluate import evaluate  # noqa: E402
from rigidbench.stages.predict import predict  # noqa: E402
from rigidbench.video import probe_video  # noqa: E402

pytestmark = [pytest.mark.integration, requires_bpy]

# The `test` preset renders 12 frames (0.458 s) at 256x144. Wan: 13 frames (4k + 1) at 24 fps, 224x128 (multiples
# of 32); Cosmos: 9 frames at 16 fps (0.5 s), 256x144 (multiples of 16). Both cover the reference span.
CASES = {
    "wan-2.2": (tiny.tiny_wan, {"height": 128, "width": 224, "num_frames": 13, "steps": 2}, 24.0),
    "cosmos-2.5": (tiny.tiny_cosmos, {"height": 144, "width": 256, "num_frames": 9, "steps": 2, "no_guardrail": True},
                   16.0),
}


@pytest.fixture(scope="module")
def data_dir(tmp_path_factory):
    return render_eval_examples(tmp_path_factory.mktemp("data"), ("00015",))  # free fall


@pytest.fixture(scope="module")
def one_thread():
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


@pytest.mark.parametrize("name", list(CASES))
def test_a_local_model_predicts_validates_and_scores(name, data_dir, tmp_path, one_thread):
    build, options, fps = CASES[name]
    ctx = PredictContext(seed=4, options=MappingProxyType({"pipeline": build(), **options}))
    preds = tmp_path / "predictions" / name
    run = predict(name, data_dir, preds, ctx, run=RunOptions(progress=False))
    assert not run.failed and run.succeeded == ["00015"]

    info = probe_video(preds / "00015.mp4")
    assert info.n_frames == options["num_frames"] and info.fps_nominal == pytest.approx(fps)
    assert (info.width, info.height) == (options["width"], options["height"]) and info.codec == "h264"

    doc = json.loads((preds / "generation.json").read_text())
    model = doc["model"]
    assert doc["predictor"] == name and doc["kind"] == "local model" and doc["settings"]["seed"] == 4
    assert model["source"] == "injected" and model["num_inference_steps"] == 2 and model["fps"] == fps
    assert model["negative_prompt"] == NEGATIVE_PROMPT and "differs_from_paper" in model
    example = doc["examples"]["00015"]
    assert example["status"] == "succeeded" and example["seed"] == example_seed(4, "00015")  # from the base seed 4
    assert example["seconds_model"] > 0
    assert example["prompt"] == model_inputs(Sample(data_dir / "00015")).prompt
    if name == "cosmos-2.5":
        assert model["guardrail"] == "pass-through (--no-guardrail)" and "NVIDIA Open Model License" in model["licence_notice"]
        assert doc["settings"]["guardrail"] == "pass-through (--no-guardrail)"

    # a tiny randomly initialised model does not reproduce the first frame it is given (its VAE is random),
    # so the first-frame check that guards against mixing sets is off for it
    report = validate_predictions(preds, data_dir, first_frames=False)
    assert report.ok and not report.errors and "00015" in report.matched

    # a rerun with the same settings skips the finished example
    assert predict(name, data_dir, preds, ctx, run=RunOptions(progress=False)).reused == ["00015"]

    models = tiny_perception.tiny_models()
    summary = evaluate(preds, data_dir, tmp_path / "runs" / name, perception="neural",
                       perception_options={"models": models, "depth_input_size": 56, "device": "cpu"},
                       nets=FeatureNets(), first_frame_check=False, run=RunOptions(progress=False))
    assert not summary.failed and summary.ran == ["00015"]
    assert summary.facts.results["protocol"]["first_frame_check"] is False
    record = json.loads((summary.root / "examples" / "00015.json").read_text())
    assert record["perception"] == "neural" and set(record["metrics"]) == set(METRICS)
    m = record["metrics"]
    assert 0.0 <= m["iou"] <= 1.0 and np.isfinite(m["ssim"]) and np.isfinite(m["centroid_l2"])
    arrays = np.load(summary.root / "examples" / "00015.npz")
    assert arrays["iou"].shape == (12,)
