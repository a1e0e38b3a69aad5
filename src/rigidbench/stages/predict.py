"""The predict stage: one video (and, where the predictor knows it, its world state) per reference example.

Outputs in ``OUT/``: ``<id>.mp4`` and ``<id>.state.npz`` for predictors that write the exact world state, and
``generation.json``: the model, every parameter, package versions and per example its status, seed, prompts,
timing and whatever the model reports (prediction id, cost). ``ctx.seed`` is the run's base seed: each example
is predicted with its own seed, ``predictors.example_seed(base, example id)``, which its record holds.

The stage runs on the stage driver (``rigidbench.driver``): ``PredictStage`` declares the examples (the
selected reference bundles) and each one's key, ``PredictWorker`` makes one example's prediction in the
driver's staging folder, and the driver commits it (``<id>.state.npz``, then ``<id>.<ext>``) and writes the
example's ledger entry, ``OUT/.stages/predict/<id>.json``, whose ``result`` IS the example's record. An
example's key (``PredictStage.key``) is a hash of the predictor's settings, the example's own seed (for a
seeded predictor) and its model inputs (the first frame's file, the prompt with the paper's suffix, the
negative prompt). So a rerun skips an example whose key is unchanged and whose video (and state) is still
there, retries a failed one, and makes again exactly those whose settings or inputs changed, saying why. One
example's failure is recorded and the others go on. Predictors that allow it (hosted APIs) run several
examples at once in threads.

Two records, one written from the other: the ledger, and ``generation.json``, written from the ledger when
the run ends (``PredictStage.finish``: every ledger entry made with this run's key for its example, plus
what failed before it ran and what this run started and stopped). A killed run leaves the ledger; the next
run writes generation.json again, and rewrites a damaged or missing one. Folders written by earlier versions
of this stage are read in one place, section "older layouts" at the end, only when an example has a video
but no ledger entry.

Several samples per example (``predict --samples K``, default 1): the stage's items are then (example, sample)
pairs, in example-major order, named by the one naming rule (``folders.sample_item``): sample 0 is ``<id>``
(its files ``<id>.mp4``, ``<id>.state.npz``, exactly as with one sample), sample k >= 1 is ``<id>.s<k>``
(``<id>.s<k>.mp4``, ``<id>.s<k>.state.npz``). Sample k is predicted from the example's bundle with seed
``sample_seed(base, id, k)`` (``SAMPLE_SEED_RULE``; sample 0's is the example's own seed). Each sample has its
own key, ledger entry, lock and record (generation.json's records are keyed by item; with several samples each
says its "example" and "sample", and the header's "samples" the seed rule), and a hosted model is paid once per
sample (its resume state is the item's, ``PredictContext.item``). Sample 0's key is the key an example had
before there were samples, so raising K on a finished folder makes only the new samples, and a killed run
resumes only the samples it had not committed. ``--ids`` and ``--limit`` choose examples (all their samples go
along), ``--shard`` splits the samples.

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
from dataclasses import dataclass, replace
from pathlib import Path
from types import MappingProxyType
from typing import Any

from ..atomic import atomic_file
from ..benchmark import NEGATIVE_PROMPT, full_prompt
from ..context import RunContext
from ..driver import (Adopted, ItemResult, RunOptions, Stage, StageReport, StageWorker, plan_only, read_ledger,
                      run_stage, stage_dir)
from ..errors import EXAMPLE_ERRORS, UserError
from ..evaluation.provenance import versions
from ..executors import LocalExecutor, Resources, failure_record
from ..folders import (FRAMES_DIR, METADATA_FILE, SPEC_FILE, VIDEO_EXTENSIONS, PredictionsFolder, find_prediction, frame_name,
                       sample_item, state_path)
from ..groundtruth.bundle import Sample, bundle_dirs, read_bundle_file, refuse_imported
from ..hashing import digest, file_digest
from ..jsonio import read_json, write_json
from ..predictors import (SAMPLE_SEED_RULE, SEED_RULE, Kind, PredictContext, Prediction, Predictor, PredictorInfo,
                          model_inputs, predictor_info, sample_seed)
from ..video import write_video

log = logging.getLogger(__name__)

INTERRUPTED = "interrupted"  # a record's status when the run stopped before the example was done
VERSION_PACKAGES = ("diffusers", "transformers", "peft", "httpx")
STAGE = "predict"  # the driver's name for it: ledger entries in OUT/.stages/predict/
WORKER = "rigidbench.stages.predict:PredictWorker"


@dataclass(frozen=True)
class DryRunFacts:
    """What a dry run adds to its ``StageReport`` (``report.facts``): the predictions (items: ``<id>`` or
    ``<id>.s<k>``) a run would generate, in selection order, and the paid API calls that takes (one per
    prediction of a paid model: K per example with ``samples`` K, less those already made); ``note``: what
    the user should know about the samples (K samples of a model that takes no seed), None when nothing."""

    planned: list[str]
    paid_calls: int
    samples: int = 1
    note: str | None = None


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


def input_digest(bundle: Path) -> str:
    """A hash of what a video model is given for the example in ``bundle`` (``predictors.model_inputs``): the
    first frame (its file's bytes: nothing is decoded), the task prompt with the paper's suffix and the
    negative prompt. A BundleError when the bundle lacks them."""
    frame = read_bundle_file(bundle, f"{FRAMES_DIR}/{frame_name(0)}", file_digest)
    return digest(frame, full_prompt(Sample(bundle).prompt), NEGATIVE_PROMPT)


class PredictStage(Stage):
    """The predict stage as the driver sees it: the reference bundles of ``split_dir`` (the driver selects),
    written into the predictions folder ``out_dir`` by ``info``'s predictor with ``settings``.

    ``source``: the predictor the run's header, preflight and lost-record recovery come from; ``instance``:
    the worker a local executor uses; ``stopper``: SIGTERM/Ctrl-C handlers installed while examples run;
    ``samples``: how many samples (generations) per example, each an item of its own (module docstring)."""

    name = STAGE
    worker = WORKER

    def __init__(self, out_dir: Path, split_dir: Path, info: PredictorInfo, settings: dict,
                 ctx: PredictContext, source: Predictor | None = None, instance: "PredictWorker | None" = None,
                 stopper: "_GracefulStop | None" = None, samples: int = 1):
        self.out_dir, self.split_dir = Path(out_dir), Path(split_dir)
        self.info, self.settings, self.ctx = info, settings, ctx
        self.source, self.instance, self.stopper = source, instance, stopper
        self.samples = check_samples(samples)
        if self.samples > 1:
            self.unit = "sample"  # what the run's progress and summary count
        self.resources = predict_resources(info, ctx)
        self.seeded = settings.get("seed") is not None  # ctx.seed is the base of per-example seeds
        self.stopped: dict[str, dict] = {}  # examples this run started and stopped: their records
        self.older = OlderLayouts(self)
        self._samples: dict[str, tuple[str, int]] = {}  # item -> (example, sample index), from items()

    # -- what the driver asks --------------------------------------------------------------------------

    @property
    def root(self) -> Path:
        return self.out_dir

    @property
    def where(self) -> str:
        return str(self.split_dir)

    def items(self) -> dict[str, dict]:
        """Every (example, sample) of the split, example-major: ``{item: {"bundle", "example", "sample"}}``."""
        found: dict[str, dict] = {}
        for bundle in bundle_dirs(self.split_dir):
            for k in range(self.samples):
                item = sample_item(bundle.name, k)
                if item in found:
                    raise UserError(f"{self.split_dir}: example {bundle.name} has the name of sample "
                                    f"{found[item]['sample']} of example {found[item]['example']} (the naming rule "
                                    f"<id>.s<k>); rename the example's folder or predict one sample per example")
                found[item] = {"bundle": str(bundle), "example": bundle.name, "sample": k}
        self._samples = {item: (p["example"], p["sample"]) for item, p in found.items()}
        return found

    def sample_of(self, item_id: str) -> tuple[str, int]:
        """(example id, sample index) of an item of ``items()``; an unknown item is sample 0 of itself."""
        return self._samples.get(item_id, (item_id, 0))

    def example_of(self, item_id: str) -> str:
        return self.sample_of(item_id)[0]

    def check(self, selected: list[str]) -> None:
        """A predictor that re-simulates the scene refuses imported bundles (they hold no scene to simulate),
        except those whose scene was rebuilt from the published metadata into the ``spec_dir`` option's folder
        (the ``twin`` predictor's geometry-only twins of a published example, ``flows.envelope``)."""
        if self.info.needs_blender:
            examples = dict.fromkeys(self.example_of(i) for i in selected)
            rebuilt = self.ctx.options.get("spec_dir")
            refuse_imported([self.split_dir / i for i in examples
                             if not (rebuilt and (Path(rebuilt) / i / SPEC_FILE).is_file())],
                            f"predictor '{self.info.name}' re-simulates the scene")

    def key(self, item_id: str, payload: Any) -> str:
        """The predictor's settings, the sample's own seed (None for a predictor that takes none) and a hash
        of the example's model inputs (``input_digest``); for the failure modes, which read the whole reference
        bundle, also its metadata (a re-rendered bundle's differs, if only in its render times). Sample 0's
        seed is the example's, so its key is the one an example had before there were samples."""
        bundle = Path(payload["bundle"])
        example, k = payload.get("example", item_id), int(payload.get("sample", 0))
        seed = sample_seed(self.ctx.seed, example, k) if self.seeded else None
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
                "samples": self.samples}

    def worker_instance(self) -> "PredictWorker | None":
        return self.instance

    def intact(self, item_id: str) -> bool:
        """The item's video is there (``find_prediction``: ``<item>.<ext>``) and, for a predictor that writes
        it, the state beside it."""
        try:
            video = find_prediction(self.out_dir, item_id)
        except EXAMPLE_ERRORS:
            return False
        return video is not None and (not self.info.writes_state or state_path(video).is_file())

    def adopt(self, item_id: str, payload: Any, key: str) -> Adopted | None:
        """An example with a video but no ledger entry: a folder an earlier version of this stage wrote, or a
        run killed between committing the video and writing its ledger entry (``OlderLayouts.adopt``)."""
        return self.older.adopt(item_id) if self.intact(item_id) else None

    def prepare(self, todo: list[str]) -> None:
        """The predictor's check before any example runs (e.g. a hosted model's token: one error, nothing
        sent; the driver calls this only when some example will run, so an up-to-date folder needs no token)."""
        if self.source is not None:
            self.source.preflight(self.ctx)
        if self.stopper is not None:
            self.stopper.install()

    def finish(self, report: StageReport) -> None:
        """Write generation.json from the ledger (``records``); when it already says that, touch nothing. After
        a run that attempted every selected example, remove what older layouts no longer need."""
        if self.stopper is not None:
            self.stopper.uninstall()
        path = PredictionsFolder(self.out_dir).generation
        examples = self.records(report)
        if examples or path.exists():
            doc = {**self.header(), **self.samples_header(examples), "examples": examples}
            if read_json(path, "it is written again from the ledger") != doc:
                write_json(path, doc, indent=2, allow_nan=False)
        if report.completed:
            self.older.clean()

    # -- records ---------------------------------------------------------------------------------------

    def header(self) -> dict:
        """generation.json's header: the predictor, its settings, the model's own parameters, package versions."""
        return {"predictor": self.info.name, "target": self.info.target, "kind": self.info.kind.value,
                "settings": self.settings, "model": self.source.generation_info(self.ctx) if self.source else {},
                "versions": versions(VERSION_PACKAGES)}

    def samples_header(self, records: dict[str, dict]) -> dict:
        """generation.json's "samples", only when there are several per example (one sample per example writes
        what it always did): the most per example (this run's K, or more that earlier runs made) and how each
        sample's seed follows from the base seed."""
        most = max([self.samples] + [r["sample"] + 1 for r in records.values() if isinstance(r.get("sample"), int)])
        if most <= 1:
            return {}
        seeds = SAMPLE_SEED_RULE if self.seeded else (
            "none: the model takes no seed, so the samples of an example differ only by its own randomness (a "
            "hosted model's: the service's; a deterministic predictor makes the same video each time)")
        return {"samples": {"per_example": most, "seeds": seeds}}

    def records(self, report: StageReport) -> dict[str, dict]:
        """Every prediction's record, sorted by item: the ledger entries made with this run's key for their item
        (whichever process made them; one outside the selection, or a sample beyond this run's K, with the key it
        would have), then the items that failed before they ran, then those this run started and stopped. With
        several samples per example every record says its "example" and "sample"."""
        found: dict[str, dict] = {}
        folder = stage_dir(self.out_dir, STAGE)
        for path in sorted(folder.glob("*.json")) if folder.is_dir() else []:
            entry = read_ledger(self.out_dir, STAGE, path.stem)
            if entry is None or entry.get("status") not in ("succeeded", "failed") or \
                    entry.get("key") != self.key_of(path.stem, report, entry):
                continue
            found[path.stem] = self.record_of(path.stem, entry.get("status"), entry.get("result"), entry.get("error"))
        for item_id, reason in report.failed.items():
            found.setdefault(item_id, self.record_of(item_id, "failed", None, reason))
        for item_id, record in self.stopped.items():
            if item_id not in found and item_id not in report.succeeded:
                found[item_id] = record
        placed = {item: self.recorded_sample(item, record) for item, record in found.items()}
        if self.samples > 1 or any(k > 0 for _, k in placed.values()):
            for item, (example, k) in placed.items():
                found[item] = {**found[item], **sample_fields(example, k, 2)}
        return dict(sorted(found.items()))

    def key_of(self, item_id: str, report: StageReport, entry: dict | None = None) -> str | None:
        """This run's key of ``item_id`` (the plan's, or computed for an item outside the selection: its example
        and sample from ``items()``, else from its ledger ``entry``'s record); None when it has none (no such
        bundle, or an unreadable one)."""
        if item_id in report.keys:
            return report.keys[item_id]
        if item_id in report.selected:
            return None
        example, k = self.recorded_sample(item_id, (entry or {}).get("result"))
        if not (self.split_dir / example).is_dir():
            return None
        try:
            return self.key(item_id, {"bundle": str(self.split_dir / example), "example": example, "sample": k})
        except EXAMPLE_ERRORS:
            return None

    def recorded_sample(self, item_id: str, record: Any) -> tuple[str, int]:
        """(example, sample) of ``item_id``: from ``items()``, else what its record says when that names this
        item (a record without them, from before samples, is sample 0 of the item itself)."""
        if item_id in self._samples:
            return self._samples[item_id]
        if isinstance(record, dict) and isinstance(record.get("example"), str) and \
                type(record.get("sample")) is int and record["sample"] >= 0 and \
                sample_item(record["example"], record["sample"]) == item_id:
            return record["example"], record["sample"]
        return item_id, 0

    def record_of(self, item_id: str, status, result: dict | None, error: str | None) -> dict:
        record = dict(result or {})
        if status == "failed":
            example, k = self.recorded_sample(item_id, record)
            record.setdefault("seed", sample_seed(self.ctx.seed, example, k))
            record.update(status="failed", error=record.get("error") or error or "failed")
        return record

    def record_result(self, sample_id: str, entry: dict) -> None:
        """``on_result``: keep the record of an example this run started and stopped (no ledger entry)."""
        result = entry.get("result") or {}
        if entry.get("status") not in ("succeeded", "failed") and result.get("started"):
            self.stopped[sample_id] = dict(result)
        else:
            self.stopped.pop(sample_id, None)

    def rebuild(self, item_id: str) -> dict:
        """What a finished video's lost record can be rebuilt from: the predictor's state, seed and prompts."""
        example, k = self.sample_of(item_id)
        entry: dict = {"seed": sample_seed(self.ctx.seed, example, k), **sample_fields(example, k, self.samples)}
        try:
            inputs = model_inputs(Sample(self.split_dir / example))
            entry.update(prompt=inputs.prompt, negative_prompt=inputs.negative_prompt)
        except EXAMPLE_ERRORS:
            pass
        entry.update((self.source.recover_record(self.out_dir, item_id) if self.source else None) or {})
        return entry


def check_samples(samples: Any) -> int:
    """The number of samples per example: an int >= 1 (a UserError otherwise)."""
    if type(samples) is not int or samples < 1:
        raise UserError(f"samples per example must be a whole number >= 1, got {samples!r}")
    return samples


def sample_fields(example: str, k: int, samples: int) -> dict:
    """What a prediction's record says of its sample: its example and index, whenever there are several per
    example (``samples`` > 1, or a sample k > 0 of an earlier run); nothing with one, so such records are as
    they always were."""
    return {"example": example, "sample": k} if samples > 1 or k > 0 else {}


def predict(name: str, split_dir: Path, out_dir: Path, ctx: PredictContext | None = None,
            run: RunOptions = RunOptions(), predictor: Predictor | None = None,
            dry_run: bool = False, samples: int = 1) -> StageReport:
    """Run predictor ``name`` (a registered name or a "module:attr" plug-in) over the reference bundles
    in ``split_dir``; returns the driver's report (with ``dry_run``: the plan, its ``facts`` a
    ``DryRunFacts`` saying what would be generated and how many paid calls that takes, sending and writing
    nothing). ``samples``: how many predictions per example (``<id>``, ``<id>.s1``, ... each with its own
    seed; see the module docstring). ``run`` selects the examples
    and runs them (default: all, in this process, ``predictor.concurrency`` at once)."""
    ctx = ctx or PredictContext()
    if not 0.0 <= ctx.severity <= 1.0:
        raise UserError(f"severity must lie in [0, 1], got {ctx.severity}")
    samples = check_samples(samples)
    out_dir = Path(out_dir)
    split_dir = Path(split_dir)
    ctx = replace(ctx, out_dir=out_dir)
    executor = run.executor or LocalExecutor()
    local = executor.in_process
    info = predictor.info if predictor is not None else predictor_info(name)
    if predictor is None and (local or dry_run):
        predictor = info.create()
    source = predictor or info.create()  # settings and provenance come from the driver's instance
    worker = None
    try:
        settings = {"predictor": info.name, "target": info.target, **source.settings(ctx)}
        if settings.get("seed") is not None:  # a seeded predictor: ctx.seed is the base of per-example seeds
            settings["seeds"] = SEED_RULE
        if dry_run:
            return _dry_run(PredictStage(out_dir, split_dir, info, settings, ctx, samples=samples), run, predictor,
                            ctx)
        stage = PredictStage(out_dir, split_dir, info, settings, ctx, source, samples=samples)
        if local:
            executor = LocalExecutor(threads=max(executor.threads, int(predictor.concurrency(ctx))))
            worker = stage.instance = PredictWorker(stage.job(), predictor=predictor, ctx=ctx)
        stopper = stage.stopper = _GracefulStop(worker) if local and info.kind == Kind.HOSTED else None
        report = run_stage(stage, replace(run, executor=executor),
                           on_result=stage.record_result)
        if stopper is not None and stopper.signal_name:
            log.warning("stopped by %s: %d example(s) finished and recorded, %d failed, %d not done; predictions "
                        "already created are kept with their ids; rerun the same command to resume without paying "
                        "twice", stopper.signal_name, len(report.ran), len(report.failed), len(report.interrupted))
            raise KeyboardInterrupt(stopper.signal_name)
        return report
    finally:
        if worker is not None:
            worker.close()  # (the executor has closed it when examples ran)
        elif predictor is not None:
            predictor.close()
        if source is not predictor:
            source.close()


def _dry_run(stage: PredictStage, run: RunOptions, predictor: Predictor, ctx: PredictContext) -> StageReport:
    """Print the request of every prediction (every sample of every example) that a real run would generate
    (the driver's ``plan_only``: the same selection, check and plan as a run); send and write nothing."""
    report, todo = plan_only(stage, run)
    planned = []
    for task in todo:
        item_id, payload = task["id"], task["payload"]
        example, k = payload["example"], payload["sample"]
        try:  # a damaged bundle fails its example, as in a run (plan() reports one whose key fails the same way)
            request = predictor.describe(Sample(stage.split_dir / example), example_context(ctx, example, k, item_id))
        except EXAMPLE_ERRORS as exc:
            report.failed[item_id] = str(exc)
            log.warning("%s: %s %s failed: %s", stage.name, stage.unit, item_id, exc)
            continue
        print(f"{item_id}: {json.dumps(request, sort_keys=True)}")
        planned.append(item_id)
    note = None
    if stage.samples > 1 and not stage.seeded:
        note = (f"{predictor.name} takes no seed: its {stage.samples} samples of an example differ only by "
                + ("the service's own randomness" if predictor.paid else "the model's own randomness (a "
                   "deterministic predictor makes the same video each time)"))
    report.facts = DryRunFacts(planned, len(planned) if predictor.paid else 0, stage.samples, note)
    return report


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
        self.stopping = threading.Event()
        self.closed = False

    def stop(self) -> None:
        """Start no new example; the predictor (if it can) creates nothing new and finishes what is paid for."""
        self.stopping.set()
        self.predictor.request_stop()

    def stopped(self) -> bool:
        return self.stopping.is_set()

    def run(self, item_id: str, payload: Any, staging: Path, progress) -> ItemResult:
        """Outputs: ``<item>.state.npz`` (when the prediction has one), then ``<item>.<ext>`` (the item is
        ``<id>`` or ``<id>.s<k>``); the result is the prediction's record (the ledger keeps it)."""
        if self.stopping.is_set():
            return ItemResult(status=INTERRUPTED, error="not started: the run was stopped",
                              result={"status": INTERRUPTED, "error": "not started: the run was stopped"})
        example, k = payload.get("example", item_id), int(payload.get("sample", 0))
        info, ctx = self.predictor.info, example_context(self.ctx, example, k, item_id)
        started = time.time()
        entry: dict = {"seed": ctx.seed, **sample_fields(example, k, int(self.job.get("samples", 1)))}
        remove_temporaries(self.out_dir, item_id)
        try:
            sample = Sample(self.split_dir / example)
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


def example_context(ctx: PredictContext, example_id: str, k: int = 0, item: str | None = None) -> PredictContext:
    """``ctx`` for sample ``k`` of example ``example_id`` (ctx.seed is the base): its seed, ``sample_seed(ctx.seed,
    example_id, k)`` (for k = 0 the example's own, ``example_seed``), and its name ``item`` (default
    ``sample_item(example_id, k)``), which a predictor keys its own per-prediction state by."""
    return replace(ctx, seed=sample_seed(ctx.seed, example_id, k), item=item or sample_item(example_id, k))


# -- older layouts ------------------------------------------------------------------------------------------
# Folders written by earlier versions of this stage, read here only: from PredictStage.adopt (an example with a
# video but no ledger entry) and, for (2), by the worker before it makes an example; their files are removed
# only by PredictStage.finish after a run that attempted every selected example, once every video in the
# folder has its ledger entry. Nothing is predicted again for a video whose settings they show to be this run's:
#   (0) before ledgers: ``.predictor.json`` (the run's settings) and generation.json's records;
#   (1) ledgers with a record per example, ``.generation/<id>.json`` ({"id", "settings": settings_digest,
#       "entry": the record}), and ``.predictor.json``;
#   (2) ``.<id>.partial*`` videos written in OUT itself, before staging (``remove_temporaries``);
#   (3) today's: a video committed without its ledger entry (a run killed in between), taken when
#       generation.json's predictor and settings are this run's; its record is rebuilt when it has none.

OLD_SETTINGS_FILE = ".predictor.json"
OLD_RECORDS_DIR = ".generation"


def settings_digest(settings: dict) -> str:
    """Layout (1): the short hash of a run's settings that its per-example records name."""
    return hashlib.sha256(json.dumps(settings, sort_keys=True, default=str).encode()).hexdigest()[:16]


class OlderLayouts:
    """The records that older layouts of ``stage.out_dir`` hold (see the comment above)."""

    def __init__(self, stage: PredictStage):
        self.stage = stage
        self.out_dir = stage.out_dir
        self._read: dict[str, Any] = {}

    def _settings(self) -> Any:
        """What ``.predictor.json`` holds, None when absent; a damaged one is a UserError (deciding that nothing
        is finished could pay for hosted predictions again)."""
        if "settings" not in self._read:
            path = self.out_dir / OLD_SETTINGS_FILE
            try:
                self._read["settings"] = json.loads(path.read_text())
            except FileNotFoundError:
                self._read["settings"] = None
            except (OSError, ValueError) as exc:
                raise UserError(f"{path}: damaged ({type(exc).__name__}); it records the settings of the "
                                f"predictions in {path.parent}. Delete it to write the selected predictions "
                                "again") from None
        return self._read["settings"]

    def _generation(self) -> dict | None:
        """generation.json's records when its predictor and settings are this run's; None when they are not."""
        if "generation" not in self._read:
            doc = read_json(PredictionsFolder(self.out_dir).generation, "it is written again from the ledger")
            same = isinstance(doc, dict) and doc.get("predictor") == self.stage.info.name \
                and doc.get("settings") == self.stage.settings
            examples = doc.get("examples") if same else None
            self._read["generation"] = (examples if isinstance(examples, dict) else {}) if same else None
        return self._read["generation"]

    def adopt(self, item_id: str) -> Adopted | None:
        """The record of ``item_id``'s video (which is there) when an older layout shows it was made with this
        run's settings; None otherwise (it is predicted)."""
        stage = self.stage
        old = read_json(self.out_dir / OLD_RECORDS_DIR / f"{item_id}.json", "ignored")
        mine = settings_digest({"predictor": stage.info.name, "settings": stage.settings})
        if isinstance(old, dict) and old.get("id") == item_id and old.get("settings") == mine \
                and isinstance(old.get("entry"), dict):
            return Adopted({**old["entry"], "status": "succeeded"}, f"its record in {OLD_RECORDS_DIR}/")
        generation = self._generation()
        if generation is None and self._settings() != stage.settings:
            return None
        record = (generation or {}).get(item_id)
        if isinstance(record, dict) and record.get("status") == "succeeded":
            return Adopted(record, "its record in generation.json")
        return Adopted({**stage.rebuild(item_id), "status": "succeeded",
                        "recovered": "the video was on disk without its record (an interrupted run); rebuilt on rerun"},
                       "its record rebuilt from the video (an interrupted run)")

    def clean(self) -> None:
        """Remove ``.predictor.json`` and ``.generation/`` once every video in the folder has its ledger entry."""
        old = [self.out_dir / OLD_SETTINGS_FILE, self.out_dir / OLD_RECORDS_DIR]
        if not any(path.exists() for path in old):
            return
        videos = {p.stem for ext in VIDEO_EXTENSIONS for p in self.out_dir.glob(f"*{ext}") if not p.name.startswith(".")}
        if any(read_ledger(self.out_dir, STAGE, video) is None for video in videos):
            return
        (self.out_dir / OLD_SETTINGS_FILE).unlink(missing_ok=True)
        shutil.rmtree(self.out_dir / OLD_RECORDS_DIR, ignore_errors=True)


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
