"""`rigidbench envelope` end to end (flows.envelope) at the `test` preset: the envelope folder and its
envelope.json, a rerun that makes nothing, scores against the envelope (the reference inside it, the static,
slowed and heavier-gravity failure modes outside), the envelope widening with the perturbation scale, a twin at
scale 0 scoring as the reference; twins of imported (published) examples from their rebuilt scene spec; the
command's output and exit status.

Three references (a drop into a cluster, a free fall and a ramp collision) are rendered and their 4-twin
geometry-only envelope made in about 20 s on two cores; the gravity counterfactual re-renders them (about 12 s).
The file takes 40-55 s.
"""

from __future__ import annotations

import json

import numpy as np
import pytest

from fixtures import published_from_sim as pfs
from fixtures.blender import render_eval_examples, requires_bpy
from fixtures.scenes import free_fall_spec


pytestmark = [pytest.mark.integration, requires_bpy]

IDS = ("00010", "00015", "00020")  # drop into cluster, free fall, ramp collision
TWINS = 4
# The example whose envelope is made again at scales 0 and 0.5: the ramp collision, whose twins respond smoothly to
# the perturbation (q95 - q05 of every geometric measurement grows strictly over scales 0.25, 0.5, 1 and 2 with 4
# twins). The drop into a cluster does not: its bottle lands on the fruit within the 12 frames and the outcome
# saturates, so with 4 twins its widths at scale 0.5 exceed those at 1 on every measurement (IoU 0.077 and 0.066).
SCALED = "00020"


def _quiet(*ids: str):
    """Run options: no progress bars; only examples ``ids`` when given."""
    from rigidbench.driver import RunOptions, Selection

    return RunOptions(selection=Selection.of(ids or None), progress=False)


@pytest.fixture(scope="module")
def split(tmp_path_factory):
    return render_eval_examples(tmp_path_factory.mktemp("data"), IDS)


@pytest.fixture(scope="module")
def made(split, tmp_path_factory):
    """(facts of the first run, facts of a second run, the envelope folder): 4 geometry-only twins at scale 1."""
    from rigidbench.flows.envelope import make_envelope

    env = tmp_path_factory.mktemp("envelope") / "env"
    first = make_envelope(split, env, twins=TWINS, run=_quiet())
    text = (env / "envelope.json").read_text()
    second = make_envelope(split, env, twins=TWINS, run=_quiet())
    assert (env / "envelope.json").read_text() == text  # nothing changed
    return first, second, env


@pytest.fixture(scope="module")
def against(split, made, tmp_path_factory):
    """mode -> (results.json's "envelope" block, the run's per-example records) of a failure mode scored against
    the envelope with gt perception."""
    from rigidbench.perception.features import FeatureNets
    from rigidbench.predictors import PredictContext
    from rigidbench.stages.evaluate import evaluate
    from rigidbench.stages.predict import predict

    root = tmp_path_factory.mktemp("modes")
    out = {}
    for mode, severity in (("reference", 0.0), ("static", 1.0), ("slow", 0.5), ("gravity", 1.0)):
        preds = root / "predictions" / mode
        assert not predict(mode, split, preds, PredictContext(severity=severity), run=_quiet()).failed
        report = evaluate(preds, split, root / "runs" / mode, nets=FeatureNets(), run=_quiet(), envelope=made[2])
        assert not report.failed, report.failed
        records = {i: json.loads((root / "runs" / mode / "examples" / f"{i}.json").read_text()) for i in IDS}
        out[mode] = (report.facts.results["envelope"], records)
    return out


@pytest.fixture(scope="module")
def scaled(split, made, tmp_path_factory):
    """scale -> envelope folder of example SCALED (scale 1: the main envelope)."""
    from rigidbench.flows.envelope import make_envelope

    root = tmp_path_factory.mktemp("scaled")
    out = {1.0: made[2]}
    for scale in (0.0, 0.5):
        facts = make_envelope(split, root / f"scale{scale}", twins=TWINS, scale=scale, run=_quiet(SCALED))
        assert list(facts.examples) == [SCALED] and facts.examples[SCALED]["status"] == "ok"
        out[scale] = root / f"scale{scale}"
    return out


# -- the folder ------------------------------------------------------------------------------------------------


def test_the_envelope_folder_holds_the_twins_their_scores_and_envelope_json(made, split):
    from rigidbench.folders import find_samples, sample_item
    from rigidbench.metrics import METRICS
    from rigidbench.scene_spec.envelope import ENTRIES, load_envelope

    first, _, env = made
    doc = json.loads((env / "envelope.json").read_text())  # strict JSON
    assert set(doc) == {"config", "twins", "geometry_only", "scale", "seed", "dataset", "examples"}
    assert (doc["twins"], doc["geometry_only"], doc["scale"], doc["seed"]) == (TWINS, True, 1.0, 0)
    assert doc["config"] == load_envelope().to_dict() and set(ENTRIES) < set(doc["config"])
    assert all(doc["config"][e]["reason"] for e in ENTRIES)
    assert doc["dataset"] == {"dataset": "rendered", "version": "bundle v1", "md5": None, "preset": "test"}
    assert {i: {k: e[k] for k in ("status", "reason", "twins")} for i, e in doc["examples"].items()} == \
        {i: {"status": "ok", "reason": None, "twins": TWINS} for i in IDS}
    for entry in doc["examples"].values():  # the floor: a scale-0 twin, i.e. the reference itself, scored
        floor = entry["floor"]
        assert floor["iou"] == 1.0 and floor["ate"] == 0.0 and floor["chamfer"] == 0.0
        assert set(floor) == {"iou", "centroid_l2", "chamfer", "ate", "ate3d", "si_mse"}  # geometry only
    for i in IDS:
        assert sorted(find_samples(env / "predictions", i)) == list(range(TWINS))
        for k in range(TWINS):
            record = json.loads((env / "run" / "examples" / f"{sample_item(i, k)}.json").read_text())
            assert (record["id"], record.get("sample", 0)) == (i, k)
            geometric = {m for m, info in METRICS.items() if info.group == "motion"}
            assert all(record["metrics"][m] is not None for m in geometric)
            assert all(record["metrics"][m] is None for m in set(METRICS) - geometric)  # no RGB
    assert sorted(first.widths) == ["drop_into_cluster", "free_fall", "ramp_collision"]


def test_a_rerun_makes_nothing(made, split):
    from rigidbench.driver import RunOptions, Selection
    from rigidbench.flows.envelope import make_envelope

    first, second, env = made
    items = [f"{i}.s{k}" if k else i for i in IDS for k in range(TWINS)]
    assert sorted(first.predicted.ran) == sorted(first.scored.ran) == sorted(items)
    for report in (second.predicted, second.scored):
        assert report.ran == [] and sorted(report.reused) == sorted(items) and not report.failed
    assert second.examples == first.examples and second.widths == first.widths
    # a shard runs its part of the twins and leaves envelope.json to a run without one
    text = (env / "envelope.json").read_text()
    shard = make_envelope(split, env, twins=TWINS, run=RunOptions(selection=Selection.of(shard="1/2"), progress=False))
    assert not shard.written and shard.predicted.selected == items[1::2] and shard.predicted.ran == []
    assert (env / "envelope.json").read_text() == text


# -- scores against it -----------------------------------------------------------------------------------------


def test_the_reference_lies_inside_its_own_envelope_on_every_example(against, made):
    block, _ = against["reference"]
    assert block["metrics"] == ["iou", "centroid_l2", "chamfer", "ate", "ate3d", "si_mse"]
    assert block["n_no_envelope"] == 0 and sorted(block["per_example"]) == list(IDS)
    for i in IDS:
        for metric, entry in block["per_example"][i].items():
            assert entry["inside"] is True and entry["excess"] == 0.0, (i, metric, entry)
            assert entry["twins"] == TWINS
    assert all(block["overall"][m]["inside"] == 1.0 for m in block["metrics"])


@pytest.mark.parametrize("mode", ["static", "slow", "gravity"])
def test_failure_modes_fall_outside_the_envelope_on_most_examples(against, mode):
    """static (severity 1), slow at 0.5 and gravity at 1: for every geometric measurement, outside on more than
    half of the examples; the excess is the distance past the worse edge (recomputed here)."""
    from rigidbench.metrics import METRICS

    block, records = against[mode]
    for metric in block["metrics"]:
        outside = [i for i in IDS if block["per_example"][i][metric]["inside"] is False]
        assert len(outside) > len(IDS) / 2, (mode, metric, outside)
        for i in IDS:
            entry = block["per_example"][i][metric]
            value = records[i]["metrics"][metric]
            assert entry["value"] == pytest.approx(value)
            past = value - entry["q95"] if not METRICS[metric].higher_is_better else entry["q05"] - value
            assert entry["excess"] == pytest.approx(max(0.0, past))


def _twin_scores(env, example, metric):
    from rigidbench.evaluation.envelope import read_envelope

    return read_envelope(env).twins[example][metric]


def test_the_envelope_widens_with_the_scale(scaled):
    """Per geometric measurement, the q95 - q05 of the twins of one example at scales 0, 0.5 and 1 (same seeds):
    zero at 0, never narrower as the scale grows, and wider at 1 than at 0.5 on most measurements."""
    from rigidbench.evaluation.envelope import read_envelope

    metrics = read_envelope(scaled[1.0]).metrics
    widths = {}
    for scale, env in scaled.items():
        for metric in metrics:
            twins = _twin_scores(env, SCALED, metric)
            assert len(twins) == TWINS
            q05, q95 = np.quantile(twins, [0.05, 0.95])
            widths.setdefault(metric, {})[scale] = q95 - q05
    for metric, by_scale in widths.items():
        assert by_scale[0.0] == 0.0 and by_scale[0.5] > 0.0, (metric, by_scale)
        assert by_scale[0.5] <= by_scale[1.0], (metric, by_scale)
    wider = [m for m in metrics if widths[m][1.0] > widths[m][0.5]]
    assert len(wider) > len(metrics) / 2, widths


def test_a_twin_at_scale_0_scores_as_the_reference(scaled, against):
    from rigidbench.evaluation.envelope import read_envelope

    _, records = against["reference"]
    reference = records[SCALED]["metrics"]
    envelope = read_envelope(scaled[0.0])
    for metric in envelope.metrics:
        assert list(envelope.twins[SCALED][metric]) == [reference[metric]] * TWINS, metric


# -- imported examples ----------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def published(tmp_path_factory):
    """An imported set made from our own simulation (fixtures.published_from_sim): 00000 a free fall our
    re-simulation reproduces, 00001 the same with the published positions moved 5 cm from frame 12."""
    from rigidbench.blender.physics import simulate
    from rigidbench.config import registry
    from rigidbench.stages.import_set import import_published

    reg = registry()
    root = tmp_path_factory.mktemp("published")
    fall = free_fall_spec(reg, asset="tennis_ball", task_rotation_deg=30.0, support_top_m=0.92,
                          support_size_m=(2.6, 0.7))
    result = simulate(fall, reg)
    samples = root / "published" / "samples"
    written = [("00000", pfs.write_example(samples / "00000", fall, result, reg)),
               ("00001", pfs.write_example(samples / "00001", fall, result, reg, shift=(12, (0.05, 0.0, 0.0))))]
    pfs.write_set(root / "published", written)
    assert not import_published(root / "published", root / "data", registry=reg, run=_quiet()).failed
    return root / "data" / "eval"


def test_a_drifting_imported_example_has_no_envelope_and_says_how_far(published, tmp_path):
    from rigidbench.flows.envelope import make_envelope

    facts = make_envelope(published, tmp_path / "env", twins=TWINS, run=_quiet("00001"))
    assert facts.predicted is None and facts.reconstructed is None  # nothing to twin
    entry = json.loads((tmp_path / "env" / "envelope.json").read_text())["examples"]["00001"]
    assert entry["status"] == "no envelope"
    assert "drifts 5.0 cm" in entry["reason"] and "from frame 12" in entry["reason"]
    assert entry["reconstruction"]["resimulation"]["max_m"] == pytest.approx(0.05, abs=1e-4)


def test_a_twin_of_an_imported_example_comes_from_its_rebuilt_spec(published, tmp_path):
    """The twin predictor with spec_dir: at scale 0 the rebuilt scene re-simulates the published trajectory and
    its data passes, through the rebuilt camera, cover the published masks; a rendered twin and a bundle without
    a rebuilt spec are refused per example."""
    from rigidbench.config import registry
    from rigidbench.datasets.resimulate import resimulate_published
    from rigidbench.errors import PredictionError
    from rigidbench.groundtruth.bundle import Sample
    from rigidbench.predictors import PredictContext, predictor_info

    resimulate_published(published, registry(), ids=["00000"], out_dir=tmp_path / "resim")
    sample = Sample(published / "00000")
    twin = predictor_info("twin").create()
    try:
        zero = twin.predict(sample, PredictContext(seed=3, options={"scale": 0.0, "geometry_only": True,
                                                                    "spec_dir": str(tmp_path / "resim")}))
        state, reference = zero.state, sample.masks[:, sample.active_indices]
        assert state.geometry_only and state.masks.shape == reference.shape
        overlap = (state.masks & reference).sum() / (state.masks | reference).sum()
        assert overlap > 0.8, overlap
        assert zero.metadata["twin"]["spec"] == "rebuilt from the published metadata"
        with pytest.raises(PredictionError, match="geometry-only"):
            twin.predict(sample, PredictContext(seed=3, options={"spec_dir": str(tmp_path / "resim")}))
        with pytest.raises(PredictionError, match="ships no scene spec"):
            twin.predict(sample, PredictContext(seed=3, options={"geometry_only": True}))
        with pytest.raises(PredictionError, match="does not exist"):
            twin.predict(Sample(published / "00001"),
                         PredictContext(seed=3, options={"geometry_only": True, "spec_dir": str(tmp_path / "resim")}))
    finally:
        twin.close()


def test_a_reproduced_imported_example_gets_twins_and_its_reconstruction_floor(published, tmp_path):
    from rigidbench.flows.envelope import make_envelope
    from rigidbench.perception.features import FeatureNets
    from rigidbench.stages.evaluate import evaluate
    from rigidbench.stages.predict import predict

    facts = make_envelope(published, tmp_path / "env", twins=TWINS, run=_quiet())
    doc = json.loads((tmp_path / "env" / "envelope.json").read_text())
    ok, drifting = doc["examples"]["00000"], doc["examples"]["00001"]
    assert (ok["status"], ok["twins"], ok["imported"]) == ("ok", TWINS, True)
    assert ok["reconstruction"]["resimulation"]["max_m"] < 1e-4
    floor = ok["reconstruction"]["zero_twin"]
    assert 0.8 < floor["iou"] <= 1.0 and floor["ate"] == pytest.approx(0.0, abs=1e-6)
    assert drifting["status"] == "no envelope" and "drifts" in drifting["reason"]
    assert doc["resimulation"]["with_envelope"] == 1 and doc["resimulation"]["examples"] == 2
    assert facts.reconstructed.ran == ["00000"] and sorted(facts.predicted.ran) == \
        ["00000", "00000.s1", "00000.s2", "00000.s3"]
    # the published reference scored as a model against it: inside (one-sided), the drifting example named
    assert not predict("reference", published, tmp_path / "reference", run=_quiet()).failed
    block = evaluate(tmp_path / "reference", published, tmp_path / "run", nets=FeatureNets(), run=_quiet(),
                     envelope=tmp_path / "env").facts.results["envelope"]
    assert all(entry["inside"] for entry in block["per_example"]["00000"].values())
    assert block["no_envelope"] == {"00001": drifting["reason"]}


# -- the command ------------------------------------------------------------------------------------------------


def test_the_command_prints_what_it_made_and_its_widths(made, split, capsys):
    from rigidbench.cli import main

    _, _, env = made
    assert main(["envelope", "--data", str(split), "--out", str(env), "--twins", str(TWINS), "--no-progress"]) == 0
    out = capsys.readouterr().out.splitlines()
    assert f"envelope: 3 of 3 examples have one ({TWINS} twins each, scale 1, geometry only); {env / 'envelope.json'}" \
        in out
    header = out.index("envelope width (median over examples of the twins' 95th - 5th percentile):")
    assert out[header + 1].split() == ["task", "iou", "centroid_l2", "chamfer", "ate", "ate3d", "si_mse"]
    rows = {line.split()[0]: line.split()[1:] for line in out[header + 2:header + 5]}
    assert sorted(rows) == ["drop_into_cluster", "free_fall", "ramp_collision"]
    widths = json.loads(json.dumps(made[0].widths))
    assert float(rows["free_fall"][0]) == pytest.approx(widths["free_fall"]["iou"], rel=1e-3)
    # fewer twins than the folder holds: refused, one line, nothing made
    assert main(["envelope", "--data", str(split), "--out", str(env), "--twins", "2", "--no-progress"]) == 2
    err = capsys.readouterr().err
    assert "made with 4 twins per example" in err and "--twins 4" in err and len(err.strip().splitlines()) == 1


def test_the_command_refuses_bad_numbers(split, tmp_path, capsys):
    from rigidbench.cli import main

    for flag, value, why in (("--twins", "1", "whole number >= 2"), ("--scale", "-1", "finite number >= 0")):
        with pytest.raises(SystemExit) as stop:
            main(["envelope", "--data", str(split), "--out", str(tmp_path / "env"), flag, value])
        assert stop.value.code == 2 and why in capsys.readouterr().err
    assert not (tmp_path / "env").exists()
