"""The physical envelope's perturbation (scene_spec.envelope) and its configuration, without Blender."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
from fixtures.scenes import ramp_body

from rigidbench import manifest
from rigidbench.config import registry as load_registry
from rigidbench.errors import SpecError, UserError
from rigidbench.evaluation.scoring import NO_RGB_REASON, metric_inputs, score_inputs, skip_reasons
from rigidbench.metrics import METRICS
from rigidbench.perception.base import Perception, load_arrays, save_arrays
from rigidbench.perception.features import FeatureNets
from rigidbench.perception.gt import WorldState
from rigidbench.predictors.twins import silhouettes
from rigidbench.rotations import quat_to_matrix
from rigidbench.scene_spec.build import build_scene_spec
from rigidbench.scene_spec.envelope import (ENTRIES, MAX_DRAWS, load_envelope, perturb_spec, ramp_normal,
                                            resting_normals)

BALL_CHAIN, CLUSTER, FREE_FALL, RAMPS = "00000", "00010", "00015", "00020"  # eval manifest ids


@pytest.fixture(scope="module")
def reg():
    return load_registry()


@pytest.fixture(scope="module")
def config():
    return load_envelope()


@pytest.fixture(scope="module")
def specs(reg):
    rows = {r.sample_id: r for r in manifest.eval_rows(reg)}
    return {i: build_scene_spec(rows[i], reg) for i in (BALL_CHAIN, CLUSTER, FREE_FALL, RAMPS)}


def _active(spec):
    return {b.name: b for b in spec.active}


# -- the configuration --------------------------------------------------------------------------------------


def test_the_packaged_envelope_gives_every_number_a_reason(config):
    numbers = config.numbers()
    assert tuple(numbers) == ENTRIES
    for name in ENTRIES:
        noise = getattr(config, name)
        assert noise.value >= 0 and len(noise.reason) > 40, name
    # one pixel at the median actor distance (1.64 m) in the paper preset: f = 35 / 36 x 1280 px
    paper = load_registry().preset("paper")
    f_px = 35.0 / 36.0 * paper.resolution[0]
    assert numbers["position_m"] == pytest.approx(1.64 / f_px, abs=5e-5)
    assert numbers["orientation_deg"] == 1.0
    assert numbers["restitution_rel"] == numbers["friction_rel"] == 0.1
    assert config.to_dict()["position_m"]["reason"].startswith("One pixel")


GOOD = {name: {"value": 0.1, "reason": "because"} for name in ENTRIES}


def _write(tmp_path, data, text: str | None = None):
    import yaml

    path = tmp_path / "envelope.yaml"
    path.write_text(text if text is not None else yaml.safe_dump(data))
    return path


@pytest.mark.parametrize("change, key, words", [
    (lambda d: d.pop("mass_rel"), "mass_rel", "missing"),
    (lambda d: d.update(velocity_m_s={"value": 0.1, "reason": "x"}), "velocity_m_s", "unknown entry"),
    (lambda d: d.update(position_m={"value": -1.0, "reason": "x"}), "position_m.value", ">= 0"),
    (lambda d: d.update(position_m={"value": "1 px", "reason": "x"}), "position_m.value", "finite number"),
    (lambda d: d.update(position_m={"value": True, "reason": "x"}), "position_m.value", "finite number"),
    (lambda d: d.update(friction_rel={"value": 1.5, "reason": "x"}), "friction_rel.value", "below 1"),
    (lambda d: d.update(orientation_deg={"value": 1.0}), "orientation_deg.reason", "its reason"),
    (lambda d: d.update(orientation_deg={"value": 1.0, "reason": "  "}), "orientation_deg.reason", "its reason"),
    (lambda d: d.update(orientation_deg={"value": 1.0, "reason": "x", "unit": "deg"}), "orientation_deg.unit",
     "unknown field"),
    (lambda d: d.update(mass_rel=0.1), "mass_rel", "mapping"),
])
def test_a_bad_envelope_names_the_file_and_the_key(tmp_path, change, key, words):
    data = {k: dict(v) for k, v in GOOD.items()}
    change(data)
    path = _write(tmp_path, data)
    with pytest.raises(UserError) as caught:
        load_envelope(path)
    message = str(caught.value)
    assert str(path) in message and f"key '{key}'" in message and words in message and "\n" not in message


def test_an_unreadable_or_absent_envelope_is_a_user_error(tmp_path):
    with pytest.raises(UserError, match="not valid YAML"):
        load_envelope(_write(tmp_path, None, "position_m: [unclosed"))
    with pytest.raises(UserError, match="expected a mapping"):
        load_envelope(_write(tmp_path, None, "- 1\n- 2\n"))
    with pytest.raises(UserError, match="cannot be read"):
        load_envelope(tmp_path / "absent.yaml")


def test_a_config_directory_replaces_the_packaged_envelope(tmp_path):
    _write(tmp_path, GOOD)
    assert load_envelope(config_dirs=(tmp_path,)).numbers() == {k: 0.1 for k in ENTRIES}


# -- the perturbation ---------------------------------------------------------------------------------------


def test_scale_zero_is_the_reference_itself(specs, reg, config):
    spec = specs[CLUSTER]
    twin, twin_reg = perturb_spec(spec, reg, config, seed=7, scale=0.0)
    assert twin is spec and twin_reg is reg
    with pytest.raises(ValueError, match=">= 0"):
        perturb_spec(spec, reg, config, seed=7, scale=-0.5)


def test_one_seed_one_twin_and_seeds_differ(specs, reg, config):
    spec = specs[CLUSTER]
    a, b, c = (perturb_spec(spec, reg, config, seed, 1.0)[0] for seed in (3, 3, 4))
    assert a == b and a != c
    assert [x.name for x in a.bodies] == [x.name for x in spec.bodies]


def test_what_each_actor_rests_on(specs, reg):
    chain = resting_normals(specs[BALL_CHAIN], reg)
    striker, *row = specs[BALL_CHAIN].active
    np.testing.assert_allclose(chain[striker.name], ramp_normal(specs[BALL_CHAIN].body("ramp")))
    assert all(np.array_equal(chain[b.name], [0, 0, 1]) for b in row)  # the line rests on the support
    cluster = resting_normals(specs[CLUSTER], reg)
    *ring, faller = specs[CLUSTER].active
    assert cluster[faller.name] is None and all(np.array_equal(cluster[b.name], [0, 0, 1]) for b in ring)
    assert resting_normals(specs[FREE_FALL], reg) == {specs[FREE_FALL].active[0].name: None}
    # a ramp descending -x (yaw pi): its slope normal leans toward -x
    ramp = ramp_body(reg, "r", 0.5, 0.3, 0.3, 0.0, descends="-x")
    n = ramp_normal(ramp)
    np.testing.assert_allclose(n, np.array([-0.3, 0.0, 0.5]) / math.hypot(0.3, 0.5), atol=1e-12)


def test_resting_actors_slide_and_turn_within_their_plane(specs, reg, config):
    for sample_id in (BALL_CHAIN, CLUSTER, RAMPS):
        spec = specs[sample_id]
        normals = resting_normals(spec, reg)
        for seed in range(5):
            twin = _active(perturb_spec(spec, reg, config, seed, 2.0)[0])
            for name, body in _active(spec).items():
                n = normals[name]
                if n is None:
                    continue
                move = np.subtract(twin[name].position_m, body.position_m)
                assert abs(move @ n) < 1e-12 and np.linalg.norm(move) > 0  # in the plane, not off it
                turn = quat_to_matrix(np.asarray(twin[name].quat_wxyz)) @ quat_to_matrix(np.asarray(body.quat_wxyz)).T
                np.testing.assert_allclose(turn @ n, n, atol=1e-12)  # turned about the normal only
                assert not np.allclose(turn, np.eye(3))


def test_the_deviations_are_the_configured_ones_times_the_scale(specs, reg, config):
    """Over 400 seeds: a free actor's offset has the configured standard deviation on each axis, its turn the
    configured angle per rotation-vector component; friction, restitution and mass change by the relative
    deviation. Scale 2 doubles the offsets of the same seed exactly."""
    spec = specs[FREE_FALL]
    body = spec.active[0]
    moves, angles, rel = [], [], []
    for seed in range(400):
        twin = perturb_spec(spec, reg, config, seed, 1.0)[0].active[0]
        moves.append(np.subtract(twin.position_m, body.position_m))
        cos = abs(float(np.dot(twin.quat_wxyz, body.quat_wxyz)))
        angles.append(2 * math.degrees(math.acos(min(1.0, cos))))
        rel.append([twin.physics.friction / body.physics.friction, twin.physics.restitution / body.physics.restitution,
                    twin.physics.mass_kg / body.physics.mass_kg])
    moves, rel = np.array(moves), np.array(rel) - 1
    np.testing.assert_allclose(moves.std(axis=0), config.position_m.value, rtol=0.12)
    # |omega| of three normals x sigma: E|omega|^2 = 3 sigma^2
    assert math.sqrt(np.mean(np.square(angles)) / 3) == pytest.approx(config.orientation_deg.value, rel=0.12)
    np.testing.assert_allclose(rel.std(axis=0), [config.friction_rel.value, config.restitution_rel.value,
                                                 config.mass_rel.value], rtol=0.12)
    one, two = (np.subtract(perturb_spec(spec, reg, config, 11, s)[0].active[0].position_m, body.position_m)
                for s in (1.0, 2.0))
    np.testing.assert_allclose(two, 2 * one, rtol=1e-9)


def test_passive_surfaces_and_the_floor_are_perturbed_and_stay_physical(specs, reg, config):
    spec = specs[BALL_CHAIN]
    for seed in range(30):
        twin, twin_reg = perturb_spec(spec, reg, config, seed, 5.0)  # large: the clipping is exercised
        ramp = twin.body("ramp")
        assert ramp.position_m == spec.body("ramp").position_m  # scene geometry is not moved
        for physics in [b.physics for b in twin.bodies] + [twin.support.physics]:
            assert 0.0 <= physics.restitution <= 1.0 and physics.friction >= 0.0
        assert all(b.physics.mass_kg > 0 for b in twin.active)
        assert (twin_reg.sim.passive_friction, twin_reg.sim.passive_restitution) != (
            reg.sim.passive_friction, reg.sim.passive_restitution)
    assert reg.sim == load_registry().sim  # the registry given is not changed


def test_refused_draws_are_followed_by_the_next_and_then_given_up(specs, reg, config):
    spec = specs[CLUSTER]
    seen = []

    def third(twin):
        seen.append(twin)
        return len(seen) == 3

    twin, _ = perturb_spec(spec, reg, config, 5, 1.0, admissible=third)
    assert twin is seen[2] and len({t.bodies for t in seen}) == 3
    with pytest.raises(SpecError, match=f"example {spec.sample_id}: {MAX_DRAWS} twins"):
        perturb_spec(spec, reg, config, 5, 1.0, admissible=lambda t: False)


def test_a_hand_made_body_rests_on_the_support_when_it_starts_on_it(specs, reg):
    spec = specs[CLUSTER]
    resting = [dataclasses.replace(b, step="somewhere") for b in spec.bodies]  # steps the task does not name
    normals = resting_normals(dataclasses.replace(spec, bodies=tuple(resting)), reg)
    *ring, faller = spec.active
    assert normals[faller.name] is None and all(np.array_equal(normals[b.name], [0, 0, 1]) for b in ring)


# -- geometry-only states and their scoring -----------------------------------------------------------------


def _state(geometry_only=None):
    t, n, h, w = 3, 1, 6, 8
    masks = np.zeros((t, n, h, w), bool)
    masks[:, 0, 2:4, 3:5] = True
    affine = np.tile(np.array([[1.0, 0, 0], [0, 1.0, 0]]), (t, 1, 1))
    kwargs = {} if geometry_only is None else {"geometry_only": geometry_only}
    return WorldState(np.arange(t) / 24.0, masks, np.full((t, h, w), 2.0, np.float32), np.zeros((1, t, 2), np.float32),
                      np.ones((1, t), bool), affine, np.zeros((t, 2, 2, 2), np.float32), **kwargs)


def test_the_geometry_only_flag_round_trips_and_older_files_read_as_false(tmp_path):
    _state(True).save(tmp_path / "twin.npz")
    assert WorldState.load(tmp_path / "twin.npz").geometry_only is True
    old = _state()
    arrays = {f.name: getattr(old, f.name) for f in dataclasses.fields(old) if f.name != "geometry_only"}
    np.savez_compressed(tmp_path / "old.npz", **arrays)  # a state written before the flag existed
    assert WorldState.load(tmp_path / "old.npz").geometry_only is False
    p = Perception(*(np.zeros(1) for _ in range(10)), geometry_only=True)
    save_arrays(p, tmp_path / "p.npz", compress=False)
    assert load_arrays(Perception, tmp_path / "p.npz").geometry_only is True


class _Sample:
    """Just what ``metric_inputs`` reads of a reference."""

    def __init__(self, state):
        t = state.times_s.shape[0]
        self.frames = np.zeros((t, 6, 8, 3), np.uint8)
        self.masks, self.depth, self.active_indices = state.masks, state.depth_m, [0]
        self.tracks = {"tracks": state.tracks, "visibility": state.visibility, "points_body_m": np.zeros((1, 3)),
                       "actor_index": np.zeros(1, int)}
        self.track_active_index = np.zeros(1, int)
        self.K, self.camera_to_world = np.eye(3), np.eye(4)
        self.trajectory = type("T", (), {"positions_m": np.zeros((1, t, 3)),
                                         "quat_wxyz": np.tile([1.0, 0, 0, 0], (1, t, 1))})()


@pytest.mark.parametrize("geometry_only", [False, True])
def test_a_geometry_only_perception_skips_the_appearance_group_with_its_reason(geometry_only):
    state = _state(geometry_only)
    t = state.times_s.shape[0]
    perception = Perception(state.times_s, state.masks, state.tracks, state.visibility, np.ones((1, t), np.float32),
                            np.zeros(1, int), 1.0 / state.depth_m, state.times_s, np.zeros((0, t, 2), np.float32),
                            np.zeros((0, t), np.float32), geometry_only=geometry_only).aligned(state.times_s)
    nets = FeatureNets(skipped={"lpips": "no weights", "iddrift": "no weights"})
    inputs = metric_inputs(_Sample(state), np.zeros((t, 6, 8, 3), np.uint8), perception, nets)
    scores = score_inputs(inputs, ("iou", "ssim", "lpips", "bgdrift"))
    reasons = skip_reasons(scores, inputs, nets)
    appearance = {m for m, info in METRICS.items() if info.group == "appearance"}
    if geometry_only:
        assert set(inputs.skipped) == appearance == {"ssim", "lpips", "iddrift", "bgdrift"}
        assert reasons == {"ssim": NO_RGB_REASON, "lpips": NO_RGB_REASON, "bgdrift": NO_RGB_REASON}
    else:
        assert inputs.skipped == {} and reasons == {"lpips": "no weights"} and scores["ssim"] is not None
    assert scores["iou"].value == 1.0


def test_silhouettes_paint_each_actor_on_the_first_frame():
    first = np.full((4, 5, 3), 7, np.uint8)
    masks = np.zeros((2, 2, 4, 5), bool)
    masks[0, 0, 1, 1] = masks[1, 1, 2, 3] = True
    frames = silhouettes(first, masks)
    assert frames.shape == (2, 4, 5, 3) and frames.dtype == np.uint8
    assert tuple(frames[0, 1, 1]) == (230, 25, 75) and tuple(frames[1, 2, 3]) == (60, 180, 75)
    assert (frames[0].reshape(-1, 3) == 7).all(axis=1).sum() == 19 and (first == 7).all()
