"""Example filmstrips in the report: frames, outlines, crops, the perception cache, and every way inputs go missing.

Bundles here are tiny (64 x 36, 13 frames at 6 fps) with one active ball moving left to right and a
passive block, written in the layout `rigidbench render` writes; predictions are H.264 files as a
predictor writes them; run directories as `rigidbench evaluate` writes them (run.json records the
predictions and data directories).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from rigidbench.metrics import METRICS
from rigidbench.report import build_report, load_runs
from rigidbench.report.analysis import analyse
from rigidbench.report.examples import (
    FULL,
    OUTLINE_COLORS,
    action_box,
    build_filmstrips,
    choose_examples,
    crop,
    draw_outlines,
    nearest_indices,
    npz_frames,
    outline,
    resolve_dir,
    scan_video,
)
from rigidbench.video import read_video, write_video

W, H, T, FPS = 64, 36, 13, 6.0
TASKS = ("ball_chain", "ramp_collision", "drop_into_cluster", "bounce", "free_fall")


def ball_masks(n_frames: int = T, speed: float = 3.0, start: int = 6) -> np.ndarray:
    """(T, 2, H, W) bool: actor 0 an 8 x 8 ball moving right `speed` px a frame, actor 1 a passive block."""
    masks = np.zeros((n_frames, 2, H, W), bool)
    for t in range(n_frames):
        x = int(start + speed * t)
        masks[t, 0, 14:22, x:x + 8] = True
        masks[t, 1, 28:34, 40:60] = True
    return masks


def paint(masks: np.ndarray) -> np.ndarray:
    """(T, N, H, W) masks -> (T, H, W, 3) uint8 frames: grey room, red ball, brown block."""
    frames = np.full(masks.shape[:1] + (H, W, 3), 120, np.uint8)
    frames[masks[:, 1]] = (120, 80, 40)
    frames[masks[:, 0]] = (220, 30, 30)
    return frames


def write_bundle(data_dir: Path, sample_id: str, task: str, partition: str = "in_distribution") -> Path:
    from PIL import Image

    bundle = data_dir / sample_id
    (bundle / "frames").mkdir(parents=True)
    masks = ball_masks()
    frames = paint(masks)
    for k, frame in enumerate(frames):
        Image.fromarray(frame).save(bundle / "frames" / f"{k:05d}.png")
    write_video(bundle / "video.mp4", frames, fps=FPS)
    np.savez_compressed(bundle / "masks.npz", masks=masks, names=np.array(["ball", "block"]),
                        roles=np.array(["active", "passive"]))
    meta = {"sample_id": sample_id, "task": task, "partition": partition, "frames": T, "fps": FPS,
            "resolution": [W, H]}
    (bundle / "metadata.json").write_text(json.dumps(meta))
    return bundle


def write_run(root: Path, model: str, ids, tasks, ate3d, predictions: str = "", data: str = "",
              official: bool = False) -> Path:
    run_dir = root / model
    (run_dir / "examples").mkdir(parents=True)
    for sample_id, task, value in zip(ids, tasks, ate3d):
        metrics = {m: 0.5 for m in METRICS}
        metrics["ate3d"] = float(value)
        record = {"id": sample_id, "model": model, "task": task, "partition": "in_distribution", "metrics": metrics,
                  "skipped": {}}
        (run_dir / "examples" / f"{sample_id}.json").write_text(json.dumps(record))
    results = {"model": model, "perception": "gt", "official": official, "n_examples": len(ids),
               "n_reference": len(ids), "failed": {}, "skipped_metrics": {},
               "why_not_official": [] if official else [f"the reference directory holds {len(ids)} examples"]}
    (run_dir / "results.json").write_text(json.dumps(results))
    run = {"model": model, "predictions": predictions, "data": data, "perception": {"backend": "gt", "version": "1"}}
    (run_dir / "run.json").write_text(json.dumps(run))
    return run_dir


def write_cache(run_dir: Path, sample_id: str, masks: np.ndarray, fps: float = FPS) -> Path:
    """A perception cache as `rigidbench evaluate` keeps it (cache/<id>-<backend>-<key>.npz)."""
    from rigidbench.perception.base import Perception

    n = masks.shape[0]
    p = Perception(times_s=np.arange(n) / fps, masks=masks, tracks=np.zeros((1, n, 2), np.float32),
                   visibility=np.ones((1, n), bool), confidence=np.ones((1, n), np.float32),
                   track_actor=np.zeros(1, np.int64), disparity=np.zeros((n, H, W), np.float32),
                   bg_times_s=np.arange(n) / fps, bg_tracks=np.zeros((1, n, 2), np.float32),
                   bg_confidence=np.ones((1, n), np.float32))
    path = run_dir / "cache" / f"{sample_id}-gt-0123456789abcdef.npz"
    path.parent.mkdir(parents=True, exist_ok=True)
    p.save(path)
    return path


@pytest.fixture()
def world(tmp_path):
    """Five examples (one per task) with bundles; 'good' copies the reference, 'frozen' repeats its first frame
    (and kept a perception cache saying so), 'lost' has no predictions on this machine."""
    ids = [f"{i:05d}" for i in range(5)]
    data = tmp_path / "data" / "eval"
    for sample_id, task in zip(ids, TASKS):
        write_bundle(data, sample_id, task)
    masks = ball_masks()
    frozen_masks = np.repeat(masks[:1, :1], T, axis=0)
    for sample_id in ids:
        write_video(tmp_path / "predictions" / "good" / f"{sample_id}.mp4", paint(masks), fps=FPS)
        write_video(tmp_path / "predictions" / "frozen" / f"{sample_id}.mp4", paint(np.repeat(masks[:1], T, 0)),
                    fps=FPS)
    runs = tmp_path / "runs"
    # ATE-3D spread is largest on example 00003 (bounce), then 00001.
    good = write_run(runs, "good", ids, TASKS, [0, 0, 0, 0, 0], str(tmp_path / "predictions" / "good"), str(data))
    frozen = write_run(runs, "frozen", ids, TASKS, [0.1, 0.5, 0.2, 0.9, 0.3], str(tmp_path / "predictions" / "frozen"),
                       str(data))
    for sample_id in ids:
        write_cache(frozen, sample_id, frozen_masks)
    lost = write_run(runs, "lost", ids, TASKS, [0.2, 0.2, 0.2, 0.2, 0.2], str(tmp_path / "predictions" / "lost"),
                     str(data))
    return {"root": tmp_path, "ids": ids, "runs": [good, frozen, lost], "data": data}


def analysed(run_dirs):
    return analyse(load_runs(run_dirs), resamples=200, seed=0)


# ------------------------------------------------------------------------------------ pure parts


def test_outline_is_the_mask_boundary():
    mask = np.zeros((10, 10), bool)
    mask[2:7, 3:8] = True
    edge = outline(mask)
    assert edge.sum() == 2 * 5 + 2 * 3  # the 5 x 5 square's rim
    assert not edge[4, 5] and edge[2, 5] and edge[4, 3]
    assert (outline(mask, width=2) & ~mask).any()  # thickened lines reach outside the mask
    tile = np.zeros((10, 10, 3), np.uint8)
    drawn = draw_outlines(tile, mask[None], 1)
    assert (drawn[edge] == OUTLINE_COLORS[0]).all() and (drawn[~edge] == 0).all()
    assert draw_outlines(tile, None, 1) is tile


def test_npz_frames_reads_only_the_frames_asked_for(tmp_path):
    arr = np.arange(7 * 2 * 3 * 4).reshape(7, 2, 3, 4).astype(np.float32)
    np.savez_compressed(tmp_path / "a.npz", masks=arr, other=np.zeros(3))
    got = npz_frames(tmp_path / "a.npz", "masks", [5, 0, 5, 3])
    assert sorted(got) == [0, 3, 5]
    for i, frame in got.items():
        np.testing.assert_array_equal(frame, arr[i])
    assert npz_frames(tmp_path / "a.npz", "masks", [9]) == {}  # past the end: nothing, no error


def test_action_box_frames_the_moving_objects():
    masks = np.zeros((2, 1, 100, 200), bool)
    masks[0, 0, 40:50, 20:30] = True
    masks[1, 0, 40:50, 60:70] = True
    box = action_box(list(masks))
    assert box[2] - box[0] == pytest.approx(box[3] - box[1])  # frame-shaped: same fraction of width and height
    assert box[2] - box[0] >= 0.4
    assert box[0] <= 20 / 200 and box[2] >= 70 / 200 and box[1] <= 40 / 100 and box[3] >= 50 / 100
    assert action_box([np.zeros((1, 10, 10), bool)]) == FULL  # nothing masked
    wide = np.zeros((1, 100, 200), bool)
    wide[0, 10:90, 10:190] = True
    assert action_box([wide]) == FULL  # the action fills the frame
    assert crop(np.zeros((100, 200, 3)), (0.25, 0.5, 0.75, 1.0)).shape == (50, 100, 3)


def test_scan_video_picks_the_nearest_frames_and_marks_the_end(tmp_path):
    frames = np.zeros((6, 16, 16, 3), np.uint8)
    for k in range(6):
        frames[k] = 40 * k  # frame k is grey level 40k
    path = write_video(tmp_path / "p.mp4", frames, fps=4.0, crf=0)
    stills, clip = scan_video(path, np.array([0.0, 0.5, 3.0]), np.arange(8) / 4.0, (8, 8), (16, 16), 0.1)
    assert abs(int(stills[0].mean()) - 0) <= 3 and abs(int(stills[1].mean()) - 80) <= 3
    assert stills[2] is None  # 3 s is past the 1.25 s clip
    assert clip.shape == (8, 16, 16, 3)
    assert abs(int(clip[-1].mean()) - 200) <= 3  # the last frame is held after the clip ends
    assert nearest_indices(np.array([0.0, 0.25]), np.array([0.2, 1.0]), 0.1) == [1, None]


def test_resolve_dir_finds_relative_paths_from_the_run_directory(tmp_path, monkeypatch):
    (tmp_path / "demo" / "predictions" / "a").mkdir(parents=True)
    run_dir = tmp_path / "demo" / "runs" / "a"
    run_dir.mkdir(parents=True)
    monkeypatch.chdir(tmp_path / "demo" / "runs")  # evaluated from tmp_path, reported from elsewhere
    assert resolve_dir("demo/predictions/a", run_dir) == tmp_path / "demo" / "predictions" / "a"
    assert resolve_dir("", run_dir) is None
    assert resolve_dir("nowhere/a", run_dir) is None
    assert resolve_dir(str(tmp_path / "missing"), run_dir) is None


def test_choose_examples_one_per_task_where_models_differ_most(world):
    data = analysed(world["runs"])
    # 'frozen' spreads most from the others on bounce (00003), then ramp collision (00001), free fall (00004).
    picks = choose_examples(data, 3)
    assert [data.table.example_ids[j] for j in picks] == ["00001", "00003", "00004"]  # in task order
    assert choose_examples(data, 0) == []
    assert len(choose_examples(data, 7)) == 5  # never more than there are examples


# ------------------------------------------------------------------------------------ end to end


def _yellow_columns(image: Path, tile: int) -> np.ndarray:
    """Columns of tile `tile` of a five-tile strip that hold outline-yellow pixels (actor 0's outline)."""
    from PIL import Image

    strip = np.asarray(Image.open(image).convert("RGB")).astype(int)
    tile_w = (strip.shape[1] - 4 * 4) // 5
    x = tile * (tile_w + 4)
    yellow = np.abs(strip[:, x:x + tile_w] - np.array(OUTLINE_COLORS[0])).sum(axis=-1) < 90
    return np.flatnonzero(yellow.any(axis=0))


def test_filmstrips_rows_outlines_and_clips(world, tmp_path):
    data = analysed(world["runs"])
    strips = build_filmstrips(data, tmp_path / "out" / "examples", n_examples=2)
    assert strips.note == "" and [ex.sample_id for ex in strips.examples] == ["00001", "00003"]
    ex = strips.examples[0]
    assert ex.times_s == pytest.approx((0.0, 0.25, 0.5, 1.0, 2.0), abs=0.09)  # frames 0, 2, 3, 6, 12 at 6 fps
    assert [row.label for row in ex.rows] == ["Reference", "good", "frozen", "lost"]
    ref, good, frozen, lost = ex.rows
    assert ref.image.is_file() and good.image.is_file() and frozen.image.is_file()
    assert lost.image is None and "predictions directory" in lost.note and "not found" in lost.note
    assert good.note == frozen.note == "" and "ATE-3D" in frozen.scores
    # Every row outlines the reference's ball, which moves right: on the frozen prediction too.
    for row in (ref, frozen):
        assert _yellow_columns(row.image, 4).mean() > _yellow_columns(row.image, 0).mean() + 10
    assert abs(_yellow_columns(frozen.image, 4).mean() - _yellow_columns(ref.image, 4).mean()) < 2
    # Clips: H.264 of the whole frame at the reference frame times, readable by others like the rest.
    clip = read_video(ref.video)
    assert clip.n_frames == T and clip.size == (W, H) and frozen.video.is_file() and lost.video is None
    assert frozen.video.stat().st_mode & 0o044


def test_perceived_outlines_come_from_the_perception_cache(world, tmp_path):
    data = analysed(world["runs"])
    ex = build_filmstrips(data, tmp_path / "ex", n_examples=1, outlines="perceived").examples[0]
    ref, good, frozen, _ = ex.rows
    assert ex.outlines == "perceived" and frozen.note == ""
    assert "no perception cache" in good.note  # 'good' kept none: the reference's masks outline it
    # The frozen run's perception cache has its ball staying where it started.
    assert abs(_yellow_columns(frozen.image, 4).mean() - _yellow_columns(frozen.image, 0).mean()) < 2
    assert _yellow_columns(ref.image, 4).mean() > _yellow_columns(frozen.image, 4).mean() + 10
    with pytest.raises(ValueError, match="outlines"):
        build_filmstrips(data, tmp_path / "x", outlines="both")


def test_report_page_shows_filmstrips_and_notes_missing_rows(world, tmp_path):
    page = build_report(world["runs"], tmp_path / "out", resamples=200, seed=0, examples=2)
    text = page.read_text()
    assert '<section id="examples">' in text and "Example 00003" in text
    assert "examples/00003/00_reference.jpg" in text and "examples/00003/00_reference.mp4" in text
    assert "<video" in text and "autoplay loop muted" in text
    assert text.count("not found") == 2  # the 'lost' row of each example, one line each
    md = (page.parent / "report.md").read_text()
    assert "examples/00003/00_reference.jpg" in md


def test_no_bundles_skip_the_section_with_one_line(world, tmp_path):
    import shutil

    shutil.rmtree(world["data"])
    page = build_report(world["runs"], tmp_path / "out", resamples=200, seed=0)
    text = page.read_text()
    assert text.count("No example filmstrips: the reference bundles are not on this machine") == 1
    assert "<img" in text and "examples/" not in text
    assert not (page.parent / "examples").exists() or not any((page.parent / "examples").iterdir())


def test_examples_zero_and_clips_off(world, tmp_path):
    data = analysed(world["runs"])
    assert build_filmstrips(data, tmp_path / "a", n_examples=0).examples == ()
    strips = build_filmstrips(data, tmp_path / "b", n_examples=1, clips=False)
    assert all(row.video is None for row in strips.examples[0].rows)
    assert list((tmp_path / "b").rglob("*.jpg")) and not list((tmp_path / "b").rglob("*.mp4"))


def test_short_prediction_gets_grey_tiles_and_a_note(world, tmp_path):
    masks = ball_masks()
    short = world["root"] / "predictions" / "short"
    for sample_id in world["ids"]:
        write_video(short / f"{sample_id}.mp4", paint(masks[:5]), fps=FPS)  # 0.67 s of a 2 s clip
    run = write_run(world["root"] / "runs", "short", world["ids"], TASKS, [1, 1, 1, 1, 1], str(short),
                    str(world["data"]))
    data = analysed([world["runs"][0], run])
    row = build_filmstrips(data, tmp_path / "ex", n_examples=1).examples[0].rows[2]
    assert row.label == "short" and "ended before that moment" in row.note
    from PIL import Image

    strip = np.asarray(Image.open(row.image).convert("RGB")).astype(int)
    assert np.abs(strip[:, -5:] - 200).max() <= 6  # the last tile is grey
