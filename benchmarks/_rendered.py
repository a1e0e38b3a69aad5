"""Shared by the benchmarks that render evaluation examples with Blender (not a benchmark itself).

Blender prints its progress on stdout, where a benchmark's JSON must stand alone: ``json_stdout`` sends
fd 1 to stderr while the work runs and gives back a function that prints the JSON on the real stdout
(then sends fd 1 to stderr again, so Blender's exit-time report does not follow the JSON).
"""

from __future__ import annotations

import json
import os
import sys
from contextlib import contextmanager
from pathlib import Path
from typing import Iterator


@contextmanager
def json_stdout() -> Iterator:
    saved = os.dup(1)
    os.dup2(2, 1)

    def emit(doc: dict) -> None:
        sys.stdout.flush()
        os.dup2(saved, 1)
        json.dump(doc, sys.stdout, indent=1)
        print()
        sys.stdout.flush()
        os.dup2(2, 1)

    try:
        yield emit
    finally:
        os.close(saved)


def render_eval_examples(ids, preset: str, root: Path) -> Path:
    """Render evaluation examples ``ids`` at ``preset`` into ``root/data/eval``; returns that folder."""
    from rigidbench import manifest
    from rigidbench.config import load_registry
    from rigidbench.stages.render import render_to_bundle

    reg = load_registry()
    rows = {r.sample_id: r for r in manifest.eval_rows(reg)}
    for sample_id in ids:
        render_to_bundle(rows[sample_id], reg, reg.preset(preset), root / "data")
    return root / "data" / "eval"
