"""wan-2.2 and cosmos-2.5: the paper's settings, options, checkpoints, the Cosmos guardrail and the
torchvision-free conditioning path, on tiny randomly initialised pipelines of the real classes (CPU,
no network, no weights). End to end through predict, validate and evaluate: tests/integration."""

import json
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

from rigidbench.benchmark import NEGATIVE_PROMPT, full_prompt  # noqa: E402
from rigidbench.errors import PredictionError, RigidBenchError, UserError  # noqa: E402
from rigidbench.predictors import PREDICTORS, Kind, PredictContext  # noqa: E402
from rigidbench.predictors import cosmos, wan  # noqa: E402
from rigidbench.stages.predict import write_prediction  # noqa: E402
from rigidbench.video import probe_video, read_video  # noqa: E402

pytestmark = pytest.mark.usefixtures("torch_one_thread")

WAN_SIZE = {"height": 64, "width": 96, "num_frames": 5, "steps": 2}
COSMOS_SIZE = {"height": 48, "width": 80, "num_frames": 5, "steps": 2}


def fake_sample(height, width, prompt="An apple drops onto the counter."):
    """What model_inputs reads from a reference Sample: frame 0, its PNG path and the task prompt."""
    frame = tiny.textured_frame(height, width)
    return types.SimpleNamespace(frame=lambda i: frame, first_frame_path=Path("frame_0000.png"), prompt=prompt)


def ctx_for(seed=0, **options):
    return PredictContext(seed=seed, options=MappingProxyType(options))


def run(name, options, seed=0, sample=None):
    predictor = PREDICTORS[name].create()
    size = WAN_SIZE if name == "wan-2.2" else COSMOS_SIZE
    ctx = ctx_for(seed, **size, **options)
    try:
        return predictor.predict(sample or fake_sample(size["height"], size["width"]), ctx), predictor, ctx
    finally:
        predictor.close()


# -- registry and the paper's settings --------------------------------------------------------------------


def test_both_models_are_registered_as_local_models_and_import_nothing_heavy():
    for name, alias in (("wan-2.2", "wan"), ("cosmos-2.5", "cosmos")):
        assert PREDICTORS[name].kind == Kind.LOCAL and PREDICTORS[alias].name == name
    code = ("import sys; from rigidbench.predictors import PREDICTORS; "
            "[PREDICTORS[n].create() for n in ('wan-2.2', 'cosmos-2.5')]; "
            "import rigidbench.predictors.wan, rigidbench.predictors.cosmos; "
            "print(sorted(m for m in ('torch', 'diffusers', 'transformers', 'peft') if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "[]"


def test_wan_defaults_are_the_papers_and_the_run_records_them():
    predictor = PREDICTORS["wan-2.2"].create()
    ctx = PredictContext(seed=7)
    settings = predictor.settings(ctx)
    assert settings == {"seed": 7, "source": "hub", "model": "Wan-AI/Wan2.2-TI2V-5B-Diffusers", "revision": "main",
                        "height": 704, "width": 1280, "num_frames": 49, "fps": 24.0, "steps": 50,
                        "guidance_scale": 5.0, "dtype": "bfloat16", "tiled_vae": False, "sampler": "flow-euler",
                        "checkpoint": None}
    json.dumps(settings)  # .predictor.json
    info = predictor.generation_info(ctx)
    json.dumps(info)  # generation.json
    assert info["model"] == "Wan-AI/Wan2.2-TI2V-5B-Diffusers" and info["pipeline_class"] == "diffusers.WanImageToVideoPipeline"
    assert "commit" in info and info["num_inference_steps"] == 50 and info["guidance_scale"] == 5.0
    assert "not stated in the paper" in info["guidance_scale_source"]
    assert info["negative_prompt"] == NEGATIVE_PROMPT and info["seed"] == 7 and "differs_from_paper" not in info
    assert info["offload"] is False and info["tiled_vae"] is False and info["device"] in ("cpu", "cuda")
    assert info["sampler"] == "flow-euler" and "DiffSynth" in info["release_sampler"]
    assert "libx264rgb" in info["storage"] and "sha256" in info["seeds"]
    # recipe ours: the release's sampler, diffusers' numerics (recipe=release takes DiffSynth's)
    assert info["recipe"] == "ours" and info["differs_from_release"] == {
        "timestep_dtype": ["float32", "bfloat16"], "update_dtype": ["float32", "bfloat16"],
        "vae_codec": ["diffusers", "diffsynth-tiled"]}


def test_cosmos_defaults_are_the_papers():
    predictor = PREDICTORS["cosmos-2.5"].create()
    settings = predictor.settings(ctx_for(no_guardrail=True))
    assert settings["model"] == "nvidia/Cosmos-Predict2.5-2B" and settings["revision"] == "diffusers/base/post-trained"
    assert (settings["width"], settings["height"], settings["num_frames"], settings["fps"], settings["steps"],
            settings["dtype"], settings["guidance_scale"]) == (1280, 704, 33, 16.0, 50, "bfloat16", 7.0)
    assert settings["guardrail"] == "pass-through (--no-guardrail)"
    assert predictor.settings(ctx_for())["guardrail"] == "cosmos_guardrail.CosmosSafetyChecker"


def test_overrides_are_validated_and_recorded_against_the_paper():
    predictor = PREDICTORS["wan-2.2"].create()
    info = predictor.generation_info(ctx_for(height=352, width=640, steps="4", guidance_scale=3.5))
    assert info["differs_from_paper"] == {"height": [352, 704], "width": [640, 1280], "steps": [4, 50]}
    assert info["guidance_scale"] == 3.5 and info["guidance_scale_source"] == "option"
    with pytest.raises(UserError, match="height must be a number"):
        predictor.settings(ctx_for(height="tall"))
    with pytest.raises(UserError, match="num_frames must be at least 1"):
        predictor.settings(ctx_for(num_frames=0))
    with pytest.raises(UserError, match="dtype must be one of"):
        predictor.settings(ctx_for(dtype="int8"))
    with pytest.raises(UserError, match="multiples of 32, got 1280x720"):
        predictor.settings(ctx_for(height=720))
    with pytest.raises(UserError, match="num_frames must be 4k \\+ 1"):
        predictor.settings(ctx_for(num_frames=48))
    assert PREDICTORS["cosmos-2.5"].create().settings(ctx_for(height=720 - 16, width=1280 + 16))["height"] == 704


def test_a_missing_model_is_a_clear_error_and_not_retried(tmp_path):
    predictor = PREDICTORS["wan-2.2"].create()
    ctx = ctx_for(model_path=str(tmp_path / "nowhere"))
    sample = fake_sample(64, 96)
    with pytest.raises(RigidBenchError, match="model_path .*nowhere is not a directory"):
        predictor.predict(sample, ctx)
    with pytest.raises(RigidBenchError, match="is not a directory"):  # the stored failure, at once
        predictor.predict(sample, ctx)
    predictor.close()


# -- Wan ----------------------------------------------------------------------------------------------------


def test_wan_makes_frames_at_24_fps_from_the_models_inputs(tmp_path):
    pipe = tiny.tiny_wan()
    calls = []
    original = type(pipe).__call__

    def spy(self, *args, **kwargs):
        calls.append(kwargs)
        return original(self, *args, **kwargs)

    sample = fake_sample(64, 96)
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(type(pipe), "__call__", spy)
        pred, _, _ = run("wan-2.2", {"pipeline": pipe}, seed=5, sample=sample)
    kwargs = calls[0]
    assert kwargs["prompt"] == full_prompt(sample.prompt) and kwargs["negative_prompt"] == NEGATIVE_PROMPT
    assert np.array_equal(np.asarray(kwargs["image"]), sample.frame(0))
    assert (kwargs["height"], kwargs["width"], kwargs["num_frames"], kwargs["num_inference_steps"]) == (64, 96, 5, 2)
    assert kwargs["guidance_scale"] == 5.0 and kwargs["output_type"] == "np"
    assert kwargs["generator"].device.type == "cpu" and kwargs["generator"].initial_seed() == 5
    assert pred.frames.dtype == np.uint8 and pred.frames.shape == (5, 64, 96, 3)
    assert np.allclose(pred.times_s, np.arange(5) / 24.0) and pred.fps == pytest.approx(24.0)
    assert pred.lossless is True and pred.metadata["seconds_model"] > 0 and pred.metadata["frames"] == 5
    assert pred.metadata["seed"] == 5 and pred.metadata["scheduler"] == "WanFlowEulerScheduler"
    write_prediction(pred, tmp_path, "00001")
    info = probe_video(tmp_path / "00001.mp4")
    assert info.n_frames == 5 and info.fps_nominal == pytest.approx(24.0) and (info.width, info.height) == (96, 64)


def test_wan_is_deterministic_per_seed_and_loads_its_pipeline_once():
    pipe = tiny.tiny_wan()
    predictor = PREDICTORS["wan-2.2"].create()
    ctx = ctx_for(0, pipeline=pipe, **WAN_SIZE)
    sample = fake_sample(64, 96)
    a = predictor.predict(sample, ctx).frames
    assert predictor._pipe is pipe
    b = predictor.predict(sample, ctx).frames
    c = predictor.predict(sample, ctx_for(1, pipeline=pipe, **WAN_SIZE)).frames
    assert np.array_equal(a, b) and not np.array_equal(a, c)
    predictor.close()
    assert predictor._pipe is None


def test_wan_first_frame_is_the_conditioning_image():
    """Wan 2.2 TI2V pins the first latent frame to the encoded image (expand_timesteps)."""
    pred, _, _ = run("wan-2.2", {"pipeline": tiny.tiny_wan()})
    other, _, _ = run("wan-2.2", {"pipeline": tiny.tiny_wan()}, seed=1)
    assert np.array_equal(pred.frames[0], other.frames[0]) and not np.array_equal(pred.frames[1:], other.frames[1:])


def test_tiled_vae_option_enables_tiling():
    pipe = tiny.tiny_wan()
    _, predictor, ctx = run("wan-2.2", {"pipeline": pipe, "tiled_vae": True})
    assert pipe.vae.use_tiling and predictor.settings(ctx)["tiled_vae"] is True


# -- Wan checkpoints ------------------------------------------------------------------------------------------


def lora_transformer(rank=4, alpha=8, seed=1):
    """A tiny Wan transformer with a random (non-zero) rank-``rank`` LoRA on the attention projections."""
    from peft import LoraConfig, get_peft_model

    config = LoraConfig(r=rank, lora_alpha=alpha, init_lora_weights=False, lora_dropout=0.0,
                        target_modules=["to_q", "to_k", "to_v", "to_out.0"])
    torch.manual_seed(seed)
    return get_peft_model(tiny.tiny_wan_transformer(), config), config


@pytest.fixture(scope="module")
def checkpoints(tmp_path_factory):
    """A PEFT adapter directory, the same adapter as a diffusers LoRA file, a fine-tuned transformer saved
    with save_pretrained and as a safetensors state dict; and the reference transformers they should give."""
    pytest.importorskip("peft")
    from diffusers import WanImageToVideoPipeline
    from peft import get_peft_model_state_dict
    from safetensors.torch import save_file

    root = tmp_path_factory.mktemp("checkpoints")
    peft_model, config = lora_transformer()
    peft_model.save_pretrained(root / "peft")
    # diffusers' format: the adapter of the bare transformer (as transformer.add_adapter gives it), "transformer."
    # prefixed by save_lora_weights, with the LoraConfig (alpha) as metadata
    layers = {k.removeprefix("base_model.model."): v for k, v in get_peft_model_state_dict(peft_model).items()}
    WanImageToVideoPipeline.save_lora_weights(root / "diffusers", transformer_lora_layers=layers,
                                              transformer_lora_adapter_metadata=config.to_dict())
    merged = peft_model.merge_and_unload()  # what the adapter should compute
    torch.manual_seed(11)
    finetuned = tiny.tiny_wan_transformer(seed=11)
    finetuned.save_pretrained(root / "full")
    save_file({k: v.contiguous() for k, v in finetuned.state_dict().items()}, root / "full.safetensors")
    return {"root": root, "merged": merged, "finetuned": finetuned}


def with_transformer(transformer):
    pipe = tiny.tiny_wan()
    pipe.register_modules(transformer=transformer)
    return pipe


def test_checkpoint_kinds_are_detected_from_their_files(checkpoints, tmp_path):
    root = checkpoints["root"]
    peft = wan.detect_checkpoint(root / "peft")
    assert peft["kind"] == "lora-peft" and peft["lora"]["r"] == 4 and peft["lora"]["lora_alpha"] == 8
    assert wan.detect_checkpoint(root / "diffusers")["kind"] == "lora"
    assert wan.detect_checkpoint(root / "diffusers" / "pytorch_lora_weights.safetensors")["kind"] == "lora"
    assert wan.detect_checkpoint(root / "full")["kind"] == "transformer-dir"
    assert wan.detect_checkpoint(root / "full.safetensors")["kind"] == "transformer-state-dict"
    with pytest.raises(wan.CheckpointError, match="does not exist"):
        wan.detect_checkpoint(tmp_path / "missing")
    (tmp_path / "weights.pt").write_bytes(b"")
    with pytest.raises(RigidBenchError, match="weights.pt: cannot be read as a PyTorch file"):  # .pt is read now
        wan.detect_checkpoint(tmp_path / "weights.pt")
    (tmp_path / "vae").mkdir()
    (tmp_path / "vae" / "config.json").write_text(json.dumps({"_class_name": "AutoencoderKLWan"}))
    with pytest.raises(wan.CheckpointError, match="describes a AutoencoderKLWan"):
        wan.detect_checkpoint(tmp_path / "vae")


def test_a_peft_lora_adapter_loads_with_its_alpha_and_changes_the_output(checkpoints):
    base, _, _ = run("wan-2.2", {"pipeline": tiny.tiny_wan()})
    pred, predictor, ctx = run("wan-2.2", {"pipeline": tiny.tiny_wan(), "checkpoint": str(checkpoints["root"] / "peft")})
    merged, _, _ = run("wan-2.2", {"pipeline": with_transformer(checkpoints["merged"])})
    assert not np.array_equal(pred.frames, base.frames)
    assert np.abs(pred.frames.astype(int) - merged.frames.astype(int)).max() <= 1  # the adapter, scaled by alpha / r
    loaded = pred.metadata["checkpoint_loaded"]
    assert loaded["lora_layers"] == 2 * 2 * 4 and loaded["rank"] == 4 and loaded["alpha"] == 8
    info = predictor.generation_info(ctx)["checkpoint"]
    assert info["kind"] == "lora-peft" and "LoRA adapter" in info["description"]
    assert all("sha256" in f for f in info["files"].values())
    assert predictor.settings(ctx)["checkpoint"]["kind"] == "lora-peft"


def test_a_diffusers_lora_file_loads_the_same_adapter(checkpoints):
    peft_pred, _, _ = run("wan-2.2", {"pipeline": tiny.tiny_wan(), "checkpoint": str(checkpoints["root"] / "peft")})
    pred, _, _ = run("wan-2.2", {"pipeline": tiny.tiny_wan(), "checkpoint": str(checkpoints["root"] / "diffusers")})
    assert np.array_equal(pred.frames, peft_pred.frames)
    assert pred.metadata["checkpoint_loaded"]["lora_layers"] == 16


def test_unprefixed_lora_keys_load_too(checkpoints, tmp_path):
    from peft import get_peft_model_state_dict
    from safetensors.torch import save_file

    peft_model, _ = lora_transformer(rank=4, alpha=4)
    layers = {k.removeprefix("base_model.model."): v for k, v in get_peft_model_state_dict(peft_model).items()}
    save_file(layers, tmp_path / "lora.safetensors")  # blocks.0.attn1.to_q.lora_A.weight, ...
    pred, _, _ = run("wan-2.2", {"pipeline": tiny.tiny_wan(), "checkpoint": str(tmp_path / "lora.safetensors")})
    merged, _, _ = run("wan-2.2", {"pipeline": with_transformer(peft_model.merge_and_unload())})
    assert np.abs(pred.frames.astype(int) - merged.frames.astype(int)).max() <= 1


def test_a_lora_for_another_model_is_refused(tmp_path):
    pytest.importorskip("peft")
    from safetensors.torch import save_file

    save_file({"transformer.blocks.0.nonexistent.lora_A.weight": torch.zeros(4, 8),
               "transformer.blocks.0.nonexistent.lora_B.weight": torch.zeros(8, 4)}, tmp_path / "other.safetensors")
    with pytest.raises(RigidBenchError, match="could not be loaded into the Wan transformer"):
        run("wan-2.2", {"pipeline": tiny.tiny_wan(), "checkpoint": str(tmp_path / "other.safetensors")})


def test_a_full_fine_tuned_transformer_loads_from_a_directory_or_a_state_dict(checkpoints):
    expected, _, _ = run("wan-2.2", {"pipeline": with_transformer(checkpoints["finetuned"])})
    base, _, _ = run("wan-2.2", {"pipeline": tiny.tiny_wan()})
    for path in ("full", "full.safetensors"):
        pred, predictor, ctx = run("wan-2.2", {"pipeline": tiny.tiny_wan(), "checkpoint": str(checkpoints["root"] / path)})
        assert np.array_equal(pred.frames, expected.frames) and not np.array_equal(pred.frames, base.frames)
        assert predictor.generation_info(ctx)["checkpoint"]["description"].startswith("full fine-tuned transformer")


def test_a_state_dict_of_another_architecture_is_refused(tmp_path):
    from safetensors.torch import save_file

    save_file({"blocks.0.weight": torch.zeros(3, 3)}, tmp_path / "other.safetensors")
    with pytest.raises(RigidBenchError, match="does not match the Wan transformer"):
        run("wan-2.2", {"pipeline": tiny.tiny_wan(), "checkpoint": str(tmp_path / "other.safetensors")})


# -- Cosmos: guardrail --------------------------------------------------------------------------------------


def cosmos_guardrail_installed():
    try:
        import cosmos_guardrail  # noqa: F401
    except ImportError:
        return False
    return True


@pytest.mark.skipif(cosmos_guardrail_installed(), reason="cosmos-guardrail is installed")
def test_cosmos_without_the_guardrail_package_names_the_extra_and_the_alternative():
    predictor = PREDICTORS["cosmos-2.5"].create()
    for call in (lambda: predictor.generation_info(ctx_for(pipeline=tiny.tiny_cosmos(), **COSMOS_SIZE)),
                 lambda: predictor.predict(fake_sample(48, 80), ctx_for(pipeline=tiny.tiny_cosmos(), **COSMOS_SIZE))):
        with pytest.raises(RigidBenchError) as err:
            call()
        assert "rigidbench[guardrail]" in str(err.value) and "--no-guardrail" in str(err.value)


def test_no_guardrail_prints_the_licence_terms_and_is_recorded(capsys):
    predictor = PREDICTORS["cosmos-2.5"].create()
    ctx = ctx_for(pipeline=tiny.tiny_cosmos(), no_guardrail=True, **COSMOS_SIZE)
    info = predictor.generation_info(ctx)
    printed = capsys.readouterr().err
    assert "NVIDIA Open Model License Agreement" in printed and "section 2.1" in printed and "Guardrail" in printed
    assert info["guardrail"] == "pass-through (--no-guardrail)" and info["licence_notice"] == cosmos.LICENCE_NOTICE
    pred = predictor.predict(fake_sample(48, 80), ctx)
    assert capsys.readouterr().err.count("NVIDIA Open Model License") == 0  # printed once per run
    assert pred.frames.shape == (5, 48, 80, 3) and np.allclose(pred.times_s, np.arange(5) / 16.0)
    predictor.close()


@pytest.fixture
def fake_guardrail(monkeypatch):
    """A stand-in ``cosmos_guardrail`` package (as if installed) whose checker records what it checks;
    ``verdict`` sets whether it blocks the prompt or the video."""
    from diffusers.pipelines.cosmos import pipeline_cosmos2_5_predict

    seen = {"text": [], "video": [], "verdict": {"text": True, "video": True}}

    class CosmosSafetyChecker(torch.nn.Module):
        def __init__(self):
            super().__init__()
            self.register_buffer("_device_tracker", torch.zeros(1), persistent=False)

        def check_text_safety(self, prompt):
            seen["text"].append(prompt)
            return seen["verdict"]["text"]

        def check_video_safety(self, frames):
            seen["video"].append(frames.shape)
            return frames if seen["verdict"]["video"] else None

        @property
        def device(self):
            return self._device_tracker.device

        @property
        def dtype(self):
            return self._device_tracker.dtype

    module = types.ModuleType("cosmos_guardrail")
    module.CosmosSafetyChecker = CosmosSafetyChecker
    monkeypatch.setitem(sys.modules, "cosmos_guardrail", module)
    # diffusers binds the class when the package is installed at its import; do what it would have done
    monkeypatch.setattr(pipeline_cosmos2_5_predict, "CosmosSafetyChecker", CosmosSafetyChecker)
    monkeypatch.setattr(cosmos, "_GUARDRAIL", None)
    return seen


def test_the_default_guardrail_checks_the_prompt_and_the_video(fake_guardrail):
    sample = fake_sample(48, 80)
    predictor = PREDICTORS["cosmos-2.5"].create()
    ctx = ctx_for(pipeline=tiny.tiny_cosmos(), **COSMOS_SIZE)
    assert predictor.generation_info(ctx)["guardrail"] == "cosmos_guardrail.CosmosSafetyChecker"
    pred = predictor.predict(sample, ctx)
    assert fake_guardrail["text"] == [full_prompt(sample.prompt)] and fake_guardrail["video"] == [(5, 48, 80, 3)]
    assert pred.frames.shape == (5, 48, 80, 3)
    fake_guardrail["verdict"]["video"] = False
    with pytest.raises(PredictionError, match="blocked the generated video"):
        predictor.predict(sample, ctx)
    fake_guardrail["verdict"]["text"] = False
    with pytest.raises(PredictionError, match="blocked the prompt"):
        predictor.predict(sample, ctx)
    predictor.close()


# -- Cosmos: torchvision -------------------------------------------------------------------------------------


def torchvision_importable():
    try:
        import torchvision  # noqa: F401
    except Exception:  # absent, or a build for another torch that fails to load
        return False
    return True


def test_the_torchvision_free_conditioning_gives_the_frames_of_the_image_path(monkeypatch):
    """Without torchvision the adapter conditions through video=[frame], num_latent_conditional_frames=1;
    with it, through image=. Both give the same frames (torchvision's to_tensor is stood in here)."""
    from diffusers.pipelines.cosmos import pipeline_cosmos2_5_predict

    monkeypatch.delattr(pipeline_cosmos2_5_predict, "torchvision", raising=False)
    predictor = PREDICTORS["cosmos-2.5"].create()
    assert predictor.generation_info(ctx_for(pipeline=tiny.tiny_cosmos(), no_guardrail=True))["conditioning"].startswith("video=")
    video_path, _, _ = run("cosmos-2.5", {"pipeline": tiny.tiny_cosmos(), "no_guardrail": True})

    def to_tensor(pic):  # torchvision.transforms.functional.to_tensor for an RGB PIL image
        return torch.from_numpy(np.asarray(pic).transpose(2, 0, 1).copy()).to(torch.get_default_dtype()).div(255)

    stand_in = types.SimpleNamespace(transforms=types.SimpleNamespace(functional=types.SimpleNamespace(to_tensor=to_tensor)))
    monkeypatch.setattr(pipeline_cosmos2_5_predict, "torchvision", stand_in, raising=False)
    assert predictor.generation_info(ctx_for(pipeline=tiny.tiny_cosmos(), no_guardrail=True))["conditioning"].startswith("image=")
    image_path, _, _ = run("cosmos-2.5", {"pipeline": tiny.tiny_cosmos(), "no_guardrail": True})
    assert np.array_equal(video_path.frames, image_path.frames)


@pytest.mark.skipif(torchvision_importable(), reason="torchvision is importable here")
def test_cosmos_with_a_padding_mask_and_no_torchvision_says_what_to_install():
    predictor = PREDICTORS["cosmos-2.5"].create()
    for ctx in (ctx_for(no_guardrail=True),  # the released model (concat_padding_mask=True)
                ctx_for(pipeline=tiny.tiny_cosmos(concat_padding_mask=True), no_guardrail=True, **COSMOS_SIZE)):
        with pytest.raises(RigidBenchError, match=r"needs torchvision at run time.*pip install 'torchvision==0\.\d+\.\*'"):
            predictor.generation_info(ctx)
        with pytest.raises(RigidBenchError, match="needs torchvision"):
            predictor.predict(fake_sample(48, 80), ctx)
        predictor.close()


def test_cosmos_video_decodes_at_16_fps(tmp_path):
    pred, _, _ = run("cosmos-2.5", {"pipeline": tiny.tiny_cosmos(), "no_guardrail": True})
    write_prediction(pred, tmp_path, "00002")
    video = read_video(tmp_path / "00002.mp4")
    assert video.frames.shape == (5, 48, 80, 3) and np.allclose(video.times_s, np.arange(5) / 16.0, atol=1e-3)


# -- loading from a local directory (model_path) --------------------------------------------------------------


def test_wan_loads_a_pipeline_directory_through_model_path(tmp_path):
    tiny.tiny_wan().save_pretrained(tmp_path / "wan")
    expected, _, _ = run("wan-2.2", {"pipeline": tiny.tiny_wan()})
    pred, predictor, ctx = run("wan-2.2", {"model_path": str(tmp_path / "wan"), "dtype": "float32"})
    assert np.array_equal(pred.frames, expected.frames)
    settings = predictor.settings(ctx)
    assert settings["source"] == "local" and settings["model"] == str((tmp_path / "wan").resolve())
    assert settings["dtype"] == "float32" and "revision" not in settings


def test_cosmos_loads_a_pipeline_directory_with_the_runs_safety_checker(tmp_path):
    pipe = tiny.tiny_cosmos()
    pipe.register_modules(safety_checker=None)  # not saved: the run supplies it
    pipe.save_pretrained(tmp_path / "cosmos")
    expected, _, _ = run("cosmos-2.5", {"pipeline": tiny.tiny_cosmos(), "no_guardrail": True})
    pred, predictor, ctx = run("cosmos-2.5", {"model_path": str(tmp_path / "cosmos"), "dtype": "float32",
                                              "no_guardrail": True})
    assert np.array_equal(pred.frames, expected.frames)
    assert predictor.settings(ctx)["source"] == "local"


def test_wan_names_the_packages_its_pipeline_needs(monkeypatch, checkpoints):
    import importlib.util

    real = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec", lambda name, *a: None if name in ("ftfy", "peft") else real(name, *a))
    predictor = PREDICTORS["wan-2.2"].create()
    with pytest.raises(RigidBenchError, match=r"wan-2.2 needs ftfy \(diffusers' Wan pipeline cleans every prompt "
                                              r"with it\), which is not installed: pip install 'rigidbench\[models\]'$"):
        predictor.generation_info(ctx_for())
    with pytest.raises(RigidBenchError, match=r"needs ftfy .*; peft \(to load a LoRA checkpoint\), which are not "
                                              r"installed: pip install 'rigidbench\[models\]'$"):
        predictor.generation_info(ctx_for(checkpoint=str(checkpoints["root"] / "peft")))
