"""The preprocessed training cache: float16 text embeddings and video latents in safetensors files.

Version 3 (what ``rigidbench preprocess`` writes; one file per clip and per distinct prompt)::

    CACHE/manifest.json                     the index: settings + every example's and prompt's file
                                            (rebuilt atomically from the stage's ledger after each run)
    CACHE/latents/<id>.safetensors          "latent/<id>": (C, F, h, w) float16, the normalised VAE latent
                                            ((z - latents_mean) / latents_std, posterior mode)
    CACHE/text/<prompt key>-<text key>.safetensors
                                            "text/<prompt key>": (text_len, D) float16, UMT5's output at
                                            every position of the padded prompt; the reader keeps the
                                            padding positions' outputs (the release) or zeros them (the
                                            pipeline). <text key>: a digest of what the encoding depends on
                                            (model, weights, text_len, dtype), so other settings never
                                            share a file
    CACHE/.stages/preprocess/<id>.json      the driver's ledger entry of each clip (its key, its files)

Versions 1 and 2 (older RigidBench, and ``CacheWriter`` below, which tests and benchmarks use to
build synthetic caches) keep clips and prompts in shared shards (``latents-00000.safetensors``,
``text-00000.safetensors``, 64 clips or 128 prompts each), and ``--shard I/N`` wrote
``CACHE/part-I-of-N/`` caches that the reader merges. Every layout is read the same way: the
manifest names, per example and per prompt, the file (its ``shard`` field, relative to CACHE) and
the tensor inside is ``latent/<id>`` or ``text/<prompt key>``.

``manifest.json``::

    {"version": 3, "model": "wan-2.2", "width": 640, "height": 352, "frames": 49,
     "latent_shape": [48, 13, 22, 40], "text_len": 512, "text_dim": 4096, "dtype": "float16",
     "prompt_format": ..., "resize": "bicubic", "vae_dtype": "bfloat16", "text_dtype": "bfloat16",
     "source": {...},
     "examples": {"<id>": {"shard": "latents/<id>.safetensors", "key": "<the clip's preprocess key>",
                           "prompt": "<key of task prompt + suffix>",
                           "prompt_task": "<key of the task prompt alone>", "task": ...,
                           "source_resolution": [W, H], "source_frames": T}},
     "prompts": {"<prompt key>": {"shard": "text/<key>-<text key>.safetensors",
                                  "text": "<the encoded prompt>", "tokens": L, "rows": text_len}}}

The prompt key is the first 16 hex digits of the SHA-256 of the prompt text.
"""

from __future__ import annotations

import fcntl
import hashlib
import json
from contextlib import contextmanager
from datetime import datetime, timezone
from pathlib import Path
from typing import Any, Iterator, Sequence

import torch

from ..atomic import atomic_file
from ..errors import ConfigError, UserError
from ..groundtruth.bundle import damaged_error
from ..hashing import digest
from ..jsonio import write_json

CACHE_VERSION = 3  # 3: one file per clip and per prompt, indexed from the driver's ledger
SHARDED_VERSION = 2  # what CacheWriter writes: clips and prompts in shared shards
READABLE_VERSIONS = (1, 2, 3)  # version 1: one prompt per example (with the suffix), real tokens only
MANIFEST = "manifest.json"
#: manifest settings that a training run must agree with (and an older cache's, for its clips to be adopted)
SETTINGS_KEYS = ("version", "model", "width", "height", "frames", "text_len", "dtype", "prompt_format", "resize",
                 "vae_dtype")
#: text.prompt of a training configuration -> the example record's key of that prompt
PROMPT_FIELDS = {"task+suffix": "prompt", "task": "prompt_task"}
#: how many files a reader keeps open at once (a version-3 cache has one per clip)
OPEN_FILES = 256
SMALL_FILE = 1 << 16


def prompt_key(text: str) -> str:
    return hashlib.sha256(text.encode("utf-8")).hexdigest()[:16]


def latent_file(example_id: str) -> str:
    """Where a version-3 cache keeps the latent of ``example_id`` (relative to the cache)."""
    return f"latents/{example_id}.safetensors"


def text_file(key: str, text_key: str) -> str:
    """Where a version-3 cache keeps the embedding of prompt ``key`` encoded with settings ``text_key``."""
    return f"text/{key}-{text_key}.safetensors"


def bundle_fingerprint(bundle_dir: str | Path, names: Sequence[str]) -> dict[str, Any]:
    """What identifies the content of the files ``names`` of a bundle without reading them all: the
    SHA-256 of each small file (metadata, prompt, contacts), the size of each large one (frames, masks;
    a re-rendered bundle has new metadata anyway). Stable when the data folder is copied or moved. A
    missing file is a BundleError naming it."""
    bundle_dir = Path(bundle_dir)
    out: dict[str, Any] = {}
    for name in names:
        path = bundle_dir / name
        try:
            size = path.stat().st_size
            out[name] = hashlib.sha256(path.read_bytes()).hexdigest() if size <= SMALL_FILE else size
        except OSError as exc:
            raise damaged_error(bundle_dir, name, exc) from exc
    return out


@contextmanager
def index_lock(stage_dir: str | Path) -> Iterator[None]:
    """An exclusive lock (``stage_dir/index.lock``) around rebuilding an index, so that concurrent runs (the
    shards of a job array) rebuild it one after another and the last rebuild sees every committed item."""
    path = Path(stage_dir) / "index.lock"
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "a") as fh:
        fcntl.flock(fh, fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(fh, fcntl.LOCK_UN)


def _atomic_safetensors(path: Path, tensors: dict[str, torch.Tensor], metadata: dict[str, str]) -> None:
    from safetensors.torch import save_file

    path.parent.mkdir(parents=True, exist_ok=True)
    # unique: several processes may write one prompt's file at once (the last rename wins; same content)
    with atomic_file(path, unique=True) as tmp:  # (it gets the umask's mode, whatever safetensors made it)
        save_file({k: v.contiguous() for k, v in tensors.items()}, str(tmp), metadata=metadata)


def write_latent_file(path: str | Path, example_id: str, latent: torch.Tensor, model: str) -> None:
    """One clip's (C, F, h, w) latent as float16 (version 3)."""
    _atomic_safetensors(Path(path), {f"latent/{example_id}": latent.to(torch.float16).cpu()},
                        {"kind": "latents", "model": str(model), "example": example_id})


def write_text_file(path: str | Path, key: str, embedding: torch.Tensor, text: str, tokens: int, model: str) -> None:
    """One prompt's (rows, D) embedding as float16, its text and real-token count in the metadata (version 3)."""
    _atomic_safetensors(Path(path), {f"text/{key}": embedding.to(torch.float16).cpu()},
                        {"kind": "text", "model": str(model), "text": text, "tokens": str(int(tokens))})


def text_file_info(path: str | Path, key: str) -> dict[str, Any]:
    """{"text", "tokens", "rows", "dim"} of a version-3 prompt file, from its header."""
    from safetensors import safe_open

    with safe_open(str(path), framework="pt") as f:
        meta = f.metadata() or {}
        rows, dim = f.get_slice(f"text/{key}").get_shape()
    return {"text": meta.get("text", ""), "tokens": int(meta.get("tokens", rows)), "rows": int(rows), "dim": int(dim)}


PART_GLOB = "part-*-of-*"


def _merged_parts(cache_dir: Path) -> dict[str, Any] | None:
    """One manifest over the parts that sharded preprocessing wrote before version 3 (shard files prefixed by
    their part), or None when ``cache_dir`` has no parts. Parts must agree on every setting."""
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
    """The cache's manifest; a cache written in parts (sharded preprocessing before version 3) reads as one."""
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
        raise UserError(f"{path}: unreadable manifest ({exc}); delete it and run `rigidbench preprocess` into "
                        f"{cache_dir} again (a version-3 cache rebuilds it without encoding anything)") from None
    if manifest.get("version") not in READABLE_VERSIONS:
        raise UserError(f"{path}: cache version {manifest.get('version')}, this RigidBench reads versions "
                        f"{', '.join(map(str, READABLE_VERSIONS))}; preprocess again into a new directory")
    return manifest


class CacheWriter:
    """Appends shards to a cache directory and keeps its manifest: the shared-shard layout of version 2
    (see the module docstring), for synthetic caches in tests and benchmarks."""

    def __init__(self, cache_dir: str | Path, settings: dict[str, Any]):
        self.dir = Path(cache_dir)
        self.dir.mkdir(parents=True, exist_ok=True)
        settings = {"version": SHARDED_VERSION, "dtype": "float16", **settings}
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
                raise UserError(f"{path}: a file the manifest lists is missing; run `rigidbench preprocess` into "
                                f"{self.dir} again (a version-3 cache re-encodes just the clips whose files are "
                                "missing)")
            if len(self._handles) >= OPEN_FILES:  # one file per clip: do not hold thousands open
                self._handles.pop(next(iter(self._handles)))
            self._handles[shard] = safe_open(str(path), framework="pt")
        return self._handles[shard].get_tensor(key)

    def entry_key(self, example_id: str, prompt: str = "task+suffix") -> str:
        """A digest of what determines ``batch`` for the example with prompt ``prompt``: the cache's settings,
        the example's record (a version-3 record holds the clip's preprocess key, which covers its bundle)
        and the prompt's record; not the file names, which differ between layouts."""
        settings = {k: self.manifest.get(k) for k in SETTINGS_KEYS + ("text_dtype", "latent_shape", "text_dim")
                    if k != "version"}
        record = {k: v for k, v in self.manifest["examples"][example_id].items() if k != "shard"}
        text = {k: v for k, v in self.manifest["prompts"][self.prompt_key(example_id, prompt)].items() if k != "shard"}
        return digest(settings, record, text)

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
