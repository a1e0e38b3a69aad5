"""Time Bullet simulation per example (scene build + all frames + contacts) and print JSON.

Target: under 0.2 s per example on one core. By default the process is pinned to one CPU and
BLAS threads are limited to one. Workloads:
  --source hand      one hand-built spec per task (tests/fixtures/scenes.py)
  --source eval|train  the first manifest row of each task, built with build_scene_spec
  --spec FILE ...    scene_spec.json files
Usage: python benchmarks/simulate.py [--quick] [--source hand] [--repeat 5] [--all-cores]
"""

from __future__ import annotations

import os
import sys

if "--all-cores" not in sys.argv:  # before numpy loads its BLAS
    for var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ[var] = "1"

import argparse  # noqa: E402
import json  # noqa: E402
import platform  # noqa: E402
import statistics  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
TARGET_S = 0.2


def hand_specs(reg):
    """One hand-built spec per task, shared with the integration tests."""
    sys.path.insert(0, str(ROOT / "tests"))  # the fixtures package
    from fixtures.scenes import hand_specs as build  # type: ignore[import-not-found]

    return build(reg)


def manifest_specs(reg, split: str):
    """The first manifest row of each task, built into a SceneSpec."""
    from rigidbench.manifest import rows
    from rigidbench.scene_spec.build import build_scene_spec

    out = {}
    for row in rows(split, reg):
        if row.task not in out:
            out[row.task] = build_scene_spec(row, reg)
    return out


def file_specs(paths):
    from rigidbench.scene_spec.types import SceneSpec

    return {f"{Path(p).parent.name or Path(p).stem}:{i}": SceneSpec.from_json(Path(p).read_text())
            for i, p in enumerate(paths)}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--source", choices=("hand", "eval", "train"), default="hand")
    parser.add_argument("--spec", nargs="+", help="scene_spec.json files (overrides --source)")
    parser.add_argument("--repeat", type=int, default=5)
    parser.add_argument("--all-cores", action="store_true", help="do not pin to one CPU")
    parser.add_argument("--quick", action="store_true", help="smoke run: 1 repeat")
    args = parser.parse_args(argv)
    if args.quick:
        args.repeat = 1

    pinned = False
    if not args.all_cores and hasattr(os, "sched_setaffinity"):
        os.sched_setaffinity(0, {sorted(os.sched_getaffinity(0))[0]})
        pinned = True

    from rigidbench.blender import physics
    from rigidbench.blender.physics import simulate
    from rigidbench.config import registry

    reg = registry()
    specs = file_specs(args.spec) if args.spec else (hand_specs(reg) if args.source == "hand"
                                                    else manifest_specs(reg, args.source))
    simulate(next(iter(specs.values())), reg)  # warm-up: first bpy operator calls, scipy import
    tasks = {}
    for key, spec in specs.items():
        # Collision hulls are built from the procedural meshes once per object and process; time that too.
        physics._HULLS.clear()
        t0 = time.perf_counter()
        for body in spec.active:
            physics.body_mesh(body, reg)
        hull_s = time.perf_counter() - t0
        wall, cpu, parts = [], [], []
        for _ in range(args.repeat):
            t0, c0 = time.perf_counter(), time.process_time()
            result = simulate(spec, reg)
            wall.append(time.perf_counter() - t0)
            cpu.append(time.process_time() - c0)
            parts.append(result.timings_s)
        tasks[key] = {
            "sample_id": spec.sample_id,
            "task": spec.task,
            "active_bodies": len(spec.active),
            "passive_bodies": len(spec.bodies) - len(spec.active),
            "contacts": len(result.contacts),
            "seconds_per_example": round(statistics.median(wall), 4),
            "cpu_seconds_per_example": round(statistics.median(cpu), 4),
            "stage_seconds": {k: round(statistics.median(p[k] for p in parts), 4) for k in parts[0]},
            "first_run_hull_seconds": round(hull_s, 4),  # extra, once per object id and process
        }
    per_example = [t["seconds_per_example"] for t in tasks.values()]
    report = {
        "benchmark": "simulate",
        "source": "files" if args.spec else args.source,
        "repeat": args.repeat,
        "pinned_to_one_cpu": pinned,
        "machine": f"{platform.machine()} {os.cpu_count()} cpus, load {os.getloadavg()[0]:.2f}",
        "frames": next(iter(specs.values())).sim.frames,
        "target_seconds_per_example": TARGET_S,
        "mean_seconds_per_example": round(statistics.mean(per_example), 4),
        "max_seconds_per_example": round(max(per_example), 4),
        "meets_target": max(per_example) < TARGET_S,
        "tasks": tasks,
    }
    print(json.dumps(report, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
