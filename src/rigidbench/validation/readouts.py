"""Readout curves for ``validate-metrics``: each physics readout under the failure mode that sets it,
with gt perception, against the value the failure mode simulates.

- ``slow`` at severity s plays (1 + s) times slower: speed 1 / (1 + s); ``fast``: 1 + s;
- ``delayed`` starts 0.5 s x s late: offset -0.5 s x s (speed 1);
- ``gravity`` (re-simulated, ``with_rendered`` only): g (1 + s), read by g^;
- ``restitution`` (re-simulated): the truth is the same restitution fit on the counterfactual's own
  simulated trajectory (Bullet's effective coefficient, not the nominal product; see docs/physics.md);
- ``static`` at severity 1 and ``camera-drift`` must raise exactly the frozen and camera flags,
  the reference none.
"""

from __future__ import annotations

import logging
import math
import tempfile
from pathlib import Path

import numpy as np

from ..atomic import atomic_file
from ..errors import EXAMPLE_ERRORS
from ..evaluation.scoring import metric_inputs, score_inputs
from ..groundtruth.bundle import Sample
from ..folders import state_path
from ..perception.features import FeatureNets
from ..perception.gt import GroundTruthBackend
from ..predictors import PREDICTORS, PredictContext
from ..readouts import compute_readouts, context_from_sample
from ..readouts.fits import bounce_coefficient
from ..video import Video, align_video, reference_times

log = logging.getLogger(__name__)

#: mode -> (readout, key, truth(severity, sample, prediction bundle or None))
TIME_MODES = {"slow": lambda s: 1.0 / (1.0 + s), "fast": lambda s: 1.0 + s}
DELAY_S = 0.5
FLAG_CASES = {"reference": (), "static": ("frozen",), "camera-drift": ("camera",)}


def prediction_readouts(sample, prediction, work_dir: Path, nets=None) -> dict:
    """Every readout of one failure-mode Prediction of ``sample``, perceived exactly as ``evaluate
    --perception gt`` would (the world state it depicts)."""
    nets = nets if nets is not None else FeatureNets()
    video = Video(prediction.frames, prediction.times_s)
    fake = Path(work_dir) / f"{sample.sample_id}.mp4"
    prediction.state.save(state_path(fake))
    perceived = GroundTruthBackend().perceive(sample, video, fake)
    ref_times = reference_times(sample.n_frames, sample.fps)
    inputs = metric_inputs(sample, align_video(video, ref_times), perceived.aligned(ref_times), nets)
    iddrift = score_inputs(inputs, ["iddrift"])["iddrift"] if nets.identity is not None else None
    ctx = context_from_sample(sample, inputs, None if iddrift is None else iddrift.value)
    return compute_readouts(ctx)


def simulated_restitution(bundle) -> float:
    """The restitution fit applied to a bundle's own simulated height (first free actor with a bounce)."""
    z = bundle.trajectory.positions_m[bundle.active_indices, :, 2]
    t = np.arange(z.shape[1]) / float(bundle.fps)
    for za in z:
        b = bounce_coefficient(t, za)
        if math.isfinite(b.e):
            return b.e
    return float("nan")


def readout_rows(samples: list, severities: np.ndarray, with_rendered: bool, nets=None,
                 progress: bool = True) -> tuple[list[dict], dict[str, str]]:
    """One row per (mode, severity, example): measured readout, truth, error. Returns (rows, failures)."""
    rows: list[dict] = []
    failures: dict[str, str] = {}
    plan = [(m, s) for m in ("slow", "fast", "delayed") for s in severities]
    plan += [(m, 1.0) for m in FLAG_CASES]
    if with_rendered:
        plan += [("gravity", s) for s in severities] + [("restitution", s) for s in severities]
    with tempfile.TemporaryDirectory(prefix="rigidbench-readouts-") as tmp:
        for mode, severity in plan:
            for sample in samples:
                try:
                    ctx = PredictContext(severity=float(severity))
                    bundle = None
                    if mode in ("gravity", "restitution"):
                        ctx = PredictContext(severity=float(severity),
                                             keep_bundle_dir=Path(tmp) / f"{sample.sample_id}-{mode}-{severity:.3f}")
                    prediction = PREDICTORS[mode].create().predict(sample, ctx)
                    if mode in ("gravity", "restitution"):
                        bundle = Sample(ctx.keep_bundle_dir)
                    r = prediction_readouts(sample, prediction, Path(tmp), nets)
                except EXAMPLE_ERRORS as exc:
                    failures.setdefault(mode, f"{sample.sample_id} at severity {severity:.2f}: {exc}")
                    continue
                rows.extend(_rows_for(mode, float(severity), sample, r, bundle))
    return rows, failures


def _rows_for(mode: str, severity: float, sample, r: dict, bundle) -> list[dict]:
    base = {"mode": mode, "severity": severity, "example": sample.sample_id, "task": sample.task,
            "fps": float(sample.fps)}
    if mode in TIME_MODES:
        return [{**base, "readout": "speed", "measured": r["speed"]["value"], "truth": TIME_MODES[mode](severity)}]
    if mode == "delayed":
        return [{**base, "readout": "speed", "measured": r["speed"]["value"], "truth": 1.0},
                {**base, "readout": "offset_s", "measured": r["speed"]["offset_s"], "truth": -DELAY_S * severity}]
    if mode == "gravity":
        g = sample.spec.sim.gravity_m_s2 * (1.0 + severity)
        return [{**base, "readout": "gravity", "measured": r["gravity"]["value"], "truth": g}]
    if mode == "restitution":
        return [{**base, "readout": "restitution", "measured": r["restitution"]["value"],
                 "truth": simulated_restitution(bundle) if bundle is not None else float("nan")}]
    raised = sorted(r["flags"]["raised"])
    return [{**base, "readout": "flags", "measured": ",".join(raised) or "none",
             "truth": ",".join(sorted(FLAG_CASES[mode])) or "none"}]


def write_readout_csv(rows: list[dict], path: Path) -> Path:
    """The readout rows as CSV (mode, severity, example, task, readout, measured, truth), atomically."""
    import csv

    fields = ("mode", "severity", "example", "task", "readout", "measured", "truth")
    with atomic_file(path) as tmp, open(tmp, "w", newline="") as fh:
        writer = csv.DictWriter(fh, fieldnames=fields)
        writer.writeheader()
        for row in rows:
            writer.writerow({k: row.get(k) for k in fields})
    return path


def write_readout_figure(rows: list[dict], path: Path) -> Path | None:
    """Measured against simulated readout per mode (one panel per readout); PNG at ``path``."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    panels = [("speed", "playback speed s^"), ("offset_s", "time offset d^ (s)"), ("gravity", "gravity g^ (m/s^2)"),
              ("restitution", "restitution e^")]
    panels = [(k, t) for k, t in panels if any(r["readout"] == k for r in rows)]
    if not panels:
        return None
    fig, axes = plt.subplots(1, len(panels), figsize=(3.6 * len(panels), 3.4), squeeze=False)
    for ax, (key, title) in zip(axes[0], panels):
        sel = [r for r in rows if r["readout"] == key and isinstance(r["measured"], float)]
        modes = sorted({r["mode"] for r in sel})
        for mode in modes:
            xs = [r["truth"] for r in sel if r["mode"] == mode]
            ys = [r["measured"] for r in sel if r["mode"] == mode]
            ax.plot(xs, ys, "o", label=mode)
        lo = min([r["truth"] for r in sel] + [r["measured"] for r in sel if math.isfinite(r["measured"])])
        hi = max([r["truth"] for r in sel] + [r["measured"] for r in sel if math.isfinite(r["measured"])])
        ax.plot([lo, hi], [lo, hi], "k--", lw=0.8, label="measured = simulated")
        ax.set_xlabel("simulated")
        ax.set_ylabel("measured (gt perception)")
        ax.set_title(title, fontsize=10)
        ax.legend(fontsize=7)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path


def readout_summary_lines(rows: list[dict]) -> list[str]:
    """Worst error per readout and mode, and the flag cases."""
    lines = []
    for key, unit in (("speed", "relative"), ("offset_s", "frames"), ("gravity", "relative"),
                      ("restitution", "absolute")):
        for mode in sorted({r["mode"] for r in rows if r["readout"] == key}):
            sel = [r for r in rows if r["readout"] == key and r["mode"] == mode]
            if unit == "relative":
                errs = [abs(r["measured"] / r["truth"] - 1) for r in sel]
                text = f"{100 * max(errs):.2f}%"
            elif unit == "frames":
                errs = [abs(r["measured"] - r["truth"]) * r["fps"] for r in sel]
                text = f"{max(errs):.2f} frames"
            else:
                errs = [abs(r["measured"] - r["truth"]) for r in sel]
                text = f"{max(errs):.3f}"
            lines.append(f"readout {key} under {mode}: largest error {text} over {len(sel)} clips")
    for r in rows:
        if r["readout"] == "flags":
            lines.append(f"flags under {r['mode']} ({r['example']}): {r['measured']} (expected {r['truth']})")
    return lines
