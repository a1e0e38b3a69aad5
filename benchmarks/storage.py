"""What storing a local model's video costs in fidelity: print one JSON object.

One video of the tiny randomly initialised Wan 2.2 TI2V pipeline (tests/fixtures/tiny_video_models.py,
through the wan-2.2 adapter: flow-euler, --steps, seed 0) is written the way ``rigidbench predict``
wrote local videos before issue 24 (H.264 yuv420p, crf 18) and the way it writes them now (lossless
H.264 RGB, libx264rgb crf 0), decoded as ``evaluate`` decodes it, and compared with the generated
frames: SSIM (the benchmark's ``metrics.appearance.ssim``, data range 255), the largest pixel error,
PSNR and the file size. For comparison, the same for the paper's storage (the authors' release wrote
every frame as a JPEG, quality 95, 4:4:4). A tiny random network's frames are noisier than a real model's, so the SSIM
loss here is an upper end for what 4:2:0 crf 18 does to real outputs; ``--reference BUNDLE`` measures
the same on a rendered reference clip (its lossless PNG frames) for natural content.

Usage: python benchmarks/storage.py [--quick] [--size 224x128] [--frames 13] [--steps 50] [--reference data/eval/00015]
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import types
from pathlib import Path
from types import MappingProxyType

import numpy as np

ROOT = Path(__file__).resolve().parents[1]


def tiny_video(width: int, height: int, frames: int, steps: int) -> np.ndarray:
    """(T,H,W,3) uint8: the tiny Wan pipeline's video through the wan-2.2 adapter."""
    sys.path.insert(0, str(ROOT / "tests"))  # the fixtures package
    from fixtures import tiny_video_models as tiny

    from rigidbench.predictors import PREDICTORS, PredictContext

    frame = tiny.textured_frame(height, width)
    sample = types.SimpleNamespace(frame=lambda i: frame, first_frame_path=Path("frame.png"),
                                   prompt="An apple drops onto the counter.")
    options = {"pipeline": tiny.tiny_wan(), "height": height, "width": width, "num_frames": frames, "steps": steps}
    predictor = PREDICTORS["wan-2.2"].create()
    try:
        return predictor.predict(sample, PredictContext(seed=0, options=MappingProxyType(options))).frames
    finally:
        predictor.close()


def fidelity(frames: np.ndarray, decoded: np.ndarray, stored_bytes: int) -> dict:
    """What storing ``frames`` lost: SSIM (mean and worst frame), largest error, PSNR (None when exact), size."""
    from rigidbench.metrics.appearance import ssim

    error = decoded.astype(np.float64) - frames
    mse = float(np.mean(error ** 2))
    result = ssim(frames, decoded)
    return {"ssim": round(result.value, 6), "ssim_min_frame": round(float(np.min(result.per_frame)), 6),
            "max_abs_error": int(np.abs(error).max()),
            "psnr_db": None if mse == 0 else round(10 * np.log10(255.0 ** 2 / mse), 2), "bytes": stored_bytes}


def compare(frames: np.ndarray, path: Path, lossless: bool) -> dict:
    """Write ``frames`` at 24 fps, decode them, and measure what was lost."""
    from rigidbench.video import read_video, write_video

    write_video(path, frames, fps=24.0, lossless=lossless)
    return fidelity(frames, read_video(path).frames, path.stat().st_size)


def compare_jpeg(frames: np.ndarray) -> dict:
    """The release's storage: each frame a JPEG, quality 95, no chroma subsampling (the rigidbench-v1 protocol's
    round trip), read back; the size is that of the JPEG files."""
    import io

    from PIL import Image

    from rigidbench.evaluation.protocol import jpeg_roundtrip

    stored = 0
    for frame in frames:
        buffer = io.BytesIO()
        Image.fromarray(frame).save(buffer, format="JPEG", quality=95, subsampling=0)
        stored += buffer.tell()
    return fidelity(frames, jpeg_roundtrip(frames, 95), stored)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--size", default="224x128", help="WxH, multiples of 32 (default 224x128)")
    parser.add_argument("--frames", type=int, default=13, help="4k + 1 frames (default 13)")
    parser.add_argument("--steps", type=int, default=50)
    parser.add_argument("--reference", type=Path, help="also measure a rendered bundle's frames/ (PNG)")
    parser.add_argument("--quick", action="store_true", help="smoke run: a 64x64 clip of 5 frames, 2 steps")
    args = parser.parse_args()
    if args.quick:
        args.steps = 2
        args.frames = 5
        args.size = '64x64'
    width, height = (int(v) for v in args.size.split("x"))
    frames = tiny_video(width, height, args.frames, args.steps)
    out = {"video": {"model": "tiny wan-2.2", "size": [width, height], "frames": args.frames, "steps": args.steps},
           **both(frames)}
    if args.reference is not None:
        from rigidbench.video import read_video

        clip = read_video(args.reference / "frames", fps=24.0).frames
        out["reference"] = {"bundle": str(args.reference), "size": [clip.shape[2], clip.shape[1]],
                            "frames": clip.shape[0], **both(clip)}
    print(json.dumps(out, indent=1))


def both(frames: np.ndarray) -> dict:
    """The earlier and the current storage of ``frames``, and the SSIM between them."""
    with tempfile.TemporaryDirectory() as tmp:
        before = compare(frames, Path(tmp) / "yuv420p_crf18.mp4", lossless=False)
        now = compare(frames, Path(tmp) / "rgb_lossless.mp4", lossless=True)
        release = compare_jpeg(frames)
    return {"h264_yuv420p_crf18": before, "h264_rgb_lossless": now, "release_jpeg_q95_444": release,
            "ssim_difference": round(now["ssim"] - before["ssim"], 6)}


if __name__ == "__main__":
    main()
