"""One response curve per metric: the failure mode meant to move it, swept over severities and
scored with exact (gt) perception through ``evaluation.score_example``, as ``rigidbench evaluate
--perception gt`` would score the written predictions.

Failure modes that re-simulate and re-render with Blender (``RENDERED_MODES``) are slow; they
drive a curve only when ``with_rendered`` is set and the mode is registered, otherwise an
image-space mode stands in and the table says which mode drove each curve.
"""

from __future__ import annotations

import logging
import tempfile
from pathlib import Path

import numpy as np
from tqdm import tqdm

from ..errors import EXAMPLE_ERRORS
from ..evaluation.scoring import score_example
from ..folders import state_path
from ..metrics import METRICS
from ..perception.gt import GroundTruthBackend
from ..predictors import PREDICTORS, PredictContext
from ..video import Video, align_video, reference_times, resize_frames

log = logging.getLogger(__name__)

#: failure modes that re-simulate or re-render with Blender (minutes per example)
RENDERED_MODES = tuple(name for name, info in PREDICTORS.items() if info.needs_blender)


def curve_plan(available_modes, with_rendered: bool) -> list[tuple[str, str, str]]:
    """available_modes: names registered in PREDICTORS. Each metric's curve modes (its registry entry)
    in order of preference; the first usable one drives its curve. Returns (metric, mode, role) per curve,
    role "main" or "control"; a metric whose preferred modes are all unusable gets no curve."""
    def usable(mode: str) -> bool:
        return mode in available_modes and (with_rendered or mode not in RENDERED_MODES)

    plan = []
    for metric, info in METRICS.items():
        preferences = info.curve_modes
        mode = next((m for m in preferences if usable(m)), None)
        if mode is None:
            log.warning("no usable failure mode for %s among %s", metric, ", ".join(preferences))
            continue
        plan.append((metric, mode, "main"))
        plan.extend((metric, m, "control") for m in info.control_modes if usable(m))
    return plan


def score_prediction(sample, prediction, nets, work_dir: Path) -> dict[str, float | None]:
    """Score one failure-mode Prediction of `sample` exactly as the evaluator does with gt perception.
    Returns metric -> value (None for a measurement skipped for want of its network)."""
    video = Video(prediction.frames, prediction.times_s)
    w, h = sample.resolution
    if video.size != (w, h):
        video.frames = resize_frames(video.frames, (w, h))
    fake_video_path = Path(work_dir) / f"{sample.sample_id}.mp4"
    prediction.state.save(state_path(fake_video_path))
    perceived = GroundTruthBackend().perceive(sample, video, fake_video_path)
    ref_times = reference_times(sample.n_frames, sample.fps)
    scores = score_example(sample, align_video(video, ref_times), perceived.aligned(ref_times), nets)
    return {m: (None if r is None else float(r.value)) for m, r in scores.items()}


def mode_sweep(samples: list, modes: list[str], severities: np.ndarray, nets, progress: bool = True
               ) -> tuple[dict[str, dict[str, np.ndarray]], dict[str, str]]:
    """Returns ({mode: {metric: (len(severities), len(samples)) float, NaN where undefined or
    skipped}}, {mode: reason} for modes that failed on some example)."""
    out = {mode: {m: np.full((len(severities), len(samples)), np.nan) for m in METRICS} for mode in modes}
    failures: dict[str, str] = {}
    bar = tqdm(total=len(modes) * len(severities) * len(samples), unit="clip", desc="failure-mode curves",
               disable=not progress)
    with tempfile.TemporaryDirectory(prefix="rigidbench-validate-") as tmp:
        for mode in modes:
            predictor = PREDICTORS[mode].create()
            for i, severity in enumerate(severities):
                for j, sample in enumerate(samples):
                    bar.set_postfix_str(f"{mode} {severity:.2f} {sample.sample_id}")
                    try:
                        prediction = predictor.predict(sample, PredictContext(severity=float(severity)))
                        scores = score_prediction(sample, prediction, nets, Path(tmp))
                    except EXAMPLE_ERRORS as exc:
                        failures.setdefault(mode, f"{sample.sample_id} at severity {severity:.2f}: {exc}")
                        log.warning("failure mode %s on %s (severity %.2f) failed: %s", mode, sample.sample_id,
                                    severity, exc)
                        bar.update(1)
                        continue
                    for metric, value in scores.items():
                        out[mode][metric][i, j] = np.nan if value is None else value
                    bar.update(1)
    bar.close()
    return out, failures
