"""The activation store ``probe extract`` writes and ``fit`` / ``intervene`` read.

Version 3 (one pair of files per clip, written through the stage driver)::

    ACTS/manifest.json                  settings, the split of every clip, the index of the clips extracted
                                        with these settings ({"clips": {id: {"rows": R, "key": ...}}},
                                        "empty", "failed"), rebuilt from the ledger after every run
    ACTS/acts/<clip>.safetensors        "b00/tau0.3": (R, D) float16, block 0's actor-pooled output at tau
                                        0.3, one tensor per (block, tau)
    ACTS/rows/<clip>.npz                one row per (actor, slot) of the clip: clip, slot, actor,
                                        actor_name, role, and every target (R, dim); the reader adds each
                                        row's split from the manifest
    ACTS/.stages/probe-extract/<clip>.json   the driver's ledger entry (the clip's key)

Version 2 (older RigidBench, still read): clips in chunks of 64, ``rows/chunk-00000.npz`` (with a
split column) and ``b00/tau0.3/chunk-00000.safetensors`` ("h"), listed under "chunks".

Rows are read in the index's order (clips sorted by id; version 2: chunk order).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from ..errors import UserError
from .recipe import Conditioning

MANIFEST = "manifest.json"
STORE_VERSION = 3  # 3: one file pair per clip (driver); 2: tau as the release maps it, chunks of clips
READABLE_VERSIONS = (2, 3)
SPLITS = ("train", "val", "test")
PAPER_SPLIT = (4000, 500, 500)


def assign_splits(ids: list[str], seed: int = 0) -> dict[str, str]:
    """Video-level split in the paper's proportions 4,000 / 500 / 500 (80 / 10 / 10 %): validation and
    test get round(n/10) clips each (at least one each once n >= 3), training the rest, over a seeded
    permutation of the sorted ids. 5,000 clips give exactly 4,000 / 500 / 500."""
    ids = sorted(ids)
    n = len(ids)
    k = int(round(n * PAPER_SPLIT[1] / sum(PAPER_SPLIT)))
    if n >= 3:
        k = max(k, 1)
    order = np.random.default_rng(seed).permutation(n)
    out = {}
    for pos, i in enumerate(order):
        out[ids[i]] = "test" if pos < k else "val" if pos < 2 * k else "train"
    return out


def tau_name(tau: float) -> str:
    return f"tau{float(tau):g}"


def shard_path(root: Path, block: int, tau: float, chunk: str) -> Path:
    """A version-2 store's shard of one (block, tau) cell and chunk."""
    return Path(root) / f"b{block:02d}" / tau_name(tau) / f"{chunk}.safetensors"


def acts_file(clip: str) -> str:
    """Where a version-3 store keeps a clip's activations (relative to the store)."""
    return f"acts/{clip}.safetensors"


def rows_file(clip: str) -> str:
    """Where a version-3 store keeps a clip's row table (relative to the store)."""
    return f"rows/{clip}.npz"


def cell_name(block: int, tau: float) -> str:
    """The tensor of (block, tau) in a clip's activation file."""
    return f"b{block:02d}/{tau_name(tau)}"


def indexed_clips(manifest: dict) -> list[str]:
    """The clips with rows that a version-3 manifest indexes, in reading order."""
    return [c for c, info in sorted(manifest.get("clips", {}).items()) if int(info.get("rows", 0)) > 0]


def read_store_manifest(acts: str | Path) -> dict:
    path = Path(acts) / MANIFEST
    if not path.is_file():
        raise UserError(f"{acts}: not an activation store (no {MANIFEST}); make one with `rigidbench probe extract`")
    manifest = json.loads(path.read_text())
    if manifest.get("version") not in READABLE_VERSIONS:
        hint = (" (version 1 stores mapped tau the other way round, 0.9 = the noisiest, and did not seed the random "
                "backbone; extract again)") if manifest.get("version") == 1 else ""
        raise UserError(f"{path}: activation store version {manifest.get('version')}, expected "
                        f"{' or '.join(map(str, READABLE_VERSIONS))}{hint}")
    if not (manifest.get("chunks") if manifest["version"] == 2 else indexed_clips(manifest)):
        raise UserError(f"{acts}: the activation store holds no rows yet; run `rigidbench probe extract` into it")
    return manifest


class ActivationStore:
    """Reader: rows (targets and split labels, concatenated over clips or chunks) and one cell's activations."""

    def __init__(self, acts: str | Path):
        self.dir = Path(acts)
        self.manifest = read_store_manifest(self.dir)
        self.version = int(self.manifest["version"])
        #: the units rows are read in: clips (version 3) or chunks (version 2)
        self.chunks = [c["name"] for c in self.manifest["chunks"]] if self.version == 2 else \
            indexed_clips(self.manifest)
        self._rows = None

    @property
    def blocks(self) -> int:
        return int(self.manifest["blocks"])

    @property
    def taus(self) -> list[float]:
        return [float(p["tau"]) for p in self.manifest["schedule"]]

    @property
    def targets(self) -> dict[str, tuple[int, str]]:
        return {k: (int(v[0]), str(v[1])) for k, v in self.manifest["targets"].items()}

    @property
    def identity(self) -> dict:
        """What the store's rows and activations are: its settings and every clip's key (a chunked store: its
        chunks); not the splits, nor where the cache and bundles were."""
        settings = {k: v for k, v in self.manifest.items()
                    if k not in ("clips", "chunks", "empty", "failed", "created", "updated", "splits", "cache", "data",
                                 "recipe", "conditioning")}
        extra = self.conditioning.key_part()  # ours adds nothing: the identity of stores made before the option
        if extra is not None:
            settings["conditioning"] = extra
        units = self.manifest.get("clips") if self.version == 3 else self.manifest.get("chunks")
        return {"settings": settings, "units": units}

    @property
    def conditioning(self) -> Conditioning:
        """How the store's clips were conditioned (a store made before the option: ours)."""
        return Conditioning.from_record(self.manifest.get("conditioning"))

    @property
    def recipe(self) -> str:
        """The recipe the store was extracted with: "ours", "release", or "<name>+changes"."""
        return str(self.manifest.get("recipe", "ours"))

    def clip_key(self, clip: str) -> str | None:
        """The extraction key of ``clip`` (version 3), or None."""
        return (self.manifest.get("clips", {}).get(clip) or {}).get("key")

    @property
    def rows(self) -> dict[str, np.ndarray]:
        if self._rows is None:
            parts = []
            for c in self.chunks:
                name = rows_file(c) if self.version == 3 else f"rows/{c}.npz"
                with np.load(self.dir / name, allow_pickle=False) as z:
                    part = {k: z[k] for k in z.files}
                if self.version == 3:
                    part["split"] = np.array([self.manifest["splits"][c]] * len(part["clip"]), dtype=str)
                parts.append(part)
            self._rows = {k: np.concatenate([p[k] for p in parts]) for k in parts[0]}
        return self._rows

    def cell(self, block: int, tau: float) -> np.ndarray:
        """(R, D) float32 activations of (block, tau), rows in ``rows`` order."""
        from safetensors import safe_open
        from safetensors.numpy import load_file

        if block not in range(self.blocks) or not any(abs(tau - t) < 1e-9 for t in self.taus):
            raise UserError(f"{self.dir}: no cell block {block}, tau {tau} (blocks 0..{self.blocks - 1}, "
                            f"taus {self.taus})")
        if self.version == 2:
            return np.concatenate([load_file(str(shard_path(self.dir, block, tau, c)))["h"].astype(np.float32)
                                   for c in self.chunks])
        tau = next(t for t in self.taus if abs(tau - t) < 1e-9)
        parts = []
        for c in self.chunks:
            with safe_open(str(self.dir / acts_file(c)), framework="np") as f:
                parts.append(f.get_tensor(cell_name(block, tau)).astype(np.float32))
        return np.concatenate(parts)
