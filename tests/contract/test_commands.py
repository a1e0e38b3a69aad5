"""The command line as a list of commands: every declared run function exists, names are unique, the shared
option groups read back the same way everywhere, and building the parser imports no heavy package."""

import subprocess
import sys

from rigidbench.cli import COMMANDS, build_parser
from rigidbench.commands import run_options
from rigidbench.executors import ProcessExecutor, RayExecutor
from rigidbench.registry import load_target


def all_commands(commands=COMMANDS, prefix=()):
    for command in commands:
        yield prefix + (command.name,), command
        yield from all_commands(command.subcommands, prefix + (command.name,))


def test_every_command_runs_a_function_that_exists_and_names_are_unique():
    names = [path for path, _ in all_commands()]
    assert len(names) == len(set(names))
    runnable = [(path, c) for path, c in all_commands() if not c.subcommands]
    assert {("render",), ("evaluate",), ("probe", "extract")} <= {path for path, _ in runnable}
    for path, command in runnable:
        assert callable(load_target(command.run, "command")), " ".join(path)


def test_selection_options_read_back_the_same_in_every_stage(tmp_path):
    parser = build_parser()
    for argv in (["evaluate", "preds", "--ids", "00001,00003", "00007", "--limit", "2", "--shard", "1/2"],
                 ["predict", "reference", "--ids", "00001,00003", "00007", "--limit", "2", "--shard", "1/2"],
                 ["preprocess", "--data", str(tmp_path), "--out", "c", "--ids", "00001,00003", "00007", "--limit",
                  "2", "--shard", "1/2"],  # (--data must be a folder that is there)
                 ["render", "--ids", "00001,00003", "00007", "--limit", "2", "--shard", "1/2"]):
        run = run_options(parser.parse_args(argv))
        selection = run.selection
        assert run.executor.in_process and run.progress and not run.wait, argv[0]
        assert selection.ids == ("00001", "00003", "00007") and selection.limit == 2, argv[0]
        assert (selection.shard.index, selection.shard.count) == (1, 2)
        assert selection.apply(["00001", "00002", "00003", "00007"], "here") == ["00003"]


def test_one_executor_per_command_from_its_options():
    """--executor ray gives every stage the same Ray executor (render's actors: --workers); otherwise the
    command's own executor (render's child processes) or this process; --no-progress and --wait travel too."""
    parser = build_parser()
    ray = run_options(parser.parse_args(["render", "--executor", "ray", "--ray-address", "auto", "--workers", "3"]),
                      local=ProcessExecutor(workers=3), actors=3)
    assert isinstance(ray.executor, RayExecutor) and not ray.executor.in_process
    assert (ray.executor.address, ray.executor.workers) == ("auto", 3)
    local = run_options(parser.parse_args(["render", "--workers", "2", "--no-progress", "--wait"]),
                        local=ProcessExecutor(workers=2))
    assert isinstance(local.executor, ProcessExecutor) and local.executor.workers == 2
    assert not local.executor.in_process and not local.progress and local.wait
    clips = run_options(parser.parse_args(["evaluate", "preds", "--limit", "5"]), limit=2)
    assert clips.selection.limit == 2 and clips.executor.in_process


def test_model_args_and_their_flag_aliases_parse():
    args = build_parser().parse_args(["predict", "wan-2.2", "--model-args", "offload=true", "--tiled-vae"])
    assert args.model_args == "offload=true" and args.tiled_vae is True and args.offload is False


def test_building_the_parser_imports_no_heavy_package():
    code = ("import sys; from rigidbench.cli import build_parser; build_parser(); "
            "print(sorted(m for m in ('torch', 'bpy', 'ray', 'diffusers', 'cv2', 'matplotlib', 'numpy') "
            "if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]"
