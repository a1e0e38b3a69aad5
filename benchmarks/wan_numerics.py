"""What DiffSynth's sampling numerics (``wan-2.2 --model-args recipe=release``) change in a video: print JSON.

One video of the tiny randomly initialised Wan 2.2 TI2V pipeline (tests/fixtures/tiny_video_models.py,
through the wan-2.2 adapter, flow-euler, seed 0) is generated with our numerics (``recipe=ours``), with
each of ``timestep_dtype=bfloat16``, ``update_dtype=bfloat16`` and ``vae_codec=diffsynth-tiled`` alone,
and with all three (``recipe=release``); each is compared with ours: the largest and the mean absolute
difference in 8-bit levels over every pixel and channel, and the fraction of values that differ. A
random network's output is close to noise, so read these as what each option can change, not as its
effect on a real model's video.

Prints: pipeline, size, frames, steps, seed, seconds_ours, and per variant in vs_ours: max_levels,
mean_levels, fraction_differing, seconds.

Usage: python benchmarks/wan_numerics.py [--quick] [--size 1024x704] [--frames 5] [--steps 10] [--dtype bfloat16]
"""

from __future__ import annotations

import argparse
import json
import sys
import time
import types
from pathlib import Path
from types import MappingProxyType

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
VARIANTS = {"timestep_dtype=bfloat16": {"timestep_dtype": "bfloat16"},
            "update_dtype=bfloat16": {"update_dtype": "bfloat16"},
            "vae_codec=diffsynth-tiled": {"vae_codec": "diffsynth-tiled"},
            "recipe=release": {"recipe": "release"}}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--size", default="1024x704",
                        help="WIDTHxHEIGHT, multiples of 32 up to 1024 (the tiny transformer's RoPE length)")
    parser.add_argument("--frames", type=int, default=5, help="4k + 1 frames")
    parser.add_argument("--steps", type=int, default=10)
    parser.add_argument("--dtype", choices=("bfloat16", "float32"), default="bfloat16",
                        help="the tiny pipeline's dtype (the release ran bfloat16)")
    parser.add_argument("--quick", action="store_true", help="a smoke run: 64x32, 1 frame, 2 steps, float32")
    args = parser.parse_args()
    if args.quick:
        args.size, args.frames, args.steps, args.dtype = "64x32", 1, 2, "float32"
    width, height = (int(v) for v in args.size.split("x"))

    import torch

    sys.path.insert(0, str(ROOT / "tests"))  # the fixtures package
    from fixtures import tiny_video_models as tiny

    from rigidbench.predictors import PREDICTORS, PredictContext

    frame = tiny.textured_frame(height, width)
    sample = types.SimpleNamespace(frame=lambda i: frame, first_frame_path=Path("frame.png"),
                                   prompt="An apple drops onto the counter.")
    pipe = tiny.tiny_wan().to(getattr(torch, args.dtype))
    base = {"pipeline": pipe, "height": height, "width": width, "num_frames": args.frames, "steps": args.steps}
    predictor = PREDICTORS["wan-2.2"].create()

    def video(options):
        started = time.perf_counter()
        pred = predictor.predict(sample, PredictContext(seed=0, options=MappingProxyType({**base, **options})))
        predictor.close()
        return pred.frames.astype(np.int16), time.perf_counter() - started

    ours, seconds = video({})
    out = {"pipeline": f"tiny Wan 2.2 TI2V (random weights), {args.dtype}", "size": [width, height],
           "frames": args.frames, "steps": args.steps, "seed": 0, "seconds_ours": round(seconds, 1), "vs_ours": {}}
    for name, options in VARIANTS.items():
        frames, seconds = video(options)
        diff = np.abs(frames - ours)
        out["vs_ours"][name] = {"max_levels": int(diff.max()), "mean_levels": round(float(diff.mean()), 4),
                                "fraction_differing": round(float((diff > 0).mean()), 4),
                                "seconds": round(seconds, 1)}
    print(json.dumps(out, indent=2))


if __name__ == "__main__":
    main()
