"""How far the release's INLP procedure parts from ours on synthetic activations; prints JSON.

    python benchmarks/inlp_procedures.py            # the cases of docs/probing.md ("INLP procedures")
    python benchmarks/inlp_procedures.py --quick    # small versions of the same cases (seconds)

For each case, INLP for a 3-d position target three ways (``rigidbench.probe.inlp``): ``stable`` (ours,
the default: one float64 Gram matrix, each round's projected ridge solved from it), ``release`` (the
release's steps literally: float32 rows re-projected one regressor at a time, float32 null spaces,
the basis from the float32 projector) and the release's steps in float64 (``rows_dtype=float64``), which
separates what the re-projection itself does from what float32 adds.

Per procedure: ``rank``, ``rounds`` (regressors added), ``stopped``, the training R^2 path ``train_r2``
(pooled, one value per round, the last one the round that stopped it), and ``heldout_r2_after_removal``:
ridge (the release's, 0.05 x rows, no intercept) refitted on the training rows with the basis projected
out, scored (pooled R^2) on the held-out 20% projected the same way, as the release's ``fit_cell``
diagnostic ``r2_test_post``. Per case, for ``release`` and ``release_float64`` against ``stable``:
``first_round_apart`` (the first round whose training R^2 differs by more than 1e-3; null if none) and
``largest_angle_deg`` (the largest principal angle between the two bases over the smaller rank).

Cases (``generate``): ``redundant``: a 3-d target z spread over D features with correlated noise and an
offset of 2, ``x = z A + e M + 2`` (A, M Gaussian, the noise columns scaled by U(0.05, 1) x 0.5), as
``tests/unit/test_probe_core.py`` uses; ``redundant_x10`` / ``_x100``: the same activations times 10 / 100
(the ridge penalty is not scale-free: 0.05 x rows against activations 100x larger is 10^4 weaker);
``outliers``: activation-like rows, a position signal through tanh (0.3 tanh(z A)) on a decaying
spectrum of Gaussian noise (scale 1/sqrt(1 + i) in a random rotation), with 4 outlier dimensions
multiplied by 10^4 and offset by 1-3 x 10^4, as transformer residual streams carry a few massive
dimensions.
"""

from __future__ import annotations

import argparse
import json
import platform
import time

import numpy as np
import torch

from rigidbench.probe.fit import r2_score
from rigidbench.probe.inlp import inlp, inlp_release, project_out, ridge_fit, split_rows

PROCEDURES = ("stable", "release", "release_float64")


def redundant(n: int, d: int, seed: int = 0, scale: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    z = rng.standard_normal((n, 3))
    noise = rng.standard_normal((n, d)) @ (rng.standard_normal((d, d)) * rng.uniform(0.05, 1.0, d)) * 0.5
    x = z @ rng.standard_normal((3, d)) + noise + 2.0
    return (x * scale).astype(np.float32), z + np.array([1.0, 0.5, -2.0])


def outliers(n: int, d: int, seed: int = 0, outlier_dims: int = 4, outlier_scale: float = 1e4):
    rng = np.random.default_rng(seed)
    z = rng.standard_normal((n, 3))
    spectrum = 1.0 / np.sqrt(1.0 + np.arange(d))
    base = (rng.standard_normal((n, d)) * spectrum) @ np.linalg.qr(rng.standard_normal((d, d)))[0]
    x = 0.3 * np.tanh(z @ rng.standard_normal((3, d))) + base
    idx = rng.choice(d, outlier_dims, replace=False)
    x[:, idx] = x[:, idx] * outlier_scale + outlier_scale * rng.uniform(1.0, 3.0, outlier_dims)
    return x.astype(np.float32), z


def generate(quick: bool) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    n, d = (1500, 48) if quick else (4000, 128)
    return {"redundant": redundant(n, d), "redundant_x10": redundant(n, d, scale=10.0),
            "redundant_x100": redundant(n, d, scale=100.0),
            "outliers": outliers(*((1500, 64) if quick else (6000, 256)))}


def largest_angle(a: np.ndarray, b: np.ndarray) -> float | None:
    if not a.shape[1] or not b.shape[1]:
        return None
    cosines = np.linalg.svd(a.T @ b, compute_uv=False)
    return float(np.degrees(np.arccos(np.clip(cosines.min(), -1.0, 1.0))))


def heldout_after_removal(x: np.ndarray, y: np.ndarray, basis: np.ndarray) -> float:
    tr, ho = split_rows(len(x))
    removed = project_out(x.astype(np.float64), basis)
    return r2_score(y[ho], removed[ho] @ ridge_fit(removed[tr], y[tr]))


def run_case(x: np.ndarray, y: np.ndarray) -> dict:
    fits, out = {}, {"rows": int(len(x)), "width": int(x.shape[1])}
    for name in PROCEDURES:
        t0 = time.perf_counter()
        if name == "stable":
            res = inlp(x, y, device="cpu")
        else:
            res = inlp_release(x, y, device="cpu",
                               rows_dtype=torch.float64 if name == "release_float64" else torch.float32)
        fits[name] = res
        out[name] = {"rank": res.rank, "rounds": res.rounds, "stopped": res.stopped,
                     "train_r2": [round(r, 5) for r in res.train_r2],
                     "heldout_r2_after_removal": heldout_after_removal(x, y, res.basis),
                     "seconds": time.perf_counter() - t0}
    for name in PROCEDURES[1:]:
        a, b = fits["stable"].train_r2, fits[name].train_r2
        apart = [i for i in range(min(len(a), len(b))) if abs(a[i] - b[i]) > 1e-3]
        out[name]["first_round_apart"] = (apart[0] + 1) if apart else None
        out[name]["largest_angle_deg"] = largest_angle(fits["stable"].basis, fits[name].basis)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="small cases (a smoke run, seconds)")
    args = ap.parse_args()
    torch.set_num_threads(1)  # the same float32 summation order on every run of this machine
    out = {"host": platform.node(), "torch": torch.__version__, "device": "cpu", "cases": {}}
    for name, (x, y) in generate(args.quick).items():
        out["cases"][name] = run_case(x, y)
    print(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
