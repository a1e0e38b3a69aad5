"""What every readout is computed from: the metrics' ``MetricInputs`` plus the few facts of the
reference that physics needs and the metrics do not (frame rate, the whole reference trajectory,
which actors start in free flight, support height and actor sizes, simulated parameters).

``context_from_sample`` builds one from a reference bundle, the example's ``MetricInputs`` and its
scores (IdDrift feeds the identity flag). A bundle imported from the published set has no scene
spec: support height, actor sizes and simulated parameters are then NaN, and the readouts that need
them say so.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Callable

import numpy as np

from rigidbench.errors import BundleError
from rigidbench.metrics.inputs import MetricInputs

#: the scene gravity of Blender's default, which the authors' release never changes (its published set)
BLENDER_DEFAULT_GRAVITY_M_S2 = 9.81


@dataclass
class ReadoutContext:
    """One example's readout inputs (N active actors, T compared frames, T_ref reference frames).

    inputs: the example's MetricInputs (generated and reference arrays cut to T frames); fps: frame
    rate of both; ref_positions_m (N,T_ref,3): simulated positions over the whole reference (a fast
    clip shows later reference frames than its own length); free_at_start (N,) bool: the actor touches
    nothing at frame 0 in the reference (its first flight is ballistic); support_top_m: height of the
    support's top face (NaN: unknown); actor_radius_m (N,): half the smallest side of each actor's
    box (NaN: unknown); gravity_m_s2 and restitution_nominal (N,) (actor x support, as Bullet
    multiplies them): the simulated parameters (NaN: unknown); iddrift: the example's IdDrift
    (None: not computed); task, actor_names: labels."""

    inputs: MetricInputs
    fps: float
    ref_positions_m: np.ndarray
    free_at_start: np.ndarray
    support_top_m: float = float("nan")
    actor_radius_m: np.ndarray | None = None
    gravity_m_s2: float = float("nan")
    restitution_nominal: np.ndarray | None = None
    iddrift: float | None = None
    task: str = ""
    actor_names: tuple[str, ...] = ()
    _shared: dict[str, Any] = field(default_factory=dict, repr=False)

    def __post_init__(self):
        n = self.n_actors
        if self.actor_radius_m is None:
            self.actor_radius_m = np.full(n, np.nan)
        if self.restitution_nominal is None:
            self.restitution_nominal = np.full(n, np.nan)
        if not self.actor_names:
            self.actor_names = tuple(f"actor_{a}" for a in range(n))

    @property
    def n_actors(self) -> int:
        return int(np.asarray(self.ref_positions_m).shape[0])

    @property
    def n_frames(self) -> int:
        return int(self.inputs.gen_tracks.shape[1])

    @property
    def times_s(self) -> np.ndarray:
        return np.arange(self.n_frames) / float(self.fps)

    def shared(self, key: str, compute: Callable[[], Any]) -> Any:
        """``compute()`` once per example, whichever readout asks first."""
        if key not in self._shared:
            self._shared[key] = compute()
        return self._shared[key]

    def reference_shared(self, key: str, compute: Callable[[], Any]) -> Any:
        """``compute()`` of a quantity of the reference alone (its trajectory, its masks), once for all the
        samples of an example when the evaluator shares the reference side (``MetricInputs.reference_shared``)."""
        return self.inputs.reference_shared(f"readout:{key}", compute)


def context_from_sample(sample, inputs: MetricInputs, iddrift: float | None = None) -> ReadoutContext:
    """The ReadoutContext of reference bundle ``sample`` and one generated clip's ``inputs``."""
    active = [int(a) for a in sample.active_indices]
    names = tuple(sample.actor_names[a] for a in active)
    positions = np.asarray(sample.trajectory.positions_m, np.float64)[active]
    touching0 = {n for c in sample.contacts if c.frame == 0 for n in (c.a, c.b)}
    free = np.array([n not in touching0 for n in names], bool)
    support_top = radius = gravity = restitution = None
    try:
        spec = sample.spec
    except BundleError:  # an imported bundle has no scene spec: the readouts needing it are NaN
        spec = None
        if sample.imported:  # the published set was simulated with Blender's default gravity (the release sets none)
            gravity = BLENDER_DEFAULT_GRAVITY_M_S2
    if spec is not None:
        bodies = {b.name: b for b in spec.bodies}
        support_top = float(spec.support.centre_m[2])
        radius = np.array([0.5 * min(bodies[n].size_m) if n in bodies else np.nan for n in names])
        gravity = float(spec.sim.gravity_m_s2)
        e_support = float(spec.support.physics.restitution)
        restitution = np.array([bodies[n].physics.restitution * e_support if n in bodies else np.nan for n in names])
    return ReadoutContext(inputs=inputs, fps=float(sample.fps), ref_positions_m=positions, free_at_start=free,
                          support_top_m=float("nan") if support_top is None else support_top,
                          actor_radius_m=radius, gravity_m_s2=float("nan") if gravity is None else gravity,
                          restitution_nominal=restitution,
                          iddrift=None if iddrift is None or not np.isfinite(iddrift) else float(iddrift),
                          task=str(sample.task), actor_names=names)
