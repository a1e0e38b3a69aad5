"""The render stage: manifest rows -> sample bundles in DATA/<split>/<id>/.

Each example runs in its own child Python process (bpy is imported only there; its job description
carries the run context's configuration directories), so a crash inside Blender loses only that example;
``--workers N`` runs N at once. A bundle is built in ``DATA/<split>/.<id>.tmp`` and renamed into place when complete and validated, so a
rerun skips finished examples and restarts interrupted ones from scratch. Failures are reported
with the example id and the reason; the other examples continue.
"""

from __future__ import annotations

import argparse
import dataclasses
import logging
import os
import shutil
import signal
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np

from .. import __version__, manifest
from ..blender.camera import camera_pose
from ..blender.render import render_example
from ..blender.session import bpy_available
from ..config import Registry, RenderPreset, registry as load_registry
from ..context import RunContext
from ..errors import EXAMPLE_ERRORS, UserError
from ..executors import Executor, Resources, Shard, make_executor
from ..groundtruth import bundle as B
from ..groundtruth.camera_model import intrinsics, project
from ..groundtruth.contact_sheet import write_contact_sheet
from ..groundtruth.contacts import quat_to_matrix
from ..groundtruth.tracks import DEPTH_TOLERANCE, EROSION_RADIUS_PX, POINTS_PER_ACTOR, ground_truth_tracks
from ..groundtruth.trajectory import save_contacts
from ..manifest import ManifestRow
from ..spec.build import build_scene_spec
from ..video import write_video

log = logging.getLogger(__name__)

DEFAULT_DATA = Path("data")
QUALITIES = ("paper", "preview", "test")
POLL_S = 0.2


@dataclass(frozen=True)
class Failure:
    sample_id: str
    reason: str


def bundle_dir(data_dir: Path, row: ManifestRow) -> Path:
    """DATA/<split>/<id>: where the example's bundle lives."""
    return Path(data_dir) / row.split / row.sample_id


def is_complete(data_dir: Path, row: ManifestRow) -> bool:
    """A bundle is complete when its final directory exists (it is only ever renamed into place)."""
    return bundle_dir(data_dir, row).is_dir()


# -- one example, in this process ------------------------------------------------------------------


def image_sides(names: Sequence[str], positions_m: np.ndarray, K: np.ndarray, R_c: np.ndarray,
                t_c: np.ndarray) -> dict[str, Any]:
    """Which side of the image each actor starts on, from the camera's point of view: actor centres at
    frame 0 (``positions_m`` (N,3)) are projected and compared with the mean projected x of all
    actors; "left" means a smaller image column (x) than that mean. Actor names themselves are neutral
    (e.g. ramp_a / ramp_b in ramp_collision) because the camera may view the task from either side."""
    uv, _ = project(np.asarray(positions_m, float), K, R_c, t_c)
    x = uv[:, 0]
    mid = float(x.mean())
    return {"convention": "camera view at frame 0: left = projected actor centre has a smaller image x "
                          "(column) than the mean over actors (within 0.5 px: centre)",
            "actors": {n: ("left" if xi < mid - 0.5 else "right" if xi > mid + 0.5 else "centre")
                       for n, xi in zip(names, map(float, x))},
            "image_x_px": {n: round(float(xi), 2) for n, xi in zip(names, x)}}


def write_bundle(tmp: Path, result: Any, preset: RenderPreset, total_s: float) -> None:
    """Turn a ``blender.render.ExampleRender`` into the bundle files inside ``tmp`` (frames already there)."""
    from PIL import Image

    spec = result.spec
    T = result.index.shape[0]
    names = tuple(b.name for b in spec.bodies)
    roles = tuple(b.role for b in spec.bodies)
    traj = B.slice_trajectory(result.simulation.trajectory, T)
    if traj.names != names:
        raise B.BundleError(f"example {spec.sample_id}: simulated actors {traj.names} differ from the spec's {names}")
    masks = B.masks_from_index(result.index, len(names))
    R_c, t_c = camera_pose(spec.camera)
    K = intrinsics(spec.camera.lens_mm, spec.camera.sensor_width_mm, *preset.resolution)
    tracks = ground_truth_tracks(masks, result.depth_m, K, R_c, t_c, quat_to_matrix(traj.quat_wxyz), traj.positions_m,
                                 np.array([r == "active" for r in roles]), seed=spec.seed)
    if tracks.n_points and not tracks.visibility[:, 0].all():
        log.warning("example %s: %d ground-truth points are not visible at frame 0", spec.sample_id,
                    int((~tracks.visibility[:, 0]).sum()))
    B.write_masks(tmp / B.MASKS_FILE, masks, names, roles)
    B.write_depth(tmp / B.DEPTH_FILE, result.depth_m)
    traj.save(tmp / B.TRAJECTORIES_FILE)
    save_contacts(tmp / B.CONTACTS_FILE, [c for c in result.simulation.contacts if c.frame < T], frames=T,
                  tolerance_m=result.simulation.tolerance_m)
    tracks.save(tmp / B.TRACKS_FILE)
    (tmp / B.PROMPT_FILE).write_text(spec.prompt + "\n")
    (tmp / B.SPEC_FILE).write_text(spec.to_json())
    frames = np.stack([np.asarray(Image.open(tmp / B.FRAMES_DIR / B.frame_name(k)).convert("RGB")) for k in range(T)])
    write_video(tmp / B.VIDEO_FILE, frames, fps=float(spec.sim.fps))
    render_facts = {"engine": "CYCLES", "device": result.device.describe(), "device_kind": result.device.kind,
                    **{k: v for k, v in dataclasses.asdict(preset).items() if k not in ("name", "resolution", "frames")},
                    "motion_blur": False, "depth_of_field": False,
                    "seed": spec.seed, "data_passes": "1 sample at pixel centres (filter width 0.01 px)",
                    "color_management": result.color_management, "procedural_assets": result.uses_assets}
    software = {**result.software, "rigidbench": __version__, "python": sys.version.split()[0],
                "numpy": np.__version__}
    seconds = {**{k: round(v, 3) for k, v in result.seconds.items()}, "total": round(total_s, 3)}
    track_facts = {"points_per_actor": POINTS_PER_ACTOR, "erosion_px": EROSION_RADIUS_PX,
                   "depth_tolerance": DEPTH_TOLERANCE, "sampled": [int(n) for n in tracks.points_per_actor]}
    meta = B.make_metadata(spec, resolution=preset.resolution, frames=T, simulated_frames=result.simulation.frames,
                           fps=float(spec.sim.fps), render=render_facts, software=software, seconds=seconds,
                           tracks=track_facts)
    meta["image_sides"] = image_sides(names, traj.positions_m[:, 0], K, R_c, t_c)
    B.write_json(tmp / B.METADATA_FILE, meta)


def render_spec(spec: Any, registry: Registry, preset: RenderPreset, final_dir: Path, device: str = "auto",
                threads: int | None = None, on_frame: Callable[[int, int], None] | None = None,
                overrides: Any = None) -> Path:
    """Render a SceneSpec into the bundle directory ``final_dir`` in this process (bpy must be
    importable); the camera search runs unless ``spec.camera`` is set. ``overrides`` (a
    ``blender.overrides.RenderOverrides``) changes actor materials or rendered poses, not the
    simulation. Returns ``final_dir``."""
    t0 = time.perf_counter()
    tmp = B.prepare_tmp(final_dir)
    passes = tmp / ".passes"
    result = render_example(spec, registry, preset, tmp / B.FRAMES_DIR, passes, device=device, threads=threads,
                            on_frame=on_frame, overrides=overrides)
    shutil.rmtree(passes)
    write_bundle(tmp, result, preset, time.perf_counter() - t0)
    problems = B.check_bundle(tmp)
    if problems:
        raise B.BundleError(f"example {spec.sample_id}: the new bundle in {tmp} is invalid: " + "; ".join(problems))
    return B.commit(tmp, final_dir)


def render_to_bundle(row: ManifestRow, registry: Registry, preset: RenderPreset, data_dir: Path,
                     device: str = "auto", threads: int | None = None,
                     on_frame: Callable[[int, int], None] | None = None) -> Path:
    """Render one manifest row into DATA/<split>/<id>/ in this process; returns the bundle path.

    Raises SpecError, BundleError, RuntimeError or OSError naming the example."""
    spec = build_scene_spec(row, registry)
    return render_spec(spec, registry, preset, bundle_dir(data_dir, row), device=device, threads=threads,
                       on_frame=on_frame)


# -- child processes -----------------------------------------------------------------------------------
#
# Each example runs in ``python -c "...; _child_main()"`` (not multiprocessing, whose spawn mode
# re-imports the caller's __main__). The job comes as one JSON argument; progress comes back as JSON
# lines on a pipe whose descriptor is the second argument, so Blender's own stdout stays separate.

_CHILD_CODE = "from rigidbench.pipeline.render import _child_main; _child_main()"


def _die_with_parent() -> None:
    """Linux: have the kernel kill this worker when the parent process dies (no orphaned renders)."""
    if sys.platform.startswith("linux"):
        import ctypes

        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl(1, signal.SIGKILL)  # PR_SET_PDEATHSIG


def _child_main() -> None:
    """Worker entry: argv = [job JSON, message fd]. Renders one example; reports on the message pipe."""
    import json

    _die_with_parent()
    job = json.loads(sys.argv[1])
    out = os.fdopen(int(sys.argv[2]), "w", buffering=1)

    def send(*msg: Any) -> None:
        out.write(json.dumps(msg) + "\n")

    row = ManifestRow.from_dict(job["row"])
    logging.basicConfig(level=logging.WARNING, format=f"%(levelname)s [{row.sample_id}] %(name)s: %(message)s")
    try:
        reg = load_registry(job["config_dirs"])
        path = render_to_bundle(row, reg, reg.preset(job["preset"]), Path(job["data_dir"]), device=job["device"],
                                threads=job["threads"], on_frame=lambda done, total: send("frame", done, total))
    except (*EXAMPLE_ERRORS, RuntimeError, ImportError) as exc:  # RuntimeError: Blender's own errors
        send("failed", f"{type(exc).__name__}: {exc}")
        return
    send("done", str(path))


def _exit_reason(code: int | None) -> str:
    if code is not None and code < 0:
        try:
            return f"worker process killed by {signal.Signals(-code).name}"
        except ValueError:
            return f"worker process killed by signal {-code}"
    return f"worker process exited with code {code} without a result (see the traceback above)"


@dataclass
class _Child:
    row: ManifestRow
    proc: Any
    fd: int
    buffer: bytes = b""
    outcome: str | None = None  # "done" or the failure reason
    frames: int = 0


def _start_child(row: ManifestRow, job: dict, quiet: bool) -> _Child:
    import json
    import subprocess

    r, w = os.pipe()
    try:
        proc = subprocess.Popen([sys.executable, "-c", _CHILD_CODE, json.dumps({**job, "row": row.to_dict()}), str(w)],
                                pass_fds=(w,), stdin=subprocess.DEVNULL,
                                stdout=subprocess.DEVNULL if quiet else None)
    finally:
        os.close(w)
    return _Child(row=row, proc=proc, fd=r)


def render_rows(rows: Sequence[ManifestRow], registry: Registry, data_dir: Path, quality: str = "paper",
                workers: int = 1, device: str = "auto", config_dirs: Sequence[str | Path] = (),
                progress: bool = True, quiet: bool = True) -> tuple[list[str], list[Failure]]:
    """Render every incomplete row, each in a child process, ``workers`` at a time.

    Returns (ids rendered now, failures). Complete bundles are skipped; ``registry`` must be the
    one ``config_dirs`` produce (children rebuild it from the directories). ``quiet`` hides
    Blender's per-frame console output."""
    import json
    import selectors

    from tqdm import tqdm

    preset = registry.preset(quality)
    if workers < 1:
        raise ValueError(f"--workers must be at least 1, got {workers}")
    todo = [r for r in rows if not is_complete(data_dir, r)]
    skipped = len(rows) - len(todo)
    if skipped:
        log.info("%d of %d examples already have complete bundles in %s; skipping them", skipped, len(rows), data_dir)
    threads = max(1, (os.cpu_count() or 1) // workers) if workers > 1 else None
    job = {"config_dirs": [str(d) for d in config_dirs], "preset": quality, "data_dir": str(Path(data_dir).resolve()),
           "device": device, "threads": threads}
    pending = list(todo)
    running: dict[int, _Child] = {}
    done_ids: list[str] = []
    failures: list[Failure] = []
    show = progress and bool(todo)
    bar = tqdm(total=len(todo), desc="examples", unit="ex", disable=not show, position=0)
    frame_bar = tqdm(total=len(todo) * 2 * preset.frames, desc="frames (passes + RGB)", unit="fr",
                     disable=not show, position=1)
    sel = selectors.DefaultSelector()

    def handle(child: _Child, line: bytes) -> None:
        try:
            msg = json.loads(line)
        except ValueError:
            log.warning("example %s: unreadable worker message %r", child.row.sample_id, line[:200])
            return
        if msg[0] == "frame":
            done, total = int(msg[1]), int(msg[2])
            if frame_bar.total != len(todo) * total:
                frame_bar.total = len(todo) * total
                frame_bar.refresh()
            frame_bar.update(done - child.frames)
            child.frames = done
        elif msg[0] == "done":
            child.outcome = "done"
        else:
            child.outcome = str(msg[1])

    def finish(child: _Child) -> None:
        sel.unregister(child.fd)
        os.close(child.fd)
        del running[child.fd]
        code = child.proc.wait()
        outcome = child.outcome or _exit_reason(code)
        bar.update(1)
        if outcome == "done":
            done_ids.append(child.row.sample_id)
        else:
            failures.append(Failure(child.row.sample_id, outcome))
            bar.write(f"FAILED {child.row.sample_id}: {outcome}")
        bar.set_postfix_str(", ".join(c.row.sample_id for c in running.values()))

    try:
        while pending or running:
            while pending and len(running) < workers:
                child = _start_child(pending.pop(0), job, quiet)
                running[child.fd] = child
                sel.register(child.fd, selectors.EVENT_READ, child)
                bar.set_postfix_str(", ".join(c.row.sample_id for c in running.values()))
            for key, _ in sel.select(timeout=POLL_S):
                child = key.data
                chunk = os.read(child.fd, 65536)
                if not chunk:  # the worker closed its end: it has exited (or is exiting)
                    if child.buffer:
                        handle(child, child.buffer)
                    finish(child)
                    continue
                child.buffer += chunk
                *lines, child.buffer = child.buffer.split(b"\n")
                for line in lines:
                    if line.strip():
                        handle(child, line)
    except KeyboardInterrupt:
        for child in running.values():
            child.proc.terminate()
        for child in running.values():
            child.proc.wait(5)
        raise
    finally:
        for child in list(running.values()):
            os.close(child.fd)
        sel.close()
        frame_bar.close()
        bar.close()
    return done_ids, failures


# -- on a Ray cluster -------------------------------------------------------------------------------------


RENDER_WORKER = "rigidbench.pipeline.render:RenderWorker"


class RenderWorker:
    """Renders one manifest row (a dict) per call into the shared data directory, in the worker's own
    process (a Ray actor: a Blender crash kills the actor, and Ray runs the example again elsewhere)."""

    def __init__(self, job: dict):
        self.job = job
        self.registry = load_registry(job["config_dirs"])
        self.preset = self.registry.preset(job["preset"])

    def __call__(self, row: dict) -> dict:
        sample = ManifestRow.from_dict(row)
        try:
            path = render_to_bundle(sample, self.registry, self.preset, Path(self.job["data_dir"]),
                                    device=self.job["device"], threads=self.job["threads"])
        except (*EXAMPLE_ERRORS, RuntimeError) as exc:  # RuntimeError: Blender's own errors
            return {"status": "failed", "error": f"{type(exc).__name__}: {exc}"}
        return {"status": "succeeded", "path": str(path)}


def render_rows_with(executor: Executor, rows: Sequence[ManifestRow], registry: Registry, data_dir: Path,
                     quality: str = "paper", device: str = "auto", config_dirs: Sequence[str | Path] = (),
                     threads: int | None = None, progress: bool = True) -> tuple[list[str], list[Failure]]:
    """``render_rows`` through an executor (one Ray actor per CPU set by default): same bundles, same layout."""
    from tqdm import tqdm

    registry.preset(quality)  # an unknown preset fails here, not on every worker
    todo = [r for r in rows if not is_complete(data_dir, r)]
    job = {"config_dirs": [str(d) for d in config_dirs], "preset": quality,
           "data_dir": str(Path(data_dir).resolve()), "device": device, "threads": threads}
    done_ids: list[str] = []
    failures: list[Failure] = []
    bar = tqdm(total=len(todo), desc="examples", unit="ex", disable=not progress or not todo)

    def collect(row: dict, record: dict) -> None:
        if record.get("status") == "succeeded":
            done_ids.append(row["sample_id"])
        else:
            failures.append(Failure(row["sample_id"], record.get("error", "failed")))
            bar.write(f"FAILED {row['sample_id']}: {failures[-1].reason}")
        bar.update(1)

    try:
        executor.map(RENDER_WORKER, job, [r.to_dict() for r in todo], Resources(num_cpus=threads or 1),
                     on_result=collect)
    finally:
        bar.close()
    return sorted(done_ids), failures


# -- command line ------------------------------------------------------------------------------------------


def _ids(values: Sequence[str] | None) -> list[str]:
    return [v.strip() for chunk in (values or []) for v in chunk.replace(",", " ").split() if v.strip()]


def cmd_render(args: argparse.Namespace, ctx: RunContext) -> int:
    reg = ctx.registry
    try:
        rows = manifest.select(manifest.rows(args.split, reg), _ids(args.ids) or None, args.limit)
    except KeyError as exc:
        raise UserError(exc.args[0]) from None
    if args.quality not in reg.presets:
        raise UserError(f"unknown quality '{args.quality}'; presets: {', '.join(reg.presets)}")
    if not bpy_available():
        raise UserError("rendering needs Blender as a Python module (bpy 4.5, Python 3.11); "
                        "install it with `pip install -e '.[sim]'`")
    data = Path(args.data)
    if B.bundle_dirs(data):
        raise UserError(f"{data} holds bundles itself: it is a split directory, and render writes into "
                        f"DATA/<split>/; did you mean --data {data.parent}?")
    rows = Shard.parse(getattr(args, "shard", None)).select(rows)
    if getattr(args, "executor", "local") == "ray":
        executor = make_executor("ray", ray_address=args.ray_address, workers=args.workers if args.workers > 1 else None)
        done, failures = render_rows_with(executor, rows, reg, data, quality=args.quality, device=args.device,
                                          config_dirs=ctx.config_dirs, progress=not args.no_progress)
    else:
        done, failures = render_rows(rows, reg, data, quality=args.quality, workers=args.workers, device=args.device,
                                     config_dirs=ctx.config_dirs, progress=not getattr(args, "no_progress", False),
                                     quiet=not getattr(args, "verbose", False))
    skipped = len(rows) - len(done) - len(failures)
    print(f"rendered {len(done)}, skipped {skipped} complete, failed {len(failures)} of {len(rows)} "
          f"{args.split} examples ({args.quality}) into {data / args.split}")
    for f in failures:
        print(f"  FAILED {f.sample_id}: {f.reason}", file=sys.stderr)
    if failures:
        print("rerun the same command to retry the failed examples; complete bundles are kept", file=sys.stderr)
    return 1 if failures else 0


def cmd_show(args: argparse.Namespace, ctx: RunContext) -> int:
    split_dir = B.resolve_split_dir(args.data, args.split)
    path = split_dir / args.id
    if not path.is_dir():
        raise UserError(f"{path}: no bundle for example {args.id}; render it first with "
                        f"`rigidbench render --split {split_dir.name} --ids {args.id}`")
    out = Path(args.out) if args.out else Path(f"{split_dir.name}_{args.id}_contact_sheet.png")
    write_contact_sheet(B.Sample(path), out)
    print(f"wrote {out}")
    return 0


__all__ = ["Failure", "RenderWorker", "bundle_dir", "is_complete", "write_bundle", "render_spec", "render_to_bundle",
           "render_rows", "render_rows_with",
           "cmd_render", "cmd_show", "QUALITIES"]
