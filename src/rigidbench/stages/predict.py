"""The predict stage: one video (and, where the predictor knows it, its world state) per reference example.

Outputs in ``OUT/``: ``<id>.mp4`` and ``<id>.state.npz`` for predictors that write the exact world state;
``generation.json`` with the model, every parameter, package versions and per example its status, seed,
prompts, timing and whatever the model reports (prediction id, cost); and a hidden ``.predictor.json``
recording the predictor and the settings of the last run. ``ctx.seed`` is the run's base seed: each example
is predicted with its own seed, ``predictors.example_seed(base, example id)``, which its record in
generation.json holds.

The stage runs on the stage driver (``rigidbench.driver``): ``PredictStage`` declares the examples (the
selected reference bundles) and each one's key, ``PredictWorker`` makes one example's prediction in the
driver's staging folder, and the driver commits it (``<id>.state.npz``, then ``<id>.<ext>``, then the
example's record ``.generation/<id>.json``) and writes the example's ledger entry,
``OUT/.stages/predict/<id>.json``. An example's key (``PredictStage.key``) is a hash of the predictor's
settings (what ``.predictor.json`` records), the example's own seed (for a seeded predictor) and its model
inputs (the first frame's file, the prompt with the paper's suffix, the negative prompt). So a rerun skips
an example whose key is unchanged and whose video (and state) is still there, retries a failed one, and
makes again exactly those whose settings or inputs changed, saying why. A folder written before ledgers is
taken over without predicting again when ``.predictor.json`` holds these settings and the video (and state)
is there. One example's failure is recorded and the others go on. Predictors that allow it (hosted APIs)
run several examples at once in threads.

Records: each example's record is written on its own, atomically and fsynced, to ``OUT/.generation/<id>.json``
(committed with the example's outputs; a failed or interrupted example's when its result comes back), and
merged into ``generation.json`` as results come in and when the run ends or is interrupted. A rerun merges
records a killed run left only there, and rebuilds the record of a finished video that has none (from the
predictor's own state, e.g. a hosted prediction's id, else from the seed and prompts).

Hosted runs in this process stop gracefully on SIGTERM or Ctrl-C: no new example starts and no new
prediction is created; requests already sent get a few seconds (the client's ``stop_grace_s``, 3 s) to be
answered and recorded, and outputs already paid for to be downloaded, then they are cut off (a creation cut
off keeps its recorded intent, so the rerun adopts its prediction); then the run ends as interrupted (a
second signal ends it at once; the records on disk and the predictor's resume state let the rerun go on
without paying twice). Two runs on one folder never make the same example at once (the driver's lock per
example): the second skips what the first is making and says so, or waits for it with ``--wait``. What an
interrupted example left in the driver's staging folder is removed when it runs again, and so is a partial
video that a run of an earlier version of this stage left in ``OUT/`` itself (``remove_temporaries``).
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
from typing import Any

from ..atomic import atomic_file
from ..benchmark import NEGATIVE_PROMPT, full_prompt
from ..context import RunContext
from ..driver import ItemResult, Selection, Stage, StageReport, StageWorker, plan, run_stage
from ..errors import EXAMPLE_ERRORS, UserError
from ..evaluation.keys import write_json
from ..evaluation.provenance import versions
from ..executors import Executor, LocalExecutor, Resources, Shard, failure_record
from ..folders import (FRAMES_DIR, METADATA_FILE, VIDEO_EXTENSIONS, PredictionsFolder, find_prediction, frame_name,
                       state_path)
from ..groundtruth.bundle import Sample, bundle_dirs, read_bundle_file, refuse_imported
from ..hashing import digest, file_digest
from ..jsonio import read_json, write_json as write_json_atomic
from ..predictors import (SEED_RULE, Kind, PredictContext, Prediction, Predictor, PredictorInfo, example_seed,
                          model_inputs, predictor_info)
from ..video import write_video

log = logging.getLogger(__name__)

INTERRUPTED = "interrupted"  # a record's status when the run stopped before the example was done
VERSION_PACKAGES = ("diffusers", "transformers", "peft", "httpx")
STAGE = "predict"  # the driver's name for it: ledger entries in OUT/.stages/predict/
WORKER = "rigidbench.stages.predict:PredictWorker"


@dataclass
class PredictSummary:
    written: list[str] = field(default_factory=list)  # finished now or before
    skipped: list[str] = field(default_factory=list)  # of those, finished by an earlier run
    failed: dict[str, str] = field(default_factory=dict)
    planned: list[str] = field(default_factory=list)  # --dry-run: what would be generated
    paid_calls: int = 0  # --dry-run: paid API calls the run would make
    redone: dict[str, str] = field(default_factory=dict)  # made before and made again now: why
    elsewhere: list[str] = field(default_factory=list)  # being made by another process in the same folder


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
        with atomic_file(video, tmp=out_dir / f".{sample_id}.partial{video.suffix}") as tmp_video:
            shutil.copyfile(source, tmp_video)
        return
    if pred.frames is None:
        raise TypeError(f"example {sample_id}: a Prediction needs frames or a video_path")
    video = PredictionsFolder(out_dir).video(sample_id)
    with atomic_file(video, tmp=out_dir / f".{sample_id}.partial.mp4") as tmp_video:
        write_video(tmp_video, pred.frames, fps=fps if fps is not None else pred.fps, lossless=pred.lossless)


def remove_temporaries(out_dir: Path, sample_id: str) -> None:
    """Remove what an interrupted run of an earlier version of this stage left of ``sample_id``'s video in
    ``out_dir`` itself: ``.<id>.partial.*`` and the encoder's ``..<id>.partial.*.tmp.*`` (runs now write in
    the driver's staging folder, which the driver cleans)."""
    for pattern in (glob.escape(f".{sample_id}.partial") + "*", glob.escape(f"..{sample_id}.partial.") + "*"):
        for stale in Path(out_dir).glob(pattern):
            try:
                stale.unlink()
            except OSError:
                pass


def input_digest(bundle: Path) -> str:
    """A hash of what a video model is given for the example in ``bundle`` (``predictors.model_inputs``): the
    first frame (its file's bytes: nothing is decoded), the task prompt with the paper's suffix and the
    negative prompt. A BundleError when the bundle lacks them."""
    frame = read_bundle_file(bundle, f"{FRAMES_DIR}/{frame_name(0)}", file_digest)
    return digest(frame, full_prompt(Sample(bundle).prompt), NEGATIVE_PROMPT)


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


def settings_digest(settings: dict) -> str:
    """A short hash of a run's settings: per-example records of other settings are not merged."""
    return hashlib.sha256(json.dumps(settings, sort_keys=True, default=str).encode()).hexdigest()[:16]


def write_example_record(out_dir: Path, sample_id: str, digest: str, entry: dict) -> None:
    """``OUT/.generation/<id>.json``: the example's record, atomically and fsynced, as soon as it is done."""
    write_json_atomic(PredictionsFolder(out_dir).record(sample_id),
                      {"id": sample_id, "settings": digest, "entry": entry}, durable=True)


class GenerationLog:
    """generation.json: the run's model and parameters, and one record per example (thread-safe).

    Records of earlier runs with the same settings are kept; the per-example records in ``.generation/``
    (committed with each example's outputs) are merged in, and a finished video without a record gets one
    rebuilt by ``repair``. Rewritten atomically after every example and by ``merge``."""

    def __init__(self, out_dir: Path, header: dict):
        self.out_dir = Path(out_dir)
        self.path = PredictionsFolder(self.out_dir).generation
        self.records_dir = PredictionsFolder(self.out_dir).records_dir
        self.digest = settings_digest({k: header[k] for k in ("predictor", "settings")})
        self.lock = threading.Lock()
        previous = read_json(self.path, "it is rebuilt from the per-example records") or {}
        if not isinstance(previous, dict):
            previous = {}
        same = {k: previous.get(k) for k in ("predictor", "settings")} == {k: header[k] for k in ("predictor", "settings")}
        examples = previous.get("examples") if same else None
        self.doc = {**header, "examples": dict(examples) if isinstance(examples, dict) else {}}
        self._merge_records(remove_others=True)
        self._write()

    def repair(self, finished, recover) -> None:
        """Give each of the ``finished`` examples (their video is there) without a succeeded record one rebuilt
        by ``recover(sample_id)`` (the run was killed between an example's video and its record)."""
        repaired = []
        with self.lock:
            for sample_id in finished:
                entry = self.doc["examples"].get(sample_id)
                if isinstance(entry, dict) and entry.get("status") == "succeeded":
                    continue
                rebuilt = {"status": "succeeded", **(recover(sample_id) or {}),
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
            doc = read_json(path, "ignored")
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


class PredictStage(Stage):
    """The predict stage as the driver sees it: the selected reference bundles of ``split_dir`` (``ids``),
    written into the predictions folder ``out_dir`` by ``info``'s predictor with ``settings``.

    ``source``: the predictor the run's header, preflight and lost-record recovery come from; ``instance``:
    the worker a local executor uses; ``stopper``: SIGTERM/Ctrl-C handlers installed while examples run."""

    name = STAGE
    worker = WORKER

    def __init__(self, out_dir: Path, split_dir: Path, ids: list[str], info: PredictorInfo, settings: dict,
                 ctx: PredictContext, source: Predictor | None = None, instance: "PredictWorker | None" = None,
                 stopper: "_GracefulStop | None" = None):
        self.out_dir, self.split_dir, self.ids = Path(out_dir), Path(split_dir), list(ids)
        self.info, self.settings, self.ctx = info, settings, ctx
        self.source, self.instance, self.stopper = source, instance, stopper
        self.resources = predict_resources(info, ctx)
        self.seeded = settings.get("seed") is not None  # ctx.seed is the base of per-example seeds
        self.previous = _read_settings(PredictionsFolder(self.out_dir).settings)  # before this run rewrites it
        self.records = settings_digest({"predictor": info.name, "settings": settings})
        self.log: GenerationLog | None = None
        self.recorded: set[str] = set()

    # -- what the driver asks --------------------------------------------------------------------------

    @property
    def root(self) -> Path:
        return self.out_dir

    @property
    def where(self) -> str:
        return str(self.split_dir)

    def items(self) -> dict[str, dict]:
        return {sample_id: {"bundle": str(self.split_dir / sample_id)} for sample_id in self.ids}

    def key(self, item_id: str, payload: Any) -> str:
        """The predictor's settings, the example's own seed (None for a predictor that takes none) and a hash
        of its model inputs (``input_digest``); for the failure modes, which read the whole reference bundle,
        also its metadata (a re-rendered bundle's differs, if only in its render times)."""
        bundle = Path(payload["bundle"])
        seed = example_seed(self.ctx.seed, item_id) if self.seeded else None
        parts = {"settings": self.settings, "seed": seed, "inputs": input_digest(bundle)}
        if self.info.kind == Kind.FAILURE_MODE:
            parts["reference"] = read_bundle_file(bundle, METADATA_FILE, file_digest)
        return digest(parts)

    def job(self) -> dict:
        info, ctx = self.info, self.ctx
        return {"predictor": {"name": info.name, "target": info.target, "description": info.description,
                              "kind": info.kind.value, "needs_blender": info.needs_blender,
                              "writes_state": info.writes_state},  # so a worker needs no registration of its own
                "split_dir": str(self.split_dir.resolve()), "out_dir": str(self.out_dir.resolve()),
                "run": ctx.run.job(), "severity": ctx.severity, "seed": ctx.seed, "options": dict(ctx.options),
                "records": self.records}

    def worker_instance(self) -> "PredictWorker | None":
        return self.instance

    def intact(self, item_id: str) -> bool:
        """The video is there (``find_prediction``) and, for a predictor that writes it, the state beside it."""
        try:
            video = find_prediction(self.out_dir, item_id)
        except EXAMPLE_ERRORS:
            return False
        return video is not None and (not self.info.writes_state or state_path(video).is_file())

    def adopt(self, item_id: str, payload: Any, key: str) -> dict | None:
        """A prediction made before ledgers: ``.predictor.json`` held these settings and the video (and state)
        is there. Its result: its record, where there is one."""
        if self.previous != self.settings or not self.intact(item_id):
            return None
        doc = read_json(PredictionsFolder(self.out_dir).record(item_id), "ignored")
        if isinstance(doc, dict) and doc.get("settings") == self.records and isinstance(doc.get("entry"), dict):
            return doc["entry"]
        return {"status": "succeeded"}

    def prepare(self, todo: list[str]) -> None:
        """The predictor's check before any example runs (e.g. a hosted model's token: one error, nothing
        sent; the driver calls this only when some example will run, so an up-to-date folder needs no token),
        then the records."""
        check = getattr(self.source, "preflight", None)
        if check is not None:
            check(self.ctx)
        self._open_log()
        if self.stopper is not None:
            self.stopper.install()

    def finish(self, report: StageReport) -> None:
        if self.stopper is not None:
            self.stopper.uninstall()
        if self.log is None:
            if report.interrupted:  # stopped before any example ran: nothing to record
                return
            self._open_log()
        self.log.merge()  # first: another process's records of examples it finished (reused here) are no loss
        self.log.repair(report.reused, self.rebuild)
        for sample_id, reason in report.failed.items():  # failed before it ran (e.g. its inputs are unreadable)
            if sample_id not in self.recorded:
                self.record_result(sample_id, {"status": "failed", "error": reason, "result": {}})
        self.log.merge()  # whatever finished, in any order, also when the run is interrupted

    # -- records ---------------------------------------------------------------------------------------

    def _open_log(self) -> None:
        source = self.source
        header = {"predictor": self.info.name, "target": self.info.target, "kind": self.info.kind.value,
                  "settings": self.settings, "model": source.generation_info(self.ctx) if source else {},
                  "versions": versions(VERSION_PACKAGES)}
        self.log = GenerationLog(self.out_dir, header)
        if self.previous != self.settings:
            if self.previous is not None:
                log.info("%s held %s; now %s", self.out_dir, self.previous, self.settings)
            write_json_atomic(PredictionsFolder(self.out_dir).settings, self.settings, indent=None)
            self.previous = self.settings

    def record_result(self, sample_id: str, entry: dict) -> None:
        """``on_result``: put an example's ledger entry into generation.json (and, for a failed or interrupted
        one, write its record; a succeeded one's came with its outputs). Examples not started: no record."""
        status, record = entry.get("status"), dict(entry.get("result") or {})
        self.recorded.add(sample_id)
        if status != "succeeded":
            if status == "failed":
                record.setdefault("seed", example_seed(self.ctx.seed, sample_id))
                record.update(status="failed", error=record.get("error") or entry.get("error") or "failed")
            elif not record.get("started"):
                return
            write_example_record(self.out_dir, sample_id, self.records, record)
        if self.log is not None:
            self.log.record(sample_id, record)

    def rebuild(self, sample_id: str) -> dict:
        """What a finished video's lost record can be rebuilt from: the predictor's state, seed and prompts."""
        entry: dict = {"seed": example_seed(self.ctx.seed, sample_id)}
        try:
            inputs = model_inputs(Sample(self.split_dir / sample_id))
            entry.update(prompt=inputs.prompt, negative_prompt=inputs.negative_prompt)
        except EXAMPLE_ERRORS:
            pass
        recover = getattr(self.source, "recover_record", None)
        entry.update((recover(self.out_dir, sample_id) if recover else None) or {})
        return entry


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
    ctx = replace(ctx, out_dir=out_dir)
    executor = executor or LocalExecutor()
    local = isinstance(executor, LocalExecutor)
    info = predictor.info if predictor is not None else predictor_info(name)
    selected = Selection.of(ids, limit, shard).apply([r.name for r in bundle_dirs(split_dir)], str(split_dir))
    if info.needs_blender:
        refuse_imported([split_dir / i for i in selected], f"predictor '{info.name}' re-simulates the scene")
    if predictor is None and (local or dry_run):
        predictor = info.create()
    source = predictor or info.create()  # settings and provenance come from the driver's instance
    worker = None
    try:
        settings = {"predictor": info.name, "target": info.target, **source.settings(ctx)}
        if settings.get("seed") is not None:  # a seeded predictor: ctx.seed is the base of per-example seeds
            settings["seeds"] = SEED_RULE
        if dry_run:
            return _dry_run(PredictStage(out_dir, split_dir, selected, info, settings, ctx), predictor, ctx)
        stage = PredictStage(out_dir, split_dir, selected, info, settings, ctx, source)
        if local:
            executor = LocalExecutor(threads=max(executor.threads, int(predictor.concurrency(ctx))))
            worker = stage.instance = PredictWorker(stage.job(), predictor=predictor, ctx=ctx)
        stopper = stage.stopper = _GracefulStop(worker) if local and info.kind == Kind.HOSTED else None
        report = run_stage(stage, Selection(), executor, progress, on_result=stage.record_result)
        if stopper is not None and stopper.signal_name:
            log.warning("stopped by %s: %d example(s) finished and recorded, %d failed, %d not done; predictions "
                        "already created are kept with their ids; rerun the same command to resume without paying "
                        "twice", stopper.signal_name, len(report.ran), len(report.failed), len(report.interrupted))
            raise KeyboardInterrupt(stopper.signal_name)
        return PredictSummary(written=report.succeeded, skipped=list(report.reused), failed=dict(report.failed),
                              redone=dict(report.redone), elsewhere=list(report.elsewhere))
    finally:
        if worker is not None:
            worker.close()  # (the executor has closed it when examples ran)
        elif predictor is not None:
            predictor.close()
        if source is not predictor:
            source.close()


def _dry_run(stage: PredictStage, predictor: Predictor, ctx: PredictContext) -> PredictSummary:
    """Print the request of every example that a real run would generate (the driver's plan, the same rule
    as a run); send and write nothing."""
    items = stage.items()
    report = StageReport(stage.name, stage.root, selected=list(items))
    todo = plan(stage, list(items), items, report, write=False)
    summary = PredictSummary(skipped=list(report.reused), failed=dict(report.failed), redone=dict(report.redone))
    for task in todo:
        sample_id = task["id"]
        try:  # a damaged bundle fails its example, as in a run (plan() reports one whose key fails the same way)
            request = predictor.describe(Sample(stage.split_dir / sample_id), example_context(ctx, sample_id))
        except EXAMPLE_ERRORS as exc:
            summary.failed[sample_id] = str(exc)
            log.warning("%s: example %s failed: %s", stage.name, sample_id, exc)
            continue
        print(f"{sample_id}: {json.dumps(request, sort_keys=True)}")
        summary.planned.append(sample_id)
    summary.paid_calls = len(summary.planned) if predictor.paid else 0
    return summary


class PredictWorker(StageWorker):
    """Makes one example's prediction per call into the driver's staging folder; keeps its predictor (and
    any model it loaded) between calls. Built from the job in a Ray actor or a child process, or handed a
    ready predictor and context in this process. Thread-safe where its predictor is (hosted ones run several
    examples at once)."""

    def __init__(self, job: dict, predictor: Predictor | None = None, ctx: PredictContext | None = None):
        super().__init__(job)
        self.split_dir = Path(job["split_dir"])
        self.out_dir = Path(job["out_dir"])
        self.ctx = ctx or PredictContext(RunContext.from_job(job["run"]), job["severity"], job["seed"],
                                         out_dir=self.out_dir, options=MappingProxyType(dict(job["options"])))
        self.predictor = predictor or PredictorInfo(**{**job["predictor"], "kind": Kind(job["predictor"]["kind"])}).create()
        self.records = job.get("records")  # the settings digest of the per-example records
        self.stopping = threading.Event()
        self.closed = False

    def stop(self) -> None:
        """Start no new example; the predictor (if it can) creates nothing new and finishes what is paid for."""
        self.stopping.set()
        request_stop = getattr(self.predictor, "request_stop", None)
        if request_stop is not None:
            request_stop()

    def stopped(self) -> bool:
        return self.stopping.is_set()

    def run(self, item_id: str, payload: Any, staging: Path, progress) -> ItemResult:
        """Outputs: ``<id>.state.npz`` (when the prediction has one), ``<id>.<ext>``, ``.generation/<id>.json``."""
        if self.stopping.is_set():
            return ItemResult(status=INTERRUPTED, error="not started: the run was stopped",
                              result={"status": INTERRUPTED, "error": "not started: the run was stopped"})
        info, ctx = self.predictor.info, example_context(self.ctx, item_id)
        started = time.time()
        entry: dict = {"seed": ctx.seed}
        remove_temporaries(self.out_dir, item_id)
        try:
            sample = Sample(self.split_dir / item_id)
            inputs = model_inputs(sample)
            entry.update(prompt=inputs.prompt, negative_prompt=inputs.negative_prompt)
            pred = self.predictor.predict(sample, ctx)
            if info.writes_state and pred.state is None:
                raise TypeError(f"predictor '{info.name}' is registered as writing the world state "
                                "but returned a Prediction without one")
            write_prediction(pred, staging, item_id, sample.fps if info.kind == Kind.FAILURE_MODE else None)
            entry.update(status="succeeded", **pred.metadata)
        except EXAMPLE_ERRORS as exc:
            entry.update(failure_record(exc))
            if self.stopping.is_set():  # stopped, not failed: the rerun takes it up again
                entry.update(status=INTERRUPTED, started=True)
        entry["seconds"] = round(time.time() - started, 3)
        if entry["status"] != "succeeded":
            return ItemResult(status=entry["status"], result=entry, error=entry.get("error"))
        video = next(PredictionsFolder(staging).video(item_id, ext) for ext in VIDEO_EXTENSIONS
                     if PredictionsFolder(staging).video(item_id, ext).exists())
        outputs = [video.name]
        if pred.state is not None:
            outputs.insert(0, PredictionsFolder(staging).state(item_id).name)
        write_example_record(staging, item_id, self.records, entry)
        outputs.append(PredictionsFolder(staging).record(item_id).relative_to(staging).as_posix())
        self._remove_superseded(item_id, video.suffix, pred.state is not None)
        return ItemResult(outputs=outputs, result=entry)

    def _remove_superseded(self, sample_id: str, ext: str, has_state: bool) -> None:
        """Files of an earlier prediction of the example that the new outputs do not replace: a video of
        another format, a world state the new prediction does not have."""
        folder = PredictionsFolder(self.out_dir)
        stale = [folder.video(sample_id, e) for e in VIDEO_EXTENSIONS if e != ext]
        if not has_state:
            stale.append(folder.state(sample_id))
        for path in stale:
            if path.is_file() or path.is_symlink():
                path.unlink(missing_ok=True)

    def close(self) -> None:
        if not self.closed:
            self.closed = True
            self.predictor.close()


class _GracefulStop:
    """SIGTERM and SIGINT handlers for a hosted run in this process: the first signal stops new work and gives
    what was already sent (and paid for) a few seconds to be answered and recorded (``Deadline.cut``); a
    second one ends the process at once
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
        sys.stderr.write(f"rigidbench predict: {name}: no new predictions are created; requests in flight get a "
                         "few seconds to be answered, and what was paid for is recorded (send it again to stop at "
                         "once)\n")
        sys.stderr.flush()


def predict_resources(info, ctx: PredictContext) -> Resources:
    """A GPU for local video models (unless the device is the CPU); a fraction of a CPU for hosted calls."""
    if info.kind == Kind.LOCAL:
        return Resources(num_cpus=1, num_gpus=0 if ctx.run.device == "cpu" else 1)
    if info.kind == Kind.HOSTED:
        return Resources(num_cpus=0.25)
    return Resources(num_cpus=1)


def example_context(ctx: PredictContext, sample_id: str) -> PredictContext:
    """``ctx`` with the seed of example ``sample_id``: ``example_seed(ctx.seed, sample_id)`` (ctx.seed is the base)."""
    return replace(ctx, seed=example_seed(ctx.seed, sample_id))
