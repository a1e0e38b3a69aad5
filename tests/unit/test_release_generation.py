"""Issue 24, items 1-3: local videos are generated as the paper's runs generated them (the authors' release):
wan-2.2 samples with DiffSynth's flow-matching Euler schedule; every example starts from its own noise,
derived from the base seed and its id; a local model's video is stored without chroma subsampling or loss.
Tiny randomly initialised pipelines of the real classes, CPU, no network."""

import hashlib
import json
import os
import shutil
import subprocess
import sys
import types
from pathlib import Path
from types import MappingProxyType

import numpy as np
import pytest

torch = pytest.importorskip("torch")
pytest.importorskip("diffusers")
pytest.importorskip("transformers")

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "fixtures"))

import tiny_video_models as tiny  # noqa: E402
from replicate_server import make_split  # noqa: E402

from rigidbench.errors import UserError  # noqa: E402
from rigidbench.folders import GENERATION_FILE  # noqa: E402
from rigidbench.pipeline.predict import predict, write_prediction  # noqa: E402
from rigidbench.predictors import PREDICTORS, SEED_RULE, PredictContext, example_seed  # noqa: E402
from rigidbench.video import probe_video, read_video  # noqa: E402

pytestmark = pytest.mark.usefixtures("torch_one_thread")

WAN_SIZE = {"height": 64, "width": 96, "num_frames": 5, "steps": 2}


def ctx_for(seed=0, **options):
    return PredictContext(seed=seed, options=MappingProxyType(options))


def tiny_sample(height=64, width=96):
    """What model_inputs reads from a reference Sample: frame 0, its PNG path and the task prompt."""
    frame = tiny.textured_frame(height, width)
    return types.SimpleNamespace(frame=lambda i: frame, first_frame_path=Path("frame_0000.png"),
                                 prompt="An apple drops onto the counter.")


# -- 1. the sampler ---------------------------------------------------------------------------------------


def diffsynth_wan_schedule(steps: int, shift: float = 5.0):
    """DiffSynth-Studio 2.0.18, FlowMatchScheduler("Wan").set_timesteps (denoising strength 1), written out
    here: sigma_min 0, sigma_max 1, a float32 grid of steps + 1 points without its last, shifted."""
    grid = torch.linspace(1.0, 0.0, steps + 1)[:-1]
    sigmas = shift * grid / (1 + (shift - 1) * grid)
    return sigmas, sigmas * 1000


def closed_form(steps: int, shift: float = 5.0) -> np.ndarray:
    """The same schedule in float64: sigma_i = s u / (1 + (s - 1) u), u = 1 - i / steps."""
    u = 1.0 - np.arange(steps) / steps
    return shift * u / (1.0 + (shift - 1.0) * u)


def timesteps_seen(pipe) -> list[float]:
    """Record the timestep of every transformer call (the largest over tokens: the first latent frame,
    pinned to the image, is called at 0)."""
    seen = []
    pipe.transformer.register_forward_pre_hook(
        lambda module, args, kwargs: seen.append(float(kwargs["timestep"].max())), with_kwargs=True)
    return seen


def test_flow_euler_sigmas_and_timesteps_are_diffsynths_for_50_steps():
    from rigidbench.predictors.wan_sampler import flow_euler_scheduler

    scheduler = flow_euler_scheduler()
    scheduler.set_timesteps(50)  # what WanImageToVideoPipeline asks for
    sigmas, timesteps = diffsynth_wan_schedule(50)
    assert scheduler.sigmas.dtype == torch.float32 and scheduler.sigmas.shape == (51,)
    assert torch.equal(scheduler.sigmas[:-1], sigmas) and float(scheduler.sigmas[-1]) == 0.0  # bit for bit
    assert torch.equal(scheduler.timesteps, timesteps)
    assert np.allclose(scheduler.sigmas[:-1].numpy(), closed_form(50), rtol=0, atol=2e-7)
    assert float(scheduler.sigmas[-2]) == pytest.approx(5 * 0.02 / (1 + 4 * 0.02), abs=1e-7)  # 0.0926, not 0.024


def test_flow_euler_steps_are_diffsynths_euler_steps():
    """x <- x + (sigma_next - sigma) v, the last step to sigma 0 (DiffSynth's FlowMatchScheduler.step)."""
    from rigidbench.predictors.wan_sampler import flow_euler_scheduler

    scheduler = flow_euler_scheduler()
    scheduler.set_timesteps(50)
    sigmas, timesteps = diffsynth_wan_schedule(50)
    generator = torch.Generator().manual_seed(0)
    x = expected = torch.randn(1, 4, 2, 3, 3, generator=generator)
    for i, t in enumerate(scheduler.timesteps):
        v = torch.randn(x.shape, generator=generator)
        x = scheduler.step(v, t, x, return_dict=False)[0]
        sigma_next = sigmas[i + 1] if i + 1 < len(sigmas) else 0
        expected = expected + v * (sigma_next - sigmas[i])
    assert torch.allclose(x, expected, rtol=0, atol=1e-6)


def test_wan_samples_with_the_release_schedule_by_default():
    pipe = tiny.tiny_wan()  # built with UniPC, as the Diffusers repository ships it
    seen = timesteps_seen(pipe)
    predictor = PREDICTORS["wan-2.2"].create()
    pred = predictor.predict(tiny_sample(), ctx_for(3, pipeline=pipe, **{**WAN_SIZE, "steps": 50}))
    predictor.close()
    per_step = seen[::2]  # guidance 5.0: a conditional and an unconditional call per step
    assert len(seen) == 100 and seen[1::2] == per_step
    assert np.array_equal(np.float32(per_step), diffsynth_wan_schedule(50)[1].numpy())
    assert pred.metadata["sampler"] == "flow-euler" and pred.metadata["scheduler"] == "WanFlowEulerScheduler"


def test_unipc_stays_a_named_option_and_is_recorded_as_a_difference():
    from diffusers import UniPCMultistepScheduler

    pipe = tiny.tiny_wan()
    unipc = pipe.scheduler
    predictor = PREDICTORS["wan-2.2"].create()
    euler = predictor.predict(tiny_sample(), ctx_for(3, pipeline=pipe, **WAN_SIZE))  # swaps the scheduler in
    predictor.close()
    seen = timesteps_seen(pipe)
    ctx = ctx_for(3, pipeline=pipe, sampler="unipc", **{**WAN_SIZE, "steps": 50})
    pred = predictor.predict(tiny_sample(), ctx)
    predictor.close()
    assert pipe.scheduler is unipc and isinstance(unipc, UniPCMultistepScheduler)  # the pipeline's own, restored
    assert not np.allclose(np.float32(seen[::2]), diffsynth_wan_schedule(50)[1].numpy(), atol=1.0)
    assert pred.metadata["sampler"] == "unipc" and pred.metadata["scheduler"] == "UniPCMultistepScheduler"
    small = predictor.predict(tiny_sample(), ctx_for(3, pipeline=pipe, sampler="unipc", **WAN_SIZE))
    assert not np.array_equal(small.frames, euler.frames)  # two steps of each: the samplers differ
    assert predictor.settings(ctx)["sampler"] == "unipc"
    info = predictor.generation_info(ctx)
    assert info["sampler"] == "unipc" and info["differs_from_release"] == {"sampler": ["unipc", "flow-euler"]}
    with pytest.raises(UserError, match="option sampler must be one of flow-euler, unipc, got 'ddim'"):
        predictor.settings(ctx_for(sampler="ddim"))


# -- 2. seeds -----------------------------------------------------------------------------------------------


def test_example_seeds_are_a_stable_hash_of_the_base_seed_and_the_id():
    # the first 8 hex digits of sha256("<base>/<id>"), top bit cleared (written out from the rule, not the code)
    digest = hashlib.sha256(b"0/00000").hexdigest()
    assert example_seed(0, "00000") == int(digest[:8], 16) % 2**31
    seeds = {example_seed(base, f"{i:05d}") for base in (0, 1) for i in range(100)}
    assert len(seeds) == 200 and all(0 <= s < 2**31 for s in seeds)
    # the same in any Python process (hash() of a str changes with PYTHONHASHSEED; this must not)
    code = "from rigidbench.predictors import example_seed; print(example_seed(7, '00042'))"
    for hash_seed in ("1", "2"):
        out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True,
                             env={**os.environ, "PYTHONHASHSEED": hash_seed}).stdout
        assert int(out) == example_seed(7, "00042")


def record_noise(pipe) -> list:
    """The initial noise of every generation by ``pipe`` (prepare_latents' latents), in call order."""
    noise = []
    original = pipe.prepare_latents

    def spy(*args, **kwargs):
        out = original(*args, **kwargs)
        noise.append(out[0].detach().clone())
        return out

    pipe.prepare_latents = spy
    return noise


def run_stage(split, out, seed, pipe, ids=None):
    ctx = PredictContext(seed=seed, options=MappingProxyType({"pipeline": pipe, **WAN_SIZE}))
    summary = predict("wan-2.2", split, out, ctx, ids=ids, progress=False)
    assert not summary.failed, summary.failed
    return json.loads((out / GENERATION_FILE).read_text())


def test_each_example_gets_its_own_noise_and_the_same_example_the_same_noise(tmp_path):
    split = make_split(tmp_path / "eval", 2, size=(96, 64))
    pipe = tiny.tiny_wan()
    noise = record_noise(pipe)
    doc = run_stage(split, tmp_path / "a", 5, pipe)
    first, second = noise  # 00000, 00001 (one at a time, in order)
    assert first.shape == second.shape and not torch.equal(first, second)
    for sample_id in ("00000", "00001"):
        assert doc["examples"][sample_id]["seed"] == example_seed(5, sample_id)
    assert doc["settings"]["seed"] == 5 and doc["settings"]["seeds"] == SEED_RULE
    assert doc["model"]["seed"] == 5 and doc["model"]["seeds"] == SEED_RULE

    again = run_stage(split, tmp_path / "b", 5, pipe, ids=["00001"])  # the same example, another run
    assert torch.equal(noise[2], second) and again["examples"]["00001"]["seed"] == example_seed(5, "00001")
    run_stage(split, tmp_path / "c", 6, pipe, ids=["00001"])  # another base seed
    assert not torch.equal(noise[3], second)


def test_videos_of_the_earlier_one_seed_rule_are_not_reused(tmp_path):
    """A folder written before per-example seeds (settings without "seeds") is generated again."""
    split = make_split(tmp_path / "eval", 1, size=(96, 64))
    out = tmp_path / "out"
    pipe = tiny.tiny_wan()
    run_stage(split, out, 0, pipe)
    settings = json.loads((out / ".predictor.json").read_text())
    del settings["seeds"]
    (out / ".predictor.json").write_text(json.dumps(settings) + "\n")
    shutil.rmtree(out / ".stages")  # such a folder has no ledger either: only .predictor.json says how it was made
    ctx = PredictContext(seed=0, options=MappingProxyType({"pipeline": pipe, **WAN_SIZE}))
    assert predict("wan-2.2", split, out, ctx, progress=False).skipped == []


# -- 3. storage ---------------------------------------------------------------------------------------------


def test_a_stored_tiny_model_video_round_trips_without_chroma_loss(tmp_path):
    predictor = PREDICTORS["wan-2.2"].create()
    pred = predictor.predict(tiny_sample(), ctx_for(1, pipeline=tiny.tiny_wan(), **WAN_SIZE))
    predictor.close()
    write_prediction(pred, tmp_path, "00003")
    decoded = read_video(tmp_path / "00003.mp4")
    assert decoded.frames.shape == pred.frames.shape == (5, 64, 96, 3)
    assert np.array_equal(decoded.frames, pred.frames)  # every pixel, so no chroma subsampling and no loss
    assert np.allclose(decoded.times_s, np.arange(5) / 24.0)
    info = probe_video(tmp_path / "00003.mp4")
    assert info.codec == "h264" and info.fps_nominal == pytest.approx(24.0)
    # the model's colour detail is there to lose: 4:2:0 at crf 18 (the earlier storage) does not keep it
    write_prediction(type(pred)(frames=pred.frames, times_s=pred.times_s, lossless=False), tmp_path, "00004")
    assert not np.array_equal(read_video(tmp_path / "00004.mp4").frames, pred.frames)
