"""What the evaluation protocol moves: the same predictions scored under `rigidbench-v1` (the published
evaluator's JPEG q95 4:4:4 round trip of generated frames) and `lossless`, with exact (gt) perception.
Prints JSON: per protocol and mode the mean of every measurement, and the change per measurement.

    .venv/bin/python benchmarks/protocol_effect.py [--ids 00000 00015 ...] [--preset preview] [--quick]

Renders at the `preview` preset by default (320x176, 49 frames; about a minute per example on a 2-core
machine); `--quick` takes one example at the `test` preset.
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

from _rendered import json_stdout, render_eval_examples

MODES = ("reference", "gamma", "slow", "camera-shake")


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--ids", nargs="+", default=["00000", "00015", "00020"])
    parser.add_argument("--preset", default="preview")
    parser.add_argument("--quick", action="store_true", help="one example at the test preset, two modes")
    args = parser.parse_args()
    ids = args.ids[:1] if args.quick else args.ids
    preset = "test" if args.quick else args.preset
    modes = MODES[:2] if args.quick else MODES
    started = time.time()
    with json_stdout() as emit, tempfile.TemporaryDirectory() as tmp:
        out = run(ids, preset, modes, Path(tmp))
        out["seconds"] = round(time.time() - started, 1)
        emit(out)
    return 0


def run(ids, preset: str, modes, root: Path) -> dict:
    """Render ``ids`` at ``preset`` under ``root``, predict ``modes`` once, score them under both protocols."""
    from rigidbench.evaluation import evaluate
    from rigidbench.perception.features import FeatureNets
    from rigidbench.pipeline.predict import predict
    from rigidbench.predictors import PredictContext

    out: dict = {"ids": ids, "preset": preset, "protocols": {}}
    data = render_eval_examples(ids, preset, root)
    for mode in modes:
        predict(mode, data, root / "predictions" / mode, PredictContext(severity=0.5), progress=False)
    for protocol in ("lossless", "rigidbench-v1"):
        out["protocols"][protocol] = {}
        for mode in modes:
            summary = evaluate(root / "predictions" / mode, data, root / protocol / mode, nets=FeatureNets(),
                               progress=False, protocol=protocol)
            out["protocols"][protocol][mode] = {m: s["mean"] for m, s in summary.results["overall"].items()}
    a, b = out["protocols"]["lossless"], out["protocols"]["rigidbench-v1"]
    out["change"] = {mode: {m: (None if a[mode][m] is None or b[mode][m] is None else b[mode][m] - a[mode][m])
                            for m in a[mode]} for mode in modes}
    return out


if __name__ == "__main__":
    raise SystemExit(main())
