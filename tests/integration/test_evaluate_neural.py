"""`evaluate --perception neural` end to end at the `test` preset, with tiny random models injected."""

import json

import numpy as np
import pytest
from fixtures.blender import render_eval_examples, requires_bpy

torch = pytest.importorskip("torch")
pytest.importorskip("transformers")

from fixtures import tiny_perception  # noqa: E402

from rigidbench.driver import RunOptions  # noqa: E402
from rigidbench.metrics import METRICS  # noqa: E402
from rigidbench.perception.features import FeatureNets  # noqa: E402
from rigidbench.predictors import PredictContext  # noqa: E402
from rigidbench.stages.evaluate import evaluate  # noqa: E402
from rigidbench.stages.predict import predict  # noqa: E402

pytestmark = [pytest.mark.integration, requires_bpy]


@pytest.fixture(scope="module")
def data_dir(tmp_path_factory):
    return render_eval_examples(tmp_path_factory.mktemp("data"), ("00015",))  # free fall


def count_forward_calls(models: dict) -> dict:
    """Counts calls of each model's forward (SAM 2 per frame, the tracker per clip, VDA per window)."""
    calls = {role: 0 for role in models}
    for role, model in models.items():
        def hook(module, args, output, role=role):
            calls[role] += 1
        model.register_forward_hook(hook)
    return calls


def test_neural_perception_scores_a_rendered_example_and_caches_each_model(data_dir, tmp_path):
    from rigidbench.perception.features import load_identity_features

    preds = tmp_path / "predictions" / "reference"
    run = predict("reference", data_dir, preds, PredictContext(severity=1.0), run=RunOptions(progress=False))
    assert not run.failed and len(run.succeeded) == 1
    models = tiny_perception.tiny_models()
    calls = count_forward_calls(models)
    options = {"models": models, "depth_input_size": 56, "device": "cpu"}
    nets = FeatureNets(lpips=tiny_perception.tiny_lpips(),
                       identity=load_identity_features(device="cpu", model=tiny_perception.tiny_dinov2()))
    out = tmp_path / "runs" / "reference"
    summary = evaluate(preds, data_dir, out, perception="neural", perception_options=options, nets=nets, run=RunOptions(progress=False))
    assert not summary.failed and summary.ran == ["00015"]
    # SAM 2: the prompt frame, then 12 propagation steps (the `test` preset has 12 frames).
    assert calls["sam2"] == 1 + 12 and calls["cotracker"] == 2 and calls["depth"] >= 1  # actors, background

    record = json.loads((out / "examples" / "00015.json").read_text())
    assert record["perception"] == "neural" and set(record["metrics"]) == set(METRICS) and not record["skipped"]
    m = record["metrics"]
    assert 0.0 <= m["iou"] <= 1.0 and m["ssim"] > 0.9 and m["lpips"] is not None and m["lpips"] >= 0.0
    assert m["si_mse"] is not None and m["si_mse"] >= 0.0
    # SAM 2 returns its frame-0 prompt as the frame-0 mask, here through the tiny model's 32 x 32 logits.
    assert np.load(out / "examples" / "00015.npz")["iou"][0] > 0.5
    run = json.loads((out / "run.json").read_text())
    assert run["perception"]["backend"] == "neural" and run["perception"]["settings"]["depth_model"] == "vda"
    cached = sorted(p.name.split("-")[1] for p in (out / "cache" / "neural").glob("00015-*.npz"))
    assert cached == ["background", "cotracker", "depth", "sam2"]

    # Unchanged inputs: the example is reused. Changed feature nets: rescored, but no model runs again.
    before = dict(calls)
    again = evaluate(preds, data_dir, out, perception="neural", perception_options=options, nets=nets, run=RunOptions(progress=False))
    assert again.reused == ["00015"] and not again.ran
    rescored = evaluate(preds, data_dir, out, perception="neural", perception_options=options, nets=FeatureNets(), run=RunOptions(progress=False))
    assert rescored.ran == ["00015"] and calls == before
    rerecord = json.loads((out / "examples" / "00015.json").read_text())
    assert rerecord["metrics"]["iou"] == m["iou"] and rerecord["metrics"]["lpips"] is None
