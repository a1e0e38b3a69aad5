"""A damaged file stops one example, never a run, and a rerun repairs it (issue 33, items 3 and 4).

Every reader of a bundle file (masks, depth, tracks, trajectories, contacts, metadata, frames; the reference
video is read by no stage that scores) and of a run folder file (``examples/<id>.readouts.json``,
``examples/<id>.json``, ``examples/<id>.npz``, ``results.json``) gets each kind of damage: truncated, empty,
not UTF-8, a document of another type, a well-formed file of the wrong shape (e.g. 5 of the 13 frames) and a
directory in its place. The damaged file sits in the MIDDLE example (00001) of three, so the test sees the
examples after it still done.

The reference set is the synthetic published set (tests/fixtures/published_set.py: 13 frames of 96x64)
imported without Blender; the predictions are the `reference` predictor's.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest


from fixtures import published_runs  # noqa: E402
from fixtures.toy_stage import ToyStage  # noqa: E402

from rigidbench.cli import main  # noqa: E402
from rigidbench.driver import ItemResult, RunOptions, Stage, StageWorker, read_ledger, run_stage
from rigidbench.groundtruth.bundle import Sample, check_bundle  # noqa: E402
from rigidbench.hashing import digest  # noqa: E402
from rigidbench.perception.features import FeatureNets  # noqa: E402
from rigidbench.preflight import validate_predictions  # noqa: E402
from rigidbench.report.load import load_runs  # noqa: E402
from rigidbench.stages.evaluate import evaluate  # noqa: E402
from rigidbench.video import read_video, write_video  # noqa: E402

pytest.importorskip("av")

IDS = ("00000", "00001", "00002")
DAMAGED = "00001"  # the middle of the selection
T = 13  # frames of every example of the synthetic set
KINDS = ("truncated", "empty", "non_utf8", "wrong_type", "wrong_shape", "directory")
LAST_FRAME = f"frames/{T - 1:05d}.png"  # validate's check opens the first and the last frame
#: each bundle file -> how a stage reads it (the reader under test)
READERS = {
    "masks.npz": lambda s: s.masks, "depth.npz": lambda s: s.depth, "tracks.npz": lambda s: s.tracks,
    "trajectories.npz": lambda s: s.trajectory, "contacts.json": lambda s: s.contacts,
    "metadata.json": lambda s: (s.n_frames, s.resolution, s.K), LAST_FRAME: lambda s: s.frames,
}
#: the bundle files the `reference` predictor reads (it needs neither trajectories nor contacts)
PREDICT_READS = ("masks.npz", "depth.npz", "tracks.npz", "metadata.json", LAST_FRAME)
RESCORED = "its output is missing or damaged"


# -- damage ---------------------------------------------------------------------------------------------


def _cut_npz(path: Path) -> None:
    """The same arrays with 5 of the 13 frames: a well-formed file of another clip's length."""
    with np.load(path) as z:
        arrays = {k: z[k] for k in z.files}
    for key, value in arrays.items():
        if value.ndim and value.shape[0] == T:
            arrays[key] = value[:5]
        elif value.ndim >= 2 and value.shape[1] == T:
            arrays[key] = value[:, :5]
    np.savez_compressed(path, **arrays)


def _wrong_shape(path: Path) -> None:
    if path.suffix == ".npz":
        _cut_npz(path)
    elif path.name == "metadata.json":  # one number where the width and height belong
        doc = json.loads(path.read_text())
        path.write_text(json.dumps({**doc, "resolution": doc["resolution"][:1]}))
    elif path.name == "contacts.json":  # a contact 5 frames after the clip ends
        doc = json.loads(path.read_text())
        doc["contacts"].append({"frame": T + 5, "a": "object_0", "b": "support_0", "points_m": [[0, 0, 0]],
                                "normals": [[0, 0, 1]], "distances_m": [0.0]})
        path.write_text(json.dumps(doc))
    elif path.suffix == ".png":  # a frame of half the size
        from PIL import Image

        with Image.open(path) as image:
            image.convert("RGB").resize((48, 32)).save(path)
    elif path.suffix == ".mp4":  # 5 of the 13 frames
        write_video(path, read_video(path).frames[:5], fps=24, lossless=True)
    elif path.name.endswith(".readouts.json"):  # an object, but its readouts are a list
        path.write_text(json.dumps({"id": DAMAGED, "task": "bounce", "readouts": [1, 2]}))
    elif path.name == "results.json":  # an object, but its readouts block is a list
        path.write_text(json.dumps({**json.loads(path.read_text()), "readouts": [1, 2]}))
    else:  # a score record whose metrics are a list
        path.write_text(json.dumps({**json.loads(path.read_text()), "metrics": [0.5, 0.25]}))


def damage(path: Path, kind: str) -> None:
    """Damage the file at ``path`` as a killed copy, a full disk, a foreign tool or a user would."""
    if kind == "truncated":
        raw = path.read_bytes()
        path.write_bytes(raw[: len(raw) // 2])
    elif kind == "empty":
        path.write_bytes(b"")
    elif kind == "non_utf8":
        path.write_bytes(b"\xff\xfe\x80 not text \x81\x00" * 8)
    elif kind == "wrong_type":  # another document: a JSON list where an object (or an archive, an image) belongs
        path.write_text("[1, 2, 3]\n")
    elif kind == "wrong_shape":
        _wrong_shape(path)
    elif kind == "directory":
        path.unlink()
        path.mkdir()
        (path / "stray").write_text("x")
    elif kind == "missing":
        path.unlink()
    else:
        raise ValueError(kind)


def restore(path: Path, original: Path) -> None:
    """Put the intact file back (what a re-import or re-render does)."""
    if path.is_dir():
        shutil.rmtree(path)
    shutil.copy2(original, path)


# -- fixtures -------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def made(tmp_path_factory):
    """(data root with eval/00000..00002 imported, the `reference` predictions, a run folder evaluating them)."""
    root = tmp_path_factory.mktemp("damaged")
    published_runs.imported_with_reference(root, "preds")
    first = evaluate(root / "preds", root / "data", root / "run", nets=FeatureNets(), run=RunOptions(progress=False))
    assert first.ran == list(IDS) and not first.failed
    return root / "data", root / "preds", root / "run"


@pytest.fixture()
def copies(made, tmp_path):
    """Private copies of the data root, the predictions and the run folder, to damage."""
    for src, name in zip(made, ("data", "preds", "run")):
        shutil.copytree(src, tmp_path / name)
    return tmp_path / "data", tmp_path / "preds", tmp_path / "run"


def no_traceback(capsys) -> tuple[str, str]:
    out, err = capsys.readouterr()
    assert "Traceback" not in out + err
    return out, err


def rescore(preds: Path, data: Path, run: Path):
    return evaluate(preds, data, run, nets=FeatureNets(), run=RunOptions(progress=False))


# -- item 3: bundle files --------------------------------------------------------------------------------


class ReadWorker(StageWorker):
    """Reads one bundle file of an example the way the scoring stages do, and records that it could."""

    def run(self, item_id, payload, staging: Path, progress) -> ItemResult:
        READERS[self.job["file"]](Sample(Path(self.job["split"]) / item_id))
        (staging / f"{item_id}.txt").write_text("read")
        return ItemResult(outputs=[f"{item_id}.txt"])


class ReadStage(Stage):
    """A stage over the three examples whose work is reading one bundle file: the driver's per-example
    isolation around each reader, in milliseconds."""

    name = "read"
    worker = "test_damaged_files:ReadWorker"

    def __init__(self, root: Path, split: Path, file: str):
        self._root, self.split, self.file = root, split, file

    @property
    def root(self) -> Path:
        return self._root

    def items(self) -> dict:
        return {i: {} for i in IDS}

    def key(self, item_id, payload) -> str:
        return digest(self.file)

    def job(self) -> dict:
        return {"split": str(self.split), "file": self.file}

    def worker_instance(self) -> ReadWorker:
        return ReadWorker(self.job())


@pytest.fixture(scope="module")
def shared_split(made, tmp_path_factory):
    """One copy of the split for the reader tests, each of which damages one file and puts it back."""
    split = tmp_path_factory.mktemp("readers") / "eval"
    shutil.copytree(made[0] / "eval", split)
    return split


@pytest.mark.parametrize("kind", KINDS)
@pytest.mark.parametrize("name", list(READERS))
def test_every_bundle_reader_fails_only_its_example_naming_the_file(made, shared_split, tmp_path, name, kind):
    """Whatever the damage, reading the file is a BundleError naming it and saying what to do (never an
    IndexError, ValueError or TypeError from deeper down): its example fails, the one after it is read, and
    once the file is repaired the rerun reads exactly that example. validate's check names the same file."""
    split, path = shared_split, shared_split / DAMAGED / name
    damage(path, kind)
    try:
        _fails_only_its_example_then_is_read(made, split, tmp_path, path, name)
    finally:
        restore(path, made[0] / "eval" / DAMAGED / name)


def _fails_only_its_example_then_is_read(made, split: Path, tmp_path: Path, path: Path, name: str) -> None:
    report = run_stage(ReadStage(tmp_path / "out", split, name), RunOptions(progress=False))
    assert report.ran == ["00000", "00002"] and list(report.failed) == [DAMAGED]
    message = report.failed[DAMAGED]
    assert message.startswith(f"example {DAMAGED}: {path} ") and "rigidbench import" in message and "\n" not in message
    shown = name.split("/")[-1] if name.startswith("frames") else name
    assert any(shown in problem for problem in check_bundle(split / DAMAGED, check_video=False))

    restore(path, made[0] / "eval" / DAMAGED / name)  # as a re-import would
    again = run_stage(ReadStage(tmp_path / "out", split, name), RunOptions(progress=False))
    assert again.ran == [DAMAGED] and again.reused == ["00000", "00002"] and not again.failed


@pytest.mark.parametrize("name", list(READERS))
def test_a_bundle_file_of_the_wrong_length_fails_only_its_example_in_evaluate_and_predict(
        copies, made, tmp_path, capsys, name):
    """The issue's case (e.g. masks.npz cut to 5 of the 13 frames) through the commands, for every file; a
    repaired file (as a re-import leaves it) is scored on the rerun, the others kept."""
    data, preds, _ = copies
    path = data / "eval" / DAMAGED / name
    damage(path, "wrong_shape")
    run = tmp_path / "fresh-run"

    # evaluate: the others are scored, the damaged one fails naming its file, results.json is written
    assert main(["evaluate", str(preds), "--data", str(data), "--out", str(run)]) == 1
    _, err = no_traceback(capsys)
    assert f"FAILED {DAMAGED}" in err and str(path) in err
    results = json.loads((run / "results.json").read_text())
    assert list(results["failed"]) == [DAMAGED] and str(path) in results["failed"][DAMAGED]
    assert results["n_examples"] == 2 and sorted(results["coverage"]["per_example"]) == ["00000", "00002"]

    # predict: the others are written; the damaged one fails when the predictor reads that file
    reads = name in PREDICT_READS
    out = tmp_path / "predicted"
    assert main(["predict", "reference", "--data", str(data), "--out", str(out)]) == (1 if reads else 0)
    _, err = no_traceback(capsys)
    assert (out / "00000.mp4").is_file() and (out / "00002.mp4").is_file()
    assert (out / f"{DAMAGED}.mp4").exists() is not reads and (str(path) in err) is reads

    # repaired (as a re-import would): the rerun scores the damaged example and keeps the others
    before = {i: (run / "examples" / f"{i}.json").stat().st_mtime_ns for i in ("00000", "00002")}
    restore(path, made[0] / "eval" / DAMAGED / name)
    again = rescore(preds, data, run)
    assert again.ran == [DAMAGED] and again.reused == ["00000", "00002"] and not again.failed
    assert again.facts.results["n_examples"] == 3 and not again.facts.results["failed"]
    assert {i: (run / "examples" / f"{i}.json").stat().st_mtime_ns for i in ("00000", "00002")} == before


@pytest.mark.parametrize("name", ["masks.npz", "tracks.npz"])
def test_show_and_audit_go_on_past_a_bundle_file_of_the_wrong_length(copies, tmp_path, capsys, name):
    """The issue's case: masks.npz or tracks.npz cut to 5 of the 13 frames stopped show (IndexError) and
    audit (ValueError in the predictor) with a traceback."""
    data, _, _ = copies
    damage(data / "eval" / DAMAGED / name, "wrong_shape")
    sheets = tmp_path / "sheets"
    assert main(["show", *IDS, "--data", str(data), "--out", str(sheets)]) == 1
    out, err = no_traceback(capsys)
    assert sorted(p.name for p in sheets.iterdir()) == [f"eval_{i}_contact_sheet.png" for i in IDS if i != DAMAGED]
    assert f"FAILED {DAMAGED}" in err and name in err and "has shape" in err
    if name == "masks.npz":  # audit: predict, validate, evaluate and the report, the damaged example failed
        audit = tmp_path / "audit"
        assert main(["audit", "--models", "reference", "--perception", "gt", "--data", str(data), "--out", str(audit),
                     "--resamples", "100"]) == 1
        out, err = no_traceback(capsys)
        results = json.loads((audit / "runs" / "reference" / "results.json").read_text())
        assert list(results["failed"]) == [DAMAGED] and results["n_examples"] == 2
        assert (audit / "report" / "report.html").is_file() and name in out + err


def test_a_paid_dry_run_lists_every_other_request_past_a_damaged_first_frame(copies, tmp_path, capsys, caplog):
    """A damaged first frame used to stop `predict --dry-run` of a paid model at that example."""
    data, _, _ = copies
    damage(data / "eval" / DAMAGED / "frames" / "00000.png", "truncated")
    assert main(["predict", "veo-3.1", "--dry-run", "--data", str(data), "--out", str(tmp_path / "veo")]) == 0
    out, _ = no_traceback(capsys)
    assert [line[:5] for line in out.splitlines() if line[:5] in IDS] == ["00000", "00002"]
    assert "predict: would make 2, 0 up to date, 1 failed of 3 example(s)" in out and "2 paid API calls" in out
    assert f"example {DAMAGED} failed" in caplog.text and "frames/00000.png" in caplog.text


def test_a_damaged_reference_video_is_read_by_no_scoring_stage_and_validate_names_it(copies, tmp_path, capsys):
    """video.mp4 is not what the scores are computed from (the frames are): every example is still done, and
    validate's check of the reference reports the damaged video of that example only."""
    data, preds, _ = copies
    damage(data / "eval" / DAMAGED / "video.mp4", "wrong_shape")
    assert main(["evaluate", str(preds), "--data", str(data), "--out", str(tmp_path / "run")]) == 0
    assert main(["predict", "reference", "--data", str(data), "--out", str(tmp_path / "p")]) == 0
    no_traceback(capsys)
    assert any("video.mp4" in p for p in check_bundle(data / "eval" / DAMAGED))
    report = validate_predictions(preds, data / "eval")
    assert {i.example_id for i in report.errors} == {DAMAGED} and "video.mp4" in report.errors[0].message


# -- item 4: run folder files ----------------------------------------------------------------------------


def readouts_listed(out: str) -> list[str]:
    """The example ids `rigidbench readouts --examples` printed a line for."""
    return [line.split()[0] for line in out.splitlines() if line.startswith("    ") and "): speed" in line]


@pytest.mark.parametrize("kind", KINDS + ("missing",))
@pytest.mark.parametrize("name", ["readouts.json", "json"])
def test_a_damaged_example_file_is_left_out_with_a_count_then_scored_again(copies, capsys, caplog, name, kind):
    data, preds, run = copies
    path = run / "examples" / f"{DAMAGED}.{name}"
    damage(path, kind)
    readouts_damaged = name == "readouts.json"

    # readouts: every other example is printed; the damaged one is counted as left out, naming its file
    assert main(["readouts", str(run), "--examples"]) == 0
    out, err = no_traceback(capsys)
    assert readouts_listed(out) == (["00000", "00002"] if readouts_damaged else list(IDS))
    if readouts_damaged:
        assert "1 example(s) without a readable readouts file" in out.splitlines()[0]
        assert f"examples/{DAMAGED}.readouts.json {'missing' if kind == 'missing' else 'damaged'}" in out
        assert "rerun `rigidbench evaluate`" in out
        if kind != "missing":  # the warning names the file and why
            assert str(path) in caplog.text

    # report's reader: a damaged or missing record is left out, the header says how many and why
    table = load_runs([run])
    assert table.example_ids == (IDS if readouts_damaged else ("00000", "00002"))
    left_out = [n for n in table.notes if "could not be read and are left out" in n]
    if readouts_damaged:
        assert not left_out
    else:
        assert len(left_out) == 1 and left_out[0].startswith(f"1 example record(s) of {preds.name} ")
        assert f"examples/{DAMAGED}.json" in left_out[0] and "rerun `rigidbench evaluate`" in left_out[0]

    # evaluate again: exactly the damaged example is scored again, and the file is whole
    again = rescore(preds, data, run)
    assert again.ran == [DAMAGED] and again.reused == ["00000", "00002"]
    assert again.redone == {DAMAGED: RESCORED}
    assert isinstance(json.loads(path.read_text()), dict)
    assert main(["readouts", str(run), "--examples"]) == 0
    out, _ = no_traceback(capsys)
    assert readouts_listed(out) == list(IDS) and "left out" not in out
    assert load_runs([run]).example_ids == IDS


@pytest.mark.parametrize("kind", ["missing", "directory"])
def test_a_missing_or_replaced_arrays_file_is_scored_again(copies, kind):
    data, preds, run = copies
    path = run / "examples" / f"{DAMAGED}.npz"
    damage(path, kind)
    again = rescore(preds, data, run)
    assert again.ran == [DAMAGED] and again.redone == {DAMAGED: RESCORED}
    with np.load(path) as z:
        assert "ssim" in z.files and z["ssim"].shape == (T,)


@pytest.mark.parametrize("kind", KINDS)
def test_a_damaged_results_file_is_one_line_and_exit_2_and_evaluate_writes_it_again(copies, capsys, kind):
    data, preds, run = copies
    path = run / "results.json"
    intact = path.read_text()
    damage(path, kind)
    for command in (["readouts", str(run)], ["report", str(run), "--out", str(run.parent / "report")]):
        assert main(command) == 2
        out, err = no_traceback(capsys)
        assert err.startswith(f"rigidbench {command[0]}: error: {path}") and err.count("\n") == 1, err
        assert "rerun `rigidbench evaluate` with --out" in err
        assert ("aside" in err) is (kind == "directory")
    if kind == "directory":  # as the message says
        shutil.rmtree(path)
    again = rescore(preds, data, run)
    assert again.reused == list(IDS) and not again.ran  # nothing scored again
    assert path.read_text() == intact
    assert main(["readouts", str(run)]) == 0


def test_report_leaves_a_damaged_record_out_and_says_so_in_its_header(copies, tmp_path, capsys, caplog):
    _, preds, run = copies
    damage(run / "examples" / f"{DAMAGED}.json", "truncated")
    out_dir = tmp_path / "report"
    assert main(["report", str(run), "--out", str(out_dir), "--resamples", "100", "--examples", "0"]) == 0
    no_traceback(capsys)
    assert f"examples/{DAMAGED}.json: truncated or not JSON" in caplog.text
    header = (out_dir / "report.md").read_text().split("###")[0]
    assert f"1 example record(s) of {preds.name} could not be read and are left out" in header
    assert "2 evaluation examples" in (out_dir / "report.md").read_text()


# -- the driver's default intactness check ----------------------------------------------------------------


class PlainToyStage(ToyStage):
    """The toy stage with the driver's default intactness check (every output its ledger entry lists)."""

    intact = Stage.intact


@pytest.mark.parametrize("damaged", ["out/b.txt", "out/b.dir"])
@pytest.mark.parametrize("kind", ["missing", "swapped"])
def test_the_default_intactness_check_covers_every_listed_output(tmp_path, damaged, kind):
    payloads = {"a": {"n": 1}, "b": {"n": 2}, "c": {"n": 3}}
    run_stage(PlainToyStage(tmp_path, payloads), RunOptions(progress=False))
    assert read_ledger(tmp_path, "toy", "b")["outputs"] == {"out/b.dir": "directory", "out/b.txt": "file"}
    path = tmp_path / damaged
    if path.is_dir():
        shutil.rmtree(path)
        if kind == "swapped":
            path.write_text("a file where the folder was")
    else:
        path.unlink()
        if kind == "swapped":
            path.mkdir()
    again = run_stage(PlainToyStage(tmp_path, payloads), RunOptions(progress=False))
    assert again.ran == ["b"] and again.reused == ["a", "c"] and again.redone == {"b": RESCORED}
    assert (tmp_path / "out" / "b.txt").read_text() == "4" and (tmp_path / "out" / "b.dir" / "value").is_file()
