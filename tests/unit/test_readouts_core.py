"""Physics readouts on synthetic arrays with hand-computed answers (issue 28)."""

import math

import numpy as np
import pytest

from rigidbench.metrics.inputs import MetricInputs
from rigidbench.readouts import READOUTS, ReadoutContext, compute_readouts
from rigidbench.readouts.fits import (ballistic_window, bounce_coefficient, fit_fixed_curvature, fit_parabola,
                                      fit_time_warp, release_frame)
from rigidbench.readouts.records import aggregate_readouts, summary, to_jsonable

FPS = 24.0


def bounce_z(t, z0=0.6, g=9.81, e=0.5, floor=0.0):
    """Height of a ball dropped from rest at z0 onto a floor with restitution e (exact, one bounce)."""
    t_c = math.sqrt(2 * (z0 - floor) / g)
    v_c = g * t_c
    return np.where(t < t_c, z0 - 0.5 * g * t ** 2, floor + e * v_c * (t - t_c) - 0.5 * g * (t - t_c) ** 2)


def test_parabola_recovers_g_and_its_uncertainty_vanishes_on_exact_data():
    t = np.arange(8) / FPS
    z = 1.0 + 0.3 * t - 0.5 * 7.3 * t ** 2
    p = fit_parabola(t, z)
    assert p.g == pytest.approx(7.3, rel=1e-9) and p.c1 == pytest.approx(0.3) and p.c0 == pytest.approx(1.0)
    assert p.g_se < 1e-9 and p.n == 8
    assert math.isnan(fit_parabola(t[:3], z[:3]).g_se)  # 3 samples fix a parabola, no uncertainty


def test_parabola_uncertainty_matches_noise():
    rng = np.random.default_rng(0)
    t = np.arange(12) / FPS
    gs = [fit_parabola(t, 1 - 4.905 * t ** 2 + rng.normal(0, 0.002, t.size)) for _ in range(400)]
    values = np.array([p.g for p in gs])
    assert values.mean() == pytest.approx(9.81, abs=0.1)
    assert np.mean([p.g_se for p in gs]) == pytest.approx(values.std(), rel=0.2)


def test_ballistic_window_ends_at_the_first_contact():
    t = np.arange(24) / FPS
    z = bounce_z(t, z0=0.6)
    t_c = math.sqrt(2 * 0.6 / 9.81)  # 0.3497 s: between frames 8 and 9
    w = ballistic_window(t, z)
    assert (w.first, w.last, w.ended_by) == (0, 8, "deviation")
    assert int(math.floor(t_c * FPS)) == w.last


def test_release_frame_of_a_delayed_drop_is_its_last_frame_at_rest():
    t = np.arange(20) / FPS
    z = np.where(t < 4 / FPS, 0.5, 0.5 - 0.5 * 9.81 * (t - 4 / FPS) ** 2)
    assert release_frame(z) == 4
    w = ballistic_window(t, z)
    assert w.first == 4
    assert fit_parabola(t[w.first:w.last + 1], z[w.first:w.last + 1]).g == pytest.approx(9.81, rel=1e-9)
    assert release_frame(np.full(10, 0.3)) is None


@pytest.mark.parametrize("e", [0.2, 0.5, 0.85])
def test_bounce_coefficient_of_an_exact_bounce(e):
    t = np.arange(30) / FPS
    b = bounce_coefficient(t, bounce_z(t, z0=0.6, e=e))
    assert b.e == pytest.approx(e, abs=1e-6)
    assert b.t_contact_s == pytest.approx(math.sqrt(2 * 0.6 / 9.81), abs=1e-6)
    assert b.v_before == pytest.approx(-math.sqrt(2 * 9.81 * 0.6), rel=1e-6)


def test_bounce_without_contact_is_nan_with_a_reason():
    t = np.arange(6) / FPS
    b = bounce_coefficient(t, 2.0 - 4.905 * t ** 2)
    assert math.isnan(b.e) and "no contact" in b.reason


def test_fixed_curvature_line():
    t = np.arange(3) / FPS
    q = fit_fixed_curvature(t, 0.1 + 2.0 * t - 4.905 * t ** 2, 9.81)
    assert (q.c0, q.c1) == pytest.approx((0.1, 2.0)) and q.g_se == 0.0


def _fall(tau):
    tau = np.asarray(tau, float)
    z = np.where(tau < 0, 0.0, -0.5 * 9.81 * np.clip(tau, 0, None) ** 2)
    return np.stack([0.2 * np.clip(tau, 0, None), 0 * tau, z], -1)[None]


@pytest.mark.parametrize("speed,offset", [(1.0, 0.0), (0.5, 0.0), (2 / 3, 0.0), (1.5, 0.0), (1.0, -0.2)])
def test_time_warp_of_an_exactly_warped_trajectory(speed, offset):
    t = np.arange(49) / FPS
    ref = _fall(t)
    tau = speed * t + offset
    gen = _fall(tau[tau <= t[-1]])
    w = fit_time_warp(gen, ref, FPS)
    assert w.speed == pytest.approx(speed, rel=2e-3)  # matched instants on a 1/16-frame grid
    assert w.offset_s == pytest.approx(offset, abs=1 / (16 * FPS))  # matched on a 1/16-frame grid
    assert w.rmse_m < 1e-3 * np.abs(ref).max()  # the 1/16-frame grid of the matched instants


def test_time_warp_of_frame_repeats_is_within_one_percent():
    t = np.arange(49) / FPS
    ref = _fall(t)
    shown = np.rint(t / 1.5 * FPS).astype(int)  # slow motion made by repeating frames
    w = fit_time_warp(ref[:, shown], ref, FPS)
    assert w.speed == pytest.approx(1 / 1.5, rel=0.01)


def test_time_warp_without_reference_motion_is_nan():
    t = np.arange(10)
    still = np.zeros((1, 10, 3))
    w = fit_time_warp(still, still, FPS)
    assert math.isnan(w.speed) and "less than 1 cm" in w.reason
    del t


# -- readouts over a whole synthetic example ---------------------------------------------------------

H, W = 48, 64
K = np.array([[60.0, 0, W / 2 - 0.5], [0, 60.0, H / 2 - 0.5], [0, 0, 1]])


def _example(z_of_t, n_frames=24, camera_shift_px=0.0, freeze=False):
    """A camera at the origin looking along +y (Blender: camera -z -> world +y), one actor 2 m in front
    falling along world z; a wall at 4 m behind it. Generated = reference except as asked."""
    R = np.array([[1.0, 0, 0], [0, 0, -1], [0, 1, 0]])  # camera x -> world x, camera -z -> world +y, y up -> z
    c2w = np.eye(4)
    c2w[:3, :3] = R
    t = np.arange(n_frames) / FPS
    z = z_of_t(t)
    pos = np.stack([np.zeros_like(z), np.full_like(z, 2.0), z], -1)[None]  # (1,T,3)
    # 9 tracked points on a small square around the actor centre, projected
    offs = np.array([(dx, 0.0, dz) for dx in (-0.03, 0, 0.03) for dz in (-0.03, 0, 0.03)])
    pts = pos[0][None] + offs[:, None]  # (P,T,3)
    cam = np.einsum("ij,ptj->pti", R.T, pts)  # world -> Blender camera (camera at origin)
    depth = -cam[..., 2]
    u = K[0, 0] * cam[..., 0] / depth + K[0, 2]
    v = -K[1, 1] * cam[..., 1] / depth + K[1, 2]
    tracks = np.stack([u, v], -1)
    depth_map = np.full((n_frames, H, W), 4.0)
    masks = np.zeros((n_frames, 1, H, W), bool)
    for k in range(n_frames):
        x0, y0 = int(round(u[:, k].mean())), int(round(v[:, k].mean()))
        masks[k, 0, max(y0 - 3, 0):y0 + 4, max(x0 - 3, 0):x0 + 4] = True
        depth_map[k][masks[k, 0]] = 2.0
    gen_tracks, gen_depth, gen_masks = tracks.copy(), depth_map.copy(), masks.copy()
    if freeze:
        gen_tracks[:] = tracks[:, :1]
        gen_depth[:] = depth_map[:1]
        gen_masks[:] = masks[:1]
    bg = np.array([(x, y) for x in (5.0, 20.0, 40.0, 58.0) for y in (5.0, 40.0)])
    bg_tracks = np.repeat(bg[:, None], n_frames, 1) + np.array([camera_shift_px, 0])[None, None] * t[None, :, None]
    inputs = MetricInputs(
        ref_rgb=np.zeros((n_frames, H, W, 3), np.uint8), gen_rgb=np.zeros((n_frames, H, W, 3), np.uint8),
        ref_masks=masks, gen_masks=gen_masks, ref_tracks=tracks, gen_tracks=gen_tracks,
        ref_visibility=np.ones(tracks.shape[:2], bool), gen_visibility=np.ones(tracks.shape[:2], bool),
        track_actor=np.zeros(len(offs), int), ref_depth_m=depth_map, gen_disparity=1.0 / gen_depth, K=K,
        camera_to_world=c2w, actor_positions_m=pos, ref_points_m=pts, bg_tracks=bg_tracks,
        bg_confidence=np.ones(bg_tracks.shape[:2]))
    return ReadoutContext(inputs=inputs, fps=FPS, ref_positions_m=pos, free_at_start=np.array([True]),
                          support_top_m=-0.6, actor_radius_m=np.array([0.03]), gravity_m_s2=9.81,
                          restitution_nominal=np.array([0.5]), task="bounce", actor_names=("ball_0",))


def test_readouts_of_a_bounce_reconstructed_through_the_camera():
    ctx = _example(lambda t: bounce_z(t, z0=0.0, e=0.5, floor=-0.5))
    r = compute_readouts(ctx)
    assert set(r) == set(READOUTS)
    assert r["world"]["value"] < 1e-9 and r["world"]["fits"]["frame0"]["scale"] == pytest.approx(1.0)
    assert r["gravity"]["value"] == pytest.approx(9.81, rel=1e-6) and r["gravity"]["frames"] == 8
    assert r["gravity"]["contact_frame"] == r["gravity"]["reference_contact_frame"] == 8
    assert r["speed"]["value"] == pytest.approx(1.0, abs=1e-3)
    assert r["gravity"]["per_speed2"] == pytest.approx(9.81, rel=1e-2)
    assert r["restitution"]["value"] == pytest.approx(0.5, abs=1e-6)
    assert r["restitution"]["reference"] == pytest.approx(0.5, abs=1e-6)
    assert r["flags"]["raised"] == []
    assert r["flags"]["example"]["identity"] is None  # IdDrift not given: undefined, not False


def test_frozen_and_camera_flags():
    frozen = compute_readouts(_example(lambda t: bounce_z(t, z0=0.0, floor=-0.5), freeze=True))
    assert frozen["flags"]["raised"] == ["frozen"]
    assert math.isnan(frozen["gravity"]["value"]) and frozen["gravity"]["reason"]
    panned = compute_readouts(_example(lambda t: bounce_z(t, z0=0.0, floor=-0.5), camera_shift_px=24.0))
    assert panned["flags"]["raised"] == ["camera"]
    assert panned["flags"]["camera"]["max_shift_h"] == pytest.approx(23 / 24 * 24.0 / 24 / H * 24, rel=1e-3)


def test_undefined_readouts_are_nan_with_a_reason_and_null_in_json():
    ctx = _example(lambda t: np.zeros_like(t))  # the reference never moves
    r = compute_readouts(ctx)
    for name in ("speed", "gravity", "restitution"):
        assert math.isnan(r[name]["value"]) and r[name]["reason"], name
    assert r["flags"]["example"]["frozen"] is None
    j = to_jsonable(r)
    assert j["speed"]["value"] is None and j["gravity"]["value"] is None


def test_aggregation_medians_iqr_and_flag_rates():
    records = []
    for i, (s, g, frozen) in enumerate([(1.0, 9.8, False), (0.5, 2.5, False), (0.0, None, True), (2.0, 40.0, None)]):
        readouts = {"speed": {"value": s}, "gravity": {"value": float("nan") if g is None else g,
                                                       "per_speed2": float("nan")},
                    "restitution": {"value": float("nan")},
                    "flags": {"example": {"frozen": frozen, "camera": False}}}
        records.append({"id": f"{i}", "task": "free_fall" if i < 2 else "bounce", "partition": "p",
                        "readouts": summary(readouts)})
    block = aggregate_readouts(records)
    o = block["overall"]
    assert o["speed"]["median"] == pytest.approx(0.75) and o["speed"]["finite"] == 4
    assert o["speed"]["q25"] == pytest.approx(np.percentile([1, 0.5, 0, 2], 25))
    assert o["gravity"]["median"] == pytest.approx(9.8) and o["gravity"]["finite"] == 3
    assert o["restitution"]["median"] is None and o["restitution"]["finite"] == 0
    assert o["flags"]["frozen"] == {"raised": 1, "defined": 3, "rate": pytest.approx(1 / 3)}
    assert block["by_task"]["free_fall"]["speed"]["median"] == pytest.approx(0.75)


def test_a_readout_of_your_own_is_one_registration():
    from rigidbench.readouts import ReadoutInfo

    with READOUTS.added(ReadoutInfo("height_drop", f"{__name__}:_height_drop", "drop", "m", "first to last height")):
        r = compute_readouts(_example(lambda t: -0.5 * t), names=["height_drop"])
    assert r["height_drop"]["value"] == pytest.approx(0.5 * 23 / FPS)


def _height_drop(ctx):
    from rigidbench.readouts.physics import anchored_positions

    z = anchored_positions(ctx)[0, :, 2]
    return {"value": float(z[0] - z[-1]), "reason": None}
