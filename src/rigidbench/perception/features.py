"""DINOv2 ViT-L/14 identity features for IdDrift (paper, appendix B.2).

Weights load with ``transformers`` from the ``path`` argument, the directory in
``RIGIDBENCH_DINOV2``, or the Hugging Face cache (``facebook/dinov2-large``), in that order (see
``perception.weights``); by default no download is attempted, so an offline machine gets a clear
message instead of a network error. Inference is bfloat16 on CUDA and float32 on the CPU; IdDrift
feeds the network batches of 256 patches.
"""

from __future__ import annotations

from typing import Callable

DINOV2_MODEL = "facebook/dinov2-large"
DINOV2_ENV = "RIGIDBENCH_DINOV2"


class WeightsUnavailable(OSError):
    """Model weights are not available locally; the message says where we looked and how to fetch them."""


def load_dinov2(path: str | None = None, allow_download: bool = False):
    """Returns the pretrained ``Dinov2Model`` (float32, CPU) from ``path``, $RIGIDBENCH_DINOV2 or the cache."""
    from . import weights

    try:
        from transformers import Dinov2Model
    except ModuleNotFoundError:
        raise WeightsUnavailable("DINOv2 identity features need the 'transformers' package: "
                                 "pip install -e '.[neural]'") from None
    return weights.load_pretrained(Dinov2Model, "dinov2", path, allow_download)


def load_identity_features(device: str | None = None, path: str | None = None, allow_download: bool = False,
                           model=None) -> Callable:
    """Return f: (B,3,224,224) ImageNet-normalised float -> (B,D) float32 DINOv2 CLS features.

    ``device`` None picks CUDA when available; bf16 on CUDA, float32 on CPU. ``model`` may be a
    ready ``Dinov2Model`` (tests pass a tiny one).
    """
    import torch

    from .device import inference_dtype, resolve_device

    device = resolve_device(device)
    if model is None:
        model = load_dinov2(path, allow_download)
    dtype = inference_dtype("dinov2", device)
    model = model.to(device=device, dtype=dtype).eval()

    @torch.no_grad()
    def features(x: "torch.Tensor") -> "torch.Tensor":
        out = model(pixel_values=x.to(device=device, dtype=dtype))
        return out.pooler_output.float()

    features.parameters = model.parameters  # lets IdDrift prepare patches on the model's device
    return features
