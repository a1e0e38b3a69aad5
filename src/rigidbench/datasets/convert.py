"""Import the published evaluation set into bundles every RigidBench command reads.

The authors' archive has its own layout (a data root holding ``manifest.json`` + ``samples/<id>/``
or ``eval/<id>/``, perhaps under a top folder; per sample ``frames/`` and/or ``video.mp4``,
``masks.npz`` with ``object_names``, ``depth.npz`` with 1e10 where nothing is hit,
``trajectories.npz`` keyed ``<actor>_positions``/``_rotations``, ``contacts.json`` as a list,
``metadata.json`` without ``sample_id``). ``import_published`` turns each sample into
``DATA/eval/<id>/`` in our bundle layout (``groundtruth.bundle``):

- metadata renamed (``sample_id``, ``task``, ``partition`` with underscores, ``fps``, ``resolution``),
  actors with roles and the physics of our object YAMLs by ``object_id``, the camera as K and both
  pose matrices (the principal point stays where the published intrinsics put it, (W/2, H/2), so
  every measurement unprojects as the published evaluator did), and ``source`` keeping the dataset's
  name, version, MD5 and the original metadata;
- masks with names and roles; depth with no-hit (1e10, or 0 for a missing pass frame) as +inf;
  trajectories stacked (N,T,.) with velocities recomputed in SI units; contacts in our schema;
- ground-truth point tracks computed by the published evaluator's rule (``TRACK_RULES["published"]``)
  from the published depth, masks and poses;
- frames: every published PNG is decoded in full (a damaged one fails its sample, naming the file); an
  8-bit RGB or RGBA PNG is hard-linked as it is (copied across file systems), and readers drop the alpha
  channel as the released evaluator did (``Image.convert("RGB")``); any other PNG is converted to 8-bit
  RGB; decoded from ``video.mp4`` when ``frames/`` is absent; ``video.mp4`` linked (or copied) when it is
  H.264 with every frame, encoded from the frames otherwise. So the import writes its own depth, masks,
  tracks and small files, nothing of the frames and video, and the extracted source may be deleted after
  it (nothing in a bundle points into it).

The import itself is a stage on the stage driver (``stages.import_set``): it resumes, skips what is
unchanged and reports one damaged sample without stopping the others. The scene spec
cannot be rebuilt from the archive: imported bundles have none, and the commands that need one
(re-simulated predictors, ``validate-metrics --with-rendered``) say so.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import shutil
from pathlib import Path
from typing import Any, Iterable

import numpy as np

from .. import __version__
from ..errors import BundleError, UserError
from ..groundtruth import bundle as B
from ..groundtruth import camera_model as cm
from ..groundtruth.layout import is_published_metadata
from ..groundtruth.tracks import DEPTH_TOLERANCE, POINTS_PER_ACTOR, TRACK_RULES, ground_truth_tracks
from ..groundtruth.trajectory import Trajectory
from ..hashing import file_digest
from ..jsonio import write_json
from ..rotations import quat_to_matrix
from ..video import VideoError, probe_video, read_video, write_video

log = logging.getLogger(__name__)

#: depth values at or above this are "nothing was hit" in the published depth.npz (Blender writes 1e10)
NO_HIT_DEPTH = 1e9
PUBLISHED_PIXEL_CONVENTION = ("published set: integer pixel indices with the principal point at (W/2, H/2), as "
                              "the released evaluator unprojects (half a pixel from Blender's pixel centres)")
TOP_FOLDERS = ("rigidbench", "rigidbench-eval-v1.1", "rigidbench-eval-v1")
SOURCE_FILES = ("metadata.json", "masks.npz", "depth.npz", "trajectories.npz", "contacts.json", "prompt.txt",
                "video.mp4")
DIGEST_VERSION = 2  # bump when the conversion changes, so a rerun re-imports every sample


# -- finding the published data root ------------------------------------------------------------


def _holds_samples(folder: Path) -> bool:
    return folder.is_dir() and any(p.is_dir() and not p.name.startswith(".") for p in folder.iterdir())


def is_published_root(folder: Path) -> bool:
    """A published data root: ``manifest.json`` with ``samples/``, or an ``eval/`` of published samples."""
    folder = Path(folder)
    if (folder / "manifest.json").is_file() and _holds_samples(folder / "samples"):
        return True
    eval_dir = folder / "eval"
    return _holds_samples(eval_dir) and any(is_published_sample(p) for p in sorted(eval_dir.iterdir())[:3])


def is_published_sample(folder: Path) -> bool:
    """A sample folder in the published layout (its metadata has ``task_type`` and no ``sample_id``)."""
    try:
        return is_published_metadata(json.loads((Path(folder) / "metadata.json").read_text()))
    except (OSError, ValueError):
        return False


def find_published_root(src: str | Path) -> Path:
    """The published data root at or below ``src`` (the folder itself, a known top folder, or any
    folder up to three levels down holding ``manifest.json`` or ``eval/``); UserError otherwise."""
    src = Path(src)
    if not src.is_dir():
        raise UserError(f"{src}: no such folder; pass the extracted archive's folder or the .tar.gz file")
    candidates = [src] + [src / name for name in TOP_FOLDERS]
    if src.name in ("samples", "eval"):
        candidates.insert(0, src.parent)
    level = [src]
    for _ in range(3):
        level = sorted(d for parent in level for d in parent.iterdir() if d.is_dir() and not d.name.startswith("."))
        candidates += level
    for folder in candidates:
        if is_published_root(folder):
            return folder
    raise UserError(f"{src}: no published RigidBench evaluation set here (looked for manifest.json with samples/, "
                    "or eval/<id>/ folders whose metadata.json has task_type); is the extraction complete?")


def published_samples(root: Path) -> list[tuple[str, Path, dict]]:
    """(id, folder, manifest row or {}) of every sample folder of a published root, sorted by id."""
    rows: dict[str, dict] = {}
    manifest = root / "manifest.json"
    if manifest.is_file():
        try:
            doc = json.loads(manifest.read_text())
        except (OSError, ValueError) as exc:
            raise BundleError(f"{manifest}: cannot be read ({exc}); extract the archive again") from None
        if not isinstance(doc, list):
            raise BundleError(f"{manifest}: expected a list of rows; extract the archive again")
        rows = {str(r["sample_id"]): r for r in doc if isinstance(r, dict) and "sample_id" in r}
    folder = root / "samples" if (root / "samples").is_dir() else root / "eval"
    return [(p.name, p, rows.get(p.name, {})) for p in sorted(folder.iterdir())
            if p.is_dir() and not p.name.startswith(".")]


# -- reading one published sample ---------------------------------------------------------------


def _read_json(path: Path) -> Any:
    try:
        return json.loads(path.read_text())
    except FileNotFoundError:
        raise BundleError(f"{path}: missing from the published sample; extract the archive again") from None
    except (OSError, ValueError) as exc:
        raise BundleError(f"{path}: cannot be read ({exc}); extract the archive again") from None


def _read_npz(path: Path, keys: Iterable[str] | None = None) -> dict[str, np.ndarray]:
    import zipfile

    try:
        with np.load(path, allow_pickle=False) as z:
            wanted = z.files if keys is None else list(keys)
            missing = [k for k in wanted if k not in z.files]
            if missing:
                raise BundleError(f"{path}: no array {', '.join(missing)} (has {', '.join(z.files)}); is this the "
                                  "published set?")
            return {k: z[k] for k in (z.files if keys is None else wanted)}
    except FileNotFoundError:
        raise BundleError(f"{path}: missing from the published sample; extract the archive again") from None
    except (OSError, ValueError, EOFError, zipfile.BadZipFile) as exc:
        raise BundleError(f"{path}: damaged ({exc}); extract the archive again") from None


def source_digest(folder: Path) -> str:
    """A sha256 of a published sample's files, names and content (every frame's too): it changes whenever
    one of them does, whatever its size. About 0.2 s for a paper-size sample of 96 MB on one core (the
    file cache warm; benchmarks/published_import.py)."""
    h = hashlib.sha256(f"rigidbench-import-{DIGEST_VERSION}".encode())
    frames = folder / B.FRAMES_DIR
    for p in [folder / name for name in SOURCE_FILES] + (sorted(frames.iterdir()) if frames.is_dir() else []):
        h.update(f"{p.relative_to(folder).as_posix()}:{file_digest(p) if p.is_file() else 'absent'};".encode())
    return h.hexdigest()


def _camera(meta: dict, where: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray, int, int]:
    """K (3,3), R_c (3,3), t_c (3,), W, H from the published camera block."""
    try:
        intr, extr = meta["camera"]["intrinsics"], meta["camera"]["extrinsics"]
        K = np.array([[float(intr["fx"]), 0.0, float(intr["cx"])], [0.0, float(intr["fy"]), float(intr["cy"])],
                      [0.0, 0.0, 1.0]])
        W, H = int(intr["width"]), int(intr["height"])
        t_c = np.array(extr["location"], dtype=np.float64)
        q = np.array(extr["rotation"], dtype=np.float64)
    except (KeyError, TypeError, ValueError) as exc:
        raise BundleError(f"{where}: camera.intrinsics/extrinsics incomplete ({exc!r}); is this the published "
                          "set?") from None
    if t_c.shape != (3,) or q.shape != (4,) or not np.isfinite(q).all() or np.linalg.norm(q) < 0.5:
        raise BundleError(f"{where}: camera extrinsics malformed (location {t_c.tolist()}, rotation {q.tolist()})")
    return K, quat_to_matrix(q), t_c, W, H


def _actor_physics(object_id: str | None, registry) -> dict[str, Any]:
    if registry is None or not object_id or object_id not in registry.objects:
        return {"mass_kg": None, "friction": None, "restitution": None, "size_m": None}
    obj = registry.objects[object_id]
    return {"mass_kg": obj.physics.mass_kg, "friction": obj.physics.friction,
            "restitution": obj.physics.restitution, "size_m": list(obj.size_m)}


#: PNG pixel layouts linked as they are (8 bits a channel; readers drop the alpha, as the released evaluator)
LINKED_LAYOUTS = ("RGB", "RGBA")


def _frames(src: Path, dst: Path, T: int, W: int, H: int) -> None:
    """Fill dst/frames with T PNGs, each published one decoded in full first: an 8-bit RGB or RGBA PNG
    linked, anything else converted to 8-bit RGB; decoded from video.mp4 when there is no frames/ folder."""
    from PIL import Image, UnidentifiedImageError

    out = dst / B.FRAMES_DIR
    out.mkdir()
    src_frames = src / B.FRAMES_DIR
    names = [B.frame_name(k) for k in range(T)]
    if src_frames.is_dir() and any(src_frames.iterdir()):
        have = sorted(p.name for p in src_frames.glob("*.png"))
        if have[:T] != names:
            raise BundleError(f"{src_frames}: expected {T} frames {names[0]}..{names[-1]}, found {len(have)}; "
                              "extract the archive again")
        for name in names:
            path = src_frames / name
            try:
                with Image.open(path) as im:
                    layout = im.tile[0][3] if im.tile else None  # (codec, box, offset, raw mode); load() empties it
                    if im.size != (W, H):
                        raise BundleError(f"{path}: {im.size[0]}x{im.size[1]}, expected {W}x{H}")
                    im.load()  # every pixel: a truncated or corrupt file fails here, not in a later command
                    linked = im.format == "PNG" and im.mode in LINKED_LAYOUTS and layout == im.mode
                    rgb = None if linked else np.asarray(im.convert("RGB"))
            except BundleError:
                raise
            except (OSError, UnidentifiedImageError, SyntaxError, ValueError) as exc:
                raise BundleError(f"{path}: cannot be decoded ({exc}); the file is damaged: extract the archive "
                                  "again") from None
            if rgb is None:
                _link(path, out / name)
            else:
                Image.fromarray(rgb).save(out / name)
        return
    video = src / B.VIDEO_FILE
    if not video.is_file():
        raise BundleError(f"{src}: neither frames/ nor video.mp4; extract the archive again")
    frames = read_video(video).frames
    if frames.shape[0] < T or frames.shape[1:3] != (H, W):
        raise BundleError(f"{video}: {frames.shape[0]} frames of {frames.shape[2]}x{frames.shape[1]}, expected {T} "
                          f"of {W}x{H}")
    frames = frames[:T]
    for name, frame in zip(names, frames):
        Image.fromarray(frame).save(out / name)


def _link(src: Path, dst: Path) -> None:
    """Hard link (no extra disk); a copy where the file system cannot link (another device, no hard links), so
    that a bundle never depends on the source folder staying."""
    try:
        os.link(src, dst)
    except OSError:
        shutil.copyfile(src, dst)


def _video(src: Path, dst: Path, T: int, W: int, H: int, fps: float) -> str:
    """dst/video.mp4: the published H.264 file linked when it has the T frames, else encoded from dst/frames."""
    from PIL import Image

    published = src / B.VIDEO_FILE
    if published.is_file():
        try:
            info = probe_video(published)
            if info.codec == "h264" and (info.width, info.height) == (W, H) and len(info.times_s) == T:
                _link(published, dst / B.VIDEO_FILE)
                return "linked"
        except VideoError:
            pass
    frames = np.stack([np.asarray(Image.open(dst / B.FRAMES_DIR / B.frame_name(k)).convert("RGB")) for k in range(T)])
    if W % 2 or H % 2:
        raise BundleError(f"{src}: {W}x{H} frames cannot be encoded as H.264 4:2:0 (odd size)")
    write_video(dst / B.VIDEO_FILE, frames, fps=fps)
    return "encoded"


def _contacts(raw: Any, names: list[str], T: int, where: Path) -> dict:
    if not isinstance(raw, list):
        raise BundleError(f"{where}: expected a list of contacts; is this the published set?")
    out = []
    for c in raw:
        try:
            frame, a, b = int(c["frame"]), str(c["obj_a"]), str(c["obj_b"])
            pts = [tuple(float(v) for v in p["point"]) for p in c.get("contacts", [])][:5]
            normals = [tuple(float(v) for v in p["normal"]) for p in c.get("contacts", [])][:5]
        except (KeyError, TypeError, ValueError) as exc:
            raise BundleError(f"{where}: malformed contact {c!r} ({exc!r})") from None
        if 0 <= frame < T and a in names:
            out.append({"frame": frame, "a": a, "b": b, "points_m": [list(p) for p in pts],
                        "normals": [list(n) for n in normals], "distances_m": [0.0] * len(pts)})
    return {"frames": T, "tolerance_m": None, "contacts": out,
            "method": "published set: BVH face overlap of the two meshes per frame (normals of body b's faces)"}


def _trajectory(path: Path, names: list[str], roles: list[str], fps: float, T: int) -> Trajectory:
    """The actors' world states of a published sample's trajectories.npz (``<actor>_positions``/``_rotations``
    for every actor, T frames each), quaternions normalised."""
    traj_npz = _read_npz(path)
    try:
        positions = np.stack([traj_npz[f"{n}_positions"] for n in names]).astype(np.float64)
        quats = np.stack([traj_npz[f"{n}_rotations"] for n in names]).astype(np.float64)
    except KeyError as exc:
        raise BundleError(f"{path}: no {exc.args[0]}; is this the published set?") from None
    N = len(names)
    if positions.shape != (N, T, 3) or quats.shape != (N, T, 4):
        raise BundleError(f"{path}: positions {positions.shape} / rotations {quats.shape}, expected ({N},{T},3) / "
                          f"({N},{T},4)")
    quats /= np.linalg.norm(quats, axis=-1, keepdims=True)
    return Trajectory(names=tuple(names), roles=tuple(roles), fps=fps, positions_m=positions, quat_wxyz=quats)


def convert_sample(src: Path, dst: Path, sample_id: str, row: dict, *, registry=None,
                   dataset: dict | None = None, digest: str | None = None) -> dict:
    """Write the bundle of one published sample ``src`` into the empty folder ``dst``; returns its metadata.
    ``digest``: its ``source_digest`` when the caller has it already."""
    meta = _read_json(src / "metadata.json")
    if not isinstance(meta, dict) or "task_type" not in meta:
        raise BundleError(f"{src / 'metadata.json'}: no task_type; is this a sample of the published set?")
    merged = {**row, **meta}
    masks_npz = _read_npz(src / "masks.npz", ("masks", "object_names"))
    masks = masks_npz["masks"].astype(bool)
    names = [str(n) for n in masks_npz["object_names"]]
    if masks.ndim != 4 or masks.shape[1] != len(names):
        raise BundleError(f"{src / 'masks.npz'}: masks {masks.shape} do not match {len(names)} object names")
    T, _, H, W = masks.shape
    K, R_c, t_c, W_meta, H_meta = _camera(meta, src / "metadata.json")
    if (W_meta, H_meta) != (W, H):
        raise BundleError(f"{src}: camera says {W_meta}x{H_meta}, masks are {W}x{H}")
    actors = meta.get("actors") or {}
    roles = [str((actors.get(n) or {}).get("role", "")) for n in names]
    if any(r not in ("active", "passive") for r in roles) or "active" not in roles:
        raise BundleError(f"{src / 'metadata.json'}: actors {names} have roles {roles}; expected active/passive with "
                          "at least one active")
    render = meta.get("render") or {}
    fps = float(render.get("fps", 24))
    depth_raw = _read_npz(src / "depth.npz", ("depth",))["depth"]
    if depth_raw.shape != (T, H, W):
        raise BundleError(f"{src / 'depth.npz'}: depth {depth_raw.shape}, expected ({T}, {H}, {W})")
    traj = _trajectory(src / "trajectories.npz", names, roles, fps, T)
    rule = TRACK_RULES["published"]
    tracks = ground_truth_tracks(masks, depth_raw.astype(np.float64), K, R_c, t_c, quat_to_matrix(traj.quat_wxyz),
                                 traj.positions_m, np.array([r == "active" for r in roles]), seed=int(meta.get("seed", 0)),
                                 rule=rule)
    prompt_path = src / "prompt.txt"
    prompt = (prompt_path.read_text().strip() if prompt_path.is_file() else str(meta.get("prompt", "")).strip())
    if not prompt:
        raise BundleError(f"{src}: no prompt (prompt.txt or metadata prompt)")

    _frames(src, dst, T, W, H)
    video = _video(src, dst, T, W, H, fps)
    depth = depth_raw.astype(np.float32, copy=True)
    missing_depth = [int(t) for t in np.nonzero((depth_raw <= 0).all(axis=(1, 2)))[0]]
    depth[(depth_raw >= NO_HIT_DEPTH) | (depth_raw <= 0) | ~np.isfinite(depth_raw)] = np.inf
    B.write_masks(dst / B.MASKS_FILE, masks, tuple(names), tuple(roles))
    B.write_depth(dst / B.DEPTH_FILE, depth)
    traj.save(dst / B.TRAJECTORIES_FILE)
    contacts_path = src / "contacts.json"
    contacts = _contacts(_read_json(contacts_path), names, T, contacts_path) if contacts_path.is_file() else \
        {"frames": T, "tolerance_m": None, "contacts": [], "method": "not in the published sample"}
    write_json(dst / B.CONTACTS_FILE, contacts, allow_nan=False)
    tracks.save(dst / B.TRACKS_FILE)
    (dst / B.PROMPT_FILE).write_text(prompt + "\n")
    actor_rows = [{"name": n, "asset": (actors.get(n) or {}).get("object_id"), "role": r, "pass_index": k + 1,
                   **_actor_physics((actors.get(n) or {}).get("object_id"), registry)}
                  for k, (n, r) in enumerate(zip(names, roles))]
    partition = str(merged.get("split", "")).replace("-", "_")
    out = {
        "bundle_version": B.BUNDLE_VERSION, "sample_id": sample_id, "split": "eval", "task": str(meta["task_type"]),
        "scene": merged.get("scene_id"), "surface": merged.get("surface", merged.get("surface_name")),
        "seed": merged.get("seed"), "partition": partition, "prompt": prompt,
        "task_rotation_deg": meta.get("task_angle"), "camera_azimuth_deg": meta.get("camera_azimuth"),
        "footprint_m": meta.get("footprint"), "actors": actor_rows, "actor_names": names, "roles": roles,
        "active_indices": [k for k, r in enumerate(roles) if r == "active"],
        "camera": {"intrinsics_K": K.tolist(), "camera_to_world_blender": cm.pose_matrix(R_c, t_c).tolist(),
                   "world_to_camera_cv": cm.world_to_camera_cv(R_c, t_c).tolist(),
                   "pixel_convention": PUBLISHED_PIXEL_CONVENTION},
        "resolution": [W, H], "fps": fps, "frames": T, "simulated_frames": int(meta.get("frames", T)),
        "depth": B.DEPTH_CONVENTION + " (imported: 1e10 and 0 became +inf)", "depth_missing_frames": missing_depth,
        "preset": None, "render": {"published": render, "video": video},
        "software": {"rigidbench_import": __version__},
        "tracks": {"points_per_actor": POINTS_PER_ACTOR, "depth_tolerance": DEPTH_TOLERANCE, **rule.facts(),
                   "sampled": [int(n) for n in tracks.points_per_actor]},
        "source": {**(dataset or {}), "sample_digest": digest or source_digest(src), "original_metadata": meta,
                   "manifest_row": row or None},
    }
    write_json(dst / B.METADATA_FILE, out, allow_nan=False)
    return out


__all__ = ["convert_sample", "find_published_root", "is_published_root", "is_published_sample", "published_samples",
           "source_digest", "DIGEST_VERSION", "NO_HIT_DEPTH", "PUBLISHED_PIXEL_CONVENTION"]
