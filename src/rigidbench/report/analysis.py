"""Every statistic the report shows, computed once from a ScoreTable (paper section 4, appendix C).

Model means carry 95% percentile bootstrap intervals over examples; paired changes and the
probability of improvement (ties count one half) compare each model with a baseline on matched
examples; the SSIM / ATE-3D correlation resamples models. All intervals come from
`rigidbench.stats` with the same resample count and seed, so each one equals what calling
`bootstrap_ci` on that model's (or pair's) per-example scores gives.

With several samples per example every per-example score is that example's sample mean (report/load.py), so the intervals, paired changes and probabilities of improvement all resample examples, each keeping
its samples; the seed std, best of K and power table are computed beside them, and the envelope's share
inside and mean excess where a run was scored against a physical envelope.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from rigidbench.metrics import METRICS
from rigidbench.report.load import ReportError, ScoreTable
from rigidbench.report.samples import (
    EnvelopeStats,
    PowerComparison,
    SampleScores,
    SampleStats,
    envelope_stats,
    power_comparisons,
    sample_stats,
)
from rigidbench.stats import (
    PairwiseMatrix,
    bootstrap_ci,
    correlation_across_models,
    improvement_indicators,
    probability_of_improvement_matrix,
)

log = logging.getLogger(__name__)

# Runs shown in every table but left out of the best / second-best marks: the reference scored
# against itself is the measurement floor, not a contestant.
UNRANKED_NAMES = ("reference",)
TASK_ORDER = ("ball_chain", "ramp_collision", "drop_into_cluster", "bounce", "free_fall")
PARTITION_LABELS = {"in_distribution": "ID", "ood_scene": "Scene", "ood_object": "Object", "ood_both": "Both"}


@dataclass(frozen=True)
class Intervals:
    """mean, lo, hi: float64 arrays of one shape (NaN where undefined); n_finite: int64 of that shape."""

    mean: np.ndarray
    lo: np.ndarray
    hi: np.ndarray
    n_finite: np.ndarray


@dataclass(frozen=True)
class ReportData:
    """Statistics over a ScoreTable; model axis first everywhere, metrics in `table.metrics` order."""

    table: ScoreTable
    overall: Intervals            # (M, K)
    tasks: tuple[str, ...]
    by_task: Intervals            # (M, T, K)
    partitions: tuple[str, ...]
    by_partition: Intervals       # (M, P, K)
    baseline: int
    paired_diff: Intervals        # (M, K) model minus baseline; NaN on the baseline row
    paired_poi: Intervals         # (M, K) PoI of model over baseline; NaN on the baseline row
    poi_matrices: tuple[PairwiseMatrix, ...]  # one (M, M) matrix per metric; empty with one model
    correlation: dict | None      # SSIM vs negative ATE-3D across model means
    ranked: np.ndarray            # (M,) bool: takes part in best / second-best marks
    resamples: int
    seed: int
    samples: SampleStats | None = None        # some run has several samples per example
    power: tuple[PowerComparison, ...] = ()   # with several samples: the power table's comparisons
    envelope: EnvelopeStats | None = None     # some run was scored against a physical envelope
    envelope_metric: str = "ate3d"            # the measurement of the envelope figure


def higher_is_better(metrics: tuple[str, ...]) -> np.ndarray:
    """metrics: K registry names. Returns (K,) bool direction per metric."""
    return np.array([METRICS[name].higher_is_better for name in metrics])


def intervals(scores: np.ndarray, resamples: int, seed: int) -> Intervals:
    """scores: (..., N, K) float64 per-example values. Returns Intervals of shape (..., K)."""
    per_row = np.moveaxis(scores, -2, -1)  # (..., K, N)
    mean, lo, hi = bootstrap_ci(per_row, n_resamples=resamples, seed=seed)
    return Intervals(np.asarray(mean), np.asarray(lo), np.asarray(hi), np.isfinite(per_row).sum(axis=-1))


def group_intervals(scores: np.ndarray, labels: np.ndarray, groups: tuple[str, ...], resamples: int,
                    seed: int) -> Intervals:
    """scores: (M, N, K); labels: (N,) str group per example. Returns Intervals of shape (M, G, K)."""
    parts = [intervals(scores[:, labels == g], resamples, seed) for g in groups]
    return Intervals(*(np.stack([getattr(p, f) for p in parts], axis=1) for f in ("mean", "lo", "hi", "n_finite")))


def ordered_groups(labels: np.ndarray, preferred: tuple[str, ...]) -> tuple[str, ...]:
    """labels: (N,) str. Returns the distinct labels, those in `preferred` first in its order, then sorted."""
    present = set(labels.tolist())
    return tuple(g for g in preferred if g in present) + tuple(sorted(present - set(preferred)))


def task_label(task: str) -> str:
    """'drop_into_cluster' -> 'Drop into cluster' (the paper's spelling)."""
    return task.replace("_", " ").capitalize()


def partition_label(partition: str) -> str:
    """'ood_scene' -> 'Scene' as in the paper's partition tables; unknown ids pass through."""
    return PARTITION_LABELS.get(partition, partition)


def paired_vs_baseline(scores: np.ndarray, baseline: int, hib: np.ndarray, resamples: int,
                       seed: int) -> tuple[Intervals, Intervals]:
    """scores: (M, N, K); hib: (K,) bool. Returns (model - baseline, PoI of model over baseline), each (M, K)."""
    base = scores[baseline]
    with np.errstate(invalid="ignore"):
        diff = scores - base[None]
    wins = np.stack([improvement_indicators(scores[:, :, k], np.broadcast_to(base[:, k], scores.shape[:2]), hib[k])
                     for k in range(scores.shape[-1])], axis=-1)
    out = []
    for per_example in (diff, wins):
        iv = intervals(per_example, resamples, seed)
        for field in (iv.mean, iv.lo, iv.hi):
            field[baseline] = np.nan
        iv.n_finite[baseline] = 0
        out.append(iv)
    return out[0], out[1]


def choose_baseline(models: tuple[str, ...], requested: str | None) -> int:
    """Index of the baseline model: `requested`, else the first run not named 'reference'."""
    if requested is not None:
        if requested not in models:
            raise ReportError(f"baseline '{requested}' is not one of the runs ({', '.join(models)}); "
                              "pass --baseline with one of these model names")
        return models.index(requested)
    for i, name in enumerate(models):
        if name not in UNRANKED_NAMES:
            return i
    return 0


def rank_marks(means: np.ndarray, higher: bool, eligible: np.ndarray, decimals: int | None = None,
               scale: float = 1.0) -> list[str]:
    """means: (M,) float; eligible: (M,) bool. Returns M marks 'best' / 'second' / ''.

    Only a unique value is marked: 'best' for the one eligible finite mean strictly better than every
    other, 'second' for the one strictly better than all but the best. A tie takes no mark (two
    tied zeros are not both 'best'), and nothing below a tie is marked. With `decimals`, means are
    compared as printed (rounded after multiplying by `scale`), so values that read the same tie.
    """
    means = np.asarray(means, dtype=np.float64)
    ok = np.asarray(eligible, dtype=bool) & np.isfinite(means)
    shown = np.round(means * scale, decimals) if decimals is not None else means
    signed = np.where(ok, shown if higher else -shown, np.nan)  # larger is better
    marks = [""] * len(means)
    if ok.sum() < 2:
        return marks
    order = sorted(np.flatnonzero(ok), key=lambda i: -signed[i])
    values = [signed[i] for i in order]
    if values[0] > values[1]:
        marks[order[0]] = "best"
        if len(values) > 2 and values[1] > values[2]:
            marks[order[1]] = "second"
    return marks


def best_first_order(means: np.ndarray, higher: bool) -> np.ndarray:
    """means: (M,) float. Returns (M,) int model order, best mean first, models without a mean last."""
    key = np.where(np.isfinite(means), -means if higher else means, np.inf)
    return np.argsort(key, kind="stable")


def correlation_ssim_ate3d(overall: Intervals, metrics: tuple[str, ...], resamples: int, seed: int) -> dict | None:
    """Pearson / Spearman of SSIM against negative ATE-3D across model means; None with < 2 usable models."""
    ssim = overall.mean[:, metrics.index("ssim")]
    neg_ate3d = -overall.mean[:, metrics.index("ate3d")]
    usable = np.isfinite(ssim) & np.isfinite(neg_ate3d)
    if usable.sum() < 2:
        return None
    result = correlation_across_models(ssim[usable], neg_ate3d[usable], n_resamples=resamples, seed=seed)
    result["has_ci"] = int(usable.sum()) >= 3
    return result


def analyse(table: ScoreTable, resamples: int = 20000, seed: int = 0, baseline: str | None = None,
            samples: SampleScores | None = None, power_differences: dict[str, float] | None = None,
            envelope_metric: str = "ate3d") -> ReportData:
    """Compute every interval, paired comparison and correlation the report shows; `samples` (report.samples.
    read_samples) adds the statistics over several samples per example and the envelope's, power_differences
    (metric -> difference) the differences the power table's "examples needed" aim at."""
    several = samples is not None and samples.several
    scores = table.scores  # each example's sample mean (report.load)
    hib = higher_is_better(table.metrics)
    tasks = ordered_groups(table.tasks, TASK_ORDER)
    partitions = ordered_groups(table.partitions, tuple(PARTITION_LABELS))
    overall = intervals(scores, resamples, seed)
    base = choose_baseline(table.models, baseline)
    diff, poi = paired_vs_baseline(scores, base, hib, resamples, seed)
    matrices = ()
    if len(table.models) >= 2:
        matrices = tuple(probability_of_improvement_matrix(scores[:, :, k], bool(hib[k]), n_resamples=resamples,
                                                           seed=seed) for k in range(len(table.metrics)))
    ranked = np.array([name not in UNRANKED_NAMES for name in table.models])
    if not ranked.any():
        ranked[:] = True
    extra = {}
    if several:
        extra["samples"] = sample_stats(samples, hib, resamples, seed)
        extra["power"] = power_comparisons(table, samples.values, base, ranked, overall.mean[base],
                                           power_differences)
    if samples is not None:
        extra["envelope"] = envelope_stats(table, samples.envelopes, tasks, partitions)
    log.info("analysed %d runs x %d examples with %d bootstrap resamples", len(table.models),
             len(table.example_ids), resamples)
    return ReportData(
        table=table, overall=overall, tasks=tasks,
        by_task=group_intervals(scores, table.tasks, tasks, resamples, seed),
        partitions=partitions,
        by_partition=group_intervals(scores, table.partitions, partitions, resamples, seed),
        baseline=base, paired_diff=diff, paired_poi=poi, poi_matrices=matrices,
        correlation=correlation_ssim_ate3d(overall, table.metrics, resamples, seed),
        ranked=ranked, resamples=int(resamples), seed=int(seed), envelope_metric=envelope_metric, **extra)
