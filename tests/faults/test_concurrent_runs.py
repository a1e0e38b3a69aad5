"""Two processes on one output folder (issue 33, items 1 and 2): the stage driver's lock per example.

Each example is made by exactly one process at a time (``driver.ItemLock``, an ``fcntl.flock`` the kernel
drops when its holder dies); a process skips the examples another one holds and says so, or waits for them
(``wait``, ``--wait``); an example another process finished since the plan is not made again; and a stage's
run-level files are written under a run-level lock, from the ledger, by whichever process finishes last.

Real subprocesses, started together: two ``evaluate`` (each scoring is slowed so they overlap) end with the
results.json of a single run and each example scored once; two waiting runs of the driver's toy stage
through ``ProcessExecutor`` (the executor ``render`` uses; the lock lives in the driver's ``ItemRunner``, the
same for every stage, so the toy stage stands in for Blender, whose render of one example takes ~26 s here)
end with a single run's outputs. Two hosted
``predict`` runs are in tests/faults/test_hosted_faults.py (the stand-in Replicate counts the creations)."""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

from fixtures import child_env, published_set as ps
from fixtures.toy_stage import ToyStage, calls

from rigidbench.config import registry
from rigidbench.driver import (ItemLock, ItemRunner, RunOptions, StageReport, ledger_outcomes, lock_path, read_ledger,
                               run_stage, write_ledger)

IDS = ["00000", "00001", "00002"]
PAYLOADS = {"a": {"n": 1}, "b": {"n": 2}, "c": {"n": 3}, "d": {"n": 4}}


def outputs(root: Path) -> dict:
    return {p.relative_to(root).as_posix(): p.read_text() for p in sorted((root / "out").rglob("*")) if p.is_file()}


def job(stage: ToyStage) -> dict:
    return {"stage": stage.name, "root": str(stage.root), "worker": stage.worker, "job": stage.job()}


def together(commands: list[list[str]], env: dict | None = None, timeout: float = 120) -> list[tuple[int, str, str]]:
    """Start every command at once; (exit status, stdout, stderr) of each."""
    procs = [subprocess.Popen(c, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
             for c in commands]
    done = [p.communicate(timeout=timeout) for p in procs]
    return [(p.returncode, stdout, stderr) for p, (stdout, stderr) in zip(procs, done)]


# -- the lock ----------------------------------------------------------------------------------------------


def test_a_lock_excludes_other_holders_and_dies_with_its_process(tmp_path):
    path = tmp_path / "x" / "a.lock"
    first, second = ItemLock(path), ItemLock(path)
    assert first.acquire() and not second.acquire()  # two open files of one path exclude each other
    first.release()
    assert not path.exists()  # the holder removes the file when it releases
    assert second.acquire()
    second.release()
    holder = subprocess.Popen([sys.executable, "-c", "import sys, time; from rigidbench.driver import ItemLock; "
                               f"ItemLock({str(path)!r}).acquire(); print('held', flush=True); time.sleep(60)"],
                              stdout=subprocess.PIPE, text=True)
    assert holder.stdout.readline().strip() == "held"
    assert not first.acquire()
    holder.send_signal(signal.SIGKILL)
    holder.wait(10)
    assert path.exists() and first.acquire()  # its file is left, its lock is not
    first.release()


def test_an_example_another_process_holds_is_skipped_and_said_or_waited_for(tmp_path, caplog):
    stage = ToyStage(tmp_path, PAYLOADS)
    held = ItemLock(lock_path(tmp_path, "toy", "b"))
    assert held.acquire()
    report = run_stage(stage, RunOptions(progress=False))
    assert report.ran == ["a", "c", "d"] and report.elsewhere == ["b"] and not report.failed
    assert "1 example(s) are being done by another process" in caplog.text and "--wait" in caplog.text
    out, err = report.lines()
    assert "1 being made by another process" in out[0]
    assert "  1 example(s) being made by another process: rerun when it is done, or pass --wait" in err
    assert read_ledger(tmp_path, "toy", "b") is None and calls(tmp_path) == ["a", "c", "d"]
    threading.Timer(0.5, held.release).start()  # the other process lets it go without finishing it
    waited = run_stage(ToyStage(tmp_path, PAYLOADS), RunOptions(progress=False, wait=True))
    assert waited.ran == ["b"] and waited.reused == ["a", "c", "d"] and not waited.elsewhere
    assert calls(tmp_path) == ["a", "c", "d", "b"]


def test_an_example_finished_elsewhere_while_waiting_is_not_made_again(tmp_path):
    payloads = dict(PAYLOADS, b={"n": 2, "slow": 1.0})
    other = ItemRunner(job(ToyStage(tmp_path, payloads)))  # "another process": it takes b's lock itself
    stage = ToyStage(tmp_path, payloads)
    task = {"id": "b", "payload": payloads["b"], "key": stage.key("b", payloads["b"])}
    thread = threading.Thread(target=other, args=(task,))
    thread.start()
    while not (tmp_path / ".stages" / "toy" / "staging" / "b").exists():
        time.sleep(0.01)
    report = run_stage(stage, RunOptions(progress=False, wait=True))
    thread.join()
    assert report.ran == ["a", "c", "d"] and report.reused == ["b"] and report.results["b"] == {"value": 4}
    assert sorted(calls(tmp_path)) == ["a", "b", "c", "d"]  # b made once, by the other
    again = run_stage(ToyStage(tmp_path, payloads), RunOptions(progress=False))
    assert again.reused == ["a", "b", "c", "d"]


def test_the_ledger_outcome_is_the_latest_entry_whoever_wrote_it(tmp_path):
    stage = ToyStage(tmp_path, PAYLOADS)
    report = StageReport("toy", tmp_path, selected=["a", "b", "c", "d"], keys={"a": "ka", "b": "kb", "c": "kc"},
                         failed={"d": "its key cannot be computed"})
    write_ledger(tmp_path, "toy", "a", "ka", "failed", error="first try")
    write_ledger(tmp_path, "toy", "a", "ka", "succeeded", result={"value": 1})  # another process, later
    write_ledger(tmp_path, "toy", "b", "kb", "failed", error="bad input")
    write_ledger(tmp_path, "toy", "c", "other settings", "succeeded")
    done, failed = ledger_outcomes(stage, report)
    assert list(done) == ["a"] and done["a"]["result"] == {"value": 1}
    assert failed == {"b": "bad input", "d": "its key cannot be computed"}


STAGE_COMMANDS = [("import",), ("simulate",), ("render",), ("predict",), ("audit",), ("evaluate",), ("preprocess",),
                  ("probe", "extract")]


def test_wait_is_an_option_of_every_stage_and_reaches_the_driver_in_its_run_options():
    from rigidbench.cli import build_parser
    from rigidbench.commands import run_options

    for path in STAGE_COMMANDS:
        parser = build_parser()
        for name in path:
            parser = next(a for a in parser._actions if hasattr(a, "choices") and isinstance(a.choices, dict)
                          ).choices[name]
        assert "--wait" in parser._option_string_actions, " ".join(path)
    assert run_options(build_parser().parse_args(["evaluate", "p", "--wait"])).wait is True
    assert run_options(build_parser().parse_args(["evaluate", "p"])).wait is False


# -- two processes, started together -------------------------------------------------------------------------

TOY_RUN = """
import json
from pathlib import Path
from rigidbench.driver import RunOptions, run_stage
from rigidbench.executors import ProcessExecutor
from fixtures.toy_stage import ToyStage
report = run_stage(ToyStage(Path({root!r}), {payloads!r}), RunOptions(executor=ProcessExecutor(workers=2), progress=False, wait=True))
print(json.dumps(report.to_json()))
"""


def test_two_waiting_runs_through_child_processes_make_each_example_once(tmp_path):
    """Render's path (each example in a child process), --wait: each run ends with every example done, each
    made by one of them; skipping without --wait is the evaluate test's below."""
    payloads = {k: {**v, "slow": 0.3} for k, v in PAYLOADS.items()}
    root = tmp_path / "shared"
    code = TOY_RUN.format(root=str(root), payloads=payloads)
    runs = together([[sys.executable, "-c", code]] * 2, env=child_env())
    reports = []
    for status, stdout, stderr in runs:
        assert status == 0 and "Traceback" not in stderr and "Errno" not in stderr, stderr
        reports.append(json.loads(stdout))
    for report in reports:
        assert not report["failed"] and not report["interrupted"] and not report["elsewhere"]
        assert sorted(report["ran"] + report["reused"]) == ["a", "b", "c", "d"]
    assert sorted(reports[0]["ran"] + reports[1]["ran"]) == ["a", "b", "c", "d"]
    assert sorted(calls(root)) == ["a", "b", "c", "d"]  # each example made once
    run_stage(ToyStage(tmp_path / "single", payloads), RunOptions(progress=False))
    assert outputs(root) == outputs(tmp_path / "single")
    assert not (root / ".stages" / "toy" / "staging").exists()  # no staging folder or lock left behind


@pytest.fixture(scope="module")
def reference_set(tmp_path_factory):
    """The synthetic published set imported (three examples), and the reference predictor's videos of it."""
    from rigidbench.stages.import_set import import_published
    from rigidbench.stages.predict import predict
    from rigidbench.predictors import PredictContext

    root = tmp_path_factory.mktemp("concurrent")
    published = ps.write_set(root / "published" / "rigidbench-eval-v1.1")
    assert import_published(published.parent, root / "data", registry=registry(), run=RunOptions(progress=False)).ran == IDS
    assert predict("reference", root / "data" / "eval", root / "reference", PredictContext(), run=RunOptions(progress=False)).succeeded \
        == IDS
    return root / "data", root / "reference"


EVALUATE = """
import sys, time
from rigidbench.stages import evaluate as runner
from rigidbench.stages.evaluate import evaluate
from rigidbench.perception.features import FeatureNets
from rigidbench.driver import RunOptions
preds, data, out, scored = sys.argv[1:5]
real = runner._score_one
def slowed(sample, *args, **kwargs):
    with open(scored, "a") as fh:
        fh.write(sample.sample_id + "\\n")
    time.sleep(0.4)  # both processes are at work at once
    return real(sample, *args, **kwargs)
runner._score_one = slowed
summary = evaluate(preds, data, out, nets=FeatureNets(), run=RunOptions(progress=False))
print(len(summary.ran), len(summary.reused), len(summary.failed), len(summary.elsewhere))
"""


def test_two_evaluates_on_one_folder_write_a_single_runs_results(reference_set, tmp_path):
    from rigidbench.stages.evaluate import evaluate
    from rigidbench.perception.features import FeatureNets

    data, preds = reference_set
    out, scored = tmp_path / "run", tmp_path / "scored.log"
    runs = together([[sys.executable, "-c", EVALUATE, str(preds), str(data), str(out), str(scored)]] * 2)
    evaluated = 0
    for status, stdout, stderr in runs:
        assert status == 0 and "Traceback" not in stderr and "Errno" not in stderr, stderr
        ran, reused, failed, elsewhere = (int(n) for n in stdout.split())
        assert failed == 0 and ran + reused + elsewhere == 3, stdout
        evaluated += ran
    assert evaluated == 3 and sorted(scored.read_text().split()) == IDS  # each example scored once
    single = evaluate(preds, data, tmp_path / "single", nets=FeatureNets(), run=RunOptions(progress=False))
    assert (out / "results.json").read_text() == (tmp_path / "single" / "results.json").read_text()
    results = json.loads((out / "results.json").read_text())
    assert results["n_examples"] == 3 and results["failed"] == {} and single.facts.results == results
    for sample_id in IDS:
        assert json.loads((out / "examples" / f"{sample_id}.json").read_text()) == \
               json.loads((tmp_path / "single" / "examples" / f"{sample_id}.json").read_text())
