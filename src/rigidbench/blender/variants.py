"""Data passes of re-simulated variants of one example, in one Blender scene kept between them (the
geometry-only physical twins, ``predictors.twins``).

A variant differs from its reference only in what a SceneSpec fixes at frame 0 and the physics that
follows: the initial pose, mass, friction and restitution of the bodies, the support's and the floor's
friction and restitution (the registry's passive physics) and gravity; its geometry, scene, camera and
simulation settings are the reference's (``VariantScene.fits`` checks it).

``VariantScene(spec, registry, preset, pass_dir)`` builds the reference's scene once, as ``render_example``
does before its first pass: the rigid-body scene simulated (``physics.simulate``), dressed, the camera added,
Cycles in data mode (``render.data_mode``: one sample at each pixel centre, no bounces, the plain material
override) writing the index and Z passes through the compositor. The world shader is removed, since no pass
sees it: the first pass of a scene then costs tens of milliseconds rather than the seconds its HDRI's load
and shader compile take. ``passes(variant_spec, variant_registry)`` then frees the rigid-body cache, sets the
variant's initial poses and physics on the same Bullet bodies, steps the simulation again through the
preset's frames (Blender rebuilds its Bullet world from frame 1) and renders their data passes. Only the rigid bodies
change between variants, so Cycles (persistent data) keeps the environment's geometry between them.

The result equals a fresh ``render_example`` of the variant: the same trajectory (positions equal; a
quaternion may come back negated, the same rotation, and ``Trajectory`` makes them sign-continuous) and the
same object index and depth at every pixel (tests/integration/test_twins.py compares them).
"""

from __future__ import annotations

import dataclasses
import itertools
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..config import Registry, RenderPreset
from ..groundtruth.trajectory import Trajectory
from ..scene_spec.types import SceneSpec
from . import physics
from .camera import add_camera
from .render import add_pass_output, configure_cycles, data_mode, dress_scene, pass_file, read_passes, select_device
from .session import import_bpy

MARK = "rigidbench_variant_scene"  # a custom property naming the VariantScene that built the current scene
_TOKENS = itertools.count(1)


@dataclass
class VariantPasses:
    """What one variant's re-simulation and passes gave over the preset's T frames (only those are simulated:
    Bullet steps frame by frame, so they are those of the full simulation): its trajectory, the object index
    (T,H,W) int16 and depth (T,H,W) float32, and wall seconds."""

    trajectory: Trajectory
    index: np.ndarray
    depth_m: np.ndarray
    seconds: dict[str, float]


def fixed_part(spec: SceneSpec, registry: Registry) -> tuple:
    """What every variant of ``spec`` shares with it: the spec with the bodies' poses and physics, the support's
    physics and gravity blanked, and the registry's simulation settings but the floor's physics."""
    blank = (0.0, 0.0, 0.0)
    bodies = tuple(dataclasses.replace(b, position_m=blank, quat_wxyz=(1.0, *blank), physics=None) for b in spec.bodies)
    support = dataclasses.replace(spec.support, physics=None)
    sim = dataclasses.replace(spec.sim, gravity_m_s2=0.0)
    floorless = dataclasses.replace(registry.sim, passive_friction=0.0, passive_restitution=0.0)
    return dataclasses.replace(spec, bodies=bodies, support=support, sim=sim), floorless


class VariantScene:
    """The reference ``spec``'s dressed scene in this process's Blender, ready to render the data passes of its
    variants at ``preset`` on ``device`` (pass EXRs in ``pass_dir``); see the module docstring. Without
    ``environment`` the room is not built: the actors stand on the physics support and floor, both visible
    (``render.dress_scene``; a spec rebuilt from a published example, whose room is not ours)."""

    def __init__(self, spec: SceneSpec, registry: Registry, preset: RenderPreset, pass_dir: str | Path,
                 device: str = "cpu", environment: bool = True):
        if spec.camera is None:
            raise ValueError(f"example {spec.sample_id}: a variant scene needs the reference's resolved camera")
        t0 = time.perf_counter()
        self.reference, self.preset, self.pass_dir = fixed_part(spec, registry), preset, Path(pass_dir)
        self.token = next(_TOKENS)
        physics.simulate(spec, registry)
        scene = import_bpy().context.scene
        self.objects = {o.name: o for o in scene.objects}
        dress_scene(scene, spec, registry, self.objects, environment=environment)
        add_camera(scene, spec.camera)
        configure_cycles(scene, preset, spec.seed, select_device(device))
        self.pass_dir.mkdir(parents=True, exist_ok=True)
        add_pass_output(scene, self.pass_dir)
        data_mode(scene)
        scene.world = None  # no pass sees it (see the module docstring)
        scene[MARK] = self.token
        self.scene = scene
        self.build_s = time.perf_counter() - t0

    def alive(self) -> bool:
        """Blender's current scene is still the one this object built (nothing has reset it since)."""
        try:
            scene = import_bpy().context.scene
            return scene == self.scene and scene.get(MARK) == self.token
        except ReferenceError:  # the scene was freed
            return False

    def fits(self, spec: SceneSpec, registry: Registry, preset: RenderPreset) -> bool:
        """Whether ``spec`` under ``registry`` is a variant of this scene's reference at ``preset``, and the scene
        is still there."""
        return preset == self.preset and fixed_part(spec, registry) == self.reference and self.alive()

    def passes(self, spec: SceneSpec, registry: Registry) -> VariantPasses:
        """Re-simulate variant ``spec`` (with ``registry``'s floor physics) and render its data passes."""
        if not self.fits(spec, registry, self.preset):
            raise ValueError(f"example {spec.sample_id}: not a variant of the scene kept in Blender (its geometry, "
                             "camera or settings differ, or the scene was replaced); build a VariantScene for it")
        bpy = import_bpy()
        scene, seconds = self.scene, {}
        t0 = time.perf_counter()
        with bpy.context.temp_override(scene=scene, point_cache=scene.rigidbody_world.point_cache):
            bpy.ops.ptcache.free_bake()
        bodies = physics.scene_bodies(spec, registry)
        for body in bodies:
            obj = self.objects[body.name]
            obj.location, obj.rotation_quaternion = body.position_m, body.quat_wxyz
            rb = obj.rigid_body
            rb.friction, rb.restitution = float(body.physics.friction), float(body.physics.restitution)
            if body.role == "active":
                rb.mass = float(body.physics.mass_kg)
        scene.gravity = (0.0, 0.0, -float(spec.sim.gravity_m_s2))
        objects = [self.objects[b.name] for b in bodies]
        T = min(self.preset.frames, spec.sim.frames)
        positions, quats = physics.run_frames(scene, objects, T)  # the frames shown; Bullet steps them in order
        physics.freeze_cache(scene)
        if not np.isfinite(positions).all() or not np.isfinite(quats).all():
            raise RuntimeError(f"example {spec.sample_id}: Bullet produced non-finite poses")
        n = len(spec.bodies)
        trajectory = Trajectory(names=tuple(b.name for b in bodies[:n]), roles=tuple(b.role for b in bodies[:n]),
                                fps=float(spec.sim.fps), positions_m=positions[:n], quat_wxyz=quats[:n])
        seconds["simulate"] = time.perf_counter() - t0
        t1 = time.perf_counter()
        W, H = self.preset.resolution
        index, depth = np.zeros((T, H, W), np.int16), np.zeros((T, H, W), np.float32)
        for f in range(T):
            scene.frame_set(f + 1)
            bpy.ops.render.render(write_still=False)
            index[f], depth[f] = read_passes(pass_file(self.pass_dir, f + 1))
        seconds["passes"] = time.perf_counter() - t1
        return VariantPasses(trajectory, index, depth, seconds)


__all__ = ["MARK", "VariantPasses", "VariantScene", "fixed_part"]
