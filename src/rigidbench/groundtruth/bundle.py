"""The sample bundle: one directory per example (paper, table "Per-sample artifact bundle").

::

    <id>/frames/00000.png ...   T RGB frames, uint8 H x W x 3
    <id>/video.mp4              the frames as H.264 (yuv420p) at the clip's fps
    <id>/masks.npz              masks bool (T,N,H,W); names (N,) str; roles (N,) str ("active"/"passive")
    <id>/depth.npz              depth float32 (T,H,W) m, Cycles Z (along the optical axis), +inf = no surface
    <id>/trajectories.npz       ``Trajectory`` of the N actors over the T frames
    <id>/contacts.json          per-frame contacts (``save_contacts``), frames < T
    <id>/tracks.npz             ground-truth point tracks (``tracks.Tracks``)
    <id>/metadata.json          task, scene, seed, angles, actors, camera K and extrinsics, render facts
    <id>/prompt.txt             the instantiated task prompt
    <id>/scene_spec.json        the resolved SceneSpec (task rotation and camera filled)

The N actors are the task actors in spec order (active objects and passive task geometry such as
ramps); mask k is the object-index pass equal to k + 1. A bundle is written into a temporary
sibling directory and renamed into place when complete (``commit``), so an existing directory
is a finished bundle.
"""

from __future__ import annotations

import functools
import json
import math
import os
import shutil
from pathlib import Path
from typing import Any

import numpy as np

from .. import jsonio
from ..errors import BundleError
from ..spec.types import SceneSpec
from ..video import VideoError, probe_video
from . import camera_model as cm
from .layout import SAMPLE_WHAT, PublishedLayoutError, check_not_published_layout, is_published_metadata, \
    published_layout_message
from .trajectory import Contact, Trajectory, load_contacts
from .tracks import Tracks

BUNDLE_VERSION = 1
FRAMES_DIR = "frames"
VIDEO_FILE = "video.mp4"
MASKS_FILE = "masks.npz"
DEPTH_FILE = "depth.npz"
TRAJECTORIES_FILE = "trajectories.npz"
CONTACTS_FILE = "contacts.json"
TRACKS_FILE = "tracks.npz"
METADATA_FILE = "metadata.json"
PROMPT_FILE = "prompt.txt"
SPEC_FILE = "scene_spec.json"
BUNDLE_FILES = (VIDEO_FILE, MASKS_FILE, DEPTH_FILE, TRAJECTORIES_FILE, CONTACTS_FILE, TRACKS_FILE, METADATA_FILE,
                PROMPT_FILE, SPEC_FILE)
PIXEL_CONVENTION = "pixel (x, y) = (column, row) with integer values at pixel centres; the image spans [-0.5, W-0.5]"
DEPTH_CONVENTION = "Cycles Z pass: metres along the camera's optical axis; +inf where no surface is hit"


def no_spec_message(sample_id: str) -> str:
    """Why a command that re-simulates cannot run on an imported bundle."""
    return (f"example {sample_id} was imported from the published set, which ships no scene spec, so it cannot be "
            "re-simulated; use a bundle rendered with `rigidbench render` for this")


def refuse_imported(bundle_dirs_: list[Path], what: str) -> None:
    """BundleError (one line, before any work) when ``what`` needs scene specs and a bundle was imported."""
    imported = [Path(d).name for d in bundle_dirs_ if _imported(Path(d)) and not (Path(d) / SPEC_FILE).is_file()]
    if imported:
        raise BundleError(f"{what}, which needs each example's scene spec; {len(imported)} of the selected examples "
                          f"(e.g. {imported[0]}) were imported from the published set, which ships none. Use bundles "
                          "rendered with `rigidbench render` for this")


def frame_name(k: int) -> str:
    """File name of frame ``k`` (0-based) inside ``frames/``."""
    return f"{k:05d}.png"


# -- writing -------------------------------------------------------------------------------------


def masks_from_index(index: np.ndarray, n_actors: int) -> np.ndarray:
    """index (T,H,W) int object-index pass (0 = no actor, k = actor k-1). Returns (T,N,H,W) bool."""
    ks = np.arange(1, n_actors + 1, dtype=index.dtype)
    return index[:, None, :, :] == ks[None, :, None, None]


def write_masks(path: Path, masks: np.ndarray, names: tuple[str, ...], roles: tuple[str, ...]) -> None:
    """masks (T,N,H,W) bool with N actor names and roles -> compressed npz."""
    np.savez_compressed(path, masks=np.asarray(masks, dtype=bool), names=np.array(names, dtype=str),
                        roles=np.array(roles, dtype=str))


def write_depth(path: Path, depth_m: np.ndarray) -> None:
    """depth_m (T,H,W) float32 Z pass -> compressed npz."""
    np.savez_compressed(path, depth=np.asarray(depth_m, dtype=np.float32))


def write_json(path: Path, data: Any) -> None:
    jsonio.write_json(path, data, allow_nan=False)


def slice_trajectory(trajectory: Trajectory, frames: int) -> Trajectory:
    """The first ``frames`` frames of a trajectory (velocities kept from the full clip)."""
    return Trajectory(names=trajectory.names, roles=trajectory.roles, fps=trajectory.fps,
                      positions_m=trajectory.positions_m[:, :frames], quat_wxyz=trajectory.quat_wxyz[:, :frames],
                      linear_velocity_m_s=trajectory.linear_velocity_m_s[:, :frames],
                      angular_velocity_rad_s=trajectory.angular_velocity_rad_s[:, :frames])


def camera_metadata(spec: SceneSpec, resolution: tuple[int, int]) -> dict[str, Any]:
    """Intrinsics and extrinsics of the spec's camera at ``resolution`` (W, H)."""
    cam = spec.camera
    if cam is None:
        raise BundleError(f"example {spec.sample_id}: the spec has no camera; run the camera search first")
    R, t = cm.camera_pose(cam.target_m, cam.azimuth_deg, cam.elevation_deg, cam.distance_m)
    K = cm.intrinsics(cam.lens_mm, cam.sensor_width_mm, *resolution)
    return {"intrinsics_K": K.tolist(), "camera_to_world_blender": cm.pose_matrix(R, t).tolist(),
            "world_to_camera_cv": cm.world_to_camera_cv(R, t).tolist(), "pixel_convention": PIXEL_CONVENTION,
            "lens_mm": cam.lens_mm, "sensor_width_mm": cam.sensor_width_mm, "sensor_fit": "HORIZONTAL"}


def make_metadata(spec: SceneSpec, *, resolution: tuple[int, int], frames: int, simulated_frames: int, fps: float,
                  render: dict[str, Any], software: dict[str, str], seconds: dict[str, float],
                  tracks: dict[str, Any]) -> dict[str, Any]:
    """metadata.json content for a rendered example (paper, table "Per-sample artifact bundle")."""
    cam = spec.camera
    assert cam is not None
    actors = [{"name": b.name, "asset": b.asset, "role": b.role, "pass_index": k + 1, "size_m": list(b.size_m),
               "mass_kg": b.physics.mass_kg, "friction": b.physics.friction, "restitution": b.physics.restitution}
              for k, b in enumerate(spec.bodies)]
    return {
        "bundle_version": BUNDLE_VERSION, "sample_id": spec.sample_id, "split": spec.split, "task": spec.task,
        "scene": spec.scene, "surface": spec.surface, "seed": spec.seed, "partition": spec.partition,
        "prompt": spec.prompt, "task_rotation_deg": spec.task_rotation_deg,
        "camera_azimuth_deg": cam.azimuth_deg, "camera_relative_azimuth_deg": cam.relative_azimuth_deg,
        "camera_elevation_deg": cam.elevation_deg, "camera_distance_m": cam.distance_m,
        "camera_target_m": list(cam.target_m), "camera_visibility": cam.visibility,
        "footprint_m": list(spec.footprint_m), "actors": actors,
        "actor_names": [b.name for b in spec.bodies], "roles": [b.role for b in spec.bodies],
        "active_indices": [k for k, b in enumerate(spec.bodies) if b.role == "active"],
        "camera": camera_metadata(spec, resolution), "resolution": list(resolution), "fps": fps, "frames": frames,
        "simulated_frames": simulated_frames, "depth": DEPTH_CONVENTION, "preset": spec.render_preset,
        "render": render, "software": software, "render_seconds": seconds, "tracks": tracks,
    }


def prepare_tmp(final_dir: Path) -> Path:
    """A fresh temporary sibling of ``final_dir`` (any leftover from a killed run is removed)."""
    final_dir = Path(final_dir)
    tmp = final_dir.with_name(f".{final_dir.name}.tmp")
    if tmp.exists():
        shutil.rmtree(tmp)
    tmp.mkdir(parents=True)
    return tmp


def commit(tmp_dir: Path, final_dir: Path) -> Path:
    """Rename a complete bundle into place (atomic on one file system); refuses to overwrite."""
    final_dir = Path(final_dir)
    if final_dir.exists():
        raise FileExistsError(f"{final_dir}: a bundle already exists; delete it to render this example again")
    os.replace(tmp_dir, final_dir)
    return final_dir


# -- reading -------------------------------------------------------------------------------------


def _load_npz(path: Path) -> dict[str, np.ndarray]:
    with np.load(path, allow_pickle=False) as z:
        return {k: z[k] for k in z.files}


class Sample:
    """Lazy reader over one bundle directory; every property loads its file on first use."""

    def __init__(self, path: str | Path):
        self.path = Path(path)
        if not (self.path / METADATA_FILE).is_file():
            raise BundleError(f"{self.path}: not a sample bundle (no {METADATA_FILE}); render it with "
                              "`rigidbench render`")
        if is_published_metadata(self.metadata):
            raise PublishedLayoutError(published_layout_message(self.path.parent, SAMPLE_WHAT))

    def __repr__(self) -> str:
        return f"Sample({str(self.path)!r})"

    @functools.cached_property
    def metadata(self) -> dict[str, Any]:
        return json.loads((self.path / METADATA_FILE).read_text())

    @property
    def sample_id(self) -> str:
        return str(self.metadata["sample_id"])

    @property
    def task(self) -> str:
        return str(self.metadata["task"])

    @property
    def partition(self) -> str:
        return str(self.metadata["partition"])

    @property
    def n_frames(self) -> int:
        return int(self.metadata["frames"])

    @property
    def fps(self) -> float:
        return float(self.metadata["fps"])

    @property
    def resolution(self) -> tuple[int, int]:
        """(W, H) pixels."""
        w, h = self.metadata["resolution"]
        return int(w), int(h)

    @property
    def frame_paths(self) -> list[Path]:
        return [self.path / FRAMES_DIR / frame_name(k) for k in range(self.n_frames)]

    @property
    def first_frame_path(self) -> Path:
        return self.path / FRAMES_DIR / frame_name(0)

    @property
    def video_path(self) -> Path:
        return self.path / VIDEO_FILE

    @functools.cached_property
    def frames(self) -> np.ndarray:
        """(T,H,W,3) uint8 RGB from the PNG frames."""
        from PIL import Image

        return np.stack([np.asarray(Image.open(p).convert("RGB")) for p in self.frame_paths])

    def frame(self, k: int) -> np.ndarray:
        """(H,W,3) uint8 RGB frame ``k``."""
        from PIL import Image

        return np.asarray(Image.open(self.frame_paths[k]).convert("RGB"))

    @functools.cached_property
    def _masks(self) -> dict[str, np.ndarray]:
        return _load_npz(self.path / MASKS_FILE)

    @property
    def masks(self) -> np.ndarray:
        """(T,N,H,W) bool, one mask per actor."""
        return self._masks["masks"]

    @property
    def actor_names(self) -> tuple[str, ...]:
        return tuple(str(s) for s in self._masks["names"])

    @property
    def roles(self) -> tuple[str, ...]:
        return tuple(str(s) for s in self._masks["roles"])

    @property
    def active_indices(self) -> np.ndarray:
        """(A,) int indices of the active actors into the N axis."""
        return np.array([k for k, r in enumerate(self.roles) if r == "active"], dtype=np.int64)

    @functools.cached_property
    def depth(self) -> np.ndarray:
        """(T,H,W) float32 Z depth in metres (+inf where nothing is hit)."""
        return _load_npz(self.path / DEPTH_FILE)["depth"]

    @functools.cached_property
    def trajectory(self) -> Trajectory:
        return Trajectory.load(self.path / TRAJECTORIES_FILE)

    @functools.cached_property
    def contacts(self) -> list[Contact]:
        return load_contacts(self.path / CONTACTS_FILE)

    @functools.cached_property
    def tracks(self) -> Tracks:
        """Ground-truth point tracks; also indexable by npz key (``tracks["visibility"]``)."""
        return Tracks.load(self.path / TRACKS_FILE)

    @property
    def track_active_index(self) -> np.ndarray:
        """(P,) int64 index of each track's actor among the active actors (into ``active_indices``)."""
        return np.searchsorted(self.active_indices, self.tracks.actor_index).astype(np.int64)

    @property
    def K(self) -> np.ndarray:
        """(3,3) camera intrinsics in pixels (integer coordinates at pixel centres)."""
        return np.array(self.metadata["camera"]["intrinsics_K"], dtype=np.float64)

    @property
    def camera_to_world(self) -> np.ndarray:
        """(4,4) Blender camera-to-world matrix (camera looks along its -z, +y up)."""
        return np.array(self.metadata["camera"]["camera_to_world_blender"], dtype=np.float64)

    @property
    def world_to_camera_cv(self) -> np.ndarray:
        """(4,4) world-to-camera matrix in the CV convention (+z forward, +y down)."""
        return np.array(self.metadata["camera"]["world_to_camera_cv"], dtype=np.float64)

    @property
    def camera_pose(self) -> tuple[np.ndarray, np.ndarray]:
        """(R_c (3,3), t_c (3,) m): Blender camera-to-world rotation and position."""
        m = self.camera_to_world
        return m[:3, :3], m[:3, 3]

    @functools.cached_property
    def prompt(self) -> str:
        return (self.path / PROMPT_FILE).read_text().strip()

    @property
    def imported(self) -> bool:
        """True for a bundle imported from a published set (``rigidbench import``): it has no scene spec."""
        return bool(self.metadata.get("source"))

    @functools.cached_property
    def spec(self) -> SceneSpec:
        if self.imported and not (self.path / SPEC_FILE).is_file():
            raise BundleError(no_spec_message(self.path.name))
        return SceneSpec.from_json((self.path / SPEC_FILE).read_text())


def dataset_identity(metadata: dict[str, Any]) -> dict[str, Any]:
    """Which set a bundle belongs to: the published set's name, version and MD5 for an imported bundle
    (``metadata["source"]``), else "rendered" with the preset it was rendered at."""
    source = metadata.get("source") or {}
    if source:
        return {"dataset": source.get("dataset"), "version": source.get("version"), "md5": source.get("md5")}
    return {"dataset": "rendered", "version": f"bundle v{metadata.get('bundle_version')}", "md5": None,
            "preset": metadata.get("preset")}


def set_identity(bundle_dirs_: list[Path]) -> dict[str, Any]:
    """The identity of a selection of bundles: one ``dataset_identity`` when they agree, else
    ``{"dataset": "mixed", "sets": [...]}`` (unreadable metadata is skipped: the example fails elsewhere)."""
    seen: list[dict[str, Any]] = []
    for d in bundle_dirs_:
        try:
            ident = dataset_identity(json.loads((Path(d) / METADATA_FILE).read_text()))
        except (OSError, ValueError, AttributeError):
            continue
        if ident not in seen:
            seen.append(ident)
    if len(seen) == 1:
        return seen[0]
    return {"dataset": "mixed" if seen else "unknown", "sets": seen}


# -- validation ----------------------------------------------------------------------------------


SPLITS = ("eval", "train")


def bundle_dirs(split_dir: str | Path) -> list[Path]:
    """Complete bundles (subdirectories with metadata.json) of one split directory, sorted by id."""
    split_dir = Path(split_dir)
    if not split_dir.is_dir():
        return []
    return sorted(p for p in split_dir.iterdir() if p.is_dir() and not p.name.startswith(".")
                  and (p / "metadata.json").is_file())


def _holders(root: Path, depth: int = 3) -> list[Path]:
    """Directories up to ``depth`` levels below ``root`` that hold bundles (shallowest first)."""
    found, level = [], [root]
    for _ in range(depth):
        level = sorted(d for parent in level if parent.is_dir() for d in parent.iterdir()
                       if d.is_dir() and not d.name.startswith("."))
        found += [d for d in level if bundle_dirs(d)]
        level = [d for d in level if d not in found]
    return found


def resolve_split_dir(data: str | Path, split: str | None = None) -> Path:
    """The directory of reference bundles that ``--data`` (and ``--split``) mean.

    ``data`` may be a split directory (``data/eval``: its subdirectories are bundles) or a data root
    (``data``: it holds ``eval/`` and/or ``train/``) with ``split`` naming one, defaulting to the only
    split present. Anything else is a BundleError saying what ``data`` holds and which ``--data`` was
    probably meant."""
    data = Path(data)
    if not data.is_dir():
        raise BundleError(f"{data}: data directory does not exist; render examples into it with "
                          f"`rigidbench render --split {split or 'eval'} --data {data}`")
    check_not_published_layout(data)
    if bundle_dirs(data):
        if split is not None and data.name in SPLITS and data.name != split:
            raise BundleError(f"{data} is the '{data.name}' split directory, but --split {split} was given; "
                              f"did you mean --data {data.parent / split}?")
        return data
    present = [s for s in SPLITS if bundle_dirs(data / s)]
    if split is not None and split in present:
        return data / split
    if split is None and len(present) == 1:
        return data / present[0]
    if split is None and len(present) > 1:
        raise BundleError(f"{data} holds the splits {' and '.join(present)}; choose one with --split "
                          f"(or pass --data {data / present[0]})")
    holders = _holders(data)
    wanted = [h for h in holders if split is None or h.name == split] or holders
    what = f"'{split}' reference bundles" if split else "reference bundles"
    if wanted:
        holds = ", ".join(f"{h.relative_to(data)}/" for h in holders[:4])
        raise BundleError(f"no {what} in {data}/; it holds {holds}: did you mean --data {wanted[0]}?")
    raise BundleError(f"no {what} in {data}/ (a bundle is a directory with metadata.json); render them with "
                      f"`rigidbench render --split {split or 'eval'} --data {data}`")


def _check(problems: list[str], ok: bool, message: str) -> bool:
    if not ok:
        problems.append(message)
    return ok


def _check_npz(path: Path, problems: list[str]) -> dict[str, np.ndarray] | None:
    try:
        return _load_npz(path)
    except (OSError, ValueError, EOFError) as exc:
        problems.append(f"{path.name}: cannot be read ({exc})")
        return None


def _check_array(problems: list[str], file: str, data: dict[str, np.ndarray], key: str, shape: tuple,
                 dtype_kind: str | tuple[str, ...]) -> np.ndarray | None:
    """shape entries of None match anything; dtype_kind is numpy's kind letter(s) ('b', 'f', 'i', 'U')."""
    if key not in data:
        problems.append(f"{file}: missing array '{key}'")
        return None
    a = data[key]
    kinds = (dtype_kind,) if isinstance(dtype_kind, str) else dtype_kind
    _check(problems, a.dtype.kind in kinds, f"{file}: '{key}' has dtype {a.dtype}, expected kind {'/'.join(kinds)}")
    if _check(problems, a.ndim == len(shape), f"{file}: '{key}' has shape {a.shape}, expected {len(shape)} axes"):
        for axis, (got, want) in enumerate(zip(a.shape, shape)):
            _check(problems, want is None or got == want,
                   f"{file}: '{key}' has shape {a.shape}, axis {axis} should be {want}")
    return a


def _imported(path: Path) -> bool:
    try:
        meta = json.loads((path / METADATA_FILE).read_text())
    except (OSError, ValueError):
        return False
    return isinstance(meta, dict) and bool(meta.get("source"))


def check_bundle(path: str | Path, check_video: bool = True) -> list[str]:
    """Problems with the bundle at ``path`` (empty when valid): every file present, documented
    shapes and dtypes, consistent T (frames), N (actors), H and W everywhere."""
    path = Path(path)
    if not path.is_dir():
        return [f"{path}: bundle directory does not exist"]
    problems: list[str] = []
    imported = _imported(path)
    for name in BUNDLE_FILES:
        if not (imported and name == SPEC_FILE):  # an imported bundle has no scene spec
            _check(problems, (path / name).is_file(), f"{name}: missing")
    if not (path / METADATA_FILE).is_file():
        return problems
    try:
        meta = json.loads((path / METADATA_FILE).read_text())
        T = int(meta["frames"])
        W, H = (int(v) for v in meta["resolution"])
        names = list(meta["actor_names"])
        roles = list(meta["roles"])
        K = np.array(meta["camera"]["intrinsics_K"], float)
        c2w = np.array(meta["camera"]["camera_to_world_blender"], float)
    except (ValueError, KeyError, TypeError) as exc:
        return problems + [f"{METADATA_FILE}: unreadable or missing a required field ({exc})"]
    N = len(names)
    _check(problems, K.shape == (3, 3) and c2w.shape == (4, 4), f"{METADATA_FILE}: camera matrices have wrong shapes")
    _check(problems, len(roles) == N and set(roles) <= {"active", "passive"},
           f"{METADATA_FILE}: roles {roles} do not match {N} actors with roles active/passive")
    _check(problems, meta.get("active_indices") == [k for k, r in enumerate(roles) if r == "active"],
           f"{METADATA_FILE}: active_indices disagree with roles")

    frame_files = sorted((path / FRAMES_DIR).glob("*.png")) if (path / FRAMES_DIR).is_dir() else []
    if _check(problems, [f.name for f in frame_files] == [frame_name(k) for k in range(T)],
              f"{FRAMES_DIR}/: expected {T} frames 00000.png..{frame_name(T - 1)}, found {len(frame_files)}"):
        from PIL import Image, UnidentifiedImageError

        for f in (frame_files[0], frame_files[-1]):
            try:
                with Image.open(f) as im:
                    _check(problems, im.size == (W, H) and im.mode == "RGB",
                           f"{FRAMES_DIR}/{f.name}: {im.mode} {im.size[0]}x{im.size[1]}, expected RGB {W}x{H}")
            except (OSError, UnidentifiedImageError) as exc:
                problems.append(f"{FRAMES_DIR}/{f.name}: cannot be read ({exc})")

    if check_video and (path / VIDEO_FILE).is_file():
        try:
            info = probe_video(path / VIDEO_FILE)
            _check(problems, (info.width, info.height) == (W, H) and len(info.times_s) == T,
                   f"{VIDEO_FILE}: {len(info.times_s)} frames of {info.width}x{info.height}, expected {T} of {W}x{H}")
            _check(problems, info.codec == "h264", f"{VIDEO_FILE}: codec {info.codec}, expected h264")
        except VideoError as exc:
            problems.append(f"{VIDEO_FILE}: {exc.reason}")

    masks = _check_npz(path / MASKS_FILE, problems) if (path / MASKS_FILE).is_file() else None
    if masks is not None:
        _check_array(problems, MASKS_FILE, masks, "masks", (T, N, H, W), "b")
        for key, want in (("names", names), ("roles", roles)):
            if key in masks:
                _check(problems, [str(s) for s in masks[key]] == want, f"{MASKS_FILE}: {key} differ from metadata")
            else:
                problems.append(f"{MASKS_FILE}: missing array '{key}'")
    depth = _check_npz(path / DEPTH_FILE, problems) if (path / DEPTH_FILE).is_file() else None
    if depth is not None:
        d = _check_array(problems, DEPTH_FILE, depth, "depth", (T, H, W), "f")
        if d is not None:
            _check(problems, d.dtype == np.float32, f"{DEPTH_FILE}: depth is {d.dtype}, expected float32")
            _check(problems, not np.isnan(d).any() and bool((d > 0).all()),
                   f"{DEPTH_FILE}: depth must be positive (inf for no surface) and never NaN")
    if (path / TRAJECTORIES_FILE).is_file():
        try:
            traj = Trajectory.load(path / TRAJECTORIES_FILE)
            _check(problems, list(traj.names) == names and list(traj.roles) == roles,
                   f"{TRAJECTORIES_FILE}: actors {list(traj.names)} differ from metadata {names}")
            _check(problems, traj.positions_m.shape == (N, T, 3) and traj.quat_wxyz.shape == (N, T, 4),
                   f"{TRAJECTORIES_FILE}: positions {traj.positions_m.shape} / quaternions {traj.quat_wxyz.shape}, "
                   f"expected ({N},{T},3) / ({N},{T},4)")
            _check(problems, bool(np.isfinite(traj.positions_m).all() and np.isfinite(traj.quat_wxyz).all()),
                   f"{TRAJECTORIES_FILE}: non-finite poses")
        except (OSError, KeyError, ValueError) as exc:
            problems.append(f"{TRAJECTORIES_FILE}: cannot be read ({exc})")
    if (path / CONTACTS_FILE).is_file():
        try:
            contacts = load_contacts(path / CONTACTS_FILE)
            bad = [c for c in contacts if not (0 <= c.frame < T) or c.a not in names or len(c.points_m) > 5
                   or len(c.points_m) != len(c.normals)]
            _check(problems, not bad, f"{CONTACTS_FILE}: {len(bad)} contacts with a frame outside [0, {T}), an "
                                      "unknown first body, or mismatched points and normals")
        except (OSError, KeyError, ValueError, TypeError) as exc:
            problems.append(f"{CONTACTS_FILE}: cannot be read ({exc})")
    tracks = _check_npz(path / TRACKS_FILE, problems) if (path / TRACKS_FILE).is_file() else None
    if tracks is not None:
        tr = _check_array(problems, TRACKS_FILE, tracks, "tracks", (None, T, 2), "f")
        P = tr.shape[0] if tr is not None and tr.ndim == 3 else None
        _check_array(problems, TRACKS_FILE, tracks, "visibility", (P, T), "b")
        idx = _check_array(problems, TRACKS_FILE, tracks, "actor_index", (P,), ("i", "u"))
        _check_array(problems, TRACKS_FILE, tracks, "query_pixels", (P, 2), ("i", "u"))
        _check_array(problems, TRACKS_FILE, tracks, "points_body_m", (P, 3), "f")
        per = _check_array(problems, TRACKS_FILE, tracks, "points_per_actor", (N,), ("i", "u"))
        if idx is not None and idx.ndim == 1 and len(idx):
            _check(problems, bool(((idx >= 0) & (idx < N)).all()) and all(roles[i] == "active" for i in idx),
                   f"{TRACKS_FILE}: actor_index must point at active actors in [0, {N})")
        if per is not None and P is not None:
            _check(problems, int(per.sum()) == P, f"{TRACKS_FILE}: points_per_actor sums to {per.sum()}, not {P}")
    if (path / PROMPT_FILE).is_file():
        prompt = (path / PROMPT_FILE).read_text().strip()
        _check(problems, bool(prompt) and prompt == meta.get("prompt"), f"{PROMPT_FILE}: empty or differs from metadata")
    if (path / SPEC_FILE).is_file():
        try:
            spec = SceneSpec.from_json((path / SPEC_FILE).read_text())
            _check(problems, spec.camera is not None and [b.name for b in spec.bodies] == names,
                   f"{SPEC_FILE}: no camera, or bodies differ from metadata actors")
            _check(problems, spec.camera is None or math.isclose(spec.task_rotation_deg, meta["task_rotation_deg"]),
                   f"{SPEC_FILE}: task rotation differs from metadata")
        except (ValueError, KeyError, TypeError) as exc:
            problems.append(f"{SPEC_FILE}: not a valid SceneSpec ({exc})")
    return problems


__all__ = ["BUNDLE_VERSION", "BUNDLE_FILES", "FRAMES_DIR", "VIDEO_FILE", "MASKS_FILE", "DEPTH_FILE",
           "TRAJECTORIES_FILE", "CONTACTS_FILE", "TRACKS_FILE", "METADATA_FILE", "PROMPT_FILE", "SPEC_FILE",
           "BundleError", "frame_name", "masks_from_index", "write_masks", "write_depth", "write_json",
           "slice_trajectory", "camera_metadata", "make_metadata", "prepare_tmp", "commit", "Sample",
           "check_bundle", "no_spec_message", "dataset_identity", "set_identity", "refuse_imported"]
