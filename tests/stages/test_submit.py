"""`rigidbench submit` and `rigidbench verify` (issue 35, items 2 and 3).

The published set is the synthetic one of tests/fixtures/published_set.py: three examples in an archive whose
description (``--config``) names it, with ``examples: 3`` (how many examples the set holds: the description's
count is what "every example scored" is checked against; the packaged description says 100). It is imported
from the archive (MD5 verified), predicted by the `reference` predictor and scored with neural perception (tiny
random networks of the real architectures, so the run is complete: nothing skipped). A second run, like the
demo's, scores five examples imported from a folder with gt perception and no feature networks.
"""

from __future__ import annotations

import hashlib
import json
import shutil
import tarfile
from pathlib import Path

import pytest
import yaml

pytest.importorskip("av")
pytest.importorskip("torch")
pytest.importorskip("transformers")

from fixtures import published_runs  # noqa: E402
from fixtures import published_set as ps  # noqa: E402
from fixtures import tiny_perception  # noqa: E402
from fixtures.dataset_server import write_description  # noqa: E402

from rigidbench.cli import main  # noqa: E402
from rigidbench.commands.submitting import rescore  # noqa: E402
from rigidbench.driver import RunOptions  # noqa: E402
from rigidbench.evaluation.aggregation import summarise  # noqa: E402
from rigidbench.perception.features import FeatureNets, load_identity_features  # noqa: E402
from rigidbench.stages.evaluate import evaluate  # noqa: E402
from rigidbench.submissions import SubmissionError, load_submission  # noqa: E402
from rigidbench.submissions.bundle import MANIFEST_FILE, manifest_text  # noqa: E402
from rigidbench.submissions.card import CARD_FIELDS, card_problems  # noqa: E402
from rigidbench.submissions.verify import aggregate_problems, rescore_ids  # noqa: E402

REPO = Path(__file__).resolve().parents[2]
EXAMPLE_CARD = REPO / "docs" / "card.example.yaml"
IDS = ["00000", "00001", "00002"]

pytestmark = pytest.mark.usefixtures("torch_one_thread")


def tiny_options() -> dict:
    return {"models": tiny_perception.tiny_models(), "depth_input_size": 56, "device": "cpu"}


def tiny_nets() -> FeatureNets:
    return FeatureNets(lpips=tiny_perception.tiny_lpips(),
                       identity=load_identity_features(device="cpu", model=tiny_perception.tiny_dinov2()))


@pytest.fixture(scope="module")
def published_run(tmp_path_factory):
    """(config dir, data root, predictions, run folder) of a complete neural run on the verified synthetic set."""
    root = tmp_path_factory.mktemp("submit")
    config, data = published_runs.verified_test_set(root)
    preds, run = root / "predictions" / "reference", root / "runs" / "reference"
    assert main(["predict", "reference", "--data", str(data), "--out", str(preds)]) == 0
    summary = evaluate(preds, data, run, perception="neural", perception_options=tiny_options(), nets=tiny_nets(),
                       run=RunOptions(progress=False))
    assert summary.ran == IDS and not summary.failed and not summary.facts.skipped_metrics
    return config, data, preds, run


@pytest.fixture(scope="module")
def demo_like_run(tmp_path_factory):
    """A run like the demo's: five examples, gt perception, no feature networks (LPIPS and IdDrift skipped), on
    the set imported from an extracted folder (so its MD5 could not be checked)."""
    root = tmp_path_factory.mktemp("demo-like")
    samples = ps.DEFAULT_SAMPLES + (ps.PublishedSample("00003", "bounce", "modern_loft", "ood-object", 11, "apple"),
                                    ps.PublishedSample("00004", "free_fall", "beach_gazebo", "in_distribution", 12,
                                                       "orange"))
    folder = ps.write_set(root / "set" / "rigidbench-eval-v1.1", samples)
    data, preds, run = root / "data", root / "predictions", root / "run"
    assert main(["import", str(folder), "--data", str(data)]) == 0
    assert main(["predict", "reference", "--data", str(data), "--out", str(preds)]) == 0
    summary = evaluate(preds, data, run, perception="gt", nets=FeatureNets(skipped={
        "lpips": "LPIPS weights not found", "iddrift": "DINOv2 weights not found"}), run=RunOptions(progress=False))
    assert len(summary.ran) == 5
    return run


def full_card(tmp_path: Path, **changes) -> Path:
    card = yaml.safe_load(EXAMPLE_CARD.read_text())
    for dotted, value in changes.items():
        section, _, key = dotted.rpartition("__")
        target = card[section] if section else card
        if value is None:
            target.pop(key, None)
        else:
            target[key] = value
    path = tmp_path / "card.yaml"
    path.write_text(yaml.safe_dump(card))
    return path


def refusal_lines(capsys) -> list[str]:
    err = capsys.readouterr().err
    assert "Traceback" not in err
    lines = err.strip().splitlines()
    assert lines[0].startswith("rigidbench submit: refused: ") and lines[0].endswith(f"{len(lines) - 1} problem(s):")
    return lines[1:]


# -- the card --------------------------------------------------------------------------------------------------


def test_the_example_card_is_complete_and_covers_every_field():
    card = yaml.safe_load(EXAMPLE_CARD.read_text())
    assert card_problems(card) == []

    def leaves(doc, prefix=""):
        for k, v in doc.items():
            yield from leaves(v, f"{prefix}{k}.") if isinstance(v, dict) else [f"{prefix}{k}"]

    assert set(leaves(card)) == {f.path for f in CARD_FIELDS}


def test_card_problems_are_one_line_per_field(tmp_path):
    card = yaml.safe_load(EXAMPLE_CARD.read_text())
    del card["contact"], card["model"]["version"], card["model"]["checkpoint_digest"]
    card["generation"].update(fps="sixteen", best_of_n=4, samples_per_example=2, resolution="1280 by 720")
    card["access"]["kind"] = "cloud"
    card["licence"]["terms"] = "ftp://example.org/terms"
    card["cost"]["currncy"] = "USD"
    card["provenance"] = {"dataset": "typed by hand"}
    lines = card_problems(card, "card.yaml")
    fields = [line.split("'")[1] for line in lines]
    assert sorted(fields) == sorted(["provenance", "cost.currncy", "model.version", "access.kind",
                                     "generation.resolution", "generation.fps", "licence.terms", "contact",
                                     "generation.best_of_n"]), lines
    assert all(line.startswith("card.yaml: field '") for line in lines)
    assert "did you mean 'cost.currency'" in next(x for x in lines if "currncy" in x)
    assert "give model.version or model.checkpoint_digest" in next(x for x in lines if "model.version" in x)
    assert "4 is more than generation.samples_per_example (2)" in next(x for x in lines if "best_of_n" in x)


def test_conditional_fields():
    card = yaml.safe_load(EXAMPLE_CARD.read_text())
    del card["compute"], card["generation"]["selection"], card["generation"]["prompt_template"]
    # an open-weights model needs its compute; best-of-1 and no rewriting need no selection or template
    assert [line.split("'")[1] for line in card_problems(card)] == ["compute.gpu_type", "compute.gpu_count",
                                                                    "compute.gpu_hours"]
    card["access"]["kind"] = "api"
    assert card_problems(card) == []
    card["generation"].update(best_of_n=4, samples_per_example=4, prompt_rewriting=True)
    assert [line.split("'")[1] for line in card_problems(card)] == ["generation.selection",
                                                                    "generation.prompt_template"]


# -- submit ----------------------------------------------------------------------------------------------------


def test_a_demo_like_run_is_refused_with_one_line_per_problem(demo_like_run, tmp_path, capsys):
    card = full_card(tmp_path)
    assert main(["submit", str(demo_like_run), "--card", str(card), "--validate-only"]) == 2
    lines = refusal_lines(capsys)
    assert any(f"{demo_like_run}: gt perception:" in line for line in lines), lines
    assert any(f"{demo_like_run}: missing examples: 5 of the 100 examples of rigidbench-eval 1.1 were scored" in line
               for line in lines), lines
    assert any("an unverified set" in line for line in lines) and any(
        "measurements skipped: iddrift (DINOv2 weights not found); lpips (LPIPS weights not found)" in line
        for line in lines), lines
    assert len(lines) == 4  # and nothing about the card, which is complete
    # a bad card adds its own lines to the run's, all listed at once
    bad = full_card(tmp_path, contact=None, generation__fps=-1)
    assert main(["submit", str(demo_like_run), "--card", str(bad), "--validate-only"]) == 2
    lines = refusal_lines(capsys)
    assert len(lines) == 6 and lines[-2:] == [f"{bad}: field 'generation.fps': must be > 0, got -1",
                                              f"{bad}: field 'contact': missing (who to ask about this entry)"]


def test_a_complete_run_is_bundled_and_verified(published_run, tmp_path, capsys):
    config, data, preds, run = published_run
    card = full_card(tmp_path)
    argv = ["--config", str(config), "submit", str(run), "--card", str(card)]
    assert main(argv + ["--validate-only"]) == 0
    assert "can be submitted (3 examples, 0 videos)" in capsys.readouterr().out
    assert not (tmp_path / "submissions").exists()
    # without the description that names the set, it is not the published set
    assert main(["submit", str(run), "--card", str(card), "--validate-only"]) == 2
    assert [line.split(": ")[1] for line in refusal_lines(capsys)] == ["not the published set",
                                                                         "missing examples"]

    bundle = tmp_path / "entry.tar.gz"
    assert main(argv + ["--videos", str(preds), "--out", str(bundle)]) == 0
    with tarfile.open(bundle) as tar:
        names = sorted(tar.getnames())
    files = ["MANIFEST.sha256", "card.yaml", "results.json"] + [
        f"examples/{i}{s}" for i in IDS for s in (".json", ".readouts.json")] + [f"videos/{i}.mp4" for i in IDS]
    assert sorted(n for n in names if "." in n.rsplit("/", 1)[-1]) == sorted(f"submission/{f}" for f in files)

    sub = load_submission(bundle)
    results = json.loads((run / "results.json").read_text())
    assert sub.results == results and sorted(sub.records) == IDS and sorted(sub.readouts) == IDS
    assert sub.name == "Wan 2.2 I2V A14B, 1 sample" and sub.card == yaml.safe_load(card.read_text())
    assert all(sub.videos[i].read_bytes() == (preds / f"{i}.mp4").read_bytes() for i in IDS)
    p = sub.provenance
    assert p["dataset"]["verified"] is True and p["dataset"]["published"]["examples"] == 3
    assert p["protocol"]["name"] == "rigidbench-v1" and p["perception"]["backend"] == "neural"
    assert set(p["perception"]["weights"]) == {"sam2", "cotracker", "depth"}
    assert p["seeds"]["found"] is True and set(p["seeds"]["per_example"]) == set(IDS)
    assert p["records"] == {i: hashlib.sha256((run / "examples" / f"{i}.json").read_bytes()).hexdigest() for i in IDS}

    assert main(["verify", str(bundle)]) == 0
    assert capsys.readouterr().out.strip().endswith("verified")


def test_clips_that_are_not_the_scored_ones_are_refused(published_run, tmp_path, capsys):
    config, _, preds, run = published_run
    swapped = tmp_path / "swapped"
    swapped.mkdir()
    for a, b in zip(IDS, IDS[1:] + IDS[:1]):
        shutil.copy(preds / f"{a}.mp4", swapped / f"{b}.mp4")
    argv = ["--config", str(config), "submit", str(run), "--card", str(full_card(tmp_path)), "--validate-only"]
    assert main(argv + ["--videos", str(swapped)]) == 2
    assert refusal_lines(capsys) == [f"--videos {swapped}: these clips are not the ones the run scored (their "
                                     "hashes differ from run.json's predictions_hash); pass the folder `rigidbench "
                                     "evaluate` read"]
    (swapped / "00001.mp4").unlink()
    assert main(argv + ["--videos", str(swapped)]) == 2
    assert refusal_lines(capsys) == [f"--videos {swapped}: no clip for 1 scored examples (00001)"]


def _extracted(bundle: Path, where: Path) -> Path:
    with tarfile.open(bundle) as tar:
        tar.extractall(where, filter="data")
    return where / "submission"


@pytest.fixture(scope="module")
def bundle(published_run, tmp_path_factory):
    config, _, preds, run = published_run
    where = tmp_path_factory.mktemp("bundle")
    card = full_card(where)
    out = where / "entry.tar.gz"
    assert main(["--config", str(config), "submit", str(run), "--card", str(card), "--videos", str(preds),
                 "--out", str(out)]) == 0
    return out


def test_an_edited_number_is_caught(bundle, tmp_path, capsys):
    folder = _extracted(bundle, tmp_path)
    results = json.loads((folder / "results.json").read_text())
    true_mean = results["overall"]["ssim"]["mean"]
    results["overall"]["ssim"]["mean"] = true_mean + 0.01
    (folder / "results.json").write_text(json.dumps(results, indent=2))
    # the manifest catches the edit first, naming the file
    with pytest.raises(SubmissionError, match="results.json: its SHA-256 is not the one MANIFEST.sha256 lists"):
        load_submission(folder)
    assert main(["verify", str(folder)]) == 1
    assert "results.json: its SHA-256" in capsys.readouterr().out
    # a manifest written again over the edit: the number itself is caught, recomputed from the records
    (folder / MANIFEST_FILE).write_text(manifest_text(folder))
    assert main(["verify", str(folder)]) == 1
    out = capsys.readouterr().out.splitlines()
    assert out == [f"{folder}: results.json: overall.ssim.mean is {true_mean + 0.01:.10g}, the records give "
                   f"{true_mean:.10g}", "not verified: 1 mismatch(es)"]
    # independently: the mean of the records' values
    ssim = [json.loads((folder / "examples" / f"{i}.json").read_text())["metrics"]["ssim"] for i in IDS]
    assert summarise(ssim)["mean"] == pytest.approx(true_mean, rel=1e-12)


def test_an_edited_record_or_a_stray_file_is_caught(bundle, tmp_path):
    folder = _extracted(bundle, tmp_path)
    (folder / "videos" / "00001.mp4").unlink()
    (folder / "notes.txt").write_text("x")
    with pytest.raises(SubmissionError, match=r"videos/00001.mp4: listed in MANIFEST.sha256 but missing \(and 1 more"):
        load_submission(folder)
    shutil.copy(bundle, tmp_path / "again.tar.gz")
    # a record edited to flatter, with the manifest rewritten: the aggregates and the card's digest disagree
    folder = _extracted(tmp_path / "again.tar.gz", tmp_path / "second")
    record = json.loads((folder / "examples" / "00002.json").read_text())
    record["metrics"]["iou"] = 1.0
    (folder / "examples" / "00002.json").write_text(json.dumps(record))
    (folder / MANIFEST_FILE).write_text(manifest_text(folder))
    problems = aggregate_problems(load_submission(folder))
    assert any("overall.iou.mean" in p for p in problems)
    assert any("provenance.records.00002 is not the SHA-256 of examples/00002.json" in p for p in problems)


def test_rescoring_from_the_videos_agrees_with_the_records_and_finds_an_edited_one(bundle, published_run,
                                                                                   tmp_path):
    _, data, _, _ = published_run
    folder = _extracted(bundle, tmp_path)
    sub = load_submission(folder)
    assert rescore_ids(sub, 2, seed=1) == rescore_ids(sub, 2, seed=1) and len(rescore_ids(sub, 2, seed=1)) == 2
    assert rescore_ids(sub, 10, seed=1) == IDS
    # one record edited (its manifest entry too): scoring every example again finds exactly that measurement
    record = json.loads((folder / "examples" / "00001.json").read_text())
    record["metrics"]["ate3d"] *= 0.5
    (folder / "examples" / "00001.json").write_text(json.dumps(record))
    (folder / MANIFEST_FILE).write_text(manifest_text(folder))
    ids, problems = rescore(load_submission(folder), data, 3, seed=0, perception_options=tiny_options(),
                            nets=tiny_nets(), device="cpu")
    assert ids == IDS and len(problems) == 1, problems
    assert problems[0].startswith(f"{folder}: 00001: ate3d is {record['metrics']['ate3d']:.10g} in its record, ")
    assert problems[0].endswith("scored again (tolerance 0.02 relative, 1e-06 absolute)")


def test_a_dataset_description_says_how_many_examples_its_set_holds(tmp_path):
    from rigidbench.datasets.describe import load_dataset, parse_dataset
    from rigidbench.errors import ConfigError

    assert load_dataset("rigidbench-eval").examples == 100  # the paper's evaluation set
    path = write_description(tmp_path, "x-v1", name="x", version="1", archive="x.tar.gz", data=b"abc", md5="0" * 32,
                             part_bytes=10, url="http://127.0.0.1:9/{part}")
    doc = yaml.safe_load(path.read_text())
    assert parse_dataset(path, doc).examples is None
    for bad in (0, "many", True):
        with pytest.raises(ConfigError, match="field 'examples'"):
            parse_dataset(path, {**doc, "examples": bad})
