"""``cosmos-2.5``: Cosmos Predict 2.5-2B run locally through diffusers (paper, section 4 and appendix B.1).

``Cosmos2_5_PredictBasePipeline.from_pretrained("nvidia/Cosmos-Predict2.5-2B",
revision="diffusers/base/post-trained", torch_dtype=bfloat16)``: 1280x704, 33 frames written at
16 fps (evaluation resamples them to the reference's 24 Hz), 50 inference steps, bfloat16, the
paper's negative prompt, the task prompt with the paper's suffix, the first reference frame as the
conditioning image. The paper does not state the guidance scale; we use the pipeline's default for
this model, 7.0, and record it.

The guardrail. The pipeline refuses to run without a safety checker. By default it gets NVIDIA's
own (``cosmos_guardrail.CosmosSafetyChecker``, the optional extra ``rigidbench[guardrail]``): it
checks each prompt and each generated video, and blurs faces; a blocked prompt or video fails that
example. The option ``no_guardrail`` (``--no-guardrail``) replaces it with a pass-through, prints
the licence terms the user then takes responsibility for (``LICENCE_NOTICE``) and is recorded in
generation.json.

torchvision. diffusers' Cosmos 2.5 code calls torchvision at run time in two places, and imports it
only when it is installed (otherwise the call fails with a NameError deep inside the pipeline):
the pipeline's ``image=`` path converts the image with ``torchvision.transforms.functional.to_tensor``,
and ``CosmosTransformer3DModel.forward`` resizes its padding mask with
``torchvision.transforms.functional.resize`` when ``concat_padding_mask`` is set, as it is for
Cosmos-Predict2.5-2B. The first is avoidable: the pipeline's own Video2World path with one
conditioning latent frame (``video=[first frame]``, ``num_latent_conditional_frames=1``) gives
exactly the frames of the ``image=`` path (the Wan VAE is causal, so the first latent frame depends
on the first frame alone, and only that latent frame conditions the generation; the tests check the
equality), and we take it when torchvision is missing. The second is not: without torchvision a
model with ``concat_padding_mask`` stops with an error naming the torchvision release to install.
"""

from __future__ import annotations

import importlib.metadata as md
import json
import logging
import sys
from typing import Any

from ..errors import PredictionError, RigidBenchError, WeightsUnavailable
from ..extras import install_command
from .base import PredictContext
from .local import LocalVideoModel
from .options import CosmosOptions

log = logging.getLogger(__name__)

LICENCE_URL = "https://www.nvidia.com/en-us/agreements/enterprise-software/nvidia-open-model-license/"
LICENCE_NOTICE = (
    "cosmos-2.5 --no-guardrail: NVIDIA's Cosmos guardrail (prompt and video safety checks, face blurring) is "
    "replaced by a pass-through. Cosmos-Predict2.5-2B is licensed under the NVIDIA Open Model License Agreement ("
    + LICENCE_URL + "). By running it without the guardrail you take responsibility for its terms, in particular "
    "section 2.1 (Conditions for Use): \"If You bypass, disable, reduce the efficacy of, or circumvent any technical "
    "limitation, safety guardrail or associated safety guardrail hyperparameter, encryption, security, digital rights "
    "management, or authentication mechanism (collectively 'Guardrail') contained in the Model without a "
    "substantially similar Guardrail appropriate for your use case, your rights under this Agreement will "
    "automatically terminate.\" and section 2.3 (AI Ethics): use of the Model must be consistent with NVIDIA's "
    "Trustworthy AI terms (https://www.nvidia.com/en-us/agreements/trustworthy-ai/terms/). RigidBench's prompts are "
    "fixed descriptions of rigid-body scenes; whether that, or anything else, is a substantially similar guardrail "
    "for your use is yours to judge.")
GUARDRAIL_EXTRA = install_command("guardrail")

_PASS_THROUGH = None  # the pass-through checker class, built on first use (it subclasses torch.nn.Module)
_GUARDRAIL = None  # the failing-loudly subclass of cosmos_guardrail.CosmosSafetyChecker, built on first use


def pass_through_checker():
    """A safety checker that lets every prompt and video through (``no_guardrail``)."""
    global _PASS_THROUGH
    if _PASS_THROUGH is None:
        import torch

        class PassThroughSafetyChecker(torch.nn.Module):
            """Stands in for Cosmos' guardrail: every prompt is safe, every video is returned as it is."""

            def __init__(self):
                super().__init__()
                self.register_buffer("_device_tracker", torch.zeros(1), persistent=False)

            def check_text_safety(self, prompt: str) -> bool:
                return True

            def check_video_safety(self, frames):
                return frames

            @property
            def device(self):
                return self._device_tracker.device

            @property
            def dtype(self):
                return self._device_tracker.dtype

        _PASS_THROUGH = PassThroughSafetyChecker
    return _PASS_THROUGH()


def guardrail_checker():
    """NVIDIA's guardrail (``cosmos_guardrail.CosmosSafetyChecker``), subclassed so that a blocked prompt or
    video fails the example with a PredictionError instead of a ValueError or a crash inside diffusers
    (the guardrail returns None for a blocked video, which the pipeline does not handle)."""
    global _GUARDRAIL
    try:
        from cosmos_guardrail import CosmosSafetyChecker
    except ImportError:
        raise RigidBenchError(
            f"cosmos-2.5 runs NVIDIA's Cosmos guardrail by default, and the cosmos-guardrail package is not "
            f"installed: install it with {GUARDRAIL_EXTRA}, or pass --no-guardrail (option no_guardrail) to replace "
            "it with a pass-through, taking responsibility for the NVIDIA Open Model License terms it prints") from None
    if _GUARDRAIL is None or not issubclass(_GUARDRAIL, CosmosSafetyChecker):

        class Guardrail(CosmosSafetyChecker):
            def check_text_safety(self, prompt: str) -> bool:
                if not super().check_text_safety(prompt):
                    raise PredictionError("the Cosmos guardrail blocked the prompt")
                return True

            def check_video_safety(self, frames):
                checked = super().check_video_safety(frames)
                if checked is None:
                    raise PredictionError("the Cosmos guardrail blocked the generated video")
                return checked

        _GUARDRAIL = Guardrail
    try:
        return _GUARDRAIL()
    except OSError as exc:
        raise WeightsUnavailable(f"cosmos-2.5: the Cosmos guardrail could not load its models ({exc}); they are "
                                 "downloaded from the Hugging Face hub on first use") from exc


def torchvision_hint() -> str:
    """Which torchvision to install for the installed torch (torchvision 0.(N+15) pairs with torch 2.N)."""
    try:
        major, minor = md.version("torch").split(".")[:2]
        if major == "2" and minor.isdigit():
            return f"pip install 'torchvision==0.{int(minor) + 15}.*' (the release built for torch {major}.{minor})"
    except md.PackageNotFoundError:
        pass
    return "pip install torchvision (the release built for your torch)"


def _cosmos_modules():
    from diffusers.models.transformers import transformer_cosmos
    from diffusers.pipelines.cosmos import pipeline_cosmos2_5_predict

    return pipeline_cosmos2_5_predict, transformer_cosmos


def image_path_available() -> bool:
    """Whether diffusers' ``image=`` path can run (it calls torchvision's ``to_tensor``)."""
    return hasattr(_cosmos_modules()[0], "torchvision")


def padding_mask_available() -> bool:
    """Whether ``CosmosTransformer3DModel.forward`` can resize its padding mask (torchvision's ``resize``)."""
    return hasattr(_cosmos_modules()[1], "transforms")


class CosmosPredictor(LocalVideoModel):
    options_type = CosmosOptions
    model_id = "nvidia/Cosmos-Predict2.5-2B"
    default_revision = "diffusers/base/post-trained"
    pipeline_class = "Cosmos2_5_PredictBasePipeline"
    defaults = {"height": 704, "width": 1280, "num_frames": 33, "fps": 16.0, "steps": 50,
                "guidance_scale": 7.0, "dtype": "bfloat16"}
    guidance_note = "not stated in the paper; the default of diffusers' Cosmos2_5_PredictBasePipeline (7.0)"

    def __init__(self, info):
        super().__init__(info)
        self._noticed = False

    def guardrail(self, ctx: PredictContext) -> str:
        return "pass-through (--no-guardrail)" if self.options(ctx).no_guardrail else "cosmos_guardrail.CosmosSafetyChecker"

    def extra_settings(self, ctx: PredictContext) -> dict[str, Any]:
        return {"guardrail": self.guardrail(ctx)}

    def conditioning(self) -> str:
        if image_path_available():
            return "image= (Image2World)"
        return "video=[first frame], num_latent_conditional_frames=1 (identical to image=, which needs torchvision)"

    def extra_info(self, ctx: PredictContext) -> dict[str, Any]:
        info: dict[str, Any] = {"guardrail": self.guardrail(ctx), "conditioning": self.conditioning()}
        if self.options(ctx).no_guardrail:
            info["licence_notice"] = LICENCE_NOTICE
        else:
            try:
                info["cosmos_guardrail_version"] = md.version("cosmos-guardrail")
            except md.PackageNotFoundError:
                pass
        return info

    def check_runnable(self, ctx: PredictContext) -> None:
        if self.options(ctx).no_guardrail:
            if not self._noticed:
                print(LICENCE_NOTICE, file=sys.stderr)
                log.warning("cosmos-2.5 runs without its guardrail (--no-guardrail)")
                self._noticed = True
        else:
            try:
                import cosmos_guardrail  # noqa: F401
            except ImportError:
                guardrail_checker()  # raises the RigidBenchError naming the extra and --no-guardrail
        if self.needs_padding_mask(ctx) and not padding_mask_available():
            raise RigidBenchError(
                "cosmos-2.5 needs torchvision at run time: diffusers' CosmosTransformer3DModel (concat_padding_mask="
                f"True, as in {self.model_id}) resizes its padding mask with torchvision.transforms.functional.resize, "
                f"and torchvision is not importable. Install it: {torchvision_hint()}")

    def needs_padding_mask(self, ctx: PredictContext) -> bool:
        """Whether the transformer concatenates a padding mask (its forward then calls torchvision): from the
        injected pipeline or model_path's transformer/config.json; the hub model does (True)."""
        o = self.options(ctx)
        if o.pipeline is not None:
            return bool(getattr(o.pipeline.transformer.config, "concat_padding_mask", False))
        if o.model_path is not None:
            config = o.model_path.expanduser() / "transformer" / "config.json"
            try:
                return bool(json.loads(config.read_text()).get("concat_padding_mask", True))
            except (OSError, ValueError):
                return True
        return True

    def load_pipeline(self, ctx: PredictContext, dtype):
        from diffusers import Cosmos2_5_PredictBasePipeline

        return self.from_pretrained(Cosmos2_5_PredictBasePipeline, ctx, dtype, safety_checker=self.safety_checker(ctx))

    def safety_checker(self, ctx: PredictContext):
        return pass_through_checker() if self.options(ctx).no_guardrail else guardrail_checker()

    def configure(self, pipe, ctx: PredictContext, injected: bool):
        if injected:  # the run's guardrail setting replaces whatever checker the injected pipeline had
            pipe.register_modules(safety_checker=self.safety_checker(ctx))
        return pipe

    def call_kwargs(self, pipe, inputs, p: dict[str, Any]) -> dict[str, Any]:
        if image_path_available():
            from PIL import Image

            return {"image": Image.fromarray(inputs.image)}
        import torch

        # exactly what the image= path builds: torchvision's to_tensor (CHW, float in [0, 1]) of the first frame
        frame = torch.from_numpy(inputs.image.transpose(2, 0, 1).copy()).to(torch.get_default_dtype()).div(255)
        return {"video": frame[None, None], "num_latent_conditional_frames": 1}
