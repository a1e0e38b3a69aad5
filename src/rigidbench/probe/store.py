"""The activation store ``probe extract`` writes and ``fit`` / ``intervene`` read.

::

    ACTS/manifest.json                      settings, the split of every clip, the chunks written
    ACTS/rows/chunk-00000.npz               one row per (clip, actor, slot) of the chunk: clip, split,
                                            slot, actor, actor_name, role, and every target (R, dim)
    ACTS/b00/tau0.3/chunk-00000.safetensors "h": (R, D) float16, block 0's actor-pooled output at tau 0.3

A chunk is written shard by shard (temporary name, then renamed), and the manifest, rewritten
atomically, lists it last; a rerun skips the clips of listed chunks and overwrites unlisted files.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from ..errors import UserError
from ..jsonio import write_json

MANIFEST = "manifest.json"
STORE_VERSION = 2  # 2: tau as the release maps it (0.9 = least noisy); the random backbone's seed recorded
SPLITS = ("train", "val", "test")
PAPER_SPLIT = (4000, 500, 500)


def atomic_json(path: Path, data) -> None:
    write_json(path, data, sort_keys=True)


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
    return Path(root) / f"b{block:02d}" / tau_name(tau) / f"{chunk}.safetensors"


def read_store_manifest(acts: str | Path) -> dict:
    path = Path(acts) / MANIFEST
    if not path.is_file():
        raise UserError(f"{acts}: not an activation store (no {MANIFEST}); make one with `rigidbench probe extract`")
    manifest = json.loads(path.read_text())
    if manifest.get("version") != STORE_VERSION:
        hint = (" (version 1 stores mapped tau the other way round, 0.9 = the noisiest, and did not seed the random "
                "backbone; extract again)") if manifest.get("version") == 1 else ""
        raise UserError(f"{path}: activation store version {manifest.get('version')}, expected {STORE_VERSION}{hint}")
    if not manifest.get("chunks"):
        raise UserError(f"{acts}: the activation store holds no rows yet; run `rigidbench probe extract` into it")
    return manifest


class ActivationStore:
    """Reader: rows (targets and split labels, concatenated over chunks) and one cell's activations."""

    def __init__(self, acts: str | Path):
        self.dir = Path(acts)
        self.manifest = read_store_manifest(self.dir)
        self.chunks = [c["name"] for c in self.manifest["chunks"]]
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
    def rows(self) -> dict[str, np.ndarray]:
        if self._rows is None:
            parts = []
            for c in self.chunks:
                with np.load(self.dir / "rows" / f"{c}.npz", allow_pickle=False) as z:
                    parts.append({k: z[k] for k in z.files})
            self._rows = {k: np.concatenate([p[k] for p in parts]) for k in parts[0]}
        return self._rows

    def cell(self, block: int, tau: float) -> np.ndarray:
        """(R, D) float32 activations of (block, tau), rows in ``rows`` order."""
        from safetensors.numpy import load_file

        if block not in range(self.blocks) or not any(abs(tau - t) < 1e-9 for t in self.taus):
            raise UserError(f"{self.dir}: no cell block {block}, tau {tau} (blocks 0..{self.blocks - 1}, "
                            f"taus {self.taus})")
        return np.concatenate([load_file(str(shard_path(self.dir, block, tau, c)))["h"].astype(np.float32)
                               for c in self.chunks])
