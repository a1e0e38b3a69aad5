"""A full disk during evaluate and predict (issue 33, item 5).

Whatever runs out of space: an example whose own files cannot be written fails alone, its reason naming the
file; when not even the run's record (an example's ledger entry, results.json, generation.json) can be
written, the command stops with one line naming the file and exit status 2. Never a traceback, never
"Exception ignored in ZipFile.__del__" (np.savez leaves its half-written archive to the garbage collector).
A rerun after space is freed gives byte-identical results.

The disk is a write wrapper (``FullDisk``: every file opened for writing under a folder shares a budget of
bytes, and ``write()`` past it fails with ENOSPC, naming no file, as on a full disk) everywhere, and a real
small tmpfs filled up where one can be mounted (root).
"""

from __future__ import annotations

import builtins
import contextlib
import errno
import gc
import io
import json
import os
import re
import sys
from pathlib import Path

import pytest


from fixtures import published_set as ps  # noqa: E402

from rigidbench.driver import RunOptions  # noqa: E402
from rigidbench.cli import main  # noqa: E402
from rigidbench.stages.import_set import import_published  # noqa: E402

NO_SPACE = os.strerror(errno.ENOSPC)


class FullDisk:
    """Files opened for writing under ``root`` (through ``open``/``io.open``: pathlib, json, zipfile, numpy)
    share ``room`` bytes; a ``write()`` larger than what is left raises OSError(ENOSPC) without a file name
    (a smaller one may still fit, as on a nearly full disk); ``largest``: no file grows past this many bytes
    (big files do not fit, small ones do). ``written`` counts what was written (a run with ``room=None``, no
    limit, measures a whole run)."""

    def __init__(self, root: Path, room: int | None, largest: int | None = None):
        self.root, self.room, self.largest, self.written = str(Path(root).resolve()), room, largest, 0
        self._open = io.open

    def open(self, file, mode="r", *args, **kwargs):
        handle = self._open(file, mode, *args, **kwargs)
        name = os.fspath(file) if isinstance(file, (str, bytes, os.PathLike)) else None
        writing = any(c in mode for c in "wax+")
        if writing and isinstance(name, str) and os.path.abspath(name).startswith(self.root + os.sep):
            return _Metered(handle, self)
        return handle


class _Metered:
    def __init__(self, handle, disk: FullDisk):
        self._handle, self._disk, self._size, self._failed = handle, disk, 0, False

    def write(self, data):
        too_big = (self._disk.room is not None and len(data) > self._disk.room  # a smaller file may still fit
                   or self._disk.largest is not None and self._size + len(data) > self._disk.largest)
        if too_big or self._failed:  # a file that ran out of space grows no more
            self._failed = True
            raise OSError(errno.ENOSPC, NO_SPACE)
        self._size += len(data)
        if self._disk.room is not None:
            self._disk.room -= len(data)
        self._disk.written += len(data)
        return self._handle.write(data)

    def __getattr__(self, name):
        return getattr(self._handle, name)

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        return self._handle.__exit__(*exc)

    def __iter__(self):
        return iter(self._handle)


@contextlib.contextmanager
def full_disk(root: Path, room: int | None, largest: int | None = None):
    """A ``FullDisk`` for ``root``, for the block (space is freed when it ends)."""
    disk = FullDisk(root, room, largest)
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(io, "open", disk.open)
        mp.setattr(builtins, "open", disk.open)
        yield disk


@pytest.fixture
def unraisable(monkeypatch):
    """Exceptions Python could only print as "Exception ignored in ..." (e.g. from a ZipFile's __del__)."""
    seen = []
    monkeypatch.setattr(sys, "unraisablehook", lambda info: seen.append(f"{info.object!r}: {info.exc_value!r}"))
    return seen


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    root = tmp_path_factory.mktemp("full-disk")
    samples = [s for s in ps.DEFAULT_SAMPLES if not s.rgba]
    ps.write_set(root / "src", samples)
    assert import_published(root / "src", root / "data", run=RunOptions(progress=False)).exit_status() == 0
    return root / "data"


@pytest.fixture(scope="module")
def clean(data, tmp_path_factory):
    """Predictions and an evaluation run made with room to spare (what a rerun must reproduce), and the bytes
    each run writes through files (``FullDisk.written``)."""
    root = tmp_path_factory.mktemp("clean")
    preds, run = root / "preds", root / "run"
    with full_disk(preds, None) as predicted:
        assert main(["predict", "reference", "--data", str(data), "--out", str(preds)]) == 0
    with full_disk(run, None) as evaluated:
        assert main(["evaluate", str(preds), "--data", str(data), "--out", str(run)]) == 0
    return {"preds": preds, "run": run, "predict_bytes": predicted.written, "evaluate_bytes": evaluated.written}


def _outcome(capsys, status: int, root: Path, unraisable: list) -> list[str]:
    """Check one run on a full disk; return its error and FAILED lines (each names a file under ``root``)."""
    gc.collect()
    err = capsys.readouterr().err
    assert "Traceback" not in err and "Exception ignored" not in err and not unraisable, (err, unraisable)
    errors = [line for line in err.splitlines() if ": error: " in line]
    failed = [line for line in err.splitlines() if line.strip().startswith("FAILED")]
    assert status in (0, 1, 2) and (status == 2) == bool(errors) and len(errors) <= 1, err
    for line in errors + failed:
        named = re.search(r"cannot write (\S+): " + NO_SPACE, line)
        assert named, line
        assert Path(named.group(1)).resolve().is_relative_to(root.resolve()), line
    if errors:
        assert "free some space and rerun" in errors[0]
    return errors + failed


def _same_files(a: Path, b: Path, pattern: str) -> None:
    names = sorted(p.name for p in a.glob(pattern))
    assert names and names == sorted(p.name for p in b.glob(pattern))
    for name in names:
        assert (a / name).read_bytes() == (b / name).read_bytes(), name


def _same_run(run: Path, clean_run: Path) -> None:
    assert (run / "results.json").read_bytes() == (clean_run / "results.json").read_bytes()
    _same_files(run / "examples", clean_run / "examples", "*")


def _same_predictions(preds: Path, clean_preds: Path) -> None:
    _same_files(preds, clean_preds, "*.mp4")
    _same_files(preds, clean_preds, "*.state.npz")

    def records(folder: Path) -> dict:  # as written, less each example's time
        doc = json.loads((folder / "generation.json").read_text())
        return {**doc, "examples": {i: {k: v for k, v in r.items() if k != "seconds"}
                                    for i, r in doc["examples"].items()}}

    assert records(preds) == records(clean_preds)


@pytest.mark.parametrize("share", [0.0, 0.35, 0.97])
def test_evaluate_on_a_full_disk_stops_in_one_line_and_a_rerun_gives_the_same_run(
        data, clean, tmp_path, capsys, unraisable, share):
    preds, run = clean["preds"], tmp_path / "run"
    argv = ["evaluate", str(preds), "--data", str(data), "--out", str(run)]
    with full_disk(run, int(share * clean["evaluate_bytes"])):
        lines = _outcome(capsys, main(argv), run, unraisable)
    assert lines, "the disk ran out, and nothing said so"
    assert main(argv) == 0  # space freed
    _same_run(run, clean["run"])


@pytest.mark.parametrize("share, largest", [(0.6, None), (None, 8 << 10)])
def test_predict_on_a_full_disk_fails_examples_naming_the_file_and_a_rerun_gives_the_same_videos(
        data, clean, tmp_path, capsys, unraisable, share, largest):
    preds = tmp_path / "preds"
    argv = ["predict", "reference", "--data", str(data), "--out", str(preds)]
    with full_disk(preds, None if share is None else int(share * clean["predict_bytes"]), largest):
        lines = _outcome(capsys, main(argv), preds, unraisable)
    assert lines, "the disk ran out, and nothing said so"
    if largest is not None:  # the state files (about 14 kB) do not fit, the records do: each example fails alone
        assert len(lines) == 2 and all("FAILED" in line and ".state.npz" in line for line in lines), lines
    assert main(argv) == 0
    _same_predictions(preds, clean["preds"])
    assert main(["evaluate", str(preds), "--data", str(data), "--out", str(tmp_path / "run")]) == 0
    _same_run(tmp_path / "run", clean["run"])


def _fill(disk: Path, leave: int) -> Path:
    """Fill the file system of ``disk`` with one file, then give back ``leave`` bytes of it."""
    filler = disk / "filler"
    chunk = b"\0" * (1 << 16)
    with open(filler, "wb") as fh:
        try:
            while True:
                fh.write(chunk)
                fh.flush()
        except OSError as exc:
            assert exc.errno == errno.ENOSPC
    size = filler.stat().st_size
    os.truncate(filler, max(0, size - leave))
    return filler


@pytest.mark.parametrize("leave", [0, 72 << 10])
def test_a_real_full_disk(data, clean, tmp_path, capsys, unraisable, small_tmpfs, leave):
    """The same on a small tmpfs filled up (where one can be mounted): predict, then evaluate, then both
    again once the filler is removed."""
    with small_tmpfs(tmp_path / "disk", "1m") as disk:
        if disk is None:
            pytest.skip("no tmpfs can be mounted here (needs root); the write wrapper tests cover a full disk")
        filler = _fill(disk, leave)
        preds, run = disk / "preds", disk / "run"
        predict = ["predict", "reference", "--data", str(data), "--out", str(preds)]
        evaluate = ["evaluate", str(clean["preds"]), "--data", str(data), "--out", str(run)]
        assert _outcome(capsys, main(predict), preds, unraisable)
        assert _outcome(capsys, main(evaluate), run, unraisable)
        filler.unlink()
        assert main(predict) == 0 and main(evaluate) == 0
        _same_predictions(preds, clean["preds"])
        _same_run(run, clean["run"])


@pytest.mark.parametrize("executor", ["local", "processes"])
def test_a_ledger_entry_that_cannot_be_written_stops_the_stage_wherever_the_example_ran(tmp_path, monkeypatch,
                                                                                       executor):
    """The driver's own record of an example (its ledger entry) cannot be written: the stage stops with one
    error naming it, also when the example ran in a child process; the examples before it are kept."""
    from rigidbench.driver import ledger_path, run_stage
    from rigidbench.errors import UserError
    from rigidbench.executors import make_executor
    from fixtures import child_env
    from fixtures.toy_stage import ToyStage

    monkeypatch.setenv("PYTHONPATH", child_env()["PYTHONPATH"])  # for the child processes
    payloads = {"a": {"n": 1}, "b": {"n": 2}, "c": {"n": 3}}
    blocked = ledger_path(tmp_path, "toy", "b")
    blocked.mkdir(parents=True)  # a folder where the ledger entry goes: writing it fails with EISDIR
    with pytest.raises(UserError, match=rf"toy stopped at example b: cannot write {re.escape(str(blocked))}: "
                                        r"Is a directory; a folder is in the way"):
        run_stage(ToyStage(tmp_path, payloads), RunOptions(executor=make_executor(executor), progress=False))
    assert (tmp_path / "out" / "a.txt").read_text() == "2" and ledger_path(tmp_path, "toy", "a").is_file()
    blocked.rmdir()
    report = run_stage(ToyStage(tmp_path, payloads), RunOptions(progress=False))
    assert report.reused == ["a"] and sorted(report.ran) == ["b", "c"] and not report.failed
