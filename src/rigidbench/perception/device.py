"""Where and at which precision the perception networks run.

The best device is CUDA when torch sees a GPU, else the CPU; a request for CUDA on a machine
without one falls back to the CPU with a warning instead of failing. On CUDA each network runs as
the published evaluation (the authors' RigidBench release) ran it:

- SAM 2.1: float32. The release builds ``SAM2VideoPredictor.from_pretrained`` and propagates with
  no autocast (``eval/track/sam2.py``); the bfloat16 autocast of SAM 2's demo notebooks was not used.
  (The predictor, like ``transformers``, stores the per-frame memory features as bfloat16.)
- CoTracker3 offline and LPIPS: float32 (``eval/track/cotracker3.py``, ``eval/score/frame.py``).
- DINOv2: float32 weights under bfloat16 autocast (``eval/score/identity.py``: the hub model is
  not cast, the batch is bf16 and the forward runs in ``torch.autocast(dtype=torch.bfloat16)``),
  so layer norms keep float32.
- Video Depth Anything: float32 weights under float16 autocast (upstream ``infer_video_depth``
  with ``fp32=False``), except the head's last output convolution, which upstream runs in float32
  with autocast disabled (``dpt_temporal.py``); Depth Anything V2 (fallback, not in the paper):
  float16 autocast.

``CUDA_PRECISION`` holds the autocast dtype (or the dtype of the weights where nothing is
autocast). On the CPU everything runs in float32.
"""

from __future__ import annotations

import logging

log = logging.getLogger(__name__)

#: Inference dtype on CUDA per network (CPU is always float32): what the forward computes in (autocast).
CUDA_PRECISION = {
    "sam2": "float32",
    "cotracker": "float32",
    "vda": "float16",
    "dav2": "float16",
    "dinov2": "bfloat16",
    "lpips": "float32",
}


def cuda_available() -> bool:
    import torch

    return bool(torch.cuda.is_available())


def resolve_device(requested: str | None = None) -> str:
    """requested: None (best available), "cpu", "cuda" or "cuda:N". Returns a usable torch device string."""
    if requested is None:
        return "cuda" if cuda_available() else "cpu"
    requested = str(requested)
    if requested.startswith("cuda") and not cuda_available():
        log.warning("device %r requested but CUDA is not available; running perception on the CPU", requested)
        return "cpu"
    return requested


def inference_dtype(network: str, device: str):
    """Returns the torch dtype ``network`` (a key of CUDA_PRECISION) runs at on ``device``."""
    import torch

    if network not in CUDA_PRECISION:
        raise KeyError(f"unknown network {network!r}; known: {', '.join(CUDA_PRECISION)}")
    if not str(device).startswith("cuda"):
        return torch.float32
    return getattr(torch, CUDA_PRECISION[network])
