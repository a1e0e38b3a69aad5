"""Neural perception run as the published evaluation ran it.

Upstream behaviour checked here (read from the sources, not from our modules):

- CoTracker3 OFFLINE predictor (facebookresearch/co-tracker, ``cotracker/predictor.py``,
  ``CoTrackerPredictor._compute_sparse_tracks``): ``visibilities > 0.9`` on the network's visibility,
  no confidence term, query frame visible; the ONLINE predictor's ``visibility * confidence > 0.6``
  is not the model the paper names;
- the RigidBench release tracks actor points (``eval/track/cotracker3.py``) and background corners
  (``eval/score/background.py``) in two separate calls, the corners on the clip resampled to the
  reference times and cut to the reference length, weighted by the boolean visibility;
- torch-hub DINOv2 (``dinov2/models/vision_transformer.py``, ``interpolate_pos_encoding``) resamples
  the 37 x 37 position grid with ``scale_factor=(16 + 0.1) / 37``, bicubic, no antialiasing;
- Video Depth Anything (``video_depth_anything/dpt_temporal.py``) runs the head's last output
  convolution in float32 with autocast disabled.
"""

import math
from pathlib import Path

import numpy as np
import pytest

torch = pytest.importorskip("torch")
pytest.importorskip("transformers")
pytest.importorskip("cv2")

import torch.nn.functional as F  # noqa: E402


from fixtures import tiny_perception  # noqa: E402

from rigidbench.metrics.background import detect_background_corners  # noqa: E402
from rigidbench.perception.cotracker import VISIBILITY_THRESHOLD, track_points  # noqa: E402
from rigidbench.perception.neural import NeuralBackend  # noqa: E402
from rigidbench.perception.sam2 import propagate_masks  # noqa: E402
from rigidbench.video import Video, align_video, frames_until, reference_times  # noqa: E402

pytestmark = pytest.mark.usefixtures("torch_one_thread")

DEPTH_INPUT = 56
# Per (point index + frame) % 4: network visibility and confidence. Old rule vis x conf > 0.6 says
# visible, hidden, visible, visible; the offline rule vis > 0.9 says hidden, visible, hidden, visible.
VIS = (0.8, 0.95, 0.9, 0.91)
CONF = (0.8, 0.5, 1.0, 0.99)
OFFLINE_RULE = tuple(v > 0.9 for v in VIS)


# -- a CoTracker3 stand-in in the upstream predictor layout ----------------------------------------

def get_points_on_a_grid(size, extent, device="cpu"):
    """Upstream's support-grid helper, looked up in the predictor's module as track_points does."""
    h, w = extent
    ys, xs = torch.meshgrid(torch.linspace(0, h - 1, size), torch.linspace(0, w - 1, size), indexing="ij")
    return torch.stack([xs, ys], dim=-1).reshape(1, -1, 2).to(device)


class ChosenNetwork(torch.nn.Module):
    """CoTracker3-network stand-in returning (tracks, visibility, confidence, None) with chosen values.

    Each point stays at its query, visibility and confidence cycle through VIS and CONF. With
    ``coupled`` every track also drifts in x by frame * (mean x of ALL queries of the call) / 100,
    like a tracker that attends across tracks: a point's output then depends on the other queries.
    ``calls`` records (frames, queries) of every call.
    """

    def __init__(self, coupled: bool = False):
        super().__init__()
        self.scale = torch.nn.Parameter(torch.ones(()))
        self.coupled = coupled
        self.calls: list[tuple[int, int]] = []

    def forward(self, video, queries, iters=4):
        b, t = video.shape[:2]
        n = queries.shape[1]
        self.calls.append((t, n))
        xy = queries[:, None, :, 1:].expand(b, t, n, 2).clone()
        if self.coupled:
            frame = torch.arange(t, dtype=xy.dtype)[None, :, None]
            xy[..., 0] = xy[..., 0] + frame * queries[:, :, 1].mean(dim=1)[:, None, None] / 100
        idx = (torch.arange(n)[None, :] + torch.arange(t)[:, None]) % 4
        vis = torch.tensor(VIS)[idx][None].expand(b, t, n)
        conf = torch.tensor(CONF)[idx][None].expand(b, t, n)
        return xy * self.scale, vis, conf, None


class ChosenPredictor(torch.nn.Module):
    """The offline predictor's layout and public call around ChosenNetwork (upstream's code path)."""

    def __init__(self, coupled: bool = False, resolution_hw=(24, 32)):
        super().__init__()
        self.model, self.interp_shape, self.support_grid_size, self.v2 = ChosenNetwork(coupled), resolution_hw, 2, False

    @torch.no_grad()
    def forward(self, video, queries):
        b, t, c, H, W = video.shape
        h, w = self.interp_shape
        x = F.interpolate(video.reshape(b * t, c, H, W), (h, w), mode="bilinear", align_corners=True)
        q = queries.clone()
        q[:, :, 1:] *= q.new_tensor([(w - 1) / (W - 1), (h - 1) / (H - 1)])
        grid = get_points_on_a_grid(self.support_grid_size, (h, w), device=video.device)
        q = torch.cat([q, torch.cat([torch.zeros_like(grid[:, :, :1]), grid], dim=2).repeat(b, 1, 1)], dim=1)
        tracks, vis, *_ = self.model(video=x.reshape(b, t, c, h, w), queries=q, iters=6)
        n = queries.shape[1]
        tracks, visible = tracks[:, :, :n].clone(), vis[:, :, :n] > 0.9
        for i in range(b):
            frame = q[i, :n, 0].long()
            tracks[i, frame, torch.arange(n)] = q[i, :n, 1:]
            visible[i, frame, torch.arange(n)] = True
        return tracks * tracks.new_tensor([(W - 1) / (w - 1), (H - 1) / (h - 1)]), visible


def expected_visible(n_points: int, n_frames: int) -> np.ndarray:
    idx = (np.arange(n_points)[:, None] + np.arange(n_frames)[None, :]) % 4
    visible = np.asarray(OFFLINE_RULE)[idx]
    visible[:, 0] = True  # the query frame
    return visible


# -- 1. the offline visibility rule, confidence kept apart ------------------------------------------

def test_visibility_is_the_offline_rule_and_confidence_a_separate_output():
    assert VISIBILITY_THRESHOLD == 0.9
    frames = np.random.default_rng(0).integers(0, 256, (6, 48, 64, 3), dtype=np.uint8)
    points = np.array([[5.0, 7.0], [40.0, 20.0], [63.0, 47.0], [0.0, 0.0], [30.0, 30.0]], np.float32)
    model = ChosenPredictor()
    tracks, visible, confidence = track_points(model, frames, points)
    np.testing.assert_array_equal(visible, expected_visible(5, 6))
    # vis 0.8 x conf 0.8 = 0.64 (visible by the online rule) -> hidden; vis 0.95 x conf 0.5 -> visible;
    # vis exactly 0.9 -> hidden (strictly greater).
    idx = (np.arange(5)[:, None] + np.arange(6)[None, :]) % 4
    later = np.zeros_like(visible)
    later[:, 1:] = True
    assert not visible[(idx == 0) & later].any() and visible[(idx == 1) & later].all()
    assert not visible[(idx == 2) & later].any() and visible[(idx == 3) & later].all()
    # The network's confidence is returned as it is (1 on the query frame), not folded into visibility.
    expected_conf = np.asarray(CONF, np.float32)[idx]
    expected_conf[:, 0] = 1.0
    np.testing.assert_allclose(confidence, expected_conf, rtol=1e-6)
    # Tracks and visibility are exactly what the predictor's own public call returns.
    video = torch.from_numpy(frames).permute(0, 3, 1, 2)[None].float()
    queries = torch.cat([torch.zeros(1, 5, 1), torch.from_numpy(points)[None]], dim=2)
    public_tracks, public_visible = model(video, queries=queries)
    np.testing.assert_allclose(tracks, public_tracks[0].permute(1, 0, 2).numpy(), atol=1e-4)
    np.testing.assert_array_equal(visible, public_visible[0].permute(1, 0).numpy())


def test_the_hub_stand_in_predictor_uses_the_offline_rule_too():
    model = torch.hub.load(str(tiny_perception.HUB_DIR), "cotracker3_offline_predictor", source="local")
    frames = np.random.default_rng(3).integers(0, 256, size=(6, 36, 64, 3), dtype=np.uint8)
    points = np.array([[5.0, 7.0], [40.0, 20.0], [63.0, 35.0]], np.float32)
    video = torch.from_numpy(frames).permute(0, 3, 1, 2)[None].float()
    queries = torch.cat([torch.zeros(1, 3, 1), torch.from_numpy(points)[None]], dim=2)
    _, visible, confidence = track_points(model, frames, points)
    np.testing.assert_array_equal(visible, model(video, queries=queries)[1][0].permute(1, 0).numpy())
    assert not np.array_equal(visible[:, 1:], confidence[:, 1:] > 0.6)  # not a confidence rule


# -- 2-4. the backend: two calls, boolean weights, background on the resampled reference clip ------

@pytest.fixture(scope="module")
def depth_and_masks():
    return tiny_perception.tiny_sam2(), tiny_perception.tiny_vda()


def backend_with(predictor, depth_and_masks):
    sam2, vda = depth_and_masks
    return NeuralBackend(models={"sam2": sam2, "cotracker": predictor, "depth": vda}, depth_input_size=DEPTH_INPUT,
                         device="cpu")


def clip(n_clip: int, n_reference: int, fps: float = 24.0):
    sample, frames = tiny_perception.synthetic_sample(n_frames=n_clip)
    sample.n_frames = n_reference  # the reference is shorter than the generated clip
    return sample, Video(frames, np.arange(n_clip) / fps)


def test_actor_tracks_and_background_corners_are_two_separate_calls(depth_and_masks):
    sample, video = clip(8, 8)
    predictor = ChosenPredictor(coupled=True)
    p = backend_with(predictor, depth_and_masks).perceive(sample, video, Path("gen.mp4"))
    corners = detect_background_corners(video.frames[0], p.masks[0]).astype(np.float32)
    queries = sample.tracks["query_pixels"].astype(np.float32)
    assert len(corners) > 0 and len(queries) == 40
    grid = predictor.support_grid_size ** 2
    assert predictor.model.calls == [(8, 40 + grid), (8, len(corners) + grid)]
    alone, _, _ = track_points(ChosenPredictor(coupled=True), video.frames, queries)
    np.testing.assert_array_equal(p.tracks, alone)
    # The stand-in would show a joint call: the corners would move the actor tracks.
    joint, _, _ = track_points(ChosenPredictor(coupled=True), video.frames, np.concatenate([queries, corners]))
    assert np.abs(joint[:40, 1:] - alone[:, 1:]).max() > 0.05
    # And the other way round: the corners' tracks are those of the corners alone.
    bg_alone, _, _ = track_points(ChosenPredictor(coupled=True), video.frames, corners)
    np.testing.assert_array_equal(p.bg_tracks, bg_alone)


def test_background_weights_are_the_boolean_offline_visibility(depth_and_masks):
    sample, video = clip(8, 8)
    p = backend_with(ChosenPredictor(), depth_and_masks).perceive(sample, video, Path("gen.mp4"))
    assert p.bg_confidence.dtype == np.float32 and np.isin(p.bg_confidence, (0.0, 1.0)).all()
    np.testing.assert_array_equal(p.bg_confidence, expected_visible(len(p.bg_tracks), 8).astype(np.float32))
    assert (p.bg_confidence == 0).any()  # sigmoids are never 0, but hidden corners now weigh nothing
    # Actor points: same rule, confidence kept apart.
    np.testing.assert_array_equal(p.visibility, expected_visible(40, 8))
    assert p.confidence.shape == (40, 8) and len(np.unique(p.confidence)) > 2


def test_background_is_tracked_on_the_clip_resampled_to_the_reference_times(depth_and_masks):
    sample, video = clip(12, 5, fps=16.0)  # a Cosmos-like 16 Hz clip against a 5-frame 24 Hz reference
    predictor = ChosenPredictor(coupled=True)
    p = backend_with(predictor, depth_and_masks).perceive(sample, video, Path("gen.mp4"))
    ref = reference_times(5, 24.0)
    np.testing.assert_array_equal(p.bg_times_s, ref)
    m = frames_until(video.times_s, ref[-1])
    assert m == 4  # 0, 1/16, 2/16 and 3/16 s, the first frame after 4/24 s
    resampled = align_video(Video(video.frames[:m], video.times_s[:m]), ref)
    corners = detect_background_corners(resampled[0], p.masks[0]).astype(np.float32)
    bg_tracks, bg_visible, _ = track_points(ChosenPredictor(coupled=True), resampled, corners)
    np.testing.assert_array_equal(p.bg_tracks, bg_tracks)
    np.testing.assert_array_equal(p.bg_confidence, bg_visible.astype(np.float32))
    assert predictor.model.calls[1][0] == 5  # the corners' call saw the 5 resampled frames
    # Alignment to the reference times keeps the background arrays as they are.
    aligned = p.aligned(ref)
    np.testing.assert_array_equal(aligned.bg_tracks, p.bg_tracks)
    np.testing.assert_array_equal(aligned.bg_confidence, p.bg_confidence)


def test_perception_goes_no_further_than_the_reference_length(depth_and_masks, monkeypatch):
    """SAM 2 and the background see nothing past the frame that closes the reference span; the
    outputs stop there. The actor tracker and the depth network see the whole decoded clip, as in
    the published runs (their outputs at early times depend on later frames)."""
    from rigidbench.perception import neural as neural_module

    seen = {}

    def recording_propagate(model, frames, masks0, device=None):
        seen["sam2"] = len(frames)
        return propagate_masks(model, frames, masks0, device)

    monkeypatch.setattr(neural_module, "propagate_masks", recording_propagate)
    sample, video = clip(12, 5)
    predictor = ChosenPredictor()
    backend = backend_with(predictor, depth_and_masks)
    depth_frames = []
    disparity = backend._disparity
    monkeypatch.setattr(backend, "_disparity", lambda frames: depth_frames.append(len(frames)) or disparity(frames))
    p = backend.perceive(sample, video, Path("gen.mp4"))
    assert seen["sam2"] == 5 and predictor.model.calls[1][0] == 5
    assert predictor.model.calls[0][0] == 12 and depth_frames == [12]
    np.testing.assert_array_equal(p.times_s, video.times_s[:5])
    assert p.masks.shape[0] == p.tracks.shape[1] == p.visibility.shape[1] == p.disparity.shape[0] == 5
    assert p.confidence.shape[1] == 5 and p.bg_tracks.shape[1] == 5
    # What a decode up to the reference length gives (read_video(until_s=...)): the same masks and
    # background; SAM 2 is causal, so the cut costs nothing there.
    cut = backend_with(ChosenPredictor(), depth_and_masks).perceive(
        sample, Video(video.frames[:5], video.times_s[:5]), Path("gen.mp4"))
    for name in ("times_s", "masks", "bg_times_s", "bg_tracks", "bg_confidence"):
        np.testing.assert_array_equal(getattr(cut, name), getattr(p, name))


def test_sam2_masks_of_a_clip_cut_short_equal_the_whole_clips():
    sample, frames = tiny_perception.synthetic_sample(n_frames=8)
    model = tiny_perception.tiny_sam2()
    masks0 = sample.masks[0][sample.active_indices]
    whole = propagate_masks(model, frames, masks0)
    np.testing.assert_array_equal(propagate_masks(model, frames[:5], masks0), whole[:5])


# -- 6. precision and DINOv2 position embeddings -----------------------------------------------------

def hub_interpolate_pos_encoding(pos_embed, x, w, h, patch_size=14, interpolate_offset=0.1):
    """torch-hub DINOv2's DinoVisionTransformer.interpolate_pos_encoding (x: tokens; w, h as upstream
    names the input's dims 2 and 3), written out from dinov2/models/vision_transformer.py."""
    previous_dtype = x.dtype
    npatch = x.shape[1] - 1
    N = pos_embed.shape[1] - 1
    if npatch == N and w == h:
        return pos_embed
    pos_embed = pos_embed.float()
    class_pos_embed = pos_embed[:, 0]
    patch_pos_embed = pos_embed[:, 1:]
    dim = x.shape[-1]
    w0, h0 = w // patch_size, h // patch_size
    M = int(math.sqrt(N))
    sx, sy = float(w0 + interpolate_offset) / M, float(h0 + interpolate_offset) / M
    patch_pos_embed = F.interpolate(patch_pos_embed.reshape(1, M, M, dim).permute(0, 3, 1, 2), mode="bicubic",
                                    antialias=False, scale_factor=(sx, sy))
    assert (w0, h0) == patch_pos_embed.shape[-2:]
    patch_pos_embed = patch_pos_embed.permute(0, 2, 3, 1).view(1, -1, dim)
    return torch.cat((class_pos_embed.unsqueeze(0), patch_pos_embed), dim=1).to(previous_dtype)


def dinov2_518(seed: int = 0):
    """A tiny Dinov2Model pretrained-layout: a 37 x 37 position grid (518 px, patch 14), as ViT-L/14."""
    from transformers import Dinov2Config, Dinov2Model

    torch.manual_seed(seed)
    model = Dinov2Model(Dinov2Config(hidden_size=32, num_hidden_layers=1, num_attention_heads=2,
                                     intermediate_size=64, patch_size=14, image_size=518)).eval()
    with torch.no_grad():  # a smooth grid, like trained embeddings (random ones exaggerate the difference)
        yy, xx = torch.meshgrid(torch.linspace(0, 1, 37), torch.linspace(0, 1, 37), indexing="ij")
        freq = torch.arange(1, 33, dtype=torch.float32)[:, None, None]
        grid = torch.sin(freq * 3 * xx + freq * yy) + torch.cos(2 * freq * yy)
        model.embeddings.position_embeddings[0, 1:] = grid.reshape(32, -1).T
    return model


def test_dinov2_position_embeddings_follow_torch_hub_at_224():
    from transformers.models.dinov2.modeling_dinov2 import Dinov2Embeddings

    from rigidbench.perception.features import use_hub_position_interpolation

    model = dinov2_518()
    tokens = torch.zeros(1, 16 * 16 + 1, 32)
    stock = Dinov2Embeddings.interpolate_pos_encoding(model.embeddings, tokens, 224, 224)
    hub = hub_interpolate_pos_encoding(model.embeddings.position_embeddings, tokens, 224, 224)
    use_hub_position_interpolation(model)
    ours = model.embeddings.interpolate_pos_encoding(tokens, 224, 224)
    assert ours.shape == hub.shape == (1, 257, 32)
    torch.testing.assert_close(ours, hub, rtol=0, atol=0)
    # transformers samples the 37 x 37 grid at a scale of 16 / 37, the hub at 16.1 / 37: they differ.
    assert (stock - hub).abs().max() > 1e-2
    # At the pretrained size nothing is resampled.
    full = torch.zeros(1, 37 * 37 + 1, 32)
    torch.testing.assert_close(model.embeddings.interpolate_pos_encoding(full, 518, 518),
                               model.embeddings.position_embeddings, rtol=0, atol=0)


def test_identity_features_use_the_hub_position_embeddings_and_fp32_weights():
    from rigidbench.perception.features import load_identity_features

    x = torch.randn(3, 3, 224, 224, generator=torch.Generator().manual_seed(1))
    stock = dinov2_518()
    with torch.no_grad():
        stock_out = stock(pixel_values=x).pooler_output
    model = dinov2_518()
    features = load_identity_features(device="cpu", model=model)
    out = features(x)
    assert out.dtype == torch.float32 and all(p.dtype == torch.float32 for p in model.parameters())
    assert not torch.allclose(out, stock_out, atol=1e-4)  # the hub interpolation is in use
    tokens = torch.zeros(1, 257, 32)
    torch.testing.assert_close(model.embeddings.interpolate_pos_encoding(tokens, 224, 224),
                               hub_interpolate_pos_encoding(model.embeddings.position_embeddings, tokens, 224, 224))


def test_identity_features_autocast_bf16_over_fp32_weights(monkeypatch):
    """The CUDA path (bf16 autocast, fp32 weights), exercised on the CPU's autocast."""
    from rigidbench.perception import features as features_mod
    from rigidbench.perception.features import load_identity_features

    x = torch.randn(2, 3, 224, 224, generator=torch.Generator().manual_seed(2))
    reference = load_identity_features(device="cpu", model=dinov2_518())(x)
    monkeypatch.setattr(features_mod, "inference_dtype", lambda net, device: torch.bfloat16)
    model = dinov2_518()
    features = load_identity_features(device="cpu", model=model)
    seen = {}
    model.embeddings.patch_embeddings.projection.register_forward_hook(
        lambda m, i, o: seen.update(conv=o.dtype))
    model.layernorm.register_forward_hook(lambda m, i, o: seen.update(norm=o.dtype))
    out = features(x)
    assert all(p.dtype == torch.float32 for p in model.parameters())  # weights are not cast
    assert seen == {"conv": torch.bfloat16, "norm": torch.float32}  # autocast: matmuls bf16, norms fp32
    assert out.dtype == torch.float32 and F.cosine_similarity(out, reference).min() > 0.99


def test_sam2_runs_in_float32_on_cuda():
    from rigidbench.perception.device import inference_dtype

    assert inference_dtype("sam2", "cuda") == torch.float32


@pytest.mark.parametrize("temporal", [True, False])
def test_vda_last_output_convolution_runs_fp32_with_autocast_off(temporal):
    seen = []
    model = tiny_perception.tiny_vda() if temporal else tiny_perception.tiny_dav2()
    head = model.head if temporal else model.depth_head
    head.scratch.output_conv2.register_forward_pre_hook(
        lambda m, args: seen.append((args[0].dtype, torch.is_autocast_enabled("cpu"))))
    head.scratch.output_conv1.register_forward_hook(lambda m, i, o: seen.append((o.dtype, "conv1")))
    x = torch.randn(1, 2, 3, 56, 56) if temporal else torch.randn(2, 3, 56, 56)
    with torch.inference_mode(), torch.autocast("cpu", dtype=torch.bfloat16):
        out = model(x)
    if temporal:  # Video Depth Anything: fp32, autocast off; the result returns to the autocast dtype
        assert seen == [(torch.bfloat16, "conv1"), (torch.float32, False)] and out.dtype == torch.bfloat16
    else:  # Depth Anything V2's head has no such override upstream
        assert seen == [(torch.bfloat16, "conv1"), (torch.bfloat16, True)]


# -- the exact backend fills the new fields and reads a video decoded up to some time -----------------

def test_ground_truth_backend_confidence_background_times_and_a_cut_decode(tmp_path):
    from rigidbench.perception.gt import GroundTruthBackend, WorldState, state_path, static_background

    sample, frames = tiny_perception.synthetic_sample(n_frames=8)
    times = np.arange(8) / 24.0
    affine, flow = static_background(8)
    depth = np.full((8, 48, 64), 2.0, np.float32)
    WorldState(times_s=times, masks=sample.masks[:, sample.active_indices], depth_m=depth,
               tracks=sample.tracks["tracks"], visibility=sample.tracks["visibility"], bg_affine=affine,
               bg_flow=flow).save(state_path(tmp_path / "gen.mp4"))
    backend = GroundTruthBackend()
    p = backend.perceive(sample, Video(frames, times), tmp_path / "gen.mp4")
    np.testing.assert_array_equal(p.confidence, sample.tracks["visibility"].astype(np.float32))
    np.testing.assert_array_equal(p.bg_times_s, times)
    assert np.isin(p.bg_confidence, (0.0, 1.0)).all()
    cut = backend.perceive(sample, Video(frames[:5], times[:5]), tmp_path / "gen.mp4")
    for name in ("times_s", "masks", "tracks", "visibility", "confidence", "disparity", "bg_times_s", "bg_tracks",
                 "bg_confidence"):
        a, b = getattr(cut, name), getattr(p, name)
        np.testing.assert_array_equal(a, b[:, :5] if name in ("tracks", "visibility", "confidence", "bg_tracks",
                                                               "bg_confidence") else b[:5])
    ref = reference_times(5, 24.0)
    np.testing.assert_array_equal(cut.aligned(ref).bg_confidence, p.aligned(ref).bg_confidence)
    p.save(tmp_path / "p.npz")
    loaded = type(p).load(tmp_path / "p.npz")
    np.testing.assert_array_equal(loaded.confidence, p.confidence)
    np.testing.assert_array_equal(loaded.bg_times_s, p.bg_times_s)
