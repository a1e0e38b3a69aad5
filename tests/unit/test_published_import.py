"""Importing the published evaluation set: a tiny synthetic set in the published layout
(tests/fixtures/published_set.py) becomes bundles our commands read, with ground-truth tracks by the
released evaluator's rule, resumably, and one damaged sample never stops the others."""

from __future__ import annotations

import json
import os
import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "fixtures"))

import published_set as ps  # noqa: E402

from rigidbench.config import registry  # noqa: E402
from rigidbench.driver import ledger_path, read_ledger, staging_path  # noqa: E402
from rigidbench.datasets.importer import find_published_root, import_published  # noqa: E402
from rigidbench.errors import BundleError, UserError  # noqa: E402
from rigidbench.groundtruth.bundle import Sample, check_bundle, resolve_split_dir  # noqa: E402

IDENTITY = {"dataset": "rigidbench-eval", "version": "1.1", "md5": "b563f279451e95fe2f32d7e258588636"}


@pytest.fixture(scope="module")
def published(tmp_path_factory):
    root = tmp_path_factory.mktemp("published") / "rigidbench-eval-v1.1"
    return ps.write_set(root)


@pytest.fixture(scope="module")
def imported(published, tmp_path_factory):
    data = tmp_path_factory.mktemp("data")
    summary = import_published(published.parent, data, dataset=IDENTITY, registry=registry(), progress=False)
    return data, summary


def test_every_sample_becomes_a_valid_bundle(imported):
    data, summary = imported
    assert summary.imported == ["00000", "00001", "00002"] and not summary.failed
    for sample_id in summary.imported:
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


def test_frames_are_linked_converted_or_decoded(imported, published):
    from PIL import Image

    data, _ = imported
    linked = data / "eval" / "00000" / "frames" / "00003.png"
    assert os.path.samefile(linked, published / "samples" / "00000" / "frames" / "00003.png")
    for sample_id in ("00001", "00002"):  # RGBA PNGs converted; no frames/ at all: decoded from video.mp4
        with Image.open(data / "eval" / sample_id / "frames" / "00000.png") as im:
            assert im.mode == "RGB" and im.size == (96, 64)
    rgba = np.asarray(Image.open(published / "samples" / "00001" / "frames" / "00005.png").convert("RGB"))
    np.testing.assert_array_equal(Sample(data / "eval" / "00001").frame(5), rgba)
    decoded = Sample(data / "eval" / "00002").frame(0).astype(int)
    assert decoded.std() > 10  # a real picture, not a blank


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
    summary = import_published(tmp_path / "a", tmp_path / "data", progress=False)
    assert summary.imported == ["00000"] and check_bundle(tmp_path / "data" / "eval" / "00000") == []
    with pytest.raises(UserError, match="no published RigidBench evaluation set"):
        find_published_root(tmp_path / "data")


def test_a_rerun_skips_unchanged_and_redoes_changed_samples(tmp_path):
    root = ps.write_set(tmp_path / "src", ps.DEFAULT_SAMPLES[:2])
    first = import_published(root, tmp_path / "data", progress=False)
    assert first.imported == ["00000", "00001"]
    stamp = (tmp_path / "data" / "eval" / "00000" / "tracks.npz").stat().st_mtime_ns
    prompt = root / "samples" / "00001" / "prompt.txt"
    prompt.write_text("A different prompt for this sample.")
    (tmp_path / "data" / "eval" / ".00000.tmp").mkdir()  # left by a killed import
    second = import_published(root, tmp_path / "data", progress=False)
    assert second.unchanged == ["00000"] and second.imported == ["00001"]
    assert (tmp_path / "data" / "eval" / "00000" / "tracks.npz").stat().st_mtime_ns == stamp
    assert Sample(tmp_path / "data" / "eval" / "00001").prompt == "A different prompt for this sample."
    assert not (tmp_path / "data" / "eval" / ".00000.tmp").exists()


def test_import_resumes_on_the_stage_driver(tmp_path):
    """A killed import (staging left behind, one sample without its ledger entry) resumes; another dataset
    identity re-imports every sample and says why; a bundle imported before ledgers existed is adopted."""
    root = ps.write_set(tmp_path / "src", ps.DEFAULT_SAMPLES[:2])
    split = tmp_path / "data" / "eval"
    clean = import_published(root, tmp_path / "clean", progress=False)
    first = import_published(root, tmp_path / "data", progress=False, dataset={"dataset": "a"})
    assert first.imported == ["00000", "00001"]
    ledger_path(split, "import", "00001").unlink()  # the kill: 00001 was written, its entry was not
    staging = staging_path(split, "import", "00000")
    staging.mkdir(parents=True)
    (staging / "half-written.npz").write_bytes(b"x")
    stamp = (split / "00000" / "tracks.npz").stat().st_mtime_ns
    again = import_published(root, tmp_path / "data", progress=False, dataset={"dataset": "a"})
    assert again.unchanged == ["00000", "00001"] and not again.imported  # 00001 adopted: same source digest
    assert not staging.exists() and (split / "00000" / "tracks.npz").stat().st_mtime_ns == stamp
    other = import_published(root, tmp_path / "data", progress=False, dataset={"dataset": "b"})
    assert other.imported == ["00000", "00001"]
    assert json.loads((split / "00000" / "metadata.json").read_text())["source"]["dataset"] == "b"
    for name in ("masks.npz", "depth.npz", "trajectories.npz", "tracks.npz"):
        a, b = np.load(split / "00001" / name), np.load(tmp_path / "clean" / "eval" / "00001" / name)
        assert all(np.array_equal(a[k], b[k]) for k in b.files)
    assert clean.imported == ["00000", "00001"]


@pytest.mark.parametrize("damage", ["masks.npz", "depth.npz", "trajectories.npz", "metadata.json"])
def test_one_damaged_sample_fails_alone_with_its_file_named(tmp_path, damage):
    root = ps.write_set(tmp_path / "src")
    path = root / "samples" / "00001" / damage
    path.write_bytes(path.read_bytes()[: path.stat().st_size // 2])
    summary = import_published(root, tmp_path / "data", progress=False)
    assert summary.imported == ["00000", "00002"] and list(summary.failed) == ["00001"]
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
