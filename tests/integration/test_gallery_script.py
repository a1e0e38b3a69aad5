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
