"""The ``rigidbench`` command. Subcommands import their stage lazily so ``--help`` is instant."""

from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path

DEFAULT_DATA = Path("data")


class UserError(Exception):
    """An error caused by the user's input: printed as one line, exit status 2."""


def _ids(value: str) -> list[str]:
    return [v.strip() for v in value.replace(",", " ").split() if v.strip()]


def _split_rows(args):
    from . import manifest
    from .config import registry

    reg = registry(args.config)
    rows = manifest.rows(args.split, reg)
    ids = [i for chunk in (args.ids or []) for i in _ids(chunk)]
    try:
        return reg, manifest.select(rows, ids or None, args.limit)
    except KeyError as exc:
        raise UserError(exc.args[0]) from None


# -- subcommands ---------------------------------------------------------------------------------


def cmd_manifest(args) -> int:
    from . import manifest
    from .config import registry

    rows = manifest.rows(args.split, registry(args.config))
    out = args.out or Path("manifests") / f"{args.split}.jsonl"
    manifest.write(out, rows)
    print(f"wrote {len(rows)} {args.split} rows to {out}")
    return 0


def cmd_simulate(args) -> int:
    from .blender.physics import simulate_rows

    reg, rows = _split_rows(args)
    out = args.out or DEFAULT_DATA / args.split
    failures = simulate_rows(rows, reg, Path(out))
    print(f"simulated {len(rows) - len(failures)} of {len(rows)} examples into {out}")
    for sample_id, reason in failures:
        print(f"  FAILED {sample_id}: {reason}", file=sys.stderr)
    return 1 if failures else 0


# -- parser --------------------------------------------------------------------------------------


def _add_selection(p: argparse.ArgumentParser, split_default: str = "eval") -> None:
    p.add_argument("--split", choices=("train", "eval"), default=split_default, help="manifest to draw examples from")
    p.add_argument("--ids", nargs="+", metavar="ID", help="sample ids, e.g. 00000 00007 (default: all)")
    p.add_argument("--limit", type=int, help="only the first N selected examples")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="rigidbench",
        description="RigidBench: simulator-grounded evaluation of rigid-body physics in video generation models.")
    parser.add_argument("--config", action="append", default=[], metavar="DIR",
                        help="extra configuration directory layered over the packaged configs (repeatable)")
    parser.add_argument("-v", "--verbose", action="store_true", help="log debug messages")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")

    p = sub.add_parser("manifest", help="write the fixed train (5,000) or eval (100) manifest as JSON Lines")
    p.add_argument("--split", choices=("train", "eval"), required=True)
    p.add_argument("--out", type=Path, help="output file (default manifests/<split>.jsonl)")
    p.set_defaults(func=cmd_manifest)

    p = sub.add_parser("simulate", help="simulate examples with Bullet (no rendering): scene_spec.json, "
                                        "trajectories.npz, contacts.json per example")
    _add_selection(p)
    p.add_argument("--out", type=Path, help="output directory (default data/<split>)")
    p.set_defaults(func=cmd_simulate)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.DEBUG if args.verbose else logging.INFO,
                        format="%(levelname)s %(name)s: %(message)s")
    if not getattr(args, "func", None):
        parser.print_help()
        return 0
    from .config import ConfigError

    try:
        return int(args.func(args) or 0)
    except (UserError, ConfigError) as exc:
        print(f"rigidbench {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"rigidbench {args.command}: interrupted; rerun the same command to resume", file=sys.stderr)
        return 130
