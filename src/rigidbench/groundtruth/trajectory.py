"""Trajectory and Contact: the simulated state of every actor, as stored in a bundle."""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..rotations import quat_conjugate, quat_continuous, quat_log_vec, quat_mul


@dataclass
class Trajectory:
    """Per-frame world state of N actors over T frames.

    positions_m (N,T,3) float64; quat_wxyz (N,T,4) float64, sign-continuous in time;
    linear_velocity_m_s (N,T,3) and angular_velocity_rad_s (N,T,3) are finite differences.
    """

    names: tuple[str, ...]
    roles: tuple[str, ...]
    fps: float
    positions_m: np.ndarray
    quat_wxyz: np.ndarray
    linear_velocity_m_s: np.ndarray = field(default=None)  # type: ignore[assignment]
    angular_velocity_rad_s: np.ndarray = field(default=None)  # type: ignore[assignment]

    def __post_init__(self) -> None:
        self.positions_m = np.asarray(self.positions_m, dtype=np.float64)
        self.quat_wxyz = quat_continuous(np.asarray(self.quat_wxyz, dtype=np.float64))
        n, t = self.positions_m.shape[:2]
        if self.positions_m.shape != (n, t, 3) or self.quat_wxyz.shape != (n, t, 4) or len(self.names) != n:
            raise ValueError(f"inconsistent trajectory shapes: positions {self.positions_m.shape}, "
                             f"quaternions {self.quat_wxyz.shape}, {len(self.names)} names")
        if self.linear_velocity_m_s is None:
            self.linear_velocity_m_s = finite_difference(self.positions_m, 1.0 / self.fps)
        if self.angular_velocity_rad_s is None:
            self.angular_velocity_rad_s = angular_velocity(self.quat_wxyz, 1.0 / self.fps)

    @property
    def times_s(self) -> np.ndarray:
        return np.arange(self.positions_m.shape[1]) / self.fps

    def index(self, name: str) -> int:
        try:
            return self.names.index(name)
        except ValueError:
            raise KeyError(f"no actor '{name}' in trajectory; actors: {', '.join(self.names)}") from None

    def save(self, path: str | Path) -> None:
        np.savez_compressed(path, names=np.array(self.names), roles=np.array(self.roles),
                            fps=np.float64(self.fps), positions_m=self.positions_m, quat_wxyz=self.quat_wxyz,
                            linear_velocity_m_s=self.linear_velocity_m_s,
                            angular_velocity_rad_s=self.angular_velocity_rad_s)

    @classmethod
    def load(cls, path: str | Path) -> "Trajectory":
        with np.load(path, allow_pickle=False) as z:
            return cls(names=tuple(str(s) for s in z["names"]), roles=tuple(str(s) for s in z["roles"]),
                       fps=float(z["fps"]), positions_m=z["positions_m"], quat_wxyz=z["quat_wxyz"],
                       linear_velocity_m_s=z["linear_velocity_m_s"],
                       angular_velocity_rad_s=z["angular_velocity_rad_s"])


def finite_difference(x: np.ndarray, dt: float) -> np.ndarray:
    """Central differences in time (axis 1), one-sided at the ends. x: (N,T,D) -> (N,T,D)."""
    if x.shape[1] < 2:
        return np.zeros_like(x)
    return np.gradient(x, dt, axis=1)


def angular_velocity(q: np.ndarray, dt: float) -> np.ndarray:
    """World-frame angular velocity (N,T,3) rad/s from quaternions (N,T,4) by finite differences.

    Interior frames use the rotation from t-1 to t+1 over 2 dt; the ends use one-sided steps.
    """
    n, t = q.shape[:2]
    out = np.zeros((n, t, 3))
    if t < 2:
        return out
    conj = quat_conjugate(q)
    if t > 2:
        out[:, 1:-1] = quat_log_vec(quat_mul(q[:, 2:], conj[:, :-2])) / (2 * dt)
    out[:, 0] = quat_log_vec(quat_mul(q[:, 1], conj[:, 0])) / dt
    out[:, -1] = quat_log_vec(quat_mul(q[:, -1], conj[:, -2])) / dt
    return out


@dataclass(frozen=True)
class Contact:
    """Bodies ``a`` and ``b`` touch at ``frame``: up to five world points (m) with unit normals
    pointing from ``b`` towards ``a``; ``distances_m`` are the point-to-surface gaps."""

    frame: int
    a: str
    b: str
    points_m: tuple[tuple[float, float, float], ...]
    normals: tuple[tuple[float, float, float], ...]
    distances_m: tuple[float, ...]

    def to_dict(self) -> dict:
        return {"frame": self.frame, "a": self.a, "b": self.b, "points_m": [list(p) for p in self.points_m],
                "normals": [list(n) for n in self.normals], "distances_m": list(self.distances_m)}

    @classmethod
    def from_dict(cls, d: dict) -> "Contact":
        return cls(frame=int(d["frame"]), a=str(d["a"]), b=str(d["b"]),
                   points_m=tuple(tuple(map(float, p)) for p in d["points_m"]),
                   normals=tuple(tuple(map(float, n)) for n in d["normals"]),
                   distances_m=tuple(map(float, d["distances_m"])))


def save_contacts(path: str | Path, contacts: list[Contact], frames: int, tolerance_m: float) -> None:
    doc = {"frames": frames, "tolerance_m": tolerance_m,
           "method": "mesh proximity: convex-hull vertices of one body within tolerance of the other's surface",
           "contacts": [c.to_dict() for c in contacts]}
    Path(path).write_text(json.dumps(doc, indent=1))


def load_contacts(path: str | Path) -> list[Contact]:
    doc = json.loads(Path(path).read_text())
    return [Contact.from_dict(c) for c in doc["contacts"]]
