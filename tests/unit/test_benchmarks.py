"""Benchmarks that cannot rot (issue 27): every ``benchmarks/*.py`` runs in its quickest mode and prints
one valid JSON object holding the fields its docstring promises. Timings are never asserted.

Scripts that need minutes even at their smallest are listed in ``SKIPPED`` with the reason; a new
script must be added to one of the two tables (``test_every_benchmark_is_covered``).
"""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
BENCHMARKS = ROOT / "benchmarks"

#: script -> (arguments of its quickest mode, fields its docstring promises as "a.b.c" paths)
QUICK = {
    "metrics.py": (["--quick"], [
        "machine.cpus", "clip.frames", "clip.corners", "clip.iddrift_pairs",
        "timings.array_metrics_total.seconds", "timings.array_metrics_total.cpu_seconds",
        "timings.array_metrics_total.tracemalloc_peak_mb", "timings.array_metrics_total.rss_peak_delta_mb",
        "timings.array_metrics_total.ru_maxrss_delta_mb", "timings.ssim_filter_floor.cpu_seconds",
        "timings.ssim_filter_floor.ssim_over_floor_cpu", "timings.iou.seconds", "timings.ssim.seconds",
        "timings.lpips_alexnet_random_weights.seconds", "timings.iddrift_pipeline_small_convnet.seconds",
        "values.iou", "values.centroid_l2", "values.chamfer", "values.ate", "values.ate3d", "values.si_mse",
        "values.ssim", "values.lpips", "values.iddrift", "values.bgdrift"]),
    "stats.py": (["--quick"], ["shape.resamples", "means_ci_80_cells_s", "poi_matrices_10_metrics_s",
                               "paired_difference_matrices_10_metrics_s", "correlation_s"]),
    "simulate.py": (["--quick"], ["mean_seconds_per_example", "max_seconds_per_example", "meets_target",
                                  "tasks.bounce.seconds_per_example", "tasks.bounce.cpu_seconds_per_example"]),
    "inlp_procedures.py": (["--quick"], [f"cases.{c}.{p}.{f}" for c in ("redundant", "redundant_x100", "outliers")
                                         for p in ("stable", "release", "release_float64")
                                         for f in ("rank", "rounds", "train_r2", "heldout_r2_after_removal")]
                           + ["cases.outliers.release.largest_angle_deg", "cases.outliers.release.first_round_apart"]),
    "storage.py": (["--quick"], [f"{k}.{f}" for k in ("h264_yuv420p_crf18", "h264_rgb_lossless", "release_jpeg_q95_444")
                                 for f in ("ssim", "max_abs_error", "psnr_db", "bytes")]),
    "generate.py": (["--quick"], ["hosted.overhead_per_call_s", "hosted.by_concurrency"]),
    "train.py": (["--quick"], ["cpu_tiny.lora.s_per_step", "cpu_tiny.lora.peak_rss_mib"]),
    "wan_numerics.py": (["--quick"], ["seconds_ours"] + [f"vs_ours.{v}.{f}" for v in (
        "timestep_dtype=bfloat16", "update_dtype=bfloat16", "vae_codec=diffsynth-tiled", "recipe=release")
        for f in ("max_levels", "mean_levels", "fraction_differing")]),
    "perception.py": (["--quick"], ["device", "clip.frames", "models.lpips.seconds", "models.lpips.cpu_seconds",
                                    "models.lpips.params_m", "models.lpips.peak_gpu_mb"]),
    "published_import.py": (["--quick"], ["source.bytes.total", "import.seconds", "import.cpu_seconds",
                                          "import.bytes_added.total", "import.added_fraction", "import.frames.linked",
                                          "digest.seconds", "frame_check.seconds", "rerun.seconds",
                                          "after_deleting_source.bundle_ok"]),
    "assets_preview.py": (["--quick"], ["object_ms.apple.first_in_process", "object_ms_after_reset_mean"]),
    "evaluate_samples.py": (["--quick"], ["machine.cpus", "clip.width", "runs.K1.wall_s", "runs.K1.cpu_s",
                                          "runs.K1.phases_s.imports", "runs.K1.phases_s.evaluate",
                                          "runs.K1.phases_s.decode_s", "runs.K1.phases_s.metrics_s",
                                          "runs.K1.records", "runs.K2.wall_s", "runs.K2.records",
                                          "runs.K2.metrics.1.iou"]),
    # renders one example twice at the test preset and makes 2 geometry-only twins (about 25 s on a 2-core CPU)
    "envelope_twins.py": (["--quick"], [f"presets.test.{f}" for f in (
        "reference.cold.wall_s", "reference.cold.cpu_s", "reference.warm.wall_s", "reference.warm.cpu_s",
        "twins.count", "twins.total.wall_s", "twins.total.cpu_s", "twins.mean_wall_s", "twins.mean_cpu_s",
        "ratio.wall_s", "ratio.cpu_s", "cheaper.wall", "cheaper.cpu")]),
    # renders two examples at the test preset with Blender (about 18 s on a 2-core CPU)
    "track_rule.py": (["--quick"], ["ids", "preset", "rules.rigidbench.points", "rules.published.visible_frac",
                                    "rules.published.scores.reference.ate", "max_abs_change.ate",
                                    "max_abs_change.ate3d", "seconds"]),
}

#: script -> why it is not run here (run them by hand: see each docstring)
SKIPPED = {
    "render.py": "--quick still renders one example's 49 preview frames with Cycles: over a minute on a 2-core CPU",
    "scale.py": "starts Ray and renders with several executors: about 45 s even with --quick (one example)",
    "probe.py": "--quick still fits probes and INLP cells: about two minutes on a 2-core CPU",
    "published_resimulation.py": "builds a synthetic published set (one example per task) and re-simulates it with "
                                 "Blender: about 45 s on a 2-core CPU; tests/integration/test_published_resim.py "
                                 "covers the same code",
    "protocol_effect.py": "--quick renders an example with Blender and scores two failure modes, five hostile "
                          "cases and a BT.709 clip under three protocols: about 60 s on a 2-core CPU",
}


def _field(data, path: str):
    for part in path.split("."):
        assert isinstance(data, dict) and part in data, f"missing {path!r} (at {part!r})"
        data = data[part]
    return data


def _strict(value) -> None:
    """json.loads accepts NaN and Infinity, which are not JSON: refuse them."""
    json.dumps(value, allow_nan=False)


def test_every_benchmark_is_covered():
    scripts = {p.name for p in BENCHMARKS.glob("*.py") if not p.name.startswith("_")}  # _*.py: shared helpers
    assert scripts == set(QUICK) | set(SKIPPED), "add each new benchmark to QUICK (or SKIPPED, with a reason)"
    for name in scripts:
        assert (BENCHMARKS / name).read_text().lstrip().startswith('"""'), f"{name} has no docstring"


@pytest.mark.parametrize("name", sorted(QUICK))
def test_benchmark_prints_its_promised_json(name, tmp_path):
    args, fields = QUICK[name]
    env = dict(os.environ, PYTHONPATH=str(ROOT / "src"), MPLBACKEND="Agg")
    out = subprocess.run([sys.executable, str(BENCHMARKS / name), *args], cwd=tmp_path, env=env,
                         capture_output=True, text=True, timeout=180)
    assert out.returncode == 0, f"{name} failed:\n{out.stderr[-3000:]}"
    text = out.stdout
    start = text.find("{")
    assert start >= 0, f"{name} printed no JSON object:\n{text[-2000:]}"
    data = json.loads(text[start:])  # one JSON object, nothing after it
    assert isinstance(data, dict)
    _strict(data)
    for path in fields:
        value = _field(data, path)
        if isinstance(value, float):
            assert math.isfinite(value), f"{name}: {path} = {value}"
    if name == "metrics.py":  # every measurement has a value on the synthetic clip
        assert all(v is not None for v in data["values"].values())
