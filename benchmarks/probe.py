"""Time probing and print JSON.

    python benchmarks/probe.py [--clips 4] [--no-gpu]             # everything
    python benchmarks/probe.py --only inlp                          # INLP per cell at the paper's size
    python benchmarks/probe.py --only inlp --inlp-fraction 0.25     # ... at a stated fraction of its rows
    python benchmarks/probe.py --quick                              # a smoke run of every part (about a minute)

CPU rows (always): the tiny Wan transformer (``--model tiny``): extraction compute per clip (five
schedule fractions, one forward each with hooks on every block, actor pooling; bundle reading and
writing shards excluded) and probe-fit seconds per cell (linear and MLP, 20 epochs, the paper's
optimiser) on synthetic rows of the tiny width (24); and one linear and one MLP cell at Wan's width
(3,072) on 8,192 synthetic rows, scaled linearly to the paper's 148,303 training rows (labelled as
a projection: the epoch cost is linear in the rows).

INLP rows: one intervention cell (``intervene.fit_bases``: INLP on 80% of the rows, the random and
variance-matched PC controls) on synthetic float32 activations of width 3,072 with a 3-d target spread
over many correlated directions (so that INLP runs many rounds), at the paper's 186,636 actor-time
rows (148,303 + 19,696 + 18,637: the bases are fitted on the full corpus, INLP trains on
int(0.8 n) = 149,308) or ``--inlp-fraction`` of them; float64 (the default) and float32. Seconds
(INLP alone and the whole cell), rounds, rank, and peak memory: on the CPU the process's peak
resident memory above what it held before the cell (Linux VmHWM after resetting it; the activations
themselves, 4 n D bytes, are held before and not counted), on a GPU torch's peak allocation, which
includes the activations copied there.

GPU rows (only when torch sees a GPU): extraction per clip at real size with random weights of Wan
2.2 TI2V-5B's transformer (bfloat16; 13 x 11 x 20 = 2,860 tokens, text 512 x 4,096), one
linear / MLP fit cell with 148,303 rows of width 3,072 trained on the GPU (``ProbeSettings(device=...)``),
and the INLP cell on the GPU.

Projection (labelled): the paper's 5,000 clips x 3 backbones of extraction, and 150 cells x 7
targets x 2 probes x 2 label conditions x 3 backbones of fits, from the measured per-clip and
per-cell times of the device each row names.
"""

from __future__ import annotations

import argparse
import json
import platform
import time

import numpy as np
import torch

from rigidbench.probe import model as wan
from rigidbench.probe.fit import ProbeSettings, fit_cell
from rigidbench.probe.pooling import pooling_matrix
from rigidbench.train.objective import FlowMatchingObjective

PAPER_CLIPS, PAPER_BACKBONES = 5000, 3
PAPER_CELLS = 30 * 5
PAPER_TRAIN_ROWS, PAPER_VAL_ROWS, PAPER_TEST_ROWS = 148_303, 19_696, 18_637
PAPER_ALL_ROWS = PAPER_TRAIN_ROWS + PAPER_VAL_ROWS + PAPER_TEST_ROWS  # INLP's corpus: 186,636 rows
WIDTH = 3072
INTERVENTION_CELLS = 30 * 3  # blocks x the three intervention taus
N_TARGETS, N_PROBES, N_LABELS = 7, 2, 2


def time_extraction(transformer, latent_shape, text_shape, clips: int, device, dtype) -> float:
    """Median seconds per clip of the extraction compute (5 taus x forward with hooks + pooling)."""
    obj = FlowMatchingObjective(patch_size=transformer.config.patch_size)
    slots, gh, gw = wan.token_grid(latent_shape, transformer.config.patch_size)
    rng = np.random.default_rng(0)
    tm = np.zeros((slots, 3, gh, gw), dtype=bool)
    tm[:, :, : max(1, gh // 3), : max(1, gw // 3)] = True
    tm[:, 1] = rng.random((slots, gh, gw)) < 0.2
    tm[:, 2] = rng.random((slots, gh, gw)) < 0.1
    w = torch.as_tensor(pooling_matrix(tm)[0], device=device)
    times = []
    for c in range(clips + 1):
        latent = torch.randn((1,) + tuple(latent_shape))
        text = torch.randn(text_shape)
        if device.type == "cuda":
            torch.cuda.synchronize()
        t0 = time.perf_counter()
        for tau in wan.DEFAULT_TAUS:
            batch = obj.prepare(latent, wan.clip_noise(str(c), latent.shape), wan.tau_index(tau))
            store: dict = {}
            with torch.no_grad(), wan.capture_blocks(transformer, store):
                wan.forward(transformer, batch, text, device, dtype)
            pooled = [(w @ store[b][0].float()).to(torch.float16).cpu() for b in range(len(transformer.blocks))]
            del pooled
        if device.type == "cuda":
            torch.cuda.synchronize()
        if c:  # the first clip warms up
            times.append(time.perf_counter() - t0)
    return float(np.median(times))


def time_fit(rows: int, width: int, probe: str, binary: bool = False, device: str = "cpu") -> float:
    rng = np.random.default_rng(0)
    x = rng.standard_normal((rows, width)).astype(np.float32)
    y = (x[:, :3] + 0.1 * rng.standard_normal((rows, 3))).astype(np.float32)
    n_eval = max(2, rows // 10)
    xe, ye = x[:n_eval], y[:n_eval]
    settings = ProbeSettings(device=device)
    if device != "cpu":
        torch.cuda.synchronize()
    t0 = time.perf_counter()
    fit_cell((x, y), (xe, ye), (xe, ye), probe, binary, "trained", settings)
    if device != "cpu":
        torch.cuda.synchronize()
    return time.perf_counter() - t0


def synthetic_cell(rows: int, width: int = WIDTH, seed: int = 0, chunk: int = 16384):
    """(x float32 (rows, width), y (rows, 3)): a 3-d target z read out through many correlated
    directions: x = z A + u B + e + 1 (u 64-d, e white noise)."""
    g = torch.Generator().manual_seed(seed)
    a = torch.randn(3, width, generator=g) * 0.3
    b = torch.randn(64, width, generator=g) * 0.5
    z = torch.randn(rows, 3, generator=g)
    x = torch.empty(rows, width)
    for s in range(0, rows, chunk):
        n = min(chunk, rows - s)
        x[s:s + n] = z[s:s + n] @ a + torch.randn(n, 64, generator=g) @ b + torch.randn(n, width, generator=g) + 1.0
    return x.numpy(), (z + torch.tensor([0.5, 1.0, -1.5])).double().numpy()


def _rss_gib(field: str) -> float:
    for line in open("/proc/self/status"):
        if line.startswith(field + ":"):
            return int(line.split()[1]) / 2**20
    return float("nan")


def _reset_peak_rss() -> bool:
    try:
        with open("/proc/self/clear_refs", "w") as fh:
            fh.write("5")
        return True
    except OSError:
        return False


def time_inlp_cell(x, y, device: str, dtype) -> dict:
    from rigidbench.stages.probe_bases import fit_bases

    dev = torch.device(device)
    if dev.type == "cuda":
        torch.cuda.synchronize()
        torch.cuda.empty_cache()
        torch.cuda.reset_peak_memory_stats()
        before = torch.cuda.memory_allocated()
    else:
        reset = _reset_peak_rss()
        before = _rss_gib("VmRSS")
    t0 = time.perf_counter()
    cell = fit_bases(x, y, device=dev, dtype=dtype)
    if dev.type == "cuda":
        torch.cuda.synchronize()
    seconds = time.perf_counter() - t0
    row = {"device": torch.cuda.get_device_name(0) if dev.type == "cuda" else "cpu",
           "dtype": str(dtype).replace("torch.", ""), "rows": len(x), "inlp_train_rows": cell["train_rows"],
           "width": x.shape[1], "inlp_seconds": cell["inlp_seconds"], "cell_seconds": seconds,
           "rounds": cell["iterations"], "rank": cell["rank"], "stopped": cell["stopped"], "k_pc": cell["k_pc"],
           "measured": True}
    if dev.type == "cuda":
        row["peak_gpu_gib"] = torch.cuda.max_memory_allocated() / 2**30
        row["peak_gpu_gib_above_before"] = (torch.cuda.max_memory_allocated() - before) / 2**30
    else:
        row["activations_gib"] = x.nbytes / 2**30
        row["peak_rss_gib"] = _rss_gib("VmHWM")
        row["peak_rss_gib_above_activations"] = (_rss_gib("VmHWM") - before) if reset else float("nan")
        row["cpu_threads"] = torch.get_num_threads()
    return row, cell


def inlp_rows(rows: int, devices: list[str], dtypes) -> list[dict]:
    x, y = synthetic_cell(rows)
    out, reference = [], None
    for device in devices:
        for dtype in dtypes:
            row, cell = time_inlp_cell(x, y, device, dtype)
            row["what"] = "INLP + controls for one intervention cell"
            if reference is None:
                reference = cell["position"]
            else:  # agreement with the first (float64) run: the largest principal angle's sine
                p = cell["position"]
                if p.shape == reference.shape and p.size:
                    s = np.linalg.svd(reference.T @ p, compute_uv=False)
                    row["max_sin_angle_to_first"] = float(np.sqrt(max(0.0, 1 - float(s.min()) ** 2)))
                row["same_rank_as_first"] = p.shape[1] == reference.shape[1]
            out.append(row)
            print(json.dumps(row), flush=True, file=__import__("sys").stderr)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--clips", type=int, default=4, help="timed clips (after one warm-up clip)")
    ap.add_argument("--no-gpu", action="store_true")
    ap.add_argument("--only", choices=("all", "inlp"), default="all", help="inlp: only the INLP cell rows")
    ap.add_argument("--quick", action="store_true", help="small sizes everywhere (a smoke run, about a minute)")
    ap.add_argument("--inlp-fraction", type=float, default=1.0,
                    help="CPU INLP rows as a fraction of the paper's 186,636 (default 1; GPU always runs 1)")
    ap.add_argument("--inlp-dtypes", default="float64,float32", help="INLP precisions to time (default both)")
    args = ap.parse_args()
    out = {"host": platform.node(), "torch": torch.__version__, "cpu_threads": torch.get_num_threads(), "rows": []}
    gpu = torch.cuda.is_available() and not args.no_gpu
    dtypes = [getattr(torch, d) for d in args.inlp_dtypes.split(",")]
    cpu_rows = 8192 if args.quick else int(round(PAPER_ALL_ROWS * args.inlp_fraction))
    inlp = inlp_rows(cpu_rows, ["cpu"], dtypes)
    if gpu:
        inlp += inlp_rows(8192 if args.quick else PAPER_ALL_ROWS, ["cuda"], dtypes)
    for r in inlp:
        r["fraction_of_paper_rows"] = r["rows"] / PAPER_ALL_ROWS
    out["inlp"] = inlp
    out["inlp_projection"] = {
        "label": "projection, not a measurement",
        "cells": INTERVENTION_CELLS,
        "hours_by_run": [{"device": r["device"], "dtype": r["dtype"],
                          "hours_for_90_cells": r["cell_seconds"] * INTERVENTION_CELLS / 3600}
                         for r in inlp if r["rows"] == PAPER_ALL_ROWS],
        "assumes": "the paper's 90 block x tau cells at the seconds per cell measured at the paper's rows (runs "
                   "at a fraction of the rows are not projected: the D x D solves and the eigendecomposition do "
                   "not scale with rows)"}
    if args.only == "inlp":
        print(json.dumps(out, indent=1))
        return
    from rigidbench.train.tiny import TINY_TRANSFORMER_CONFIG, tiny_transformer

    clips = 1 if args.quick else args.clips
    cpu = torch.device("cpu")
    t = time_extraction(tiny_transformer(), (48, 3, 4, 8), (1, 512, TINY_TRANSFORMER_CONFIG["text_dim"]),
                        clips, cpu, torch.float32)
    out["rows"].append({"what": "extraction compute per clip (5 taus, all blocks)", "model": "tiny", "device": "cpu",
                        "seconds_per_clip": t, "measured": True})
    time_fit(100, 24, "mlp")  # warm-up (torch's first backward is slow)
    wide_rows = 1024 if args.quick else 8192
    for probe in ("linear", "mlp"):
        s = float(np.median([time_fit(1000, 24, probe) for _ in range(1 if args.quick else 3)]))
        out["rows"].append({"what": f"fit one {probe} cell (median of 3)", "model": "tiny", "device": "cpu",
                            "rows": 1000, "width": 24, "seconds_per_cell": s, "measured": True})
        s = time_fit(wide_rows, 3072, probe)
        out["rows"].append({"what": f"fit one {probe} cell", "model": "wan-2.2 width", "device": "cpu",
                            "rows": wide_rows, "width": 3072, "seconds_per_cell": s, "measured": True})
        out["rows"].append({"what": f"fit one {probe} cell, scaled to the paper's rows", "device": "cpu",
                            "rows": PAPER_TRAIN_ROWS, "width": 3072,
                            "seconds_per_cell": s * PAPER_TRAIN_ROWS / wide_rows, "measured": False,
                            "note": f"projection: linear in rows from the {wide_rows:,}-row measurement"})
    if gpu and not args.quick:
        from diffusers import WanTransformer3DModel

        from rigidbench.train.tiny import WAN22_TI2V_5B_TRANSFORMER_CONFIG

        dev = torch.device("cuda")
        with torch.device(dev):
            big = WanTransformer3DModel(**WAN22_TI2V_5B_TRANSFORMER_CONFIG).to(torch.bfloat16).eval()
        t = time_extraction(big, (48, 13, 22, 40), (1, 512, 4096), clips, dev, torch.bfloat16)
        name = torch.cuda.get_device_name(0)
        out["rows"].append({"what": "extraction compute per clip (5 taus, 30 blocks)", "model": "wan-2.2 (random "
                            "weights)", "device": name, "seconds_per_clip": t, "measured": True,
                            "peak_gpu_gib": torch.cuda.max_memory_allocated() / 2**30})
        del big
        torch.cuda.empty_cache()
        fits = {p: time_fit(PAPER_TRAIN_ROWS, 3072, p, device="cuda") for p in ("linear", "mlp")}
        for p, s in fits.items():
            out["rows"].append({"what": f"fit one {p} cell", "device": name, "rows": PAPER_TRAIN_ROWS, "width": 3072,
                                "seconds_per_cell": s, "measured": True})
        cells = PAPER_CELLS * N_TARGETS * N_LABELS * PAPER_BACKBONES
        out["projection"] = {
            "label": "projection, not a measurement",
            "device": name,
            "extraction_gpu_hours": t * PAPER_CLIPS * PAPER_BACKBONES / 3600,
            "fit_gpu_hours": (fits["linear"] + fits["mlp"]) * cells / 3600,
            "assumes": f"{PAPER_CLIPS} clips x {PAPER_BACKBONES} backbones at the measured s/clip; "
                       f"{PAPER_CELLS} cells x {N_TARGETS} targets x {N_LABELS} label conditions x "
                       f"{PAPER_BACKBONES} backbones per probe class at the measured s/cell"}
    else:
        fit_s = sum(r["seconds_per_cell"] for r in out["rows"] if not r["measured"])
        cells = PAPER_CELLS * N_TARGETS * N_LABELS * PAPER_BACKBONES
        out["projection"] = {
            "label": "projection, not a measurement (CPU fit times only; extraction at real size "
                     "needs a GPU and is not projected from the tiny model)",
            "device": "cpu",
            "fit_cpu_hours": fit_s * cells / 3600,
            "assumes": f"{PAPER_CELLS} cells x {N_TARGETS} targets x {N_LABELS} label conditions x {PAPER_BACKBONES} "
                       "backbones, linear + MLP, at the row-scaled CPU s/cell"}
    print(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
