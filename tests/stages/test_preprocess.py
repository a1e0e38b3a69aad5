"""``preprocess`` on the stage driver, with the tiny Wan models on hand-made bundles (no Blender): a rerun
encodes nothing, a changed clip or setting re-encodes exactly what changed and says why, a killed run
resumes to the cache an uninterrupted run makes, shards fill one cache, a bad clip fails alone, and a
cache of the older shard layout is read and its clips adopted."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

torch = pytest.importorskip("torch")
pytest.importorskip("diffusers")

from fixtures import child_env  # noqa: E402
from fixtures.children import kill_when, python  # noqa: E402
from rigidbench.cli import main  # noqa: E402
from rigidbench.driver import RunOptions, Selection, ledger_path, read_ledger, staging_path  # noqa: E402
from rigidbench.executors import ProcessExecutor, Shard  # noqa: E402
from rigidbench.stages.preprocess import PROMPT_FORMAT, run_preprocess  # noqa: E402
from rigidbench.train import models  # noqa: E402
from rigidbench.train.cache import CacheWriter, LatentCache  # noqa: E402

pytestmark = pytest.mark.usefixtures("torch_one_thread")

W, H, T = 160, 96, 10  # resized to the tiny model's 128 x 64, its first 9 frames encoded
PROMPTS = {"00000": "A red ball rolls to the right.", "00001": "A red ball rolls to the right.",
           "00002": "Two blocks fall onto a table."}


def write_clip(split_dir: Path, sample_id: str, seed: int, prompt: str, frames: int = T) -> Path:
    """A bundle as far as preprocessing reads one: PNG frames, metadata.json and prompt.txt."""
    from PIL import Image

    d = split_dir / sample_id
    (d / "frames").mkdir(parents=True)
    rng = np.random.default_rng(seed)
    base = rng.integers(0, 255, (H, W, 3), dtype=np.uint8)
    for k in range(frames):
        Image.fromarray(np.roll(base, 6 * k, axis=1)).save(d / "frames" / f"{k:05d}.png")
    (d / "prompt.txt").write_text(prompt)
    (d / "metadata.json").write_text(json.dumps({"sample_id": sample_id, "task": "bounce", "frames": frames,
                                                 "fps": 8.0, "resolution": [W, H]}))
    return d


@pytest.fixture
def data(tmp_path):
    split = tmp_path / "data" / "train"
    for n, (sample_id, prompt) in enumerate(PROMPTS.items()):
        write_clip(split, sample_id, n, prompt)
    return split


@pytest.fixture
def calls(monkeypatch):
    """How often the models were loaded and a clip encoded."""
    counts = {"vae": 0, "text": 0, "clips": 0}

    def counting(name, fn):
        def wrapped(*args, **kwargs):
            counts[name] += 1
            return fn(*args, **kwargs)
        return wrapped

    monkeypatch.setattr(models, "load_vae", counting("vae", models.load_vae))
    monkeypatch.setattr(models, "load_text_encoder", counting("text", models.load_text_encoder))
    monkeypatch.setattr(models, "encode_video", counting("clips", models.encode_video))
    return counts


def preprocess(data, out, ids=None, shard=None, executor=None, **options):
    run = RunOptions(Selection.of(ids, shard=shard), executor, progress=False)
    return run_preprocess(data, out, model="tiny", run=run, **options)


def cache_content(cache_dir) -> dict:
    """Every example's latent and both prompts' embeddings and token counts, by id."""
    c = LatentCache(cache_dir)
    return {i: (c.latent(i), c.text(i), c.text(i, "task"), c.tokens(i), c.tokens(i, "task")) for i in c.ids}


def safetensors_content(path: Path) -> tuple[dict, dict]:
    from safetensors import safe_open

    with safe_open(str(path), framework="pt") as f:
        return f.metadata(), {k: f.get_tensor(k) for k in f.keys()}


def assert_same_content(a: dict, b: dict) -> None:
    assert a.keys() == b.keys()
    for i in a:
        for x, y in zip(a[i], b[i]):
            assert torch.equal(x, y) if isinstance(x, torch.Tensor) else x == y, i


def test_a_rerun_encodes_nothing_and_a_changed_clip_or_setting_is_encoded_again(data, tmp_path, calls, capsys):
    cache = tmp_path / "cache"
    first = preprocess(data, cache)
    assert first.ran == ["00000", "00001", "00002"] and not first.failed
    assert first.facts.prompts_encoded == 4  # two distinct task prompts, each alone and with the suffix
    assert calls == {"vae": 1, "text": 1, "clips": 3}
    manifest = json.loads((cache / "manifest.json").read_text())
    examples = manifest["examples"]
    assert manifest["version"] == 3 and examples["00000"]["prompt"] == examples["00001"]["prompt"]  # one file
    before = cache_content(cache)
    stamps = {p: p.stat().st_mtime_ns for p in cache.rglob("*.safetensors")}

    again = preprocess(data, cache)
    assert again.ran == [] and again.reused == ["00000", "00001", "00002"] and again.facts.prompts_encoded == 0
    assert calls == {"vae": 1, "text": 1, "clips": 3}  # no model loaded, no clip encoded
    assert {p: p.stat().st_mtime_ns for p in cache.rglob("*.safetensors")} == stamps
    assert json.loads((cache / "manifest.json").read_text())["examples"] == manifest["examples"]

    # one clip's prompt changes: that clip alone, and its two new prompts, are encoded
    (data / "00001" / "prompt.txt").write_text("A green ball rolls to the left.")
    changed = preprocess(data, cache)
    assert changed.ran == ["00001"] and changed.redone == {"00001": "its inputs or settings changed"}
    assert changed.facts.prompts_encoded == 2 and calls["clips"] == 4
    after = cache_content(cache)
    for i in ("00000", "00002"):
        assert all(torch.equal(x, y) for x, y in zip(before[i][:3], after[i][:3]))
    assert torch.equal(before["00001"][0], after["00001"][0])  # same frames: the same latent, re-encoded
    assert not torch.equal(before["00001"][1], after["00001"][1])
    assert LatentCache(cache).manifest["prompts"][LatentCache(cache).prompt_key("00001", "task")]["text"] == \
        "A green ball rolls to the left."

    # a setting every clip shares: all of them, and the command line says so
    assert main(["preprocess", "--data", str(data), "--out", str(cache), "--model", "tiny", "--no-progress",
                 "--resize", "lanczos"]) == 0
    out = capsys.readouterr().out
    assert "preprocess: 3 made, 0 up to date, 0 failed of 3 clip(s)" in out and "prompts encoded: 0 (" in out
    assert "  made again, its inputs or settings changed: 00000, 00001, 00002" in out
    lanczos = LatentCache(cache)
    assert lanczos.manifest["resize"] == "lanczos"
    assert not torch.equal(lanczos.latent("00000"), after["00000"][0])
    assert torch.equal(lanczos.text("00000"), after["00000"][1])  # the prompts' files are reused


def test_a_killed_run_resumes_to_the_cache_an_uninterrupted_run_makes(data, tmp_path):
    """The run is killed (SIGKILL) while it encodes the last clip; the rerun encodes just that clip, and the
    cache equals one made in one go (file for file, and its index)."""
    clean = tmp_path / "clean"
    preprocess(data, clean)
    cache, marker = tmp_path / "cache", tmp_path / "encoding-00002"
    code = f"""
import time
from pathlib import Path
from rigidbench.train import models
from rigidbench.stages.preprocess import run_preprocess
from rigidbench.driver import RunOptions, Selection
encode = models.encode_video
def slow(vae, frames):
    if Path({str(tmp_path)!r}, "encoded").exists():
        Path({str(marker)!r}).touch()
        time.sleep(120)
    Path({str(tmp_path)!r}, "encoded").touch()
    return encode(vae, frames)
models.encode_video = slow
run_preprocess({str(data)!r}, {str(cache)!r}, model="tiny", run=RunOptions(Selection.of(["00000", "00002"]), progress=False))
"""
    kill_when(python(code), marker, timeout=120, env=child_env(OMP_NUM_THREADS="1"))
    assert read_ledger(cache, "preprocess", "00000")["status"] == "succeeded"
    assert read_ledger(cache, "preprocess", "00002") is None and staging_path(cache, "preprocess", "00002").is_dir()
    assert not (cache / "latents" / "00002.safetensors").exists()

    resumed = preprocess(data, cache)
    assert resumed.reused == ["00000"] and resumed.ran == ["00001", "00002"]
    assert not staging_path(cache, "preprocess", "00002").exists()
    assert_same_content(cache_content(cache), cache_content(clean))
    files = sorted(p.relative_to(cache).as_posix() for p in cache.rglob("*.safetensors"))
    assert files == sorted(p.relative_to(clean).as_posix() for p in clean.rglob("*.safetensors"))
    for f in files:  # (safetensors writes its metadata in no fixed order: compare what the files hold)
        (meta_a, tensors_a), (meta_b, tensors_b) = safetensors_content(cache / f), safetensors_content(clean / f)
        assert meta_a == meta_b and tensors_a.keys() == tensors_b.keys()
        assert all(torch.equal(tensors_a[k], tensors_b[k]) for k in tensors_a)
    index, reference = (json.loads((d / "manifest.json").read_text()) for d in (cache, clean))
    assert index["examples"] == reference["examples"] and index["prompts"] == reference["prompts"]


def test_a_bad_clip_fails_alone_and_runs_again_once_repaired(data, tmp_path, calls, capsys):
    cache = tmp_path / "cache"
    write_clip(data, "00003", 3, "Too short.", frames=5)  # fewer frames than the model encodes
    good = (data / "00001" / "frames" / "00004.png").read_bytes()
    (data / "00001" / "frames" / "00004.png").write_bytes(good[:100])  # a truncated PNG
    assert main(["preprocess", "--data", str(data), "--out", str(cache), "--model", "tiny", "--no-progress"]) == 1
    err = capsys.readouterr().err
    assert "FAILED 00001" in err and "00004.png" in err and "FAILED 00003" in err and "needs the first 9" in err
    assert sorted(LatentCache(cache).ids) == ["00000", "00002"]
    assert read_ledger(cache, "preprocess", "00001")["status"] == "failed"
    (data / "00001" / "frames" / "00004.png").write_bytes(good)
    repaired = preprocess(data, cache)
    assert repaired.ran == ["00001"] and "00001" in repaired.redone and list(repaired.failed) == ["00003"]
    assert sorted(LatentCache(cache).ids) == ["00000", "00001", "00002"]


def test_shards_and_child_processes_fill_one_cache_equal_to_a_single_run(data, tmp_path):
    whole = tmp_path / "whole"
    preprocess(data, whole)
    sharded = tmp_path / "sharded"
    parts = [preprocess(data, sharded, shard=Shard(i, 2)).ran for i in range(2)]
    assert parts == [["00000", "00002"], ["00001"]]
    assert not list(sharded.glob("part-*"))  # the shards share the cache (and its ledger)
    assert_same_content(cache_content(sharded), cache_content(whole))
    assert preprocess(data, sharded).reused == ["00000", "00001", "00002"]
    # workers elsewhere (child processes here, Ray actors on a cluster) encode their clips' prompts themselves
    remote = tmp_path / "remote"
    report = preprocess(data, remote, executor=ProcessExecutor(workers=2), device="cpu")
    assert sorted(report.ran) == ["00000", "00001", "00002"] and report.facts.prompts_encoded >= 4
    assert_same_content(cache_content(remote), cache_content(whole))


def test_a_cache_of_the_older_shard_layout_is_read_and_its_clips_adopted(data, tmp_path, calls):
    """A version-2 cache (clips in shared shards, no ledger) made with the same settings: training reads it as
    before, and preprocessing into it again encodes only the clips it lacks."""
    fresh = tmp_path / "fresh"
    preprocess(data, fresh, ids=["00000", "00001"])
    made = LatentCache(fresh)
    old = tmp_path / "old"
    writer = CacheWriter(old, {k: made.manifest[k] for k in ("model", "width", "height", "frames", "text_len",
                                                             "prompt_format", "resize", "vae_dtype")})
    assert writer.manifest["version"] == 2 and made.manifest["prompt_format"] == PROMPT_FORMAT
    texts = {made.prompt_key(i, p): made.text(i, p) for i in made.ids for p in ("task+suffix", "task")}
    writer.add_text(texts, {k: made.manifest["prompts"][k]["text"] for k in texts},
                    {k: made.manifest["prompts"][k]["tokens"] for k in texts})
    records = {i: {k: v for k, v in made.manifest["examples"][i].items() if k not in ("shard", "key")}
               for i in made.ids}
    writer.add_latents({i: made.latent(i) for i in made.ids}, records)
    writer.set(latent_shape=made.manifest["latent_shape"], text_dim=made.manifest["text_dim"])
    assert_same_content(cache_content(old), cache_content(fresh))
    loads = dict(calls)

    report = preprocess(data, old)
    assert report.reused == ["00000", "00001"] and report.ran == ["00002"]
    assert calls["clips"] == loads["clips"] + 1
    assert read_ledger(old, "preprocess", "00000")["adopted"] is True
    index = LatentCache(old)
    assert index.manifest["version"] == 3
    assert index.manifest["examples"]["00000"]["shard"] == "latents-00000.safetensors"  # the older shard, read
    whole = tmp_path / "whole"
    preprocess(data, whole)
    assert_same_content(cache_content(old), cache_content(whole))
    # the older manifest is kept: a later run still knows where those clips are
    ledger_path(old, "preprocess", "00001").unlink()
    assert preprocess(data, old).reused == ["00000", "00001", "00002"]
    assert calls["clips"] == loads["clips"] + 1 + 3  # (the run into `whole`)
