"""What importing the published set costs in disk and time: print one JSON object.

Writes one synthetic sample in the published layout at the paper's size (1280x704, 49 frames; RGBA
frame PNGs as the release's Blender renders are, an H.264 ``video.mp4``, ``depth.npz`` with 1e10 where
nothing is hit; tests/fixtures/published_set.py), with ``--noise`` grey levels of Gaussian noise added
to the frames (a renderer's sampling noise: noiseless synthetic frames compress far better than real
renders), and imports it with ``rigidbench import``'s own function in this process. Prints:

- ``source.bytes``: the sample's bytes by kind (frames, video, depth, masks, other) and in all;
- ``import.seconds`` / ``import.cpu_seconds``: the first import (wall clock, this process's CPU);
- ``import.bytes_added``: bytes of the files the import created (an inode shared with the source, a
  hard link, counts nothing), by kind, the ledger included; ``import.added_fraction``: of the source;
- ``import.frames``: how the frames got into the bundle (linked or written);
- ``digest.seconds``: the source digest that keys the import (a sha256 of every file's content);
- ``frame_check.seconds``: decoding every frame PNG (what the import checks);
- ``rerun.seconds``: an unchanged rerun (digests only);
- ``after_deleting_source.bundle_ok``: the bundle still passes its check once the extracted source
  folder is deleted (what the README says may be deleted).

Usage: python benchmarks/published_import.py [--quick] [--size 1280x704] [--frames 49] [--noise 3]
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]


def kind(name: str) -> str:
    """The kind of a file for the byte tables."""
    if name.endswith(".png"):
        return "frames"
    return {"video.mp4": "video", "depth.npz": "depth", "masks.npz": "masks"}.get(name, "other")


def add_noise(sample_dir: Path, sigma: float, seed: int = 0) -> None:
    """Add Gaussian noise (sigma grey levels) to every frame PNG, keeping its mode (RGBA stays RGBA)."""
    from PIL import Image

    rng = np.random.default_rng(seed)
    for path in sorted((sample_dir / "frames").glob("*.png")):
        with Image.open(path) as im:
            mode, pixels = im.mode, np.asarray(im).astype(np.float32)
        pixels[..., :3] += rng.normal(0.0, sigma, pixels[..., :3].shape)
        Image.fromarray(np.clip(pixels.round(), 0, 255).astype(np.uint8), mode).save(path)


def files(root: Path) -> list[Path]:
    return sorted(p for p in root.rglob("*") if p.is_file() and not p.is_symlink())


def bytes_by_kind(paths, skip_inodes=frozenset()) -> dict:
    """{kind: bytes, "total": bytes} of the files, each inode once, those in ``skip_inodes`` not at all."""
    out: dict[str, int] = {}
    seen = set(skip_inodes)
    for p in paths:
        st = p.stat()
        if (st.st_dev, st.st_ino) in seen:
            continue
        seen.add((st.st_dev, st.st_ino))
        out[kind(p.name)] = out.get(kind(p.name), 0) + st.st_size
    out["total"] = sum(out.values())
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="a 96x64, 9-frame sample (seconds)")
    parser.add_argument("--size", default="1280x704", help="W x H (default: the paper's 1280x704)")
    parser.add_argument("--frames", type=int, default=49)
    parser.add_argument("--noise", type=float, default=3.0, help="grey levels of noise on the frames (default 3)")
    args = parser.parse_args()
    width, height = (96, 64) if args.quick else (int(v) for v in args.size.lower().split("x"))
    frames = 9 if args.quick else args.frames

    sys.path.insert(0, str(ROOT / "tests"))  # the fixtures package
    from fixtures import published_set as ps

    from rigidbench.config import registry
    from rigidbench.driver import RunOptions
    from rigidbench.stages.import_set import import_published
    from rigidbench.datasets.convert import source_digest
    from rigidbench.groundtruth.bundle import check_bundle

    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        sample = ps.PublishedSample("00000", "bounce", "modern_loft", "in_distribution", 107420369, "tennis_ball",
                                    rgba=True)
        started = time.perf_counter()
        root = ps.write_set(tmp / "extracted" / "rigidbench-eval-v1.1", [sample], width=width, height=height,
                            n_frames=frames)
        source = root / "samples" / "00000"
        if args.noise > 0:
            add_noise(source, args.noise)
        make_s = time.perf_counter() - started
        source_files = files(root)
        src_total = bytes_by_kind(source_files)
        source_inodes = {(p.stat().st_dev, p.stat().st_ino) for p in source_files}

        from PIL import Image

        t0 = time.perf_counter()
        for p in sorted((source / "frames").glob("*.png")):
            with Image.open(p) as im:
                im.load()
        frame_check_s = time.perf_counter() - t0
        t0 = time.perf_counter()
        source_digest(source)
        digest_s = time.perf_counter() - t0

        reg = registry()
        data = tmp / "data"
        t0, c0 = time.perf_counter(), time.process_time()
        summary = import_published(tmp / "extracted", data, registry=reg, run=RunOptions(progress=False))
        import_s, import_cpu = time.perf_counter() - t0, time.process_time() - c0
        if summary.failed:
            raise SystemExit(f"the import failed: {summary.failed}")
        bundle = data / "eval" / "00000"
        frame_files = sorted((bundle / "frames").glob("*.png"))
        linked = sum((f.stat().st_dev, f.stat().st_ino) in source_inodes for f in frame_files)
        added = bytes_by_kind(files(data), source_inodes)
        t0 = time.perf_counter()
        rerun = import_published(tmp / "extracted", data, registry=reg, run=RunOptions(progress=False))
        rerun_s = time.perf_counter() - t0
        shutil.rmtree(tmp / "extracted")
        out = {
            "machine": {"cpus": os.cpu_count()},
            "sample": {"width": width, "height": height, "frames": frames, "noise_grey_levels": args.noise,
                       "frame_mode": "RGBA", "written_in_s": round(make_s, 2)},
            "source": {"bytes": src_total},
            "import": {"seconds": round(import_s, 3), "cpu_seconds": round(import_cpu, 3),
                       "bytes_added": added, "added_fraction": round(added["total"] / src_total["total"], 4),
                       "frames": {"linked": linked, "written": len(frame_files) - linked}},
            "digest": {"seconds": round(digest_s, 4)},
            "frame_check": {"seconds": round(frame_check_s, 4)},
            "rerun": {"seconds": round(rerun_s, 3), "unchanged": len(rerun.reused)},
            "after_deleting_source": {"bundle_ok": check_bundle(bundle) == []},
        }
    print(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
