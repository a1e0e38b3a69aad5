"""Scoring several samples of one example shares its reference side (``evaluation.reference_side``), and changes
no score: two samples scored against one shared ``ReferenceSide`` give records, per-frame arrays and readouts
files identical, bit for bit, to the same two scored each against a fresh one; the reference's frames are
decoded once instead of twice; the evaluate worker keeps a side only for the same bundle content.

The reference set is the synthetic published set (tests/fixtures/published_set.py) imported without Blender;
sample 0 is the ``reference`` predictor's clip, sample 1 the same clip brightened after frame 0, with its world
state's masks moved one pixel right and its tracks half a pixel, so that every measurement is exercised away
from its perfect value."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from fixtures import published_set as ps

from rigidbench.config import registry
from rigidbench.driver import RunOptions
from rigidbench.evaluation.protocol import get_protocol
from rigidbench.evaluation.reference_side import ReferenceSide
from rigidbench.folders import RunFolder, sample_item, state_path
from rigidbench.groundtruth import bundle
from rigidbench.perception.features import FeatureNets
from rigidbench.perception.gt import GroundTruthBackend, WorldState
from rigidbench.predictors import PredictContext
from rigidbench.stages import evaluate as runner
from rigidbench.stages.import_set import import_published
from rigidbench.stages.predict import predict
from rigidbench.video import read_video, write_video

pytest.importorskip("av")

EXAMPLE = "00001"  # a bounce: the readouts' restitution and gravity fits have something to fit


@pytest.fixture(scope="module")
def two_samples(tmp_path_factory):
    """(reference split, sample 0's video, sample 1's video)."""
    root = tmp_path_factory.mktemp("reference-side")
    published = ps.write_set(root / "published" / "rigidbench-eval-v1.1", ps.DEFAULT_SAMPLES[:2])
    import_published(published.parent, root / "data", registry=registry(), run=RunOptions(progress=False))
    preds = root / "predictions"
    made = predict("reference", root / "data" / "eval", preds, PredictContext(), run=RunOptions(progress=False))
    assert not made.failed
    first = preds / f"{EXAMPLE}.mp4"
    clip, state = read_video(first), WorldState.load(state_path(first))
    frames = clip.frames.copy()
    frames[1:] = np.minimum(frames[1:].astype(np.int16) + 6, 255).astype(np.uint8)
    second = preds / f"{sample_item(EXAMPLE, 1)}.mp4"
    write_video(second, frames, fps=24.0, lossless=True)
    masks, tracks = state.masks.copy(), state.tracks.copy()
    masks[1:] = np.roll(masks[1:], 1, axis=-1)
    tracks[:, 1:] += np.float32(0.5)
    WorldState(state.times_s, masks, state.depth_m, tracks, state.visibility, state.bg_affine,
               state.bg_flow).save(state_path(second))
    return root / "data" / "eval", first, second


def score(reference_dir: Path, videos: list[Path], out: Path, shared: bool) -> list[ReferenceSide]:
    """Score each video as sample k of the example into ``out``; one ReferenceSide for all (told how many
    samples follow) or a fresh one per sample. Returns the sides used."""
    sides = []
    shared_side = ReferenceSide.read(reference_dir, "hash", samples=len(videos)) if shared else None
    for k, video in enumerate(videos):
        side = shared_side or ReferenceSide.read(reference_dir)
        runner._score_one(side.sample, video, GroundTruthBackend(), FeatureNets(), "model", f"key{k}", out,
                          out / "cache", dict.fromkeys(("decode_s", "perception_s", "metrics_s"), 0.0),
                          get_protocol(None), index=k, reference=side)
        sides.append(side)
    return sides


def outputs(out: Path, k: int) -> tuple[dict, dict, dict]:
    folder, item = RunFolder(out), sample_item(EXAMPLE, k)
    with np.load(folder.arrays(item)) as arrays:
        per_frame = {name: arrays[name] for name in arrays.files}
    return (json.loads(folder.record(item).read_text()), per_frame,
            json.loads(folder.readouts(item).read_text()))


def test_a_shared_reference_side_gives_the_same_records_bit_for_bit(two_samples, tmp_path, monkeypatch):
    split, first, second = two_samples
    decoded = []
    real_read_rgb = bundle._read_rgb

    def counting(path):
        decoded.append(Path(path).name)
        return real_read_rgb(path)

    monkeypatch.setattr(bundle, "_read_rgb", counting)
    alone = score(split / EXAMPLE, [first, second], tmp_path / "alone", shared=False)
    decoded_alone, decoded[:] = len(decoded), []
    together = score(split / EXAMPLE, [first, second], tmp_path / "together", shared=True)
    frames = alone[0].sample.n_frames
    assert together[0] is together[1] and alone[0] is not alone[1]
    assert decoded_alone >= 2 * frames and len(decoded) <= frames + 1  # the reference's frames read once
    assert any(key.startswith("reference:ssim_maps") for key in together[0].cache)  # SSIM's reference kept
    records = []
    for k in (0, 1):
        (record_a, arrays_a, readouts_a), (record_b, arrays_b, readouts_b) = (outputs(tmp_path / "alone", k),
                                                                              outputs(tmp_path / "together", k))
        assert record_a == record_b and readouts_a == readouts_b
        assert arrays_a.keys() == arrays_b.keys() and arrays_a
        for name, values in arrays_a.items():
            assert values.tobytes() == arrays_b[name].tobytes(), name  # bit for bit, NaN included
        records.append(record_a)
    # the second sample really differs from the first (the shared side did not hand it the first's results)
    assert records[0]["metrics"]["iou"] == 1.0 and records[1]["metrics"]["iou"] < 1.0
    assert records[1]["metrics"]["ssim"] < records[0]["metrics"]["ssim"]
    assert records[1]["sample"] == 1 and records[1]["id"] == EXAMPLE


def test_the_shared_arrays_are_read_only(two_samples, tmp_path):
    split, first, _ = two_samples
    (side,) = score(split / EXAMPLE, [first], tmp_path / "run", shared=True)
    n = side.sample.n_frames
    for array in (side.sample.frames, side.sample.depth, side.sample.masks, side.active_masks(n),
                  side.tracked_points(n)):
        assert not array.flags.writeable
    with pytest.raises(ValueError):
        side.sample.frames[0, 0, 0, 0] = 1
    # the frames, decoded on several threads, are those read one by one
    assert np.array_equal(side.sample.frames, np.stack([side.sample.frame(k) for k in range(n)]))


def test_the_worker_keeps_a_side_only_for_the_same_bundle_content(two_samples, tmp_path):
    split, first, _ = two_samples
    job = {"pred_dir": str(first.parent), "data_dir": str(split), "out_dir": str(tmp_path / "run"), "model": "m",
           "perception": "gt"}
    worker = runner.EvaluateWorker(job, backend=GroundTruthBackend(), nets=FeatureNets())
    side = worker.reference_side(EXAMPLE, "h1")
    assert side.samples == 2  # <id>.mp4 and <id>.s1.mp4 in the predictions folder
    assert worker.reference_side(EXAMPLE, "h1") is side
    assert worker.reference_side(EXAMPLE, "h2") is not side  # the bundle changed: read again
    other = worker.reference_side("00000", "h1")
    assert other.sample.path == split / "00000" and other.samples == 1
    assert not ReferenceSide.read(split / EXAMPLE).serves(split / EXAMPLE, None)  # no hash: never reused
