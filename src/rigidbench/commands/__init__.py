"""The command line as a list of commands, each declared one way, and the option groups they share.

A command is a ``Command``: its name, help, a function adding its own arguments, the option groups it takes
(declared once here: which examples, which reference data, which executor, which model options) and its
run function, ``"module:function"`` taking ``(args, ctx)``, imported only when the command runs so that
``rigidbench --help`` stays instant. The command modules (``commands.data``, ``commands.models``,
``commands.scoring``, ``commands.training``, ``commands.probing``) each export ``COMMANDS``; ``cli.py`` builds the
parser from them in order. This package is the command line: like ``cli.py`` it imports the stages it runs
lazily, inside the run functions.
"""

from __future__ import annotations

import argparse
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

from ..argtypes import IdList, positive_int, selected_ids, split_ids, writable
from ..context import RunContext
from ..driver import RunOptions, Selection, StageReport
from ..errors import UserError
from ..executors import Executor, RayExecutor, make_executor
from ..registry import load_target

DEFAULT_DATA = Path("data")

Arguments = Callable[[argparse.ArgumentParser], None]


def _no_arguments(p: argparse.ArgumentParser) -> None:
    pass


@dataclass(frozen=True)
class Command:
    """One ``rigidbench`` command: ``groups`` are option groups of ``GROUPS`` (added before ``arguments``);
    ``run``: "module:function" of ``f(args, ctx) -> exit status``; ``subcommands``: for a command group
    such as ``probe`` (then ``run`` is unused)."""

    name: str
    help: str
    run: str = ""
    arguments: Arguments = _no_arguments
    groups: tuple[str, ...] = ()
    subcommands: tuple["Command", ...] = field(default_factory=tuple)

    def add_to(self, subparsers) -> argparse.ArgumentParser:
        p = subparsers.add_parser(self.name, help=self.help, description=self.help)
        for group in self.groups:
            GROUPS[group](p)
        self.arguments(p)
        if self.subcommands:
            sub = p.add_subparsers(dest=f"{self.name}_command", metavar="COMMAND", required=True)
            for command in self.subcommands:
                command.add_to(sub)
        else:
            p.set_defaults(func=lazy(self.run))
        return p


def lazy(target: str):
    """A run function ``f(args, ctx)`` imported only when its command runs."""
    def run(args, ctx: RunContext):
        return load_target(target, "command")(args, ctx)

    return run


# -- option groups, declared once ------------------------------------------------------------------------


def selection_options(p: argparse.ArgumentParser) -> None:
    """--ids and --limit: which examples a stage runs; --wait: what it does with those another process is making."""
    p.add_argument("--ids", nargs="+", action=IdList, metavar="ID",
                   help="sample ids, e.g. 00000 00007 or 00000,00007 (default: all)")
    p.add_argument("--limit", type=positive_int, help="only the first N selected examples")
    p.add_argument("--wait", action="store_true",
                   help="wait for the examples another process is making in the same output folder (default: "
                        "skip them and say so)")


def manifest_options(p: argparse.ArgumentParser) -> None:
    """--split of a command that draws its examples from a manifest (render, simulate)."""
    p.add_argument("--split", choices=("train", "eval"), default="eval", help="manifest to draw examples from")


def data_options(p: argparse.ArgumentParser) -> None:
    """--data and --split for a command that reads reference bundles (one convention for all of them)."""
    p.add_argument("--data", type=Path, default=DEFAULT_DATA,
                   help="reference bundles: a split directory (data/eval) or a data root (data) with --split "
                        "(default: data)")
    p.add_argument("--split", choices=("train", "eval"),
                   help="split under a data root (default: the only split present)")


def executor_options(p: argparse.ArgumentParser) -> None:
    """--executor, --ray-address and --shard: how and which part of a stage's examples run."""
    p.add_argument("--executor", choices=("local", "ray"), default="local",
                   help="local: this machine; ray: one task per example on a Ray cluster (outputs go to a directory "
                        "every node sees)")
    p.add_argument("--ray-address", help="Ray cluster to join (default: $RAY_ADDRESS, else a local Ray)")
    p.add_argument("--shard", metavar="I/N", help="only the I-th of N deterministic parts of the examples "
                                                  "(0-based; for job arrays), e.g. --shard 0/4")


def model_options(p: argparse.ArgumentParser) -> None:
    """Options of video models: --model-args KEY=VALUE,... (each model's own typed options; `rigidbench predict
    --list` shows them), and the older flags, kept as aliases of model arguments."""
    p.add_argument("--severity", type=float, default=1.0,
                   help="failure modes: 0 = the reference, 1 = strong (default 1)")
    p.add_argument("--seed", type=int, default=0, help="base seed for video models: each example gets its own, "
                                                       "derived from this and its id (default 0)")
    p.add_argument("--device", dest="net_device", help="local models and networks: cuda or cpu (default: CUDA "
                                                       "when available)")
    p.add_argument("--model-args", metavar="KEY=VALUE,...",
                   help="the model's own options, e.g. offload=true,checkpoint=lora.safetensors (predict --list "
                        "shows each model's options); the flags below are aliases")
    aliases = p.add_argument_group("model options as flags (aliases of --model-args)")
    aliases.add_argument("--concurrency", type=positive_int, help="hosted models: concurrency=N, predictions in "
                                                                   "flight at once (default 8)")
    aliases.add_argument("--repay-expired", action="store_true",
                         help="hosted models: repay_expired=true, pay for a new prediction when a paid one's output "
                              "has expired at the API")
    aliases.add_argument("--offload", action="store_true", help="local models: offload=true, model CPU offload "
                                                                "(smaller GPUs)")
    aliases.add_argument("--tiled-vae", action="store_true", help="local models: tiled_vae=true, tiled VAE decoding "
                                                                  "(smaller GPUs)")
    aliases.add_argument("--checkpoint", type=Path, help="wan-2.2: checkpoint=PATH, a LoRA adapter or a full "
                                                         "fine-tuned transformer")
    aliases.add_argument("--sampler", choices=("flow-euler", "unipc"),
                         help="wan-2.2: sampler=flow-euler (default; the paper's runs: DiffSynth's flow-matching "
                              "Euler schedule, shift 5) or unipc (the Diffusers repository's scheduler)")
    aliases.add_argument("--model-path", type=Path, help="local models: model_path=DIR, weights from this directory "
                                                         "instead of the hub")
    aliases.add_argument("--no-guardrail", action="store_true",
                         help="cosmos-2.5: no_guardrail=true, replace the Cosmos guardrail with a pass-through (you "
                              "take on its licence terms)")


def progress_options(p: argparse.ArgumentParser) -> None:
    p.add_argument("--no-progress", action="store_true", help="no progress bars")


GROUPS: dict[str, Arguments] = {"selection": selection_options, "manifest": manifest_options, "data": data_options,
                                "executor": executor_options, "model": model_options, "progress": progress_options}

# -- reading the groups back -----------------------------------------------------------------------------


def run_options(args, *, local: Executor | None = None, actors: int | None = None,
                limit: int | None = None) -> RunOptions:
    """How a command runs its stage, built once from its arguments: the ``Selection`` of --ids, --limit (or
    ``limit``, a command's own count such as ``--clips``) and --shard; one executor of --executor and
    --ray-address (``local``: the command's own executor when it runs here, e.g. render's child processes;
    ``actors``: Ray actors to start, default as many as fit); --no-progress; --wait."""
    selection = Selection.of(selected_ids(args), limit if limit is not None else getattr(args, "limit", None),
                             getattr(args, "shard", None))
    if getattr(args, "executor", "local") == "ray":
        executor: Executor | None = RayExecutor(address=getattr(args, "ray_address", None), workers=actors)
    elif local is not None:
        executor = local
    else:
        executor = make_executor("local")
    return RunOptions(selection, executor, progress=not getattr(args, "no_progress", False),
                      wait=bool(getattr(args, "wait", False)))


def report_stage(report: StageReport) -> int:
    """Print what a stage run did, the same words for every stage (``StageReport.lines``); returns the
    command's exit status (1 when any example failed or did not start)."""
    out, err = report.lines()
    for line in out:
        print(line)
    for line in err:
        print(line, file=sys.stderr)
    return report.exit_status()


def split_dir(args) -> Path:
    """The reference split directory ``--data`` (and ``--split``) name; BundleError with a did-you-mean, or
    naming `rigidbench import` when ``--data`` is in the published archive's own layout."""
    from ..groundtruth.bundle import resolve_split_dir  # numpy: not needed for --help

    data = Path(args.data)
    if data.exists() and not data.is_dir():
        raise UserError(f"--data {data}: is a file, not a folder; pass the folder of reference bundles (a split "
                        "directory such as data/eval, or a data root such as data)")
    return resolve_split_dir(args.data, getattr(args, "split", None))


def output_dir(path: Path, option: str = "--out", *, dry_run: bool = False) -> Path:
    """A directory to write into: UserError when ``path`` is an existing file (not a folder) or nothing can be
    written there (``argtypes.where_to_write``: read-only, not writable, a file above it); ``dry_run``: only
    the first (nothing will be written)."""
    if not dry_run:
        return writable(path, option)
    if path.exists() and not path.is_dir():
        raise UserError(f"{option} {path}: is a file, not a folder; pass a folder for the outputs")
    return path


__all__ = ["Command", "DEFAULT_DATA", "GROUPS", "lazy", "output_dir", "report_stage", "run_options", "selected_ids",
           "split_dir", "split_ids"]
