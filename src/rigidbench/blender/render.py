"""Cycles settings, scene dressing and per-frame passes for one example, in one Blender session.

Per example (paper, appendix A.3-A.4):
1. a geometry-only scene (actors at their frame-0 poses, support, floor and the environment) for
   the camera search (``camera.search_camera``), which fixes the task rotation and the camera;
2. ``physics.simulate`` on the resolved spec (Bullet, the same code as ``rigidbench simulate``);
3. the simulated scene is dressed (each actor's procedural model and the furnished environment,
   from ``blender.assets``), the camera is added and every frame is rendered from the rigid-body
   cache: first a data pass per frame (object index and Z through the compositor into 32-bit EXR),
   then the RGB frames (PNG).

The data passes are rendered separately with one sample and a 0.01 px pixel filter, so the index
and Z passes sample every pixel at its centre (Cycles writes them from the first sample only,
which the pixel filter otherwise jitters across the pixel); the RGB frames keep the full filter.
The data render uses an emission-only material override: the passes depend on geometry alone (the assets
use no alpha cut-outs or displacement), and the procedural shaders would dominate its cost.
Object indices: pass_index = k for the k-th actor (1..N, active objects and passive task geometry
such as ramps, in spec order); the support and the environment keep index 0.
"""

from __future__ import annotations

import dataclasses
import logging
import os
import shutil
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np

from ..atomic import atomic_dir
from ..config import RenderPreset, Registry
from ..groundtruth import bundle as B
from ..groundtruth.writer import write_bundle
from ..scene_spec.types import SceneSpec
from . import physics
from .assets import objects as asset_objects, scenes as asset_scenes
from .camera import add_camera, search_camera
from .physics import FLOOR_NAME, SUPPORT_NAME, scene_bodies
from .session import link_object, reset_scene

log = logging.getLogger(__name__)

DATA_FILTER_WIDTH_PX = 0.01
BEAUTY_FILTER_WIDTH_PX = 1.5  # Cycles' default Blackman-Harris width
BACKGROUND_DEPTH_M = 1e9  # Cycles writes 1e10 where a ray leaves the scene; stored as +inf
POSE_TOLERANCE_M = 1e-5
# A preset's denoise_quality -> (OpenImageDenoise quality, prefilter of its albedo and normal guides).
DENOISE_SETTINGS = {"high": ("HIGH", "ACCURATE"), "balanced": ("BALANCED", "FAST"), "fast": ("FAST", "FAST")}
DEVICE_CHOICES = ("auto", "cpu", "gpu")
SUPPORT_RGB = (0.55, 0.5, 0.45)  # a physics support the environment does not provide (hand-made specs)


@dataclass(frozen=True)
class RenderDevice:
    """The Cycles device: kind "CPU", "OPTIX" or "CUDA", and the device names used."""

    kind: str
    names: tuple[str, ...]

    @property
    def is_gpu(self) -> bool:
        return self.kind != "CPU"

    def describe(self) -> str:
        return f"{self.kind}: {', '.join(self.names)}" if self.names else self.kind


def _cpu_name() -> str:
    try:
        with open("/proc/cpuinfo", encoding="utf-8") as fh:
            for line in fh:
                if line.startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return "CPU"


def select_device(request: str = "auto") -> RenderDevice:
    """Pick the Cycles device: OptiX, else CUDA, else CPU for "auto"; "cpu" forces the CPU and
    "gpu" raises RuntimeError when no GPU is found. Also sets Cycles' preferences accordingly."""
    import bpy

    if request not in DEVICE_CHOICES:
        raise ValueError(f"unknown render device '{request}'; choose one of {', '.join(DEVICE_CHOICES)}")
    prefs = None if request == "cpu" else bpy.context.preferences.addons["cycles"].preferences
    return pick_device(prefs, request)


def pick_device(prefs: Any, request: str) -> RenderDevice:
    """``select_device`` on Cycles' add-on preferences ``prefs`` (None for "cpu"): the first of OptiX and
    CUDA with a device of its own type is enabled (its devices only) and returned."""
    if request != "cpu":
        prefs.refresh_devices()  # Blender does not probe GPUs at startup
        for kind in ("OPTIX", "CUDA"):
            try:
                devices = [d for d in prefs.get_devices_for_type(kind) if d.type == kind]
            except (TypeError, ValueError, RuntimeError) as exc:  # this build lacks the backend
                log.debug("Cycles %s backend unavailable: %s", kind, exc)
                continue
            if devices:
                prefs.compute_device_type = kind
                for d in prefs.devices:
                    d.use = d.type == kind
                return RenderDevice(kind, tuple(d.name for d in devices))
        if request == "gpu":
            raise RuntimeError("no OptiX or CUDA device is visible to Cycles; render with --device cpu or auto")
    return RenderDevice("CPU", (f"{_cpu_name()} ({os.cpu_count()} threads)",))


# Colour management of the RGB frames, set explicitly rather than left at Blender's default (AgX since
# 4.0). AgX desaturates bright saturated albedos towards beige/cream (a measured lemon at the preview
# preset: AgX (216, 192, 140) sRGB, AgX Punchy (200, 173, 109), Standard (242, 228, 99); a photo's
# lemon is about (240, 220, 60)), so the frames use the plain sRGB transfer ("Standard", no look),
# which maps the textures' sRGB albedos back to themselves under unit lighting, as a camera's
# standard picture profile roughly does. Recorded per bundle as render.color_management.
COLOR_MANAGEMENT = {"display_device": "sRGB", "view_transform": "Standard", "look": "None", "exposure": 0.0,
                    "gamma": 1.0}


def set_color_management(scene: Any) -> None:
    """Apply ``COLOR_MANAGEMENT`` to ``scene``."""
    scene.display_settings.display_device = COLOR_MANAGEMENT["display_device"]
    vs = scene.view_settings
    vs.view_transform = COLOR_MANAGEMENT["view_transform"]
    vs.look = COLOR_MANAGEMENT["look"]
    vs.exposure = COLOR_MANAGEMENT["exposure"]
    vs.gamma = COLOR_MANAGEMENT["gamma"]
    vs.use_curve_mapping = False


def configure_cycles(scene: Any, preset: RenderPreset, seed: int, device: RenderDevice,
                     threads: int | None = None) -> None:
    """Cycles settings shared by every frame (paper, table "Simulation and rendering configuration")."""
    r, c = scene.render, scene.cycles
    r.engine = "CYCLES"
    r.resolution_x, r.resolution_y = preset.resolution
    r.resolution_percentage = 100
    r.pixel_aspect_x = r.pixel_aspect_y = 1.0
    r.use_motion_blur = False
    r.use_persistent_data = bool(preset.persistent_data)
    r.film_transparent = False
    r.use_sequencer = False
    r.use_border = False
    if threads:
        r.threads_mode, r.threads = "FIXED", int(threads)
    else:
        r.threads_mode = "AUTO"
    c.device = "GPU" if device.is_gpu else "CPU"
    c.seed = int(seed) % (2**31 - 1)
    c.use_animated_seed = False
    c.max_bounces = preset.max_bounces
    c.diffuse_bounces = preset.diffuse_bounces
    c.glossy_bounces = preset.glossy_bounces
    c.transmission_bounces = preset.transmission_bounces
    c.pixel_filter_type = "BLACKMAN_HARRIS"
    light_transport(scene, preset)
    set_color_management(scene)
    r.image_settings.file_format = "PNG"
    r.image_settings.color_mode = "RGB"
    r.image_settings.color_depth = "8"
    r.use_file_extension = True
    r.use_overwrite = True
    layer = scene.view_layers[0]
    layer.use_pass_object_index = True
    layer.use_pass_z = True


def beauty_mode(scene: Any, preset: RenderPreset, device: RenderDevice) -> None:
    """Settings for the RGB frames: the preset's samples, adaptive threshold and denoiser."""
    c = scene.cycles
    c.samples = preset.samples
    c.use_adaptive_sampling = preset.adaptive_threshold is not None
    if preset.adaptive_threshold is not None:
        c.adaptive_threshold = preset.adaptive_threshold
    c.use_denoising = bool(preset.denoise)
    if preset.denoise:
        c.denoiser = "OPTIX" if device.kind == "OPTIX" else "OPENIMAGEDENOISE"
        c.denoising_quality, c.denoising_prefilter = DENOISE_SETTINGS[preset.denoise_quality]
        c.denoising_input_passes = "RGB_ALBEDO_NORMAL"
        c.denoising_use_gpu = device.is_gpu
    c.filter_width = BEAUTY_FILTER_WIDTH_PX
    c.max_bounces = preset.max_bounces
    scene.view_layers[0].material_override = None
    scene.render.use_compositing = False
    if preset.light_transport == "fast":
        drop_bump_mapping()


def light_transport(scene: Any, preset: RenderPreset) -> None:
    """``light_transport: fast``: indirect light past the first bounce approximated by ambient occlusion
    against the world (Cycles "fast GI"), and one light picked per shading point by power rather than
    by the light tree; about 2.5x cheaper per sample in the furnished rooms. ``full`` path traces every
    bounce up to the preset's limits with the light tree."""
    c, fast = scene.cycles, preset.light_transport == "fast"
    c.use_fast_gi = fast
    c.fast_gi_method = "REPLACE"
    c.ao_bounces_render = 1
    c.use_light_tree = not fast


def drop_bump_mapping() -> int:
    """Disconnect every Bump node from the shader normals it feeds, in all materials; returns how many links
    were removed. Bump mapping evaluates its height graph three times per shading point and its millimetre
    detail is below a pixel at the fast presets' resolution (a quarter of the cost of a `preview` frame)."""
    import bpy

    removed = 0
    for mat in bpy.data.materials:
        if not mat.use_nodes or mat.node_tree is None:
            continue
        links = mat.node_tree.links
        for link in [lk for lk in links if lk.from_node.bl_idname == "ShaderNodeBump"
                     and lk.to_socket.name == "Normal" and lk.to_node.bl_idname != "ShaderNodeBump"]:
            links.remove(link)
            removed += 1
    return removed


def _override_material() -> Any:
    import bpy

    mat = bpy.data.materials.get("rb_data_pass")
    if mat is None:  # pure emission: no BSDF, so Cycles samples no lights and casts no shadow rays
        mat = bpy.data.materials.new("rb_data_pass")
        mat.use_nodes = True
        nodes = mat.node_tree.nodes
        nodes.clear()
        emit = nodes.new("ShaderNodeEmission")
        out = nodes.new("ShaderNodeOutputMaterial")
        mat.node_tree.links.new(emit.outputs["Emission"], out.inputs["Surface"])
    return mat


def data_mode(scene: Any) -> None:
    """Settings for the index and Z passes: one sample at each pixel centre, no light bounces, and a
    plain material override (the passes depend on geometry only; skipping the procedural shaders
    makes them several times cheaper)."""
    c = scene.cycles
    c.samples = 1
    c.use_adaptive_sampling = False
    c.use_denoising = False
    c.filter_width = DATA_FILTER_WIDTH_PX
    c.max_bounces = 0
    scene.view_layers[0].material_override = _override_material()
    scene.render.use_compositing = True


def add_pass_output(scene: Any, directory: Path) -> Any:
    """Compositor: Render Layers IndexOB and Depth -> one 32-bit multilayer EXR per frame
    (``directory/####.exr``, Blender frame number); returns the File Output node."""
    scene.use_nodes = True
    tree = scene.node_tree
    layers = next((n for n in tree.nodes if n.bl_idname == "CompositorNodeRLayers"), None)
    if layers is None:
        layers = tree.nodes.new("CompositorNodeRLayers")
    out = tree.nodes.new("CompositorNodeOutputFile")
    out.base_path = str(directory) + os.sep
    out.format.file_format = "OPEN_EXR_MULTILAYER"
    out.format.color_depth = "32"
    out.format.exr_codec = "ZIP"
    out.layer_slots.clear()
    out.layer_slots.new("index")
    out.layer_slots.new("depth")
    tree.links.new(layers.outputs["IndexOB"], out.inputs["index"])
    tree.links.new(layers.outputs["Depth"], out.inputs["depth"])
    return out


def pass_file(directory: Path, frame: int) -> Path:
    """EXR written by ``add_pass_output`` for Blender frame ``frame``."""
    return Path(directory) / f"{frame:04d}.exr"


def read_passes(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """One pass EXR -> (object index (H,W) int16, Z depth (H,W) float32 m, +inf where nothing is hit)."""
    import OpenEXR

    try:
        channels = OpenEXR.File(str(path)).parts[0].channels
        index = channels["index.V"].pixels
        depth = np.array(channels["depth.V"].pixels, dtype=np.float32)
    except (OSError, RuntimeError, KeyError) as exc:
        raise RuntimeError(f"{path}: cannot read the index/depth passes ({exc}); the compositor output "
                           "may be missing or truncated") from exc
    depth[depth >= BACKGROUND_DEPTH_M] = np.inf
    return np.rint(index).astype(np.int16), depth


# -- dressing ------------------------------------------------------------------------------------


@dataclass
class Dressing:
    """Rendered bpy object per actor (spec order, each a procedural model parented to its hidden physics
    body), the environment (``assets.scenes.Environment``) and the physics bodies hidden from render."""

    render_objects: dict[str, Any]
    environment: Any
    hidden: list[str] = field(default_factory=list)


def _plain_material(name: str, rgb: tuple[float, float, float], roughness: float = 0.5) -> Any:
    import bpy

    mat = bpy.data.materials.get(name) or bpy.data.materials.new(name)
    mat.use_nodes = True
    bsdf = mat.node_tree.nodes.get("Principled BSDF")
    bsdf.inputs["Base Color"].default_value = (*rgb, 1.0)
    bsdf.inputs["Roughness"].default_value = roughness
    return mat


def _set_material(obj: Any, mat: Any) -> None:
    obj.data.materials.clear()
    obj.data.materials.append(mat)


def _hide(obj: Any) -> None:
    """Hide a physics stand-in from render and from ``scene.ray_cast`` (which skips objects hidden
    in the view layer), so rays reach the dressed mesh that coincides with it."""
    obj.hide_render = True
    obj.hide_set(True)


def dress_scene(scene: Any, spec: SceneSpec, registry: Registry, objects: dict[str, Any],
                environment: bool = True) -> Dressing:
    """Give the physics scene its looks. ``objects`` maps body name (actors, "support", "floor") to
    the physics bpy object. Each actor gets its procedural model as a child of its physics object
    (which is hidden from render) and the scene's environment is built; the physics floor, and the
    physics support when the environment has a support of its name, are hidden from render. A
    support the environment lacks (a hand-made spec) stays visible in a plain material. Without
    ``environment`` (data passes of a scene rebuilt from a published example, whose room is not ours)
    no environment is built and the physics support and floor stay visible in plain materials."""
    import bpy

    render_objects: dict[str, Any] = {}
    hidden: list[str] = []
    for body in spec.bodies:
        phys = objects[body.name]
        name = f"{body.name}.render"
        if body.ramp is not None:
            obj = asset_objects.build_ramp(body.ramp, registry.material(body.ramp.material), name)
        else:
            obj = asset_objects.build_object(registry.object(body.asset), name)
        obj.parent = phys
        obj.matrix_parent_inverse.identity()
        obj.location, obj.rotation_mode = (0.0, 0.0, 0.0), "QUATERNION"
        obj.rotation_quaternion, obj.scale = (1.0, 0.0, 0.0, 0.0), (1.0, 1.0, 1.0)
        _hide(phys)
        hidden.append(body.name)
        render_objects[body.name] = obj
    built = asset_scenes.build_environment(registry.scene(spec.scene)) if environment else None
    for name in (SUPPORT_NAME, FLOOR_NAME):
        if name in objects and built is not None and (name == FLOOR_NAME or spec.support.name in built.supports):
            _hide(objects[name])
            hidden.append(name)
    for name in (SUPPORT_NAME, FLOOR_NAME):
        if name in objects and name not in hidden:
            _set_material(objects[name], _plain_material(f"rb_{name}", SUPPORT_RGB, 0.7))
    for obj in scene.objects:
        obj.pass_index = 0
    for k, body in enumerate(spec.bodies, start=1):
        render_objects[body.name].pass_index = k
    bpy.context.view_layer.update()
    return Dressing(render_objects=render_objects, environment=built, hidden=hidden)


# -- one example --------------------------------------------------------------------------------


@dataclass
class ExampleRender:
    """What one example's Blender session produced (RGB frames are already on disk)."""

    spec: SceneSpec  # with task rotation, camera and render preset resolved
    simulation: Any  # physics.SimulationResult over all simulated frames
    index: np.ndarray  # (T,H,W) int16 object index per pixel (0 = not an actor)
    depth_m: np.ndarray  # (T,H,W) float32 Z pass, +inf where nothing is hit
    device: RenderDevice
    seconds: dict[str, float]
    software: dict[str, str]
    color_management: dict[str, Any]


def build_search_scene(spec: SceneSpec, registry: Registry) -> tuple[Any, dict[str, Any], Dressing]:
    """Reset Blender; link every physics body's mesh (no rigid bodies) at its frame-0 pose and dress
    the scene. Returns (scene, physics objects by name, dressing)."""
    scene = reset_scene()
    objects = {}
    for body in scene_bodies(spec, registry):
        obj = link_object(scene, body.name, body.mesh.vertices, body.mesh.faces)
        obj.rotation_mode = "QUATERNION"
        obj.location = body.position_m
        obj.rotation_quaternion = body.quat_wxyz
        objects[body.name] = obj
    return scene, objects, dress_scene(scene, spec, registry, objects)


def resolve_camera(spec: SceneSpec, registry: Registry) -> SceneSpec:
    """Run the camera search (paper A.3) in a geometry-only scene; returns the resolved spec."""
    scene, objects, dressing = build_search_scene(spec, registry)
    active = [dressing.render_objects[b.name] for b in spec.active]
    posed = {b.name: objects[b.name] for b in spec.bodies}
    return search_camera(spec, registry.camera, scene, posed, active, actors=list(dressing.render_objects.values()),
                         scene_id=dressing.environment.scene_id)


def _check_poses(objects: Sequence[Any], positions_m: np.ndarray, frame: int, sample_id: str) -> None:
    now = np.array([tuple(o.matrix_world.translation) for o in objects])
    err = float(np.abs(now - positions_m[:, frame]).max()) if len(now) else 0.0
    if err > POSE_TOLERANCE_M:
        raise RuntimeError(f"example {sample_id}: rendered frame {frame} is {err:.2e} m away from the simulated "
                           "trajectory; the rigid-body cache was invalidated between simulation and render")


def render_example(spec: SceneSpec, registry: Registry, preset: RenderPreset, frames_dir: Path, pass_dir: Path,
                   device: str = "auto", threads: int | None = None,
                   on_frame: Callable[[int, int], None] | None = None, overrides: Any = None,
                   rgb_frames: Callable[[Any], Sequence[int]] | None = None) -> ExampleRender:
    """Camera search, simulation and render of one example in this process's Blender.

    RGB frames go to ``frames_dir/00000.png ...`` and pass EXRs to ``pass_dir``; ``on_frame(done,
    total)`` reports progress over the 2T renders (T data passes, then T RGB frames). ``overrides``
    (``overrides.RenderOverrides``) swaps actor materials or offsets rendered actor poses.
    ``rgb_frames(simulation)``, if given, picks the only frames whose RGB is rendered (the gallery's
    event frames); the data passes still cover every frame. Such a render is not a bundle."""
    import bpy

    seconds: dict[str, float] = {}
    t0 = time.perf_counter()
    if spec.camera is None:
        spec = resolve_camera(spec, registry)
    seconds["camera_search"] = time.perf_counter() - t0
    spec = _with_preset(spec, preset.name)
    t1 = time.perf_counter()
    sim = physics.simulate(spec, registry)
    seconds["simulate"] = time.perf_counter() - t1
    T = min(preset.frames, sim.frames)
    t2 = time.perf_counter()
    scene = bpy.context.scene
    objects = {o.name: o for o in scene.objects}
    dressing = dress_scene(scene, spec, registry, objects)
    if overrides is not None:
        overrides.check(tuple(b.name for b in spec.bodies), T, spec.sample_id)
        overrides.apply_dressing(dressing, registry)
    add_camera(scene, spec.camera)
    chosen = select_device(device)
    configure_cycles(scene, preset, spec.seed, chosen, threads)
    pass_dir.mkdir(parents=True, exist_ok=True)
    frames_dir.mkdir(parents=True, exist_ok=True)
    add_pass_output(scene, pass_dir)
    seconds["setup"] = time.perf_counter() - t2
    actors = [objects[b.name] for b in spec.bodies]
    W, H = preset.resolution
    index = np.zeros((T, H, W), np.int16)
    depth = np.zeros((T, H, W), np.float32)
    t3, c3 = time.perf_counter(), time.process_time()
    data_mode(scene)
    for f in range(T):
        scene.frame_set(f + 1)
        _check_poses(actors, sim.trajectory.positions_m, f, spec.sample_id)
        if overrides is not None:
            overrides.pose(objects, dressing, f)
        bpy.ops.render.render(write_still=False)
        index[f], depth[f] = read_passes(pass_file(pass_dir, f + 1))
        if on_frame:
            on_frame(f + 1, 2 * T)
    seconds["passes"] = time.perf_counter() - t3
    seconds["passes_cpu"] = time.process_time() - c3
    t4, c4 = time.perf_counter(), time.process_time()
    beauty_mode(scene, preset, chosen)
    wanted = range(T) if rgb_frames is None else sorted({int(f) for f in rgb_frames(sim) if 0 <= f < T})
    for k, f in enumerate(wanted):
        scene.frame_set(f + 1)
        if overrides is not None:
            overrides.pose(objects, dressing, f)
        scene.render.filepath = str(Path(frames_dir) / f"{f:05d}.png")
        bpy.ops.render.render(write_still=True)
        if on_frame:
            on_frame(T + k + 1, T + len(wanted))
    seconds["rgb"] = time.perf_counter() - t4
    seconds["rgb_cpu"] = time.process_time() - c4  # CPU time of all render threads (wall time suffers on a busy machine)
    vs = scene.view_settings
    return ExampleRender(
        spec=spec, simulation=sim, index=index, depth_m=depth, device=chosen, seconds=seconds,
        software={"blender": bpy.app.version_string, "blender_build": bpy.app.build_hash.decode(errors="replace")},
        color_management={"view_transform": vs.view_transform, "look": vs.look, "exposure": vs.exposure,
                          "gamma": vs.gamma, "display_device": scene.display_settings.display_device})


def render_spec(spec: SceneSpec, registry: Registry, preset: RenderPreset, final_dir: Path, device: str = "auto",
                threads: int | None = None, on_frame: Callable[[int, int], None] | None = None,
                overrides: Any = None) -> Path:
    """Render a SceneSpec into the bundle directory ``final_dir`` in this process (bpy must be
    importable); the camera search runs unless ``spec.camera`` is set. ``overrides`` (a
    ``blender.overrides.RenderOverrides``) changes actor materials or rendered poses, not the
    simulation. Returns ``final_dir``."""
    t0 = time.perf_counter()
    final_dir = Path(final_dir)
    if final_dir.exists():
        raise FileExistsError(f"{final_dir}: a bundle already exists; delete it to render this example again")
    with atomic_dir(final_dir) as tmp:  # .<id>.tmp beside it; a killed render's leftover is removed first
        passes = tmp / ".passes"
        result = render_example(spec, registry, preset, tmp / B.FRAMES_DIR, passes, device=device, threads=threads,
                                on_frame=on_frame, overrides=overrides)
        shutil.rmtree(passes)
        write_bundle(tmp, result, preset, time.perf_counter() - t0)
        problems = B.check_bundle(tmp)
        if problems:
            raise B.BundleError(f"example {spec.sample_id}: the new bundle is invalid: " + "; ".join(problems))
    return final_dir


def _with_preset(spec: SceneSpec, preset: str) -> SceneSpec:
    return dataclasses.replace(spec, render_preset=preset)


__all__ = ["RenderDevice", "select_device", "pick_device", "COLOR_MANAGEMENT", "set_color_management",
           "configure_cycles", "beauty_mode", "light_transport",
           "drop_bump_mapping", "DENOISE_SETTINGS", "data_mode", "add_pass_output",
           "pass_file", "read_passes", "Dressing", "dress_scene", "ExampleRender",
           "build_search_scene", "resolve_camera", "render_example", "render_spec", "DEVICE_CHOICES"]
