"""Bad command-line input gets one line and exit status 2, never a traceback (issue 26, item 5)."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "fixtures"))

import published_set as ps  # noqa: E402

from rigidbench.cli import main  # noqa: E402
from rigidbench.datasets.importer import import_published  # noqa: E402


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    root = tmp_path_factory.mktemp("faults")
    ps.write_set(root / "src", ps.DEFAULT_SAMPLES[:1])
    assert import_published(root / "src", root / "data", progress=False).ok
    return root / "data"


def _one_line_error(capsys, *needles: str) -> str:
    err = capsys.readouterr().err
    assert "Traceback" not in err
    lines = [line for line in err.splitlines() if line.strip()]
    assert lines, "no message"
    assert all(n in err for n in needles), err
    return err


@pytest.mark.parametrize("command", ["predict", "evaluate"])
def test_out_pointing_at_a_file(data, tmp_path, capsys, command):
    target = tmp_path / "not-a-folder"
    target.write_text("x")
    if command == "predict":
        argv = ["predict", "reference", "--data", str(data), "--out", str(target)]
    else:
        (tmp_path / "preds").mkdir()
        argv = ["evaluate", str(tmp_path / "preds"), "--data", str(data), "--out", str(target)]
    assert main(argv) == 2
    _one_line_error(capsys, "is a file, not a folder")
    assert target.read_text() == "x"


@pytest.mark.parametrize("argv, needle", [
    (["render", "--workers", "0"], "--workers"),
    (["render", "--limit", "-1"], "--limit"),
    (["predict", "reference", "--limit", "-1"], "--limit"),
    (["evaluate", "p", "--limit", "0"], "--limit"),
])
def test_counts_below_one_are_refused(argv, needle, capsys):
    with pytest.raises(SystemExit) as caught:
        main(argv)
    assert caught.value.code == 2
    _one_line_error(capsys, needle, ">= 1")


def test_render_into_a_file(tmp_path, capsys):
    target = tmp_path / "data"
    target.write_text("x")
    assert main(["render", "--split", "eval", "--ids", "00000", "--quality", "test", "--data", str(target)]) == 2
    _one_line_error(capsys, "is a file, not a folder")


def test_a_configuration_file_that_is_not_utf8(tmp_path, capsys):
    config = tmp_path / "config" / "objects"
    config.mkdir(parents=True)
    (config / "odd.yaml").write_bytes("id: odd\nname: caf\xe9\n".encode("latin-1"))
    assert main(["--config", str(tmp_path / "config"), "manifest", "--split", "eval",
                 "--out", str(tmp_path / "m.jsonl")]) == 2
    _one_line_error(capsys, "odd.yaml", "not UTF-8")


@pytest.mark.parametrize("damage", [b'{"id": "00000", "input_k', b"[1, 2]", b"\xff\xfe"])
def test_a_damaged_score_record_is_scored_again(data, tmp_path, damage):
    from rigidbench.evaluation import evaluate
    from rigidbench.perception.features import FeatureNets

    preds = tmp_path / "preds"
    assert main(["predict", "reference", "--data", str(data), "--out", str(preds)]) == 0
    first = evaluate(preds, data, tmp_path / "run", nets=FeatureNets(), progress=False)
    assert first.evaluated == ["00000"]
    (tmp_path / "run" / "examples" / "00000.json").write_bytes(damage)
    second = evaluate(preds, data, tmp_path / "run", nets=FeatureNets(), progress=False)
    assert second.evaluated == ["00000"] and not second.failed
    assert second.results["overall"]["iou"]["mean"] == first.results["overall"]["iou"]["mean"]


def test_a_score_made_without_the_first_frame_check_is_not_reused_with_it(data, tmp_path):
    """The first-frame check is a rule, not an input: a record scored with it off is refused (not reused) by a
    later run with it on, and scored again when it is off."""
    from rigidbench.evaluation import evaluate
    from rigidbench.perception.features import FeatureNets

    other = tmp_path / "other"  # the same id in another set: a different scene and camera
    ps.write_set(other / "src", [ps.PublishedSample("00000", "free_fall", "modern_loft", "in_distribution", 991,
                                                    "apple")])
    assert import_published(other / "src", other / "data", progress=False).ok
    preds = tmp_path / "preds"
    assert main(["predict", "reference", "--data", str(other / "data"), "--out", str(preds)]) == 0
    loose = evaluate(preds, data, tmp_path / "run", nets=FeatureNets(), progress=False, first_frame_check=False)
    assert loose.evaluated == ["00000"] and not loose.failed
    strict = evaluate(preds, data, tmp_path / "run", nets=FeatureNets(), progress=False)
    assert not strict.reused and "first frame does not match" in strict.failed["00000"]
    again = evaluate(preds, data, tmp_path / "run", nets=FeatureNets(), progress=False, first_frame_check=False)
    assert again.evaluated == ["00000"] and not again.reused and not again.failed
