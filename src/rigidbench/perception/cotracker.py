"""Point tracks with CoTracker3 offline (paper, appendix B.2, Table 9).

The tracker is the torch-hub entry ``cotracker3_offline`` of ``facebookresearch/co-tracker``,
called as ``tracks, visible = model(video, queries=queries)`` with video (B,T,3,H,W) float in
[0, 255] and queries (B,N,3) rows (t, x, y) in pixels (integer values at pixel centres, the
RigidBench convention); it returns tracks (B,T,N,2) pixels and visibility (B,T,N).

Loading, without network unless allowed: the hub repository comes from the ``repo_dir``
argument, $RIGIDBENCH_COTRACKER, or the torch hub cache (``<hub>/facebookresearch_co-tracker_main``)
and is loaded with ``source="local"``; the checkpoint from ``checkpoint``,
$RIGIDBENCH_COTRACKER_CKPT, or the torch hub cache (``<hub>/checkpoints/scaled_offline.pth``).

Two separate calls, as the published evaluation made them (RigidBench release:
``eval/track/cotracker3.py`` tracks the actor points, ``eval/score/background.py`` the
background corners): the ground-truth track points (the reference's frame-0 query pixels, 20 per
active actor from a 3-pixel erosion of its mask) on the generated clip, and the background
Shi-Tomasi corners on the clip resampled to the reference times. CoTracker3 attends across all
tracks of a call, so one joint call would let the corners move the actor tracks and back.

Visibility is the OFFLINE predictor's rule (``cotracker/predictor.py``,
``CoTrackerPredictor._compute_sparse_tracks``): visible where the network's visibility
(a sigmoid) > 0.9, with no confidence term, and always on the query frame. (The ONLINE predictor
uses visibility x confidence > 0.6; that is not the model the paper names.) The network's
confidence head is kept as a separate output: when the loaded model has the upstream predictor
layout (``model.model`` the network, ``interp_shape``, ``support_grid_size`` and
``get_points_on_a_grid`` in its forward's module), ``track_points`` runs the network the way the
predictor does (resize to the model resolution, a 6 x 6 support grid appended, 6 iterations, the
query frame overwritten with the query), so tracks and visibility equal the public call's and the
confidence comes along. Other models fall back to the public call: a boolean visibility is taken
as it is, a float one is thresholded at 0.9, and the confidence is that decision as 1 or 0.
BGDrift weights each corner by the boolean visibility (0/1), as the published runs did.
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from ..errors import WeightsUnavailable
from . import weights

log = logging.getLogger(__name__)

HUB_REPO = "facebookresearch/co-tracker"
HUB_ENTRY = "cotracker3_offline"
VISIBILITY_THRESHOLD = 0.9  # CoTracker3 offline predictor: visible where visibility > 0.9 (no confidence term)
NETWORK_ITERS = 6  # refinement iterations the upstream predictor asks of its network


def load_cotracker(repo_dir: str | Path | None = None, checkpoint: str | Path | None = None, device: str = "cpu",
                   pretrained: bool = True, allow_download: bool = False):
    """CoTracker3 offline predictor in eval mode on ``device`` (float32). ``pretrained=False`` keeps the
    hub entry's random initialisation (tests, benchmarks). Raises WeightsUnavailable when absent, before
    importing torch."""
    repo = weights.locate("cotracker-code", repo_dir)
    if repo is None and not allow_download:
        raise WeightsUnavailable(weights.missing_message("cotracker-code", repo_dir))
    ckpt = weights.locate("cotracker", checkpoint) if pretrained else None
    if pretrained and ckpt is None and not allow_download:
        raise WeightsUnavailable(weights.missing_message("cotracker", checkpoint))
    import torch

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
    """frames (T,H,W,3) uint8; points_xy (N,2) frame-0 pixels (x, y), tracked together in one call.
    Returns tracks (N,T,2) float32, visible (N,T) bool (the offline predictor's visibility > 0.9)
    and confidence (N,T) float32 in [0, 1] (CoTracker3's confidence head; 1 on the query frame; the
    0/1 visibility for models without one)."""
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
        out = network_tracks(model, video, queries)
        if out is not None:
            tracks, visibility, confidence = (x[0].float().transpose(0, 1).cpu() for x in out)
            visible = (visibility > VISIBILITY_THRESHOLD).numpy()
            confidence = confidence.clamp(0, 1).numpy()
        else:
            tracks, visibility = model(video, queries=queries)
            tracks = tracks[0].float().transpose(0, 1).cpu()
            visibility = visibility[0].transpose(0, 1).cpu()
            visible = (visibility if visibility.dtype == torch.bool else visibility.float() > VISIBILITY_THRESHOLD
                       ).numpy()
            confidence = visible.astype(np.float32)
    tracks = tracks.numpy()
    if tracks.shape != (n, t, 2) or visible.shape != (n, t):
        raise ValueError(f"CoTracker returned tracks of shape {tracks.shape}, expected {(n, t, 2)}")
    return tracks.astype(np.float32), visible.astype(bool), confidence.astype(np.float32)


def network_tracks(model, video, queries):
    """video (B,T,3,H,W) float [0, 255]; queries (B,N,3) (t, x, y) px. Returns (tracks (B,T,N,2) px,
    visibility (B,T,N), confidence (B,T,N)) from a CoTracker3 predictor's network, run as the
    offline predictor runs it (``_compute_sparse_tracks`` with its support grid), visibility and
    confidence 1 on the query frame; or None when ``model`` does not have the upstream predictor
    layout (then only its public call is usable)."""
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
    tracks, vis, conf = out[0][:, :, :n].clone(), out[1][:, :, :n].clone(), out[2][:, :, :n].clone()
    frame = q[:, :, 0].long()  # the query frame shows the query point itself, visible
    for i in range(b):
        tracks[i, frame[i], torch.arange(n)] = q[i, :, 1:]
        vis[i, frame[i], torch.arange(n)] = 1.0
        conf[i, frame[i], torch.arange(n)] = 1.0
    return tracks * tracks.new_tensor([(W - 1) / (w - 1), (H - 1) / (h - 1)]), vis, conf
