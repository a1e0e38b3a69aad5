"""What every measurement is computed from: one example's reference and generated arrays, aligned.

The evaluator builds one ``MetricInputs`` per example (reference bundle + perception of the
generated clip, both cut to the T frames they share) and hands it to every registered metric's
``compute(inputs) -> MetricResult | None`` (None: skipped, e.g. its feature network is missing).
A metric of your own reads the fields it needs; quantities several metrics share (the disparity
alignment) are computed once through ``shared``; quantities of the reference alone (its depth's valid pixels,
its mask centroids) through ``reference_shared``, once for all the samples of an example.
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
    "published" (``common.EDGE_RULES``; the evaluation protocol decides it); skipped: measurements not to compute
    for this example, each with the reason (a geometry-only twin's clip has no RGB to compare); reference_cache:
    where quantities of the reference alone are kept for the other samples of the example (``reference_shared``;
    None: kept with these inputs only); reference_samples: how many samples of the example are scored against
    it (the evaluator's count): a large reference-side quantity (SSIM's filtered reference) is kept only for more
    than one.
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
    skipped: dict[str, str] = field(default_factory=dict)
    reference_cache: dict[str, Any] | None = field(default=None, repr=False)
    reference_samples: int = 1
    _shared: dict[str, Any] = field(default_factory=dict, repr=False)
    _reference: dict[str, Any] = field(default_factory=dict, repr=False)  # reference_shared without a cache

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

    def reference_shared(self, key: str, compute: Callable[[], Any]) -> Any:
        """``compute()`` of a quantity of the reference arrays alone (as cut to these T frames), once per
        reference: kept in ``reference_cache`` when the evaluator shares one between the samples of an example
        (``evaluation.reference_side``), else once per example like ``shared``. ``compute`` must read nothing
        generated."""
        store = self._reference if self.reference_cache is None else self.reference_cache
        key = f"reference:{key}:{self.n_frames}"
        if key not in store:
            store[key] = compute()
        return store[key]
