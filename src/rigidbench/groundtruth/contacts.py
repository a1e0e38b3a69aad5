"""Per-frame contacts between simulated bodies, detected from mesh proximity (pure numpy).

Blender exposes no list of Bullet contact points, so contacts are recovered from the simulated
poses and the same convex hulls that Bullet collides:

1. Every body's collision mesh is reduced once to its convex hull in the model frame
   (``scipy.spatial.ConvexHull``): the hull vertices and the outward face planes ``n . x <= d``,
   coplanar facets merged. Active bodies collide as convex hulls in Bullet (their collision mesh,
   ``blender.physics.body_mesh``, is already the decimated hull of the rendered model, so this is
   the very polytope Bullet uses); passive geometry (support box, floor box, ramp wedge) is convex
   already, so the hull *is* its surface.
2. Broad phase, per pair over all frames at once: a bounding-sphere test (spheres about the
   model origins enclosing the hulls, plus the tolerance) rejects distant frames.
3. Candidates, in both directions: the hull vertices of body A are carried into B's model frame,
   those outside B's bounding box grown by the tolerance are dropped, and the signed distance of
   the rest to B's hull is taken as ``max_k (n_k . p - d_k)`` over B's face planes (exact inside
   the hull, a lower bound on the Euclidean distance outside it). A vertex within
   ``tolerance_m`` is a candidate; B's planes within the tolerance of its nearest plane are the
   faces it may be touching.
4. Normal: one per pair and frame, as in a contact manifold. Among the candidate faces of both
   bodies, the face normal along which the two hulls are most separated (a separating-axis test
   restricted to those faces) is the contact normal, oriented from ``b`` towards ``a``; if even
   that separation exceeds the tolerance, the bodies are apart. Choosing the normal per pair
   rather than per vertex keeps it right where a vertex sits on an edge of the other body
   (e.g. stacked cubes). Beside edges and corners a contact may still be reported for bodies up
   to about sqrt(2)-sqrt(3) times the tolerance apart, since edge-edge axes are not tested.
5. Points: each candidate's gap is its distance beyond the other body's extent along the normal
   (negative when penetrating); candidates with gap ``<= tolerance_m`` are kept, the point being
   midway across the gap. Up to ``max_points`` are reported per pair and frame, spread out by
   farthest-point selection starting from the deepest one.

Only vertex-face proximity yields candidates, so a pure edge-edge touch with no vertex inside
the tolerance band is missed; the tolerance (3 mm by default) exceeds Bullet's summed collision
margins (1.1 mm), which keeps resting and rolling contacts detected in every frame.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np

from ..rotations import quat_to_matrix  # re-exported: tests and callers import it from here
from .trajectory import Contact

PLANE_MERGE_DECIMALS = 6  # normals/offsets equal to this many decimals are one plane


@dataclass(frozen=True)
class Hull:
    """Convex hull in a body's model frame.

    vertices (V,3) float64 m; normals (P,3) unit outward plane normals; offsets (P,) m so that the
    hull is ``normals @ x <= offsets``; lower_m, upper_m (3,) its axis-aligned bounds; radius_m
    encloses every vertex about the model origin.
    """

    vertices: np.ndarray
    normals: np.ndarray
    offsets: np.ndarray
    lower_m: np.ndarray
    upper_m: np.ndarray
    radius_m: float


def convex_hull(vertices: np.ndarray) -> Hull:
    """vertices: (V,3) float m in the model frame -> Hull with merged coplanar face planes."""
    from scipy.spatial import ConvexHull, QhullError

    pts = np.asarray(vertices, dtype=np.float64)
    try:
        hull = ConvexHull(pts)
    except QhullError as exc:
        raise ValueError(f"cannot build a convex hull from {len(pts)} vertices (flat or degenerate mesh); "
                         f"check the collision mesh: {exc}") from None
    eq = hull.equations  # (F,4): n . x + c <= 0 inside
    normals, offsets = eq[:, :3], -eq[:, 3]
    scale = max(float(np.abs(pts).max()), 1e-9)
    keys = np.round(np.c_[normals, offsets / scale], PLANE_MERGE_DECIMALS)
    _, first = np.unique(keys, axis=0, return_index=True)
    first = np.sort(first)
    hv = pts[hull.vertices]
    return Hull(vertices=hv, normals=normals[first], offsets=offsets[first], lower_m=hv.min(0), upper_m=hv.max(0),
                radius_m=float(np.linalg.norm(hv, axis=1).max()))


def farthest_points(points: np.ndarray, k: int, start: int = 0) -> np.ndarray:
    """points: (M,3). Returns (min(k,M),) int indices chosen greedily farthest from those chosen."""
    m = len(points)
    if m <= k:
        return np.arange(m)
    chosen = [start]
    dist = np.linalg.norm(points - points[start], axis=1)
    for _ in range(k - 1):
        nxt = int(np.argmax(dist))
        chosen.append(nxt)
        dist = np.minimum(dist, np.linalg.norm(points - points[nxt], axis=1))
    return np.array(chosen)


def _vertices_near(hull_a: Hull, rot_a: np.ndarray, pos_a: np.ndarray, hull_b: Hull, rot_b: np.ndarray,
                   pos_b: np.ndarray, tolerance_m: float) -> tuple[np.ndarray, ...]:
    """Vertices of A within tolerance of B's hull over T frames (rot (T,3,3), pos (T,3) each).

    Returns A's world vertices (T,V,3), A's vertices in B's model frame (T,V,3), and for each of
    the M vertices found: frame (M,), vertex index (M,) and (M,P) bool marking B's planes within
    the tolerance of the nearest one (the faces the vertex may be touching).
    """
    world = hull_a.vertices @ np.swapaxes(rot_a, 1, 2) + pos_a[:, None]  # (T,V,3)
    local = (world - pos_b[:, None]) @ rot_b  # into B's model frame
    box = np.all((local >= hull_b.lower_m - tolerance_m) & (local <= hull_b.upper_m + tolerance_m), axis=2)
    frame, vert = np.nonzero(box)  # a vertex within tolerance of the hull lies within its bounds + tolerance
    signed = local[frame, vert] @ hull_b.normals.T - hull_b.offsets  # (M,P)
    nearest = signed.max(axis=1, initial=-np.inf)
    keep = nearest <= tolerance_m
    faces = signed[keep] >= nearest[keep, None] - tolerance_m
    return world, local, frame[keep], vert[keep], faces


def _separation(local_other: np.ndarray, hull: Hull, planes: np.ndarray) -> np.ndarray:
    """Gap (K,) m between ``hull`` and points local_other (V,3) (in its frame) along its face normals ``planes``."""
    return (local_other @ hull.normals[planes].T).min(0) - hull.offsets[planes]


def pair_contacts(hull_a: Hull, rot_a: np.ndarray, pos_a: np.ndarray, hull_b: Hull, rot_b: np.ndarray,
                  pos_b: np.ndarray, tolerance_m: float, max_points: int
                  ) -> dict[int, tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """One pair over T frames (rot (T,3,3), pos (T,3) m each). Returns {frame: (points (K,3) m,
    unit normals (K,3) from b towards a, gaps along the normal (K,) m)} with K <= max_points,
    for touching frames only."""
    wa, la, fa, va, pa = _vertices_near(hull_a, rot_a, pos_a, hull_b, rot_b, pos_b, tolerance_m)
    wb, lb, fb, vb, pb = _vertices_near(hull_b, rot_b, pos_b, hull_a, rot_a, pos_a, tolerance_m)
    out = {}
    for f in np.union1d(fa, fb):
        sa, sb = fa == f, fb == f
        planes_b, planes_a = np.nonzero(pa[sa].any(0))[0], np.nonzero(pb[sb].any(0))[0]
        # Contact normal: of the face planes nearest to the candidate vertices, the one along which
        # the hulls are most separated (a separating-axis test over those faces).
        seps = np.concatenate([_separation(la[f], hull_b, planes_b), _separation(lb[f], hull_a, planes_a)])
        axes = np.concatenate([hull_b.normals[planes_b] @ rot_b[f].T, -(hull_a.normals[planes_a] @ rot_a[f].T)])
        best = int(np.argmax(seps))
        if seps[best] > tolerance_m:
            continue
        n = axes[best]
        proj_a, proj_b = wa[f] @ n, wb[f] @ n
        gap_a = proj_a[va[sa]] - proj_b.max()  # A's candidates above B's extent along n
        gap_b = proj_a.min() - proj_b[vb[sb]]  # B's candidates below A's extent along n
        points = np.concatenate([wa[f, va[sa]] - 0.5 * gap_a[:, None] * n, wb[f, vb[sb]] + 0.5 * gap_b[:, None] * n])
        gaps = np.concatenate([gap_a, gap_b])
        keep = np.nonzero(gaps <= tolerance_m)[0]
        if not len(keep):
            continue
        points, gaps = points[keep], gaps[keep]
        pick = farthest_points(points, max_points, start=int(np.argmin(gaps)))
        out[int(f)] = (points[pick], np.repeat(n[None], len(pick), axis=0), gaps[pick])
    return out


def pair_contact(hull_a: Hull, rot_a: np.ndarray, pos_a: np.ndarray, hull_b: Hull, rot_b: np.ndarray,
                 pos_b: np.ndarray, tolerance_m: float, max_points: int
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """One pair at one pose (rot (3,3), pos (3,) m each): (points (K,3), normals (K,3) b->a,
    gaps (K,) m) with K <= max_points, or None when apart."""
    hit = pair_contacts(hull_a, np.asarray(rot_a)[None], np.asarray(pos_a, float)[None], hull_b,
                        np.asarray(rot_b)[None], np.asarray(pos_b, float)[None], tolerance_m, max_points)
    return hit.get(0)


def contact_pairs(roles: Sequence[str]) -> list[tuple[int, int]]:
    """Pairs (i, j) to test: active-active (i < j) and active-passive (i active); passive pairs
    never move relative to each other and are skipped."""
    active = [i for i, r in enumerate(roles) if r == "active"]
    passive = [i for i, r in enumerate(roles) if r != "active"]
    pairs = [(i, j) for k, i in enumerate(active) for j in active[k + 1:]]
    pairs += [(i, j) for i in active for j in passive]
    return pairs


def detect_contacts(names: Sequence[str], hulls: Sequence[Hull], positions_m: np.ndarray, quat_wxyz: np.ndarray,
                    pairs: Sequence[tuple[int, int]], tolerance_m: float, max_points: int) -> list[Contact]:
    """positions_m (N,T,3), quat_wxyz (N,T,4) world poses of the N bodies whose model-frame hulls
    are ``hulls``. Returns Contacts ordered by frame, then by pair order."""
    positions_m = np.asarray(positions_m, dtype=np.float64)
    rots = quat_to_matrix(quat_wxyz)  # (N,T,3,3)
    n = positions_m.shape[0]
    if len(names) != n or len(hulls) != n:
        raise ValueError(f"{len(names)} names and {len(hulls)} hulls for {n} bodies")
    found: list[tuple[int, int, Contact]] = []
    for k, (i, j) in enumerate(pairs):
        reach = hulls[i].radius_m + hulls[j].radius_m + tolerance_m
        frames = np.nonzero(np.linalg.norm(positions_m[i] - positions_m[j], axis=1) <= reach)[0]  # broad phase
        if not len(frames):
            continue
        hits = pair_contacts(hulls[i], rots[i, frames], positions_m[i, frames], hulls[j], rots[j, frames],
                             positions_m[j, frames], tolerance_m, max_points)
        for local_frame, (pts, nrm, dist) in hits.items():
            f = int(frames[local_frame])
            found.append((f, k, Contact(frame=f, a=names[i], b=names[j],
                                        points_m=tuple(tuple(float(v) for v in p) for p in pts),
                                        normals=tuple(tuple(float(v) for v in q) for q in nrm),
                                        distances_m=tuple(float(d) for d in dist))))
    found.sort(key=lambda item: item[:2])
    return [c for _, _, c in found]


__all__ = ["Hull", "convex_hull", "quat_to_matrix", "farthest_points", "pair_contact", "pair_contacts", "contact_pairs",
           "detect_contacts"]
