"""Importing the published evaluation set: a tiny synthetic set in the published layout
(tests/fixtures/published_set.py) becomes bundles our commands read, with ground-truth tracks by the
released evaluator's rule, resumably, and one damaged sample never stops the others."""

from __future__ import annotations

import json
import os

import numpy as np
import pytest


from fixtures import published_set as ps  # noqa: E402

from rigidbench.config import registry  # noqa: E402
from rigidbench.datasets.convert import find_published_root
from rigidbench.driver import RunOptions, Selection, ledger_path, read_ledger, staging_path  # noqa: E402
from rigidbench.errors import BundleError, UserError  # noqa: E402
from rigidbench.groundtruth.bundle import Sample, check_bundle, resolve_split_dir  # noqa: E402
from rigidbench.stages.import_set import import_published  # noqa: E402

IDENTITY = {"dataset": "rigidbench-eval", "version": "1.1", "md5": "b563f279451e95fe2f32d7e258588636"}


@pytest.fixture(scope="module")
def published(tmp_path_factory):
    root = tmp_path_factory.mktemp("published") / "rigidbench-eval-v1.1"
    return ps.write_set(root)


@pytest.fixture(scope="module")
def imported(published, tmp_path_factory):
    data = tmp_path_factory.mktemp("data")
    summary = import_published(published.parent, data, dataset=IDENTITY, registry=registry(), run=RunOptions(progress=False))
    return data, summary


def test_every_sample_becomes_a_valid_bundle(imported):
    data, summary = imported
    assert summary.ran == ["00000", "00001", "00002"] and not summary.failed
    for sample_id in summary.ran:
        assert check_bundle(data / "eval" / sample_id) == []
    assert resolve_split_dir(data) == data / "eval"


def test_metadata_is_renamed_and_keeps_the_source(imported, published):
    data, _ = imported
    meta = Sample(data / "eval" / "00001").metadata
    original = json.loads((published / "samples" / "00001" / "metadata.json").read_text())
    assert meta["sample_id"] == "00001" and meta["task"] == "bounce" and meta["partition"] == "ood_scene"
    assert meta["fps"] == 24 and meta["resolution"] == [96, 64] and meta["frames"] == 13
    assert meta["source"]["dataset"] == "rigidbench-eval" and meta["source"]["version"] == "1.1"
    assert meta["source"]["md5"] == IDENTITY["md5"] and meta["source"]["original_metadata"] == original
    ball = next(a for a in meta["actors"] if a["name"] == "object_0")
    assert ball["asset"] == "bouncy_ball" and ball["role"] == "active" and ball["restitution"] == 0.85
    assert meta["roles"] == ["active", "passive"] and meta["active_indices"] == [0]


def test_camera_keeps_the_published_principal_point_and_pose(imported, published):
    data, _ = imported
    sample = Sample(data / "eval" / "00000")
    original = json.loads((published / "samples" / "00000" / "metadata.json").read_text())["camera"]
    K = sample.K
    assert K[0, 2] == 48.0 and K[1, 2] == 32.0 and K[0, 0] == original["intrinsics"]["fx"]
    R_c, t_c = sample.camera_pose
    np.testing.assert_allclose(t_c, original["extrinsics"]["location"])
    np.testing.assert_allclose(R_c, ps._matrix_from_quat(np.array(original["extrinsics"]["rotation"])), atol=1e-12)
    np.testing.assert_allclose(sample.world_to_camera_cv @ sample.camera_to_world,
                               np.diag([1.0, -1.0, -1.0, 1.0]), atol=1e-12)


def test_arrays_are_converted(imported, published):
    data, _ = imported
    src = published / "samples" / "00000"
    sample = Sample(data / "eval" / "00000")
    raw_depth = np.load(src / "depth.npz")["depth"]
    assert np.isinf(sample.depth[raw_depth >= 1e9]).all() and (raw_depth >= 1e9).any()
    np.testing.assert_array_equal(sample.depth[raw_depth < 1e9], raw_depth[raw_depth < 1e9])
    np.testing.assert_array_equal(sample.masks, np.load(src / "masks.npz")["masks"])
    assert sample.actor_names == ("object_0", "support_0") and sample.roles == ("active", "passive")
    traj = np.load(src / "trajectories.npz")
    np.testing.assert_allclose(sample.trajectory.positions_m[0], traj["object_0_positions"], atol=1e-6)
    # velocities recomputed in m/s: the ball falls at g (central differences of 0.5 g t^2 are exact)
    vz = sample.trajectory.linear_velocity_m_s[0, 1:6, 2]
    np.testing.assert_allclose(vz, -ps.G * np.arange(1, 6) / 24, atol=1e-4)
    contacts = json.loads((data / "eval" / "00000" / "contacts.json").read_text())["contacts"]
    published_contacts = json.loads((src / "contacts.json").read_text())
    assert [c["frame"] for c in contacts] == [c["frame"] for c in published_contacts]


def test_frames_are_linked_or_decoded(imported, published):
    """RGB and RGBA PNGs are hard-linked, nothing written (readers drop the alpha channel, as the released
    evaluator's Image.convert("RGB")); no frames/ at all: decoded from video.mp4."""
    from PIL import Image

    data, _ = imported
    for sample_id in ("00000", "00001"):
        for k in range(13):
            name = f"{k:05d}.png"
            assert os.path.samefile(data / "eval" / sample_id / "frames" / name,
                                    published / "samples" / sample_id / "frames" / name)
    with Image.open(published / "samples" / "00001" / "frames" / "00005.png") as im:
        assert im.mode == "RGBA"
        rgba = np.asarray(im)
    np.testing.assert_array_equal(Sample(data / "eval" / "00001").frame(5), rgba[..., :3])  # alpha dropped
    with Image.open(data / "eval" / "00002" / "frames" / "00000.png") as im:
        assert im.mode == "RGB" and im.size == (96, 64)
    decoded = Sample(data / "eval" / "00002").frame(0).astype(int)
    assert decoded.std() > 10  # a real picture, not a blank


def test_other_png_layouts_are_converted_to_8_bit_rgb(tmp_path):
    """A 16-bit or palette PNG is not linked: the bundle gets the 8-bit RGB a reader expects."""
    import cv2
    from PIL import Image

    root = ps.write_set(tmp_path / "src", ps.DEFAULT_SAMPLES[:1])
    frames = root / "samples" / "00000" / "frames"
    rgb = np.asarray(Image.open(frames / "00002.png").convert("RGB"))
    deep = rgb.astype(np.uint16) * 257 + 3  # the high byte is the 8-bit value
    cv2.imwrite(str(frames / "00002.png"), deep[..., ::-1])
    Image.fromarray(rgb).convert("P", palette=Image.Palette.ADAPTIVE).save(frames / "00003.png")
    palette = np.asarray(Image.open(frames / "00003.png").convert("RGB"))
    summary = import_published(root, tmp_path / "data", run=RunOptions(progress=False))
    assert summary.ran == ["00000"], summary.failed
    out = tmp_path / "data" / "eval" / "00000" / "frames"
    for name, want in (("00002.png", rgb), ("00003.png", palette)):
        assert not os.path.samefile(out / name, frames / name)
        with Image.open(out / name) as im:
            assert im.mode == "RGB"
            np.testing.assert_array_equal(np.asarray(im), want)


def test_tracks_follow_the_released_rule(imported, published):
    data, _ = imported
    for sample_id in ("00000", "00001", "00002"):
        tracks = Sample(data / "eval" / sample_id).tracks
        ref = ps.release_tracks(published / "samples" / sample_id, "object_0")
        np.testing.assert_array_equal(tracks.query_pixels, ref["query"])
        np.testing.assert_allclose(tracks.tracks_px, ref["tracks"], atol=1e-4)
        np.testing.assert_array_equal(tracks.visibility, ref["visibility"])
        assert set(tracks.actor_index.tolist()) == {0}  # only the active actor is tracked


def test_no_scene_spec_is_one_clear_error(imported):
    data, _ = imported
    with pytest.raises(BundleError, match="imported from the published set.*rigidbench render"):
        Sample(data / "eval" / "00000").spec


def test_both_root_layouts_and_a_top_folder_are_found(tmp_path):
    ps.write_set(tmp_path / "a" / "rigidbench-eval-v1.1", ps.DEFAULT_SAMPLES[:1], layout="eval")
    assert find_published_root(tmp_path / "a") == tmp_path / "a" / "rigidbench-eval-v1.1"
    summary = import_published(tmp_path / "a", tmp_path / "data", run=RunOptions(progress=False))
    assert summary.ran == ["00000"] and check_bundle(tmp_path / "data" / "eval" / "00000") == []
    with pytest.raises(UserError, match="no published RigidBench evaluation set"):
        find_published_root(tmp_path / "data")


def test_a_rerun_skips_unchanged_and_redoes_changed_samples(tmp_path):
    root = ps.write_set(tmp_path / "src", ps.DEFAULT_SAMPLES[:2])
    first = import_published(root, tmp_path / "data", run=RunOptions(progress=False))
    assert first.ran == ["00000", "00001"]
    stamp = (tmp_path / "data" / "eval" / "00000" / "tracks.npz").stat().st_mtime_ns
    prompt = root / "samples" / "00001" / "prompt.txt"
    prompt.write_text("A different prompt for this sample.")
    (tmp_path / "data" / "eval" / ".00000.tmp").mkdir()  # left by a killed import
    second = import_published(root, tmp_path / "data", run=RunOptions(progress=False))
    assert second.reused == ["00000"] and second.ran == ["00001"]
    assert (tmp_path / "data" / "eval" / "00000" / "tracks.npz").stat().st_mtime_ns == stamp
    assert Sample(tmp_path / "data" / "eval" / "00001").prompt == "A different prompt for this sample."
    assert not (tmp_path / "data" / "eval" / ".00000.tmp").exists()


def test_import_resumes_on_the_stage_driver(tmp_path):
    """A killed import (staging left behind, one sample without its ledger entry) resumes; another dataset
    identity re-imports every sample and says why; a bundle imported before ledgers existed is adopted."""
    root = ps.write_set(tmp_path / "src", ps.DEFAULT_SAMPLES[:2])
    split = tmp_path / "data" / "eval"
    clean = import_published(root, tmp_path / "clean", run=RunOptions(progress=False))
    first = import_published(root, tmp_path / "data", dataset={"dataset": "a"}, run=RunOptions(progress=False))
    assert first.ran == ["00000", "00001"]
    ledger_path(split, "import", "00001").unlink()  # the kill: 00001 was written, its entry was not
    staging = staging_path(split, "import", "00000")
    staging.mkdir(parents=True)
    (staging / "half-written.npz").write_bytes(b"x")
    stamp = (split / "00000" / "tracks.npz").stat().st_mtime_ns
    again = import_published(root, tmp_path / "data", dataset={"dataset": "a"}, run=RunOptions(progress=False))
    assert again.reused == ["00000", "00001"] and not again.ran  # 00001 adopted: same source digest
    assert not staging.exists() and (split / "00000" / "tracks.npz").stat().st_mtime_ns == stamp
    other = import_published(root, tmp_path / "data", dataset={"dataset": "b"}, run=RunOptions(progress=False))
    assert other.ran == ["00000", "00001"]
    assert json.loads((split / "00000" / "metadata.json").read_text())["source"]["dataset"] == "b"
    for name in ("masks.npz", "depth.npz", "trajectories.npz", "tracks.npz"):
        a, b = np.load(split / "00001" / name), np.load(tmp_path / "clean" / "eval" / "00001" / name)
        assert all(np.array_equal(a[k], b[k]) for k in b.files)
    assert clean.ran == ["00000", "00001"]


@pytest.mark.parametrize("damage", ["masks.npz", "depth.npz", "trajectories.npz", "metadata.json"])
def test_one_damaged_sample_fails_alone_with_its_file_named(tmp_path, damage):
    root = ps.write_set(tmp_path / "src")
    path = root / "samples" / "00001" / damage
    path.write_bytes(path.read_bytes()[: path.stat().st_size // 2])
    summary = import_published(root, tmp_path / "data", run=RunOptions(progress=False))
    assert summary.ran == ["00000", "00002"] and list(summary.failed) == ["00001"]
    assert damage in summary.failed["00001"] and "extract the archive again" in summary.failed["00001"]
    assert not (tmp_path / "data" / "eval" / "00001").exists()
    # no temporaries: only the stage ledger (which records the failure) is hidden there
    assert [p.name for p in (tmp_path / "data" / "eval").glob(".*")] == [".stages"]
    assert not (tmp_path / "data" / "eval" / ".stages" / "import" / "staging").exists()
    assert read_ledger(tmp_path / "data" / "eval", "import", "00001")["status"] == "failed"


def test_commands_refuse_the_published_layout_with_the_import_hint(published, tmp_path):
    from rigidbench.cli import main

    with pytest.raises(BundleError, match="rigidbench import"):
        resolve_split_dir(published)
    with pytest.raises(BundleError, match="rigidbench import"):
        Sample(published / "samples" / "00000")
    (tmp_path / "preds").mkdir()
    assert main(["evaluate", str(tmp_path / "preds"), "--data", str(published / "samples")]) == 2
    assert main(["validate", str(tmp_path / "preds"), "--data", str(published)]) == 2


def test_commands_that_re_simulate_refuse_imported_bundles_up_front(imported, tmp_path, capsys):
    from rigidbench.cli import main

    data, _ = imported
    assert main(["predict", "gravity", "--data", str(data), "--out", str(tmp_path / "p")]) == 2
    assert "scene spec" in capsys.readouterr().err
    assert not (tmp_path / "p").exists() or not list((tmp_path / "p").glob("*.mp4"))
    assert main(["validate-metrics", "--data", str(data), "--out", str(tmp_path / "v"), "--with-rendered",
                 "--examples", "1", "--severities", "2"]) == 2
    assert "scene spec" in capsys.readouterr().err


# -- issue 32: every frame decodes, content changes are seen, one run at a time, one source, clear errors -----


def test_a_truncated_frame_beside_a_valid_video_fails_its_sample_naming_the_file(tmp_path):
    root = ps.write_set(tmp_path / "src", ps.DEFAULT_SAMPLES[:2])
    frame = root / "samples" / "00000" / "frames" / "00007.png"  # an RGB PNG: linked, so only a decode finds it
    frame.write_bytes(frame.read_bytes()[: frame.stat().st_size * 2 // 3])
    summary = import_published(root, tmp_path / "data", run=RunOptions(progress=False))
    assert summary.ran == ["00001"] and list(summary.failed) == ["00000"]
    assert str(frame) in summary.failed["00000"] and "cannot be decoded" in summary.failed["00000"]
    assert not (tmp_path / "data" / "eval" / "00000").exists()


def test_a_same_size_change_of_a_source_file_is_imported_again(tmp_path):
    root = ps.write_set(tmp_path / "src", ps.DEFAULT_SAMPLES[:1])
    assert import_published(root, tmp_path / "data", run=RunOptions(progress=False)).ran == ["00000"]
    prompt = root / "samples" / "00000" / "prompt.txt"
    text = prompt.read_text()
    changed = text.replace("falls onto", "drops onto")
    assert changed != text and len(changed) == len(text)  # the same size: only the content tells
    prompt.write_text(changed)
    again = import_published(root, tmp_path / "data", run=RunOptions(progress=False))
    assert again.ran == ["00000"] and not again.reused
    assert Sample(tmp_path / "data" / "eval" / "00000").prompt == changed
    assert import_published(root, tmp_path / "data", run=RunOptions(progress=False)).reused == ["00000"]


def test_a_second_import_into_the_same_data_is_refused_with_one_line(tmp_path, capsys):
    import fcntl

    from rigidbench.cli import main
    from rigidbench.datasets.datadir import LOCK_FILE, DataBusyError

    root = ps.write_set(tmp_path / "src", ps.DEFAULT_SAMPLES[:1])
    data = tmp_path / "data"
    data.mkdir()
    with open(data / LOCK_FILE, "a") as running:  # what a running import or download holds
        fcntl.flock(running.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
        assert main(["import", str(root), "--data", str(data)]) == 2
        err = capsys.readouterr().err
        assert "another rigidbench download or import" in err and len(err.strip().splitlines()) == 1
        with pytest.raises(DataBusyError):
            import_published(root, data, run=RunOptions(progress=False))
        assert not (data / "eval" / "00000").exists()
    assert main(["import", str(root), "--data", str(data)]) == 0  # released: the next run goes ahead


@pytest.mark.parametrize("src_kind", ["folder", "archive"])
def test_data_naming_a_file_is_a_clear_error(tmp_path, capsys, src_kind):
    from rigidbench.cli import main

    root = ps.write_set(tmp_path / "src", ps.DEFAULT_SAMPLES[:1])
    src = root
    if src_kind == "archive":
        src = tmp_path / "set.tar.gz"
        ps.make_archive(root, src)
    (tmp_path / "afile").write_text("not a folder")
    try:  # the command line may refuse it while parsing (argparse's exit 2) or when it runs
        status = main(["import", str(src), "--data", str(tmp_path / "afile")])
    except SystemExit as exc:
        status = exc.code
    assert status == 2
    err = capsys.readouterr().err
    assert str(tmp_path / "afile") in err and "Traceback" not in err and "NotADirectoryError" not in err
    with pytest.raises(UserError, match="a file, not a folder"):
        import_published(root, tmp_path / "afile", run=RunOptions(progress=False))
    with pytest.raises(UserError, match="a part of this path is a file"):
        import_published(root, tmp_path / "afile" / "data", run=RunOptions(progress=False))


def test_parts_messages_name_what_is_missing_or_stray(tmp_path):
    from rigidbench.datasets.archive import archive_parts

    folder = tmp_path / "parts"
    folder.mkdir()
    name = "rigidbench-eval-v1.1.tar.gz.part{:02d}-of-05"
    for k in (2, 3, 4, 5):
        (folder / name.format(k)).write_bytes(b"x")
    with pytest.raises(UserError) as err:
        archive_parts(folder)
    assert "missing: 1 of 5" in str(err.value)
    (folder / name.format(1)).write_bytes(b"x")
    (folder / name.format(6)).write_bytes(b"x")  # a stray part06-of-05
    with pytest.raises(UserError) as err:
        archive_parts(folder / name.format(3))
    assert f"{name.format(6)} cannot be a part of the 5-part archive" in str(err.value)
    (folder / name.format(6)).unlink()
    (folder / "rigidbench-eval-v1.1.tar.gz.part01-of-04").write_bytes(b"x")
    with pytest.raises(UserError, match="disagree on how many there are"):
        archive_parts(folder)
    (folder / "rigidbench-eval-v1.1.tar.gz.part01-of-04").unlink()
    assert [p.name for p in archive_parts(folder)] == [name.format(k) for k in range(1, 6)]
    (folder / "other.tar.gz.part01-of-01").write_bytes(b"x")
    with pytest.raises(UserError, match="parts of 2 archives"):
        archive_parts(folder)


def test_a_corrupt_archive_during_import_says_what_import_can_do(tmp_path, capsys):
    from rigidbench.cli import main

    root = ps.write_set(tmp_path / "src", ps.DEFAULT_SAMPLES[:1])
    archive = tmp_path / "rigidbench-eval-v1.1.tar.gz"
    ps.make_archive(root, archive)
    data = archive.read_bytes()
    archive.write_bytes(data[:200] + bytes(b ^ 0x5A for b in data[200:2000]) + data[2000:])
    assert main(["import", str(archive), "--data", str(tmp_path / "data")]) == 2
    err = capsys.readouterr().err
    assert "not a readable .tar.gz" in err and "--no-verify" not in err and "fetch it again" in err
    assert len(err.strip().splitlines()) == 1


def test_an_archive_is_checked_against_its_md5_by_import(tmp_path, capsys):
    """The archive given to import is hashed while it is extracted: a mismatch is refused (the extraction is
    kept), the right description then imports it verified without extracting it again."""
    import hashlib

    from rigidbench.cli import main

    from fixtures.dataset_server import write_description

    root = ps.write_set(tmp_path / "src", ps.DEFAULT_SAMPLES[:1])
    archive = tmp_path / "test-eval-v0.1.tar.gz"
    md5 = ps.make_archive(root, archive)
    assert md5 == hashlib.md5(archive.read_bytes()).hexdigest()
    data = tmp_path / "data"
    assert main(["import", str(archive), "--data", str(data)]) == 2  # described as the packaged set: another MD5
    err = capsys.readouterr().err
    assert f"the archive's MD5 is {md5}" in err and "b563f279451e95fe2f32d7e258588636" in err
    assert not (data / "eval" / "00000").exists()
    extracted = data / ".import" / "test-eval-v0.1"
    stamp = (extracted / "rigidbench-eval-v1.1" / "manifest.json").stat().st_mtime_ns
    config = tmp_path / "config"
    write_description(config, "test-eval-v0.1", name="test-eval", version="0.1", archive=archive.name,
                      data=archive.read_bytes(), md5=md5, part_bytes=1 << 20, url="http://127.0.0.1:9/{part}")
    assert main(["--config", str(config), "import", str(archive), "--data", str(data), "--dataset", "test-eval"]) == 0
    assert (extracted / "rigidbench-eval-v1.1" / "manifest.json").stat().st_mtime_ns == stamp  # not extracted again
    source = Sample(data / "eval" / "00000").metadata["source"]
    assert (source["md5"], source["verified"]) == (md5, True) and "import checked" in source["verification"]
    # the folder import extracted, given back to import, keeps that check; any other folder is unverified
    assert main(["--config", str(config), "import", str(extracted), "--data", str(data), "--dataset",
                 "test-eval"]) == 0
    assert Sample(data / "eval" / "00000").metadata["source"]["verified"] is True
    assert main(["--config", str(config), "import", str(root), "--data", str(tmp_path / "d2"), "--dataset",
                 "test-eval"]) == 0
    assert Sample(tmp_path / "d2" / "eval" / "00000").metadata["source"]["verified"] is False
    assert "not checked (imported from an extracted folder" in capsys.readouterr().out


def test_importing_another_source_into_the_same_data_is_refused_or_replaced(tmp_path, capsys):
    from rigidbench.cli import main

    two = ps.write_set(tmp_path / "two", ps.DEFAULT_SAMPLES[:2])
    one = ps.write_set(tmp_path / "one", ps.DEFAULT_SAMPLES[:1])
    data = tmp_path / "data"
    other = {**IDENTITY, "version": "1.2", "md5": "0" * 32}
    assert import_published(two, data, dataset=IDENTITY, run=RunOptions(progress=False)).ran == ["00000", "00001"]
    assert import_published(two, data, dataset=IDENTITY, run=RunOptions(Selection.of(None, 1), progress=False)).reused == ["00000"]  # a subset
    with pytest.raises(UserError) as err:  # 00001 is not in the new source: the two sets would be mixed
        import_published(one, data, dataset=IDENTITY, run=RunOptions(progress=False))
    assert "00001" in str(err.value) and "--replace" in str(err.value) and "\n" not in str(err.value)
    with pytest.raises(UserError, match="00001"):  # another release of the same ids, only 00000 imported again
        import_published(two, data, dataset=other, run=RunOptions(Selection.of(["00000"]), progress=False))
    assert Sample(data / "eval" / "00000").metadata["source"]["version"] == "1.1"  # nothing changed
    assert main(["import", str(one), "--data", str(data)]) == 2
    assert "--replace" in capsys.readouterr().err
    summary = import_published(one, data, dataset=other, replace=True, run=RunOptions(progress=False))
    assert summary.ran == ["00000"]
    assert sorted(p.name for p in (data / "eval").iterdir() if not p.name.startswith(".")) == ["00000"]
    assert Sample(data / "eval" / "00000").metadata["source"]["version"] == "1.2"
    assert read_ledger(data / "eval", "import", "00001") is None


def test_the_import_refuses_to_start_without_the_disk_it_writes(tmp_path, monkeypatch):
    """The free-disk check counts what the import writes (depth, masks, trajectories and small files again;
    frames and video are hard-linked), before anything is written; the bundles outlive their source."""
    import shutil

    from rigidbench.stages.import_set import DISK_MARGIN_BYTES

    root = ps.write_set(tmp_path / "src", ps.DEFAULT_SAMPLES[:2])
    writes = 0
    for sample in ("00000", "00001"):
        folder = root / "samples" / sample
        writes += sum((folder / n).stat().st_size for n in ("depth.npz", "masks.npz", "trajectories.npz",
                                                            "contacts.json", "prompt.txt"))
        writes += 2 * (folder / "metadata.json").stat().st_size  # read, and kept whole inside the bundle's
    real = shutil.disk_usage
    monkeypatch.setattr(shutil, "disk_usage", lambda p: real(p)._replace(free=writes + DISK_MARGIN_BYTES - 1))
    with pytest.raises(UserError, match="not enough free disk space") as err:
        import_published(root, tmp_path / "data", run=RunOptions(progress=False))
    assert "2 sample(s)" in str(err.value)
    assert not [p for p in (tmp_path / "data" / "eval").iterdir() if not p.name.startswith(".")]
    monkeypatch.setattr(shutil, "disk_usage", lambda p: real(p)._replace(free=writes + DISK_MARGIN_BYTES))
    assert import_published(root, tmp_path / "data", run=RunOptions(progress=False)).ran == ["00000", "00001"]
    shutil.rmtree(root)  # what the README says may be deleted after the import
    for sample in ("00000", "00001"):
        bundle = tmp_path / "data" / "eval" / sample
        assert check_bundle(bundle) == [] and Sample(bundle).frames.shape == (13, 64, 96, 3)
