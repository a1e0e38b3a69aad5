"""The stage driver: selection, the one resume rule (same key -> skipped, other key -> redone and said),
atomic commit through staging, failure records, and the same outputs through every executor."""

import json
import os
from pathlib import Path

import pytest

from rigidbench.driver import (Adopted, ItemRunner, Redo, RunOptions, Selection, StageReport, Why, commit, ledger_path,
                               read_ledger, run_stage, staging_path, validate_selection)
from rigidbench.errors import UserError
from rigidbench.executors import LocalExecutor, ProcessExecutor, Shard

from fixtures import child_env
from fixtures.children import kill_when, python
from fixtures.toy_stage import ToyStage, calls

PAYLOADS = {"a": {"n": 1}, "b": {"n": 2}, "c": {"n": 3}, "d": {"n": 4}}


def outputs(root: Path) -> dict:
    return {p.relative_to(root).as_posix(): p.read_text() for p in sorted((root / "out").rglob("*")) if p.is_file()}


def test_selection_orders_limits_shards_and_names_unknown_ids():
    ids = ["a", "b", "c", "d", "e"]
    assert Selection.of(["d", "b"]).apply(ids, "x") == ["b", "d"]  # the stage's order, not the caller's
    assert Selection.of(limit=3).apply(ids, "x") == ["a", "b", "c"]
    parts = [Selection.of(shard=f"{i}/2").apply(ids, "x") for i in range(2)]
    assert parts == [["a", "c", "e"], ["b", "d"]]
    with pytest.raises(UserError, match=r"unknown example id\(s\) zz in data/eval \(ids run from a to e\)"):
        Selection.of(["a", "zz"]).apply(ids, "data/eval")


def test_rerun_skips_changed_settings_redo_exactly_the_changed_items(tmp_path):
    first = run_stage(ToyStage(tmp_path, PAYLOADS), RunOptions(progress=False))
    assert first.ran == ["a", "b", "c", "d"] and not first.reused and not first.failed
    assert outputs(tmp_path)["out/c.txt"] == "6" and outputs(tmp_path)["out/c.dir/value"] == "6"
    again = run_stage(ToyStage(tmp_path, PAYLOADS), RunOptions(progress=False))
    assert again.ran == [] and again.reused == ["a", "b", "c", "d"]
    assert again.results["b"] == {"value": 4}
    assert calls(tmp_path) == ["a", "b", "c", "d"]  # nothing ran twice
    changed = dict(PAYLOADS, b={"n": 20})
    third = run_stage(ToyStage(tmp_path, changed), RunOptions(progress=False))
    assert third.ran == ["b"] and third.redone == {"b": "its inputs or settings changed"}
    assert outputs(tmp_path)["out/b.txt"] == "40"
    fourth = run_stage(ToyStage(tmp_path, changed, factor=3), RunOptions(progress=False))  # a setting every item shares
    assert fourth.ran == ["a", "b", "c", "d"] and outputs(tmp_path)["out/d.txt"] == "12"


def test_a_bad_example_is_recorded_and_retried_and_the_others_go_on(tmp_path):
    payloads = dict(PAYLOADS, b={"n": 2, "bad": True})
    report = run_stage(ToyStage(tmp_path, payloads), RunOptions(progress=False))
    assert report.ran == ["a", "c", "d"] and report.failed == {"b": "example b: bad input"}
    entry = read_ledger(tmp_path, "toy", "b")
    assert entry["status"] == "failed" and entry["error"] == "example b: bad input"
    assert not (tmp_path / "out" / "b.txt").exists() and not (tmp_path / "out" / "b.dir").exists()
    fixed = run_stage(ToyStage(tmp_path, PAYLOADS), RunOptions(progress=False))
    assert fixed.ran == ["b"] and fixed.redone["b"] == "its inputs or settings changed"
    retried = run_stage(ToyStage(tmp_path / "r", payloads), RunOptions(progress=False))
    again = run_stage(ToyStage(tmp_path / "r", payloads), RunOptions(progress=False))
    assert retried.failed and again.redone["b"].startswith("it failed before (example b: bad input)")


def test_missing_output_or_damaged_ledger_runs_the_item_again(tmp_path):
    run_stage(ToyStage(tmp_path, PAYLOADS), RunOptions(progress=False))
    (tmp_path / "out" / "a.txt").unlink()
    ledger_path(tmp_path, "toy", "c").write_text("{trunc")
    report = run_stage(ToyStage(tmp_path, PAYLOADS), RunOptions(progress=False))
    assert report.ran == ["a", "c"] and report.redone == {"a": "its output is missing or damaged"}
    assert outputs(tmp_path)["out/a.txt"] == "2"


def test_a_killed_run_resumes_without_redoing_committed_items(tmp_path):
    """A run killed mid-example (SIGKILL) leaves its staging behind and commits nothing of that example;
    the rerun cleans it, runs the unfinished examples only, and the outputs equal an uninterrupted run's."""
    payloads = dict(PAYLOADS, c={"n": 3, "slow": 30})
    code = ("from pathlib import Path; "
            "from rigidbench.driver import RunOptions, run_stage; from fixtures.toy_stage import ToyStage; "
            f"run_stage(ToyStage(Path({str(tmp_path)!r}), {payloads!r}), RunOptions(progress=False))")
    staging = staging_path(tmp_path, "toy", "c")
    kill_when(python(code), (staging / "out" / "c.dir").exists)
    assert calls(tmp_path) == ["a", "b"] and not (tmp_path / "out" / "c.dir").exists()
    report = run_stage(ToyStage(tmp_path, PAYLOADS), RunOptions(progress=False))
    assert report.reused == ["a", "b"] and report.ran == ["c", "d"]
    assert not staging.exists()
    clean = tmp_path / "clean"
    run_stage(ToyStage(clean, PAYLOADS), RunOptions(progress=False))
    assert outputs(tmp_path) == outputs(clean)


def test_process_executor_gives_the_same_outputs_and_a_crash_fails_only_its_item(tmp_path, monkeypatch):
    monkeypatch.setenv("PYTHONPATH", child_env()["PYTHONPATH"])
    run_stage(ToyStage(tmp_path / "local", PAYLOADS), RunOptions(progress=False))
    steps = []
    payloads = dict(PAYLOADS, d={"n": 4, "crash": True})
    executor = ProcessExecutor(workers=2)
    stage = ToyStage(tmp_path / "proc", payloads)
    report = run_stage(stage, RunOptions(executor=executor, progress=False))
    assert sorted(report.ran) == ["a", "b", "c"] and "exited with code 3" in report.failed["d"]
    local = outputs(tmp_path / "local")
    assert outputs(tmp_path / "proc") == {k: v for k, v in local.items() if not k.startswith("out/d")}
    # progress comes back from the children
    tasks = [{"id": "a", "payload": {"n": 1}, "key": "other"}]
    executor.map("rigidbench.driver:ItemRunner", {"stage": "toy", "root": str(stage.root),
                                                  "worker": stage.worker, "job": stage.job()},
                 tasks, on_progress=lambda item, done, total: steps.append((item["id"], done, total)))
    assert steps == [("a", 1, 3), ("a", 2, 3), ("a", 3, 3)]


def test_shards_partition_the_work_and_a_final_run_reuses_all(tmp_path):
    for i in range(2):
        run_stage(ToyStage(tmp_path, PAYLOADS), RunOptions(Selection.of(shard=Shard(i, 2)), progress=False))
    final = run_stage(ToyStage(tmp_path, PAYLOADS), RunOptions(progress=False))
    assert final.reused == ["a", "b", "c", "d"] and sorted(calls(tmp_path)) == ["a", "b", "c", "d"]


def test_commit_replaces_directories_whole_and_refuses_paths_outside_the_root(tmp_path):
    root, staging = tmp_path / "root", tmp_path / "staging"
    (root / "x").mkdir(parents=True)
    (root / "x" / "old").write_text("old")
    (staging / "x").mkdir(parents=True)
    (staging / "x" / "new").write_text("new")
    commit(staging, root, ["x"])
    assert sorted(p.name for p in (root / "x").iterdir()) == ["new"]
    assert not [p for p in root.iterdir() if p.name.startswith(".")]
    with pytest.raises(ValueError):
        commit(staging, root, ["../escape"])
    with pytest.raises(FileNotFoundError, match="did not write it"):
        commit(staging, root, ["never-written"])


def test_item_runner_writes_a_durable_ledger_entry(tmp_path):
    stage = ToyStage(tmp_path, PAYLOADS)
    runner = ItemRunner({"stage": "toy", "root": str(tmp_path), "worker": stage.worker, "job": stage.job()})
    entry = runner({"id": "a", "payload": {"n": 5}, "key": "k1"})
    assert entry["status"] == "succeeded" and entry["result"] == {"value": 10}
    on_disk = json.loads(ledger_path(tmp_path, "toy", "a").read_text())
    assert on_disk["key"] == "k1" and on_disk["id"] == "a" and oct(os.stat(ledger_path(tmp_path, "toy", "a")).st_mode)[-3:] == "644"


class LegacyToyStage(ToyStage):
    """Outputs made before ledgers: ``out/<id>.txt`` with the right value counts, another value does not."""

    def adopt(self, item_id, payload, key):
        path = self.root / "out" / f"{item_id}.txt"
        if not path.exists():
            return None
        held = path.read_text()
        if held == str(payload["n"] * self.factor):
            return Adopted({"value": int(held)}, f"{path} holds the right value")
        return Redo(Why.CHANGED, f"the old output holds {held}")


class UntypedLegacyStage(ToyStage):
    """An ``adopt`` that returns a bare dict, as adopt did before its outcomes were typed."""

    def adopt(self, item_id, payload, key):
        return {"value": 0}


def test_outputs_from_before_ledgers_are_adopted_or_redone_with_the_reason(tmp_path):
    (tmp_path / "out").mkdir()
    (tmp_path / "out" / "a.txt").write_text("2")  # right for n=1, factor 2
    (tmp_path / "out" / "b.txt").write_text("99")  # wrong
    report = run_stage(LegacyToyStage(tmp_path, PAYLOADS), RunOptions(progress=False))
    assert report.reused == ["a"] and report.results["a"] == {"value": 2}
    assert report.ran == ["b", "c", "d"] and report.redone["b"].why is Why.CHANGED
    assert report.redone == {"b": "its inputs or settings changed (the old output holds 99)"}
    assert read_ledger(tmp_path, "toy", "a")["adopted"] is True
    assert read_ledger(tmp_path, "toy", "a")["result"] == {"value": 2}
    assert outputs(tmp_path)["out/b.txt"] == "4"


def test_an_adopt_outcome_that_is_not_typed_is_a_bug_not_an_output(tmp_path):
    with pytest.raises(TypeError, match="UntypedLegacyStage.adopt returned a dict: it returns an Adopted, a Redo"):
        run_stage(UntypedLegacyStage(tmp_path, PAYLOADS), RunOptions(progress=False))
    assert read_ledger(tmp_path, "toy", "a") is None and not (tmp_path / "out").exists()


def test_validate_selection_fails_an_unknown_id_before_any_key_or_check(tmp_path, monkeypatch):
    """What a facade calls before its heavy work (probe intervene's bases): the selected ids in the stage's order, the
    stage's check of them; an unknown id is the driver's one error, before ``check`` or ``key`` runs."""
    stage, checked = ToyStage(tmp_path, PAYLOADS), []
    monkeypatch.setattr(stage, "check", checked.append)
    monkeypatch.setattr(stage, "key", lambda *args: pytest.fail("validate_selection computed a key"))
    assert validate_selection(stage, RunOptions(Selection.of(["c", "a"]))) == ["a", "c"]
    assert checked == [["a", "c"]]
    with pytest.raises(UserError, match="unknown example id"):
        validate_selection(stage, RunOptions(Selection.of(["a", "zz"])))
    assert checked == [["a", "c"]] and not (tmp_path / ".stages").exists()


def test_every_stage_reports_in_the_same_words(tmp_path, capsys):
    """``StageReport.lines`` (what ``commands.report_stage`` prints): one count line, one line per reason examples
    were made again (the first ten ids), each failure, and what to do, on stderr."""
    from rigidbench.commands import report_stage

    ids = [f"{i:05d}" for i in range(14)]
    report = StageReport("render", tmp_path, selected=ids, unit="example", ran=ids[:12], reused=[],
                         failed={"00012": "bad spec"}, interrupted=["00013"],
                         redone={**{i: Redo(Why.CHANGED) for i in ids[:11]},
                                 "00011": Redo(Why.FAILED_BEFORE, "disk full")})
    out, err = report.lines()
    assert out == [f"render: 12 made, 0 up to date, 1 failed, 1 not started of 14 example(s) -> {tmp_path}",
                   "  made again, its inputs or settings changed: " + ", ".join(ids[:10]) + " and 1 more",
                   "  made again, it failed before: 00011"]
    assert err == ["  FAILED 00012: bad spec",
                   "  rerun the same command to retry what failed or did not start; finished examples are kept"]
    assert report_stage(report) == 1
    printed = capsys.readouterr()
    assert printed.out.splitlines() == out and printed.err.splitlines() == err
    clean = StageReport("evaluate", tmp_path, selected=["a"], reused=["a"], elsewhere=[], unit="example")
    assert clean.lines() == ([f"evaluate: 0 made, 1 up to date, 0 failed of 1 example(s) -> {tmp_path}"], [])
    assert clean.exit_status() == 0
