"""The neural perception models one by one: device choice, SAM 2.1 masks, CoTracker queries and tracks."""

import logging

import numpy as np
import pytest

torch = pytest.importorskip("torch")
pytest.importorskip("transformers")

from fixtures import tiny_perception  # noqa: E402

from rigidbench.perception import device as device_mod  # noqa: E402
from rigidbench.perception import sam2  # noqa: E402
from rigidbench.perception.cotracker import query_points, track_points  # noqa: E402


# -- device and precision


def test_cuda_request_without_cuda_falls_back_to_cpu_with_a_log_line(monkeypatch, caplog):
    monkeypatch.setattr(device_mod, "cuda_available", lambda: False)
    with caplog.at_level(logging.WARNING, logger="rigidbench.perception.device"):
        assert device_mod.resolve_device("cuda:1") == "cpu"
    assert "'cuda:1' requested but CUDA is not available" in caplog.text
    assert device_mod.resolve_device(None) == "cpu" and device_mod.resolve_device("cpu") == "cpu"
    monkeypatch.setattr(device_mod, "cuda_available", lambda: True)
    assert device_mod.resolve_device(None) == "cuda" and device_mod.resolve_device("cuda:1") == "cuda:1"


def test_precision_is_float32_on_cpu_and_the_reference_precision_on_cuda():
    for net in device_mod.CUDA_PRECISION:
        assert device_mod.inference_dtype(net, "cpu") == torch.float32
    assert device_mod.inference_dtype("dinov2", "cuda") == torch.bfloat16  # stated by the paper (autocast)
    assert device_mod.inference_dtype("sam2", "cuda:0") == torch.float32  # the published runs: no autocast
    assert device_mod.inference_dtype("cotracker", "cuda") == torch.float32
    with pytest.raises(KeyError, match="unknown network"):
        device_mod.inference_dtype("raft", "cpu")


# -- SAM 2.1


def test_frames_are_resized_to_the_square_input_and_imagenet_normalised():
    frames = np.full((2, 36, 64, 3), (255, 0, 128), np.uint8)
    x = sam2.preprocess_frames(frames, 32)
    assert x.shape == (2, 3, 32, 32) and x.dtype == torch.float32
    expected = [(1.0 - 0.485) / 0.229, (0.0 - 0.456) / 0.224, (128 / 255 - 0.406) / 0.225]
    torch.testing.assert_close(x[:, :, 5, 7], torch.tensor([expected, expected]))


def test_prompt_masks_are_binary_at_the_input_size():
    masks = np.zeros((1, 40, 80), bool)
    masks[0, :, :40] = True  # left half
    m = sam2.prompt_masks(masks, 16)
    assert m.shape == (1, 1, 16, 16) and set(torch.unique(m).tolist()) == {0.0, 1.0}
    assert bool((m[0, 0, :, :8] == 1).all()) and bool((m[0, 0, :, 8:] == 0).all())


def test_masks_are_logits_above_zero_after_upsampling():
    logits = torch.full((2, 1, 8, 8), -3.0)
    logits[0, 0, :, :4] = 3.0  # object 0: left half; object 1: nothing
    masks = sam2.logits_to_masks(logits, 16, 12, 20)
    assert masks.shape == (2, 12, 20) and masks.dtype == bool
    assert masks[0, :, :10].all() and not masks[0, :, 10:].any() and not masks[1].any()
    assert not sam2.logits_to_masks(torch.zeros(1, 1, 4, 4), 8, 4, 4).any()  # zero is not above zero


@pytest.fixture(scope="module")
def synthetic():
    return tiny_perception.synthetic_sample(n_frames=4)


def test_propagation_returns_one_mask_per_prompt_starting_from_the_prompts(synthetic):
    sample, frames = synthetic
    prompts = sample.masks[0][sample.active_indices]
    masks = sam2.propagate_masks(tiny_perception.tiny_sam2(), frames, prompts)
    assert masks.shape == (4, 2, 48, 64) and masks.dtype == bool
    # Frame 0 is the prompt itself (SAM 2 uses a mask input as the output), up to the 128-px round trip.
    for a in range(2):
        inter = (masks[0, a] & prompts[a]).sum()
        union = (masks[0, a] | prompts[a]).sum()
        assert inter / union > 0.9
    assert sam2.propagate_masks(None, frames, np.zeros((0, 48, 64), bool)).shape == (4, 0, 48, 64)


def test_hiera_large_config_matches_the_released_model():
    cfg = sam2.hiera_large_config()
    backbone = cfg.vision_config.backbone_config
    assert backbone.blocks_per_stage == [2, 6, 36, 4] and backbone.embed_dim_per_stage == [144, 288, 576, 1152]
    assert backbone.global_attention_blocks == [23, 33, 43] and cfg.image_size == 1024


# -- CoTracker queries and tracks


def test_query_points_are_the_ground_truth_track_points(synthetic):
    from rigidbench.groundtruth.tracks import erode

    sample, _ = synthetic
    q = query_points(sample)
    tracks = sample.tracks
    assert q.dtype == np.float32 and q.shape == (40, 2)
    np.testing.assert_array_equal(q, tracks["query_pixels"])
    # The ground-truth track starts at its query pixel.
    np.testing.assert_allclose(tracks["tracks"][:, 0], q, atol=1e-3)
    # 20 distinct points per active actor, each inside the actor's frame-0 mask eroded by 3 px.
    for k, actor in enumerate(sample.active_indices):
        mine = q[sample.track_active_index == k].astype(int)
        assert len(mine) == 20 and len({tuple(p) for p in mine}) == 20
        eroded = erode(sample.masks[0, actor], 3)
        assert eroded[mine[:, 1], mine[:, 0]].all()
    assert not (sample.tracks.actor_index == 1).any()  # the passive actor gets none


def test_tracks_follow_the_predictor_interface(synthetic):
    sample, frames = synthetic
    model = tiny_perception.tiny_cotracker()
    points = query_points(sample)
    tracks, visible, confidence = track_points(model, frames, points)
    assert tracks.shape == (40, 4, 2) and tracks.dtype == np.float32
    assert visible.shape == (40, 4) and visible.dtype == bool and confidence.dtype == np.float32
    np.testing.assert_allclose(tracks[:, 0], points, atol=1e-4)  # queried on frame 0
    np.testing.assert_array_equal(confidence, visible.astype(np.float32))  # boolean visibility -> 0/1
    # The stand-in really reads the video: other frames move the points elsewhere.
    moved, _, _ = track_points(model, frames[:, :, ::-1].copy(), points)
    assert not np.allclose(moved[:, 1:], tracks[:, 1:])
    empty = track_points(model, frames, np.zeros((0, 2), np.float32))
    assert [a.shape for a in empty] == [(0, 4, 2), (0, 4), (0, 4)]


class FloatVisibilityTracker(torch.nn.Module):
    """Returns fixed tracks and a float visibility ramp 0 .. 1 over the points."""

    def forward(self, video, queries):
        b, t = video.shape[:2]
        n = queries.shape[1]
        tracks = queries[:, None, :, 1:].expand(b, t, n, 2)
        vis = torch.linspace(0, 1, n)[None, None].expand(b, t, n)
        return tracks, vis


def test_a_float_visibility_is_thresholded_at_the_offline_predictors_0_9():
    frames = np.zeros((3, 8, 8, 3), np.uint8)
    _, visible, confidence = track_points(FloatVisibilityTracker(), frames, np.zeros((5, 2), np.float32))
    np.testing.assert_array_equal(visible[:, 2], [False, False, False, False, True])
    np.testing.assert_array_equal(confidence, visible.astype(np.float32))  # no confidence head: the decision


def test_cotracker_confidences_are_continuous_with_the_predictor_layout():
    from rigidbench.perception.cotracker import track_points

    model = torch.hub.load(str(tiny_perception.HUB_DIR), "cotracker3_offline_predictor", source="local")
    rng = np.random.default_rng(3)
    frames = rng.integers(0, 256, size=(6, 36, 64, 3), dtype=np.uint8)
    points = np.array([[5.0, 7.0], [40.0, 20.0], [63.0, 35.0]], np.float32)
    tracks, visible, confidence = track_points(model, frames, points)
    assert tracks.shape == (3, 6, 2) and confidence.dtype == np.float32
    np.testing.assert_allclose(tracks[:, 0], points, atol=1e-4)  # the query frame shows the query
    assert np.all(confidence[:, 0] == 1.0) and np.all((confidence >= 0) & (confidence <= 1))
    assert len(np.unique(confidence[:, 1:])) > 2  # continuous, not a 0/1 decision
    assert visible.any() and not visible.all()
    # Same tracks and decisions as the predictor's own public call.
    video = torch.from_numpy(frames).permute(0, 3, 1, 2)[None].float()
    queries = torch.cat([torch.zeros(1, 3, 1), torch.from_numpy(points)[None]], dim=2)
    public_tracks, public_visible = model(video, queries=queries)
    np.testing.assert_allclose(tracks, public_tracks[0].permute(1, 0, 2).numpy(), atol=1e-4)
    assert np.array_equal(visible, public_visible[0].permute(1, 0).numpy())
