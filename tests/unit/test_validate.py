"""Preflight validation of a predictions directory against reference sample metadata."""

from __future__ import annotations

import json

import numpy as np
import pytest

from rigidbench.preflight import (ERROR, WARNING, ValidationReport, format_report, main, read_reference_specs,
                                  validate_predictions)
from rigidbench.video import write_video

pytest.importorskip("av")

REF_META = {"resolution": [64, 36], "fps": 24, "frames": 49}


@pytest.fixture(autouse=True)
def metadata_only_references(monkeypatch):
    """The reference stand-ins here hold only metadata.json (and a first frame): the checks of the
    predictions are under test, so the bundle check of each reference (validate.check_reference) is off.
    Damaged reference bundles are tested in tests/faults/test_bundle_faults.py."""
    monkeypatch.setattr("rigidbench.preflight.check_reference", lambda bundle_dir, report: None)


def clip(n_frames: int, size=(64, 36)) -> np.ndarray:
    """(T,H,W,3) uint8 frames with a brightness ramp, so the encoder sees real content."""
    width, height = size
    values = (np.arange(n_frames) * 4 % 256).astype(np.uint8)
    return np.broadcast_to(values[:, None, None, None], (n_frames, height, width, 3)).copy()


def make_data_dir(root, ids, meta=REF_META):
    for example_id in ids:
        (root / example_id).mkdir(parents=True)
        (root / example_id / "metadata.json").write_text(json.dumps(meta))
    (root / "not_a_sample").mkdir()  # no metadata.json: not expected
    return root


@pytest.fixture()
def scenario(tmp_path):
    ids = ["ex_good", "ex_cosmos", "ex_missing", "ex_bad", "ex_short", "ex_one_short", "ex_aspect", "ex_dup"]
    data = make_data_dir(tmp_path / "data", ids)
    pred = tmp_path / "pred"
    pred.mkdir()
    write_video(pred / "ex_good.mp4", clip(49), fps=24)
    write_video(pred / "ex_cosmos.mp4", clip(33), fps=16)  # 2.0 s at 16 Hz covers the span
    (pred / "ex_bad.mp4").write_bytes(np.random.default_rng(0).bytes(3000))
    write_video(pred / "ex_short.mp4", clip(24), fps=24)  # ends at 0.958 s
    write_video(pred / "ex_one_short.mp4", clip(48), fps=24)  # ends at 1.958 s, half a frame is 1/48 s
    write_video(pred / "ex_aspect.mp4", clip(49, size=(48, 36)), fps=24)
    write_video(pred / "ex_dup.mp4", clip(49), fps=24)
    write_video(pred / "ex_dup.webm", clip(49), fps=24)
    write_video(pred / "stranger.mp4", clip(49), fps=24)
    (pred / "ex_good.json").write_text("{}")  # a sidecar beside a clip is fine
    (pred / "ex_missing.flv").write_bytes(b"FLV")
    (pred / ".ex_good.tmp.mp4").write_bytes(b"")  # hidden temporaries are ignored
    return pred, data


def ids_of(report: ValidationReport, kind: str) -> set:
    return {issue.example_id for issue in report.of_kind(kind)}


def test_each_problem_is_reported(scenario):
    pred, data = scenario
    report = validate_predictions(pred, data)
    assert set(report.references) == {"ex_good", "ex_cosmos", "ex_missing", "ex_bad", "ex_short",
                                      "ex_one_short", "ex_aspect", "ex_dup"}
    assert report.missing == ["ex_missing"]
    assert ids_of(report, "undecodable") == {"ex_bad"}
    assert ids_of(report, "too_short") == {"ex_short", "ex_one_short"}
    assert ids_of(report, "duplicate") == {"ex_dup"}
    assert ids_of(report, "aspect_ratio") == {"ex_aspect"}
    extras = {issue.path.name for issue in report.of_kind("extra")}
    assert extras == {"stranger.mp4"}
    assert "ex_missing.flv" in report.of_kind("missing")[0].message
    assert all(issue.severity == WARNING for issue in report.of_kind("extra") + report.of_kind("aspect_ratio"))
    blocking = {issue.kind for issue in report.errors}
    assert blocking == {"missing", "undecodable", "too_short", "duplicate"}
    assert not report.ok
    # The good clips produce no issue of their own.
    assert not [i for i in report.issues if i.example_id in ("ex_good", "ex_cosmos") and i.kind != "extra"]
    good = report.files[pred / "ex_good.mp4"]
    assert (good.width, good.height, good.n_frames) == (64, 36, 49)
    assert good.duration_s == pytest.approx(2.0) and good.fps_measured == pytest.approx(24.0)
    cosmos = report.files[pred / "ex_cosmos.mp4"]
    assert cosmos.fps_nominal == pytest.approx(16.0) and cosmos.duration_s == pytest.approx(2.0)
    short = report.files[pred / "ex_short.mp4"]
    assert short.n_frames == 24 and short.duration_s == pytest.approx(23 / 24)


def test_exit_code_and_printed_report(scenario, capsys):
    pred, data = scenario
    assert main(pred, data) == 1
    out = capsys.readouterr().out
    assert "BLOCKED" in out
    for name in ("ex_missing", "ex_bad.mp4", "ex_short.mp4", "ex_aspect.mp4", "stranger.mp4", "ex_dup"):
        assert name in out


def test_clean_predictions_pass(tmp_path, capsys):
    data = make_data_dir(tmp_path / "data", ["a", "b"])
    pred = tmp_path / "pred"
    pred.mkdir()
    write_video(pred / "a.mp4", clip(49), fps=24)
    write_video(pred / "b.mkv", clip(97), fps=24)  # longer clips are fine: cut at 49 frames
    report = validate_predictions(pred, data)
    assert report.ok and report.issues == [] and set(report.matched) == {"a", "b"}
    assert main(pred, data) == 0
    assert "OK: ready for evaluation" in capsys.readouterr().out


def test_aspect_within_two_percent_is_not_flagged(tmp_path):
    # Against a 65x36 reference (1.806): a 64x36 clip differs by 1.5%, a 68x36 clip by 4.6%.
    data = make_data_dir(tmp_path / "data", ["a"], {"resolution": [65, 36], "fps": 24, "frames": 49})
    pred = tmp_path / "pred"
    pred.mkdir()
    write_video(pred / "a.mp4", clip(49), fps=24)
    assert validate_predictions(pred, data).of_kind("aspect_ratio") == []
    write_video(pred / "a.mp4", clip(49, size=(68, 36)), fps=24)
    assert len(validate_predictions(pred, data).of_kind("aspect_ratio")) == 1


def test_metadata_defaults_and_overrides(tmp_path):
    data = make_data_dir(tmp_path / "data", ["plain"], meta={"task": "drop"})
    (data / "short_ref").mkdir()
    (data / "short_ref" / "metadata.json").write_text(json.dumps({"resolution": [64, 36], "fps": 16, "frames": 17}))
    (data / "broken").mkdir()
    (data / "broken" / "metadata.json").write_text("{not json")
    report = ValidationReport(pred_dir=tmp_path, data_dir=data)
    read_reference_specs(data, report, ref_fps=24.0, ref_frames=25)
    plain = report.references["plain"]
    assert (plain.width, plain.height, plain.fps, plain.frames) == (1280, 704, 24.0, 25)
    assert report.references["short_ref"].span_s == pytest.approx(1.0)
    assert "broken" not in report.references
    assert [(i.kind, i.severity, i.example_id) for i in report.issues] == [("bad_metadata", ERROR, "broken")]


def test_reference_span_follows_metadata(tmp_path):
    # A reference of 25 frames at 24 fps only needs 1.0 s.
    data = make_data_dir(tmp_path / "data", ["a"], {"resolution": [64, 36], "fps": 24, "frames": 25})
    pred = tmp_path / "pred"
    pred.mkdir()
    write_video(pred / "a.mp4", clip(25), fps=24)
    assert validate_predictions(pred, data).ok
    write_video(pred / "a.mp4", clip(24), fps=24)
    assert validate_predictions(pred, data).of_kind("too_short")


def test_missing_directories_block(tmp_path):
    report = validate_predictions(tmp_path / "nope", tmp_path / "nodata")
    assert not report.ok and report.errors[0].kind == "no_data"
    data = make_data_dir(tmp_path / "data", ["a"])
    report = validate_predictions(tmp_path / "nope", data)
    assert [i.kind for i in report.errors] == ["no_predictions"]
    assert "BLOCKED" in format_report(report)


# -- the first frame must be the reference's (no silent mixing of sets); the published layout is refused ---


FRAME_SIZE = (128, 72)


def scene_frame(seed: int) -> np.ndarray:
    """(H,W,3) uint8: a blocky random scene; different seeds are unrelated examples."""
    width, height = FRAME_SIZE
    blocks = np.random.default_rng(seed).integers(0, 256, (height // 8, width // 8, 3))
    return np.kron(blocks, np.ones((8, 8, 1))).astype(np.uint8)


def make_bundles(root, seeds: dict, source=None):
    """Reference bundles with a real first frame (frames/00000.png), as renders and imports write them."""
    from PIL import Image

    for example_id, seed in seeds.items():
        (root / example_id / "frames").mkdir(parents=True)
        Image.fromarray(scene_frame(seed)).save(root / example_id / "frames" / "00000.png")
        meta = {"sample_id": example_id, "task": "bounce", "resolution": list(FRAME_SIZE), "fps": 24, "frames": 49}
        if source is not None:
            meta["source"] = source
        (root / example_id / "metadata.json").write_text(json.dumps(meta))
    return root


def still_clip(frame: np.ndarray, n_frames: int = 49) -> np.ndarray:
    return np.repeat(frame[None], n_frames, axis=0)


def test_a_prediction_from_another_sets_first_frame_is_an_error(tmp_path):
    data = make_bundles(tmp_path / "data" / "eval", {"00000": 0, "00001": 1, "00002": 2})
    pred = tmp_path / "predictions" / "model"
    pred.mkdir(parents=True)
    write_video(pred / "00000.mp4", still_clip(scene_frame(0)), fps=24)  # its own first frame: fine
    write_video(pred / "00001.mp4", still_clip(scene_frame(11)), fps=24)  # another set's example 00001
    from PIL import Image

    smaller = np.asarray(Image.fromarray(scene_frame(2)).resize((96, 54), Image.Resampling.LANCZOS))
    write_video(pred / "00002.mp4", still_clip(smaller, 33), fps=16)  # its own frame at another size and rate
    report = validate_predictions(pred, data)
    mismatches = report.of_kind("first_frame_mismatch")
    assert [(i.example_id, i.severity, i.path) for i in mismatches] == [("00001", ERROR, pred / "00001.mp4")]
    assert [i.kind for i in report.errors] == ["first_frame_mismatch"] and not report.ok
    message = mismatches[0].message
    for part in ("00001.mp4", "reference example 00001", str(data), "rendered by rigidbench render",
                 "another set's inputs", "regenerate", "inputs.jsonl"):
        assert part in message, part
    text = format_report(report)
    assert "[first_frame_mismatch]" in text and "BLOCKED" in text and "OK: ready" not in text
    assert validate_predictions(pred, data, first_frames=False).ok  # the opt-out for random test models


def test_the_mismatch_names_an_imported_reference_sets_dataset_and_version(tmp_path):
    source = {"dataset": "rigidbench-eval", "version": "1.1", "md5": "b563f279451e95fe2f32d7e258588636",
              "original_metadata": {"task_type": "bounce"}}
    data = make_bundles(tmp_path / "data-published" / "eval", {"00000": 0, "00001": 1}, source=source)
    pred = tmp_path / "pred"
    pred.mkdir()
    write_video(pred / "00000.mp4", still_clip(scene_frame(0)), fps=24)
    write_video(pred / "00001.mp4", still_clip(scene_frame(0)), fps=24)  # 00000's frame under 00001's id
    report = validate_predictions(pred, data)
    assert report.references["00001"].source == source
    (issue,) = report.errors
    assert issue.kind == "first_frame_mismatch" and issue.example_id == "00001"
    assert "dataset rigidbench-eval version 1.1" in issue.message and str(data) in issue.message
    assert "rendered by rigidbench render" not in issue.message


def published_sample(folder, sample_id):
    """A sample folder as the authors published it: metadata.json with task_type and no sample_id."""
    (folder / sample_id / "frames").mkdir(parents=True)
    (folder / sample_id / "metadata.json").write_text(json.dumps(
        {"task_type": "bounce", "scene_id": "loft", "split": "in-distribution", "seed": 3,
         "render": {"fps": 24, "resolution": [64, 36]}}))


def test_a_reference_folder_in_the_published_layout_is_one_clear_error(tmp_path, capsys):
    from rigidbench.cli import main as cli_main

    root = tmp_path / "rigidbench-eval-v1.1"
    for k in range(3):
        published_sample(root / "samples", f"{k:05d}")
    (root / "manifest.json").write_text(json.dumps([{"sample_id": f"{k:05d}", "task_type": "bounce"}
                                                    for k in range(3)]))
    eval_layout = tmp_path / "published-eval"
    published_sample(eval_layout / "eval", "00000")
    pred = tmp_path / "pred"
    pred.mkdir()
    write_video(pred / "00000.mp4", clip(49), fps=24)
    for folder in (root, root / "samples", eval_layout, eval_layout / "eval", tmp_path):
        report = validate_predictions(pred, folder)
        assert [i.kind for i in report.issues] == ["published_layout"] and not report.ok, folder
        assert "rigidbench import" in report.issues[0].message
        assert main(pred, folder) == 1
        out = capsys.readouterr().out
        assert "BLOCKED" in out and "OK: ready" not in out and "rigidbench import" in out
        assert cli_main(["validate", str(pred), "--data", str(folder)]) == 2  # one line on stderr
        captured = capsys.readouterr()
        assert "rigidbench import" in captured.out + captured.err and "Traceback" not in captured.err
        assert "OK: ready" not in captured.out


def test_a_published_sample_among_ours_is_an_error_for_that_sample(tmp_path):
    data = make_bundles(tmp_path / "eval", {"00000": 0, "00001": 1, "00002": 2})
    published_sample(data, "00003")  # sorts after the three bundles the folder check looks at
    pred = tmp_path / "pred"
    pred.mkdir()
    for k in range(3):
        write_video(pred / f"{k:05d}.mp4", still_clip(scene_frame(k)), fps=24)
    report = validate_predictions(pred, data)
    assert [(i.kind, i.example_id) for i in report.errors] == [("published_layout", "00003")]
    assert "00003" not in report.references and "rigidbench import" in report.errors[0].message


def test_several_samples_per_example_follow_the_naming_rule(tmp_path):
    """``<id>.s<k>.<ext>`` is sample k of ``<id>`` and ``<id>.<ext>`` sample 0: each is checked as one video is;
    ``<id>.mp4`` beside ``<id>.s0.mp4`` is one error naming both; the report counts the samples."""
    data = make_data_dir(tmp_path / "data", ["a", "b", "c", "d"])
    pred = tmp_path / "pred"
    pred.mkdir()
    for name, frames in (("a.mp4", 49), ("a.s1.mp4", 49), ("a.s2.webm", 49), ("b.s0.mp4", 49), ("b.s1.mp4", 24),
                         ("c.mp4", 49), ("c.s0.mp4", 49), ("d.mp4", 49), ("d.s01.mp4", 49), ("e.s1.mp4", 49)):
        write_video(pred / name, clip(frames), fps=24)
    (pred / "a.s1.state.npz").write_bytes(b"state")  # a sample's world state beside its video is not a stranger
    report = validate_predictions(pred, data)
    assert {e: {k: p.name for k, p in found.items()} for e, found in report.samples.items()} == {
        "a": {0: "a.mp4", 1: "a.s1.mp4", 2: "a.s2.webm"}, "b": {0: "b.s0.mp4", 1: "b.s1.mp4"},
        "c": {0: "c.mp4"}, "d": {0: "d.mp4"}}
    assert len(report.files) == 8 and report.missing == []
    (dup,) = report.of_kind("duplicate")
    assert dup.severity == ERROR and dup.example_id == "c" and "c.mp4" in dup.message and "c.s0.mp4" in dup.message
    (short,) = report.of_kind("too_short")  # every sample is checked
    assert short.example_id == "b" and short.path.name == "b.s1.mp4"
    assert {i.path.name for i in report.of_kind("extra")} == {"d.s01.mp4", "e.s1.mp4"}  # no leading zeros; no e
    assert report.samples_per_example() == (1, 3)
    (uneven,) = report.of_kind("uneven_samples")
    assert uneven.severity == WARNING and "2 with 1, 1 with 2, 1 with 3" in uneven.message
    assert "samples per example: 1 to 3 (8 videos read;" in format_report(report) and not report.ok


def test_one_sample_per_example_reports_as_before(tmp_path):
    data = make_data_dir(tmp_path / "data", ["a"])
    pred = tmp_path / "pred"
    pred.mkdir()
    write_video(pred / "a.s0.mp4", clip(49), fps=24)  # sample 0 under its other name
    report = validate_predictions(pred, data)
    assert report.ok and report.samples_per_example() == (1, 1) and report.matched == {"a": pred / "a.s0.mp4"}
    assert "samples per example" not in format_report(report)
