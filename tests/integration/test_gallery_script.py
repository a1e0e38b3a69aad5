"""scripts/make_gallery.py end to end on one example and the objects, at the `test` preset."""

from __future__ import annotations

import importlib.util
import io
import json
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("bpy", reason="bpy (Blender as a Python module) is not installed; run `make test`, which installs it")

from PIL import Image  # noqa: E402

from rigidbench import manifest  # noqa: E402


ROOT = Path(__file__).resolve().parents[2]


def _script():
    spec = importlib.util.spec_from_file_location("make_gallery", ROOT / "scripts" / "make_gallery.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_event_frames_are_rendered_and_drawn(tmp_path, reg):
    mg = _script()
    assert mg.main(["--quality", "test", "--only", "00005", "--render-only", "--work", str(tmp_path)]) == 0
    done = tmp_path / "00005"
    info = json.loads((done / "info.json").read_text())
    assert info["task"] == "bounce" and info["events"][0] == [0, "release"]
    # RGB exists for exactly the event frames, in order
    assert sorted(int(p.stem) for p in (done / "frames").glob("*.png")) == info["frames"] == sorted(info["frames"])
    gt = np.load(done / "gt.npz")
    T = reg.preset("test").frames
    assert gt["masks"].shape[0] == len(info["frames"]) and gt["tracks"].shape[1] == T
    assert gt["masks"].any()
    # a rerun reuses the finished example instead of rendering it again
    before = (done / "info.json").stat().st_mtime_ns
    assert mg.main(["--quality", "test", "--only", "00005", "--render-only", "--work", str(tmp_path)]) == 0
    assert (done / "info.json").stat().st_mtime_ns == before
    data, _ = mg.example_sheet_bytes(done)
    assert len(data) <= mg.MAX_BYTES
    sheet = Image.open(io.BytesIO(data))
    assert sheet.format == "JPEG" and sheet.mode == "RGB" and sheet.width >= 3 * 640

    # writing the gallery: the sheet, examples.json (events and camera) and a README naming the rest
    out = tmp_path / "gallery"
    assert mg.main(["--quality", "test", "--only", "00005", "--partial", "--work", str(tmp_path),
                    "--out", str(out)]) == 0
    written = out / f"task_{info['task']}.jpg"
    assert Image.open(written).format == "JPEG"
    index = json.loads((out / "examples.json").read_text())
    assert set(index) == {"00005"}
    assert index["00005"]["events"] == info["events"] and index["00005"]["preset"] == "test"
    assert set(index["00005"]["camera"]) >= {"azimuth_deg", "distance_m", "target_m", "visibility"}
    readme = (out / "README.md").read_text()
    assert "| bounce | 00005 |" in readme and "Not rendered yet" in readme

    # a later run with an empty --work keeps the committed sheet: same preset, and the search still
    # picks the recorded camera (checked without rendering)
    fresh_work = tmp_path / "fresh_work"
    sheet_bytes = written.read_bytes()
    assert mg.main(["--quality", "test", "--only", "00005", "--partial", "--work", str(fresh_work),
                    "--out", str(out)]) == 0
    assert not (fresh_work / "00005").exists() and written.read_bytes() == sheet_bytes
    assert json.loads((out / "examples.json").read_text()) == index
    # --fresh renders it again whatever --out holds (the render, not the sheet, is reused from --work)
    assert mg.main(["--quality", "test", "--only", "00005", "--fresh", "--render-only", "--work", str(fresh_work),
                    "--out", str(out)]) == 0
    assert (fresh_work / "00005" / "info.json").exists()
    # ... but not when the recorded camera, the preset or the sheet differ
    row = next(r for r in manifest.rows("eval", reg) if r.sample_id == "00005")
    prefixes = [f"task_{info['task']}"]
    assert mg.committed_is_current(row, reg, reg.preset("test"), out, index, prefixes)
    moved = json.loads(json.dumps(index))
    moved["00005"]["camera"]["azimuth_deg"] += 15.0
    assert not mg.committed_is_current(row, reg, reg.preset("test"), out, moved, prefixes)
    assert not mg.committed_is_current(row, reg, reg.preset("preview"), out, index, prefixes)
    assert not mg.committed_is_current(row, reg, reg.preset("test"), out, index, [*prefixes, "scene_nowhere"])
    with pytest.raises(SystemExit):  # an id that is not a gallery example is refused up front
        mg.main(["--quality", "test", "--only", "99999", "--work", str(fresh_work)])


def test_objects_sheet_shows_every_object(tmp_path, reg):
    mg = _script()
    assert mg.main(["--quality", "test", "--only", "objects", "--render-only", "--work", str(tmp_path)]) == 0
    tiles = sorted(p.stem for p in (tmp_path / "objects").glob("*.png"))
    assert tiles == sorted(reg.objects)
    for oid in ("tomato", "lemon"):  # each tile is centred on its object: the centre differs from the floor
        img = np.asarray(Image.open(tmp_path / "objects" / f"{oid}.png").convert("RGB"), float)
        h, w = img.shape[:2]
        centre = img[h // 2 - 5:h // 2 + 5, w // 2 - 5:w // 2 + 5].mean((0, 1))
        corner = img[:10, :10].mean((0, 1))
        assert np.abs(centre - corner).max() > 40, oid
    data = mg.objects_sheet_bytes(reg, tmp_path / "objects", reg.preset("test"))
    assert len(data) <= mg.MAX_BYTES
