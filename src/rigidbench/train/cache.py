"""The preprocessed training cache: float16 text embeddings and video latents in safetensors shards.

::

    CACHE/manifest.json                 settings + what every shard holds (rewritten atomically)
    CACHE/text-00000.safetensors        "text/<prompt key>": (text_len, D) float16, UMT5's output at
                                        every position of the padded prompt (version 1: only the
                                        prompt's L real tokens); the reader keeps the padding
                                        positions' outputs (the release) or zeros them (the pipeline)
    CACHE/latents-00000.safetensors     "latent/<example id>": (C, F, h, w) float16, the normalised
                                        VAE latent ((z - latents_mean) / latents_std, posterior mode)
    CACHE/part-I-of-N/...               instead, with ``--shard I/N`` or ``--executor ray``: one such cache
                                        per shard; readers merge the parts into one

``manifest.json``::

    {"version": 2, "model": "wan-2.2", "width": 640, "height": 352, "frames": 49,
     "latent_shape": [48, 13, 22, 40], "text_len": 512, "text_dim": 4096, "dtype": "float16",
     "prompt_format": ..., "resize": "bicubic", "vae_dtype": "bfloat16", "source": {...},
     "shards": [{"file": "latents-00000.safetensors", "kind": "latents", "count": 64}, ...],
     "examples": {"<id>": {"shard": ..., "prompt": "<key of task prompt + suffix>",
                           "prompt_task": "<key of the task prompt alone>", "task": ...,
                           "source_resolution": [W, H], "source_frames": T}},
     "prompts": {"<prompt key>": {"shard": ..., "text": "<the encoded prompt>", "tokens": L}}}

A shard is written to a temporary file and renamed into place, then the manifest is rewritten the
same way, so an interrupted run leaves at most an unreferenced shard that the rerun overwrites; a
rerun skips every example and prompt the manifest lists. The prompt key is the first 16 hex digits
of the SHA-256 of the prompt text.
"""

from __future__ import annotations

import hashlib
import json
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

import torch

from ..atomic import atomic_file
from ..errors import ConfigError, UserError
from ..jsonio import write_json

CACHE_VERSION = 2
READABLE_VERSIONS = (1, 2)  # version 1: one prompt per example (with the suffix), real tokens only
MANIFEST = "manifest.json"
#: manifest settings that a rerun (and a training run) must agree with
SETTINGS_KEYS = ("version", "model", "width", "height", "frames", "text_len", "dtype", "prompt_format", "resize",
                 "vae_dtype")
#: text.prompt of a training configuration -> the example record's key of that prompt
PROMPT_FIELDS = {"task+suffix": "prompt", "task": "prompt_task"}


def prompt_key(text: str) -> str:
    return hashlib.sha256(text.encode("utf-8")).hexdigest()[:16]




def _atomic_safetensors(path: Path, tensors: dict[str, torch.Tensor], metadata: dict[str, str]) -> None:
    from safetensors.torch import save_file

    with atomic_file(path, mode=0o644) as tmp:  # safetensors creates the file private to its owner
        save_file({k: v.contiguous() for k, v in tensors.items()}, str(tmp), metadata=metadata)


PART_GLOB = "part-*-of-*"


def part_dir(cache_dir: str | Path, index: int, count: int) -> Path:
    """Where shard ``index`` of ``count`` writes its part of a cache (``preprocess --shard`` or Ray)."""
    return Path(cache_dir) / f"part-{index}-of-{count}"


def _merged_parts(cache_dir: Path) -> dict[str, Any] | None:
    """One manifest over the parts that sharded preprocessing wrote (shard files prefixed by their part),
    or None when ``cache_dir`` has no parts. Parts must agree on every setting."""
    parts = sorted(p for p in cache_dir.glob(PART_GLOB) if (p / MANIFEST).is_file())
    if not parts:
        return None
    merged: dict[str, Any] | None = None
    for part in parts:
        manifest = read_manifest(part)
        if merged is None:
            merged = {**manifest, "shards": [], "examples": {}, "prompts": {}, "parts": []}
        differs = [k for k in SETTINGS_KEYS + ("latent_shape", "text_dim")
                   if k in manifest and k in merged and manifest[k] != merged[k]]
        if differs:
            raise ConfigError(f"{part}: made with other settings than {parts[0]} ({', '.join(differs)}); "
                              "preprocess all parts with the same command")
        merged.update({k: manifest[k] for k in ("latent_shape", "text_dim") if k in manifest})
        merged["parts"].append(part.name)
        merged["shards"] += [{**sh, "file": f"{part.name}/{sh['file']}"} for sh in manifest["shards"]]
        merged["examples"].update({k: {**v, "shard": f"{part.name}/{v['shard']}"}
                                   for k, v in manifest["examples"].items()})
        merged["prompts"].update({k: {**v, "shard": f"{part.name}/{v['shard']}"}
                                  for k, v in manifest["prompts"].items()})
    return merged


def read_manifest(cache_dir: str | Path) -> dict[str, Any]:
    """The cache's manifest; a cache written in parts (sharded preprocessing) reads as one."""
    path = Path(cache_dir) / MANIFEST
    if not path.is_file():
        merged = _merged_parts(Path(cache_dir))
        if merged is not None:
            return merged
        raise UserError(f"{cache_dir}: not a training cache (no {MANIFEST}); make one with "
                        f"`rigidbench preprocess --data DATA/train --out {cache_dir}`")
    try:
        manifest = json.loads(path.read_text())
    except ValueError as exc:
        raise UserError(f"{path}: unreadable manifest ({exc}); delete the cache and preprocess again") from None
    if manifest.get("version") not in READABLE_VERSIONS:
        raise UserError(f"{path}: cache version {manifest.get('version')}, this RigidBench reads versions "
                        f"{', '.join(map(str, READABLE_VERSIONS))}; preprocess again into a new directory")
    return manifest


class CacheWriter:
    """Appends shards to a cache directory and keeps its manifest (see the module docstring)."""

    def __init__(self, cache_dir: str | Path, settings: dict[str, Any]):
        self.dir = Path(cache_dir)
        self.dir.mkdir(parents=True, exist_ok=True)
        settings = {"version": CACHE_VERSION, "dtype": "float16", **settings}
        if (self.dir / MANIFEST).is_file():
            self.manifest = read_manifest(self.dir)
            differs = {k: (self.manifest.get(k), settings.get(k)) for k in SETTINGS_KEYS
                       if self.manifest.get(k) != settings.get(k)}
            if differs:
                what = "; ".join(f"{k}: cache has {a!r}, this run {b!r}" for k, (a, b) in differs.items())
                raise ConfigError(f"{self.dir}: the cache was made with other settings ({what}); use a new --out")
        else:
            self.manifest = {**settings, "shards": [], "examples": {}, "prompts": {},
                             "created": datetime.now(timezone.utc).isoformat(timespec="seconds")}
            self._save_manifest()

    @property
    def done_ids(self) -> set[str]:
        return set(self.manifest["examples"])

    @property
    def known_prompts(self) -> set[str]:
        return set(self.manifest["prompts"])

    def _next_file(self, kind: str) -> str:
        n = sum(1 for s in self.manifest["shards"] if s["kind"] == kind)
        return f"{kind}-{n:05d}.safetensors"

    def _save_manifest(self) -> None:
        self.manifest["updated"] = datetime.now(timezone.utc).isoformat(timespec="seconds")
        write_json(self.dir / MANIFEST, self.manifest, sort_keys=True)

    def set(self, **fields) -> None:
        """Record extra manifest fields (e.g. latent_shape, text_dim once known)."""
        self.manifest.update(fields)
        self._save_manifest()

    def add_text(self, embeddings: dict[str, torch.Tensor], texts: dict[str, str],
                 tokens: dict[str, int] | None = None) -> str:
        """Write one text shard: prompt key -> (rows, D) embedding, of which the first ``tokens[key]`` rows
        are the prompt's real tokens (default: all rows); returns the shard's file name."""
        name = self._next_file("text")
        _atomic_safetensors(self.dir / name, {f"text/{k}": v.to(torch.float16).cpu() for k, v in embeddings.items()},
                            {"kind": "text", "model": str(self.manifest["model"])})
        self.manifest["shards"].append({"file": name, "kind": "text", "count": len(embeddings)})
        for k, v in embeddings.items():
            n = int(v.shape[0]) if tokens is None else int(tokens[k])
            self.manifest["prompts"][k] = {"shard": name, "text": texts[k], "tokens": n, "rows": int(v.shape[0])}
        self._save_manifest()
        return name

    def add_latents(self, latents: dict[str, torch.Tensor], records: dict[str, dict[str, Any]]) -> str:
        """Write one latent shard: example id -> (C, F, h, w) latent, with each example's record
        (its prompt key and facts); returns the shard's file name."""
        name = self._next_file("latents")
        _atomic_safetensors(self.dir / name, {f"latent/{k}": v.to(torch.float16).cpu() for k, v in latents.items()},
                            {"kind": "latents", "model": str(self.manifest["model"])})
        self.manifest["shards"].append({"file": name, "kind": "latents", "count": len(latents)})
        for k in latents:
            self.manifest["examples"][k] = {"shard": name, **records[k]}
        self._save_manifest()
        return name


class LatentCache:
    """Reader over a cache directory: example ids in sorted order, each with its latent and its
    prompt's text embedding, read lazily (memory-mapped) from the shards."""

    def __init__(self, cache_dir: str | Path):
        self.dir = Path(cache_dir)
        self.manifest = read_manifest(self.dir)
        self.ids: list[str] = sorted(self.manifest["examples"])
        if not self.ids:
            raise UserError(f"{self.dir}: the cache holds no examples; run `rigidbench preprocess` into it first")
        self.text_len = int(self.manifest["text_len"])
        self._handles: dict[str, Any] = {}

    def __len__(self) -> int:
        return len(self.ids)

    @property
    def latent_shape(self) -> tuple[int, ...]:
        return tuple(self.manifest["latent_shape"])

    @property
    def text_dim(self) -> int:
        return int(self.manifest["text_dim"])

    def _get(self, shard: str, key: str) -> torch.Tensor:
        from safetensors import safe_open

        if shard not in self._handles:
            path = self.dir / shard
            if not path.is_file():
                raise UserError(f"{path}: a shard the manifest lists is missing; preprocess again into a new "
                                "directory")
            self._handles[shard] = safe_open(str(path), framework="pt")
        return self._handles[shard].get_tensor(key)

    def latent(self, example_id: str) -> torch.Tensor:
        """(C, F, h, w) float16."""
        return self._get(self.manifest["examples"][example_id]["shard"], f"latent/{example_id}")

    def prompt_key(self, example_id: str, prompt: str = "task+suffix") -> str:
        """The key of the prompt ``prompt`` ("task+suffix" or "task") of an example; ConfigError when the cache
        does not hold that prompt (a version-1 cache holds only the task prompt with the suffix)."""
        field = PROMPT_FIELDS.get(prompt)
        if field is None:
            raise ConfigError(f"unknown text.prompt {prompt!r}; known: {', '.join(PROMPT_FIELDS)}")
        key = self.manifest["examples"][example_id].get(field)
        if key is None:
            raise ConfigError(f"{self.dir}: the cache holds no '{prompt}' prompt for {example_id} (cache version "
                              f"{self.manifest.get('version')}); preprocess again into a new directory, or train "
                              "with --set text.prompt=task+suffix")
        return key

    def text(self, example_id: str, prompt: str = "task+suffix") -> torch.Tensor:
        """(rows, D) float16: UMT5's output for the example's prompt, all text_len positions (version 1:
        the real tokens only)."""
        key = self.prompt_key(example_id, prompt)
        return self._get(self.manifest["prompts"][key]["shard"], f"text/{key}")

    def tokens(self, example_id: str, prompt: str = "task+suffix") -> int:
        """How many of the prompt's rows are real tokens (the rest are padding positions)."""
        return int(self.manifest["prompts"][self.prompt_key(example_id, prompt)]["tokens"])

    def check_text(self, prompt: str, padding: str) -> None:
        """ConfigError (naming the cache and the setting) when a training run's text.prompt / text.padding
        cannot be served by this cache."""
        if not self.ids:
            return
        example = self.ids[0]
        key = self.prompt_key(example, prompt)
        if padding not in ("zeros", "encoder"):
            raise ConfigError(f"unknown text.padding {padding!r}; known: encoder, zeros")
        record = self.manifest["prompts"][key]
        if padding == "encoder" and int(record.get("rows", record["tokens"])) < self.text_len:
            raise ConfigError(f"{self.dir}: the cache stores only each prompt's real tokens (cache version "
                              f"{self.manifest.get('version')}), not UMT5's outputs at the padding positions that "
                              "text.padding=encoder uses; preprocess again into a new directory, or train with "
                              "--set text.padding=zeros")

    def batch(self, indices, device=None, dtype=torch.float32, prompt: str = "task+suffix",
              padding: str = "zeros") -> tuple[torch.Tensor, torch.Tensor]:
        """Examples ``indices`` (into ``ids``) -> latents (B, C, F, h, w) and text (B, text_len, D) of prompt
        ``prompt`` ("task+suffix" or "task"). ``padding="zeros"``: the rows after the prompt's real tokens
        are zero, as the Wan pipeline pads prompt embeddings; ``"encoder"``: they are UMT5's outputs at
        the padding positions, as the release's cache stored them."""
        ids = [self.ids[i] for i in indices]
        latents = torch.stack([self.latent(i) for i in ids]).to(device=device, dtype=dtype)
        text = torch.zeros(len(ids), self.text_len, self.text_dim, dtype=dtype, device=device)
        for row, example_id in enumerate(ids):
            t = self.text(example_id, prompt)[: self.text_len]
            if padding == "zeros":
                t = t[: self.tokens(example_id, prompt)]
            elif t.shape[0] < self.text_len:
                self.check_text(prompt, padding)
            text[row, : t.shape[0]] = t.to(device=device, dtype=dtype)
        return latents, text
