"""Scores against the physical envelope; formulas in docs/statistics.md ("Scores against the envelope").

The envelope of an example and measurement is the distribution of that measurement over N physical twins
(the reference re-simulated with its initial state and materials perturbed within what one frame cannot
resolve), each scored against the reference like a model. Arrays arrive as ``twins`` (E, N): E examples,
N twins each, and a model's ``samples`` (E, K): K samples each; NaN marks a missing value.

Missing values: a non-finite twin is omitted; an example with fewer than 2 finite twins has no envelope for
that measurement (every output NaN); a model's value is the mean of its finite samples
(``samples.per_example_means``), and an example without one has quantiles but no position, excess or
inside. Quantiles are numpy's ``"linear"`` method (Hyndman and Fan type 7): for the n sorted finite twins
x_0 <= ... <= x_{n-1}, q(p) = x_j + (h - j)(x_{j+1} - x_j) with h = (n - 1) p, j = floor(h).

Numpy only; pure functions, no randomness.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Mapping, Sequence

import numpy as np

from rigidbench.stats.samples import per_example_means

#: The quantiles of the twins' distribution reported: lower edge, centre, upper edge.
LOWER, CENTRE, UPPER = 0.05, 0.5, 0.95
QUANTILE_METHOD = "linear"  # numpy's default, Hyndman and Fan type 7
MIN_TWINS = 2  # fewer finite twins: no envelope


def _as_2d(arr, name: str) -> np.ndarray:
    out = np.asarray(arr, dtype=np.float64)
    if out.ndim != 2:
        raise ValueError(f"{name} must have shape (examples, values), got shape {out.shape}")
    return out


@dataclass(frozen=True)
class EnvelopeScores:
    """One measurement's envelope and a model's place in it, per example (arrays of shape (E,) unless said).

    q05, median, q95: the twins' quantiles (NaN: no envelope); twins: finite twins per example (int);
    value: the model's per-example mean of finite samples; position: the fraction of finite twins the value
    beats (ties count one half), 0..1; sample_positions (E, K): the same for each sample; bound: the envelope's
    worse-side bound, q95 (q05 for a higher-is-better measurement) or the measurement's floor on the example when
    that is worse (``score_against_envelope``); excess: how far the value lies beyond ``bound`` (0 inside or on the
    better side); inside: 1.0 when the excess is 0, 0.0 when not, NaN when undefined (no envelope or no value)."""

    q05: np.ndarray
    median: np.ndarray
    q95: np.ndarray
    twins: np.ndarray
    value: np.ndarray
    position: np.ndarray
    sample_positions: np.ndarray
    excess: np.ndarray
    inside: np.ndarray
    bound: np.ndarray | None = None

    @property
    def has_envelope(self) -> np.ndarray:
        """(E,) bool: the example has at least MIN_TWINS finite twins."""
        return self.twins >= MIN_TWINS

    @property
    def scored(self) -> np.ndarray:
        """(E,) bool: the example has an envelope and a finite model value (it counts in the summaries)."""
        return np.isfinite(self.inside)


def twin_quantiles(twins) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """twins: (E, N) float, NaN missing. Returns (q05, median, q95, n_finite), each (E,); the quantiles are
    NaN where an example has fewer than MIN_TWINS finite twins."""
    arr = _as_2d(twins, "twins")
    finite = np.isfinite(arr)
    n = finite.sum(axis=1)
    out = np.full((3, arr.shape[0]), np.nan)
    for e in np.flatnonzero(n >= MIN_TWINS):
        out[:, e] = np.quantile(arr[e, finite[e]], (LOWER, CENTRE, UPPER), method=QUANTILE_METHOD)
    return out[0], out[1], out[2], n.astype(np.int64)


def positions(twins, values, higher_is_better: bool) -> np.ndarray:
    """twins: (E, N); values: (E,) or (E, K). Returns the fraction of each example's finite twins that a value
    beats (strictly better: lower for a lower-is-better measurement), ties counting one half, with the shape
    of ``values``; NaN for a non-finite value or an example with fewer than MIN_TWINS finite twins."""
    arr = _as_2d(twins, "twins")
    vals = np.asarray(values, dtype=np.float64)
    flat = vals[:, None] if vals.ndim == 1 else vals
    if flat.ndim != 2 or flat.shape[0] != arr.shape[0]:
        raise ValueError(f"values must have shape ({arr.shape[0]},) or ({arr.shape[0]}, K), got {vals.shape}")
    finite = np.isfinite(arr)[:, None, :]
    t, v = arr[:, None, :], flat[:, :, None]
    better = (t < v) if higher_is_better else (t > v)
    ties = t == v
    n = finite.sum(axis=-1)
    with np.errstate(invalid="ignore", divide="ignore"):
        pos = ((better & finite).sum(axis=-1) + 0.5 * (ties & finite).sum(axis=-1)) / n
    pos = np.where((n >= MIN_TWINS) & np.isfinite(flat), pos, np.nan)
    return pos[:, 0] if vals.ndim == 1 else pos


def excess(values, q05, q95, higher_is_better: bool) -> np.ndarray:
    """How far each value lies beyond the envelope on the worse side: lower is better: max(0, value - q95);
    higher is better: max(0, q05 - value). NaN where a value or the quantile is NaN."""
    v = np.asarray(values, dtype=np.float64)
    gap = (np.asarray(q05, dtype=np.float64) - v) if higher_is_better else (v - np.asarray(q95, dtype=np.float64))
    return np.where(np.isnan(gap), np.nan, np.maximum(gap, 0.0))


def inside(values, q05, q95, higher_is_better: bool) -> np.ndarray:
    """1.0 where the value is no worse than the envelope allows (lower-is-better: value <= q95; higher-is-better:
    value >= q05), i.e. its excess is 0; 0.0 where not; NaN where any of the three is NaN. One-sided: a value
    better than every twin (the reference itself scores 0 on a distance) is inside, not outside."""
    v, lo, hi = (np.asarray(a, dtype=np.float64) for a in (values, q05, q95))
    flag = ((v >= lo) if higher_is_better else (v <= hi)).astype(np.float64)
    return np.where(np.isnan(v) | np.isnan(lo) | np.isnan(hi), np.nan, flag)


def worse_bound(q05, q95, floor, higher_is_better: bool) -> np.ndarray:
    """The envelope's bound on the worse side: q95 (lower is better) or q05 (higher is better), or the
    measurement's floor on the example (what it gives the reference itself, scored as a model) where that is
    worse; a NaN floor is ignored. A measurement that reconstructs what it compares (ATE-3D from depth and
    masks) does not give the reference 0, and an error the measurement makes on a perfect prediction is no
    physical error."""
    lo, hi = np.asarray(q05, np.float64), np.asarray(q95, np.float64)
    if floor is None:
        return lo if higher_is_better else hi
    f = np.broadcast_to(np.asarray(floor, np.float64), hi.shape)
    with np.errstate(invalid="ignore"):
        if higher_is_better:
            return np.where(np.isnan(lo), np.nan, np.fmin(lo, f))
        return np.where(np.isnan(hi), np.nan, np.fmax(hi, f))


def score_against_envelope(twins, samples, higher_is_better: bool, floor=None) -> EnvelopeScores:
    """twins: (E, N) the twins' scores of one measurement; samples: (E, K) the model's scores of the same
    examples (NaN: missing; pad examples with fewer samples with NaN); floor: (E,) the measurement's value for
    the reference itself on each example (NaN or None: not known), which the worse-side bound never goes
    below (``worse_bound``). Returns an ``EnvelopeScores``."""
    arr = _as_2d(twins, "twins")
    smp = _as_2d(samples, "samples")
    if smp.shape[0] != arr.shape[0]:
        raise ValueError(f"twins and samples must have the same examples, got {arr.shape[0]} and {smp.shape[0]}")
    q05, med, q95, n = twin_quantiles(arr)
    value = per_example_means(smp)
    bound = worse_bound(q05, q95, floor, higher_is_better)
    lo, hi = (bound, q95) if higher_is_better else (q05, bound)
    return EnvelopeScores(q05=q05, median=med, q95=q95, twins=n, value=value,
                          position=positions(arr, value, higher_is_better),
                          sample_positions=positions(arr, smp, higher_is_better),
                          excess=excess(value, lo, hi, higher_is_better), inside=inside(value, lo, hi, higher_is_better),
                          bound=bound)


def summarize(scores: EnvelopeScores, mask=None) -> dict:
    """Over the examples with an envelope and a model value (and in ``mask``, an (E,) bool, when given): the
    share inside the envelope, the mean excess (None when no example counts) and their number n."""
    keep = scores.scored if mask is None else scores.scored & np.asarray(mask, dtype=bool)
    n = int(keep.sum())
    return {"inside": float(scores.inside[keep].mean()) if n else None,
            "excess": float(scores.excess[keep].mean()) if n else None, "n": n}


def summarize_by(scores: EnvelopeScores, groups: Sequence[str]) -> dict[str, dict]:
    """``summarize`` per group label (one per example, e.g. its task), sorted by label."""
    labels = np.asarray(list(groups), dtype=object)
    return {g: summarize(scores, labels == g) for g in sorted(set(labels.tolist()))}


def width_table(bands: Mapping[str, tuple[np.ndarray, np.ndarray]], groups: Sequence[str]) -> dict[str, dict]:
    """bands: measurement -> (q05, q95), each (E,); groups: one label per example (its task). Returns
    {label: {measurement: median over the label's examples with an envelope of q95 - q05, or None}}."""
    labels = np.asarray(list(groups), dtype=object)
    table: dict[str, dict] = {}
    for g in sorted(set(labels.tolist())):
        row = {}
        for metric, (lo, hi) in bands.items():
            width = (np.asarray(hi, dtype=np.float64) - np.asarray(lo, dtype=np.float64))[labels == g]
            width = width[np.isfinite(width)]
            row[metric] = float(np.median(width)) if width.size else None
        table[g] = row
    return table
