"""The render stage: manifest rows -> sample bundles in DATA/<split>/<id>/.

Each example runs in its own child Python process (bpy is imported only there; its job description
carries the run context's configuration directories), so a crash inside Blender loses only that example;
``--workers N`` runs N at once. A bundle is built in ``DATA/<split>/.<id>.tmp`` and renamed into place when complete and validated, so a
rerun skips finished examples and restarts interrupted ones from scratch. Failures are reported
with the example id and the reason; the other examples continue.
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import shutil
import signal
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Sequence


from .. import manifest
from ..blender.render import render_spec
from ..blender.session import bpy_available
from ..config import Registry, RenderPreset, registry as load_registry
from ..context import RunContext
from ..errors import EXAMPLE_ERRORS, UserError
from ..executors import Executor, Resources, Shard, make_executor
from ..groundtruth import bundle as B
from ..groundtruth.contact_sheet import write_contact_sheet
from ..manifest import ManifestRow
from ..spec.build import build_scene_spec

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
    """A bundle is complete when its final directory exists (it is only ever renamed into place) and passes
    ``check_bundle`` (shapes from the array headers: milliseconds), so a damaged one is rendered again."""
    path = bundle_dir(data_dir, row)
    return path.is_dir() and not B.check_bundle(path, deep=False)


def rows_to_render(rows: Sequence[ManifestRow], data_dir: Path, preset: str | None = None) -> list[ManifestRow]:
    """The rows without a complete bundle rendered at ``preset`` (any preset when None). A damaged bundle (one
    that fails ``check_bundle``) or one rendered at another preset is removed with a warning saying why, so
    that it is rendered again in its place; stale temporaries of every row to render (``.<id>.tmp``, a killed
    render's) are removed too. Bundles imported from the published set are never rendered over: UserError."""
    todo = []
    for row in rows:
        path = bundle_dir(data_dir, row)
        if path.is_dir():
            if B.is_imported(path):
                raise UserError(f"{path.parent} holds bundles imported from the published set (e.g. {path.name}); "
                                "`render` does not overwrite them: render into another --data")
            problems = B.check_bundle(path, deep=False)
            rendered_at = _metadata(path).get("preset")
            if not problems and (preset is None or rendered_at == preset):
                continue
            why = (f"is damaged ({'; '.join(problems[:3])})" if problems else
                   f"was rendered at the '{rendered_at}' preset, not '{preset}'")
            log.warning("example %s: the bundle in %s %s; rendering it again", row.sample_id, path, why)
            shutil.rmtree(path)
        shutil.rmtree(path.with_name(f".{path.name}.tmp"), ignore_errors=True)  # a killed render's leftovers
        todo.append(row)
    return todo


def _metadata(path: Path) -> dict:
    """A bundle's metadata.json, or {} when it cannot be read (check_bundle then reports it as damaged)."""
    try:
        meta = json.loads((path / B.METADATA_FILE).read_text())
    except (OSError, ValueError):
        return {}
    return meta if isinstance(meta, dict) else {}


# -- one example, in this process ------------------------------------------------------------------


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
    todo = rows_to_render(rows, data_dir, quality)
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
    todo = rows_to_render(rows, data_dir, quality)
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
    if data.exists() and not data.is_dir():
        raise UserError(f"--data {data}: is a file, not a folder; pass the data folder to render into")
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
    """One contact sheet per id; an example whose bundle is missing or damaged is reported (naming the file
    and what to do) and the others are still written. Exit 1 when any failed."""
    split_dir = B.resolve_split_dir(args.data, args.split)
    ids = _ids(args.ids)
    if args.out is not None and len(ids) > 1 and Path(args.out).suffix.lower() == ".png":
        raise UserError(f"--out {args.out}: several examples need a folder for their sheets, not one PNG file")
    failed: dict[str, str] = {}
    for sample_id in ids:
        path = split_dir / sample_id
        name = f"{split_dir.name}_{sample_id}_contact_sheet.png"
        if args.out is None:
            out = Path(name)
        elif len(ids) == 1 and Path(args.out).suffix.lower() == ".png":
            out = Path(args.out)
        else:
            out = Path(args.out) / name
        try:
            if not path.is_dir():
                raise UserError(f"{path}: no bundle for example {sample_id}; render it first with "
                                f"`rigidbench render --split {split_dir.name} --ids {sample_id}`")
            out.parent.mkdir(parents=True, exist_ok=True)
            write_contact_sheet(B.Sample(path), out)
        except EXAMPLE_ERRORS as exc:
            failed[sample_id] = str(exc)
            print(f"FAILED {sample_id}: {exc}", file=sys.stderr)
            continue
        print(f"wrote {out}")
    if failed and len(ids) == 1:
        return 1
    if failed:
        print(f"{len(failed)} of {len(ids)} contact sheets failed", file=sys.stderr)
    return 1 if failed else 0


__all__ = ["Failure", "RenderWorker", "bundle_dir", "is_complete", "rows_to_render", "render_to_bundle",
           "render_rows", "render_rows_with",
           "cmd_render", "cmd_show", "QUALITIES"]
