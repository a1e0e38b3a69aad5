"""The render stage: manifest rows -> sample bundles in DATA/<split>/<id>/, run by the stage driver.

``RenderStage`` declares the stage to ``driver.run_stage``, which owns the rest: which examples are
selected, which are already done, staging and the atomic commit, failures, progress and the report.
An example's *key* is a digest of what its pixels and files are made from: the scene spec built from its
manifest row, the configuration the renderer reads besides the spec (the objects' and ramp materials'
entries, the scene's, the camera search settings, the content of any user mesh they name), every setting of the render preset that changes the
output, and ``RENDER_FORMAT``; not the device, the worker count or the threads. So a rerun skips the
examples rendered with the same key (their bundle still passing ``check_bundle``), renders again exactly
those whose key changed (another ``--quality``, an edited object in a config directory) and says why, and
resumes a killed run from the examples it had not committed. A bundle rendered before the driver kept a
ledger is taken over when it is complete and its metadata names the preset asked for.

Locally each example renders in its own child Python process (``executors.ProcessExecutor``: bpy is
imported only there, and a crash inside Blender loses only that example); ``--workers N`` runs N at
once; ``--executor ray`` runs them on Ray actors. A worker renders into the driver's staging folder, and
the finished bundle is renamed into DATA/<split>/<id>/ whole. Bundles imported from the published set
are never rendered over.
"""

from __future__ import annotations

import functools
import json
import logging
import os
import shutil
from dataclasses import replace
from pathlib import Path
from typing import Any, Callable, Sequence

from ..blender.render import render_spec
from ..blender.session import bpy_available
from ..config import Registry, RenderPreset, plain, registry as load_registry
from ..driver import (Adopted, ItemResult, Progress, Redo, RunOptions, Stage, StageReport, StageWorker, Why, plan_only,
                      run_stage)
from ..errors import EXAMPLE_ERRORS, SpecError, UserError
from ..executors import ProcessExecutor, Resources
from ..extras import missing
from ..groundtruth import bundle as B
from ..hashing import digest, file_digest
from ..manifest import ManifestRow
from ..scene_spec.build import build_scene_spec
from ..scene_spec.types import SceneSpec

log = logging.getLogger(__name__)

DEFAULT_DATA = Path("data")
QUALITIES = ("paper", "preview", "test")
RENDER_WORKER = "rigidbench.stages.render:RenderWorker"
#: Bump when the renderer writes other files or pixels for the same spec, configuration and preset: every
#: bundle rendered before is then rendered again (its key changes).
RENDER_FORMAT = 1
#: Preset fields that do not change what is rendered (how Blender keeps its data between frames).
UNKEYED_PRESET_FIELDS = ("persistent_data",)


def bundle_dir(data_dir: Path, row: ManifestRow) -> Path:
    """DATA/<split>/<id>: where the example's bundle lives."""
    return Path(data_dir) / row.split / row.sample_id


def is_complete(data_dir: Path, row: ManifestRow) -> bool:
    """A bundle is complete when its final directory exists (it is only ever renamed into place) and passes
    ``check_bundle`` (shapes from the array headers: milliseconds), so a damaged one is rendered again."""
    path = bundle_dir(data_dir, row)
    return path.is_dir() and not B.check_bundle(path, deep=False)


def _metadata(path: Path) -> dict:
    """A bundle's metadata.json, or {} when it cannot be read (check_bundle then reports it as damaged)."""
    try:
        meta = json.loads((path / B.METADATA_FILE).read_text())
    except (OSError, ValueError):
        return {}
    return meta if isinstance(meta, dict) else {}


# -- the key -----------------------------------------------------------------------------------------------


def preset_settings(preset: RenderPreset) -> dict:
    """Every setting of ``preset`` that changes the rendered bundle (its name too: the metadata records it)."""
    return plain(preset, UNKEYED_PRESET_FIELDS)


def looks(spec: SceneSpec, registry: Registry) -> dict:
    """The configuration the renderer reads besides the spec: the entries of the spec's objects and ramp
    materials, its scene (room, style, support) and the camera search settings (the spec has no camera yet)."""
    assets = sorted({b.asset for b in spec.bodies if b.ramp is None})
    materials = sorted({b.ramp.material for b in spec.bodies if b.ramp is not None})
    objects = {a: registry.object(a) for a in assets}
    scene = registry.scene(spec.scene)
    meshes = {m: mesh_digest(m) for m in sorted({c.mesh_path for c in [*objects.values(), scene] if c.mesh_path})}
    return {"objects": {a: plain(c) for a, c in objects.items()},
            "materials": {m: plain(registry.material(m)) for m in materials},
            "scene": plain(scene), "camera": plain(registry.camera), "meshes": meshes}


@functools.lru_cache(maxsize=256)
def _file_digest(path: str, size: int, mtime_ns: int) -> str:
    return file_digest(path)  # cached per (path, size, time)


def mesh_digest(path: str) -> str:
    """A user mesh file's content hash (read once per process while its size and time are unchanged), so an
    edited mesh renders its examples again; SpecError when it cannot be read."""
    try:
        st = os.stat(path)
        return _file_digest(path, st.st_size, st.st_mtime_ns)
    except OSError as exc:
        raise SpecError(f"mesh file {path}: cannot be read ({exc.strerror or exc})") from None


def render_key(spec: SceneSpec, registry: Registry, preset: RenderPreset) -> str:
    """The render stage's key of one example (see the module docstring)."""
    return digest("render", RENDER_FORMAT, B.BUNDLE_VERSION, spec.to_dict(), looks(spec, registry),
                  preset_settings(preset))


# -- the stage -------------------------------------------------------------------------------------------


class RenderWorker(StageWorker):
    """Renders one manifest row into ``staging/<id>/`` (a child process, a Ray actor or this process),
    forwarding frame progress. Blender's own errors (RuntimeError) and a missing bpy (ImportError) fail the
    example like a bad spec does; the message starts with the error's type."""

    def __init__(self, job: dict, registry: Registry | None = None):
        super().__init__(job)
        self.registry = registry if registry is not None else load_registry(job["config_dirs"])
        self.preset = self.registry.preset(job["preset"])

    def run(self, item_id: str, payload: Any, staging: Path, progress: Progress) -> ItemResult:
        row = ManifestRow.from_dict(payload)
        try:
            spec = build_scene_spec(row, self.registry)
            path = render_spec(spec, self.registry, self.preset, staging / item_id, device=self.job["device"],
                               threads=self.job["threads"], on_frame=progress)
        except (*EXAMPLE_ERRORS, RuntimeError, ImportError) as exc:  # RuntimeError: Blender's own errors
            return ItemResult(status="failed", error=f"{type(exc).__name__}: {exc}")
        meta = _metadata(path)
        return ItemResult(outputs=[item_id], result={
            "preset": meta.get("preset"), "frames": meta.get("frames"),
            "device": (meta.get("render") or {}).get("device_kind"),
            "seconds": (meta.get("render_seconds") or {}).get("total")})


class RenderStage(Stage):
    """Render ``rows`` (one split's manifest rows, the candidates) into ``data_dir/<split>/`` at ``quality``.
    ``registry`` must be the one ``config_dirs`` produce (workers elsewhere rebuild it from the directories)."""

    name = "render"
    worker = RENDER_WORKER
    steps = "frame"  # passes and RGB, as the worker reports them

    def __init__(self, data_dir: str | Path, split: str, rows: Sequence[ManifestRow], registry: Registry,
                 quality: str = "paper", device: str = "auto", threads: int | None = None,
                 config_dirs: Sequence[str | Path] = ()):
        self.data_dir, self.split, self.registry, self.quality = Path(data_dir), split, registry, quality
        self.preset = registry.preset(quality)  # an unknown preset fails here, not on every worker
        self.rows = {r.sample_id: r for r in rows}
        strays = sorted({r.split for r in rows} - {split})
        if strays:
            raise ValueError(f"render stage of split {split} was given rows of split(s) {', '.join(strays)}")
        self.device, self.threads, self.config_dirs = device, threads, [str(d) for d in config_dirs]
        self.resources = Resources(num_cpus=threads or 1)

    @property
    def root(self) -> Path:
        return self.data_dir / self.split

    @property
    def where(self) -> str:
        return f"the {self.split} manifest"

    def items(self) -> dict[str, dict]:
        return {sample_id: row.to_dict() for sample_id, row in self.rows.items()}

    def key(self, item_id: str, payload: Any) -> str:
        try:
            spec = build_scene_spec(self.rows[item_id], self.registry)
        except SpecError as exc:  # the example fails; its reason reads like a worker's ("SpecError: ...")
            raise SpecError(f"{type(exc).__name__}: {exc}") from exc
        return render_key(spec, self.registry, self.preset)

    def job(self) -> dict:
        return {"config_dirs": self.config_dirs, "preset": self.quality, "device": self.device,
                "threads": self.threads}

    def worker_instance(self) -> RenderWorker:
        return RenderWorker(self.job(), self.registry)

    def intact(self, item_id: str) -> bool:
        path = self.root / item_id
        return path.is_dir() and not B.check_bundle(path, deep=False)

    def adopt(self, item_id: str, payload: Any, key: str) -> Adopted | Redo | None:
        """A bundle rendered before ledgers existed counts when complete and rendered at this preset (the old
        rule); otherwise it is rendered again, with a warning saying why."""
        path = self.root / item_id
        if not path.is_dir():
            return None
        problems = B.check_bundle(path, deep=False)
        rendered_at = _metadata(path).get("preset")
        if not problems and rendered_at == self.quality:
            return Adopted({"preset": rendered_at}, f"a complete bundle rendered at the '{rendered_at}' preset")
        why = (f"is damaged ({'; '.join(problems[:3])})" if problems else
               f"was rendered at the '{rendered_at}' preset, not '{self.quality}'")
        log.warning("example %s: the bundle in %s %s; rendering it again", item_id, path, why)
        return Redo(Why.DAMAGED if problems else Why.CHANGED, f"the bundle {why}")

    def check(self, selected: list[str]) -> None:
        self.refuse_imported(selected)

    def refuse_imported(self, ids: Sequence[str]) -> None:
        """UserError when a bundle of ``ids`` was imported from the published set (never rendered over)."""
        for sample_id in ids:
            path = self.root / sample_id
            if path.is_dir() and B.is_imported(path):
                raise UserError(f"{self.root} holds bundles imported from the published set (e.g. {sample_id}); "
                                "`render` does not overwrite them: render into another --data")

    def prepare(self, todo: list[str]) -> None:
        if not bpy_available():  # checked here, in the driver's process: one line, before any worker starts
            raise missing("bpy", "rendering (Blender as a Python module, bpy 4.5 on Python 3.11)")
        for sample_id in todo:  # a killed render's leftovers from before the driver (renders now use staging)
            leftover = self.root / f".{sample_id}.tmp"
            if leftover.is_dir():
                shutil.rmtree(leftover, ignore_errors=True)


def render_threads(workers: int) -> int | None:
    """Blender's threads per example: the CPUs shared among ``workers`` at once (None: all, one worker)."""
    if workers < 1:
        raise ValueError(f"--workers must be at least 1, got {workers}")
    return max(1, (os.cpu_count() or 1) // workers) if workers > 1 else None


def render_stage(stage: RenderStage, run: RunOptions = RunOptions(), workers: int = 1,
                 quiet: bool = True) -> StageReport:
    """Run ``stage`` as ``run`` says; returns the driver's report. No executor in ``run``: each example in a
    child process, ``workers`` at once (``quiet`` hides Blender's console output)."""
    if run.executor is None:
        run = replace(run, executor=ProcessExecutor(workers=workers, quiet=quiet, label=lambda task: task["id"]))
    return run_stage(stage, run)


def _by_split(rows: Sequence[ManifestRow]) -> dict[str, list[ManifestRow]]:
    groups: dict[str, list[ManifestRow]] = {}
    for row in rows:
        groups.setdefault(row.split, []).append(row)
    return groups


def render_rows(rows: Sequence[ManifestRow], registry: Registry, data_dir: Path, quality: str = "paper",
                workers: int = 1, device: str = "auto", config_dirs: Sequence[str | Path] = (),
                run: RunOptions = RunOptions(), quiet: bool = True, threads: int | None = None) -> list[StageReport]:
    """Render the rows that are not up to date into DATA/<split>/<id>/ (see the module docstring); returns the
    driver's report of each split. ``registry`` must be the one ``config_dirs`` produce. No executor in
    ``run``: each example in a child process, ``workers`` at once; ``threads``: Blender's per example
    (default: the CPUs shared among the workers)."""
    threads = threads if threads is not None else render_threads(workers)
    return [render_stage(RenderStage(data_dir, split, group, registry, quality, device, threads, config_dirs), run,
                         workers=workers, quiet=quiet)
            for split, group in _by_split(rows).items()]


def rows_to_render(rows: Sequence[ManifestRow], data_dir: Path, preset: str,
                   registry: Registry | None = None) -> list[ManifestRow]:
    """The rows a render at ``preset`` would render now (a dry run of the driver's decision: nothing is
    written or removed); bundles imported from the published set raise UserError, as the render does."""
    registry = registry or load_registry()
    todo: list[ManifestRow] = []
    for split, group in _by_split(rows).items():
        stage = RenderStage(data_dir, split, group, registry, preset)
        _, tasks = plan_only(stage)
        todo += [stage.rows[t["id"]] for t in tasks]
    return todo


# -- one example, in this process ------------------------------------------------------------------


def render_to_bundle(row: ManifestRow, registry: Registry, preset: RenderPreset, data_dir: Path,
                     device: str = "auto", threads: int | None = None,
                     on_frame: Callable[[int, int], None] | None = None) -> Path:
    """Render one manifest row into DATA/<split>/<id>/ in this process, outside the stage driver (no ledger:
    a later ``render`` takes the bundle over when it is complete at the preset asked for); returns its path.

    Raises SpecError, BundleError, RuntimeError or OSError naming the example."""
    spec = build_scene_spec(row, registry)
    return render_spec(spec, registry, preset, bundle_dir(data_dir, row), device=device, threads=threads,
                       on_frame=on_frame)


# -- command line ------------------------------------------------------------------------------------------


__all__ = ["QUALITIES", "RENDER_FORMAT", "RenderStage", "RenderWorker", "bundle_dir",
           "is_complete", "looks", "preset_settings", "render_key", "render_rows",
           "render_stage", "render_threads", "render_to_bundle", "rows_to_render"]
