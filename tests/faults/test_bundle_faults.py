"""Fault injection into reference bundles and prediction files (issue 26, items 1-4 and the
render_seconds part of item 10).

Bundles come from the synthetic published set (tests/fixtures/published_set.py) imported with
``import_published``: three valid examples (13 frames of 96x64 at 24 fps) in milliseconds, no Blender.
Each damaged file sits in the MIDDLE example (00001), so the test sees that the examples after it are
still processed and that results are still written.
"""

from __future__ import annotations

import json
import os
import shutil
from pathlib import Path

import numpy as np
import pytest


from fixtures import published_runs  # noqa: E402

from rigidbench.driver import RunOptions, Selection  # noqa: E402
from rigidbench.cli import main  # noqa: E402
from rigidbench.config import registry  # noqa: E402
from rigidbench.errors import BundleError  # noqa: E402
from rigidbench.groundtruth.bundle import Sample, check_bundle  # noqa: E402
from rigidbench.preflight import validate_predictions  # noqa: E402
from rigidbench.stages.evaluate import evaluate  # noqa: E402
from rigidbench.video import read_video, write_video  # noqa: E402

pytest.importorskip("av")

IDS = ("00000", "00001", "00002")
DAMAGED = "00001"  # the middle of the selection
NPZ_FILES = ("masks.npz", "depth.npz", "tracks.npz", "trajectories.npz")


@pytest.fixture(scope="module")
def reference_set(tmp_path_factory):
    """(data root with eval/00000..00002 imported, predictions/reference made by `rigidbench predict`)."""
    return published_runs.imported_with_reference(tmp_path_factory.mktemp("faults"))


@pytest.fixture()
def copies(reference_set, tmp_path):
    """A private copy of the data root and of the predictions, to damage."""
    data, preds = reference_set
    shutil.copytree(data, tmp_path / "data")
    shutil.copytree(preds, tmp_path / "preds")
    return tmp_path / "data", tmp_path / "preds"


def damage(path: Path) -> None:
    """Cut the file to half its length (a killed copy, a full disk)."""
    raw = path.read_bytes()
    path.write_bytes(raw[: len(raw) // 2])


def results_of(run: Path) -> dict:
    return json.loads((run / "results.json").read_text())


# -- item 1: one damaged reference bundle file -----------------------------------------------------


@pytest.mark.parametrize("name", NPZ_FILES + ("metadata.json",))
def test_a_damaged_bundle_file_fails_only_its_example(copies, tmp_path, capsys, name):
    data, preds = copies
    bundle = data / "eval" / DAMAGED
    damage(bundle / name)

    # the reader: a BundleError naming the file and what to do (imported bundle: import again)
    with pytest.raises(BundleError, match=name.replace(".", r"\.")) as caught:
        sample = Sample(bundle)
        {"masks.npz": lambda: sample.masks, "depth.npz": lambda: sample.depth, "tracks.npz": lambda: sample.tracks,
         "trajectories.npz": lambda: sample.trajectory}[name]()
    assert "rigidbench import" in str(caught.value) and DAMAGED in str(caught.value)
    assert any(name in p for p in check_bundle(bundle)) and any(name in p for p in check_bundle(bundle, deep=False))

    # evaluate: the others are scored, the damaged one fails naming its file, results.json is written
    run = tmp_path / "run"
    assert main(["evaluate", str(preds), "--data", str(data), "--out", str(run)]) == 1
    results = results_of(run)
    assert set(results["failed"]) == {DAMAGED} and name in results["failed"][DAMAGED]
    assert "rigidbench import" in results["failed"][DAMAGED]
    assert results["n_examples"] == 2 and sorted(results["coverage"]["per_example"]) == ["00000", "00002"]
    assert results["overall"]["iou"]["mean"] == 1.0
    assert {p.name for p in (run / "examples").glob("?????.json")} == {"00000.json", "00002.json"}

    # predict: the others are written, the damaged one is reported with its file (the reference predictor
    # reads every file but trajectories.npz, which it does not need: that example is predicted)
    capsys.readouterr()
    out = tmp_path / "predicted"
    reads = name != "trajectories.npz"
    assert main(["predict", "reference", "--data", str(data), "--out", str(out)]) == (1 if reads else 0)
    assert (out / "00000.mp4").is_file() and (out / "00002.mp4").is_file()
    assert (out / "00001.mp4").exists() is not reads
    assert (name in capsys.readouterr().err) is reads

    # show: a sheet for each of the others, the damaged one named on stderr (the sheet, too, does without
    # trajectories.npz)
    sheets = tmp_path / "sheets"
    assert main(["show", *IDS, "--data", str(data), "--out", str(sheets)]) == (1 if reads else 0)
    written = sorted(p.name for p in sheets.iterdir())
    assert written == [f"eval_{i}_contact_sheet.png" for i in IDS if i != DAMAGED or not reads]
    err = capsys.readouterr().err
    assert (f"FAILED {DAMAGED}" in err and name in err) is reads

    # validate: the damaged reference is an error of that example, naming the file
    report = validate_predictions(preds, data / "eval")
    errors = [i for i in report.errors if i.example_id == DAMAGED]
    assert errors and all(i.example_id == DAMAGED for i in report.errors) and name in errors[0].message


def test_a_rendered_bundle_is_to_be_rendered_again(copies):
    """The message of a rendered bundle (no `source`) says to re-render that id."""
    data, _ = copies
    bundle = data / "eval" / DAMAGED
    meta = json.loads((bundle / "metadata.json").read_text())
    meta.pop("source")
    (bundle / "metadata.json").write_text(json.dumps(meta))
    damage(bundle / "depth.npz")
    with pytest.raises(BundleError, match=rf"rigidbench render --ids {DAMAGED}"):
        Sample(bundle).depth


def _as_our_renders(data: Path, dst: Path, monkeypatch) -> Path:
    """Copies of the imported bundles that look like our own renders at the `test` preset (no `source`). They
    have no scene spec, so render's completeness check is told to ignore that one file (check_bundle's own
    rules are tested elsewhere); every other problem still counts."""
    import json
    import shutil

    from rigidbench.stages import render

    shutil.copytree(data, dst)
    for meta_path in (dst / "eval").glob("*/metadata.json"):
        meta = json.loads(meta_path.read_text())
        meta.pop("source")
        meta["preset"] = "test"
        meta_path.write_text(json.dumps(meta))
    from PIL import Image

    for png in (dst / "eval").glob("*/frames/*.png"):  # our renders are RGB PNGs; the published ones RGBA
        with Image.open(png) as im:
            rgb = im.convert("RGB")
        png.unlink()
        rgb.save(png)
    real = render.B.check_bundle
    monkeypatch.setattr(render.B, "check_bundle", lambda path, **kw: [p for p in real(path, **kw)
                                                                     if not p.startswith("scene_spec.json")])
    return dst


def test_render_redoes_a_bundle_rendered_at_another_preset_and_never_overwrites_an_imported_one(copies, tmp_path,
                                                                                                   monkeypatch):
    """Rendering with another --quality into the same data folder used to keep the old bundles silently."""
    from rigidbench import manifest
    from rigidbench.errors import UserError
    from rigidbench.stages.render import rows_to_render

    data, _ = copies
    rows = manifest.select(manifest.rows("eval", registry()), list(IDS), None)
    with pytest.raises(UserError, match="imported from the published set"):
        rows_to_render(rows, data, "preview")
    with pytest.raises(UserError, match="imported from the published set"):
        rows_to_render(rows, data, "test")  # not even at the preset they name
    ours = _as_our_renders(data, tmp_path / "ours", monkeypatch)
    assert rows_to_render(rows, ours, "test") == []  # complete, made at `test` before ledgers: taken over
    assert [r.sample_id for r in rows_to_render(rows[:1], ours, "preview")] == [rows[0].sample_id]
    # a dry run: the bundle stays until its new render replaces it whole, and no ledger is written
    assert (ours / "eval" / rows[0].sample_id).is_dir() and not (ours / "eval" / ".stages" / "render").exists()


def test_render_renders_a_damaged_bundle_again_and_skips_intact_ones(copies, tmp_path, monkeypatch):
    from rigidbench import manifest
    from rigidbench.stages.render import is_complete, rows_to_render

    data = _as_our_renders(copies[0], tmp_path / "ours", monkeypatch)
    rows = manifest.select(manifest.rows("eval", registry()), list(IDS), None)
    assert [r.sample_id for r in rows] == list(IDS)
    assert rows_to_render(rows, data, "test") == []  # every bundle intact: nothing to render
    damage(data / "eval" / DAMAGED / "tracks.npz")
    (data / "eval" / f".{IDS[2]}.tmp").mkdir()  # a killed render's leftover of another row: not rerun, kept
    assert not is_complete(data, rows[1]) and is_complete(data, rows[0])
    todo = rows_to_render(rows, data, "test")
    assert [r.sample_id for r in todo] == [DAMAGED]
    assert (data / "eval" / DAMAGED).is_dir()  # kept until the new render replaces it whole
    assert (data / "eval" / "00000").is_dir() and (data / "eval" / f".{IDS[2]}.tmp").is_dir()


# -- item 2: a truncated clip ------------------------------------------------------------------------


def test_a_one_frame_clip_is_refused_and_scored_marked_with_allow_short(copies, tmp_path):
    data, preds = copies
    clip = read_video(preds / f"{DAMAGED}.mp4")
    write_video(preds / f"{DAMAGED}.mp4", clip.frames[:1], fps=24, lossless=True)

    run = tmp_path / "run"
    summary = evaluate(preds, data, run, run=RunOptions(progress=False))
    results = results_of(run)
    assert sorted(summary.ran) == ["00000", "00002"] and set(summary.failed) == {DAMAGED}
    message = results["failed"][DAMAGED]
    assert f"{DAMAGED}.mp4" in message and "0.000 s" in message and "0 to 0.500 s" in message
    assert "--allow-short" in message
    assert results["protocol"]["allow_short"] is False and results["coverage"]["short"] == []

    summary = evaluate(preds, data, run, allow_short=True, run=RunOptions(progress=False))
    results = results_of(run)
    # --allow-short is one of the rules in every example's key: all are scored again under it
    assert not summary.failed and summary.ran == list(IDS) and not summary.reused
    assert summary.redone == {i: "its inputs or settings changed" for i in IDS}
    record = json.loads((run / "examples" / f"{DAMAGED}.json").read_text())
    assert record["coverage"]["short"] is True and record["coverage"]["fraction"] == 0.0
    assert record["coverage"]["frames"] == 1 and record["frames_compared"] == 1
    assert results["coverage"]["short"] == [DAMAGED] and results["coverage"]["min_fraction"] == 0.0
    assert results["coverage"]["per_example"]["00000"]["fraction"] == 1.0
    assert results["protocol"]["allow_short"] is True and not results["official"]
    assert any("--allow-short" in reason for reason in results["why_not_official"])

    # an official run again: the cached score of the short clip is not reused
    summary = evaluate(preds, data, run, run=RunOptions(progress=False))
    assert set(summary.failed) == {DAMAGED} and DAMAGED not in results_of(run)["coverage"]["per_example"]


def test_the_report_shows_coverage(copies, tmp_path):
    from rigidbench.report import build_report

    data, preds = copies
    clip = read_video(preds / f"{DAMAGED}.mp4")
    write_video(preds / f"{DAMAGED}.mp4", clip.frames[:7], fps=24, lossless=True)  # 0.25 s of the 0.5 s span
    evaluate(preds, data, tmp_path / "run", allow_short=True, run=RunOptions(progress=False))
    per = results_of(tmp_path / "run")["coverage"]["per_example"]
    assert per[DAMAGED]["fraction"] == 0.5 and per[DAMAGED]["seconds"] == 0.25
    page = build_report([tmp_path / "run"], tmp_path / "report", resamples=100, examples=0, clips=False)
    html = page.read_text()
    assert "Coverage of the span" in html and f"83% (1 short: {DAMAGED})" in html  # (1 + 0.5 + 1) / 3
    assert "shorter than the reference span were scored" in html


# -- item 3: files that are not regular ------------------------------------------------------------------


@pytest.mark.timeout(30)
def test_a_fifo_and_a_link_to_dev_zero_fail_fast(copies, tmp_path):
    data, preds = copies
    (preds / f"{DAMAGED}.mp4").unlink()
    os.mkfifo(preds / f"{DAMAGED}.mp4")
    (preds / "00002.mp4").unlink()
    (preds / "00002.mp4").symlink_to("/dev/zero")
    summary = evaluate(preds, data, tmp_path / "run", run=RunOptions(progress=False))
    assert summary.ran == ["00000"]
    assert "FIFO" in summary.failed[DAMAGED] and f"{DAMAGED}.mp4" in summary.failed[DAMAGED]
    assert "character device" in summary.failed["00002"] and "/dev/zero" in summary.failed["00002"]
    assert results_of(tmp_path / "run")["failed"] == summary.failed
    report = validate_predictions(preds, data / "eval", first_frames=False)
    assert {i.example_id for i in report.errors} == {DAMAGED, "00002"}


def test_a_link_to_a_regular_file_is_read(copies, tmp_path):
    data, preds = copies
    target = tmp_path / "elsewhere.mp4"
    shutil.move(preds / "00000.mp4", target)
    (preds / "00000.mp4").symlink_to(target)
    summary = evaluate(preds, data, tmp_path / "run", run=RunOptions(Selection.of(["00000"]), progress=False))
    assert summary.ran == ["00000"] and not summary.failed


def test_the_size_cap_is_checked_before_reading(tmp_path, monkeypatch):
    from rigidbench.errors import VideoError
    from rigidbench.video import check_video_file

    big = tmp_path / "big.mp4"
    with open(big, "wb") as fh:  # sparse: 3 GB that occupy no disk and that nobody should read
        fh.truncate(3 * 1024 ** 3)
    with pytest.raises(VideoError, match="over the 2.15 GB limit"):
        check_video_file(big)


# -- item 4: one coverage rule for validate and evaluate ---------------------------------------------------


def test_a_vfr_clip_a_fraction_of_a_millisecond_short_is_compared_whole(copies, tmp_path):
    data, preds = copies
    clip = read_video(preds / "00000.mp4")
    assert clip.n_frames == 13
    times = np.arange(13) / 24.0
    times[-1] -= 0.0003  # the last timestamp 0.3 ms early
    write_video(preds / "00000.mp4", clip.frames, times_s=times, lossless=True)
    assert read_video(preds / "00000.mp4").times_s[-1] == pytest.approx(0.5 - 0.0003, abs=2e-5)

    report = validate_predictions(preds, data / "eval")
    assert report.ok, [i.message for i in report.errors]
    summary = evaluate(preds, data, tmp_path / "run", run=RunOptions(Selection.of(["00000"]), progress=False))
    assert summary.ran == ["00000"]
    record = json.loads((tmp_path / "run" / "examples" / "00000.json").read_text())
    assert record["frames_compared"] == 13 and record["coverage"]["frames"] == 13
    assert record["coverage"]["short"] is False and record["coverage"]["fraction"] == 1.0


# -- item 10: a re-render that changes only its timings keeps the cached scores ------------------------------


def test_render_timings_do_not_invalidate_cached_scores(copies, tmp_path):
    data, preds = copies
    run = tmp_path / "run"
    assert sorted(evaluate(preds, data, run, run=RunOptions(progress=False)).ran) == list(IDS)
    for sample_id, seconds in (("00000", 12.5), ("00002", 99.0)):
        meta_path = data / "eval" / sample_id / "metadata.json"
        meta = json.loads(meta_path.read_text())
        meta["render_seconds"] = {"total": seconds}
        meta["software"] = {"blender": "4.5.9"}
        meta_path.write_text(json.dumps(meta))
    meta_path = data / "eval" / DAMAGED / "metadata.json"
    meta = json.loads(meta_path.read_text())
    meta["partition"] = "ood_objects"  # this one moves the results: scored again
    meta_path.write_text(json.dumps(meta))
    summary = evaluate(preds, data, run, run=RunOptions(progress=False))
    assert sorted(summary.reused) == ["00000", "00002"] and summary.ran == [DAMAGED]


# -- item 10: scratch files of re-rendering predictors live in the output folder ------------------------------


def test_rerendering_scratch_lives_in_the_output_folder_and_a_killed_runs_is_removed(tmp_path, monkeypatch):
    import socket

    from rigidbench.predictors import counterfactuals as cf
    from rigidbench.predictors.base import SCRATCH_DIR, FailureMode, PredictContext

    monkeypatch.setattr(cf, "import_bpy_into", lambda folder: None)  # (bpy's own folder: checked by hand)
    out = tmp_path / "predictions"
    dead = out / SCRATCH_DIR / f"{socket.gethostname()}-{2 ** 22 + 17}"  # above Linux's default pid_max
    (dead / "rigidbench-00001-abc" / "00001").mkdir(parents=True)
    (dead / "blender_xyz").mkdir()
    foreign = out / SCRATCH_DIR / "another-host-12"  # another machine's, on a shared disk: left alone
    foreign.mkdir()
    seen = {}

    def predictor(sample, severity, scratch_dir=None):
        with cf.scratch_bundle_dir("00001", scratch_dir) as folder:
            seen["folder"] = folder
            assert folder.is_dir()
        return None

    FailureMode(None, predictor).predict(None, PredictContext(severity=0.5, out_dir=out))
    mine = out / SCRATCH_DIR / f"{socket.gethostname()}-{os.getpid()}"
    assert seen["folder"].parent == mine and not seen["folder"].exists()
    assert not dead.exists() and foreign.is_dir()
