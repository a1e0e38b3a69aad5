"""The numbers on the leaderboard: one board per measurement and view, and paired comparisons of two entries.

A view is a subset of the examples: all of them, one task, one evaluation partition, or one task within one
partition (the site's two filters). For each measurement and view, a board row per entry holds the mean over
examples of per-example sample means with its percentile bootstrap interval over examples
(``stats.hierarchical_bootstrap_ci``, scheme "examples": with one sample per example it is
``bootstrap_ci`` exactly), its finite and total example counts, the seed spread across sample indices
(``stats.samples.seed_spread``; NaN below two samples) and the samples per example. The paper's rows are
added where the paper prints a number for that measurement and view (``paper_rows``). Comparisons pair two
entries on the examples both have, as ``stats.paired_difference_samples`` and
``probability_of_improvement_samples`` do (``comparisons`` computes every pair in one bootstrap call).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Sequence

import numpy as np

from rigidbench.leaderboard.entries import Entry, score_array
from rigidbench.metrics import METRICS
from rigidbench.report.paper import PaperCell, PaperNumbers
from rigidbench.stats import bootstrap_ci, hierarchical_bootstrap_ci, per_example_means
from rigidbench.stats.samples import improvement_fractions, paired_example_differences, seed_spread

CONFIDENCE = 0.95


@dataclass(frozen=True)
class View:
    """A subset of the examples: ``task`` and ``partition`` ids, "" meaning any."""

    task: str = ""
    partition: str = ""

    def includes(self, task: str, partition: str) -> bool:
        return (not self.task or self.task == task) and (not self.partition or self.partition == partition)

    @property
    def label(self) -> str:
        parts = [f"task {self.task}" if self.task else "", f"partition {self.partition}" if self.partition else ""]
        return ", ".join(p for p in parts if p) or "all examples"


ALL = View()


def views_of(groups: dict[str, tuple[str, str]], combined: bool = True) -> list[View]:
    """Every view of the examples ``groups`` (id -> (task, partition)): all, each task, each partition and, when
    ``combined``, each task within each partition."""
    tasks = sorted({t for t, _ in groups.values()})
    partitions = sorted({p for _, p in groups.values()})
    out = [ALL] + [View(t, "") for t in tasks] + [View("", p) for p in partitions]
    return out + ([View(t, p) for t in tasks for p in partitions] if combined else [])


def view_masks(groups: dict[str, tuple[str, str]], views: Sequence[View]) -> np.ndarray:
    """(V, E) bool: which of the examples (in ``groups`` order) each view includes."""
    return np.array([[v.includes(t, p) for t, p in groups.values()] for v in views], dtype=bool).reshape(
        len(views), len(groups))


@dataclass(frozen=True)
class BoardRow:
    """One row of a board: a scored entry (``paper`` False; ``key`` its slug) or a paper row (``key``
    "paper:<name>", ``text`` as printed). Means and intervals are in the run's units (not display-scaled);
    ``rank`` among the scored entries with a value (ties share a rank), None for paper rows."""

    key: str
    name: str
    paper: bool
    mean: float
    lo: float
    hi: float
    n_finite: int
    n_examples: int
    seed_std: float = math.nan
    samples: int | None = None
    rank: int | None = None
    text: str = ""


def paper_rows(paper: PaperNumbers, metric: str, view: View) -> list[PaperCell]:
    """The paper's numbers for ``metric`` on ``view``, one per row of its model comparison: the whole set from
    the model table, a task or a partition from the tables that break results down that way (released models
    only, not fine-tuned checkpoints); none for a task within a partition, which the paper never prints."""
    if view.task and view.partition:
        return []
    by, group = ("task", view.task) if view.task else ("partition", view.partition) if view.partition else (
        "model", None)
    names = [row.name for table in paper.tables_by("model") for row in table.rows if row.checkpoint is None]
    found: dict[str, PaperCell] = {}
    for table in paper.tables_by(by):
        for row in table.rows:
            if row.checkpoint is None and row.name in names and row.name not in found:
                cell = table.cell(row, metric, group)
                if cell is not None:
                    found[row.name] = cell
    return [found[name] for name in names if name in found]


def ranked(rows: Sequence[BoardRow], higher_is_better: bool) -> list[BoardRow]:
    """Rows best first by mean (paper rows among them; those without a value last, by name), the scored
    entries ranked: 1 + how many scored entries are strictly better."""
    sign = -1.0 if higher_is_better else 1.0
    valued = sorted((r for r in rows if math.isfinite(r.mean)), key=lambda r: sign * r.mean)
    rest = sorted((r for r in rows if not math.isfinite(r.mean)), key=lambda r: (r.paper, r.name.lower()))
    scored = [r.mean for r in valued if not r.paper]
    out = []
    for r in valued + rest:
        rank = None
        if not r.paper and math.isfinite(r.mean):
            rank = 1 + sum(1 for m in scored if sign * m < sign * r.mean)
        out.append(BoardRow(**{**r.__dict__, "rank": rank}))
    return out


def boards(entries: Sequence[Entry], groups: dict[str, tuple[str, str]], views: Sequence[View],
           metrics: Sequence[str], paper: PaperNumbers | None = None, resamples: int = 20000,
           seed: int = 0) -> dict[str, dict[View, list[BoardRow]]]:
    """metric -> view -> rows (ranked), for every entry and, when ``paper`` is given, the paper's rows."""
    ids = list(groups)
    k = max((e.samples_per_example for e in entries), default=1)
    masks = view_masks(groups, views)  # (V, E)
    scores = np.stack([score_array(e, ids, metrics, k) for e in entries]) if entries else np.empty(
        (0, len(metrics), len(ids), k))  # (N, M, E, K)
    in_view = np.where(masks[None, None, :, :, None], scores[:, :, None], np.nan)  # (N, M, V, E, K)
    mean, lo, hi = (np.asarray(x).reshape(len(entries), len(metrics), len(views))
                    for x in hierarchical_bootstrap_ci(in_view, "examples", resamples, CONFIDENCE, seed))
    n_finite = np.isfinite(in_view).any(axis=-1).sum(axis=-1)  # (N, M, V)
    has = np.array([[i in e.records for i in ids] for e in entries], dtype=bool).reshape(len(entries), len(ids))
    n_examples = (has[:, None, :] & masks[None]).sum(axis=-1)  # (N, V)
    out: dict[str, dict[View, list[BoardRow]]] = {}
    for m, metric in enumerate(metrics):
        out[metric] = {}
        for v, view in enumerate(views):
            rows = []
            for n, e in enumerate(entries):
                spread = seed_spread(in_view[n, m, v]) if e.samples_per_example >= 2 else math.nan
                rows.append(BoardRow(e.slug, e.name, False, float(mean[n, m, v]), float(lo[n, m, v]),
                                     float(hi[n, m, v]), int(n_finite[n, m, v]), int(n_examples[n, v]), spread,
                                     e.samples_per_example))
            if paper is not None:
                rows += [BoardRow(f"paper:{c.row}", c.row, True, c.value, math.nan, math.nan, c.n_finite,
                                  c.n_examples, text=c.text) for c in paper_rows(paper, metric, view)]
            out[metric][view] = ranked(rows, METRICS[metric].higher_is_better)
    return out


# ------------------------------------------------------------------------------------ comparisons


@dataclass(frozen=True)
class PairCell:
    """Entry a against entry b on one measurement and view: mean over matched examples of a - b (per-example
    sample means) and the probability that a beats b on an example, each with its interval; ``n`` matched
    examples (both have a finite value)."""

    diff: float
    diff_lo: float
    diff_hi: float
    poi: float
    poi_lo: float
    poi_hi: float
    n: int

    def swapped(self) -> "PairCell":
        """The same comparison read from b's side: -diff with the interval mirrored, 1 - PoI likewise."""
        return PairCell(-self.diff, -self.diff_hi, -self.diff_lo, 1.0 - self.poi, 1.0 - self.poi_hi,
                        1.0 - self.poi_lo, self.n)


@dataclass(frozen=True)
class Comparison:
    """Entry ``a`` against entry ``b`` (slugs) over the examples both hold: cells[metric][view]."""

    a: str
    b: str
    shared: tuple[str, ...]
    cells: dict[str, dict[View, PairCell]]

    def swapped(self) -> "Comparison":
        return Comparison(self.b, self.a, self.shared,
                          {m: {v: c.swapped() for v, c in by.items()} for m, by in self.cells.items()})


def comparisons(pairs: Sequence[tuple[Entry, Entry]], groups: dict[str, tuple[str, str]], views: Sequence[View],
                metrics: Sequence[str], resamples: int = 20000, seed: int = 0) -> list[Comparison]:
    """Paired differences and probability of improvement of a over b on their shared examples, for every
    (a, b) of ``pairs``, measurement and view: per example, the difference of sample means and the share of
    sample pairs a wins (``stats.samples``), then the examples bootstrap over matched examples, all pairs in
    one ``bootstrap_ci`` call (a row's interval does not depend on the other rows)."""
    if not pairs:
        return []
    ids = list(groups)
    masks = view_masks(groups, views)  # (V, E)

    def in_views(entry: Entry) -> np.ndarray:  # (V, M, E, K), NaN outside the view
        return np.where(masks[:, None, :, None], score_array(entry, ids, metrics)[None], np.nan)

    diffs = np.full((len(pairs), len(views), len(metrics), len(ids)), np.nan)
    wins = np.full_like(diffs, np.nan)
    for p, (a, b) in enumerate(pairs):
        xa, xb = in_views(a), in_views(b)
        diffs[p] = paired_example_differences(xa, xb)
        for higher in (True, False):
            cols = [m for m, name in enumerate(metrics) if METRICS[name].higher_is_better == higher]
            wins[p][:, cols] = improvement_fractions(xa[:, cols], xb[:, cols], higher)
    diff = bootstrap_ci(diffs, resamples, CONFIDENCE, seed)
    poi = bootstrap_ci(wins, resamples, CONFIDENCE, seed)
    matched = np.isfinite(diffs).sum(axis=-1)  # (P, V, M)
    out = []
    for p, (a, b) in enumerate(pairs):
        cells = {metric: {view: PairCell(*(float(x[p, v, m]) for x in (*diff, *poi)), int(matched[p, v, m]))
                          for v, view in enumerate(views)} for m, metric in enumerate(metrics)}
        shared = tuple(i for i in ids if i in a.records and i in b.records)
        out.append(Comparison(a.slug, b.slug, shared, cells))
    return out


def compare(a: Entry, b: Entry, groups: dict[str, tuple[str, str]], views: Sequence[View], metrics: Sequence[str],
            resamples: int = 20000, seed: int = 0) -> Comparison:
    """``comparisons`` of one pair."""
    return comparisons([(a, b)], groups, views, metrics, resamples, seed)[0]


def example_means(entry: Entry, ids: Sequence[str], metrics: Sequence[str]) -> np.ndarray:
    """(M, E) float64 per-example sample means of ``entry`` (NaN where it has no finite value)."""
    return per_example_means(score_array(entry, ids, metrics))


__all__ = ["ALL", "BoardRow", "CONFIDENCE", "Comparison", "PairCell", "View", "boards", "compare", "comparisons",
           "example_means", "paper_rows", "ranked", "view_masks", "views_of"]
