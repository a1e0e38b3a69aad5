"""evaluate on the stage driver: what a rerun scores again and what it keeps.

The reference set is the synthetic published set (tests/fixtures/published_set.py) imported with
``import_published`` (three examples, no Blender); the predictions are the `reference` predictor's. A
rerun scores nothing again, a replaced video rescoring only its example, another protocol every example
(saying why), a killed run resumes to a clean run's results, and a run folder written before ledgers is
taken over without scoring."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest


from fixtures import published_set as ps  # noqa: E402
from fixtures.children import kill_when, python  # noqa: E402

from rigidbench.config import registry  # noqa: E402
from rigidbench.driver import LEDGER_DIR, RunOptions, Selection, ledger_path, read_ledger, staging_path  # noqa: E402
from rigidbench.executors import ProcessExecutor  # noqa: E402
from rigidbench.perception.features import FeatureNets  # noqa: E402
from rigidbench.predictors import PredictContext  # noqa: E402
from rigidbench.stages import evaluate as runner  # noqa: E402
from rigidbench.stages.evaluate import evaluate
from rigidbench.stages.import_set import import_published  # noqa: E402
from rigidbench.stages.predict import predict  # noqa: E402
from rigidbench.video import read_video, write_video  # noqa: E402

pytest.importorskip("av")

IDS = ["00000", "00001", "00002"]
CHANGED = "its inputs or settings changed"


@pytest.fixture(scope="module")
def reference_set(tmp_path_factory):
    root = tmp_path_factory.mktemp("resume")
    published = ps.write_set(root / "published" / "rigidbench-eval-v1.1")
    assert import_published(published.parent, root / "data", registry=registry(), run=RunOptions(progress=False)).ran == IDS
    made = predict("reference", root / "data" / "eval", root / "reference", PredictContext(), run=RunOptions(progress=False))
    assert made.succeeded == IDS and not made.failed
    return root / "data", root / "reference"


@pytest.fixture()
def inputs(reference_set, tmp_path):
    """A private copy of the predictions (to replace videos in) and the shared reference data."""
    data, preds = reference_set
    shutil.copytree(preds, tmp_path / "reference")
    return data, tmp_path / "reference"


def run(preds, data, out, **options):
    return evaluate(preds, data, out, nets=FeatureNets(), **options, run=RunOptions(progress=False))


def stamps(out: Path) -> dict[str, int]:
    """Every file in a run folder's examples/ -> its modification time in ns."""
    return {p.name: p.stat().st_mtime_ns for p in sorted((out / "examples").iterdir())}


def never_score(monkeypatch):
    def boom(*args, **kwargs):
        raise AssertionError("an up-to-date example was scored again")

    monkeypatch.setattr(runner, "_score_one", boom)


def outputs(out: Path) -> tuple[dict, dict, str]:
    """(records, per-frame arrays, results.json text) of a run folder."""
    records = {p.name: json.loads(p.read_text()) for p in sorted((out / "examples").glob("*.json"))}
    arrays = {p.name: dict(np.load(p)) for p in sorted((out / "examples").glob("*.npz"))}
    return records, arrays, (out / "results.json").read_text()


def assert_same_outputs(a: Path, b: Path) -> None:
    records_a, arrays_a, results_a = outputs(a)
    records_b, arrays_b, results_b = outputs(b)
    assert records_a == records_b and results_a == results_b
    assert arrays_a.keys() == arrays_b.keys()
    for name, arrays in arrays_a.items():
        assert arrays.keys() == arrays_b[name].keys()
        for key, value in arrays.items():
            np.testing.assert_array_equal(value, arrays_b[name][key], err_msg=f"{name}/{key}")


def test_a_rerun_scores_nothing_again(inputs, tmp_path, monkeypatch):
    data, preds = inputs
    out = tmp_path / "run"
    first = run(preds, data, out)
    assert first.ran == IDS and not first.reused and not first.failed
    for sample_id in IDS:
        entry = read_ledger(out, "evaluate", sample_id)
        record = json.loads((out / "examples" / f"{sample_id}.json").read_text())
        assert entry["status"] == "succeeded" and entry["result"]["record"] == record
    before, results = stamps(out), (out / "results.json").read_text()
    assert sorted(before) == sorted(f"{i}{ext}" for i in IDS for ext in (".json", ".npz", ".readouts.json"))

    never_score(monkeypatch)
    again = run(preds, data, out)
    assert again.reused == IDS and not again.ran and not again.failed and not again.redone
    assert stamps(out) == before  # no example file written again
    assert (out / "results.json").read_text() == results  # the same numbers, from the kept records
    info = json.loads((out / "run.json").read_text())
    assert info["reused"] == IDS and info["evaluated"] == [] and info["timings_s"]["perception_s"] == 0.0


def test_a_replaced_video_rescores_only_its_example(inputs, tmp_path):
    data, preds = inputs
    out = tmp_path / "run"
    run(preds, data, out)
    before = stamps(out)
    old = json.loads((out / "examples" / "00001.json").read_text())
    clip = read_video(preds / "00001.mp4")
    frames = clip.frames.copy()
    frames[1:] = frames[1:] // 2  # darker from frame 1 on (frame 0 kept: the first-frame check passes)
    write_video(preds / "00001.mp4", frames, fps=24, lossless=True)

    again = run(preds, data, out)
    assert again.ran == ["00001"] and again.reused == ["00000", "00002"] and not again.failed
    assert again.redone == {"00001": CHANGED}
    after = stamps(out)
    assert {k for k in before if after[k] != before[k]} == {f"00001{ext}" for ext in (".json", ".npz", ".readouts.json")}
    new = json.loads((out / "examples" / "00001.json").read_text())
    assert new["input_key"] != old["input_key"] and new["metrics"]["ssim"] < old["metrics"]["ssim"]
    assert again.facts.results["n_examples"] == 3


def test_another_protocol_rescores_every_example_and_says_why(inputs, tmp_path, caplog):
    data, preds = inputs
    out = tmp_path / "run"
    first = run(preds, data, out)
    lossless = run(preds, data, out, protocol="lossless")
    assert lossless.ran == IDS and not lossless.reused
    assert lossless.redone == {i: CHANGED for i in IDS}
    assert "3 example(s) made with other inputs or settings are made again" in caplog.text
    assert all(json.loads((out / "examples" / f"{i}.json").read_text())["protocol"] == "lossless" for i in IDS)
    assert lossless.facts.results["protocol"]["name"] == "lossless" and lossless.facts.results["overall"]["ssim"]["mean"] == 1.0
    back = run(preds, data, out)  # one key per example: the default protocol's scores are made again too
    assert back.ran == IDS and back.facts.results == first.facts.results


def test_a_missing_prediction_fails_only_its_example_and_the_others_are_kept(inputs, tmp_path, monkeypatch):
    data, preds = inputs
    out = tmp_path / "run"
    run(preds, data, out)
    (preds / "00002.mp4").unlink()
    never_score(monkeypatch)
    again = run(preds, data, out)
    assert again.reused == ["00000", "00001"] and list(again.failed) == ["00002"]
    assert "no prediction 00002.mp4" in again.failed["00002"]
    results = json.loads((out / "results.json").read_text())
    assert results["failed"] == again.failed and results["n_examples"] == 2


def test_a_record_missing_or_from_other_inputs_is_scored_again(inputs, tmp_path):
    data, preds = inputs
    out = tmp_path / "run"
    run(preds, data, out)
    (out / "examples" / "00000.json").unlink()
    record = json.loads((out / "examples" / "00002.json").read_text())
    (out / "examples" / "00002.json").write_text(json.dumps({**record, "input_key": "another run's"}))
    again = run(preds, data, out)
    assert again.ran == ["00000", "00002"] and again.reused == ["00001"]
    assert again.redone == {i: "its output is missing or damaged" for i in ("00000", "00002")}
    assert json.loads((out / "examples" / "00002.json").read_text()) == record


def test_a_killed_run_resumes_to_the_results_of_a_clean_run(inputs, tmp_path):
    """SIGKILL while the second example is being written into staging: the first is committed, nothing of
    the second is; the rerun clears the staging leftovers, keeps the first, scores the other two, and its
    outputs equal those of an uninterrupted run."""
    data, preds = inputs
    out, marker = tmp_path / "run", tmp_path / "in-staging"
    code = f"""
import pathlib, time
from rigidbench.stages import evaluate as runner
from rigidbench.perception.features import FeatureNets
from rigidbench.driver import RunOptions
real = runner.example_readouts
def slow(sample, inputs, scores, out_dir, item=None):
    summary = real(sample, inputs, scores, out_dir, item)
    if sample.sample_id == "00001":
        pathlib.Path({str(marker)!r}).write_text(str(out_dir))
        time.sleep(120)
    return summary
runner.example_readouts = slow
runner.evaluate({str(preds)!r}, {str(data)!r}, {str(out)!r}, nets=FeatureNets(), run=RunOptions(progress=False))
"""
    kill_when(python(code), marker, timeout=120)
    staging = staging_path(out, "evaluate", "00001")
    assert Path(marker.read_text()) == staging and (staging / "examples" / "00001.readouts.json").is_file()
    assert sorted(p.name for p in (out / "examples").iterdir()) == ["00000.json", "00000.npz", "00000.readouts.json"]
    assert not ledger_path(out, "evaluate", "00001").exists() and not (out / "results.json").exists()

    resumed = run(preds, data, out)
    assert resumed.reused == ["00000"] and resumed.ran == ["00001", "00002"] and not resumed.failed
    assert not staging.exists()
    clean = run(preds, data, tmp_path / "clean")
    assert_same_outputs(out, tmp_path / "clean")
    assert resumed.facts.results == clean.facts.results


def test_a_run_folder_from_before_ledgers_is_adopted_without_scoring(inputs, tmp_path, monkeypatch):
    """Records of a run made before ledgers (the same files, no .stages/) are taken over when they were
    scored from these inputs and these rules accept them: a short clip scored under --allow-short is not
    taken over by a run without it (it is refused again), the others are kept."""
    data, preds = inputs
    clip = read_video(preds / "00001.mp4")
    write_video(preds / "00001.mp4", clip.frames[:7], fps=24, lossless=True)  # half the span
    out = tmp_path / "run"
    run(preds, data, out, allow_short=True)
    shutil.rmtree(out / LEDGER_DIR)
    before = stamps(out)

    never_score(monkeypatch)
    adopted = run(preds, data, out, allow_short=True)
    assert adopted.reused == IDS and not adopted.ran and not adopted.failed
    assert stamps(out) == before
    assert all(read_ledger(out, "evaluate", i)["adopted"] is True for i in IDS)
    assert adopted.facts.results["coverage"]["short"] == ["00001"]

    shutil.rmtree(out / LEDGER_DIR)
    monkeypatch.undo()
    strict = run(preds, data, out)
    assert strict.reused == ["00000", "00002"] and not strict.ran
    assert list(strict.failed) == ["00001"] and "--allow-short" in strict.failed["00001"]
    assert strict.redone == {}  # not taken over, so scored (and refused) as a new example


def test_child_processes_write_what_this_process_writes(inputs, tmp_path):
    data, preds = inputs
    here = evaluate(preds, data, tmp_path / "here", run=RunOptions(Selection.of(["00000", "00002"]), progress=False))
    there = evaluate(preds, data, tmp_path / "there", run=RunOptions(Selection.of(["00000", "00002"]), executor=ProcessExecutor(workers=2), progress=False))
    assert there.ran == here.ran == ["00000", "00002"]
    assert_same_outputs(tmp_path / "here", tmp_path / "there")
