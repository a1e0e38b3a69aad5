"""evaluate --envelope ENV: the run's records against a physical envelope folder written here by hand.

The reference set is the synthetic published set imported (three examples, no Blender), scored with gt
perception; the `reference` and `static` predictions are the predict stage's. Each envelope folder is
written by the test in the layout `rigidbench envelope` makes (envelope.json, run/examples/<id>.json and
<id>.s<k>.json twin records), with twin scores placed around the reference's own scores, so every expected
number follows from the records by hand."""

from __future__ import annotations

import json
import logging
import math
import shutil
from pathlib import Path

import numpy as np
import pytest

from fixtures.published_runs import IDS, imported_with_reference
from rigidbench.cli import main
from rigidbench.driver import RunOptions
from rigidbench.errors import UserError
from rigidbench.evaluation.envelope import check_envelope, envelope_block, read_envelope
from rigidbench.groundtruth.bundle import dataset_identity
from rigidbench.metrics import METRICS
from rigidbench.perception.features import FeatureNets
from rigidbench.predictors import PredictContext
from rigidbench.stages import evaluate as runner
from rigidbench.stages.evaluate import evaluate
from rigidbench.stages.predict import predict

pytest.importorskip("av")

N = 8
# twins at v + spread * OFFSETS: type-7 quantiles of linspace(-1, 1, 8): h = 0.35 -> -1 + 0.35 * 2/7 = -0.9
OFFSETS = np.linspace(-1.0, 1.0, N)
Q = 0.9


def score(preds: Path, data: Path, out: Path, **options):
    return evaluate(preds, data, out, nets=FeatureNets(), run=RunOptions(progress=False), **options)


@pytest.fixture(scope="module")
def scored(tmp_path_factory):
    """(data root, reference predictions, static predictions, the reference's records, the static's records)."""
    root = tmp_path_factory.mktemp("envelope")
    data, reference = imported_with_reference(root)
    static = root / "static"
    made = predict("static", data / "eval", static, PredictContext(severity=1.0), run=RunOptions(progress=False))
    assert made.succeeded == list(IDS)
    records = {}
    for name, preds in (("reference", reference), ("static", static)):
        report = score(preds, data, root / "runs" / name)
        assert not report.failed
        records[name] = {i: json.loads((root / "runs" / name / "examples" / f"{i}.json").read_text()) for i in IDS}
    return data, reference, static, records["reference"], records["static"]


def never_score(monkeypatch, why: str) -> None:
    def boom(*args, **kwargs):
        raise AssertionError(why)

    monkeypatch.setattr(runner, "_score_one", boom)


def twin_values(value: float | None, spread: float) -> list[float | None]:
    return [None] * N if value is None else [value + spread * o for o in OFFSETS]


def write_envelope(env: Path, ref_records: dict, spread, status: dict | None = None, **doc) -> Path:
    """An envelope folder whose twins of example i score ``ref value + spread(value) * OFFSETS`` per measurement
    (None stays None); ``status``: id -> reason for examples marked "no envelope" (no twin records)."""
    status = status or {}
    examples = env / "run" / "examples"
    examples.mkdir(parents=True)
    for sample_id, record in ref_records.items():
        if sample_id in status:
            continue
        twins = {m: twin_values(v, spread(v) if v is not None else 0.0) for m, v in record["metrics"].items()}
        for k in range(N):
            twin = {"id": sample_id, "sample": k, "task": record["task"], "partition": record["partition"],
                    "metrics": {m: twins[m][k] for m in twins}}
            if k == 0 and sample_id == "00000":
                del twin["sample"]  # a record without "sample" is twin 0
            name = sample_id if k == 0 else f"{sample_id}.s{k}"
            (examples / f"{name}.json").write_text(json.dumps(twin))
    body = {"config": {"position_px": 1.0}, "twins": N, "geometry_only": False, "scale": 1.0,
            "examples": {i: ({"status": "no envelope", "reason": status[i], "twins": 0} if i in status else
                             {"status": "ok", "reason": None, "twins": N}) for i in ref_records}, **doc}
    (env / "envelope.json").write_text(json.dumps(body))
    return env


def measured(ref_records: dict) -> list[str]:
    return [m for m in METRICS if any(r["metrics"].get(m) is not None for r in ref_records.values())]


def test_the_reference_lies_inside_an_envelope_that_straddles_it(scored, tmp_path):
    data, reference, _, ref, _ = scored
    env = write_envelope(tmp_path / "env", ref, lambda v: 0.05 * (abs(v) + 1.0))
    results = score(reference, data, tmp_path / "run", envelope=env).facts.results
    block = results["envelope"]
    metrics = measured(ref)
    assert {"iou", "centroid_l2", "ate"} <= set(metrics)
    assert block["metrics"] == metrics and block["twins"] == N and block["geometry_only"] is False
    assert block["source"] == str(env) and block["n_no_envelope"] == 0 and block["no_envelope"] == {}
    for m in metrics:
        assert block["overall"][m] == {"inside": 1.0, "excess": 0.0, "n": 3}
    tasks = sorted({r["task"] for r in ref.values()})
    assert sorted(block["by_task"]) == tasks and sorted(block["widths"]) == tasks
    assert sorted(block["by_partition"]) == sorted({r["partition"] for r in ref.values()})
    for sample_id, record in ref.items():
        for m in metrics:
            v = record["metrics"][m]
            entry = block["per_example"][sample_id][m]
            spread = 0.05 * (abs(v) + 1.0)
            assert entry["q05"] == pytest.approx(v - Q * spread) and entry["q95"] == pytest.approx(v + Q * spread)
            assert entry["median"] == pytest.approx(v) and entry["value"] == pytest.approx(v)
            assert entry["position"] == 0.5 and entry["sample_positions"] == [0.5]  # beats 4 of 8
            assert entry["inside"] is True and entry["excess"] == 0.0 and entry["twins"] == N
    for task in tasks:  # the width: q95 - q05 = 1.8 spread, its median over the task's examples
        widths = [2 * Q * 0.05 * (abs(r["metrics"]["ate"]) + 1.0) for r in ref.values() if r["task"] == task]
        assert block["widths"][task]["ate"] == pytest.approx(float(np.median(widths)))
    # the scores themselves are those of a run without an envelope
    plain = json.loads((tmp_path / "run" / "results.json").read_text())
    assert {k: v for k, v in plain.items() if k != "envelope"} == {k: v for k, v in results.items() if k != "envelope"}


def test_static_falls_outside_an_envelope_of_near_reference_twins(scored, tmp_path):
    data, _, static, ref, stat = scored
    env = write_envelope(tmp_path / "env", ref, lambda v: 1e-3)
    block = score(static, data, tmp_path / "run", envelope=env).facts.results["envelope"]
    moved = [m for m in ("iou", "centroid_l2", "chamfer", "ate")
             if all(abs(stat[i]["metrics"][m] - ref[i]["metrics"][m]) > 1e-2 for i in IDS)]
    assert len(moved) >= 3, "static should move the motion measurements on every example"
    for m in moved:
        assert block["overall"][m]["inside"] == 0.0 and block["overall"][m]["n"] == 3
        assert block["overall"][m]["excess"] > 0
    for sample_id in IDS:  # the excess, by hand: beyond q95 = v + 0.9e-3 (lower is better), q05 = v - 0.9e-3 (IoU)
        v_ref, v = ref[sample_id]["metrics"], stat[sample_id]["metrics"]
        for m in moved:
            want = (max(0.0, v_ref[m] - Q * 1e-3 - v[m]) if METRICS[m].higher_is_better
                    else max(0.0, v[m] - (v_ref[m] + Q * 1e-3)))
            entry = block["per_example"][sample_id][m]
            assert entry["excess"] == pytest.approx(want, abs=1e-12) and entry["inside"] is False
            assert entry["position"] == 0.0  # worse than every twin
    excesses = [block["per_example"][i]["iou"]["excess"] for i in IDS]
    assert block["overall"]["iou"]["excess"] == pytest.approx(np.mean(excesses))


def test_the_envelope_is_not_part_of_an_examples_key(scored, tmp_path, monkeypatch, capsys):
    """A rerun with an envelope, or another one, scores nothing again and rewrites only results.json (through the
    command line: --envelope)."""
    data, reference, _, ref, _ = scored
    out = tmp_path / "run"
    score(reference, data, out)
    before = {p.name: p.read_bytes() for p in (out / "examples").iterdir()}

    never_score(monkeypatch, "an up-to-date example was scored again")
    monkeypatch.setattr(runner, "load_feature_nets", lambda device=None: FeatureNets())
    env = write_envelope(tmp_path / "env", ref, lambda v: 0.1)
    assert main(["evaluate", str(reference), "--data", str(data), "--out", str(out), "--envelope", str(env)]) == 0
    printed = capsys.readouterr().out
    assert f"against the envelope {env} ({N} twins)" in printed and "inside 100.0%" in printed
    results = json.loads((out / "results.json").read_text())
    assert results["envelope"]["source"] == str(env) and results["envelope"]["overall"]["ate"]["n"] == 3
    other = write_envelope(tmp_path / "other", ref, lambda v: 1e-3, status={"00002": "re-simulation off by 3 cm"})
    results = score(reference, data, out, envelope=other).facts.results
    assert results["envelope"]["source"] == str(other) and results["envelope"]["overall"]["ate"]["n"] == 2
    assert {p.name: p.read_bytes() for p in (out / "examples").iterdir()} == before


def test_examples_without_an_envelope_are_counted_and_named(scored, tmp_path):
    data, reference, _, ref, _ = scored
    env = write_envelope(tmp_path / "env", ref, lambda v: 0.1, status={"00002": "re-simulation off by 3 cm"})
    for twin in (env / "run" / "examples").glob("00001*.json"):  # declared ok, but its twins are gone
        twin.unlink()
    block = score(reference, data, tmp_path / "run", envelope=env).facts.results["envelope"]
    assert block["n_no_envelope"] == 2 and sorted(block["no_envelope"]) == ["00001", "00002"]
    assert block["no_envelope"]["00002"] == "re-simulation off by 3 cm"
    assert "no readable twin record" in block["no_envelope"]["00001"]
    assert list(block["per_example"]) == ["00000"] and block["overall"]["ate"]["n"] == 1


def test_a_geometry_only_envelope_measures_the_motion_group(scored, tmp_path):
    _, _, _, ref, _ = scored
    env = read_envelope(write_envelope(tmp_path / "env", ref, lambda v: 0.1, geometry_only=True))
    assert env.geometry_only and env.metrics and all(METRICS[m].group == "motion" for m in env.metrics)
    assert "ssim" not in env.metrics and "iou" in env.metrics


def test_an_envelope_for_another_set_is_refused_before_scoring(scored, tmp_path, monkeypatch):
    data, reference, _, ref, _ = scored
    never_score(monkeypatch, "scored although the envelope is for another set")
    others = {f"1{i}": {**r, "id": f"1{i}"} for i, r in ref.items()}
    env = write_envelope(tmp_path / "ids", others, lambda v: 0.1)
    with pytest.raises(UserError, match="none of the run's 3 examples"):
        score(reference, data, tmp_path / "run", envelope=env)
    identity = dataset_identity(json.loads((data / "eval" / "00000" / "metadata.json").read_text()))
    assert identity["version"] != "9.9"
    env = write_envelope(tmp_path / "version", ref, lambda v: 0.1, dataset={**identity, "version": "9.9"})
    with pytest.raises(UserError, match=r"made for the set version 9\.9, but .*rigidbench envelope"):
        score(reference, data, tmp_path / "run", envelope=env)
    rendered = {"dataset": "rendered", "version": "bundle v3", "md5": None, "preset": "paper"}
    env = write_envelope(tmp_path / "rendered", ref, lambda v: 0.1, dataset=rendered)
    with pytest.raises(UserError, match="made for the set dataset rendered version bundle v3 preset paper, but"):
        score(reference, data, tmp_path / "run", envelope=env)
    env = write_envelope(tmp_path / "same", ref, lambda v: 0.1, dataset={**identity, "verified": True})
    check_envelope(read_envelope(env), IDS, identity)  # the same set, whether or not its MD5 was checked
    assert not (tmp_path / "run" / "examples").exists()


def test_damaged_envelope_files(scored, tmp_path, caplog):
    _, _, _, ref, _ = scored
    good = write_envelope(tmp_path / "good", ref, lambda v: 0.1)

    def copy(name: str) -> Path:
        return Path(shutil.copytree(good, tmp_path / name))

    env = copy("absent")
    (env / "envelope.json").unlink()
    with pytest.raises(UserError, match=r"envelope\.json: not found.*rigidbench envelope"):
        read_envelope(env)
    env = copy("truncated")
    (env / "envelope.json").write_text((good / "envelope.json").read_text()[:40])
    with pytest.raises(UserError, match=r"envelope\.json: truncated or not JSON.*rigidbench envelope"):
        read_envelope(env)
    env = copy("field")
    doc = json.loads((good / "envelope.json").read_text())
    (env / "envelope.json").write_text(json.dumps({**doc, "twins": "eight"}))
    with pytest.raises(UserError, match="'twins' is not a positive whole number"):
        read_envelope(env)
    env = copy("no-run")
    shutil.rmtree(env / "run")
    with pytest.raises(UserError, match=r"run/examples: not found"):
        read_envelope(env)
    with pytest.raises(UserError, match="no such envelope folder"):
        read_envelope(tmp_path / "nowhere")

    # one damaged twin record and one under another twin's name: each left out with a warning, not fatal
    env = copy("one-twin")
    (env / "run" / "examples" / "00001.s3.json").write_text('{"id": "00001", "sa')
    misnamed = json.loads((env / "run" / "examples" / "00001.s5.json").read_text())
    (env / "run" / "examples" / "00001.s5.json").write_text(json.dumps({**misnamed, "sample": 6}))
    with caplog.at_level(logging.WARNING):
        envelope = read_envelope(env)
    assert sorted(Path(p).name for p in envelope.skipped) == ["00001.s3.json", "00001.s5.json"]
    assert "00001.s3.json" in caplog.text and "whose file is 00001.s6.json" in caplog.text
    ate = envelope.twins["00001"]["ate"]
    assert len(ate) == N - 2 and np.isfinite(ate).all()
    want = [ref["00001"]["metrics"]["ate"] + 0.1 * OFFSETS[k] for k in range(N) if k not in (3, 5)]
    assert ate.tolist() == pytest.approx(want)
    assert len(envelope.twins["00000"]["ate"]) == N and not envelope.no_envelope
    assert math.isclose(envelope.scale, 1.0) and envelope.n_twins == N


def test_several_samples_per_example_are_placed_by_their_mean(scored, tmp_path):
    """Records of (example, sample) as a K-sample run writes them: the value is the mean of the example's finite
    samples, and each sample gets its own position."""
    _, _, _, ref, _ = scored
    envelope = read_envelope(write_envelope(tmp_path / "env", ref, lambda v: 0.1))
    v = ref["00000"]["metrics"]["ate"]
    records = []
    for k, ate in enumerate([v + 0.2, v - 0.2, None]):  # twins span v +- 0.1: beyond, better than all, missing
        records.append({**ref["00000"], "sample": k, "metrics": {**ref["00000"]["metrics"], "ate": ate}})
    block = envelope_block(envelope, records)
    entry = block["per_example"]["00000"]["ate"]
    assert entry["value"] == pytest.approx(v) and entry["inside"] is True and entry["position"] == 0.5
    assert entry["sample_positions"] == [0.0, 1.0, None]
    assert block["overall"]["ate"] == {"inside": 1.0, "excess": 0.0, "n": 1}
    assert block["no_envelope"] == {} and list(block["per_example"]) == ["00000"]
