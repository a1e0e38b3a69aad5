"""The evaluator's perception cache (issue 27): an uncompressed .npz with bit-packed masks that reads back
exactly what was written, frame by frame where the report needs it; the gt backend is not cached; and a
machine without the feature networks' weights never imports their libraries."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import zipfile

import numpy as np

from rigidbench.perception.base import Perception, load_arrays, packed_frames, save_arrays


def _perception(rng, t=7, n=3, h=13, w=21, p=5, c=4) -> Perception:
    disparity = rng.normal(size=(t, h, w)).astype(np.float32)
    disparity[0, 0, 0] = np.nan
    tracks = rng.normal(size=(p, t, 2)).astype(np.float32)
    tracks[1, 2] = np.nan
    return Perception(times_s=np.arange(t) / 24.0, masks=rng.random((t, n, h, w)) < 0.3, tracks=tracks,
                      visibility=rng.random((p, t)) < 0.8, confidence=rng.random((p, t)).astype(np.float32),
                      track_actor=rng.integers(0, n, p), disparity=disparity, bg_times_s=np.arange(t) / 24.0,
                      bg_tracks=rng.normal(size=(c, t, 2)).astype(np.float32),
                      bg_confidence=(rng.random((c, t)) < 0.5).astype(np.float32))


def _assert_same(a: Perception, b: Perception) -> None:
    for name in a.__dataclass_fields__:
        x, y = np.asarray(getattr(a, name)), np.asarray(getattr(b, name))  # (geometry_only: a Python bool)
        assert x.dtype == y.dtype and x.shape == y.shape, name
        np.testing.assert_array_equal(x, y, err_msg=name)


def test_cache_round_trip_is_exact_and_uncompressed_with_packed_masks(tmp_path):
    rng = np.random.default_rng(0)
    p = _perception(rng)
    path = tmp_path / "x.npz"
    p.save(path)
    _assert_same(p, Perception.load(path))
    with zipfile.ZipFile(path) as z:
        infos = {i.filename: i for i in z.infolist()}
    assert all(i.compress_type == zipfile.ZIP_STORED for i in infos.values())
    assert "masks.npy" not in infos and "visibility.npy" not in infos  # bool arrays are stored packed
    per_frame_bytes = -(-p.masks[0].size // 8)  # one bit a pixel, each frame's row rounded up to a byte
    assert infos["__packbits__masks.npy"].file_size <= per_frame_bytes * len(p.masks) + 128  # + the .npy header
    assert not list(tmp_path.glob("*.tmp.npz"))  # written atomically


def test_packed_frames_reads_single_frames(tmp_path):
    rng = np.random.default_rng(1)
    p = _perception(rng, t=9, n=2, h=5, w=7)  # 70 bits a frame: rows end mid-byte
    path = tmp_path / "x.npz"
    p.save(path)
    frames = packed_frames(path, "masks", [0, 4, 8, 12])
    assert sorted(frames) == [0, 4, 8]
    for i, m in frames.items():
        np.testing.assert_array_equal(m, p.masks[i])
    assert packed_frames(path, "disparity", [0]) is None


def test_compressed_files_still_load(tmp_path):
    """World states and caches written before (savez_compressed, plain bool arrays) read as before."""
    rng = np.random.default_rng(2)
    p = _perception(rng)
    save_arrays(p, tmp_path / "old.npz")  # the compressed format
    _assert_same(p, load_arrays(Perception, tmp_path / "old.npz"))
    assert packed_frames(tmp_path / "old.npz", "masks", [0]) is None


def test_gt_backend_is_not_cached():
    from rigidbench.perception.base import BACKENDS

    assert BACKENDS.load("gt").cache is False
    assert getattr(BACKENDS.load("neural"), "cache", True) is True


def test_feature_nets_without_weights_import_neither_torch_nor_transformers(tmp_path):
    env = dict(os.environ, HF_HOME=str(tmp_path / "hf"), HF_HUB_CACHE=str(tmp_path / "hf" / "hub"),
               TORCH_HOME=str(tmp_path / "torch"), HF_HUB_OFFLINE="1")
    for var in ("RIGIDBENCH_DINOV2", "RIGIDBENCH_ALEXNET", "RIGIDBENCH_LPIPS_LIN"):
        env.pop(var, None)
    code = ("import json, sys\n"
            "from rigidbench.perception.features import load_feature_nets\n"
            "nets = load_feature_nets()\n"
            "print(json.dumps({'skipped': sorted(nets.skipped), 'iddrift': nets.skipped.get('iddrift', ''),\n"
            "                  'torch': 'torch' in sys.modules, 'transformers': 'transformers' in sys.modules}))\n")
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=120, check=True)
    result = json.loads(out.stdout.strip().splitlines()[-1])
    assert "iddrift" in result["skipped"] and "DINOv2" in result["iddrift"]
    assert result["torch"] is False and result["transformers"] is False
