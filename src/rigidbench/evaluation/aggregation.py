"""Per-example records -> the numbers in results.json: mean, population std and finite count per
metric overall, per task and per partition, and whether the run is an official result.

A run scored with several samples (generations) per example holds one record per (example, sample): each
has the example's ``id`` and its ``sample`` index (absent: sample 0). Every number here is over examples:
an example's value of a measurement is the mean of its samples' finite values (``example_means``), so a run
with one sample per example gives exactly the numbers it gave before samples existed.
"""

from __future__ import annotations

import math
from typing import Iterable, Mapping, Sequence

import numpy as np

from ..stats.samples import per_example_means, summarize_samples, within_example_std

EVAL_SIZE = 100  # examples in the evaluation split


def summarise(values: list[float | None]) -> dict:
    """Mean, population std, finite count and total count of the finite values (None and NaN omitted)."""
    arr = np.array([v for v in values if v is not None and math.isfinite(v)], dtype=np.float64)
    return {"mean": float(arr.mean()) if arr.size else None, "std": float(arr.std()) if arr.size else None,
            "finite": int(arr.size), "n": len(values)}


def sample_index(record: dict) -> int:
    """The sample a record scored (``sample``; a record without one is sample 0)."""
    return int(record.get("sample", 0) or 0)


def by_example(records: Iterable[dict]) -> dict[str, list[dict]]:
    """Records grouped by example id (in order of first appearance), each group sorted by sample index."""
    groups: dict[str, list[dict]] = {}
    for r in records:
        groups.setdefault(r["id"], []).append(r)
    return {i: sorted(rs, key=sample_index) for i, rs in groups.items()}


def _finite_mean(values: list) -> float | None:
    finite = [float(v) for v in values if v is not None and math.isfinite(v)]
    return sum(finite) / len(finite) if finite else None


def example_means(records: Iterable[dict], metrics: Sequence[str]) -> list[dict]:
    """One record per example (in order of first appearance): its first sample's record with ``metrics`` the
    mean of each measurement over the samples where it is finite (None where no sample has a finite value) and
    ``n_samples`` its sample count. An example with one sample keeps its values as they are."""
    out = []
    for rs in by_example(records).values():
        if len(rs) == 1:
            out.append({**rs[0], "n_samples": 1})
            continue
        means = {m: _finite_mean([r["metrics"].get(m) for r in rs]) for m in metrics}
        out.append({**rs[0], "metrics": means, "n_samples": len(rs)})
    return out


def aggregate(records: list[dict], metrics: Sequence[str]) -> dict:
    """Summaries of ``metrics`` overall, per task and per partition, over the examples of ``records``: each
    example's per-sample mean (``example_means``; one record per example: its values)."""
    def block(rs: list[dict]) -> dict:
        return {m: summarise([r["metrics"].get(m) for r in rs]) for m in metrics}

    records = example_means(records, metrics)
    out = {"overall": block(records), "by_task": {}, "by_partition": {}}
    for key, name in (("task", "by_task"), ("partition", "by_partition")):
        for value in sorted({r[key] for r in records}):
            out[name][value] = block([r for r in records if r[key] == value])
    return out


def example_notes(records: Iterable[dict]) -> dict[str, dict]:
    """results.json's "notes": per example with any, its records' notes (measurement -> why its value is left
    undefined); with several samples each note names its sample ("sample 1: ...; sample 3: ...")."""
    out = {}
    for sample_id, rs in by_example(records).items():
        if len(rs) == 1:
            if rs[0].get("notes"):
                out[sample_id] = rs[0]["notes"]
            continue
        merged: dict[str, list[str]] = {}
        for r in rs:
            for metric, note in (r.get("notes") or {}).items():
                merged.setdefault(metric, []).append(f"sample {sample_index(r)}: {note}")
        if merged:
            out[sample_id] = {metric: "; ".join(notes) for metric, notes in merged.items()}
    return out


def _least_covered(rs: list[dict]) -> dict | None:
    """Of an example's sample records, the coverage of the one that covers least (short when any is short)."""
    covered = [r["coverage"] for r in rs if isinstance(r.get("coverage"), dict)]
    if not covered:
        return None
    if len(covered) == 1:
        return covered[0]
    least = min(covered, key=lambda c: (c.get("fraction") is None, c.get("fraction") or 0.0))
    return {**least, "short": any(bool(c.get("short")) for c in covered)}


def sample_scores(records: Iterable[dict], metrics: Sequence[str]) -> tuple[list[str], np.ndarray]:
    """(example ids in order of first appearance, scores (metrics, examples, K) float64): sample k of an example
    in column k (K: the largest sample index + 1), NaN where a value is null or not finite or the example has no
    such sample."""
    groups = by_example(records)
    k = max((sample_index(r) + 1 for rs in groups.values() for r in rs), default=1)
    out = np.full((len(metrics), len(groups), k), np.nan)
    for e, rs in enumerate(groups.values()):
        for r in rs:
            for m, metric in enumerate(metrics):
                v = r["metrics"].get(metric)
                if v is not None and math.isfinite(v):
                    out[m, e, sample_index(r)] = float(v)
    return list(groups), out


def _json_number(x: float) -> float | None:
    return float(x) if x is not None and math.isfinite(x) else None


def samples_summary(records: list[dict], metrics: Sequence[str], higher_is_better: Mapping[str, bool],
                    n_resamples: int = 20000, seed: int = 0) -> dict:
    """results.json's "samples" block over every example's samples (``stats.samples.summarize_samples``, the
    examples scheme): per measurement the headline (mean over examples of per-example sample means) with its
    bootstrap interval, the seed spread (std over sample indices of the whole-set mean of sample k), the
    within-example std, each sample index's mean and the best of K, labelled (never the headline). NaN is null."""
    _, scores = sample_scores(records, metrics)
    counts = [len(rs) for rs in by_example(records).values()]
    out: dict = {}
    for m, metric in enumerate(metrics):
        s = summarize_samples(scores[m], higher_is_better[metric], n_resamples=n_resamples, seed=seed)
        out[metric] = {"mean": _json_number(s.mean), "lo": _json_number(s.lo), "hi": _json_number(s.hi),
                       "seed_std": _json_number(s.seed_spread),
                       "within_example_std": _json_number(s.within_example_std),
                       "sample_index_means": [_json_number(v) for v in s.sample_index_means],
                       "best_of_k": {"label": s.best_of_k.label, "mean": _json_number(s.best_of_k.mean),
                                     "lo": _json_number(s.best_of_k.lo), "hi": _json_number(s.best_of_k.hi)}}
    return {"samples_per_example": {"min": min(counts, default=0), "max": max(counts, default=0)},
            "n_items": sum(counts), "scheme": "examples", "metrics": out}


def variance_components(records: list[dict], metrics: Sequence[str]) -> dict:
    """results.json's "variance" (for the report's power table), per measurement: ``between_example``, the
    variance (ddof 1) of the per-example sample means, and ``within_example``, the pooled variance of samples
    about their example's mean (``stats.samples.within_example_std`` squared); null where undefined (fewer than
    two examples; no example with two finite samples)."""
    _, scores = sample_scores(records, metrics)
    out = {}
    for m, metric in enumerate(metrics):
        means = per_example_means(scores[m])
        means = means[np.isfinite(means)]
        between = float(np.var(means, ddof=1)) if means.size >= 2 else math.nan
        out[metric] = {"between_example": _json_number(between),
                       "within_example": _json_number(within_example_std(scores[m]) ** 2)}
    return out


def coverage_summary(records: list[dict]) -> dict:
    """results.json's "coverage": per example the seconds and fraction of the reference span its clip
    covers (and the frames compared), the smallest and mean fraction, and the ids scored although short
    of the span (``evaluate --allow-short``). With several samples, an example's entry is that of its sample
    that covers least, short when any sample is. Records without coverage (older runs) are left out."""
    least = {i: _least_covered(rs) for i, rs in by_example(records).items()}
    per = {i: {k: c[k] for k in ("seconds", "fraction", "frames", "reference_frames", "short") if k in c}
           for i, c in least.items() if c is not None}
    fractions = [c["fraction"] for c in per.values() if c.get("fraction") is not None]
    return {"min_fraction": min(fractions) if fractions else None,
            "mean_fraction": float(np.mean(fractions)) if fractions else None,
            "short": sorted(i for i, c in per.items() if c.get("short")), "per_example": per}


def why_not_official(all_ids: Sequence[str], complete_ids: set[str], failed: dict, missing_metrics: Sequence[str],
                     short: Sequence[str] = ()) -> list[str]:
    """The reasons a run is not an official result (empty: it is one): the full evaluation split, every
    example scored over the whole reference span, none failed, no measurement skipped."""
    reasons = []
    if len(all_ids) != EVAL_SIZE:
        reasons.append(f"the reference directory holds {len(all_ids)} examples, not the {EVAL_SIZE} of the eval split")
    if set(all_ids) - complete_ids:
        reasons.append(f"{len(set(all_ids) - complete_ids)} examples were not scored")
    if failed:
        reasons.append(f"{len(failed)} examples failed")
    if missing_metrics:
        reasons.append(f"measurements skipped: {', '.join(missing_metrics)}")
    if short:
        reasons.append(f"{len(short)} clips shorter than the reference span were scored (--allow-short): "
                       f"{', '.join(short[:5])}{' ...' if len(short) > 5 else ''}")
    return reasons
