"""Content hashes that decide whether an example must be scored again, and the files they key."""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

from ..folders import DEPTH_FILE, MASKS_FILE, METADATA_FILE, TRACKS_FILE, TRAJECTORIES_FILE, VIDEO_FILE
from ..hashing import file_digest as file_hash

# 2: ATE-3D against the simulated actor positions (the paper's target); 3: records hold the clip's coverage
# of the reference span, and the reference key leaves out metadata that does not move scores
SCORE_VERSION = "3"

REFERENCE_FILES = (METADATA_FILE, MASKS_FILE, DEPTH_FILE, TRACKS_FILE, TRAJECTORIES_FILE, VIDEO_FILE)

#: metadata.json fields that record how a bundle was made, not what it holds: a re-render that changes
#: only these (its timings, package versions) keeps every cached score.
VOLATILE_METADATA = ("render_seconds", "software")


def metadata_hash(path: Path) -> str:
    """Hash of a metadata.json without its VOLATILE_METADATA fields (canonical JSON); of its bytes when it
    is not a readable JSON object (the example then fails where it is read, naming the file)."""
    try:
        meta = json.loads(path.read_text())
    except (OSError, ValueError):
        return file_hash(path)
    if not isinstance(meta, dict):
        return file_hash(path)
    kept = {k: v for k, v in meta.items() if k not in VOLATILE_METADATA}
    return hashlib.sha256(json.dumps(kept, sort_keys=True, allow_nan=True).encode()).hexdigest()


def reference_hash(sample_dir: Path) -> str:
    """One hash over what the scores depend on in a reference bundle: its arrays and video, and its
    metadata without the fields that only record how it was made (VOLATILE_METADATA)."""
    digest = hashlib.sha256()
    for name in REFERENCE_FILES:
        path = sample_dir / name
        digest.update(name.encode())
        if not path.exists():
            digest.update(b"missing")
        else:
            digest.update((metadata_hash(path) if name == METADATA_FILE else file_hash(path)).encode())
    return digest.hexdigest()


def input_key(prediction_key: str, reference_key: str, backend: str, nets_key: str, metrics: tuple[str, ...],
              rules: str = "") -> str:
    """Everything an example's scores depend on: prediction, reference, perception backend and version,
    feature networks, the metric set, the evaluation protocol (``rules``) and the scoring version. It is
    stored in the example's record and names its perception cache; the evaluate stage's key
    (``runner.EvaluateStage.key``) adds the rules that refuse an example (the first-frame check and
    ``allow_short``), so a record scored under other rules is never reused."""
    text = f"{prediction_key}|{reference_key}|{backend}|{nets_key}|{','.join(metrics)}|{rules}|{SCORE_VERSION}"
    return hashlib.sha256(text.encode()).hexdigest()


def digest(mapping: dict[str, str]) -> str:
    return hashlib.sha256(json.dumps(mapping, sort_keys=True).encode()).hexdigest()
