"""rigidbench.atomic: files and directories appear whole or not at all."""

import stat

import numpy as np
import pytest

from rigidbench.atomic import atomic_dir, atomic_file, current_umask, write_bytes, write_text


def test_a_file_appears_complete_and_a_failed_write_leaves_nothing(tmp_path):
    path = tmp_path / "a.txt"
    write_text(path, "old")
    with pytest.raises(RuntimeError):
        with atomic_file(path) as tmp:
            tmp.write_text("half")
            raise RuntimeError("killed")
    assert path.read_text() == "old" and sorted(p.name for p in tmp_path.iterdir()) == ["a.txt"]
    write_bytes(path, b"new", unique=True)  # mkstemp's temporary is private; the file gets the umask's mode
    assert path.read_bytes() == b"new" and stat.S_IMODE(path.stat().st_mode) == 0o666 & ~current_umask()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.txt"]


def test_npz_writers_get_a_temporary_that_ends_in_npz(tmp_path):
    with atomic_file(tmp_path / "x.npz", suffix=".npz") as tmp:
        assert tmp.name == ".x.npz.tmp.npz"
        np.savez(tmp, a=np.arange(3))
    assert np.array_equal(np.load(tmp_path / "x.npz")["a"], np.arange(3))
    assert sorted(p.name for p in tmp_path.iterdir()) == ["x.npz"]


def test_a_directory_is_renamed_into_place_or_removed(tmp_path):
    out = tmp_path / "d"
    (tmp_path / ".d.tmp").mkdir()  # a killed run's leftover
    with atomic_dir(out) as tmp:
        (tmp / "f").write_text("1")
    assert (out / "f").read_text() == "1" and not (tmp_path / ".d.tmp").exists()
    with pytest.raises(RuntimeError):
        with atomic_dir(out, unique=True, replace=True) as tmp:
            (tmp / "f").write_text("2")
            raise RuntimeError("killed")
    assert (out / "f").read_text() == "1" and sorted(p.name for p in tmp_path.iterdir()) == ["d"]
    with atomic_dir(out, unique=True, replace=True) as tmp:
        (tmp / "g").write_text("2")
    assert sorted(p.name for p in out.iterdir()) == ["g"] and sorted(p.name for p in tmp_path.iterdir()) == ["d"]
