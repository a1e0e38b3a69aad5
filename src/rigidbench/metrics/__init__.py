"""The ten RigidBench measurements as pure functions over arrays, and their registry.

``METRICS`` holds one ``MetricInfo`` per measurement, in the paper's table order: its compute
function (``target``, "module:attr" of ``compute(MetricInputs) -> MetricResult | None``, imported
on first use so this package pulls in neither torch nor OpenCV), display name, direction, group,
display scale and the failure modes whose response curve ``validate-metrics`` draws for it.
Evaluation, the demo table, ``validate-metrics`` and the report all read the metric list from here;
adding a metric is one module with its compute function plus one ``METRICS.add(...)``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

from rigidbench.metrics.common import MetricResult
from rigidbench.metrics.inputs import MetricInputs
from rigidbench.registry import LazyRegistry

__all__ = ["METRICS", "GROUPS", "MetricInfo", "MetricInputs", "MetricResult", "get_metric"]

#: metric group -> heading in tables (the paper's two blocks)
GROUPS = {"motion": "Object motion and geometry", "appearance": "Visual similarity and stability"}


@dataclass(frozen=True)
class MetricInfo:
    """Registry entry of one measurement.

    target: "module:attr" of compute(MetricInputs) -> MetricResult (None: skipped); group: a key of
    GROUPS; display_scale: factor applied in report tables (BGDrift is shown x10^3); curve_modes:
    failure modes meant to move it, in order of preference (validate-metrics' response curve);
    control_modes: failure modes it must not respond to, drawn beside the main curve."""

    name: str
    target: str
    display_name: str
    higher_is_better: bool
    group: str
    summary: str
    curve_modes: tuple[str, ...] = ()
    control_modes: tuple[str, ...] = ()
    display_scale: float = 1.0
    aliases: tuple[str, ...] = ()

    @property
    def direction(self) -> str:
        return "higher" if self.higher_is_better else "lower"

    @property
    def arrow(self) -> str:
        return "\u2191" if self.higher_is_better else "\u2193"

    def load(self) -> Callable[[MetricInputs], MetricResult | None]:
        """Import and return this metric's compute function."""
        return METRICS.load(self.name)


METRICS: LazyRegistry[MetricInfo] = LazyRegistry("metric")


def _builtin(name: str, display: str, higher: bool, group: str, target: str, summary: str, curve: tuple[str, ...],
             control: tuple[str, ...] = (), scale: float = 1.0, aliases: tuple[str, ...] = ()) -> None:
    METRICS.add(MetricInfo(name, f"rigidbench.metrics.{target}", display, higher, group, summary, curve, control,
                           scale, (display, *aliases)))


_builtin("iou", "IoU", True, "motion", "masks:score_iou", "per-actor mask IoU, empty union = 1; actors then frames",
         ("slow",))
_builtin("centroid_l2", "L2", False, "motion", "masks:score_centroid_l2",
         "mask-centroid distance / H; empty actor-frames omitted", ("slow",), aliases=("centroid",))
_builtin("chamfer", "Cham.", False, "motion", "masks:score_chamfer",
         "bidirectional mean nearest-pixel distance / H", ("slow",))
_builtin("ate", "ATE", False, "motion", "tracks:score_ate", "mean track distance / H over jointly visible point-frames",
         ("slow",))
_builtin("ate3d", "ATE-3D", False, "motion", "depth:score_ate3d",
         "actor-position RMSE / mean displacement of moving actors", ("depth-offset", "slow"))
_builtin("si_mse", "SI-MSE", False, "motion", "depth:score_si_mse", "per-frame variance of the log-depth residual",
         ("depth-offset", "camera-shake"))
_builtin("ssim", "SSIM", True, "appearance", "appearance:score_ssim", "mean frame SSIM, data range 255", ("gamma",))
_builtin("lpips", "LPIPS", False, "appearance", "appearance:score_lpips", "mean frame LPIPS, AlexNet backbone",
         ("gamma",))
_builtin("iddrift", "IdDrift", False, "appearance", "identity:score_iddrift",
         "1 - patch feature cosine similarity, actors equal weight", ("identity-swap", "gamma"))
_builtin("bgdrift", "BGDrift", False, "appearance", "background:score_bgdrift",
         "weighted residual of background corners after RANSAC / H", ("background-wobble",), ("camera-shake",),
         scale=1e3)


def get_metric(name: str) -> MetricInfo:
    """The registry entry for a metric name or display name (case-insensitive); UnknownNameError
    (a KeyError) with the nearest names otherwise."""
    return METRICS[name]
