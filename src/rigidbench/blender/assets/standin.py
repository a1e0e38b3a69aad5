"""Stand-in meshes in pure numpy: primitives of an object's listed size, and the task ramp.

Every mesh is in the model frame: origin at the centre of its bounding box, +z up, +x along the
long axis, scaled so the bounding box equals the requested size exactly. Faces are triangles.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Mesh:
    vertices: np.ndarray  # (V,3) float64, metres
    faces: np.ndarray  # (F,3) int64 triangle indices

    def fitted(self, size_m) -> "Mesh":
        """Translate to the bounding-box centre and scale each axis to ``size_m``."""
        lo, hi = self.vertices.min(0), self.vertices.max(0)
        v = (self.vertices - (lo + hi) / 2) / np.where(hi - lo > 0, hi - lo, 1.0) * np.asarray(size_m, float)
        return Mesh(v, self.faces)


def _grid_faces(rows: int, cols: int, wrap: bool = True) -> list[tuple[int, int, int]]:
    faces = []
    for i in range(rows - 1):
        for j in range(cols if wrap else cols - 1):
            a, b = i * cols + j, i * cols + (j + 1) % cols
            c, d = a + cols, b + cols
            faces += [(a, c, b), (b, c, d)]
    return faces


def uv_sphere(segments: int = 32, rings: int = 16) -> Mesh:
    """Unit-diameter sphere with poles on the z axis."""
    verts = [(0.0, 0.0, -0.5)]
    for i in range(1, rings):
        theta = np.pi * i / rings
        for j in range(segments):
            phi = 2 * np.pi * j / segments
            verts.append((0.5 * np.sin(theta) * np.cos(phi), 0.5 * np.sin(theta) * np.sin(phi), -0.5 * np.cos(theta)))
    verts.append((0.0, 0.0, 0.5))
    faces = [(0, 1 + (j + 1) % segments, 1 + j) for j in range(segments)]
    faces += [(a + 1, b + 1, c + 1) for a, b, c in _grid_faces(rings - 1, segments)]
    top = len(verts) - 1
    base = 1 + (rings - 2) * segments
    faces += [(base + j, base + (j + 1) % segments, top) for j in range(segments)]
    return Mesh(np.array(verts), np.array(faces, dtype=np.int64))


def cylinder(segments: int = 32) -> Mesh:
    """Unit cylinder along z, capped."""
    ang = 2 * np.pi * np.arange(segments) / segments
    ring = np.stack([0.5 * np.cos(ang), 0.5 * np.sin(ang)], 1)
    verts = np.concatenate([np.c_[ring, np.full(segments, -0.5)], np.c_[ring, np.full(segments, 0.5)],
                            [[0, 0, -0.5], [0, 0, 0.5]]])
    faces = _grid_faces(2, segments)
    cb, ct = 2 * segments, 2 * segments + 1
    faces += [(cb, (j + 1) % segments, j) for j in range(segments)]
    faces += [(ct, segments + j, segments + (j + 1) % segments) for j in range(segments)]
    return Mesh(verts, np.array(faces, dtype=np.int64))


def box() -> Mesh:
    v = np.array([[x, y, z] for x in (-0.5, 0.5) for y in (-0.5, 0.5) for z in (-0.5, 0.5)], float)
    quads = [(0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4), (1, 5, 7, 3)]
    faces = [f for a, b, c, d in quads for f in ((a, b, c), (a, c, d))]
    return Mesh(v, np.array(faces, dtype=np.int64))


def banana(segments: int = 16, steps: int = 24) -> Mesh:
    """A tube of varying radius swept along a circular arc in the x-y plane (unit-ish size)."""
    arc = np.linspace(-0.9, 0.9, steps)  # radians of a radius-1 arc
    centres = np.stack([np.sin(arc), 1 - np.cos(arc), np.zeros(steps)], 1)
    tangents = np.stack([np.cos(arc), np.sin(arc), np.zeros(steps)], 1)
    normals = np.stack([-np.sin(arc), np.cos(arc), np.zeros(steps)], 1)
    binormal = np.array([0.0, 0.0, 1.0])
    radius = 0.09 * np.sqrt(np.clip(1 - (arc / 0.95) ** 2, 0.02, None))
    ang = 2 * np.pi * np.arange(segments) / segments
    verts = []
    for c, n, r in zip(centres, normals, radius):
        for a in ang:
            verts.append(c + r * (np.cos(a) * n + np.sin(a) * binormal))
    verts = np.array(verts)
    del tangents
    faces = _grid_faces(steps, segments)
    start, end = len(verts), len(verts) + 1
    verts = np.vstack([verts, centres[0], centres[-1]])
    last = (steps - 1) * segments
    faces += [(start, (j + 1) % segments, j) for j in range(segments)]
    faces += [(end, last + j, last + (j + 1) % segments) for j in range(segments)]
    return Mesh(verts, np.array(faces, dtype=np.int64))


_SHAPES = {"ellipsoid": uv_sphere, "cylinder": cylinder, "box": box, "banana": banana}


def object_mesh(shape: str, size_m) -> Mesh:
    """Stand-in mesh for an object of primitive ``shape`` fitted to ``size_m`` (x, y, z)."""
    try:
        make = _SHAPES[shape]
    except KeyError:
        raise ValueError(f"unknown stand-in shape '{shape}'; known: {', '.join(_SHAPES)}") from None
    return make().fitted(size_m)


def ramp_mesh(length_m: float, height_m: float, width_m: float) -> Mesh:
    """Five-face wedge: high end (back wall) at x=-L/2, slope descending to the foot at x=+L/2."""
    L, H, W = length_m / 2, height_m / 2, width_m / 2
    v = np.array([[-L, -W, -H], [L, -W, -H], [L, W, -H], [-L, W, -H],  # bottom
                  [-L, -W, H], [-L, W, H]], float)  # top edge of the back wall
    faces = [(0, 2, 1), (0, 3, 2),  # bottom
             (0, 4, 5), (0, 5, 3),  # back wall
             (4, 1, 2), (4, 2, 5),  # slope
             (0, 1, 4), (3, 5, 2)]  # sides
    return Mesh(v, np.array(faces, dtype=np.int64))
