"""Physics readouts recover what the failure modes simulate (issue 28), with gt perception.

The `test` preset's 12 frames (0.5 s) hold a free fall of at most 8 frames and no bounce after it, too
short for a playback speed (frame repeats quantise it by half a frame) or a restitution, so this
module defines a `readouts` preset: the `test` preset with 49 frames (the paper's 2 s) and one sample
(about 20 s per render on two cores). Two examples: eval 00015 (free fall, a pomegranate dropped
~0.57 m, lands at frame 9) for gravity, and eval 00006 (bounce, e = 0.85 x 0.6 on the support; it
falls 9 frames and bounces twice) for restitution, playback speed, delay and the flags; a free fall
resting after 9 frames carries too little timing for 3% (its speed rests on ~8 moving frames).
"""

import dataclasses
import math

import numpy as np
import pytest
from fixtures.blender import requires_bpy

from rigidbench import manifest
from rigidbench.config import registry as load_registry
from rigidbench.groundtruth.bundle import Sample
from rigidbench.predictors import PREDICTORS, PredictContext
from rigidbench.predictors.counterfactuals import physics_counterfactual
from rigidbench.validation.readouts import prediction_readouts, simulated_restitution

pytestmark = [pytest.mark.integration, requires_bpy]

FREE_FALL, BOUNCE = "00015", "00006"


@pytest.fixture(scope="module")
def reg():
    base = load_registry()
    preset = dataclasses.replace(base.preset("test"), name="readouts", frames=49, samples=1)
    return dataclasses.replace(base, presets={**base.presets, "readouts": preset})


@pytest.fixture(scope="module")
def samples(reg, tmp_path_factory):
    from rigidbench.stages.render import render_to_bundle

    root = tmp_path_factory.mktemp("data")
    rows = {r.sample_id: r for r in manifest.eval_rows(reg)}
    for sample_id in (FREE_FALL, BOUNCE):
        render_to_bundle(rows[sample_id], reg, reg.preset("readouts"), root)
    return {i: Sample(root / "eval" / i) for i in (FREE_FALL, BOUNCE)}


@pytest.fixture(scope="module")
def work(tmp_path_factory):
    return tmp_path_factory.mktemp("work")


def readouts(sample, mode, severity, work):
    prediction = PREDICTORS[mode].create().predict(sample, PredictContext(severity=severity))
    return prediction_readouts(sample, prediction, work)


@pytest.mark.parametrize("severity", [0.5, 1.0])
def test_gravity_counterfactual_recovers_g(samples, reg, work, tmp_path, severity):
    sample = samples[FREE_FALL]
    bundle = tmp_path / "cf"
    r = prediction_readouts(sample, physics_counterfactual(sample, "gravity", severity, bundle, reg), work)
    g_true = sample.spec.sim.gravity_m_s2 * (1 + severity)
    g = r["gravity"]
    assert g["value"] == pytest.approx(g_true, rel=0.05)
    assert g["frames"] >= 5 and g["se"] < 0.05 * g_true
    # the window is the counterfactual's own flight: it ends where its simulated body first deviates
    assert g["contact_frame"] is not None and g["contact_frame"] < g["reference_contact_frame"]
    # A fall from the same height under g (1 + s) is the reference played sqrt(1 + s) times faster (only the
    # landing differs), so s^ reads a faster clip and g^ s^-2 moves back towards the reference's g.
    print(f"gravity s={severity}: g^ {g['value']:.3f} (true {g_true:.3f}), s^ {r['speed']['value']:.3f}, "
          f"g^ s^-2 {g['per_speed2']:.3f}")
    assert 1.0 < r["speed"]["value"] < 1.1 * math.sqrt(1 + severity)
    assert abs(g["per_speed2"] - 9.81) < abs(g["value"] - 9.81)


def test_reference_readouts_and_no_flags(samples, work):
    for sample in samples.values():
        r = readouts(sample, "reference", 0.0, work)
        assert r["flags"]["raised"] == [], sample.sample_id
        assert r["gravity"]["value"] == pytest.approx(sample.spec.sim.gravity_m_s2, rel=0.05)
        assert r["gravity"]["window_matches_reference"]
    r = readouts(samples[BOUNCE], "reference", 0.0, work)
    assert r["speed"]["value"] == pytest.approx(1.0, rel=0.03)
    assert abs(r["speed"]["offset_frames"]) < 1
    assert r["restitution"]["value"] == pytest.approx(simulated_restitution(samples[BOUNCE]), abs=0.05)


def test_restitution_counterfactual_recovers_its_coefficient(samples, reg, work, tmp_path):
    sample = samples[BOUNCE]
    bundle = tmp_path / "cf"
    r = prediction_readouts(sample, physics_counterfactual(sample, "restitution", 0.5, bundle, reg), work)
    truth = simulated_restitution(Sample(bundle))
    ref_e = simulated_restitution(sample)
    assert r["restitution"]["value"] == pytest.approx(truth, abs=0.05)
    assert truth > ref_e + 0.1  # the counterfactual really is bouncier
    # Bullet's effective coefficient lies between the product of the two restitutions and that + 0.2
    body = next(b for b in Sample(bundle).spec.bodies if b.role == "active")
    product = body.physics.restitution * Sample(bundle).spec.support.physics.restitution
    assert product - 0.02 < truth < product + 0.2


@pytest.mark.parametrize("mode,severity,speed", [("slow", 0.5, 1 / 1.5), ("slow", 1.0, 0.5), ("fast", 0.5, 1.5),
                                                 ("fast", 1.0, 2.0)])
def test_playback_speed_within_three_percent(samples, work, mode, severity, speed):
    r = readouts(samples[BOUNCE], mode, severity, work)
    assert r["speed"]["value"] == pytest.approx(speed, rel=0.03)
    assert abs(r["speed"]["offset_frames"]) < 1


@pytest.mark.parametrize("severity", [0.2, 0.5])
def test_delay_within_one_frame(samples, work, severity):
    r = readouts(samples[BOUNCE], "delayed", severity, work)
    assert r["speed"]["value"] == pytest.approx(1.0, rel=0.03)
    assert r["speed"]["offset_s"] * samples[BOUNCE].fps == pytest.approx(-0.5 * severity * 24, abs=1.0)
    # gravity is read from the delayed flight itself
    assert r["gravity"]["value"] == pytest.approx(9.81, rel=0.05)


@pytest.mark.parametrize("mode,expected", [("static", ["frozen"]), ("camera-drift", ["camera"])])
def test_failure_modes_raise_exactly_their_flag(samples, work, mode, expected):
    r = readouts(samples[BOUNCE], mode, 1.0, work)
    assert r["flags"]["raised"] == expected
    if mode == "static":
        assert r["speed"]["value"] == 0.0 and math.isnan(r["gravity"]["value"])
    else:
        assert r["flags"]["camera"]["max_shift_h"] > 0.1
    assert np.isfinite(r["world"]["value"])
