"""The predict stage for built-in predictors: one video (+ world state) per reference example."""

from __future__ import annotations

import logging
from pathlib import Path

log = logging.getLogger(__name__)


def predict(name: str, data_dir: Path, out_dir: Path, severity: float, ids: list[str] | None = None,
            limit: int | None = None, progress: bool = True) -> tuple[list[str], dict[str, str]]:
    """Run failure mode ``name`` over the reference bundles; returns (written ids, failures)."""
    from tqdm import tqdm

    from ..evaluate import reference_dirs
    from ..groundtruth.bundle import BundleError, Sample
    from ..models.failure_modes import FAILURE_MODES, write_prediction

    if name not in FAILURE_MODES:
        raise KeyError(f"unknown predictor '{name}'; built-in predictors: {', '.join(FAILURE_MODES)}")
    if not 0.0 <= severity <= 1.0:
        raise ValueError(f"severity must lie in [0, 1], got {severity}")
    refs = reference_dirs(Path(data_dir))
    if ids:
        refs = [r for r in refs if r.name in set(ids)]
    refs = refs[:limit] if limit is not None else refs
    written, failed = [], {}
    for ref in tqdm(refs, unit="example", desc=f"predict {name}", disable=not progress):
        try:
            sample = Sample(ref)
            write_prediction(FAILURE_MODES[name](sample, severity), out_dir, ref.name, sample.fps)
            written.append(ref.name)
        except (BundleError, OSError, ValueError, KeyError) as exc:
            failed[ref.name] = str(exc)
            log.error("example %s failed: %s", ref.name, exc)
    return written, failed
