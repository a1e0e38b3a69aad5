"""Footprint fit: the task rotations at which a task footprint fits inside a support rectangle.

For a task footprint (L_T, W_T) (axis-aligned in the task frame) and a support (L_S, W_S), a
rotation psi (relative to the support's long axis) fits when

    L_T |cos psi| + W_T |sin psi| <= L_S   and   L_T |sin psi| + W_T |cos psi| <= W_S.

We solve both inequalities in closed form over the first quadrant, tile the valid set by the
rectangle's symmetries (psi -> pi - psi, pi + psi, 2 pi - psi), rotate it into the world by the
support's long-axis angle and sample an angle in proportion to interval length.
"""

from __future__ import annotations

import math

import numpy as np

Interval = tuple[float, float]
HALF_PI = math.pi / 2
TWO_PI = 2 * math.pi
_EPS = 1e-12


def _first_quadrant_constraint(a: float, b: float, c: float) -> list[Interval]:
    """Angles psi in [0, pi/2] with a cos(psi) + b sin(psi) <= c (a, b >= 0)."""
    rho = math.hypot(a, b)
    if c >= rho:
        return [(0.0, HALF_PI)]
    if c < 0 or rho == 0:
        return [] if c < 0 else [(0.0, HALF_PI)]
    phi = math.atan2(b, a)  # a cos + b sin = rho cos(psi - phi)
    alpha = math.acos(c / rho)  # valid where |psi - phi| >= alpha
    out = []
    if phi - alpha >= -_EPS:  # tolerate rounding when the footprint fits exactly at psi = 0
        out.append((0.0, max(phi - alpha, 0.0)))
    if phi + alpha <= HALF_PI + _EPS:
        out.append((min(phi + alpha, HALF_PI), HALF_PI))
    return out


def _intersect(xs: list[Interval], ys: list[Interval]) -> list[Interval]:
    out = []
    for a0, a1 in xs:
        for b0, b1 in ys:
            lo, hi = max(a0, b0), min(a1, b1)
            if lo <= hi:
                out.append((lo, hi))
    return sorted(out)


def fit_intervals_first_quadrant(task_lw: tuple[float, float], support_lw: tuple[float, float]) -> list[Interval]:
    """Valid rotations in [0, pi/2] (radians) for footprint (L_T, W_T) on support (L_S, W_S)."""
    lt, wt = task_lw
    ls, ws = support_lw
    first = _first_quadrant_constraint(lt, wt, ls)
    second = _first_quadrant_constraint(wt, lt, ws)
    return _intersect(first, second)


def tile_symmetries(quadrant: list[Interval]) -> list[Interval]:
    """Extend first-quadrant intervals to [0, 2 pi) using the rectangle's symmetries."""
    out = []
    for lo, hi in quadrant:
        out += [(lo, hi), (math.pi - hi, math.pi - lo), (math.pi + lo, math.pi + hi), (TWO_PI - hi, TWO_PI - lo)]
    return sorted(out)


def fit_intervals(task_lw: tuple[float, float], support_lw: tuple[float, float],
                  support_angle_rad: float = 0.0) -> list[Interval]:
    """Valid world yaw intervals (radians, possibly beyond 2 pi) for the task on a rotated support."""
    return [(lo + support_angle_rad, hi + support_angle_rad)
            for lo, hi in tile_symmetries(fit_intervals_first_quadrant(task_lw, support_lw))]


def fits(task_lw: tuple[float, float], support_lw: tuple[float, float], psi_rad: float, tol: float = 1e-9) -> bool:
    """Whether rotation psi (relative to the support's long axis) satisfies both inequalities."""
    lt, wt = task_lw
    ls, ws = support_lw
    c, s = abs(math.cos(psi_rad)), abs(math.sin(psi_rad))
    return lt * c + wt * s <= ls + tol and lt * s + wt * c <= ws + tol


def sample_rotation(rng: np.random.Generator, intervals: list[Interval]) -> float:
    """Sample an angle uniformly over the union of intervals (radians, wrapped to [0, 2 pi)).

    Intervals of zero length (a footprint that fits exactly) are chosen uniformly when no
    interval has positive length. Raises ValueError when the list is empty.
    """
    if not intervals:
        raise ValueError("no rotation fits: the task footprint is larger than the support")
    lengths = np.array([hi - lo for lo, hi in intervals])
    total = float(lengths.sum())
    if total <= 0.0:
        lo, _ = intervals[int(rng.integers(len(intervals)))]
        return _wrap(lo)
    u = float(rng.random()) * total
    idx = int(np.searchsorted(np.cumsum(lengths), u, side="right"))
    idx = min(idx, len(intervals) - 1)
    lo, hi = intervals[idx]
    offset = u - (float(np.cumsum(lengths)[idx - 1]) if idx else 0.0)
    return _wrap(min(lo + offset, hi))


def _wrap(angle_rad: float) -> float:
    wrapped = angle_rad % TWO_PI
    return 0.0 if wrapped >= TWO_PI else wrapped
