"""Actor masks with SAM 2.1 Hiera Large (paper, appendix B.2, Table 9).

The generated clip shares its first frame with the reference, so each active actor's frame-0
reference mask is the prompt: it is added as a mask input on frame 0 and propagated through the
generated video with ``transformers``' ``Sam2VideoModel``; the propagated logits are upsampled
to the frame size and thresholded at zero.

The model is driven directly (no ``Sam2VideoProcessor``, whose video path needs torchvision):
frames are resized to the model's square input (bilinear, antialiased), scaled to [0, 1] and
ImageNet-normalised, as the SAM 2 video processor does; a prompt mask is resized the same way
and binarised at 0.5; output logits (256 x 256) go to the input size and then to the frame
size, both bilinearly, as the processor's ``post_process_masks`` does.

Precision: float32 (``device.CUDA_PRECISION``), as in the published runs, which used the official
``SAM2VideoPredictor`` without autocast. Like that predictor (``sam2_video_predictor.py``), which
stores each frame's memory features as bfloat16, ``transformers`` rounds the memory features to
bfloat16 when it stores them and computes with them in the session dtype (float32 here).
"""

from __future__ import annotations

import logging

import numpy as np

from ..errors import WeightsUnavailable
from ..extras import require
from . import weights
from .device import inference_dtype

log = logging.getLogger(__name__)

SAM2_MODEL = "facebook/sam2.1-hiera-large"
SAM2_ENV = "RIGIDBENCH_SAM2"
IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)
MASK_THRESHOLD = 0.0


def hiera_large_config():
    """The Sam2VideoConfig of SAM 2.1 Hiera Large (1024 px input), for random-weight benchmarks."""
    from transformers import Sam2HieraDetConfig, Sam2VideoConfig, Sam2VisionConfig

    backbone = Sam2HieraDetConfig(hidden_size=144, embed_dim_per_stage=[144, 288, 576, 1152],
                                  num_attention_heads_per_stage=[2, 4, 8, 16], blocks_per_stage=[2, 6, 36, 4],
                                  global_attention_blocks=[23, 33, 43], window_size_per_stage=[8, 4, 16, 8],
                                  window_positional_embedding_background_size=[7, 7])
    vision = Sam2VisionConfig(backbone_config=backbone, backbone_channel_list=[1152, 576, 288, 144])
    return Sam2VideoConfig(vision_config=vision, enable_temporal_pos_encoding_for_object_pointers=True,
                           enable_occlusion_spatial_embedding=True)


def load_sam2(path: str | None = None, device: str = "cpu", dtype=None, allow_download: bool = False):
    """SAM 2.1 Hiera Large from ``path``, $RIGIDBENCH_SAM2 or the Hugging Face cache, in eval mode on
    ``device`` (``dtype`` default: float32 on CUDA and CPU, as the published runs' ``SAM2VideoPredictor``
    ran with no autocast: weights, frames and activations float32). Raises WeightsUnavailable if absent,
    before importing ``transformers``."""
    if weights.locate("sam2", path) is None and not allow_download:
        raise WeightsUnavailable(weights.missing_message("sam2", path))
    transformers = require("transformers", "SAM 2.1 actor masks (neural perception)")
    model = weights.load_pretrained(transformers.Sam2VideoModel, "sam2", path, allow_download)
    dtype = dtype if dtype is not None else inference_dtype("sam2", device)
    return model.to(device=device, dtype=dtype).eval()


def preprocess_frames(frames: np.ndarray, image_size: int, device="cpu", dtype=None):
    """frames (T,H,W,3) uint8 -> (T,3,S,S) tensor on ``device``: bilinear antialiased resize, ImageNet-normalised."""
    import torch
    import torch.nn.functional as F

    x = torch.from_numpy(np.ascontiguousarray(frames)).to(device).permute(0, 3, 1, 2).float() / 255.0
    x = F.interpolate(x, size=(image_size, image_size), mode="bilinear", align_corners=False, antialias=True)
    mean = torch.tensor(IMAGENET_MEAN, device=x.device).view(1, 3, 1, 1)
    std = torch.tensor(IMAGENET_STD, device=x.device).view(1, 3, 1, 1)
    x = (x - mean) / std
    return x.to(dtype) if dtype is not None else x


def prompt_masks(masks0: np.ndarray, image_size: int, device="cpu"):
    """masks0 (N,H,W) bool -> (N,1,S,S) float {0,1}: antialiased bilinear resize binarised at 0.5."""
    import torch
    import torch.nn.functional as F

    m = torch.from_numpy(np.ascontiguousarray(masks0, dtype=np.float32)).to(device)[:, None]
    if m.shape[-2:] != (image_size, image_size):
        m = F.interpolate(m, size=(image_size, image_size), mode="bilinear", align_corners=False, antialias=True)
        m = (m >= 0.5).float()
    return m


def logits_to_masks(logits, image_size: int, height: int, width: int) -> np.ndarray:
    """logits (N,1,h,w) low-res SAM output -> (N,H,W) bool: bilinear to (S,S), then to (H,W), then > 0."""
    import torch.nn.functional as F

    x = logits.float()
    x = F.interpolate(x, size=(image_size, image_size), mode="bilinear", align_corners=False)
    x = F.interpolate(x, size=(height, width), mode="bilinear", align_corners=False)
    return (x[:, 0] > MASK_THRESHOLD).cpu().numpy()


def propagate_masks(model, frames: np.ndarray, masks0: np.ndarray, device=None) -> np.ndarray:
    """frames (T,H,W,3) uint8; masks0 (N,H,W) bool frame-0 prompts. Returns (T,N,H,W) bool masks
    (propagated logits > 0). Runs at the model's device and dtype unless ``device`` is given."""
    import torch
    from transformers.models.sam2_video.modeling_sam2_video import Sam2VideoInferenceSession

    t, h, w = frames.shape[:3]
    n = masks0.shape[0]
    if masks0.shape[1:] != (h, w):
        raise ValueError(f"prompt masks are {masks0.shape[1:]} but frames are {(h, w)}")
    out = np.zeros((t, n, h, w), dtype=bool)
    if n == 0:
        return out
    param = next(model.parameters())
    device = torch.device(device) if device is not None else param.device
    size = int(model.config.image_size)
    session = Sam2VideoInferenceSession(video=preprocess_frames(frames, size, device, param.dtype), video_height=h,
                                        video_width=w, inference_device=device, inference_state_device=device,
                                        video_storage_device=device, dtype=param.dtype)
    prompts = prompt_masks(masks0, size, device)
    obj_ids = list(range(1, n + 1))
    for obj_id, prompt in zip(obj_ids, prompts):
        session.add_mask_inputs(session.obj_id_to_idx(obj_id), 0, prompt[None])
    session.obj_with_new_inputs = list(obj_ids)
    with torch.inference_mode():
        model(inference_session=session, frame_idx=0)
        for output in model.propagate_in_video_iterator(session, start_frame_idx=0):
            order = [output.object_ids.index(i) for i in obj_ids]
            out[output.frame_idx] = logits_to_masks(output.pred_masks[order], size, h, w)
    return out
