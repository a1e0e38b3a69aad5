"""Re-simulate imported published examples with our Bullet simulation, and say which can have an envelope.

The published set ships no scene spec, so the physical envelope (twins re-simulated around the reference)
can only be made for a published example whose scene we can rebuild and whose published trajectory our
simulation reproduces. ``resimulate_published(split_dir)`` does, per imported example:

1. rebuild a spec from the published metadata (``scene_spec.from_published``): the actors at their pose of
   frame 0, the support's top measured from the published contacts with the surface where there are any
   (``support_top_from_contacts``), each ramp's length, height and width measured from its depth and mask at
   frame 0 (``measure_ramp``); or record why it cannot ("cannot: ...");
2. simulate it at zero perturbation (``blender.physics.simulate``; needs bpy);
3. compare the re-simulated trajectory of every active actor with the published one: position error in
   metres and in pixels at the published camera, orientation error in degrees, over the first
   ``RESIM_WINDOW_S`` of the clip and over the whole clip;
4. give it an envelope ("ok") when the largest position error over the window is at most
   ``RESIM_TOLERANCE_M``, else "no envelope" with the measured reason.

An example that cannot be read (a damaged file) is recorded as failed and the others go on.
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Iterable, Mapping, Sequence

import numpy as np

from ..blender.physics import simulate, write_simulation
from ..config import Registry, registry as load_registry
from ..errors import RigidBenchError
from ..groundtruth import camera_model as cm
from ..groundtruth.bundle import Sample, bundle_dirs, resolve_split_dir
from ..groundtruth.trajectory import Contact, Trajectory
from ..jsonio import write_json
from ..rotations import quat_to_matrix
from ..scene_spec.from_published import RAMP_ASSET, Cannot, RebuiltSpec, published_metadata, spec_from_published

log = logging.getLogger(__name__)

#: Seconds from the first frame over which a re-simulation must match the published trajectory. The first
#: second is where our rebuilt scene (our procedural meshes, not the published assets; a box for the published
#: table) is expected to follow the published one; later, every contact-rich example diverges for any small
#: difference of shape, and that sensitivity is what the envelope's twins measure themselves.
RESIM_WINDOW_S = 1.0
#: The largest position error (m) of any active actor over that window for an example to get an envelope.
#: 1 cm is under half the smallest extent of every object in our catalogue (a banana is 3.5 cm thick, a bouncy
#: ball 4.5 cm across), so the re-simulated object overlaps the published one in every frame and the mask and
#: track measurements of twins compare like with like; at the paper's camera (fx = 35/36 x 1280 = 1244 px, the
#: release's nearest camera distance 1.4 m) it is at most 9 px, about a tenth of what a dropped object moves in
#: one frame after a 0.6 m fall (3.4 m/s / 24 fps = 14 cm). The pixel error is reported beside it.
RESIM_TOLERANCE_M = 0.01
#: The contact points with the support that ``support_top_from_contacts`` needs, and the least upward
#: component of their normals (a point on a side face of a table says nothing about the height of its top).
SUPPORT_CONTACT_MIN_POINTS = 3
SUPPORT_NORMAL_MIN_Z = 0.9
#: How far (m) the contacts' height of the support top may be from the published ``center``'s z before it replaces
#: it. Contact points scatter by a few millimetres about the top (a face size, or our detector's 3 mm tolerance);
#: Bullet's bounces are chaotic (an apple dropped on a 0.1 mm higher support lands elsewhere), so the recorded
#: centre is kept unless the contacts show it is not the top.
SUPPORT_CONTACT_AGREEMENT_M = 0.005
#: The fewest ramp pixels (mask and finite depth at frame 0) from which ``measure_ramp`` measures a ramp.
RAMP_MIN_PIXELS = 30
RESULT_FILE = "resimulation.json"
OUTCOMES = ("reproduced", "drifts", "cannot", "failed")


# -- measurements that fill what the published metadata lacks ----------------------------------------------------


def support_top_from_contacts(contacts: Iterable[Contact], surface: str) -> float | None:
    """The height (m) of the support's top face from the published contacts of the actors with the surface named
    ``surface`` (their points with an upward normal): the median of their z, or None with too few of them.
    The release records a contact point as the midpoint of two overlapping faces, one of the object and one of
    the surface, so it lies within a face size of the top."""
    zs = [p[2] for c in contacts if c.b == surface
          for p, n in zip(c.points_m, c.normals) if n[2] >= SUPPORT_NORMAL_MIN_Z]
    return float(np.median(zs)) if len(zs) >= SUPPORT_CONTACT_MIN_POINTS else None


def support_top(centre_z_m: float, from_contacts_m: float | None) -> float | None:
    """The support top to rebuild with: None (keep the published centre's z) unless the contacts put the top more
    than ``SUPPORT_CONTACT_AGREEMENT_M`` away from it, then the contacts' height."""
    if from_contacts_m is None or abs(from_contacts_m - centre_z_m) <= SUPPORT_CONTACT_AGREEMENT_M:
        return None
    return from_contacts_m


def pixel_centres(cols: np.ndarray, rows: np.ndarray, K: np.ndarray, width: int, height: int) -> np.ndarray:
    """(n,2) image coordinates of pixel centres in the convention of ``K``: a renderer puts its principal point
    at the image centre, so pixel column c is centred at u = c + 0.5 + (cx - W/2) (c for our K, whose cx is
    W/2 - 0.5; c + 0.5 for the published K, whose cx is W/2)."""
    return np.stack([cols + 0.5 + (K[0, 2] - width / 2), rows + 0.5 + (K[1, 2] - height / 2)], axis=-1)


def _point_map(depth: np.ndarray, hit: np.ndarray, K: np.ndarray, R_c: np.ndarray, t_c: np.ndarray, position_m,
               quat_wxyz) -> np.ndarray:
    """(H,W,3) points of the hit pixels in the frame of the body at ``position_m``/``quat_wxyz`` (NaN elsewhere)."""
    H, W = hit.shape
    rows, cols = np.nonzero(hit)
    world = cm.unproject(pixel_centres(cols.astype(float), rows.astype(float), K, W, H), depth[rows, cols], K, R_c, t_c)
    out = np.full((H, W, 3), np.nan)
    out[rows, cols] = (world - np.asarray(position_m, float)) @ quat_to_matrix(np.asarray(quat_wxyz, float))
    return out


def _normals(points: np.ndarray, eye: np.ndarray) -> np.ndarray:
    """(H,W,3) unit normals from the four neighbours of each point of a point map, turned toward ``eye`` (NaN at
    the border of the map or of the hit pixels)."""
    n = np.full(points.shape, np.nan)
    du = points[1:-1, 2:] - points[1:-1, :-2]
    dv = points[2:, 1:-1] - points[:-2, 1:-1]
    c = np.cross(du, dv)
    c /= np.linalg.norm(c, axis=-1, keepdims=True)
    toward = np.sum(c * (eye - points[1:-1, 1:-1]), axis=-1, keepdims=True)
    n[1:-1, 1:-1] = np.where(toward < 0, -c, c)
    return n


def _fit_slope(y: np.ndarray, z: np.ndarray) -> tuple[float, float] | None:
    """(h, a) of the line z = h - a y through the points by least squares, refitted once without the points farther
    than three times the median residual; None unless h and a are positive."""
    keep = np.ones(len(y), bool)
    for _ in range(2):
        A = np.stack([np.ones(keep.sum()), -y[keep]], axis=1)
        (h, a), *_ = np.linalg.lstsq(A, z[keep], rcond=None)
        residual = np.abs(z - (h - a * y))
        keep = residual <= 3 * np.median(residual[keep]) + 1e-9
    return (float(h), float(a)) if h > 0 and a > 0 else None


def _upper_edge(y: np.ndarray, z: np.ndarray, bins: int = 24) -> np.ndarray:
    """Indices of the highest point in each of ``bins`` equal slices of y: the upper edge of a side face."""
    edges = np.linspace(y.min(), y.max(), bins + 1)
    which = np.clip(np.searchsorted(edges, y, side="right") - 1, 0, bins - 1)
    return np.array([np.argmax(np.where(which == k, z, -np.inf)) for k in range(bins) if (which == k).any()])


def measure_ramp(depth: np.ndarray, mask: np.ndarray, K: np.ndarray, R_c: np.ndarray, t_c: np.ndarray,
                 position_m, quat_wxyz) -> tuple[float, float, float] | None:
    """(length, height, width) m of a published ramp from its depth (H,W) and mask (H,W) at frame 0, in the ramp's
    own frame (origin at the bottom edge of its high end, length along +y, height along +z, width across x centred
    on the origin; the slope is the plane z = H (1 - y / L)). None when it cannot be measured: fewer than
    ``RAMP_MIN_PIXELS`` pixels see it, or neither its slope nor a side face is in view (a camera behind it).

    Where the slope is in view (pixels whose normal, from the depth, points up and toward +y), the plane is fitted
    to its points by least squares: its intercept is H and its slope H/L, to a small fraction of a pixel. Else the
    upper edge of a side face (the points on its plane, x = +-W/2; the highest in each slice of y) is fitted the
    same way, each point raised by half its pixel's footprint (the highest pixel centre of a slice lies on average
    half a pixel under the edge): good to one or two pixels' footprints (depth / fx). The width is twice the
    median |x| of the side faces' pixels, or twice the largest |x| seen when no side is in view."""
    hit = np.asarray(mask, bool) & np.isfinite(depth) & (depth > 0)
    if hit.sum() < RAMP_MIN_PIXELS:
        return None
    local = _point_map(depth, hit, K, R_c, t_c, position_m, quat_wxyz)
    eye = (np.asarray(t_c, float) - np.asarray(position_m, float)) @ quat_to_matrix(np.asarray(quat_wxyz, float))
    normals = _normals(local, eye)
    with np.errstate(invalid="ignore"):
        slope = (normals[..., 2] > 0.2) & (normals[..., 1] > 0.05) & (np.abs(normals[..., 0]) < 0.5)
        side = np.abs(normals[..., 0]) > 0.9
    enough = RAMP_MIN_PIXELS // 3
    fit = None
    if slope.sum() >= enough:
        fit = _fit_slope(local[slope][:, 1], local[slope][:, 2])
    if fit is None and side.sum() >= enough:
        # every pixel on the side face's plane (not only those whose four neighbours are on it: the edge's own)
        plane = float(np.median(np.abs(local[side][:, 0])))
        on_side = hit & (np.abs(np.abs(local[..., 0]) - plane) <= 0.05 * float(np.median(depth[side])) / K[0, 0])
        points, footprint = local[on_side], depth[on_side] / K[0, 0]  # a pixel's footprint where each point is
        top = _upper_edge(points[:, 1], points[:, 2])
        fit = _fit_slope(points[top, 1], points[top, 2] + footprint[top] / 2) if len(top) >= 3 else None
    if fit is None:
        return None
    height, length = fit[0], fit[0] / fit[1]
    xs = np.abs(local[side][:, 0]) if side.sum() >= enough else np.abs(local[hit][:, 0])
    width = float(2 * (np.median(xs) if side.sum() >= enough else xs.max()))
    return (length, height, width) if min(length, height, width) > 0 else None


# -- comparing two trajectories ----------------------------------------------------------------------------------


@dataclass(frozen=True)
class Drift:
    """How far a re-simulation is from the published trajectory (active actors; all errors are maxima over them)."""

    window_frames: int  # frames compared for the verdict (those within RESIM_WINDOW_S of the first)
    max_m: float  # largest position error over the window
    final_m: float  # position error at the window's last frame
    max_px: float  # the same at the published camera (NaN where an actor is behind it)
    final_px: float
    max_deg: float  # largest orientation error over the window
    final_deg: float
    clip_frames: int
    clip_max_m: float  # over the whole clip
    clip_final_m: float
    clip_max_px: float
    clip_max_deg: float
    worst_actor: str  # the actor with the largest error over the window
    first_frame_over: int | None  # first frame whose error exceeds the tolerance (None: none)


def _angle_deg(q1: np.ndarray, q2: np.ndarray) -> np.ndarray:
    dot = np.abs(np.sum(q1 * q2, axis=-1)) / (np.linalg.norm(q1, axis=-1) * np.linalg.norm(q2, axis=-1))
    return np.degrees(2 * np.arccos(np.clip(dot, 0.0, 1.0)))


def _nanmax(x: np.ndarray) -> float:
    finite = x[np.isfinite(x)]
    return float(finite.max()) if finite.size else float("nan")


def compare(published: Trajectory, resimulated: Trajectory, actors: Sequence[str], K: np.ndarray, R_c: np.ndarray,
            t_c: np.ndarray, window_s: float = RESIM_WINDOW_S, tolerance_m: float = RESIM_TOLERANCE_M) -> Drift:
    """The errors of ``resimulated`` against ``published`` for the named actors, frame by frame (frame k of one is
    frame k of the other; the shorter sets the clip), in metres, pixels (``K``, ``R_c``, ``t_c``: the published
    camera) and degrees."""
    T = min(published.positions_m.shape[1], resimulated.positions_m.shape[1])
    n_win = min(T, int(math.floor(window_s * published.fps + 1e-9)) + 1)
    pi = [published.index(a) for a in actors]
    ri = [resimulated.index(a) for a in actors]
    p_pub, p_sim = published.positions_m[pi, :T], resimulated.positions_m[ri, :T]
    err_m = np.linalg.norm(p_sim - p_pub, axis=-1)  # (A,T)
    uv_pub, z_pub = cm.project(p_pub, K, R_c, t_c)
    uv_sim, z_sim = cm.project(p_sim, K, R_c, t_c)
    err_px = np.where((z_pub > 0) & (z_sim > 0), np.linalg.norm(uv_sim - uv_pub, axis=-1), np.nan)
    err_deg = _angle_deg(published.quat_wxyz[pi, :T], resimulated.quat_wxyz[ri, :T])
    win = slice(0, n_win)
    per_frame = err_m.max(axis=0)
    over = np.nonzero(per_frame[win] > tolerance_m)[0]
    return Drift(window_frames=n_win, max_m=float(err_m[:, win].max()), final_m=float(err_m[:, n_win - 1].max()),
                 max_px=_nanmax(err_px[:, win]), final_px=_nanmax(err_px[:, n_win - 1]),
                 max_deg=float(err_deg[:, win].max()), final_deg=float(err_deg[:, n_win - 1].max()),
                 clip_frames=T, clip_max_m=float(err_m.max()), clip_final_m=float(err_m[:, T - 1].max()),
                 clip_max_px=_nanmax(err_px), clip_max_deg=float(err_deg.max()),
                 worst_actor=actors[int(np.argmax(err_m[:, win].max(axis=1)))],
                 first_frame_over=int(over[0]) if len(over) else None)


# -- one example --------------------------------------------------------------------------------------------------


@dataclass
class ResimRow:
    """One example's re-simulation: ``outcome`` is "reproduced" (within tolerance: it can have an envelope),
    "drifts" (re-simulated, beyond tolerance), "cannot" (no spec could be rebuilt) or "failed" (unreadable or the
    simulation failed); ``envelope`` is "ok" for "reproduced" and "no envelope" otherwise, with ``reason``."""

    sample_id: str
    task: str
    partition: str
    outcome: str
    envelope: str
    reason: str | None = None
    drift: Drift | None = None
    notes: dict[str, Any] = field(default_factory=dict)
    seconds: float = 0.0

    def to_dict(self) -> dict[str, Any]:
        return _finite_or_none(asdict(self))


def _verdict(drift: Drift, fps: float, tolerance_m: float) -> tuple[str, str | None]:
    if drift.max_m <= tolerance_m:
        return "reproduced", None
    return "drifts", (f"re-simulation drifts {drift.max_m * 100:.1f} cm ({drift.max_px:.1f} px) from the published "
                      f"trajectory of {drift.worst_actor} within the first {(drift.window_frames - 1) / fps:.2f} s; "
                      f"it exceeds the {tolerance_m * 100:g} cm tolerance from frame {drift.first_frame_over}")


def rebuild(sample: Sample, registry: Registry) -> RebuiltSpec | Cannot:
    """The spec of one imported example (``spec_from_published`` with the support's top and the ramps' sizes
    measured from the bundle), or why there is none."""
    meta = sample.metadata
    published = published_metadata(meta)
    traj = sample.trajectory
    poses = {name: (traj.positions_m[k, 0], traj.quat_wxyz[k, 0]) for k, name in enumerate(traj.names)}
    surface = str(published.get("surface", published.get("surface_name", "")))
    measured = support_top_from_contacts(sample.contacts, surface)
    try:
        top = support_top(float(published["center"][2]), measured)
    except (KeyError, TypeError, ValueError, IndexError):
        top = None  # spec_from_published says what is missing
    ramps: dict[str, tuple[float, float, float]] = {}
    actors = published.get("actors") if isinstance(published.get("actors"), Mapping) else {}
    ramp_names = [n for n, a in actors.items() if isinstance(a, Mapping) and a.get("object_id") == RAMP_ASSET]
    if ramp_names:
        R_c, t_c = sample.camera_pose
        for name in ramp_names:
            if name in sample.actor_names and name in poses:
                k = sample.actor_names.index(name)
                size = measure_ramp(sample.depth[0], sample.masks[0, k], sample.K, R_c, t_c, *poses[name])
                if size is not None:
                    ramps[name] = size
    rebuilt = spec_from_published(meta, poses, registry, sample_id=sample.path.name, support_top_m=top,
                                  ramp_sizes=ramps)
    if isinstance(rebuilt, RebuiltSpec):
        rebuilt.notes["support_top_from_contacts_m"] = measured
        if ramps:
            rebuilt.notes["ramp_sizes_m"] = {n: [round(v, 5) for v in s] for n, s in ramps.items()}
    return rebuilt


def resimulate_example(bundle_dir: str | Path, registry: Registry, *, window_s: float = RESIM_WINDOW_S,
                       tolerance_m: float = RESIM_TOLERANCE_M, out_dir: str | Path | None = None) -> ResimRow:
    """Rebuild, re-simulate and compare one imported example; never raises for a damaged or incomplete example
    (its row says why). ``out_dir``: where to write the rebuilt spec and its re-simulation
    (``<out_dir>/<id>/scene_spec.json``, ``trajectories.npz``, ``contacts.json``)."""
    path = Path(bundle_dir)
    t0 = time.perf_counter()
    row = ResimRow(sample_id=path.name, task="", partition="", outcome="failed", envelope="no envelope")
    try:
        sample = Sample(path)
        row.task, row.partition = str(sample.metadata.get("task", "")), str(sample.metadata.get("partition", ""))
        if not sample.imported:
            row.outcome, row.reason = "cannot", "not imported from the published set (it has its own scene spec)"
            return row
        rebuilt = rebuild(sample, registry)
        if isinstance(rebuilt, Cannot):
            row.outcome, row.reason = "cannot", f"cannot rebuild its scene: {rebuilt.reason}"
            return row
        row.notes = dict(rebuilt.notes)
        try:
            result = simulate(rebuilt.spec, registry)
        except RuntimeError as exc:  # Bullet produced non-finite poses, or its cache could not be kept
            row.reason = f"the re-simulation failed: {exc}"
            return row
        R_c, t_c = sample.camera_pose
        actors = [b.name for b in rebuilt.spec.bodies if b.role == "active"]
        row.drift = compare(sample.trajectory, result.trajectory, actors, sample.K, R_c, t_c, window_s, tolerance_m)
        row.outcome, row.reason = _verdict(row.drift, sample.trajectory.fps, tolerance_m)
        row.envelope = "ok" if row.outcome == "reproduced" else "no envelope"
        if out_dir is not None:
            write_simulation(Path(out_dir) / path.name, rebuilt.spec, result, overwrite=True)
    except (RigidBenchError, OSError) as exc:
        row.outcome, row.envelope, row.reason = "failed", "no envelope", f"cannot be read: {exc}"
    finally:
        row.seconds = time.perf_counter() - t0
    return row


# -- a set ------------------------------------------------------------------------------------------------------


@dataclass
class ResimTable:
    """Per-example rows of a set's re-simulation and their summary per task."""

    rows: list[ResimRow]
    window_s: float = RESIM_WINDOW_S
    tolerance_m: float = RESIM_TOLERANCE_M

    @property
    def with_envelope(self) -> list[str]:
        return [r.sample_id for r in self.rows if r.envelope == "ok"]

    def envelope_examples(self) -> dict[str, dict[str, Any]]:
        """example id -> {"status": "ok" | "no envelope", "reason"} (the statuses of envelope.json)."""
        return {r.sample_id: {"status": r.envelope, "reason": r.reason} for r in self.rows}

    def by_task(self) -> list[dict[str, Any]]:
        """One summary per task (sorted), then one for the whole set ("all")."""
        tasks = sorted({r.task for r in self.rows})
        return [summarise([r for r in self.rows if r.task == t], t) for t in tasks] + [summarise(self.rows, "all")]

    def to_dict(self) -> dict[str, Any]:
        return {"tolerance": {"window_s": self.window_s, "max_position_error_m": self.tolerance_m,
                              "rule": "an example gets an envelope when the largest position error of any active "
                                      "actor over the window is at most the tolerance"},
                "examples": len(self.rows), "with_envelope": len(self.with_envelope),
                "by_task": self.by_task(), "rows": [r.to_dict() for r in self.rows]}


def _finite_or_none(value: Any) -> Any:
    """``value`` with every non-finite float (a pixel error behind the camera) replaced by None, for JSON."""
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, dict):
        return {k: _finite_or_none(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_finite_or_none(v) for v in value]
    return value


def _median(values: list[float]) -> float | None:
    finite = [v for v in values if math.isfinite(v)]
    return float(np.median(finite)) if finite else None


def summarise(rows: Sequence[ResimRow], task: str) -> dict[str, Any]:
    """count, outcomes, how many have an envelope and their share, and the median errors of the re-simulated rows."""
    drifts = [r.drift for r in rows if r.drift is not None]
    return {"task": task, "count": len(rows), **{k: sum(r.outcome == k for r in rows) for k in OUTCOMES},
            "with_envelope": sum(r.envelope == "ok" for r in rows),
            "share_within_tolerance": (sum(r.envelope == "ok" for r in rows) / len(rows)) if rows else None,
            "median_max_m": _median([d.max_m for d in drifts]), "median_final_m": _median([d.final_m for d in drifts]),
            "median_max_px": _median([d.max_px for d in drifts]),
            "median_max_deg": _median([d.max_deg for d in drifts]),
            "median_clip_max_m": _median([d.clip_max_m for d in drifts])}


def resimulate_published(split_dir: str | Path, registry: Registry | None = None, *, ids: Iterable[str] | None = None,
                         out_dir: str | Path | None = None, window_s: float = RESIM_WINDOW_S,
                         tolerance_m: float = RESIM_TOLERANCE_M) -> ResimTable:
    """Re-simulate every imported example of ``split_dir`` (a split directory such as ``DATA/eval``, or a data root
    holding one) at zero perturbation; returns the table (``ResimTable.to_dict()`` for JSON). ``ids``: only these
    examples. ``out_dir``: also write each rebuilt spec with its re-simulation (``<out_dir>/<id>/``) and the table
    (``<out_dir>/resimulation.json``)."""
    registry = registry or load_registry()
    dirs = bundle_dirs(resolve_split_dir(split_dir))
    if ids is not None:
        wanted = set(ids)
        dirs = [d for d in dirs if d.name in wanted]
    rows = []
    for d in dirs:
        row = resimulate_example(d, registry, window_s=window_s, tolerance_m=tolerance_m, out_dir=out_dir)
        log.info("example %s: %s%s", row.sample_id, row.outcome, f" ({row.reason})" if row.reason else "")
        rows.append(row)
    table = ResimTable(rows=rows, window_s=window_s, tolerance_m=tolerance_m)
    if out_dir is not None:
        Path(out_dir).mkdir(parents=True, exist_ok=True)
        write_json(Path(out_dir) / RESULT_FILE, table.to_dict(), allow_nan=False)
    return table


__all__ = ["RESIM_WINDOW_S", "RESIM_TOLERANCE_M", "RESULT_FILE", "OUTCOMES", "Drift", "ResimRow", "ResimTable",
           "support_top_from_contacts", "support_top", "pixel_centres", "measure_ramp", "compare", "rebuild",
           "resimulate_example", "resimulate_published", "summarise"]
