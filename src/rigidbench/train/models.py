"""Loading the base model's parts for preprocessing and training: the tiny builders for ``tiny``,
``from_pretrained`` of the diffusers repository (or ``model_path``) for ``wan-2.2``, and random
weights of the real shape for benchmarks. Missing weights are a WeightsUnavailable naming where
we looked; nothing is downloaded unless the hub is reachable and allowed."""

from __future__ import annotations

import html
import re

import torch

from ..errors import WeightsUnavailable
from . import tiny
from .config import model_spec

DTYPES = {"float32": torch.float32, "bfloat16": torch.bfloat16, "float16": torch.float16}


def _to(module, device, dtype):
    """``module`` on ``device`` with its parameters at ``dtype``, except those of the submodules the class
    keeps in float32 (``_keep_in_fp32_modules``, as ``from_pretrained(torch_dtype=...)`` does)."""
    module = module.to(device)
    if dtype in (None, torch.float32):
        return module
    keep = tuple(getattr(module, "_keep_in_fp32_modules", None) or ())
    for name, param in module.named_parameters():
        fp32 = any(k in name.split(".") for k in keep)
        param.data = param.data.to(torch.float32 if fp32 else dtype)
    return module


def _source(model: str, model_path: str | None) -> str:
    spec = model_spec(model)
    return str(model_path) if model_path else spec.hub_id


def _pretrained(cls, model: str, model_path: str | None, subfolder: str, **kwargs):
    where = _source(model, model_path)
    try:
        return cls.from_pretrained(where, subfolder=subfolder, **kwargs)
    except (OSError, ValueError) as exc:
        raise WeightsUnavailable(
            f"{model}: cannot load {subfolder} from {where} ({str(exc).splitlines()[0][:200]}); download the "
            f"pipeline (huggingface-cli download {model_spec(model).hub_id}) or pass --model-path DIR with a "
            "local copy") from None


def load_text_encoder(model: str, model_path: str | None, device, dtype):
    """(tokenizer, UMT5 encoder in eval mode on ``device`` at ``dtype``)."""
    if model == "tiny" and not model_path:
        return tiny.tiny_tokenizer(), _to(tiny.tiny_text_encoder(), device, dtype)
    from transformers import AutoTokenizer, UMT5EncoderModel

    tokenizer = _pretrained(AutoTokenizer, model, model_path, "tokenizer")
    encoder = _pretrained(UMT5EncoderModel, model, model_path, "text_encoder", torch_dtype=dtype)
    return tokenizer, encoder.to(device).eval()


def load_vae(model: str, model_path: str | None, device, dtype=torch.float32):
    if model == "tiny" and not model_path:
        return _to(tiny.tiny_vae(), device, dtype)
    from diffusers import AutoencoderKLWan

    return _pretrained(AutoencoderKLWan, model, model_path, "vae", torch_dtype=dtype).to(device).eval()


def load_transformer(model: str, model_path: str | None, init: str = "pretrained", dtype=torch.float32,
                     device="cpu"):
    """The DiT to fine-tune: the tiny one, the pretrained one, or (``init="random"``) random weights
    of the real configuration built directly on ``device``."""
    if model == "tiny" and not model_path:
        return _to(tiny.tiny_transformer(), device, dtype)
    from diffusers import WanTransformer3DModel

    if init == "random":
        with torch.device(device):
            return _to(WanTransformer3DModel(**tiny.WAN22_TI2V_5B_TRANSFORMER_CONFIG), device, dtype)
    return _pretrained(WanTransformer3DModel, model, model_path, "transformer", torch_dtype=dtype).to(device)


def clean_prompt(text: str) -> str:
    """The prompt as the Wan pipelines clean it before tokenizing: HTML unescaped twice, whitespace
    runs collapsed, stripped (ftfy's fix_text too when ftfy is installed, as diffusers does)."""
    try:
        import ftfy

        text = ftfy.fix_text(text)
    except ImportError:
        pass
    text = html.unescape(html.unescape(text)).strip()
    return re.sub(r"\s+", " ", text).strip()


@torch.no_grad()
def encode_prompts_padded(tokenizer, encoder, prompts: list[str], text_len: int) -> list[tuple[torch.Tensor, int]]:
    """Each prompt's UMT5 hidden states at all ``text_len`` positions (cleaned, padded to ``text_len``,
    truncated there, ``</s>`` appended, attention-masked, as the Wan pipeline and DiffSynth tokenize),
    with the number L_i of real tokens: a list of ((text_len, D) tensor, L_i). The rows after L_i are
    the encoder's output at the padding positions: the pipeline zeroes them, the release kept them."""
    device = next(encoder.parameters()).device
    inputs = tokenizer([clean_prompt(p) for p in prompts], padding="max_length", max_length=text_len,
                       truncation=True, add_special_tokens=True, return_attention_mask=True, return_tensors="pt")
    ids, mask = inputs.input_ids.to(device), inputs.attention_mask.to(device)
    hidden = encoder(ids, mask).last_hidden_state
    lengths = mask.gt(0).sum(dim=1).tolist()
    return [(h, int(n)) for h, n in zip(hidden, lengths)]


def encode_prompts(tokenizer, encoder, prompts: list[str], text_len: int) -> list[torch.Tensor]:
    """Each prompt's UMT5 hidden states over its real tokens, as the Wan pipeline computes them: a list
    of (L_i, D) tensors (``encode_prompts_padded`` without the padding positions)."""
    return [h[:n] for h, n in encode_prompts_padded(tokenizer, encoder, prompts, text_len)]


@torch.no_grad()
def encode_video(vae, frames_uint8) -> torch.Tensor:
    """frames (T,H,W,3) uint8 at the encoding size -> (C, F, h, w) float32 latents as the Wan
    pipeline normalises them: the posterior mode (the pipeline's ``sample_mode="argmax"``), then
    (z - latents_mean) / latents_std per channel. F = (T - 1) / 4 + 1."""
    param = next(vae.parameters())
    x = torch.as_tensor(frames_uint8).to(device=param.device, dtype=torch.float32)
    x = (x / 127.5 - 1.0).permute(3, 0, 1, 2).unsqueeze(0).to(param.dtype)  # (1,3,T,H,W) in [-1, 1]
    z = vae.encode(x).latent_dist.mode()[0].float()
    mean = torch.tensor(vae.config.latents_mean, device=z.device, dtype=torch.float32).view(-1, 1, 1, 1)
    std = torch.tensor(vae.config.latents_std, device=z.device, dtype=torch.float32).view(-1, 1, 1, 1)
    return (z - mean) / std
