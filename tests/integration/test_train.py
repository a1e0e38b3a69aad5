"""Fine-tuning end to end on `test`-preset training clips with the tiny Wan models (CPU): the
preprocess command, overfitting two clips, kill-and-resume reproducing the loss curve, two FSDP
processes under torchrun (and their loss curve against one process's), and checkpoints loading through
``predict wan-2.2 --checkpoint``."""

import json
import os
import subprocess
import sys
from pathlib import Path
from types import MappingProxyType

import pytest

from fixtures.blender import render_train_examples, requires_bpy

torch = pytest.importorskip("torch")
pytest.importorskip("diffusers")
pytest.importorskip("peft")

from rigidbench.cli import main  # noqa: E402
from rigidbench.train import tiny  # noqa: E402
from rigidbench.train.cache import LatentCache  # noqa: E402
from rigidbench.train.config import load_train_config  # noqa: E402
from rigidbench.train.objective import FlowMatchingObjective, transformer_prediction  # noqa: E402
from rigidbench.train.trainer import train  # noqa: E402

pytestmark = requires_bpy

TRAIN_IDS = 2


@pytest.fixture(scope="module")
def train_split(tmp_path_factory):
    """The first two training-manifest clips rendered at the `test` preset (12 frames, 256x144)."""
    return render_train_examples(tmp_path_factory.mktemp("data"), TRAIN_IDS)


@pytest.fixture(scope="module")
def cache(train_split, tmp_path_factory, torch_single_thread):
    out = tmp_path_factory.mktemp("cache")
    assert main(["preprocess", "--data", str(train_split), "--out", str(out), "--model", "tiny", "--no-progress"]) == 0
    return out


def metrics(run_dir):
    return [json.loads(line) for line in (Path(run_dir) / "metrics.jsonl").read_text().splitlines()]


def tiny_cfg(mode, steps, every, *extra):
    return load_train_config("tiny", overrides=[f"mode={mode}", f"max_steps={steps}", f"checkpoint_every={every}",
                                                *extra])


def test_preprocess_writes_a_resumable_float16_cache(cache, train_split, capsys):
    manifest = json.loads((cache / "manifest.json").read_text())
    assert sorted(manifest["examples"]) == ["00000", "00001"]
    assert manifest["latent_shape"] == [48, 3, 4, 8] and manifest["text_dim"] == 32
    assert (manifest["model"], manifest["width"], manifest["height"], manifest["frames"]) == ("tiny", 128, 64, 9)
    for record in manifest["examples"].values():  # both prompts: with the suffix (evaluation), alone (the release)
        suffixed, task = manifest["prompts"][record["prompt"]], manifest["prompts"][record["prompt_task"]]
        assert suffixed["text"].endswith("Motion begins on the first frame.") and suffixed["text"].startswith(task["text"])
        assert suffixed["rows"] == task["rows"] == 512 and task["tokens"] < suffixed["tokens"] <= 512
    assert (manifest["resize"], manifest["vae_dtype"]) == ("bicubic", "float32")  # the CPU default
    c = LatentCache(cache)
    assert c.latent(c.ids[0]).dtype == torch.float16 and c.text(c.ids[0]).dtype == torch.float16
    assert main(["preprocess", "--data", str(train_split.parent), "--out", str(cache), "--model", "tiny",
                 "--no-progress"]) == 0
    assert "0 made, 2 up to date, 0 failed of 2 clip(s)" in capsys.readouterr().out
    again = json.loads((cache / "manifest.json").read_text())
    assert again["examples"] == manifest["examples"] and again["prompts"] == manifest["prompts"]


def test_the_tiny_model_overfits_two_clips(cache, tmp_path, torch_single_thread):
    c = LatentCache(cache)
    objective = FlowMatchingObjective()
    z, text = c.batch([0, 1])

    def held_loss(model):  # the objective at 16 fixed (timestep, noise) draws on the two clips
        total = 0.0
        with torch.no_grad():
            for s in range(16):
                index, noise = objective.draw(torch.Generator().manual_seed(1000 + s), z.shape)
                batch = objective.prepare(z, noise, index)
                total += float(objective.loss(transformer_prediction(model, batch, text), batch))
        return total / 16

    cfg = tiny_cfg("full", 120, 120, "schedule.horizon_steps=150", "schedule.warmup_steps=5")
    train(cfg, cache, tmp_path / "run", progress=False)
    from diffusers import WanTransformer3DModel

    trained = WanTransformer3DModel.from_pretrained(tmp_path / "run" / "checkpoints" / "step-120")
    before, after = held_loss(tiny.tiny_transformer()), held_loss(trained)
    assert after < 0.75 * before, (before, after)
    losses = [m["loss"] for m in metrics(tmp_path / "run")]
    assert sum(losses[-20:]) / 20 < 0.75 * sum(losses[:20]) / 20


class Killed(Exception):
    pass


@pytest.fixture(scope="module")
def uninterrupted(cache, tmp_path_factory, torch_single_thread):
    """6-step LoRA and full runs with checkpoints at 3 and 6, never stopped."""
    runs = {}
    for mode in ("lora", "full"):
        runs[mode] = tmp_path_factory.mktemp(f"run-{mode}")
        train(tiny_cfg(mode, 6, 3), cache, runs[mode], progress=False)
    return runs


@pytest.mark.parametrize("mode", ["lora", "full"])
def test_kill_and_resume_reproduces_the_uninterrupted_loss_curve(mode, cache, uninterrupted, tmp_path, torch_single_thread):
    run = tmp_path / "run"

    def kill_after_5(record):
        if record["step"] == 5:
            raise Killed

    with pytest.raises(Killed):
        train(tiny_cfg(mode, 6, 3), cache, run, progress=False, on_step=kill_after_5)
    assert len(metrics(run)) == 5 and (run / "checkpoints" / "step-3").is_dir()
    assert (run / "training_state" / "step-3" / "state.json").is_file()
    assert not (run / "checkpoints" / "step-6").exists()
    summary = train(tiny_cfg(mode, 6, 3), cache, run, progress=False)
    assert (summary.start_step, summary.end_step) == (3, 6)
    resumed, expected = metrics(run), metrics(uninterrupted[mode])
    keys = ("step", "loss", "lr", "grad_norm", "examples_seen", "timestep")
    assert [{k: m[k] for k in keys} for m in resumed] == [{k: m[k] for k in keys} for m in expected]
    from safetensors.torch import load_file

    name = "adapter_model.safetensors" if mode == "lora" else "diffusion_pytorch_model.safetensors"
    a, b = (load_file(r / "checkpoints" / "step-6" / name) for r in (run, uninterrupted[mode]))
    assert a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)
    assert len(json.loads((run / "run.json").read_text())) == 2  # two launches recorded


def test_a_run_refuses_to_resume_with_other_settings(cache, uninterrupted):
    from rigidbench.errors import ConfigError

    with pytest.raises(ConfigError, match="optimizer"):
        train(tiny_cfg("lora", 6, 3, "optimizer.lr=0.5"), cache, uninterrupted["lora"], progress=False)


def test_older_checkpoints_can_drop_their_training_state_but_keep_their_exports(cache, tmp_path, torch_single_thread):
    run = tmp_path / "run"
    train(tiny_cfg("lora", 4, 1, "keep_training_states=2"), cache, run, progress=False)
    steps = sorted((run / "checkpoints").iterdir())
    assert [p.name for p in steps] == ["step-1", "step-2", "step-3", "step-4"]
    assert all(sorted(f.name for f in p.iterdir()) == ["adapter_config.json", "adapter_model.safetensors",
                                                        "checkpoint.json"] for p in steps)
    assert sorted(p.name for p in (run / "training_state").iterdir()) == ["step-3", "step-4"]


@pytest.fixture(scope="module")
def two_processes(cache, tmp_path_factory):
    """Three updates of the full tiny model by two FSDP processes under torchrun (update 1 runs at lr 0, so the
    third is the first whose loss shows an update)."""
    run = tmp_path_factory.mktemp("torchrun") / "run"
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    cmd = [sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc_per_node=2", "-m", "rigidbench",
           "train", "--config", "tiny", "--set", "mode=full", "--set", "max_steps=3", "--set", "checkpoint_every=3",
           "--cache", str(cache), "--out", str(run), "--no-progress"]
    done = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-3000:]
    return run


def test_torchrun_runs_fsdp_steps_of_the_full_tiny_model(two_processes):
    run = two_processes
    assert [m["step"] for m in metrics(run)] == [1, 2, 3]
    record = json.loads((run / "run.json").read_text())[0]
    assert (record["world_size"], record["wrapper"], record["examples_per_update"]) == \
        (2, "FSDP2 fully_shard per block, then root", 4)
    assert sorted(p.name for p in (run / "training_state" / "step-3" / "dcp").glob("*.distcp")) == \
        ["__0_0.distcp", "__1_0.distcp"]
    from diffusers import WanTransformer3DModel

    trained = WanTransformer3DModel.from_pretrained(run / "checkpoints" / "step-3")
    base = tiny.tiny_transformer()
    assert torch.equal(trained.condition_embedder.time_proj.weight, base.condition_embedder.time_proj.weight)
    assert not torch.equal(trained.blocks[0].attn1.to_q.weight, base.blocks[0].attn1.to_q.weight)


def test_two_processes_train_as_one_process_on_the_same_global_batch(two_processes, cache, tmp_path, monkeypatch,
                                                                     torch_single_thread):
    """One process with 2 micro-batches of 2 (gradient accumulation) sees what the 2 ranks of 2 see: the same 4
    examples per update (rank r / micro-batch r takes positions 2r, 2r + 1 of each 4), the mean of the two
    batch losses and of their gradients. Its draws are made those of the 2 ranks: with ``objective.draws:
    shared`` every rank draws with the seed of (step, micro-batch 0, rank 0), so micro-batch 1 draws with it too.
    The curves then agree to float rounding (measured: 1e-7; a plain one-process run of batch 4, whose draws
    differ for 2 of the 4 examples, is 0.6-1.1% off in loss and 20% in gradient norm), so the 1e-5 tolerance
    leaves no room for a rank that logs only its own loss, skips the gradient all-reduce or reads the other
    rank's examples."""
    from rigidbench.train import trainer

    monkeypatch.setattr(trainer, "draw_seed", lambda cfg, step, micro, rank: trainer.stream_seed(cfg.seed, step, 0, 0))
    one = tmp_path / "one"
    train(tiny_cfg("full", 3, 3, "batch_size=2", "grad_accum=2"), cache, one, progress=False)
    two, single = metrics(two_processes), metrics(one)
    assert [m["examples_seen"] for m in single] == [m["examples_seen"] for m in two] == [4, 8, 12]
    assert [m["timestep"] for m in single] == [m["timestep"] for m in two]
    assert [m["lr"] for m in single] == [m["lr"] for m in two] and two[1]["lr"] > 0
    assert [m["loss"] for m in single] == pytest.approx([m["loss"] for m in two], rel=1e-5)
    assert [m["grad_norm"] for m in single] == pytest.approx([m["grad_norm"] for m in two], rel=1e-5)


def _merged_lora(adapter_dir):
    """The tiny base transformer with the adapter merged by hand: W += alpha / r * B @ A."""
    from safetensors.torch import load_file

    config = json.loads((adapter_dir / "adapter_config.json").read_text())
    scale = config["lora_alpha"] / config["r"]
    state = load_file(adapter_dir / "adapter_model.safetensors")
    model = tiny.tiny_transformer()
    merged = 0
    with torch.no_grad():
        for key, a in state.items():
            if ".lora_A." not in key:
                continue
            module = key.removeprefix("base_model.model.").split(".lora_A.")[0]
            b = state[key.replace(".lora_A.", ".lora_B.")]
            model.get_submodule(module).weight += scale * (b @ a)
            merged += 1
    return model, merged


def _velocity(model):
    g = torch.Generator().manual_seed(5)
    objective = FlowMatchingObjective()
    z = torch.randn(1, 48, 3, 4, 8, generator=g)
    index, noise = objective.draw(g, z.shape)
    with torch.no_grad():
        return transformer_prediction(model, objective.prepare(z, noise, index), torch.randn(1, 512, 32, generator=g))


def test_tiny_lora_and_full_checkpoints_load_through_the_wan_predictor(uninterrupted, train_split, torch_single_thread):
    from rigidbench.groundtruth.bundle import Sample
    from rigidbench.predictors import PREDICTORS, PredictContext

    sample = Sample(train_split / "00000")
    size = {"height": 64, "width": 128, "num_frames": 9, "steps": 2}
    for mode in ("lora", "full"):
        checkpoint = uninterrupted[mode] / "checkpoints" / "step-6"
        pipe = tiny.tiny_pipeline()
        predictor = PREDICTORS["wan-2.2"].create()
        options = {**size, "pipeline": pipe, "checkpoint": str(checkpoint)}
        ctx = PredictContext(seed=0, options=MappingProxyType(options))
        try:
            pred = predictor.predict(sample, ctx)
        finally:
            predictor.close()
        assert pred.frames.shape == (9, 64, 128, 3)
        loaded = pred.metadata["checkpoint_loaded"]
        if mode == "lora":
            reference, merged = _merged_lora(checkpoint)
            assert loaded["lora_layers"] == merged == 20 and loaded["rank"] == 4
        else:
            from diffusers import WanTransformer3DModel

            reference = WanTransformer3DModel.from_pretrained(checkpoint)
            assert loaded["loader"]
        # the predictor's transformer computes what the trained weights compute
        assert torch.allclose(_velocity(pipe.transformer), _velocity(reference), atol=1e-5)
        assert not torch.allclose(_velocity(tiny.tiny_transformer()), _velocity(reference), atol=1e-5)


def test_sharded_preprocess_reads_as_the_single_cache(train_split, cache, tmp_path, torch_single_thread):
    """Shards 0/2 and 1/2 (job arrays) each encode their part of the clips into the one cache; together they
    hold exactly the examples, prompts and latents of one unsharded run."""
    out = tmp_path / "sharded"
    for shard in ("0/2", "1/2"):
        assert main(["preprocess", "--data", str(train_split), "--out", str(out), "--model", "tiny",
                     "--no-progress", "--shard", shard]) == 0
    assert not list(out.glob("part-*")) and sorted(p.stem for p in (out / ".stages" / "preprocess").glob("0*.json")) \
        == ["00000", "00001"]
    whole, parts = LatentCache(cache), LatentCache(out)
    assert parts.ids == whole.ids and len(parts) == TRAIN_IDS
    for example_id in whole.ids:
        assert torch.equal(parts.latent(example_id), whole.latent(example_id))
        assert torch.equal(parts.text(example_id), whole.text(example_id))
