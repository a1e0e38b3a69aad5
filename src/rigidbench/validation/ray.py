"""ATE-3D along versus across the viewing ray (paper, appendix "Controlled Metric Perturbations").

Every active actor is displaced by a 3D offset of ``offset_m`` at every frame, either along the
camera ray through its position (p -> p + d r, r = (p - c) / |p - c|) or perpendicular to it
(p -> p + d e, e the camera's image-right axis made orthogonal to r). The generated perception is
derived from the reference world state by treating each actor as a rigid image layer:

- the actor's mask, depth and tracks move in the image by the projected offset of its position,
  du = pi(p + d v) - pi(p) (tracks by the exact sub-pixel du, mask and depth by round(du));
  along the ray du = 0, so masks and tracks are unchanged;
- the actor's depth grows by the change of its position's camera depth, dZ = Z(p + d v) - Z(p);
- pixels the actor uncovers take the depth of the nearest background pixel of the same frame;
  actors are painted far to near, so a nearer actor covers a farther one;
- a track point stays visible where it was, unless it leaves the image.

Disparity is 1/depth (the gt backend's rule), and ATE-3D and 2D ATE are the real metric functions
with the evaluator's arguments, so the response includes the clip-level disparity alignment.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..evaluation.scoring import tracked_points_world
from ..metrics import depth as depth_metrics, masks as mask_metrics, tracks as track_metrics
from ..metrics.common import project
from ..perception.gt import disparity_from_depth, reference_state

DIRECTIONS = ("along", "across")


@dataclass(frozen=True)
class RayScene:
    """Reference arrays of one clip with A active actors, P track points and T frames.

    masks (T,A,H,W) bool; depth_m (T,H,W) float32 m along the optical axis; tracks (P,T,2) px;
    visibility (P,T) bool; actor_index (P,) int into A; positions_m (A,T,3) actor positions;
    points_m (P,T,3) world positions of the tracked points; K (3,3); camera_to_world (4,4) Blender.
    """

    masks: np.ndarray
    depth_m: np.ndarray
    tracks: np.ndarray
    visibility: np.ndarray
    actor_index: np.ndarray
    positions_m: np.ndarray
    points_m: np.ndarray
    K: np.ndarray
    camera_to_world: np.ndarray
    name: str = ""


def scene_from_sample(sample) -> RayScene:
    """The reference bundle's gt world state (perception.gt.reference_state) as a RayScene."""
    state = reference_state(sample)
    n = state.masks.shape[0]
    return RayScene(masks=state.masks.astype(bool), depth_m=np.asarray(state.depth_m, np.float32),
                    tracks=np.asarray(state.tracks, np.float64), visibility=state.visibility.astype(bool),
                    actor_index=np.asarray(sample.track_active_index, np.int64),
                    positions_m=np.asarray(sample.trajectory.positions_m[sample.active_indices, :n], np.float64),
                    points_m=tracked_points_world(sample, n), K=sample.K, camera_to_world=sample.camera_to_world,
                    name=sample.sample_id)


def offset_directions(positions_m: np.ndarray, camera_to_world: np.ndarray, direction: str) -> np.ndarray:
    """positions_m: (A,T,3) m; camera_to_world (4,4). Returns (A,T,3) unit vectors along the camera
    ray through each position, or perpendicular to it along the camera's image-right axis."""
    if direction not in DIRECTIONS:
        raise ValueError(f"direction must be one of {DIRECTIONS}, got '{direction}'")
    centre = np.asarray(camera_to_world, np.float64)[:3, 3]
    ray = np.asarray(positions_m, np.float64) - centre
    ray /= np.linalg.norm(ray, axis=-1, keepdims=True)
    if direction == "along":
        return ray
    right = np.asarray(camera_to_world, np.float64)[:3, 0]
    across = right - np.sum(right * ray, axis=-1, keepdims=True) * ray
    return across / np.linalg.norm(across, axis=-1, keepdims=True)


def projected_offsets(positions_m: np.ndarray, directions: np.ndarray, offset_m: float, K: np.ndarray,
                      camera_to_world: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """positions_m, directions: (A,T,3). Returns the image shift (A,T,2) px and camera-depth change
    (A,T) m of each position moved by offset_m along its direction."""
    c2w = np.asarray(camera_to_world, np.float64)
    flat = np.asarray(positions_m, np.float64).reshape(-1, 3)
    moved = flat + offset_m * np.asarray(directions, np.float64).reshape(-1, 3)
    xy0, z0 = project(flat, K, c2w[:3, :3], c2w[:3, 3])
    xy1, z1 = project(moved, K, c2w[:3, :3], c2w[:3, 3])
    shape = positions_m.shape[:2]
    return (xy1 - xy0).reshape(*shape, 2), (z1 - z0).reshape(shape)


def shift_image(image: np.ndarray, dx: int, dy: int, fill) -> np.ndarray:
    """image: (H,W,...) array. Returns it translated by (dx, dy) whole pixels, `fill` where nothing lands."""
    h, w = image.shape[:2]
    out = np.full_like(image, fill)
    if abs(dx) >= w or abs(dy) >= h:
        return out
    out[max(dy, 0):h + min(dy, 0), max(dx, 0):w + min(dx, 0)] = \
        image[max(-dy, 0):h - max(dy, 0), max(-dx, 0):w - max(dx, 0)]
    return out


def fill_covered(depth_m: np.ndarray, covered: np.ndarray) -> np.ndarray:
    """depth_m: (H,W); covered: (H,W) bool. Returns (H,W) depth with covered pixels set to the
    nearest uncovered pixel's depth (unchanged if every pixel is covered)."""
    from scipy import ndimage

    if not covered.any() or covered.all():
        return depth_m.copy()
    _, (rows, cols) = ndimage.distance_transform_edt(covered, return_indices=True)
    return depth_m[rows, cols]


def perturb_scene(scene: RayScene, offset_m: float, direction: str
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Move every actor by offset_m (m) along or across its viewing ray (see the module docstring).
    Returns masks (T,A,H,W) bool, depth (T,H,W) float32 m, tracks (P,T,2) px and visibility (P,T) bool."""
    t_len, n_actors, h, w = scene.masks.shape
    dirs = offset_directions(scene.positions_m, scene.camera_to_world, direction)
    du, dz = projected_offsets(scene.positions_m, dirs, offset_m, scene.K, scene.camera_to_world)
    shift = np.rint(du).astype(np.int64)
    masks = np.zeros_like(scene.masks)
    depth = np.empty_like(scene.depth_m)
    for t in range(t_len):
        layer = fill_covered(scene.depth_m[t], scene.masks[t].any(axis=0))
        new_depth_cam = _camera_depth(scene.positions_m[:, t], scene.camera_to_world) + dz[:, t]
        for a in np.argsort(-new_depth_cam, kind="stable"):  # far to near: nearer actors cover farther ones
            dx, dy = int(shift[a, t, 0]), int(shift[a, t, 1])
            moved_mask = shift_image(scene.masks[t, a], dx, dy, False)
            moved_depth = shift_image(scene.depth_m[t] + np.float32(dz[a, t]), dx, dy, np.inf)
            layer[moved_mask] = moved_depth[moved_mask]
            masks[t][:, moved_mask] = False
            masks[t, a] = moved_mask
        depth[t] = layer
    tracks = np.asarray(scene.tracks, np.float64) + du[scene.actor_index]
    inside = ((tracks[..., 0] >= -0.5) & (tracks[..., 0] <= w - 0.5)
              & (tracks[..., 1] >= -0.5) & (tracks[..., 1] <= h - 0.5))
    return masks, depth, tracks, scene.visibility & inside


def _camera_depth(points_m: np.ndarray, camera_to_world: np.ndarray) -> np.ndarray:
    """points_m: (M,3) world. Returns (M,) depth along the camera's optical axis (its -z in Blender)."""
    c2w = np.asarray(camera_to_world, np.float64)
    return -(np.asarray(points_m, np.float64) - c2w[:3, 3]) @ c2w[:3, 2]


def ray_metrics(scene: RayScene, masks: np.ndarray, depth_m: np.ndarray, tracks: np.ndarray,
                visibility: np.ndarray) -> dict[str, float]:
    """Generated arrays as returned by perturb_scene. Returns {"ate3d", "ate", "iou"} scored against
    the scene with the evaluator's arguments (disparity = 1/depth, ref_points_m = tracked points)."""
    c2w = np.asarray(scene.camera_to_world, np.float64)
    ate3d = depth_metrics.ate3d(tracks, scene.visibility, visibility, scene.actor_index,
                                disparity_from_depth(depth_m), scene.depth_m, scene.K, c2w[:3, :3], c2w[:3, 3],
                                scene.positions_m, ref_points_m=scene.points_m)
    ate = track_metrics.ate(scene.tracks, tracks, scene.visibility, visibility, scene.masks.shape[2])
    return {"ate3d": ate3d.value, "ate": ate.value, "iou": mask_metrics.iou(scene.masks, masks).value}


def ray_sweep(scenes: list[RayScene], offsets_m: np.ndarray) -> dict[str, np.ndarray]:
    """Returns {"<direction>/<metric>": (len(offsets_m), len(scenes)) float} for both directions and
    the metrics of ray_metrics."""
    out = {f"{d}/{m}": np.full((len(offsets_m), len(scenes)), np.nan)
           for d in DIRECTIONS for m in ("ate3d", "ate", "iou")}
    for direction in DIRECTIONS:
        for i, offset in enumerate(offsets_m):
            for j, scene in enumerate(scenes):
                values = ray_metrics(scene, *perturb_scene(scene, float(offset), direction))
                for metric, value in values.items():
                    out[f"{direction}/{metric}"][i, j] = value
    return out


def slope_through_origin(x: np.ndarray, y: np.ndarray) -> float:
    """x, y: (K,) float. Returns the least-squares slope of y = b x over finite pairs (NaN if none)."""
    x = np.asarray(x, np.float64)
    y = np.asarray(y, np.float64)
    keep = np.isfinite(x) & np.isfinite(y)
    denominator = float(x[keep] @ x[keep])
    return float(x[keep] @ y[keep]) / denominator if denominator > 0 else float("nan")
