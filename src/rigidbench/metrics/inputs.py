"""What every measurement is computed from: one example's reference and generated arrays, aligned.

The evaluator builds one ``MetricInputs`` per example (reference bundle + perception of the
generated clip, both cut to the T frames they share) and hands it to every registered metric's
``compute(inputs) -> MetricResult | None`` (None: skipped, e.g. its feature network is missing).
A metric of your own reads the fields it needs; quantities several metrics share (the disparity
alignment) are computed once through ``shared``.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Callable

import numpy as np

from rigidbench.metrics.common import PAPER_RULES, EdgeRules, check_rules


@dataclass
class MetricInputs:
    """Aligned arrays of one example (T frames, N active actors, P tracked points, C background corners).

    ref_rgb, gen_rgb (T,H,W,3) uint8; ref_masks, gen_masks (T,N,H,W) bool; ref_tracks, gen_tracks
    (P,T,2) float px; ref_visibility, gen_visibility (P,T) bool; track_actor (P,) index into the N
    active actors; ref_depth_m (T,H,W) float (Cycles Z, m); gen_disparity (T,H,W) float (affine-
    invariant); K (3,3); camera_to_world (4,4); actor_positions_m (N,T,3) simulated body positions;
    ref_points_m (P,T,3) simulated world positions of the tracked surface points; bg_tracks (C,T,2) px,
    bg_confidence (C,T) in [0, 1]; lpips_net and identity_net the feature networks (None: unavailable);
    edge_rules: which rule set the metrics follow in the edge cases of docs/metrics.md, "paper" or
    "published" (``common.EDGE_RULES``; the evaluation protocol decides it).
    """

    ref_rgb: np.ndarray
    gen_rgb: np.ndarray
    ref_masks: np.ndarray
    gen_masks: np.ndarray
    ref_tracks: np.ndarray
    gen_tracks: np.ndarray
    ref_visibility: np.ndarray
    gen_visibility: np.ndarray
    track_actor: np.ndarray
    ref_depth_m: np.ndarray
    gen_disparity: np.ndarray
    K: np.ndarray
    camera_to_world: np.ndarray
    actor_positions_m: np.ndarray
    ref_points_m: np.ndarray
    bg_tracks: np.ndarray
    bg_confidence: np.ndarray
    lpips_net: Callable | None = None
    identity_net: Callable | None = None
    edge_rules: EdgeRules = PAPER_RULES
    _shared: dict[str, Any] = field(default_factory=dict, repr=False)

    def __post_init__(self) -> None:
        check_rules(self.edge_rules)

    @property
    def height(self) -> int:
        """Image height in pixels (the normaliser of every pixel distance)."""
        return int(self.ref_rgb.shape[1])

    @property
    def n_frames(self) -> int:
        return int(self.gen_rgb.shape[0])

    def shared(self, key: str, compute: Callable[[], Any]) -> Any:
        """``compute()`` once per example, whichever metric asks first."""
        if key not in self._shared:
            self._shared[key] = compute()
        return self._shared[key]
