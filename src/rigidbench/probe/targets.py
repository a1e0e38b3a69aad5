"""Simulator targets per actor and latent slot (paper appendix E), from a sample bundle.

For slot s with pixel frames F_s (``pooling.slot_frames``, clipped to the encoded frames):

    position          (3) mean world position (m) over F_s
    orientation       (4) mean of the unit quaternions (w, x, y, z) over F_s, sign-fixed to w >= 0 and
                          renormalised (the sign fix makes q and -q one target)
    linear_velocity   (3) mean of the bundle's finite-difference velocity (m/s) over F_s
    angular_velocity  (3) mean angular velocity (rad/s) over F_s
    acceleration      (3) mean of the finite difference of the linear velocity (m/s^2) over F_s
    contact           (1) 1 when any simulator contact in F_s involves the actor, else 0 (binary)
    contact_normal    (3) mean unit contact normal over the actor's contacts in F_s, oriented towards
                          the actor (0 when it has none)

Actors are the bundle's mask actors (both roles), matched to the trajectory by name.
"""

from __future__ import annotations

import numpy as np

from ..rotations import quat_canonical
from .pooling import slot_frames

#: name -> (dimension, kind); kind "binary" is scored by ROC-AUC, "continuous" by R^2
TARGETS: dict[str, tuple[int, str]] = {
    "position": (3, "continuous"),
    "orientation": (4, "continuous"),
    "linear_velocity": (3, "continuous"),
    "angular_velocity": (3, "continuous"),
    "acceleration": (3, "continuous"),
    "contact": (1, "binary"),
    "contact_normal": (3, "continuous"),
}


def slot_targets(positions: np.ndarray, quats: np.ndarray, velocity: np.ndarray, angular: np.ndarray,
                 fps: float, contacts, names: tuple[str, ...], slots: int, frames: int) -> dict[str, np.ndarray]:
    """Arrays (N, T, .) of the N actors ``names`` -> {target: (slots, N, dim) float32}; ``contacts``:
    objects with ``frame``, ``a``, ``b``, ``normals`` (pointing from b towards a); ``frames``: how many
    pixel frames were encoded."""
    n, t = positions.shape[:2]
    accel = np.gradient(velocity, 1.0 / fps, axis=1) if t > 1 else np.zeros_like(velocity)
    out = {k: np.zeros((slots, n, d), dtype=np.float32) for k, (d, _) in TARGETS.items()}
    index = {name: i for i, name in enumerate(names)}
    touching = np.zeros((t, n), dtype=bool)
    normal_sum = np.zeros((t, n, 3))
    for c in contacts:
        if not 0 <= c.frame < t:
            continue
        normal = np.mean(np.asarray(c.normals, dtype=np.float64), axis=0) if c.normals else np.zeros(3)
        for name, sign in ((c.a, 1.0), (c.b, -1.0)):
            if name in index:
                touching[c.frame, index[name]] = True
                normal_sum[c.frame, index[name]] += sign * normal
    for s in range(slots):
        f = [k for k in slot_frames(s) if k < min(t, frames)]
        if not f:
            continue
        out["position"][s] = positions[:, f].mean(axis=1)
        q = quat_canonical(quats[:, f]).mean(axis=1)
        out["orientation"][s] = quat_canonical(q / np.maximum(np.linalg.norm(q, axis=-1, keepdims=True), 1e-12))
        out["linear_velocity"][s] = velocity[:, f].mean(axis=1)
        out["angular_velocity"][s] = angular[:, f].mean(axis=1)
        out["acceleration"][s] = accel[:, f].mean(axis=1)
        out["contact"][s, :, 0] = touching[f].any(axis=0)
        ns = normal_sum[f].sum(axis=0)
        norm = np.linalg.norm(ns, axis=-1, keepdims=True)
        out["contact_normal"][s] = np.where(norm > 1e-12, ns / np.maximum(norm, 1e-12), 0.0)
    return out


def sample_targets(sample, slots: int, frames: int) -> tuple[dict[str, np.ndarray], tuple[str, ...], tuple[str, ...]]:
    """Targets of the bundle ``sample`` for its mask actors: ({target: (slots, N, dim)}, names, roles);
    an actor without a trajectory gets NaN targets (its rows are dropped)."""
    traj = sample.trajectory
    names, roles = sample.actor_names, sample.roles
    order = {name: i for i, name in enumerate(traj.names)}
    pick = [order.get(name, -1) for name in names]
    have = np.array([p >= 0 for p in pick])
    idx = np.array([max(p, 0) for p in pick], dtype=np.int64)
    found = slot_targets(traj.positions_m[idx], traj.quat_wxyz[idx], traj.linear_velocity_m_s[idx],
                         traj.angular_velocity_rad_s[idx], traj.fps, sample.contacts, names, slots, frames)
    for v in found.values():
        v[:, ~have] = np.nan
    return found, names, roles
