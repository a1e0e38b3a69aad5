"""Re-rendered failure modes at the `test` preset: physics counterfactuals, depth offset, identity swap.

One reference (eval 00015, a free fall) is rendered once; each counterfactual re-renders it once
(about 15 s each on two cores) and is shared by the tests that look at it.
"""

import math

import numpy as np
import pytest
from conftest import ate3d_floor, render_eval_examples, requires_bpy

from rigidbench.evaluation import evaluate
from rigidbench.perception.features import FeatureNets
from rigidbench.groundtruth.bundle import Sample
from rigidbench.predictors.counterfactuals import MAX_DEPTH_OFFSET_M, depth_offsets
from rigidbench.pipeline.predict import write_prediction
from rigidbench.predictors import PREDICTORS, PredictContext
from rigidbench.predictors.identity_swap import prediction_from_swapped
from rigidbench.perception.gt import WorldState, reference_state, state_path
from rigidbench.pipeline.predict import predict
from rigidbench.video import read_video

pytestmark = [pytest.mark.integration, requires_bpy]

SAMPLE_ID = "00015"  # free fall: one pomegranate dropped ~0.58 m, lands at frame ~8 of 12


@pytest.fixture(scope="module")
def data_dir(tmp_path_factory):
    return render_eval_examples(tmp_path_factory.mktemp("data"), (SAMPLE_ID,))


@pytest.fixture(scope="module")
def sample(data_dir):
    return Sample(data_dir / SAMPLE_ID)


@pytest.fixture(scope="module")
def counterfactual(sample, tmp_path_factory):
    """(mode, severity) -> (Prediction, kept counterfactual bundle), each rendered once per module."""
    root = tmp_path_factory.mktemp("counterfactuals")
    cache = {}

    def get(mode: str, severity: float):
        if (mode, severity) not in cache:
            bundle = root / f"{mode}-{severity}"
            ctx = PredictContext(severity=severity, keep_bundle_dir=bundle)
            cache[mode, severity] = (PREDICTORS[mode].create().predict(sample, ctx), Sample(bundle))
        return cache[mode, severity]

    return get


@pytest.fixture(scope="module")
def scored(data_dir, sample, counterfactual, tmp_path_factory):
    """(mode, severity) -> overall metric means of that prediction under gt perception."""
    root = tmp_path_factory.mktemp("scored")

    def get(mode: str, severity: float) -> dict[str, float]:
        preds = root / "predictions" / f"{mode}-{severity}"
        write_prediction(counterfactual(mode, severity)[0], preds, SAMPLE_ID, sample.fps)
        summary = evaluate(preds, data_dir, root / "runs" / preds.name, nets=FeatureNets(), progress=False)
        assert not summary.failed
        return {k: v["mean"] for k, v in summary.results["overall"].items()}

    return get


def _actor_z(bundle: Sample) -> np.ndarray:
    return bundle.trajectory.positions_m[bundle.active_indices[0], :, 2]


def test_zero_severity_rerender_is_the_reference(data_dir, sample, tmp_path):
    """Same spec, seed, preset and device: Bullet and Cycles reproduce the reference."""
    preds = tmp_path / "predictions" / "gravity"
    run = predict("gravity", data_dir, preds, PredictContext(severity=0.0), progress=False)
    assert run.written == [SAMPLE_ID] and not run.failed
    video = read_video(preds / f"{SAMPLE_ID}.mp4")
    assert video.frames.shape == sample.frames.shape
    assert np.abs(video.frames.astype(int) - sample.frames.astype(int)).max() <= 1
    state, ref = WorldState.load(state_path(preds / f"{SAMPLE_ID}.mp4")), reference_state(sample)
    for field in ("masks", "depth_m", "tracks", "visibility"):
        np.testing.assert_array_equal(getattr(state, field), getattr(ref, field), err_msg=field)
    overall = evaluate(preds, data_dir, tmp_path / "runs", nets=FeatureNets(), progress=False).results["overall"]
    assert overall["iou"]["mean"] == 1.0 and overall["ate"]["mean"] == 0.0
    assert overall["ate3d"]["mean"] == pytest.approx(ate3d_floor(sample), abs=2e-3)  # the metric's floor


def test_double_gravity_doubles_the_fall(sample, counterfactual):
    _, bundle = counterfactual("gravity", 1.0)
    z_ref, z_cf = _actor_z(sample), _actor_z(bundle)
    # Airborne frames 1-5 in both clips. Bullet's update is linear in g (damping included), so the
    # fall under 2g is exactly twice the reference's. The extra drop is g t^2 / 2 from rest, times
    # (1 + 1/n) after n semi-implicit Euler substeps, less ~1% of linear damping.
    frames = np.arange(1, 6)
    t, n = frames / sample.fps, frames * sample.spec.sim.substeps
    drop_ref, drop_cf = z_ref[0] - z_ref[1:6], z_cf[0] - z_cf[1:6]
    np.testing.assert_allclose(drop_cf / drop_ref, 2.0, rtol=1e-3)
    np.testing.assert_allclose(drop_cf - drop_ref, 0.5 * 9.81 * t ** 2 * (1 + 1 / n), rtol=0.015)


def test_gravity_error_raises_trajectory_errors(scored):
    g = scored("gravity", 1.0)
    assert g["ate3d"] > 0.2 and g["ate"] > 0.02 and g["iou"] < 0.8


def test_elastic_restitution_bounces_higher(sample, counterfactual):
    _, bundle = counterfactual("restitution", 1.0)
    g = 9.81
    body = sample.spec.active[0]
    contact_z = sample.spec.support.centre_m[2] + body.size_m[2] / 2
    h = _actor_z(sample)[0] - contact_z
    v = math.sqrt(2 * g * h)
    tau = (sample.n_frames - 1) / sample.fps - math.sqrt(2 * h / g)  # time since impact at the last frame
    rise_cf = _actor_z(bundle)[-1] - contact_z
    rise_ref = _actor_z(sample)[-1] - contact_z
    # Restitution 1 on both surfaces: rebound speed between v and 1.2 v (see blender/physics.py).
    assert 0.85 * (v * tau - g * tau ** 2 / 2) < rise_cf < 1.15 * (1.2 * v * tau - g * tau ** 2 / 2)
    assert rise_cf > 5 * max(rise_ref, 0.01)


def test_depth_offset_keeps_image_position_and_moves_depth(sample, counterfactual, scored):
    pred, _ = counterfactual("depth-offset", 1.0)
    ref = reference_state(sample)
    R_c, t_c = sample.camera_pose
    forward = -R_c[:, 2]  # Blender cameras look along their -z
    active = sample.active_indices[0]
    offsets = depth_offsets(sample.trajectory.positions_m[[active]], t_c, MAX_DEPTH_OFFSET_M)[0]
    expected_drop = -(offsets @ forward)  # axial depth change of every point of a translated rigid body
    assert (expected_drop > 0.45).all()
    for t in range(sample.n_frames):
        m_ref, m_cf = ref.masks[t, 0], pred.state.masks[t, 0]
        assert m_cf.sum() > m_ref.sum()  # nearer, so larger
        c_ref = np.argwhere(m_ref).mean(axis=0)
        c_cf = np.argwhere(m_cf).mean(axis=0)
        assert np.abs(c_cf - c_ref).max() < 1.0, t
        drop = np.median(ref.depth_m[t][m_ref]) - np.median(pred.state.depth_m[t][m_cf])
        assert drop == pytest.approx(expected_drop[t], abs=0.03), t
    d = scored("depth-offset", 1.0)
    motion = np.linalg.norm(sample.trajectory.positions_m[active, -1] - sample.trajectory.positions_m[active, 0])
    # Every reconstructed point is 0.5 m off, so ATE-3D is about offset / motion; a little less, as the
    # clip-level disparity fit (scale and shift over all pixels) absorbs part of the nearer actor's depth.
    assert 0.7 * MAX_DEPTH_OFFSET_M / motion < d["ate3d"] < 1.05 * MAX_DEPTH_OFFSET_M / motion
    assert d["ate"] < 0.03 and d["ate3d"] > 20 * d["ate"]


def test_identity_swap_changes_only_actor_pixels(sample, counterfactual, scored):
    pred, _ = counterfactual("identity-swap", 1.0)
    ref = reference_state(sample)
    for field in ("masks", "depth_m", "tracks", "visibility"):
        np.testing.assert_array_equal(getattr(pred.state, field), getattr(ref, field), err_msg=field)
    inside = ref.masks.any(axis=1)
    inside[0] = False
    diff = np.abs(pred.frames.astype(int) - sample.frames.astype(int)).sum(axis=-1)
    assert (diff[~inside] == 0).all()  # frame 0 and the background are the reference
    assert diff[inside].mean() > 60  # pomegranate red -> large_dice white
    s = scored("identity-swap", 1.0)
    assert s["iou"] == 1.0 and s["ate"] == 0.0 and s["ate3d"] == pytest.approx(ate3d_floor(sample), abs=2e-3)
    assert s["ssim"] < 1.0
    # Half severity blends the same render half-way: half the pixel change.
    _, bundle = counterfactual("identity-swap", 1.0)
    diff_half = np.abs(prediction_from_swapped(sample, bundle, 0.5).frames.astype(int)
                       - sample.frames.astype(int)).sum(axis=-1)
    assert diff_half[inside].mean() == pytest.approx(diff[inside].mean() / 2, rel=0.02)
