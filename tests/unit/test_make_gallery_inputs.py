"""scripts/make_gallery.py on unusable input: one error naming the file (or a warning naming the example),
never a silent skip. No rendering here (tests/integration/test_gallery_script.py renders)."""

from __future__ import annotations

import importlib.util
import json
import logging
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
from PIL import Image

from rigidbench.errors import UserError

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def mg():
    spec = importlib.util.spec_from_file_location("make_gallery", ROOT / "scripts" / "make_gallery.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_an_unreadable_gallery_index_names_the_file(mg, tmp_path):
    path = tmp_path / "examples.json"
    assert mg.read_index(path) == {}  # none yet: every example is rendered
    path.write_text('{"00005": {"preset": "paper"')
    with pytest.raises(UserError, match=r"examples\.json: not a readable gallery index"):
        mg.read_index(path)
    path.write_text("[1, 2]")
    with pytest.raises(UserError, match=r"examples\.json: .*found a list"):
        mg.read_index(path)
    path.write_text('{"00005": "paper"}')
    with pytest.raises(UserError, match=r"examples\.json: entry 00005 is a str"):
        mg.read_index(path)


def test_an_index_entry_without_its_facts_is_rendered_again_with_a_warning(mg, tmp_path, caplog):
    row, preset = SimpleNamespace(sample_id="00005"), SimpleNamespace(name="test")
    entry = {"sample_id": "00005", "task": "bounce", "scene": "modern_loft", "surface": "counter",
             "partition": "in_distribution", "preset": "test", "events": [[0, "release"]],
             "camera": {"azimuth_deg": 0.0, "distance_m": 2.0}}  # no target_m
    with caplog.at_level(logging.WARNING, logger="make_gallery"):
        assert not mg.committed_is_current(row, None, preset, tmp_path, {"00005": entry}, ["task_bounce"])
    assert "00005" in caplog.text and "camera.target_m" in caplog.text


def _render_dir(tmp_path: Path) -> Path:
    done = tmp_path / "00005"
    (done / "frames").mkdir(parents=True)
    info = {"sample_id": "00005", "task": "bounce", "scene": "modern_loft", "surface": "counter",
            "partition": "in_distribution", "prompt": "p", "fps": 24.0, "frames": [0], "events": [[0, "release"]],
            "legend": ["baseball_0: baseball (active)"], "preset": "test", "camera": {}}
    (done / "info.json").write_text(json.dumps(info))
    Image.fromarray(np.zeros((8, 8, 3), np.uint8)).save(done / "frames" / "00000.png")
    np.savez_compressed(done / "gt.npz", masks=np.zeros((1, 1, 8, 8), bool), depth=np.ones((1, 8, 8), np.float32),
                        tracks=np.zeros((1, 1, 2)), visibility=np.ones((1, 1), bool), actor_index=np.zeros(1, int))
    return done


def test_a_damaged_cached_render_names_its_file_and_the_fix(mg, tmp_path):
    done = _render_dir(tmp_path)
    info, gt, frames = mg.read_render(done)
    assert info["frames"] == [0] and set(frames) == {0} and gt["masks"].shape == (1, 1, 8, 8)

    (done / "gt.npz").write_bytes((done / "gt.npz").read_bytes()[:40])  # truncated
    with pytest.raises(UserError, match=r"gt\.npz: the cached render of example 00005 cannot be read .*delete"):
        mg.read_render(done)
    done = _render_dir(tmp_path / "again")
    (done / "frames" / "00000.png").unlink()
    with pytest.raises(UserError, match=r"00000\.png: the cached render of example 00005"):
        mg.read_render(done)
    info = json.loads((done / "info.json").read_text())
    del info["legend"]
    (done / "info.json").write_text(json.dumps(info))
    with pytest.raises(UserError, match=r"info\.json: .*no legend"):
        mg.read_render(done)


def test_a_missing_before_input_is_refused_up_front(mg, tmp_path, capsys):
    with pytest.raises(SystemExit) as exit_info:
        mg.main(["--before-objects", str(tmp_path / "old_objects.png"), "--work", str(tmp_path)])
    assert exit_info.value.code == 2 and "old_objects.png: no such file" in capsys.readouterr().err
    with pytest.raises(SystemExit) as exit_info:
        mg.main(["--before-data", str(tmp_path / "old_eval"), "--work", str(tmp_path)])
    assert exit_info.value.code == 2 and "old_eval: not a directory of bundles" in capsys.readouterr().err
