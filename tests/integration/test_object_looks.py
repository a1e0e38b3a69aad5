"""Object looks: a few procedural objects rendered small in Cycles read as what they are.

Each object is rendered alone at 128x128 under the studio setup of ``benchmarks/assets_preview.py``
(Blender's courtyard HDRI plus a sun, a grey floor that lights but is not seen, the benchmark's
Standard view transform), filling most of the frame with a transparent background, and the
colour inside its silhouette (alpha) is compared with what a photo of the real thing shows:
the watermelon is green with dark stripes, the kiwi brown (not pink), the lemon a saturated
yellow, the tomato and apple red, and pale or yellow objects are not blown out to white.
"""

from __future__ import annotations

import colorsys
import math

import numpy as np
import pytest

bpy = pytest.importorskip("bpy", reason="bpy (Blender as a Python module) is not installed; "
                                        "install the 'sim' extra to run the asset tests")

from rigidbench.blender.assets import _paint  # noqa: E402
from rigidbench.blender.assets.objects import build_object  # noqa: E402
from rigidbench.blender.assets.scenes import build_studio  # noqa: E402
from rigidbench.blender.render import set_color_management  # noqa: E402
from rigidbench.config import registry  # noqa: E402

pytestmark = pytest.mark.integration

REG = registry()
SIZE = 128


def render_object(object_id: str, tmp_path, azimuth_deg: float = 30.0, elevation_deg: float = 10.0,
                  samples: int = 8) -> np.ndarray:
    """Render ``object_id`` alone in the studio; returns (n, 3) display sRGB in 0..255 of the pixels
    the object fully covers."""
    from mathutils import Vector

    bpy.ops.wm.read_factory_settings(use_empty=True)
    scene = bpy.context.scene
    scene.render.engine = "CYCLES"
    scene.cycles.device = "CPU"
    scene.cycles.samples = samples
    scene.cycles.use_denoising = False
    scene.cycles.max_bounces = 4
    scene.render.resolution_x = scene.render.resolution_y = SIZE
    scene.render.resolution_percentage = 100
    set_color_management(scene)
    scene.render.film_transparent = True
    scene.render.image_settings.file_format = "PNG"
    scene.render.image_settings.color_mode = "RGBA"
    floor = build_studio(scene)
    floor.visible_camera = False  # lights the object from below but leaves the background transparent
    cam_data = bpy.data.cameras.new("cam")
    cam_data.lens, cam_data.sensor_width, cam_data.clip_start = 50.0, 36.0, 0.002
    cam = bpy.data.objects.new("cam", cam_data)
    scene.collection.objects.link(cam)
    scene.camera = cam
    cfg = REG.object(object_id)
    ob = build_object(cfg, f"{object_id}_0")
    ob.location = (0.0, 0.0, cfg.size_m[2] / 2)
    target = Vector((0.0, 0.0, cfg.size_m[2] / 2))
    distance = max(cfg.size_m) / 0.8 / (2 * 18 / 50)  # the longest side spans ~80% of the frame
    az, el = math.radians(azimuth_deg), math.radians(elevation_deg)
    offset = Vector((math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), math.sin(el))) * distance
    cam.location = target + offset
    cam.rotation_euler = (-offset).to_track_quat("-Z", "Y").to_euler()
    path = tmp_path / f"{object_id}.png"
    scene.render.filepath = str(path)
    bpy.ops.render.render(write_still=True)
    img = bpy.data.images.load(str(path))
    px = np.empty(SIZE * SIZE * 4, np.float32)
    img.pixels.foreach_get(px)
    px = px.reshape(SIZE, SIZE, 4)
    inside = px[..., 3] > 0.99
    assert inside.mean() > 0.05, f"{object_id} covers only {inside.mean():.1%} of the frame"
    return px[..., :3][inside] * 255.0


def luminance(rgb: np.ndarray) -> np.ndarray:
    return rgb @ np.array([0.2126, 0.7152, 0.0722])


def hue_sat_val(rgb_mean) -> tuple[float, float, float]:
    """(hue in degrees, saturation, value) of a mean sRGB colour in 0..255."""
    h, s, v = colorsys.rgb_to_hsv(*(np.asarray(rgb_mean, float) / 255.0))
    return 360.0 * h, s, v


def blown(rgb: np.ndarray) -> float:
    """Fraction of pixels clipped to white (every channel at 250 or more)."""
    return float((rgb.min(1) >= 250).mean())


def test_watermelon_is_green_with_dark_stripes(tmp_path):
    rgb = render_object("watermelon", tmp_path)
    r, g, b = rgb.mean(0)
    assert g > r + 10 and g > b + 25, (r, g, b)  # green, not beige
    lum = luminance(rgb)
    assert lum.mean() < 135, lum.mean()  # a darkish rind, not pale
    assert lum.std() > 25, lum.std()  # high-contrast stripes
    assert (lum < 70).mean() > 0.15 and (lum > 110).mean() > 0.15  # both dark stripes and light rind


def test_kiwi_is_brown_not_pink(tmp_path):
    rgb = render_object("kiwi", tmp_path)
    hue, sat, val = hue_sat_val(rgb.mean(0))
    assert 20 <= hue <= 45, hue  # brown (orange hue at low value); pink would be < 15 or > 330
    assert 0.3 <= sat <= 0.75 and val < 0.7, (sat, val)  # muted and dark, not a saturated pale peach
    assert luminance(rgb).std() > 8  # fuzzy, mottled skin to track


def test_lemon_is_saturated_yellow_and_not_blown_out(tmp_path):
    rgb = render_object("lemon", tmp_path)
    hue, sat, val = hue_sat_val(rgb.mean(0))
    assert 42 <= hue <= 62, hue
    assert sat > 0.6 and val > 0.7, (sat, val)
    assert blown(rgb) < 0.03, blown(rgb)


@pytest.mark.parametrize("object_id", ["tomato", "apple"])
def test_tomato_and_apple_are_red(tmp_path, object_id):
    rgb = render_object(object_id, tmp_path)
    r, g, b = rgb.mean(0)
    hue, sat, _ = hue_sat_val((r, g, b))
    assert (hue < 18 or hue > 345) and sat > 0.55, (object_id, hue, sat, (r, g, b))
    assert r > 1.8 * g, (r, g, b)


@pytest.mark.parametrize("object_id", ["banana", "toy_duck"])
def test_yellow_objects_keep_their_highlights_small(tmp_path, object_id):
    # seen from above so the thin banana fills enough of the frame; a yellow albedo never reaches
    # white by diffuse light alone, so white pixels are specular highlights clipped by a glossy coat
    rgb = render_object(object_id, tmp_path, elevation_deg=60.0)
    hue, sat, _ = hue_sat_val(rgb.mean(0))
    assert 38 <= hue <= 60 and sat > 0.55, (object_id, hue, sat)
    assert blown(rgb) < 0.02, (object_id, blown(rgb))


def test_baseball_is_off_white_with_red_stitches(tmp_path):
    rgb = render_object("baseball", tmp_path)
    r, g, b = rgb.mean(0)
    assert min(r, g, b) > 150 and r - b < 45, (r, g, b)  # near-neutral white leather
    stitches = (rgb[:, 0] > rgb[:, 1] + 50) & (rgb[:, 0] > rgb[:, 2] + 50)
    assert 0.005 < stitches.mean() < 0.2, stitches.mean()


def test_large_objects_have_paper_resolution_textures():
    for painter in (_paint.watermelon, _paint.rugby_ball, _paint.coconut, _paint.bottle_label):
        img = painter()
        assert img.shape[0] >= 256 and img.shape[1] >= 512, (painter.__name__, img.shape)


SKIN_PAINTERS = ("apple", "orange", "lemon", "kiwi", "pomegranate", "pear", "mango", "banana", "watermelon", "peach",
                 "tomato", "coconut", "duck", "baseball", "tennis_ball", "cricket_ball", "bouncy_ball", "rugby_ball",
                 "energy_can", "soda_can", "food_can_label", "bottle_label", "die", "puzzle_cube")
NATURAL = ("apple", "orange", "lemon", "kiwi", "pomegranate", "pear", "mango", "banana", "watermelon", "peach",
           "tomato", "coconut", "baseball", "tennis_ball", "cricket_ball")


@pytest.mark.parametrize("name", SKIN_PAINTERS)
def test_object_textures_have_fine_detail_to_track(name):
    from scipy import ndimage

    img = getattr(_paint, name)()
    lum = img @ np.array([0.2126, 0.7152, 0.0722])
    fine = np.abs(lum - ndimage.uniform_filter(lum, 9)).mean()  # detail finer than ~9 texels
    assert fine > 0.002, (name, fine)
    if name in NATURAL:  # real fruit and leather: albedo well below white, so Standard view does not clip
        assert np.percentile(img.max(2), 99) <= 0.93, (name, np.percentile(img.max(2), 99))
