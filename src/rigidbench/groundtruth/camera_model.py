"""Pinhole camera model shared by the renderer and the ground truth (pure numpy).

Conventions
- Pixel coordinates (x, y) = (u, v) put integer values at pixel centres (OpenCV): pixel ``[row, col]``
  of an image is centred on ``u = col, v = row`` and the image spans ``[-0.5, W - 0.5]``. Hence
  ``cx = W/2 - 0.5`` and ``cy = H/2 - 0.5`` for Blender's centred principal point.
- Blender camera frame: +x right, +y up, the camera looks along -z. The computer-vision (CV)
  camera frame: +x right, +y down, looking along +z. ``S = diag(1, -1, -1)`` maps one to the other.
- ``R_c`` (3,3) and ``t_c`` (3,) are the Blender camera-to-world rotation and position (m), i.e.
  ``matrix_world`` of the camera object. World-to-camera in the CV convention is
  ``x_cv = S R_c^T (p - t_c)``.
- Depth is Cycles' Z pass: distance along the optical axis (the CV z), not along the ray.
"""

from __future__ import annotations

import math

import numpy as np

S = np.diag([1.0, -1.0, -1.0])  # CV camera coordinates <-> Blender camera coordinates


def intrinsics(lens_mm: float, sensor_width_mm: float, width_px: int, height_px: int) -> np.ndarray:
    """K (3,3) float64 for a Blender camera with sensor fit HORIZONTAL and square pixels."""
    f_px = lens_mm / sensor_width_mm * width_px
    return np.array([[f_px, 0.0, width_px / 2.0 - 0.5],
                     [0.0, f_px, height_px / 2.0 - 0.5],
                     [0.0, 0.0, 1.0]])


def camera_position(target_m, azimuth_deg: float, elevation_deg: float, distance_m: float) -> np.ndarray:
    """(3,) m: the point ``distance_m`` from ``target_m`` at world azimuth (about +z, from +x) and elevation."""
    az, el = math.radians(azimuth_deg), math.radians(elevation_deg)
    offset = np.array([math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), math.sin(el)])
    return np.asarray(target_m, dtype=np.float64) + distance_m * offset


def look_at(position_m, target_m) -> np.ndarray:
    """R_c (3,3): Blender camera-to-world rotation looking from ``position_m`` at ``target_m``, +z world up."""
    forward = np.asarray(target_m, float) - np.asarray(position_m, float)
    forward /= np.linalg.norm(forward)
    right = np.cross(forward, [0.0, 0.0, 1.0])
    if np.linalg.norm(right) < 1e-9:  # looking straight up or down: any horizontal right vector
        right = np.array([1.0, 0.0, 0.0])
    right /= np.linalg.norm(right)
    up = np.cross(right, forward)
    return np.stack([right, up, -forward], axis=1)


def camera_pose(target_m, azimuth_deg: float, elevation_deg: float, distance_m: float) -> tuple[np.ndarray, np.ndarray]:
    """(R_c (3,3), t_c (3,) m): Blender camera-to-world pose of an orbit camera looking at the target."""
    t_c = camera_position(target_m, azimuth_deg, elevation_deg, distance_m)
    return look_at(t_c, target_m), t_c


def pose_matrix(R_c: np.ndarray, t_c: np.ndarray) -> np.ndarray:
    """(4,4) homogeneous camera-to-world matrix in the Blender convention."""
    m = np.eye(4)
    m[:3, :3], m[:3, 3] = R_c, t_c
    return m


def world_to_camera_cv(R_c: np.ndarray, t_c: np.ndarray) -> np.ndarray:
    """(4,4) world-to-camera matrix in the CV convention: x_cv = R p + t with R = S R_c^T, t = -S R_c^T t_c."""
    R = S @ np.asarray(R_c).T
    m = np.eye(4)
    m[:3, :3], m[:3, 3] = R, -R @ np.asarray(t_c)
    return m


def to_camera_cv(points_m: np.ndarray, R_c: np.ndarray, t_c: np.ndarray) -> np.ndarray:
    """points_m (...,3) world m -> (...,3) CV camera coordinates m (z = axial depth, > 0 in front)."""
    return (np.asarray(points_m, float) - t_c) @ np.asarray(R_c) @ S  # == (S R_c^T (p - t_c)) per row


def project(points_m: np.ndarray, K: np.ndarray, R_c: np.ndarray, t_c: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """points_m (...,3) world m. Returns pixels (...,2) (u, v) and axial depth (...,) m; u is NaN-free
    only where depth > 0."""
    x = to_camera_cv(points_m, R_c, t_c)
    z = x[..., 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        uv = (x[..., :2] / z[..., None]) @ K[:2, :2].T + K[:2, 2]
    return uv, z


def unproject(uv: np.ndarray, depth_m: np.ndarray, K: np.ndarray, R_c: np.ndarray, t_c: np.ndarray) -> np.ndarray:
    """uv (...,2) pixels, depth_m (...,) axial (Z-pass) depth. Returns world points (...,3) m:
    p = R_c S (Z K^-1 [u, v, 1]) + t_c."""
    uv = np.asarray(uv, float)
    rays = np.concatenate([uv, np.ones(uv.shape[:-1] + (1,))], axis=-1) @ np.linalg.inv(K).T  # third comp. 1
    x_cv = rays * np.asarray(depth_m, float)[..., None]
    return x_cv @ S @ np.asarray(R_c).T + t_c


def pixel_rays(K: np.ndarray, R_c: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """uv (...,2) pixels -> (...,3) world direction of the ray through each pixel, scaled so its
    component along the optical axis is 1 m (so ``t_c + Z * ray`` is the point at axial depth Z)."""
    uv = np.asarray(uv, float)
    rays = np.concatenate([uv, np.ones(uv.shape[:-1] + (1,))], axis=-1) @ np.linalg.inv(K).T
    return rays @ S @ np.asarray(R_c).T


__all__ = ["S", "intrinsics", "camera_position", "look_at", "camera_pose", "pose_matrix", "world_to_camera_cv",
           "to_camera_cv", "project", "unproject", "pixel_rays"]
