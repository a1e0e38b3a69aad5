"""What evaluating K samples of one example costs with ground-truth perception: print one JSON object.

Builds, without Blender, one paper-size reference example (1280x704, 49 frames at 24 fps: the synthetic
published sample of tests/fixtures/published_set.py, a bounce of one active ball beside a passive one, with
``--noise`` grey levels of noise on its frames, default none, imported with ``rigidbench import``'s own
function) and K prediction videos of it: sample 0 is the ``reference`` predictor's output (video and world
state), sample k >= 1 (``<id>.s<k>.mp4``, the naming rule of ``folders.sample_item``) the same clip with
frames 1.. brightened by 2k grey levels and the world state's tracks moved by 0.25k pixels after frame 0,
written with the project's video writer (``video.write_video``) losslessly, as the failure modes and the
local video models store their clips. Then, for each K of ``--samples``, it times a whole ``evaluate(...)``
of that folder (gt perception, the default protocol, the feature networks whose weights are present here) in
a fresh Python process, ``--repeat`` times, and reports the median:

- ``runs.K<k>.wall_s``: the process's wall clock from its start to its exit (interpreter start-up and
  imports included), median over the repeats, with ``wall_s_all`` (every run) and ``cpu_s`` (the child's
  user + system seconds, median);
- ``runs.K<k>.phases_s``: the child's own timings, median: ``imports`` (importing the evaluate stage),
  ``evaluate`` (the call), and the per-phase sums run.json records (``decode_s``, ``reference_s``,
  ``perception_s``, ``metrics_s``, ``readouts_s``, ``write_s``);
- ``runs.K<k>.records``: how many (example, sample) records the run wrote, and ``metrics`` the scores of
  each, so that before/after runs can be compared for identical scores; ``skipped_metrics`` the
  measurements without their network weights here.

``machine`` gives the cores and the load average before the runs (other jobs share the machine).
``--profile DIR`` also writes a cProfile of each K's first run to ``DIR/K<k>.prof``; ``--src DIR`` times the
evaluate of another source tree (the example is always built with this checkout's). ``--keep DIR`` reuses the
example built there earlier (its size and noise are then those it was built with). Noise costs in decoding, a
cost of each sample that no sharing removes: with ``--noise 3`` each lossless clip is 69 MB instead of 0.5 MB
and OpenCV decodes it in 2.8 s instead of 0.1 s (the 2-core development machine).

Usage: python benchmarks/evaluate_samples.py [--quick] [--size 1280x704] [--frames 49] [--samples 1,4]
                                             [--repeat 3] [--noise 0] [--keep DIR] [--profile DIR] [--src DIR]
       python benchmarks/evaluate_samples.py --quick     # a 160x96, 9-frame example, K = 1 and 2, once
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
EXAMPLE = "00000"


def build(root: Path, width: int, height: int, frames: int, noise: float, k_max: int) -> tuple[Path, Path]:
    """The reference split and a predictions folder with ``k_max`` samples of its one example."""
    sys.path.insert(0, str(ROOT / "tests"))  # the fixtures package
    sys.path.insert(0, str(ROOT / "benchmarks"))
    from fixtures import published_set as ps
    from published_import import add_noise

    from rigidbench.config import registry
    from rigidbench.driver import RunOptions
    from rigidbench.folders import sample_item, state_path
    from rigidbench.perception.gt import WorldState
    from rigidbench.predictors import PredictContext
    from rigidbench.stages.import_set import import_published
    from rigidbench.stages.predict import predict
    from rigidbench.video import read_video, write_video

    sample = ps.PublishedSample(EXAMPLE, "bounce", "modern_loft", "in_distribution", 107420369, "tennis_ball")
    published = ps.write_set(root / "published" / "rigidbench-eval-v1.1", [sample], width=width, height=height,
                             n_frames=frames)
    if noise > 0:
        add_noise(published / "samples" / EXAMPLE, noise)
    report = import_published(published.parent, root / "data", registry=registry(), run=RunOptions(progress=False))
    if report.failed:
        raise SystemExit(f"the import failed: {report.failed}")
    shutil.rmtree(root / "published")
    data = root / "data" / "eval"
    preds = root / "predictions"
    made = predict("reference", data, preds, PredictContext(), run=RunOptions(progress=False))
    if made.failed:
        raise SystemExit(f"the reference predictor failed: {made.failed}")
    video = preds / f"{EXAMPLE}.mp4"
    clip = read_video(video)
    state = WorldState.load(state_path(video))
    for k in range(1, k_max):
        shown = clip.frames.copy()
        shown[1:] = np.minimum(shown[1:].astype(np.int16) + 2 * k, 255).astype(np.uint8)
        target = preds / f"{sample_item(EXAMPLE, k)}.mp4"
        write_video(target, shown, fps=float(clip.fps_measured or 24.0), lossless=True)
        tracks = state.tracks.copy()
        tracks[:, 1:] += np.float32(0.25 * k)
        WorldState(state.times_s, state.masks, state.depth_m, tracks, state.visibility, state.bg_affine,
                   state.bg_flow).save(state_path(target))
    return data, preds


def with_samples(preds: Path, k: int, folder: Path) -> Path:
    """A predictions folder holding samples 0..k-1 of ``preds`` (hard links)."""
    from rigidbench.folders import sample_item

    folder.mkdir(parents=True, exist_ok=True)
    for s in range(k):
        for suffix in (".mp4", ".state.npz"):
            src = preds / f"{sample_item(EXAMPLE, s)}{suffix}"
            os.link(src, folder / src.name)
    return folder


def child(pred: str, data: str, out: str, profile: str | None) -> None:
    """One evaluate in this process; prints its own timings and the records as JSON."""
    t0 = time.perf_counter()
    from rigidbench.driver import RunOptions
    from rigidbench.stages.evaluate import evaluate
    imports_s = time.perf_counter() - t0
    t0 = time.perf_counter()
    if profile:
        import cProfile

        with cProfile.Profile() as prof:
            report = evaluate(pred, data, out, run=RunOptions(progress=False))
        prof.dump_stats(profile)
    else:
        report = evaluate(pred, data, out, run=RunOptions(progress=False))
    evaluate_s = time.perf_counter() - t0
    if report.failed:
        raise SystemExit(f"evaluate failed: {report.failed}")
    run = json.loads((Path(out) / "run.json").read_text())
    records = sorted((json.loads(p.read_text()) for p in (Path(out) / "examples").glob("*.json")
                      if not p.name.endswith(".readouts.json")), key=lambda r: (r["id"], r.get("sample", 0)))
    print(json.dumps({"imports": imports_s, "evaluate": evaluate_s, "timings_s": run["timings_s"],
                      "skipped": report.facts.skipped_metrics,
                      "records": [{"sample": r.get("sample", 0), "metrics": r["metrics"]} for r in records]}))


def time_child(pred: Path, data: Path, out: Path, profile: Path | None, src: Path) -> dict:
    env = dict(os.environ, PYTHONPATH=str(src), MPLBACKEND="Agg")
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    done = subprocess.run([sys.executable, __file__, "--child", str(pred), str(data), str(out)]
                          + (["--profile", str(profile)] if profile else []), env=env, capture_output=True,
                          text=True)
    wall = time.perf_counter() - t0
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    if done.returncode != 0:
        raise SystemExit(f"the evaluate child failed:\n{done.stderr[-3000:]}")
    doc = json.loads(done.stdout.strip().splitlines()[-1])
    doc["wall"] = wall
    doc["cpu"] = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    return doc


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="a 160x96, 9-frame example, K = 1 and 2, once")
    parser.add_argument("--size", default="1280x704", help="W x H (default: the paper's 1280x704)")
    parser.add_argument("--frames", type=int, default=49)
    parser.add_argument("--samples", default="1,4", help="the values of K to time (default 1,4)")
    parser.add_argument("--repeat", type=int, default=3, help="fresh-process runs per K; the median is reported")
    parser.add_argument("--noise", type=float, default=0.0, help="grey levels of noise on the frames (default 0)")
    parser.add_argument("--keep", type=Path, help="build the example here, or reuse it if it is there")
    parser.add_argument("--profile", type=Path, help="write a cProfile of each K's first run into this folder")
    parser.add_argument("--src", type=Path, default=ROOT / "src",
                        help="the source tree whose evaluate is timed (default this checkout's src/; another "
                             "tree, e.g. an older commit's, gives the before figures)")
    parser.add_argument("--child", nargs=3, metavar=("PRED", "DATA", "OUT"), help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.child:
        child(*args.child, profile=str(args.profile) if args.profile else None)
        return
    width, height = (160, 96) if args.quick else (int(v) for v in args.size.lower().split("x"))
    frames = 9 if args.quick else args.frames
    ks = [1, 2] if args.quick else [int(k) for k in args.samples.split(",")]
    repeat = 1 if args.quick else args.repeat
    load = os.getloadavg()
    with tempfile.TemporaryDirectory() as tmp:
        work = args.keep or Path(tmp)
        t0 = time.perf_counter()
        if not (work / "predictions").is_dir():
            data, preds = build(work, width, height, frames, args.noise, max(ks))
        else:
            data, preds = work / "data" / "eval", work / "predictions"
        build_s = time.perf_counter() - t0
        runs = {}
        for k in ks:
            pred_k = with_samples(preds, k, Path(tmp) / f"pred-K{k}")
            docs = []
            for r in range(repeat):
                out = Path(tmp) / f"run-K{k}-{r}"
                profile = args.profile / f"K{k}.prof" if args.profile and r == 0 else None
                if profile:
                    args.profile.mkdir(parents=True, exist_ok=True)
                docs.append(time_child(pred_k, data, out, profile, args.src.resolve()))
                shutil.rmtree(out)
            phases = {"imports": statistics.median(d["imports"] for d in docs),
                      "evaluate": statistics.median(d["evaluate"] for d in docs)}
            for key in docs[0]["timings_s"]:
                phases[key] = statistics.median(d["timings_s"].get(key, 0.0) for d in docs)
            runs[f"K{k}"] = {"wall_s": round(statistics.median(d["wall"] for d in docs), 3),
                             "wall_s_all": [round(d["wall"], 3) for d in docs],
                             "cpu_s": round(statistics.median(d["cpu"] for d in docs), 3),
                             "phases_s": {key: round(v, 3) for key, v in phases.items()},
                             "records": len(docs[0]["records"]), "skipped_metrics": sorted(docs[0]["skipped"]),
                             "metrics": {str(r["sample"]): r["metrics"] for r in docs[0]["records"]}}
    doc = {"machine": {"cpus": os.cpu_count(), "load_average_1_5_15": [round(v, 2) for v in load]},
           "clip": {"width": width, "height": height, "frames": frames, "noise_grey_levels": args.noise,
                    "perception": "gt", "built_in_s": round(build_s, 2)},
           "repeat": repeat, "runs": runs}
    print(json.dumps(doc, indent=1, allow_nan=False))


if __name__ == "__main__":
    main()
