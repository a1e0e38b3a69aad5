"""Render stage at the `test` preset: one eval example per task, checked against Blender ray casts.

The module fixture renders each bundle in this process and, while that example's Blender scene is
still loaded, ray-casts every pixel centre at the first and last frame, so masks and depth can be
compared with the simulated geometry (a ray cast does not share Cycles' code path).
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import shutil
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import numpy as np
import pytest

from fixtures.blender import requires_bpy
from fixtures.scenes import make_spec, object_body, ramp_body

from rigidbench.driver import RunOptions
from rigidbench import manifest
from rigidbench.blender.camera import framing
from rigidbench.config import registry as load_registry
from rigidbench.groundtruth import bundle as B
from rigidbench.groundtruth import camera_model as cm
from rigidbench.groundtruth.contacts import quat_to_matrix
from rigidbench.groundtruth.tracks import erode_cross
from rigidbench.scene_spec.types import CameraSpec

pytestmark = [pytest.mark.integration, requires_bpy]

QUALITY = "test"
SRC = str(Path(__file__).resolve().parents[2] / "src")


def _raycast(sample: B.Sample, frames: list[int]) -> dict[int, tuple[np.ndarray, np.ndarray]]:
    """Object index (pass_index of the first rendered hit) and axial depth per pixel centre, from
    Blender's own BVH on the currently loaded scene. Returns frame -> ((H,W) int, (H,W) float)."""
    import bpy

    from rigidbench.blender.camera import first_render_hit

    scene = bpy.context.scene
    R, t = sample.camera_pose
    W, H = sample.resolution
    rows, cols = np.mgrid[0:H, 0:W]
    rays = cm.pixel_rays(sample.K, R, np.stack([cols, rows], -1).astype(float))
    out = {}
    for f in frames:
        scene.frame_set(f + 1)
        depsgraph = bpy.context.evaluated_depsgraph_get()
        index = np.zeros((H, W), int)
        depth = np.full((H, W), np.inf)
        for y in range(H):
            for x in range(W):
                d = rays[y, x]
                n = float(np.linalg.norm(d))
                obj, dist = first_render_hit(scene, depsgraph, t, d / n, 1e4)
                if obj is not None:
                    index[y, x] = obj.pass_index
                    depth[y, x] = dist / n  # rays have unit axial component
        out[f] = (index, depth)
    return out


@pytest.fixture(scope="module")
def reg():
    return load_registry()


@pytest.fixture(scope="module")
def task_rows(reg):
    first = {}
    for row in manifest.rows("eval", reg):
        first.setdefault(row.task, row)
    return first


@pytest.fixture(scope="module")
def rendered(reg, task_rows, tmp_path_factory):
    """task -> (bundle path, ray casts at the first and last frame)."""
    from rigidbench.stages.render import render_to_bundle

    data = tmp_path_factory.mktemp("data")
    out = {}
    for task, row in sorted(task_rows.items()):
        path = render_to_bundle(row, reg, reg.preset(QUALITY), data)
        sample = B.Sample(path)
        out[task] = (path, _raycast(sample, [0, sample.n_frames - 1]))
    return out


def test_each_task_renders_a_valid_bundle(rendered, reg, task_rows):
    preset = reg.preset(QUALITY)
    assert sorted(rendered) == sorted(reg.tasks)
    for task, (path, _) in rendered.items():
        assert B.check_bundle(path) == [], task
        s = B.Sample(path)
        W, H = preset.resolution
        assert s.frames.shape == (preset.frames, H, W, 3) and s.frames.dtype == np.uint8
        assert s.masks.shape == (preset.frames, len(s.spec.bodies), H, W)
        assert s.depth.dtype == np.float32
        assert s.metadata["preset"] == QUALITY and s.metadata["render"]["device_kind"] == "CPU"
        assert s.metadata["render"]["light_transport"] == preset.light_transport
        assert s.metadata["render"]["samples"] == preset.samples
        assert s.prompt and s.prompt == s.spec.prompt == (path / B.PROMPT_FILE).read_text().strip()
        assert s.sample_id == task_rows[task].sample_id and s.task == task
        assert not (path.parent / f".{path.name}.tmp").exists()
        # every file of the bundle (the video too, whose encoder's temporary is private) has the umask's mode
        mask = os.umask(0)
        os.umask(mask)
        modes = {f.relative_to(path).as_posix(): (f.stat().st_mode & 0o777, (0o777 if f.is_dir() else 0o666) & ~mask)
                 for f in [path, *path.rglob("*")] if not f.is_symlink()}
        assert {f: m for f, m in modes.items() if m[0] != m[1]} == {}, task
        # when the camera search found a view seeing half the sampled points, the actors are in view
        if s.spec.camera.visibility >= 0.5:
            assert any(s.masks[0, a].any() for a in s.active_indices), f"{task}: no active actor in view"


def test_camera_follows_the_paper_rule(rendered, reg):
    cfg = reg.camera
    for task, (path, _) in rendered.items():
        s = B.Sample(path)
        spec, cam = s.spec, s.spec.camera
        assert spec.task_rotation_deg in spec.rotation_candidates_deg
        assert cam.relative_azimuth_deg in spec.azimuth_candidates_deg
        assert math.isclose((spec.task_rotation_deg + cam.relative_azimuth_deg) % 360, cam.azimuth_deg)
        assert cam.elevation_deg == 10.0 and cam.lens_mm == 35.0
        target, distance = framing(spec, cfg)
        assert cam.distance_m == pytest.approx(distance) and cam.distance_m >= 1.4
        np.testing.assert_allclose(cam.target_m, target)
        # the camera looks at the target: it projects onto the principal point, distance_m away
        R, t = s.camera_pose
        uv, z = cm.project(np.array(cam.target_m), s.K, R, t)
        np.testing.assert_allclose(uv, [s.K[0, 2], s.K[1, 2]], atol=1e-6)
        assert z == pytest.approx(cam.distance_m)
        np.testing.assert_allclose(t[2] - cam.target_m[2], cam.distance_m * math.sin(math.radians(10)), atol=1e-9)
        assert s.K[0, 0] == pytest.approx(35.0 / 36.0 * s.resolution[0])


def test_masks_agree_with_ray_cast(rendered):
    for task, (path, casts) in rendered.items():
        s = B.Sample(path)
        for f, (index, _) in casts.items():
            rendered_index = np.zeros(index.shape, int)
            for k in range(s.masks.shape[1]):
                rendered_index[s.masks[f, k]] = k + 1
            agree = float((rendered_index == index).mean())
            assert agree >= 0.99, f"{task} frame {f}: masks agree with the ray cast on {agree:.4f} of pixels"
            for k in range(s.masks.shape[1]):  # each actor's own pixels agree too
                hit = index == k + 1
                if hit.sum() >= 20:
                    iou = (hit & s.masks[f, k]).sum() / (hit | s.masks[f, k]).sum()
                    assert iou >= 0.9, f"{task} frame {f} actor {k}: IoU {iou:.3f}"


def test_depth_agrees_with_ray_cast(rendered):
    for task, (path, casts) in rendered.items():
        s = B.Sample(path)
        for f, (index, depth) in casts.items():
            ref = s.depth[f]
            both = np.isfinite(depth) & np.isfinite(ref)
            assert (np.isfinite(depth) == np.isfinite(ref)).mean() >= 0.99
            err = np.where(both, np.abs(depth - ref), 0.0)
            # on the actors, every pixel; elsewhere a ray grazing the edge of thin decor (a rail, a frame)
            # may pick the surface behind it in one implementation and not the other: a few pixels at most
            actor = both & (index > 0)
            assert err[actor].max(initial=0.0) < 1e-3, f"{task} frame {f}: actor depth off by {err[actor].max() * 1000:.2f} mm"
            off = float((err >= 1e-3).mean())
            assert off <= 1e-3, f"{task} frame {f}: depth differs on {off:.4%} of pixels (up to {err.max() * 1000:.2f} mm)"


def test_track_points_start_inside_their_masks(rendered):
    total = 0
    for task, (path, _) in rendered.items():
        s = B.Sample(path)
        tr = s.tracks
        total += tr.n_points
        assert (tr.points_per_actor[[k for k, r in enumerate(s.roles) if r != "active"]] == 0).all()
        assert (tr.points_per_actor <= 20).all()
        qx, qy = tr.query_pixels[:, 0], tr.query_pixels[:, 1]
        assert s.masks[0, tr.actor_index, qy, qx].all(), task
        np.testing.assert_allclose(tr.tracks_px[:, 0], tr.query_pixels, atol=1e-3)
        assert tr.visibility[:, 0].all(), task
        # the published evaluator's rule: query pixels are unique per actor and lie in 3 iterations of a 3x3-cross
        # erosion (the diamond |dx| + |dy| <= 3 around each is inside the mask), unless fewer than 20 pixels
        # survive it, when they come from the whole mask
        assert s.metadata["tracks"]["rule"] == "published"
        H, W = s.masks.shape[2:]
        for k in np.unique(tr.actor_index):
            q = tr.query_pixels[tr.actor_index == k]
            assert len({tuple(p) for p in q}) == len(q)
            if erode_cross(s.masks[0, k], 3).sum() < 20:
                assert len(q) == min(20, s.masks[0, k].sum()), task
                continue
            for dx, dy in ((3, 0), (-3, 0), (0, 3), (0, -3), (2, 1), (-1, -2)):
                assert s.masks[0, k, np.clip(q[:, 1] + dy, 0, H - 1), np.clip(q[:, 0] + dx, 0, W - 1)].all(), task
    assert total >= 40


def test_tracks_follow_the_rendered_surface(rendered):
    """Unproject the rendered depth at each visible track position: the point found there, moved
    back into the actor's body frame by the simulated pose, is the tracked body point."""
    errors = []
    for task, (path, _) in rendered.items():
        s = B.Sample(path)
        tr, traj = s.tracks, s.trajectory
        R_c, t_c = s.camera_pose
        rot = quat_to_matrix(traj.quat_wxyz)
        for f in range(s.n_frames):
            vis = np.flatnonzero(tr.visibility[:, f])
            if not len(vis):
                continue
            uv = tr.tracks_px[vis, f].astype(float)
            px = np.rint(uv).astype(int)
            world = cm.unproject(uv, s.depth[f, px[:, 1], px[:, 0]], s.K, R_c, t_c)
            a = tr.actor_index[vis]
            body = np.einsum("pji,pj->pi", rot[a, f], world - traj.positions_m[a, f])
            errors.append(np.linalg.norm(body - tr.points_body_m[vis], axis=1))
    errors = np.concatenate(errors)
    assert np.median(errors) < 0.003 and np.percentile(errors, 90) < 0.01, (np.median(errors), errors.max())


def test_trajectory_is_the_simulation_of_the_resolved_spec(rendered, reg):
    from rigidbench.blender.physics import simulate

    path, _ = rendered["free_fall"]
    s = B.Sample(path)
    sim = simulate(s.spec, reg)
    np.testing.assert_array_equal(s.trajectory.positions_m, sim.trajectory.positions_m[:, :s.n_frames])
    z = s.trajectory.positions_m[0, :, 2]
    assert z[0] > z[-1]  # it falls
    frame0 = s.spec.world_bodies()[0].position_m
    np.testing.assert_allclose(s.trajectory.positions_m[0, 0], frame0, atol=1e-6)


def test_visibility_turns_off_behind_passive_ramp(reg, tmp_path):
    """A coconut drops behind a ramp's 0.45 m back wall, seen from the wall's side: its points are
    visible over the wall at frame 0 and hidden behind it once it lands."""
    from rigidbench.blender.render import render_spec

    ramp = ramp_body(reg, "ramp", 0.40, 0.45, 0.60, foot_x_m=-0.10, descends="+x")  # back wall at x = -0.5
    ball = object_body(reg, "coconut_0", "coconut", (0.10, 0.0, 0.60 + 0.06))
    spec = make_spec(reg, "free_fall", [ramp, ball], sample_id="occlusion")
    top = spec.support.centre_m[2]
    spec = dataclasses.replace(spec, camera=CameraSpec(
        azimuth_deg=180.0, relative_azimuth_deg=180.0, elevation_deg=5.0, distance_m=2.0,
        target_m=(spec.support.centre_m[0], spec.support.centre_m[1], top + 0.35), lens_mm=35.0,
        sensor_width_mm=36.0, visibility=1.0))
    path = render_spec(spec, reg, reg.preset(QUALITY), tmp_path / "occlusion")
    s = B.Sample(path)
    tr = s.tracks
    assert tr.n_points >= 10
    assert tr.visibility[:, 0].all()
    assert not tr.visibility[:, -1].any()
    assert not s.masks[-1, 1].any()  # the coconut is fully hidden
    assert (np.diff(tr.visibility.astype(int), axis=1) <= 0).all()  # once hidden, stays hidden
    px = np.rint(tr.tracks_px[:, -1]).astype(int)
    W, H = s.resolution
    inside = (px[:, 0] >= 0) & (px[:, 0] < W) & (px[:, 1] >= 0) & (px[:, 1] < H)
    assert inside.all()
    assert s.masks[-1, 0, px[:, 1], px[:, 0]].all()  # they project onto the ramp that hides them


def test_check_bundle_reports_damage(rendered, tmp_path):
    path, _ = rendered["bounce"]
    bad = tmp_path / "bad"
    shutil.copytree(path, bad)
    assert B.check_bundle(bad) == []
    (bad / B.FRAMES_DIR / B.frame_name(3)).unlink()
    depth = B.Sample(bad).depth
    B.write_depth(bad / B.DEPTH_FILE, depth[:-1])
    (bad / B.PROMPT_FILE).unlink()
    problems = B.check_bundle(bad)
    assert any(p.startswith("frames/") for p in problems)
    assert any(p.startswith("depth.npz") and "axis 0" in p for p in problems)
    assert any(p.startswith("prompt.txt") for p in problems)


def test_show_writes_contact_sheet(rendered, tmp_path):
    from PIL import Image

    from rigidbench.cli import build_context, build_parser

    path, _ = rendered["ramp_collision"]
    parser = build_parser()
    out = tmp_path / "sheet.png"
    args = parser.parse_args(["show", path.name, "--split", "eval", "--data", str(path.parents[1]), "--out", str(out)])
    assert args.func(args, build_context(args)) == 0
    with Image.open(out) as im:
        assert im.size[0] > 800 and im.size[1] > 400


def test_rerun_skips_complete_bundles(rendered, reg, task_rows):
    from rigidbench.stages.render import render_rows

    path, _ = rendered["free_fall"]
    before = (path / B.METADATA_FILE).stat().st_mtime_ns
    [report] = render_rows([task_rows["free_fall"]], reg, path.parents[1], quality=QUALITY,
                           run=RunOptions(progress=False))
    assert report.ran == [] and report.failed == {}
    assert (path / B.METADATA_FILE).stat().st_mtime_ns == before


def _children(pid: int) -> list[int]:
    try:
        text = Path(f"/proc/{pid}/task/{pid}/children").read_text()
    except OSError:
        return []
    return [int(c) for c in text.split()]


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="finds the worker process through /proc")
def test_killed_worker_then_rerun_gives_the_same_bundle(rendered, reg, task_rows, tmp_path):
    """Kill the worker mid-render: the run reports the example as failed and leaves no bundle; a
    rerun renders it completely, identical to the first render (RGB within one level)."""
    from rigidbench.stages.render import render_rows

    row = task_rows["ball_chain"]
    data = tmp_path / "data"
    # the render is staged by the stage driver; render_spec builds its temporary inside the example's staging
    tmp_dir = data / row.split / ".stages" / "render" / "staging" / row.sample_id / f".{row.sample_id}.tmp"
    script = textwrap.dedent(f"""
        import sys
        from pathlib import Path
        from rigidbench import manifest
        from rigidbench.config import registry
        from rigidbench.driver import RunOptions
        from rigidbench.stages.render import render_rows
        reg = registry()
        rows = manifest.select(manifest.rows("eval", reg), ["{row.sample_id}"])
        [report] = render_rows(rows, reg, Path(r"{data}"), quality="{QUALITY}", run=RunOptions(progress=False))
        for sample_id, reason in report.failed.items():
            print("FAILED", sample_id, reason)
        sys.exit(report.exit_status())
    """)
    env = {**os.environ, "PYTHONPATH": SRC + os.pathsep + os.environ.get("PYTHONPATH", "")}
    parent = subprocess.Popen([sys.executable, "-c", script], stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                              text=True, env=env)
    killed = False
    deadline = time.time() + 120
    while time.time() < deadline and parent.poll() is None:
        if (tmp_dir / ".passes").is_dir() and any((tmp_dir / ".passes").glob("*.exr")):
            for pid in _children(parent.pid):
                os.kill(pid, signal.SIGKILL)
                killed = True
            break
        time.sleep(0.02)
    output, _ = parent.communicate(timeout=120)
    assert killed, f"the worker finished before it could be killed:\n{output}"
    assert parent.returncode == 1, output
    assert f"FAILED {row.sample_id} worker process killed by SIGKILL" in output
    assert not (data / row.split / row.sample_id).exists()
    assert tmp_dir.exists()  # the half-written bundle is left where a rerun will replace it

    [report] = render_rows([row], reg, data, quality=QUALITY, run=RunOptions(progress=False))
    assert report.ran == [row.sample_id] and report.failed == {}
    assert not tmp_dir.exists()
    again = B.Sample(data / row.split / row.sample_id)
    assert B.check_bundle(again.path) == []
    first = B.Sample(rendered["ball_chain"][0])
    np.testing.assert_array_equal(again.masks, first.masks)
    np.testing.assert_array_equal(again.depth, first.depth)
    assert np.abs(again.frames.astype(int) - first.frames.astype(int)).max() <= 1
    np.testing.assert_array_equal(again.tracks.tracks_px, first.tracks.tracks_px)
    np.testing.assert_array_equal(again.tracks.visibility, first.tracks.visibility)
    assert json.loads((again.path / B.SPEC_FILE).read_text()) == json.loads((first.path / B.SPEC_FILE).read_text())


def test_render_command_rejects_unknown_ids(tmp_path):
    from rigidbench.cli import build_context, build_parser
    from rigidbench.errors import UserError

    parser = build_parser()
    args = parser.parse_args(["render", "--split", "eval", "--ids", "99999", "--data", str(tmp_path)])
    with pytest.raises(UserError, match="99999"):
        args.func(args, build_context(args))


def test_failing_example_is_reported_and_the_others_continue(reg, task_rows, tmp_path):
    import yaml

    from rigidbench.config import PACKAGE_CONFIG_DIR
    from rigidbench.stages.render import render_rows

    bad, good = task_rows["bounce"], task_rows["free_fall"]
    assert bad.scene != good.scene
    scene = yaml.safe_load((PACKAGE_CONFIG_DIR / "scenes" / f"{bad.scene}.yaml").read_text())
    for support in scene["supports"]:
        support["size_m"] = [0.05, 0.05]  # no task fits: the spec builder raises SpecError
    (tmp_path / "cfg" / "scenes").mkdir(parents=True)
    (tmp_path / "cfg" / "scenes" / f"{bad.scene}.yaml").write_text(yaml.safe_dump(scene))
    reg2 = load_registry([tmp_path / "cfg"])
    data = tmp_path / "data"
    [report] = render_rows([bad, good], reg2, data, quality=QUALITY, config_dirs=[tmp_path / "cfg"],
                           run=RunOptions(progress=False))
    done, failures = report.ran, list(report.failed.items())
    assert done == [good.sample_id]
    assert [sample_id for sample_id, _ in failures] == [bad.sample_id]
    assert failures[0][1].startswith("SpecError") and bad.sample_id in failures[0][1]
    assert not (data / bad.split / bad.sample_id).exists()
    assert B.check_bundle(data / good.split / good.sample_id) == []


def test_fast_presets_approximate_light_transport_and_drop_bump_paper_keeps_both():
    # `preview` and `test` trade light transport and sub-pixel relief for speed; `paper` renders in full.
    # The choice is the preset's `light_transport` and `denoise_quality` keys, not its name.
    import bpy

    from rigidbench.blender import render as R
    from rigidbench.blender.assets import materials as M
    from rigidbench.blender.session import reset_scene

    reg = load_registry()
    scene = reset_scene()
    for name, fast in (("paper", False), ("preview", True), ("test", True)):
        R.light_transport(scene, reg.preset(name))
        assert scene.cycles.use_fast_gi is fast and scene.cycles.use_light_tree is (not fast), name
    device = R.RenderDevice("CPU", ("cpu",))
    for name, quality, prefilter in (("paper", "HIGH", "ACCURATE"), ("preview", "FAST", "FAST")):
        R.beauty_mode(scene, reg.preset(name), device)
        assert (scene.cycles.denoising_quality, scene.cycles.denoising_prefilter) == (quality, prefilter), name
    mine = dataclasses.replace(reg.preset("paper"), name="mine", light_transport="fast", denoise_quality="balanced")
    R.light_transport(scene, mine)
    assert scene.cycles.use_fast_gi and not scene.cycles.use_light_tree
    R.beauty_mode(scene, dataclasses.replace(mine, light_transport="full"), device)
    assert scene.cycles.denoising_quality == "BALANCED"
    mats = [M.painted("rb_t_painted", (0.5, 0.5, 0.5)), M.wood("rb_t_wood", (0.6, 0.4, 0.2), 0.5)]

    def bump_links(mat):
        return [lk for lk in mat.node_tree.links if lk.from_node.bl_idname == "ShaderNodeBump"]

    assert all(len(bump_links(m)) == 1 for m in mats)
    R.beauty_mode(scene, reg.preset("paper"), device)
    assert all(len(bump_links(m)) == 1 for m in mats)  # paper keeps its bump mapping
    assert R.drop_bump_mapping() == 2
    assert not any(bump_links(m) for m in mats)
    bsdf = next(n for n in mats[0].node_tree.nodes if n.bl_idname == "ShaderNodeBsdfPrincipled")
    assert not bsdf.inputs["Normal"].is_linked and bsdf.outputs["BSDF"].is_linked
    assert R.drop_bump_mapping() == 0
    del bpy


def test_select_device_with_blender_probes_the_gpu_backends_and_falls_back_to_the_cpu():
    from rigidbench.blender import render as R

    chosen = R.select_device("auto")
    if chosen.is_gpu:
        assert chosen.kind in ("OPTIX", "CUDA") and R.select_device("gpu") == chosen
    else:  # no OptiX or CUDA device visible here: "gpu" must refuse rather than render on the CPU
        assert chosen.kind == "CPU"
        with pytest.raises(RuntimeError, match="no OptiX or CUDA device"):
            R.select_device("gpu")
    assert R.select_device("cpu").kind == "CPU"
    with pytest.raises(ValueError, match="unknown render device 'tpu'"):
        R.select_device("tpu")
