"""``rigidbench preprocess``: encode a training split once, before fine-tuning (paper, appendix D).

Each distinct prompt is encoded once by Wan's UMT5 (the 5,000-example training set has 624), and
each clip's first ``frames`` frames (all 49 for Wan 2.2) are resized from the render size
(1280x704) to the model's encoding size (640x352) and encoded by Wan's VAE into 13 latent slots.
Frames are read from the bundle's lossless PNGs.

Every example's prompt is encoded twice: the task prompt alone (what the authors' release trained
on: its cache encoded ``metadata.json``'s prompt) and the task prompt followed by the paper's fixed
suffix (``benchmark.full_prompt``, what every model is evaluated with). The suffix is the same for
every clip, so each variant has 624 distinct prompts. UMT5's output is stored at all ``text_len``
positions with the number of real tokens, so the training configuration chooses both the prompt
(``text.prompt``) and whether the positions after the prompt keep the encoder's output (the
release) or are zeroed (the pipeline) (``text.padding``) without preprocessing again.

Two settings follow the release where the paper is silent (docs/finetuning.md) and are recorded in
the manifest: ``resize="bicubic"`` (PIL's ``Image.resize`` default, which the release used;
``"lanczos"``: ``video.resize_frames``) and ``vae_dtype`` (``"auto"``: bfloat16 on a GPU as the
release ran its VAE, float32 on the CPU).

On the stage driver (``rigidbench.driver``): an item is a clip; its worker writes the clip's latent
file, and the file of each of its two prompts that the cache does not hold yet (``cache.py`` has the
layout). The shared work is done once: run in this process, ``prepare`` encodes every missing prompt
of the clips to do in batches and frees the text encoder before the VAE loads; a worker elsewhere (a
Ray actor) encodes a missing prompt itself. A clip's key is a digest of the settings that determine
its files (model and weights, size, frames, text_len, resize, the VAE's and text encoder's dtypes, the
prompt format) and of its bundle (metadata, prompt, frame files: ``cache.bundle_fingerprint``), so a
rerun skips the clips already encoded this way and re-encodes exactly those whose key changed, saying
why. After every run the manifest (the index training reads) is rebuilt from the ledger: the clips
encoded with this run's settings. A cache written by an older RigidBench (versions 1-2, shards) keeps
its clips: those made with the same settings are adopted, the rest re-encoded. ``--shard I/N`` runs
write into the same cache (each its part of the clips); one example that cannot be read is recorded
as failed and the others go on.
"""

from __future__ import annotations

import gc
import json
import logging
from dataclasses import dataclass
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

import torch

from ..benchmark import full_prompt
from ..driver import (Adopted, ItemResult, RunOptions, Stage, StageReport, StageWorker, read_ledger, run_stage,
                      stage_dir)
from ..errors import BundleError, ConfigError, UserError
from ..executors import LocalExecutor, Resources
from ..folders import FRAMES_DIR, METADATA_FILE, PROMPT_FILE, frame_name
from ..groundtruth.bundle import Sample, bundle_dirs, resolve_split_dir
from ..hashing import digest
from ..jsonio import read_json, write_json
from ..perception.device import resolve_device
from ..train import models
from ..train.cache import (CACHE_VERSION, MANIFEST, SETTINGS_KEYS, bundle_fingerprint, index_lock, latent_file,
                           prompt_key, read_manifest, text_file, text_file_info, write_latent_file, write_text_file)
from ..train.config import RESIZES, VAE_DTYPES, model_spec
from ..video import resize_frames

log = logging.getLogger(__name__)

STAGE = "preprocess"
PROMPT_FORMAT = ("two per example: 'prompt' = task prompt + the paper's suffix (rigidbench.benchmark.full_prompt), "
                 "'prompt_task' = the task prompt alone; UMT5 outputs at all text_len positions")
PROMPT_BATCH = 8
LEGACY_MANIFEST = "legacy-manifest.json"  # an older cache's manifest, kept when the index replaces it


@dataclass(frozen=True)
class PreprocessFacts:
    """What ``run_preprocess`` adds to its ``StageReport`` (``report.facts``): how many prompts this run encoded
    and the device the encoders ran on."""

    prompts_encoded: int
    device: str


def resize_frame(frame, size: tuple[int, int], resize: str = "lanczos"):
    """One (H,W,3) uint8 frame resized to ``size`` (W, H): ``bicubic`` is PIL's ``Image.resize`` default for
    RGB images (the release's preprocessing), ``lanczos`` is ``video.resize_frames``."""
    if resize == "lanczos":
        return resize_frames(frame, size)
    if resize != "bicubic":
        raise ValueError(f"resize must be one of {', '.join(RESIZES)}, got {resize!r}")
    import numpy as np
    from PIL import Image

    if frame.shape[:2] == (size[1], size[0]):
        return frame
    return np.asarray(Image.fromarray(frame).resize((int(size[0]), int(size[1])), Image.Resampling.BICUBIC))


def read_frames(sample: Sample, frames: int, size: tuple[int, int], resize: str = "lanczos"):
    """The first ``frames`` frames of ``sample`` (PNG) resized to ``size`` (W, H): (T,H,W,3) uint8."""
    import numpy as np

    if sample.n_frames < frames:
        raise BundleError(f"{sample.path}: {sample.n_frames} frames, but the cache needs the first {frames}; "
                          "render the clips with a preset that has at least that many frames")
    return np.stack([resize_frame(sample.frame(k), size, resize) for k in range(frames)])


def clip_prompts(sample: Sample) -> dict[str, str]:
    """{record field: prompt text} of a clip: the task prompt with the paper's suffix, and alone."""
    return {"prompt": full_prompt(sample.prompt), "prompt_task": sample.prompt}


def _release_memory() -> None:
    gc.collect()
    if torch.cuda.is_available():
        torch.cuda.empty_cache()


def _encode(tokenizer, encoder, prompts: list[str], text_len: int) -> list[tuple[torch.Tensor, int]]:
    return [(e.float().cpu(), n) for e, n in models.encode_prompts_padded(tokenizer, encoder, prompts, text_len)]


class PreprocessStage(Stage):
    """The clips of a split directory -> the cache ``out`` (see the module docstring)."""

    name = STAGE
    worker = "rigidbench.stages.preprocess:PreprocessWorker"
    unit = "clip"

    def __init__(self, split_dir: Path, out: Path, *, model: str = "wan-2.2", model_path: str | None = None,
                 device: str | None = None, resize: str = "bicubic", vae_dtype: str = "auto",
                 remote: bool = False, progress: bool = True):
        if resize not in RESIZES:
            raise ConfigError(f"--resize must be one of {', '.join(RESIZES)}, got {resize!r}")
        if vae_dtype not in VAE_DTYPES:
            raise ConfigError(f"--vae-dtype must be one of {', '.join(VAE_DTYPES)}, got {vae_dtype!r}")
        self.spec = spec = model_spec(model)
        self.split_dir, self.out = Path(split_dir), Path(out)
        # remote workers (Ray actors) run where the GPUs are: not this machine's devices decide, but --device
        # (default: a GPU each, as the actors ask for one)
        self.device = str(device or "cuda") if remote else str(torch.device(resolve_device(device)))
        cuda = torch.device(self.device).type == "cuda"
        if vae_dtype == "auto":
            vae_dtype = "bfloat16" if cuda else "float32"
        self.model, self.model_path = model, model_path
        self.text_first, self.progress = not remote, progress
        source = {"model_path": model_path, "hub_id": spec.hub_id}
        #: what determines every clip's files (the manifest's settings; the data folder is not among them)
        self.settings = {"version": CACHE_VERSION, "model": model, "width": spec.width, "height": spec.height,
                         "frames": spec.frames, "text_len": spec.text_len, "dtype": "float16",
                         "prompt_format": PROMPT_FORMAT, "resize": resize, "vae_dtype": vae_dtype,
                         "text_dtype": "bfloat16" if cuda else "float32", "source": source}
        self.settings_key = digest(self.settings)
        self.text_key = digest(model, source, spec.text_len, self.settings["text_dtype"], PROMPT_FORMAT)[:12]
        self.prompts: dict[str, dict[str, str]] = {}  # clip -> its prompts (filled by key())
        self.prompts_encoded = 0
        self._legacy: dict | None | bool = False

    @property
    def root(self) -> Path:
        return self.out

    @property
    def where(self) -> str:
        return str(self.split_dir)

    def items(self) -> dict[str, Any]:
        return {d.name: {"dir": str(d.resolve())} for d in bundle_dirs(self.split_dir)}

    def key(self, item_id: str, payload: Any) -> str:
        sample = Sample(payload["dir"])
        frames = self.spec.frames
        if sample.n_frames < frames:  # before any model is loaded
            raise BundleError(f"{sample.path}: {sample.n_frames} frames, but the {self.model} cache needs the "
                              f"first {frames}; render the clips with a preset that has that many")
        prompts = clip_prompts(sample)
        self.prompts[item_id] = prompts
        files = [METADATA_FILE, PROMPT_FILE] + [f"{FRAMES_DIR}/{frame_name(k)}" for k in range(frames)]
        return digest(self.settings_key, prompts, bundle_fingerprint(sample.path, files))

    def job(self) -> dict:
        return {"root": str(self.out.resolve()), "model": self.model, "model_path": self.model_path,
                "device": self.device, "width": self.spec.width, "height": self.spec.height,
                "frames": self.spec.frames, "text_len": self.spec.text_len, "resize": self.settings["resize"],
                "vae_dtype": self.settings["vae_dtype"], "text_dtype": self.settings["text_dtype"],
                "text_key": self.text_key, "settings_key": self.settings_key}

    @property
    def resources(self) -> Resources:  # type: ignore[override]
        return Resources(num_cpus=1, num_gpus=1 if torch.device(self.device).type == "cuda" else 0)

    # -- what is done ---------------------------------------------------------------------------------

    def intact(self, item_id: str) -> bool:
        entry = read_ledger(self.out, STAGE, item_id) or {}
        return _files_present(self.out, entry.get("result") or {})

    def legacy(self) -> dict | None:
        """The manifest of an older (version 1-2) cache in ``out``, or None."""
        if self._legacy is False:
            kept = stage_dir(self.out, STAGE) / LEGACY_MANIFEST
            manifest = None
            try:
                if kept.is_file():
                    manifest = json.loads(kept.read_text())
                elif (self.out / MANIFEST).is_file() or any(self.out.glob("part-*-of-*")):
                    found = read_manifest(self.out)
                    manifest = found if found.get("version") != CACHE_VERSION else None
            except (UserError, ConfigError, OSError, ValueError) as exc:
                log.warning("%s: the older cache's manifest cannot be read (%s); its clips are encoded again",
                            self.out, exc)
            self._legacy = manifest
        return self._legacy  # type: ignore[return-value]

    def _legacy_result(self, item_id: str) -> dict | None:
        old = self.legacy()
        if not old:
            return None
        if any(old.get(k) != self.settings[k] for k in SETTINGS_KEYS if k != "version"):
            return None  # made with other settings (or version 1's prompt format): encoded again
        record = old["examples"].get(item_id)
        if record is None or any(record.get(f) not in old["prompts"] for f in ("prompt", "prompt_task")):
            return None
        result = {"record": {k: v for k, v in record.items() if k not in ("shard", "key")}, "latent": record["shard"],
                  "prompts": {record[f]: old["prompts"][record[f]] for f in ("prompt", "prompt_task")},
                  "latent_shape": old.get("latent_shape"), "text_dim": old.get("text_dim"),
                  "settings": self.settings_key, "prompts_encoded": 0}
        return result if _files_present(self.out, result) else None

    def adopt(self, item_id: str, payload: Any, key: str) -> Adopted | None:
        result = self._legacy_result(item_id)
        return None if result is None else Adopted(result, "its entry in an older cache's manifest")

    # -- the shared work ------------------------------------------------------------------------------

    def prepare(self, todo: list[str]) -> None:
        """Encode every prompt of the clips in ``todo`` that the cache does not hold yet, in batches, then
        free the text encoder (only when the workers run in this process; a remote worker encodes its own)."""
        from tqdm import tqdm

        if not self.text_first:
            return
        missing: dict[str, str] = {}
        for item_id in todo:
            for text in self.prompts[item_id].values():
                pk = prompt_key(text)
                if not (self.out / text_file(pk, self.text_key)).is_file():
                    missing.setdefault(pk, text)
        if not missing:
            return
        dev = torch.device(self.device)
        tokenizer, encoder = models.load_text_encoder(self.model, self.model_path, dev,
                                                      getattr(torch, self.settings["text_dtype"]))
        keys = list(missing)
        bar = tqdm(total=len(keys), unit="prompt", desc="encode prompts", disable=not self.progress)
        for b in range(0, len(keys), PROMPT_BATCH):
            batch = keys[b:b + PROMPT_BATCH]
            for pk, (embedding, tokens) in zip(batch, _encode(tokenizer, encoder, [missing[k] for k in batch],
                                                               self.spec.text_len)):
                write_text_file(self.out / text_file(pk, self.text_key), pk, embedding, missing[pk], tokens,
                                self.model)
            self.prompts_encoded += len(batch)
            bar.update(len(batch))
        bar.close()
        del encoder, tokenizer
        _release_memory()

    def finish(self, report: StageReport) -> None:
        """Rebuild the manifest (the index training reads) from the ledger: every clip encoded with this
        run's settings whose files are there (also those of other shards' runs and of earlier runs)."""
        sdir = stage_dir(self.out, STAGE)
        if not sdir.is_dir() and not report.selected:
            return
        self.out.mkdir(parents=True, exist_ok=True)
        with index_lock(sdir):
            legacy = self.legacy()
            if legacy and not (sdir / LEGACY_MANIFEST).is_file():  # keep it: the index replaces it below
                write_json(sdir / LEGACY_MANIFEST, legacy, sort_keys=True)
            examples, prompts, shape, dim, other = {}, {}, None, None, []
            ledgered = set()
            for path in sorted(sdir.glob("*.json")):
                if path.name == LEGACY_MANIFEST:
                    continue
                entry = read_ledger(self.out, STAGE, path.stem)
                if entry is None:
                    continue
                ledgered.add(path.stem)
                result = entry.get("result") or {}
                if entry.get("status") != "succeeded":
                    continue
                if result.get("settings") != self.settings_key:
                    other.append(path.stem)
                    continue
                if not _files_present(self.out, result):
                    continue
                examples[path.stem] = {"shard": result["latent"], "key": entry["key"], **result["record"]}
                prompts.update(result["prompts"])
                shape, dim = result.get("latent_shape") or shape, result.get("text_dim") or dim
            if legacy:  # an older cache's clips not yet seen by this stage stay in the index
                for item_id in sorted(set(legacy["examples"]) - ledgered):
                    result = self._legacy_result(item_id)
                    if result is not None:
                        examples[item_id] = {"shard": result["latent"], **result["record"]}
                        prompts.update(result["prompts"])
                        shape, dim = result["latent_shape"] or shape, result["text_dim"] or dim
            previous = read_json(self.out / MANIFEST, "rebuilt") or {}
            manifest = {**self.settings, "source": {**self.settings["source"], "data": str(self.split_dir.resolve())},
                        "layout": "one file per clip (latents/) and per prompt (text/)",
                        "examples": dict(sorted(examples.items())), "prompts": dict(sorted(prompts.items())),
                        "created": previous.get("created") or _now(), "updated": _now()}
            if shape is not None:
                manifest["latent_shape"] = shape
            if dim is not None:
                manifest["text_dim"] = dim
            write_json(self.out / MANIFEST, manifest, sort_keys=True)
        if other:
            log.warning("%s: %d clip(s) in the cache were encoded with other settings and are not in its index "
                        "(%s); select them to encode them with these settings", self.out, len(other),
                        ", ".join(other[:10]) + (" ..." if len(other) > 10 else ""))


def _now() -> str:
    return datetime.now(timezone.utc).isoformat(timespec="seconds")


def _files_present(root: Path, result: dict) -> bool:
    """Whether a clip's latent and prompt files (as its ledger result names them) are in the cache."""
    if not result.get("latent") or not result.get("prompts"):
        return False
    return (root / result["latent"]).is_file() and all((root / p["shard"]).is_file()
                                                       for p in result["prompts"].values())


class PreprocessWorker(StageWorker):
    """One clip per call: its prompts' files (those the cache lacks) and its latent file. The models load
    on first use and stay loaded for the worker's next clips."""

    def __init__(self, job: dict):
        super().__init__(job)
        self.root = Path(job["root"])
        self.dev = torch.device(resolve_device(job["device"]))
        self.text_encoder = None
        self.vae = None

    def _text(self, text: str) -> tuple[torch.Tensor, int]:
        if self.text_encoder is None:
            self.text_encoder = models.load_text_encoder(self.job["model"], self.job["model_path"], self.dev,
                                                         getattr(torch, self.job["text_dtype"]))
        return _encode(*self.text_encoder, [text], self.job["text_len"])[0]

    def run(self, item_id: str, payload: Any, staging: Path, progress) -> ItemResult:
        job = self.job
        sample = Sample(payload["dir"])
        prompts = clip_prompts(sample)
        outputs, infos, encoded, dim = [], {}, 0, None
        for text in prompts.values():
            pk = prompt_key(text)
            rel = text_file(pk, job["text_key"])
            if (self.root / rel).is_file():
                info = text_file_info(self.root / rel, pk)
            else:
                embedding, tokens = self._text(text)
                write_text_file(staging / rel, pk, embedding, text, tokens, job["model"])
                outputs.append(rel)
                encoded += 1
                info = {"text": text, "tokens": int(tokens), "rows": int(embedding.shape[0]),
                        "dim": int(embedding.shape[-1])}
            dim = info.pop("dim")
            infos[pk] = {"shard": rel, **info}
        progress(1, 2)
        frames = read_frames(sample, job["frames"], (job["width"], job["height"]), job["resize"])
        if self.vae is None:
            self.vae = models.load_vae(job["model"], job["model_path"], self.dev, getattr(torch, job["vae_dtype"]))
        latent = models.encode_video(self.vae, frames).cpu()
        rel = latent_file(item_id)
        write_latent_file(staging / rel, item_id, latent, job["model"])
        outputs.append(rel)  # last: the clip's completion mark
        progress(2, 2)
        record = {**{f: prompt_key(p) for f, p in prompts.items()}, "task": sample.task,
                  "source_resolution": list(sample.resolution), "source_frames": sample.n_frames}
        return ItemResult(outputs=outputs, result={"record": record, "latent": rel, "prompts": infos,
                                                   "latent_shape": list(latent.shape), "text_dim": dim,
                                                   "settings": job["settings_key"], "prompts_encoded": encoded})

    def close(self) -> None:
        self.text_encoder = self.vae = None
        _release_memory()


def run_preprocess(data: str | Path, out: str | Path, *, model: str = "wan-2.2", split: str | None = None,
                   run: RunOptions = RunOptions(), model_path: str | None = None, device: str | None = None,
                   shard_size: int | None = None, resize: str = "bicubic",
                   vae_dtype: str = "auto") -> StageReport:
    """Encode the bundles of ``data`` (a split directory or a data root) into the cache ``out``: the first
    ``limit`` (or the ``ids``), this ``shard``'s part of them, on ``executor`` (default: this process).
    ``shard_size`` is accepted for older callers and unused (version 3 keeps one file per clip). Returns the
    driver's report, its ``facts`` a ``PreprocessFacts``."""
    split_dir = resolve_split_dir(data, split)
    if split_dir.name == "eval":
        log.warning("%s looks like the evaluation split; the paper fine-tunes on the disjoint training split",
                    split_dir)
    executor = run.executor or LocalExecutor()
    stage = PreprocessStage(split_dir, Path(out), model=model, model_path=model_path, device=device, resize=resize,
                            vae_dtype=vae_dtype, remote=not executor.in_process, progress=run.progress)
    report = run_stage(stage, run)
    encoded = stage.prompts_encoded + sum(int(report.results[i].get("prompts_encoded", 0)) for i in report.ran)
    report.facts = PreprocessFacts(encoded, stage.device)
    return report
