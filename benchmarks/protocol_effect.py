"""What the evaluation protocol moves: the same predictions scored under `rigidbench-v1` (the published
evaluator: OpenCV decoding, JPEG q95 4:4:4 round trip, the release's edge rules), `paper-rules` (the same
round trip, PyAV decoding honouring the colour tag, our edge rules) and `lossless` (our rules, no JPEG),
with exact (gt) perception. Prints JSON:

- ``suite``: per protocol, failure mode and measurement the mean over the examples (clips shorter than the
  reference span, the ``fast`` mode's, scored on the frames they have: ``allow_short``), and per measurement
  the largest change over the modes between rigidbench-v1 and paper-rules (``rules_max_abs_change``:
  decoder and edge rules; the predictors write untagged clips, so this is the edge rules) and between
  paper-rules and lossless (``jpeg_max_abs_change``);
- ``hostile``: per hostile case (synthetic edits of one example's perceived arrays: an actor leaving
  the frame with its tracks still flagged visible, a NaN track flagged visible, no actor moving more than
  1 cm, a NaN background corner) the five measurements with edge rules under both rule sets, the notes
  of values the release cannot compute, and the measurements that do not depend on the rules;
- ``tagged_clip``: the reference prediction of one example re-encoded as BT.709-tagged H.264 (what
  hosted models return) and scored under the three protocols (means of every measurement), with the
  decoders' mean and max pixel difference.

    .venv/bin/python benchmarks/protocol_effect.py [--ids 00000 00015 ...] [--preset test] [--modes ...] [--quick]

Renders at the `test` preset by default (256x144, 12 frames); three examples and all 15 failure modes took
553 s on a shared 2-core machine. `--quick` takes one example and two failure modes (about a minute).
"""

from __future__ import annotations

import argparse
import math
import tempfile
import time
from fractions import Fraction
from pathlib import Path

import numpy as np
from _rendered import json_stdout, render_eval_examples

PROTOCOLS = ("rigidbench-v1", "paper-rules", "lossless")
RULE_METRICS = ("ate", "ate3d", "si_mse", "iddrift", "bgdrift")  # the measurements with edge rules


def num(x):
    """A JSON-safe number: finite values rounded, NaN as null, infinities as strings."""
    if x is None or (isinstance(x, float) and math.isnan(x)):
        return None
    if isinstance(x, float) and math.isinf(x):
        return "inf" if x > 0 else "-inf"
    return round(float(x), 6)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--ids", nargs="+", default=["00000", "00015", "00020"])
    parser.add_argument("--preset", default="test")
    parser.add_argument("--modes", nargs="+", default=None, help="failure modes (default: every one)")
    parser.add_argument("--quick", action="store_true", help="one example, two modes")
    args = parser.parse_args()
    from rigidbench.predictors import failure_modes

    modes = tuple(args.modes or failure_modes())
    ids = args.ids[:1] if args.quick else args.ids
    modes = modes[:2] if args.quick else modes
    started = time.time()
    with json_stdout() as emit, tempfile.TemporaryDirectory() as tmp:
        out = run(ids, args.preset, modes, Path(tmp))
        out["seconds"] = round(time.time() - started, 1)
        emit(out)
    return 0


def run(ids, preset: str, modes, root: Path) -> dict:
    data = render_eval_examples(ids, preset, root)
    return {"ids": list(ids), "preset": preset, "perception": "gt", "suite": suite(data, modes, root),
            "hostile": hostile(data, ids[0], root), "tagged_clip": tagged_clip(data, ids[0], root)}


def evaluate_means(preds: Path, data: Path, out: Path, protocol: str) -> dict:
    from rigidbench.driver import RunOptions
    from rigidbench.stages.evaluate import evaluate
    from rigidbench.perception.features import FeatureNets

    summary = evaluate(preds, data, out, nets=FeatureNets(), run=RunOptions(progress=False), protocol=protocol, allow_short=True)
    return {m: (summary.facts.results["overall"].get(m) or {}).get("mean") for m in summary.facts.results["metrics"]}


def change(a: dict, b: dict) -> dict:
    """Per measurement, the largest |a - b| over the modes (null where either is undefined everywhere)."""
    out = {}
    for metric in next(iter(a.values())):
        diffs = [abs(a[k][metric] - b[k][metric]) for k in a if a[k][metric] is not None and b[k][metric] is not None]
        out[metric] = num(max(diffs)) if diffs else None
    return out


def suite(data: Path, modes, root: Path) -> dict:
    """Every failure mode predicted once and scored under each protocol."""
    from rigidbench.driver import RunOptions
    from rigidbench.stages.predict import predict
    from rigidbench.predictors import PredictContext

    means: dict = {p: {} for p in PROTOCOLS}
    for mode in modes:
        preds = root / "predictions" / mode
        predict(mode, data, preds, PredictContext(severity=0.5), run=RunOptions(progress=False))
        for protocol in PROTOCOLS:
            means[protocol][mode] = evaluate_means(preds, data, root / "runs" / protocol / mode, protocol)
    return {"modes": list(modes),
            "means": {p: {k: {m: num(v) for m, v in row.items()} for k, row in by_mode.items()}
                      for p, by_mode in means.items()},
            "rules_max_abs_change": change(means["rigidbench-v1"], means["paper-rules"]),
            "jpeg_max_abs_change": change(means["paper-rules"], means["lossless"])}


def perceived_inputs(data: Path, sample_id: str, root: Path):
    """One example's MetricInputs (paper rules) for its `reference` prediction, gt perception, no JPEG."""
    from rigidbench.evaluation.scoring import metric_inputs
    from rigidbench.groundtruth.bundle import Sample
    from rigidbench.perception.base import get_backend
    from rigidbench.perception.features import FeatureNets
    from rigidbench.stages.predict import predict
    from rigidbench.predictors import PredictContext
    from rigidbench.video import align_video, read_video, reference_times
    from rigidbench.driver import RunOptions, Selection

    preds = root / "predictions-hostile"
    predict("reference", data, preds, PredictContext(), run=RunOptions(Selection.of([sample_id]), progress=False))
    sample = Sample(data / sample_id)
    pred = preds / f"{sample_id}.mp4"
    video = read_video(pred)
    ref_times = reference_times(sample.n_frames, sample.fps)
    perceived = get_backend("gt").perceive(sample, video, pred).aligned(ref_times)
    return metric_inputs(sample, align_video(video, ref_times), perceived, FeatureNets())


def mean_colour(x):
    """A stand-in for DINOv2 (its weights are not needed to show where IdDrift is undefined)."""
    return x.mean(dim=(2, 3))


def hostile(data: Path, sample_id: str, root: Path) -> dict:
    """The synthetic edge cases of docs/metrics.md on one example, scored with both rule sets."""
    from dataclasses import replace

    from rigidbench.evaluation.scoring import score_inputs

    base = replace(perceived_inputs(data, sample_id, root), identity_net=mean_colour)
    t_len, height, width = base.gen_rgb.shape[:3]
    first = base.track_actor == 0
    cases = {"none": {}}

    # An actor leaves the frame: from the middle frame on, actor 0's generated tracks slide right until
    # they are half an image width past the right edge at the last frame, still flagged visible.
    tracks = base.gen_tracks.copy()
    half = t_len // 2
    ramp = np.clip((np.arange(t_len) - half) / max(t_len - 1 - half, 1), 0, None) * 1.5 * width
    tracks[first] += np.stack([ramp, np.zeros(t_len)], axis=-1)[None]
    vis = base.gen_visibility.copy()
    vis[first] |= base.ref_visibility[first]
    cases["actor leaves the frame"] = {"gen_tracks": tracks, "gen_visibility": vis}

    # A NaN generated track position flagged visible (one point-frame).
    joint = base.ref_visibility & base.gen_visibility
    p, t = np.argwhere(joint[:, 1:])[0] + [0, 1]
    tracks = base.gen_tracks.copy()
    tracks[p, t] = np.nan
    cases["NaN track flagged visible"] = {"gen_tracks": tracks}

    # No actor moves more than 1 cm: the reference positions held at frame 0 (the clip is unchanged).
    cases["no actor moves > 1 cm"] = {
        "actor_positions_m": np.repeat(base.actor_positions_m[:, :1], t_len, axis=1)}

    # A NaN background corner with confidence 1 at one frame.
    bg = base.bg_tracks.copy()
    if len(bg):
        bg[0, t_len // 2] = np.nan
    cases["NaN background corner"] = {"bg_tracks": bg, "bg_confidence": np.where(np.arange(len(bg))[:, None] == 0,
                                                                                1.0, base.bg_confidence)}

    out = {"example": sample_id, "frames": int(t_len), "size": [int(width), int(height)],
           "iddrift_features": "mean colour (a stand-in for DINOv2)", "cases": {}}
    for name, edits in cases.items():
        row: dict = {"published": {}, "paper": {}, "notes": {}}
        for rules in ("published", "paper"):
            x = replace(base, **edits, edge_rules=rules, _shared={})
            with np.errstate(invalid="ignore", over="ignore"):
                scores = score_inputs(x)
            row[rules] = {m: num(scores[m].value) for m in RULE_METRICS}
            row["notes"].update({m: r.note for m, r in scores.items() if r is not None and r.note})
            rest = {m: num(r.value) for m, r in scores.items() if m not in RULE_METRICS and r is not None}
            row.setdefault("other_metrics", {})[rules] = rest
        row["other_metrics_equal"] = row["other_metrics"]["published"] == row["other_metrics"]["paper"]
        row["other_metrics"] = row["other_metrics"]["paper"]
        out["cases"][name] = row
    return out


def tagged_clip(data: Path, sample_id: str, root: Path) -> dict:
    """The reference prediction re-encoded as BT.709-tagged H.264 (yuv420p, crf 12), scored per protocol."""
    import av

    from rigidbench.folders import state_path
    from rigidbench.video import read_video

    src = root / "predictions-hostile" / f"{sample_id}.mp4"
    frames = read_video(src).frames
    preds = root / "predictions-bt709"
    preds.mkdir()
    path = preds / f"{sample_id}.mp4"
    with av.open(str(path), "w") as container:
        stream = container.add_stream("libx264", rate=Fraction(24))
        stream.width, stream.height, stream.pix_fmt = frames.shape[2], frames.shape[1], "yuv420p"
        stream.options = {"crf": "12"}
        cc = stream.codec_context
        cc.colorspace = cc.color_primaries = cc.color_trc = 1  # BT.709
        cc.color_range = 1
        for frame in frames:
            vf = av.VideoFrame.from_ndarray(frame, format="rgb24").reformat(format="yuv420p", dst_colorspace=1)
            vf.colorspace, vf.color_range = 1, 1
            container.mux(stream.encode(vf))
        container.mux(stream.encode(None))
    state_path(path).write_bytes(state_path(src).read_bytes())
    opencv, pyav = (read_video(path, decoder=d).frames.astype(int) for d in ("opencv", "pyav"))
    diff = np.abs(opencv - pyav)
    return {"decoder_mean_abs_diff": num(diff.mean()), "decoder_max_abs_diff": int(diff.max()),
            "means": {p: {m: num(v) for m, v in evaluate_means(preds, data, root / "runs-bt709" / p, p).items()}
                      for p in PROTOCOLS}}


if __name__ == "__main__":
    raise SystemExit(main())
