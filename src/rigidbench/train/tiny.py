"""Tiny, randomly initialised Wan 2.2 models of the real classes, for tests, benchmarks and newcomers.

``WanTransformer3DModel``, ``AutoencoderKLWan`` (Wan 2.2 layout: residual, patch size 2, 48 latent
channels, 16x spatial and 4x temporal compression), ``UMT5EncoderModel`` and an offline tokenizer,
each built from the configs below with a fixed seed, so every call returns the same weights (the
tiny "pretrained" model that ``train --config tiny`` starts from and ``predict wan-2.2`` with an
injected tiny pipeline generates with). ``tiny_pipeline`` assembles them into the
``WanImageToVideoPipeline`` that Wan 2.2 TI2V-5B uses (``expand_timesteps=True``, UniPC flow
scheduler with shift 5).

The tokenizer needs no hub access: a byte-level BPE with no merges (the ``tokenizers`` library),
so every UTF-8 byte is one token and any prompt tokenizes, wrapped in a transformers fast tokenizer
with T5's special tokens (pad 0, ``</s>`` 1 appended to every sequence, unk 2). It saves and loads
with ``save_pretrained`` / ``AutoTokenizer.from_pretrained`` like the real one.

Sizes (TINY_VIDEO): 9 frames at 128x64 -> latents (48, 3, 4, 8) -> 3 x 2 x 4 = 24 transformer tokens;
the transformer has 2 blocks of width 24 and about 35,000 parameters.
"""

from __future__ import annotations

from pathlib import Path

import torch

TINY_SEED = 0
TINY_VIDEO = {"width": 128, "height": 64, "frames": 9}

TINY_TRANSFORMER_CONFIG = {
    "patch_size": (1, 2, 2),
    "num_attention_heads": 2,
    "attention_head_dim": 12,
    "in_channels": 48,
    "out_channels": 48,
    "text_dim": 32,
    "freq_dim": 256,
    "ffn_dim": 32,
    "num_layers": 2,
    "cross_attn_norm": True,
    "qk_norm": "rms_norm_across_heads",
    "rope_max_seq_len": 32,
}

TINY_VAE_CONFIG = {
    "base_dim": 8,
    "z_dim": 48,
    "in_channels": 12,
    "out_channels": 12,
    "is_residual": True,
    "patch_size": 2,
    "latents_mean": [0.0] * 48,
    "latents_std": [1.0] * 48,
    "dim_mult": [1, 1, 1, 1],
    "num_res_blocks": 1,
    "scale_factor_spatial": 16,
    "scale_factor_temporal": 4,
    "temperal_downsample": [False, True, True],
}

SPECIAL_TOKENS = {"<pad>": 0, "</s>": 1, "<unk>": 2}

TINY_TEXT_ENCODER_CONFIG = {
    "d_model": 32,
    "d_kv": 8,
    "d_ff": 64,
    "num_layers": 2,
    "num_heads": 4,
    "relative_attention_num_buckets": 8,
    "relative_attention_max_distance": 32,
    "feed_forward_proj": "gated-gelu",
    "dropout_rate": 0.0,
    "pad_token_id": 0,
    "eos_token_id": 1,
    "decoder_start_token_id": 0,
}

# The real Wan 2.2 TI2V-5B transformer (Wan-AI/Wan2.2-TI2V-5B-Diffusers, transformer/config.json), for
# random-weight benchmarks when the weights are not on this machine.
WAN22_TI2V_5B_TRANSFORMER_CONFIG = {
    "patch_size": (1, 2, 2),
    "num_attention_heads": 24,
    "attention_head_dim": 128,
    "in_channels": 48,
    "out_channels": 48,
    "text_dim": 4096,
    "freq_dim": 256,
    "ffn_dim": 14336,
    "num_layers": 30,
    "cross_attn_norm": True,
    "qk_norm": "rms_norm_across_heads",
    "eps": 1e-6,
    "rope_max_seq_len": 1024,
}


def tiny_transformer(seed: int = TINY_SEED, **overrides):
    """A ``WanTransformer3DModel`` with TINY_TRANSFORMER_CONFIG (fp32, CPU, eval mode), same weights per seed."""
    from diffusers import WanTransformer3DModel

    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(seed)
        return WanTransformer3DModel(**{**TINY_TRANSFORMER_CONFIG, **overrides}).eval()


def tiny_vae(seed: int = TINY_SEED):
    """An ``AutoencoderKLWan`` in Wan 2.2's layout with TINY_VAE_CONFIG (fp32, CPU, eval mode)."""
    from diffusers import AutoencoderKLWan

    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(seed)
        return AutoencoderKLWan(**TINY_VAE_CONFIG).eval()


def tiny_tokenizer(model_max_length: int = 512):
    """A byte-level T5-style fast tokenizer built offline (see the module docstring)."""
    from tokenizers import Tokenizer, decoders, models, pre_tokenizers, processors
    from transformers import PreTrainedTokenizerFast

    vocab = dict(SPECIAL_TOKENS)
    for symbol in sorted(pre_tokenizers.ByteLevel.alphabet()):
        vocab[symbol] = len(vocab)
    backend = Tokenizer(models.BPE(vocab=vocab, merges=[], unk_token="<unk>"))
    backend.pre_tokenizer = pre_tokenizers.ByteLevel(add_prefix_space=False, use_regex=False)
    backend.decoder = decoders.ByteLevel()
    eos = SPECIAL_TOKENS["</s>"]
    backend.post_processor = processors.TemplateProcessing(single="$A </s>", pair="$A </s> $B </s>",
                                                           special_tokens=[("</s>", eos)])
    return PreTrainedTokenizerFast(tokenizer_object=backend, pad_token="<pad>", eos_token="</s>",
                                   unk_token="<unk>", model_max_length=model_max_length)


def tiny_text_encoder(seed: int = TINY_SEED):
    """A ``UMT5EncoderModel`` with TINY_TEXT_ENCODER_CONFIG and the tiny tokenizer's vocabulary."""
    from transformers import UMT5Config, UMT5EncoderModel

    vocab_size = len(SPECIAL_TOKENS) + 256
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(seed)
        return UMT5EncoderModel(UMT5Config(vocab_size=vocab_size, **TINY_TEXT_ENCODER_CONFIG)).eval()


def tiny_scheduler(shift: float = 5.0):
    """Wan 2.2 TI2V-5B's inference scheduler (UniPC with flow sigmas) at ``shift``."""
    from diffusers import UniPCMultistepScheduler

    return UniPCMultistepScheduler(prediction_type="flow_prediction", use_flow_sigmas=True, flow_shift=shift)


def tiny_pipeline(seed: int = TINY_SEED, transformer=None):
    """A ``WanImageToVideoPipeline`` of the tiny models with ``expand_timesteps=True`` (the TI2V-5B
    layout: no image encoder, first latent frame pinned); ``transformer`` replaces the tiny one."""
    from diffusers import WanImageToVideoPipeline

    return WanImageToVideoPipeline(
        tokenizer=tiny_tokenizer(), text_encoder=tiny_text_encoder(seed), vae=tiny_vae(seed),
        scheduler=tiny_scheduler(), transformer=transformer if transformer is not None else tiny_transformer(seed),
        image_encoder=None, image_processor=None, transformer_2=None, boundary_ratio=None, expand_timesteps=True)


def save_tiny_pipeline(path: str | Path, seed: int = TINY_SEED) -> Path:
    """Write the tiny pipeline as a diffusers pipeline directory (loadable with ``model_path``)."""
    path = Path(path)
    tiny_pipeline(seed).save_pretrained(path)
    return path
