"""Time video generation and print one JSON object, one key per section.

Sections:
  hosted  the Replicate client against the stand-in server of tests/fixtures/replicate_server.py on
          127.0.0.1 (nothing leaves the machine): its overhead per call (first-frame JPEG, creation,
          download, decode check, atomic writes; the stand-in answers at once, so this is all client
          time) and calls per second through the predict stage at concurrency 1 and 8.
  local   wan-2.2 and cosmos-2.5 through their adapters (the code path of ``rigidbench predict``) with
          randomly initialised pipelines of the real classes: on a GPU at the released architecture
          sizes (Wan 2.2 TI2V-5B with UMT5-XXL; Cosmos Predict 2.5-2B with Qwen2.5-VL-7B) in
          bfloat16 at the paper's settings (1280x704, 49 / 33 frames, 50 steps); without one the
          tiny test configurations (tests/fixtures/tiny_video_models.py) at 224x128 / 256x144, 13 / 9
          frames, 50 steps, in float32. Per model: seconds per video (best of --local-repeats after
          one 1-step warm-up) and peak memory (GPU: torch's peak allocation during the video; CPU:
          the peak resident set of a fresh process that builds the pipeline and generates).

Usage: python benchmarks/generate.py [--quick] [--sections hosted,local] [--examples 24] [--repeats 3]
       [--local-size auto|tiny|real] [--local-steps N] [--local-repeats 1] [--local-models wan-2.2,cosmos-2.5]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _stand_in():
    """The stand-in server module of the tests' fixtures package."""
    sys.path.insert(0, str(ROOT / "tests"))  # the fixtures package
    from fixtures import replicate_server

    return replicate_server


def hosted_section(examples: int = 24, repeats: int = 3, concurrency: tuple[int, ...] = (1, 8)) -> dict:
    """Client overhead per call and calls per second against the stand-in server."""
    import yaml

    from rigidbench.config import PACKAGE_CONFIG_DIR
    from rigidbench.context import RunContext
    from rigidbench.driver import RunOptions
    from rigidbench.stages.predict import predict
    from rigidbench.predictors import PREDICTORS, PredictContext
    from rigidbench.predictors.replicate import CallStats, ClientSettings, Deadline, ReplicateClient

    fixtures = _stand_in()
    saved = {k: os.environ.get(k) for k in ("REPLICATE_API_TOKEN", "REPLICATE_BASE_URL")}
    with tempfile.TemporaryDirectory() as tmp_name:
        tmp = Path(tmp_name)
        video = fixtures.tiny_mp4(tmp / "clip.mp4")
        split = fixtures.make_split(tmp / "eval", examples, size=(1280, 704))
        config_dir = tmp / "config"
        config_dir.mkdir()
        data = yaml.safe_load((PACKAGE_CONFIG_DIR / "models.yaml").read_text())
        data["client"].update(poll_interval_s=0.01, poll_max_interval_s=0.01)
        (config_dir / "models.yaml").write_text(yaml.safe_dump(data))
        server = fixtures.StandInReplicate(video).start()
        try:
            os.environ["REPLICATE_API_TOKEN"] = fixtures.TOKEN
            os.environ["REPLICATE_BASE_URL"] = server.url
            # 1. One GET round trip of the bare client (connection kept alive).
            client = ReplicateClient(ClientSettings())
            first = client.create("google/veo-3.1", {"prompt": "x"}, Deadline(60), CallStats())
            rtts = []
            for _ in range(200):
                t0 = time.perf_counter()
                client.get(first["id"], Deadline(60), CallStats())
                rtts.append(time.perf_counter() - t0)
            client.close()
            # 2. Whole examples through the predict stage.
            runs = {}
            for workers in concurrency:
                seconds = []
                for r in range(repeats):
                    out = tmp / f"out-{workers}-{r}"
                    ctx = PredictContext(RunContext(config_dirs=(config_dir,)), options={"concurrency": workers})
                    t0 = time.perf_counter()
                    summary = predict("veo-3.1", split, out, ctx, run=RunOptions(progress=False),
                                      predictor=PREDICTORS["veo-3.1"].create())
                    seconds.append(time.perf_counter() - t0)
                    if summary.failed:
                        raise RuntimeError(f"stand-in run failed: {summary.failed}")
                best = min(seconds)
                runs[str(workers)] = {"seconds": [round(s, 4) for s in seconds], "calls_per_s": round(examples / best, 2),
                                      "seconds_per_call": round(best / examples, 5)}
            gen = json.loads((tmp / f"out-1-{repeats - 1}" / "generation.json").read_text())
            parts = {}
            for entry in gen["examples"].values():
                for key, value in entry["client_seconds"].items():
                    parts.setdefault(key, []).append(value)
        finally:
            server.stop()
            for key, value in saved.items():
                if value is None:
                    os.environ.pop(key, None)
                else:
                    os.environ[key] = value
    return {
        "server": "stand-in on 127.0.0.1 (answers at once; Prefer: wait returns a finished prediction)",
        "examples": examples, "first_frame": "1280x704 PNG -> 1280x720 JPEG data URI",
        "output_bytes": len(video),
        "api_round_trip_ms": {"median": round(statistics.median(rtts) * 1e3, 3),
                              "p90": round(sorted(rtts)[int(0.9 * len(rtts))] * 1e3, 3)},
        "overhead_per_call_s": runs[str(concurrency[0])]["seconds_per_call"],
        "overhead_parts_median_s": {k: round(statistics.median(v), 4) for k, v in parts.items()},
        "by_concurrency": runs,
    }


# -- local models -----------------------------------------------------------------------------------------

#: per model: the tiny CPU run's options and the paper's (real-size) settings
LOCAL_RUNS = {
    "wan-2.2": {"tiny": {"height": 128, "width": 224, "num_frames": 13}, "real": {}},
    "cosmos-2.5": {"tiny": {"height": 144, "width": 256, "num_frames": 9}, "real": {}},
}
TASK_PROMPT = "An apple is released above the counter and falls onto it."


def _local_row(name: str, size: str, steps: int | None, repeats: int) -> dict:
    """One model: build its pipeline (random weights), one 1-step warm-up, then ``repeats`` timed videos.
    Runs in a fresh process (see local_section), so the CPU peak memory is this model's alone."""
    import contextlib
    import io
    import resource
    from types import MappingProxyType, SimpleNamespace

    import torch

    sys.path.insert(0, str(ROOT / "tests"))  # the fixtures package
    from fixtures import tiny_video_models

    from rigidbench.errors import PredictionError
    from rigidbench.predictors import PREDICTORS, PredictContext

    device = "cuda" if size == "real" else "cpu"
    build = tiny_video_models.tiny_wan if name == "wan-2.2" else tiny_video_models.tiny_cosmos
    t0 = time.perf_counter()
    pipe = build(size=size, device=device)
    build_s = time.perf_counter() - t0
    params = sum(p.numel() for c in pipe.components.values() if isinstance(c, torch.nn.Module) for p in c.parameters())
    predictor = PREDICTORS[name].create()
    options = {"pipeline": pipe, "no_guardrail": True, **LOCAL_RUNS[name][size]}
    if steps is not None:
        options["steps"] = steps
    ctx = PredictContext(options=MappingProxyType(options))
    p = predictor.params(ctx)
    frame = tiny_video_models.textured_frame(p["height"], p["width"])
    sample = SimpleNamespace(frame=lambda i: frame, first_frame_path=Path("frame_0000.png"), prompt=TASK_PROMPT)
    with contextlib.redirect_stderr(io.StringIO()):  # the --no-guardrail notice, printed once
        try:  # warm-up: one step at the same size (allocator, kernels)
            predictor.predict(sample, PredictContext(options=MappingProxyType({**options, "steps": 1})))
        except PredictionError:
            pass
    rss_before_mib = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    seconds, peaks, outcome = [], [], "frames"
    for _ in range(repeats):
        if device == "cuda":
            torch.cuda.synchronize()
            torch.cuda.reset_peak_memory_stats()
        t0 = time.perf_counter()
        try:
            predictor.predict(sample, ctx)  # the whole video: text encoding, denoising, VAE decoding
        except PredictionError as exc:  # random weights may overflow; the timing still counts
            outcome = f"no video: {exc}"
        if device == "cuda":
            torch.cuda.synchronize()
            peaks.append(torch.cuda.max_memory_allocated() / 2**30)
        seconds.append(time.perf_counter() - t0)
    predictor.close()
    row = {"size": "released architecture, random weights" if size == "real" else "tiny test configuration",
           "device": torch.cuda.get_device_name(0) if device == "cuda" else "cpu",
           "dtype": p["dtype"], "parameters_m": round(params / 1e6, 3),
           "height": p["height"], "width": p["width"], "num_frames": p["num_frames"], "steps": p["steps"],
           "guidance_scale": p["guidance_scale"], "build_s": round(build_s, 2),
           "seconds_per_video": round(min(seconds), 3), "seconds_all": [round(x, 3) for x in seconds],
           "output": outcome}
    if device == "cuda":
        row["peak_gpu_memory_gib"] = round(max(peaks), 3)
    else:
        row["peak_rss_mib"] = round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, 1)
        row["peak_rss_before_timed_videos_mib"] = round(rss_before_mib, 1)
        row["torch_threads"] = torch.get_num_threads()
        row["load_average_1min"] = round(os.getloadavg()[0], 2)  # other work on the machine slows these down
    return row


def local_section(size: str = "auto", steps: int | None = None, repeats: int = 1,
                  models: tuple[str, ...] = tuple(LOCAL_RUNS)) -> dict:
    """Seconds per video and peak memory of the local models; ``size`` auto: real on a GPU, else tiny."""
    import multiprocessing
    from concurrent.futures import ProcessPoolExecutor

    import torch

    gpu = torch.cuda.is_available()
    if size == "auto":
        size = "real" if gpu else "tiny"
    if size == "real" and not gpu:
        raise SystemExit("--local-size real needs a CUDA GPU")
    out = {"size": size, "note": "random weights: timings and memory only, the frames are noise"}
    for name in models:
        with ProcessPoolExecutor(max_workers=1, mp_context=multiprocessing.get_context("spawn")) as pool:
            out[name] = pool.submit(_local_row, name, size, steps, repeats).result()
    return out


#: name -> function returning that section's JSON
SECTIONS = {"hosted": hosted_section, "local": local_section}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sections", default=",".join(SECTIONS), help=f"comma-separated, of {', '.join(SECTIONS)}")
    parser.add_argument("--examples", type=int, default=24, help="hosted: examples per run")
    parser.add_argument("--repeats", type=int, default=3, help="hosted: runs per concurrency (the best counts)")
    parser.add_argument("--local-size", choices=("auto", "tiny", "real"), default="auto",
                        help="local: real architecture sizes (GPU) or the tiny test configurations (auto: real on a GPU)")
    parser.add_argument("--local-steps", type=int, default=None, help="local: inference steps (default: the paper's 50)")
    parser.add_argument("--local-repeats", type=int, default=1, help="local: timed videos per model (the best counts)")
    parser.add_argument("--local-models", default=",".join(LOCAL_RUNS), help="local: comma-separated model names")
    parser.add_argument("--quick", action="store_true", help="smoke run: the hosted section only, 2 examples, 1 repeat")
    args = parser.parse_args()
    if args.quick:
        args.sections = 'hosted'
        args.examples = 2
        args.repeats = 1
    names = [s.strip() for s in args.sections.split(",") if s.strip()]
    unknown = sorted(set(names) - set(SECTIONS))
    if unknown:
        parser.error(f"unknown section(s) {', '.join(unknown)}; known: {', '.join(SECTIONS)}")
    result = {"machine": {"python": platform.python_version(), "platform": platform.platform(),
                          "cpus": os.cpu_count()}}
    for name in names:
        if name == "hosted":
            result[name] = hosted_section(args.examples, args.repeats)
        elif name == "local":
            result[name] = local_section(args.local_size, args.local_steps, args.local_repeats,
                                         tuple(m.strip() for m in args.local_models.split(",") if m.strip()))
        else:
            result[name] = SECTIONS[name]()
    print(json.dumps(result, indent=2))


if __name__ == "__main__":
    main()
