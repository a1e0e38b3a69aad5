"""Quaternions and rotation matrices, in one place: (w, x, y, z) order as Blender stores them, numpy only.

Arrays are (..., 4) quaternions and (..., 3, 3) matrices; ``quat_about_z``/``quat_about_y`` give plain
tuples of floats (what a ``SceneSpec`` holds).
"""

from __future__ import annotations

import math

import numpy as np

IDENTITY = (1.0, 0.0, 0.0, 0.0)
_CONJUGATE = np.array([1.0, -1.0, -1.0, -1.0])


def quat_about_z(angle_rad: float) -> tuple[float, float, float, float]:
    """The rotation by ``angle_rad`` about +z."""
    return (math.cos(angle_rad / 2), 0.0, 0.0, math.sin(angle_rad / 2))


def quat_about_y(angle_rad: float) -> tuple[float, float, float, float]:
    """The rotation by ``angle_rad`` about +y."""
    return (math.cos(angle_rad / 2), 0.0, math.sin(angle_rad / 2), 0.0)


def quat_mul(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Hamilton product a * b of (..., 4) quaternions (broadcast)."""
    aw, ax, ay, az = np.moveaxis(np.asarray(a), -1, 0)
    bw, bx, by, bz = np.moveaxis(np.asarray(b), -1, 0)
    return np.stack([aw * bw - ax * bx - ay * by - az * bz, aw * bx + ax * bw + ay * bz - az * by,
                     aw * by - ax * bz + ay * bw + az * bx, aw * bz + ax * by - ay * bx + az * bw], axis=-1)


def quat_conjugate(q: np.ndarray) -> np.ndarray:
    """(w, -x, -y, -z): the inverse of a unit quaternion. (..., 4)."""
    return q * _CONJUGATE


def quat_canonical(q: np.ndarray) -> np.ndarray:
    """Sign-fixed to w >= 0 (q and -q are the same rotation). (..., 4)."""
    return np.where(q[..., :1] < 0, -q, q)


def quat_continuous(q: np.ndarray) -> np.ndarray:
    """Flip signs so consecutive quaternions lie in the same hemisphere. q: (N,T,4)."""
    q = q.copy()
    for t in range(1, q.shape[1]):
        flip = np.sum(q[:, t] * q[:, t - 1], axis=-1) < 0
        q[flip, t] *= -1
    return q


def quat_log_vec(q: np.ndarray) -> np.ndarray:
    """Rotation vector (axis * angle) of unit quaternions (...,4)."""
    q = quat_canonical(q)
    v = q[..., 1:]
    s = np.linalg.norm(v, axis=-1, keepdims=True)
    angle = 2.0 * np.arctan2(s, q[..., :1])
    scale = np.where(s > 1e-12, angle / np.maximum(s, 1e-300), 2.0)
    return v * scale


def quat_to_matrix(q_wxyz: np.ndarray, normalize: bool = True) -> np.ndarray:
    """q_wxyz: (...,4) unit quaternions -> (...,3,3) rotation matrices. ``normalize``: divide by the norm
    first (off: the quaternion is taken as it is, as for a spec's exact poses)."""
    q = np.asarray(q_wxyz, dtype=np.float64)
    if normalize:
        q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    w, x, y, z = np.moveaxis(q, -1, 0)
    return np.stack([
        np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
        np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
        np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
    ], -2)
