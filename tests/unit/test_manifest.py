import collections
import subprocess
import sys

import pytest

from rigidbench import manifest
from rigidbench.config import registry


@pytest.fixture(scope="module")
def reg():
    return registry()


@pytest.fixture(scope="module")
def train(reg):
    return manifest.train_rows(reg)


@pytest.fixture(scope="module")
def evaluation(reg):
    return manifest.eval_rows(reg)


def test_train_counts(train, reg):
    assert len(train) == 5000
    assert collections.Counter(r.task for r in train) == {
        "free_fall": 1047, "bounce": 1000, "ball_chain": 953, "drop_into_cluster": 1000, "ramp_collision": 1000}
    scenes = collections.Counter(r.scene for r in train)
    assert set(scenes) == set(reg.scenes_in("train")) and set(scenes.values()) == {625}
    train_objects = set(reg.objects_in("train"))
    assert all(set(r.allowed_objects) == train_objects for r in train)
    assert all(r.partition == "train" and r.split == "train" for r in train)
    assert [r.sample_id for r in train] == [f"{i:05d}" for i in range(5000)]
    assert all(r.surface in [s.name for s in reg.scene(r.scene).supports] for r in train)


def test_eval_partitions(evaluation, reg):
    assert len(evaluation) == 100
    cells = collections.Counter((r.partition, r.task) for r in evaluation)
    assert len(cells) == 20 and set(cells.values()) == {5}
    held_scenes, train_scenes = set(reg.scenes_in("held_out")), set(reg.scenes_in("train"))
    held_objects, train_objects = set(reg.objects_in("held_out")), set(reg.objects_in("train"))
    expect = {"in_distribution": (train_scenes, train_objects), "ood_scene": (held_scenes, train_objects),
              "ood_object": (train_scenes, held_objects), "ood_both": (held_scenes, held_objects)}
    for r in evaluation:
        scenes, objects = expect[r.partition]
        assert r.scene in scenes and set(r.allowed_objects) == objects


def test_train_and_eval_disjoint(train, evaluation):
    train_seeds = {r.seed for r in train}
    assert len(train_seeds) == 5000
    assert not train_seeds & {r.seed for r in evaluation}
    # Held-out scenes and objects never appear in training rows.
    held = {"beach_gazebo", "butterfly_mural_room", "cozy_living_room", "modern_warm_kitchen"}
    assert not held & {r.scene for r in train}


def test_manifest_is_deterministic_across_processes(tmp_path, evaluation):
    out = tmp_path / "eval.jsonl"
    subprocess.run([sys.executable, "-m", "rigidbench", "manifest", "--split", "eval", "--out", str(out)],
                   check=True, capture_output=True)
    assert manifest.read(out) == evaluation


def test_select_by_id_and_limit(evaluation):
    assert [r.sample_id for r in manifest.select(evaluation, ["00003", "00001"])] == ["00003", "00001"]
    assert len(manifest.select(evaluation, limit=7)) == 7
    with pytest.raises(KeyError, match="unknown sample id"):
        manifest.select(evaluation, ["12345"])
