"""Neural perception: what the metrics need, estimated from any generated video (paper, appendix B.2).

- masks: SAM 2.1 Hiera Large, prompted with each active actor's frame-0 reference mask and
  propagated through the generated clip, logits > 0 (``sam2``);
- tracks: CoTracker3 offline from the reference's ground-truth query points (the same points as
  the ground-truth tracks); ``visibility`` is the generated clip's own visibility, the metrics
  AND it with the reference's (``cotracker``);
- disparity: Video Depth Anything Large (``video_depth``; ``depth_model="dav2"`` selects Depth
  Anything V2 per frame), bilinearly resized to the frame grid when needed;
- background: Shi-Tomasi corners of the generated frame 0 outside the generated frame-0 masks
  (15-pixel erosion), tracked by the same CoTracker3 call; their confidences weight BGDrift.

Models load on first use (``perception.weights`` says where from) on the best device at their
reference precision. Each model's output is cached per example under ``cache_dir`` by a hash of
its inputs (the decoded frames and timestamps, the prompts or queries), the model identity and
its settings, so a second run, or a run that changes only another model, redoes no model work.
"""

from __future__ import annotations

import hashlib
import logging
import time
from pathlib import Path
from typing import Callable

import numpy as np

from .base import Perception, PerceptionError

log = logging.getLogger(__name__)

VERSION = "1"
DEPTH_MODELS = ("vda", "dav2")
DEPTH_INPUT_SIZE = 384


def array_digest(*arrays: np.ndarray) -> str:
    """sha256 over the dtype, shape and bytes of each array."""
    digest = hashlib.sha256()
    for a in arrays:
        a = np.ascontiguousarray(a)
        digest.update(f"{a.dtype.str}{a.shape}".encode())
        digest.update(a.tobytes())
    return digest.hexdigest()


def model_identity(model) -> str:
    """Class name and parameter count of a ready model (tells a tiny test model from the real one)."""
    parameters = getattr(model, "parameters", None)
    count = sum(int(p.numel()) for p in parameters()) if callable(parameters) else 0
    return f"{type(model).__name__}:{count}"


class NeuralBackend:
    """SAM 2.1 + CoTracker3 + Video Depth Anything perception with a per-model, per-example cache.

    depth_model: "vda" (default) or "dav2"; device: None for CUDA when available else CPU;
    cache_dir: where model outputs are cached (None: no cache unless the evaluator sets one);
    weights: local paths by registry name ("sam2", "cotracker", "cotracker-code", "vda", "dav2");
    models: ready models by role ("sam2", "cotracker", "depth") used instead of loading (tests);
    pretrained: False keeps hub entries randomly initialised (CoTracker stand-ins in tests);
    depth_input_size: the depth network's input size (the paper's 384; smaller only for tests).
    """

    name = "neural"

    def __init__(self, depth_model: str = "vda", device: str | None = None, cache_dir: str | Path | None = None,
                 allow_download: bool = False, weights: dict[str, str] | None = None,
                 models: dict[str, object] | None = None, pretrained: bool = True,
                 depth_input_size: int = DEPTH_INPUT_SIZE):
        from .device import resolve_device

        if depth_model not in DEPTH_MODELS:
            raise PerceptionError(f"unknown depth model '{depth_model}'; choose one of {', '.join(DEPTH_MODELS)}")
        self.depth_model = depth_model
        self.device = resolve_device(device)
        self.cache_dir = Path(cache_dir) if cache_dir is not None else None
        self.allow_download = allow_download
        self.weights = dict(weights or {})
        self.models = dict(models or {})
        self._injected = frozenset(self.models)
        self.pretrained = pretrained
        self.depth_input_size = int(depth_input_size)
        self.runs: dict[str, int] = {"sam2": 0, "cotracker": 0, "depth": 0}  # model invocations (cache misses)

    @property
    def version(self) -> str:
        """Backend version, depth model and a digest of the models used (changes when the weights do)."""
        models = hashlib.sha256(repr(self.settings["models"]).encode()).hexdigest()[:8]
        size = "" if self.depth_input_size == DEPTH_INPUT_SIZE else f"@{self.depth_input_size}"
        return f"{VERSION}+{self.depth_model}{size}-{models}"

    @property
    def settings(self) -> dict:
        return {"depth_model": self.depth_model, "device": self.device, "depth_input_size": self.depth_input_size,
                "mask_threshold": 0.0,
                "models": {role: self._identity(role) for role in ("sam2", "cotracker", "depth")}}

    def use_cache_dir(self, path: str | Path) -> None:
        """Cache model outputs under ``path`` unless a cache directory was given explicitly."""
        if self.cache_dir is None:
            self.cache_dir = Path(path)

    # -- models ------------------------------------------------------------------------------

    def _weight_name(self, role: str) -> str:
        return {"sam2": "sam2", "cotracker": "cotracker", "depth": self.depth_model}[role]

    def _identity(self, role: str) -> str:
        if role in self._injected:
            return model_identity(self.models[role])
        from . import weights

        name = self._weight_name(role)
        found = weights.locate(name, self.weights.get(name))
        if role != "cotracker":
            return f"{name}:{found}"
        code = weights.locate("cotracker-code", self.weights.get("cotracker-code"))
        return f"{name}:{found if self.pretrained else 'random'}:{code}"

    def missing_weights(self) -> list[str]:
        """One message per weight file this backend would need but cannot find (nothing to fetch when empty)."""
        from . import weights

        if self.allow_download:
            return []
        names = [self._weight_name(r) for r in ("sam2", "cotracker", "depth") if r not in self._injected]
        if "cotracker" in names:
            names.append("cotracker-code")
            if not self.pretrained:
                names.remove("cotracker")
        return [weights.missing_message(n, self.weights.get(n)) for n in names
                if weights.locate(n, self.weights.get(n)) is None]

    def model(self, role: str):
        """The model for ``role`` ("sam2", "cotracker", "depth"), loaded on first use."""
        if role not in self.models:
            t0 = time.time()
            self.models[role] = self._load(role)
            log.info("loaded %s for neural perception on %s in %.1f s", self._weight_name(role), self.device,
                     time.time() - t0)
        return self.models[role]

    def _load(self, role: str):
        w, dl = self.weights, self.allow_download
        if role == "sam2":
            from .sam2 import load_sam2

            return load_sam2(w.get("sam2"), device=self.device, allow_download=dl)
        if role == "cotracker":
            from .cotracker import load_cotracker

            return load_cotracker(w.get("cotracker-code"), w.get("cotracker"), device=self.device,
                                  pretrained=self.pretrained, allow_download=dl)
        if self.depth_model == "vda":
            from .video_depth import load_video_depth_anything

            return load_video_depth_anything(w.get("vda"), device=self.device, allow_download=dl)
        try:
            from .depth_anything_v2 import load_depth_anything_v2
        except ModuleNotFoundError as exc:
            raise PerceptionError(f"the Depth Anything V2 fallback is not available ({exc}); "
                                  "use depth_model='vda'") from None
        return load_depth_anything_v2(w.get("dav2"), device=self.device, allow_download=dl)

    # -- cache -------------------------------------------------------------------------------

    def _cached(self, sample_id: str, role: str, key: str, compute: Callable[[], dict]) -> dict[str, np.ndarray]:
        """The arrays ``compute`` returns for (role, key), from the cache when present."""
        # The device fixes the precision (bf16/fp16 on CUDA, float32 on CPU), so it is part of the key.
        digest = hashlib.sha256(f"{VERSION}|{role}|{self._identity(role)}|{self.device}|{key}".encode()
                                ).hexdigest()[:16]
        path = self.cache_dir / f"{sample_id}-{role}-{digest}.npz" if self.cache_dir is not None else None
        if path is not None and path.exists():
            with np.load(path, allow_pickle=False) as z:
                return {k: z[k] for k in z.files}
        t0 = time.time()
        arrays = compute()
        self.runs[role] += 1
        log.info("%s: %s took %.1f s", sample_id, role, time.time() - t0)
        if path is not None:
            path.parent.mkdir(parents=True, exist_ok=True)
            for stale in path.parent.glob(f"{sample_id}-{role}-*.npz"):
                stale.unlink()
            tmp = path.with_name(path.name + ".tmp.npz")
            np.savez_compressed(tmp, **arrays)
            tmp.replace(path)
        return arrays

    # -- perception --------------------------------------------------------------------------

    def perceive(self, sample, video, prediction_path: Path) -> Perception:
        """sample: reference ``Sample``; video: generated ``Video`` at the reference resolution (native times)."""
        from ..metrics.background import detect_background_corners
        from .cotracker import query_points, track_points
        from .sam2 import propagate_masks

        frames = video.frames
        t, h, w = frames.shape[:3]
        if (w, h) != tuple(sample.resolution):
            raise PerceptionError(f"{prediction_path}: frames are {w}x{h} but reference {sample.sample_id} is "
                                  f"{sample.resolution[0]}x{sample.resolution[1]}; resize before perception")
        sid = sample.sample_id
        video_key = array_digest(frames, np.asarray(video.times_s, np.float64))
        masks0 = np.asarray(sample.masks[0][sample.active_indices], dtype=bool)
        masks = self._cached(sid, "sam2", array_digest(masks0) + video_key, lambda: {
            "masks": propagate_masks(self.model("sam2"), frames, masks0)})["masks"]
        queries = query_points(sample)
        corners = detect_background_corners(frames[0], masks[0]).astype(np.float32)
        points = np.concatenate([queries, corners]).astype(np.float32)
        tracked = self._cached(sid, "cotracker", array_digest(points) + video_key, lambda: dict(zip(
            ("tracks", "visible", "confidence"), track_points(self.model("cotracker"), frames, points))))
        disparity = self._cached(sid, "depth", f"{self.depth_model}|{self.depth_input_size}|{video_key}",
                                 lambda: {"disparity": self._disparity(frames)})["disparity"]
        n_query = queries.shape[0]
        return Perception(
            times_s=np.asarray(video.times_s, np.float64), masks=masks.astype(bool),
            tracks=tracked["tracks"][:n_query].astype(np.float32),
            visibility=tracked["visible"][:n_query].astype(bool),
            track_actor=np.asarray(sample.track_active_index, dtype=np.int64),
            disparity=disparity.astype(np.float32), bg_tracks=tracked["tracks"][n_query:].astype(np.float32),
            bg_confidence=np.clip(tracked["confidence"][n_query:], 0.0, 1.0).astype(np.float32))

    def _disparity(self, frames: np.ndarray) -> np.ndarray:
        """frames (T,H,W,3) uint8 -> (T,H,W) float32 relative disparity on the frame grid."""
        from ..video import resize_maps

        model = self.model("depth")
        if self.depth_model == "vda":
            from .video_depth import video_disparity

            out = video_disparity(model, frames, input_size=self.depth_input_size)
        else:
            from .depth_anything_v2 import frame_disparity

            out = frame_disparity(model, frames, input_size=self.depth_input_size)
        h, w = frames.shape[1:3]
        out = np.asarray(out, dtype=np.float32)
        if out.shape[0] != frames.shape[0]:
            raise PerceptionError(f"depth model returned {out.shape[0]} maps for {frames.shape[0]} frames")
        return resize_maps(out, (w, h), "bilinear")
