"""Re-simulate imported published examples and print one JSON object (``datasets.resimulate``).

With ``--data DIR`` (an imported set: DATA or DATA/eval): every imported example's spec is rebuilt from its
published metadata, re-simulated at zero perturbation and compared with its published trajectory; prints the
table (``ResimTable.to_dict()``: per example the outcome, envelope status, reason and errors; per task the count,
outcomes, the share within tolerance and the median errors). ``--out DIR`` also keeps each rebuilt spec with its
re-simulation and ``resimulation.json``.

Without ``--data`` (the synthetic set): one hand-built example per task (tests/fixtures/scenes.py, on our
catalogue's modern_loft counter, task rotation 30 degrees) is simulated, written in the published layout at
``--size`` (tests/fixtures/published_from_sim.py: float32 trajectories, masks and depth ray-cast from the same
meshes, contacts), imported with ``rigidbench import``'s function and re-simulated. It adds ``sensitivity``: for
each task, the largest position error over the first second when one active body's initial x is moved by
1e-9, 1e-7 and 1e-5 m (how much Bullet amplifies a difference below the published data's float32 precision), and
``seconds`` (simulate, write, import, re-simulate; wall clock on this machine).

Usage: python benchmarks/published_resimulation.py [--data DIR] [--out DIR] [--size 320x240]
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
NUDGES_M = (1e-9, 1e-7, 1e-5)


def sensitivity(spec, reg, result) -> dict[str, float]:
    """Largest position error of the active bodies over the first second after moving the last one by each nudge."""
    from rigidbench.blender.physics import simulate

    traj = result.trajectory
    active = [k for k, r in enumerate(traj.roles) if r == "active"]
    window = int(traj.fps) + 1
    out = {}
    for nudge in NUDGES_M:
        body = spec.bodies[active[-1]]
        moved = dataclasses.replace(body, position_m=(body.position_m[0] + nudge, *body.position_m[1:]))
        other = simulate(dataclasses.replace(spec, bodies=tuple(moved if b is body else b for b in spec.bodies)), reg)
        err = np.linalg.norm(other.trajectory.positions_m[active, :window] - traj.positions_m[active, :window], axis=-1)
        out[f"{nudge:g}"] = float(err.max())
    return out


def synthetic(root: Path, size: tuple[int, int], out: Path | None) -> dict:
    sys.path.insert(0, str(ROOT / "tests"))  # the fixtures package
    from fixtures import published_from_sim as pfs  # type: ignore[import-not-found]
    from fixtures.scenes import TASK_SPECS  # type: ignore[import-not-found]

    from rigidbench.blender.physics import simulate
    from rigidbench.config import registry
    from rigidbench.datasets.resimulate import resimulate_published
    from rigidbench.driver import RunOptions
    from rigidbench.stages.import_set import import_published

    reg = registry()
    catalogue = reg.scene("modern_loft").support("counter")
    seconds = {"simulate": 0.0, "write": 0.0}
    written, sens = [], {}
    for k, (task, make) in enumerate(TASK_SPECS.items()):
        spec = make(reg, task_rotation_deg=30.0, support_top_m=catalogue.centre_m[2], support_size_m=catalogue.size_m)
        t0 = time.perf_counter()
        result = simulate(spec, reg)
        t1 = time.perf_counter()
        written.append((f"{k:05d}", pfs.write_example(root / "published" / "samples" / f"{k:05d}", spec, result, reg,
                                                      width=size[0], height=size[1])))
        seconds["simulate"] += t1 - t0
        seconds["write"] += time.perf_counter() - t1
        sens[task] = sensitivity(spec, reg, result)
    pfs.write_set(root / "published", written)
    t0 = time.perf_counter()
    report = import_published(root / "published", root / "data", registry=reg, run=RunOptions(progress=False))
    seconds["import"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    table = resimulate_published(root / "data", reg, out_dir=out)
    seconds["resimulate"] = time.perf_counter() - t0
    return {"source": "synthetic: our simulation of one hand-built example per task in the published layout",
            "size": list(size), "imported": report.ran, "seconds": seconds, "sensitivity_m": sens,
            "table": table.to_dict()}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, help="an imported set (DATA or DATA/eval); default: the synthetic set")
    parser.add_argument("--out", type=Path, help="keep the rebuilt specs, re-simulations and resimulation.json here")
    parser.add_argument("--size", default="320x240", help="synthetic set: frame size WxH (default 320x240)")
    args = parser.parse_args(argv)
    if args.data is not None:
        from rigidbench.datasets.resimulate import resimulate_published

        doc = {"source": str(args.data), "table": resimulate_published(args.data, out_dir=args.out).to_dict()}
    else:
        width, height = (int(v) for v in args.size.lower().split("x"))
        with tempfile.TemporaryDirectory() as tmp:
            doc = synthetic(Path(tmp), (width, height), args.out)
    print(json.dumps(doc, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
