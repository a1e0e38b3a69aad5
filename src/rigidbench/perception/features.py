"""DINOv2 ViT-L/14 identity features for IdDrift (paper, appendix B.2).

Weights load with ``transformers`` from a local directory (``RIGIDBENCH_DINOV2`` or the
``path`` argument) or the Hugging Face cache (``facebook/dinov2-large``); by default no download
is attempted, so an offline machine gets a clear message instead of a network error.
"""

from __future__ import annotations

import os
from typing import Callable

DINOV2_MODEL = "facebook/dinov2-large"
DINOV2_ENV = "RIGIDBENCH_DINOV2"


class WeightsUnavailable(OSError):
    """Model weights are not available locally; the message says where we looked and how to fetch them."""


def load_identity_features(device: str = "cpu", path: str | None = None, allow_download: bool = False,
                           model=None) -> Callable:
    """Return f: (B,3,224,224) ImageNet-normalised float -> (B,D) DINOv2 CLS features.

    bf16 on CUDA, float32 on CPU. ``model`` may be a ready ``Dinov2Model`` (tests pass a tiny one).
    """
    import torch

    if model is None:
        try:
            from transformers import Dinov2Model
        except ModuleNotFoundError:
            raise WeightsUnavailable("DINOv2 identity features need the 'transformers' package: "
                                     "pip install -e '.[neural]'") from None
        source = path or os.environ.get(DINOV2_ENV) or DINOV2_MODEL
        try:
            model = Dinov2Model.from_pretrained(source, local_files_only=not allow_download)
        except OSError:
            raise WeightsUnavailable(
                f"DINOv2 weights '{source}' are not available locally (looked in ${DINOV2_ENV} and the Hugging Face "
                f"cache); fetch them once with `rigidbench weights --download` on a machine with network access, "
                f"or set {DINOV2_ENV} to a local copy of {DINOV2_MODEL}") from None
    dtype = torch.bfloat16 if device.startswith("cuda") else torch.float32
    model = model.to(device=device, dtype=dtype).eval()

    @torch.no_grad()
    def features(x: "torch.Tensor") -> "torch.Tensor":
        out = model(pixel_values=x.to(device=device, dtype=dtype))
        return out.pooler_output.float()

    return features
