"""Commands that make reference data: download, import, manifest, simulate, render, show, inputs."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from ..argtypes import IdList, output_file, output_folder, positive_int, writable
from ..context import RunContext
from ..errors import UserError
from . import DEFAULT_DATA, Command, output_dir, selected_ids, split_dir


def _published_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--data", type=output_folder, default=DEFAULT_DATA,
                   help="data root (default: data); bundles go to DATA/eval")
    p.add_argument("--replace", action="store_true",
                   help="delete the examples in DATA/eval that come from another source (another set or release, "
                        "rendered bundles) instead of refusing to mix them with this one")


def _download_arguments(p: argparse.ArgumentParser) -> None:
    _published_arguments(p)
    p.add_argument("--dataset", help="dataset id or name from configs/datasets (default: the newest published set)")
    p.add_argument("--keep-archive", action="store_true", help="keep the downloaded parts after extraction")
    p.add_argument("--no-verify", action="store_true", help="skip the archive's MD5 check (not recommended)")


def _import_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("src", type=Path, help="the archive (.tar.gz), or the folder it was extracted into")
    _published_arguments(p)
    p.add_argument("--dataset", help="which published set this is: an archive is checked against its MD5, and the "
                                     "bundles record it (default: the newest described)")


def _manifest_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--split", choices=("train", "eval"), required=True)
    p.add_argument("--out", type=output_file, help="output file (default manifests/<split>.jsonl)")


def cmd_manifest(args, ctx: RunContext) -> int:
    from .. import manifest

    out = writable(args.out or Path("manifests") / f"{args.split}.jsonl", kind="file")
    rows = manifest.rows(args.split, ctx.registry)
    manifest.write(out, rows)
    print(f"wrote {len(rows)} {args.split} rows to {out}")
    return 0


def _simulate_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--out", type=output_folder, help="output directory (default data/<split>)")


def manifest_rows(args, ctx: RunContext):
    """The manifest rows of --split selected by --ids and --limit (an unknown id is a UserError)."""
    from .. import manifest

    try:
        return manifest.select(manifest.rows(args.split, ctx.registry), selected_ids(args), args.limit)
    except KeyError as exc:
        raise UserError(exc.args[0]) from None


def cmd_simulate(args, ctx: RunContext) -> int:
    from ..pipeline.simulate import simulate_rows

    out = output_dir(args.out or DEFAULT_DATA / args.split)
    rows = manifest_rows(args, ctx)
    failures, skipped = simulate_rows(rows, ctx.registry, Path(out), config_dirs=ctx.config_dirs)
    print(f"simulated {len(rows) - len(failures) - len(skipped)} of {len(rows)} examples into {out} "
          f"({len(skipped)} already done)")
    for sample_id, reason in failures:
        print(f"  FAILED {sample_id}: {reason}", file=sys.stderr)
    return 1 if failures else 0


def _render_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--quality", default="paper", help="render preset: paper, preview or test (configs/render.yaml)")
    p.add_argument("--data", type=Path, default=DEFAULT_DATA, help="data directory (default: data)")
    p.add_argument("--workers", type=positive_int, default=1,
                   help="examples rendered at once, one process each (default 1)")
    p.add_argument("--device", choices=("auto", "cpu", "gpu"), default="auto",
                   help="Cycles device: auto picks OptiX, then CUDA, then the CPU (default auto)")


def _show_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("ids", nargs="+", action=IdList, metavar="ID", help="sample id(s), e.g. 00000 00007")
    p.add_argument("--data", type=Path, default=DEFAULT_DATA,
                   help="reference bundles: a split directory (data/eval) or a data root (data) with --split "
                        "(default: data)")
    p.add_argument("--split", choices=("train", "eval"),
                   help="split under a data root (default: the only split present)")
    p.add_argument("--out", type=Path, help="output PNG for one id, or a folder for the sheets (default: "
                                            "<split>_<id>_contact_sheet.png here)")


def _inputs_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--out", type=output_file,
                   help="output file (default DATA/inputs.jsonl beside DATA/eval, where `download` and `import` "
                        "write it; DIR/inputs.jsonl for a split directory DIR not named eval)")


def cmd_inputs(args, ctx: RunContext) -> int:
    from ..benchmark import write_inputs

    try:
        out = write_inputs(split_dir(args), args.out)
    except FileNotFoundError as exc:
        raise UserError(str(exc)) from None
    print(f"wrote {out}")
    return 0


COMMANDS = (
    Command("download", "the paper's published evaluation set: download (resumable), verify, extract and import "
                        "into DATA/eval (about 37 GB of free disk while it runs)",
            "rigidbench.datasets.commands:cmd_download", _download_arguments),
    Command("import", "import a published evaluation set you downloaded by hand (the .tar.gz, its parts' folder, "
                      "or the extracted folder) into DATA/eval",
            "rigidbench.datasets.commands:cmd_import", _import_arguments, groups=("selection",)),
    Command("manifest", "write the fixed train (5,000) or eval (100) manifest as JSON Lines",
            "rigidbench.commands.data:cmd_manifest", _manifest_arguments),
    Command("simulate", "simulate examples with Bullet (no rendering): scene_spec.json, trajectories.npz, "
                        "contacts.json per example; reruns skip examples whose scene is unchanged",
            "rigidbench.commands.data:cmd_simulate", _simulate_arguments, groups=("manifest", "selection")),
    Command("render", "simulate and render examples into sample bundles (DATA/<split>/<id>/); reruns skip bundles "
                      "whose scene and preset are unchanged and render the others again",
            "rigidbench.pipeline.render:cmd_render", _render_arguments,
            groups=("manifest", "selection", "progress", "executor")),
    Command("show", "write a PNG contact sheet of a rendered example (frames, masks, depth, ground-truth tracks)",
            "rigidbench.pipeline.render:cmd_show", _show_arguments),
    Command("inputs", "write inputs.jsonl: first frame, prompt and negative prompt per example",
            "rigidbench.commands.data:cmd_inputs", _inputs_arguments, groups=("data",)),
)
