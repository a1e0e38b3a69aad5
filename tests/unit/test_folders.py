"""The typed homes of the three folders a user handles (rigidbench.folders): names on disk and the one
rule for finding an example's prediction."""

import os
from pathlib import Path

import pytest

from rigidbench.errors import EvaluationError, VideoError
from rigidbench.folders import (BundleFolder, PredictionsFolder, RunFolder, SplitFolder, find_prediction,
                                state_path)


def test_the_file_names_are_the_ones_on_disk():
    pred = PredictionsFolder("p")
    assert pred.generation == Path("p/generation.json")
    assert pred.hosted_state("00001") == Path("p/.hosted/00001.json")
    assert pred.scratch_dir == Path("p/.scratch")
    assert pred.state("00001") == Path("p/00001.state.npz") == state_path("p/00001.webm")
    run = RunFolder("r")
    assert (run.results, run.run, run.cache_dir) == (Path("r/results.json"), Path("r/run.json"), Path("r/cache"))
    assert [run.record("7"), run.arrays("7"), run.readouts("7")] == [
        Path("r/examples/7.json"), Path("r/examples/7.npz"), Path("r/examples/7.readouts.json")]
    bundle = SplitFolder("data/eval").bundle("00003")
    assert bundle == BundleFolder(Path("data/eval/00003"))
    assert (bundle.metadata, bundle.prompt, bundle.frame(0)) == (
        Path("data/eval/00003/metadata.json"), Path("data/eval/00003/prompt.txt"),
        Path("data/eval/00003/frames/00000.png"))


def test_run_records_leave_out_the_other_per_example_files(tmp_path):
    run = RunFolder(tmp_path)
    run.examples_dir.mkdir()
    for name in ("b.json", "a.json", "a.readouts.json", "a.npz"):
        (run.examples_dir / name).write_text("{}")
    assert [p.name for p in run.records()] == ["a.json", "b.json"]


def test_find_prediction_one_video_per_example(tmp_path):
    assert find_prediction(tmp_path, "00000") is None
    (tmp_path / "00000.webm").write_bytes(b"x")
    assert find_prediction(tmp_path, "00000") == tmp_path / "00000.webm"
    (tmp_path / "00000.mp4").write_bytes(b"x")
    with pytest.raises(EvaluationError, match="several predictions"):
        find_prediction(tmp_path, "00000")
    (tmp_path / "00001.mp4").write_bytes(b"")
    with pytest.raises(VideoError, match="empty"):
        find_prediction(tmp_path, "00001")
    os.symlink(tmp_path / "missing.mp4", tmp_path / "00002.mp4")
    with pytest.raises(VideoError, match="broken symbolic link"):
        find_prediction(tmp_path, "00002")


def test_import_rigidbench_does_not_import_numpy():
    import subprocess
    import sys

    out = subprocess.run([sys.executable, "-c", "import sys, rigidbench; print('numpy' in sys.modules)"],
                         capture_output=True, text=True, check=True).stdout
    assert out.strip() == "False"
