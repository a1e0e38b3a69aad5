"""The predict stage: one video (and, where the predictor knows it, its world state) per reference example.

Outputs in ``OUT/``: ``<id>.mp4`` (written last, atomically) and ``<id>.state.npz`` for predictors
that write the exact world state; ``generation.json`` with the model, every parameter, package
versions and per example its status, seed, prompts, timing and whatever the model reports
(prediction id, cost); and a hidden ``.predictor.json`` recording the predictor and its settings.
``ctx.seed`` is the run's base seed: each example is predicted with its own seed,
``predictors.example_seed(base, example id)``, which its record in generation.json holds.
A rerun with the same settings skips finished examples and retries failed ones; with other
settings it writes the selected examples again. One example's failure is recorded and the others
go on. Predictors that allow it (hosted APIs) run several examples at once in threads.
"""

from __future__ import annotations

import json
import logging
import shutil
import threading
import time
from dataclasses import dataclass, field, replace
from pathlib import Path
from types import MappingProxyType

from tqdm import tqdm

from ..context import RunContext
from ..errors import EXAMPLE_ERRORS, UserError
from ..executors import Executor, LocalExecutor, Resources, Shard, failure_record
from ..evaluation.cache import write_json
from ..evaluation.provenance import versions
from ..groundtruth.bundle import Sample, bundle_dirs, refuse_imported
from ..perception.gt import state_path
from ..predictors import (SEED_RULE, Kind, PredictContext, Prediction, Predictor, PredictorInfo, example_seed,
                          model_inputs, predictor_info)
from ..video import VIDEO_EXTENSIONS, write_video

log = logging.getLogger(__name__)

SETTINGS_FILE = ".predictor.json"  # hidden: validate and evaluate skip it
GENERATION_FILE = "generation.json"
VERSION_PACKAGES = ("diffusers", "transformers", "peft", "httpx")


@dataclass
class PredictSummary:
    written: list[str] = field(default_factory=list)  # finished now or before
    skipped: list[str] = field(default_factory=list)  # of those, finished by an earlier run
    failed: dict[str, str] = field(default_factory=dict)
    planned: list[str] = field(default_factory=list)  # --dry-run: what would be generated
    paid_calls: int = 0  # --dry-run: paid API calls the run would make


def write_prediction(pred: Prediction, out_dir: str | Path, sample_id: str, fps: float | None = None) -> None:
    """Write ``<id>.state.npz`` (when the prediction has a state) then ``<id>.mp4``, each via a temporary
    file, so an existing video always has its complete state beside it. Frames are encoded (lossless
    H.264 RGB when ``pred.lossless``); a ready ``pred.video_path`` is moved into place as it is."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    if pred.state is not None:
        pred.state.save(state_path(out_dir / f"{sample_id}.mp4"))  # atomic
    if pred.video_path is not None:
        source = Path(pred.video_path)
        video = out_dir / f"{sample_id}{source.suffix.lower() or '.mp4'}"
        tmp_video = out_dir / f".{sample_id}.partial{video.suffix}"  # hidden: validate and evaluate ignore it
        shutil.copyfile(source, tmp_video)
        tmp_video.replace(video)
        return
    if pred.frames is None:
        raise TypeError(f"example {sample_id}: a Prediction needs frames or a video_path")
    tmp_video = out_dir / f".{sample_id}.partial.mp4"
    write_video(tmp_video, pred.frames, fps=fps if fps is not None else pred.fps, lossless=pred.lossless)
    tmp_video.replace(out_dir / f"{sample_id}.mp4")


def finished_ids(out_dir: Path, settings: dict, needs_state: bool) -> set[str]:
    """Ids whose video (and state, where the predictor writes one) exist from a run with the same settings.

    ``.predictor.json`` records the settings of the last run; with other settings nothing counts as
    finished and the selected examples are written again (other files are left alone)."""
    path = out_dir / SETTINGS_FILE
    previous = json.loads(path.read_text()) if path.exists() else None
    out_dir.mkdir(parents=True, exist_ok=True)
    if previous != settings:
        if previous is not None:
            log.info("%s held %s; writing the selected predictions again for %s", out_dir, previous, settings)
        path.write_text(json.dumps(settings) + "\n")
        return set()
    videos = [v for v in out_dir.iterdir() if v.suffix.lower() in VIDEO_EXTENSIONS]
    return {v.stem for v in videos
            if "." not in v.stem and not v.name.startswith(".") and (not needs_state or state_path(v).exists())}


def select_examples(split_dir: Path, ids: list[str] | None = None, limit: int | None = None) -> list[Path]:
    """Bundles of ``split_dir``, narrowed to ``ids`` (an unknown id is a UserError) and the first ``limit``."""
    refs = bundle_dirs(split_dir)
    if ids:
        unknown = sorted(set(ids) - {r.name for r in refs})
        if unknown:
            raise UserError(f"unknown example id(s) {', '.join(unknown)} in {split_dir}")
        refs = [r for r in refs if r.name in set(ids)]
    return refs[:limit] if limit is not None else refs


class GenerationLog:
    """generation.json: the run's model and parameters, and one record per example, rewritten atomically
    after every example (thread-safe); records of earlier runs with the same settings are kept."""

    def __init__(self, path: Path, header: dict):
        self.path = path
        self.lock = threading.Lock()
        previous = json.loads(path.read_text()) if path.exists() else {}
        same = {k: previous.get(k) for k in ("predictor", "settings")} == {k: header[k] for k in ("predictor", "settings")}
        self.doc = {**header, "examples": dict(previous.get("examples", {})) if same else {}}

    def record(self, sample_id: str, entry: dict) -> None:
        with self.lock:
            self.doc["examples"][sample_id] = entry
            self.doc["examples"] = dict(sorted(self.doc["examples"].items()))
            write_json(self.path, self.doc)


def predict(name: str, split_dir: Path, out_dir: Path, ctx: PredictContext | None = None,
            ids: list[str] | None = None, limit: int | None = None, progress: bool = True,
            predictor: Predictor | None = None, dry_run: bool = False, executor: Executor | None = None,
            shard: Shard = Shard()) -> PredictSummary:
    """Run predictor ``name`` (a registered name or a "module:attr" plug-in) over the reference bundles
    in ``split_dir``; returns what was written, skipped and failed (with ``dry_run``: what would be
    generated and how many paid calls that takes, sending and writing nothing). ``executor`` runs the
    examples (default: this process, ``predictor.concurrency`` at once); ``shard`` takes its part."""
    ctx = ctx or PredictContext()
    if not 0.0 <= ctx.severity <= 1.0:
        raise UserError(f"severity must lie in [0, 1], got {ctx.severity}")
    out_dir = Path(out_dir)
    split_dir = Path(split_dir)
    ctx = PredictContext(ctx.run, ctx.severity, ctx.seed, ctx.keep_bundle_dir, out_dir, ctx.options)
    executor = executor or LocalExecutor()
    local = isinstance(executor, LocalExecutor)
    info = predictor.info if predictor is not None else predictor_info(name)
    if predictor is None and (local or dry_run):
        predictor = info.create()
    settings_source = predictor or info.create()  # settings and provenance come from the driver's instance
    refs = shard.select(select_examples(split_dir, ids, limit))
    if info.needs_blender:
        refuse_imported(refs, f"predictor '{info.name}' re-simulates the scene")
    settings = {"predictor": info.name, "target": info.target, **settings_source.settings(ctx)}
    if settings.get("seed") is not None:  # a seeded predictor: ctx.seed is the base of per-example seeds
        settings["seeds"] = SEED_RULE
    summary = PredictSummary()
    if dry_run:
        return _dry_run(predictor, refs, out_dir, settings, ctx, summary)
    done = finished_ids(out_dir, settings, info.writes_state)
    todo = [r.name for r in refs if r.name not in done]
    summary.skipped = [r.name for r in refs if r.name in done]
    summary.written = list(summary.skipped)
    if summary.skipped:
        log.info("%s: %d of %d predictions already written with these settings; skipping them", out_dir,
                 len(summary.skipped), len(refs))
    log_file = GenerationLog(out_dir / GENERATION_FILE, {
        "predictor": info.name, "target": info.target, "kind": info.kind.value, "settings": settings,
        "model": settings_source.generation_info(ctx), "versions": versions(VERSION_PACKAGES)})
    if settings_source is not predictor:
        settings_source.close()
    bar = tqdm(total=len(todo), unit="example", desc=f"predict {info.name}", disable=not progress or not todo)

    def collect(sample_id: str, entry: dict) -> None:
        if entry.get("status") == "succeeded":
            summary.written.append(sample_id)
        else:
            summary.failed[sample_id] = entry.get("error", "failed")
            log.error("example %s failed: %s", sample_id, summary.failed[sample_id])
        log_file.record(sample_id, entry)
        bar.update(1)

    job = {"predictor": {"name": info.name, "target": info.target, "description": info.description,
                         "kind": info.kind.value, "needs_blender": info.needs_blender,
                         "writes_state": info.writes_state},  # so a worker needs no registration of its own
           "split_dir": str(split_dir.resolve()), "out_dir": str(out_dir.resolve()),
           "run": ctx.run.job(), "severity": ctx.severity, "seed": ctx.seed, "options": dict(ctx.options)}
    if local:
        executor = LocalExecutor(threads=max(executor.threads, int(predictor.concurrency(ctx))))
    worker = PredictWorker(job, predictor=predictor, ctx=ctx) if local else None
    try:
        executor.map(WORKER, job, todo, predict_resources(info, ctx), on_result=collect, instance=worker)
    finally:
        bar.close()
    summary.written.sort()
    return summary


def predict_resources(info, ctx: PredictContext) -> Resources:
    """A GPU for local video models (unless the device is the CPU); a fraction of a CPU for hosted calls."""
    if info.kind == Kind.LOCAL:
        return Resources(num_cpus=1, num_gpus=0 if ctx.run.device == "cpu" else 1)
    if info.kind == Kind.HOSTED:
        return Resources(num_cpus=0.25)
    return Resources(num_cpus=1)


WORKER = "rigidbench.pipeline.predict:PredictWorker"


class PredictWorker:
    """Makes and writes one example's prediction per call (sample id -> generation.json entry); keeps its
    predictor (and any model it loaded) between calls. Built from the job in a Ray actor, or handed a
    ready predictor and context in this process."""

    def __init__(self, job: dict, predictor: Predictor | None = None, ctx: PredictContext | None = None):
        self.split_dir = Path(job["split_dir"])
        self.out_dir = Path(job["out_dir"])
        self.ctx = ctx or PredictContext(RunContext.from_job(job["run"]), job["severity"], job["seed"],
                                         out_dir=self.out_dir, options=MappingProxyType(dict(job["options"])))
        self.predictor = predictor or PredictorInfo(**{**job["predictor"], "kind": Kind(job["predictor"]["kind"])}).create()

    def __call__(self, sample_id: str) -> dict:
        info, ctx = self.predictor.info, example_context(self.ctx, sample_id)
        started = time.time()
        entry: dict = {"seed": ctx.seed}
        try:
            sample = Sample(self.split_dir / sample_id)
            inputs = model_inputs(sample)
            entry.update(prompt=inputs.prompt, negative_prompt=inputs.negative_prompt)
            pred = self.predictor.predict(sample, ctx)
            if info.writes_state and pred.state is None:
                raise TypeError(f"predictor '{info.name}' is registered as writing the world state "
                                "but returned a Prediction without one")
            write_prediction(pred, self.out_dir, sample_id, sample.fps if info.kind == Kind.FAILURE_MODE else None)
            entry.update(status="succeeded", **pred.metadata)
        except EXAMPLE_ERRORS as exc:
            entry.update(failure_record(exc))
        entry["seconds"] = round(time.time() - started, 3)
        return entry

    def close(self) -> None:
        self.predictor.close()


def example_context(ctx: PredictContext, sample_id: str) -> PredictContext:
    """``ctx`` with the seed of example ``sample_id``: ``example_seed(ctx.seed, sample_id)`` (ctx.seed is the base)."""
    return replace(ctx, seed=example_seed(ctx.seed, sample_id))


def _dry_run(predictor: Predictor, refs: list[Path], out_dir: Path, settings: dict, ctx: PredictContext,
             summary: PredictSummary) -> PredictSummary:
    """Print the request of every example that a real run would generate; send and write nothing."""
    previous = out_dir / SETTINGS_FILE
    same = previous.exists() and json.loads(previous.read_text()) == settings
    for ref in refs:
        if same and any((out_dir / f"{ref.name}{ext}").exists() for ext in VIDEO_EXTENSIONS):
            summary.skipped.append(ref.name)
            continue
        request = predictor.describe(Sample(ref), example_context(ctx, ref.name))
        print(f"{ref.name}: {json.dumps(request, sort_keys=True)}")
        summary.planned.append(ref.name)
    summary.paid_calls = len(summary.planned) if predictor.paid else 0
    predictor.close()
    return summary
