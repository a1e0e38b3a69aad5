"""Re-simulating imported published examples (datasets.resimulate) on a published set made from our own simulation:
examples whose physics is ours re-simulate within tolerance, a published trajectory moved 5 cm is "no envelope"
with the measured drift, an unknown object id is a "cannot" reason and a damaged example does not stop the others."""

from __future__ import annotations

import json

import numpy as np
import pytest

from fixtures import published_from_sim as pfs
from fixtures.blender import requires_bpy
from fixtures.scenes import ball_chain_spec, free_fall_spec

pytestmark = [pytest.mark.integration, requires_bpy]

SUPPORT = {"support_top_m": 0.92, "support_size_m": (2.6, 0.7)}  # our catalogue's modern_loft counter
SHIFT = (12, (0.05, 0.0, 0.0))  # the published position of 00001 moved 5 cm along x from frame 12


@pytest.fixture(scope="module")
def resimulated(tmp_path_factory):
    from rigidbench.blender.physics import simulate
    from rigidbench.config import registry
    from rigidbench.datasets.resimulate import resimulate_published
    from rigidbench.driver import RunOptions
    from rigidbench.stages.import_set import import_published

    reg = registry()
    root = tmp_path_factory.mktemp("published_resim")
    fall = free_fall_spec(reg, asset="tennis_ball", task_rotation_deg=30.0, **SUPPORT)
    chain = ball_chain_spec(reg, task_rotation_deg=-20.0, **SUPPORT)
    fall_sim, chain_sim = simulate(fall, reg), simulate(chain, reg)
    samples = root / "published" / "samples"
    written = [("00000", pfs.write_example(samples / "00000", fall, fall_sim, reg)),
               ("00001", pfs.write_example(samples / "00001", fall, fall_sim, reg, shift=SHIFT)),
               ("00002", pfs.write_example(samples / "00002", fall, fall_sim, reg,
                                           object_ids={"tennis_ball_0": "unobtainium"})),
               ("00003", pfs.write_example(samples / "00003", fall, fall_sim, reg)),
               ("00004", pfs.write_example(samples / "00004", chain, chain_sim, reg, width=128, height=96))]
    pfs.write_set(root / "published", written)
    report = import_published(root / "published", root / "data", registry=reg, run=RunOptions(progress=False))
    assert report.ran == [sid for sid, _ in written] and not report.failed
    (root / "data" / "eval" / "00003" / "trajectories.npz").write_bytes(b"not a zip file")
    table = resimulate_published(root / "data", reg, out_dir=root / "resim")
    return {"table": table, "rows": {r.sample_id: r for r in table.rows}, "fall": fall, "fall_sim": fall_sim,
            "chain": chain, "root": root, "meta": dict(written)}


def test_our_own_simulation_re_simulates_within_tolerance(resimulated):
    from rigidbench.datasets.resimulate import RESIM_TOLERANCE_M
    from rigidbench.scene_spec.types import SceneSpec

    row = resimulated["rows"]["00000"]
    assert row.outcome == "reproduced" and row.envelope == "ok" and row.reason is None
    assert row.drift.max_m < 1e-4 < RESIM_TOLERANCE_M and row.drift.clip_max_m < 1e-4
    assert row.drift.window_frames == 25 and row.drift.clip_frames == resimulated["fall"].sim.frames
    spec = SceneSpec.from_json((resimulated["root"] / "resim" / "00000" / "scene_spec.json").read_text())
    (rebuilt,), (original,) = spec.world_bodies(), resimulated["fall"].world_bodies()
    assert np.allclose(rebuilt.position_m, original.position_m, atol=1e-6)
    assert abs(np.dot(rebuilt.quat_wxyz, original.quat_wxyz)) == pytest.approx(1.0, abs=1e-6)
    assert spec.support.centre_m == pytest.approx(resimulated["fall"].support.centre_m)


def _project(meta: dict, points: np.ndarray) -> np.ndarray:
    """Pixels of world points at the published camera, by hand: Blender camera looks along -z with +y up."""
    from scipy.spatial.transform import Rotation

    intr, extr = meta["camera"]["intrinsics"], meta["camera"]["extrinsics"]
    w, x, y, z = extr["rotation"]
    cam = (points - np.array(extr["location"])) @ Rotation.from_quat([x, y, z, w]).as_matrix()
    depth = -cam[:, 2]
    return np.stack([intr["fx"] * cam[:, 0] / depth + intr["cx"], intr["fy"] * -cam[:, 1] / depth + intr["cy"]], 1)


def test_a_published_trajectory_moved_5_cm_has_no_envelope_and_says_how_far(resimulated):
    row = resimulated["rows"]["00001"]
    assert row.outcome == "drifts" and row.envelope == "no envelope"
    assert row.drift.first_frame_over == SHIFT[0] and row.drift.max_m == pytest.approx(0.05, abs=1e-4)
    assert "drifts 5.0 cm" in row.reason and f"from frame {SHIFT[0]}" in row.reason and "tennis_ball_0" in row.reason
    ours = resimulated["fall_sim"].trajectory.positions_m[0, SHIFT[0]:25]
    px = np.linalg.norm(_project(resimulated["meta"]["00001"], ours + SHIFT[1])
                        - _project(resimulated["meta"]["00001"], ours), axis=1)
    assert row.drift.max_px == pytest.approx(px.max(), rel=1e-3)


def test_an_unknown_object_and_a_damaged_example_are_reasons_and_the_rest_still_runs(resimulated):
    rows = resimulated["rows"]
    assert rows["00002"].outcome == "cannot" and rows["00002"].envelope == "no envelope"
    assert "object id 'unobtainium' is not in our catalogue" in rows["00002"].reason
    assert rows["00003"].outcome == "failed" and "trajectories.npz" in rows["00003"].reason
    assert rows["00004"].drift is not None  # after the damaged one


def test_ramps_are_measured_from_the_published_depth(resimulated):
    row = resimulated["rows"]["00004"]
    (ramp,) = [b.ramp for b in resimulated["chain"].bodies if b.ramp is not None]
    assert row.notes["ramp_sizes_m"]["ramp"] == pytest.approx([ramp.length_m, ramp.height_m, ramp.width_m], abs=1e-3)
    assert row.outcome in ("reproduced", "drifts")


def test_the_table_records_how_many_examples_have_an_envelope(resimulated):
    doc = json.loads((resimulated["root"] / "resim" / "resimulation.json").read_text())  # strict JSON: no NaN
    assert doc["examples"] == 5 and doc["with_envelope"] == len(resimulated["table"].with_envelope)
    by_task = {t["task"]: t for t in doc["by_task"]}
    fall = by_task["free_fall"]
    assert (fall["count"], fall["reproduced"], fall["drifts"], fall["cannot"], fall["failed"]) == (4, 1, 1, 1, 1)
    assert fall["share_within_tolerance"] == pytest.approx(0.25)
    drifts = [resimulated["rows"][i].drift.max_m for i in ("00000", "00001")]
    assert fall["median_max_m"] == pytest.approx(np.median(drifts))
    assert by_task["all"]["count"] == 5 and by_task["ball_chain"]["count"] == 1
    assert doc["tolerance"]["window_s"] == 1.0
