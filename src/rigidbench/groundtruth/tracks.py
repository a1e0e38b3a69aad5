"""Ground-truth point tracks from the frame-zero depth pass and the simulated rigid-body poses.

Paper, appendix "Ground-truth Point Trajectories": for a query pixel u = [u, v, 1] with Z-pass
depth d0, the body-fixed point is p^b = R_a0^T (R_c S d0 K^-1 u + t_c - t_a0); at frame t it is
carried to p_t = R_at p^b + t_at and projected u_t = pi(K S R_c^T (p_t - t_c)). Query pixels are
drawn without replacement (example seed) from a three-pixel erosion of each active actor's
frame-zero mask. A point is visible at frame t only if it lies in front of the camera, inside the
image and the actor's mask there, and its camera depth is at most 1.01 x the rendered depth.

Pixel coordinates put integer values at pixel centres (see ``camera_model``).

Two sampling rules exist (``TRACK_RULES``); they differ only in how query pixels are drawn:
``rigidbench`` (our renders until now) erodes by a disk of radius 3 and draws every actor's points
from one generator seeded with the example seed; ``published`` is the rule of the paper's released
evaluator, which computed the tracks of the published evaluation set at evaluation time: 3
iterations of a 3x3 cross (a diamond of radius 3), the raw mask when fewer than 20 pixels survive,
and a fresh generator seeded 42 for every actor. Projection and visibility are the same in both;
the principal point is whatever the bundle's K says (the published set's is (W/2, H/2)). Our renders
use the published rule too (``RENDER_TRACK_RULE``); bundles rendered before record no rule and
used ``rigidbench``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .camera_model import project, unproject

POINTS_PER_ACTOR = 20
EROSION_RADIUS_PX = 3
DEPTH_TOLERANCE = 1.01  # visible while camera depth <= 1.01 x rendered depth


@dataclass(frozen=True)
class TrackRule:
    """How query pixels are drawn from an actor's frame-0 mask.

    erosion: "disk" (one erosion by a disk of radius ``erosion_px``) or "cross" (``erosion_px``
    iterations of a 3x3 cross); fallback_to_mask: draw from the raw mask when fewer than the wanted
    points survive erosion; fixed_seed: None draws every actor from one generator seeded with the
    example seed, an int gives each actor a fresh generator with that seed."""

    name: str
    erosion: str
    erosion_px: int
    fallback_to_mask: bool
    fixed_seed: int | None

    def facts(self) -> dict:
        return {"rule": self.name, "erosion": self.erosion, "erosion_px": self.erosion_px,
                "fallback_to_mask": self.fallback_to_mask,
                "seed": "example seed" if self.fixed_seed is None else f"{self.fixed_seed} per actor"}


TRACK_RULES = {
    "rigidbench": TrackRule("rigidbench", "disk", EROSION_RADIUS_PX, False, None),
    "published": TrackRule("published", "cross", 3, True, 42),
}
#: the rule our renders use: the published one, so that one rule holds everywhere (docs/metrics.md gives
#: what the switch moved, measured with benchmarks/track_rule.py)
RENDER_TRACK_RULE = "published"


@dataclass
class Tracks:
    """P ground-truth point tracks over T frames.

    tracks_px (P,T,2) float32 (x, y) pixels; visibility (P,T) bool; actor_index (P,) int64 index
    into the bundle's actor list (the masks' N axis); query_pixels (P,2) int64 (x, y) pixel of each
    point at frame 0; points_body_m (P,3) float64 body-frame coordinates; points_per_actor (N,) int64
    how many points each actor got (0 for passive actors; < 20 when its eroded mask is smaller).
    """

    tracks_px: np.ndarray
    visibility: np.ndarray
    actor_index: np.ndarray
    query_pixels: np.ndarray
    points_body_m: np.ndarray
    points_per_actor: np.ndarray

    _KEYS = {"tracks": "tracks_px", "visibility": "visibility", "actor_index": "actor_index",
             "query_pixels": "query_pixels", "points_body_m": "points_body_m", "points_per_actor": "points_per_actor"}

    def __getitem__(self, key: str) -> np.ndarray:
        """Array by its tracks.npz key ("tracks", "visibility", "actor_index", ...)."""
        try:
            return getattr(self, self._KEYS[key])
        except KeyError:
            raise KeyError(f"no tracks array '{key}'; known: {', '.join(self._KEYS)}") from None

    def keys(self) -> tuple[str, ...]:
        return tuple(self._KEYS)

    @property
    def n_points(self) -> int:
        return int(self.tracks_px.shape[0])

    def save(self, path) -> None:
        np.savez_compressed(path, tracks=self.tracks_px.astype(np.float32), visibility=self.visibility.astype(bool),
                            actor_index=self.actor_index.astype(np.int64),
                            query_pixels=self.query_pixels.astype(np.int64),
                            points_body_m=self.points_body_m.astype(np.float64),
                            points_per_actor=self.points_per_actor.astype(np.int64))

    @classmethod
    def load(cls, path) -> "Tracks":
        with np.load(path, allow_pickle=False) as z:
            return cls(tracks_px=z["tracks"], visibility=z["visibility"], actor_index=z["actor_index"],
                       query_pixels=z["query_pixels"], points_body_m=z["points_body_m"],
                       points_per_actor=z["points_per_actor"])


def disk(radius_px: int) -> np.ndarray:
    """(2r+1, 2r+1) bool disk structuring element of the given radius in pixels."""
    r = int(radius_px)
    y, x = np.mgrid[-r:r + 1, -r:r + 1]
    return x * x + y * y <= r * r


def erode(mask: np.ndarray, radius_px: int = EROSION_RADIUS_PX) -> np.ndarray:
    """mask (H,W) bool -> (H,W) bool binary erosion by a disk; outside the image counts as background."""
    mask = np.asarray(mask, dtype=bool)
    r = int(radius_px)
    if r <= 0:
        return mask.copy()
    h, w = mask.shape
    padded = np.zeros((h + 2 * r, w + 2 * r), dtype=bool)
    padded[r:r + h, r:r + w] = mask
    out = np.ones_like(mask)
    for dy, dx in zip(*np.nonzero(disk(r))):
        out &= padded[dy:dy + h, dx:dx + w]
    return out


def erode_cross(mask: np.ndarray, iterations: int) -> np.ndarray:
    """mask (H,W) bool -> (H,W) bool eroded ``iterations`` times by a 3x3 cross (outside = background)."""
    from scipy import ndimage

    mask = np.asarray(mask, dtype=bool)
    if iterations <= 0:
        return mask.copy()
    return ndimage.binary_erosion(mask, structure=ndimage.generate_binary_structure(2, 1), iterations=iterations)


def sample_query_pixels(mask0: np.ndarray, count: int, rng: np.random.Generator,
                        radius_px: int = EROSION_RADIUS_PX, rule: TrackRule | None = None) -> np.ndarray:
    """mask0 (H,W) bool. Returns (min(count, M), 2) int64 (x, y) pixels drawn without replacement
    from the M pixels of the mask eroded by ``radius_px`` (or as ``rule`` says)."""
    if rule is not None and rule.erosion == "cross":
        pool = erode_cross(mask0, rule.erosion_px)
    else:
        pool = erode(mask0, rule.erosion_px if rule is not None else radius_px)
    if rule is not None and rule.fallback_to_mask and int(pool.sum()) < count:
        pool = np.asarray(mask0, dtype=bool)
    rows, cols = np.nonzero(pool)
    if len(rows) == 0:
        return np.zeros((0, 2), dtype=np.int64)
    pick = rng.choice(len(rows), size=min(count, len(rows)), replace=False)
    return np.stack([cols[pick], rows[pick]], axis=1).astype(np.int64)


def body_points(query_px: np.ndarray, depth0_m: np.ndarray, K: np.ndarray, R_c: np.ndarray, t_c: np.ndarray,
                R_a0: np.ndarray, t_a0: np.ndarray) -> np.ndarray:
    """query_px (P,2) int (x, y); depth0_m (H,W) Z pass at frame 0; actor pose R_a0 (3,3), t_a0 (3,) m.
    Returns body-frame points (P,3) m: p^b = R_a0^T (R_c S d0 K^-1 [u,v,1] + t_c - t_a0)."""
    d0 = depth0_m[query_px[:, 1], query_px[:, 0]].astype(np.float64)
    world = unproject(query_px.astype(np.float64), d0, K, R_c, t_c)
    return (world - t_a0) @ R_a0  # rows: R_a0^T (p - t_a0)


def carry(points_body_m: np.ndarray, R_a: np.ndarray, t_a: np.ndarray) -> np.ndarray:
    """points_body_m (P,3); actor poses R_a (T,3,3), t_a (T,3) m. Returns world points (P,T,3) m."""
    return np.einsum("tij,pj->pti", R_a, points_body_m) + t_a[None]


def visibility(uv: np.ndarray, depth_cam_m: np.ndarray, actor_mask: np.ndarray, depth_m: np.ndarray,
               tolerance: float = DEPTH_TOLERANCE) -> np.ndarray:
    """uv (P,T,2) pixels and depth_cam_m (P,T) axial depth (m) of points of one actor; actor_mask
    (T,H,W) bool; depth_m (T,H,W) rendered Z. Returns (P,T) bool: in front of the camera, inside the
    image and the mask (nearest pixel), and depth_cam_m <= tolerance x rendered depth."""
    P, T = depth_cam_m.shape
    H, W = depth_m.shape[1:]
    with np.errstate(invalid="ignore"):
        cols = np.rint(uv[..., 0])
        rows = np.rint(uv[..., 1])
        inside = (depth_cam_m > 0) & (cols >= 0) & (cols <= W - 1) & (rows >= 0) & (rows <= H - 1)
    ci = np.where(inside, cols, 0).astype(np.int64)
    ri = np.where(inside, rows, 0).astype(np.int64)
    t_idx = np.broadcast_to(np.arange(T), (P, T))
    in_mask = actor_mask[t_idx, ri, ci]
    rendered = depth_m[t_idx, ri, ci]
    return inside & in_mask & (depth_cam_m <= tolerance * rendered)


def ground_truth_tracks(masks: np.ndarray, depth_m: np.ndarray, K: np.ndarray, R_c: np.ndarray, t_c: np.ndarray,
                        rotations: np.ndarray, positions_m: np.ndarray, active: np.ndarray, seed: int,
                        points_per_actor: int = POINTS_PER_ACTOR,
                        erosion_px: int = EROSION_RADIUS_PX, rule: TrackRule | None = None) -> Tracks:
    """masks (T,N,H,W) bool; depth_m (T,H,W) Z pass; K (3,3); camera R_c (3,3), t_c (3,) (Blender
    camera-to-world); actor poses rotations (N,T,3,3), positions_m (N,T,3); active (N,) bool.
    Returns Tracks for the active actors, sampled with ``np.random.default_rng(seed)`` in actor order
    (or as ``rule`` says: the published rule ignores ``seed``)."""
    T, N = masks.shape[:2]
    rng = np.random.default_rng(seed)
    per_actor = np.zeros(N, dtype=np.int64)
    parts: list[tuple[np.ndarray, ...]] = []
    for a in range(N):
        if not active[a]:
            continue
        if rule is not None and rule.fixed_seed is not None:
            rng = np.random.default_rng(rule.fixed_seed)
        query = sample_query_pixels(masks[0, a], points_per_actor, rng, erosion_px, rule)
        per_actor[a] = len(query)
        if not len(query):
            continue
        pb = body_points(query, depth_m[0], K, R_c, t_c, rotations[a, 0], positions_m[a, 0])
        world = carry(pb, rotations[a], positions_m[a])
        uv, z = project(world, K, R_c, t_c)
        vis = visibility(uv, z, masks[:, a], depth_m)
        parts.append((uv.astype(np.float32), vis, np.full(len(query), a, dtype=np.int64), query, pb))
    if not parts:
        return Tracks(np.zeros((0, T, 2), np.float32), np.zeros((0, T), bool), np.zeros(0, np.int64),
                      np.zeros((0, 2), np.int64), np.zeros((0, 3)), per_actor)
    uv, vis, idx, query, pb = (np.concatenate(x) for x in zip(*parts))
    return Tracks(tracks_px=uv, visibility=vis, actor_index=idx, query_pixels=query, points_body_m=pb,
                  points_per_actor=per_actor)


__all__ = ["Tracks", "TrackRule", "TRACK_RULES", "RENDER_TRACK_RULE", "erode_cross", "POINTS_PER_ACTOR", "EROSION_RADIUS_PX", "DEPTH_TOLERANCE", "disk", "erode",
           "sample_query_pixels", "body_points", "carry", "visibility", "ground_truth_tracks"]
