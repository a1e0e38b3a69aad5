"""The neural backend end to end on tiny random models: outputs, visibility, caching, errors."""

import logging
from pathlib import Path

import numpy as np
import pytest

torch = pytest.importorskip("torch")
pytest.importorskip("transformers")

from fixtures import tiny_perception  # noqa: E402

from rigidbench.metrics.background import detect_background_corners  # noqa: E402
from rigidbench.perception.base import PerceptionError, get_backend  # noqa: E402
from rigidbench.perception.cotracker import track_points  # noqa: E402
from rigidbench.perception.features import WeightsUnavailable  # noqa: E402
from rigidbench.perception.neural import NeuralBackend  # noqa: E402
from rigidbench.perception.sam2 import propagate_masks  # noqa: E402
from rigidbench.video import Video  # noqa: E402

DEPTH_INPUT = 56  # the paper's 384 works too, it is only slower on CPU


@pytest.fixture(scope="module")
def models():
    return tiny_perception.tiny_models()


@pytest.fixture(scope="module")
def clip():
    sample, frames = tiny_perception.synthetic_sample(n_frames=5)
    return sample, Video(frames, np.arange(5) / 24.0)


@pytest.fixture(scope="module")
def perceived(models, clip, tmp_path_factory):
    cache = tmp_path_factory.mktemp("neural_cache")
    backend = NeuralBackend(models=models, cache_dir=cache, depth_input_size=DEPTH_INPUT, device="cpu")
    sample, video = clip
    return backend.perceive(sample, video, Path("synthetic.mp4")), backend, cache


def test_outputs_have_the_perception_shapes_dtypes_and_ranges(perceived, clip):
    p, backend, _ = perceived
    sample, video = clip
    assert backend.runs == {"sam2": 1, "cotracker": 1, "background": 1, "depth": 1}
    np.testing.assert_array_equal(p.times_s, video.times_s)
    np.testing.assert_array_equal(p.bg_times_s, np.arange(5) / 24.0)  # the reference times
    assert p.masks.shape == (5, 2, 48, 64) and p.masks.dtype == bool
    assert p.tracks.shape == (40, 5, 2) and p.tracks.dtype == np.float32
    assert p.visibility.shape == (40, 5) and p.visibility.dtype == bool
    assert p.confidence.shape == (40, 5) and p.confidence.dtype == np.float32
    np.testing.assert_array_equal(p.track_actor, sample.track_active_index)
    assert p.disparity.shape == (5, 48, 64) and p.disparity.dtype == np.float32
    assert np.isfinite(p.disparity).all() and (p.disparity >= 0).all()
    assert p.bg_tracks.shape[1:] == (5, 2) and p.bg_confidence.shape == p.bg_tracks.shape[:2]
    assert p.bg_tracks.shape[0] > 0 and np.isin(p.bg_confidence, (0.0, 1.0)).all()  # 0/1 visibility weights


def test_masks_are_sam2_propagated_from_the_reference_frame0_masks(perceived, clip, models):
    p, _, _ = perceived
    sample, video = clip
    direct = propagate_masks(models["sam2"], video.frames, sample.masks[0][sample.active_indices])
    np.testing.assert_array_equal(p.masks, direct)


def test_tracks_start_at_the_ground_truth_points_and_keep_the_generated_visibility(perceived, clip, models):
    from rigidbench.metrics.tracks import ate

    p, _, _ = perceived
    sample, video = clip
    corners = detect_background_corners(video.frames[0], p.masks[0])
    np.testing.assert_allclose(p.bg_tracks[:, 0], corners, atol=1e-4)
    # Two calls: the actor points alone, the corners alone (here the clip is at the reference times).
    tracks, visible, confidence = track_points(models["cotracker"], video.frames, sample.tracks["query_pixels"])
    np.testing.assert_array_equal(p.tracks, tracks)
    np.testing.assert_allclose(p.tracks[:, 0], sample.tracks["query_pixels"], atol=1e-4)
    # The backend stores the generated visibility alone; the metrics AND it with the reference's once.
    np.testing.assert_array_equal(p.visibility, visible)
    np.testing.assert_array_equal(p.confidence, confidence)
    bg_tracks, bg_visible, _ = track_points(models["cotracker"], video.frames, corners.astype(np.float32))
    np.testing.assert_array_equal(p.bg_tracks, bg_tracks)
    np.testing.assert_array_equal(p.bg_confidence, bg_visible.astype(np.float32))
    ref_tracks, ref_vis = sample.tracks["tracks"], sample.tracks["visibility"]
    assert (p.visibility & ~ref_vis).any() or (~p.visibility & ref_vis).any()  # the two flags do differ
    joint = ref_vis & p.visibility
    by_hand = np.linalg.norm(p.tracks - ref_tracks, axis=-1)[joint].mean() / 48
    assert ate(ref_tracks, p.tracks, ref_vis, p.visibility, 48).value == pytest.approx(by_hand)


def test_a_second_run_does_no_model_work(perceived, clip):
    p, _, cache = perceived
    sample, video = clip
    assert sorted(f.name.split("-")[1] for f in cache.glob("*.npz")) == ["background", "cotracker", "depth", "sam2"]

    def must_not_load(role):
        raise AssertionError(f"{role} was loaded although its output is cached")

    again = NeuralBackend(cache_dir=cache, depth_input_size=DEPTH_INPUT, device="cpu",
                          models=tiny_perception.tiny_models())
    again._load = must_not_load
    q = again.perceive(sample, video, Path("synthetic.mp4"))
    assert again.runs == {"sam2": 0, "cotracker": 0, "background": 0, "depth": 0}
    for name in ("masks", "tracks", "visibility", "confidence", "disparity", "bg_times_s", "bg_tracks",
                 "bg_confidence"):
        np.testing.assert_array_equal(getattr(q, name), getattr(p, name))


def test_changing_one_model_setting_reruns_only_that_model(perceived, clip, models):
    _, _, cache = perceived
    sample, video = clip
    other = NeuralBackend(models=models, cache_dir=cache, depth_input_size=DEPTH_INPUT + 14, device="cpu")
    other.perceive(sample, video, Path("synthetic.mp4"))
    assert other.runs == {"sam2": 0, "cotracker": 0, "background": 0, "depth": 1}
    assert other.version != NeuralBackend(depth_input_size=DEPTH_INPUT).version
    # A changed video invalidates everything; without a cache directory nothing is reused.
    shifted = Video(np.roll(video.frames, 3, axis=2), video.times_s)
    uncached = NeuralBackend(models=models, depth_input_size=DEPTH_INPUT, device="cpu")
    uncached.perceive(sample, shifted, Path("shifted.mp4"))
    assert uncached.runs == {"sam2": 1, "cotracker": 1, "background": 1, "depth": 1}


def test_dav2_fallback_replaces_only_the_depth_model(perceived, clip, models):
    from rigidbench.perception.depth_anything_v2 import frame_disparity

    _, _, cache = perceived
    sample, video = clip
    dav2 = tiny_perception.tiny_dav2()
    backend = NeuralBackend(depth_model="dav2", models={**models, "depth": dav2}, cache_dir=cache,
                            depth_input_size=DEPTH_INPUT, device="cpu")
    p = backend.perceive(sample, video, Path("synthetic.mp4"))
    assert backend.runs == {"sam2": 0, "cotracker": 0, "background": 0, "depth": 1} and "dav2" in backend.version
    np.testing.assert_array_equal(p.disparity, frame_disparity(dav2, video.frames, input_size=DEPTH_INPUT))


def test_identity_patches_outside_the_image_are_left_out(perceived, clip):
    from rigidbench.metrics.identity import iddrift
    from rigidbench.perception.features import load_identity_features

    p, _, _ = perceived
    sample, video = clip
    feats = load_identity_features(device="cpu", model=tiny_perception.tiny_dinov2())
    keep = [0, 1, 20, 21]  # two points of each actor keep the test fast
    rgb, ref_tracks, gen_tracks = video.frames, sample.tracks["tracks"][keep], p.tracks[keep]
    seen = np.ones((4, 5), bool)

    def score(gen_tracks, gen_visible):
        return iddrift(rgb, rgb, ref_tracks, gen_tracks, seen, gen_visible, p.track_actor[keep], feats).value

    # Point 0's generated track far outside the image removes exactly the pairs it had, as if unseen.
    far = gen_tracks.copy()
    far[0, 1:] = (-500.0, -500.0)
    hidden = seen.copy()
    hidden[0, 1:] = False
    assert score(far, seen) == pytest.approx(score(gen_tracks, hidden))
    assert score(far, seen) != pytest.approx(score(gen_tracks, seen))


def test_backend_is_registered_and_rejects_bad_inputs(clip, models, caplog, monkeypatch):
    from rigidbench.perception import device as device_mod

    sample, video = clip
    assert isinstance(get_backend("neural", depth_model="dav2"), NeuralBackend)
    with pytest.raises(PerceptionError, match="unknown depth model 'midas'"):
        NeuralBackend(depth_model="midas")
    monkeypatch.setattr(device_mod, "cuda_available", lambda: False)
    with caplog.at_level(logging.WARNING):
        assert NeuralBackend(device="cuda").device == "cpu"
    assert "CUDA is not available" in caplog.text
    small = Video(video.frames[:, :24, :32].copy(), video.times_s)
    with pytest.raises(PerceptionError, match="frames are 32x24 but reference synthetic is 64x48"):
        NeuralBackend(models=models).perceive(sample, small, Path("small.mp4"))


def test_missing_weights_name_the_model_not_a_stack_trace(clip, tmp_path, monkeypatch):
    import huggingface_hub.constants

    monkeypatch.setattr(huggingface_hub.constants, "HF_HUB_CACHE", str(tmp_path / "hf"))
    monkeypatch.delenv("RIGIDBENCH_SAM2", raising=False)
    sample, video = clip
    expected = r"SAM 2.1 Hiera Large weights .* `rigidbench weights --download sam2`"
    with pytest.raises(WeightsUnavailable, match=expected):
        NeuralBackend(cache_dir=tmp_path / "cache").perceive(sample, video, Path("x.mp4"))
