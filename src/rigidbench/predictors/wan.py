"""``wan-2.2``: Wan 2.2 TI2V-5B run locally through diffusers (paper, section 4 and appendix B.1).

``WanImageToVideoPipeline.from_pretrained("Wan-AI/Wan2.2-TI2V-5B-Diffusers", torch_dtype=bfloat16)``:
the hub repository is stored as a ``WanPipeline``; loading it as the image-to-video class works and
keeps its ``expand_timesteps`` (the TI2V model conditions on the first frame by pinning the first
latent frame, with no image encoder). 1280x704, 49 frames written at 24 fps, 50 inference steps,
bfloat16, the paper's negative prompt, the task prompt with the paper's suffix, the first reference
frame as ``image``. The paper does not state the guidance scale; we use the model's published
default, 5.0 (``sample_guide_scale`` of the TI2V-5B configuration), and record it.

Besides the options of ``local.LocalVideoModel`` (``offload``, ``tiled_vae``, overrides), ``options.WanOptions``:

``sampler``: ``flow-euler`` (default) or ``unipc``. The paper does not name its sampler; its runs (the
authors' release, through DiffSynth-Studio) used DiffSynth's flow-matching Euler schedule for Wan (shift
5.0, 50 steps), which ``flow-euler`` reproduces with diffusers' FlowMatchEulerDiscreteScheduler
(``wan_sampler``). ``unipc`` keeps the pipeline's own scheduler (the Diffusers repository's
UniPCMultistepScheduler, flow_shift 5.0), this adapter's default before; it is recorded as a difference
from the release.

``recipe``: ``ours`` (default) or ``release``, the sampling numerics (``RECIPES``): ``timestep_dtype``
(the timestep the transformer sees: float32, or rounded to bfloat16 as DiffSynth casts it),
``update_dtype`` (the Euler update: diffusers' float32 step, or DiffSynth's on bfloat16 latents) and
``vae_codec`` (diffusers' VAE, or DiffSynth's tiled encode and decode and its uint8 conversion); see
``wan_sampler`` and ``wan_diffsynth``. ``release`` sets all three to the release's; each may also be
given on its own, and then overrides the recipe's value. The recipe is one option rather than a
separate model so that runs keep the model name ``wan-2.2`` (reports pair and compare by it), it is
checked without torch like every option, and it travels to worker processes in the options mapping.
Numerics other than ours' enter the run's settings (so a folder of other numerics is generated again,
and a folder made before these options existed is still reused under ``ours``); generation.json
records the recipe, the three values and every one that differs from the release.

``checkpoint``: a fine-tuned model (the paper's section 5), one of

- a LoRA adapter: a PEFT adapter directory (``adapter_config.json`` + ``adapter_model.safetensors``,
  as ``PeftModel.save_pretrained`` writes it; its LoraConfig, alpha included, is used as saved), or
  a LoRA safetensors file (or a directory holding one) in any format diffusers'
  ``load_lora_weights`` reads for Wan (diffusers' ``transformer.``-prefixed keys, the original Wan /
  DiffSynth ``diffusion_model.``-prefixed keys, musubi-tuner keys) or with unprefixed diffusers or
  original Wan module names; its scale comes from the LoraConfig diffusers stores in the file's
  header or from ``.alpha`` keys, else alpha = rank;
- a full fine-tuned transformer: a ``WanTransformer3DModel.save_pretrained`` directory
  (``config.json`` + safetensors), or a safetensors state dict of the whole transformer (diffusers
  or original Wan key names; loaded strictly into the base model's architecture).

Which one was found is decided from file names and safetensors headers alone, before the first
example (an unusable path stops the run there), and recorded in generation.json with each file's
sha256. Every adapter layer must land on a module of the transformer and a full state dict must
match the architecture exactly; otherwise loading fails with the reason, and so does every example
(the load is not retried).

The pipeline calls ftfy (prompt cleaning) and, for LoRA checkpoints, peft; a missing one is named
before the first example.
"""

from __future__ import annotations

import json
import logging
from pathlib import Path
from typing import Any

from ..errors import PredictionError, RigidBenchError, UserError
from ..extras import available, install_command
from ..hashing import file_digest
from .base import PredictContext
from .local import LocalVideoModel, dtype_kwarg
from .options import WanOptions

log = logging.getLogger(__name__)

ADAPTER_NAME = "checkpoint"
PEFT_PREFIX = "base_model.model."
ORIGINAL_PREFIX = "diffusion_model."
#: module names of the original Wan code (DiffSynth too) that diffusers renames (attn1.to_q, ffn.net.0.proj, ...)
ORIGINAL_NAMES = (".self_attn.", ".cross_attn.", ".ffn.0.", ".ffn.2.", "head.head", "text_embedding.0")
SAMPLERS = {
    "flow-euler": ("flow-matching Euler with DiffSynth's Wan schedule (the release's): sigma_i = 5 u_i / (1 + 4 u_i), "
                   "u = linspace(1, 0, steps + 1)[:-1], timestep_i = 1000 sigma_i, last step to sigma 0; diffusers "
                   "FlowMatchEulerDiscreteScheduler(shift=5.0) given that grid"),
    "unipc": "the pipeline's own scheduler (Wan2.2-TI2V-5B-Diffusers: UniPCMultistepScheduler, flow_shift 5.0)",
}
DEFAULT_SAMPLER = "flow-euler"  # SAMPLERS and this are WanOptions.sampler's choices and default (tests check)
RELEASE_SAMPLER = ("DiffSynth-Studio 2.0.18 WanVideoPipeline defaults: FlowMatchScheduler('Wan'), sigma_shift 5.0, "
                   "50 steps")
#: the sampling numerics of each ``recipe`` (WanOptions.recipe; every value one of the option's choices)
RECIPES = {
    "ours": {"timestep_dtype": "float32", "update_dtype": "float32", "vae_codec": "diffusers"},
    "release": {"timestep_dtype": "bfloat16", "update_dtype": "bfloat16", "vae_codec": "diffsynth-tiled"},
}
NUMERICS = {
    "timestep_dtype": {"float32": "the scheduler's float32 timestep",
                       "bfloat16": "each timestep rounded to bfloat16 before the transformer (DiffSynth)"},
    "update_dtype": {"float32": "diffusers' Euler step: x + dt v in float32, stored in the model output's dtype",
                     "bfloat16": "DiffSynth's Euler step on bfloat16 latents: dt v rounded to bfloat16, then the sum"},
    "vae_codec": {"diffusers": "diffusers' VAE encode and decode (tiled by diffusers only with tiled_vae); frames "
                               "rounded from (x / 2 + 0.5) x 255",
                  "diffsynth-tiled": "DiffSynth's tiled VAE (tiles of 30x52 latents, stride 15x26, linear blending) "
                                     "for the first frame's encode and the decode; frames ((x + 1) x 127.5) "
                                     "truncated to uint8"},
}
HASH_LIMIT_BYTES = 2 * 2**30  # checkpoints up to this size are identified by their sha256, larger by size and mtime
_FINGERPRINTS: dict[tuple, dict] = {}  # (path, size, mtime) -> fingerprint, so a run hashes each file once


class CheckpointError(UserError):
    """A ``checkpoint`` option that cannot be used; names the path and what was expected."""


def detect_checkpoint(path: str | Path) -> dict[str, Any]:
    """What the checkpoint at ``path`` is, from its files: {"kind": "lora-peft" | "lora" |
    "transformer-dir" | "transformer-state-dict", "path", "weights" (the weight file or directory)}."""
    path = Path(path).expanduser().resolve()
    if not path.exists():
        raise CheckpointError(f"checkpoint {path} does not exist")
    if path.is_dir():
        if (path / "adapter_config.json").exists():
            weights = path / "adapter_model.safetensors"
            if not weights.exists():
                raise CheckpointError(f"checkpoint {path}: a PEFT adapter directory needs adapter_model.safetensors")
            try:
                config = json.loads((path / "adapter_config.json").read_text())
            except (OSError, ValueError) as exc:
                raise CheckpointError(f"checkpoint {path}: unreadable adapter_config.json ({exc})") from None
            return {"kind": "lora-peft", "path": str(path), "weights": str(weights),
                    "lora": {k: config.get(k) for k in ("r", "lora_alpha", "target_modules", "lora_dropout")}}
        config = path / "config.json"
        if config.exists():
            try:
                class_name = json.loads(config.read_text()).get("_class_name")
            except (OSError, ValueError) as exc:
                raise CheckpointError(f"checkpoint {config}: unreadable config ({exc})") from None
            if class_name != "WanTransformer3DModel":
                raise CheckpointError(f"checkpoint {path}: config.json describes a {class_name}, expected a "
                                      "WanTransformer3DModel (WanTransformer3DModel.save_pretrained) or a LoRA adapter")
            return {"kind": "transformer-dir", "path": str(path), "weights": str(path)}
        files = sorted(path.glob("*.safetensors"))
        if len(files) != 1:
            raise CheckpointError(f"checkpoint {path}: expected a PEFT adapter (adapter_config.json), a saved "
                                  "WanTransformer3DModel (config.json) or exactly one .safetensors file; found "
                                  f"{len(files)} .safetensors files")
        path = files[0]
    from .wan_checkpoints import detect_file  # also the release's formats: .pt/.ckpt, DiffSynth key names

    return detect_file(path)


def checkpoint_files(found: dict[str, Any]) -> list[Path]:
    """The files that define a detected checkpoint's weights (not, e.g., a training run's optimizer state)."""
    path = Path(found["path"])
    if found["kind"] == "lora-peft":
        return [path / "adapter_config.json", Path(found["weights"])]
    if found["kind"] == "transformer-dir":
        return sorted(p for p in path.iterdir() if p.is_file() and (p.suffix == ".safetensors" or p.suffix == ".json"))
    return [Path(found["weights"])]


def fingerprint(found: dict[str, Any]) -> dict[str, Any]:
    """Identifies a checkpoint's weights: the sha256 of each file up to HASH_LIMIT_BYTES, else its size and mtime."""
    out = {}
    for f in checkpoint_files(found):
        stat = f.stat()
        key = (str(f), stat.st_size, stat.st_mtime_ns)
        if key in _FINGERPRINTS:
            out[f.name] = _FINGERPRINTS[key]
            continue
        if stat.st_size <= HASH_LIMIT_BYTES:
            out[f.name] = {"sha256": file_digest(f), "bytes": stat.st_size}
        else:
            out[f.name] = {"bytes": stat.st_size, "mtime": int(stat.st_mtime)}
        _FINGERPRINTS[key] = out[f.name]
    return out


def _lora_key_count(state_dict) -> int:
    return sum(1 for k in state_dict if ".lora_A." in k or ".lora_down." in k)


def _lora_module_count(transformer, adapter: str) -> int:
    return sum(1 for m in transformer.modules() if adapter in getattr(m, "lora_A", {}))


def _prefixed_lora(state_dict: dict) -> dict:
    """Unprefixed LoRA keys (e.g. ``get_peft_model_state_dict(transformer)``, DiffSynth) get the prefix
    diffusers' Wan loader dispatches on: ``diffusion_model.`` for original Wan names, ``transformer.``
    for diffusers names."""
    known = ("transformer.", ORIGINAL_PREFIX, "lora_unet_")
    if any(k.startswith(known) for k in state_dict):
        return state_dict
    if any(k.startswith(PEFT_PREFIX) for k in state_dict):
        state_dict = {k.removeprefix(PEFT_PREFIX): v for k, v in state_dict.items()}
    original = any(any(name in f".{k}" for name in ORIGINAL_NAMES) for k in state_dict)
    prefix = ORIGINAL_PREFIX if original else "transformer."
    return {prefix + k: v for k, v in state_dict.items()}


def _check_adapter(transformer, expected: int, path) -> int:
    loaded = _lora_module_count(transformer, ADAPTER_NAME)
    if expected == 0 or loaded != expected:
        raise CheckpointError(f"checkpoint {path}: {expected} LoRA layers in the file but {loaded} loaded into the "
                              "Wan transformer; is it an adapter of another model?")
    return loaded


def load_lora(pipe, found: dict) -> dict[str, Any]:
    """Load a LoRA checkpoint into ``pipe.transformer`` as adapter "checkpoint"; returns facts for the record."""
    if found.get("reader") == "rigidbench" or not hasattr(pipe, "lora_state_dict"):  # wan_checkpoints.py merges it
        from .wan_checkpoints import apply_file

        return apply_file(pipe.transformer, found)
    try:
        return _load_lora(pipe, found)
    except (ValueError, KeyError, RuntimeError) as exc:  # peft / diffusers: no matching module, bad shapes
        raise CheckpointError(f"checkpoint {found['path']} could not be loaded into the Wan transformer: "
                              f"{str(exc).splitlines()[0][:500]}") from exc


def _load_lora(pipe, found: dict) -> dict[str, Any]:
    from safetensors.torch import load_file

    path = found["path"]
    if found["kind"] == "lora-peft":
        from peft import LoraConfig

        config = LoraConfig.from_pretrained(path)
        state = {k.removeprefix(PEFT_PREFIX): v for k, v in load_file(found["weights"]).items()}
        expected = _lora_key_count(state)
        metadata = {k: v for k, v in config.to_dict().items() if k not in ("peft_type", "task_type")}
        for key, value in metadata.items():
            if isinstance(value, set):
                metadata[key] = sorted(value)
        pipe.transformer.load_lora_adapter(state, prefix=None, adapter_name=ADAPTER_NAME, metadata=metadata)
        loaded = _check_adapter(pipe.transformer, expected, path)
        targets = config.target_modules
        return {"loader": "diffusers load_lora_adapter with the adapter's LoraConfig", "lora_layers": loaded,
                "rank": config.r, "alpha": config.lora_alpha,
                "target_modules": sorted(targets) if isinstance(targets, (set, list)) else targets}
    state = _prefixed_lora(load_file(found["weights"]))
    metadata = _lora_metadata(found["weights"])  # the LoraConfig diffusers' save_lora_weights may store (alpha)
    converted = pipe.lora_state_dict(state)  # diffusers' Wan conversions (original, musubi) -> "transformer." keys
    expected = _lora_key_count(converted)
    pipe.load_lora_into_transformer(converted, transformer=pipe.transformer, adapter_name=ADAPTER_NAME,
                                    metadata=metadata, _pipeline=pipe)
    loaded = _check_adapter(pipe.transformer, expected, path)
    return {"loader": "diffusers WanImageToVideoPipeline.lora_state_dict + load_lora_into_transformer",
            "lora_layers": loaded, "config_from_file": metadata is not None}


def _lora_metadata(path) -> dict | None:
    """The LoRA adapter config that diffusers stores in a safetensors header ("lora_adapter_metadata"), if any."""
    from safetensors import safe_open

    with safe_open(str(path), framework="pt") as f:
        raw = (f.metadata() or {}).get("lora_adapter_metadata")
    return json.loads(raw) if raw else None


def load_full_transformer(pipe, found: dict):
    """Put a fine-tuned ``WanTransformer3DModel`` into ``pipe``: a saved directory replaces the
    transformer; a state dict is loaded strictly into the pipeline's transformer (same architecture,
    same dtype; every key must match)."""
    if found.get("reader") == "rigidbench":  # the release's / DiffSynth's formats (wan_checkpoints.py)
        from .wan_checkpoints import apply_file

        return apply_file(pipe.transformer, found)["loader"]
    if found["kind"] == "transformer-dir":
        from diffusers import WanTransformer3DModel

        transformer = WanTransformer3DModel.from_pretrained(found["path"], **dtype_kwarg(pipe.transformer.dtype))
        pipe.register_modules(transformer=transformer)
        return "WanTransformer3DModel.from_pretrained"
    from safetensors.torch import load_file

    state = load_file(found["weights"])
    for prefix in ("transformer.", "model.", ORIGINAL_PREFIX):
        if all(k.startswith(prefix) for k in state):
            state = {k.removeprefix(prefix): v for k, v in state.items()}
    if any(any(name in f".{k}" for name in ORIGINAL_NAMES) for k in state):
        from diffusers.loaders.single_file_utils import convert_wan_transformer_to_diffusers

        state = convert_wan_transformer_to_diffusers(state)
    try:
        pipe.transformer.load_state_dict(state, strict=True)
    except RuntimeError as exc:
        raise CheckpointError(f"checkpoint {found['path']} does not match the Wan transformer: "
                              f"{str(exc).splitlines()[0]} {' '.join(str(exc).split()[1:40])}") from None
    return "strict load_state_dict into the base architecture"


class WanPredictor(LocalVideoModel):
    options_type = WanOptions
    model_id = "Wan-AI/Wan2.2-TI2V-5B-Diffusers"
    default_revision = None
    pipeline_class = "WanImageToVideoPipeline"
    defaults = {"height": 704, "width": 1280, "num_frames": 49, "fps": 24.0, "steps": 50,
                "guidance_scale": 5.0, "dtype": "bfloat16"}
    guidance_note = ("not stated in the paper; Wan 2.2 TI2V-5B's published default (sample_guide_scale 5.0, "
                     "also WanImageToVideoPipeline's default)")
    size_multiple = 32  # the Wan 2.2 VAE's 16x spatial compression x the 2x2 patches

    def __init__(self, info):
        super().__init__(info)
        self._checkpoint_record: dict[str, Any] | None = None
        self._hooks: list = []  # the timestep hook on the loaded transformer (removed by close)
        self._configured = None  # the pipeline configure changed (its numerics are undone by close)

    def checkpoint(self, ctx: PredictContext) -> dict[str, Any] | None:
        path = self.options(ctx).checkpoint
        return None if path is None else detect_checkpoint(path)

    def sampler(self, ctx: PredictContext) -> str:
        """The ``sampler`` option: "flow-euler" (default, the release's) or "unipc" (checked by WanOptions)."""
        return self.options(ctx).sampler

    def numerics(self, ctx: PredictContext) -> dict[str, str]:
        """The sampling numerics of this run: the recipe's, each overridden by its option when given."""
        o = self.options(ctx)
        chosen = {key: getattr(o, key) or value for key, value in RECIPES[o.recipe].items()}
        if chosen["update_dtype"] == "bfloat16" and o.sampler != DEFAULT_SAMPLER:
            raise UserError(f"{self.name}: update_dtype bfloat16 (recipe {o.recipe}) is DiffSynth's Euler step and "
                            f"needs sampler {DEFAULT_SAMPLER}, got {o.sampler}; give update_dtype=float32 or drop "
                            "the sampler")
        if chosen["vae_codec"] == "diffsynth-tiled" and o.tiled_vae:
            raise UserError(f"{self.name}: vae_codec diffsynth-tiled (recipe {o.recipe}) and tiled_vae both tile the "
                            "VAE; give one of them")
        return chosen

    def extra_settings(self, ctx: PredictContext) -> dict[str, Any]:
        found = self.checkpoint(ctx)
        checkpoint = None if found is None else {"kind": found["kind"], "path": found["path"],
                                                 "files": fingerprint(found)}
        numerics = self.numerics(ctx)
        extra = {"numerics": numerics} if numerics != RECIPES["ours"] else {}  # ours: the settings as before
        return {"sampler": self.sampler(ctx), "checkpoint": checkpoint, **extra}

    def extra_info(self, ctx: PredictContext) -> dict[str, Any]:
        sampler, numerics = self.sampler(ctx), self.numerics(ctx)
        info: dict[str, Any] = {"sampler": sampler, "scheduler": SAMPLERS[sampler], "release_sampler": RELEASE_SAMPLER,
                                "recipe": self.options(ctx).recipe, "numerics": numerics,
                                "numerics_described": {k: NUMERICS[k][v] for k, v in numerics.items()}}
        release = {"sampler": DEFAULT_SAMPLER, **RECIPES["release"]}
        differs = {k: [v, release[k]] for k, v in {"sampler": sampler, **numerics}.items() if v != release[k]}
        if differs:
            info["differs_from_release"] = differs
        found = self.checkpoint(ctx)
        if found is None:
            return {**info, "checkpoint": None}
        described = {"lora-peft": "LoRA adapter (PEFT directory)", "lora": "LoRA adapter (safetensors)",
                     "transformer-dir": "full fine-tuned transformer (save_pretrained directory)",
                     "transformer-state-dict": "full fine-tuned transformer (safetensors state dict)"}
        record = {**found, "description": described[found["kind"]], "files": fingerprint(found)}
        return {**info, "checkpoint": record}

    def output_type(self, ctx: PredictContext) -> str:
        return "latent" if self.numerics(ctx)["vae_codec"] == "diffsynth-tiled" else "np"

    def frames(self, pipe, out, ctx: PredictContext):
        """The pipeline's frames, or with vae_codec diffsynth-tiled its latents decoded as DiffSynth decodes."""
        if self.output_type(ctx) != "latent":
            return super().frames(pipe, out, ctx)
        import torch

        from .wan_diffsynth import diffsynth_to_uint8, tiled_decode

        vae = pipe.vae
        latents = out.frames.to(dtype=vae.dtype)
        shape = (1, vae.config.z_dim, 1, 1, 1)
        mean = torch.tensor(vae.config.latents_mean).view(shape).to(latents.device, latents.dtype)
        inverse_std = 1.0 / torch.tensor(vae.config.latents_std).view(shape).to(latents.device, latents.dtype)
        video = tiled_decode(vae, latents / inverse_std + mean)  # the pipeline's un-normalisation, then DiffSynth's
        if not torch.isfinite(video).all():
            raise PredictionError(f"{self.name}: the decoded video has non-finite values: no video written")
        return diffsynth_to_uint8(video)

    def predict(self, sample, ctx: PredictContext):
        pred = super().predict(sample, ctx)
        pred.metadata["sampler"] = self.sampler(ctx)
        pred.metadata["numerics"] = self.numerics(ctx)
        pred.metadata["scheduler"] = type(self._pipe.scheduler).__name__
        if self._checkpoint_record:
            pred.metadata["checkpoint_loaded"] = dict(self._checkpoint_record)
        return pred

    def check_runnable(self, ctx: PredictContext) -> None:
        """Before the first example: the checkpoint is usable, and the packages the pipeline calls are there
        (diffusers' Wan pipeline cleans every prompt with ftfy, which it imports only when installed)."""
        found = self.checkpoint(ctx)
        missing = [pkg for pkg in ("ftfy",) + (("peft",) if found and found["kind"].startswith("lora") else ())
                   if not available(pkg)]
        if missing:
            why = {"ftfy": "diffusers' Wan pipeline cleans every prompt with it", "peft": "to load a LoRA checkpoint"}
            raise RigidBenchError(f"wan-2.2 needs {'; '.join(f'{pkg} ({why[pkg]})' for pkg in missing)}, which "
                                  f"{'is' if len(missing) == 1 else 'are'} not installed: {install_command('models')}")

    def load_pipeline(self, ctx: PredictContext, dtype):
        from diffusers import WanImageToVideoPipeline

        kwargs = {}
        found = self.checkpoint(ctx)
        if found is not None and found["kind"] == "transformer-dir":  # never load the base transformer
            from diffusers import WanTransformer3DModel

            kwargs["transformer"] = WanTransformer3DModel.from_pretrained(found["path"], **dtype_kwarg(dtype))
            self._checkpoint_record = {"loader": "WanTransformer3DModel.from_pretrained"}
        pipe = self.from_pretrained(WanImageToVideoPipeline, ctx, dtype, **kwargs)
        if not pipe.config.get("expand_timesteps", False):
            log.warning("%s: the loaded pipeline has expand_timesteps=False; Wan 2.2 TI2V-5B needs True", self.name)
        return pipe

    def configure(self, pipe, ctx: PredictContext, injected: bool):
        """Set the sampler's scheduler, load the checkpoint and set the numerics (an injected pipeline is changed
        in place until ``close``)."""
        from .wan_diffsynth import TiledEncoder, round_timesteps
        from .wan_sampler import WanFlowEulerScheduler, use_sampler

        scheduler = use_sampler(pipe, self.sampler(ctx))
        found = self.checkpoint(ctx)
        if found is not None and not (found["kind"] == "transformer-dir" and not injected):
            if found["kind"].startswith("lora"):
                self._checkpoint_record = load_lora(pipe, found)
            else:
                self._checkpoint_record = {"loader": load_full_transformer(pipe, found)}
            log.info("%s: loaded checkpoint %s (%s)", self.name, found["path"], found["kind"])
        numerics = self.numerics(ctx)
        self._configured = pipe
        if isinstance(scheduler, WanFlowEulerScheduler):
            scheduler.update_dtype = numerics["update_dtype"]
        if numerics["timestep_dtype"] == "bfloat16":
            self._hooks.append(round_timesteps(pipe.transformer))
        if numerics["vae_codec"] == "diffsynth-tiled":
            TiledEncoder.install(pipe.vae)
        return pipe

    def close(self) -> None:
        """Undo the numerics' changes to the pipeline (hooks, the tiled encoder), then free it."""
        pipe, self._configured = self._configured, None
        for hook in self._hooks:
            hook.remove()
        self._hooks = []
        if pipe is not None:
            from .wan_diffsynth import TiledEncoder

            TiledEncoder.remove(pipe.vae)
            if hasattr(pipe.scheduler, "update_dtype"):
                pipe.scheduler.update_dtype = "float32"
        super().close()
