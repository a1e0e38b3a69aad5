"""Per-example records -> the numbers in results.json: mean, population std and finite count per
metric overall, per task and per partition, and whether the run is an official result."""

from __future__ import annotations

import math
from typing import Sequence

import numpy as np

EVAL_SIZE = 100  # examples in the evaluation split


def summarise(values: list[float | None]) -> dict:
    """Mean, population std, finite count and total count of the finite values (None and NaN omitted)."""
    arr = np.array([v for v in values if v is not None and math.isfinite(v)], dtype=np.float64)
    return {"mean": float(arr.mean()) if arr.size else None, "std": float(arr.std()) if arr.size else None,
            "finite": int(arr.size), "n": len(values)}


def aggregate(records: list[dict], metrics: Sequence[str]) -> dict:
    """Summaries of ``metrics`` over ``records`` overall, per task and per partition."""
    def block(rs: list[dict]) -> dict:
        return {m: summarise([r["metrics"].get(m) for r in rs]) for m in metrics}

    out = {"overall": block(records), "by_task": {}, "by_partition": {}}
    for key, name in (("task", "by_task"), ("partition", "by_partition")):
        for value in sorted({r[key] for r in records}):
            out[name][value] = block([r for r in records if r[key] == value])
    return out


def coverage_summary(records: list[dict]) -> dict:
    """results.json's "coverage": per example the seconds and fraction of the reference span its clip
    covers (and the frames compared), the smallest and mean fraction, and the ids scored although short
    of the span (``evaluate --allow-short``). Records without coverage (older runs) are left out."""
    per = {r["id"]: {k: r["coverage"][k] for k in ("seconds", "fraction", "frames", "reference_frames", "short")
                     if k in r["coverage"]}
           for r in records if isinstance(r.get("coverage"), dict)}
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
