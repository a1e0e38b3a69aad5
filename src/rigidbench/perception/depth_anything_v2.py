"""Depth Anything V2 Large, frame by frame: the fallback when Video Depth Anything is unavailable.

Not the paper's setting (which is Video Depth Anything, see ``video_depth``): each frame is
predicted independently, so its relative disparity may drift in scale between frames. Two
equivalent weight layouts load:

- the ``transformers`` model ``depth-anything/Depth-Anything-V2-Large-hf`` (a folder with
  ``config.json``), run by ``DepthAnythingForDepthEstimation``;
- the original checkpoint ``depth_anything_v2_vitl.pth`` (``depth-anything/Depth-Anything-V2-Large``),
  run by ``vda_model.DepthAnythingV2`` with strict key matching.

Preprocessing is done here, as in the reference code: both sides >= input size and multiples of
14 (bicubic, aspect kept), ImageNet statistics; the output is resized back to the frame
(bilinear, corners aligned).
"""

from __future__ import annotations

import contextlib
import logging
import os
from pathlib import Path

import numpy as np

from ..errors import WeightsUnavailable
from ..extras import require
from .video_depth import (autocast_dtype, build_vda_network, check_frames, hf_cached_file, network_size,
                          preprocess_frames)

log = logging.getLogger(__name__)

DAV2_MODEL = "depth-anything/Depth-Anything-V2-Large-hf"
DAV2_ENV = "RIGIDBENCH_DAV2"
DAV2_CHECKPOINT_REPO = "depth-anything/Depth-Anything-V2-Large"
DAV2_FILENAME = "depth_anything_v2_vitl.pth"


def _unavailable(where: str) -> WeightsUnavailable:
    return WeightsUnavailable(
        f"Depth Anything V2 Large weights are not available locally: looked at {where}. Fetch them once with "
        f"`rigidbench weights --download dav2` on a machine with network access, or set {DAV2_ENV} to a local "
        f"copy of {DAV2_MODEL} (a folder with config.json) or of {DAV2_FILENAME} from {DAV2_CHECKPOINT_REPO}.")


def build_depth_anything_v2(encoder: str = "vitl", device="cpu", **overrides):
    """Randomly initialised original-layout DepthAnythingV2 in eval mode; ``device="meta"`` allocates nothing."""
    from .vda_model import DepthAnythingV2

    return build_vda_network(DepthAnythingV2, encoder, device, **overrides)


def _load_checkpoint(path: Path, encoder: str = "vitl", **overrides):
    import torch

    state = torch.load(path, map_location="cpu", weights_only=True)
    model = build_depth_anything_v2(encoder, device="meta", **overrides)
    try:
        model.load_state_dict(state, strict=True, assign=True)
    except RuntimeError as err:
        raise ValueError(f"{path} is not a Depth Anything V2 '{encoder}' checkpoint: {err}") from None
    return model


def _load_transformers(source: str, offline: bool, cache_dir: str | Path | None = None):
    model = require("transformers", "the Depth Anything V2 transformers model").DepthAnythingForDepthEstimation
    return model.from_pretrained(source, local_files_only=offline, cache_dir=cache_dir)


def load_depth_anything_v2(path: str | Path | None = None, device="cpu", dtype=None, allow_download: bool = False,
                           cache_dir: str | Path | None = None, encoder: str = "vitl", **overrides):
    """Depth Anything V2 from ``path`` / $RIGIDBENCH_DAV2 (a transformers folder, a .pth or a folder holding it),
    else the Hugging Face cache (transformers model first, then the original checkpoint); eval mode on ``device``.

    ``overrides`` shape a tiny original-layout model (tests). Raises WeightsUnavailable.
    """
    local = path if path is not None else (os.environ.get(DAV2_ENV) or None)
    if local is not None:
        where = Path(local).expanduser()
        if (where / "config.json").is_file():
            model = _load_transformers(str(where), offline=True)
        elif where.is_file() or (where / DAV2_FILENAME).is_file():
            model = _load_checkpoint(where if where.is_file() else where / DAV2_FILENAME, encoder, **overrides)
        else:
            raise _unavailable(f"{where} (from {'the given path' if path is not None else '$' + DAV2_ENV})")
    else:
        checkpoint = hf_cached_file(DAV2_CHECKPOINT_REPO, DAV2_FILENAME, cache_dir)
        if checkpoint is None and not allow_download and hf_cached_file(DAV2_MODEL, "config.json", cache_dir) is None:
            # nothing local: say so before importing transformers
            raise _unavailable(f"${DAV2_ENV} (unset) and the Hugging Face cache ({DAV2_MODEL}, "
                               f"{DAV2_CHECKPOINT_REPO}/{DAV2_FILENAME})")
        try:
            model = _load_transformers(DAV2_MODEL, offline=not allow_download or checkpoint is not None,
                                       cache_dir=cache_dir)
        except OSError:
            if checkpoint is None:
                raise _unavailable(f"${DAV2_ENV} (unset) and the Hugging Face cache ({DAV2_MODEL}, "
                                   f"{DAV2_CHECKPOINT_REPO}/{DAV2_FILENAME})") from None
            model = _load_checkpoint(checkpoint, encoder, **overrides)
    log.info("loaded Depth Anything V2 (%s)", type(model).__name__)
    return model.to(device=device, dtype=dtype).eval()


def frame_disparity(model, frames: np.ndarray, input_size: int = 384, device=None, dtype=None,
                    batch_size: int = 8) -> np.ndarray:
    """frames: (T,H,W,3) uint8 RGB. Returns (T,H,W) float32 relative disparity >= 0, each frame on its own scale.

    ``model``: a transformers DepthAnythingForDepthEstimation or a ``vda_model.DepthAnythingV2``.
    ``device`` defaults to the model's; ``dtype`` is the autocast precision (default fp16 on CUDA,
    float32 on CPU).
    """
    import torch
    import torch.nn.functional as F

    from .vda_model import DepthAnythingV2

    check_frames(frames)
    n_frames, height, width = frames.shape[:3]
    param = next(model.parameters())
    device = torch.device(device) if device is not None else param.device
    amp = autocast_dtype(device, dtype)
    size = network_size(height, width, input_size, cap_aspect=False)  # the image model has no aspect rule
    out = np.empty((n_frames, height, width), dtype=np.float32)
    for start in range(0, n_frames, batch_size):
        batch = torch.from_numpy(preprocess_frames(frames[start:start + batch_size], size))
        batch = batch.to(device=device, dtype=param.dtype)
        precision = torch.autocast(device.type, dtype=amp) if amp is not None else contextlib.nullcontext()
        with torch.inference_mode(), precision:
            if isinstance(model, DepthAnythingV2):
                predicted = model(batch)
            else:
                predicted = model(pixel_values=batch).predicted_depth
        predicted = F.interpolate(predicted.float()[:, None], size=(height, width), mode="bilinear",
                                  align_corners=True)[:, 0]
        out[start:start + len(batch)] = predicted.clamp_min(0).cpu().numpy()
    return out
