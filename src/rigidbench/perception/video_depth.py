"""Video Depth Anything Large: relative disparity for a whole clip (paper appendix, "Perception and
Feature Extraction", table tab:perception-settings).

Paper settings: ``depth-anything/Video-Depth-Anything-Large`` (ViT-L encoder), input size 384,
24 Hz; the saved output is disparity. The network lives in ``vda_model``; this module loads
the official checkpoint (strict key match) and runs a clip the way the authors' reference code
does:

- every frame is resized (bicubic) so both sides are at least ``input_size`` and multiples of
  14, keeping the aspect ratio; clips wider than 1.78:1 get a proportionally smaller
  ``input_size`` first (upstream's memory rule, which applies to 1280x704 clips); ImageNet
  normalisation;
- 32-frame windows advance by 22 frames; the first 10 slots of each later window hold key
  frames of the previous window (its slots 0, 12 and 24..31); the clip end is padded by
  repeating the last frame;
- each window's disparity is resized back to the frame size (bilinear, corners aligned),
  mapped onto the previous windows by a least-squares scale and shift fitted on the two
  re-used key frames (clipped at zero), and cross-faded linearly over the 8 overlapping frames.

Precision follows upstream: float32 weights under fp16 autocast on CUDA, except the head's last
output convolution, which runs in float32 with autocast off (``vda_model.DPTHead``, as upstream's
``dpt_temporal.py``); float32 on CPU.
"""

from __future__ import annotations

import contextlib
import logging
import os
from pathlib import Path
from typing import Iterable, Sequence

import numpy as np

from ..errors import WeightsUnavailable
from ..extras import available, require

log = logging.getLogger(__name__)

VDA_REPO = "depth-anything/Video-Depth-Anything-Large"
VDA_FILENAME = "video_depth_anything_vitl.pth"
VDA_ENV = "RIGIDBENCH_VDA"
VDA_INPUT_SIZE = 384
VDA_WINDOW = 32
VDA_OVERLAP = 10
PATCH = 14
IMAGENET_MEAN = np.array([0.485, 0.456, 0.406], dtype=np.float32)
IMAGENET_STD = np.array([0.229, 0.224, 0.225], dtype=np.float32)
N_ALIGN = 2  # key frames used for the scale/shift fit: the clip's first frame and one mid-window frame


# ---------------------------------------------------------------------------------------------
# Model construction and weights
# ---------------------------------------------------------------------------------------------

def vda_config(encoder: str = "vitl", **overrides):
    """Architecture of the released ``encoder`` (vits, vitb, vitl) with field overrides (tiny test models)."""
    from .vda_model import ENCODER_CONFIGS, VDAConfig

    if encoder not in ENCODER_CONFIGS:
        raise ValueError(f"unknown Video Depth Anything encoder {encoder!r}; choose one of {sorted(ENCODER_CONFIGS)}")
    fields = {**ENCODER_CONFIGS[encoder], **overrides}
    for key in ("layer_idx", "out_channels"):
        fields[key] = tuple(fields[key])
    return VDAConfig(**fields)


def build_vda_network(model_cls, encoder: str = "vitl", device="cpu", **overrides):
    """Randomly initialised ``model_cls`` (``vda_model.VideoDepthAnything`` or ``DepthAnythingV2``) for
    ``vda_config(encoder, **overrides)``, in eval mode; ``device="meta"`` allocates no memory."""
    import torch

    cfg = vda_config(encoder, **overrides)
    if str(device) == "meta":
        with torch.device("meta"):
            return model_cls(cfg).eval()
    return model_cls(cfg).to(device).eval()


def build_video_depth_anything(encoder: str = "vitl", device="cpu", **overrides):
    """Randomly initialised VideoDepthAnything in eval mode; ``device="meta"`` allocates no memory."""
    from .vda_model import VideoDepthAnything

    return build_vda_network(VideoDepthAnything, encoder, device, **overrides)


def expected_state_dict_shapes(encoder: str = "vitl", **overrides) -> dict[str, tuple[int, ...]]:
    """Checkpoint key -> tensor shape for ``encoder`` (built on the meta device)."""
    model = build_video_depth_anything(encoder, device="meta", **overrides)
    return {key: tuple(value.shape) for key, value in model.state_dict().items()}


def hf_cached_file(repo: str, filename: str, cache_dir: str | Path | None) -> Path | None:
    """Path of ``filename`` of ``repo`` in the Hugging Face cache, or None."""
    if not available("huggingface_hub"):  # nothing can be found there without it; missing_message says so
        return None
    from huggingface_hub import try_to_load_from_cache

    found = try_to_load_from_cache(repo, filename, cache_dir=None if cache_dir is None else str(cache_dir))
    return Path(found) if isinstance(found, str) and Path(found).is_file() else None


def find_vda_weights(path: str | Path | None = None, cache_dir: str | Path | None = None) -> Path | None:
    """Checkpoint file from ``path`` (file or folder), else $RIGIDBENCH_VDA, else the HF cache; None if absent.

    An explicit ``path`` or the environment variable, when given, is the only place looked at, so
    a stale setting is reported rather than silently replaced by another copy.
    """
    where = path if path is not None else (os.environ.get(VDA_ENV) or None)
    if where is not None:
        candidate = Path(where).expanduser()
        if candidate.is_dir():
            candidate = candidate / VDA_FILENAME
        return candidate if candidate.is_file() else None
    return hf_cached_file(VDA_REPO, VDA_FILENAME, cache_dir)


def _looked_at(path, cache_dir) -> str:
    if path is not None:
        return f"the given path {path}"
    if os.environ.get(VDA_ENV):
        return f"${VDA_ENV}={os.environ[VDA_ENV]}"
    return f"${VDA_ENV} (unset) and the Hugging Face cache{'' if cache_dir is None else f' at {cache_dir}'}"


def _download(cache_dir) -> Path:
    hf_hub_download = require("huggingface_hub", "downloading Video Depth Anything").hf_hub_download
    try:
        return Path(hf_hub_download(VDA_REPO, VDA_FILENAME, cache_dir=None if cache_dir is None else str(cache_dir)))
    except OSError as err:  # hub HTTP and offline errors are OSErrors
        raise WeightsUnavailable(f"could not download {VDA_FILENAME} from {VDA_REPO}: {err}; download it by hand "
                                 f"and set {VDA_ENV} to the file") from None


def load_video_depth_anything(path: str | Path | None = None, device="cpu", dtype=None, allow_download: bool = False,
                              encoder: str = "vitl", cache_dir: str | Path | None = None, **overrides):
    """Video Depth Anything with the official weights, strict key match, eval mode on ``device``.

    ``dtype`` casts the weights (default: keep float32; ``video_disparity`` autocasts on CUDA).
    Raises WeightsUnavailable naming where it looked and how to fetch the file (before importing torch).
    """
    weights = find_vda_weights(path, cache_dir)
    if weights is None and allow_download and path is None and not os.environ.get(VDA_ENV):
        weights = _download(cache_dir)
    if weights is None:
        raise WeightsUnavailable(
            f"Video Depth Anything Large weights ({VDA_FILENAME} from the Hugging Face repo {VDA_REPO}) are not "
            f"available locally: looked at {_looked_at(path, cache_dir)}. Fetch them once with "
            f"`rigidbench weights --download vda` on a machine with network access, or download the file and set "
            f"{VDA_ENV} to it (or to its folder).")
    log.info("loading Video Depth Anything (%s) from %s", encoder, weights)
    import torch

    state = torch.load(weights, map_location="cpu", weights_only=True)
    if isinstance(state, dict) and "model" in state and isinstance(state["model"], dict):
        raise ValueError(f"{weights} wraps its weights in a training checkpoint; save model.state_dict() instead")
    model = build_video_depth_anything(encoder, device="meta", **overrides)
    try:
        model.load_state_dict(state, strict=True, assign=True)
    except RuntimeError as err:
        raise ValueError(f"{weights} is not a Video Depth Anything '{encoder}' checkpoint: {err}") from None
    return model.to(device=device, dtype=dtype).eval()


# ---------------------------------------------------------------------------------------------
# Preprocessing
# ---------------------------------------------------------------------------------------------

def network_size(height: int, width: int, input_size: int = VDA_INPUT_SIZE, cap_aspect: bool = True) -> tuple[int, int]:
    """Network input (h, w) for a height x width frame: both >= input_size, multiples of 14, aspect kept.

    ``cap_aspect`` applies upstream VDA's rule for clips wider than 1.78:1 (a smaller input size).
    Rounding is Python's (half to even), as upstream's numpy rounding.
    """
    if cap_aspect:
        ratio = max(height, width) / min(height, width)
        if ratio > 1.78:
            input_size = max(PATCH, round(int(input_size * 1.777 / ratio) / PATCH) * PATCH)
    scale = max(input_size / height, input_size / width)

    def fit(x: float) -> int:
        y = round(x / PATCH) * PATCH
        return y if y >= input_size else int(np.ceil(x / PATCH)) * PATCH

    return fit(scale * height), fit(scale * width)


def preprocess_frames(frames: np.ndarray, size_hw: tuple[int, int]) -> np.ndarray:
    """frames: (T,H,W,3) uint8 RGB. Returns (T,3,h,w) float32, bicubic-resized and ImageNet-normalised."""
    import cv2

    h, w = size_hw
    out = np.empty((len(frames), 3, h, w), dtype=np.float32)
    for i, frame in enumerate(frames):
        rgb = cv2.resize(frame.astype(np.float32) / 255.0, (w, h), interpolation=cv2.INTER_CUBIC)
        out[i] = ((rgb - IMAGENET_MEAN) / IMAGENET_STD).transpose(2, 0, 1)
    return out


def check_frames(frames: np.ndarray) -> None:
    """Raise ValueError unless frames is a non-empty (T,H,W,3) uint8 array."""
    if not (isinstance(frames, np.ndarray) and frames.ndim == 4 and frames.shape[-1] == 3 and frames.dtype == np.uint8
            and frames.shape[0] >= 1):
        raise ValueError(f"expected frames as a (T,H,W,3) uint8 array with T >= 1, got "
                         f"{getattr(frames, 'shape', type(frames))} {getattr(frames, 'dtype', '')}")


# ---------------------------------------------------------------------------------------------
# Windowing (pure index logic) and stitching
# ---------------------------------------------------------------------------------------------

def key_slots(window: int = VDA_WINDOW, overlap: int = VDA_OVERLAP) -> tuple[int, ...]:
    """Slots of a window re-used as the first ``overlap`` slots of the next: (0, 12, 24..31) for 32/10."""
    step = window - overlap
    if step < 2 or overlap < N_ALIGN + 2:
        raise ValueError(f"window {window} with overlap {overlap}: need window - overlap >= 2 and overlap >= 4")
    interp = overlap - N_ALIGN
    return (0, step // 2 + 1) + tuple(range(window - interp, window))


def window_slot_frames(n_frames: int, window: int = VDA_WINDOW, overlap: int = VDA_OVERLAP) -> np.ndarray:
    """Source frame of every slot of every window. Returns (n_windows, window) int; past the end: the last frame."""
    if n_frames < 1:
        raise ValueError("a clip needs at least one frame")
    keys = list(key_slots(window, overlap))
    plan = []
    for start in range(0, n_frames, window - overlap):
        slots = np.minimum(np.arange(start, start + window), n_frames - 1)
        if plan:
            slots[:overlap] = plan[-1][keys]
        plan.append(slots)
    return np.stack(plan)


def window_output_frames(n_frames: int, window: int = VDA_WINDOW, overlap: int = VDA_OVERLAP) -> list[np.ndarray]:
    """For each window, the frames its prediction first writes (before trimming to the clip). Returns [(k,) int]."""
    step = window - overlap
    starts = range(0, n_frames, step)
    return [np.arange(0, window) if i == 0 else np.arange(s + overlap, s + window) for i, s in enumerate(starts)]


def affine_fit(prediction: np.ndarray, target: np.ndarray) -> tuple[float, float]:
    """Least-squares scale, shift with scale * prediction + shift ~ target (any equal shapes); (1, 0) if degenerate."""
    p = prediction.astype(np.float64).ravel()
    t = target.astype(np.float64).ravel()
    a00, a01, a11 = p @ p, p.sum(), float(p.size)
    b0, b1 = p @ t, t.sum()
    det = a00 * a11 - a01 * a01
    if not det > 1e-12 * a00 * a11:
        return 1.0, 0.0
    return float((a11 * b0 - a01 * b1) / det), float((a00 * b1 - a01 * b0) / det)


def stitch_windows(windows: Iterable[np.ndarray], n_frames: int, overlap: int = VDA_OVERLAP) -> np.ndarray:
    """windows: per-window (window,H,W) disparity in slot order (see window_slot_frames). Returns (T,H,W) float32.

    Each later window is mapped onto the earlier ones by the scale/shift that best matches its
    key-frame slots to the already aligned key frames, clipped at zero, then its overlapping
    slots are cross-faded linearly into the last ``overlap - 2`` frames.
    """
    out: list[np.ndarray] = []
    ref: list[np.ndarray] = []
    keys: Sequence[int] = ()
    for cur in windows:
        window = cur.shape[0]
        if not out:
            keys = key_slots(window, overlap)
            out = [d.astype(np.float32) for d in cur]
            ref = [out[s] for s in keys[:N_ALIGN]]
            continue
        scale, shift = affine_fit(np.stack([cur[i] for i in range(N_ALIGN)]), np.stack(ref))

        def fix(d: np.ndarray) -> np.ndarray:
            return np.maximum(d * np.float32(scale) + np.float32(shift), 0).astype(np.float32)

        interp = overlap - N_ALIGN
        weights = np.linspace(0.0, 1.0, interp, dtype=np.float32)
        for j in range(interp):
            out[-interp + j] = out[-interp + j] * (1 - weights[j]) + fix(cur[N_ALIGN + j]) * weights[j]
        out.extend(fix(cur[i]) for i in range(overlap, window))
        ref = [ref[0]] + [fix(cur[s]) for s in keys[1:N_ALIGN]]
    if len(out) < n_frames:
        raise ValueError(f"windows cover {len(out)} frames, the clip has {n_frames}")
    return np.stack(out[:n_frames]).astype(np.float32)


# ---------------------------------------------------------------------------------------------
# Inference
# ---------------------------------------------------------------------------------------------

def autocast_dtype(device, dtype):
    """Lower precision to autocast to on ``device`` (None = plain float32): fp16 on CUDA unless told otherwise."""
    import torch

    if dtype is None:
        return torch.float16 if torch.device(device).type == "cuda" else None
    return None if dtype == torch.float32 else dtype


def video_disparity(model, frames: np.ndarray, input_size: int = VDA_INPUT_SIZE, device=None, dtype=None,
                    window: int = VDA_WINDOW, overlap: int = VDA_OVERLAP,
                    encoder_batch: int | None = None) -> np.ndarray:
    """frames: (T,H,W,3) uint8 RGB, any T >= 1. Returns (T,H,W) float32 relative disparity >= 0.

    ``device`` defaults to the model's; ``dtype`` is the autocast precision (default fp16 on CUDA,
    float32 on CPU); ``encoder_batch`` runs the ViT on that many frames at a time (memory only).
    """
    import torch
    import torch.nn.functional as F

    check_frames(frames)
    n_frames, height, width = frames.shape[:3]
    param = next(model.parameters())
    device = torch.device(device) if device is not None else param.device
    if window > model.config.num_frames:
        raise ValueError(f"window {window} exceeds the model's temporal length {model.config.num_frames}")
    amp = autocast_dtype(device, dtype)
    inputs = torch.from_numpy(preprocess_frames(frames, network_size(height, width, input_size)))
    plan = window_slot_frames(n_frames, window, overlap)
    log.debug("VDA: %d frames -> %d windows at %s", n_frames, len(plan), tuple(inputs.shape[-2:]))

    def predictions():
        for slots in plan:
            x = inputs[torch.from_numpy(slots)].unsqueeze(0).to(device=device, dtype=param.dtype)
            precision = torch.autocast(device.type, dtype=amp) if amp is not None else contextlib.nullcontext()
            with torch.inference_mode(), precision:
                disparity = model(x, encoder_batch=encoder_batch)[0]
            disparity = F.interpolate(disparity.float()[:, None], size=(height, width), mode="bilinear",
                                      align_corners=True)[:, 0]
            yield disparity.cpu().numpy()

    return stitch_windows(predictions(), n_frames, overlap)
