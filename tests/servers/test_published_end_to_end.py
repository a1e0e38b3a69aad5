"""The README's path for the published set, end to end on a synthetic archive served from 127.0.0.1:
download (cut mid-part, resumed) -> import -> inputs.jsonl -> predict reference -> validate -> evaluate,
to a results.json that names the dataset, its version and the protocol."""

from __future__ import annotations

import hashlib
import html
import json
import shutil

import numpy as np
import pytest


from fixtures import published_set as ps  # noqa: E402
from fixtures.dataset_server import StandInDatasetServer, split, write_description  # noqa: E402

from rigidbench.cli import main  # noqa: E402
from rigidbench.groundtruth.bundle import Sample, check_bundle  # noqa: E402
from rigidbench.report import build_report  # noqa: E402
from rigidbench.report.load import read_run  # noqa: E402

PART_BYTES = 40_000


@pytest.fixture
def no_proxy(monkeypatch):
    for var in ("HTTP_PROXY", "HTTPS_PROXY", "ALL_PROXY", "http_proxy", "https_proxy", "all_proxy"):
        monkeypatch.delenv(var, raising=False)


@pytest.fixture
def served(tmp_path, no_proxy):
    root = ps.write_set(tmp_path / "authors" / "set")
    archive = tmp_path / "authors" / "test-eval-v0.1.tar.gz"
    md5 = ps.make_archive(root, archive)
    data = archive.read_bytes()
    parts = split(data, PART_BYTES, archive.name)
    assert len(parts) >= 3
    with StandInDatasetServer(parts) as server:
        config = tmp_path / "config"
        write_description(config, "test-eval-v0.1", name="test-eval", version="0.1", archive=archive.name, data=data,
                          md5=md5, part_bytes=PART_BYTES, url=server.url_template)
        yield server, config, md5, list(parts)


def ate3d_floor(sample: Sample) -> float:
    """ATE-3D of a perfect clip, from the bundle alone: the median of each actor's visible tracked
    surface points (unprojected from the tracks and the Z pass) against its body origin, RMS over
    actor-frames, divided by the mean start-to-end displacement of moving actors."""
    from rigidbench.groundtruth.camera_model import unproject
    from rigidbench.metrics.common import geometric_median

    tracks, vis, actor = sample.tracks.tracks_px, sample.tracks.visibility, sample.track_active_index
    R_c, t_c = sample.camera_pose
    positions = sample.trajectory.positions_m[sample.active_indices]
    errors = []
    for t in range(sample.n_frames):
        for a in range(len(positions)):
            mine = (actor == a) & vis[:, t]
            if not mine.any():
                continue
            uv = tracks[mine, t].astype(np.float64)
            z = np.array([sample.depth[t, int(round(v)), int(round(u))] for u, v in uv])
            # bilinear depth at sub-pixel track positions differs from the nearest pixel by < 1 mm here
            errors.append(np.sum((geometric_median(unproject(uv, z, sample.K, R_c, t_c)) - positions[a, t]) ** 2))
    displacement = np.linalg.norm(positions[:, -1] - positions[:, 0], axis=-1)
    return float(np.sqrt(np.mean(errors)) / displacement[displacement > 0.01].mean())


def test_from_a_url_to_results_that_name_the_dataset(served, tmp_path, monkeypatch, capsys):
    server, config, md5, parts = served
    monkeypatch.chdir(tmp_path)
    server.cut[parts[1]] = [5000]  # the connection drops inside the second part: resumed with Range
    assert main(["--config", str(config), "download", "--data", "data", "--dataset", "test-eval"]) == 0
    assert server.bytes_served() < sum(PART_BYTES for _ in parts) + 5000 + 1
    bundles = sorted(p.name for p in (tmp_path / "data" / "eval").iterdir() if p.name != ".stages")  # .stages: ledger
    assert bundles == ["00000", "00001", "00002"]
    meta = Sample(tmp_path / "data" / "eval" / "00000").metadata
    assert meta["source"]["dataset"] == "test-eval" and meta["source"]["md5"] == md5
    assert meta["source"]["verified"] is True and "download checked the MD5" in meta["source"]["verification"]

    # inputs.jsonl: the release's keys, images relative to the file's folder
    rows = [json.loads(line) for line in (tmp_path / "data" / "inputs.jsonl").read_text().splitlines()]
    assert [r["id"] for r in rows] == ["00000", "00001", "00002"]
    assert all((tmp_path / "data" / r["image"]).is_file() for r in rows)

    # a rerun makes no request and changes nothing
    before = server.requests()
    assert main(["--config", str(config), "download", "--data", "data", "--dataset", "test-eval"]) == 0
    assert server.requests() == before
    # its extraction given to import keeps the download's check: the same identity, nothing imported again
    extracted = tmp_path / "data" / ".download" / "test-eval-v0.1" / "extracted"
    capsys.readouterr()
    assert main(["--config", str(config), "import", str(extracted), "--data", "data", "--dataset", "test-eval"]) == 0
    assert "import: 0 made, 3 up to date, 0 failed of 3 example(s)" in capsys.readouterr().out
    assert Sample(tmp_path / "data" / "eval" / "00000").metadata["source"]["verified"] is True
    # the extraction may be deleted after the import (README): the bundles keep their files, nothing is fetched
    shutil.rmtree(extracted)
    assert main(["--config", str(config), "download", "--data", "data", "--dataset", "test-eval"]) == 0
    assert server.requests() == before and check_bundle(tmp_path / "data" / "eval" / "00001") == []

    assert main(["predict", "reference", "--data", "data", "--out", "predictions/reference"]) == 0
    assert main(["validate", "predictions/reference", "--data", "data"]) == 0
    assert main(["evaluate", "predictions/reference", "--data", "data", "--perception", "gt", "--out",
                 "runs/reference"]) == 0
    results = json.loads((tmp_path / "runs" / "reference" / "results.json").read_text())
    assert results["dataset"] == {"dataset": "test-eval", "version": "0.1", "md5": md5, "verified": True,
                                  "verification": "rigidbench download checked the MD5 of the parts it fetched"}
    assert not any("MD5" in reason for reason in results.get("why_not_official", []))
    assert results["protocol"]["name"] == "rigidbench-v1" and results["protocol"]["jpeg_quality"] == 95
    overall = results["overall"]
    assert overall["iou"]["mean"] == 1.0 and overall["ate"]["mean"] == pytest.approx(0.0, abs=1e-9)
    floor = np.mean([ate3d_floor(Sample(tmp_path / "data" / "eval" / i)) for i in ("00000", "00001", "00002")])
    assert floor > 0.01 and overall["ate3d"]["mean"] == pytest.approx(floor, rel=0.05)
    run = json.loads((tmp_path / "runs" / "reference" / "run.json").read_text())
    assert run["dataset"]["version"] == "0.1" and run["protocol"]["name"] == "rigidbench-v1"


def test_import_by_hand_from_the_parts_or_the_archive(tmp_path, monkeypatch):
    root = ps.write_set(tmp_path / "set", ps.DEFAULT_SAMPLES[:1])
    archive = tmp_path / "dl" / "rigidbench-eval-v1.1.tar.gz"
    archive.parent.mkdir()
    md5 = ps.make_archive(root, archive)
    config = tmp_path / "config"  # the description of this archive (its MD5): import checks the archive against it
    write_description(config, "test-eval-v0.1", name="test-eval", version="0.1", archive=archive.name,
                      data=archive.read_bytes(), md5=md5, part_bytes=15_000, url="http://127.0.0.1:9/{part}")
    monkeypatch.chdir(tmp_path)
    described = ["--config", str(config), "import"]
    assert main(described + [str(archive), "--data", "a", "--dataset", "test-eval"]) == 0
    assert (tmp_path / "a" / "eval" / "00000" / "tracks.npz").is_file()
    names = [name for name, _ in ps.split_parts(archive, tmp_path / "parts", 15_000)]
    assert len(names) >= 3
    assert main(described + [str(tmp_path / "parts"), "--data", "b", "--dataset", "test-eval"]) == 0
    assert main(described + [str(tmp_path / "set"), "--data", "c", "--dataset", "test-eval"]) == 0
    source = Sample(tmp_path / "b" / "eval" / "00000").metadata["source"]
    assert source["verified"] is True and "import checked the MD5" in source["verification"]
    source = Sample(tmp_path / "c" / "eval" / "00000").metadata["source"]
    assert source["verified"] is False and "extracted folder" in source["verification"]
    # a result on an unverified set is never official, and the report's header says so
    assert main(["predict", "reference", "--data", "c", "--out", "predictions/c"]) == 0
    assert main(["evaluate", "predictions/c", "--data", "c", "--perception", "gt", "--out", "runs/c"]) == 0
    results = json.loads((tmp_path / "runs" / "c" / "results.json").read_text())
    assert results["dataset"]["verified"] is False and results["official"] is False
    reason = next(r for r in results["why_not_official"] if "MD5" in r)
    assert "test-eval 0.1 was not checked against its published MD5" in reason
    page = build_report([tmp_path / "runs" / "c"], tmp_path / "report", resamples=100, seed=0, examples=0)
    header = html.unescape(page.read_text().split("<h2")[0])
    assert "reference set test-eval 0.1 (MD5 not verified)" in header and reason in header
    # a results.json written before verification was recorded may say official: the report does not repeat it
    results.update(official=True, why_not_official=[], dataset={"dataset": "test-eval", "version": "0.1", "md5": md5})
    (tmp_path / "runs" / "c" / "results.json").write_text(json.dumps(results))
    info, _ = read_run(tmp_path / "runs" / "c")
    assert info.official is False and "not checked against its published MD5" in info.why_not_official[0]
    digest = {d: hashlib.sha256((tmp_path / d / "eval" / "00000" / "tracks.npz").read_bytes()).hexdigest()
              for d in "abc"}
    assert len(set(digest.values())) == 1
    (tmp_path / "parts" / names[1]).unlink()
    assert main(["import", str(tmp_path / "parts"), "--data", "d"]) == 2  # a gap in the parts: one clear line
