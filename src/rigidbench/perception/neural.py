"""Neural perception: what the metrics need, estimated from any generated video (paper, appendix B.2).

Run as the published evaluation (the authors' RigidBench release, ``eval/track/*.py`` and
``eval/score/background.py``) ran each model:

- masks: SAM 2.1 Hiera Large, prompted with each active actor's frame-0 reference mask and
  propagated through the generated clip, logits > 0 (``sam2``), float32;
- tracks: CoTracker3 offline from the reference's ground-truth query points (the same points as
  the ground-truth tracks) on the whole generated clip at its own frame times; ``visibility`` is
  the generated clip's own visibility (the offline predictor's visibility > 0.9), the metrics
  AND it with the reference's; ``confidence`` is CoTracker3's confidence head (``cotracker``);
- disparity: Video Depth Anything Large on the whole generated clip (``video_depth``;
  ``depth_model="dav2"`` selects Depth Anything V2 per frame), bilinearly resized to the frame
  grid when needed;
- background: the clip resampled to the reference times (linear in time, ``video.align_video``)
  and cut to the reference length; Shi-Tomasi corners of its frame 0 outside the generated
  frame-0 masks (15-pixel erosion), tracked by a SECOND CoTracker3 call on that resampled clip
  (never together with the actor points: CoTracker3 attends across all tracks of a call); the
  0/1 visibility of each corner is its BGDrift weight.

What can be cut is cut: the arrays returned stop at the first generated frame at or after the
last reference time the clip covers (``video.frames_until``, what ``read_video(until_s=...)``
decodes), and SAM 2 (causal: a frame's mask depends only on the frames before it) sees only those
frames. CoTracker3 offline (time attention over the whole clip, a time embedding sized to it) and
Video Depth Anything (32-frame windows reaching past the cut, stitched across windows) see the
whole decoded clip, because the published runs gave them every generated frame and their output
at early times depends on later frames; decoding a clip only up to the reference length changes
actor tracks and disparity near its end.

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

from ..atomic import atomic_file
from ..extras import available, missing
from ..metrics.background import detect_background_corners
from ..video import REFERENCE_FPS, Video, align_video, aligned_length, frames_until, reference_times, resize_maps
from . import weights
from .base import Perception, PerceptionError
from .cotracker import load_cotracker, query_points, track_points
from .depth_anything_v2 import frame_disparity, load_depth_anything_v2
from .device import resolve_device
from .sam2 import load_sam2, propagate_masks
from .video_depth import load_video_depth_anything, video_disparity

log = logging.getLogger(__name__)

VERSION = "2"  # 2: offline visibility rule, two CoTracker3 calls, background on the resampled clip, SAM 2 fp32
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
    whole_clip = True  # CoTracker3 offline and VDA see every generated frame, as in the published runs

    def __init__(self, depth_model: str = "vda", device: str | None = None, cache_dir: str | Path | None = None,
                 allow_download: bool = False, weights: dict[str, str] | None = None,
                 models: dict[str, object] | None = None, pretrained: bool = True,
                 depth_input_size: int = DEPTH_INPUT_SIZE):
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
        # model invocations (cache misses): "cotracker" the actor points, "background" the corners' call
        self.runs: dict[str, int] = {"sam2": 0, "cotracker": 0, "background": 0, "depth": 0}

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

        name = self._weight_name(role)
        found = weights.locate(name, self.weights.get(name))
        if role != "cotracker":
            return f"{name}:{found}"
        code = weights.locate("cotracker-code", self.weights.get("cotracker-code"))
        return f"{name}:{found if self.pretrained else 'random'}:{code}"

    def missing_weights(self) -> list[str]:
        """One message per weight file this backend would need but cannot find (nothing to fetch when empty);
        MissingExtra first when transformers, which runs SAM 2.1 and Depth Anything V2, is not installed."""
        names = [self._weight_name(r) for r in ("sam2", "cotracker", "depth") if r not in self._injected]
        for name in names:
            if name in ("sam2", "dav2") and not available("transformers"):
                raise missing("transformers", f"neural perception ({weights.spec(name).title})")
        if self.allow_download:
            return []
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
            return load_sam2(w.get("sam2"), device=self.device, allow_download=dl)
        if role == "cotracker":
            return load_cotracker(w.get("cotracker-code"), w.get("cotracker"), device=self.device,
                                  pretrained=self.pretrained, allow_download=dl)
        if self.depth_model == "vda":
            return load_video_depth_anything(w.get("vda"), device=self.device, allow_download=dl)
        return load_depth_anything_v2(w.get("dav2"), device=self.device, allow_download=dl)

    # -- cache -------------------------------------------------------------------------------

    def _cached(self, sample_id: str, role: str, key: str, compute: Callable[[], dict],
                label: str | None = None) -> dict[str, np.ndarray]:
        """The arrays ``compute`` returns for (role, key), from the cache when present. ``label`` names
        the output (cache file, ``runs`` counter) when one model makes several (default: ``role``)."""
        label = role if label is None else label
        # The device fixes the precision (fp16 autocast on CUDA, float32 on CPU), so it is part of the key.
        digest = hashlib.sha256(f"{VERSION}|{label}|{self._identity(role)}|{self.device}|{key}".encode()
                                ).hexdigest()[:16]
        path = self.cache_dir / f"{sample_id}-{label}-{digest}.npz" if self.cache_dir is not None else None
        if path is not None and path.exists():
            with np.load(path, allow_pickle=False) as z:
                return {k: z[k] for k in z.files}
        t0 = time.time()
        arrays = compute()
        self.runs[label] += 1
        log.info("%s: %s took %.1f s", sample_id, label, time.time() - t0)
        if path is not None:
            path.parent.mkdir(parents=True, exist_ok=True)
            for stale in path.parent.glob(f"{sample_id}-{label}-*.npz"):
                stale.unlink()
            with atomic_file(path, suffix=".npz") as tmp:
                np.savez_compressed(tmp, **arrays)
        return arrays

    # -- perception --------------------------------------------------------------------------

    def perceive(self, sample, video, prediction_path: Path) -> Perception:
        """sample: reference ``Sample``; video: generated ``Video`` at the reference resolution (native times).

        Returns the masks, tracks and disparity at the clip's own frame times up to the first frame
        at or after the last reference time it covers, and the background corners at those
        reference times.
        """
        frames = video.frames
        t, h, w = frames.shape[:3]
        if (w, h) != tuple(sample.resolution):
            raise PerceptionError(f"{prediction_path}: frames are {w}x{h} but reference {sample.sample_id} is "
                                  f"{sample.resolution[0]}x{sample.resolution[1]}; resize before perception")
        sid = sample.sample_id
        times = np.asarray(video.times_s, np.float64)
        ref_times = reference_times_of(sample)
        n_ref = aligned_length(times, ref_times)  # reference times this clip covers (the 49 frames, or fewer)
        if n_ref == 0:
            raise PerceptionError(f"{prediction_path}: the clip covers no reference time (its first frame is at "
                                  f"{times[0]:.3f} s); re-encode it with timestamps starting at 0")
        m = frames_until(times, ref_times[n_ref - 1])  # generated frames the alignment to those times uses
        video_key = array_digest(frames, times)
        head_key = video_key if m == t else array_digest(frames[:m], times[:m])

        # Masks: SAM 2 is causal, so the first m frames give the same masks as the whole clip.
        masks0 = np.asarray(sample.masks[0][sample.active_indices], dtype=bool)
        masks = self._cached(sid, "sam2", array_digest(masks0) + head_key, lambda: {
            "masks": propagate_masks(self.model("sam2"), frames[:m], masks0)})["masks"]

        # Actor points: one CoTracker3 call on every generated frame, as published.
        queries = query_points(sample)
        tracked = self._cached(sid, "cotracker", array_digest(queries) + video_key, lambda: dict(zip(
            ("tracks", "visible", "confidence"), track_points(self.model("cotracker"), frames, queries))))

        # Background corners: a second call, on the clip resampled to the reference times.
        bg_times = ref_times[:n_ref].copy()
        bg_frames = align_video(Video(frames[:m], times[:m]), bg_times)
        corners = detect_background_corners(bg_frames[0], masks[0]).astype(np.float32)
        background = self._cached(sid, "cotracker", array_digest(corners, bg_frames, bg_times), lambda: dict(zip(
            ("tracks", "visible", "confidence"), track_points(self.model("cotracker"), bg_frames, corners))),
            label="background")

        disparity = self._cached(sid, "depth", f"{self.depth_model}|{self.depth_input_size}|{video_key}",
                                 lambda: {"disparity": self._disparity(frames)})["disparity"]
        return Perception(
            times_s=times[:m].copy(), masks=masks.astype(bool),
            tracks=tracked["tracks"][:, :m].astype(np.float32),
            visibility=tracked["visible"][:, :m].astype(bool),
            confidence=np.clip(tracked["confidence"][:, :m], 0.0, 1.0).astype(np.float32),
            track_actor=np.asarray(sample.track_active_index, dtype=np.int64),
            disparity=disparity[:m].astype(np.float32), bg_times_s=bg_times,
            bg_tracks=background["tracks"].astype(np.float32),
            bg_confidence=background["visible"].astype(np.float32))

    def _disparity(self, frames: np.ndarray) -> np.ndarray:
        """frames (T,H,W,3) uint8 -> (T,H,W) float32 relative disparity on the frame grid."""
        model = self.model("depth")
        if self.depth_model == "vda":
            out = video_disparity(model, frames, input_size=self.depth_input_size)
        else:
            out = frame_disparity(model, frames, input_size=self.depth_input_size)
        h, w = frames.shape[1:3]
        out = np.asarray(out, dtype=np.float32)
        if out.shape[0] != frames.shape[0]:
            raise PerceptionError(f"depth model returned {out.shape[0]} maps for {frames.shape[0]} frames")
        return resize_maps(out, (w, h), "bilinear")


def reference_times_of(sample) -> np.ndarray:
    """The reference timestamps k / fps of ``sample`` (its frame count and rate; 49 at 24 Hz by default)."""
    n = getattr(sample, "n_frames", None)
    n = int(n) if n is not None else int(np.asarray(sample.masks).shape[0])
    return reference_times(n, float(getattr(sample, "fps", REFERENCE_FPS)))
