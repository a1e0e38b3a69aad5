"""The ten RigidBench measurements as pure functions over arrays, and their registry.

`METRICS` maps each metric name, in the paper's table order, to a `MetricInfo` with its
display name, direction and the function computing it (loaded lazily from "module:attr",
so importing this package pulls in neither torch nor OpenCV). Every function returns a
`MetricResult(value, per_frame)`; callers pass only active actors, with all arrays already
cut to the common length T of the two clips.
"""

from __future__ import annotations

import difflib
import importlib
from dataclasses import dataclass
from types import MappingProxyType
from typing import Callable

from rigidbench.metrics.common import MetricResult

__all__ = ["METRICS", "MetricInfo", "MetricResult", "get_metric"]


@dataclass(frozen=True)
class MetricInfo:
    """Registry entry: `target` is "module:function" returning a MetricResult."""

    name: str
    display_name: str
    higher_is_better: bool
    target: str
    summary: str

    @property
    def direction(self) -> str:
        return "higher" if self.higher_is_better else "lower"

    def load(self) -> Callable[..., MetricResult]:
        """Import and return the function that computes this metric."""
        module, attr = self.target.split(":")
        return getattr(importlib.import_module(module), attr)


def _entry(name: str, display: str, higher: bool, target: str, summary: str) -> tuple[str, MetricInfo]:
    return name, MetricInfo(name, display, higher, f"rigidbench.metrics.{target}", summary)


METRICS: MappingProxyType[str, MetricInfo] = MappingProxyType(dict([
    _entry("iou", "IoU", True, "masks:iou", "per-actor mask IoU, empty union = 1; actors then frames"),
    _entry("centroid_l2", "L2", False, "masks:centroid_l2", "mask-centroid distance / H; empty actor-frames omitted"),
    _entry("chamfer", "Cham.", False, "masks:chamfer", "bidirectional mean nearest-pixel distance / H"),
    _entry("ate", "ATE", False, "tracks:ate", "mean track distance / H over jointly visible point-frames"),
    _entry("ate3d", "ATE-3D", False, "depth:ate3d", "actor-position RMSE / mean displacement of moving actors"),
    _entry("si_mse", "SI-MSE", False, "depth:si_mse", "per-frame variance of the log-depth residual"),
    _entry("ssim", "SSIM", True, "appearance:ssim", "mean frame SSIM, data range 255"),
    _entry("lpips", "LPIPS", False, "appearance:lpips", "mean frame LPIPS, AlexNet backbone"),
    _entry("iddrift", "IdDrift", False, "identity:iddrift", "1 - patch feature cosine similarity, actors equal weight"),
    _entry("bgdrift", "BGDrift", False, "background:bgdrift", "weighted residual of background corners after RANSAC / H"),
]))


def get_metric(name: str) -> MetricInfo:
    """Return the registry entry for a metric name or display name (case-insensitive)."""
    lookup = {key: info for info in METRICS.values() for key in (info.name, info.display_name.lower())}
    info = lookup.get(name.lower())
    if info is None:
        close = difflib.get_close_matches(name.lower(), list(lookup), n=1)
        hint = f" Did you mean '{lookup[close[0]].name}'?" if close else ""
        raise KeyError(f"unknown metric '{name}'.{hint} Known metrics: {', '.join(METRICS)}")
    return info
