"""argparse value types and readers shared by every command (the CLI's and the stages' own ``cmd_*``)."""

from __future__ import annotations

import argparse
from typing import Sequence


def positive_int(value: str) -> int:
    """argparse type: an integer >= 1 (a count such as --limit or --workers); one clear line otherwise."""
    try:
        number = int(value)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a whole number >= 1, got {value!r}") from None
    if number < 1:
        raise argparse.ArgumentTypeError(f"expected a whole number >= 1, got {number}")
    return number


def split_ids(values: Sequence[str] | None) -> list[str]:
    """Ids given as several arguments and/or comma- or space-separated lists (``--ids 00000,00007 00009``)."""
    return [v.strip() for chunk in (values or []) for v in str(chunk).replace(",", " ").split() if v.strip()]


def selected_ids(args) -> list[str] | None:
    """The ids of ``--ids`` (None: not given, every example)."""
    return split_ids(getattr(args, "ids", None)) or None


__all__ = ["positive_int", "selected_ids", "split_ids"]
