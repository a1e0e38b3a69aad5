"""The ``rigidbench`` command: the parser is built from the command list (``COMMANDS``), each command declared
one way in its module (``commands.Command``); a command's stage is imported only when it runs, so ``--help`` is
instant."""

from __future__ import annotations

import argparse
import logging
import os
import sys
from pathlib import Path

from .atomic import WRITE_ERRNOS, describe_os_error
from .commands import (Command, data as data_commands, models as model_commands, probing as probe_commands,
                       scoring as scoring_commands, training as train_commands)
from .commands import envelope as envelope_commands
from .commands import leaderboard as leaderboard_commands
from .commands import submitting as submit_commands
from .context import RunContext
from .errors import RigidBenchError, UserError
from .extras import explain
from .logsafe import configure_logging

CONFIG_PATH_ENV = "RIGIDBENCH_CONFIG_PATH"

#: Every command, in the order ``rigidbench --help`` lists them.
COMMANDS: tuple[Command, ...] = (data_commands.COMMANDS + model_commands.COMMANDS + scoring_commands.COMMANDS
                                 + envelope_commands.COMMANDS
                                 + train_commands.COMMANDS + probe_commands.COMMANDS + submit_commands.COMMANDS
                                 + leaderboard_commands.COMMANDS)


def build_context(args) -> RunContext:
    """The run context of one command: $RIGIDBENCH_CONFIG_PATH, then each --config, layered over the packaged
    configs (the only place the environment variable is read); ConfigError names a missing directory."""
    from .config import config_dirs

    env = [Path(p) for p in os.environ.get(CONFIG_PATH_ENV, "").split(os.pathsep) if p]
    dirs = tuple(p.resolve() for p in env + [Path(d) for d in args.config])
    config_dirs(dirs)  # check they exist before any work starts
    return RunContext(config_dirs=dirs, device=getattr(args, "net_device", None))


def load_plugins(modules) -> None:
    """Import each plug-in module (it registers its entries when imported); a missing one is a UserError."""
    import importlib

    for name in modules:
        try:
            importlib.import_module(name)
        except ModuleNotFoundError as exc:
            if exc.name and name.startswith(exc.name):
                raise UserError(f"--plugin {name}: no module named '{exc.name}' (is it installed or on "
                                "PYTHONPATH?)") from None
            raise


class Parser(argparse.ArgumentParser):
    """argparse whose refusal of a command line is one line, as every other user error:
    ``rigidbench CMD: error: argument --limit: ... (rigidbench CMD --help)``, exit status 2."""

    def error(self, message: str):
        self.exit(2, f"{self.prog}: error: {message} (see {self.prog} --help)\n")


def build_parser() -> argparse.ArgumentParser:
    parser = Parser(
        prog="rigidbench",
        description="RigidBench: simulator-grounded evaluation of rigid-body physics in video generation models.")
    parser.add_argument("--config", action="append", default=[], metavar="DIR",
                        help="extra configuration directory layered over the packaged configs and "
                             "$RIGIDBENCH_CONFIG_PATH, for every stage of the command (repeatable)")
    parser.add_argument("--plugin", action="append", default=[], metavar="MODULE",
                        help="import MODULE first, so the metrics, predictors or perception backends it registers "
                             "are available to the command (repeatable)")
    parser.add_argument("-v", "--verbose", action="store_true", help="log debug messages")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for command in COMMANDS:
        command.add_to(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    configure_logging(logging.DEBUG if args.verbose else logging.INFO)  # HTTP libraries quiet, URLs scrubbed
    if not getattr(args, "func", None):
        parser.print_help()
        return 0
    try:
        ctx = build_context(args)
        load_plugins(args.plugin)
        return int(args.func(args, ctx) or 0)
    except RigidBenchError as exc:
        print(f"rigidbench {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except OSError as exc:  # an output that cannot be written (a full disk, a read-only folder, ...): one line
        if exc.errno not in WRITE_ERRNOS:
            raise
        print(f"rigidbench {args.command}: error: {describe_os_error(exc)}", file=sys.stderr)
        return 2
    except ModuleNotFoundError as exc:  # an optional package not installed: one line naming its extra
        line = explain(exc, "this command")
        if line is None:
            raise
        print(f"rigidbench {args.command}: error: {line}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"rigidbench {args.command}: interrupted; rerun the same command to resume", file=sys.stderr)
        return 130
