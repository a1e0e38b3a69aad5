"""Regenerate docs/gallery/: one sheet per task and per scene (all different eval examples) and an
objects sheet, rendered at the `paper` preset.

    python scripts/make_gallery.py [--work /tmp/rigidbench_gallery] [--quality paper] [--only 00027,objects] [--fresh]
    python scripts/make_gallery.py --before-data DIR --before-objects PNG   # also the before/after thumbnails

Each example is simulated and its data passes (masks, depth, hence the ground-truth tracks) are
rendered for every frame, but RGB only at its event frames (release, first new contact, rebound
apex, rest: ``rigidbench.report.gallery.event_frames``), so a sheet costs 3-4 paper frames
(about 105 s each on a 2-core CPU) instead of 49. Per-example results land in ``--work`` first and
are reused, so an interrupted run resumes where it stopped. Sheets already in ``--out`` are kept
when ``examples.json`` there lists them at this preset and the camera search still picks the same
camera (checked without rendering), and so is the objects sheet unless ``--only objects`` asks for it.
Changes to scenes, objects or light are not detected: ``--fresh`` renders every example (with
``--only``, the ones given) whatever ``--out`` holds; renders already in ``--work`` are still reused,
so give a new ``--work`` to redo those. The objects sheet renders the 24
objects four at a time on a plain floor under the same studio light as
``benchmarks/assets_preview.py`` and crops a tile around each. Sheets are JPEG under ``MAX_BYTES``.

``--before-data`` takes bundles of the same example ids rendered by an older checkout (any
preset) and writes ``before_after/<scene>.jpg``: that first frame beside the new one.

Errors: an example that cannot be rendered (a ``RigidBenchError`` or an I/O error) is logged with its id
and the reason, the others go on, and the run exits with status 1; an unreadable ``examples.json``, cached
render in ``--work`` or ``--before-*`` input stops the run with one line naming the file (status 2); any
other exception is a bug and stops the run with its traceback.
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import shutil
import sys
import tempfile
import zipfile
from pathlib import Path

import numpy as np

from rigidbench import jsonio, manifest
from rigidbench.blender.assets.objects import build_object
from rigidbench.blender.assets.scenes import build_studio
from rigidbench.blender.camera import camera_pose
from rigidbench.blender.render import (beauty_mode, configure_cycles, render_example, resolve_camera,
                                       select_device)
from rigidbench.blender.session import reset_scene
from rigidbench.config import registry
from rigidbench.errors import EXAMPLE_ERRORS, RigidBenchError, UserError
from rigidbench.groundtruth import bundle as B, camera_model as cm
from rigidbench.groundtruth.contacts import quat_to_matrix
from rigidbench.groundtruth.tracks import ground_truth_tracks
from rigidbench.report.gallery import (Event, encode_under, event_frames, example_sheet, font, marker_subset,
                                       objects_sheet, pick_examples)
from rigidbench.scene_spec.build import build_scene_spec

ROOT = Path(__file__).resolve().parents[1]
OUT_DIR = ROOT / "docs" / "gallery"
MAX_BYTES = 1_000_000
OBJECTS_PER_RENDER = 4
THUMB_W = 480
INDEX_KEYS = ("sample_id", "task", "scene", "surface", "partition", "preset", "events", "camera")  # examples.json
INFO_KEYS = ("sample_id", "task", "scene", "surface", "partition", "prompt", "fps", "frames", "events", "legend",
             "preset", "camera")  # info.json of a render in --work
CAMERA_KEYS = ("azimuth_deg", "distance_m", "target_m")

log = logging.getLogger("make_gallery")


# -- one example ---------------------------------------------------------------------------------


def render_example_events(row, reg, preset, work: Path) -> Path:
    """Render ``row``'s event frames into ``work/<id>/`` (frames/*.png, gt.npz, info.json); reused if done."""
    from PIL import Image

    final = work / row.sample_id
    if (final / "info.json").exists():
        return final
    tmp = work / f".{row.sample_id}.tmp"
    if tmp.exists():  # an interrupted earlier render (a failure to remove it is this example's error)
        shutil.rmtree(tmp)
    chosen: list = []

    def pick(sim):
        chosen[:] = event_frames(sim.trajectory, sim.contacts, min(preset.frames, sim.frames))
        return [e.frame for e in chosen]

    spec = build_scene_spec(row, reg)
    result = render_example(spec, reg, preset, tmp / "frames", tmp / ".passes", rgb_frames=pick)
    shutil.rmtree(tmp / ".passes")
    spec = result.spec
    T = result.index.shape[0]
    names = tuple(b.name for b in spec.bodies)
    traj = B.slice_trajectory(result.simulation.trajectory, T)
    masks = B.masks_from_index(result.index, len(names))
    R_c, t_c = camera_pose(spec.camera)
    K = cm.intrinsics(spec.camera.lens_mm, spec.camera.sensor_width_mm, *preset.resolution)
    tracks = ground_truth_tracks(masks, result.depth_m, K, R_c, t_c, quat_to_matrix(traj.quat_wxyz), traj.positions_m,
                                 np.array([b.role == "active" for b in spec.bodies]), seed=spec.seed)
    keep = marker_subset(tracks.actor_index)
    frames = [e.frame for e in chosen]
    np.savez_compressed(tmp / "gt.npz", masks=masks[frames], depth=result.depth_m[frames],
                        tracks=tracks.tracks_px[keep], visibility=tracks.visibility[keep],
                        actor_index=tracks.actor_index[keep])
    legend = [f"{b.name}: {b.ramp.material if b.ramp is not None else b.asset} ({b.role})" for b in spec.bodies]
    info = {"sample_id": row.sample_id, "task": row.task, "scene": row.scene, "surface": row.surface,
            "partition": row.partition, "prompt": spec.prompt, "fps": float(spec.sim.fps), "frames": frames,
            "events": [[e.frame, e.label] for e in chosen], "legend": legend, "preset": preset.name,
            "seconds": {k: round(v, 1) for k, v in result.seconds.items()},
            "camera": camera_record(spec.camera)}
    (tmp / "info.json").write_text(json.dumps(info, indent=1))
    Image.open(tmp / "frames" / f"{frames[0]:05d}.png").load()  # the frames were written
    if final.exists():  # a render without its info.json: incomplete
        shutil.rmtree(final)
    tmp.rename(final)
    return final


def read_render(path: Path) -> tuple[dict, dict, dict]:
    """(info.json, gt.npz arrays, RGB frame by frame number) of one example's render in ``path``
    (``render_example_events``); UserError naming the file when one is missing or damaged."""
    from PIL import Image

    def unreadable(what: Path, exc: Exception) -> UserError:
        return UserError(f"{what}: the cached render of example {path.name} cannot be read ({exc}); "
                         f"delete {path} to render it again")

    try:
        info = json.loads((path / "info.json").read_text())
        missing = [k for k in INFO_KEYS if k not in info]
        if missing:
            raise KeyError(f"no {', '.join(missing)}")
        info["frames"] = [int(f) for f in info["frames"]]
        info["events"] = [[int(f), str(label)] for f, label in info["events"]]
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise unreadable(path / "info.json", exc) from exc
    try:
        with np.load(path / "gt.npz") as npz:
            gt = {k: npz[k] for k in ("masks", "depth", "tracks", "visibility", "actor_index")}
    except (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile) as exc:
        raise unreadable(path / "gt.npz", exc) from exc
    frames = {}
    for f in info["frames"]:
        png = path / "frames" / f"{f:05d}.png"
        try:
            frames[f] = np.asarray(Image.open(png).convert("RGB"))
        except (OSError, ValueError) as exc:
            raise unreadable(png, exc) from exc
    return info, gt, frames


def example_sheet_bytes(path: Path) -> tuple[bytes, dict]:
    info, gt, frames = read_render(path)
    events = [Event(f, label) for f, label in info["events"]]
    # masks and depth were saved for the event frames only, in the order of info["frames"]
    masks, depth = dict(zip(info["frames"], gt["masks"])), dict(zip(info["frames"], gt["depth"]))
    first = frames[info["frames"][0]]
    title = (f"{info['sample_id']}  {info['task']} in {info['scene']} ({info['surface']}), "
             f"{info['partition'].replace('_', ' ')}  -  {info['preset']} preset, {first.shape[1]}x{first.shape[0]}")
    sheet = example_sheet(frames, events, masks, depth, gt["tracks"], gt["visibility"], gt["actor_index"],
                          info["fps"], title, info["legend"])
    return encode_under(sheet, MAX_BYTES), info


# -- sheets already in docs/gallery ----------------------------------------------------------------


def camera_key(camera: dict) -> tuple:
    """What identifies a camera in ``info["camera"]`` (rounded, so a float round trip matches)."""
    return (round(float(camera["azimuth_deg"]) % 360.0, 4), round(float(camera["distance_m"]), 4),
            tuple(round(float(v), 4) for v in camera["target_m"]))


def camera_record(cam) -> dict:
    """The ``info["camera"]`` entry of a CameraSpec."""
    return {"azimuth_deg": cam.azimuth_deg, "distance_m": cam.distance_m, "target_m": list(cam.target_m),
            "visibility": cam.visibility}


def current_camera(row, reg) -> dict:
    """The camera today's code and configs choose for ``row`` (the search alone, no render: about a
    second)."""
    return camera_record(resolve_camera(build_scene_spec(row, reg), reg).camera)


def read_index(path: Path) -> dict:
    """The gallery's examples.json (sample id -> INDEX_KEYS), {} when there is none; UserError naming the
    file, and the entry, when it is not JSON mapping ids to records."""
    if not path.exists():
        return {}
    try:
        index = json.loads(path.read_text())
    except (OSError, ValueError) as exc:
        raise UserError(f"{path}: not a readable gallery index ({exc}); delete it (every example is then "
                        "rendered again) or restore it from git") from exc
    if not isinstance(index, dict):
        raise UserError(f"{path}: a gallery index maps example ids to their sheets' facts, found a "
                        f"{type(index).__name__}; delete it or restore it from git")
    for sid, info in index.items():
        if not isinstance(info, dict):
            raise UserError(f"{path}: entry {sid} is a {type(info).__name__}, not a record of its sheets; delete "
                            "the entry (its example is then rendered again) or restore the file from git")
    return index


def committed_is_current(row, reg, preset, out: Path, index: dict, prefixes: list[str]) -> bool:
    """True when ``out`` already holds this example's sheets (listed in ``index``, the gallery's
    examples.json) at this preset and with the camera today's search picks, so they need no render.
    Scene, object and light changes are not detected: pass --fresh after those."""
    info = index.get(row.sample_id)
    if info is None or info.get("preset") != preset.name:
        return False
    lacking = [k for k in INDEX_KEYS if k not in info]
    lacking += [f"camera.{k}" for k in CAMERA_KEYS if "camera" in info and k not in info["camera"]]
    if lacking:
        log.warning("example %s: its entry in %s lacks %s; rendering it again", row.sample_id,
                    out / "examples.json", ", ".join(lacking))
        return False
    if not all((out / f"{p}.jpg").exists() for p in prefixes):
        return False
    now = current_camera(row, reg)
    if camera_key(now) != camera_key(info["camera"]):
        log.info("example %s: the camera moved (azimuth %.1f -> %.1f deg); rendering it again", row.sample_id,
                 info["camera"]["azimuth_deg"], now["azimuth_deg"])
        return False
    return True


# -- objects ---------------------------------------------------------------------------------------


def render_objects(reg, preset, work: Path) -> Path:
    """Render every object at the paper preset, OBJECTS_PER_RENDER per frame, and crop a square tile
    around each into ``work/objects/<id>.png``; reused if done."""
    import bpy
    from PIL import Image

    out = work / "objects"
    ids = sorted(reg.objects, key=lambda o: (max(reg.object(o).size_m), o))
    if all((out / f"{o}.png").exists() for o in ids):
        return out
    out.mkdir(parents=True, exist_ok=True)
    device = select_device("auto")
    for g in range(0, len(ids), OBJECTS_PER_RENDER):
        group = ids[g:g + OBJECTS_PER_RENDER]
        if all((out / f"{o}.png").exists() for o in group):
            continue
        scene = reset_scene()
        configure_cycles(scene, preset, seed=g, device=device)
        beauty_mode(scene, preset, device)
        build_studio(scene)
        spacing = 1.35 * max(max(reg.object(o).size_m) for o in group)
        xs = (np.arange(len(group)) - (len(group) - 1) / 2) * spacing
        for x, oid in zip(xs, group):
            ob = build_object(reg.object(oid), f"{oid}_gallery")
            ob.location = (float(x), 0.0, reg.object(oid).size_m[2] / 2)
        W, H = preset.resolution
        half_fov = math.atan(18.0 / 35.0)
        target = np.array([0.0, 0.0, max(reg.object(o).size_m[2] for o in group) / 2])
        distance = (len(group) * spacing / 2) / math.tan(half_fov) * 1.02
        R, t = cm.camera_pose(target, 270.0, 10.0, distance)
        from mathutils import Matrix

        cam = bpy.data.objects.new("cam", bpy.data.cameras.new("cam"))
        cam.data.lens, cam.data.sensor_width, cam.data.sensor_fit = 35.0, 36.0, "HORIZONTAL"
        cam.matrix_world = Matrix(cm.pose_matrix(R, t).tolist())
        scene.collection.objects.link(cam)
        scene.camera = cam
        with tempfile.TemporaryDirectory() as tmp:
            scene.render.filepath = str(Path(tmp) / "group.png")
            bpy.ops.render.render(write_still=True)
            frame = Image.open(Path(tmp) / "group.png").convert("RGB")
        K = cm.intrinsics(35.0, 36.0, W, H)
        half = int(W / len(group) / 2)
        for x, oid in zip(xs, group):
            uv, _ = cm.project(np.array([x, 0.0, target[2]]), K, R, t)
            u, v = int(round(uv[0])), int(round(uv[1]))
            v = min(max(v, half), H - half)
            frame.crop((u - half, v - half, u + half, v + half)).save(out / f"{oid}.png")
        log.info("objects %s rendered", ", ".join(group))
    return out


def objects_sheet_bytes(reg, tiles_dir: Path, preset) -> bytes:
    from PIL import Image

    ids = sorted(reg.objects)
    size = 300
    tiles = [(reg.object(o).name, np.asarray(Image.open(tiles_dir / f"{o}.png").convert("RGB").resize((size, size))),
              reg.object(o).partition != "train") for o in ids]
    W, H = preset.resolution
    sheet = objects_sheet(tiles, cols=6, title=f"The {len(ids)} objects at the {preset.name} preset ({W}x{H}, "
                                              f"{preset.samples} samples), {OBJECTS_PER_RENDER} per render; "
                                              "held-out objects framed in orange")
    return encode_under(sheet, MAX_BYTES)


# -- before / after ------------------------------------------------------------------------------


def before_after(before_png: Path, after_png: Path, label: str) -> bytes:
    from PIL import Image, ImageDraw

    imgs = []
    for p in (before_png, after_png):
        im = Image.open(p).convert("RGB")
        imgs.append(im.resize((THUMB_W, int(round(THUMB_W * im.height / im.width))), Image.Resampling.LANCZOS))
    h = max(i.height for i in imgs)
    sheet = Image.new("RGB", (2 * THUMB_W + 6, h + 26), (255, 255, 255))
    draw = ImageDraw.Draw(sheet)
    for k, (im, name) in enumerate(zip(imgs, ("before", "after"))):
        sheet.paste(im, (k * (THUMB_W + 6), 26))
        draw.text((k * (THUMB_W + 6) + 2, 4), f"{label}: {name}", fill=(0, 0, 0), font=font(16))
    return encode_under(sheet, 200_000)


def objects_before_after(reg, before_sheet: Path, tiles_dir: Path, preview_tile: int = 256) -> bytes:
    """Each object's old look (the first view of its tile in ``benchmarks/assets_preview.py``'s
    objects.png: ids in sorted order, four per row, two views of ``preview_tile`` px each) beside
    its new gallery tile."""
    from PIL import Image

    old = Image.open(before_sheet).convert("RGB")
    tiles = []
    for k, oid in enumerate(sorted(reg.objects)):
        r, c = divmod(k, 4)
        before = old.crop((c * 2 * preview_tile, r * preview_tile, c * 2 * preview_tile + preview_tile,
                           (r + 1) * preview_tile)).resize((200, 200))
        after = Image.open(tiles_dir / f"{oid}.png").convert("RGB").resize((200, 200))
        tiles.append((f"{reg.object(oid).name}: before", np.asarray(before), False))
        tiles.append(("after", np.asarray(after), reg.object(oid).partition != "train"))
    return encode_under(objects_sheet(tiles, cols=8, title="Objects before (left, preview light) and after (right)"),
                        MAX_BYTES)


# -- README ----------------------------------------------------------------------------------------


def readme(by_task: dict, by_scene: dict, infos: dict, befores: list[str]) -> str:
    lines = ["# Gallery", "",
             "Every sheet is one eval example rendered at the `paper` preset (1280x704, 32 samples), a "
             "different example for each sheet. Columns are event frames found from the simulated trajectory "
             "and contacts (release, first new contact, rebound apex, rest). Rows: the clean RGB frame; the "
             "same frame with the actor mask outlines and a few ground-truth point tracks (hollow circle: "
             "visible, cross: occluded, with a short trail); the disparity. Regenerate with "
             "`python scripts/make_gallery.py`: it renders the examples whose sheets are missing here or whose "
             "camera the search now places differently (5.5-7.5 min each on a 2-core CPU; interrupted runs "
             "resume), and `--fresh` renders all 17 (about two hours). `examples.json` records each sheet's "
             "events and camera. A sheet of every frame of any rendered example comes from `rigidbench show ID`.",
             "", "[All 24 objects](objects.jpg) at the paper preset, held-out ones marked.", "",
             "## One example per task", "", "| task | example | scene | frames | sheet |", "|---|---|---|---|---|"]

    def frames_of(row):
        return ", ".join(f"{f} {label}" for f, label in infos[row.sample_id]["events"])

    for task, row in sorted(by_task.items()):
        lines.append(f"| {task} | {row.sample_id} | {row.scene} | {frames_of(row)} | [task_{task}.jpg](task_{task}.jpg) |")
    lines += ["", "## One example per scene", "", "| scene | example | task | frames | sheet |", "|---|---|---|---|---|"]
    for scene, row in sorted(by_scene.items()):
        lines.append(f"| {scene} | {row.sample_id} | {row.task} | {frames_of(row)} | "
                     f"[scene_{scene}.jpg](scene_{scene}.jpg) |")
    if befores:
        lines += ["", "## Before and after", "",
                  "First frames of the same examples from the previous scenes and objects (left) and now (right); "
                  "see `before_after/`.", ""]
        lines += [f"![{b}](before_after/{b}.jpg)" for b in befores]
    lines += ["", "![objects](objects.jpg)", "", *[f"![{t}](task_{t}.jpg)" for t in sorted(by_task)], ""]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--work", type=Path, default=Path(tempfile.gettempdir()) / "rigidbench_gallery",
                        help="scratch directory for the per-example renders (reused between runs)")
    parser.add_argument("--quality", default="paper")
    parser.add_argument("--out", type=Path, default=OUT_DIR)
    parser.add_argument("--only", default="",
                        help="comma-separated example ids and/or 'objects': consider only these now")
    parser.add_argument("--fresh", action="store_true",
                        help="render the examples (with --only: those given) even where their sheets in --out are "
                             "current: after a change to scenes, objects or light, which the camera check misses")
    parser.add_argument("--render-only", action="store_true", help="render into --work, write no sheets")
    parser.add_argument("--partial", action="store_true",
                        help="write the sheets of the examples rendered so far (the README lists the missing ones)")
    parser.add_argument("--before-data", type=Path, help="split directory of bundles from an older checkout")
    parser.add_argument("--before-objects", type=Path, help="objects PNG (benchmarks/assets_preview.py) from it")
    args = parser.parse_args(argv)
    if args.before_data is not None and not args.before_data.is_dir():
        parser.error(f"--before-data {args.before_data}: not a directory of bundles")
    if args.before_objects is not None and not args.before_objects.is_file():
        parser.error(f"--before-objects {args.before_objects}: no such file")
    logging.basicConfig(level=logging.INFO, format="%(message)s")

    reg = registry()
    preset = reg.preset(args.quality)
    rows = list(manifest.rows("eval", reg))
    by_task, by_scene = pick_examples(rows, sorted(reg.tasks), sorted(reg.scenes))
    chosen = sorted({r.sample_id: r for r in [*by_task.values(), *by_scene.values()]}.values(),
                    key=lambda r: r.sample_id)
    prefixes = {r.sample_id: [] for r in chosen}
    for prefix, picks in (("task", by_task), ("scene", by_scene)):
        for key, row in picks.items():
            prefixes[row.sample_id].append(f"{prefix}_{key}")
    index_path = args.out / "examples.json"
    index = read_index(index_path)
    only = {s for s in args.only.split(",") if s}
    unknown = sorted(only - set(prefixes) - {"objects"})
    if unknown:
        parser.error(f"--only {','.join(unknown)}: not a gallery example; the gallery's examples are "
                     f"{', '.join(sorted(prefixes))} (and 'objects')")
    args.work.mkdir(parents=True, exist_ok=True)
    failed: list[str] = []
    current: dict[str, bool] = {}

    def is_current(row) -> bool:  # the committed sheets need no render (camera search once per example)
        if args.fresh and (not only or row.sample_id in only):
            return False  # --fresh renders the examples it is given (all without --only)
        if row.sample_id not in current:
            current[row.sample_id] = committed_is_current(row, reg, preset, args.out, index, prefixes[row.sample_id])
        return current[row.sample_id]

    if "objects" in only or (not only and (args.fresh or not (args.out / "objects.jpg").exists())):
        render_objects(reg, preset, args.work)  # otherwise the committed objects sheet stays
    for row in chosen:
        if only and row.sample_id not in only:
            continue
        if not (args.work / row.sample_id / "info.json").exists() and is_current(row):
            log.info("example %s: its sheets in %s are current; kept", row.sample_id, args.out)
            continue
        log.info("example %s (%s, %s)", row.sample_id, row.task, row.scene)
        try:
            render_example_events(row, reg, preset, args.work)
        except EXAMPLE_ERRORS as exc:  # an example that cannot be rendered: report it, go on; a bug stops the run
            log.error("example %s failed: %s", row.sample_id, exc)
            failed.append(row.sample_id)
    if failed:
        log.error("%d example(s) could not be rendered: %s (the reasons are above)", len(failed), " ".join(failed))
    if args.render_only:
        return 1 if failed else 0
    rendered = {r.sample_id for r in chosen if (args.work / r.sample_id / "info.json").exists()}
    kept = [r.sample_id for r in chosen if r.sample_id not in rendered and is_current(r)]
    missing = [r.sample_id for r in chosen if r.sample_id not in rendered and r.sample_id not in kept]
    if missing and not args.partial:
        log.error("not rendered yet: %s; rerun without --only (or pass --partial)", " ".join(missing))
        return 1
    if missing:
        log.warning("writing the sheets that are rendered; missing: %s", " ".join(missing))
        by_task = {k: r for k, r in by_task.items() if r.sample_id not in missing}
        by_scene = {k: r for k, r in by_scene.items() if r.sample_id not in missing}
    args.out.mkdir(parents=True, exist_ok=True)
    for stale in [*args.out.glob("task_*.png"), *args.out.glob("scene_*.png")]:
        stale.unlink()
    infos = {sid: index[sid] for sid in kept}
    for prefix, picks in (("task", by_task), ("scene", by_scene)):
        for key, row in sorted(picks.items()):
            if row.sample_id in kept:
                continue
            data, infos[row.sample_id] = example_sheet_bytes(args.work / row.sample_id)
            (args.out / f"{prefix}_{key}.jpg").write_bytes(data)
            log.info("wrote %s (%d KB)", args.out / f"{prefix}_{key}.jpg", len(data) // 1024)
    if (args.work / "objects").is_dir():
        (args.out / "objects.jpg").write_bytes(objects_sheet_bytes(reg, args.work / "objects", preset))
    elif not (args.out / "objects.jpg").exists():
        log.warning("no objects sheet: render it with --only objects")
    if args.before_data:
        (args.out / "before_after").mkdir(exist_ok=True)
        for scene, row in sorted(by_scene.items()):
            old = args.before_data / row.sample_id / "frames" / "00000.png"
            new = args.work / row.sample_id / "frames" / "00000.png"
            if not old.is_file():
                log.warning("scene %s: no before/after thumbnail, %s has no first frame", scene, old.parent.parent)
            elif row.sample_id not in rendered or not new.is_file():
                log.warning("scene %s: no before/after thumbnail, example %s was not rendered in %s (its first "
                            "frame is needed)", scene, row.sample_id, args.work)
            else:
                (args.out / "before_after" / f"{scene}.jpg").write_bytes(before_after(old, new, f"{scene} ({row.sample_id})"))
    if args.before_objects and not (args.work / "objects").is_dir():
        log.warning("no objects before/after: the objects are not rendered in %s (add --only objects)", args.work)
    elif args.before_objects:
        (args.out / "before_after").mkdir(exist_ok=True)
        data = objects_before_after(reg, args.before_objects, args.work / "objects")
        (args.out / "before_after" / "objects.jpg").write_bytes(data)
    befores = sorted(p.stem for p in (args.out / "before_after").glob("*.jpg") if p.stem != "objects")
    if (args.out / "before_after" / "objects.jpg").exists():
        befores.append("objects")
    jsonio.write_json(index_path, {sid: {k: infos[sid][k] for k in INDEX_KEYS if k in infos[sid]}
                                   for sid in sorted(infos)})
    text = readme(by_task, by_scene, infos, befores)
    if missing:
        text += (f"\nNot rendered yet (this gallery was written with `--partial`): examples {', '.join(missing)}; "
                 "`python scripts/make_gallery.py` renders them and rewrites this page.\n")
    (args.out / "README.md").write_text(text)
    return 1 if failed else 0


if __name__ == "__main__":
    try:
        sys.exit(main())
    except RigidBenchError as exc:  # unusable input: one line naming it (as the CLI does), status 2
        print(f"make_gallery: {exc}", file=sys.stderr)
        sys.exit(2)
