"""What the two locally run video models (``wan-2.2``, ``cosmos-2.5``) share: a diffusers pipeline
loaded once, lazily, on the first example and kept until ``close()``; the paper's generation
settings with per-run overrides; the call that turns one reference example into frames.

Options (``options.LocalOptions``, read typed with ``Predictor.options(ctx)`` from ``PredictContext.options``;
None means "not given"):

- ``model_path``: a local copy of the model (a diffusers pipeline directory) instead of the hub id;
- ``revision``: the hub revision (default: the model's, see each model);
- ``height``, ``width``, ``num_frames``, ``steps``, ``guidance_scale``, ``fps``: override the paper's
  values (the tests run tiny pipelines at a few pixels and two steps; every value is recorded, and
  generation.json lists those that differ from the paper's); height and width must be multiples of
  the model's ``size_multiple``, num_frames of the form 4k + 1;
- ``dtype``: "bfloat16" (the paper), "float16" or "float32", applied when the pipeline is loaded;
- ``offload``: ``enable_model_cpu_offload`` (each component on the GPU only while it runs);
- ``tiled_vae``: tiled VAE encoding and decoding (less GPU memory);
- ``pipeline``: an already built pipeline of the model's class to use instead of loading one (tests
  and benchmarks inject tiny or randomly initialised pipelines this way; it is used at its own
  dtype, and changed in place by what the run asks for: a checkpoint, the guardrail, offload).

A run's settings (part of each example's key: a change makes its finished video stale)
are the seed, where the pipeline comes from, every generation parameter, tiled VAE decoding and the
model's own (checkpoint fingerprint, guardrail); offload and the device are recorded in
generation.json but do not make finished videos stale. The hub commit of a downloaded model is recorded per example (``model_commit``).

The device is ``ctx.run.device``, else CUDA when torch sees a GPU, else the CPU. The generator is
a CPU ``torch.Generator`` seeded with ``ctx.seed``, so a seed gives the same initial noise on
every device; the predict stage passes each example its own seed (``example_seed(--seed, id)``), so
no two examples start from the same noise. torch and diffusers are imported only when a pipeline is loaded.

Storage: the frames are written losslessly (H.264 in RGB, libx264rgb with crf 0; ``STORAGE``), so
``validate`` and ``evaluate`` decode exactly the pipeline's uint8 frames: no chroma subsampling and no
generation loss (the paper's runs kept JPEG q95 4:4:4 frames; docs/reproducing.md has the SSIM effect of
the H.264 4:2:0 crf 18 file written before).
"""

from __future__ import annotations

import gc
import logging
import time
from abc import abstractmethod
from pathlib import Path
from typing import Any

import numpy as np

from ..benchmark import NEGATIVE_PROMPT
from ..errors import PredictionError, UserError, WeightsUnavailable
from ..perception.device import resolve_device
from .base import SEED_RULE, PredictContext, Prediction, Predictor, model_inputs
from .options import DTYPES, LocalOptions  # noqa: F401 (DTYPES re-exported)

log = logging.getLogger(__name__)

GENERATOR = "torch.Generator('cpu').manual_seed(seed of the example)"
STORAGE = "lossless H.264 RGB (libx264rgb, crf 0, 4:4:4, no chroma subsampling): decodes to exactly the frames"
FRAME_CONVERSION = "pipeline frames in [0, 1] (output_type='np'), x 255, rounded to uint8"


def hub_commit(repo_id: str, revision: str | None) -> str | None:
    """The commit that ``revision`` of hub repo ``repo_id`` resolves to in the local hub cache, without
    any network access (None when the repository was never downloaded)."""
    try:
        from huggingface_hub import constants
    except ImportError:
        return None
    ref = Path(constants.HF_HUB_CACHE) / f"models--{repo_id.replace('/', '--')}" / "refs" / (revision or "main")
    try:
        return ref.read_text().strip() or None
    except OSError:
        return None


def dtype_kwarg(dtype) -> dict[str, Any]:
    """``{"dtype": dtype}`` for diffusers' ``from_pretrained`` where it takes ``dtype`` (newer releases, which
    deprecate ``torch_dtype``), else ``{"torch_dtype": dtype}``."""
    from diffusers.utils import deprecation_utils

    return {"dtype" if hasattr(deprecation_utils, "_resolve_dtype") else "torch_dtype": dtype}


def frames_to_uint8(frames) -> np.ndarray:
    """(1,T,H,W,3) or (T,H,W,3) floats in [0, 1] -> (T,H,W,3) uint8 (rounded)."""
    frames = np.asarray(frames, dtype=np.float32)
    if frames.ndim == 5:
        frames = frames[0]
    if frames.ndim != 4 or frames.shape[-1] != 3:
        raise PredictionError(f"the pipeline returned frames of shape {frames.shape}, expected (T,H,W,3)")
    if not np.isfinite(frames).all():
        raise PredictionError(f"the pipeline returned non-finite frames ({int((~np.isfinite(frames)).sum())} values; "
                              "e.g. a float16 overflow): no video written")
    return np.clip(np.rint(frames * 255.0), 0, 255).astype(np.uint8)


class LocalVideoModel(Predictor):
    """A diffusers image-to-video pipeline run locally. Subclasses set the class attributes and
    implement ``load_pipeline`` (and, where the model needs them, ``configure`` and ``call_kwargs``);
    ``options_type`` is a ``LocalOptions`` (``options(ctx)``)."""

    options_type = LocalOptions
    model_id: str = ""
    default_revision: str | None = None
    pipeline_class: str = ""  # a class name in ``diffusers``
    #: the paper's settings (appendix B.1); ``guidance_scale`` is the model's published default
    defaults: dict[str, Any] = {}
    guidance_note: str = ""
    max_sequence_length: int = 512
    size_multiple: int = 16  # height and width: the VAE's spatial factor x the transformer's patch size

    def __init__(self, info):
        super().__init__(info)
        self._pipe = None
        self._load_error: Exception | None = None
        self._device: str | None = None
        self._commit: str | None = None  # the hub commit the loaded pipeline came from

    # -- settings ---------------------------------------------------------------------------------------

    def params(self, ctx: PredictContext) -> dict[str, Any]:
        """The generation parameters of this run: the defaults, overridden by options; validated."""
        o = self.options(ctx)  # typed and range-checked (at least 1, fps positive)
        p = dict(self.defaults)
        for key in ("height", "width", "num_frames", "steps", "guidance_scale", "fps"):
            value = getattr(o, key)
            if value is not None:
                p[key] = value
        if p["height"] % self.size_multiple or p["width"] % self.size_multiple:
            raise UserError(f"{self.name}: height and width must be multiples of {self.size_multiple}, got "
                            f"{p['width']}x{p['height']}")
        if (p["num_frames"] - 1) % 4:
            raise UserError(f"{self.name}: num_frames must be 4k + 1 (the VAE compresses 4 frames into one latent "
                            f"frame after the first), got {p['num_frames']}")
        if o.pipeline is not None:  # used as it is
            p["dtype"] = self._pipeline_dtype(o.pipeline)
            return p
        p["dtype"] = o.dtype or p["dtype"]  # one of DTYPES
        return p

    def source(self, ctx: PredictContext) -> dict[str, Any]:
        """Where the pipeline comes from: an injected object, a local directory or the hub."""
        o = self.options(ctx)
        injected = o.pipeline
        if injected is not None:
            return {"source": "injected", "pipeline": f"{type(injected).__module__}.{type(injected).__name__}"}
        if o.model_path is not None:
            return {"source": "local", "model": str(o.model_path.expanduser().resolve())}
        revision = self.revision(ctx)
        return {"source": "hub", "model": self.model_id, "revision": revision or "main",
                "commit": hub_commit(self.model_id, revision)}

    def revision(self, ctx: PredictContext) -> str | None:
        """The hub revision: the option ``revision``, else the model's."""
        return self.options(ctx).revision or self.default_revision

    def extra_settings(self, ctx: PredictContext) -> dict[str, Any]:
        """Model-specific settings that change the output (checkpoint, guardrail)."""
        return {}

    def settings(self, ctx: PredictContext) -> dict[str, Any]:
        src = self.source(ctx)
        where = {k: src[k] for k in ("source", "model", "revision", "pipeline") if k in src}
        return {"seed": ctx.seed, **where, **self.params(ctx), "tiled_vae": self.options(ctx).tiled_vae,
                **self.extra_settings(ctx)}

    def check_runnable(self, ctx: PredictContext) -> None:
        """Raise a RigidBenchError, before any example, when this configuration cannot run."""

    def generation_info(self, ctx: PredictContext) -> dict[str, Any]:
        self.check_runnable(ctx)
        p, o = self.params(ctx), self.options(ctx)
        info = {
            **self.source(ctx),
            "pipeline_class": f"diffusers.{self.pipeline_class}",
            "height": p["height"], "width": p["width"], "num_frames": p["num_frames"], "fps": p["fps"],
            "num_inference_steps": p["steps"], "guidance_scale": p["guidance_scale"],
            "guidance_scale_source": "option" if o.guidance_scale is not None else self.guidance_note,
            "dtype": p["dtype"],
            "prompt": "task prompt + the paper's suffix (per example in 'examples')",
            "negative_prompt": NEGATIVE_PROMPT,
            "image": "the reference example's first frame (PNG, as rendered)",
            "max_sequence_length": self.max_sequence_length,
            "generator": GENERATOR, "seed": ctx.seed, "seeds": SEED_RULE, "frames": FRAME_CONVERSION,
            "storage": STORAGE,
            "device": self._resolve_device(ctx), "offload": o.offload, "tiled_vae": o.tiled_vae,
        }
        if self.paper_values(p):
            info["differs_from_paper"] = self.paper_values(p)
        info.update(self.extra_info(ctx))
        return info

    def paper_values(self, p: dict[str, Any]) -> dict[str, Any]:
        """The parameters that differ from the paper's, as {name: [this run, paper]}."""
        return {k: [p[k], self.defaults[k]] for k in ("height", "width", "num_frames", "fps", "steps", "dtype")
                if p[k] != self.defaults[k]}

    def extra_info(self, ctx: PredictContext) -> dict[str, Any]:
        return {}

    # -- the pipeline ---------------------------------------------------------------------------------

    @staticmethod
    def _pipeline_dtype(pipe) -> str:
        module = getattr(pipe, "transformer", None)
        dtype = getattr(module, "dtype", None)
        return str(dtype).replace("torch.", "") if dtype is not None else "unknown"

    @staticmethod
    def _resolve_device(ctx: PredictContext) -> str:
        return resolve_device(ctx.run.device)

    @abstractmethod
    def load_pipeline(self, ctx: PredictContext, dtype):
        """Build the pipeline from the hub or ``model_path`` (not moved to a device yet)."""

    def configure(self, pipe, ctx: PredictContext, injected: bool):
        """Model-specific changes to a loaded or injected pipeline (checkpoint, guardrail); returns it."""
        return pipe

    def from_pretrained(self, cls, ctx: PredictContext, dtype, **kwargs):
        """``cls.from_pretrained`` on ``model_path`` or the hub id; a missing model is WeightsUnavailable."""
        path = self.options(ctx).model_path
        where = str(path.expanduser()) if path is not None else self.model_id
        if path is not None and not Path(where).is_dir():
            raise WeightsUnavailable(f"{self.name}: model_path {where} is not a directory (expected a diffusers "
                                     f"pipeline directory, e.g. a download of {self.model_id})")
        revision = None if path is not None else self.revision(ctx)
        if revision is not None:
            kwargs["revision"] = revision
        try:
            return cls.from_pretrained(where, **dtype_kwarg(dtype), **kwargs)
        except OSError as exc:
            hint = (f"download it first (huggingface-cli download {self.model_id}"
                    + (f" --revision {revision}" if revision else "") + ") or pass the option model_path"
                    if path is None else "check the directory")
            raise WeightsUnavailable(f"{self.name}: could not load {where}: {exc}; {hint}") from exc

    def pipeline(self, ctx: PredictContext):
        """The pipeline, loaded (or taken from the ``pipeline`` option) on first use and kept."""
        if self._pipe is not None:
            return self._pipe
        if self._load_error is not None:  # do not retry a failed load for every example
            raise self._load_error
        try:
            self.check_runnable(ctx)
            import torch

            p, o = self.params(ctx), self.options(ctx)
            device = self._resolve_device(ctx)
            injected = o.pipeline
            if injected is None:
                dtype = getattr(torch, p["dtype"])
                if device == "cpu":
                    log.warning("%s: loading the real model on the CPU; a video will take hours (use a GPU)",
                                self.name)
                pipe = self.load_pipeline(ctx, dtype)
            else:
                pipe = injected
            pipe = self.configure(pipe, ctx, injected is not None)
            if o.offload and device.startswith("cuda"):
                pipe.enable_model_cpu_offload(device=device)
            else:
                if o.offload:
                    log.warning("%s: offload asks for a GPU; running on %s without it", self.name, device)
                pipe.to(device)
            if o.tiled_vae:
                pipe.vae.enable_tiling()
            if injected is not None:
                pipe.set_progress_bar_config(disable=True)
        except Exception as exc:
            self._load_error = exc
            raise
        self._pipe, self._device = pipe, device
        src = self.source(ctx)
        self._commit = hub_commit(self.model_id, self.revision(ctx)) if src["source"] == "hub" else None
        return pipe

    def output_type(self, ctx: PredictContext) -> str:
        """The pipeline call's ``output_type``: "np" (frames in [0, 1], converted by ``frames``); a model that
        decodes the latents itself returns "latent" and overrides ``frames``."""
        return "np"

    def frames(self, pipe, out, ctx: PredictContext) -> np.ndarray:
        """(T,H,W,3) uint8 frames from the pipeline call's output (``frames_to_uint8``)."""
        return frames_to_uint8(out.frames)

    def call_kwargs(self, pipe, inputs, p: dict[str, Any]) -> dict[str, Any]:
        """The model-specific arguments of the pipeline call (its image conditioning)."""
        from PIL import Image

        return {"image": Image.fromarray(inputs.image)}

    def predict(self, sample, ctx: PredictContext) -> Prediction:
        import torch

        pipe = self.pipeline(ctx)
        p = self.params(ctx)
        inputs = model_inputs(sample)
        generator = torch.Generator("cpu").manual_seed(int(ctx.seed))
        if self._device and self._device.startswith("cuda"):
            torch.cuda.reset_peak_memory_stats()
        started = time.perf_counter()
        out = pipe(prompt=inputs.prompt, negative_prompt=inputs.negative_prompt, height=p["height"],
                   width=p["width"], num_frames=p["num_frames"], num_inference_steps=p["steps"],
                   guidance_scale=p["guidance_scale"], generator=generator, output_type=self.output_type(ctx),
                   max_sequence_length=self.max_sequence_length, **self.call_kwargs(pipe, inputs, p))
        frames = self.frames(pipe, out, ctx)
        seconds = time.perf_counter() - started
        metadata: dict[str, Any] = {"seed": int(ctx.seed), "seconds_model": round(seconds, 3),
                                    "frames": int(frames.shape[0]),
                                    "resolution": [int(frames.shape[2]), int(frames.shape[1])]}
        if self._commit:
            metadata["model_commit"] = self._commit
        if self._device and self._device.startswith("cuda"):
            metadata["peak_gpu_memory_gib"] = round(torch.cuda.max_memory_allocated() / 2**30, 3)
        if frames.shape[0] != p["num_frames"]:
            log.warning("%s: asked for %d frames, the pipeline returned %d", self.name, p["num_frames"],
                        frames.shape[0])
        times_s = np.arange(frames.shape[0], dtype=np.float64) / p["fps"]
        return Prediction(frames=frames, times_s=times_s, lossless=True, metadata=metadata)

    def close(self) -> None:
        """Free the pipeline (and the GPU memory it held)."""
        had = self._pipe is not None
        self._pipe, self._load_error = None, None
        gc.collect()
        if had:
            try:
                import torch

                if torch.cuda.is_available():
                    torch.cuda.empty_cache()
            except ImportError:  # pragma: no cover - a pipeline was loaded, so torch is there
                pass
