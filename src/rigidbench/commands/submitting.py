"""Commands that package and check a submission: submit, verify (docs/submitting.md)."""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

from ..argtypes import existing_folder, input_folder, non_negative_int, output_file, positive_int, writable
from ..context import RunContext
from ..errors import UserError
from . import Command


def _submit_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("run", type=Path, metavar="RUN", help="the run folder `rigidbench evaluate` wrote (runs/MODEL)")
    p.add_argument("--card", type=Path, required=True,
                   help="the submission card (YAML): what only you know about how the videos were made; "
                        "docs/card.example.yaml is a complete one")
    p.add_argument("--validate-only", action="store_true",
                   help="check the run and the card and list every problem; write nothing")
    p.add_argument("--videos", type=existing_folder, metavar="PREDICTIONS_DIR",
                   help="also bundle the clips the run scored (<id>.mp4), so that `rigidbench verify --rescore` can "
                        "score a subset again")
    p.add_argument("--out", type=output_file, metavar="FILE",
                   help="the bundle to write (default: submissions/<RUN folder name>.tar.gz)")


def cmd_submit(args, ctx: RunContext) -> int:
    from ..submissions.submit import prepare, write_bundle

    run = input_folder(args.run, "RUN", "the folder `rigidbench evaluate --out` wrote")
    if not args.card.is_file():
        raise UserError(f"--card {args.card}: {'is a folder' if args.card.is_dir() else 'no such file'}; pass a card "
                        "YAML file (docs/card.example.yaml is a complete one)")
    out = args.out or Path("submissions") / f"{run.resolve().name}.tar.gz"
    if not args.validate_only:
        writable(out, "--out", "file")
    prepared = prepare(run, args.card, ctx.config_dirs, args.videos)
    if prepared.problems:
        print(f"rigidbench submit: refused: {len(prepared.problems)} problem(s):", file=sys.stderr)
        for line in prepared.problems:
            print(line, file=sys.stderr)
        return 2
    n, videos = len(prepared.files.records), len(prepared.videos)
    if args.validate_only:
        print(f"{run}: can be submitted ({n} examples, {videos} videos); nothing written (--validate-only)")
        return 0
    write_bundle(prepared, out)
    print(f"wrote {out} ({n} examples, {videos} videos, {out.stat().st_size / 1e6:.1f} MB); check it with "
          f"`rigidbench verify {out}`")
    return 0


def _verify_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("submission", type=Path, metavar="SUBMISSION",
                   help="a bundle `rigidbench submit` wrote (.tar.gz), or its extracted folder")
    p.add_argument("--rescore", type=positive_int, metavar="N",
                   help="also score N examples drawn at random (seeded) again from the bundled videos, and compare")
    p.add_argument("--data", type=existing_folder, help="with --rescore: the reference set the submission was "
                                                        "scored on (a split directory or a data root)")
    p.add_argument("--seed", type=non_negative_int, default=0, help="with --rescore: the draw's seed (default 0)")
    p.add_argument("--device", dest="net_device", help="with --rescore: device of the perception networks "
                                                       "(default: CUDA when available)")


def rescore(sub, data: Path, n: int, seed: int = 0, *, perception_options: dict | None = None, nets=None,
            device: str | None = None) -> tuple[list[str], list[str]]:
    """Score ``n`` examples of the submission ``sub`` drawn with ``seed`` again from its videos, on ``data`` under
    its recorded protocol and perception (neural: its recorded depth model and input size), and compare with its
    records: (the ids scored again, one line per difference beyond the stated tolerance)."""
    from ..driver import RunOptions, Selection
    from ..jsonio import load_json
    from ..stages.evaluate import evaluate
    from ..submissions.verify import check_rescore_set, rescore_differences, rescore_ids

    split = check_rescore_set(sub, data)
    ids = rescore_ids(sub, n, seed)
    perception = str(sub.results.get("perception"))
    settings = (sub.provenance.get("perception") or {}).get("settings") or {}
    options = None
    if perception == "neural":
        options = {k: settings[k] for k in ("depth_model", "depth_input_size") if k in settings}
        options = {**options, "device": device, **(perception_options or {})}
    protocol = sub.results.get("protocol") or {}
    with tempfile.TemporaryDirectory(prefix="rigidbench-rescore-") as tmp:
        preds, out = Path(tmp) / "predictions", Path(tmp) / "run"
        preds.mkdir()
        for sample_id in ids:
            (preds / f"{sample_id}.mp4").symlink_to(Path(sub.videos[sample_id]).resolve())
        summary = evaluate(preds, split, out, perception=perception, nets=nets, device=device,
                           run=RunOptions(Selection(tuple(ids)), progress=False), perception_options=options,
                           model=sub.results.get("model"), protocol=protocol.get("name"),
                           first_frame_check=protocol.get("first_frame_check", True),
                           allow_short=protocol.get("allow_short", False))
        problems = [f"{sub.path}: {i}: could not be scored again: {why}" for i, why in summary.failed.items()]
        again = {i: load_json(out / "examples" / f"{i}.json", expect=dict) for i in ids if i not in summary.failed}
    return ids, problems + rescore_differences(sub, again)


def cmd_verify(args, ctx: RunContext) -> int:
    from ..submissions.bundle import load_submission, manifest_problems, submission_root
    from ..submissions.verify import RESCORE_ABS_TOL, RESCORE_REL_TOL, aggregate_problems

    if args.rescore and args.data is None:
        raise UserError("--rescore needs --data: the reference set the submission was scored on")
    problems = manifest_problems(submission_root(args.submission), str(args.submission))
    if not problems:
        sub = load_submission(args.submission)
        problems = aggregate_problems(sub)
    if problems:
        for line in problems:
            print(line)
        print(f"not verified: {len(problems)} mismatch(es)")
        return 1
    print(f"{args.submission}: manifest holds; every aggregate of results.json recomputed from the {len(sub.records)} "
          "records")
    if args.rescore:
        ids, problems = rescore(sub, args.data, args.rescore, args.seed, device=ctx.device)
        for line in problems:
            print(line)
        if problems:
            print(f"not verified: {len(problems)} difference(s) on re-scoring {', '.join(ids)}")
            return 1
        print(f"re-scored {', '.join(ids)}: every measurement within {RESCORE_REL_TOL:g} (relative) or "
              f"{RESCORE_ABS_TOL:g} (absolute) of its record")
    print("verified")
    return 0


COMMANDS = (
    Command("submit", "check a run and its submission card, and bundle them (results, per-example records, card "
                      "with the run's provenance, SHA-256 manifest; videos optional) (docs/submitting.md)",
            "rigidbench.commands.submitting:cmd_submit", _submit_arguments),
    Command("verify", "check a submission bundle: its manifest, every aggregate recomputed from its records, and "
                      "optionally a seeded subset scored again from its videos",
            "rigidbench.commands.submitting:cmd_verify", _verify_arguments),
)
