"""Video Depth Anything: official key layout, weight loading, windowing, stitching and inference.

The expected checkpoint layout below is written out from the upstream code
(DepthAnything/Video-Depth-Anything: video_depth.py, dpt.py, dpt_temporal.py,
motion_module/*.py, dinov2.py and its torch-hub DINOv2 layers), not from our modules.
"""

import math

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from rigidbench.perception.features import WeightsUnavailable  # noqa: E402
from rigidbench.perception.video_depth import (VDA_ENV, VDA_FILENAME, VDA_REPO, affine_fit,  # noqa: E402
                                               build_video_depth_anything, expected_state_dict_shapes,
                                               find_vda_weights, key_slots, load_video_depth_anything,
                                               network_size, preprocess_frames, stitch_windows, video_disparity,
                                               window_output_frames, window_slot_frames)

pytestmark = pytest.mark.usefixtures("torch_one_thread")


TINY = dict(embed_dim=32, depth=4, num_heads=2, layer_idx=(0, 1, 2, 3), features=16, out_channels=(16, 16, 32, 32),
            img_size=70, norm_groups=8)


def official_vitl_layout():
    """Key -> shape of video_depth_anything_vitl.pth as implied by the upstream modules."""
    d, oc, f = 1024, (256, 512, 1024, 1024), 256
    keys = {"pretrained.cls_token": (1, 1, d), "pretrained.pos_embed": (1, 37 * 37 + 1, d),
            "pretrained.mask_token": (1, d), "pretrained.patch_embed.proj.weight": (d, 3, 14, 14),
            "pretrained.patch_embed.proj.bias": (d,), "pretrained.norm.weight": (d,), "pretrained.norm.bias": (d,)}
    for i in range(24):
        b = f"pretrained.blocks.{i}."
        keys.update({b + "norm1.weight": (d,), b + "norm1.bias": (d,), b + "attn.qkv.weight": (3 * d, d),
                     b + "attn.qkv.bias": (3 * d,), b + "attn.proj.weight": (d, d), b + "attn.proj.bias": (d,),
                     b + "ls1.gamma": (d,), b + "norm2.weight": (d,), b + "norm2.bias": (d,),
                     b + "mlp.fc1.weight": (4 * d, d), b + "mlp.fc1.bias": (4 * d,), b + "mlp.fc2.weight": (d, 4 * d),
                     b + "mlp.fc2.bias": (d,), b + "ls2.gamma": (d,)})
    for i, c in enumerate(oc):
        keys.update({f"head.projects.{i}.weight": (c, d, 1, 1), f"head.projects.{i}.bias": (c,),
                     f"head.scratch.layer{i + 1}_rn.weight": (f, c, 3, 3)})
    for i, k in ((0, 4), (1, 2)):  # ConvTranspose2d weights are (in, out, k, k)
        keys.update({f"head.resize_layers.{i}.weight": (oc[i], oc[i], k, k), f"head.resize_layers.{i}.bias": (oc[i],)})
    keys.update({"head.resize_layers.3.weight": (1024, 1024, 3, 3), "head.resize_layers.3.bias": (1024,)})
    for r in range(1, 5):
        p = f"head.scratch.refinenet{r}."
        keys.update({p + "out_conv.weight": (f, f, 1, 1), p + "out_conv.bias": (f,)})
        for u in (1, 2):
            for c in (1, 2):
                unit = p + f"resConfUnit{u}.conv{c}."
                keys.update({unit + "weight": (f, f, 3, 3), unit + "bias": (f,)})
    keys.update({"head.scratch.output_conv1.weight": (128, f, 3, 3), "head.scratch.output_conv1.bias": (128,),
                 "head.scratch.output_conv2.0.weight": (32, 128, 3, 3), "head.scratch.output_conv2.0.bias": (32,),
                 "head.scratch.output_conv2.2.weight": (1, 32, 1, 1), "head.scratch.output_conv2.2.bias": (1,)})
    for m, c in enumerate((oc[2], oc[3], f, f)):
        p = f"head.motion_modules.{m}.temporal_transformer."
        keys.update({p + "norm.weight": (c,), p + "norm.bias": (c,), p + "proj_in.weight": (c, c),
                     p + "proj_in.bias": (c,), p + "proj_out.weight": (c, c), p + "proj_out.bias": (c,)})
        t = p + "transformer_blocks.0."
        for a in (0, 1):
            q = t + f"attention_blocks.{a}."
            keys.update({q + "to_q.weight": (c, c), q + "to_k.weight": (c, c), q + "to_v.weight": (c, c),
                         q + "to_out.0.weight": (c, c), q + "to_out.0.bias": (c,), q + "pos_encoder.pe": (1, 32, c),
                         t + f"norms.{a}.weight": (c,), t + f"norms.{a}.bias": (c,)})
        keys.update({t + "ff.net.0.proj.weight": (8 * c, c), t + "ff.net.0.proj.bias": (8 * c,),
                     t + "ff.net.2.weight": (c, 4 * c), t + "ff.net.2.bias": (c,),
                     t + "ff_norm.weight": (c,), t + "ff_norm.bias": (c,)})
    return keys


# --- layout -----------------------------------------------------------------------------------

def test_real_size_model_has_exactly_the_official_keys_and_shapes():
    expected = official_vitl_layout()
    got = expected_state_dict_shapes("vitl")
    assert sorted(set(got) - set(expected)) == [] and sorted(set(expected) - set(got)) == []
    assert {k: v for k, v in got.items() if v != expected[k]} == {}
    # 343 encoder + 176 head tensors (24 blocks x 14 + 7; DPT 64 + 4 motion modules x 28)
    assert len(got) == 519
    assert sum(k.startswith("pretrained.") for k in got) == 343


def test_meta_build_allocates_nothing():
    model = build_video_depth_anything("vitl", device="meta")
    assert {p.device.type for p in model.parameters()} == {"meta"}
    assert sum(p.numel() for p in model.parameters()) > 380_000_000  # ViT-L 304M + temporal head


def test_temporal_positions_are_the_fixed_sinusoid():
    model = build_video_depth_anything(**TINY)
    pe = model.head.motion_modules[2].temporal_transformer.transformer_blocks[0].attention_blocks[0].pos_encoder.pe
    c = 16
    for t in (0, 1, 31):
        assert pe[0, t, 0].item() == pytest.approx(math.sin(t), abs=1e-6)
        assert pe[0, t, 1].item() == pytest.approx(math.cos(t), abs=1e-6)
        assert pe[0, t, 2].item() == pytest.approx(math.sin(t * 10000 ** (-2 / c)), abs=1e-6)


# --- weights ----------------------------------------------------------------------------------

def tiny_checkpoint(tmp_path, seed=0):
    torch.manual_seed(seed)
    model = build_video_depth_anything(**TINY)
    path = tmp_path / VDA_FILENAME
    torch.save(model.state_dict(), path)
    return model, path


def same_outputs(a, b):
    x = torch.randn(1, 3, 3, 28, 42, generator=torch.Generator().manual_seed(1))
    with torch.no_grad():
        return torch.equal(a(x), b(x))


def test_tiny_checkpoint_round_trips_via_path_folder_and_env(tmp_path, monkeypatch):
    monkeypatch.delenv(VDA_ENV, raising=False)
    model, path = tiny_checkpoint(tmp_path)
    assert find_vda_weights(path) == path
    assert find_vda_weights(tmp_path) == path
    assert same_outputs(model, load_video_depth_anything(path, **TINY))
    monkeypatch.setenv(VDA_ENV, str(tmp_path))
    assert find_vda_weights() == path
    loaded = load_video_depth_anything(**TINY)
    assert same_outputs(model, loaded)
    assert not loaded.training
    assert {p.device.type for p in loaded.parameters()} == {"cpu"}


def test_weights_found_in_a_hugging_face_cache_layout(tmp_path, monkeypatch):
    monkeypatch.delenv(VDA_ENV, raising=False)
    repo = tmp_path / ("models--" + VDA_REPO.replace("/", "--"))
    (repo / "refs").mkdir(parents=True)
    (repo / "refs" / "main").write_text("0123abcd")
    snapshot = repo / "snapshots" / "0123abcd"
    snapshot.mkdir(parents=True)
    model, _ = tiny_checkpoint(snapshot)
    assert find_vda_weights(cache_dir=tmp_path) == snapshot / VDA_FILENAME
    assert same_outputs(model, load_video_depth_anything(cache_dir=tmp_path, **TINY))


def test_strict_loading_rejects_a_checkpoint_with_a_missing_key(tmp_path):
    model, path = tiny_checkpoint(tmp_path)
    state = model.state_dict()
    del state["head.motion_modules.1.temporal_transformer.proj_out.bias"]
    torch.save(state, path)
    with pytest.raises(ValueError, match="proj_out.bias"):
        load_video_depth_anything(path, **TINY)


def test_missing_weights_say_where_we_looked_and_how_to_fetch(tmp_path, monkeypatch):
    monkeypatch.delenv(VDA_ENV, raising=False)
    missing = tmp_path / "nowhere.pth"
    with pytest.raises(WeightsUnavailable) as err:
        load_video_depth_anything(missing)
    message = str(err.value)
    assert str(missing) in message and "rigidbench weights --download vda" in message and VDA_ENV in message
    assert VDA_REPO in message
    monkeypatch.setenv(VDA_ENV, str(tmp_path))  # a folder without the file
    with pytest.raises(WeightsUnavailable, match=str(tmp_path)):
        load_video_depth_anything()
    assert find_vda_weights() is None


# --- preprocessing ----------------------------------------------------------------------------

def test_network_size_by_hand():
    # 1280x704 is wider than 1.78:1: size int(384*1.777/1.818)=375 -> 378; width 1280*378/704=687.3 -> 686
    assert network_size(704, 1280, 384) == (378, 686)
    # 36x64 (1.778:1): height 384 -> 27.4 patches rounds down below 384, so ceil -> 392; width 682.7 -> 686
    assert network_size(36, 64, 384) == (392, 686)
    assert network_size(480, 640, 384) == (392, 518)
    assert network_size(640, 480, 384) == (518, 392)
    assert network_size(704, 1280, 384, cap_aspect=False) == (392, 700)  # width 1280*384/704 = 698.2 -> 700


def test_preprocess_normalises_a_uniform_frame_exactly():
    frames = np.full((2, 36, 64, 3), (255, 0, 128), dtype=np.uint8)
    x = preprocess_frames(frames, (28, 56))
    assert x.shape == (2, 3, 28, 56) and x.dtype == np.float32
    want = (np.array([1.0, 0.0, 128 / 255]) - [0.485, 0.456, 0.406]) / [0.229, 0.224, 0.225]
    np.testing.assert_allclose(x[:, :, 5, 7], np.tile(want, (2, 1)), atol=1e-5)


# --- windowing --------------------------------------------------------------------------------

def test_key_slots_and_the_second_window_by_hand():
    assert key_slots() == (0, 12, 24, 25, 26, 27, 28, 29, 30, 31)
    plan = window_slot_frames(40)
    assert plan.shape == (2, 32)
    np.testing.assert_array_equal(plan[0], np.arange(32))
    np.testing.assert_array_equal(plan[1], [0, 12] + list(range(24, 40)) + [39] * 14)
    np.testing.assert_array_equal(window_slot_frames(1), np.zeros((1, 32), int))


@pytest.mark.parametrize("n_frames", list(range(1, 80)) + [121])
def test_every_frame_is_written_exactly_once_and_blended_frames_exist(n_frames):
    plan = window_slot_frames(n_frames)
    written = window_output_frames(n_frames)
    assert len(written) == len(plan)
    frames = np.concatenate(written)
    frames = frames[frames < n_frames]
    np.testing.assert_array_equal(np.sort(frames), np.arange(n_frames))  # each frame once
    seen = set(written[0].tolist())
    for k in range(1, len(plan)):
        start = 22 * k
        # new slots carry their own frames; slots 2..9 carry frames already written and are cross-faded
        np.testing.assert_array_equal(plan[k][10:], np.minimum(np.arange(start + 10, start + 32), n_frames - 1))
        np.testing.assert_array_equal(written[k], np.arange(start + 10, start + 32))
        assert set(np.arange(start + 2, start + 10).tolist()) <= seen
        np.testing.assert_array_equal(plan[k][2:10], np.minimum(np.arange(start + 2, start + 10), n_frames - 1))
        assert plan[k][0] == 0 and plan[k][1] == start - 10  # first frame and slot 12 of the previous window
        seen |= set(written[k].tolist())


def test_affine_fit_recovers_scale_and_shift():
    p = np.random.default_rng(0).uniform(0, 1, (2, 5, 6))
    assert affine_fit(p, 3 * p + 0.5) == pytest.approx((3.0, 0.5))
    assert affine_fit(np.ones((2, 3)), np.full((2, 3), 4.0)) == (1.0, 0.0)  # degenerate: identity


@pytest.mark.parametrize("n_frames", [1, 20, 32, 33, 40, 54, 55, 100])
def test_stitching_undoes_per_window_scale_and_shift(n_frames):
    """Windows that see the true disparity up to their own positive affine map stitch to the first window's map."""
    rng = np.random.default_rng(n_frames)
    truth = rng.uniform(0.5, 2.0, (n_frames, 4, 5)).astype(np.float32)
    plan = window_slot_frames(n_frames)
    scales, shifts = rng.uniform(0.5, 3.0, len(plan)), rng.uniform(0.0, 1.0, len(plan))
    windows = [truth[slots] * a + b for slots, a, b in zip(plan, scales, shifts)]
    out = stitch_windows(iter(windows), n_frames)
    assert out.shape == (n_frames, 4, 5) and out.dtype == np.float32
    np.testing.assert_allclose(out, truth * scales[0] + shifts[0], rtol=1e-4, atol=1e-4)


# --- inference --------------------------------------------------------------------------------

class FrameIndexModel(torch.nn.Module):
    """Fake VDA: for uniform frames whose grey level is the frame index, predicts index + 1 everywhere."""

    def __init__(self):
        super().__init__()
        self.config = type("Config", (), {"num_frames": 32})()
        self.dummy = torch.nn.Parameter(torch.zeros(()))
        self.calls = []

    def forward(self, x, encoder_batch=None):
        grey = (x[:, :, 0] * 0.229 + 0.485) * 255  # undo the ImageNet normalisation of the red channel
        self.calls.append(grey[0, :, 0, 0].round().long().tolist())
        return grey + 1 + self.dummy


def test_video_disparity_feeds_the_planned_frames_and_stitches_them_back():
    n = 40
    frames = np.repeat(np.arange(n, dtype=np.uint8)[:, None, None, None], 3, axis=3) * np.ones((1, 9, 16, 3), np.uint8)
    model = FrameIndexModel()
    out = video_disparity(model, frames, input_size=28)
    assert model.calls == [list(range(32)), [0, 12] + list(range(24, 40)) + [39] * 14]
    np.testing.assert_allclose(out, np.broadcast_to(np.arange(1, n + 1, dtype=np.float32)[:, None, None], (n, 9, 16)),
                               atol=2e-3)


@pytest.fixture(scope="module")
def tiny_model():
    torch.manual_seed(0)
    return build_video_depth_anything(**TINY)


@pytest.mark.parametrize("n_frames", [1, 5, 40])
def test_video_disparity_shape_dtype_and_range(tiny_model, n_frames):
    frames = np.random.default_rng(n_frames).integers(0, 256, (n_frames, 36, 64, 3), dtype=np.uint8)
    out = video_disparity(tiny_model, frames, input_size=28)
    assert out.shape == (n_frames, 36, 64) and out.dtype == np.float32
    assert np.isfinite(out).all() and (out >= 0).all()


def test_constant_output_head_gives_that_disparity_everywhere():
    torch.manual_seed(0)
    model = build_video_depth_anything(**TINY)
    last = model.head.scratch.output_conv2[2]
    with torch.no_grad():
        last.weight.zero_()
        last.bias.fill_(0.7)
    frames = np.random.default_rng(2).integers(0, 256, (40, 36, 64, 3), dtype=np.uint8)
    np.testing.assert_allclose(video_disparity(model, frames, input_size=28), 0.7, rtol=1e-6)
    with torch.no_grad():
        last.bias.fill_(-0.3)  # the final ReLUs clamp negative disparity to zero
    assert (video_disparity(model, frames[:3], input_size=28) == 0).all()


def test_clips_in_a_batch_do_not_interact(tiny_model):
    x = torch.randn(2, 4, 3, 28, 56, generator=torch.Generator().manual_seed(3))
    y = x.clone()
    y[1] += 1.0
    with torch.no_grad():
        a, b = tiny_model(x), tiny_model(y)
    assert a.shape == (2, 4, 28, 56)
    torch.testing.assert_close(a[0], b[0])


def test_motion_module_attends_along_time_only():
    """Without its per-frame GroupNorm, a motion module mixes a pixel only with the same pixel in other frames."""
    torch.manual_seed(0)
    module = build_video_depth_anything(**TINY).head.motion_modules[2]
    module.temporal_transformer.norm = torch.nn.Identity()
    with torch.no_grad():
        module.temporal_transformer.proj_out.weight.normal_()
        frames, c, h, w = 5, 16, 3, 4
        x = torch.randn(frames, c, h, w)
        y = x.clone()
        y[2, :, 1, 1] += 5.0
        changed = (module(x, frames) - module(y, frames)).abs().amax(dim=1) > 1e-6  # (T, h, w)
    expected = torch.zeros(frames, h, w, dtype=torch.bool)
    expected[:, 1, 1] = True
    assert torch.equal(changed, expected)


def test_encoder_matches_transformers_dinov2():
    """Our torch-hub-layout DINOv2 against the independent transformers implementation on its trained grid."""
    transformers = pytest.importorskip("transformers")
    torch.manual_seed(0)
    ours = build_video_depth_anything(**TINY).pretrained
    with torch.no_grad():
        for p in ours.parameters():
            p.normal_(0, 0.2)
    cfg = transformers.Dinov2Config(hidden_size=32, num_hidden_layers=4, num_attention_heads=2, mlp_ratio=4,
                                    image_size=70, patch_size=14, layer_norm_eps=1e-6)
    ref = transformers.Dinov2Model(cfg).eval()
    s = ours.state_dict()
    mapped = {"embeddings.cls_token": s["cls_token"], "embeddings.mask_token": s["mask_token"],
              "embeddings.position_embeddings": s["pos_embed"],
              "embeddings.patch_embeddings.projection.weight": s["patch_embed.proj.weight"],
              "embeddings.patch_embeddings.projection.bias": s["patch_embed.proj.bias"],
              "layernorm.weight": s["norm.weight"], "layernorm.bias": s["norm.bias"]}
    for i in range(4):
        b, e = f"blocks.{i}.", f"encoder.layer.{i}."
        for part in ("weight", "bias"):
            qkv = s[b + f"attn.qkv.{part}"].chunk(3, dim=0)
            mapped.update({e + f"attention.q_proj.{part}": qkv[0], e + f"attention.k_proj.{part}": qkv[1],
                           e + f"attention.v_proj.{part}": qkv[2],
                           e + f"attention.o_proj.{part}": s[b + f"attn.proj.{part}"]})
            for name in ("norm1", "norm2", "mlp.fc1", "mlp.fc2"):
                mapped[e + f"{name}.{part}"] = s[b + f"{name}.{part}"]
        mapped[e + "layer_scale1.lambda1"] = s[b + "ls1.gamma"]
        mapped[e + "layer_scale2.lambda1"] = s[b + "ls2.gamma"]
    ref.load_state_dict(mapped, strict=True)
    x = torch.randn(2, 3, 70, 70, generator=torch.Generator().manual_seed(4), dtype=torch.float64)
    with torch.no_grad():  # float64, so only a different computation (not rounding) can show
        got = ours.double().intermediate(x, (1, 3))
        hidden = ref.double()(pixel_values=x, output_hidden_states=True).hidden_states
        want = [ref.layernorm(hidden[i + 1])[:, 1:] for i in (1, 3)]
    for g, w in zip(got, want):
        torch.testing.assert_close(g, w, rtol=1e-9, atol=1e-9)


def test_position_embedding_resamples_to_any_token_grid(tiny_model):
    enc = tiny_model.pretrained
    assert torch.equal(enc.position_embedding(5, 5, torch.float32), enc.pos_embed)
    table = enc.position_embedding(2, 4, torch.float32)
    assert table.shape == (1, 1 + 2 * 4, 32)
    assert torch.equal(table[:, 0], enc.pos_embed[:, 0])
