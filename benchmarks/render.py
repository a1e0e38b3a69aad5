"""Time the render stage and print JSON: seconds per frame at `preview` on the CPU and at `paper` on
the best device present (on a CPU only ``--paper-frames`` frames, 2 by default; a paper frame
takes tens of seconds there).

    python benchmarks/render.py [--quick] [--ids 00000 00014 00025 00030] [--paper-frames 2] [--skip-paper]
                                [--preview-samples N]

Per example and preset it reports the camera search, simulation and setup seconds, the data
passes (index + Z) and RGB seconds per frame, and their sum per frame, as wall clock and as CPU
seconds (all render threads of this process, from ``resource.getrusage``, children included);
the target for `preview` on a CPU is < 0.5 s wall per frame on an idle machine. Wall time grows
when other jobs share the cores and CPU time much less, so both are printed with the 1-minute
load average before and after each example: on a busy machine, CPU seconds / cores is the
better estimate of the idle wall time. The default ids are four scenes with different
lighting and materials (white kitchen, marble kitchen, the slowest to render, tiled kitchen, mural room).
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import json
import logging
import os
import platform
import resource
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


def cpu_seconds() -> float:
    """User + system CPU seconds of this process (all threads) and its waited-for children."""
    total = 0.0
    for who in (resource.RUSAGE_SELF, resource.RUSAGE_CHILDREN):
        r = resource.getrusage(who)
        total += r.ru_utime + r.ru_stime
    return total


def load_average() -> float | None:
    """1-minute load average, or None where the platform has none."""
    return round(os.getloadavg()[0], 2) if hasattr(os, "getloadavg") else None


def time_example(row, reg, preset, device: str) -> dict:
    """Render one example in this process; returns timings (seconds, per frame where named so)."""
    from rigidbench.blender.render import render_example
    from rigidbench.scene_spec.build import build_scene_spec

    spec = build_scene_spec(row, reg)
    load_before = load_average()
    with tempfile.TemporaryDirectory() as tmp, _quiet_stdout():
        t0, c0 = time.perf_counter(), cpu_seconds()
        out = render_example(spec, reg, preset, Path(tmp) / "frames", Path(tmp) / "passes", device=device)
        total, total_cpu = time.perf_counter() - t0, cpu_seconds() - c0
    frames = out.index.shape[0]
    s = out.seconds
    return {"id": row.sample_id, "task": row.task, "preset": preset.name, "frames": frames,
            "resolution": list(preset.resolution), "samples": preset.samples, "device": out.device.describe(),
            "camera_search_s": round(s["camera_search"], 3), "simulate_s": round(s["simulate"], 3),
            "setup_s": round(s["setup"], 3), "passes_s_per_frame": round(s["passes"] / frames, 4),
            "rgb_s_per_frame": round(s["rgb"] / frames, 4),
            "render_s_per_frame": round((s["passes"] + s["rgb"]) / frames, 4),
            "passes_cpu_s_per_frame": round(s["passes_cpu"] / frames, 4),
            "rgb_cpu_s_per_frame": round(s["rgb_cpu"] / frames, 4),
            "render_cpu_s_per_frame": round((s["passes_cpu"] + s["rgb_cpu"]) / frames, 4),
            "total_s": round(total, 2), "total_cpu_s": round(total_cpu, 2),
            "scene": row.scene, "load_average_1min": [load_before, load_average()]}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--ids", nargs="+", default=["00000", "00014", "00025", "00030"],
                        help="eval sample ids (default: four scenes with different lighting and materials)")
    parser.add_argument("--paper-frames", type=int, default=2, help="frames rendered at `paper` on a CPU")
    parser.add_argument("--skip-paper", action="store_true")
    parser.add_argument("--preview-samples", type=int, default=None,
                        help="render `preview` with this many samples instead of the preset's (to measure the "
                             "speed/noise trade-off; the JSON records the samples used)")
    parser.add_argument("--quick", action="store_true", help="smoke run: one example at `preview`, no `paper` frames")
    args = parser.parse_args(argv)
    if args.quick:
        args.ids = args.ids[:1]
        args.skip_paper = True
    logging.basicConfig(level=logging.WARNING)
    from rigidbench import manifest
    from rigidbench.config import registry

    reg = registry()
    rows = manifest.select(manifest.rows("eval", reg), args.ids)
    preview_preset = reg.preset("preview")
    if args.preview_samples:
        preview_preset = dataclasses.replace(preview_preset, samples=args.preview_samples)
    results = []
    for row in rows:
        results.append(time_example(row, reg, preview_preset, device="cpu"))
        if not args.skip_paper:
            from rigidbench.blender.render import select_device

            paper = reg.preset("paper")
            if not select_device("auto").is_gpu:
                paper = dataclasses.replace(paper, frames=args.paper_frames)
            results.append(time_example(row, reg, paper, device="auto"))
    preview = [r for r in results if r["preset"] == "preview"]
    cores = os.cpu_count() or 1
    report = {"benchmark": "render", "machine": {"cpus": cores, "platform": platform.platform(),
                                                 "python": sys.version.split()[0],
                                                 "load_average_1min_at_end": load_average()},
              # preview renders on the CPU device: wall seconds, CPU seconds (all threads), and CPU / cores
              "preview_wall_s_per_frame": max(r["render_s_per_frame"] for r in preview),
              "preview_cpu_seconds_per_frame": max(r["render_cpu_s_per_frame"] for r in preview),
              "preview_idle_estimate_s_per_frame": round(max(r["render_cpu_s_per_frame"] for r in preview) / cores, 4),
              "preview_target_s_per_frame": 0.5,
              "preview_samples": preview_preset.samples,
              "paper_s_per_frame": max((r["render_s_per_frame"] for r in results if r["preset"] == "paper"),
                                       default=None),
              "examples": results}
    sys.stdout.flush()
    print(json.dumps(report, indent=1), flush=True)
    os.dup2(os.open(os.devnull, os.O_WRONLY), 1)  # Blender prints a memory report on exit; keep stdout JSON
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
