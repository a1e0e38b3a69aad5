"""The predict stage for built-in predictors: one video (+ world state) per reference example."""

from __future__ import annotations

import logging
from pathlib import Path

log = logging.getLogger(__name__)


SETTINGS_FILE = ".predictor.json"  # hidden: validate and evaluate skip it


def finished_ids(out_dir: Path, name: str, severity: float) -> set[str]:
    """Ids whose video (written last, atomically) and state exist from a run with the same settings.

    ``.predictor.json`` records the predictor and severity of the last run; with other settings nothing
    counts as finished and the selected examples are written again (other files are left alone)."""
    import json

    from ..perception.gt import state_path

    settings = {"predictor": name, "severity": float(severity)}
    path = out_dir / SETTINGS_FILE
    previous = json.loads(path.read_text()) if path.exists() else None
    out_dir.mkdir(parents=True, exist_ok=True)
    if previous != settings:
        if previous is not None:
            log.info("%s held %s; writing the selected predictions again for %s", out_dir, previous, settings)
        path.write_text(json.dumps(settings) + "\n")
        return set()
    return {v.stem for v in out_dir.glob("*.mp4") if "." not in v.stem and state_path(v).exists()}


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
    out_dir = Path(out_dir)
    done = finished_ids(out_dir, name, severity)
    if done:
        log.info("%s: %d of %d predictions already written at severity %g; skipping them", out_dir,
                 len(done & {r.name for r in refs}), len(refs), severity)
    written, failed = [], {}
    for ref in tqdm(refs, unit="example", desc=f"predict {name}", disable=not progress):
        if ref.name in done:
            written.append(ref.name)
            continue
        try:
            sample = Sample(ref)
            write_prediction(FAILURE_MODES[name](sample, severity), out_dir, ref.name, sample.fps)
            written.append(ref.name)
        except (BundleError, OSError, ValueError, KeyError) as exc:
            failed[ref.name] = str(exc)
            log.error("example %s failed: %s", ref.name, exc)
    return written, failed
