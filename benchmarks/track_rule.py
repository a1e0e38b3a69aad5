"""What the ground-truth track rule moves: the same rendered examples scored with tracks drawn by our
earlier rule (disk erosion, one generator seeded with the example seed) and by the published evaluator's
rule (3 iterations of a 3x3 cross, raw-mask fallback, seed 42 per actor), for several failure modes with
exact (gt) perception. Prints JSON: per rule and mode the mean of every track-based measurement, and the
largest absolute change between the rules.

    .venv/bin/python benchmarks/track_rule.py [--ids 00000 00015 ...] [--preset test] [--quick]

Renders at the `test` preset by default (about a minute for five examples on a 2-core machine).
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np
from _rendered import json_stdout, render_eval_examples

MODES = ("reference", "slow", "static", "delayed", "camera-drift")
TRACK_METRICS = ("ate", "ate3d", "iddrift")


def retrack(bundle: Path, rule_name: str) -> dict:
    """Rewrite bundle/tracks.npz with ``rule_name``; returns points and frame-0 visibility."""
    from rigidbench.groundtruth.bundle import Sample
    from rigidbench.groundtruth.contacts import quat_to_matrix
    from rigidbench.groundtruth.tracks import TRACK_RULES, ground_truth_tracks

    s = Sample(bundle)
    R_c, t_c = s.camera_pose
    traj = s.trajectory
    tracks = ground_truth_tracks(s.masks, s.depth, s.K, R_c, t_c, quat_to_matrix(traj.quat_wxyz)[:, :s.n_frames],
                                 traj.positions_m[:, :s.n_frames], np.array([r == "active" for r in s.roles]),
                                 seed=int(s.metadata["seed"]), rule=TRACK_RULES[rule_name])
    tracks.save(bundle / "tracks.npz")
    return {"points": int(tracks.n_points), "visible_frac": float(tracks.visibility.mean())}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--ids", nargs="+", default=["00000", "00015", "00020", "00045", "00070"])
    parser.add_argument("--preset", default="test")
    parser.add_argument("--quick", action="store_true", help="two examples, two modes")
    args = parser.parse_args()
    ids = args.ids[:2] if args.quick else args.ids
    modes = MODES[:2] if args.quick else MODES
    started = time.time()
    with json_stdout() as emit, tempfile.TemporaryDirectory() as tmp:
        out = run(ids, args.preset, modes, Path(tmp))
        out["seconds"] = round(time.time() - started, 1)
        emit(out)
    return 0


def run(ids, preset: str, modes, root: Path) -> dict:
    """Render ``ids`` at ``preset`` under ``root``, then score ``modes`` with tracks by each rule."""
    from rigidbench.driver import RunOptions
    from rigidbench.stages.evaluate import evaluate
    from rigidbench.perception.features import FeatureNets
    from rigidbench.stages.predict import predict
    from rigidbench.predictors import PredictContext

    out: dict = {"ids": ids, "preset": preset, "rules": {}}
    data = render_eval_examples(ids, preset, root)
    for rule in ("rigidbench", "published"):
        facts = [retrack(data / i, rule) for i in ids]
        scores = {}
        for mode in modes:
            preds = root / rule / "predictions" / mode
            predict(mode, data, preds, PredictContext(severity=0.5), run=RunOptions(progress=False))
            summary = evaluate(preds, data, root / rule / "runs" / mode, nets=FeatureNets(), run=RunOptions(progress=False),
                               protocol="lossless")
            scores[mode] = {m: summary.facts.results["overall"][m]["mean"] for m in TRACK_METRICS}
        out["rules"][rule] = {"points": sum(f["points"] for f in facts),
                              "visible_frac": round(float(np.mean([f["visible_frac"] for f in facts])), 4),
                              "scores": scores}
    a, b = out["rules"]["rigidbench"]["scores"], out["rules"]["published"]["scores"]
    out["max_abs_change"] = {m: max(abs((a[k][m] or 0) - (b[k][m] or 0)) for k in modes) for m in TRACK_METRICS}
    out["max_rel_change"] = {m: max(abs((a[k][m] or 0) - (b[k][m] or 0)) / max(abs(a[k][m] or 0), 1e-9)
                                    for k in modes if a[k][m]) if any(a[k][m] for k in modes) else None
                             for m in TRACK_METRICS}
    return out


if __name__ == "__main__":
    raise SystemExit(main())
