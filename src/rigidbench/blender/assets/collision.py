"""Collision hulls from the render meshes (pure numpy + scipy).

Active objects collide in Bullet as convex hulls of their vertices. The hull of a procedural
model has up to a few thousand vertices; ``hull_mesh`` keeps at most ``MAX_HULL_VERTICES`` of
them: the six axis-extreme vertices first (so the hull's bounding box is the model's bounding
box exactly, which keeps resting heights and the spec's footprints unchanged), then farthest-point
sampling over the remaining hull vertices, which spreads the kept vertices evenly over the surface.
The kept vertices are a subset of the full hull's, so the decimated hull lies inside it: by under
1 mm for the balls and fruit, up to ~2 mm for the watermelon and rugby ball and ~4 mm along the
banana's curve (20 cm long). The result is a closed triangle mesh with outward faces in the model
frame, used for Bullet and for contact detection.
"""

from __future__ import annotations

import numpy as np

from .standin import Mesh

MAX_HULL_VERTICES = 200


def hull_vertex_indices(points: np.ndarray) -> np.ndarray:
    """points: (V,3) float m. Returns the indices (K,) int of the convex hull's vertices."""
    from scipy.spatial import ConvexHull, QhullError

    try:
        return np.sort(ConvexHull(points).vertices)
    except QhullError as exc:
        raise ValueError(f"cannot build a convex hull from {len(points)} vertices (flat or degenerate mesh): "
                         f"{exc}") from None


def decimate(points: np.ndarray, max_vertices: int = MAX_HULL_VERTICES) -> np.ndarray:
    """points: (K,3) float m hull vertices. Returns (min(K, max_vertices), 3): the axis-extreme points,
    then farthest-point samples."""
    pts = np.asarray(points, dtype=np.float64)
    if len(pts) <= max_vertices:
        return pts
    if max_vertices < 6:
        raise ValueError(f"max_vertices must be at least 6 (the axis-extreme points), got {max_vertices}")
    chosen = list(dict.fromkeys(int(i) for i in np.r_[pts.argmin(0), pts.argmax(0)]))
    dist = np.min(np.linalg.norm(pts[:, None, :] - pts[None, chosen, :], axis=2), axis=1)
    while len(chosen) < max_vertices:
        k = int(dist.argmax())
        chosen.append(k)
        dist = np.minimum(dist, np.linalg.norm(pts - pts[k], axis=1))
    return pts[np.sort(chosen)]


def hull_mesh(vertices: np.ndarray, max_vertices: int = MAX_HULL_VERTICES) -> Mesh:
    """vertices: (V,3) float m of a model. Returns its convex hull with at most ``max_vertices``
    vertices as a Mesh of outward-facing triangles."""
    from scipy.spatial import ConvexHull

    pts = np.asarray(vertices, dtype=np.float64)
    kept = decimate(pts[hull_vertex_indices(pts)], max_vertices)
    hull = ConvexHull(kept)
    used = np.unique(hull.simplices)
    remap = np.full(len(kept), -1, np.int64)
    remap[used] = np.arange(len(used))
    faces = remap[hull.simplices]
    v = kept[used]
    a, b, c = v[faces[:, 0]], v[faces[:, 1]], v[faces[:, 2]]
    inward = np.einsum("ij,ij->i", np.cross(b - a, c - a), hull.equations[:, :3]) < 0
    faces[inward] = faces[inward][:, ::-1]
    return Mesh(v, faces.astype(np.int64))


__all__ = ["MAX_HULL_VERTICES", "hull_vertex_indices", "decimate", "hull_mesh"]
