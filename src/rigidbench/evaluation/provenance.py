"""run.json: what produced a run's numbers (inputs' hashes, backend, networks, versions, timings)."""

from __future__ import annotations

import importlib.metadata as md
import platform
import time

from .keys import SCORE_VERSION, digest

PACKAGES = ("rigidbench", "numpy", "scipy", "opencv-python-headless", "av", "torch", "pytorch-msssim",
            "transformers")


def versions(extra: tuple[str, ...] = ()) -> dict[str, str]:
    """Python and the installed version of each package we depend on (plus ``extra``)."""
    out = {"python": platform.python_version()}
    for pkg in dict.fromkeys(PACKAGES + tuple(extra)):
        try:
            out[pkg] = md.version(pkg)
        except md.PackageNotFoundError:
            out[pkg] = "not installed"
    return out


def run_info(model, pred_dir, data_dir, backend, nets, metrics, pred_hashes, ref_hashes, timings, total_s,
             evaluated, reused, failed) -> dict:
    return {"model": model, "predictions": str(pred_dir), "data": str(data_dir),
            "predictions_hash": digest(pred_hashes), "data_hash": digest(ref_hashes),
            "perception": {"backend": backend.name, "version": backend.version,
                           "settings": getattr(backend, "settings", {})},
            "feature_nets": {"lpips": nets.lpips is not None, "iddrift": nets.identity is not None,
                             "device": nets.device, "skipped": nets.skipped},
            "metrics": list(metrics),
            "settings": {"reference_fps": 24, "score_version": SCORE_VERSION},
            "versions": versions(), "timings_s": {**{k: round(v, 3) for k, v in timings.items()},
                                                  "total_s": round(total_s, 3)},
            "evaluated": evaluated, "reused": reused, "failed": failed,
            "finished_at": time.strftime("%Y-%m-%dT%H:%M:%S%z")}
