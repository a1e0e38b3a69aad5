"""Several samples per example and the physical envelope, as the report reads and summarises them.

A run scored with K samples per example holds one record per (example, sample) (``examples/<id>.json`` is
sample 0, ``examples/<id>.s<k>.json`` sample k); report.load reads them into the ScoreTable, whose per-example
scores are each example's sample mean, with the samples beside them. `read_samples` takes those and each run's
results.json "envelope" block (written by `rigidbench evaluate --envelope ENV`). The statistics follow
docs/statistics.md:

- the headline of a measurement is the mean over examples of each example's sample mean, its interval the
  percentile bootstrap over examples (each keeping its samples): ``stats.samples`` with scheme "examples";
- the seed std is the std (ddof 1) over sample indices k of the whole-set mean of sample k
  (``stats.samples.seed_spread``), the spread Physics-IQ reports as "mean ± std" over runs;
- best of K (each example's best sample) is optimistic by construction and is reported apart;
- the envelope's share inside and mean excess are the means over the shared examples of the run's
  per-example "inside" and "excess";
- the power table comes from the variance components of the per-example difference between two runs
  (``stats.power``), or, with one run, from that run's own components doubled.

Nothing here applies when every run has one sample per example and no envelope, so such a report is exactly
what it was before samples existed.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from rigidbench.errors import ReportError
from rigidbench.stats import bootstrap_ci, paired_variance_components, power_table
from rigidbench.stats.power import PairedVarianceComponents, PowerRow
from rigidbench.stats.samples import best_of_k_per_example, per_example_means, seed_spread, within_example_std

#: samples per example the power table shows, and the examples its smallest detectable difference assumes
POWER_SAMPLES = (1, 2, 4, 8)
POWER_EXAMPLES = 100
POWER_TARGET = 0.8
POWER_ALPHA = 0.05
#: the difference the power table's "examples needed" columns aim at when the user gives none: this share of
#: the baseline's mean
DEFAULT_RELATIVE_DIFFERENCE = 0.10


@dataclass(frozen=True)
class SampleScores:
    """values: (M, N, S, K) float64 per-sample scores on the ScoreTable's examples (NaN: no such sample, or a
    non-finite measurement); counts: (M, N) int, sample records per example; envelopes: each run's
    results.json "envelope" block, or None."""

    values: np.ndarray
    counts: np.ndarray
    envelopes: tuple[dict | None, ...]

    @property
    def several(self) -> bool:
        """Whether some run has more than one sample of some example."""
        return bool(self.counts.max(initial=0) > 1)

    def samples_range(self, m: int) -> tuple[int, int]:
        """(fewest, most) samples per example of run m."""
        counts = self.counts[m]
        return (int(counts.min()), int(counts.max())) if counts.size else (0, 0)


def read_samples(table) -> SampleScores:
    """The per-sample scores and envelope blocks of a ScoreTable (report.load): its ``samples`` (M, N, K, S) as
    (M, N, S, K) and each run's ``envelope``; a table without samples (built by hand) has one per example."""
    if getattr(table, "samples", None) is None:
        values, counts = table.scores[:, :, None, :], np.ones(table.scores.shape[:2], dtype=np.int64)
    else:
        values, counts = np.moveaxis(table.samples, 3, 2), np.asarray(table.n_samples, dtype=np.int64)
    return SampleScores(values, counts, tuple(run.envelope for run in table.runs))


# ----------------------------------------------------------------------------------- statistics


@dataclass(frozen=True)
class SampleStats:
    """Per (model, metric): seed std, within-example std and the best-of-K mean with its interval, all (M, K);
    samples: (M, 2) fewest and most samples per example; values: (M, N, S, K) the per-sample scores."""

    samples: np.ndarray
    seed_std: np.ndarray
    within_std: np.ndarray
    best_mean: np.ndarray
    best_lo: np.ndarray
    best_hi: np.ndarray
    best_n: np.ndarray
    values: np.ndarray

    def several(self, m: int) -> bool:
        """Whether run m has more than one sample of some example."""
        return bool(self.samples[m, 1] > 1)


def sample_stats(scores: SampleScores, higher_is_better: np.ndarray, resamples: int, seed: int) -> SampleStats:
    """The seed spread, within-example spread and best of K of every run and measurement; higher_is_better: (K,)."""
    values = scores.values
    n_models, _, _, n_metrics = values.shape
    seed_std = np.full((n_models, n_metrics), np.nan)
    within = np.full((n_models, n_metrics), np.nan)
    best = np.empty((n_models, values.shape[1], n_metrics))
    for m in range(n_models):
        for k in range(n_metrics):
            seed_std[m, k] = seed_spread(values[m, :, :, k])
            within[m, k] = within_example_std(values[m, :, :, k])
            best[m, :, k] = best_of_k_per_example(values[m, :, :, k], bool(higher_is_better[k]))
    per_row = np.moveaxis(best, -2, -1)  # (M, K, N)
    mean, lo, hi = bootstrap_ci(per_row, n_resamples=resamples, seed=seed)
    ranges = np.array([scores.samples_range(m) for m in range(n_models)], dtype=np.int64).reshape(n_models, 2)
    return SampleStats(ranges, seed_std, within, np.asarray(mean), np.asarray(lo), np.asarray(hi),
                       np.isfinite(per_row).sum(axis=-1), values)


@dataclass(frozen=True)
class EnvelopeStats:
    """Where each run falls against the physical envelope, per metric of `metrics` (all arrays index metrics in
    the ScoreTable's order; NaN where a run has no envelope or the envelope lacks the metric).

    inside, excess, n: (M, K) share of examples inside, mean excess, examples counted; by_task, by_partition:
    (M, G, K) arrays (inside, excess, n) over the groups of report.analysis; q05, median, q95: (M, N, K) the
    twins' distribution per example; blocks: the results.json blocks."""

    metrics: tuple[str, ...]
    inside: np.ndarray
    excess: np.ndarray
    n: np.ndarray
    by_task: tuple[np.ndarray, np.ndarray, np.ndarray]
    by_partition: tuple[np.ndarray, np.ndarray, np.ndarray]
    q05: np.ndarray
    median: np.ndarray
    q95: np.ndarray
    blocks: tuple[dict | None, ...]

    def has(self, m: int) -> bool:
        return self.blocks[m] is not None

    @property
    def sources(self) -> tuple[str, ...]:
        """The distinct envelope folders the runs were scored against."""
        return tuple(sorted({str(b.get("source", "")) for b in self.blocks if b is not None}))


def finite(value) -> float:
    """A stored number (or a JSON true/false) as float64; NaN for null, text or a non-finite number."""
    try:
        value = float(value)
    except (TypeError, ValueError):
        return math.nan
    return value if math.isfinite(value) else math.nan


def _group_means(flags: np.ndarray, excess: np.ndarray, labels: np.ndarray, groups) -> tuple:
    """flags, excess: (M, N, K) with NaN where absent. Returns (inside, excess, n), each (M, G, K)."""
    parts = [_means(flags[:, labels == g], excess[:, labels == g]) for g in groups]
    return tuple(np.stack([p[i] for p in parts], axis=1) for i in range(3))


def _means(flags: np.ndarray, excess: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """flags, excess: (M, n, K). Returns (share inside, mean excess, examples counted), each (M, K)."""
    present = np.isfinite(flags)
    n = present.sum(axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        inside = np.where(present, flags, 0.0).sum(axis=1) / n
        found = np.isfinite(excess)
        mean_excess = np.where(found, excess, 0.0).sum(axis=1) / found.sum(axis=1)
    return np.where(n > 0, inside, np.nan), mean_excess, n


def envelope_stats(table, blocks: tuple[dict | None, ...], tasks, partitions) -> EnvelopeStats | None:
    """Share inside and mean excess per run and metric over the table's examples from each run's per-example
    envelope entries; None when no run has an envelope block. tasks, partitions: the group orders."""
    if not any(b is not None for b in blocks):
        return None
    shape = (len(table.runs), len(table.example_ids), len(table.metrics))
    fields = {key: np.full(shape, np.nan) for key in ("inside", "excess", "q05", "median", "q95")}
    measured: set[str] = set()
    for m, block in enumerate(blocks):
        if block is None:
            continue
        measured.update(str(x) for x in block.get("metrics") or ())
        per_example = block.get("per_example") or {}
        for j, sample_id in enumerate(table.example_ids):
            entry = per_example.get(sample_id)
            if not isinstance(entry, dict):
                continue
            for k, metric in enumerate(table.metrics):
                cell = entry.get(metric)
                if isinstance(cell, dict):
                    measured.add(metric)
                    for key, arr in fields.items():
                        arr[m, j, k] = finite(cell.get(key))
    inside, excess, n = _means(fields["inside"], fields["excess"])
    return EnvelopeStats(
        metrics=tuple(x for x in table.metrics if x in measured), inside=inside, excess=excess, n=n,
        by_task=_group_means(fields["inside"], fields["excess"], table.tasks, tasks),
        by_partition=_group_means(fields["inside"], fields["excess"], table.partitions, partitions),
        q05=fields["q05"], median=fields["median"], q95=fields["q95"], blocks=tuple(blocks))


def own_components(scores) -> PairedVarianceComponents:
    """scores: (E, K) of one run and measurement. The components of the difference between this run and a second
    run with the same between-example and within-example variances and independent example effects: this run's
    between-example variance of true per-example means and its within-example variance, each counted twice."""
    arr = np.asarray(scores, dtype=np.float64)
    means = per_example_means(arr)
    ok = np.isfinite(means)
    n = int(ok.sum())
    k_e = np.isfinite(arr[ok]).sum(axis=1)
    within = within_example_std(arr[ok]) ** 2
    variance = float(np.var(means[ok], ddof=1)) if n >= 2 else math.nan
    between = variance - within * float(np.mean(1.0 / k_e)) if n >= 2 else math.nan
    constant = n > 0 and bool(np.all(k_e == k_e[0]))
    return PairedVarianceComponents(
        between=2.0 * max(between, 0.0) if math.isfinite(between) else math.nan,
        within_a=within, within_b=within, n_examples=n, measured_variance=2.0 * variance,
        measured_samples=(int(k_e[0]), int(k_e[0])) if constant else None)


@dataclass(frozen=True)
class PowerComparison:
    """The power table of one comparison: `model` against `baseline` (the same name when one run's components
    are doubled), its assumption in words, each metric's components and one PowerRow per (metric, K)."""

    model: str
    baseline: str
    assumption: str
    components: dict[str, PairedVarianceComponents]
    rows: tuple[PowerRow, ...]


PAIRED_ASSUMPTION = "paired"
DOUBLED_ASSUMPTION = "one run doubled"


def power_comparisons(table, values: np.ndarray, baseline: int, ranked: np.ndarray, baseline_means: np.ndarray,
                      differences: dict[str, float] | None = None) -> tuple[PowerComparison, ...]:
    """One PowerComparison per ranked run against the baseline, from their per-sample scores (values (M, N, S, K));
    with no other ranked run, the baseline's own components doubled. The difference each comparison's
    "examples needed" aims at: `differences[metric]` when given, else DEFAULT_RELATIVE_DIFFERENCE of
    |baseline_means[metric]| (baseline_means: (K,))."""
    differences = dict(differences or {})
    target = {metric: float(differences.get(metric, DEFAULT_RELATIVE_DIFFERENCE * abs(baseline_means[k])))
              for k, metric in enumerate(table.metrics)}
    target = {metric: value for metric, value in target.items() if math.isfinite(value) and value != 0}
    others = [m for m in range(len(table.runs)) if m != baseline and ranked[m]]
    pairs = [(m, PAIRED_ASSUMPTION) for m in others] or [(baseline, DOUBLED_ASSUMPTION)]
    out = []
    for m, assumption in pairs:
        components = {}
        for k, metric in enumerate(table.metrics):
            if assumption == PAIRED_ASSUMPTION:
                components[metric] = paired_variance_components(values[m, :, :, k], values[baseline, :, :, k])
            else:
                components[metric] = own_components(values[baseline, :, :, k])
        rows = power_table(components, n_examples=POWER_EXAMPLES, samples_per_example=POWER_SAMPLES,
                           differences=target, alpha=POWER_ALPHA, power=POWER_TARGET)
        out.append(PowerComparison(table.models[m], table.models[baseline], assumption, components, tuple(rows)))
    return tuple(out)


def check_metric(metric: str, metrics, what: str) -> str:
    """`metric` when it is one of `metrics`, else a ReportError naming `what` and the choices."""
    if metric not in metrics:
        raise ReportError(f"{what} '{metric}' is not a measurement; choose one of {', '.join(metrics)}")
    return metric


def parse_differences(items, metrics) -> dict[str, float]:
    """METRIC=VALUE strings (the report's --power-difference) as {metric: value}; a bad one is a ReportError."""
    out = {}
    for item in items or ():
        name, sep, text = str(item).partition("=")
        if not sep:
            raise ReportError(f"--power-difference {item!r}: write METRIC=VALUE, e.g. ate3d=0.05")
        check_metric(name.strip(), metrics, "--power-difference")
        try:
            value = float(text)
        except ValueError:
            value = math.nan
        if not (math.isfinite(value) and value > 0):
            raise ReportError(f"--power-difference {item!r}: the difference must be a positive number "
                              "(in the measurement's own unit, before any display scale)")
        out[name.strip()] = value
    return out


def envelope_metric_note(stats: EnvelopeStats, metric: str) -> str:
    """Why the envelope figure is missing for `metric` ("" when it can be drawn)."""
    if metric in stats.metrics:
        return ""
    return (f"The envelope figure shows {metric}, which the runs' envelope does not measure (it measures "
            f"{', '.join(stats.metrics) or 'nothing'}); choose one of those with --envelope-metric.")


