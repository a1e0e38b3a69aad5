"""Metric validation: the controlled perturbations on synthetic arrays with hand-computed answers."""

import math

import numpy as np
import pytest

from rigidbench.metrics.identity import IMAGENET_MEAN, IMAGENET_STD, extract_patches
from rigidbench.validation.background import corner_tracks, mean_displacement, motion_sweep
from rigidbench.validation.curves import RENDERED_MODES, curve_plan
from rigidbench.validation.identity import apply_gamma, mosaic, swap_vs_gamma
from rigidbench.validation.ray import RayScene, fill_covered, perturb_scene, ray_metrics, shift_image

# -- ATE-3D along vs across the viewing ray ------------------------------------------------------

F_PX, W, H, T = 200.0, 320, 240, 6
K = np.array([[F_PX, 0.0, W / 2 - 0.5], [0.0, F_PX, H / 2 - 0.5], [0.0, 0.0, 1.0]])
CAMERA = np.eye(4)  # Blender camera at the origin looking down world -z, +y up
ACTOR_DEPTH_M = 2.0
HALF_SIDE_M = 0.1
TRAVEL_M = 0.4


def pixel(points_m):
    """World points (M,3) in front of CAMERA -> (M,2) px, by hand: x_cv = x, y_cv = -y, z_cv = -z."""
    p = np.asarray(points_m, float)
    return np.stack([F_PX * p[:, 0] / -p[:, 2] + K[0, 2], F_PX * -p[:, 1] / -p[:, 2] + K[1, 2]], axis=1)


def synthetic_scene() -> RayScene:
    """A 0.2 m fronto-parallel square 2 m away sliding 0.4 m to the right in front of a floor-like
    background whose depth runs from 1.2 m (bottom row) to 9 m (top row), so the actor's disparity
    is no outlier for the clip-level disparity alignment."""
    rows = np.arange(H, dtype=float)[:, None]
    background = np.broadcast_to(9.0 - 7.8 * rows / (H - 1), (H, W)).astype(np.float32)
    xs = np.linspace(-TRAVEL_M / 2, TRAVEL_M / 2, T)
    positions = np.stack([xs, np.zeros(T), np.full(T, -ACTOR_DEPTH_M)], axis=1)  # (T,3)
    body = np.array([[bx, by, 0.0] for bx in (-0.05, 0.0, 0.05) for by in (-0.05, 0.0, 0.05)])  # (P,3)
    points = positions[None, :, :] + body[:, None, :]  # (P,T,3)
    tracks = np.stack([pixel(points[:, t]) for t in range(T)], axis=1)
    masks = np.zeros((T, 1, H, W), bool)
    depth = np.empty((T, H, W), np.float32)
    half_px = F_PX * HALF_SIDE_M / ACTOR_DEPTH_M
    cols = np.arange(W)[None, :]
    for t in range(T):
        u, v = pixel(positions[t][None])[0]
        masks[t, 0] = (np.abs(cols - u) <= half_px) & (np.abs(rows - v) <= half_px)
        depth[t] = np.where(masks[t, 0], ACTOR_DEPTH_M, background)
    return RayScene(masks=masks, depth_m=depth, tracks=tracks, visibility=np.ones(tracks.shape[:2], bool),
                    actor_index=np.zeros(len(body), np.int64), positions_m=positions[None], points_m=points,
                    K=K, camera_to_world=CAMERA, name="synthetic")


def test_shift_image_and_fill_covered_by_hand():
    a = np.arange(12).reshape(3, 4)
    np.testing.assert_array_equal(shift_image(a, 1, -1, -1), [[-1, 4, 5, 6], [-1, 8, 9, 10], [-1, -1, -1, -1]])
    depth = np.array([[1.0, 2.0, 3.0]])
    np.testing.assert_array_equal(fill_covered(depth, np.array([[False, True, True]])), [[1.0, 1.0, 1.0]])


def test_unperturbed_scene_scores_perfectly():
    scene = synthetic_scene()
    values = ray_metrics(scene, *perturb_scene(scene, 0.0, "across"))
    assert values["ate"] == 0.0 and values["iou"] == 1.0
    assert values["ate3d"] == pytest.approx(0.0, abs=1e-6)


@pytest.mark.parametrize("offset_m", [0.1, 0.3])
def test_along_ray_moves_ate3d_like_across_ray_and_leaves_2d_ate_at_zero(offset_m):
    scene = synthetic_scene()
    masks, depth, tracks, vis = perturb_scene(scene, offset_m, "along")
    along = ray_metrics(scene, masks, depth, tracks, vis)
    across = ray_metrics(scene, *perturb_scene(scene, offset_m, "across"))
    # Along the ray the image is unchanged: same masks and tracks, only the actor's depth grows.
    np.testing.assert_array_equal(masks, scene.masks)
    assert along["ate"] == pytest.approx(0.0, abs=1e-9) and along["iou"] == 1.0
    assert np.all(depth[scene.masks[:, 0]] > ACTOR_DEPTH_M)
    # Every actor point moves by about offset_m in 3D, so ATE-3D ~ offset / travel in both directions.
    assert along["ate3d"] == pytest.approx(offset_m / TRAVEL_M, rel=0.05)
    assert across["ate3d"] == pytest.approx(along["ate3d"], rel=0.05)
    # Across the ray the tracks move by the projected offset of the actor's position.
    centre = scene.positions_m[0]
    ray = centre / np.linalg.norm(centre, axis=1, keepdims=True)
    right = np.array([1.0, 0.0, 0.0]) - ray[:, :1] * ray
    right /= np.linalg.norm(right, axis=1, keepdims=True)
    shift_px = np.linalg.norm(pixel(centre + offset_m * right) - pixel(centre), axis=1)
    assert across["ate"] == pytest.approx(shift_px.mean() / H, rel=1e-9)


# -- BGDrift: coherent translation vs independent jitter ----------------------------------------


def test_translation_and_jitter_have_matched_displacement():
    rng = np.random.default_rng(1)
    for motion in ("translation", "jitter"):
        tracks = corner_tracks(12.0, motion, rng, n_corners=50, n_frames=7)
        assert tracks.shape == (50, 7, 2)
        per_frame = np.linalg.norm(tracks[:, 1:] - tracks[:, :1], axis=-1).mean(axis=0)
        np.testing.assert_allclose(per_frame, 12.0, rtol=1e-12)
        assert mean_displacement(tracks) == pytest.approx(12.0)


def test_bgdrift_ignores_translation_and_follows_jitter():
    magnitudes = np.array([0.0, 10.0, 20.0, 40.0])
    sweep = motion_sweep(magnitudes, trials=2, seed=0, n_frames=9)
    translation = sweep["translation/bgdrift"].mean(axis=1) * 704
    jitter = sweep["jitter/bgdrift"].mean(axis=1) * 704
    np.testing.assert_allclose(sweep["jitter/displacement"].mean(axis=1) * 704, magnitudes, atol=1e-9)
    assert np.all(translation < 1e-3)  # pixels: the similarity transform absorbs the translation
    assert np.all(np.diff(jitter) > 0)
    # No similarity can explain independent jitter: the residual is at least most of the displacement.
    assert np.all(jitter[1:] > 0.8 * magnitudes[1:])


# -- IdDrift: identity swap vs gamma ------------------------------------------------------------


def mean_colour(x):
    """Feature = per-channel mean of the normalised patch (B, 3)."""
    return x.mean(dim=(2, 3))


def normalised(rgb):
    v = (np.asarray(rgb, float) / 255 - IMAGENET_MEAN) / IMAGENET_STD
    return v / np.linalg.norm(v)


def test_mosaic_gives_the_patches_back_through_the_metric_patch_extractor():
    rng = np.random.default_rng(0)
    patches = rng.integers(0, 256, (7, 64, 64, 3), dtype=np.uint8)
    image, centres = mosaic(patches)
    assert image.shape == (128, 320, 3)
    np.testing.assert_array_equal(extract_patches(image, centres), patches)


def test_swap_vs_gamma_with_a_small_feature_function():
    pytest.importorskip("torch")
    # A light grey actor swapped for a blue one, or darkened by gamma 2.5.
    grey, blue = (200, 200, 200), (40, 40, 200)
    patches = np.broadcast_to(np.array(grey, np.uint8), (4, 64, 64, 3)).copy()
    donors = np.broadcast_to(np.array(blue, np.uint8), (4, 64, 64, 3)).copy()
    sweep = swap_vs_gamma(patches, donors, np.array([0.0, 1.0]), trials=2, seed=0, feature_fn=mean_colour)
    gamma_grey = round(255 * (200 / 255) ** 2.5)  # gamma 1 + 1.5 q at q = 1
    assert int(apply_gamma(np.array([200], np.uint8), 2.5)[0]) == gamma_grey
    for key in sweep:
        np.testing.assert_allclose(sweep[key][0], 0.0, atol=1e-6)  # q = 0 changes nothing
    l2_swap = math.sqrt(np.mean((np.array(blue) - 200.0) ** 2)) / 255
    l2_gamma = abs(gamma_grey - 200) / 255
    np.testing.assert_allclose(sweep["swap/pixel_l2"][1], l2_swap, rtol=1e-12)
    np.testing.assert_allclose(sweep["gamma/pixel_l2"][1], l2_gamma, rtol=1e-12)
    id_swap = 1 - normalised(grey) @ normalised(blue)
    id_gamma = 1 - normalised(grey) @ normalised([gamma_grey] * 3)
    np.testing.assert_allclose(sweep["swap/iddrift"][1], id_swap, atol=1e-5)
    np.testing.assert_allclose(sweep["gamma/iddrift"][1], id_gamma, atol=1e-5)
    # Colour features see the swap as a new identity (about 44x the gamma change) while pixel L2 sees ~2x.
    assert id_swap / id_gamma > l2_swap / l2_gamma


def test_without_a_feature_function_only_pixel_l2_is_measured():
    patches = np.zeros((2, 64, 64, 3), np.uint8)
    sweep = swap_vs_gamma(patches, patches + 255, np.array([0.0, 0.5, 1.0]), trials=20, seed=3, feature_fn=None)
    assert set(sweep) == {"swap/pixel_l2", "gamma/pixel_l2"}
    # Black patches: gamma leaves 0 at 0, a white donor moves every pixel by 1; at q = 0.5 about half swap.
    np.testing.assert_array_equal(sweep["gamma/pixel_l2"], 0.0)
    np.testing.assert_allclose(sweep["swap/pixel_l2"][2], 1.0)
    assert 0.3 < sweep["swap/pixel_l2"][1].mean() < 0.7


# -- which failure mode drives each curve -------------------------------------------------------


def test_curve_plan_uses_rendered_modes_only_when_asked():
    image_space = {"slow", "gamma", "camera-shake", "background-wobble", "static"}
    plan = {(m, role): mode for m, mode, role in curve_plan(image_space | set(RENDERED_MODES), False)}
    assert not set(plan.values()) & set(RENDERED_MODES)
    assert plan[("ate3d", "main")] == "slow" and plan[("si_mse", "main")] == "camera-shake"
    assert plan[("iddrift", "main")] == "gamma" and plan[("bgdrift", "control")] == "camera-shake"
    rendered = {(m, role): mode for m, mode, role in curve_plan(image_space | set(RENDERED_MODES), True)}
    assert rendered[("ate3d", "main")] == "depth-offset" and rendered[("iddrift", "main")] == "identity-swap"
    # Asked for rendered modes that are not registered (yet): the image-space ones stand in.
    fallback = {(m, role): mode for m, mode, role in curve_plan(image_space, True)}
    assert fallback[("ate3d", "main")] == "slow" and len(fallback) == 11
