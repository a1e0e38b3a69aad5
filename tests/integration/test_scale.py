"""Beyond one machine: the same stages on a local Ray cluster and as shards give the same files."""

import json
import os
from pathlib import Path

import numpy as np
import pytest
from fixtures import TESTS_DIR
from fixtures.blender import render_eval_examples, requires_bpy

from rigidbench.driver import RunOptions, Selection
from rigidbench import manifest
from rigidbench.config import registry
from rigidbench.executors import RayExecutor, Shard
from rigidbench.predictors import PREDICTORS, Kind, PredictContext, Predictor, PredictorInfo
from rigidbench.predictors.image_space import reference
from rigidbench.stages.evaluate import evaluate
from rigidbench.stages.predict import predict
from rigidbench.stages.render import render_rows

ray = pytest.importorskip("ray", reason="the Ray tests need the [ray] extra")
pytestmark = [pytest.mark.integration, requires_bpy]

IDS = ("00015", "00020", "00025")
HERE = Path(__file__).parent


@pytest.fixture(scope="module")
def cluster():
    """A local Ray cluster: 2 CPUs and one logical GPU; workers can import this test module (and the fixtures
    package it imports)."""
    pythonpath = os.pathsep.join([str(HERE), str(TESTS_DIR), os.environ.get("PYTHONPATH", "")])
    ray.init(num_cpus=2, num_gpus=1, include_dashboard=False, log_to_driver=False,
             runtime_env={"env_vars": {"PYTHONPATH": pythonpath, "RIGIDBENCH_TEST_DIR": str(HERE)}})
    yield
    ray.shutdown()


@pytest.fixture(scope="module")
def local_data(tmp_path_factory):
    return render_eval_examples(tmp_path_factory.mktemp("local"), IDS)


def _arrays(path: Path) -> dict:
    with np.load(path) as z:
        return {k: z[k] for k in z.files}


def test_ray_renders_the_same_bundles_as_a_local_run(cluster, local_data, tmp_path):
    reg = registry()
    rows = manifest.select(manifest.eval_rows(reg), list(IDS[:1]), None)
    [report] = render_rows(rows, reg, tmp_path, quality="test",
                           run=RunOptions(executor=RayExecutor(workers=1), progress=False))
    assert report.ran == list(IDS[:1]) and not report.failed
    for sample_id in IDS[:1]:
        for name in ("masks.npz", "depth.npz", "trajectories.npz", "tracks.npz"):
            ours, theirs = _arrays(tmp_path / "eval" / sample_id / name), _arrays(local_data / sample_id / name)
            assert ours.keys() == theirs.keys()
            for key in ours:
                np.testing.assert_array_equal(ours[key], theirs[key], err_msg=f"{sample_id}/{name}/{key}")


def test_ray_and_shards_score_exactly_like_a_local_run(cluster, local_data, tmp_path):
    preds = tmp_path / "predictions"
    assert not predict("static", local_data, preds, PredictContext(severity=0.5), run=RunOptions(progress=False)).failed
    # The default feature networks everywhere (none are present here: LPIPS and IdDrift are skipped alike).
    local = evaluate(preds, local_data, tmp_path / "local", run=RunOptions(progress=False))
    on_ray = evaluate(preds, local_data, tmp_path / "ray", run=RunOptions(executor=RayExecutor(workers=2), progress=False))
    for shard in (Shard(i, 3) for i in range(3)):
        evaluate(preds, local_data, tmp_path / "shards", run=RunOptions(Selection.of(None, None, shard), progress=False))
    assert sorted(local.ran) == sorted(on_ray.ran) == list(IDS)
    for sample_id in IDS:
        records = [json.loads((tmp_path / run / "examples" / f"{sample_id}.json").read_text())
                   for run in ("local", "ray", "shards")]
        for other in records[1:]:
            differ = {m: (records[0]["metrics"][m], other["metrics"][m]) for m in records[0]["metrics"]
                      if records[0]["metrics"][m] != other["metrics"][m]}
            assert not differ, f"{sample_id}: {differ}"
            assert other == records[0]
        arrays = [_arrays(tmp_path / run / "examples" / f"{sample_id}.npz") for run in ("local", "ray", "shards")]
        for key in arrays[0]:
            np.testing.assert_array_equal(arrays[0][key], arrays[1][key])
            np.testing.assert_array_equal(arrays[0][key], arrays[2][key])
    # A final run over the whole split reuses every shard's example and aggregates them.
    final = evaluate(preds, local_data, tmp_path / "shards", run=RunOptions(progress=False))
    assert sorted(final.reused) == list(IDS) and not final.ran
    assert final.facts.results["overall"] == local.facts.results["overall"]


def test_shards_partition_the_manifest():
    rows = manifest.eval_rows(registry())
    parts = [Shard(i, 3).select(rows) for i in range(3)]
    ids = [r.sample_id for part in parts for r in part]
    assert sorted(ids) == sorted(r.sample_id for r in rows) and len(ids) == len(set(ids)) == 100
    assert [len(p) for p in parts] == [34, 33, 33]
    assert Shard.parse("2/3") == Shard(2, 3) and Shard.parse(None) == Shard(0, 1)
    for bad in ("3/3", "a/b", "1"):
        with pytest.raises(Exception, match="--shard"):
            Shard.parse(bad)


class DiesOnce(Predictor):
    """The reference, except that the first attempt at each example kills its own worker process."""

    def predict(self, sample, ctx):
        marker = Path(ctx.out_dir) / f".attempted-{sample.sample_id}"
        if not marker.exists():
            marker.write_text(str(os.getpid()))
            os._exit(1)  # the worker dies mid-example, as a crashed node would
        return reference(sample, 0.0)


def test_a_worker_killed_mid_example_still_yields_every_example_once(cluster, local_data, tmp_path):
    info = PredictorInfo("dies-once", "test_scale:DiesOnce", "dies on its first attempt", Kind.PLUGIN,
                         writes_state=True)
    out = tmp_path / "predictions"
    with PREDICTORS.added(info):
        summary = predict("dies-once", local_data, out, PredictContext(), run=RunOptions(executor=RayExecutor(workers=1, max_retries=3), progress=False))
    assert summary.succeeded == list(IDS) and not summary.failed
    videos = sorted(p.name for p in out.glob("*.mp4"))
    assert videos == [f"{i}.mp4" for i in IDS]
    generation = json.loads((out / "generation.json").read_text())
    assert sorted(generation["examples"]) == list(IDS)
    assert all(e["status"] == "succeeded" for e in generation["examples"].values())
    for sample_id in IDS:
        assert (out / f".attempted-{sample_id}").exists()  # each example's first attempt really died
