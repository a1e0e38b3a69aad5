"""Physical twins (predictors.twins) at the `test` preset: a twin at scale 0 is the reference, rendered or
geometry-only; a geometry-only twin equals the rendered twin of the same seed; twins of one example differ
by their seeds; the trajectories spread more as the scale grows.

One reference (eval 00010, a drop into a cluster of three) is rendered once, and twins of it twice in full
(about 7 s each on two cores); the geometry-only twins take under a second each.
"""

import json

import numpy as np
import pytest
from fixtures.blender import render_eval_examples, requires_bpy

from rigidbench.blender.physics import simulate
from rigidbench.driver import RunOptions
from rigidbench.folders import find_samples
from rigidbench.groundtruth.bundle import Sample
from rigidbench.metrics import METRICS
from rigidbench.perception.features import FeatureNets
from rigidbench.perception.gt import WorldState, reference_state, state_path
from rigidbench.predictors import PredictContext, sample_seed
from rigidbench.predictors.twins import apart_as_in
from rigidbench.scene_spec.envelope import load_envelope, perturb_spec
from rigidbench.stages.evaluate import evaluate
from rigidbench.stages.predict import predict
from rigidbench.video import read_video

pytestmark = [pytest.mark.integration, requires_bpy]

SAMPLE_ID = "00010"  # drop into cluster: a plastic bottle dropped onto an apple, a lemon and a pomegranate
APPEARANCE = {m for m, info in METRICS.items() if info.group == "appearance"}
STATE_FIELDS = ("masks", "depth_m", "tracks", "visibility")


@pytest.fixture(scope="module")
def sample(tmp_path_factory):
    """The reference, rendered at the `test` preset; its folder's parent is the data directory."""
    return Sample(render_eval_examples(tmp_path_factory.mktemp("data"), (SAMPLE_ID,)) / SAMPLE_ID)


@pytest.fixture(scope="module")
def data_dir(sample):
    return sample.path.parent


@pytest.fixture(scope="module")
def made(data_dir, tmp_path_factory):
    """name -> predictions folder: the reference itself, twins at scale 0 rendered and geometry-only, and at
    scale 1 (base seed 5) one rendered twin and two geometry-only ones (samples 0 and 1)."""
    root = tmp_path_factory.mktemp("predictions")
    runs = {"reference": ("reference", {}, 1), "twin": ("twin", {"scale": 0.0}, 1),
            "geometry": ("twin", {"scale": 0.0, "geometry_only": True}, 1),
            "twin1": ("twin", {}, 1), "geometry1": ("twin", {"geometry_only": True}, 2)}
    for name, (predictor, options, samples) in runs.items():
        report = predict(predictor, data_dir, root / name, PredictContext(seed=5, options=options),
                         run=RunOptions(progress=False), samples=samples)
        assert len(report.succeeded) == samples and not report.failed, report.failed
    return {name: root / name for name in runs}


@pytest.fixture(scope="module")
def records(made, data_dir, tmp_path_factory):
    """name -> the example's evaluate record (gt perception, no feature networks)."""
    root = tmp_path_factory.mktemp("runs")
    out = {}
    for name, preds in made.items():
        if name.endswith("1"):
            continue
        report = evaluate(preds, data_dir, root / name, nets=FeatureNets(), run=RunOptions(progress=False))
        assert not report.failed
        out[name] = json.loads((root / name / "examples" / f"{SAMPLE_ID}.json").read_text())
    return out


def test_a_zero_scale_twin_shows_the_reference(made, sample):
    """Same spec, seed, preset and device: Bullet and Cycles reproduce the reference, and the geometry-only
    twin's data passes are the reference's own."""
    video = read_video(made["twin"] / f"{SAMPLE_ID}.mp4")
    np.testing.assert_array_equal(video.frames, read_video(made["reference"] / f"{SAMPLE_ID}.mp4").frames)
    reference = reference_state(sample)
    for name in ("twin", "geometry"):
        state = WorldState.load(state_path(made[name] / f"{SAMPLE_ID}.mp4"))
        for field in STATE_FIELDS:
            np.testing.assert_array_equal(getattr(state, field), getattr(reference, field), err_msg=f"{name} {field}")
        assert state.geometry_only is (name == "geometry")
    generation = json.loads((made["geometry"] / "generation.json").read_text())
    record = generation["examples"][SAMPLE_ID]
    assert record["twin"] == {"seed": record["seed"], "scale": 0.0, "geometry_only": True}
    assert generation["settings"]["geometry_only"] is True and generation["settings"]["envelope"] == \
        load_envelope().numbers()


def test_a_zero_scale_twin_scores_as_the_reference(records):
    reference = records["reference"]["metrics"]
    assert records["twin"]["metrics"] == reference
    assert records["twin"]["skipped"] == records["reference"]["skipped"]
    geometry = records["geometry"]
    assert {m: v for m, v in geometry["metrics"].items() if m not in APPEARANCE} == {
        m: v for m, v in reference.items() if m not in APPEARANCE}
    assert reference["iou"] == 1.0 and reference["ate"] == 0.0
    assert all(geometry["metrics"][m] is None for m in APPEARANCE) and set(geometry["skipped"]) == APPEARANCE
    assert records["geometry"]["first_frame"]["matches"]  # the silhouettes on the first frame pass the check


def test_a_geometry_only_twin_equals_the_rendered_twin_of_its_seed(made):
    """The second geometry-only twin re-simulates in the scene the first left in Blender; the first equals the
    rendered twin of the same seed, made from a freshly built scene."""
    rendered = WorldState.load(state_path(made["twin1"] / f"{SAMPLE_ID}.mp4"))
    geometry = WorldState.load(state_path(made["geometry1"] / f"{SAMPLE_ID}.mp4"))
    for field in STATE_FIELDS:
        np.testing.assert_array_equal(getattr(geometry, field), getattr(rendered, field), err_msg=field)
    seeds = [json.loads((made[name] / "generation.json").read_text())["examples"][SAMPLE_ID]["twin"]["seed"]
             for name in ("twin1", "geometry1")]
    assert seeds[0] == seeds[1] == sample_seed(5, SAMPLE_ID, 0)


def test_geometry_only_twins_of_an_example_differ_by_their_seeds(made, sample):
    videos = find_samples(made["geometry1"], SAMPLE_ID)
    assert sorted(videos) == [0, 1]
    states = [WorldState.load(state_path(videos[k])) for k in (0, 1)]
    assert all(s.geometry_only for s in states)
    reference = reference_state(sample)
    for state in states:  # moved, but the same clip: frames, actors and resolution
        assert state.masks.shape == reference.masks.shape and not np.array_equal(state.depth_m, reference.depth_m)
    assert not np.array_equal(states[0].masks, states[1].masks)
    frames = read_video(videos[1]).frames
    assert frames.shape == sample.frames.shape and not np.array_equal(frames[0], frames[-1])
    assert sample_seed(5, SAMPLE_ID, 0) != sample_seed(5, SAMPLE_ID, 1)


def test_the_trajectories_spread_more_as_the_scale_grows(sample, reg):
    """RMS distance of the active actors from their reference trajectory over all simulated frames, mean over
    three twins (seeds 1-3, the same at every scale): zero at scale 0, then strictly growing with the scale."""
    spec, config = sample.spec, load_envelope()
    admissible = apart_as_in(spec, reg)
    reference = simulate(spec, reg).trajectory
    active = [i for i, role in enumerate(reference.roles) if role == "active"]
    spread = []
    for scale in (0.0, 0.5, 1.0, 2.0):
        rms = []
        for seed in (1, 2, 3):
            twin = simulate(*perturb_spec(spec, reg, config, seed, scale, admissible=admissible)).trajectory
            error = np.linalg.norm(twin.positions_m[active] - reference.positions_m[active], axis=-1)
            rms.append(np.sqrt(np.mean(error ** 2)))
        spread.append(float(np.mean(rms)))
    assert spread[0] == 0.0
    assert np.all(np.diff(spread) > 0), spread
    assert spread[1] > 1e-3  # millimetres at frame 0 grow to more than a millimetre over the clip
