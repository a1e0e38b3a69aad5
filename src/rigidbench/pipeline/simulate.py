"""The simulate stage: manifest rows -> scene_spec.json, trajectories.npz, contacts.json per example.

Each example's files are written to a temporary directory and renamed into place, so a rerun
skips finished examples and redoes interrupted ones; a failing example is reported and the
others continue.
"""

from __future__ import annotations

import logging
from pathlib import Path

from ..blender.physics import CONTACTS_FILE, simulate_to_dir
from ..config import Registry
from ..errors import EXAMPLE_ERRORS
from ..spec.build import build_scene_spec

log = logging.getLogger(__name__)


def simulate_rows(rows, registry: Registry, out_dir: Path,
                  progress: bool = True) -> tuple[list[tuple[str, str]], list[str]]:
    """Simulate every row into ``out_dir/<id>/``; returns ((sample id, reason) per failure, skipped ids)."""
    from tqdm import tqdm

    failures, skipped = [], []
    out_dir.mkdir(parents=True, exist_ok=True)
    for row in tqdm(rows, unit="example", desc="simulate", disable=not progress):
        target = out_dir / row.sample_id
        if (target / CONTACTS_FILE).exists():
            skipped.append(row.sample_id)
            continue
        try:
            simulate_to_dir(build_scene_spec(row, registry), target, registry, overwrite=True)
        except (*EXAMPLE_ERRORS, RuntimeError) as exc:  # RuntimeError: Blender's own errors
            failures.append((row.sample_id, str(exc)))
            log.error("example %s failed: %s", row.sample_id, exc)
    return failures, skipped
