"""Time probing and print JSON.

    python benchmarks/probe.py [--clips 4] [--no-gpu]

CPU rows (always): the tiny Wan transformer (``--model tiny``): extraction compute per clip (five
schedule fractions, one forward each with hooks on every block, actor pooling; bundle reading and
writing shards excluded) and probe-fit seconds per cell (linear and MLP, 20 epochs, the paper's
optimiser) on synthetic rows of the tiny width (24); and one linear and one MLP cell at Wan's width
(3,072) on 8,192 synthetic rows, scaled linearly to the paper's 148,303 training rows (labelled as
a projection: the epoch cost is linear in the rows).

GPU rows (only when torch sees a GPU): extraction per clip at real size with random weights of Wan
2.2 TI2V-5B's transformer (bfloat16; 13 x 11 x 20 = 2,860 tokens, text 512 x 4,096), and one
linear / MLP fit cell with 148,303 rows of width 3,072 trained on the GPU (``ProbeSettings(device=...)``).

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


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--clips", type=int, default=4, help="timed clips (after one warm-up clip)")
    ap.add_argument("--no-gpu", action="store_true")
    args = ap.parse_args()
    from rigidbench.train.tiny import TINY_TRANSFORMER_CONFIG, tiny_transformer

    out = {"host": platform.node(), "torch": torch.__version__, "cpu_threads": torch.get_num_threads(), "rows": []}
    cpu = torch.device("cpu")
    t = time_extraction(tiny_transformer(), (48, 3, 4, 8), (1, 512, TINY_TRANSFORMER_CONFIG["text_dim"]),
                        args.clips, cpu, torch.float32)
    out["rows"].append({"what": "extraction compute per clip (5 taus, all blocks)", "model": "tiny", "device": "cpu",
                        "seconds_per_clip": t, "measured": True})
    time_fit(100, 24, "mlp")  # warm-up (torch's first backward is slow)
    for probe in ("linear", "mlp"):
        s = float(np.median([time_fit(1000, 24, probe) for _ in range(3)]))
        out["rows"].append({"what": f"fit one {probe} cell (median of 3)", "model": "tiny", "device": "cpu",
                            "rows": 1000, "width": 24, "seconds_per_cell": s, "measured": True})
        s = time_fit(8192, 3072, probe)
        out["rows"].append({"what": f"fit one {probe} cell", "model": "wan-2.2 width", "device": "cpu",
                            "rows": 8192, "width": 3072, "seconds_per_cell": s, "measured": True})
        out["rows"].append({"what": f"fit one {probe} cell, scaled to the paper's rows", "device": "cpu",
                            "rows": PAPER_TRAIN_ROWS, "width": 3072,
                            "seconds_per_cell": s * PAPER_TRAIN_ROWS / 8192, "measured": False,
                            "note": "projection: linear in rows from the 8,192-row measurement"})
    if torch.cuda.is_available() and not args.no_gpu:
        from diffusers import WanTransformer3DModel

        from rigidbench.train.tiny import WAN22_TI2V_5B_TRANSFORMER_CONFIG

        gpu = torch.device("cuda")
        with torch.device(gpu):
            big = WanTransformer3DModel(**WAN22_TI2V_5B_TRANSFORMER_CONFIG).to(torch.bfloat16).eval()
        t = time_extraction(big, (48, 13, 22, 40), (1, 512, 4096), args.clips, gpu, torch.bfloat16)
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
            "label": "projection, not a measurement (no GPU here: CPU fit times only; extraction at real size "
                     "needs a GPU and is not projected from the tiny model)",
            "device": "cpu",
            "fit_cpu_hours": fit_s * cells / 3600,
            "assumes": f"{PAPER_CELLS} cells x {N_TARGETS} targets x {N_LABELS} label conditions x {PAPER_BACKBONES} "
                       "backbones, linear + MLP, at the row-scaled CPU s/cell"}
    print(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
