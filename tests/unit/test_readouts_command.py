"""`rigidbench readouts RUN`: what it prints for a run scored with readouts (results.json holds the block) and
for an older run without the block (recomputed from the per-example readouts files), on hand-built run
folders whose medians, quartiles and flag counts are computed here independently."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from rigidbench.cli import main
from rigidbench.readouts.flags import FLAGS

#: id -> (task, partition, speed, gravity, gravity per speed^2, restitution, raised flags, undefined flags)
EXAMPLES = {
    "00000": ("bounce", "p1", 1.0, 9.7, 9.7, 0.5, [], ["identity"]),
    "00001": ("bounce", "p1", 0.5, None, None, None, [], ["identity"]),
    "00002": ("free_fall", "p2", 0.0, None, None, None, ["frozen"], ["identity"]),
    "00003": ("free_fall", "p2", 2.0, 40.0, 10.0, None, ["camera", "through_support"], ["identity", "frozen"]),
}


def readouts_file(sample_id: str) -> dict:
    task, partition, s, g, gs, e, raised, undefined = EXAMPLES[sample_id]
    flags = {f: (None if f in undefined else f in raised) for f in FLAGS}
    return {"id": sample_id, "task": task, "partition": partition,
            "readouts": {"speed": {"value": s, "reason": None}, "gravity": {"value": g, "per_speed2": gs},
                         "restitution": {"value": e}, "flags": {"example": flags, "raised": raised}}}


def write_run(run, with_block: dict | None = None):
    (run / "examples").mkdir(parents=True)
    for sample_id, (task, partition, *_) in EXAMPLES.items():
        record = {"id": sample_id, "task": task, "partition": partition, "metrics": {"ate": 0.1}}
        (run / "examples" / f"{sample_id}.json").write_text(json.dumps(record))
        (run / "examples" / f"{sample_id}.readouts.json").write_text(json.dumps(readouts_file(sample_id)))
    if with_block is not None:
        (run / "results.json").write_text(json.dumps({"model": "stored-model", "readouts": with_block}))
    return run


def cell(values) -> str:
    """The printed distribution of the values (None = undefined), computed without the package."""
    finite = [v for v in values if v is not None]
    if not finite:
        return "-"
    q25, med, q75 = np.percentile(finite, [25, 50, 75])
    return f"{med:.3g} [{q25:.3g}, {q75:.3g}] ({len(finite)}/{len(values)})"


def column(index: int, ids=None) -> list:
    return [EXAMPLES[i][index] for i in (ids or EXAMPLES)]


def run_command(capsys, *argv) -> tuple[int, list[str], str]:
    code = main(["readouts", *map(str, argv)])
    out = capsys.readouterr()
    return code, out.out.splitlines(), out.err


def test_an_older_run_without_the_block_is_recomputed_from_its_readouts_files(tmp_path, capsys):
    run = write_run(tmp_path / "runs" / "old-model")
    code, lines, _ = run_command(capsys, run, "--examples")
    assert code == 0
    assert lines[0].startswith("old-model: readouts of 4 examples")  # the folder names the model
    overall = next(line for line in lines if line.strip().startswith("overall"))
    assert overall.split()[1:] == " ".join(cell(column(i)) for i in (2, 3, 4, 5)).split()
    by_task = {t: [i for i in EXAMPLES if EXAMPLES[i][0] == t] for t in ("bounce", "free_fall")}
    for task, ids in by_task.items():
        row = next(line for line in lines if line.strip().startswith(f"task {task}"))
        assert row.split()[2:] == " ".join(cell(column(i, ids)) for i in (2, 3, 4, 5)).split()
    flags = next(line for line in lines if "flags (raised/defined)" in line)
    for flag in FLAGS:
        raised = sum(flag in EXAMPLES[i][6] for i in EXAMPLES)
        defined = sum(flag not in EXAMPLES[i][7] for i in EXAMPLES)
        assert f"{flag} {raised}/{defined}" in flags
    # --examples: one line per example with its values and raised flags
    for sample_id, (task, _, s, g, gs, e, raised, _) in EXAMPLES.items():
        line = next(x for x in lines if x.strip().startswith(f"{sample_id} ({task})"))
        shown = ", ".join(f"{k} {'-' if v is None else format(v, '.3g')}"
                          for k, v in zip(("speed", "gravity", "gravity_per_speed2", "restitution"), (s, g, gs, e)))
        assert shown in line
        assert line.endswith(f"flags: {', '.join(f for f in FLAGS if f in raised) or 'none'}")  # in FLAGS order


def test_a_run_with_the_block_prints_the_stored_block_not_a_recomputation(tmp_path, capsys):
    # the stored block says 1 example with speed 7: a recomputation from the 4 files would say otherwise
    stored = {"n": 1, "missing": [], "fit": "frame0",
              "overall": {"speed": {"median": 7.0, "q25": 7.0, "q75": 7.0, "iqr": 0.0, "finite": 1, "n": 1},
                          "flags": {f: {"raised": 0, "defined": 1, "rate": 0.0} for f in FLAGS}},
              "by_task": {}, "by_partition": {}}
    run = write_run(tmp_path / "runs" / "dir-name", with_block=stored)
    code, lines, _ = run_command(capsys, run)
    assert code == 0
    assert lines[0].startswith("stored-model: readouts of 1 examples")
    overall = next(line for line in lines if line.strip().startswith("overall"))
    assert overall.split()[1:5] == ["7", "[7,", "7]", "(1/1)"] and overall.split()[5:] == ["-"] * 3
    assert not any(line.strip().startswith("task ") for line in lines)


def test_the_block_the_evaluator_would_store_matches_the_recomputation(tmp_path):
    """Both branches agree: the block aggregate_readouts writes into results.json from the score records'
    compact entries equals the one recomputed from the readouts files of an older run."""
    from rigidbench.readouts.records import aggregate_readouts, load_run_readouts, summary

    run = write_run(tmp_path / "run")
    records = [{"id": i, "task": EXAMPLES[i][0], "partition": EXAMPLES[i][1],
                "readouts": summary(readouts_file(i)["readouts"])} for i in EXAMPLES]
    _, block, examples = load_run_readouts(run)
    assert [e["id"] for e in examples] == list(EXAMPLES)
    stored = aggregate_readouts(records)
    assert {k: block[k] for k in stored} == stored
    assert block["overall"]["speed"]["median"] == pytest.approx(np.median(column(2)))
    assert math.isclose(block["overall"]["gravity_per_speed2"]["iqr"], 0.15)  # quartiles of (9.7, 10.0): 9.775, 9.925


def test_a_folder_that_is_not_a_run_is_one_error_line(tmp_path, capsys):
    (tmp_path / "empty").mkdir()
    code, lines, err = run_command(capsys, tmp_path / "empty")
    assert code == 2 and lines == []
    assert err.strip().count("\n") == 0 and "not a run folder" in err and "rigidbench evaluate" in err
