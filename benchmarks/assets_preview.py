"""Render PNG contact sheets of every procedural object and scene, and time the builders.

    python benchmarks/assets_preview.py [--quick] --out /tmp/rb_preview [--what objects|scenes|timing|all]
        [--tile 192] [--samples 16] [--only apple,kiwi]

Writes objects.png (two views per object: 30 deg azimuth at 10 deg elevation and a higher back
view) and scenes.png (per scene, the benchmark-style camera from two azimuths, 10 deg elevation,
35 mm lens, 1280x704 aspect, azimuths where a ray reaches the support) and prints JSON with
build times in milliseconds (``--what timing`` measures them without rendering).
"""

from __future__ import annotations

import argparse
import json
import math
import tempfile
import time
from pathlib import Path

import numpy as np


def _reset() -> None:
    import bpy

    bpy.ops.wm.read_factory_settings(use_empty=True)


def _setup_render(width: int, height: int, samples: int) -> None:
    import bpy

    scene = bpy.context.scene
    scene.render.engine = "CYCLES"
    scene.cycles.device = "CPU"
    scene.cycles.samples = samples
    scene.cycles.use_adaptive_sampling = True
    scene.cycles.use_denoising = True
    scene.cycles.max_bounces = 6
    scene.cycles.diffuse_bounces = 3
    scene.cycles.glossy_bounces = 3
    scene.cycles.transmission_bounces = 4
    scene.render.resolution_x, scene.render.resolution_y = width, height
    scene.render.resolution_percentage = 100
    scene.render.image_settings.file_format = "PNG"
    from rigidbench.blender.render import set_color_management

    set_color_management(scene)  # the benchmark's own colour management (Standard view transform)
    scene.render.film_transparent = False


def _camera(lens_mm: float = 35.0):
    import bpy

    cam_data = bpy.data.cameras.new("preview_cam")
    cam_data.lens = lens_mm
    cam_data.sensor_width = 36.0
    cam_data.sensor_fit = "HORIZONTAL"
    cam = bpy.data.objects.new("preview_cam", cam_data)
    bpy.context.scene.collection.objects.link(cam)
    bpy.context.scene.camera = cam
    return cam


def _look_at(cam, target, azimuth_deg: float, elevation_deg: float, distance_m: float) -> None:
    from mathutils import Vector

    az, el = math.radians(azimuth_deg), math.radians(elevation_deg)
    offset = Vector((math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), math.sin(el))) * distance_m
    cam.location = Vector(target) + offset
    cam.rotation_euler = (-offset).to_track_quat("-Z", "Y").to_euler()


def _render(path: Path) -> np.ndarray:
    """Render the current scene to ``path``; returns (H,W,3) float display RGB, row 0 at the top."""
    import bpy

    bpy.context.scene.render.filepath = str(path)
    bpy.ops.render.render(write_still=True)
    img = bpy.data.images.load(str(path))
    w, h = img.size
    px = np.empty(w * h * 4, np.float32)
    img.pixels.foreach_get(px)
    bpy.data.images.remove(img)
    return px.reshape(h, w, 4)[::-1, :, :3]


def _save_png(pixels: np.ndarray, path: Path) -> None:
    import bpy

    h, w = pixels.shape[:2]
    img = bpy.data.images.new(path.stem, w, h, alpha=False)
    rgba = np.concatenate([pixels, np.ones((h, w, 1), np.float32)], 2)[::-1]
    img.pixels.foreach_set(rgba.astype(np.float32).reshape(-1))
    img.filepath_raw = str(path)
    img.file_format = "PNG"
    img.save()
    bpy.data.images.remove(img)


def preview_objects(out: Path, tile: int, samples: int, only: list[str] | None) -> dict:
    import bpy

    from rigidbench.blender.assets.objects import build_object
    from rigidbench.blender.assets.scenes import build_studio
    from rigidbench.config import registry

    reg = registry()
    ids = only or sorted(reg.objects)
    _reset()
    _setup_render(tile, tile, samples)
    build_studio(bpy.context.scene)
    cam = _camera(50.0)
    timings, tiles = {}, []
    with tempfile.TemporaryDirectory() as tmp:
        for i, oid in enumerate(ids):
            cfg = reg.object(oid)
            t0 = time.perf_counter()
            ob = build_object(cfg, f"{oid}_0")
            timings[oid] = round(1000 * (time.perf_counter() - t0), 2)
            spot = ((i % 6) * 2.0, (i // 6) * 2.0)
            ob.location = (spot[0], spot[1], cfg.size_m[2] / 2)
            target = (spot[0], spot[1], cfg.size_m[2] / 2)
            extent = max(cfg.size_m)
            dist = extent / 0.36 / (2 * math.tan(math.atan(18 / 50)))
            views = []
            for az, el in ((30.0, 10.0), (215.0, 40.0)):
                _look_at(cam, target, az, el, dist)
                views.append(_render(Path(tmp) / f"{oid}_{az}.png"))
            tiles.append(np.concatenate(views, 1))
    cols = 4
    rows = math.ceil(len(tiles) / cols)
    sheet = np.ones((rows * tile, cols * 2 * tile, 3), np.float32)
    for k, t in enumerate(tiles):
        r, c = divmod(k, cols)
        sheet[r * tile:(r + 1) * tile, c * 2 * tile:(c + 1) * 2 * tile] = t
        sheet[r * tile:(r + 1) * tile, c * 2 * tile:c * 2 * tile + 1] = 0
    _save_png(sheet, out / "objects.png")
    return {"object_build_ms": timings, "objects_sheet": str(out / "objects.png"), "order": ids}


def _clear_azimuths(target, distance_m: float, elevation_deg: float, count: int) -> list[float]:
    """First ``count`` azimuths (spread, every 30 deg) whose camera sees ``target`` unobstructed."""
    import bpy
    from mathutils import Vector

    scene = bpy.context.scene
    depsgraph = bpy.context.evaluated_depsgraph_get()
    found = []
    goal = Vector((target[0], target[1], target[2] + 0.05))
    for az in (255.0, 315.0, 195.0, 15.0, 135.0, 75.0, 285.0, 225.0, 345.0, 165.0, 45.0, 105.0):
        el = math.radians(elevation_deg)
        cam = goal + Vector((math.cos(el) * math.cos(math.radians(az)), math.cos(el) * math.sin(math.radians(az)),
                             math.sin(el))) * distance_m
        direction = (goal - cam).normalized()
        hit, loc, *_ = scene.ray_cast(depsgraph, cam, direction, distance=(goal - cam).length - 0.3)
        if not hit:
            found.append(az)
        if len(found) == count:
            break
    return found or [255.0]


def preview_scenes(out: Path, width: int, samples: int, only: list[str] | None) -> dict:
    from rigidbench.blender.assets.objects import build_object
    from rigidbench.blender.assets.scenes import build_environment
    from rigidbench.config import registry

    reg = registry()
    ids = only or sorted(reg.scenes)
    height = int(round(width * 704 / 1280))
    timings, rows = {}, []
    with tempfile.TemporaryDirectory() as tmp:
        for sid in ids:
            _reset()
            _setup_render(width, height, samples)
            t0 = time.perf_counter()
            env = build_environment(reg.scene(sid))
            timings[sid] = round(1000 * (time.perf_counter() - t0), 1)
            cam = _camera(35.0)
            views = []
            for k, support in enumerate(reg.scene(sid).supports):
                top = support.centre_m
                for n, oid in enumerate(("apple", "red_bull_can", "tennis_ball")):
                    cfg = reg.object(oid)
                    ob = build_object(cfg, f"{sid}_{k}_{oid}")
                    yaw = math.radians(support.long_axis_deg)
                    dx = (n - 1) * 0.18
                    ob.location = (top[0] + math.cos(yaw) * dx, top[1] + math.sin(yaw) * dx, top[2] + cfg.size_m[2] / 2)
                for az in _clear_azimuths(top, 2.0, 10.0, 2):
                    _look_at(cam, (top[0], top[1], top[2] + 0.1), az, 10.0, 2.0)
                    views.append(_render(Path(tmp) / f"{sid}_{k}_{az}.png"))
            del env
            views = views[:4] + [np.ones_like(views[0])] * (4 - len(views))
            rows.append(np.concatenate(views, 1))
    sheet = np.concatenate(rows, 0)
    _save_png(sheet, out / "scenes.png")
    return {"scene_build_ms": timings, "scenes_sheet": str(out / "scenes.png"), "order": ids}


def build_timings(only: list[str] | None) -> dict:
    """Milliseconds to build each object and scene: first in the process (textures painted), after a
    factory reset (materials rebuilt from cached textures) and again in the same bpy scene."""
    from rigidbench.blender.assets.objects import build_object
    from rigidbench.blender.assets.scenes import build_environment
    from rigidbench.config import registry

    reg = registry()
    objects = [o for o in sorted(reg.objects) if not only or o in only]
    scenes = [s for s in sorted(reg.scenes) if not only or s in only]
    out: dict = {"object_ms": {}, "scene_ms": {}}

    def ms(fn) -> float:
        t0 = time.perf_counter()
        fn()
        return round(1000 * (time.perf_counter() - t0), 2)

    _reset()
    first = {o: ms(lambda o=o: build_object(reg.object(o), f"{o}_a")) for o in objects}
    _reset()
    reset = {o: ms(lambda o=o: build_object(reg.object(o), f"{o}_b")) for o in objects}
    warm = {o: ms(lambda o=o: build_object(reg.object(o), f"{o}_c")) for o in objects}
    for o in objects:
        out["object_ms"][o] = {"first_in_process": first[o], "after_reset": reset[o], "same_scene": warm[o]}
    for sid in scenes:
        _reset()
        a = ms(lambda: build_environment(reg.scene(sid)))
        _reset()
        b = ms(lambda: build_environment(reg.scene(sid)))
        out["scene_ms"][sid] = {"first_in_process": a, "after_reset": b}
    for key in ("object_ms", "scene_ms"):
        for phase in ("first_in_process", "after_reset"):
            values = [v[phase] for v in out[key].values()]
            if values:
                out[f"{key}_{phase}_max"] = max(values)
                out[f"{key}_{phase}_mean"] = round(sum(values) / len(values), 2)
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=Path(tempfile.gettempdir()) / "rb_preview")
    parser.add_argument("--what", choices=("objects", "scenes", "timing", "all"), default="all")
    parser.add_argument("--tile", type=int, default=192, help="object tile size / scene view width in pixels")
    parser.add_argument("--samples", type=int, default=16)
    parser.add_argument("--only", default="", help="comma-separated ids to restrict the sheet to")
    parser.add_argument("--quick", action="store_true", help="smoke run: builder timing of one object, no rendering")
    args = parser.parse_args()
    if args.quick:
        args.what = 'timing'
        args.only = 'apple'
    args.out.mkdir(parents=True, exist_ok=True)
    only = [s for s in args.only.split(",") if s] or None
    result = {}
    if args.what in ("timing", "all"):
        result.update(build_timings(only))
    if args.what in ("objects", "all"):
        result.update(preview_objects(args.out, args.tile, args.samples, only))
    if args.what in ("scenes", "all"):
        result.update(preview_scenes(args.out, max(args.tile, 256), args.samples, only))
    print(json.dumps(result, indent=2))


if __name__ == "__main__":
    main()
