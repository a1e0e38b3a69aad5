"""The predict stage: one video (and, where the predictor knows it, its world state) per reference example.

Outputs in ``OUT/``: ``<id>.mp4`` (written last, atomically) and ``<id>.state.npz`` for predictors
that write the exact world state; ``generation.json`` with the model, every parameter, package
versions and per example its status, seed, prompts, timing and whatever the model reports
(prediction id, cost); and a hidden ``.predictor.json`` recording the predictor and its settings.
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
from concurrent.futures import ThreadPoolExecutor, as_completed
from dataclasses import dataclass, field
from pathlib import Path

from tqdm import tqdm

from ..errors import EXAMPLE_ERRORS, UserError
from ..evaluation.cache import write_json
from ..evaluation.provenance import versions
from ..groundtruth.bundle import Sample, bundle_dirs
from ..perception.gt import state_path
from ..predictors import Kind, PredictContext, Prediction, Predictor, model_inputs, predictor_info
from ..video import write_video

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
    videos = [v for v in out_dir.iterdir() if v.suffix.lower() in (".mp4", ".webm", ".mov", ".mkv")]
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
            predictor: Predictor | None = None, dry_run: bool = False) -> PredictSummary:
    """Run predictor ``name`` (a registered name or a "module:attr" plug-in) over the reference bundles
    in ``split_dir``; returns what was written, skipped and failed (with ``dry_run``: what would be
    generated and how many paid calls that takes, sending and writing nothing)."""
    ctx = ctx or PredictContext()
    if not 0.0 <= ctx.severity <= 1.0:
        raise UserError(f"severity must lie in [0, 1], got {ctx.severity}")
    out_dir = Path(out_dir)
    ctx = PredictContext(ctx.run, ctx.severity, ctx.seed, ctx.keep_bundle_dir, out_dir, ctx.options)
    predictor = predictor or predictor_info(name).create()
    info = predictor.info
    refs = select_examples(Path(split_dir), ids, limit)
    settings = {"predictor": info.name, "target": info.target, **predictor.settings(ctx)}
    summary = PredictSummary()
    if dry_run:
        return _dry_run(predictor, refs, out_dir, settings, ctx, summary)
    done = finished_ids(out_dir, settings, info.writes_state)
    todo = [r for r in refs if r.name not in done]
    for ref in refs:
        if ref.name in done:
            summary.written.append(ref.name)
            summary.skipped.append(ref.name)
    if summary.skipped:
        log.info("%s: %d of %d predictions already written with these settings; skipping them", out_dir,
                 len(summary.skipped), len(refs))
    log_file = GenerationLog(out_dir / GENERATION_FILE, {
        "predictor": info.name, "target": info.target, "kind": info.kind.value, "settings": settings,
        "model": predictor.generation_info(ctx), "versions": versions(VERSION_PACKAGES)})
    bar = tqdm(total=len(todo), unit="example", desc=f"predict {info.name}", disable=not progress or not todo)

    def one(ref: Path) -> None:
        started = time.time()
        entry: dict = {"seed": ctx.seed}
        try:
            sample = Sample(ref)
            inputs = model_inputs(sample)
            entry.update(prompt=inputs.prompt, negative_prompt=inputs.negative_prompt)
            pred = predictor.predict(sample, ctx)
            if info.writes_state and pred.state is None:
                raise TypeError(f"predictor '{info.name}' is registered as writing the world state "
                                "but returned a Prediction without one")
            write_prediction(pred, out_dir, ref.name, sample.fps if info.kind == Kind.FAILURE_MODE else None)
            entry.update(status="succeeded", **pred.metadata)
            summary.written.append(ref.name)
        except EXAMPLE_ERRORS as exc:
            entry.update(status="failed", error=str(exc))
            summary.failed[ref.name] = str(exc)
            log.error("example %s failed: %s", ref.name, exc)
        finally:
            entry["seconds"] = round(time.time() - started, 3)
            log_file.record(ref.name, entry)
            bar.update(1)

    try:
        workers = max(1, int(predictor.concurrency(ctx)))
        if workers == 1:
            for ref in todo:
                one(ref)
        else:
            with ThreadPoolExecutor(max_workers=workers, thread_name_prefix=f"predict-{info.name}") as pool:
                for future in as_completed([pool.submit(one, ref) for ref in todo]):
                    future.result()  # a bug in one example stops the run
    finally:
        bar.close()
        predictor.close()
    summary.written.sort()
    return summary


def _dry_run(predictor: Predictor, refs: list[Path], out_dir: Path, settings: dict, ctx: PredictContext,
             summary: PredictSummary) -> PredictSummary:
    """Print the request of every example that a real run would generate; send and write nothing."""
    previous = out_dir / SETTINGS_FILE
    same = previous.exists() and json.loads(previous.read_text()) == settings
    for ref in refs:
        if same and any((out_dir / f"{ref.name}{ext}").exists() for ext in (".mp4", ".webm", ".mov", ".mkv")):
            summary.skipped.append(ref.name)
            continue
        request = predictor.describe(Sample(ref), ctx)
        print(f"{ref.name}: {json.dumps(request, sort_keys=True)}")
        summary.planned.append(ref.name)
    summary.paid_calls = len(summary.planned) if predictor.paid else 0
    predictor.close()
    return summary
