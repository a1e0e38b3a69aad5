"""evaluate with several samples (generations) per example: items, records and results.json.

The reference set is the synthetic published set imported (three examples, no Blender), scored with gt
perception. Samples are put together by hand under the naming rule (``<id>.mp4`` is sample 0, ``<id>.s<k>.mp4``
sample k, each with its world state beside it) from the predict stage's `reference` and `slow` predictions, so
the samples of one example differ. Every expected number is computed here with numpy from the records on
disk (or, for the rules, from the files), not taken from the code under test."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from fixtures.published_runs import IDS, imported_with_reference
from rigidbench.cli import main
from rigidbench.driver import RunOptions, Selection, read_ledger
from rigidbench.evaluation.keys import file_hash, input_key, reference_hash
from rigidbench.folders import RunFolder
from rigidbench.hashing import digest
from rigidbench.metrics import METRICS
from rigidbench.perception.features import FeatureNets, feature_nets_key
from rigidbench.predictors import PredictContext
from rigidbench.report.load import load_runs
from rigidbench.stages import evaluate as runner
from rigidbench.stages.evaluate import evaluate
from rigidbench.stages.predict import predict
from rigidbench.submissions.provenance import read_run_files
from rigidbench.submissions.validate import run_problems

pytest.importorskip("av")

MS = tuple(METRICS)
#: example -> the prediction folder (by name) each of its samples comes from, sample 0 first
LAYOUT = {"00000": ("reference", "slow05"), "00001": ("reference", "slow05", "slow08"),
          "00002": ("slow08", "reference")}
ITEMS = ["00000", "00000.s1", "00001", "00001.s1", "00001.s2", "00002", "00002.s1"]


def score(preds: Path, data: Path, out: Path, ids=None, limit=None):
    return evaluate(preds, data, out, nets=FeatureNets(), run=RunOptions(Selection.of(ids, limit), progress=False))


def copy_sample(source: Path, example: str, preds: Path, k: int) -> None:
    stem = example if k == 0 else f"{example}.s{k}"
    shutil.copyfile(source / f"{example}.mp4", preds / f"{stem}.mp4")
    shutil.copyfile(source / f"{example}.state.npz", preds / f"{stem}.state.npz")


@pytest.fixture(scope="module")
def made(tmp_path_factory):
    """(data root, the reference predictions, the samples folder of LAYOUT, its run folder scored once)."""
    root = tmp_path_factory.mktemp("samples")
    data, reference = imported_with_reference(root)
    folders = {"reference": reference}
    for name, severity in (("slow05", 0.5), ("slow08", 0.8)):
        report = predict("slow", data / "eval", root / name, PredictContext(severity=severity),
                         run=RunOptions(progress=False))
        assert report.succeeded == list(IDS)
        folders[name] = root / name
    samples = root / "samples"
    samples.mkdir()
    for example, sources in LAYOUT.items():
        for k, name in enumerate(sources):
            copy_sample(folders[name], example, samples, k)
    run = root / "run"
    report = score(samples, data, run)
    assert report.ran == ITEMS and not report.failed and report.unit == "sample"
    return data, reference, samples, run


@pytest.fixture()
def private(made, tmp_path):
    """A private copy of the samples folder and of its scored run folder."""
    data, _, samples, run = made
    shutil.copytree(samples, tmp_path / "samples")
    shutil.copytree(run, tmp_path / "run")
    return data, tmp_path / "samples", tmp_path / "run"


def sample_records(run: Path) -> dict[str, list[dict]]:
    """Example id -> its records read from examples/ (every .json but the readouts), by sample index."""
    out: dict[str, list[dict]] = {}
    for p in sorted((run / "examples").glob("*.json")):
        if not p.name.endswith(".readouts.json"):
            record = json.loads(p.read_text())
            out.setdefault(record["id"], []).append(record)
    return {i: sorted(rs, key=lambda r: r.get("sample", 0)) for i, rs in sorted(out.items())}


def matrix(records: dict[str, list[dict]], metric: str) -> np.ndarray:
    """(E, K) of one measurement, NaN-padded: sample k of an example in column k."""
    k = max(r.get("sample", 0) for rs in records.values() for r in rs) + 1
    out = np.full((len(records), k), np.nan)
    for e, rs in enumerate(records.values()):
        for r in rs:
            v = r["metrics"][metric]
            out[e, r.get("sample", 0)] = np.nan if v is None else v
    return out


def test_one_sample_per_example_keeps_todays_items_keys_and_numbers(made, tmp_path):
    """A folder of <id>.mp4 only: the items are the example ids, each key is the pre-samples formula of its
    video, and every number of results.json follows from the three records by hand."""
    data, reference, _, _ = made
    out = tmp_path / "run"
    report = score(reference, data, out)
    assert report.ran == list(IDS) and report.unit == "example" and not report.failed
    assert sorted(p.name for p in (out / ".stages" / "evaluate").glob("*.json")) == [f"{i}.json" for i in IDS]
    assert [p.name for p in RunFolder(out).records()] == [f"{i}.json" for i in IDS]
    for i in IDS:  # the key as it was computed before samples existed
        pred = reference / f"{i}.mp4"
        backend = runner.get_backend("gt")
        key = input_key(file_hash(pred) + file_hash(reference / f"{i}.state.npz"), reference_hash(data / "eval" / i),
                        f"{backend.name}:{backend.version}", feature_nets_key(), MS, "protocol="
                        + runner.get_protocol(None).key())
        assert read_ledger(out, "evaluate", i)["key"] == digest(key, {"first_frame_check": True, "allow_short": False})
    records = [json.loads((out / "examples" / f"{i}.json").read_text()) for i in IDS]
    assert [r["sample"] for r in records] == [0, 0, 0] and [r["id"] for r in records] == list(IDS)
    results = json.loads((out / "results.json").read_text())
    assert results["n_examples"] == 3 and results["failed"] == {}
    assert sorted(results["coverage"]["per_example"]) == list(IDS)
    for m in MS:
        values = [r["metrics"][m] for r in records]
        finite = np.array([v for v in values if v is not None], float)
        want = ({"mean": float(finite.mean()), "std": float(finite.std()), "finite": len(finite), "n": 3}
                if len(finite) else {"mean": None, "std": None, "finite": 0, "n": 3})
        assert results["overall"][m] == want  # exactly: the mean of one sample is the sample
        for task in {r["task"] for r in records}:
            part = [r["metrics"][m] for r in records if r["task"] == task and r["metrics"][m] is not None]
            assert results["by_task"][task][m]["finite"] == len(part)
            if part:
                assert results["by_task"][task][m]["mean"] == float(np.mean(part))
        block = results["samples"]["metrics"][m]
        assert block["seed_std"] is None and block["within_example_std"] is None
        assert results["variance"][m]["within_example"] is None
        if len(finite) >= 2:
            assert block["mean"] == pytest.approx(finite.mean(), rel=1e-12, abs=1e-15)
            assert block["best_of_k"]["mean"] == pytest.approx(finite.mean(), rel=1e-12, abs=1e-15)
            assert results["variance"][m]["between_example"] == pytest.approx(np.var(finite, ddof=1), rel=1e-12,
                                                                               abs=1e-18)
    assert results["samples"]["samples_per_example"] == {"min": 1, "max": 1} and results["samples"]["n_items"] == 3


def test_several_samples_are_averaged_per_example_with_their_spreads(made):
    data, _, samples, run = made
    assert [p.name for p in RunFolder(run).records()] == [f"{i}.json" for i in ITEMS]
    records = sample_records(run)
    assert {i: [r["sample"] for r in rs] for i, rs in records.items()} == {"00000": [0, 1], "00001": [0, 1, 2],
                                                                         "00002": [0, 1]}
    results = json.loads((run / "results.json").read_text())
    assert results["n_examples"] == 3 and results["failed"] == {}
    assert results["samples"]["samples_per_example"] == {"min": 2, "max": 3} and results["samples"]["n_items"] == 7
    assert results["samples"]["scheme"] == "examples"
    differ = 0
    for m in MS:
        y = matrix(records, m)
        if np.isnan(y).all():
            assert results["overall"][m]["mean"] is None
            continue
        has = np.isfinite(y)
        means = np.nansum(y, axis=1) / has.sum(axis=1)
        assert results["overall"][m]["mean"] == pytest.approx(means.mean(), rel=1e-12, abs=1e-15)
        assert results["overall"][m]["std"] == pytest.approx(means.std(), rel=1e-9, abs=1e-15)
        assert results["overall"][m]["n"] == 3
        tasks = np.array([rs[0]["task"] for rs in records.values()])
        for task in set(tasks):
            assert results["by_task"][task][m]["mean"] == pytest.approx(means[tasks == task].mean(), rel=1e-12,
                                                                        abs=1e-15)
        block = results["samples"]["metrics"][m]
        column_means = [float(np.nanmean(y[:, k])) for k in range(3)]  # sample k over the examples that have it
        assert block["sample_index_means"] == pytest.approx(column_means, rel=1e-12, abs=1e-15)
        assert block["seed_std"] == pytest.approx(np.std(column_means, ddof=1), rel=1e-9, abs=1e-15)
        resid = np.nansum((y - means[:, None]) ** 2)
        within = np.sqrt(resid / (has.sum() - 3))  # pooled over 1 + 2 + 1 degrees of freedom
        assert block["within_example_std"] == pytest.approx(within, rel=1e-9, abs=1e-15)
        assert results["variance"][m]["within_example"] == pytest.approx(within ** 2, rel=1e-9, abs=1e-18)
        assert results["variance"][m]["between_example"] == pytest.approx(np.var(means, ddof=1), rel=1e-9, abs=1e-18)
        assert block["mean"] == pytest.approx(means.mean(), rel=1e-12, abs=1e-15)
        best = np.nanmax(y, axis=1) if METRICS[m].higher_is_better else np.nanmin(y, axis=1)
        assert block["best_of_k"]["mean"] == pytest.approx(best.mean(), rel=1e-12, abs=1e-15)
        assert "best of 3" in block["best_of_k"]["label"] and "not the headline" in block["best_of_k"]["label"]
        differ += within > 0
    assert differ >= 3  # the samples do differ (slow and reference), on several measurements


def test_the_report_reads_per_example_means_and_keeps_the_samples(made):
    _, _, _, run = made
    table = load_runs([run])
    records = sample_records(run)
    assert table.example_ids == IDS and table.samples.shape == (1, 3, len(MS), 3)
    assert table.n_samples.tolist() == [[2, 3, 2]]
    for j, m in enumerate(table.metrics):
        y = matrix(records, m)
        np.testing.assert_array_equal(table.samples[0, :, j, :], y)  # NaN where an example has no sample 2
        finite = np.isfinite(y).sum(axis=1)
        want = np.where(finite > 0, np.nansum(y, axis=1) / np.maximum(finite, 1), np.nan)
        np.testing.assert_allclose(table.scores[0, :, j], want, rtol=1e-12, atol=1e-15)


def test_a_deleted_sample_record_is_scored_again_alone(private):
    data, samples, run = private
    results = json.loads((run / "results.json").read_text())
    (run / "examples" / "00001.s2.json").unlink()
    again = score(samples, data, run)
    assert again.ran == ["00001.s2"] and again.reused == [i for i in ITEMS if i != "00001.s2"]
    assert again.redone == {"00001.s2": "its output is missing or damaged"}
    assert json.loads((run / "results.json").read_text()) == results


def test_ids_and_limit_choose_examples_with_all_their_samples(private, tmp_path):
    data, samples, _ = private
    one = score(samples, data, tmp_path / "one", ids=["00001"])
    assert one.selected == ["00001", "00001.s1", "00001.s2"] and one.ran == one.selected
    results = one.facts.results
    assert results["n_examples"] == 1 and list(results["coverage"]["per_example"]) == ["00001"]
    assert results["samples"]["n_items"] == 3 and not results["official"]
    first = score(samples, data, tmp_path / "first", limit=1)
    assert first.selected == ["00000", "00000.s1"]


def test_a_damaged_sample_fails_alone_and_fails_its_example(private, tmp_path):
    """A sample that does not decode and one that is an empty file fail on their own; every other sample is
    scored; their examples count as failed and are left out of the numbers."""
    data, samples, _ = private
    (samples / "00001.s1.mp4").write_bytes(b"not a video at all" * 64)
    (samples / "00002.s1.mp4").write_bytes(b"")
    out = tmp_path / "fresh"
    report = score(samples, data, out)
    assert sorted(report.failed) == ["00001.s1", "00002.s1"]
    assert report.ran == ["00000", "00000.s1", "00001", "00001.s2", "00002"]
    assert "empty" in report.failed["00002.s1"]
    results = report.facts.results
    assert sorted(results["failed"]) == ["00001", "00002"]
    assert results["failed"]["00001"].startswith("sample 1: ") and results["failed"]["00002"].startswith("sample 1: ")
    assert results["n_examples"] == 1 and list(results["coverage"]["per_example"]) == ["00000"]
    records = sample_records(out)
    y = matrix({"00000": records["00000"]}, "iou")[0]
    assert results["overall"]["iou"]["mean"] == pytest.approx(float(np.mean(y)), rel=1e-12)
    assert any("2 examples failed" in why for why in results["why_not_official"])


def test_a_bare_video_beside_sample_0_fails_only_its_example(private, tmp_path):
    data, samples, _ = private
    shutil.copyfile(samples / "00002.mp4", samples / "00002.s0.mp4")
    report = score(samples, data, tmp_path / "fresh")
    assert list(report.failed) == ["00002"] and "00002.mp4, 00002.s0.mp4" in report.failed["00002"]
    assert report.ran == ITEMS[:5]
    assert report.facts.results["failed"] == report.failed and report.facts.results["n_examples"] == 2


def test_the_command_prints_samples_and_seed_spread_and_a_submission_refuses_them(private, monkeypatch, capsys):
    data, samples, run = private
    monkeypatch.setattr(runner, "load_feature_nets", lambda device=None: FeatureNets())
    assert main(["evaluate", str(samples), "--data", str(data), "--out", str(run)]) == 0
    printed = capsys.readouterr().out
    results = json.loads((run / "results.json").read_text())
    assert "samples per example: 2 to 3 (7 scored)" in printed
    assert "0 made, 7 up to date, 0 failed of 7 sample(s)" in printed
    seed_std = results["samples"]["metrics"]["iou"]["seed_std"]
    assert f"{results['overall']['iou']['mean']:.4f} ± {seed_std:.4f}" in printed
    problems = run_problems(read_run_files(run))
    assert any("several samples per example (up to 3)" in p for p in problems)


def test_a_run_folder_lists_sample_records_and_not_other_files(tmp_path):
    examples = tmp_path / "examples"
    examples.mkdir()
    names = ["00001.json", "00001.s2.json", "00001.s0.json", "00001.s01.json", "00001.readouts.json",
             "00001.s2.readouts.json", "00001.x.json", "00002.json"]
    for name in names:
        (examples / name).write_text("{}")
    assert [p.name for p in RunFolder(tmp_path).records()] == ["00001.json", "00001.s2.json", "00002.json"]


def test_coverage_and_notes_are_per_example():
    """Pure aggregation over sample records: an example's coverage is its least covered sample's (short when any
    is), its notes name their samples, and a single-sample example keeps its own."""
    from rigidbench.evaluation.aggregation import coverage_summary, example_notes

    def rec(i, k, fraction, short=False, notes=None):
        return {"id": i, "sample": k, "coverage": {"seconds": 2 * fraction, "fraction": fraction, "frames": 10,
                                                   "reference_frames": 10, "short": short}, "notes": notes or {}}

    records = [rec("a", 0, 1.0), rec("a", 1, 0.5, True, {"ate": "no track"}), rec("a", 2, 0.75),
               rec("b", 0, 1.0, notes={"iou": "empty"})]
    coverage = coverage_summary(records)
    assert coverage["per_example"]["a"]["fraction"] == 0.5 and coverage["short"] == ["a"]
    assert coverage["min_fraction"] == 0.5 and coverage["mean_fraction"] == pytest.approx(0.75)
    assert example_notes(records) == {"a": {"ate": "sample 1: no track"}, "b": {"iou": "empty"}}
