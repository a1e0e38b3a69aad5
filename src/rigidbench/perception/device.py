"""Where and at which precision the perception networks run.

The best device is CUDA when torch sees a GPU, else the CPU; a request for CUDA on a machine
without one falls back to the CPU with a warning instead of failing. On CUDA each network runs at
the precision of its reference implementation (the paper states bfloat16 for DINOv2; SAM 2.1
runs under bfloat16 and Video Depth Anything / Depth Anything V2 under float16 in their own
releases; CoTracker3 and LPIPS run in float32). On the CPU everything runs in float32.
"""

from __future__ import annotations

import logging

log = logging.getLogger(__name__)

#: Inference dtype on CUDA per network (CPU is always float32).
CUDA_PRECISION = {
    "sam2": "bfloat16",
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
