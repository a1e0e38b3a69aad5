"""Point tracks with CoTracker3 offline (paper, appendix B.2, Table 9).

The tracker is the torch-hub entry ``cotracker3_offline`` of ``facebookresearch/co-tracker``,
called as ``tracks, visible = model(video, queries=queries)`` with video (B,T,3,H,W) float in
[0, 255] and queries (B,N,3) rows (t, x, y) in pixels (integer values at pixel centres, the
RigidBench convention); it returns tracks (B,T,N,2) pixels and visibility (B,T,N).

Loading, without network unless allowed: the hub repository comes from the ``repo_dir``
argument, $RIGIDBENCH_COTRACKER, or the torch hub cache (``<hub>/facebookresearch_co-tracker_main``)
and is loaded with ``source="local"``; the checkpoint from ``checkpoint``,
$RIGIDBENCH_COTRACKER_CKPT, or the torch hub cache (``<hub>/checkpoints/scaled_offline.pth``).

Queries are the ground-truth track points (the reference's frame-0 query pixels, 20 per active
actor from a 3-pixel erosion of its mask) and the background Shi-Tomasi corners, tracked
together in one call. The public predictor returns a thresholded visibility (CoTracker3:
visibility x confidence > 0.6); where a model returns a float visibility it is used as the
confidence, otherwise the boolean decision is (1 or 0).
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

log = logging.getLogger(__name__)

HUB_REPO = "facebookresearch/co-tracker"
HUB_ENTRY = "cotracker3_offline"
VISIBLE_THRESHOLD = 0.5  # only for models that return a float visibility


def load_cotracker(repo_dir: str | Path | None = None, checkpoint: str | Path | None = None, device: str = "cpu",
                   pretrained: bool = True, allow_download: bool = False):
    """CoTracker3 offline predictor in eval mode on ``device`` (float32). ``pretrained=False`` keeps the
    hub entry's random initialisation (tests, benchmarks). Raises WeightsUnavailable when absent."""
    import torch

    from . import weights
    from .features import WeightsUnavailable

    repo = weights.locate("cotracker-code", repo_dir)
    if repo is None and not allow_download:
        raise WeightsUnavailable(weights.missing_message("cotracker-code", repo_dir))
    ckpt = weights.locate("cotracker", checkpoint) if pretrained else None
    if pretrained and ckpt is None and not allow_download:
        raise WeightsUnavailable(weights.missing_message("cotracker", checkpoint))
    explicit_ckpt = ckpt is not None and (checkpoint is not None
                                          or weights.env_path(weights.WEIGHTS["cotracker"]) is not None)
    # The hub entry fetches (or reads from the hub cache) its own checkpoint when pretrained=True.
    hub_pretrained = pretrained and not explicit_ckpt
    try:
        if repo is not None:
            model = torch.hub.load(str(repo), HUB_ENTRY, source="local", pretrained=hub_pretrained)
        else:
            model = torch.hub.load(HUB_REPO, HUB_ENTRY, trust_repo=True, pretrained=hub_pretrained)
    except OSError as exc:
        raise WeightsUnavailable(f"{weights.missing_message('cotracker-code', repo_dir)} "
                                 f"(loading failed: {exc})") from None
    if explicit_ckpt:
        state = torch.load(ckpt, map_location="cpu", weights_only=True)
        target = getattr(model, "model", model)
        target.load_state_dict(state)
    return model.to(device).eval()


def query_points(sample) -> np.ndarray:
    """The reference's ground-truth query pixels (P,2) as float32 (x, y): frame-0 positions of its tracks."""
    return np.asarray(sample.tracks["query_pixels"], dtype=np.float32).reshape(-1, 2)


def track_points(model, frames: np.ndarray, points_xy: np.ndarray, device=None):
    """frames (T,H,W,3) uint8; points_xy (N,2) frame-0 pixels (x, y). Returns tracks (N,T,2) float32,
    visible (N,T) bool and confidence (N,T) float32 in [0, 1]."""
    import torch

    t = frames.shape[0]
    n = points_xy.shape[0]
    if n == 0:
        return np.zeros((0, t, 2), np.float32), np.zeros((0, t), bool), np.zeros((0, t), np.float32)
    if device is None:
        param = next(iter(model.parameters()), None)
        device = param.device if param is not None else "cpu"
    video = torch.from_numpy(np.ascontiguousarray(frames)).to(device).permute(0, 3, 1, 2)[None].float()
    queries = torch.zeros((1, n, 3), dtype=torch.float32, device=device)
    queries[0, :, 1:] = torch.from_numpy(np.asarray(points_xy, np.float32)).to(device)
    with torch.inference_mode():
        tracks, visible = model(video, queries=queries)
    tracks = tracks[0].float().permute(1, 0, 2).cpu().numpy()  # (N,T,2)
    visible = visible[0].permute(1, 0).cpu()
    if visible.dtype == torch.bool:
        confidence = visible.float().numpy()
        visible = visible.numpy()
    else:
        confidence = visible.float().clamp(0, 1).numpy()
        visible = confidence > VISIBLE_THRESHOLD
    if tracks.shape != (n, t, 2):
        raise ValueError(f"CoTracker returned tracks of shape {tracks.shape}, expected {(n, t, 2)}")
    return tracks.astype(np.float32), visible.astype(bool), confidence.astype(np.float32)
