"""argparse value types and readers shared by every command (the CLI's and the stages' own ``cmd_*``).

A bad value is refused while the command line is read, before any work: argparse prints one line naming
the option (``rigidbench CMD: error: argument --limit: expected a whole number >= 1, got 0``) and exits with
status 2. Paths are checked the same way: an output folder or file that cannot be written (a file or a
folder in the way, a read-only file system, no permission) and an input folder that is not there
(``where_to_write`` and ``input_folder`` also serve defaults decided later, as a ``UserError``).
"""

from __future__ import annotations

import argparse
import os
from pathlib import Path
from typing import Callable, Sequence

from .errors import UserError


def int_at_least(low: int) -> Callable[[str], int]:
    """argparse type: an integer >= ``low``; one clear line otherwise."""
    def parse(value: str) -> int:
        try:
            number = int(value)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected a whole number >= {low}, got {value!r}") from None
        if number < low:
            raise argparse.ArgumentTypeError(f"expected a whole number >= {low}, got {number}")
        return number

    parse.__name__ = "positive_int" if low == 1 else "non_negative_int" if low == 0 else f"int_at_least_{low}"
    return parse


#: a count such as --limit, --workers or --resamples
positive_int = int_at_least(1)
#: a seed, or a count where 0 means none (report --examples)
non_negative_int = int_at_least(0)


def _read_only(path: Path) -> bool:
    try:
        return bool(os.statvfs(path).f_flag & os.ST_RDONLY)
    except (OSError, AttributeError):
        return False


def where_to_write(path: str | Path, kind: str = "folder") -> str | None:
    """Why nothing can be written at ``path`` (``kind``: "folder", created if need be, or "file"), or None
    when it can: a file where the folder is or where a folder above it should be, a folder where the file
    should be, or a nearest existing folder that is read-only or not writable. Looks only; creates nothing."""
    path = Path(path)
    if path.is_dir() and kind == "file":
        return "is a folder, not a file; pass a file name"
    if path.exists() and not path.is_dir() and kind == "folder":
        return "is a file, not a folder; pass a folder for the outputs"
    existing = path if kind == "folder" else path.parent
    while not (existing.exists() or existing.is_symlink()) and existing != existing.parent:
        existing = existing.parent
    if not existing.is_dir():
        return f"{existing} is a file, not a folder; pass a path in a folder"
    if not os.access(existing, os.W_OK | os.X_OK):
        why = "is on a read-only file system" if _read_only(existing) else "is not writable by you"
        where = "it" if existing == path else str(existing)
        return f"cannot write there: {where} {why}; pass a folder you can write to"
    return None


def writable(path: str | Path, option: str = "--out", kind: str = "folder") -> Path:
    """``path`` when something can be written there (``where_to_write``); else a UserError naming ``option``
    (for an output decided after parsing: a default, or one whose kind depends on other arguments)."""
    problem = where_to_write(path, kind)
    if problem:
        raise UserError(f"{option} {path}: {problem}")
    return Path(path)


def output_folder(value: str) -> Path:
    """argparse type: a folder to write into (created when absent; see ``where_to_write``)."""
    problem = where_to_write(value, "folder")
    if problem:
        raise argparse.ArgumentTypeError(f"{value}: {problem}")
    return Path(value)


def output_file(value: str) -> Path:
    """argparse type: a file to write (replaced when present; see ``where_to_write``)."""
    problem = where_to_write(value, "file")
    if problem:
        raise argparse.ArgumentTypeError(f"{value}: {problem}")
    return Path(value)


def _not_a_folder(path: Path) -> str | None:
    if not path.exists():
        return "no such folder"
    return None if path.is_dir() else "is a file, not a folder"


def existing_folder(value: str) -> Path:
    """argparse type: a folder to read that must be there (a cache, a store, a data folder)."""
    problem = _not_a_folder(Path(value))
    if problem:
        raise argparse.ArgumentTypeError(f"{value}: {problem}")
    return Path(value)


def input_folder(path: str | Path, name: str, what: str = "") -> Path:
    """``path`` when it is an existing folder; else a UserError naming the argument ``name`` (e.g. "--acts")
    and what it should hold (for an argument whose folder is decided after parsing, or a positional one)."""
    path = Path(path)
    problem = _not_a_folder(path)
    if problem:
        raise UserError(f"{name} {path}: {problem}" + (f"; pass {what}" if what else ""))
    return path


def split_ids(values: Sequence[str] | None) -> list[str]:
    """Ids given as several arguments and/or comma- or space-separated lists (``--ids 00000,00007 00009``)."""
    return [v.strip() for chunk in (values or []) for v in str(chunk).replace(",", " ").split() if v.strip()]


def _none_given(values: Sequence[str], option: str | None) -> str:
    shown = " ".join(repr(v) for v in values)
    return (f"nothing in {shown}; give at least one (several: comma- or space-separated)"
            + (f", or leave {option} out for all of them" if option else ""))


def given_ids(values: Sequence[str], option: str = "--ids") -> list[str]:
    """The ids of an argument that was given (``split_ids``); a UserError when it holds none (``--ids ''`` or
    ``--ids ,,,``: an empty selection is a mistake, never "every example")."""
    ids = split_ids(values)
    if not ids:
        raise UserError(f"{option}: {_none_given(values, option)}")
    return ids


class IdList(argparse.Action):
    """``nargs="+"`` ids (or names) given as several arguments and/or comma-separated lists: stores their
    ``split_ids``; an argument with none at all (``--ids ''``, ``--ids ,,,``) is refused while the command
    line is read."""

    def __call__(self, parser, namespace, values, option_string=None):
        ids = split_ids(values)
        if not ids:
            raise argparse.ArgumentError(self, _none_given(values, None if self.required else option_string))
        setattr(namespace, self.dest, ids)


def selected_ids(args) -> list[str] | None:
    """The ids of ``--ids`` (None: not given, every example; given but empty: a UserError)."""
    values = getattr(args, "ids", None)
    return None if values is None else given_ids(values)


__all__ = ["IdList", "existing_folder", "given_ids", "input_folder", "int_at_least", "non_negative_int", "output_file",
           "output_folder", "positive_int", "selected_ids", "split_ids", "where_to_write", "writable"]
