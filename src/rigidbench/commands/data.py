"""Commands that make reference data: download, import, manifest, simulate, render, show, inputs (their stages,
imported when a command runs: ``stages.import_set``, ``stages.simulate``, ``stages.render``)."""

from __future__ import annotations

import argparse
import json
import sys
from datetime import datetime, timezone
from pathlib import Path

from ..argtypes import IdList, output_file, output_folder, positive_int, split_ids, writable
from ..context import RunContext
from ..errors import UserError
from . import DEFAULT_DATA, Command, output_dir, report_stage, run_options, split_dir


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


def _finish(report, data: Path) -> int:
    """Print what the import did, write DATA/inputs.jsonl; exit status 1 when a sample failed."""
    from ..benchmark import write_inputs

    status = report_stage(report)
    if report.succeeded:
        inputs = write_inputs(data)
        print(f"model inputs: {inputs}")
        print(f"next: generate one video per line of {inputs} into predictions/MODEL/<id>.mp4, then "
              f"`rigidbench validate predictions/MODEL --data {data}` and "
              f"`rigidbench evaluate predictions/MODEL --data {data} --perception neural`")
    return status


def _say_deletable(folder: Path, extra: str = "") -> None:
    from ..datasets.archive import unshared_bytes
    from ..datasets.datadir import format_bytes

    print(f"{folder}: the bundles need nothing from it (frames and video are hard-linked or copied); deleting it "
          f"frees {format_bytes(unshared_bytes(folder))}{extra}")


def _imported_earlier(desc, data: Path) -> list[str] | None:
    """The samples a complete import of this download made, when they are all still in DATA/eval; else None."""
    from ..datasets.archive import IMPORTED
    from ..datasets.download import download_dir

    try:
        record = json.loads((download_dir(desc, data) / IMPORTED).read_text())
        ids = [str(i) for i in record["ids"]]
    except (OSError, ValueError, KeyError, TypeError):
        return None
    for sample_id in ids:
        try:
            meta = json.loads((data / "eval" / sample_id / "metadata.json").read_text())
        except (OSError, ValueError):
            return None
        if (meta.get("source") or {}).get("md5") != desc.md5:
            return None
    return ids or None


def cmd_download(args, ctx) -> int:
    from ..benchmark import write_inputs
    from ..datasets.archive import BY_DOWNLOAD, IMPORTED, NO_VERIFY, dataset_identity
    from ..datasets.datadir import data_lock, prepare_data_dir
    from ..datasets.describe import load_dataset
    from ..datasets.download import download_dataset, download_dir, extracted_dir, read_marker
    from ..jsonio import write_json
    from ..stages.import_set import import_published

    desc = load_dataset(args.dataset, ctx.config_dirs)
    data = prepare_data_dir(args.data)
    print(f"{desc.name} {desc.version}: {desc.size_bytes / 1e9:.1f} GB in {len(desc.parts)} parts ({desc.licence}"
          f"{', doi:' + desc.doi if desc.doi else ''})")
    with data_lock(data):
        if read_marker(desc, data) is not None and not extracted_dir(desc, data).is_dir():
            done = _imported_earlier(desc, data)
            if done is not None:
                print(f"{desc.id}: downloaded and imported before ({len(done)} samples in {data / 'eval'}); its "
                      "extraction was deleted since, so nothing is fetched")
                print(f"model inputs: {write_inputs(data)}")
                return 0
        extracted = download_dataset(desc, data, keep_archive=args.keep_archive, verify=not args.no_verify)
        verified = bool((read_marker(desc, data) or {}).get("md5_verified"))
        report = import_published(extracted, data, dataset=dataset_identity(desc, verified,
                                                                            BY_DOWNLOAD if verified else NO_VERIFY),
                                  registry=ctx.registry, run=run_options(args), config_dirs=ctx.config_dirs,
                                  replace=args.replace)
        status = _finish(report, data)
        if status == 0:
            write_json(download_dir(desc, data) / IMPORTED, {
                "id": desc.id, "md5": desc.md5, "ids": sorted(report.succeeded),
                "imported_at": datetime.now(timezone.utc).isoformat(timespec="seconds")})
            _say_deletable(extracted, "; `rigidbench download` will not fetch the archive again for it")
        return status


def cmd_import(args, ctx) -> int:
    from ..datasets.archive import (BY_IMPORT, archive_parts, dataset_identity, extract_checked,
                                   folder_verification)
    from ..datasets.datadir import data_lock, prepare_data_dir
    from ..datasets.describe import load_dataset
    from ..stages.import_set import import_published

    src = Path(args.src)
    if not src.exists():
        raise UserError(f"{src}: no such file or folder")
    desc = load_dataset(args.dataset, ctx.config_dirs)
    parts = archive_parts(src)
    data = prepare_data_dir(args.data)
    with data_lock(data):
        if parts is not None:
            src = extract_checked(parts, desc, data)
            verified, verification = True, BY_IMPORT
        else:
            verified, verification = folder_verification(src, desc, data)
        report = import_published(src, data, dataset=dataset_identity(desc, verified, verification),
                                  registry=ctx.registry, run=run_options(args), config_dirs=ctx.config_dirs,
                                  replace=args.replace)
        status = _finish(report, data)
        if not verified:
            print(f"note: the set's MD5 was not checked ({verification}); results on it are not official: import "
                  "its .tar.gz or parts, or download it, to check it")
        if status == 0 and parts is not None:
            _say_deletable(src)
        return status


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


def cmd_simulate(args, ctx: RunContext) -> int:
    from .. import manifest
    from ..stages.simulate import simulate_rows

    out = output_dir(args.out or DEFAULT_DATA / args.split)
    report = simulate_rows(manifest.rows(args.split, ctx.registry), ctx.registry, Path(out), run_options(args),
                           config_dirs=ctx.config_dirs)
    return report_stage(report)


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


def cmd_render(args: argparse.Namespace, ctx: RunContext) -> int:
    from .. import manifest
    from ..executors import ProcessExecutor
    from ..groundtruth import bundle as B
    from ..stages.render import RenderStage, render_stage, render_threads

    reg = ctx.registry
    if args.quality not in reg.presets:
        raise UserError(f"unknown quality '{args.quality}'; presets: {', '.join(reg.presets)}")
    data = Path(args.data)
    writable(data, "--data")
    if B.bundle_dirs(data):
        raise UserError(f"{data} holds bundles itself: it is a split directory, and render writes into "
                        f"DATA/<split>/; did you mean --data {data.parent}?")
    threads = render_threads(args.workers)
    stage = RenderStage(data, args.split, manifest.rows(args.split, reg), reg, args.quality, args.device, threads,
                        ctx.config_dirs)
    local = ProcessExecutor(workers=args.workers, quiet=not getattr(args, "verbose", False),
                            label=lambda task: task["id"])
    run = run_options(args, local=local, actors=args.workers if args.workers > 1 else None)
    return report_stage(render_stage(stage, run))


def cmd_show(args: argparse.Namespace, ctx: RunContext) -> int:
    """One contact sheet per id; an example whose bundle is missing or damaged is reported (naming the file
    and what to do) and the others are still written. Exit 1 when any failed."""
    from ..errors import EXAMPLE_ERRORS
    from ..groundtruth import bundle as B
    from ..groundtruth.contact_sheet import write_contact_sheet

    split_dir = B.resolve_split_dir(args.data, args.split)
    ids = split_ids(args.ids)
    if args.out is not None and len(ids) > 1 and Path(args.out).suffix.lower() == ".png":
        raise UserError(f"--out {args.out}: several examples need a folder for their sheets, not one PNG file")
    if args.out is not None:
        one_file = len(ids) == 1 and Path(args.out).suffix.lower() == ".png"
        writable(args.out, kind="file" if one_file else "folder")
    failed: dict[str, str] = {}
    for sample_id in ids:
        path = split_dir / sample_id
        name = f"{split_dir.name}_{sample_id}_contact_sheet.png"
        if args.out is None:
            out = Path(name)
        elif len(ids) == 1 and Path(args.out).suffix.lower() == ".png":
            out = Path(args.out)
        else:
            out = Path(args.out) / name
        try:
            if not path.is_dir():
                raise UserError(f"{path}: no bundle for example {sample_id}; render it first with "
                                f"`rigidbench render --split {split_dir.name} --ids {sample_id}`")
            out.parent.mkdir(parents=True, exist_ok=True)
            write_contact_sheet(B.Sample(path), out)
        except EXAMPLE_ERRORS as exc:
            failed[sample_id] = str(exc)
            print(f"FAILED {sample_id}: {exc}", file=sys.stderr)
            continue
        print(f"wrote {out}")
    if failed and len(ids) == 1:
        return 1
    if failed:
        print(f"{len(failed)} of {len(ids)} contact sheets failed", file=sys.stderr)
    return 1 if failed else 0


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
            "rigidbench.commands.data:cmd_download", _download_arguments),
    Command("import", "import a published evaluation set you downloaded by hand (the .tar.gz, its parts' folder, "
                      "or the extracted folder) into DATA/eval",
            "rigidbench.commands.data:cmd_import", _import_arguments, groups=("selection",)),
    Command("manifest", "write the fixed train (5,000) or eval (100) manifest as JSON Lines",
            "rigidbench.commands.data:cmd_manifest", _manifest_arguments),
    Command("simulate", "simulate examples with Bullet (no rendering): scene_spec.json, trajectories.npz, "
                        "contacts.json per example; reruns skip examples whose scene is unchanged",
            "rigidbench.commands.data:cmd_simulate", _simulate_arguments, groups=("manifest", "selection")),
    Command("render", "simulate and render examples into sample bundles (DATA/<split>/<id>/); reruns skip bundles "
                      "whose scene and preset are unchanged and render the others again",
            "rigidbench.commands.data:cmd_render", _render_arguments,
            groups=("manifest", "selection", "progress", "executor")),
    Command("show", "write a PNG contact sheet of a rendered example (frames, masks, depth, ground-truth tracks)",
            "rigidbench.commands.data:cmd_show", _show_arguments),
    Command("inputs", "write inputs.jsonl: first frame, prompt and negative prompt per example",
            "rigidbench.commands.data:cmd_inputs", _inputs_arguments, groups=("data",)),
)
