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

Records: each example's record is written on its own, atomically and fsynced, to
``OUT/.generation/<id>.json`` as soon as that example is done (whatever order examples finish in), and
merged into ``generation.json`` as results come in and when the run ends or is interrupted. A rerun merges
records a killed run left only there, and rebuilds the record of a finished video that has none (from
the predictor's own state, e.g. a hosted prediction's id, else from the seed and prompts).

Hosted runs in this process stop gracefully on SIGTERM or Ctrl-C: no new example starts and no new
prediction is created, requests already sent are answered and recorded, outputs already paid for are
downloaded; then the run ends as interrupted (a second signal ends it at once; the records on disk and
the predictor's resume state let the rerun go on without paying twice). Temporaries an interrupted run
left for an example are removed when the example runs again.
"""

from __future__ import annotations

import glob
import hashlib
import json
import logging
import os
import shutil
import signal
import sys
import threading
import time
from dataclasses import dataclass, field, replace
from pathlib import Path
from types import MappingProxyType

from tqdm import tqdm

from ..atomic import atomic_file
from ..context import RunContext
from ..errors import EXAMPLE_ERRORS, UserError
from ..executors import Executor, LocalExecutor, Resources, Shard, failure_record
from ..evaluation.cache import write_json
from ..jsonio import write_json as write_json_atomic
from ..evaluation.provenance import versions
from ..folders import (GENERATION_FILE, RECORDS_DIR, SETTINGS_FILE, VIDEO_EXTENSIONS,  # noqa: F401 (re-exported)
                       PredictionsFolder, state_path)
from ..groundtruth.bundle import Sample, bundle_dirs, refuse_imported
from ..predictors import (SEED_RULE, Kind, PredictContext, Prediction, Predictor, PredictorInfo, example_seed,
                          model_inputs, predictor_info)
from ..video import write_video

log = logging.getLogger(__name__)

FILE_MODE = 0o644  # videos get the permissions of the JSON files beside them (jsonio)
INTERRUPTED = "interrupted"  # a record's status when the run stopped before the example was done
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
        pred.state.save(PredictionsFolder(out_dir).state(sample_id))  # atomic
    if pred.video_path is not None:
        source = Path(pred.video_path)
        video = PredictionsFolder(out_dir).video(sample_id, source.suffix.lower() or ".mp4")
        # hidden: validate and evaluate ignore it; remove_temporaries finds it by name
        with atomic_file(video, tmp=out_dir / f".{sample_id}.partial{video.suffix}", mode=FILE_MODE) as tmp_video:
            shutil.copyfile(source, tmp_video)
        return
    if pred.frames is None:
        raise TypeError(f"example {sample_id}: a Prediction needs frames or a video_path")
    video = PredictionsFolder(out_dir).video(sample_id)
    with atomic_file(video, tmp=out_dir / f".{sample_id}.partial.mp4", mode=FILE_MODE) as tmp_video:
        write_video(tmp_video, pred.frames, fps=fps if fps is not None else pred.fps, lossless=pred.lossless)


def remove_temporaries(out_dir: Path, sample_id: str) -> None:
    """Remove what an interrupted run left of ``sample_id``'s video: ``.<id>.partial.*`` and the encoder's
    ``..<id>.partial.*.tmp.*``."""
    for pattern in (glob.escape(f".{sample_id}.partial") + "*", glob.escape(f"..{sample_id}.partial.") + "*"):
        for stale in Path(out_dir).glob(pattern):
            try:
                stale.unlink()
            except OSError:
                pass


def finished_ids(out_dir: Path, settings: dict, needs_state: bool) -> set[str]:
    """Ids whose video (and state, where the predictor writes one) exist from a run with the same settings.

    ``.predictor.json`` records the settings of the last run; with other settings nothing counts as
    finished and the selected examples are written again (other files are left alone)."""
    path = PredictionsFolder(out_dir).settings
    previous = _read_settings(path)
    out_dir.mkdir(parents=True, exist_ok=True)
    if previous != settings:
        if previous is not None:
            log.info("%s held %s; writing the selected predictions again for %s", out_dir, previous, settings)
        write_json_atomic(path, settings, indent=None)
        return set()
    videos = [v for v in out_dir.iterdir() if v.suffix.lower() in VIDEO_EXTENSIONS]
    return {v.stem for v in videos
            if "." not in v.stem and not v.name.startswith(".") and (not needs_state or state_path(v).exists())}


def _read_settings(path: Path):
    """The settings ``.predictor.json`` records, None when absent; a damaged one is a UserError (deciding that
    nothing is finished could pay for hosted predictions again)."""
    try:
        return json.loads(path.read_text())
    except FileNotFoundError:
        return None
    except (OSError, ValueError) as exc:
        raise UserError(f"{path}: damaged ({type(exc).__name__}); it records the settings of the predictions in "
                        f"{path.parent}. Delete it to write the selected predictions again") from None


def select_examples(split_dir: Path, ids: list[str] | None = None, limit: int | None = None) -> list[Path]:
    """Bundles of ``split_dir``, narrowed to ``ids`` (an unknown id is a UserError) and the first ``limit``."""
    refs = bundle_dirs(split_dir)
    if ids:
        unknown = sorted(set(ids) - {r.name for r in refs})
        if unknown:
            raise UserError(f"unknown example id(s) {', '.join(unknown)} in {split_dir}")
        refs = [r for r in refs if r.name in set(ids)]
    return refs[:limit] if limit is not None else refs


def settings_digest(settings: dict) -> str:
    """A short hash of a run's settings: per-example records of other settings are not merged."""
    return hashlib.sha256(json.dumps(settings, sort_keys=True, default=str).encode()).hexdigest()[:16]


def write_example_record(out_dir: Path, sample_id: str, digest: str, entry: dict) -> None:
    """``OUT/.generation/<id>.json``: the example's record, atomically and fsynced, as soon as it is done."""
    write_json_atomic(PredictionsFolder(out_dir).record(sample_id),
                      {"id": sample_id, "settings": digest, "entry": entry}, durable=True)


def _read_json(path: Path, what: str):
    try:
        return json.loads(path.read_text())
    except FileNotFoundError:
        return None
    except (OSError, ValueError) as exc:
        log.warning("%s: unreadable (%s); %s", path, type(exc).__name__, what)
        return None


class GenerationLog:
    """generation.json: the run's model and parameters, and one record per example (thread-safe).

    Records of earlier runs with the same settings are kept; the per-example records in ``.generation/``
    (written by the workers as each example finishes) are merged in, and a finished video without a record
    gets one rebuilt by ``recover(sample_id)``. Rewritten atomically after every example and by ``merge``."""

    def __init__(self, out_dir: Path, header: dict, finished: set[str] = frozenset(), recover=None):
        self.out_dir = Path(out_dir)
        self.path = PredictionsFolder(self.out_dir).generation
        self.records_dir = PredictionsFolder(self.out_dir).records_dir
        self.digest = settings_digest({k: header[k] for k in ("predictor", "settings")})
        self.lock = threading.Lock()
        previous = _read_json(self.path, "it is rebuilt from the per-example records") or {}
        if not isinstance(previous, dict):
            previous = {}
        same = {k: previous.get(k) for k in ("predictor", "settings")} == {k: header[k] for k in ("predictor", "settings")}
        examples = previous.get("examples") if same else None
        self.doc = {**header, "examples": dict(examples) if isinstance(examples, dict) else {}}
        self._merge_records(remove_others=True)
        repaired = []
        for sample_id in sorted(finished):
            entry = self.doc["examples"].get(sample_id)
            if isinstance(entry, dict) and entry.get("status") == "succeeded":
                continue
            rebuilt = {"status": "succeeded", **((recover(sample_id) if recover else None) or {}),
                       "recovered": "the video was on disk without its record (an interrupted run); rebuilt on rerun"}
            rebuilt["status"] = "succeeded"
            write_example_record(self.out_dir, sample_id, self.digest, rebuilt)
            self.doc["examples"][sample_id] = rebuilt
            repaired.append(sample_id)
        if repaired:
            log.warning("%s: rebuilt the lost records of %d finished example(s): %s", self.path, len(repaired),
                        ", ".join(repaired))
        self._write()

    def _merge_records(self, remove_others: bool = False) -> None:
        """Take every per-example record of these settings (newer than generation.json's copy)."""
        if not self.records_dir.is_dir():
            return
        for path in sorted(self.records_dir.glob("*.json")):
            doc = _read_json(path, "ignored")
            if not isinstance(doc, dict) or not isinstance(doc.get("entry"), dict) or not isinstance(doc.get("id"), str):
                continue
            if doc.get("settings") != self.digest:
                if remove_others:  # a record of other settings: those examples are written again
                    path.unlink(missing_ok=True)
                continue
            self.doc["examples"][doc["id"]] = doc["entry"]

    def _write(self) -> None:
        self.doc["examples"] = dict(sorted(self.doc["examples"].items()))
        write_json(self.path, self.doc)

    def record(self, sample_id: str, entry: dict) -> None:
        with self.lock:
            self.doc["examples"][sample_id] = entry
            self._write()

    def merge(self) -> None:
        """Merge the per-example records (workers elsewhere, or examples whose result never came back)."""
        with self.lock:
            self._merge_records()
            self._write()


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
    preflight = getattr(settings_source, "preflight", None)
    if todo and preflight is not None:  # e.g. a hosted model's token: one error before any example
        try:
            preflight(ctx)
        except BaseException:
            if settings_source is not predictor:
                settings_source.close()
            raise
    header = {"predictor": info.name, "target": info.target, "kind": info.kind.value, "settings": settings,
              "model": settings_source.generation_info(ctx), "versions": versions(VERSION_PACKAGES)}
    recover = getattr(settings_source, "recover_record", None)

    def rebuild(sample_id: str) -> dict:
        """What a finished video's lost record can be rebuilt from: the predictor's state, seed and prompts."""
        entry: dict = {"seed": example_seed(ctx.seed, sample_id)}
        try:
            inputs = model_inputs(Sample(split_dir / sample_id))
            entry.update(prompt=inputs.prompt, negative_prompt=inputs.negative_prompt)
        except EXAMPLE_ERRORS:
            pass
        entry.update((recover(out_dir, sample_id) if recover else None) or {})
        return entry

    log_file = GenerationLog(out_dir, header, done, rebuild)
    if settings_source is not predictor:
        settings_source.close()
    bar = tqdm(total=len(todo), unit="example", desc=f"predict {info.name}", disable=not progress or not todo)

    def collect(sample_id: str, entry: dict) -> None:
        if entry.get("status") == INTERRUPTED:
            if entry.get("started"):
                log_file.record(sample_id, entry)
            return
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
           "run": ctx.run.job(), "severity": ctx.severity, "seed": ctx.seed, "options": dict(ctx.options),
           "records": log_file.digest}
    if local:
        executor = LocalExecutor(threads=max(executor.threads, int(predictor.concurrency(ctx))))
    worker = PredictWorker(job, predictor=predictor, ctx=ctx) if local else None
    stopper = _GracefulStop(worker) if local and info.kind == Kind.HOSTED and todo else None
    try:
        if stopper is not None:
            stopper.install()
        executor.map(WORKER, job, todo, predict_resources(info, ctx), on_result=collect, instance=worker)
    finally:
        if stopper is not None:
            stopper.uninstall()
        bar.close()
        log_file.merge()  # whatever finished, in any order, also when the run is interrupted
    if stopper is not None and stopper.signal_name:
        finished = len(summary.written) - len(summary.skipped)
        log.warning("stopped by %s: %d example(s) finished and recorded, %d failed, %d not done; predictions "
                    "already created are kept with their ids; rerun the same command to resume without paying twice",
                    stopper.signal_name, finished, len(summary.failed), len(todo) - finished - len(summary.failed))
        raise KeyboardInterrupt(stopper.signal_name)
    summary.written.sort()
    return summary


class _GracefulStop:
    """SIGTERM and SIGINT handlers for a hosted run in this process: the first signal stops new work and lets
    what was already sent (and paid for) be answered and recorded; a second one ends the process at once
    (the resume state on disk makes that safe). Installed only from the main thread."""

    SIGNALS = ("SIGINT", "SIGTERM")

    def __init__(self, worker: "PredictWorker"):
        self.worker = worker
        self.signal_name: str | None = None
        self.previous: dict = {}

    def install(self) -> None:
        if threading.current_thread() is not threading.main_thread():
            return
        for name in self.SIGNALS:
            signum = getattr(signal, name, None)
            if signum is not None:
                self.previous[signum] = signal.signal(signum, self._handle)

    def uninstall(self) -> None:
        for signum, handler in self.previous.items():
            signal.signal(signum, handler)
        self.previous = {}

    def _handle(self, signum, frame) -> None:
        name = signal.Signals(signum).name
        if self.signal_name is not None:
            sys.stderr.write(f"rigidbench predict: second {name}: stopping at once; finished examples and created "
                             "predictions are recorded on disk, rerun the same command to resume\n")
            sys.stderr.flush()
            os._exit(128 + signum)
        self.signal_name = name
        self.worker.stop()
        sys.stderr.write(f"rigidbench predict: {name}: no new predictions are created; waiting for the requests in "
                         "flight and recording what was paid for (send it again to stop at once)\n")
        sys.stderr.flush()


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
        self.records = job.get("records")  # the settings digest of per-example records (None: none written)
        self.stopping = threading.Event()

    def stop(self) -> None:
        """Start no new example; the predictor (if it can) creates nothing new and finishes what is paid for."""
        self.stopping.set()
        request_stop = getattr(self.predictor, "request_stop", None)
        if request_stop is not None:
            request_stop()

    def __call__(self, sample_id: str) -> dict:
        if self.stopping.is_set():
            return {"status": INTERRUPTED, "error": "not started: the run was stopped"}
        info, ctx = self.predictor.info, example_context(self.ctx, sample_id)
        started = time.time()
        entry: dict = {"seed": ctx.seed}
        remove_temporaries(self.out_dir, sample_id)
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
            if self.stopping.is_set():  # stopped, not failed: the rerun takes it up again
                entry.update(status=INTERRUPTED, started=True)
        entry["seconds"] = round(time.time() - started, 3)
        if self.records is not None:
            write_example_record(self.out_dir, sample_id, self.records, entry)
        return entry

    def close(self) -> None:
        self.predictor.close()


def example_context(ctx: PredictContext, sample_id: str) -> PredictContext:
    """``ctx`` with the seed of example ``sample_id``: ``example_seed(ctx.seed, sample_id)`` (ctx.seed is the base)."""
    return replace(ctx, seed=example_seed(ctx.seed, sample_id))


def _dry_run(predictor: Predictor, refs: list[Path], out_dir: Path, settings: dict, ctx: PredictContext,
             summary: PredictSummary) -> PredictSummary:
    """Print the request of every example that a real run would generate; send and write nothing."""
    previous = PredictionsFolder(out_dir).settings
    same = _read_settings(previous) == settings
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
