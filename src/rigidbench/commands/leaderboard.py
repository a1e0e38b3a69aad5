"""The command that publishes scores: leaderboard (a static site of submission bundles)."""

from __future__ import annotations

import argparse
from pathlib import Path

from ..argtypes import non_negative_int, output_folder, positive_int
from ..context import RunContext
from . import Command


def _leaderboard_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("submissions", nargs="+", type=Path, metavar="SUBMISSION",
                   help="submission bundles (.tar.gz, as `rigidbench submit` writes them) or their extracted folders")
    p.add_argument("--out", type=output_folder, default="site",
                   help="folder for the site (default site/); open site/index.html, or publish the folder as it is "
                        "(docs/submitting.md)")
    p.add_argument("--no-paper", action="store_true",
                   help="leave out the paper's rows (reported in the paper, not re-scored here)")
    p.add_argument("--resamples", type=positive_int, default=20000, help="bootstrap resamples (default 20000)")
    p.add_argument("--seed", type=non_negative_int, default=0, help="bootstrap seed (default 0)")


def cmd_leaderboard(args, ctx: RunContext | None = None) -> int:
    """`rigidbench leaderboard SUBMISSION... --out DIR [--no-paper] [--resamples N] [--seed S]`."""
    from ..leaderboard import build_site
    from ..submissions import load_submission

    loaded = [load_submission(path) for path in args.submissions]  # every bundle checked before anything is written
    index = build_site(loaded, args.out, paper=not args.no_paper, resamples=args.resamples, seed=args.seed)
    print(f"leaderboard of {len(loaded)} submission(s): {index}")
    return 0


COMMANDS = (
    Command("leaderboard", "a static leaderboard site of submission bundles: boards per measurement with intervals, "
                           "the paper's rows, entry pages, comparisons, an example viewer (docs/submitting.md)",
            "rigidbench.commands.leaderboard:cmd_leaderboard", _leaderboard_arguments),
)
