"""``probe extract`` and ``probe intervene`` on the stage driver, with the tiny Wan models on hand-made
bundles (no Blender): a rerun computes nothing, a changed clip, cache entry or setting redoes exactly what
changed and says why, an interrupted run resumes to the outputs of an uninterrupted one, a bad clip fails
alone, and an activation store of the older chunked layout is still read."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

torch = pytest.importorskip("torch")
pytest.importorskip("diffusers")

from fixtures.probe_bundles import contact, write_bundle  # noqa: E402
from rigidbench.cli import main  # noqa: E402
from rigidbench.driver import RunOptions, Selection, Why, ledger_path, read_ledger, staging_path  # noqa: E402
from rigidbench.errors import UserError  # noqa: E402
from rigidbench.probe import model as wan  # noqa: E402
from rigidbench.probe.store import ActivationStore, shard_path  # noqa: E402
from rigidbench.stages import probe_bases  # noqa: E402
from rigidbench.stages.preprocess import run_preprocess  # noqa: E402
from rigidbench.stages.probe_extract import run_extract  # noqa: E402
from rigidbench.stages.probe_intervene import run_intervene  # noqa: E402

pytestmark = pytest.mark.usefixtures("torch_one_thread")

CLIPS = ("00000", "00001", "00002", "00003")


@pytest.fixture(scope="module")
def made(tmp_path_factory, torch_one_thread):
    """Four bundles and their tiny cache."""
    root = tmp_path_factory.mktemp("made")
    for n, clip in enumerate(CLIPS):
        write_bundle(root / "data" / "train", clip, n)
    run_preprocess(root / "data" / "train", root / "cache", model="tiny", run=RunOptions(progress=False))
    return root / "data" / "train", root / "cache"


@pytest.fixture
def data(made, tmp_path):
    """A copy of the bundles and the cache this test may change."""
    shutil.copytree(made[0], tmp_path / "data" / "train")
    shutil.copytree(made[1], tmp_path / "cache")
    return tmp_path / "data" / "train", tmp_path / "cache"


@pytest.fixture
def loads(monkeypatch):
    """How often a backbone was loaded, a clip run through it and a cell's bases fitted."""
    counts = {"backbone": 0, "forward": 0, "bases": 0}

    def counting(module, name, key):
        fn = getattr(module, name)

        def wrapped(*args, **kwargs):
            counts[key] += 1
            return fn(*args, **kwargs)
        monkeypatch.setattr(module, name, wrapped)

    counting(wan, "load_backbone", "backbone")
    counting(wan, "capture_blocks", "forward")
    counting(probe_bases, "fit_bases", "bases")
    return counts


def extract(data, cache, out, **options):
    return run_extract("base", cache, data, out, model="tiny", **options, run=RunOptions(progress=False))


def store_content(acts) -> tuple[dict, dict]:
    store = ActivationStore(acts)
    return store.rows, {(b, t): store.cell(b, t) for b in range(store.blocks) for t in store.taus}


def clip_part(content, clip):
    """The rows and cells of one clip of ``store_content``."""
    rows, cells = content
    keep = rows["clip"] == clip
    return {k: v[keep] for k, v in rows.items()}, {k: v[keep] for k, v in cells.items()}


def rows_of(acts, clip):
    return clip_part(store_content(acts), clip)


def assert_same(a, b) -> None:
    assert a[0].keys() == b[0].keys() and a[1].keys() == b[1].keys()
    for k in a[0]:
        np.testing.assert_array_equal(a[0][k], b[0][k])
    for k in a[1]:
        np.testing.assert_array_equal(a[1][k], b[1][k])


# -- extract -------------------------------------------------------------------------------------------


def test_extract_rerun_computes_nothing_and_a_changed_clip_or_setting_is_redone(data, tmp_path, loads, capsys):
    bundles, cache = data
    acts = tmp_path / "acts"
    first = extract(bundles, cache, acts)
    assert first.ran == list(CLIPS) and not first.failed and not first.facts.empty and not first.facts.missing
    assert first.facts.rows == len(ActivationStore(acts).rows["clip"]) > 0
    assert loads["backbone"] == 1 and loads["forward"] == 4 * 5  # clips x taus
    manifest = json.loads((acts / "manifest.json").read_text())
    assert manifest["version"] == 3 and sorted(manifest["clips"]) == list(CLIPS)
    assert sorted(manifest["splits"].values()) == ["test", "train", "train", "val"]
    before = store_content(acts)

    again = extract(bundles, cache, acts)
    assert again.ran == [] and again.reused == list(CLIPS) and again.facts.rows == 0
    assert loads == {"backbone": 1, "forward": 20, "bases": 0}  # the backbone is not even loaded
    assert json.loads((acts / "manifest.json").read_text())["clips"] == manifest["clips"]
    assert_same(store_content(acts), before)

    # one bundle's contacts change: that clip's targets, and only that clip, are extracted again
    contact(bundles / "00002", 2)
    changed = extract(bundles, cache, acts)
    assert changed.ran == ["00002"] and {i: why.why for i, why in changed.redone.items()} == {"00002": Why.CHANGED}
    assert changed.facts.rows == len(rows_of(acts, "00002")[0]["clip"])
    after = store_content(acts)
    keep = before[0]["clip"] != "00002"
    for k in after[1]:
        np.testing.assert_array_equal(after[1][k], before[1][k])  # same latent and noise: same activations
    assert not np.array_equal(after[0]["contact"][~keep], before[0]["contact"][~keep])
    np.testing.assert_array_equal(after[0]["contact"][keep], before[0]["contact"][keep])
    assert json.loads((acts / "manifest.json").read_text())["splits"] == manifest["splits"]  # splits are kept

    # one clip of the cache is encoded again from another prompt: extraction redoes that clip alone
    (bundles / "00001" / "prompt.txt").write_text("A blue ball rolls to the right.")
    assert run_preprocess(bundles, cache, model="tiny", run=RunOptions(progress=False)).ran == ["00001"]
    assert extract(bundles, cache, acts).ran == ["00001"]
    new, old = rows_of(acts, "00001"), clip_part(before, "00001")
    np.testing.assert_array_equal(new[0]["position"], old[0]["position"])  # the same targets, another text
    assert not np.array_equal(new[1][(1, 0.5)], old[1][(1, 0.5)])

    # a setting every clip shares (the schedule fractions): all of them, and the command line says so
    assert main(["probe", "extract", "--backbone", "base", "--cache", str(cache), "--data", str(bundles),
                 "--out", str(acts), "--taus", "0.3,0.7", "--no-progress"]) == 0
    out = capsys.readouterr().out.splitlines()
    store = ActivationStore(acts)
    assert out == [f"probe-extract: 4 made, 0 up to date, 0 failed of 4 clip(s) -> {acts}",
                   "  made again, its inputs or settings changed: 00000, 00001, 00002, 00003",
                   f"  actor-slot rows extracted: {len(store.rows['clip'])} (base backbone)"]
    assert store.taus == [0.3, 0.7] and store.manifest["splits"] == manifest["splits"]
    np.testing.assert_array_equal(rows_of(acts, "00000")[1][(1, 0.3)], clip_part(before, "00000")[1][(1, 0.3)])


def test_extract_resumes_an_interrupted_run_to_the_store_of_an_uninterrupted_one(data, tmp_path, monkeypatch):
    bundles, cache = data
    clean = tmp_path / "clean"
    extract(bundles, cache, clean)
    acts = tmp_path / "acts"
    forward, seen = wan.forward, []

    def interrupted(transformer, batch, *args, **kwargs):  # Ctrl-C while the third clip runs
        seen.append(1)
        if len(seen) > 2 * 5:
            raise KeyboardInterrupt
        return forward(transformer, batch, *args, **kwargs)

    monkeypatch.setattr(wan, "forward", interrupted)
    with pytest.raises(KeyboardInterrupt):
        extract(bundles, cache, acts)
    monkeypatch.setattr(wan, "forward", forward)
    assert [read_ledger(acts, "probe-extract", c) is not None for c in CLIPS] == [True, True, False, False]
    assert sorted(json.loads((acts / "manifest.json").read_text())["clips"]) == ["00000", "00001"]
    # what a kill leaves too: a staging folder, and a committed clip whose ledger entry was never written
    (staging_path(acts, "probe-extract", "00002") / "acts").mkdir(parents=True)
    ledger_path(acts, "probe-extract", "00001").unlink()
    resumed = extract(bundles, cache, acts)
    assert resumed.reused == ["00000"] and resumed.ran == ["00001", "00002", "00003"]
    assert not staging_path(acts, "probe-extract", "00002").exists()
    assert_same(store_content(acts), store_content(clean))
    for name in ("splits", "clips"):
        assert json.loads((acts / "manifest.json").read_text())[name] == \
            json.loads((clean / "manifest.json").read_text())[name]


def test_extract_records_a_bad_clip_and_goes_on_and_refuses_an_older_store(data, tmp_path, capsys):
    bundles, cache = data
    (bundles / "00001" / "masks.npz").write_bytes(b"not a zip")
    shutil.rmtree(bundles / "00003")
    acts = tmp_path / "acts"
    assert main(["probe", "extract", "--backbone", "base", "--cache", str(cache), "--data", str(bundles),
                 "--out", str(acts), "--no-progress"]) == 1
    printed = capsys.readouterr()
    assert printed.out.splitlines()[0] == f"probe-extract: 2 made, 0 up to date, 1 failed of 3 clip(s) -> {acts}"
    err = printed.err
    assert "FAILED 00001" in err and "masks.npz" in err and "FAILED 00003: no bundle 00003" in err
    manifest = json.loads((acts / "manifest.json").read_text())
    assert sorted(manifest["clips"]) == ["00000", "00002"] and sorted(manifest["failed"]) == ["00001", "00003"]
    old = tmp_path / "old"
    old.mkdir()
    (old / "manifest.json").write_text(json.dumps({"version": 2, "chunks": []}))
    with pytest.raises(UserError, match="older RigidBench.*new --out"):
        extract(bundles, cache, old)


def test_a_checkpoint_backbone_is_keyed_by_its_weights_not_its_folder(data, tmp_path, loads):
    from rigidbench.train.tiny import tiny_transformer

    bundles, cache = data
    model = tiny_transformer()
    model.save_pretrained(tmp_path / "run-a" / "step-1")
    acts = tmp_path / "acts"
    first = run_extract(str(tmp_path / "run-a" / "step-1"), cache, bundles, acts, run=RunOptions(Selection.of(None, 2), progress=False))
    assert first.ran == ["00000", "00001"]
    shutil.copytree(tmp_path / "run-a", tmp_path / "run-b")  # the same weights elsewhere: nothing to do
    moved = run_extract(str(tmp_path / "run-b" / "step-1"), cache, bundles, acts, run=RunOptions(Selection.of(None, 2), progress=False))
    assert moved.reused == ["00000", "00001"] and loads["backbone"] == 1
    with torch.no_grad():
        model.blocks[0].attn1.to_q.weight.mul_(2.0)
    model.save_pretrained(tmp_path / "run-b" / "step-1")  # other weights at the same place: all again
    trained = run_extract(str(tmp_path / "run-b" / "step-1"), cache, bundles, acts, run=RunOptions(Selection.of(None, 2), progress=False))
    assert trained.ran == ["00000", "00001"] and {why.why for why in trained.redone.values()} == {Why.CHANGED}


def test_an_activation_store_of_the_older_chunked_layout_reads_the_same(data, tmp_path):
    """Version 2 (chunks of clips, a split column in the rows): the reader gives the same rows and cells."""
    from safetensors.numpy import save_file

    bundles, cache = data
    acts = tmp_path / "acts"
    extract(bundles, cache, acts)
    rows, cells = store_content(acts)
    manifest = json.loads((acts / "manifest.json").read_text())
    old = tmp_path / "old"
    (old / "rows").mkdir(parents=True)
    chunks = []
    for n, part in enumerate((["00000", "00001"], ["00002", "00003"])):
        keep = np.isin(rows["clip"], part)
        name = f"chunk-{n:05d}"
        np.savez(old / "rows" / f"{name}.npz", **{k: v[keep] for k, v in rows.items()})
        for (b, tau), x in cells.items():
            shard_path(old, b, tau, name).parent.mkdir(parents=True, exist_ok=True)
            save_file({"h": x[keep].astype(np.float16)}, str(shard_path(old, b, tau, name)))
        chunks.append({"name": name, "clips": part, "rows": int(keep.sum())})
    legacy = {k: v for k, v in manifest.items() if k not in ("clips", "empty", "settings_key")}
    (old / "manifest.json").write_text(json.dumps({**legacy, "version": 2, "chunks": chunks}))
    assert_same(store_content(old), (rows, cells))


# -- intervene -----------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def store(made, tmp_path_factory, torch_one_thread):
    acts = tmp_path_factory.mktemp("store") / "acts"
    run_extract("base", made[1], made[0], acts, model="tiny", run=RunOptions(progress=False))
    return acts


def intervene(store, cache, out, clips=2, **options):
    return run_intervene(store, cache, out, **{"run": RunOptions(Selection(limit=clips), progress=False),
                                               "n_resamples": 50, **options})


def effects(out):
    return [json.loads(x) for x in (Path(out) / "effects.jsonl").read_text().splitlines()]


def test_intervene_rerun_computes_nothing_and_changed_settings_redo_exactly_the_changed_clips(made, store, tmp_path,
                                                                                            loads, capsys):
    cache = made[1]
    out = tmp_path / "intv"
    first = intervene(store, cache, out)
    assert first.facts.results["clips"] == first.ran == ["00000", "00001"] and len(first.facts.bases.ran) == 2 * 3
    assert loads == {"backbone": 1, "forward": 2 * 3, "bases": 2 * 3}  # clips x taus; blocks x taus
    lines = effects(out)
    assert len(lines) == 2 * 2 * 3 * 3 * 2  # clips x blocks x taus x variants x readouts

    again = intervene(store, cache, out, n_resamples=80)
    assert again.ran == [] and again.reused == ["00000", "00001"] and again.facts.bases.ran == []
    assert again.facts.results["n_resamples"] == 80
    assert loads == {"backbone": 1, "forward": 6, "bases": 6}  # only the summary was computed again
    assert effects(out) == lines
    # the command prints both stages' reports in the words every stage uses, then the summary it wrote
    assert main(["probe", "intervene", "--acts", str(store), "--cache", str(cache), "--out", str(out), "--clips", "2",
                 "--resamples", "80", "--no-progress"]) == 0
    summary = json.loads((out / "intervene.json").read_text())["summary"]
    assert capsys.readouterr().out.splitlines() == [
        f"probe-bases: 0 made, 6 up to date, 0 failed of 6 cell(s) -> {out}",
        f"probe-intervene: 0 made, 2 up to date, 0 failed of 2 clip(s) -> {out}",
        "  loss change over the 2 clip(s) done, mean [95% CI]:",
        *(f"  {r['variant']:>8} {r['readout']:>6}: dL = {r['mean']:.4g} [{r['lo']:.4g}, {r['hi']:.4g}]"
          for r in summary)]
    assert len(summary) == 3 * 2 and loads["forward"] == 6

    more = intervene(store, cache, out, clips=3)  # one more clip: only it runs
    assert more.facts.results["clips"] == ["00000", "00001", "00002"] and more.ran == ["00002"]
    assert effects(out)[:len(lines)] == lines and loads["forward"] == 6 + 3

    hooked = intervene(store, cache, out, full_readout="hook")  # a setting of every clip
    assert hooked.ran == ["00000", "00001"] and hooked.facts.bases.ran == []
    assert {i: why.why for i, why in hooked.redone.items()} == {"00000": Why.CHANGED, "00001": Why.CHANGED}
    assert [e["delta"] for e in effects(out)] == pytest.approx([e["delta"] for e in lines], abs=1e-6)

    float32 = intervene(store, cache, out, inlp_dtype="float32")  # INLP's precision: the bases and every clip
    assert len(float32.facts.bases.ran) == 2 * 3 and len(float32.ran) == 2
    assert {b["inlp_dtype"] for b in float32.facts.results["bases"]} == {"float32"}


def test_intervene_refits_the_bases_of_a_store_that_changed_and_reuses_copied_ones(made, store, tmp_path, loads):
    cache = made[1]
    out = tmp_path / "intv"
    intervene(store, cache, out)
    copy = tmp_path / "copy"
    shutil.copytree(out / "bases", copy / "bases")  # bases fitted on the same store, without their ledger
    reused = intervene(store, cache, copy)
    assert reused.facts.bases.reused == ["b00_tau0.3", "b00_tau0.5", "b00_tau0.7", "b01_tau0.3", "b01_tau0.5",
                                         "b01_tau0.7"]
    assert reused.facts.bases.ran == [] and loads["bases"] == 6 and effects(copy) == effects(out)
    changed = tmp_path / "acts"
    shutil.copytree(store, changed)
    ledger_path(changed, "probe-extract", "00003").unlink()  # the store loses a clip: other rows, other bases
    run_extract("base", cache, made[0], changed, model="tiny", run=RunOptions(Selection.of(None, 3), progress=False))
    assert sorted(json.loads((changed / "manifest.json").read_text())["clips"]) == list(CLIPS[:3])
    refit = intervene(changed, cache, out)
    assert len(refit.facts.bases.ran) == 6 and len(refit.ran) == 2


def test_intervene_resumes_an_interrupted_run_to_the_effects_of_an_uninterrupted_one(made, store, tmp_path,
                                                                                   monkeypatch):
    cache = made[1]
    clean = tmp_path / "clean"
    intervene(store, cache, clean, clips=3)
    out = tmp_path / "intv"
    flow_loss, seen = wan.flow_loss, []

    def interrupted(*args, **kwargs):  # Ctrl-C during the second clip
        seen.append(1)
        if len(seen) > 3 * (1 + 2 * (1 + 3 * 2)):  # one clip: taus x (baseline + blocks x (direct0 + variants x 2))
            raise KeyboardInterrupt
        return flow_loss(*args, **kwargs)

    monkeypatch.setattr(wan, "flow_loss", interrupted)
    with pytest.raises(KeyboardInterrupt):
        intervene(store, cache, out, clips=3)
    monkeypatch.setattr(wan, "flow_loss", flow_loss)
    assert [read_ledger(out, "probe-intervene", c) is not None for c in CLIPS[:3]] == [True, False, False]
    (staging_path(out, "probe-intervene", "00001") / "effects").mkdir(parents=True)  # a kill's leftovers
    resumed = intervene(store, cache, out, clips=3)
    assert resumed.ran == ["00001", "00002"] and not staging_path(out, "probe-intervene", "00001").exists()
    assert effects(out) == effects(clean)
    assert resumed.facts.results["summary"] == json.loads((clean / "intervene.json").read_text())["summary"]


# -- recipes -------------------------------------------------------------------------------------------


@pytest.fixture
def seen_forwards(monkeypatch):
    """What every transformer forward got: (the clip whose noise was drawn last, batch, text, dtype, a block
    weight's dtype), and the noise drawn per clip."""
    calls, noises, last = [], {}, {}
    forward, noise_for = wan.forward, wan.noise_for

    def spy_noise(clip_id, shape, seed, conditioning):
        noises[clip_id] = noise_for(clip_id, shape, seed, conditioning)
        last["clip"] = clip_id
        return noises[clip_id]

    def spy(transformer, batch, text, device, dtype=torch.float32):
        calls.append((last["clip"], batch, text, dtype, transformer.blocks[0].attn1.to_q.weight.dtype))
        return forward(transformer, batch, text, device, dtype)

    monkeypatch.setattr(wan, "noise_for", spy_noise)
    monkeypatch.setattr(wan, "forward", spy)
    return calls, noises


def test_extract_with_the_release_recipe_conditions_as_the_release_and_a_changed_choice_redoes_the_clips(
        data, tmp_path, seen_forwards, capsys):
    from rigidbench.benchmark import PROMPT_SUFFIX
    from rigidbench.probe.recipe import RECIPES
    from rigidbench.train.cache import LatentCache

    bundles, cache_dir = data
    calls, noises = seen_forwards
    cache = LatentCache(cache_dir)
    acts = tmp_path / "acts"
    args = ["probe", "extract", "--backbone", "base", "--cache", str(cache_dir), "--data", str(bundles), "--out",
            str(acts), "--limit", "2", "--no-progress"]
    assert main(args + ["--recipe", "release"]) == 0
    manifest = json.loads((acts / "manifest.json").read_text())
    assert manifest["recipe"] == "release" and manifest["conditioning"] == RECIPES["release"].conditioning.as_dict()
    assert [p["schedule_index"] for p in manifest["schedule"]] == [93, 303, 502, 698, 899]
    assert len(calls) == 2 * 5
    for clip, batch, text, dtype, weights in calls:
        # the task prompt alone (no suffix), UMT5's outputs at all 512 positions
        record = cache.manifest["prompts"][cache.prompt_key(clip, "task")]
        assert record["text"] == (bundles / clip / "prompt.txt").read_text() and PROMPT_SUFFIX not in record["text"]
        assert text.shape[1] == 512 and record["tokens"] < 512
        np.testing.assert_array_equal(text[0].numpy(), cache.text(clip, "task")[:512].float().numpy())
        assert text[0, record["tokens"]:].abs().sum() > 0
        # one timestep for every token (slot 0 too), rounded to bfloat16; a bfloat16 forward
        assert batch.timestep_tokens.shape == (1,)
        assert float(batch.timestep_tokens[0]) in {980.0, 920.0, 832.0, 684.0, 360.0}
        assert dtype == torch.bfloat16 and weights == torch.bfloat16
    assert set(noises) == {"00000", "00001"} and torch.equal(noises["00000"], noises["00001"])  # shared noise

    assert main(args + ["--recipe", "release"]) == 0 and len(calls) == 10  # the same recipe: nothing to do
    capsys.readouterr()
    calls.clear()
    assert main(args) == 0  # ours: every clip again, with the evaluation prompt, zero padding, per-clip noise
    assert "  made again, its inputs or settings changed: 00000, 00001" in capsys.readouterr().out.splitlines()
    manifest = json.loads((acts / "manifest.json").read_text())
    assert manifest["recipe"] == "ours" and manifest["conditioning"]["noise"] == "per-clip"
    for clip, batch, text, dtype, weights in calls:
        tokens = cache.tokens(clip, "task+suffix")
        assert PROMPT_SUFFIX in cache.manifest["prompts"][cache.prompt_key(clip)]["text"]
        assert text[0, tokens:].abs().sum() == 0 and dtype == torch.float32 and weights == torch.float32
        assert batch.timestep_tokens.shape == (1, 24) and (batch.timestep_tokens[0, :8] == 0).all()
    assert not torch.equal(noises["00000"], noises["00001"])
    calls.clear()
    assert main(args + ["--recipe", "release", "--noise", "per-clip"]) == 0  # one choice changed: again
    assert "  made again, its inputs or settings changed: 00000, 00001" in capsys.readouterr().out.splitlines()
    assert len(calls) == 10
    manifest = json.loads((acts / "manifest.json").read_text())
    assert manifest["recipe"] == "release+changes" and manifest["conditioning"]["noise"] == "per-clip"
    assert manifest["conditioning"]["prompt"] == "task"


def test_intervene_on_a_release_store_uses_its_conditioning_and_the_release_inlp(made, tmp_path, seen_forwards,
                                                                                caplog):
    from rigidbench.probe.recipe import RECIPES

    bundles, cache = made
    acts = tmp_path / "acts"
    run_extract("base", cache, bundles, acts, model="tiny", recipe="release", run=RunOptions(progress=False))
    calls, _ = seen_forwards
    calls.clear()
    out = tmp_path / "intv"
    result = intervene(acts, cache, out, clips=1).facts.results
    assert result["recipe"] == "release" and result["inlp"]["procedure"] == "release"
    assert result["conditioning"] == RECIPES["release"].conditioning.as_dict() == result["store_conditioning"]
    assert calls and all(c[3] == torch.bfloat16 and c[1].timestep_tokens.shape == (1,) for c in calls)
    import csv

    with (out / "bases.csv").open() as fh:
        rows = list(csv.DictReader(fh))
    assert len(rows) == 2 * 3
    for row, facts in zip(rows, result["bases"]):
        added = [r for r in facts["train_r2"] if not r < 0.05]
        assert row["procedure"] == "release" and int(row["rounds"]) == len(added)
        assert int(row["rounds_x3"]) == 3 * len(added) and int(row["rank"]) == facts["rank"]
    # ours on the same store: the stable INLP refits every cell, the clip runs again, and the log says that
    # the conditioning is not the store's
    ours = intervene(acts, cache, out, clips=1, recipe="ours")
    assert ours.facts.results["inlp"]["procedure"] == "stable" and len(ours.facts.bases.ran) == 6
    assert ours.ran == ["00000"] and "conditioning other than the store's extraction" in caplog.text
    with (out / "bases.csv").open() as fh:
        assert {r["procedure"] for r in csv.DictReader(fh)} == {"stable"}
