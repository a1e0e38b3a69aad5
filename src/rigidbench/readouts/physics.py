"""World trajectories of the generated clip and the readouts fitted to them: playback speed and time
offset, gravity, restitution.

World trajectories (``world``). Each active actor's position per frame is the geometric median of
its generated track points that are visible in the generated clip, unprojected with the known camera
at the depth of the generated disparity (``metrics.depth.reconstruct_actor_positions``, the ATE-3D
reconstruction), except where half or more of an actor's visible points are silhouette points (their
bilinear depth lookup reads a pixel off the actor's generated mask, another surface, often metres behind):
their median is not the actor's, so that actor-frame has no position (ATE-3D keeps the paper's rule). The
disparity's scale and shift are fitted on frame 0 only (``frame0``): that frame is the image the model was
given, and its rendered depth is known, so nothing of the reference's later frames enters. ATE-3D instead
fits one scale and shift over every frame of the reference (``clip``), which absorbs a depth model's scale
drift over time but uses the reference's future.
Both are computed; every readout uses ``frame0``; the speed and gravity readouts also report their
``clip``-fit values beside it, and the ``world`` record says which fit reproduces the simulated
trajectory better on that example (a diagnostic that does use the reference).

A median of visible surface points is not the body origin: it sits about one radius towards the
camera. Readouts therefore use displacements from frame 0, anchored at the reference's frame-0
position (shared with the model): p~(t) = p_ref(0) + p^(t) - p^(0). World +z is up.
"""

from __future__ import annotations

import math

import numpy as np

from rigidbench.metrics.common import inside_image
from rigidbench.metrics.depth import DepthAlignment, fit_disparity_alignment, reconstruct_actor_positions
from rigidbench.readouts.fits import (MIN_GRAVITY_FRAMES, ballistic_window, bounce_coefficient, fit_parabola,
                                      fit_time_warp)

FITS = ("frame0", "clip")
#: below this playback speed g s^-2 is not reported (it divides by s^2)
MIN_SPEED_FOR_SCALING = 0.1
#: an actor moves when its reference displacement from frame 0 exceeds this (as ATE-3D's A_m)
MIN_MOTION_M = 0.01


def _nan(reason: str, **extra) -> dict:
    return {"value": float("nan"), "reason": reason, **extra}


def alignment(ctx, fit: str = "frame0") -> DepthAlignment:
    """The disparity-to-depth fit: ``frame0`` (the model's input frame only) or ``clip`` (ATE-3D's)."""
    x = ctx.inputs
    if fit == "frame0":
        return ctx.shared("alignment:frame0", lambda: fit_disparity_alignment(x.gen_disparity[:1], x.ref_depth_m[:1]))
    if fit == "clip":
        return x.shared("disparity_alignment", lambda: fit_disparity_alignment(x.gen_disparity, x.ref_depth_m))
    raise ValueError(f"unknown fit '{fit}': one of {', '.join(FITS)}")


def off_own_mask(inputs) -> np.ndarray:
    """(P,T) bool: the generated track points whose bilinear depth lookup reads a pixel outside their own
    actor's generated mask (a silhouette point: that pixel is another surface); False outside the image."""
    tracks = np.asarray(inputs.gen_tracks, np.float64)
    masks = inputs.gen_masks
    h, w = masks.shape[2:]
    actor = np.asarray(inputs.track_actor)
    out = np.zeros(tracks.shape[:2], bool)
    inside = inside_image(tracks, h, w)
    for t in range(tracks.shape[1]):
        use = np.flatnonzero(inside[:, t])
        c0 = np.minimum(np.floor(np.clip(tracks[use, t, 0], 0.0, w - 1.0)).astype(np.int64), max(w - 2, 0))
        r0 = np.minimum(np.floor(np.clip(tracks[use, t, 1], 0.0, h - 1.0)).astype(np.int64), max(h - 2, 0))
        c1, r1 = np.minimum(c0 + 1, w - 1), np.minimum(r0 + 1, h - 1)
        a, frame = actor[use], masks[t]
        out[use, t] = ~(frame[a, r0, c0] & frame[a, r0, c1] & frame[a, r1, c0] & frame[a, r1, c1])
    return out


def world_positions(ctx, fit: str = "frame0") -> np.ndarray:
    """(N,T,3) reconstructed world positions (m) of the generated clip; NaN where no point is usable or where
    half or more of an actor's visible points are silhouette points (``off_own_mask``): their depth lookup
    mixes in another surface, and a median of them is not the actor's (eval 00020's kiwi, half hidden by a
    ramp: its last 1-6 visible points mixed 1.95 m with the wall at 6.3 m and read it 0.7-1 m deeper and
    12-16 cm below the counter)."""
    def compute():
        x = ctx.inputs
        c2w = np.asarray(x.camera_to_world, np.float64)
        out, _ = reconstruct_actor_positions(x.gen_tracks, x.gen_visibility, x.track_actor, ctx.n_actors,
                                             x.gen_disparity, x.ref_depth_m.shape[1:], alignment(ctx, fit), x.K,
                                             c2w[:3, :3], c2w[:3, 3])
        shown = np.asarray(x.gen_visibility, bool) & inside_image(x.gen_tracks, *x.ref_depth_m.shape[1:])
        silhouette = shown & off_own_mask(x)
        for a in range(ctx.n_actors):
            mine = np.asarray(x.track_actor) == a
            out[a, 2 * silhouette[mine].sum(axis=0) >= np.maximum(shown[mine].sum(axis=0), 1)] = np.nan
        return out
    return ctx.shared(f"world:{fit}", compute)


def anchored_positions(ctx, fit: str = "frame0") -> np.ndarray:
    """(N,T,3) p_ref(0) + p^(t) - p^(0): generated displacements from the shared first frame, placed at
    the reference's frame-0 body positions. NaN for an actor without a frame-0 reconstruction."""
    p = world_positions(ctx, fit)
    return np.asarray(ctx.ref_positions_m, np.float64)[:, :1] + (p - p[:, :1])


def generated_displacements(ctx, fit: str = "frame0") -> np.ndarray:
    p = world_positions(ctx, fit)
    return p - p[:, :1]


def reference_displacements(ctx) -> np.ndarray:
    ref = np.asarray(ctx.ref_positions_m, np.float64)
    return ref - ref[:, :1]


def _trajectory_rmse(ctx, fit: str) -> float:
    ref = np.asarray(ctx.ref_positions_m, np.float64)[:, :ctx.n_frames]
    d = np.sum((anchored_positions(ctx, fit) - ref) ** 2, axis=-1)
    ok = np.isfinite(d)
    return float(np.sqrt(d[ok].mean())) if ok.any() else float("nan")


def readout_world(ctx) -> dict:
    """Both disparity fits and how well each one's anchored trajectory matches the simulated one."""
    fits = {}
    for fit in FITS:
        a = alignment(ctx, fit)
        fits[fit] = {"scale": a.scale, "shift": a.shift, "n_pixels": a.n_pixels,
                     "rmse_vs_reference_m": _trajectory_rmse(ctx, fit)}
    f0, fc = fits["frame0"]["rmse_vs_reference_m"], fits["clip"]["rmse_vs_reference_m"]
    frames = np.isfinite(world_positions(ctx)).all(axis=-1).sum(axis=1)
    better = ("clip" if fc < f0 else "frame0") if math.isfinite(f0) and math.isfinite(fc) else None
    out = {"value": f0, "unit": "m", "used": "frame0", "fits": fits, "better_fit": better,
           "frames_reconstructed": [int(n) for n in frames], "reason": None}
    if not math.isfinite(f0):
        out["reason"] = ("no pixel of frame 0 has a finite disparity and a valid depth"
                         if alignment(ctx).n_pixels == 0 else "no actor has a reconstruction at frame 0")
    return out


def time_warp(ctx, fit: str = "frame0"):
    """The example's TimeWarp (playback speed and offset against the reference), computed once per fit."""
    memo = ctx.reference_shared("time_warp", dict)  # the reference on the warp grid, shared by fits and samples
    return ctx.shared(f"warp:{fit}", lambda: fit_time_warp(generated_displacements(ctx, fit),
                                                           reference_displacements(ctx), ctx.fps, MIN_MOTION_M,
                                                           memo=memo))


def readout_speed(ctx) -> dict:
    """Playback speed s and time offset d with p~(t) ~ p_ref(s t + d), its standard errors and the error left."""
    w = time_warp(ctx, "frame0")
    wc = time_warp(ctx, "clip")
    moving = np.linalg.norm(reference_displacements(ctx), axis=-1).max(axis=1) > MIN_MOTION_M
    scale = float(np.linalg.norm(reference_displacements(ctx)[moving][:, -1], axis=-1).mean()) if moving.any() else 0
    out = {"value": w.speed, "unit": "x real time", "offset_s": w.offset_s, "offset_frames": w.offset_s * ctx.fps,
           "speed_se": w.speed_se, "offset_se_s": w.offset_se_s, "confidence": w.explained,
           "rmse_after_m": w.rmse_m, "rmse_after_rel": w.rmse_m / scale if scale > 0 else float("nan"),
           "n_compared": w.n_compared, "fit": "frame0", "value_clip_fit": wc.speed,
           "offset_s_clip_fit": wc.offset_s, "reason": w.reason}
    return out


def _reference_window(ctx, a: int):
    def compute():
        ref = np.asarray(ctx.ref_positions_m, np.float64)[a, :, 2]
        return ballistic_window(np.arange(ref.size) / ctx.fps, ref)
    return ctx.reference_shared(f"ballistic_window:{a}", compute)


def _gravity_fits(ctx, fit: str) -> list[dict]:
    z_all = anchored_positions(ctx, fit)[..., 2]
    t = ctx.times_s
    actors = []
    for a in range(ctx.n_actors):
        rec = {"actor": ctx.actor_names[a], "g": float("nan"), "g_se": float("nan"), "frames": 0,
               "first_frame": None, "contact_frame": None, "reference_contact_frame": None, "reason": None}
        if not ctx.free_at_start[a]:
            rec["reason"] = "touches another body at frame 0 in the reference: not ballistic"
            actors.append(rec)
            continue
        ref_w = _reference_window(ctx, a)
        if ref_w is not None and ref_w.ended_by == "deviation":
            rec["reference_contact_frame"] = ref_w.last + 1
        w = ballistic_window(t, z_all[a])
        if w is None:
            rec["reason"] = ("no reconstruction at frame 0" if not np.isfinite(z_all[a, 0])
                             else "the generated actor never leaves its starting height")
        else:
            rec["first_frame"] = w.first
            rec["contact_frame"] = w.last + 1 if w.ended_by == "deviation" else None
            rec["frames"] = w.n
            if w.n < MIN_GRAVITY_FRAMES:
                rec["reason"] = f"ballistic window of {w.n} frames, fewer than {MIN_GRAVITY_FRAMES}"
            else:
                p = fit_parabola(t[w.first:w.last + 1], z_all[a, w.first:w.last + 1])
                rec.update(g=p.g, g_se=p.g_se, rms_m=p.rms)
        actors.append(rec)
    return actors


def _best(actors: list[dict]) -> dict | None:
    ok = [r for r in actors if math.isfinite(r["g"])]
    return max(ok, key=lambda r: (r["frames"], -r["g_se"] if math.isfinite(r["g_se"]) else -np.inf)) if ok else None


def readout_gravity(ctx) -> dict:
    """g^ (m/s^2) from the ballistic flight of each free actor; the example's value is the fit with the most
    frames. Also g^ s^-2 (s from the speed readout) and the window's check against the reference's contact."""
    actors = _gravity_fits(ctx, "frame0")
    best = _best(actors)
    clip_best = _best(_gravity_fits(ctx, "clip"))
    if best is None:
        reasons = sorted({r["reason"] for r in actors if r["reason"]})
        return _nan("; ".join(reasons) or "no active actor", unit="m/s^2", actors=actors, per_speed2=float("nan"),
                    per_speed2_reason="no gravity fit", simulated=ctx.gravity_m_s2, fit="frame0",
                    value_clip_fit=float("nan"))
    s = time_warp(ctx, "frame0").speed
    scaled, scaled_reason = float("nan"), None
    if not math.isfinite(s):
        scaled_reason = "playback speed undefined"
    elif s < MIN_SPEED_FOR_SCALING:
        scaled_reason = f"playback speed {s:.3g} below {MIN_SPEED_FOR_SCALING}"
    else:
        scaled = best["g"] / s ** 2
    ref_c, gen_c = best["reference_contact_frame"], best["contact_frame"]
    return {"value": best["g"], "unit": "m/s^2", "se": best["g_se"], "frames": best["frames"],
            "actor": best["actor"], "per_speed2": scaled, "per_speed2_reason": scaled_reason,
            "contact_frame": gen_c, "reference_contact_frame": ref_c,
            "window_matches_reference": None if ref_c is None or gen_c is None else abs(ref_c - gen_c) <= 1,
            "simulated": ctx.gravity_m_s2, "fit": "frame0",
            "value_clip_fit": clip_best["g"] if clip_best else float("nan"), "actors": actors, "reason": None}


def _reference_bounce(ctx, a: int):
    ref = np.asarray(ctx.ref_positions_m, np.float64)[a, :, 2]
    return bounce_coefficient(np.arange(ref.size) / ctx.fps, ref)


def readout_restitution(ctx) -> dict:
    """e^ = -v_after / v_before at the first contact of each free actor's generated height; the example's
    value is the first actor with one. ``reference`` is the same fit on the simulated trajectory, ``nominal``
    the product of the actor's and the support's restitution (what Bullet multiplies)."""
    z_all = anchored_positions(ctx)[..., 2]
    t = ctx.times_s
    actors = []
    for a in range(ctx.n_actors):
        if not ctx.free_at_start[a]:
            actors.append({"actor": ctx.actor_names[a], "e": float("nan"),
                           "reason": "touches another body at frame 0 in the reference: no free first bounce"})
            continue
        b = bounce_coefficient(t, z_all[a])
        rb = ctx.reference_shared(f"bounce:{a}", lambda: _reference_bounce(ctx, a))
        actors.append({"actor": ctx.actor_names[a], "e": b.e, "v_before_m_s": b.v_before, "v_after_m_s": b.v_after,
                       "contact_time_s": b.t_contact_s, "frames_before": b.frames_before,
                       "frames_after": b.frames_after, "reason": b.reason, "reference": rb.e,
                       "reference_reason": rb.reason, "nominal": float(ctx.restitution_nominal[a])})
    ok = [r for r in actors if math.isfinite(r["e"])]
    if not ok:
        reasons = sorted({r["reason"] for r in actors if r["reason"]})
        return _nan("; ".join(reasons) or "no active actor", unit="1", actors=actors, reference=float("nan"),
                    nominal=float("nan"), fit="frame0")
    r = ok[0]
    return {"value": r["e"], "unit": "1", "actor": r["actor"], "frames_before": r["frames_before"],
            "frames_after": r["frames_after"], "reference": r["reference"], "nominal": r["nominal"], "fit": "frame0",
            "actors": actors, "reason": None}
