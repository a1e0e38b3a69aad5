"""Integration-test helpers: a ``requires_bpy`` skip marker and hand-built SceneSpecs, one per task.

The hand-built layouts use round numbers so tests can predict what Bullet should do; they are
also imported by benchmarks/simulate.py as its default workload.
"""

from __future__ import annotations

import math

import pytest

from rigidbench.blender.session import bpy_available
from rigidbench.config import Registry, registry as load_registry
from rigidbench.spec.types import Body, BodyPhysics, RampShape, SceneSpec, SimSpec, SupportSpec, quat_mul

requires_bpy = pytest.mark.skipif(not bpy_available(), reason="bpy (Blender as a Python module) is not importable; "
                                                               "install it with `pip install -e '.[sim]'`")

CLEARANCE_M = 0.002  # gap between a placed object and the surface below it at frame 0
SUPPORT_TOP_M = 0.9
IDENTITY = (1.0, 0.0, 0.0, 0.0)


def quat_axis(axis: str, angle_rad: float) -> tuple[float, float, float, float]:
    """Rotation by ``angle_rad`` about the x, y or z axis as (w, x, y, z)."""
    s = math.sin(angle_rad / 2)
    return (math.cos(angle_rad / 2), s if axis == "x" else 0.0, s if axis == "y" else 0.0, s if axis == "z" else 0.0)


def sim_spec(reg: Registry) -> SimSpec:
    s = reg.sim
    return SimSpec(fps=s.fps, frames=s.frames, substeps=s.substeps, solver_iterations=s.solver_iterations,
                   gravity_m_s2=s.gravity_m_s2, linear_damping=s.linear_damping, angular_damping=s.angular_damping,
                   active_margin_m=s.active_margin_m, passive_margin_m=s.passive_margin_m)


def object_body(reg: Registry, name: str, asset: str, position_m, quat_wxyz=IDENTITY, step: str = "object") -> Body:
    obj = reg.object(asset)
    return Body(name=name, asset=asset, role="active", step=step, position_m=tuple(map(float, position_m)),
                quat_wxyz=tuple(map(float, quat_wxyz)), size_m=obj.size_m,
                physics=BodyPhysics(obj.physics.mass_kg, obj.physics.friction, obj.physics.restitution))


def ramp_body(reg: Registry, name: str, length_m: float, height_m: float, width_m: float, foot_x_m: float,
              descends: str = "+x") -> Body:
    """A ramp on the support whose foot edge is at x = ``foot_x_m`` (task frame)."""
    plus = descends == "+x"
    centre_x = foot_x_m - length_m / 2 if plus else foot_x_m + length_m / 2
    return Body(name=name, asset="ramp", role="passive", step=name, position_m=(centre_x, 0.0, height_m / 2),
                quat_wxyz=IDENTITY if plus else quat_axis("z", math.pi), size_m=(length_m, width_m, height_m),
                physics=BodyPhysics(0.0, reg.sim.passive_friction, reg.sim.passive_restitution),
                ramp=RampShape(length_m, height_m, width_m, "light_wood"))


def on_ramp(reg: Registry, name: str, asset: str, ramp: Body, fraction: float = 0.25) -> Body:
    """An object ``fraction`` of the way down ``ramp``'s slope, its +z along the slope normal."""
    r = ramp.ramp
    sign = 1.0 if ramp.quat_wxyz == IDENTITY else -1.0
    theta = math.atan2(r.height_m, r.length_m)
    x = ramp.position_m[0] - sign * r.length_m / 2 + sign * fraction * r.length_m
    z = r.height_m * (1 - fraction)
    lift = reg.object(asset).size_m[2] / 2 + CLEARANCE_M
    pos = (x + sign * math.sin(theta) * lift, ramp.position_m[1], z + math.cos(theta) * lift)
    return object_body(reg, name, asset, pos, quat_mul(quat_axis("y", sign * theta), quat_axis("z", math.pi / 2)),
                       step=name)


def resting(reg: Registry, name: str, asset: str, x: float, y: float, step: str) -> Body:
    return object_body(reg, name, asset, (x, y, reg.object(asset).size_m[2] / 2 + CLEARANCE_M), step=step)


def make_spec(reg: Registry, task: str, bodies: list[Body], support_physics: BodyPhysics | None = None,
              support_top_m: float = SUPPORT_TOP_M, support_size_m=(2.4, 1.0), long_axis_deg: float = 0.0,
              task_rotation_deg: float = 0.0, sample_id: str | None = None) -> SceneSpec:
    physics = support_physics or BodyPhysics(0.0, reg.sim.passive_friction, reg.sim.passive_restitution)
    xs = [b.position_m[0] for b in bodies]
    ys = [b.position_m[1] for b in bodies]
    return SceneSpec(
        sample_id=sample_id or f"hand_{task}", split="test", task=task, scene="modern_loft", surface="counter",
        seed=0, partition="test", allowed_objects=tuple(sorted({b.asset for b in bodies if b.role == "active"})),
        prompt=f"hand-built {task}",
        support=SupportSpec(name="counter", centre_m=(0.1, -0.2, support_top_m), size_m=tuple(support_size_m),
                            long_axis_deg=long_axis_deg, physics=physics),
        bodies=tuple(bodies), footprint_m=(max(xs) - min(xs) + 0.1, max(ys) - min(ys) + 0.1),
        rotation_candidates_deg=(task_rotation_deg,), task_rotation_deg=task_rotation_deg,
        azimuth_candidates_deg=(0.0,), sim=sim_spec(reg))


# -- one spec per task -------------------------------------------------------------------------


def free_fall_spec(reg: Registry, asset: str = "apple", drop_m: float = 0.6, **kw) -> SceneSpec:
    """One object whose bottom starts ``drop_m`` above the support."""
    z = drop_m + reg.object(asset).size_m[2] / 2
    return make_spec(reg, "free_fall", [object_body(reg, f"{asset}_0", asset, (0.0, 0.0, z))], **kw)


def bounce_spec(reg: Registry, asset: str = "baseball", drop_m: float = 0.6, **kw) -> SceneSpec:
    """A bouncy object over the bounce task's support override (friction 0.3, restitution 0.6)."""
    override = reg.task("bounce").support_override
    z = drop_m + reg.object(asset).size_m[2] / 2
    return make_spec(reg, "bounce", [object_body(reg, f"{asset}_0", asset, (0.0, 0.0, z))],
                     support_physics=BodyPhysics(0.0, override.friction, override.restitution), **kw)


def ramp_collision_spec(reg: Registry, left: str = "orange", right: str = "apple", gap_m: float = 0.12,
                        **kw) -> SceneSpec:
    """Two 0.40 x 0.20 x 0.25 m ramps facing each other, feet ``gap_m`` apart, one object on each."""
    lr = ramp_body(reg, "ramp_a", 0.40, 0.20, 0.25, foot_x_m=-gap_m / 2, descends="+x")
    rr = ramp_body(reg, "ramp_b", 0.40, 0.20, 0.25, foot_x_m=gap_m / 2, descends="-x")
    return make_spec(reg, "ramp_collision", [lr, rr, on_ramp(reg, f"{left}_0", left, lr),
                                             on_ramp(reg, f"{right}_1", right, rr)], **kw)


def ball_chain_spec(reg: Registry, striker: str = "baseball", row: str = "apple", offset_m: float = 0.10,
                    gap_m: float = 0.03, **kw) -> SceneSpec:
    """A 0.60 x 0.40 x 0.35 m ramp descending +x, a striker on it and three objects beyond its foot."""
    ramp = ramp_body(reg, "ramp", 0.60, 0.40, 0.35, foot_x_m=0.0)
    bodies = [ramp, on_ramp(reg, f"{striker}_0", striker, ramp)]
    width = reg.object(row).size_m[0]
    for i in range(3):
        x = offset_m + width / 2 + i * (width + gap_m)
        bodies.append(resting(reg, f"{row}_{i + 1}", row, x, 0.0, step="row"))
    return make_spec(reg, "ball_chain", bodies, **kw)


def drop_into_cluster_spec(reg: Registry, member: str = "food_can", faller: str = "apple", gap_m: float = 0.005,
                           drop_m: float = 0.6, **kw) -> SceneSpec:
    """Three objects on a ring (footprints ``gap_m`` apart) and a faller centred above them."""
    r = reg.object(member).footprint_radius_m
    ring = (r + gap_m / 2) / math.sin(math.pi / 3)
    bodies = [resting(reg, f"{member}_{i}", member, ring * math.cos(2 * math.pi * i / 3 + 0.3),
                      ring * math.sin(2 * math.pi * i / 3 + 0.3), step="cluster") for i in range(3)]
    top = reg.object(member).size_m[2]
    z = top + drop_m + reg.object(faller).size_m[2] / 2
    bodies.append(object_body(reg, f"{faller}_3", faller, (0.0, 0.0, z), step="faller"))
    return make_spec(reg, "drop_into_cluster", bodies, **kw)


TASK_SPECS = {"free_fall": free_fall_spec, "bounce": bounce_spec, "ramp_collision": ramp_collision_spec,
              "ball_chain": ball_chain_spec, "drop_into_cluster": drop_into_cluster_spec}


def render_eval_examples(root, ids: tuple[str, ...], preset: str = "test"):
    """Render evaluation examples ``ids`` into ``root/eval`` at ``preset``; returns that directory."""
    from rigidbench import manifest
    from rigidbench.pipeline.render import render_to_bundle

    reg = load_registry()
    rows = {r.sample_id: r for r in manifest.eval_rows(reg)}
    for sample_id in ids:
        render_to_bundle(rows[sample_id], reg, reg.preset(preset), root)
    return root / "eval"


def render_train_examples(root, n: int, preset: str = "test"):
    """Render the first ``n`` training-manifest rows into ``root/train`` at ``preset``; returns that directory."""
    from rigidbench import manifest
    from rigidbench.pipeline.render import render_to_bundle

    reg = load_registry()
    for row in manifest.train_rows(reg)[:n]:
        render_to_bundle(row, reg, reg.preset(preset), root)
    return root / "train"


@pytest.fixture(scope="module")
def torch_single_thread():
    """torch on one thread for the module (the tiny models' numbers then do not depend on the machine)."""
    torch = pytest.importorskip("torch")
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


def hand_specs(reg: Registry | None = None) -> dict[str, SceneSpec]:
    """One hand-built spec per task (realistic body counts), keyed by task id."""
    reg = reg or load_registry()
    return {task: make(reg, task_rotation_deg=30.0) for task, make in TASK_SPECS.items()}


@pytest.fixture
def empty_scene():
    """A factory-empty Blender scene (the asset tests build into it)."""
    bpy = pytest.importorskip("bpy", reason="bpy (Blender as a Python module) is not installed; run `make test`")
    bpy.ops.wm.read_factory_settings(use_empty=True)
    yield bpy.context.scene


@pytest.fixture(scope="session")
def reg() -> Registry:
    return load_registry()


def ate3d_floor(sample) -> float:
    """ATE-3D of a perfect prediction, computed independently of the evaluator: a perfect reconstruction
    is the geometric median of an actor's visible surface points, and ATE-3D compares it with the body
    origin p_{a,t}. Returns RMS over actor-frames with a visible point of |median - p| / mean displacement."""
    import numpy as np

    from rigidbench.evaluation.scoring import tracked_points_world
    from rigidbench.metrics.common import geometric_median

    points = tracked_points_world(sample, sample.n_frames)  # (P,T,3)
    visible = sample.tracks["visibility"]
    actor = sample.track_active_index
    positions = sample.trajectory.positions_m[sample.active_indices, :sample.n_frames]
    errors = [np.sum((geometric_median(points[(actor == a) & visible[:, t], t]) - positions[a, t]) ** 2)
              for a in range(len(positions)) for t in range(sample.n_frames) if ((actor == a) & visible[:, t]).any()]
    displacement = np.linalg.norm(positions[:, -1] - positions[:, 0], axis=-1)
    return float(np.sqrt(np.mean(errors)) / displacement[displacement > 0.01].mean())
