"""Physics counterfactuals: the reference example re-simulated and re-rendered with one thing changed.

Each predictor rebuilds the reference's resolved ``SceneSpec`` (``scene_spec.json``: same scene,
camera, task rotation and seed), changes one physical quantity by severity s in [0, 1], simulates
it again in Bullet and renders it with Cycles at the reference's own render preset (recorded in its
``metadata.json``; a ``test`` bundle re-renders at ``test``) on the same kind of device (CPU when the
reference was rendered on the CPU). At s = 0 nothing changes and the re-render reproduces the
reference: the simulation and Cycles (fixed seed) are deterministic.

Severities (s = 0 is the reference in every mode):

- ``gravity``: g -> g (1 + s), up to twice Earth gravity at s = 1;
- ``restitution``: every surface in the scene (actors, ramps, support and floor) gets
  e -> e + s (1 - e); Bullet multiplies the two restitutions of a contact, so at s = 1 every
  collision is elastic;
- ``friction``: every surface gets mu -> mu (1 - s); frictionless at s = 1;
- ``mass``: active actors in spec order alternately get m (1 + 4 s) and m / (1 + 4 s), so the mass
  ratio of neighbouring actors changes by up to 25x. Mass matters only where actors collide with
  each other; a single free actor moves exactly as in the reference;
- ``depth-offset``: every active actor is rendered displaced by 0.5 s metres along its viewing ray
  (the line from the camera centre through its origin) at every frame, frame 0 included; the
  simulation is the reference's. Its image position is unchanged (it looks nearer and larger)
  while its depth drops by about the offset. The offset is *toward* the camera: a move away would
  push resting actors into the support below them (the camera looks down by 10 degrees), which
  would then hide them.

The world state of a counterfactual comes from its own render: masks and depth from its passes,
and the reference's ground-truth tracks re-derived for it, i.e. the same body-frame points (the
reference's query points on its frame-0 mask, ``tracks.npz`` ``points_body_m``) carried by the
counterfactual pose, projected with the same camera, visible by the same rule against the new masks
and depth (``groundtruth.tracks``).

The counterfactual bundle is rendered into a temporary directory that is removed afterwards, or
into ``bundle_dir`` when one is given (kept there, e.g. for ``rigidbench show``; for
``depth-offset`` its trajectories and tracks are the undisplaced simulation's). The temporary directory
lives in ``scratch_dir`` (``rigidbench predict`` passes ``OUT/.scratch``), in a folder of this process
(``<host>-<pid>``) that also holds Blender's own ``blender_*`` folder when this process first imports
bpy; what a killed run left there is removed by the next run (``scratch_bundle_dir``).
"""

from __future__ import annotations

import contextlib
import dataclasses
import logging
import os
import shutil
import socket
import sys
import tempfile
from pathlib import Path
from typing import Callable, Iterator

import numpy as np

from ..blender.overrides import RenderOverrides
from ..blender.render import render_spec
from ..blender.session import import_bpy_into
from ..config import Registry, registry as packaged_registry
from ..errors import BundleError, PredictionError
from ..groundtruth.bundle import Sample
from ..groundtruth.camera_model import project
from ..groundtruth.tracks import carry, visibility
from ..perception.gt import WorldState, static_background
from ..rotations import quat_to_matrix
from ..scene_spec.types import BodyPhysics
from .base import Prediction

log = logging.getLogger(__name__)

MAX_GRAVITY_FACTOR = 2.0  # g (1 + s): twice Earth gravity at s = 1
MAX_MASS_FACTOR = 5.0  # alternate actors x (1 + 4 s) and / (1 + 4 s)
MAX_DEPTH_OFFSET_M = 0.5  # along the viewing ray, toward the camera, at s = 1


# -- what changes (pure: SceneSpec and Registry in, SceneSpec and Registry out) ---------------------


def _with_body_physics(spec, registry, change: Callable) -> tuple:
    """Apply ``change(BodyPhysics) -> BodyPhysics`` to every body, the support and the floor (whose
    physics the simulator takes from ``registry.sim``)."""
    bodies = tuple(dataclasses.replace(b, physics=change(b.physics)) for b in spec.bodies)
    support = dataclasses.replace(spec.support, physics=change(spec.support.physics))
    floor = change(BodyPhysics(0.0, registry.sim.passive_friction, registry.sim.passive_restitution))
    sim = dataclasses.replace(registry.sim, passive_friction=floor.friction, passive_restitution=floor.restitution)
    return (dataclasses.replace(spec, bodies=bodies, support=support), dataclasses.replace(registry, sim=sim))


def gravity_change(spec, registry, severity: float) -> tuple:
    """(spec, registry) with gravity g (1 + s)."""
    g = spec.sim.gravity_m_s2 * (1.0 + (MAX_GRAVITY_FACTOR - 1.0) * severity)
    return dataclasses.replace(spec, sim=dataclasses.replace(spec.sim, gravity_m_s2=g)), registry


def restitution_change(spec, registry, severity: float) -> tuple:
    """(spec, registry) with every surface's restitution e + s (1 - e)."""
    return _with_body_physics(spec, registry, lambda p: dataclasses.replace(
        p, restitution=p.restitution + severity * (1.0 - p.restitution)))


def friction_change(spec, registry, severity: float) -> tuple:
    """(spec, registry) with every surface's friction mu (1 - s)."""
    return _with_body_physics(spec, registry, lambda p: dataclasses.replace(p, friction=p.friction * (1.0 - severity)))


def mass_change(spec, registry, severity: float) -> tuple:
    """(spec, registry) with active actors alternately (1 + 4 s) times heavier and lighter, in spec order."""
    factor = 1.0 + (MAX_MASS_FACTOR - 1.0) * severity
    bodies, k = [], 0
    for b in spec.bodies:
        if b.role == "active":
            scale = factor if k % 2 == 0 else 1.0 / factor
            b = dataclasses.replace(b, physics=dataclasses.replace(b.physics, mass_kg=b.physics.mass_kg * scale))
            k += 1
        bodies.append(b)
    return dataclasses.replace(spec, bodies=tuple(bodies)), registry


PHYSICS_CHANGES: dict[str, Callable] = {"gravity": gravity_change, "restitution": restitution_change,
                                        "friction": friction_change, "mass": mass_change}


def depth_offsets(positions_m: np.ndarray, camera_m: np.ndarray, offset_m: float) -> np.ndarray:
    """positions_m (A,T,3) actor origins; camera_m (3,) camera centre. Returns (A,T,3) translations
    of length ``offset_m`` along each origin's viewing ray, toward the camera."""
    towards = np.asarray(camera_m, np.float64) - np.asarray(positions_m, np.float64)
    return offset_m * towards / np.linalg.norm(towards, axis=-1, keepdims=True)


# -- scratch space ----------------------------------------------------------------------------------


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def process_scratch(scratch_dir: str | Path) -> Path:
    """``scratch_dir/<host>-<pid>``, this process's scratch folder, created; folders there of processes of
    this host that no longer run (a killed run's re-renders and Blender temporaries) are removed first."""
    scratch_dir = Path(scratch_dir)
    host = socket.gethostname()
    mine = scratch_dir / f"{host}-{os.getpid()}"
    if scratch_dir.is_dir():
        for folder in scratch_dir.iterdir():
            owner, _, pid = folder.name.rpartition("-")
            if folder != mine and owner == host and pid.isdigit() and not _alive(int(pid)):
                shutil.rmtree(folder, ignore_errors=True)
    mine.mkdir(parents=True, exist_ok=True)
    return mine


@contextlib.contextmanager
def scratch_bundle_dir(sample_id: str, scratch_dir: str | Path | None = None) -> Iterator[Path]:
    """A temporary directory for one example's re-rendered bundle, removed afterwards: inside
    ``process_scratch(scratch_dir)`` when given (the run's output folder), else in $TMPDIR. This example's
    leftovers from an earlier failure of this process are removed first."""
    if scratch_dir is None:
        with tempfile.TemporaryDirectory(prefix=f"rigidbench-{sample_id}-") as tmp:
            yield Path(tmp)
        return
    mine = process_scratch(scratch_dir)
    import_bpy_into(mine)  # Blender's own temporary folder goes here too; a missing bpy is reported per example
    for stale in mine.glob(f"rigidbench-{sample_id}-*"):
        shutil.rmtree(stale, ignore_errors=True)
    with tempfile.TemporaryDirectory(prefix=f"rigidbench-{sample_id}-", dir=mine) as tmp:
        yield Path(tmp)


# -- render -----------------------------------------------------------------------------------------


@contextlib.contextmanager
def blender_output_silenced() -> Iterator[None]:
    """Send file descriptor 1 (where Blender prints every render step) to /dev/null for the block."""
    sys.stdout.flush()
    saved = os.dup(1)
    try:
        with open(os.devnull, "wb") as null:
            os.dup2(null.fileno(), 1)
        yield
    finally:
        sys.stdout.flush()
        os.dup2(saved, 1)
        os.close(saved)


def render_target(sample, spec, registry) -> tuple:
    """(render preset, Cycles device request) that re-render ``spec`` like the reference ``sample``: its preset,
    which must still be configured at its resolution, and its device kind (CPU when the reference was rendered
    on the CPU). A PredictionError naming the example otherwise, or when ``spec`` has no camera."""
    ref_id = sample.sample_id
    preset_name = sample.metadata.get("preset")
    try:
        preset = registry.preset(preset_name)
    except KeyError:
        raise PredictionError(f"example {ref_id}: its render preset '{preset_name}' is not configured here; "
                                  "re-render the reference with `rigidbench render`") from None
    if tuple(preset.resolution) != sample.resolution:
        raise PredictionError(f"example {ref_id}: rendered at {sample.resolution} but preset '{preset_name}' is "
                                  f"{tuple(preset.resolution)} here; re-render the reference with this configuration")
    if spec.camera is None:
        raise PredictionError(f"example {ref_id}: {sample.path / 'scene_spec.json'} has no camera; re-render "
                                  "the reference with `rigidbench render`")
    device = "cpu" if sample.metadata.get("render", {}).get("device_kind", "CPU") == "CPU" else "auto"
    return preset, device


def render_counterfactual(sample, spec, registry, out_dir: str | Path, overrides=None) -> Path:
    """Simulate and render ``spec`` like the reference ``sample`` (its preset, device kind and camera)
    into the new bundle directory ``out_dir``; returns it. Raises PredictionError naming the example."""
    ref_id = sample.sample_id
    preset, device = render_target(sample, spec, registry)
    try:
        with blender_output_silenced():
            path = render_spec(spec, registry, preset, Path(out_dir), device=device, overrides=overrides)
    except (RuntimeError, BundleError) as exc:
        raise PredictionError(f"example {ref_id}: the counterfactual render failed: {exc}") from exc
    except ImportError as exc:  # no bpy: this predictor cannot run here; say so per example
        raise PredictionError(f"example {ref_id}: {exc}") from exc
    cf = Sample(path)
    if cf.actor_names != sample.actor_names or cf.n_frames != sample.n_frames or cf.resolution != sample.resolution:
        raise PredictionError(f"example {ref_id}: the counterfactual has actors {cf.actor_names}, "
                                  f"{cf.n_frames} frames at {cf.resolution}; the reference {sample.actor_names}, "
                                  f"{sample.n_frames} frames at {sample.resolution}")
    return path


# -- world state ------------------------------------------------------------------------------------


def carried_tracks(sample, rotations: np.ndarray, positions_m: np.ndarray, masks: np.ndarray,
                   depth_m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The reference's GT query points (body frame) carried by other poses: rotations (N,T,3,3),
    positions_m (N,T,3) of all N actors; masks (T,N,H,W) bool and depth_m (T,H,W) of the clip that
    shows them. Returns tracks (P,T,2) float32 px and visibility (P,T) bool, in reference order."""
    tr = sample.tracks
    R_c, t_c = sample.camera_pose
    K = sample.K
    P, T = tr["tracks"].shape[0], masks.shape[0]
    uv_all = np.zeros((P, T, 2), np.float32)
    vis_all = np.zeros((P, T), bool)
    for a in np.unique(tr["actor_index"]):
        mine = np.flatnonzero(tr["actor_index"] == a)
        world = carry(tr["points_body_m"][mine], rotations[a, :T], positions_m[a, :T])
        uv, z = project(world, K, R_c, t_c)
        uv_all[mine] = uv
        vis_all[mine] = visibility(uv, z, masks[:, a], depth_m)
    return uv_all, vis_all


def world_state(sample, quat_wxyz: np.ndarray, positions_m: np.ndarray, masks: np.ndarray, depth_m: np.ndarray,
                fps: float) -> WorldState:
    """The world state of a re-simulated clip of reference ``sample``: quat_wxyz (N,T,4) and positions_m (N,T,3)
    of all N actors as shown, masks (T,N,H,W) bool and depth_m (T,H,W) of its passes, at ``fps``; the
    reference's ground-truth points carried by these poses (``carried_tracks``), a locked camera."""
    T = masks.shape[0]
    tracks, vis = carried_tracks(sample, quat_to_matrix(quat_wxyz[:, :T]), positions_m[:, :T], masks, depth_m)
    affine, flow = static_background(T)
    return WorldState(np.arange(T) / float(fps), masks[:, sample.active_indices], depth_m.astype(np.float32), tracks,
                      vis, affine, flow)


def prediction_from_bundle(sample, cf, offsets_m: dict[str, np.ndarray] | None = None):
    """A ``Prediction`` showing counterfactual bundle ``cf`` of reference ``sample``; ``offsets_m``
    (actor name -> (T,3) m) are the render-time displacements ``cf`` was rendered with."""
    T = cf.n_frames
    traj = cf.trajectory
    positions = traj.positions_m[:, :T].copy()
    for name, off in (offsets_m or {}).items():
        positions[cf.actor_names.index(name)] += np.asarray(off, np.float64)[:T]
    state = world_state(sample, traj.quat_wxyz, positions, cf.masks, cf.depth, cf.fps)
    return Prediction(cf.frames, state.times_s, state)


# -- predictors -------------------------------------------------------------------------------------


def rendered_prediction(sample, spec, registry, bundle_dir: str | Path | None, offsets_m=None,
                        scratch_dir: str | Path | None = None):
    """The Prediction of ``spec`` re-simulated and rendered like reference ``sample`` (``render_counterfactual``),
    its bundle kept in ``bundle_dir`` or (None) in a scratch folder removed afterwards (``scratch_bundle_dir``);
    ``offsets_m``: render-time actor displacements (``blender.overrides.RenderOverrides``)."""
    overrides = RenderOverrides(offsets_m=offsets_m) if offsets_m else None
    if bundle_dir is not None:
        path = render_counterfactual(sample, spec, registry, bundle_dir, overrides)
        return prediction_from_bundle(sample, Sample(path), offsets_m)
    with scratch_bundle_dir(sample.sample_id, scratch_dir) as tmp:
        path = render_counterfactual(sample, spec, registry, tmp / sample.sample_id, overrides)
        return prediction_from_bundle(sample, Sample(path), offsets_m)


def physics_counterfactual(sample, change: str, severity: float, bundle_dir: str | Path | None = None,
                           registry: Registry | None = None, scratch_dir: str | Path | None = None):
    """Re-simulate and re-render ``sample`` with PHYSICS_CHANGES[change] at ``severity`` under ``registry``
    (default: the packaged configuration); returns a Prediction. ``scratch_dir``: see ``scratch_bundle_dir``."""
    base = registry if registry is not None else packaged_registry()
    spec, reg = PHYSICS_CHANGES[change](sample.spec, base, float(severity))
    log.info("example %s: rendering the %s counterfactual at severity %.3g", sample.sample_id, change, severity)
    return rendered_prediction(sample, spec, reg, bundle_dir, scratch_dir=scratch_dir)


def gravity(sample, severity: float, bundle_dir: str | Path | None = None, registry: Registry | None = None,
            scratch_dir: str | Path | None = None):
    return physics_counterfactual(sample, "gravity", severity, bundle_dir, registry, scratch_dir)


def restitution(sample, severity: float, bundle_dir: str | Path | None = None, registry: Registry | None = None,
                scratch_dir: str | Path | None = None):
    return physics_counterfactual(sample, "restitution", severity, bundle_dir, registry, scratch_dir)


def friction(sample, severity: float, bundle_dir: str | Path | None = None, registry: Registry | None = None,
             scratch_dir: str | Path | None = None):
    return physics_counterfactual(sample, "friction", severity, bundle_dir, registry, scratch_dir)


def mass(sample, severity: float, bundle_dir: str | Path | None = None, registry: Registry | None = None,
         scratch_dir: str | Path | None = None):
    return physics_counterfactual(sample, "mass", severity, bundle_dir, registry, scratch_dir)


def depth_offset(sample, severity: float, bundle_dir: str | Path | None = None, registry: Registry | None = None,
                 scratch_dir: str | Path | None = None):
    """Every active actor rendered 0.5 s m nearer the camera along its viewing ray, at every frame."""
    traj = sample.trajectory
    _, camera_m = sample.camera_pose
    active = sample.active_indices
    shift = depth_offsets(traj.positions_m[active, :sample.n_frames], camera_m, MAX_DEPTH_OFFSET_M * float(severity))
    offsets = {sample.actor_names[a]: shift[i] for i, a in enumerate(active)}
    log.info("example %s: rendering actors %.3g m nearer the camera", sample.sample_id,
             MAX_DEPTH_OFFSET_M * severity)
    reg = registry if registry is not None else packaged_registry()
    return rendered_prediction(sample, sample.spec, reg, bundle_dir, offsets, scratch_dir)


__all__ = ["PHYSICS_CHANGES", "gravity_change", "restitution_change", "friction_change",
           "mass_change", "depth_offsets", "render_target", "render_counterfactual", "carried_tracks", "world_state",
           "prediction_from_bundle", "rendered_prediction", "blender_output_silenced",
           "physics_counterfactual", "gravity", "restitution", "friction", "mass", "depth_offset",
           "scratch_bundle_dir", "process_scratch",
           "MAX_GRAVITY_FACTOR", "MAX_MASS_FACTOR", "MAX_DEPTH_OFFSET_M"]
