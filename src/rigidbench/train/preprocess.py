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
from ..errors import EXAMPLE_ERRORS, BundleError, ConfigError
from ..executors import Shard
from ..groundtruth.bundle import Sample, bundle_dirs, resolve_split_dir
from ..perception.device import resolve_device
from ..video import resize_frames
from . import models
from .cache import CacheWriter, part_dir, prompt_key
from .config import model_spec

log = logging.getLogger(__name__)

PROMPT_FORMAT = ("two per example: 'prompt' = task prompt + the paper's suffix (rigidbench.benchmark.full_prompt), "
                 "'prompt_task' = the task prompt alone; UMT5 outputs at all text_len positions")
RESIZES = ("bicubic", "lanczos")
VAE_DTYPES = ("auto", "bfloat16", "float32")
PROMPTS_PER_SHARD = 128


@dataclass
class PreprocessSummary:
    cache: Path
    encoded: list[str] = field(default_factory=list)
    skipped: list[str] = field(default_factory=list)
    failed: dict[str, str] = field(default_factory=dict)
    prompts_encoded: int = 0
    device: str = "cpu"


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


def _release_memory() -> None:
    gc.collect()
    if torch.cuda.is_available():
        torch.cuda.empty_cache()


def run_preprocess(data: str | Path, out: str | Path, *, model: str = "wan-2.2", split: str | None = None,
                   limit: int | None = None, model_path: str | None = None, device: str | None = None,
                   shard_size: int = 64, progress: bool = True, shard: Shard = Shard(), resize: str = "bicubic",
                   vae_dtype: str = "auto") -> PreprocessSummary:
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
    if resize not in RESIZES:
        raise ConfigError(f"--resize must be one of {', '.join(RESIZES)}, got {resize!r}")
    if vae_dtype not in VAE_DTYPES:
        raise ConfigError(f"--vae-dtype must be one of {', '.join(VAE_DTYPES)}, got {vae_dtype!r}")
    if vae_dtype == "auto":
        vae_dtype = "bfloat16" if dev.type == "cuda" else "float32"
    summary = PreprocessSummary(cache=Path(out), device=str(dev))
    source = {"data": str(split_dir.resolve()), "model_path": model_path, "hub_id": spec.hub_id}
    writer = CacheWriter(out, {"model": model, "width": spec.width, "height": spec.height, "frames": spec.frames,
                               "text_len": spec.text_len, "prompt_format": PROMPT_FORMAT, "resize": resize,
                               "vae_dtype": vae_dtype, "source": source})
    done = writer.done_ids
    todo: list[tuple[Sample, dict[str, str]]] = []  # (sample, {record field: prompt text})
    for d in dirs:
        if d.name in done:
            summary.skipped.append(d.name)
            continue
        try:
            sample = Sample(d)
            prompts = {"prompt": full_prompt(sample.prompt), "prompt_task": sample.prompt}
            if sample.n_frames < spec.frames:  # before any model is loaded
                raise BundleError(f"{d}: {sample.n_frames} frames, but the {model} cache needs the first "
                                  f"{spec.frames}; render the clips with a preset that has that many")
        except EXAMPLE_ERRORS as exc:
            summary.failed[d.name] = str(exc)
            continue
        todo.append((sample, prompts))

    # 1. text: every distinct prompt (both variants) not yet in the cache, once
    new_prompts = {}
    for _, prompts in todo:
        for prompt in prompts.values():
            key = prompt_key(prompt)
            if key not in writer.known_prompts:
                new_prompts.setdefault(key, prompt)
    if new_prompts:
        text_dtype = torch.bfloat16 if dev.type == "cuda" else torch.float32
        tokenizer, encoder = models.load_text_encoder(model, model_path, dev, text_dtype)
        keys = list(new_prompts)
        bar = tqdm(total=len(keys), unit="prompt", desc="encode prompts", disable=not progress)
        for start in range(0, len(keys), PROMPTS_PER_SHARD):
            chunk = keys[start:start + PROMPTS_PER_SHARD]
            embeddings, tokens = {}, {}
            for b in range(0, len(chunk), 8):
                batch = chunk[b:b + 8]
                encoded = models.encode_prompts_padded(tokenizer, encoder, [new_prompts[k] for k in batch],
                                                       spec.text_len)
                for k, (e, n) in zip(batch, encoded):
                    embeddings[k], tokens[k] = e.float().cpu(), n
                bar.update(len(batch))
            writer.add_text(embeddings, {k: new_prompts[k] for k in chunk}, tokens)
            summary.prompts_encoded += len(chunk)
        bar.close()
        writer.set(text_dim=int(next(iter(embeddings.values())).shape[-1]))
        del encoder, tokenizer
        _release_memory()

    # 2. video latents, shard by shard
    if todo:
        vae = models.load_vae(model, model_path, dev, getattr(torch, vae_dtype))
        bar = tqdm(total=len(todo), unit="clip", desc="encode clips", disable=not progress)
        latents, records = {}, {}
        for n, (sample, prompts) in enumerate(todo):
            try:
                frames = read_frames(sample, spec.frames, (spec.width, spec.height), resize)
                latent = models.encode_video(vae, frames).cpu()
            except EXAMPLE_ERRORS as exc:
                summary.failed[sample.path.name] = str(exc)
            else:
                latents[sample.path.name] = latent
                records[sample.path.name] = {**{f: prompt_key(p) for f, p in prompts.items()}, "task": sample.task,
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
                                 progress=False, shard=Shard(int(index), int(job["shards"])),
                                 resize=job.get("resize", "bicubic"), vae_dtype=job.get("vae_dtype", "auto"))
        return {"status": "failed" if summary.failed else "succeeded", "encoded": summary.encoded,
                "skipped": summary.skipped, "failed": summary.failed, "prompts_encoded": summary.prompts_encoded,
                "error": "; ".join(f"{k}: {v}" for k, v in summary.failed.items())}
