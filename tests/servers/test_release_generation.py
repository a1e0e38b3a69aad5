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

from fixtures import tiny_video_models as tiny  # noqa: E402
from fixtures.replicate_server import make_split  # noqa: E402

from rigidbench.driver import RunOptions, Selection  # noqa: E402
from rigidbench.errors import UserError  # noqa: E402
from rigidbench.folders import GENERATION_FILE  # noqa: E402
from rigidbench.predictors import PREDICTORS, SEED_RULE, PredictContext, example_seed  # noqa: E402
from rigidbench.stages.predict import predict, write_prediction  # noqa: E402
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
    assert info["sampler"] == "unipc" and info["differs_from_release"]["sampler"] == ["unipc", "flow-euler"]
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
    summary = predict("wan-2.2", split, out, ctx, run=RunOptions(Selection.of(ids), progress=False))
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
    settings = json.loads((out / "generation.json").read_text())["settings"]
    del settings["seeds"]
    (out / ".predictor.json").write_text(json.dumps(settings) + "\n")  # how folders before ledgers said it
    (out / "generation.json").unlink()
    shutil.rmtree(out / ".stages")  # such a folder has no ledger either: only .predictor.json says how it was made
    ctx = PredictContext(seed=0, options=MappingProxyType({"pipeline": pipe, **WAN_SIZE}))
    assert predict("wan-2.2", split, out, ctx, run=RunOptions(progress=False)).reused == []


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


# -- 4. DiffSynth's numerics: recipe=release (issue 32, item 13) -------------------------------------------------

RELEASE = {"timestep_dtype": "bfloat16", "update_dtype": "bfloat16", "vae_codec": "diffsynth-tiled"}


def test_the_release_recipe_sets_diffsynths_numerics_and_is_recorded():
    from rigidbench.predictors.options import model_options

    predictor = PREDICTORS["wan-2.2"].create()
    ours, release = ctx_for(3), ctx_for(3, **model_options(PREDICTORS["wan-2.2"], "recipe=release"))
    assert "numerics" not in predictor.settings(ours)  # the settings (and keys) of earlier folders are unchanged
    assert predictor.settings(release)["numerics"] == RELEASE
    assert predictor.settings(ctx_for(3, **RELEASE)) == predictor.settings(release)  # the same videos, one key
    info = predictor.generation_info(release)
    assert info["recipe"] == "release" and info["numerics"] == RELEASE and "differs_from_release" not in info
    assert "bfloat16" in info["numerics_described"]["timestep_dtype"]
    mixed = ctx_for(3, recipe="release", update_dtype="float32")  # an option beside the recipe overrides it
    assert predictor.numerics(mixed) == {**RELEASE, "update_dtype": "float32"}
    assert predictor.generation_info(mixed)["differs_from_release"] == {"update_dtype": ["float32", "bfloat16"]}
    with pytest.raises(UserError, match="needs sampler flow-euler, got unipc"):
        predictor.settings(ctx_for(recipe="release", sampler="unipc"))
    with pytest.raises(UserError, match="give one of them"):
        predictor.settings(ctx_for(vae_codec="diffsynth-tiled", tiled_vae=True))
    with pytest.raises(UserError, match="must be one of ours, release"):
        model_options(PREDICTORS["wan-2.2"], "recipe=diffsynth")


def test_release_timesteps_reach_the_transformer_rounded_to_bfloat16():
    pipe = tiny.tiny_wan()
    predictor = PREDICTORS["wan-2.2"].create()
    size = {**WAN_SIZE, "height": 32, "width": 32, "steps": 50, "guidance_scale": 1.0}  # one call per step
    ctx = ctx_for(3, pipeline=pipe, timestep_dtype="bfloat16", **size)
    predictor.pipeline(ctx)  # loads and configures: the rounding hook comes first
    seen, smallest = timesteps_seen(pipe), []
    pipe.transformer.register_forward_pre_hook(
        lambda module, args, kwargs: smallest.append(float(kwargs["timestep"].min())), with_kwargs=True)
    predictor.predict(tiny_sample(), ctx)
    predictor.close()
    expected = diffsynth_wan_schedule(50)[1].bfloat16().float().numpy()  # DiffSynth: timestep.to(bfloat16)
    assert np.array_equal(np.float32(seen), expected) and seen[1] == 996.0  # 995.93 reaches the model as 996
    assert set(smallest) == {0.0}  # the pinned first slot still sees 0
    seen.clear()
    predictor.predict(tiny_sample(), ctx_for(3, pipeline=pipe, **{**size, "steps": 2}))  # ours: the hook is gone
    predictor.close()
    assert seen == [1000.0, pytest.approx(2500 / 3, abs=1e-3)]  # 833.33 (bfloat16: 832)


def test_the_bfloat16_update_is_diffsynths_euler_step_on_bfloat16_latents():
    """FlowMatchScheduler.step on bfloat16 latents, written with torch's own bfloat16 arithmetic."""
    from rigidbench.predictors.wan_sampler import flow_euler_scheduler

    scheduler = flow_euler_scheduler()
    scheduler.update_dtype = "bfloat16"
    scheduler.set_timesteps(50)
    sigmas, _ = diffsynth_wan_schedule(50)
    generator = torch.Generator().manual_seed(0)
    x = torch.randn(1, 4, 2, 3, 3, generator=generator)
    expected = x.bfloat16()  # DiffSynth: the noise cast to the pipeline's dtype
    for i, t in enumerate(scheduler.timesteps):
        v = torch.randn(x.shape, generator=generator).bfloat16()
        x = scheduler.step(v, t, x, return_dict=False)[0]
        sigma_next = sigmas[i + 1] if i + 1 < len(sigmas) else torch.tensor(0.0)
        expected = expected + v * (sigma_next - sigmas[i])
    assert x.dtype == torch.bfloat16 and torch.equal(x, expected)  # bit for bit
    scheduler.update_dtype = "float32"
    scheduler.set_timesteps(50)
    assert scheduler.step(v, scheduler.timesteps[0], x.float(), return_dict=False)[0].dtype == torch.bfloat16
    assert scheduler.step(v.float(), scheduler.timesteps[1], x.float(), return_dict=False)[0].dtype == torch.float32


def test_diffsynths_tiles_at_the_papers_size():
    """1280x704: latents 44 x 80 -> rows from 0 and 15, columns from 0, 26 and 52 (6 tiles, the last of each
    cut at the edge); the first frame's 704 x 1280 pixels in tiles of 480 x 832 from 0, 240 / 0, 416, 832."""
    from rigidbench.predictors.wan_diffsynth import TILE_SIZE, TILE_STRIDE, tile_starts

    assert tile_starts(44, TILE_SIZE[0], TILE_STRIDE[0]) == [0, 15]
    assert tile_starts(80, TILE_SIZE[1], TILE_STRIDE[1]) == [0, 26, 52]
    assert tile_starts(704, 16 * TILE_SIZE[0], 16 * TILE_STRIDE[0]) == [0, 240]
    assert tile_starts(1280, 16 * TILE_SIZE[1], 16 * TILE_STRIDE[1]) == [0, 416, 832]
    assert tile_starts(22, 30, 15) == [0]  # 640x352 fits one tile: nothing is blended


def reference_blend(tiles, out_shape, border):
    """Written from DiffSynth's description, in float64: each tile's output times a weight that is 1 but for
    a linear ramp (1 .. b) / b over the b cells of each side facing another tile; summed and normalised.
    ``tiles``: [(top, left, first_row, last_row, first_col, last_col, output (C,T,h,w))]."""
    values, weight = np.zeros(out_shape), np.zeros((1,) + out_shape[1:])

    def axis(n, b, first, last):
        i = np.arange(n, dtype=np.float64)
        w = np.ones(n)
        if not first:
            w = np.minimum(w, (i + 1) / b)
        if not last:
            w = np.minimum(w, (n - i) / b)
        return w

    for top, left, first_r, last_r, first_c, last_c, out in tiles:
        h, w = out.shape[-2:]
        m = np.minimum(axis(h, border[0], first_r, last_r)[:, None], axis(w, border[1], first_c, last_c)[None, :])
        values[:, :, top:top + h, left:left + w] += out * m
        weight[:, :, top:top + h, left:left + w] += m
    return values / weight


def test_tiled_decode_and_encode_blend_tiles_as_diffsynth():
    from rigidbench.predictors.wan_diffsynth import TiledEncoder, tiled_decode

    vae = tiny.tiny_wan().vae
    g = torch.Generator().manual_seed(0)
    latents = torch.randn(1, 48, 2, 4, 6, generator=g)
    with torch.no_grad():
        ours = tiled_decode(vae, latents, size=(2, 4), stride=(1, 2))  # rows from 0, 1, 2; columns from 0, 2
        whole = vae.decode(latents).sample
        tiles = [(16 * r, 16 * c, r == 0, r + 2 >= 4, c == 0, c + 4 >= 6,
                  vae.decode(latents[:, :, :, r:r + 2, c:c + 4]).sample[0].double().numpy())
                 for r in (0, 1, 2) for c in (0, 2)]
    expected = np.clip(reference_blend(tiles, (3, 5, 64, 96), (16, 32)), -1, 1)
    assert ours.shape == whole.shape == (1, 3, 5, 64, 96)
    assert np.allclose(ours[0].numpy(), expected, atol=1e-5)
    assert float((ours - whole).abs().max()) > 1e-3  # the tiles see less context than the whole: seams differ

    video = torch.rand(1, 3, 1, 128, 128, generator=g) * 2 - 1
    encoder = TiledEncoder(vae, size=(4, 4), stride=(2, 2))  # 64-pixel tiles from 0, 32, 64 on both axes
    with torch.no_grad():
        blended = encoder(video).latents
        tiles = [(p // 16, q // 16, p == 0, p + 64 >= 128, q == 0, q + 64 >= 128,
                  vae.encode(video[:, :, :, p:p + 64, q:q + 64]).latent_dist.mode()[0].double().numpy())
                 for p in (0, 32, 64) for q in (0, 32, 64)]
    assert blended.shape == (1, 48, 1, 8, 8)
    assert np.allclose(blended[0].numpy(), reference_blend(tiles, (48, 1, 8, 8), (2, 2)), atol=1e-5)
    TiledEncoder.install(vae)
    assert isinstance(vae.encode, TiledEncoder)
    TiledEncoder.remove(vae)
    assert "encode" not in vae.__dict__  # the class's encode again


def test_diffsynth_tiled_codec_within_one_tile_changes_only_the_uint8_conversion():
    """At a size inside one tile the tiled encode and decode are the untiled ones, so the frames differ from
    ours only by DiffSynth's conversion: ((x + 1) x 127.5) truncated where ours rounds, at most one level."""
    from rigidbench.predictors.wan_diffsynth import diffsynth_to_uint8

    pipe, predictor = tiny.tiny_wan(), PREDICTORS["wan-2.2"].create()
    ours = predictor.predict(tiny_sample(), ctx_for(4, pipeline=pipe, **WAN_SIZE))
    predictor.close()
    tiled = predictor.predict(tiny_sample(), ctx_for(4, pipeline=pipe, vae_codec="diffsynth-tiled", **WAN_SIZE))
    predictor.close()
    diff = ours.frames.astype(int) - tiled.frames.astype(int)
    assert tiled.frames.shape == ours.frames.shape and set(np.unique(diff)) == {0, 1}
    assert tiled.metadata["numerics"]["vae_codec"] == "diffsynth-tiled" and "encode" not in pipe.vae.__dict__
    x = torch.tensor([-1.0, -0.2, 0.0, 0.5, 0.999, 1.0]).view(1, 1, 6, 1, 1).expand(1, 3, 6, 1, 1)
    assert diffsynth_to_uint8(x)[:, 0, 0, 0].tolist() == [0, 102, 127, 191, 254, 255]  # floor((x + 1) x 127.5)
    assert diffsynth_to_uint8(x.bfloat16())[:, 0, 0, 0].tolist() == [0, 102, 127, 191, 255, 255]  # bfloat16 rounds


def test_the_release_recipe_generates_end_to_end_in_bfloat16():
    pipe, predictor = tiny.tiny_wan().to(torch.bfloat16), PREDICTORS["wan-2.2"].create()
    ours = predictor.predict(tiny_sample(), ctx_for(2, pipeline=pipe, **WAN_SIZE))
    predictor.close()
    release = predictor.predict(tiny_sample(), ctx_for(2, pipeline=pipe, recipe="release", **WAN_SIZE))
    predictor.close()
    assert release.frames.dtype == np.uint8 and release.frames.shape == ours.frames.shape == (5, 64, 96, 3)
    assert release.metadata["numerics"] == RELEASE and not np.array_equal(release.frames, ours.frames)
    assert pipe.scheduler.update_dtype == "float32" and not pipe.transformer._forward_pre_hooks  # undone by close
