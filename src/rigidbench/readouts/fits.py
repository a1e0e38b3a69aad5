"""The fits behind the physics readouts, as pure functions over small arrays (no camera, no images).

- ``fit_parabola``: least squares z(t) = c0 + c1 t - g t^2 / 2 with the standard error of g;
- ``ballistic_window``: the frames over which one height trajectory follows one parabola, grown
  frame by frame from its release until a frame leaves the parabola (the first contact);
- ``fit_fixed_curvature``: z(t) + g t^2 / 2 = b0 + b1 t for a known g (the flight after a bounce);
- ``bounce_coefficient``: restitution from the parabolas before and after the first contact;
- ``fit_time_warp``: the playback speed s and offset d with p_gen(t) ~ p_ref(s t + d).

Units are whatever the caller passes (metres and seconds in the readouts). Undefined results are
NaN, never 0; every function that can fail says why in its result.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

#: a frame leaves the parabola fitted to the frames before it when its height differs from the
#: parabola's prediction by more than max(WINDOW_TOL_M, WINDOW_TOL_RMS x the fit's RMS residual)
WINDOW_TOL_M = 0.005
WINDOW_TOL_RMS = 4.0
#: an actor has been released at the first frame whose height differs from frame 0 by more than this
RELEASE_TOL_M = 0.002
#: fewest frames a gravity fit uses (3 fix a parabola; the 4th gives its uncertainty)
MIN_GRAVITY_FRAMES = 4


@dataclass(frozen=True)
class Parabola:
    """z(t) = c0 + c1 t - g t^2 / 2 over ``n`` samples; ``g_se`` the least-squares standard error of g
    (NaN with 3 samples), ``rms`` the residual RMS."""

    c0: float
    c1: float
    g: float
    g_se: float
    rms: float
    n: int

    def __call__(self, t):
        t = np.asarray(t, np.float64)
        return self.c0 + self.c1 * t - 0.5 * self.g * t * t

    def velocity(self, t):
        return self.c1 - self.g * np.asarray(t, np.float64)


def fit_parabola(t: np.ndarray, z: np.ndarray) -> Parabola:
    """t (n,) s, z (n,) m with n >= 3 finite samples. Least squares of z = c0 + c1 t - g t^2/2."""
    t, z = np.asarray(t, np.float64), np.asarray(z, np.float64)
    if t.size < 3:
        raise ValueError(f"a parabola needs 3 samples, got {t.size}")
    t_mid = t.mean()  # centred for conditioning; g does not depend on the origin of time
    X = np.stack([np.ones_like(t), t - t_mid, -0.5 * (t - t_mid) ** 2], axis=1)
    coef, *_ = np.linalg.lstsq(X, z, rcond=None)
    resid = z - X @ coef
    dof = t.size - 3
    rms = float(np.sqrt(np.mean(resid ** 2)))
    if dof > 0:
        sigma2 = float(resid @ resid) / dof
        cov = sigma2 * np.linalg.inv(X.T @ X)
        g_se = float(math.sqrt(max(cov[2, 2], 0.0)))
    else:
        g_se = float("nan")
    a0, a1, g = (float(c) for c in coef)
    # back to the origin t = 0: z = a0 + a1 (t - m) - g (t - m)^2 / 2
    c1 = a1 + g * t_mid
    c0 = a0 - a1 * t_mid - 0.5 * g * t_mid ** 2
    return Parabola(c0, c1, g, g_se, rms, int(t.size))


@dataclass(frozen=True)
class Window:
    """Frames ``first``..``last`` (inclusive) follow one parabola; ``ended_by`` is "deviation" (frame
    last + 1 left it: a contact), "end" (the clip ran out) or "gap" (a missing position)."""

    first: int
    last: int
    ended_by: str

    @property
    def n(self) -> int:
        return self.last - self.first + 1


def release_frame(z: np.ndarray, tol_m: float = RELEASE_TOL_M) -> int | None:
    """The last frame at rest before the height first differs from frame 0 by more than ``tol_m``
    (0 for a release at the first frame); None when it never moves or frame 0 is missing."""
    z = np.asarray(z, np.float64)
    if not np.isfinite(z[0]):
        return None
    moved = np.flatnonzero(np.isfinite(z) & (np.abs(z - z[0]) > tol_m))
    if moved.size == 0:
        return None
    return int(max(moved[0] - 1, 0))


def grow_window(t: np.ndarray, z: np.ndarray, first: int, min_frames: int, fit, tol_m: float = WINDOW_TOL_M,
                tol_rms: float = WINDOW_TOL_RMS) -> Window | None:
    """Grow a window from ``first``: the first ``min_frames`` frames are taken as they are; each later
    frame joins while ``fit(t, z)`` of the frames before it predicts it within max(tol_m, tol_rms x rms).
    ``fit`` returns an object with ``__call__(t)`` and ``rms``. None when fewer than min_frames are finite."""
    n = len(z)
    last = first + min_frames - 1
    if last >= n or not np.isfinite(z[first:last + 1]).all():
        return None
    while last + 1 < n:
        nxt = last + 1
        if not np.isfinite(z[nxt]):
            return Window(first, last, "gap")
        model = fit(t[first:last + 1], z[first:last + 1])
        tol = max(tol_m, tol_rms * model.rms)
        if abs(float(model(t[nxt])) - z[nxt]) > tol:
            return Window(first, last, "deviation")
        last = nxt
    return Window(first, last, "end")


def ballistic_window(t: np.ndarray, z: np.ndarray, tol_m: float = WINDOW_TOL_M) -> Window | None:
    """The free flight of height trajectory z (T,) m at times t (T,) s, from its release (the last
    frame at rest) to the last frame before it leaves the parabola; None when it never moves."""
    start = release_frame(z)
    if start is None:
        return None
    return grow_window(np.asarray(t, np.float64), np.asarray(z, np.float64), start, 3, fit_parabola, tol_m)


def fit_fixed_curvature(t: np.ndarray, z: np.ndarray, g: float) -> Parabola:
    """The flight with known gravity ``g``: least squares of z + g t^2/2 = c0 + c1 t (``g_se`` 0: not fitted)."""
    t, z = np.asarray(t, np.float64), np.asarray(z, np.float64)
    y = z + 0.5 * g * t * t
    if t.size == 1:
        raise ValueError("a flight with known gravity needs 2 samples")
    b1, b0 = np.polyfit(t, y, 1)
    resid = y - (b0 + b1 * t)
    return Parabola(float(b0), float(b1), float(g), 0.0, float(np.sqrt(np.mean(resid ** 2))), int(t.size))


@dataclass(frozen=True)
class Bounce:
    """Restitution ``e`` = -v_after / v_before at the contact time ``t_contact_s``; NaN with ``reason``."""

    e: float
    v_before: float = float("nan")
    v_after: float = float("nan")
    t_contact_s: float = float("nan")
    frames_before: int = 0
    frames_after: int = 0
    reason: str | None = None


def bounce_coefficient(t: np.ndarray, z: np.ndarray, tol_m: float = WINDOW_TOL_M) -> Bounce:
    """Restitution of the first bounce of height trajectory z (T,) m at times t (T,) s: the flight before
    the first contact is a parabola (its g is used after the contact too); the flight after it starts at
    the next frame and is grown with that g; the contact time is where the two parabolas meet (clamped to
    the frame interval); e = -v_after / v_before there."""
    t, z = np.asarray(t, np.float64), np.asarray(z, np.float64)
    pre = ballistic_window(t, z, tol_m)
    if pre is None:
        return Bounce(float("nan"), reason="the actor never leaves its starting height")
    if pre.ended_by != "deviation":
        return Bounce(float("nan"), reason="no contact ends the first flight within the clip"
                      if pre.ended_by == "end" else "a missing position interrupts the first flight")
    if pre.n < 3:
        return Bounce(float("nan"), reason="fewer than 3 frames before the contact")
    p = fit_parabola(t[pre.first:pre.last + 1], z[pre.first:pre.last + 1])
    first_after = pre.last + 1
    post = grow_window(t, z, first_after, 2, lambda tt, zz: fit_fixed_curvature(tt, zz, p.g), tol_m)
    if post is None:
        return Bounce(float("nan"), frames_before=pre.n, reason="fewer than 2 frames after the first contact")
    q = fit_fixed_curvature(t[post.first:post.last + 1], z[post.first:post.last + 1], p.g)
    # p(t) - q(t) is linear (same curvature): they meet at t_c
    slope = p.c1 - q.c1
    t_lo, t_hi = t[pre.last], t[first_after]
    t_c = (q.c0 - p.c0) / slope if slope != 0 else 0.5 * (t_lo + t_hi)
    t_c = float(min(max(t_c, t_lo), t_hi))
    v_before, v_after = float(p.velocity(t_c)), float(q.velocity(t_c))
    if not v_before < 0:
        return Bounce(float("nan"), v_before, v_after, t_c, pre.n, post.n, "not moving down before the contact")
    return Bounce(float(max(-v_after / v_before, 0.0)), v_before, v_after, t_c, pre.n, post.n)


@dataclass(frozen=True)
class TimeWarp:
    """p_gen(t) ~ p_ref(speed t + offset_s). ``speed_se``/``offset_se_s``: Gauss-Newton standard errors;
    ``rmse_m``: RMS position error after the alignment over ``n_compared`` actor-frames; ``explained``:
    1 - SSE / sum |p_gen|^2 (the share of the generated displacement the aligned reference explains)."""

    speed: float
    offset_s: float
    speed_se: float = float("nan")
    offset_se_s: float = float("nan")
    rmse_m: float = float("nan")
    explained: float = float("nan")
    n_compared: int = 0
    reason: str | None = None
    grid: dict = field(default_factory=dict, repr=False)


#: the search range of the playback speed and its grid step
SPEED_RANGE = (0.0, 3.0)
SPEED_STEP = 0.02
#: the grid caps each actor-frame's position error at this share of the reference's largest displacement,
#: so a few misreconstructed frames cannot pay for a warp that pushes them out of the comparison (eval 00020
#: under ``slow`` 1.0: kiwi frames read 0.7-1 m off gave s = 3.12 instead of 0.5 with an uncapped sum)
WARP_OUTLIER_SHARE = 0.25
#: refinement: a generated frame is matched to the reference instant nearest in position within this
#: many frames of the current alignment, and counts when the reference moves faster there (m/s, summed
#: over actors) and is past its first half frame (before it, every instant at rest looks the same)
MATCH_WINDOW_FRAMES = 1.5
MIN_MATCH_SPEED = 0.2


def _sample_reference(ref: np.ndarray, t_ref: np.ndarray, tau: np.ndarray) -> np.ndarray:
    """ref (N,T,3) displacements at times t_ref (T,); tau (...) s. Linear interpolation; before the
    first frame the reference holds its first value (at rest before release); NaN past the last."""
    n_act = ref.shape[0]
    flat = tau.reshape(-1)
    out = np.empty((n_act, flat.size, 3))
    for a in range(n_act):
        for c in range(3):
            out[a, :, c] = np.interp(flat, t_ref, ref[a, :, c])
    out[:, flat > t_ref[-1] + 1e-9] = np.nan
    return out.reshape(n_act, *tau.shape, 3)


def _warp_sse(gen: np.ndarray, ref: np.ndarray, t: np.ndarray, t_ref: np.ndarray, speeds: np.ndarray,
              offsets: np.ndarray, min_compared: int, outlier: float,
              pred: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """SSE (each actor-frame's squared error capped at outlier^2) and number compared on the (S, D) grid;
    SSE inf where fewer than min_compared actor-frames. ``pred``: the reference sampled on the grid
    (``_warp_grid``) when already known."""
    if pred is None:
        pred = _warp_grid(ref, t, t_ref, speeds, offsets)
    diff = pred - gen[:, None, None, :, :]
    sq = np.minimum(np.sum(diff * diff, axis=-1), outlier * outlier)  # (N,S,D,T); NaN stays NaN
    ok = np.isfinite(sq)
    n = ok.sum(axis=(0, 3))
    sse = np.where(ok, sq, 0.0).sum(axis=(0, 3))
    sse = np.where(n >= min_compared, sse, np.inf)
    return sse, n


def _warp_grid(ref: np.ndarray, t: np.ndarray, t_ref: np.ndarray, speeds: np.ndarray,
               offsets: np.ndarray) -> np.ndarray:
    """(N,S,D,T,3): the reference displacements at s t + d for every speed s and offset d of the grid."""
    tau = speeds[:, None, None] * t[None, None, :] + offsets[None, :, None]  # (S,D,T)
    return _sample_reference(ref, t_ref, tau)


def _matching_instants(gen: np.ndarray, ref: np.ndarray, t: np.ndarray, t_ref: np.ndarray, centre: np.ndarray,
                       usable: np.ndarray, fps: float, step: float) -> np.ndarray:
    """(T,) for each usable generated frame k, the reference instant within MATCH_WINDOW_FRAMES of ``centre[k]``
    (searched in steps of ``step`` s) whose positions are nearest the generated ones; NaN where the best is at
    the search window's edge (not a minimum) or the window is empty."""
    taus = np.full(t.size, np.nan)
    for k in np.flatnonzero(usable):
        lo = max(0.0, centre[k] - MATCH_WINDOW_FRAMES / fps)
        hi = min(t_ref[-1], centre[k] + MATCH_WINDOW_FRAMES / fps)
        if hi <= lo:
            continue
        cand = np.arange(lo, hi + 0.5 * step, step)
        dist = np.sum((_sample_reference(ref, t_ref, cand) - gen[:, k][:, None]) ** 2, axis=(0, 2))
        m = int(np.argmin(dist))
        taus[k] = cand[m] if 0 < m < cand.size - 1 or cand[m] in (0.0, t_ref[-1]) else np.nan
    return taus


def fit_time_warp(gen: np.ndarray, ref: np.ndarray, fps: float, min_motion_m: float = 0.01,
                  memo: dict | None = None) -> TimeWarp:
    """gen (N,T,3) and ref (N,T_ref,3) displacements from frame 0 (m) of the same actors at frames k / fps
    (the reference may be longer: a fast clip shows its later frames); NaN = no position. Finds (s, d) minimising sum |gen(t_k) - ref(s t_k + d)|^2 over the actor-frames where both
    exist (the reference is held at rest before t = 0 and undefined after its last frame), each error capped
    at WARP_OUTLIER_SHARE of the reference's largest displacement, requiring at least half of the finite
    generated actor-frames (and 3 frames) to be compared: a grid over s in
    SPEED_RANGE (step SPEED_STEP) and d in [-(clip length), +(clip length) / 2] in half frames, then a refinement in time (see MATCH_WINDOW_FRAMES): each generated frame's best
    matching reference instant tau_k, and the least-squares line tau_k = s t_k + d through the informative
    frames, whose standard errors are reported (TimeWarp.grid["informative_frames"] counts them). NaN with a reason when the reference moves less than ``min_motion_m``.
    ``memo``: a dict kept between calls with the same ``ref`` and ``fps`` (the samples of one example), where
    the reference sampled on the grid is kept for each generated length."""
    gen, ref = np.asarray(gen, np.float64), np.asarray(ref, np.float64)
    t = np.arange(gen.shape[1]) / float(fps)
    t_ref = np.arange(ref.shape[1]) / float(fps)
    # actors with a usable reference; generated NaN frames simply do not count
    keep = np.isfinite(ref).all(axis=(1, 2))
    if not keep.any():
        return TimeWarp(float("nan"), float("nan"), reason="no actor has a complete reference trajectory")
    gen, ref = gen[keep], ref[keep]
    if not np.nanmax(np.linalg.norm(ref, axis=-1)) > min_motion_m:
        return TimeWarp(float("nan"), float("nan"),
                        reason=f"the reference moves less than {min_motion_m * 100:g} cm: no timing to recover")
    finite = np.isfinite(gen).all(axis=-1)
    n_finite = int(finite.sum())
    if finite.any(axis=0).sum() < 3:
        return TimeWarp(float("nan"), float("nan"), reason="fewer than 3 frames with a generated position")
    min_compared = max(3, int(math.ceil(0.5 * n_finite)))
    speeds = np.arange(SPEED_RANGE[0], SPEED_RANGE[1] + 1e-9, SPEED_STEP)
    span = max(t[-1], t_ref[-1])
    offsets = np.arange(-span, 0.5 * span + 1e-9, 0.5 / fps)
    outlier = WARP_OUTLIER_SHARE * float(np.nanmax(np.linalg.norm(ref, axis=-1)))
    if memo is None:
        pred = _warp_grid(ref, t, t_ref, speeds, offsets)
    else:
        key = ("grid", t.size, float(fps))
        if key not in memo:
            memo[key] = _warp_grid(ref, t, t_ref, speeds, offsets)
        pred = memo[key]
    sse, _ = _warp_sse(gen, ref, t, t_ref, speeds, offsets, min_compared, outlier, pred)
    if not np.isfinite(sse).any():
        return TimeWarp(float("nan"), float("nan"), reason="no speed and offset compare enough frames")
    i, j = np.unravel_index(int(np.argmin(sse)), sse.shape)
    s, d = float(speeds[i]), float(offsets[j])
    # Refinement in time: each generated frame's matching reference instant, searched within
    # MATCH_WINDOW_FRAMES of the current alignment, then a straight line through the informative ones
    # (where the reference moves faster than MIN_MATCH_SPEED and has left its first half frame).
    step = 1.0 / (16 * fps)
    v_ref = np.linalg.norm(np.gradient(ref, t_ref, axis=1), axis=-1).sum(axis=0)  # (T_ref,) summed speeds
    usable = finite.all(axis=0)
    n_informative, line_se = 0, (float("nan"), float("nan"))
    for _ in range(3):
        taus = _matching_instants(gen, ref, t, t_ref, s * t + d, usable, fps, step)
        speed_at = np.interp(taus, t_ref, v_ref)
        info = np.isfinite(taus) & (taus > 0.5 / fps) & (taus < t_ref[-1]) & (speed_at > MIN_MATCH_SPEED)
        n_informative = int(info.sum())
        if n_informative < 3:
            break
        w = np.ones(n_informative)
        A = np.stack([t[info], np.ones(n_informative)], axis=1)
        sw = np.sqrt(w)
        coef, *_ = np.linalg.lstsq(A * sw[:, None], taus[info] * sw, rcond=None)
        s, d = float(coef[0]), float(coef[1])
        resid = taus[info] - A @ coef
        if n_informative > 2:
            AtWA = A.T @ (A * w[:, None])
            cov = float(np.sum(w * resid ** 2)) / (n_informative - 2) * np.linalg.inv(AtWA)
            line_se = (math.sqrt(max(cov[0, 0], 0.0)), math.sqrt(max(cov[1, 1], 0.0)))
    tau = s * t + d
    pred = _sample_reference(ref, t_ref, tau)  # (N,T,3)
    sq = np.sum((pred - gen) ** 2, axis=-1)
    ok = np.isfinite(sq)
    n = int(ok.sum())
    sse_best = float(sq[ok].sum())
    total = float(np.sum(np.where(ok, np.sum(gen * gen, axis=-1), 0.0)))
    explained = 1.0 - sse_best / total if total > 0 else float("nan")
    speed_se, offset_se = line_se
    return TimeWarp(s, d, speed_se, offset_se, float(math.sqrt(sse_best / n)) if n else float("nan"),
                    explained, n, None, {"informative_frames": n_informative})
