"""Every file and folder a run writes gets the mode the user's umask gives a new one, whatever its kind
(issue 33, item 8): 0644 and 0755 under umask 022, 0600 and 0700 under 077. Temporaries made by mkstemp and
mkdtemp are private to their owner, and some writers (PyAV, safetensors) make their own files: no kind of
output may keep such a mode, or come out more open than the umask allows.

One small run of every stage that writes without Blender: a .tar.gz extracted and imported (bundles,
videos, inputs.jsonl), manifest, predict with a failure mode (videos, state) and with a stand-in hosted
model (downloads), evaluate and report (tables, figures, filmstrip clips); plus the two temporary-making
helpers directly (a video, a unique directory).
"""

from __future__ import annotations

import os
import stat
from pathlib import Path

import numpy as np
import pytest


from fixtures import published_set as ps  # noqa: E402
from fixtures.replicate_server import TOKEN, make_split  # noqa: E402,F401
from fixtures.replicate_server import server, video  # noqa: E402,F401 (pytest fixtures)

from rigidbench.atomic import atomic_dir  # noqa: E402
from rigidbench.cli import main  # noqa: E402
from rigidbench.datasets.extract import safe_extract  # noqa: E402
from rigidbench.video import write_video  # noqa: E402


def _modes(root: Path) -> dict[str, set[Path]]:
    """Every file and folder under ``root`` (not ``root`` itself), by mode; symbolic links are not counted."""
    found: dict[str, set[Path]] = {}
    for path in root.rglob("*"):
        st = path.lstat()
        if stat.S_ISLNK(st.st_mode):
            continue
        kind = "dir" if stat.S_ISDIR(st.st_mode) else "file"
        found.setdefault(f"{kind} {stat.S_IMODE(st.st_mode):o}", set()).add(path)
    return found


@pytest.fixture
def umask(request):
    old = os.umask(request.param)
    yield request.param
    os.umask(old)


@pytest.mark.parametrize("umask", [0o022, 0o077], indirect=True, ids=["umask-022", "umask-077"])
def test_every_file_a_small_run_writes_gets_the_umask_mode(tmp_path, umask, server):
    given = tmp_path / "given"  # what the test hands in (an archive of the published layout), not checked
    ps.write_set(given / "set", [s for s in ps.DEFAULT_SAMPLES if not s.rgba])
    ps.make_archive(given / "set", given / "set.tar.gz")
    out = tmp_path / "out"
    data, preds, run = out / "data", out / "predictions", out / "run"
    extracted = safe_extract([given / "set.tar.gz"], out / "extracted")
    assert main(["import", str(extracted), "--data", str(data)]) == 0
    assert main(["manifest", "--split", "eval", "--out", str(out / "eval.jsonl")]) == 0
    assert main(["predict", "reference", "--data", str(data), "--out", str(preds)]) == 0
    assert main(["evaluate", str(preds), "--data", str(data), "--out", str(run)]) == 0
    if umask == 0o077:  # (slow) its clips were given 0644 whatever the umask; under 022 that is the umask's mode
        assert main(["report", str(run), "--out", str(out / "report"), "--resamples", "20", "--examples", "1"]) == 0
    hosted = make_split(given / "hosted" / "eval", 1)
    config = tmp_path / "given" / "config"
    config.mkdir()
    assert main(["--config", str(config), "predict", "grok-imagine", "--data", str(hosted), "--out",
                 str(out / "hosted"), "--concurrency", "1"]) == 0
    write_video(out / "clip.mp4", np.zeros((4, 16, 16, 3), np.uint8), fps=24.0)
    with atomic_dir(out / "unique", unique=True) as tmp:
        (tmp / "inside.json").write_text("{}")

    modes = _modes(out)
    expected = {f"file {0o666 & ~umask:o}", f"dir {0o777 & ~umask:o}"}
    assert set(modes) == expected, {m: sorted(str(p.relative_to(out)) for p in paths)[:8]
                                     for m, paths in modes.items() if m not in expected}
    # each kind of output was there to be checked
    files = {p.relative_to(out).as_posix() for p in modes[f"file {0o666 & ~umask:o}"]}
    for made in ("data/eval/00000/video.mp4", "data/eval/00000/masks.npz", "data/eval/00000/metadata.json",
                 "data/eval/00000/frames/00000.png", "data/inputs.jsonl", "eval.jsonl",
                 "predictions/00000.mp4", "predictions/00000.state.npz", "predictions/generation.json",
                 "predictions/.stages/predict/00000.json", "run/results.json", "run/examples/00000.npz",
                 "run/examples/00000.readouts.json", "hosted/00000.mp4", "clip.mp4", "unique/inside.json"):
        assert made in files, made
    if umask == 0o077:
        assert "report/report.html" in files
        assert any(f.startswith("report/examples/") and f.endswith(".mp4") for f in files), "no filmstrip clip"
    assert any(f.startswith("extracted/") and f.endswith(".npz") for f in files), "no extracted file"
