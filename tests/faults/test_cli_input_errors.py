"""Bad command-line input gets one line and exit status 2, never a traceback (issue 26, item 5)."""

from __future__ import annotations

import shlex
import sys
from pathlib import Path

import pytest


from fixtures import published_set as ps  # noqa: E402

from rigidbench.driver import RunOptions  # noqa: E402
from rigidbench.cli import main  # noqa: E402
from rigidbench.stages.import_set import import_published  # noqa: E402


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    root = tmp_path_factory.mktemp("faults")
    ps.write_set(root / "src", ps.DEFAULT_SAMPLES[:1])
    assert import_published(root / "src", root / "data", run=RunOptions(progress=False)).exit_status() == 0
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
    from rigidbench.stages.evaluate import evaluate
    from rigidbench.perception.features import FeatureNets

    preds = tmp_path / "preds"
    assert main(["predict", "reference", "--data", str(data), "--out", str(preds)]) == 0
    first = evaluate(preds, data, tmp_path / "run", nets=FeatureNets(), run=RunOptions(progress=False))
    assert first.ran == ["00000"]
    (tmp_path / "run" / "examples" / "00000.json").write_bytes(damage)
    second = evaluate(preds, data, tmp_path / "run", nets=FeatureNets(), run=RunOptions(progress=False))
    assert second.ran == ["00000"] and not second.failed
    assert second.facts.results["overall"]["iou"]["mean"] == first.facts.results["overall"]["iou"]["mean"]


def test_a_score_made_without_the_first_frame_check_is_not_reused_with_it(data, tmp_path):
    """The first-frame check is a rule, not an input: a record scored with it off is refused (not reused) by a
    later run with it on, and scored again when it is off."""
    from rigidbench.stages.evaluate import evaluate
    from rigidbench.perception.features import FeatureNets

    other = tmp_path / "other"  # the same id in another set: a different scene and camera
    ps.write_set(other / "src", [ps.PublishedSample("00000", "free_fall", "modern_loft", "in_distribution", 991,
                                                    "apple")])
    assert import_published(other / "src", other / "data", run=RunOptions(progress=False)).exit_status() == 0
    preds = tmp_path / "preds"
    assert main(["predict", "reference", "--data", str(other / "data"), "--out", str(preds)]) == 0
    loose = evaluate(preds, data, tmp_path / "run", nets=FeatureNets(), first_frame_check=False, run=RunOptions(progress=False))
    assert loose.ran == ["00000"] and not loose.failed
    strict = evaluate(preds, data, tmp_path / "run", nets=FeatureNets(), run=RunOptions(progress=False))
    assert not strict.reused and "first frame does not match" in strict.failed["00000"]
    again = evaluate(preds, data, tmp_path / "run", nets=FeatureNets(), first_frame_check=False, run=RunOptions(progress=False))
    assert again.ran == ["00000"] and not again.reused and not again.failed


# -- every command, each kind of bad argument (issue 33) --------------------------------------------------
#
# Each row: the kind of mistake, the command line ({data}: an imported split root; {file}: a plain file; {dir}:
# an empty folder; {missing}: nothing there; {ro}: a folder nothing can be written into; {new}: a fresh path
# to write) and the argument the one error line must name. Every command is refused with exit status 2,
# one line, no traceback, before it does any work.

BAD_ARGUMENTS = [
    # a file where a folder is expected
    ("file for folder", "download --data {file}", "--data"),
    ("file for folder", "import {dir} --data {file}", "--data"),
    ("file for folder", "simulate --split eval --ids 00000 --out {file}", "--out"),
    ("file for folder", "render --split eval --ids 00000 --quality test --data {file}", "--data"),
    ("file for folder", "show 00000 00001 --data {data} --out {file}", "--out"),
    ("file for folder", "predict reference --data {data} --out {file}", "--out"),
    ("file for folder", "predict reference --data {file} --out {new}", "--data"),
    ("file for folder", "audit --models reference --data {data} --out {file}", "--out"),
    ("file for folder", "validate {file} --data {data}", "predictions"),
    ("file for folder", "evaluate {file} --data {data} --out {new}", "predictions"),
    ("file for folder", "evaluate {dir} --data {data} --out {file}", "--out"),
    ("file for folder", "report {file} --out {new}", "{file}"),
    ("file for folder", "report {dir} --out {file}", "--out"),
    ("file for folder", "readouts {file}", "{file}"),
    ("file for folder", "validate-metrics --data {data} --out {file}", "--out"),
    ("file for folder", "demo --out {file}", "--out"),
    ("file for folder", "preprocess --data {file} --out {new}", "--data"),
    ("file for folder", "train --config tiny --cache {file} --out {new}", "--cache"),
    ("file for folder", "probe extract --backbone base --cache {dir} --data {dir} --out {file}", "--out"),
    ("file for folder", "probe fit --acts {file} --out {new}", "--acts"),
    ("file for folder", "probe intervene --acts {dir} --cache {dir} --out {file}", "--out"),
    ("file for folder", "probe report --probes {file} --out {new}", "--probes"),
    ("file for folder", "leaderboard {dir} --out {file}", "--out"),
    # a folder where a file is expected
    ("folder for file", "manifest --split eval --out {dir}", "--out"),
    ("folder for file", "inputs --data {data} --out {dir}", "--out"),
    ("folder for file", "show 00000 --data {data} --out {dir}/sheet.png", "--out"),
    ("folder for file", "train --config {dir} --cache {dir} --out {new}", "{dir}"),
    # a file above the path where a folder should be
    ("file above", "manifest --split eval --out {file}/x.jsonl", "--out"),
    ("file above", "inputs --data {data} --out {file}/inputs.jsonl", "--out"),
    ("file above", "evaluate {dir} --data {data} --out {file}/run", "--out"),
    # missing
    ("missing", "import {missing} --data {new}", "{missing}"),
    ("missing", "show 00000 --data {missing}", "{missing}"),
    ("missing", "inputs --data {missing}", "{missing}"),
    ("missing", "predict reference --data {missing} --out {new}", "{missing}"),
    ("missing", "validate {missing} --data {data}", "predictions"),
    ("missing", "evaluate {missing} --data {data} --out {new}", "predictions"),
    ("missing", "report {missing} --out {new}", "{missing}"),
    ("missing", "readouts {missing}", "{missing}"),
    ("missing", "validate-metrics --data {missing} --out {new}", "{missing}"),
    ("missing", "preprocess --data {missing} --out {new}", "--data"),
    ("missing", "train --config {missing}.yaml --cache {dir} --out {new}", "{missing}.yaml"),
    ("missing", "train --config tiny --cache {missing} --out {new}", "--cache"),
    ("missing", "probe extract --backbone base --cache {missing} --data {dir} --out {new}", "--cache"),
    ("missing", "probe fit --acts {missing} --out {new}", "--acts"),
    ("missing", "probe intervene --acts {dir} --cache {missing} --out {new}", "--cache"),
    ("missing", "probe report --intervene {missing} --out {new}", "--intervene"),
    ("missing", "leaderboard {missing} --out {new}", "{missing}"),
    # read-only
    ("read-only", "download --data {ro}/data", "--data"),
    ("read-only", "import {dir} --data {ro}/data", "--data"),
    ("read-only", "manifest --split eval --out {ro}/eval.jsonl", "--out"),
    ("read-only", "simulate --split eval --ids 00000 --out {ro}/sim", "--out"),
    ("read-only", "render --split eval --ids 00000 --quality test --data {ro}", "--data"),
    ("read-only", "show 00000 --data {data} --out {ro}/sheet.png", "--out"),
    ("read-only", "inputs --data {data} --out {ro}/inputs.jsonl", "--out"),
    ("read-only", "predict reference --data {data} --out {ro}/preds", "--out"),
    ("read-only", "audit --models reference --data {data} --out {ro}", "--out"),
    ("read-only", "evaluate {dir} --data {data} --out {ro}/run", "--out"),
    ("read-only", "report {dir} --out {ro}/report", "--out"),
    ("read-only", "validate-metrics --data {data} --out {ro}/validation", "--out"),
    ("read-only", "demo --out {ro}/demo", "--out"),
    ("read-only", "preprocess --data {dir} --out {ro}/cache", "--out"),
    ("read-only", "train --config tiny --cache {dir} --out {ro}/train", "--out"),
    ("read-only", "probe extract --backbone base --cache {dir} --data {dir} --out {ro}/acts", "--out"),
    ("read-only", "probe fit --acts {dir} --out {ro}", "--out"),
    ("read-only", "probe intervene --acts {dir} --cache {dir} --out {ro}/intervene", "--out"),
    ("read-only", "probe report --out {ro}/report", "--out"),
    ("read-only", "leaderboard {dir} --out {ro}/site", "--out"),
    # negative
    ("negative", "import {dir} --data {new} --limit -1", "--limit"),
    ("negative", "simulate --split eval --limit -3", "--limit"),
    ("negative", "render --split eval --workers -1", "--workers"),
    ("negative", "predict reference --data {data} --concurrency -2", "--concurrency"),
    ("negative", "audit --models reference --data {data} --resamples -1", "--resamples"),
    ("negative", "evaluate {dir} --data {data} --limit -1", "--limit"),
    ("negative", "report {dir} --examples -1", "--examples"),
    ("negative", "report {dir} --seed -1", "--seed"),
    ("negative", "validate-metrics --data {data} --examples -2", "--examples"),
    ("negative", "validate-metrics --data {data} --seed -1", "--seed"),
    ("negative", "preprocess --data {dir} --out {new} --ray-shards -1", "--ray-shards"),
    ("negative", "probe extract --backbone random --cache {dir} --data {dir} --out {new} --random-seed -1",
     "--random-seed"),
    ("negative", "probe fit --acts {dir} --out {new} --batch-size -64", "--batch-size"),
    ("negative", "probe intervene --acts {dir} --cache {dir} --out {new} --clips -1", "--clips"),
    # zero
    ("zero", "render --split eval --workers 0", "--workers"),
    ("zero", "predict reference --data {data} --limit 0", "--limit"),
    ("zero", "audit --models reference --data {data} --resamples 0", "--resamples"),
    ("zero", "evaluate {dir} --data {data} --limit 0", "--limit"),
    ("zero", "report {dir} --resamples 0", "--resamples"),
    ("zero", "validate-metrics --data {data} --examples 0", "--examples"),
    ("zero", "validate-metrics --data {data} --severities 1", "--severities"),
    ("zero", "preprocess --data {dir} --out {new} --limit 0", "--limit"),
    ("zero", "probe fit --acts {dir} --out {new} --epochs 0", "--epochs"),
    ("zero", "probe intervene --acts {dir} --cache {dir} --out {new} --resamples 0", "--resamples"),
    ("zero", "leaderboard {dir} --out {new} --resamples 0", "--resamples"),
    ("zero", "envelope --data {data} --out {new} --twins 1", "--twins"),
    ("negative", "envelope --data {data} --out {new} --scale -0.5", "--scale"),
    ("file for folder", "envelope --data {data} --out {file}", "--out"),
    # empty
    ("empty", "import {dir} --data {new} --ids ''", "--ids"),
    ("empty", "simulate --split eval --ids ,,,", "--ids"),
    ("empty", "render --split eval --ids ''", "--ids"),
    ("empty", "show '' --data {data}", "ID"),
    ("empty", "predict reference --data {data} --ids ''", "--ids"),
    ("empty", "predict veo-3.1 --data {data} --ids ,,, --dry-run", "--ids"),
    ("empty", "audit --models ,, --data {data}", "--models"),
    ("empty", "evaluate {dir} --data {data} --ids ,", "--ids"),
    ("empty", "demo --modes ''", "--modes"),
    ("empty", "weights --download ''", "--download"),
    ("empty", "preprocess --data {dir} --out {new} --ids ''", "--ids"),
    ("empty", "probe extract --backbone base --cache {dir} --data {dir} --out {new} --ids ,,,", "--ids"),
    # a name that is not one
    ("unknown", "weights --download sam3", "--download"),
    ("unknown", "predict os:path --data {data} --out {new}", "os:path"),
    # submit and verify, each kind of mistake
    ("file for folder", "submit {file} --card {file} --validate-only", "RUN"),
    ("file for folder", "submit {dir} --card {file} --videos {file}", "--videos"),
    ("file for folder", "verify {dir} --rescore 1 --data {file}", "--data"),
    ("folder for file", "submit {dir} --card {dir}", "--card"),
    ("folder for file", "submit {dir} --card {file} --out {dir}", "--out"),
    ("file above", "submit {dir} --card {file} --out {file}/entry.tar.gz", "--out"),
    ("missing", "submit {missing} --card {file}", "RUN"),
    ("missing", "submit {dir} --card {missing}", "--card"),
    ("missing", "verify {missing}", "{missing}"),
    ("missing", "verify {dir} --rescore 1 --data {missing}", "--data"),
    ("missing", "verify {dir} --rescore 1", "--data"),
    ("read-only", "submit {dir} --card {file} --out {ro}/entry.tar.gz", "--out"),
    ("negative", "verify {dir} --rescore -1 --data {data}", "--rescore"),
    ("negative", "verify {dir} --seed -1", "--seed"),
    ("zero", "verify {dir} --rescore 0 --data {data}", "--rescore"),
]


@pytest.fixture
def places(data, tmp_path, read_only_dir, monkeypatch) -> dict[str, str]:
    monkeypatch.chdir(tmp_path)  # a default output path lands here if a check lets a command through
    (tmp_path / "a-file").write_text("x")
    (tmp_path / "a-folder").mkdir()
    (tmp_path / "a-folder" / "sheet.png").mkdir()
    return {"data": str(data), "file": str(tmp_path / "a-file"), "dir": str(tmp_path / "a-folder"),
            "missing": str(tmp_path / "not-there"), "ro": str(read_only_dir), "new": str(tmp_path / "new")}


def _argv(row: str, places: dict[str, str]) -> list[str]:
    return shlex.split(row.format(**places))


def _command_of(argv: list[str]) -> str:
    return " ".join(argv[:2]) if argv[0] == "probe" else argv[0]


def _refused(capsys, argv: list[str], call) -> str:
    """Run ``call()``; assert exit status 2 and one error line with no traceback; return that line."""
    try:
        status = call()
    except SystemExit as exc:  # argparse: the value was refused while the command line was read
        status = exc.code
    err = capsys.readouterr().err
    assert status == 2, f"{argv}: exit status {status}\n{err}"
    assert "Traceback" not in err and "Exception ignored" not in err, err
    lines = [line for line in err.splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith(f"rigidbench {_command_of(argv)}: error: "), err
    return lines[0]


@pytest.mark.parametrize("kind, row, names", BAD_ARGUMENTS, ids=[f"{k}: {r}" for k, r, _ in BAD_ARGUMENTS])
def test_every_command_refuses_a_bad_argument_in_one_line(places, capsys, kind, row, names):
    argv = _argv(row, places)
    here, folder = Path(places["new"]).parent, Path(places["dir"])
    before = sorted(here.rglob("*"))
    line = _refused(capsys, argv, lambda: main(argv))
    assert names.format(**places) in line, line
    assert sorted(here.rglob("*")) == before, "a refused command wrote something"
    assert Path(places["file"]).read_text() == "x" and [p.name for p in folder.iterdir()] == ["sheet.png"]


def test_the_table_covers_every_command_and_every_kind_of_mistake():
    from rigidbench.cli import COMMANDS

    commands = set()
    for command in COMMANDS:
        commands |= ({f"{command.name} {sub.name}" for sub in command.subcommands} if command.subcommands
                     else {command.name})
    covered = {_command_of(shlex.split(row)) for _, row, _ in BAD_ARGUMENTS}
    assert commands - covered == set(), "commands with no bad-argument row"
    kinds = {kind for kind, _, _ in BAD_ARGUMENTS}
    assert {"file for folder", "folder for file", "missing", "read-only", "negative", "zero", "empty"} <= kinds


# a few through a real process: the installed entry point, its exit status and its stderr
SUBPROCESS_ROWS = [
    "validate-metrics --data {data} --seed -1",
    "report {dir} --out {file}",
    "predict reference --data {data} --out {ro}/preds",
]


@pytest.mark.parametrize("row", SUBPROCESS_ROWS)
def test_bad_arguments_through_the_command(places, row):
    import subprocess

    argv = _argv(row, places)
    done = subprocess.run([sys.executable, "-m", "rigidbench", *argv], capture_output=True, text=True, timeout=120)
    assert done.returncode == 2, done.stderr
    lines = [line for line in done.stderr.splitlines() if line.strip()]  # all of stderr: logging included
    assert len(lines) == 1 and lines[0].startswith(f"rigidbench {argv[0]}: error: "), done.stderr
    named = {"validate-metrics": "--seed", "report": "--out", "predict": "--out"}[argv[0]]
    assert named in lines[0] and done.stdout == ""


@pytest.mark.parametrize("name, text", [
    ("simulation.yaml", "gravity: [1, 2\n"),
    ("camera.yaml", "lens_mm: 35\nno_such_field: 3\n"),
    ("splits.yaml", "eval: 5\n"),
    ("tags.yaml", "tags: 7\n"),
])
def test_a_bad_configuration_file_stops_predict_before_any_example(data, tmp_path, capsys, name, text):
    """One error naming the file, before any example runs (as render does), not one failure per example."""
    config = tmp_path / "config"
    config.mkdir()
    (config / name).write_text(text)
    out = tmp_path / "preds"
    argv = ["--config", str(config), "predict", "reference", "--data", str(data), "--out", str(out)]
    line = _refused(capsys, argv[2:], lambda: main(argv))
    assert str(config / name) in line and "FAILED" not in line
    assert not out.exists()


@pytest.mark.parametrize("where", ["generation.json", ".stages/predict/00000.json"])
def test_a_folder_where_predict_keeps_a_record_is_one_line_naming_it(data, tmp_path, capsys, where):
    out = tmp_path / "preds"
    argv = ["predict", "reference", "--data", str(data), "--out", str(out)]
    assert main(argv) == 0
    (out / where).unlink()
    (out / where).mkdir()
    (out / where / "something").write_text("kept")
    capsys.readouterr()
    line = _refused(capsys, argv, lambda: main(argv))
    assert f"cannot write {out / where}: Is a directory" in line and "move it aside" in line
    assert (out / where / "something").read_text() == "kept"  # nobody's folder is removed


def test_a_folder_where_evaluate_keeps_a_ledger_entry_is_one_line_naming_it(data, tmp_path, capsys):
    preds, run = tmp_path / "preds", tmp_path / "run"
    assert main(["predict", "reference", "--data", str(data), "--out", str(preds)]) == 0
    argv = ["evaluate", str(preds), "--data", str(data), "--out", str(run)]
    assert main(argv) == 0
    entry = run / ".stages" / "evaluate" / "00000.json"
    entry.unlink()
    entry.mkdir()
    capsys.readouterr()
    line = _refused(capsys, argv, lambda: main(argv))
    assert f"cannot write {entry.resolve()}: Is a directory" in line or f"cannot write {entry}: Is a directory" in line
    entry.rmdir()  # the user moves it aside: the rerun scores the example again
    assert main(argv) == 0
