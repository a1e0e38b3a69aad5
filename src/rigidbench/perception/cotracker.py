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
together in one call. The public predictor returns only a thresholded visibility (CoTracker3:
visibility x confidence > 0.6), but BGDrift weights corners by CoTracker3's confidences. When the
loaded model has the upstream predictor layout (``model.model`` the network, ``interp_shape``,
``support_grid_size`` and ``get_points_on_a_grid`` in its forward's module), ``track_points`` runs the network
the way the predictor does (resize to the model resolution, a support grid appended, the query
frame overwritten with the query) and keeps the continuous visibility x confidence; ``visible`` is
then that value > 0.6, the predictor's own decision. Other models fall back to the public call, where
a float visibility is used as the confidence and a boolean one gives 1 or 0.
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

log = logging.getLogger(__name__)

HUB_REPO = "facebookresearch/co-tracker"
HUB_ENTRY = "cotracker3_offline"
VISIBLE_THRESHOLD = 0.5  # only for models that return a float visibility
SOFT_THRESHOLD = 0.6  # CoTracker3's predictor: visible where visibility x confidence > 0.6
NETWORK_ITERS = 6  # refinement iterations the upstream predictor asks of its network


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
        soft = soft_visibility_tracks(model, video, queries)
        if soft is not None:
            tracks, confidence = soft
            tracks = tracks[0].float().permute(1, 0, 2).cpu().numpy()
            confidence = confidence[0].float().clamp(0, 1).permute(1, 0).cpu().numpy()
            if tracks.shape != (n, t, 2):
                raise ValueError(f"CoTracker returned tracks of shape {tracks.shape}, expected {(n, t, 2)}")
            return tracks.astype(np.float32), confidence > SOFT_THRESHOLD, confidence.astype(np.float32)
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


def soft_visibility_tracks(model, video, queries):
    """video (B,T,3,H,W) float [0, 255]; queries (B,N,3) (t, x, y) px. Returns (tracks (B,T,N,2) px,
    visibility x confidence (B,T,N)) from a CoTracker3 predictor's network, or None when ``model``
    does not have the upstream predictor layout (then only its public call is usable)."""
    import inspect

    import torch
    import torch.nn.functional as F

    net, shape = getattr(model, "model", None), getattr(model, "interp_shape", None)
    # The grid helper the predictor's own module uses (hub modules need not be in sys.modules).
    forward = inspect.unwrap(type(model).forward)  # upstream decorates it with torch.no_grad()
    grid_points = getattr(forward, "__globals__", {}).get("get_points_on_a_grid")
    if net is None or shape is None or grid_points is None or getattr(model, "v2", False):
        return None
    b, t, c, H, W = video.shape
    h, w = int(shape[0]), int(shape[1])
    small = F.interpolate(video.reshape(b * t, c, H, W), (h, w), mode="bilinear", align_corners=True)
    q = queries.clone()
    q[:, :, 1:] *= q.new_tensor([(w - 1) / (W - 1), (h - 1) / (H - 1)])
    n = q.shape[1]
    grid = grid_points(int(getattr(model, "support_grid_size", 6)), (h, w), device=video.device)
    grid = torch.cat([torch.zeros_like(grid[:, :, :1]), grid], dim=2).repeat(b, 1, 1)
    out = net(video=small.reshape(b, t, c, h, w), queries=torch.cat([q, grid], dim=1), iters=NETWORK_ITERS)
    if len(out) != 4:  # CoTracker2's network has no confidence head
        return None
    tracks, vis, conf = out[0][:, :, :n].clone(), out[1][:, :, :n], out[2][:, :, :n]
    soft = (vis * conf).clone()
    frame = q[:, :, 0].long()  # the query frame shows the query point itself, fully visible
    for i in range(b):
        tracks[i, frame[i], torch.arange(n)] = q[i, :, 1:]
        soft[i, frame[i], torch.arange(n)] = 1.0
    return tracks * tracks.new_tensor([(W - 1) / (w - 1), (H - 1) / (h - 1)]), soft
