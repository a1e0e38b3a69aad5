"""Examples per minute for `render --quality test` with the local executor and with Ray at 1 and 2
workers on this machine, and Ray's overhead per task; prints one JSON object.

The local executor renders in child processes (``--workers`` of them); Ray runs one actor per
worker, each rendering in its own process. Each configuration renders the same examples into a
fresh directory, so nothing is skipped as already done. Ray's overhead per task is measured with
a worker that does nothing.

Usage: python benchmarks/scale.py [--quick] [--examples 6] [--quality test]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import tempfile
import time
from pathlib import Path


class NoopWorker:
    """A worker that returns at once: what is left of a task's time is Ray's overhead."""

    def __init__(self, job: dict):
        pass

    def __call__(self, item):
        return {"status": "succeeded"}


def render_rate(rows, reg, quality: str, executor_name: str, workers: int) -> dict:
    from rigidbench.driver import RunOptions
    from rigidbench.executors import RayExecutor
    from rigidbench.stages.render import render_rows

    with tempfile.TemporaryDirectory(prefix="rigidbench-scale-") as tmp:
        t0 = time.perf_counter()
        if executor_name == "local":
            reports = render_rows(rows, reg, Path(tmp), quality=quality, workers=workers,
                                  run=RunOptions(progress=False))
        else:
            reports = render_rows(rows, reg, Path(tmp), quality=quality,
                                  run=RunOptions(executor=RayExecutor(workers=workers), progress=False))
        done = [i for report in reports for i in report.ran]
        failures = [i for report in reports for i in report.failed]
        seconds = time.perf_counter() - t0
    return {"executor": executor_name, "workers": workers, "examples": len(done), "failed": len(failures),
            "seconds": round(seconds, 2), "examples_per_minute": round(60.0 * len(done) / seconds, 2)}


def ray_overhead(tasks: int = 200) -> dict:
    from rigidbench.executors import RayExecutor

    executor = RayExecutor(workers=2)
    executor.map("scale:NoopWorker", {}, list(range(4)))  # start-up: actors, imports (this file on PYTHONPATH)
    t0 = time.perf_counter()
    executor.map("scale:NoopWorker", {}, list(range(tasks)))
    seconds = time.perf_counter() - t0
    return {"tasks": tasks, "seconds": round(seconds, 3), "ms_per_task": round(1000.0 * seconds / tasks, 2)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--examples", type=int, default=6)
    parser.add_argument("--quality", default="test")
    parser.add_argument("--quick", action="store_true", help="smoke run: one example per configuration")
    args = parser.parse_args()
    if args.quick:
        args.examples = 1

    import ray

    from rigidbench import manifest
    from rigidbench.config import registry

    reg = registry()
    rows = manifest.eval_rows(reg)[: args.examples]
    here = str(Path(__file__).resolve().parent)
    ray.init(num_cpus=os.cpu_count(), include_dashboard=False, log_to_driver=False,
             runtime_env={"env_vars": {"PYTHONPATH": os.pathsep.join([here, os.environ.get("PYTHONPATH", "")])}})
    try:
        runs = [render_rate(rows, reg, args.quality, "local", 1), render_rate(rows, reg, args.quality, "local", 2),
                render_rate(rows, reg, args.quality, "ray", 1), render_rate(rows, reg, args.quality, "ray", 2)]
        overhead = ray_overhead()
    finally:
        ray.shutdown()
    base = runs[0]["examples_per_minute"] or float("nan")
    for run in runs:
        run["speedup_vs_local_1"] = round(run["examples_per_minute"] / base, 2)
    print(json.dumps({"benchmark": "scale", "quality": args.quality, "examples": len(rows),
                      "machine": {"cpus": os.cpu_count(), "python": platform.python_version()},
                      "render": runs, "ray_overhead": overhead}, indent=2))


if __name__ == "__main__":
    main()
