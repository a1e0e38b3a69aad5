"""Cluster layout: n objects on a ring, relaxed by a short 2D pymunk simulation.

The ring radius R = (r + g/2) / sin(pi/n), with r the largest footprint radius and g the gap,
puts neighbouring centres 2r + g apart. A zero-gravity pymunk run of 80 steps at 1/60 s then
removes any remaining overlap: circular footprints collide (and so repel when they overlap)
while damped springs hold each object near its sampled ring position.
"""

from __future__ import annotations

import math

import numpy as np

RELAX_STEPS = 80
RELAX_DT_S = 1.0 / 60.0
COLLISION_CORRECTION = 0.3  # fraction of overlap removed per 1/60 s
_MM = 1000.0  # pymunk works in millimetres so its default tolerances are small in metres
_SPRING_STIFFNESS = 10.0  # per unit mass, 1/s^2; weak, so collisions win quickly
_SPRING_DAMPING = 2.0 * math.sqrt(_SPRING_STIFFNESS)  # critically damped


def ring_radius(max_radius_m: float, gap_m: float, n: int) -> float:
    """R = (r + g/2) / sin(pi/n)."""
    if n < 2:
        return 0.0
    return (max_radius_m + gap_m / 2) / math.sin(math.pi / n)


def ring_positions(n: int, radius_m: float, phase_rad: float) -> np.ndarray:
    """(n,2) centres evenly spaced on a circle of ``radius_m`` starting at ``phase_rad``."""
    ang = phase_rad + 2 * math.pi * np.arange(n) / n
    return np.stack([radius_m * np.cos(ang), radius_m * np.sin(ang)], axis=1)


def relax(positions_m: np.ndarray, radii_m: np.ndarray, steps: int = RELAX_STEPS,
          dt_s: float = RELAX_DT_S) -> np.ndarray:
    """Relax overlapping circular footprints. positions_m: (n,2), radii_m: (n,). Returns (n,2)."""
    import pymunk

    space = pymunk.Space()
    space.gravity = (0.0, 0.0)
    space.iterations = 30
    space.collision_slop = 0.001  # mm
    space.collision_bias = pow(1.0 - COLLISION_CORRECTION, 60.0)  # resolve overlap quickly
    bodies = []
    for (x, y), r in zip(np.asarray(positions_m, float) * _MM, np.asarray(radii_m, float) * _MM):
        body = pymunk.Body(1.0, pymunk.moment_for_circle(1.0, 0.0, r))
        body.position = (float(x), float(y))
        shape = pymunk.Circle(body, float(r))
        shape.elasticity = 0.0
        shape.friction = 0.0
        spring = pymunk.DampedSpring(space.static_body, body, (float(x), float(y)), (0.0, 0.0), 0.0,
                                     _SPRING_STIFFNESS, _SPRING_DAMPING)
        space.add(body, shape, spring)
        bodies.append(body)
    for _ in range(steps):
        space.step(dt_s)
    return np.array([[b.position.x, b.position.y] for b in bodies]) / _MM


def max_overlap_m(positions_m: np.ndarray, radii_m: np.ndarray) -> float:
    """Largest pairwise footprint overlap (sum of radii minus centre distance); <= 0 means none."""
    p = np.asarray(positions_m, float)
    r = np.asarray(radii_m, float)
    worst = -math.inf
    for i in range(len(p)):
        for j in range(i + 1, len(p)):
            worst = max(worst, r[i] + r[j] - float(np.linalg.norm(p[i] - p[j])))
    return worst
