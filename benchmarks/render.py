"""Time the render stage and print JSON: seconds per frame at `preview` on the CPU and at `paper` on
the best device present (on a CPU only ``--paper-frames`` frames, 2 by default; a paper frame
takes tens of seconds there).

    python benchmarks/render.py [--ids 00000 ...] [--paper-frames 2] [--skip-paper]

Per example and preset it reports the camera search, simulation and setup seconds, the data
passes (index + Z) and RGB seconds per frame, and their sum per frame (wall clock; also the CPU
seconds of all render threads, which do not grow when other jobs share the machine); the target
for `preview` on a CPU is < 0.5 s per frame. Run it on an otherwise idle machine.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import json
import logging
import os
import platform
import sys
import tempfile
import time
from pathlib import Path


@contextlib.contextmanager
def _quiet_stdout():
    """Send the C-level stdout (Blender's per-tile progress) to /dev/null, so stdout holds only the JSON."""
    sys.stdout.flush()
    saved = os.dup(1)
    devnull = os.open(os.devnull, os.O_WRONLY)
    os.dup2(devnull, 1)
    try:
        yield
    finally:
        os.dup2(saved, 1)
        os.close(saved)
        os.close(devnull)


def time_example(row, reg, preset, device: str) -> dict:
    """Render one example in this process; returns timings (seconds, per frame where named so)."""
    from rigidbench.blender.render import render_example
    from rigidbench.spec.build import build_scene_spec

    spec = build_scene_spec(row, reg)
    with tempfile.TemporaryDirectory() as tmp, _quiet_stdout():
        t0 = time.perf_counter()
        out = render_example(spec, reg, preset, Path(tmp) / "frames", Path(tmp) / "passes", device=device)
        total = time.perf_counter() - t0
    frames = out.index.shape[0]
    s = out.seconds
    return {"id": row.sample_id, "task": row.task, "preset": preset.name, "frames": frames,
            "resolution": list(preset.resolution), "samples": preset.samples, "device": out.device.describe(),
            "camera_search_s": round(s["camera_search"], 3), "simulate_s": round(s["simulate"], 3),
            "setup_s": round(s["setup"], 3), "passes_s_per_frame": round(s["passes"] / frames, 4),
            "rgb_s_per_frame": round(s["rgb"] / frames, 4),
            "render_s_per_frame": round((s["passes"] + s["rgb"]) / frames, 4),
            "render_cpu_s_per_frame": round((s["passes_cpu"] + s["rgb_cpu"]) / frames, 4),
            "total_s": round(total, 2)}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--ids", nargs="+", default=["00000"], help="eval sample ids (default 00000, a ball chain)")
    parser.add_argument("--paper-frames", type=int, default=2, help="frames rendered at `paper` on a CPU")
    parser.add_argument("--skip-paper", action="store_true")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.WARNING)
    from rigidbench import manifest
    from rigidbench.config import registry

    reg = registry()
    rows = manifest.select(manifest.rows("eval", reg), args.ids)
    results = []
    for row in rows:
        results.append(time_example(row, reg, reg.preset("preview"), device="cpu"))
        if not args.skip_paper:
            from rigidbench.blender.render import select_device

            paper = reg.preset("paper")
            if not select_device("auto").is_gpu:
                paper = dataclasses.replace(paper, frames=args.paper_frames)
            results.append(time_example(row, reg, paper, device="auto"))
    preview = [r["render_s_per_frame"] for r in results if r["preset"] == "preview"]
    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else None
    report = {"benchmark": "render", "machine": {"cpus": os.cpu_count(), "platform": platform.platform(),
                                                 "python": sys.version.split()[0],
                                                 "load_average_1min_at_end": load},
              "preview_cpu_s_per_frame": max(preview), "preview_target_s_per_frame": 0.5,
              "paper_s_per_frame": max((r["render_s_per_frame"] for r in results if r["preset"] == "paper"),
                                       default=None),
              "examples": results}
    sys.stdout.flush()
    print(json.dumps(report, indent=1), flush=True)
    os.dup2(os.open(os.devnull, os.O_WRONLY), 1)  # Blender prints a memory report on exit; keep stdout JSON
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
