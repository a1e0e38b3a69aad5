"""Time rigidbench.stats at the paper's size and print JSON.

Paper size: 8 models x 10 metrics x 100 examples, 20,000 bootstrap resamples (appendix C).
Synthetic scores; one cell has two non-finite examples, as Veo 3.1 on IdDrift does in the paper,
so the run exercises a second example-count group.

Usage: python benchmarks/stats.py [--quick] [--repeats 3] [--resamples 20000]
"""

from __future__ import annotations

import argparse
import json
import platform
import time

import numpy as np

from rigidbench.stats import (
    bootstrap_ci,
    correlation_across_models,
    paired_difference_matrix,
    probability_of_improvement_matrix,
)

N_METRICS, N_MODELS, N_EXAMPLES = 10, 8, 100
# Direction per metric, in the paper's table order: IoU up, L2, Chamfer, ATE, ATE-3D, SI-MSE down,
# SSIM up, LPIPS, IdDrift, BGDrift down.
HIGHER_IS_BETTER = [True, False, False, False, False, False, True, False, False, False]


def synthetic_scores(seed: int = 0) -> np.ndarray:
    """Returns (N_METRICS, N_MODELS, N_EXAMPLES) float64 scores with per-model offsets and two NaNs."""
    rng = np.random.default_rng(seed)
    example_effect = rng.normal(size=(N_METRICS, 1, N_EXAMPLES))
    model_effect = rng.normal(scale=0.3, size=(N_METRICS, N_MODELS, 1))
    scores = example_effect + model_effect + rng.normal(scale=0.5, size=(N_METRICS, N_MODELS, N_EXAMPLES))
    scores[8, 2, [13, 57]] = np.nan
    return scores


def best_of(fn, repeats: int) -> tuple[float, list[float]]:
    """Runs fn `repeats` times. Returns (fastest seconds, all seconds)."""
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
    return min(times), times


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--resamples", type=int, default=20000)
    parser.add_argument("--quick", action="store_true", help="smoke run: 1 repeat, 200 resamples")
    args = parser.parse_args()
    if args.quick:
        args.repeats = 1
        args.resamples = 200
    scores = synthetic_scores()
    b = args.resamples

    def means_ci():
        return bootstrap_ci(scores, n_resamples=b)

    def poi_matrices():
        return [
            probability_of_improvement_matrix(scores[k], HIGHER_IS_BETTER[k], n_resamples=b)
            for k in range(N_METRICS)
        ]

    def diff_matrices():
        return [paired_difference_matrix(scores[k], n_resamples=b) for k in range(N_METRICS)]

    model_means = np.nanmean(scores, axis=-1)

    def correlation():
        return correlation_across_models(model_means[6], -model_means[4], n_resamples=b)

    means_s, means_all = best_of(means_ci, args.repeats)
    poi_s, poi_all = best_of(poi_matrices, args.repeats)
    diff_s, diff_all = best_of(diff_matrices, args.repeats)
    corr_s, corr_all = best_of(correlation, args.repeats)
    corr = correlation()
    report = {
        "benchmark": "rigidbench.stats",
        "shape": {"metrics": N_METRICS, "models": N_MODELS, "examples": N_EXAMPLES, "resamples": b},
        "machine": {"python": platform.python_version(), "numpy": np.__version__, "processor": platform.machine()},
        "repeats": args.repeats,
        "means_ci_80_cells_s": round(means_s, 4),
        "poi_matrices_10_metrics_s": round(poi_s, 4),
        "paired_difference_matrices_10_metrics_s": round(diff_s, 4),
        "correlation_s": round(corr_s, 4),
        "all_runs_s": {
            "means_ci": [round(t, 4) for t in means_all],
            "poi_matrices": [round(t, 4) for t in poi_all],
            "paired_difference_matrices": [round(t, 4) for t in diff_all],
            "correlation": [round(t, 4) for t in corr_all],
        },
        "correlation_n_degenerate": corr["n_degenerate"],
    }
    print(json.dumps(report, indent=2))


if __name__ == "__main__":
    main()
