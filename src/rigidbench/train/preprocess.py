"""``rigidbench preprocess``: encode a training split once, before fine-tuning (paper, appendix D).

Each distinct prompt is encoded once by Wan's UMT5 (the 5,000-example training set has 624), and
each clip's first ``frames`` frames (all 49 for Wan 2.2) are resized with Lanczos from the render
size (1280x704) to the model's encoding size (640x352) and encoded by Wan's VAE into 13 latent
slots. Frames are read from the bundle's lossless PNGs.

The prompt is the task prompt followed by the paper's fixed suffix (``benchmark.full_prompt``):
appendix B.1 appends that suffix "for every model" at evaluation, appendix D says the fine-tuned
checkpoints are evaluated under the same conditioning, and the suffix is identical for every clip,
so the 624 distinct prompts stay 624. Training on the same text the checkpoint is evaluated with
avoids a train/test mismatch in the conditioning.

Resumable: the cache's manifest lists what is done (``cache.py``); one example that cannot be read
is recorded as failed and the others go on.
"""

from __future__ import annotations

import gc
import logging
from dataclasses import dataclass, field
from pathlib import Path

import torch

from ..benchmark import full_prompt
from ..errors import EXAMPLE_ERRORS, BundleError
from ..executors import Shard
from ..groundtruth.bundle import Sample, bundle_dirs, resolve_split_dir
from ..perception.device import resolve_device
from ..video import resize_frames
from . import models
from .cache import CacheWriter, part_dir, prompt_key
from .config import model_spec

log = logging.getLogger(__name__)

PROMPT_FORMAT = "task prompt + the paper's fixed suffix (rigidbench.benchmark.full_prompt)"
PROMPTS_PER_SHARD = 128


@dataclass
class PreprocessSummary:
    cache: Path
    encoded: list[str] = field(default_factory=list)
    skipped: list[str] = field(default_factory=list)
    failed: dict[str, str] = field(default_factory=dict)
    prompts_encoded: int = 0
    device: str = "cpu"


def read_frames(sample: Sample, frames: int, size: tuple[int, int]):
    """The first ``frames`` frames of ``sample`` (PNG) resized to ``size`` (W, H): (T,H,W,3) uint8."""
    import numpy as np

    if sample.n_frames < frames:
        raise BundleError(f"{sample.path}: {sample.n_frames} frames, but the cache needs the first {frames}; "
                          "render the clips with a preset that has at least that many frames")
    return np.stack([resize_frames(sample.frame(k), size) for k in range(frames)])


def _release_memory() -> None:
    gc.collect()
    if torch.cuda.is_available():
        torch.cuda.empty_cache()


def run_preprocess(data: str | Path, out: str | Path, *, model: str = "wan-2.2", split: str | None = None,
                   limit: int | None = None, model_path: str | None = None, device: str | None = None,
                   shard_size: int = 64, progress: bool = True, shard: Shard = Shard()) -> PreprocessSummary:
    """Encode the bundles of ``data`` (a split directory or a data root) into the cache ``out``; with a
    ``shard`` of several, only its part of the bundles, into ``out/part-I-of-N`` (readers merge the parts)."""
    from tqdm import tqdm

    spec = model_spec(model)
    split_dir = resolve_split_dir(data, split)
    if split_dir.name == "eval":
        log.warning("%s looks like the evaluation split; the paper fine-tunes on the disjoint training split",
                    split_dir)
    dirs = shard.select(bundle_dirs(split_dir)[: limit if limit is not None else None])
    if shard.count > 1:
        out = part_dir(out, shard.index, shard.count)
    dev = torch.device(resolve_device(device))
    summary = PreprocessSummary(cache=Path(out), device=str(dev))
    source = {"data": str(split_dir.resolve()), "model_path": model_path, "hub_id": spec.hub_id}
    writer = CacheWriter(out, {"model": model, "width": spec.width, "height": spec.height, "frames": spec.frames,
                               "text_len": spec.text_len, "prompt_format": PROMPT_FORMAT, "source": source})
    done = writer.done_ids
    todo: list[tuple[Sample, str, str]] = []  # (sample, prompt, prompt key)
    for d in dirs:
        if d.name in done:
            summary.skipped.append(d.name)
            continue
        try:
            sample = Sample(d)
            prompt = full_prompt(sample.prompt)
            if sample.n_frames < spec.frames:  # before any model is loaded
                raise BundleError(f"{d}: {sample.n_frames} frames, but the {model} cache needs the first "
                                  f"{spec.frames}; render the clips with a preset that has that many")
        except EXAMPLE_ERRORS as exc:
            summary.failed[d.name] = str(exc)
            continue
        todo.append((sample, prompt, prompt_key(prompt)))

    # 1. text: every distinct prompt not yet in the cache, once
    new_prompts = {}
    for _, prompt, key in todo:
        if key not in writer.known_prompts:
            new_prompts.setdefault(key, prompt)
    if new_prompts:
        text_dtype = torch.bfloat16 if dev.type == "cuda" else torch.float32
        tokenizer, encoder = models.load_text_encoder(model, model_path, dev, text_dtype)
        keys = list(new_prompts)
        bar = tqdm(total=len(keys), unit="prompt", desc="encode prompts", disable=not progress)
        for start in range(0, len(keys), PROMPTS_PER_SHARD):
            chunk = keys[start:start + PROMPTS_PER_SHARD]
            embeddings = {}
            for b in range(0, len(chunk), 8):
                batch = chunk[b:b + 8]
                for k, e in zip(batch, models.encode_prompts(tokenizer, encoder, [new_prompts[k] for k in batch],
                                                             spec.text_len)):
                    embeddings[k] = e.float().cpu()
                bar.update(len(batch))
            writer.add_text(embeddings, {k: new_prompts[k] for k in chunk})
            summary.prompts_encoded += len(chunk)
        bar.close()
        writer.set(text_dim=int(next(iter(embeddings.values())).shape[-1]))
        del encoder, tokenizer
        _release_memory()

    # 2. video latents, shard by shard
    if todo:
        vae = models.load_vae(model, model_path, dev)
        bar = tqdm(total=len(todo), unit="clip", desc="encode clips", disable=not progress)
        latents, records = {}, {}
        for n, (sample, _, key) in enumerate(todo):
            try:
                frames = read_frames(sample, spec.frames, (spec.width, spec.height))
                latent = models.encode_video(vae, frames).cpu()
            except EXAMPLE_ERRORS as exc:
                summary.failed[sample.path.name] = str(exc)
            else:
                latents[sample.path.name] = latent
                records[sample.path.name] = {"prompt": key, "task": sample.task,
                                             "source_resolution": list(sample.resolution),
                                             "source_frames": sample.n_frames}
                if "latent_shape" not in writer.manifest:
                    writer.set(latent_shape=list(latent.shape))
            bar.update(1)
            if latents and (len(latents) >= shard_size or n == len(todo) - 1):
                writer.add_latents(latents, records)
                summary.encoded += list(latents)
                latents, records = {}, {}
        bar.close()
        del vae
        _release_memory()
    return summary


class PreprocessWorker:
    """One shard of a split per call (a shard index), for ``--executor ray``: ``job`` holds the
    arguments of ``run_preprocess`` and the number of shards."""

    def __init__(self, job: dict):
        self.job = job

    def __call__(self, index: int) -> dict:
        job = self.job
        summary = run_preprocess(job["data"], job["out"], model=job["model"], split=job["split"], limit=job["limit"],
                                 model_path=job["model_path"], device=job["device"], shard_size=job["shard_size"],
                                 progress=False, shard=Shard(int(index), int(job["shards"])))
        return {"status": "failed" if summary.failed else "succeeded", "encoded": summary.encoded,
                "skipped": summary.skipped, "failed": summary.failed, "prompts_encoded": summary.prompts_encoded,
                "error": "; ".join(f"{k}: {v}" for k, v in summary.failed.items())}
