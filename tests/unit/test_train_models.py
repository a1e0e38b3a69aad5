"""Fine-tuning on the tiny Wan models: which parameters LoRA and full fine-tuning train, the tiny
builders, preprocessing encodings against the Wan pipeline's own, and the cache format (CPU)."""

import json

import numpy as np
import pytest

torch = pytest.importorskip("torch")
pytest.importorskip("diffusers")
pytest.importorskip("peft")

from rigidbench.errors import ConfigError, UserError  # noqa: E402
from rigidbench.train import models, tiny  # noqa: E402
from rigidbench.train.cache import CacheWriter, LatentCache, prompt_key  # noqa: E402
from rigidbench.train.config import load_train_config  # noqa: E402
from rigidbench.train.distributed import DistInfo  # noqa: E402
from rigidbench.train.objective import FlowMatchingObjective, transformer_prediction  # noqa: E402
from rigidbench.train.trainer import build_model, make_optimizer  # noqa: E402

pytestmark = pytest.mark.usefixtures("torch_one_thread")

CPU = DistInfo(0, 1, 0, torch.device("cpu"), None)
SIX = ("to_q", "to_k", "to_v", "to_out.0", "ffn.net.0.proj", "ffn.net.2")


def one_step(model, params=None, seed=0):
    """One objective evaluation and backward pass on random latents; returns the loss."""
    g = torch.Generator().manual_seed(seed)
    z = torch.randn(2, 48, 3, 4, 8, generator=g)
    text = torch.randn(2, 512, 32, generator=g)
    objective = FlowMatchingObjective()
    index, noise = objective.draw(g, z.shape)
    batch = objective.prepare(z, noise, index)
    loss = objective.loss(transformer_prediction(model, batch, text), batch)
    loss.backward()
    return loss


def test_lora_adds_adapters_to_the_six_projections_of_every_block_and_only_they_learn():
    cfg = load_train_config("tiny", overrides=["mode=lora"])
    model = build_model(cfg, CPU, use_bf16=False)
    layers = tiny.TINY_TRANSFORMER_CONFIG["num_layers"]
    adapted = {name for name, m in model.named_modules() if hasattr(m, "lora_A") and "default" in m.lora_A}
    expected = {f"blocks.{b}.{attn}.{p}" for b in range(layers) for attn in ("attn1", "attn2")
                for p in SIX[:4]} | {f"blocks.{b}.{p}" for b in range(layers) for p in SIX[4:]}
    assert adapted == expected and len(adapted) == 10 * layers
    base_names = set(dict(tiny.tiny_transformer().named_parameters()))
    new = {n for n, _ in model.named_parameters()} - {n.replace(".weight", ".base_layer.weight")
                                                       .replace(".bias", ".base_layer.bias") for n in base_names}
    new -= base_names
    assert all(".lora_A.default." in n or ".lora_B.default." in n for n in new) and len(new) == 2 * len(expected)
    trainable = {n for n, p in model.named_parameters() if p.requires_grad}
    assert trainable == new
    for name, module in model.named_modules():
        if name in expected:
            assert module.lora_A["default"].weight.shape[0] == cfg.lora_rank
            assert module.scaling["default"] == pytest.approx(cfg.lora_alpha / cfg.lora_rank)
    one_step(model)
    for name, p in model.named_parameters():
        assert (p.grad is not None) == (name in trainable), name
    assert any(float(p.grad.abs().sum()) > 0 for n, p in model.named_parameters() if ".lora_B." in n)
    assert all(p.dtype == torch.float32 for n, p in model.named_parameters() if n in trainable)


def test_full_mode_trains_everything_but_the_conditioning_which_stays_bitwise_equal():
    cfg = load_train_config("tiny", overrides=["mode=full"])
    model = build_model(cfg, CPU, use_bf16=False)
    frozen = {k: v.clone() for k, v in model.condition_embedder.state_dict().items()}
    others = {k: v.clone() for k, v in model.state_dict().items() if not k.startswith("condition_embedder.")}
    params = [p for p in model.parameters() if p.requires_grad]
    optimizer, _ = make_optimizer(params, cfg)
    for _ in range(2):
        one_step(model)
        for name, p in model.named_parameters():
            if name.startswith("condition_embedder."):
                assert p.grad is None and not p.requires_grad, name
            else:
                assert p.grad is not None, name
        optimizer.step()
        optimizer.zero_grad(set_to_none=True)
    after = model.condition_embedder.state_dict()
    assert all(torch.equal(after[k], v) for k, v in frozen.items())  # weight decay never touched them
    state = model.state_dict()
    assert sum(not torch.equal(state[k], v) for k, v in others.items()) >= len(params) - 2


def test_unknown_frozen_module_is_a_config_error():
    cfg = load_train_config("tiny", overrides=["mode=full", "frozen_modules=[conditioning]"])
    with pytest.raises(ConfigError, match="no module 'conditioning'"):
        build_model(cfg, CPU, use_bf16=False)


def test_fused_adamw_is_used_where_available_and_recorded():
    cfg = load_train_config("tiny")
    _, impl = make_optimizer([torch.nn.Parameter(torch.zeros(3))], cfg)
    assert impl.startswith("AdamW")
    _, impl = make_optimizer([torch.nn.Parameter(torch.zeros(3))],
                             load_train_config("tiny", overrides=["optimizer.fused=false"]))
    assert impl == "AdamW (fused: false in the config)"


def test_tiny_models_are_the_real_classes_deterministic_and_offline(tmp_path):
    from diffusers import AutoencoderKLWan, WanTransformer3DModel
    from transformers import AutoTokenizer, UMT5EncoderModel

    a, b = tiny.tiny_transformer(), tiny.tiny_transformer()
    assert isinstance(a, WanTransformer3DModel)
    assert all(torch.equal(x, y) for x, y in zip(a.state_dict().values(), b.state_dict().values()))
    assert isinstance(tiny.tiny_vae(), AutoencoderKLWan) and isinstance(tiny.tiny_text_encoder(), UMT5EncoderModel)
    tok = tiny.tiny_tokenizer()
    ids = tok(["Ein Würfel fällt."]).input_ids[0]
    assert ids[-1] == 1 and 2 not in ids and tok.decode(ids, skip_special_tokens=True) == "Ein Würfel fällt."
    tok.save_pretrained(tmp_path)
    assert AutoTokenizer.from_pretrained(tmp_path)(["abc"]).input_ids == tok(["abc"]).input_ids


def test_prompt_encoding_is_the_pipelines():
    pipe = tiny.tiny_pipeline()
    prompt = "A baseball  is dropping.\n Static shot &amp; no pan."
    ours = models.encode_prompts(pipe.tokenizer, pipe.text_encoder, [prompt], 512)[0]
    theirs = pipe.encode_prompt(prompt, do_classifier_free_guidance=False, max_sequence_length=512)[0][0]
    assert torch.allclose(theirs[: len(ours)], ours, atol=1e-6)
    assert torch.count_nonzero(theirs[len(ours):]) == 0  # the pipeline zero-pads; the cache pads when read


def test_the_cached_first_slot_is_the_pipelines_first_frame_condition():
    pipe = tiny.tiny_pipeline()
    rng = np.random.default_rng(0)
    frames = rng.integers(0, 256, (9, 64, 128, 3), dtype=np.uint8)
    latent = models.encode_video(pipe.vae, frames)
    assert latent.shape == (48, 3, 4, 8)
    from PIL import Image

    image = pipe.video_processor.preprocess(Image.fromarray(frames[0]), height=64, width=128)
    _, condition, mask = pipe.prepare_latents(image, 1, 48, 64, 128, 9, torch.float32, "cpu",
                                              torch.Generator().manual_seed(0))
    assert torch.allclose(latent[:, 0], condition[0, :, 0], atol=1e-5)
    assert float(mask[0, 0, 0].max()) == 0.0 and float(mask[0, 0, 1:].min()) == 1.0


def test_cache_shards_round_trip_pad_text_and_refuse_other_settings(tmp_path):
    settings = {"model": "tiny", "width": 128, "height": 64, "frames": 9, "text_len": 6, "prompt_format": "x"}
    writer = CacheWriter(tmp_path, settings)
    t = {prompt_key("a"): torch.ones(2, 4), prompt_key("b"): 2 * torch.ones(3, 4)}
    writer.add_text(t, {prompt_key("a"): "a", prompt_key("b"): "b"})
    writer.set(text_dim=4, latent_shape=[2, 1, 1, 1])
    writer.add_latents({"00001": torch.full((2, 1, 1, 1), 0.5)}, {"00001": {"prompt": prompt_key("b")}})
    writer.add_latents({"00000": torch.full((2, 1, 1, 1), 0.25)}, {"00000": {"prompt": prompt_key("a")}})
    assert (tmp_path / "latents-00001.safetensors").is_file()
    assert CacheWriter(tmp_path, settings).done_ids == {"00000", "00001"}
    cache = LatentCache(tmp_path)
    latents, text = cache.batch([0, 1])
    assert cache.ids == ["00000", "00001"] and latents.dtype == torch.float32
    assert latents[:, 0, 0, 0, 0].tolist() == [0.25, 0.5]
    assert text.shape == (2, 6, 4)
    assert text[0, :2].eq(1).all() and text[0, 2:].eq(0).all() and text[1, :3].eq(2).all() and text[1, 3:].eq(0).all()
    manifest = json.loads((tmp_path / "manifest.json").read_text())
    assert manifest["prompts"][prompt_key("b")] == {"shard": "text-00000.safetensors", "text": "b", "tokens": 3,
                                                     "rows": 3}
    with pytest.raises(ConfigError, match="frames"):
        CacheWriter(tmp_path, {**settings, "frames": 49})
    with pytest.raises(UserError, match="not a training cache"):
        LatentCache(tmp_path / "nowhere")


def test_training_refuses_a_cache_of_another_model(tmp_path):
    from rigidbench.train.trainer import train

    settings = {"model": "wan-2.2", "width": 640, "height": 352, "frames": 49, "text_len": 512, "prompt_format": "x"}
    writer = CacheWriter(tmp_path / "cache", settings)
    writer.add_text({"k": torch.zeros(2, 4096)}, {"k": "a prompt"})
    writer.set(text_dim=4096, latent_shape=[48, 13, 22, 40])
    writer.add_latents({"00000": torch.zeros(48, 1, 1, 1)}, {"00000": {"prompt": "k"}})
    with pytest.raises(ConfigError, match="preprocessed for model 'wan-2.2'"):
        train(load_train_config("tiny"), tmp_path / "cache", tmp_path / "run", progress=False)
