"""The leaderboard site: ``rigidbench leaderboard SUBMISSION... --out site/``.

Submission bundles (``submissions.load_submission``) in, a static site out that works from ``file://`` and any
static host: a sortable board per measurement with intervals, seed spread and samples per entry, the paper's
rows marked as reported, filters by task and partition, a page per entry, paired comparisons of two entries and
an example viewer with filmstrips of the included clips.

- ``entries``: submissions as entries and their per-example scores as arrays;
- ``scores``: the boards (bootstrap intervals, ranks, the paper's rows) and the paired comparisons;
- ``filmstrips``: a few decoded frames of each included clip as one JPEG;
- ``html``, ``assets``, ``pages``: the page frame, the one style sheet and script, each page;
- ``site``: ``build_site``, which writes them all.
"""

from rigidbench.leaderboard.site import build_site

__all__ = ["build_site"]
