"""``build_site``: submission bundles in, a static leaderboard site out.

Writes into ``out``::

    index.html                      the entries, the task and partition filters, one board per measurement
    entries/<slug>.html             one page per entry
    compare/index.html              pick two entries; every pair
    compare/<a>--<b>.html           a against b, for every ordered pair
    examples/index.html             every example
    examples/<id>.html              every entry on one example, with filmstrips of the included clips
    examples/strips/<slug>/<id>.jpg the filmstrips
    assets/style.css, leaderboard.js
    leaderboard.json                every board's numbers (unscaled, unrounded), for other tools

Every link is relative and nothing is fetched when the site is viewed.
"""

from __future__ import annotations

import json
import logging
import math
from pathlib import Path
from typing import Sequence

from rigidbench.atomic import write_text
from rigidbench.errors import UserError
from rigidbench.leaderboard.assets import CSS, JS
from rigidbench.leaderboard.entries import entries_from, example_groups, paper_problem
from rigidbench.leaderboard.filmstrips import filmstrips
from rigidbench.leaderboard.pages import (Site, bundle_name, compare_index_page, compare_page, entry_page,
                                          example_page, examples_index_page, index_page, site_decimals)
from rigidbench.leaderboard.scores import boards, comparisons, example_means, views_of
from rigidbench.metrics import METRICS
from rigidbench.report.paper import load_paper_numbers
from rigidbench.submissions import Submission, load_submission

log = logging.getLogger(__name__)


def collect(submissions: Sequence[Submission], out: Path, *, paper: bool = True, resamples: int = 20000,
            seed: int = 0) -> Site:
    """Every number and filmstrip the pages show (the filmstrips are written under ``out`` here)."""
    if not submissions:
        raise UserError("no submission given; pass one or more bundles `rigidbench submit` wrote")
    entries = entries_from(submissions)
    groups = example_groups(entries)
    if not groups:
        raise UserError(f"{', '.join(str(s.path) for s in submissions)}: no per-example records; a bundle holds "
                        "examples/<id>.json for every scored example (make it again with `rigidbench submit`)")
    metrics = tuple(METRICS)
    views = views_of(groups)
    numbers = load_paper_numbers() if paper else None
    by_metric = boards(entries, groups, views, metrics, numbers, resamples, seed)
    pairs = [(a, b) for k, a in enumerate(entries) for b in entries[k + 1:]]
    by_pair = {}
    for c in comparisons(pairs, groups, views_of(groups, combined=False), metrics, resamples, seed):
        by_pair[(c.a, c.b)], by_pair[(c.b, c.a)] = c, c.swapped()
    ids = list(groups)
    return Site(out=out, entries=tuple(entries), groups=groups, metrics=metrics, views=tuple(views),
                boards=by_metric, comparisons=by_pair,
                means={x.slug: example_means(x, ids, metrics) for x in entries},
                strips={x.slug: filmstrips(x.videos, out / "examples" / "strips" / x.slug) for x in entries},
                paper=numbers, problems={x.slug: paper_problem(x, numbers) if numbers else None for x in entries},
                decimals=site_decimals(by_metric, numbers), resamples=resamples)


def _finite(x):
    return x if isinstance(x, (int, float)) and math.isfinite(x) else None


def board_json(site: Site) -> dict:
    """The boards as JSON: per measurement and view, each row's numbers in the run's units."""
    return {
        "resamples": site.resamples, "confidence": 0.95,
        "paper_marker": site.paper.marker if site.paper else None,
        "entries": [{"slug": x.slug, "name": x.name, "bundle": bundle_name(x.source), "examples": len(x.records),
                     "samples_per_example": x.samples_per_example, "official": x.official,
                     "paper_footing": site.problems.get(x.slug) or "same"} for x in site.entries],
        "boards": {m: [{"task": v.task, "partition": v.partition,
                        "rows": [{"key": r.key, "name": r.name, "reported_in_paper": r.paper,
                                  "mean": _finite(r.mean), "lo": _finite(r.lo), "hi": _finite(r.hi),
                                  "finite": r.n_finite, "examples": r.n_examples, "seed_std": _finite(r.seed_std),
                                  "samples": r.samples, "rank": r.rank} for r in rows]}
                       for v, rows in by_view.items()] for m, by_view in site.boards.items()},
    }


def write_site(site: Site) -> Path:
    """Every page of ``site`` under ``site.out``; returns index.html."""
    out = site.out
    files = {"assets/style.css": CSS, "assets/leaderboard.js": JS, "index.html": index_page(site),
             "compare/index.html": compare_index_page(site), "examples/index.html": examples_index_page(site),
             "leaderboard.json": json.dumps(board_json(site), indent=1)}
    for x in site.entries:
        files[f"entries/{x.slug}.html"] = entry_page(site, x)
    for (a, b), c in site.comparisons.items():
        files[f"compare/{a}--{b}.html"] = compare_page(site, c)
    for sample_id in site.groups:
        files[f"examples/{sample_id}.html"] = example_page(site, sample_id)
    for rel, text in files.items():
        path = out / rel
        path.parent.mkdir(parents=True, exist_ok=True)
        write_text(path, text)
    log.info("leaderboard: %d pages under %s", sum(rel.endswith(".html") for rel in files), out)
    return out / "index.html"


def build_site(submissions: Sequence[str | Path | Submission], out: str | Path, *, paper: bool = True,
               resamples: int = 20000, seed: int = 0) -> Path:
    """The leaderboard site of ``submissions`` (bundles, their folders, or loaded ``Submission``s) under ``out``,
    with the paper's rows unless ``paper`` is False; returns the path of index.html."""
    loaded = [s if isinstance(s, Submission) else load_submission(s) for s in submissions]
    out = Path(out)
    return write_site(collect(loaded, out, paper=paper, resamples=resamples, seed=seed))


__all__ = ["board_json", "build_site", "collect", "write_site"]
