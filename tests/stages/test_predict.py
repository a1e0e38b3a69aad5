"""The predict stage on the stage driver: each example's ledger entry is keyed by the predictor's settings,
the example's own seed and its model inputs, so a rerun predicts nothing again, a change of settings or of
one example's inputs redoes exactly the examples it touches (and says why), a killed run resumes with the
same outputs as a clean run, and a folder written before ledgers is taken over without predicting again.

Cheap predictors only: an image-space failure mode on bundles imported from the synthetic published set,
and the hosted models against the stand-in Replicate server on 127.0.0.1."""

from __future__ import annotations

import json
import logging
from pathlib import Path

import numpy as np
import pytest
import yaml

pytest.importorskip("av")
pytest.importorskip("PIL")

from fixtures.predicting import IDS, SLOW, Counted, generation, run  # noqa: E402
from fixtures.children import kill_when, python  # noqa: E402
from fixtures.predicting import imported, split  # noqa: E402,F401 (pytest fixtures)
from PIL import Image  # noqa: E402
from fixtures.replicate_server import make_split  # noqa: E402
from fixtures.replicate_server import server, video  # noqa: E402,F401 (pytest fixtures)

from rigidbench.config import PACKAGE_CONFIG_DIR  # noqa: E402
from rigidbench.context import RunContext  # noqa: E402
from rigidbench.driver import RunOptions, ledger_path, read_ledger, staging_path  # noqa: E402
from rigidbench.errors import UserError  # noqa: E402
from rigidbench.folders import GENERATION_FILE  # noqa: E402
from rigidbench.predictors import PredictContext, example_seed  # noqa: E402
from rigidbench.stages.predict import STAGE, predict  # noqa: E402
from rigidbench.video import read_video  # noqa: E402

CHANGED = "its inputs or settings changed"


def outputs(out: Path) -> dict:
    """What a user reads of a predictions folder: each video's frames and times, each state's arrays, and
    generation.json's records without their timings."""
    found = {}
    for video in sorted(out.glob("*.mp4")):
        decoded = read_video(video)
        found[video.name] = (decoded.frames, decoded.times_s)
    for state in sorted(out.glob("*.state.npz")):
        with np.load(state) as z:
            found[state.name] = {k: z[k] for k in z.files}
    found["examples"] = {i: {k: v for k, v in e.items() if k != "seconds"} for i, e in generation(out)["examples"].items()}
    return found


def assert_same(a: dict, b: dict) -> None:
    assert a.keys() == b.keys()
    for name in a:
        if name.endswith(".mp4"):
            assert np.array_equal(a[name][0], b[name][0]) and np.allclose(a[name][1], b[name][1]), name
        elif name.endswith(".npz"):
            assert a[name].keys() == b[name].keys()
            for key in a[name]:
                assert np.array_equal(a[name][key], b[name][key]), (name, key)
        else:
            assert a[name] == b[name]


def snapshot(folder: Path) -> dict:
    return {p.relative_to(folder).as_posix(): p.stat().st_mtime_ns for p in sorted(folder.rglob("*")) if p.is_file()}


# -- the failure mode on imported bundles ----------------------------------------------------------------


def test_a_rerun_predicts_nothing_again(split, tmp_path):
    out, counter = tmp_path / "out", Counted()
    first = run(split, out, counter)
    assert first.succeeded == IDS and first.reused == [] and not first.failed and counter.calls == IDS
    for sample_id in IDS:
        entry = read_ledger(out, STAGE, sample_id)
        assert entry["status"] == "succeeded" and len(entry["key"]) == 64
        assert (out / f"{sample_id}.mp4").is_file() and (out / f"{sample_id}.state.npz").is_file()
        assert entry["result"]["status"] == "succeeded" and entry["result"] == generation(out)["examples"][sample_id]
    assert generation(out)["settings"] == {"predictor": "slow", "target": SLOW, "severity": 0.5}
    assert sorted(p.name for p in out.iterdir()) == sorted([".stages", GENERATION_FILE, *(f"{i}.mp4" for i in IDS),
                                                           *(f"{i}.state.npz" for i in IDS)])  # two records, no more
    staging = staging_path(out, STAGE, "00000").parent
    assert not staging.exists() or not any(staging.iterdir())  # committed: nothing left behind
    before = snapshot(out)
    again = run(split, out, counter)
    assert again.succeeded == IDS and again.reused == IDS and not again.redone
    assert counter.calls == IDS  # the predictor was not asked again
    after = snapshot(out)
    assert after == before  # nothing touched: videos, states, ledger, generation.json


def test_changed_settings_redo_exactly_the_examples_made_with_other_ones(split, tmp_path, caplog):
    out, counter = tmp_path / "out", Counted()
    run(split, out, counter, severity=0.5)
    with caplog.at_level(logging.WARNING, logger="rigidbench.driver"):
        stronger = run(split, out, counter, severity=1.0)
    assert stronger.reused == [] and stronger.redone == {i: CHANGED for i in IDS}
    assert "made with other inputs or settings are made again: 00000, 00001, 00002" in caplog.text
    assert counter.calls == IDS * 2
    assert generation(out)["settings"]["severity"] == 1.0
    # one example back to the first severity: only it is made again ...
    back = run(split, out, counter, severity=0.5, ids=["00001"])
    assert back.succeeded == ["00001"] and back.redone == {"00001": CHANGED}
    assert counter.calls == IDS * 2 + ["00001"]
    # ... and a full run at the second severity redoes just that one, the others are up to date
    full = run(split, out, counter, severity=1.0)
    assert full.reused == ["00000", "00002"] and full.redone == {"00001": CHANGED}
    assert counter.calls == IDS * 2 + ["00001", "00001"]
    assert generation(out)["settings"]["severity"] == 1.0 and list(generation(out)["examples"]) == IDS
    # the failure mode takes no seed: another --seed changes nothing it makes
    assert run(split, out, counter, severity=1.0, seed=99).reused == IDS
    assert counter.calls == IDS * 2 + ["00001", "00001"]


def test_a_changed_input_of_one_example_redoes_only_that_example(split, tmp_path):
    out, counter = tmp_path / "out", Counted()
    run(split, out, counter)
    keys = {i: read_ledger(out, STAGE, i)["key"] for i in IDS}
    prompt = split / "00001" / "prompt.txt"
    prompt.write_text("A ball rolls off the table and bounces twice.\n")
    summary = run(split, out, counter)
    assert summary.reused == ["00000", "00002"] and summary.redone == {"00001": CHANGED}
    assert counter.calls == IDS + ["00001"]
    assert read_ledger(out, STAGE, "00001")["key"] != keys["00001"]
    assert {i: read_ledger(out, STAGE, i)["key"] for i in ("00000", "00002")} == {i: keys[i] for i in ("00000", "00002")}
    assert generation(out)["examples"]["00001"]["prompt"].startswith("A ball rolls off the table and bounces twice.")
    # the first frame is an input too
    frame = split / "00002" / "frames" / "00000.png"
    pixels = np.asarray(Image.open(frame).convert("RGB")).copy()
    pixels[0, 0] = 255 - pixels[0, 0]
    Image.fromarray(pixels).save(frame)
    assert run(split, out, counter).redone == {"00002": CHANGED}
    assert counter.calls == IDS + ["00001", "00002"]
    # a failure mode reads the whole reference: a re-rendered bundle (same first frame and prompt) redoes it
    meta_path = split / "00000" / "metadata.json"
    meta = json.loads(meta_path.read_text())
    meta["render_seconds"] = {"total": 123.0}
    meta_path.write_text(json.dumps(meta))
    assert run(split, out, counter).redone == {"00000": CHANGED}
    assert counter.calls == IDS + ["00001", "00002", "00000"]


def test_an_unreadable_example_fails_alone_and_runs_when_fixed(split, tmp_path):
    out, counter = tmp_path / "out", Counted()
    frame = split / "00001" / "frames" / "00000.png"
    kept = frame.read_bytes()
    frame.unlink()
    summary = run(split, out, counter)
    assert summary.succeeded == ["00000", "00002"] and list(summary.failed) == ["00001"]
    assert "00000.png" in summary.failed["00001"]
    record = generation(out)["examples"]["00001"]
    assert record["status"] == "failed" and record["seed"] == example_seed(0, "00001")
    frame.write_bytes(kept)
    again = run(split, out, counter)
    assert again.reused == ["00000", "00002"] and again.succeeded == IDS and not again.failed
    assert counter.calls == ["00000", "00002", "00001"]
    assert generation(out)["examples"]["00001"]["status"] == "succeeded"


def test_an_unknown_id_is_one_error_and_nothing_is_written(split, tmp_path):
    out = tmp_path / "out"
    with pytest.raises(UserError, match=r"unknown example id\(s\) 00007 in .*eval"):
        run(split, out, Counted(), ids=["00001", "00007"])
    assert not out.exists()


KILLED_RUN = """
import pathlib, sys, time
from rigidbench.predictors import image_space
real = image_space.slow
split, out, mark = (pathlib.Path(a) for a in sys.argv[1:4])

def slow(sample, severity):
    if pathlib.Path(sample.path).name == "00001":  # hangs on the second example, to be killed there
        mark.write_text("started")
        time.sleep(120)
    return real(sample, severity)

image_space.slow = slow
from rigidbench.stages.predict import predict
from rigidbench.predictors import PredictContext
from rigidbench.driver import RunOptions
predict("slow", split, out, PredictContext(severity=0.5), run=RunOptions(progress=False))
"""


def test_a_killed_run_resumes_with_the_outputs_of_a_clean_run(split, tmp_path):
    out, mark = tmp_path / "out", tmp_path / "started"
    kill_when(python(KILLED_RUN, split, out, mark), mark)
    assert read_ledger(out, STAGE, "00000")["status"] == "succeeded" and (out / "00000.mp4").is_file()
    assert read_ledger(out, STAGE, "00001") is None and not (out / "00001.mp4").exists()
    assert staging_path(out, STAGE, "00001").is_dir()  # what the killed example had begun
    (out / ".00001.partial.mp4").write_bytes(b"half")  # and what a run of the earlier stage left in the folder
    counter = Counted()
    resumed = run(split, out, counter)
    assert resumed.reused == ["00000"] and resumed.succeeded == IDS and not resumed.failed
    assert counter.calls == ["00001", "00002"]
    assert not staging_path(out, STAGE, "00001").exists() and not (out / ".00001.partial.mp4").exists()
    clean = tmp_path / "clean"
    run(split, clean, Counted())
    assert_same(outputs(out), outputs(clean))
    assert sorted(p.name for p in out.iterdir() if not p.name.startswith(".")) == \
           sorted(p.name for p in clean.iterdir() if not p.name.startswith("."))


def test_a_dry_run_follows_the_run_rule_and_writes_nothing(split, tmp_path, capsys):
    out, counter = tmp_path / "out", Counted()
    run(split, out, counter, ids=["00000", "00002"])
    (split / "00002" / "prompt.txt").write_text("Another task.\n")
    before = snapshot(out)
    capsys.readouterr()
    planned = run(split, out, counter, dry_run=True)
    assert planned.facts.planned == ["00001", "00002"] and planned.reused == ["00000"] and planned.facts.paid_calls == 0
    assert planned.redone == {"00002": CHANGED}
    lines = capsys.readouterr().out.strip().splitlines()
    assert [line.split(":", 1)[0] for line in lines] == ["00001", "00002"]
    assert json.loads(lines[0].split(": ", 1)[1]) == {"severity": 0.5, "re-rendered": False}
    assert snapshot(out) == before and counter.calls == ["00000", "00002"]
    assert run(split, out, counter).succeeded == IDS and counter.calls == ["00000", "00002", "00001", "00002"]


# -- a hosted model against the stand-in server ---------------------------------------------------------

FAST_CLIENT = {"request_timeout_s": 5, "poll_interval_s": 0.01, "poll_max_interval_s": 0.02, "max_retries": 3,
               "backoff_base_s": 0.01, "backoff_max_s": 0.05, "example_timeout_s": 10, "max_output_bytes": 200_000}



def hosted_config(tmp_path, seed_field=None) -> Path:
    data = yaml.safe_load((PACKAGE_CONFIG_DIR / "models.yaml").read_text())
    data["client"].update(FAST_CLIENT)
    if seed_field:
        data["models"]["grok-imagine"]["seed_field"] = seed_field
    folder = tmp_path / f"config-{seed_field or 'paper'}"
    folder.mkdir()
    (folder / "models.yaml").write_text(yaml.safe_dump(data))
    return folder


def hosted(split, out, config, seed=7):
    ctx = PredictContext(RunContext(config_dirs=(config,)), seed=seed, options={"concurrency": 3})
    return predict("grok-imagine", split, out, ctx, run=RunOptions(progress=False))


def test_hosted_reruns_pay_only_for_examples_whose_request_changed(server, tmp_path):
    split, out = make_split(tmp_path / "eval", 3), tmp_path / "out"
    config = hosted_config(tmp_path)
    assert hosted(split, out, config).succeeded == IDS and len(server.created) == 3
    requests = len(server.requests)
    again = hosted(split, out, config, seed=8)  # no seed is sent to this model: the same requests
    assert again.reused == IDS and len(server.requests) == requests  # not even a status poll
    (split / "00001" / "prompt.txt").write_text("A green pear rolls off the shelf.\n")
    changed = hosted(split, out, config)
    assert changed.reused == ["00000", "00002"] and changed.redone == {"00001": CHANGED}
    assert len(server.created) == 4
    assert server.creations()[-1].json["input"]["prompt"].startswith("A green pear rolls off the shelf.")
    entry = generation(out)["examples"]["00001"]
    assert entry["status"] == "succeeded" and entry["prediction_id"] == server.created[-1]


def test_hosted_seeds_are_part_of_each_examples_key_when_the_model_takes_one(server, tmp_path):
    split, out = make_split(tmp_path / "eval", 2), tmp_path / "out"
    config = hosted_config(tmp_path, seed_field="seed")
    hosted(split, out, config, seed=7)
    assert sorted(c.json["input"]["seed"] for c in server.creations()) == \
           sorted(example_seed(7, i) for i in ("00000", "00001"))
    assert hosted(split, out, config, seed=7).reused == ["00000", "00001"] and len(server.created) == 2
    other = hosted(split, out, config, seed=8)
    assert other.redone == {"00000": CHANGED, "00001": CHANGED} and len(server.created) == 4
    assert sorted(c.json["input"]["seed"] for c in server.creations()[2:]) == \
           sorted(example_seed(8, i) for i in ("00000", "00001"))
    assert {i: e["seed"] for i, e in generation(out)["examples"].items()} == \
           {i: example_seed(8, i) for i in ("00000", "00001")}
    assert ledger_path(out, STAGE, "00000").is_file()
