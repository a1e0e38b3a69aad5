"""K samples per example on the predict stage (``predict --samples K``): the items are (example, sample) pairs
named by the one naming rule (``<id>``, ``<id>.s1``, ...), each predicted with the seed ``sample_seed`` gives it,
keyed, locked, resumed and recorded on its own; sample 0 keeps the key an example always had, so raising K makes
only the new samples; ``--ids``/``--limit`` choose examples and the shard splits samples.

Cheap predictors only: the ``reference``/``static`` failure modes on bundles imported from the synthetic
published set, and ``seed_frames`` below, a plug-in that writes the seed it was given into its frames."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("av")

from fixtures.children import kill_when, python  # noqa: E402
from fixtures.predicting import IDS, generation  # noqa: E402
from fixtures.predicting import imported, split  # noqa: E402,F401 (pytest fixtures)

from rigidbench.cli import main  # noqa: E402
from rigidbench.driver import RunOptions, Selection, ledger_path, read_ledger  # noqa: E402
from rigidbench.errors import UserError  # noqa: E402
from rigidbench.executors import ProcessExecutor, Shard  # noqa: E402
from rigidbench.folders import GENERATION_FILE, find_samples  # noqa: E402
from rigidbench.hashing import digest  # noqa: E402
from rigidbench.preflight import format_report, validate_predictions  # noqa: E402
from rigidbench.predictors import (SAMPLE_SEED_RULE, PredictContext, Prediction, example_seed,  # noqa: E402
                                   sample_seed)
from rigidbench.stages.predict import STAGE, input_digest, predict  # noqa: E402
from rigidbench.video import read_video  # noqa: E402

SEED_FRAMES = f"{__name__}:seed_frames"  # this module, importable as a plug-in (pytest puts its folder on the path)
BASE = 5


def seed_frames(sample, ctx) -> Prediction:
    """A plug-in ``f(sample, ctx)`` whose video shows the seed it was given: the red channel of four 8-pixel
    wide columns holds the seed's four bytes (big-endian); the record names the prediction it was asked for."""
    frames = np.zeros((3, 16, 32, 3), np.uint8)
    for i, byte in enumerate(int(ctx.seed).to_bytes(4, "big")):
        frames[:, :, 8 * i:8 * i + 8, 0] = byte
    frames[:, :, :, 1] = np.arange(3, dtype=np.uint8)[:, None, None] * 40
    return Prediction(frames=frames, times_s=np.arange(3) / 24.0, metadata={"asked_for": ctx.item})


def seen_seed(video: Path) -> int:
    """The seed ``seed_frames`` wrote into ``video`` (read back from the decoded frames)."""
    frame = read_video(video).frames[0]
    return int.from_bytes(bytes(int(frame[8, 8 * i + 4, 0]) for i in range(4)), "big")


def items(ids, k: int) -> list[str]:
    """The items of ``ids`` with ``k`` samples each, example-major, written out by hand."""
    return [i if s == 0 else f"{i}.s{s}" for i in ids for s in range(k)]


def run(name, split, out, samples=1, ids=None, shard=None, executor=None, **kwargs):
    selection = Selection.of(ids, shard=shard) if shard else Selection.of(ids)
    return predict(name, split, out, PredictContext(seed=kwargs.pop("seed", BASE)), samples=samples,
                   run=RunOptions(selection, progress=False, executor=executor), **kwargs)


def snapshot(folder: Path) -> dict:
    return {p.relative_to(folder).as_posix(): p.stat().st_mtime_ns for p in sorted(folder.rglob("*"))
            if p.is_file() and ".stages/predict/staging" not in p.as_posix() and not p.name.endswith(".lock")}


# -- items, seeds, names and records -------------------------------------------------------------------


def test_k_samples_are_items_of_their_own_with_the_seeds_of_sample_seed(split, tmp_path):
    out = tmp_path / "out"
    report = run(SEED_FRAMES, split, out, samples=3)
    assert report.succeeded == items(IDS, 3) and not report.failed and report.unit == "sample"
    for example in IDS:
        found = find_samples(out, example)
        assert {k: p.name for k, p in found.items()} == {0: f"{example}.mp4", 1: f"{example}.s1.mp4",
                                                         2: f"{example}.s2.mp4"}
        seeds = [seen_seed(found[k]) for k in range(3)]
        assert seeds == [sample_seed(BASE, example, k) for k in range(3)]
        assert seeds[0] == example_seed(BASE, example) and len(set(seeds)) == 3  # sample 0 keeps today's seed
    doc = generation(out)
    assert list(doc["examples"]) == sorted(items(IDS, 3))
    for example in IDS:
        for k in range(3):
            item = items([example], 3)[k]
            record = doc["examples"][item]
            assert (record["example"], record["sample"], record["seed"]) == (example, k, sample_seed(BASE, example, k))
            assert record["status"] == "succeeded" and record["asked_for"] == item
            assert read_ledger(out, STAGE, item)["result"] == record
    assert doc["samples"] == {"per_example": 3, "seeds": SAMPLE_SEED_RULE}
    assert "samples" not in doc["settings"]  # the settings (in every key) are those of one sample per example


def test_sample_0_keeps_the_key_an_example_had_and_one_sample_writes_what_it_always_did(split, tmp_path):
    one, three = tmp_path / "one", tmp_path / "three"
    run(SEED_FRAMES, split, one)
    run(SEED_FRAMES, split, three, samples=3)
    settings = generation(one)["settings"]
    assert generation(three)["settings"] == settings
    for example in IDS:  # the key as it was computed before there were samples, written out here
        today = digest({"settings": settings, "seed": example_seed(BASE, example),
                        "inputs": input_digest(split / example)})
        assert read_ledger(one, STAGE, example)["key"] == today == read_ledger(three, STAGE, example)["key"]
        assert read_ledger(three, STAGE, f"{example}.s1")["key"] != today
    doc = generation(one)
    assert "samples" not in doc and sorted(doc["examples"]) == IDS
    assert all("sample" not in r and "example" not in r for r in doc["examples"].values())
    assert sorted(p.name for p in one.glob("*.mp4")) == [f"{i}.mp4" for i in IDS]


def test_raising_k_on_a_finished_folder_makes_only_the_new_samples(split, tmp_path):
    out = tmp_path / "out"
    assert run("reference", split, out).succeeded == IDS
    first = snapshot(out)
    raised = run("reference", split, out, samples=3)
    assert raised.reused == IDS and raised.ran == [i for i in items(IDS, 3) if i not in IDS]
    assert not raised.redone and not raised.failed
    after = snapshot(out)
    for example in IDS:  # sample 0's video, state and ledger entry were not touched
        for name in (f"{example}.mp4", f"{example}.state.npz", f".stages/predict/{example}.json"):
            assert after[name] == first[name], name
    # the reference failure mode is deterministic and takes no seed: its samples are the same video
    for example in IDS:
        frames = [read_video(p).frames for p in find_samples(out, example).values()]
        assert len(frames) == 3 and all(np.array_equal(frames[0], f) for f in frames[1:])
    assert generation(out)["samples"]["per_example"] == 3 and "no seed" in generation(out)["samples"]["seeds"]
    assert generation(out)["examples"]["00000"]["sample"] == 0  # sample 0's record, made with one, says so now
    # back to one sample: nothing to make, and the records of the samples already made stay listed
    again = run("reference", split, out)
    assert again.reused == IDS and not again.ran
    assert sorted(generation(out)["examples"]) == sorted(items(IDS, 3))
    assert generation(out)["examples"]["00001.s2"]["sample"] == 2 and generation(out)["samples"]["per_example"] == 3
    assert run("reference", split, out, samples=3).reused == items(IDS, 3)


KILLED_RUN = """
import pathlib, sys, time
from rigidbench.predictors import image_space
real = image_space.static
split, out, mark = (pathlib.Path(a) for a in sys.argv[1:4])
calls = []

def static(sample, severity):
    calls.append(1)
    if len(calls) == 5:  # items in order 00000, 00000.s1, 00000.s2, 00001, 00001.s1: hangs on the fifth
        mark.write_text("started")
        time.sleep(120)
    return real(sample, severity)

image_space.static = static
from rigidbench.stages.predict import predict
from rigidbench.predictors import PredictContext
from rigidbench.driver import RunOptions
predict("static", split, out, PredictContext(severity=0.5), run=RunOptions(progress=False), samples=3)
"""


def test_a_killed_run_resumes_only_the_missing_samples(split, tmp_path):
    out, mark = tmp_path / "out", tmp_path / "started"
    kill_when(python(KILLED_RUN, split, out, mark), mark)
    done = ["00000", "00000.s1", "00000.s2", "00001"]
    assert all(read_ledger(out, STAGE, i)["status"] == "succeeded" for i in done)
    assert read_ledger(out, STAGE, "00001.s1") is None and not (out / "00001.s1.mp4").exists()
    resumed = predict("static", split, out, PredictContext(severity=0.5), samples=3, run=RunOptions(progress=False))
    assert resumed.reused == done and resumed.ran == [i for i in items(IDS, 3) if i not in done]
    clean = tmp_path / "clean"
    predict("static", split, clean, PredictContext(severity=0.5), samples=3, run=RunOptions(progress=False))
    names = sorted(p.name for p in clean.iterdir() if not p.name.startswith("."))
    assert sorted(p.name for p in out.iterdir() if not p.name.startswith(".")) == names
    for name in names:
        if name.endswith(".mp4"):
            assert np.array_equal(read_video(out / name).frames, read_video(clean / name).frames), name
    assert untimed(generation(out)) == untimed(generation(clean))


def untimed(doc: dict) -> dict:
    """generation.json's records without their timings."""
    return {i: {k: v for k, v in r.items() if k != "seconds"} for i, r in doc["examples"].items()}


# -- selection, shards, other executors ---------------------------------------------------------------


def test_ids_and_limit_choose_examples_and_shards_split_samples(split, tmp_path):
    out = tmp_path / "out"
    chosen = run("reference", split, out, samples=2, ids=["00001"])
    assert chosen.selected == ["00001", "00001.s1"]
    with pytest.raises(UserError, match=r"unknown example id\(s\) 00001.s1"):
        run("reference", split, out, samples=2, ids=["00001.s1"])
    limited = predict("reference", split, tmp_path / "limited", PredictContext(), samples=2,
                      run=RunOptions(Selection.of(limit=2), progress=False))
    assert limited.selected == items(["00000", "00001"], 2)
    everything = items(IDS, 2)
    shards = [run("reference", split, tmp_path / "sharded", samples=2, shard=Shard(i, 2)) for i in range(2)]
    assert shards[0].selected == everything[0::2] and shards[1].selected == everything[1::2]
    assert sorted(shards[0].ran + shards[1].ran) == sorted(everything)  # each sample made once, by one shard
    assert sorted(generation(tmp_path / "sharded")["examples"]) == sorted(everything)
    assert run("reference", split, tmp_path / "sharded", samples=2).reused == everything


def test_samples_made_in_child_processes_get_the_same_seeds_and_files(split, tmp_path, monkeypatch):
    """Another executor builds its worker from the job (as a Ray actor does): the payload says each item's
    example and sample, and the worker derives the same seed."""
    tests = Path(__file__).resolve().parents[1]
    monkeypatch.setenv("PYTHONPATH", f"{Path(__file__).resolve().parent}:{tests}")
    here, there = tmp_path / "here", tmp_path / "there"
    run(SEED_FRAMES, split, here, samples=2, ids=["00000", "00002"])
    report = run(SEED_FRAMES, split, there, samples=2, ids=["00000", "00002"], executor=ProcessExecutor(workers=2))
    assert sorted(report.succeeded) == sorted(items(["00000", "00002"], 2)) and not report.failed
    for item in items(["00000", "00002"], 2):
        example, k = item.split(".s")[0], int(item.split(".s")[1]) if ".s" in item else 0
        assert seen_seed(there / f"{item}.mp4") == seen_seed(here / f"{item}.mp4") == sample_seed(BASE, example, k)
        assert read_ledger(there, STAGE, item)["key"] == read_ledger(here, STAGE, item)["key"]


# -- records, recovery, dry run, the command line, validation -------------------------------------------


def test_a_sample_committed_without_its_record_is_taken_over_with_its_own_seed(split, tmp_path):
    out = tmp_path / "out"
    run(SEED_FRAMES, split, out, samples=2)
    ledger_path(out, STAGE, "00001.s1").unlink()  # killed between committing the video and its ledger entry
    doc = generation(out)
    del doc["examples"]["00001.s1"]
    (out / GENERATION_FILE).write_text(json.dumps(doc))
    video = (out / "00001.s1.mp4").stat().st_mtime_ns
    report = run(SEED_FRAMES, split, out, samples=2)
    assert report.reused == items(IDS, 2) and not report.ran and (out / "00001.s1.mp4").stat().st_mtime_ns == video
    record = generation(out)["examples"]["00001.s1"]
    assert (record["example"], record["sample"], record["seed"]) == ("00001", 1, sample_seed(BASE, "00001", 1))
    assert "recovered" in record and read_ledger(out, STAGE, "00001.s1")["adopted"] is True


def test_a_failed_sample_fails_alone_with_its_own_seed(split, tmp_path):
    out = tmp_path / "out"
    (split / "00002" / "frames" / "00000.png").unlink()
    report = run(SEED_FRAMES, split, out, samples=2)
    assert sorted(report.failed) == ["00002", "00002.s1"] and report.succeeded == items(["00000", "00001"], 2)
    record = generation(out)["examples"]["00002.s1"]
    assert record["status"] == "failed" and record["seed"] == sample_seed(BASE, "00002", 1) and record["sample"] == 1


def test_the_dry_run_plans_each_sample_and_says_when_samples_share_a_seed(split, tmp_path, capsys):
    out = tmp_path / "out"
    run(SEED_FRAMES, split, out, ids=["00000"])
    capsys.readouterr()
    planned = run(SEED_FRAMES, split, out, samples=2, dry_run=True)
    assert planned.facts.planned == [i for i in items(IDS, 2) if i != "00000"] and planned.reused == ["00000"]
    assert planned.facts.paid_calls == 0 and planned.facts.samples == 2 and planned.facts.note is None
    printed = {line.split(": ", 1)[0]: json.loads(line.split(": ", 1)[1])
               for line in capsys.readouterr().out.strip().splitlines()}
    assert printed["00001.s1"]["seed"] == sample_seed(BASE, "00001", 1)
    assert printed["00000.s1"]["seed"] == sample_seed(BASE, "00000", 1)
    unseeded = run("static", split, tmp_path / "static", samples=2, dry_run=True)
    assert "static takes no seed" in unseeded.facts.note and not (tmp_path / "static").exists()


def test_the_command_line_takes_samples(split, tmp_path, capsys):
    out = tmp_path / "out"
    command = ["predict", "reference", "--data", str(split), "--out", str(out), "--ids", "00000,00001"]
    assert main(command + ["--samples", "2", "--dry-run"]) == 0
    text = capsys.readouterr().out
    assert "would make 4, 0 up to date, 0 failed of 4 sample(s)" in text
    assert "reference: 0 paid API calls; nothing was sent" in text and "note: reference takes no seed" in text
    assert main(command + ["--samples", "2"]) == 0
    assert sorted(p.name for p in out.glob("*.mp4")) == ["00000.mp4", "00000.s1.mp4", "00001.mp4", "00001.s1.mp4"]
    with pytest.raises(SystemExit):
        main(command + ["--samples", "0"])
    for bad in (0, -1, 1.5, True, "2"):
        with pytest.raises(UserError, match="samples per example must be a whole number >= 1"):
            run("reference", split, out, samples=bad)


def test_an_example_named_like_another_examples_sample_is_one_error(split, tmp_path):
    shutil.copytree(split / "00000", split / "00000.s1")
    with pytest.raises(UserError, match=r"example 00000.s1 has the name of sample 1 of example 00000"):
        run("reference", split, tmp_path / "out", samples=2)


def test_a_k_sample_folder_validates_and_says_how_many_samples_it_found(split, tmp_path):
    out = tmp_path / "out"
    run("reference", split, out, samples=2)
    report = validate_predictions(out, split)
    assert report.ok and report.issues == [] and report.samples_per_example() == (2, 2)
    assert {e: sorted(f) for e, f in report.samples.items()} == {i: [0, 1] for i in IDS}
    assert "samples per example: 2 (6 videos read;" in format_report(report)
