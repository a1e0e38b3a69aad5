"""Do N geometry-only physical twins of an example cost less than rendering the example itself? Prints JSON.

    python benchmarks/envelope_twins.py [--quick] [--id 00010] [--presets test preview] [--twins 8]

Per preset (default `test` and `preview`; ``--quick``: `test` and 2 twins), in one process on the CPU:

- ``reference.cold``: the example rendered as ``rigidbench render`` does (camera search, simulation, data
  passes, RGB frames, bundle files), the first Blender work of the process (kernel and texture loading);
- ``reference.warm``: its resolved spec rendered again into a new bundle (no camera search), the same
  process warm: what a twin would cost if it were rendered in full;
- ``twins``: N geometry-only twins (``twin`` predictor, option geometry_only, scale 1, samples 0..N-1 of
  base seed 0) made and written as ``rigidbench predict`` writes them (video and world state) in the same
  warm process: total and per-twin seconds, split into making the prediction and writing it, with the
  kept scene's own breakdown (simulate, passes; the first twin of an example also builds the scene);
- ``ratio``: twins total / warm reference (wall and CPU) and ``cheaper``: whether the N twins cost less
  than one warm reference render, by wall clock and by CPU seconds.

Wall and CPU seconds (all threads of this process) are both given, with the 1-minute load average: on a
busy machine CPU seconds are the steadier measure.
"""

from __future__ import annotations

import argparse
import os
import platform
import resource
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _rendered import json_stdout  # noqa: E402


def cpu_seconds() -> float:
    r = resource.getrusage(resource.RUSAGE_SELF)
    return r.ru_utime + r.ru_stime


def timed(fn):
    """(result, {"wall_s", "cpu_s"}) of fn()."""
    t0, c0 = time.perf_counter(), cpu_seconds()
    out = fn()
    return out, {"wall_s": round(time.perf_counter() - t0, 3), "cpu_s": round(cpu_seconds() - c0, 3)}


def bench_preset(sample_id: str, preset_name: str, twins: int, root: Path) -> dict:
    from rigidbench import manifest
    from rigidbench.blender.render import render_spec
    from rigidbench.config import load_registry
    from rigidbench.groundtruth.bundle import Sample
    from rigidbench.predictors import PREDICTORS, PredictContext, sample_seed
    from rigidbench.folders import sample_item
    from rigidbench.stages.predict import write_prediction
    from rigidbench.stages.render import render_to_bundle

    reg = load_registry()
    preset = reg.preset(preset_name)
    row = next(r for r in manifest.eval_rows(reg) if r.sample_id == sample_id)
    out = root / preset_name
    _, cold = timed(lambda: render_to_bundle(row, reg, preset, out))
    sample = Sample(out / "eval" / sample_id)
    _, warm = timed(lambda: render_spec(sample.spec, reg, preset, out / "again" / sample_id, device="cpu"))
    predictor = PREDICTORS["twin"].create()
    per_twin = []
    load_before = os.getloadavg()[0]
    t0, c0 = time.perf_counter(), cpu_seconds()

    def make(k: int) -> dict:
        ctx = PredictContext(seed=sample_seed(0, sample_id, k), options={"geometry_only": True})
        pred, made = timed(lambda: predictor.predict(sample, ctx))
        _, written = timed(lambda: write_prediction(pred, out / "twins", sample_item(sample_id, k), sample.fps))
        return {"predict": made, "write": written, "render": pred.metadata["render_seconds"]}

    for k in range(twins):
        parts, cost = timed(lambda: make(k))
        per_twin.append({**cost, **parts})
    total = {"wall_s": round(time.perf_counter() - t0, 3), "cpu_s": round(cpu_seconds() - c0, 3)}
    ratio = {k: round(total[k] / warm[k], 3) for k in ("wall_s", "cpu_s")}
    return {"preset": preset_name, "resolution": list(preset.resolution), "frames": preset.frames,
            "samples": preset.samples,
            "reference": {"cold": {**cold, "render": sample.metadata.get("render_seconds")}, "warm": warm},
            "twins": {"count": twins, "total": total, "per_twin": per_twin,
                      "mean_wall_s": round(total["wall_s"] / twins, 3), "mean_cpu_s": round(total["cpu_s"] / twins, 3),
                      "load_1min_before": round(load_before, 2), "load_1min_after": round(os.getloadavg()[0], 2)},
            "ratio": ratio, "cheaper": {"wall": ratio["wall_s"] < 1, "cpu": ratio["cpu_s"] < 1}}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--quick", action="store_true", help="the test preset and 2 twins")
    parser.add_argument("--id", default="00010", help="evaluation example (default 00010, a drop into a cluster)")
    parser.add_argument("--presets", nargs="+", default=["test", "preview"])
    parser.add_argument("--twins", type=int, default=8)
    args = parser.parse_args()
    presets, twins = (["test"], 2) if args.quick else (args.presets, args.twins)
    with json_stdout() as emit, tempfile.TemporaryDirectory() as tmp:
        results = {p: bench_preset(args.id, p, twins, Path(tmp)) for p in presets}
        emit({"id": args.id, "machine": {"cpus": os.cpu_count(), "platform": platform.platform()},
              "device": "cpu", "presets": results})


if __name__ == "__main__":
    main()
