"""Leaderboard entries: one per submission, with its per-example scores as arrays and where it stands with the
paper's numbers.

An ``Entry`` wraps what ``submissions.load_submission`` read (card, provenance, results.json, the per-example
records and readouts, the included videos) and adds a URL-safe ``slug`` for its pages. ``score_array`` turns
its records into ``(M, E, K)`` scores over a list of example ids: NaN where a measurement is null, skipped or
not finite, where the entry has no record of the example, or beyond the samples it has. A record holds one
generation per example today (its ``metrics``); a record with a ``samples`` list of ``{"metrics": {...}}``
holds one per item (``record_samples``).
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass
from functools import cached_property
from pathlib import Path
from typing import Sequence

import numpy as np

from rigidbench.report.load import RunInfo
from rigidbench.report.paper import PaperNumbers, run_problem
from rigidbench.submissions import Submission


@dataclass(frozen=True)
class Entry:
    """One submission on the board: ``slug`` (unique on the site, [a-z0-9-]) and the submission as
    ``load_submission`` read it, whose parts it shows under the same names (``source``: its path)."""

    slug: str
    submission: Submission

    @property
    def name(self) -> str:
        return self.submission.name

    @property
    def card(self) -> dict:
        return self.submission.card

    @property
    def provenance(self) -> dict:
        return self.submission.provenance

    @property
    def results(self) -> dict:
        return self.submission.results

    @property
    def records(self) -> dict[str, dict]:
        return self.submission.records

    @property
    def readouts(self) -> dict[str, dict]:
        return self.submission.readouts

    @property
    def videos(self) -> dict[str, Path | None]:
        return self.submission.videos

    @property
    def source(self) -> Path:
        return Path(self.submission.path)

    @property
    def example_ids(self) -> tuple[str, ...]:
        return tuple(sorted(self.records))

    @cached_property
    def samples_per_example(self) -> int:
        """The most generations any example of this entry has (1 today)."""
        return max((len(record_samples(r)) for r in self.records.values()), default=1)

    @property
    def official(self) -> bool:
        return self.results.get("official") is True

    @property
    def protocol(self) -> str:
        protocol = self.results.get("protocol")
        return str(protocol.get("name", "")) if isinstance(protocol, dict) else str(protocol or "")

    @property
    def perception(self) -> str:
        return str(self.results.get("perception") or "")

    @property
    def dataset(self) -> dict:
        d = self.results.get("dataset")
        return d if isinstance(d, dict) else {}

    @property
    def has_videos(self) -> bool:
        return any(p is not None for p in self.videos.values())


def slugify(name: str) -> str:
    """A name as lowercase letters, digits and single dashes ("Wan 2.2 (LoRA)" -> "wan-2-2-lora"); "entry" if
    nothing is left."""
    return re.sub(r"-+", "-", re.sub(r"[^a-z0-9]+", "-", name.lower())).strip("-") or "entry"


def unique_slugs(names: Sequence[str]) -> list[str]:
    """One slug per name, made unique by -2, -3, ... in order ("a", "a" -> "a", "a-2")."""
    seen: set[str] = set()
    out = []
    for name in names:
        base = slugify(name)
        slug, k = base, 1
        while slug in seen:
            k += 1
            slug = f"{base}-{k}"
        seen.add(slug)
        out.append(slug)
    return out


def entries_from(submissions: Sequence[Submission]) -> list[Entry]:
    """The submissions as entries, in the order given; two with one name keep it, their slugs differ."""
    slugs = unique_slugs([s.name for s in submissions])
    return [Entry(slug, s) for slug, s in zip(slugs, submissions)]


def record_samples(record: dict) -> list[dict]:
    """The measurement values of each generation scored for one example: one ``{metric: value}`` per sample."""
    samples = record.get("samples")
    if isinstance(samples, list) and samples:
        return [s.get("metrics") or {} for s in samples if isinstance(s, dict)]
    metrics = record.get("metrics")
    return [metrics if isinstance(metrics, dict) else {}]


def _value(x) -> float:
    if isinstance(x, bool) or not isinstance(x, (int, float)):
        return math.nan
    return float(x) if math.isfinite(x) else math.nan


def score_array(entry: Entry, ids: Sequence[str], metrics: Sequence[str], samples: int | None = None) -> np.ndarray:
    """(M, E, K) float64 scores of ``entry`` on ``ids`` (K: ``samples``, default the entry's most); NaN where
    there is no finite value."""
    k = samples or entry.samples_per_example
    out = np.full((len(metrics), len(ids), k), np.nan)
    for j, sample_id in enumerate(ids):
        record = entry.records.get(sample_id)
        if record is None:
            continue
        for s, values in enumerate(record_samples(record)[:k]):
            for m, metric in enumerate(metrics):
                out[m, j, s] = _value(values.get(metric))
    return out


def example_groups(entries: Sequence[Entry]) -> dict[str, tuple[str, str]]:
    """Example id -> (task, partition) over every entry's records (the first entry holding an id names them)."""
    out: dict[str, tuple[str, str]] = {}
    for entry in entries:
        for sample_id, record in sorted(entry.records.items()):
            out.setdefault(sample_id, (str(record.get("task") or ""), str(record.get("partition") or "")))
    return dict(sorted(out.items()))


def paper_problem(entry: Entry, paper: PaperNumbers) -> str | None:
    """Why this entry's numbers do not stand on the paper's footing (another set, an unverified copy, another
    protocol or perception, fewer examples), as one clause; None when they do."""
    run = RunInfo(name=entry.name, path=entry.source, perception=entry.perception, perception_version="",
                  official=entry.official, why_not_official=(), skipped_metrics={}, failed={},
                  n_examples=len(entry.records), n_reference=None, finished_at="", protocol=entry.protocol,
                  dataset=entry.dataset)
    problem = run_problem(run, paper)
    if problem is not None:
        return problem.format(**{"is": "is", "was": "was", "s": "s"})
    if len(entry.records) != paper.examples:
        return f"covers {len(entry.records)} of the paper's {paper.examples} examples"
    return None


__all__ = ["Entry", "entries_from", "example_groups", "paper_problem", "record_samples", "score_array", "slugify",
           "unique_slugs"]
