"""Physical twins: the reference re-simulated with its initial state and materials drawn within what one
frame cannot resolve (``scene_spec.envelope``; the numbers and their reasons: ``configs/envelope.yaml``).

A twin is a predictor like the physics counterfactuals: it rebuilds the reference's resolved SceneSpec
(same scene, camera, task rotation and seed), perturbs it (``perturb_spec``) with the example's
generation seed ``ctx.seed`` (so ``predict twin --samples N`` makes N different twins, sample k seeded by
``sample_seed``), simulates it in Bullet and renders it with Cycles at the reference's preset and device
kind. Its scale multiplies every deviation of the envelope: the ``scale`` option when given (any number
>= 0), else the severity (s in [0, 1]; the default 1 is the envelope as configured). At scale 0 the twin is
the reference's own spec, and the re-simulation and re-render reproduce the reference.

A draw that brings two active actors within their collision margins (convex hulls closer than twice the
active margin, ``groundtruth.contacts``) where the reference's are apart is not a possible initial state
of the same scene (Bullet would push the two apart at once); it is drawn again (``apart_as_in``).

Geometry-only mode (option ``geometry_only``): no path tracing. The twin is simulated and only its data
passes (object index and Z, one sample at each pixel centre, the very passes of a full render) are
rendered, so its trajectories, masks, depth and carried tracks equal a full render's exactly. The
reference's dressed scene is kept in Blender between the twins of an example (``blender.variants``): each
twin re-simulates the same Bullet bodies from its own initial state and renders its passes, without
building the room again (``GeometryTwins``). Its video is no render: every frame is the
reference's first frame (the input every model is given) with each actor's silhouette of that frame
painted in a flat colour (``SILHOUETTE_RGB``), and its world state is marked ``geometry_only``, which makes
``--perception gt`` skip the appearance measurements (SSIM, LPIPS, IdDrift, BGDrift) with the reason
"geometry-only twin: no RGB". The geometric measurements are scored as for any prediction.

Imported (published) examples ship no scene spec. With the option ``spec_dir`` (``rigidbench envelope`` passes
its ``resimulation/`` folder) a bundle without one takes ``<spec_dir>/<id>/scene_spec.json``, the spec rebuilt
from the published metadata (``datasets.resimulate``; written only where its re-simulation reproduces the
published trajectory). Such a twin is geometry-only: its RGB cannot be re-rendered (our procedural meshes
stand in for the published assets), and a rendered one is refused with a PredictionError. Its data passes
are rendered at the bundle's own resolution and frame count (``published_preset``; a published bundle names
no preset of ours), through the rebuilt spec's camera, in a scene of the rebuilt actors, ramps, support and
floor only (``VariantScene(..., environment=False)``: the published room is not ours). It is scored against
the published reference, so its scores include the reconstruction's own error (a twin at scale 0 shows it).
"""

from __future__ import annotations

import dataclasses
import logging
import shutil
import tempfile
from pathlib import Path
from typing import Any, Callable

import numpy as np

from ..blender.physics import body_mesh
from ..blender.session import import_bpy_into
from ..blender.variants import VariantScene
from ..config import Registry, RenderPreset
from ..errors import BundleError, PredictionError
from ..folders import SPEC_FILE, PredictionsFolder
from ..groundtruth.bundle import masks_from_index
from ..groundtruth.contacts import convex_hull, pair_contact
from ..rotations import quat_to_matrix
from ..scene_spec.envelope import EnvelopeConfig, load_envelope, perturb_spec
from ..scene_spec.types import SceneSpec
from .base import PredictContext, Prediction, Predictor
from .counterfactuals import blender_output_silenced, process_scratch, render_target, rendered_prediction, world_state
from .options import TwinOptions

log = logging.getLogger(__name__)

#: Flat colours of the actors' silhouettes in a geometry-only twin's video, by active-actor index (cycled).
SILHOUETTE_RGB = ((230, 25, 75), (60, 180, 75), (0, 130, 200), (245, 130, 48), (145, 30, 180), (70, 240, 240))


# -- which draws are possible ------------------------------------------------------------------------------


def touching_pairs(spec: SceneSpec, hulls: dict[str, Any], gap_m: float) -> set[tuple[str, str]]:
    """Pairs of active actors of ``spec`` whose convex hulls (``hulls``: name -> ``contacts.Hull``) come within
    ``gap_m`` of each other at their initial poses."""
    active = spec.active
    poses = {b.name: (quat_to_matrix(np.asarray(b.quat_wxyz, np.float64)), np.asarray(b.position_m, np.float64))
             for b in active}
    out = set()
    for i, a in enumerate(active):
        for b in active[i + 1:]:
            if pair_contact(hulls[a.name], *poses[a.name], hulls[b.name], *poses[b.name], gap_m, 1) is not None:
                out.add((a.name, b.name))
    return out


def apart_as_in(reference: SceneSpec, registry: Registry) -> Callable[[SceneSpec], bool]:
    """``admissible(twin)`` for ``perturb_spec``: no two active actors come within their summed collision margins
    (2 x ``sim.active_margin_m``) in the twin unless they do in ``reference``."""
    hulls = {b.name: convex_hull(body_mesh(b, registry).vertices) for b in reference.active}
    gap = 2.0 * reference.sim.active_margin_m
    before = touching_pairs(reference, hulls, gap)
    return lambda twin: touching_pairs(twin, hulls, gap) <= before


# -- the reference's scene ---------------------------------------------------------------------------------


def reference_spec(sample, spec_dir: str | Path | None) -> tuple[SceneSpec, bool]:
    """(the scene spec the twins of reference ``sample`` perturb, whether it was rebuilt from published
    metadata): the bundle's own, else, for an imported bundle, ``<spec_dir>/<id>/scene_spec.json``. A
    PredictionError naming the example when there is none."""
    ref_id = sample.sample_id
    if not sample.imported or (sample.path / SPEC_FILE).is_file():
        return sample.spec, False
    if spec_dir is None:
        raise PredictionError(f"example {ref_id}: imported from the published set, which ships no scene spec; "
                              "`rigidbench envelope` rebuilds one where the re-simulation reproduces the published "
                              "trajectory (or pass spec_dir=FOLDER of rebuilt specs)")
    path = Path(spec_dir) / ref_id / SPEC_FILE
    if not path.is_file():
        raise PredictionError(f"example {ref_id}: imported, and {path} does not exist (no rebuilt scene spec: its "
                              "re-simulation did not reproduce the published trajectory, or it was not re-simulated)")
    try:
        return SceneSpec.from_json(path.read_text()), True
    except (OSError, ValueError, TypeError, KeyError) as exc:
        raise PredictionError(f"example {ref_id}: {path}: not a readable scene spec ({exc}); make the envelope "
                              "again with `rigidbench envelope`") from exc


def published_preset(sample) -> RenderPreset:
    """The data passes of an imported example: its own resolution and frame count at one sample per pixel with
    no bounces (what ``render.data_mode`` sets anyway; the published bundle names no preset of ours)."""
    return RenderPreset(name=f"published-passes-{sample.resolution[0]}x{sample.resolution[1]}",
                        resolution=tuple(sample.resolution), frames=int(sample.n_frames), samples=1,
                        adaptive_threshold=None, denoise=False, max_bounces=0, diffuse_bounces=0, glossy_bounces=0,
                        transmission_bounces=0, persistent_data=True, light_transport="fast", denoise_quality="fast")


# -- geometry only -----------------------------------------------------------------------------------------


def silhouettes(first_frame: np.ndarray, masks: np.ndarray) -> np.ndarray:
    """(T,H,W,3) uint8: ``first_frame`` (H,W,3) with the N actors' masks (T,N,H,W) of each frame painted in
    ``SILHOUETTE_RGB``."""
    frames = np.repeat(np.asarray(first_frame, np.uint8)[None], masks.shape[0], axis=0)
    for a in range(masks.shape[1]):
        frames[masks[:, a]] = SILHOUETTE_RGB[a % len(SILHOUETTE_RGB)]
    return frames


class GeometryTwins:
    """Geometry-only twins of one example after another, in the scene of the last example kept in Blender
    (``blender.variants.VariantScene``, its pass files in a folder of this process's scratch space)."""

    def __init__(self):
        self.kept: VariantScene | None = None
        self.folder: Path | None = None

    def scene(self, sample, reference: SceneSpec, spec: SceneSpec, registry: Registry,
              scratch_dir: str | Path | None, rebuilt: bool = False) -> VariantScene:
        """The kept scene when ``spec`` is a variant of it, else a new one built from ``reference``, the scene
        spec of reference ``sample`` (``rebuilt``: from published metadata; see the module docstring)."""
        preset, device = (published_preset(sample), "cpu") if rebuilt else render_target(sample, spec, registry)
        if self.kept is not None and self.kept.fits(spec, registry, preset):
            return self.kept
        self.close()
        parent = process_scratch(scratch_dir) if scratch_dir is not None else None
        if parent is not None:
            import_bpy_into(parent)  # Blender's own temporary folder there too
        self.folder = Path(tempfile.mkdtemp(prefix=f"rigidbench-{sample.sample_id}-passes-", dir=parent))
        with blender_output_silenced():
            self.kept = VariantScene(reference, registry, preset, self.folder, device, environment=not rebuilt)
        return self.kept

    def predict(self, sample, spec: SceneSpec, registry: Registry, scratch_dir: str | Path | None = None,
                reference: SceneSpec | None = None, rebuilt: bool = False):
        """A geometry-only Prediction of twin ``spec`` of reference ``sample`` (whose scene spec is ``reference``,
        default the bundle's); see the module docstring. PredictionError naming the example when it cannot be
        made."""
        ref_id = sample.sample_id
        try:
            scene = self.scene(sample, sample.spec if reference is None else reference, spec, registry, scratch_dir,
                               rebuilt)
            with blender_output_silenced():
                result = scene.passes(spec, registry)
        except (RuntimeError, ValueError, BundleError) as exc:
            raise PredictionError(f"example {ref_id}: the twin's data passes failed: {exc}") from exc
        except ImportError as exc:  # no bpy here
            raise PredictionError(f"example {ref_id}: {exc}") from exc
        traj = result.trajectory
        T = result.index.shape[0]
        if traj.names != sample.actor_names or T != sample.n_frames:
            raise PredictionError(f"example {ref_id}: the twin has actors {traj.names} and {T} frames; the "
                                  f"reference {sample.actor_names} and {sample.n_frames}")
        masks = masks_from_index(result.index, len(traj.names))
        state = dataclasses.replace(world_state(sample, traj.quat_wxyz, traj.positions_m, masks, result.depth_m,
                                                sample.fps), geometry_only=True)
        seconds = {k: round(v, 3) for k, v in result.seconds.items()}
        return Prediction(silhouettes(sample.frame(0), state.masks), state.times_s, state,
                          metadata={"render_seconds": seconds})

    def close(self) -> None:
        """Forget the kept scene and remove its pass files."""
        self.kept = None
        if self.folder is not None:
            shutil.rmtree(self.folder, ignore_errors=True)
            self.folder = None


# -- the predictor -----------------------------------------------------------------------------------------


class TwinPredictor(Predictor):
    """``twin``: one physical twin of each example per sample (see the module docstring)."""

    options_type = TwinOptions

    def __init__(self, info):
        super().__init__(info)
        self.geometry = GeometryTwins()

    def scale(self, ctx: PredictContext) -> float:
        """The ``scale`` option when given, else the severity."""
        given = self.options(ctx).scale
        return float(ctx.severity if given is None else given)

    def envelope(self, ctx: PredictContext) -> EnvelopeConfig:
        """The envelope configuration: the ``envelope`` option's file, else the configuration directories'."""
        return load_envelope(self.options(ctx).envelope, ctx.run.config_dirs)

    def preflight(self, ctx: PredictContext) -> None:
        self.envelope(ctx)  # a bad file is one error before any example

    def predict(self, sample, ctx: PredictContext) -> Prediction:
        options, scale = self.options(ctx), self.scale(ctx)
        registry = ctx.registry
        reference, rebuilt = reference_spec(sample, options.spec_dir)
        if rebuilt and not options.geometry_only:
            raise PredictionError(f"example {sample.sample_id}: imported from the published set: its twins are "
                                  "geometry-only (its RGB cannot be re-rendered: our meshes stand in for the published "
                                  "assets); pass geometry_only=true")
        spec, twin_registry = perturb_spec(reference, registry, self.envelope(ctx), ctx.seed, scale,
                                           admissible=apart_as_in(reference, registry))
        scratch = PredictionsFolder(ctx.out_dir).scratch_dir if ctx.out_dir is not None else None
        log.info("example %s: %s twin at scale %.3g, seed %d", sample.sample_id,
                 "geometry-only" if options.geometry_only else "rendered", scale, ctx.seed)
        if options.geometry_only:
            pred = self.geometry.predict(sample, spec, twin_registry, scratch, reference, rebuilt)
        else:
            pred = rendered_prediction(sample, spec, twin_registry, ctx.keep_bundle_dir, scratch_dir=scratch)
        pred.metadata["twin"] = {"seed": int(ctx.seed), "scale": scale, "geometry_only": bool(options.geometry_only)}
        if rebuilt:
            pred.metadata["twin"]["spec"] = "rebuilt from the published metadata"
        return pred

    def settings(self, ctx: PredictContext) -> dict[str, Any]:
        return {"seed": ctx.seed, "scale": self.scale(ctx), "geometry_only": bool(self.options(ctx).geometry_only),
                "envelope": self.envelope(ctx).numbers()}

    def describe(self, sample, ctx: PredictContext) -> dict[str, Any]:
        geometry_only = bool(self.options(ctx).geometry_only)
        return {"seed": ctx.seed, "scale": self.scale(ctx), "geometry_only": geometry_only,
                "re-rendered": not geometry_only}

    def close(self) -> None:
        self.geometry.close()


__all__ = ["SILHOUETTE_RGB", "GeometryTwins", "TwinPredictor", "apart_as_in", "published_preset", "reference_spec",
           "silhouettes", "touching_pairs"]
