"""Loading fine-tuned Wan 2.2 checkpoints written outside ``rigidbench train``: the authors' release
(PyTorch Lightning ``.ckpt`` files of a DiffSynth-Studio ``WanModel``) and DiffSynth-Studio's own
exports, as well as plain state dicts, into diffusers' ``WanTransformer3DModel``.

Formats read (one file; ``.safetensors`` is read from its header and tensors, ``.pt``/``.pth``/
``.bin``/``.ckpt`` with ``torch.load(weights_only=True, mmap=True)``, never by unpickling code):

- a Lightning checkpoint (the release's ``ckpt-NNNNNN.ckpt``): the tensors of ``state_dict`` under the
  ``dit.`` prefix; a LoRA run keeps only its ``lora_`` tensors and states rank and alpha in
  ``hyper_parameters["lora"]``;
- a LoRA state dict: per adapted module ``<module>.lora_A[.<adapter>].weight`` (r, in) and
  ``<module>.lora_B[.<adapter>].weight`` (out, r) (peft / DiffSynth: DiffSynth saves peft's names,
  ``.default.`` included), or ``<module>.lora_down.weight`` / ``lora_up.weight`` with an optional
  ``<module>.alpha`` (kohya style);
- a full transformer state dict.

Module names may be DiffSynth's (= the original Wan code's: ``blocks.N.self_attn.q``, ``cross_attn.o``,
``ffn.0``, ``norm3``, ``modulation``, ``head.head`` ...) or diffusers' (``blocks.N.attn1.to_q`` ...),
under any one common prefix of ``dit.``, ``pipe.dit.``, ``model.diffusion_model.``,
``diffusion_model.``, ``base_model.model.``, ``transformer.`` or ``model.``. DiffSynth names are mapped
to diffusers' (``DIFFSYNTH_TO_DIFFUSERS``), as DiffSynth's own diffusers converter pairs them.

A LoRA is merged into the weights: W <- W + s * B A, computed in float32 and stored in W's dtype, with
s = alpha / r when the file has ``alpha`` tensors (DiffSynth's loader does the same), else
lora_alpha / r from the configuration stored with the file (Lightning ``hyper_parameters``, diffusers'
``lora_adapter_metadata`` header), else 1 (DiffSynth's ``load_lora(alpha=1)``: the release's
rank-32, alpha-32 adapters have s = 1 either way). A full state dict must match the transformer
exactly (every key, every shape). Anything else is a ``CheckpointFileError`` naming the file.
"""

from __future__ import annotations

import json
import re
from pathlib import Path
from typing import Any

import torch

from ..errors import UserError

SUFFIXES = (".safetensors", ".pt", ".pth", ".bin", ".ckpt")
PREFIXES = ("pipe.dit.", "dit.", "model.diffusion_model.", "diffusion_model.", "base_model.model.", "transformer.",
            "model.")
_LORA_KEY = re.compile(r"^(?P<module>.+)\.(?P<kind>lora_A|lora_B|lora_down|lora_up)(?:\.(?P<adapter>[^.]+))?"
                       r"\.weight$")

#: DiffSynth-Studio / original Wan module and parameter names -> diffusers' WanTransformer3DModel names
#: (a prefix of the key; what follows it, ``.weight``, ``.lora_A.weight`` ..., is kept)
DIFFSYNTH_TO_DIFFUSERS: list[tuple[str, str]] = [
    (r"blocks\.(\d+)\.self_attn\.([qkv])\.", r"blocks.\1.attn1.to_\2."),
    (r"blocks\.(\d+)\.self_attn\.o\.", r"blocks.\1.attn1.to_out.0."),
    (r"blocks\.(\d+)\.self_attn\.norm_([qk])\.", r"blocks.\1.attn1.norm_\2."),
    (r"blocks\.(\d+)\.cross_attn\.([qkv])\.", r"blocks.\1.attn2.to_\2."),
    (r"blocks\.(\d+)\.cross_attn\.o\.", r"blocks.\1.attn2.to_out.0."),
    (r"blocks\.(\d+)\.cross_attn\.norm_([qk])\.", r"blocks.\1.attn2.norm_\2."),
    (r"blocks\.(\d+)\.cross_attn\.k_img\.", r"blocks.\1.attn2.add_k_proj."),
    (r"blocks\.(\d+)\.cross_attn\.v_img\.", r"blocks.\1.attn2.add_v_proj."),
    (r"blocks\.(\d+)\.cross_attn\.norm_k_img\.", r"blocks.\1.attn2.norm_added_k."),
    (r"blocks\.(\d+)\.ffn\.0\.", r"blocks.\1.ffn.net.0.proj."),
    (r"blocks\.(\d+)\.ffn\.2\.", r"blocks.\1.ffn.net.2."),
    (r"blocks\.(\d+)\.norm3\.", r"blocks.\1.norm2."),          # the cross-attention norm
    (r"blocks\.(\d+)\.modulation$", r"blocks.\1.scale_shift_table"),
    (r"text_embedding\.0\.", "condition_embedder.text_embedder.linear_1."),
    (r"text_embedding\.2\.", "condition_embedder.text_embedder.linear_2."),
    (r"time_embedding\.0\.", "condition_embedder.time_embedder.linear_1."),
    (r"time_embedding\.2\.", "condition_embedder.time_embedder.linear_2."),
    (r"time_projection\.1\.", "condition_embedder.time_proj."),
    (r"img_emb\.proj\.0\.", "condition_embedder.image_embedder.norm1."),
    (r"img_emb\.proj\.1\.", "condition_embedder.image_embedder.ff.net.0.proj."),
    (r"img_emb\.proj\.3\.", "condition_embedder.image_embedder.ff.net.2."),
    (r"img_emb\.proj\.4\.", "condition_embedder.image_embedder.norm2."),
    (r"head\.head\.", "proj_out."),
    (r"head\.modulation$", "scale_shift_table"),
]
_RULES = [(re.compile("^" + pattern), replacement) for pattern, replacement in DIFFSYNTH_TO_DIFFUSERS]
#: names only DiffSynth / the original Wan code use
_DIFFSYNTH_MARKERS = re.compile(r"(^|\.)(self_attn|cross_attn|ffn\.[02]|norm3|modulation|head\.head|text_embedding|"
                                r"time_embedding|time_projection|img_emb)(\.|$)")


class CheckpointFileError(UserError):
    """A checkpoint file that cannot be read or does not fit the Wan transformer; names the file."""


def _torch_load(path: Path):
    # Lightning pickles its hyper-parameters as an AttributeDict (a dict subclass); read it as a plain dict
    allowed = [(dict, "lightning.fabric.utilities.data.AttributeDict"),
               (dict, "pytorch_lightning.utilities.parsing.AttributeDict")]
    try:
        with torch.serialization.safe_globals(allowed):
            return torch.load(str(path), map_location="cpu", weights_only=True, mmap=True)
    except Exception as exc:  # noqa: BLE001 - pickle, zip and weights-only errors alike
        reason = str(exc).strip().splitlines()[0][:300] if str(exc).strip() else type(exc).__name__
        raise CheckpointFileError(f"checkpoint {path}: cannot be read as a PyTorch file of tensors ({reason}); "
                                  "expected a state dict or a Lightning .ckpt (read with weights_only=True)") from None


def _read(path: Path, keys_only: bool = False) -> tuple[dict[str, Any], dict[str, Any]]:
    """(tensors by key (or key -> shape when ``keys_only``), facts: container, LoRA settings if stored)."""
    facts: dict[str, Any] = {}
    if path.suffix == ".safetensors":
        from safetensors import safe_open

        try:
            with safe_open(str(path), framework="pt") as f:
                meta = f.metadata() or {}
                state = {k: (tuple(f.get_slice(k).get_shape()) if keys_only else f.get_tensor(k)) for k in f.keys()}
        except Exception as exc:  # noqa: BLE001 - safetensors raises several types
            reason = str(exc).splitlines()[0][:300] if str(exc) else type(exc).__name__
            raise CheckpointFileError(f"checkpoint {path}: not a readable safetensors file ({reason})") from None
        facts["container"] = "safetensors"
        raw = meta.get("lora_adapter_metadata")
        if raw:
            try:
                config = json.loads(raw)
                facts["lora_config"] = {"r": config.get("r"), "lora_alpha": config.get("lora_alpha")}
            except ValueError:
                pass
        return state, facts
    obj = _torch_load(path)
    facts["container"] = "torch"
    if isinstance(obj, dict) and isinstance(obj.get("state_dict"), dict):
        facts["container"] = "lightning" if "pytorch-lightning_version" in obj or "hyper_parameters" in obj \
            else "torch (state_dict entry)"
        hparams = obj.get("hyper_parameters")
        lora = hparams.get("lora") if isinstance(hparams, dict) else None
        if isinstance(lora, dict) and lora.get("rank"):
            facts["lora_config"] = {"r": lora["rank"], "lora_alpha": lora.get("alpha", lora["rank"])}
        obj = obj["state_dict"]
    if not isinstance(obj, dict):
        raise CheckpointFileError(f"checkpoint {path}: holds a {type(obj).__name__}, expected a dict of tensors")
    state = {k: (tuple(v.shape) if keys_only else v) for k, v in obj.items()
             if isinstance(k, str) and isinstance(v, torch.Tensor)}
    return state, facts


def _strip_prefix(keys) -> str:
    """The longest known prefix that every key starts with ('' if none), applied repeatedly."""
    keys = list(keys)
    prefix = ""
    changed = True
    while changed:
        changed = False
        for p in PREFIXES:
            if keys and all(k.startswith(prefix + p) for k in keys):
                prefix += p
                changed = True
                break
    return prefix


def is_lora_key(key: str) -> bool:
    return bool(_LORA_KEY.match(key)) or key.endswith(".alpha")


def diffusers_name(key: str) -> str:
    """A DiffSynth / original Wan key (module path plus what follows) in diffusers' naming; other keys as they are."""
    for pattern, replacement in _RULES:
        if pattern.match(key):
            return pattern.sub(replacement, key, count=1)
    return key


def naming(keys) -> str:
    """"diffsynth" when any key uses the DiffSynth / original Wan module names, else "diffusers"."""
    return "diffsynth" if any(_DIFFSYNTH_MARKERS.search(k) for k in keys) else "diffusers"


def detect_file(path: str | Path) -> dict[str, Any]:
    """What a single-file checkpoint is, from its keys (the tensors are not read): {"kind": "lora" |
    "transformer-state-dict", "path", "weights", "container", "naming", "reader"}. ``reader`` is
    "rigidbench" (this module loads it) for DiffSynth / original Wan names and for PyTorch files, and
    "diffusers" for safetensors in diffusers' names or musubi-tuner's ``lora_unet_`` layout, which the
    Wan predictor hands to diffusers' LoRA loader (this module reads diffusers' names too)."""
    path = Path(path).expanduser().resolve()
    if not path.is_file():
        raise CheckpointFileError(f"checkpoint {path} does not exist or is not a file")
    if path.suffix not in SUFFIXES:
        raise CheckpointFileError(f"checkpoint {path}: unknown file type '{path.suffix}'; expected one of "
                                  f"{', '.join(SUFFIXES)}")
    shapes, facts = _read(path, keys_only=True)
    if not shapes:
        raise CheckpointFileError(f"checkpoint {path} holds no tensors")
    prefix = _strip_prefix(shapes)
    keys = [k[len(prefix):] for k in shapes]
    lora = [k for k in keys if is_lora_key(k)]
    kind = "lora" if lora else "transformer-state-dict"
    names = naming(keys)
    ours = (names == "diffsynth" or facts["container"] != "safetensors") and not any(k.startswith("lora_unet_")
                                                                                      for k in keys)
    return {"kind": kind, "path": str(path), "weights": str(path), "container": facts["container"],
            "naming": names, "reader": "rigidbench" if ours else "diffusers"}


def read_lora(path: str | Path, scale: float = 1.0) -> dict[str, dict[str, Any]]:
    """The LoRA of a file as diffusers module name -> {"A": (r, in), "B": (out, r), "scale": s, "rank": r}
    (float32), ``scale`` multiplying every s (DiffSynth's ``alpha`` argument)."""
    path = Path(path)
    state, facts = _read(path)
    prefix = _strip_prefix(state)
    state = {k[len(prefix):]: v for k, v in state.items()}
    modules: dict[str, dict[str, Any]] = {}
    adapters, others = set(), []
    for key, value in state.items():
        m = _LORA_KEY.match(key)
        if m:
            if m.group("adapter"):
                adapters.add(m.group("adapter"))
            slot = {"lora_A": "A", "lora_down": "A", "lora_B": "B", "lora_up": "B"}[m.group("kind")]
            modules.setdefault(m.group("module"), {})[slot] = value
        elif key.endswith(".alpha"):
            modules.setdefault(key[: -len(".alpha")], {})["alpha"] = value
        else:
            others.append(key)
    if len(adapters) > 1:
        raise CheckpointFileError(f"checkpoint {path}: LoRA tensors of several adapters "
                                  f"({', '.join(sorted(adapters))}); expected one")
    if others:
        raise CheckpointFileError(f"checkpoint {path}: besides LoRA A/B (down/up) and alpha tensors it holds "
                                  f"{len(others)} other tensors (e.g. {', '.join(sorted(others)[:3])}); mixed "
                                  "LoRA + weight files are not supported")
    config = facts.get("lora_config") or {}
    out = {}
    for module, parts in modules.items():
        if "A" not in parts or "B" not in parts:
            missing = "no A (down)" if "A" not in parts else "no B (up)"
            raise CheckpointFileError(f"checkpoint {path}: module {module} has {missing} LoRA matrix")
        a, b = parts["A"].float(), parts["B"].float()
        if a.ndim == 4:  # 1x1 convolution LoRA (kohya) on a Linear
            a, b = a.flatten(1), b.flatten(1)
        if a.ndim != 2 or b.ndim != 2 or a.shape[0] != b.shape[1]:
            raise CheckpointFileError(f"checkpoint {path}: module {module}: LoRA A {tuple(parts['A'].shape)} and B "
                                      f"{tuple(parts['B'].shape)} do not form a rank-r product B @ A")
        rank = a.shape[0]
        if "alpha" in parts:
            s = float(parts["alpha"]) / rank
        elif config.get("r") and config.get("lora_alpha") is not None:
            s = float(config["lora_alpha"]) / float(config["r"])
        else:
            s = 1.0
        out[diffusers_name(module + ".")[:-1]] = {"A": a, "B": b, "scale": s * scale, "rank": rank, "file_name": module}
    if not out:
        raise CheckpointFileError(f"checkpoint {path}: no LoRA tensors found")
    return out


@torch.no_grad()
def merge_lora(transformer, path: str | Path, scale: float = 1.0) -> dict[str, Any]:
    """Merge the LoRA in ``path`` into ``transformer`` (W <- W + s B A); returns facts for the record.
    Every LoRA module must be a Linear of the transformer with matching shapes, else nothing changes and
    a CheckpointFileError names the file and the module."""
    path = Path(path)
    lora = read_lora(path, scale)
    modules = dict(transformer.named_modules())
    updates = []
    for name, part in lora.items():
        module = modules.get(name)
        weight = getattr(module, "weight", None) if module is not None else None
        if weight is None or weight.ndim != 2:
            raise CheckpointFileError(f"checkpoint {path} could not be loaded into the Wan transformer: LoRA module "
                                      f"{part['file_name']} (diffusers name {name}) is not one of its linear layers; "
                                      "is it an adapter of another model?")
        expected = (part["B"].shape[0], part["A"].shape[1])
        if tuple(weight.shape) != expected:
            raise CheckpointFileError(f"checkpoint {path} could not be loaded into the Wan transformer: LoRA module "
                                      f"{part['file_name']} changes a {expected[0]}x{expected[1]} weight but {name} "
                                      f"is {weight.shape[0]}x{weight.shape[1]}")
        updates.append((weight, part))
    for weight, part in updates:
        delta = part["scale"] * (part["B"].to(weight.device) @ part["A"].to(weight.device))
        weight.copy_((weight.float() + delta).to(weight.dtype))
    ranks = sorted({p["rank"] for p in lora.values()})
    scales = sorted({p["scale"] for p in lora.values()})
    return {"loader": "LoRA merged into the weights (rigidbench.predictors.wan_checkpoints)", "lora_layers": len(updates),
            "rank": ranks[0] if len(ranks) == 1 else ranks, "scale": scales[0] if len(scales) == 1 else scales}


def read_full(path: str | Path) -> dict[str, torch.Tensor]:
    """A full transformer state dict from ``path`` in diffusers' names (prefix removed, DiffSynth names mapped)."""
    state, _ = _read(Path(path))
    prefix = _strip_prefix(state)
    return {diffusers_name(k[len(prefix):]): v for k, v in state.items()}


@torch.no_grad()
def load_full(transformer, path: str | Path) -> dict[str, Any]:
    """Load a full state dict into ``transformer`` strictly (every key and shape; values cast to the
    transformer's dtypes); a CheckpointFileError names the file and the first mismatches otherwise."""
    path = Path(path)
    state = read_full(path)
    own = transformer.state_dict()
    missing, unexpected = sorted(set(own) - set(state)), sorted(set(state) - set(own))
    if missing or unexpected:
        what = []
        if missing:
            what.append(f"{len(missing)} missing (e.g. {', '.join(missing[:3])})")
        if unexpected:
            what.append(f"{len(unexpected)} unexpected (e.g. {', '.join(unexpected[:3])})")
        raise CheckpointFileError(f"checkpoint {path} does not match the Wan transformer: keys {'; '.join(what)}")
    wrong = [k for k in own if tuple(own[k].shape) != tuple(state[k].shape)]
    if wrong:
        k = wrong[0]
        raise CheckpointFileError(f"checkpoint {path} does not match the Wan transformer: {len(wrong)} shapes differ, "
                                  f"e.g. {k} {tuple(state[k].shape)} in the file, {tuple(own[k].shape)} in the model")
    transformer.load_state_dict(state, strict=True)
    return {"loader": "strict load_state_dict (rigidbench.predictors.wan_checkpoints)", "tensors": len(state)}


def apply_file(transformer, found: dict[str, Any]) -> dict[str, Any]:
    """Load the single-file checkpoint ``found`` (``detect_file``) into ``transformer``; returns facts."""
    if found["kind"] == "lora":
        record = merge_lora(transformer, found["weights"])
    else:
        record = load_full(transformer, found["weights"])
    return {**record, "container": found.get("container"), "naming": found.get("naming")}
