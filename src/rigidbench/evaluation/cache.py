"""Content hashes that decide whether an example must be scored again, and the files they key."""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

from ..jsonio import write_json as _write

SCORE_VERSION = "2"  # 2: ATE-3D against the simulated actor positions (the paper's target)

REFERENCE_FILES = ("metadata.json", "masks.npz", "depth.npz", "tracks.npz", "trajectories.npz", "video.mp4")


def file_hash(path: Path, chunk: int = 1 << 20) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as fh:
        while block := fh.read(chunk):
            digest.update(block)
    return digest.hexdigest()


def reference_hash(sample_dir: Path) -> str:
    """One hash over the reference files the scores depend on."""
    digest = hashlib.sha256()
    for name in REFERENCE_FILES:
        path = sample_dir / name
        digest.update(name.encode())
        digest.update(file_hash(path).encode() if path.exists() else b"missing")
    return digest.hexdigest()


def input_key(prediction_key: str, reference_key: str, backend: str, nets_key: str, metrics: tuple[str, ...]) -> str:
    """Everything an example's scores depend on: prediction, reference, perception backend and version,
    feature networks, the metric set and the scoring version."""
    text = f"{prediction_key}|{reference_key}|{backend}|{nets_key}|{','.join(metrics)}|{SCORE_VERSION}"
    return hashlib.sha256(text.encode()).hexdigest()


def digest(mapping: dict[str, str]) -> str:
    return hashlib.sha256(json.dumps(mapping, sort_keys=True).encode()).hexdigest()


def write_json(path: Path, doc: dict) -> None:
    """An evaluation output, atomically; NaN is refused (non-finite scores are written as null)."""
    _write(path, doc, indent=2, allow_nan=False)
