"""The sample bundle: one directory per example (paper, table "Per-sample artifact bundle").

::

    <id>/frames/00000.png ...   T RGB frames, uint8 H x W x 3 (imported: the published RGBA PNGs, read without alpha)
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
import zipfile
import zlib
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, TypeVar

import numpy as np

from .. import jsonio
from ..errors import BundleError
from ..executors import usable_cores
from ..folders import (BUNDLE_FILES, CONTACTS_FILE, DEPTH_FILE, FRAMES_DIR, MASKS_FILE,  # noqa: F401 (re-exported)
                       METADATA_FILE, PROMPT_FILE, SPEC_FILE, TRACKS_FILE, TRAJECTORIES_FILE, VIDEO_FILE, frame_name)
from ..scene_spec.types import SceneSpec
from ..video import VideoError, probe_video
from . import camera_model as cm
from .layout import SAMPLE_WHAT, PublishedLayoutError, check_not_published_layout, is_published_metadata, \
    published_layout_message
from .tracks import Tracks
from .trajectory import Contact, Trajectory, load_contacts

BUNDLE_VERSION = 1
PIXEL_CONVENTION = "pixel (x, y) = (column, row) with integer values at pixel centres; the image spans [-0.5, W-0.5]"
DEPTH_CONVENTION = "Cycles Z pass: metres along the camera's optical axis; +inf where no surface is hit"


def no_spec_message(sample_id: str) -> str:
    """Why a command that re-simulates cannot run on an imported bundle."""
    return (f"example {sample_id} was imported from the published set, which ships no scene spec, so it cannot be "
            "re-simulated; use a bundle rendered with `rigidbench render` for this")


def refuse_imported(bundle_dirs_: list[Path], what: str) -> None:
    """BundleError (one line, before any work) when ``what`` needs scene specs and a bundle was imported."""
    imported = [Path(d).name for d in bundle_dirs_ if is_imported(Path(d)) and not (Path(d) / SPEC_FILE).is_file()]
    if imported:
        raise BundleError(f"{what}, which needs each example's scene spec; {len(imported)} of the selected examples "
                          f"(e.g. {imported[0]}) were imported from the published set, which ships none. Use bundles "
                          "rendered with `rigidbench render` for this")


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


# -- reading -------------------------------------------------------------------------------------


#: What reading a damaged bundle file raises: truncated or corrupt zip (npz), JSON, PNG or npy data, a
#: missing array or field, an unreadable file.
READ_ERRORS: tuple[type[BaseException], ...] = (OSError, ValueError, EOFError, KeyError, IndexError, TypeError,
                                                zipfile.BadZipFile, zlib.error)

_T = TypeVar("_T")


def _load_npz(path: Path) -> dict[str, np.ndarray]:
    with np.load(path, allow_pickle=False) as z:
        return {k: z[k] for k in z.files}


def repair_hint(bundle_dir: str | Path) -> str:
    """What to do about a damaged bundle: import it again (a bundle imported from a published set, or one
    without a readable metadata.json and no scene spec) or re-render it (our renders)."""
    bundle_dir = Path(bundle_dir)
    sample_id, split, root = bundle_dir.name, bundle_dir.parent.name, bundle_dir.parent.parent
    imported = is_imported(bundle_dir)
    if not imported and not (bundle_dir / SPEC_FILE).is_file():
        try:
            jsonio.load_json(bundle_dir / METADATA_FILE, expect=dict)
        except READ_ERRORS:  # metadata unreadable and no scene spec: most likely an imported bundle
            imported = True
    if imported:
        return (f"import it again with `rigidbench import <the published archive or folder> --data {root}` "
                f"(or `rigidbench download --data {root}`), which replaces the damaged bundle")
    split_option = f" --split {split}" if split in SPLITS else ""
    return (f"re-render example {sample_id} with `rigidbench render --ids {sample_id}{split_option} --data {root}` "
            "(the damaged bundle is replaced)")


def damaged_error(bundle_dir: str | Path, name: str, exc: BaseException) -> BundleError:
    """The per-example error for a bundle file ``name`` that cannot be read: names the file, the reason and
    what to do."""
    bundle_dir = Path(bundle_dir)
    reason = f"{type(exc).__name__}: {exc}" if str(exc) else type(exc).__name__
    return BundleError(f"example {bundle_dir.name}: {bundle_dir / name} is damaged or unreadable ({reason}); "
                       f"{repair_hint(bundle_dir)}")


def read_bundle_file(bundle_dir: str | Path, name: str, loader: Callable[[Path], _T]) -> _T:
    """``loader(bundle_dir / name)``, with any read error (truncated npz, JSON or PNG, a missing array)
    turned into a BundleError naming the file and what to do (``damaged_error``)."""
    path = Path(bundle_dir) / name
    try:
        return loader(path)
    except BundleError:
        raise
    except READ_ERRORS as exc:
        raise damaged_error(bundle_dir, name, exc) from exc


def _read_json_dict(path: Path) -> dict[str, Any]:
    doc = json.loads(path.read_text())
    if not isinstance(doc, dict):
        raise ValueError(f"expected a JSON object, found {type(doc).__name__}")
    return doc


def _read_rgb(path: Path) -> np.ndarray:
    from PIL import Image

    with Image.open(path) as image:
        return np.asarray(image.convert("RGB"))


def _check_shape(what: str, array: np.ndarray, want: tuple[int | None, ...]) -> np.ndarray:
    """``array`` when its shape is ``want`` (None: any length); else a ValueError giving both, for the reader's
    BundleError (a well-formed file of another clip's length or size must not reach the measurements)."""
    got = tuple(int(n) for n in np.shape(array))
    if len(got) != len(want) or any(w is not None and g != w for g, w in zip(got, want)):
        shown = "(" + ", ".join("any" if w is None else str(w) for w in want) + ("," if len(want) == 1 else "") + ")"
        raise ValueError(f"'{what}' has shape {got}, expected {shown} from {METADATA_FILE} (its frames, resolution "
                         "and actors)")
    return array


class Sample:
    """Lazy reader over one bundle directory; every property loads its file on first use. A file that
    cannot be read (missing, truncated, corrupt) raises a BundleError naming it and what to do."""

    def __init__(self, path: str | Path):
        self.path = Path(path)
        if not (self.path / METADATA_FILE).exists():  # (a folder in its place is a damaged bundle: read below)
            raise BundleError(f"{self.path}: not a sample bundle (no {METADATA_FILE}); render it with "
                              "`rigidbench render`")
        if is_published_metadata(self.metadata):
            raise PublishedLayoutError(published_layout_message(self.path.parent, SAMPLE_WHAT))

    def __repr__(self) -> str:
        return f"Sample({str(self.path)!r})"

    def _read(self, name: str, loader: Callable[[Path], _T]) -> _T:
        return read_bundle_file(self.path, name, loader)

    @functools.cached_property
    def _dims(self) -> dict[str, Any]:
        """What every file must agree with, from metadata.json: frames T, size H and W, actor names and roles
        (None where the metadata gives none)."""
        def dims(_: Path) -> dict[str, Any]:
            meta = self.metadata
            w, h = (int(v) for v in meta["resolution"]) if "resolution" in meta else (None, None)
            names, roles = ([str(s) for s in meta[k]] if k in meta else None for k in ("actor_names", "roles"))
            return {"T": int(meta["frames"]) if "frames" in meta else None, "H": h, "W": w, "names": names,
                    "N": None if names is None else len(names), "roles": roles}

        return self._read(METADATA_FILE, dims)

    def _check_actors(self, what: str, names: Any) -> None:
        """ValueError when the actor names ``names`` of a file differ from metadata.json's."""
        want = self._dims["names"]
        if want is not None and [str(s) for s in names] != want:
            raise ValueError(f"{what} {[str(s) for s in names]} differ from {METADATA_FILE}'s actors {want}")

    @functools.cached_property
    def metadata(self) -> dict[str, Any]:
        return self._read(METADATA_FILE, _read_json_dict)

    def _field(self, key: str, convert: Callable[[Any], _T]) -> _T:
        """metadata[key] converted; a missing or malformed field is a BundleError naming metadata.json."""
        def get(_: Path) -> _T:
            return convert(self.metadata[key])

        return self._read(METADATA_FILE, get)

    @property
    def sample_id(self) -> str:
        return self._field("sample_id", str)

    @property
    def task(self) -> str:
        return self._field("task", str)

    @property
    def partition(self) -> str:
        return self._field("partition", str)

    @property
    def n_frames(self) -> int:
        return self._field("frames", int)

    @property
    def fps(self) -> float:
        return self._field("fps", float)

    @property
    def resolution(self) -> tuple[int, int]:
        """(W, H) pixels."""
        def wh(value: Any) -> tuple[int, int]:
            w, h = value
            return int(w), int(h)

        return self._field("resolution", wh)

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
        """(T,H,W,3) uint8 RGB from the PNG frames, decoded on a few threads (PNG decoding releases the GIL)."""
        n = self.n_frames
        if n < 2:
            return np.stack([self.frame(k) for k in range(n)])
        first = self.frame(0)
        out = np.empty((n,) + first.shape, first.dtype)
        out[0] = first

        def decode(k: int) -> None:
            frame = self.frame(k)
            if frame.shape != first.shape:  # only without a resolution in metadata.json: as np.stack refuses
                raise ValueError(f"frame {k} is {frame.shape}, frame 0 {first.shape}: all input arrays must "
                                 "have the same shape")
            out[k] = frame

        with ThreadPoolExecutor(max_workers=usable_cores(min(4, n - 1))) as pool:
            list(pool.map(decode, range(1, n)))
        return out

    def frame(self, k: int) -> np.ndarray:
        """(H,W,3) uint8 RGB frame ``k``."""
        d = self._dims
        return self._read(f"{FRAMES_DIR}/{frame_name(k)}",
                          lambda path: _check_shape("frame", _read_rgb(path), (d["H"], d["W"], 3)))

    @functools.cached_property
    def _masks(self) -> dict[str, np.ndarray]:
        def load(path: Path) -> dict[str, np.ndarray]:
            arrays = _load_npz(path)
            for key in ("masks", "names", "roles"):
                if key not in arrays:
                    raise KeyError(f"no array '{key}'")
            d = self._dims
            _check_shape("masks", arrays["masks"], (d["T"], d["N"], d["H"], d["W"]))
            for key in ("names", "roles"):
                _check_shape(key, arrays[key], (arrays["masks"].shape[1],))
            self._check_actors("names", arrays["names"])
            return arrays

        return self._read(MASKS_FILE, load)

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
        d = self._dims
        return self._read(DEPTH_FILE, lambda path: _check_shape("depth", _load_npz(path)["depth"],
                                                                (d["T"], d["H"], d["W"])))

    @functools.cached_property
    def trajectory(self) -> Trajectory:
        def load(path: Path) -> Trajectory:
            traj = Trajectory.load(path)
            d = self._dims
            n = d["N"] if d["N"] is not None else len(traj.names)
            _check_shape("roles", np.asarray(traj.roles), (n,))
            for key, width in (("positions_m", 3), ("quat_wxyz", 4), ("linear_velocity_m_s", 3),
                               ("angular_velocity_rad_s", 3)):
                _check_shape(key, getattr(traj, key), (n, d["T"], width))
            self._check_actors("actors", traj.names)
            return traj

        return self._read(TRAJECTORIES_FILE, load)

    @functools.cached_property
    def contacts(self) -> list[Contact]:
        def load(path: Path) -> list[Contact]:
            contacts = load_contacts(path)
            T, names = self._dims["T"], self._dims["names"]
            bad = [c for c in contacts if (T is not None and not 0 <= c.frame < T)
                   or (names is not None and c.a not in names)]
            if bad:
                raise ValueError(f"{len(bad)} contacts (first at frame {bad[0].frame}, body {bad[0].a!r}) lie outside "
                                 f"the {T} frames or name no actor of {METADATA_FILE}")
            return contacts

        return self._read(CONTACTS_FILE, load)

    @functools.cached_property
    def tracks(self) -> Tracks:
        """Ground-truth point tracks; also indexable by npz key (``tracks["visibility"]``)."""
        def load(path: Path) -> Tracks:
            tracks = Tracks.load(path)
            d = self._dims
            P = _check_shape("tracks", tracks.tracks_px, (None, d["T"], 2)).shape[0]
            for key, want in (("visibility", (P, d["T"])), ("actor_index", (P,)), ("query_pixels", (P, 2)),
                              ("points_body_m", (P, 3)), ("points_per_actor", (d["N"],))):
                _check_shape(key, tracks[key], want)
            roles = d["roles"]
            idx = tracks.actor_index
            if roles is not None and not all(0 <= int(i) < len(roles) and roles[int(i)] == "active" for i in idx):
                raise ValueError(f"'actor_index' must point at the active actors of {METADATA_FILE}")
            return tracks

        return self._read(TRACKS_FILE, load)

    @property
    def track_active_index(self) -> np.ndarray:
        """(P,) int64 index of each track's actor among the active actors (into ``active_indices``)."""
        return np.searchsorted(self.active_indices, self.tracks.actor_index).astype(np.int64)

    def _camera_matrix(self, key: str, shape: tuple[int, int]) -> np.ndarray:
        def matrix(camera: Any) -> np.ndarray:
            m = np.array(camera[key], dtype=np.float64)
            if m.shape != shape:
                raise ValueError(f"camera.{key} has shape {m.shape}, expected {shape}")
            return m

        return self._field("camera", matrix)

    @property
    def K(self) -> np.ndarray:
        """(3,3) camera intrinsics in pixels (integer coordinates at pixel centres)."""
        return self._camera_matrix("intrinsics_K", (3, 3))

    @property
    def camera_to_world(self) -> np.ndarray:
        """(4,4) Blender camera-to-world matrix (camera looks along its -z, +y up)."""
        return self._camera_matrix("camera_to_world_blender", (4, 4))

    @property
    def world_to_camera_cv(self) -> np.ndarray:
        """(4,4) world-to-camera matrix in the CV convention (+z forward, +y down)."""
        return self._camera_matrix("world_to_camera_cv", (4, 4))

    @property
    def camera_pose(self) -> tuple[np.ndarray, np.ndarray]:
        """(R_c (3,3), t_c (3,) m): Blender camera-to-world rotation and position."""
        m = self.camera_to_world
        return m[:3, :3], m[:3, 3]

    @functools.cached_property
    def prompt(self) -> str:
        return self._read(PROMPT_FILE, lambda path: path.read_text().strip())

    @property
    def imported(self) -> bool:
        """True for a bundle imported from a published set (``rigidbench import``): it has no scene spec."""
        return bool(self.metadata.get("source"))

    @functools.cached_property
    def spec(self) -> SceneSpec:
        if self.imported and not (self.path / SPEC_FILE).is_file():
            raise BundleError(no_spec_message(self.path.name))
        return self._read(SPEC_FILE, lambda path: SceneSpec.from_json(path.read_text()))


def dataset_identity(metadata: dict[str, Any]) -> dict[str, Any]:
    """Which set a bundle belongs to: the published set's name, version and MD5 for an imported bundle
    (``metadata["source"]``), with whether that MD5 was checked against the archive and how (``verified``,
    ``verification``), else "rendered" with the preset it was rendered at."""
    source = metadata.get("source") or {}
    if source:
        verified = bool(source.get("verified", source.get("md5_verified", False)))  # md5_verified: before issue 32
        return {"dataset": source.get("dataset"), "version": source.get("version"), "md5": source.get("md5"),
                "verified": verified, "verification": source.get("verification") or
                (None if verified else "imported before verification was recorded")}
    return {"dataset": "rendered", "version": f"bundle v{metadata.get('bundle_version')}", "md5": None,
            "preset": metadata.get("preset")}


def unverified_reason(identity: dict[str, Any]) -> str | None:
    """Why a result on the set ``identity`` names (``dataset_identity`` or ``set_identity``) cannot be official
    because of the set itself: a published set whose MD5 was never checked against its archive (None: checked,
    or a rendered set)."""
    for ident in identity.get("sets") or [identity]:
        if "verified" not in ident and ident.get("dataset") in ("rendered", "unknown", None):
            continue  # rendered by us (or nothing readable); a published set recorded before issue 32 counts
        if not ident.get("verified"):
            name = " ".join(str(v) for v in (ident.get("dataset"), ident.get("version")) if v)
            return (f"the reference set{' ' + name if name else ''} was not checked against its published MD5 "
                    f"({ident.get('verification') or 'no record of a check'}); import its .tar.gz or parts, or "
                    "download it, to check it")
    return None


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
    """Complete bundles (subdirectories with metadata.json) of one split directory, sorted by id. A folder in
    place of metadata.json counts: that example fails naming the damaged file instead of vanishing."""
    split_dir = Path(split_dir)
    if not split_dir.is_dir():
        return []
    return sorted(p for p in split_dir.iterdir() if p.is_dir() and not p.name.startswith(".")
                  and (p / METADATA_FILE).exists())


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


class _NpzView:
    """An npz file read lazily: its zip directory on opening (a truncated file fails here), each member's
    shape and dtype from its .npy header (no data decompressed), an array's data only when asked for."""

    def __init__(self, path: Path):
        self.path = path
        self.zip = zipfile.ZipFile(path)
        self.keys = {n[:-4] for n in self.zip.namelist() if n.endswith(".npy")}
        self._headers: dict[str, tuple[tuple[int, ...], np.dtype]] = {}

    def header(self, key: str) -> tuple[tuple[int, ...], np.dtype]:
        if key not in self._headers:
            with self.zip.open(f"{key}.npy") as fh:
                version = np.lib.format.read_magic(fh)
                read = np.lib.format.read_array_header_1_0 if version == (1, 0) else \
                    np.lib.format.read_array_header_2_0
                shape, _, dtype = read(fh)
            self._headers[key] = (tuple(int(n) for n in shape), np.dtype(dtype))
        return self._headers[key]

    def __getitem__(self, key: str) -> np.ndarray:
        with self.zip.open(f"{key}.npy") as fh:
            return np.lib.format.read_array(fh, allow_pickle=False)

    def close(self) -> None:
        self.zip.close()


def _check_npz(path: Path, problems: list[str]) -> _NpzView | None:
    try:
        return _NpzView(path)
    except READ_ERRORS as exc:
        problems.append(f"{path.name}: cannot be read ({type(exc).__name__}: {exc})")
        return None


def _check_load(problems: list[str], file: str, data: _NpzView, key: str) -> np.ndarray | None:
    """The array ``key`` of an npz, or None with a problem when its data cannot be read (corrupt member)."""
    try:
        return data[key]
    except READ_ERRORS as exc:
        problems.append(f"{file}: '{key}' cannot be read ({type(exc).__name__}: {exc})")
        return None


def _check_array(problems: list[str], file: str, data: _NpzView, key: str, shape: tuple,
                 dtype_kind: str | tuple[str, ...]) -> tuple[int, ...] | None:
    """Checks the header of array ``key``: shape entries of None match anything; dtype_kind is numpy's kind
    letter(s) ('b', 'f', 'i', 'U'). Returns its shape (None when it is missing or unreadable)."""
    if key not in data.keys:
        problems.append(f"{file}: missing array '{key}'")
        return None
    try:
        got_shape, dtype = data.header(key)
    except READ_ERRORS as exc:
        problems.append(f"{file}: '{key}' cannot be read ({type(exc).__name__}: {exc})")
        return None
    kinds = (dtype_kind,) if isinstance(dtype_kind, str) else dtype_kind
    _check(problems, dtype.kind in kinds, f"{file}: '{key}' has dtype {dtype}, expected kind {'/'.join(kinds)}")
    if _check(problems, len(got_shape) == len(shape), f"{file}: '{key}' has shape {got_shape}, expected "
                                                      f"{len(shape)} axes"):
        for axis, (got, want) in enumerate(zip(got_shape, shape)):
            _check(problems, want is None or got == want,
                   f"{file}: '{key}' has shape {got_shape}, axis {axis} should be {want}")
    return got_shape


def is_imported(path: Path) -> bool:
    """A bundle imported from a published set (its metadata has ``source``); False when unreadable."""
    try:
        meta = json.loads((path / METADATA_FILE).read_text())
    except READ_ERRORS:
        return False
    return isinstance(meta, dict) and bool(meta.get("source"))


@dataclass(frozen=True)
class _Expected:
    """What every file of a bundle must agree with: its metadata's frames T, size W x H, actors and roles."""

    meta: dict
    T: int
    W: int
    H: int
    names: list
    roles: list

    @property
    def N(self) -> int:
        return len(self.names)


def _check_metadata(path: Path, problems: list[str]) -> _Expected | None:
    try:
        meta = _read_json_dict(path / METADATA_FILE)
        expected = _Expected(meta, int(meta["frames"]), *(int(v) for v in meta["resolution"]),
                             list(meta["actor_names"]), list(meta["roles"]))
        K = np.array(meta["camera"]["intrinsics_K"], float)
        c2w = np.array(meta["camera"]["camera_to_world_blender"], float)
    except READ_ERRORS as exc:
        problems.append(f"{METADATA_FILE}: unreadable or missing a required field ({type(exc).__name__}: {exc})")
        return None
    roles, N = expected.roles, expected.N
    _check(problems, K.shape == (3, 3) and c2w.shape == (4, 4), f"{METADATA_FILE}: camera matrices have wrong shapes")
    _check(problems, len(roles) == N and set(roles) <= {"active", "passive"},
           f"{METADATA_FILE}: roles {roles} do not match {N} actors with roles active/passive")
    _check(problems, meta.get("active_indices") == [k for k, r in enumerate(roles) if r == "active"],
           f"{METADATA_FILE}: active_indices disagree with roles")
    return expected


def _check_frames(path: Path, e: _Expected, problems: list[str], deep: bool) -> None:
    frame_files = sorted((path / FRAMES_DIR).glob("*.png")) if (path / FRAMES_DIR).is_dir() else []
    if not _check(problems, [f.name for f in frame_files] == [frame_name(k) for k in range(e.T)],
                  f"{FRAMES_DIR}/: expected {e.T} frames 00000.png..{frame_name(e.T - 1)}, found {len(frame_files)}"):
        return
    from PIL import Image, UnidentifiedImageError

    for f in (frame_files[0], frame_files[-1]):
        try:
            with Image.open(f) as im:  # an imported bundle links the published RGBA PNGs (read without alpha)
                if deep:
                    im.load()  # the pixels: a cut file fails here, not on opening
                modes = ("RGB", "RGBA") if e.meta.get("source") else ("RGB",)
                _check(problems, im.size == (e.W, e.H) and im.mode in modes,
                       f"{FRAMES_DIR}/{f.name}: {im.mode} {im.size[0]}x{im.size[1]}, expected RGB {e.W}x{e.H}")
        except (OSError, UnidentifiedImageError) as exc:
            problems.append(f"{FRAMES_DIR}/{f.name}: cannot be read ({exc})")


def _check_video(path: Path, e: _Expected, problems: list[str], deep: bool) -> None:
    try:
        info = probe_video(path / VIDEO_FILE)
        _check(problems, (info.width, info.height) == (e.W, e.H) and len(info.times_s) == e.T,
               f"{VIDEO_FILE}: {len(info.times_s)} frames of {info.width}x{info.height}, expected {e.T} of "
               f"{e.W}x{e.H}")
        _check(problems, info.codec == "h264", f"{VIDEO_FILE}: codec {info.codec}, expected h264")
    except VideoError as exc:
        problems.append(f"{VIDEO_FILE}: {exc.reason}")


def _check_masks(path: Path, e: _Expected, problems: list[str], deep: bool) -> None:
    masks = _check_npz(path / MASKS_FILE, problems)
    if masks is None:
        return
    if _check_array(problems, MASKS_FILE, masks, "masks", (e.T, e.N, e.H, e.W), "b") is not None and deep:
        _check_load(problems, MASKS_FILE, masks, "masks")
    for key, want in (("names", e.names), ("roles", e.roles)):
        if key in masks.keys:
            got = _check_load(problems, MASKS_FILE, masks, key)
            if got is not None:
                _check(problems, [str(s) for s in got] == want, f"{MASKS_FILE}: {key} differ from metadata")
        else:
            problems.append(f"{MASKS_FILE}: missing array '{key}'")
    masks.close()


def _check_depth(path: Path, e: _Expected, problems: list[str], deep: bool) -> None:
    depth = _check_npz(path / DEPTH_FILE, problems)
    if depth is None:
        return
    if _check_array(problems, DEPTH_FILE, depth, "depth", (e.T, e.H, e.W), "f") is not None:
        dtype = depth.header("depth")[1]
        _check(problems, dtype == np.float32, f"{DEPTH_FILE}: depth is {dtype}, expected float32")
        d = _check_load(problems, DEPTH_FILE, depth, "depth") if deep else None
        if d is not None:
            _check(problems, not np.isnan(d).any() and bool((d > 0).all()),
                   f"{DEPTH_FILE}: depth must be positive (inf for no surface) and never NaN")
    depth.close()


def _check_trajectories(path: Path, e: _Expected, problems: list[str], deep: bool) -> None:
    traj = Trajectory.load(path / TRAJECTORIES_FILE)
    _check(problems, list(traj.names) == e.names and list(traj.roles) == e.roles,
           f"{TRAJECTORIES_FILE}: actors {list(traj.names)} differ from metadata {e.names}")
    _check(problems, traj.positions_m.shape == (e.N, e.T, 3) and traj.quat_wxyz.shape == (e.N, e.T, 4),
           f"{TRAJECTORIES_FILE}: positions {traj.positions_m.shape} / quaternions {traj.quat_wxyz.shape}, "
           f"expected ({e.N},{e.T},3) / ({e.N},{e.T},4)")
    _check(problems, bool(np.isfinite(traj.positions_m).all() and np.isfinite(traj.quat_wxyz).all()),
           f"{TRAJECTORIES_FILE}: non-finite poses")


def _check_contacts(path: Path, e: _Expected, problems: list[str], deep: bool) -> None:
    contacts = load_contacts(path / CONTACTS_FILE)
    bad = [c for c in contacts if not (0 <= c.frame < e.T) or c.a not in e.names or len(c.points_m) > 5
           or len(c.points_m) != len(c.normals)]
    _check(problems, not bad, f"{CONTACTS_FILE}: {len(bad)} contacts with a frame outside [0, {e.T}), an "
                              "unknown first body, or mismatched points and normals")


def _check_tracks(path: Path, e: _Expected, problems: list[str], deep: bool) -> None:
    tracks = _check_npz(path / TRACKS_FILE, problems)
    if tracks is None:
        return
    T, N = e.T, e.N
    tr = _check_array(problems, TRACKS_FILE, tracks, "tracks", (None, T, 2), "f")
    P = tr[0] if tr is not None and len(tr) == 3 else None
    for key, shape, kinds in (("tracks", None, None), ("visibility", (P, T), "b"),
                              ("query_pixels", (P, 2), ("i", "u")), ("points_body_m", (P, 3), "f")):
        if shape is None or _check_array(problems, TRACKS_FILE, tracks, key, shape, kinds) is not None:
            if key in tracks.keys:
                _check_load(problems, TRACKS_FILE, tracks, key)  # small: read to find damaged data
    idx = per = None
    if _check_array(problems, TRACKS_FILE, tracks, "actor_index", (P,), ("i", "u")) is not None:
        idx = _check_load(problems, TRACKS_FILE, tracks, "actor_index")
    if _check_array(problems, TRACKS_FILE, tracks, "points_per_actor", (N,), ("i", "u")) is not None:
        per = _check_load(problems, TRACKS_FILE, tracks, "points_per_actor")
    if idx is not None and idx.ndim == 1 and len(idx):
        _check(problems, bool(((idx >= 0) & (idx < N)).all()) and all(e.roles[i] == "active" for i in idx),
               f"{TRACKS_FILE}: actor_index must point at active actors in [0, {N})")
    if per is not None and P is not None:
        _check(problems, int(per.sum()) == P, f"{TRACKS_FILE}: points_per_actor sums to {per.sum()}, not {P}")
    tracks.close()


def _check_prompt(path: Path, e: _Expected, problems: list[str], deep: bool) -> None:
    prompt = (path / PROMPT_FILE).read_text().strip()
    _check(problems, bool(prompt) and prompt == e.meta.get("prompt"), f"{PROMPT_FILE}: empty or differs from metadata")


def _check_spec(path: Path, e: _Expected, problems: list[str], deep: bool) -> None:
    try:
        spec = SceneSpec.from_json((path / SPEC_FILE).read_text())
    except READ_ERRORS as exc:
        problems.append(f"{SPEC_FILE}: not a valid SceneSpec ({exc})")
        return
    _check(problems, spec.camera is not None and [b.name for b in spec.bodies] == e.names,
           f"{SPEC_FILE}: no camera, or bodies differ from metadata actors")
    _check(problems, spec.camera is None or math.isclose(spec.task_rotation_deg, e.meta["task_rotation_deg"]),
           f"{SPEC_FILE}: task rotation differs from metadata")


#: Each bundle file's check, in the order problems are listed: (file or folder, check, read errors are caught
#: and reported as "cannot be read" by check_bundle).
_FILE_CHECKS = ((FRAMES_DIR, _check_frames, False), (VIDEO_FILE, _check_video, False),
                (MASKS_FILE, _check_masks, False), (DEPTH_FILE, _check_depth, False),
                (TRAJECTORIES_FILE, _check_trajectories, True), (CONTACTS_FILE, _check_contacts, True),
                (TRACKS_FILE, _check_tracks, False), (PROMPT_FILE, _check_prompt, True),
                (SPEC_FILE, _check_spec, False))


def check_bundle(path: str | Path, check_video: bool = True, deep: bool = True) -> list[str]:
    """Problems with the bundle at ``path`` (empty when valid): every file present and readable, documented
    shapes and dtypes, consistent T (frames), N (actors), H and W everywhere.

    ``deep`` (default) also reads the large arrays (masks, depth) to check their values; without it their
    shapes and dtypes come from the .npy headers alone, so a damaged (e.g. truncated) file is still found
    in milliseconds, but not a flipped bit inside the compressed data (``render`` skips with this check)."""
    path = Path(path)
    if not path.is_dir():
        return [f"{path}: bundle directory does not exist"]
    problems: list[str] = []
    imported = is_imported(path)
    for name in BUNDLE_FILES:
        if not (imported and name == SPEC_FILE):  # an imported bundle has no scene spec
            _check(problems, (path / name).is_file(), f"{name}: missing")
    if not (path / METADATA_FILE).is_file():
        return problems
    expected = _check_metadata(path, problems)
    if expected is None:
        return problems
    for name, check, catch in _FILE_CHECKS:
        if name == VIDEO_FILE and not check_video:
            continue
        if name != FRAMES_DIR and not (path / name).is_file():
            continue
        if not catch:
            check(path, expected, problems, deep)
            continue
        try:
            check(path, expected, problems, deep)
        except READ_ERRORS as exc:
            problems.append(f"{name}: cannot be read ({type(exc).__name__}: {exc})")
    return problems


__all__ = ["BUNDLE_VERSION", "BUNDLE_FILES", "FRAMES_DIR", "VIDEO_FILE", "MASKS_FILE", "DEPTH_FILE",
           "TRAJECTORIES_FILE", "CONTACTS_FILE", "TRACKS_FILE", "METADATA_FILE", "PROMPT_FILE", "SPEC_FILE",
           "BundleError", "frame_name", "masks_from_index", "write_masks", "write_depth",
           "slice_trajectory", "camera_metadata", "make_metadata", "Sample",
           "check_bundle", "no_spec_message", "dataset_identity", "set_identity", "unverified_reason", "refuse_imported", "READ_ERRORS",
           "read_bundle_file", "damaged_error", "repair_hint", "is_imported"]
