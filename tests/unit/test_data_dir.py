"""One meaning for --data: a split directory, or a data root with --split (default: the only split
present); anything else is exit 2 with a did-you-mean, never an empty success."""

import pytest

from rigidbench.cli import main
from rigidbench.errors import BundleError
from rigidbench.groundtruth.bundle import resolve_split_dir


def fake_bundles(split_dir, ids=("00000", "00001")):
    for sample_id in ids:
        (split_dir / sample_id).mkdir(parents=True)
        (split_dir / sample_id / "metadata.json").write_text("{}")
    return split_dir


def test_a_split_directory_and_a_root_with_one_split_mean_the_same(tmp_path):
    split = fake_bundles(tmp_path / "data" / "eval")
    assert resolve_split_dir(split) == split
    assert resolve_split_dir(tmp_path / "data") == split
    assert resolve_split_dir(tmp_path / "data", "eval") == split


def test_two_splits_need_a_choice(tmp_path):
    fake_bundles(tmp_path / "data" / "eval")
    train = fake_bundles(tmp_path / "data" / "train")
    assert resolve_split_dir(tmp_path / "data", "train") == train
    with pytest.raises(BundleError, match="holds the splits eval and train; choose one with --split"):
        resolve_split_dir(tmp_path / "data")
    with pytest.raises(BundleError, match="did you mean --data .*train"):
        resolve_split_dir(tmp_path / "data" / "eval", "train")


def test_a_parent_directory_names_where_the_bundles_are(tmp_path):
    split = fake_bundles(tmp_path / "out" / "data" / "eval")
    with pytest.raises(BundleError) as err:
        resolve_split_dir(tmp_path / "out")
    assert str(err.value) == (f"no reference bundles in {tmp_path / 'out'}/; it holds data/eval/: "
                              f"did you mean --data {split}?")


def test_an_empty_directory_says_how_to_render(tmp_path):
    (tmp_path / "empty").mkdir()
    with pytest.raises(BundleError, match="rigidbench render --split eval"):
        resolve_split_dir(tmp_path / "empty")
    with pytest.raises(BundleError, match="does not exist"):
        resolve_split_dir(tmp_path / "missing")


@pytest.mark.parametrize("argv", [
    ["inputs"], ["predict", "static"], ["validate", "PREDS"], ["evaluate", "PREDS"], ["validate-metrics"],
    ["show", "00000"]])
def test_every_command_that_reads_bundles_exits_2_on_a_parent_directory(tmp_path, capsys, argv):
    split = fake_bundles(tmp_path / "out" / "data" / "eval")
    (tmp_path / "preds").mkdir()
    argv = [str(tmp_path / "preds") if a == "PREDS" else a for a in argv]
    assert main(argv + ["--data", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err
    assert f"did you mean --data {split}?" in err and len(err.strip().splitlines()) == 1


def test_render_refuses_a_split_directory(tmp_path, capsys):
    pytest.importorskip("bpy", reason="render checks for Blender before it looks at --data")
    fake_bundles(tmp_path / "data" / "eval")
    assert main(["render", "--split", "eval", "--limit", "1", "--data", str(tmp_path / "data" / "eval")]) == 2
    assert f"did you mean --data {tmp_path / 'data'}?" in capsys.readouterr().err


def test_a_plugin_module_registers_before_the_command_runs(tmp_path, monkeypatch, capsys):
    (tmp_path / "my_plugin.py").write_text(
        "from rigidbench.predictors import PREDICTORS, Kind, PredictorInfo\n"
        "PREDICTORS.add(PredictorInfo('my-model', 'my_plugin:f', 'a plug-in model', Kind.PLUGIN))\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    from rigidbench.predictors import PREDICTORS

    try:
        assert main(["--plugin", "my_plugin", "predict", "--list"]) == 0
        assert "my-model" in capsys.readouterr().out
    finally:
        PREDICTORS.remove("my-model")
    assert main(["--plugin", "surely_not_a_module", "predict", "--list"]) == 2
    assert "--plugin surely_not_a_module: no module named" in capsys.readouterr().err
