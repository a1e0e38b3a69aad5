"""Render and simulate on the stage driver (issue 25): a rerun skips every example, changed settings redo
exactly the examples they change and say why, a killed run resumes from the examples it had not committed
(and gives what a clean run gives), and outputs made before ledgers existed are taken over, not made again.

Two one-object free-fall examples at the `test` preset: 00015 (a pomegranate) and 00019 (a food can), so an
edited pomegranate changes one of them only.
"""

from __future__ import annotations

import dataclasses
import json
import os
import shutil
import sys
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pytest
import yaml

from fixtures.blender import requires_bpy
from fixtures.children import kill_when

from rigidbench import manifest
from rigidbench.cli import main
from rigidbench.config import PACKAGE_CONFIG_DIR, registry as load_registry
from rigidbench.driver import RunOptions, Why, ledger_path, read_ledger, staging_path
from rigidbench.executors import LocalExecutor, ProcessExecutor
from rigidbench.groundtruth import bundle as B
from rigidbench.stages.render import RenderStage, render_rows, render_stage
from rigidbench.stages.simulate import SimulateStage, simulate_rows, simulate_stage

pytestmark = [pytest.mark.integration, requires_bpy]

QUALITY = "test"
IDS = ("00015", "00019")
CHANGED = "00015"  # the pomegranate's example
SRC = str(Path(__file__).resolve().parents[2] / "src")
VOLATILE_METADATA = ("render", "render_seconds", "software")  # timings, thread counts, versions
ARRAYS = ("trajectories.npz", "masks.npz", "depth.npz", "tracks.npz")


@dataclass
class RecordingProcesses(ProcessExecutor):
    """The render stage's executor, remembering which examples it was asked to run."""

    seen: list = field(default_factory=list)

    def map(self, worker, job, items, *args, **kwargs):
        self.seen += [task["id"] for task in items]
        return super().map(worker, job, items, *args, **kwargs)


@dataclass
class RecordingLocal(LocalExecutor):
    seen: list = field(default_factory=list)

    def map(self, worker, job, items, *args, **kwargs):
        self.seen += [task["id"] for task in items]
        return super().map(worker, job, items, *args, **kwargs)


@pytest.fixture(scope="module")
def reg():
    return load_registry()


@pytest.fixture(scope="module")
def rows(reg):
    return manifest.select(manifest.eval_rows(reg), list(IDS))


@pytest.fixture(scope="module")
def clean(rows, reg, tmp_path_factory):
    """A data root with both examples rendered by one uninterrupted run (each in a child process)."""
    data = tmp_path_factory.mktemp("clean")
    [report] = render_rows(rows, reg, data, quality=QUALITY, run=RunOptions(progress=False))
    assert report.ran == list(IDS) and not report.failed
    return data


@pytest.fixture
def edited_pomegranate(tmp_path):
    """A configuration directory in which the pomegranate bounces more (restitution 0.15 -> 0.45)."""
    entry = yaml.safe_load((PACKAGE_CONFIG_DIR / "objects" / "pomegranate.yaml").read_text())
    assert entry["physics"]["restitution"] != 0.45
    entry["physics"]["restitution"] = 0.45
    (tmp_path / "cfg" / "objects").mkdir(parents=True)
    (tmp_path / "cfg" / "objects" / "pomegranate.yaml").write_text(yaml.safe_dump(entry))
    return tmp_path / "cfg"


def mtimes(root: Path) -> dict[str, int]:
    """Modification time of every file under ``root`` (bundles and ledgers), by relative path."""
    return {p.relative_to(root).as_posix(): p.stat().st_mtime_ns for p in sorted(root.rglob("*")) if p.is_file()}


def arrays(path: Path) -> dict:
    with np.load(path) as z:
        return {k: z[k] for k in z.files}


def assert_same_bundle(ours: Path, theirs: Path) -> None:
    """The same example: spec, metadata (but timings and versions), trajectories, masks, depth and tracks."""
    assert B.check_bundle(ours) == []
    meta = [{k: v for k, v in json.loads((p / B.METADATA_FILE).read_text()).items() if k not in VOLATILE_METADATA}
            for p in (ours, theirs)]
    assert meta[0] == meta[1]
    assert json.loads((ours / B.SPEC_FILE).read_text()) == json.loads((theirs / B.SPEC_FILE).read_text())
    for name in ARRAYS:
        a, b = arrays(ours / name), arrays(theirs / name)
        assert a.keys() == b.keys()
        for key in a:
            np.testing.assert_array_equal(a[key], b[key], err_msg=f"{ours.name}/{name}/{key}")


def restitution_of(bundle: Path, asset: str) -> float:
    spec = json.loads((bundle / B.SPEC_FILE).read_text())
    return next(b["physics"]["restitution"] for b in spec["bodies"] if b["asset"] == asset)


# -- the key ---------------------------------------------------------------------------------------------


def test_the_render_key_is_the_spec_configuration_and_preset_not_the_device(reg, rows, tmp_path, edited_pomegranate):
    def keys(registry, quality=QUALITY, **kw):
        stage = RenderStage(tmp_path, "eval", rows, registry, quality, **kw)
        return {i: stage.key(i, p) for i, p in stage.items().items()}

    base = keys(reg)
    assert len(set(base.values())) == 2
    assert keys(reg, device="cpu", threads=3, config_dirs=[tmp_path]) == base  # how, not what, is rendered
    assert all(base[i] != k for i, k in keys(reg, "preview").items())
    test = reg.preset(QUALITY)
    fewer = dataclasses.replace(reg, presets={**reg.presets, QUALITY: dataclasses.replace(test, samples=1)})
    kept = dataclasses.replace(reg, presets={**reg.presets, QUALITY: dataclasses.replace(
        test, persistent_data=not test.persistent_data)})
    assert all(base[i] != k for i, k in keys(fewer).items()) and keys(kept) == base
    edited = keys(load_registry([edited_pomegranate]))
    assert edited[CHANGED] != base[CHANGED] and edited["00019"] == base["00019"]
    # a user mesh is keyed by its content, not its path
    mesh = tmp_path / "mesh" / "objects" / "pomegranate.obj"
    mesh.parent.mkdir(parents=True)
    mesh.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n")
    entry = yaml.safe_load((PACKAGE_CONFIG_DIR / "objects" / "pomegranate.yaml").read_text())
    (mesh.parent / "pomegranate.yaml").write_text(yaml.safe_dump({**entry, "mesh": "pomegranate.obj"}))
    first = keys(load_registry([mesh.parent.parent]))
    mesh.write_text("v 0 0 0\nv 2 0 0\nv 0 2 0\nf 1 2 3\n")  # same path, new content
    second = keys(load_registry([mesh.parent.parent]))
    assert first[CHANGED] != base[CHANGED] and second[CHANGED] != first[CHANGED]
    assert first["00019"] == second["00019"] == base["00019"]


# -- render -----------------------------------------------------------------------------------------------


def test_a_rerun_renders_nothing_and_touches_nothing(clean, rows, reg):
    before = mtimes(clean)
    stage = RenderStage(clean, "eval", rows, reg, QUALITY)
    executor = RecordingProcesses()
    report = render_stage(stage, RunOptions(executor=executor, progress=False))
    assert executor.seen == [] and report.ran == [] and report.reused == list(IDS) and not report.redone
    assert mtimes(clean) == before
    for sample_id in IDS:
        entry = read_ledger(clean / "eval", "render", sample_id)
        assert entry["status"] == "succeeded" and entry["key"] == stage.key(sample_id, None)
        assert entry["result"]["preset"] == QUALITY and entry["result"]["frames"] == reg.preset(QUALITY).frames


def test_an_edited_object_renders_again_exactly_its_examples(clean, tmp_path, edited_pomegranate, capsys):
    data = tmp_path / "data"
    shutil.copytree(clean, data)
    before = mtimes(data / "eval" / "00019")
    argv = ["--config", str(edited_pomegranate), "render", "--split", "eval", "--ids", *IDS, "--quality", QUALITY,
            "--data", str(data), "--no-progress"]
    assert main(argv) == 0
    out = capsys.readouterr().out
    assert f"render: 1 made, 1 up to date, 0 failed of 2 example(s) -> {data / 'eval'}" in out
    assert f"  made again, its inputs or settings changed: {CHANGED}" in out
    assert mtimes(data / "eval" / "00019") == before
    assert restitution_of(data / "eval" / CHANGED, "pomegranate") == 0.45
    assert restitution_of(clean / "eval" / CHANGED, "pomegranate") == 0.15
    assert read_ledger(data / "eval", "render", CHANGED)["key"] != read_ledger(clean / "eval", "render", CHANGED)["key"]
    # the same settings again: nothing to do
    assert main(argv) == 0
    assert "render: 0 made, 2 up to date, 0 failed of 2 example(s)" in capsys.readouterr().out


def test_a_damaged_bundle_made_before_ledgers_is_rendered_again_and_the_report_says_why(clean, rows, reg, tmp_path):
    data = tmp_path / "data"
    shutil.copytree(clean, data)
    ledger_path(data / "eval", "render", "00019").unlink()  # made before ledgers existed ...
    tracks = data / "eval" / "00019" / B.TRACKS_FILE
    tracks.write_bytes(tracks.read_bytes()[:100])  # ... and damaged since
    executor = RecordingProcesses()
    report = render_stage(RenderStage(data, "eval", rows, reg, QUALITY), RunOptions(executor=executor, progress=False))
    assert executor.seen == ["00019"] and report.ran == ["00019"] and report.reused == ["00015"]
    assert list(report.redone) == ["00019"] and report.redone["00019"].why is Why.DAMAGED
    assert report.redone["00019"].detail.startswith("the bundle is damaged (tracks.npz")
    assert_same_bundle(data / "eval" / "00019", clean / "eval" / "00019")


def test_a_bundle_made_before_ledgers_is_taken_over_not_rendered_again(clean, rows, reg, tmp_path):
    data = tmp_path / "data"
    for sample_id in IDS:  # the bundles only, as an earlier version of `render` left them
        shutil.copytree(clean / "eval" / sample_id, data / "eval" / sample_id)
    before = mtimes(data)
    stage = RenderStage(data, "eval", rows, reg, QUALITY)
    executor = RecordingProcesses()
    report = render_stage(stage, RunOptions(executor=executor, progress=False))
    assert executor.seen == [] and report.reused == list(IDS) and not report.ran and not report.redone
    assert {k: v for k, v in mtimes(data).items() if not k.startswith("eval/.stages")} == before
    for sample_id in IDS:
        entry = read_ledger(data / "eval", "render", sample_id)
        assert entry["adopted"] is True and entry["key"] == stage.key(sample_id, None)
    # at another preset, the same bundles are not taken over
    other = RenderStage(tmp_path / "other", "eval", rows, reg, "preview")
    shutil.copytree(data / "eval" / "00019", tmp_path / "other" / "eval" / "00019")
    why = other.adopt("00019", None, "k")
    assert why.why is Why.CHANGED and why.detail == f"the bundle was rendered at the '{QUALITY}' preset, not 'preview'"


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="kills a process group")
def test_a_killed_render_resumes_from_the_unfinished_example(clean, rows, reg, tmp_path):
    """00015 is up to date (from the clean run, with its ledger); the command is killed while it renders 00019."""
    data = tmp_path / "data"
    shutil.copytree(clean / "eval" / "00015", data / "eval" / "00015")
    ledger_path(data / "eval", "render", "00015").parent.mkdir(parents=True)
    shutil.copy2(ledger_path(clean / "eval", "render", "00015"), ledger_path(data / "eval", "render", "00015"))
    staging = staging_path(data / "eval", "render", "00019")
    passes = staging / ".00019.tmp" / ".passes"
    env = {**os.environ, "PYTHONPATH": SRC + os.pathsep + os.environ.get("PYTHONPATH", "")}
    # the command and its render process (one process group), killed mid-example
    kill_when([sys.executable, "-m", "rigidbench", "render", "--split", "eval", "--ids", *IDS, "--quality", QUALITY,
               "--data", str(data), "--no-progress"], lambda: passes.is_dir() and any(passes.glob("*.exr")),
              timeout=120, env=env)
    assert B.check_bundle(data / "eval" / "00015") == [] and not (data / "eval" / "00019").exists()
    assert staging.is_dir() and read_ledger(data / "eval", "render", "00019") is None

    executor = RecordingProcesses()
    report = render_stage(RenderStage(data, "eval", rows, reg, QUALITY), RunOptions(executor=executor, progress=False))
    assert executor.seen == ["00019"] and report.ran == ["00019"] and report.reused == ["00015"]
    assert not staging.exists() and not report.redone  # never committed: new, not redone
    for sample_id in IDS:
        assert_same_bundle(data / "eval" / sample_id, clean / "eval" / sample_id)


# -- simulate ---------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def simulated(rows, reg, tmp_path_factory):
    out = tmp_path_factory.mktemp("simulated")
    first = simulate_rows(rows, reg, out, run=RunOptions(progress=False))
    assert first.ran == list(IDS) and not first.failed and not first.reused
    return out


def test_simulate_rerun_skips_and_an_edited_object_simulates_again_exactly_its_example(simulated, rows, reg, tmp_path,
                                                                                      edited_pomegranate):
    before = mtimes(simulated)
    executor = RecordingLocal()
    report = simulate_stage(SimulateStage(simulated, rows, reg), RunOptions(executor=executor, progress=False))
    assert executor.seen == [] and report.reused == list(IDS) and mtimes(simulated) == before
    again = simulate_rows(rows, reg, simulated, run=RunOptions(progress=False))  # the CLI's call
    assert not again.failed and again.reused == list(IDS)

    out = tmp_path / "sim"
    shutil.copytree(simulated, out)
    kept = mtimes(out / "00019")
    edited = load_registry([edited_pomegranate])
    report = simulate_stage(SimulateStage(out, rows, edited, [edited_pomegranate]), RunOptions(executor=executor, progress=False))
    assert executor.seen == [CHANGED] and report.ran == [CHANGED] and report.reused == ["00019"]
    assert report.redone == {CHANGED: "its inputs or settings changed"}
    assert mtimes(out / "00019") == kept and restitution_of(out / CHANGED, "pomegranate") == 0.45
    moved = [arrays(d / CHANGED / "trajectories.npz")["positions_m"] for d in (simulated, out)]
    assert moved[0].shape == moved[1].shape and not np.array_equal(*moved)  # it bounces higher


def test_a_killed_simulation_resumes_and_an_old_one_is_taken_over(simulated, rows, reg, tmp_path):
    out = tmp_path / "sim"
    shutil.copytree(simulated, out)
    # what a run killed inside 00019 leaves: no output, no ledger, a half-written staging folder
    shutil.rmtree(out / "00019")
    ledger_path(out, "simulate", "00019").unlink()
    half = staging_path(out, "simulate", "00019") / ".00019.tmp-killed"
    half.mkdir(parents=True)
    (half / "trajectories.npz").write_bytes(b"PK\x03\x04 half")
    executor = RecordingLocal()
    report = simulate_stage(SimulateStage(out, rows, reg), RunOptions(executor=executor, progress=False))
    assert executor.seen == ["00019"] and report.ran == ["00019"] and report.reused == ["00015"]
    assert not staging_path(out, "simulate", "00019").exists()
    for sample_id in IDS:
        for name in ("trajectories.npz",):
            a, b = arrays(out / sample_id / name), arrays(simulated / sample_id / name)
            for key in a:
                np.testing.assert_array_equal(a[key], b[key])
        for name in ("contacts.json", "scene_spec.json"):
            assert (out / sample_id / name).read_text() == (simulated / sample_id / name).read_text()

    legacy = tmp_path / "legacy"
    for sample_id in IDS:  # simulated before ledgers existed
        shutil.copytree(simulated / sample_id, legacy / sample_id)
    report = simulate_stage(SimulateStage(legacy, rows, reg), RunOptions(executor=executor, progress=False))
    assert executor.seen == ["00019"] and report.reused == list(IDS)  # nothing more ran
    assert all(read_ledger(legacy, "simulate", i)["adopted"] for i in IDS)
