"""Predictions folders written by earlier versions of the predict stage, one hand-made folder per layout:
(0) before ledgers (``.predictor.json`` and generation.json's records), (1) ledgers with a record per example
in ``.generation/<id>.json`` beside ``.predictor.json``, and today's folder with a video whose ledger entry a
kill lost, or with a damaged or missing generation.json. In each, nothing is predicted again, each video keeps
its record, generation.json lists the same examples with the same seeds, and the old files go."""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import pytest

pytest.importorskip("av")

from fixtures.predicting import IDS, SLOW, Counted, generation, run  # noqa: E402
from fixtures.predicting import imported, split  # noqa: E402,F401 (pytest fixtures)

from rigidbench.driver import ledger_path, read_ledger  # noqa: E402
from rigidbench.folders import GENERATION_FILE  # noqa: E402
from rigidbench.groundtruth.bundle import Sample  # noqa: E402
from rigidbench.predictors import example_seed, image_space  # noqa: E402
from rigidbench.stages.predict import STAGE, write_prediction  # noqa: E402

SETTINGS = {"predictor": "slow", "target": SLOW, "severity": 0.5}


def old_header(settings=SETTINGS) -> dict:
    return {"predictor": "slow", "target": SLOW, "kind": "failure_mode", "settings": settings, "model": {},
            "versions": {}}


def videos(split: Path, out: Path, severity: float = 0.5, ids=IDS) -> None:
    for sample_id in ids:
        sample = Sample(split / sample_id)
        write_prediction(image_space.slow(sample, severity), out, sample_id, sample.fps)


def assert_taken_over(out: Path, records: dict) -> None:
    """Every video has its ledger entry holding its record, and generation.json lists exactly these records;
    the older layouts' files are gone."""
    assert generation(out)["examples"] == records
    for sample_id, record in records.items():
        entry = read_ledger(out, STAGE, sample_id)
        assert entry["status"] == "succeeded" and entry["result"] == record
    assert not (out / ".predictor.json").exists() and not (out / ".generation").exists()


def test_a_folder_written_before_ledgers_is_taken_over_without_predicting_again(split, tmp_path):
    out, counter = tmp_path / "out", Counted()
    videos(split, out)
    (out / ".predictor.json").write_text(json.dumps(SETTINGS))
    old = {i: {"status": "succeeded", "seed": example_seed(0, i), "prompt": f"old {i}", "seconds": 1.5}
           for i in ("00000", "00001")}  # 00002's record was lost
    (out / GENERATION_FILE).write_text(json.dumps({**old_header(), "examples": old}))
    stamps = {p.name: p.stat().st_mtime_ns for p in out.glob("*.mp4")}
    planned = run(split, out, counter, dry_run=True)
    assert planned.reused == IDS and planned.facts.planned == [] and not (out / ".stages").exists()
    report = run(split, out, counter)
    assert report.reused == IDS and counter.calls == []  # nothing predicted again
    assert {p.name: p.stat().st_mtime_ns for p in out.glob("*.mp4")} == stamps
    rebuilt = generation(out)["examples"]["00002"]
    assert rebuilt["seed"] == example_seed(0, "00002") and "recovered" in rebuilt
    assert rebuilt["prompt"] == Sample(split / "00002").prompt + image_space_suffix(split, "00002")
    assert_taken_over(out, {**old, "00002": rebuilt})
    assert all(read_ledger(out, STAGE, i)["adopted"] is True for i in IDS)
    assert run(split, out, counter).reused == IDS and counter.calls == []


def image_space_suffix(split: Path, sample_id: str) -> str:
    """What the paper's prompt adds after the bundle's own prompt (the record holds the model's prompt)."""
    from rigidbench.predictors import model_inputs
    return model_inputs(Sample(split / sample_id)).prompt[len(Sample(split / sample_id).prompt):]


def test_a_folder_made_with_other_settings_or_without_a_state_is_predicted(split, tmp_path):
    out, counter = tmp_path / "out", Counted()
    videos(split, out, severity=0.2)
    (out / ".predictor.json").write_text(json.dumps({**SETTINGS, "severity": 0.2}))
    assert run(split, out, counter).reused == [] and counter.calls == IDS
    other, counter = tmp_path / "other", Counted()
    videos(split, other)
    (other / ".predictor.json").write_text(json.dumps(SETTINGS))
    (other / "00002.state.npz").unlink()
    assert run(split, other, counter).reused == ["00000", "00001"] and counter.calls == ["00002"]


def settings_digest(settings: dict) -> str:
    """How layout (1) named the settings of its records (re-implemented here)."""
    doc = {"predictor": "slow", "settings": settings}
    return hashlib.sha256(json.dumps(doc, sort_keys=True).encode()).hexdigest()[:16]


def test_a_folder_with_per_example_records_is_taken_over_without_predicting_again(split, tmp_path):
    out, counter = tmp_path / "out", Counted()
    run(split, out, counter)  # the ledger's keys are the same in layout (1): make them, then add its files
    records = generation(out)["examples"]
    records["00001"] = {**records["00001"], "prediction_id": "kept"}  # only its .generation record says so
    for sample_id in IDS:
        rel = f".generation/{sample_id}.json"
        (out / rel).parent.mkdir(exist_ok=True)
        (out / rel).write_text(json.dumps({"id": sample_id, "settings": settings_digest(SETTINGS),
                                           "entry": records[sample_id]}))
        entry = read_ledger(out, STAGE, sample_id)
        entry["outputs"][rel] = "object"
        ledger_path(out, STAGE, sample_id).write_text(json.dumps(entry))
    (out / ".predictor.json").write_text(json.dumps(SETTINGS))
    ledger_path(out, STAGE, "00001").unlink()  # killed between the commit and the ledger entry
    (out / GENERATION_FILE).write_text(json.dumps({**old_header(), "examples": {}}))  # killed before it
    report = run(split, out, Counted())
    assert report.reused == IDS and report.succeeded == IDS
    assert_taken_over(out, records)
    assert [i for i in IDS if read_ledger(out, STAGE, i).get("adopted")] == ["00001"]


def test_a_video_without_its_ledger_entry_and_a_lost_generation_json_are_rebuilt(split, tmp_path):
    out, counter = tmp_path / "out", Counted()
    run(split, out, counter)
    made = generation(out)
    ledger_path(out, STAGE, "00001").unlink()  # killed between the commit and the ledger entry
    assert run(split, out, counter).reused == IDS and counter.calls == IDS
    assert generation(out) == made and read_ledger(out, STAGE, "00001")["adopted"] is True
    (out / GENERATION_FILE).write_text('{"predictor": "sl')  # damaged
    assert run(split, out, counter).reused == IDS and generation(out) == made
    (out / GENERATION_FILE).unlink()
    assert run(split, out, counter).reused == IDS and generation(out) == made
    assert counter.calls == IDS
