"""Probing end to end on the tiny Wan models (CPU): `test`-preset training clips -> preprocess ->
probe extract (base and random) -> fit -> intervene -> report, and extraction resumes."""

import json

import numpy as np
import pytest

from fixtures.blender import render_train_examples, requires_bpy

torch = pytest.importorskip("torch")
pytest.importorskip("diffusers")

from rigidbench.cli import main  # noqa: E402

pytestmark = requires_bpy

CLIPS = 4


@pytest.fixture(scope="module")
def data_and_cache(tmp_path_factory, torch_single_thread):
    data = render_train_examples(tmp_path_factory.mktemp("data"), CLIPS)
    cache = tmp_path_factory.mktemp("cache")
    assert main(["preprocess", "--data", str(data), "--out", str(cache), "--model", "tiny", "--no-progress"]) == 0
    return data, cache


def test_probe_end_to_end_on_tiny(data_and_cache, tmp_path):
    data, cache = data_and_cache
    acts = {}
    for backbone in ("base", "random"):
        acts[backbone] = tmp_path / f"acts-{backbone}"
        assert main(["probe", "extract", "--backbone", backbone, "--cache", str(cache), "--data", str(data),
                     "--out", str(acts[backbone]), "--model", "tiny", "--chunk-size", "2", "--no-progress"]) == 0
    man = json.loads((acts["base"] / "manifest.json").read_text())
    assert man["token_grid"] == [3, 2, 4] and man["blocks"] == 2 and man["width"] == 24
    assert sorted(man["splits"].values()) == ["test", "train", "train", "val"]
    assert [p["tau"] for p in man["schedule"]] == [0.1, 0.3, 0.5, 0.7, 0.9]
    sigmas = [p["sigma"] for p in man["schedule"]]
    assert sigmas == sorted(sigmas, reverse=True)  # tau 0.9 is the least noisy (the paper's and release's tau)
    assert man["version"] == 3 and man["backbone_seed"] is None
    rand = json.loads((acts["random"] / "manifest.json").read_text())
    assert rand["backbone_seed"] == 0 and "RMSNorm" in rand["random_init"]
    assert sorted(man["clips"]) == ["00000", "00001", "00002", "00003"]  # one file pair per clip
    from rigidbench.probe.store import ActivationStore

    store = ActivationStore(acts["base"])
    rows = store.rows
    x = store.cell(1, 0.5)
    assert x.shape == (len(rows["clip"]), 24) and np.isfinite(x).all()
    assert set(rows["slot"]) <= {0, 1, 2} and rows["position"].shape[1] == 3
    # a rerun skips every clip
    assert main(["probe", "extract", "--backbone", "base", "--cache", str(cache), "--data", str(data),
                 "--out", str(acts["base"]), "--no-progress"]) == 0
    assert json.loads((acts["base"] / "manifest.json").read_text())["clips"] == man["clips"]

    probes = {}
    for backbone in ("base", "random"):
        probes[backbone] = tmp_path / f"probes-{backbone}"
        assert main(["probe", "fit", "--acts", str(acts[backbone]), "--out", str(probes[backbone]),
                     "--targets", "position,contact,linear_velocity", "--no-progress"]) == 0
    lines = (probes["base"] / "scores.jsonl").read_text().splitlines()
    assert len(lines) == 2 * 5 * 3 * 2 * 2  # blocks x taus x targets x probes x labels

    intv = tmp_path / "intv"
    assert main(["probe", "intervene", "--acts", str(acts["base"]), "--cache", str(cache), "--out", str(intv),
                 "--clips", "2", "--resamples", "200", "--no-progress"]) == 0
    result = json.loads((intv / "intervene.json").read_text())
    assert len(result["clips"]) == 2 and len(result["bases"]) == 2 * 3
    effects = [json.loads(x) for x in (intv / "effects.jsonl").read_text().splitlines()]
    assert len(effects) == 2 * 2 * 3 * 3 * 2  # clips x blocks x taus x variants x readouts
    for e in effects:  # the two readouts coincide at the last block
        if e["block"] == 1 and e["readout"] == "full":
            twin = next(f for f in effects if f["readout"] == "direct" and
                        all(f[k] == e[k] for k in ("clip", "block", "tau", "variant")))
            assert twin["loss"] == pytest.approx(e["loss"], rel=1e-5, abs=1e-7)
    for b in result["bases"]:
        assert b["alpha_pc"] <= 1.0 and b["rank"] >= 0
        assert b["version"] == 2 and b["inlp_dtype"] == "float64" and b["train_rows"] == int(0.8 * len(rows["clip"]))
    assert result["inlp"]["ridge_per_row"] == 0.05 and result["inlp"]["intercept"] is False
    # the hook-based full readout gives the same numbers (bases reused from intv)
    hooked = tmp_path / "intv-hook"
    import shutil

    shutil.copytree(intv / "bases", hooked / "bases")
    assert main(["probe", "intervene", "--acts", str(acts["base"]), "--cache", str(cache), "--out", str(hooked),
                 "--clips", "2", "--resamples", "200", "--full-readout", "hook", "--no-progress"]) == 0
    other = [json.loads(x) for x in (hooked / "effects.jsonl").read_text().splitlines()]
    assert [e["delta"] for e in other] == pytest.approx([e["delta"] for e in effects], abs=1e-6)

    report = tmp_path / "report"
    assert main(["probe", "report", "--probes", str(probes["base"]), str(probes["random"]), "--intervene", str(intv),
                 "--out", str(report)]) == 0
    for name in ("index.html", "probe_by_block.png", "probe_by_block.pdf", "probe_heatmap_linear.png",
                 "probe_by_noise_mlp.png", "intervention_by_block.png", "probe_summary.csv",
                 "probe_state_summary.csv", "intervention_summary.csv"):
        assert (report / name).is_file(), name
    assert "probe_by_block.png" in (report / "index.html").read_text()
