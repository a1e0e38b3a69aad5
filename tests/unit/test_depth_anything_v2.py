"""Depth Anything V2 per-frame fallback on a tiny random transformers model."""

import numpy as np
import pytest

torch = pytest.importorskip("torch")
transformers = pytest.importorskip("transformers")

from rigidbench.perception.depth_anything_v2 import (DAV2_CHECKPOINT_REPO, DAV2_ENV, DAV2_FILENAME,  # noqa: E402
                                                     DAV2_MODEL, build_depth_anything_v2, frame_disparity,
                                                     load_depth_anything_v2)
from rigidbench.perception.features import WeightsUnavailable  # noqa: E402


pytestmark = pytest.mark.usefixtures("torch_one_thread")


def tiny_model(seed=0):
    torch.manual_seed(seed)
    backbone = transformers.Dinov2Config(hidden_size=32, num_hidden_layers=4, num_attention_heads=2,
                                         intermediate_size=64, image_size=70, patch_size=14,
                                         out_features=["stage1", "stage2", "stage3", "stage4"],
                                         reshape_hidden_states=False)
    config = transformers.DepthAnythingConfig(backbone_config=backbone, patch_size=14, reassemble_hidden_size=32,
                                              neck_hidden_sizes=[8, 16, 32, 32], fusion_hidden_size=16,
                                              head_hidden_size=8)
    model = transformers.DepthAnythingForDepthEstimation(config).eval()
    with torch.no_grad():
        model.head.conv3.bias.fill_(0.5)  # keep the random model's output away from the ReLU floor
    return model


def frames_of(n, seed=0):
    return np.random.default_rng(seed).integers(0, 256, (n, 36, 64, 3), dtype=np.uint8)


def test_shape_dtype_range_and_batching_independence():
    model = tiny_model()
    frames = frames_of(5)
    out = frame_disparity(model, frames, input_size=28, batch_size=2)
    assert out.shape == (5, 36, 64) and out.dtype == np.float32
    assert np.isfinite(out).all() and (out >= 0).all() and out.max() > 0
    np.testing.assert_allclose(frame_disparity(model, frames, input_size=28, batch_size=8), out, rtol=1e-5, atol=1e-6)
    # frames are independent: the third frame alone gives the same map
    np.testing.assert_allclose(frame_disparity(model, frames[2:3], input_size=28), out[2:3], rtol=1e-5, atol=1e-6)


def test_constant_head_gives_that_disparity_at_frame_size():
    model = tiny_model()
    with torch.no_grad():
        model.head.conv3.weight.zero_()
        model.head.conv3.bias.fill_(1.25)
    np.testing.assert_allclose(frame_disparity(model, frames_of(3), input_size=28), 1.25, rtol=1e-6)


def test_load_from_a_folder_given_directly_or_by_env(tmp_path, monkeypatch):
    model = tiny_model(1)
    model.save_pretrained(tmp_path)
    frames = frames_of(2, seed=3)
    want = frame_disparity(model, frames, input_size=28)
    loaded = load_depth_anything_v2(tmp_path)
    assert not loaded.training
    np.testing.assert_allclose(frame_disparity(loaded, frames, input_size=28), want, rtol=1e-6)
    monkeypatch.setenv(DAV2_ENV, str(tmp_path))
    np.testing.assert_allclose(frame_disparity(load_depth_anything_v2(), frames, input_size=28), want, rtol=1e-6)


def test_missing_weights_raise_a_helpful_error(tmp_path, monkeypatch):
    with pytest.raises(WeightsUnavailable) as err:
        load_depth_anything_v2(tmp_path / "absent")
    assert str(tmp_path / "absent") in str(err.value) and DAV2_ENV in str(err.value) and DAV2_MODEL in str(err.value)
    monkeypatch.setenv(DAV2_ENV, str(tmp_path))  # exists, but holds no model
    with pytest.raises(WeightsUnavailable, match=DAV2_ENV):
        load_depth_anything_v2()


def test_rejects_frames_that_are_not_uint8_rgb():
    with pytest.raises(ValueError, match="uint8"):
        frame_disparity(tiny_model(), np.zeros((2, 36, 64, 3), np.float32), input_size=28)


# --- the original checkpoint layout (depth_anything_v2_vitl.pth) -------------------------------

TINY = dict(embed_dim=32, depth=4, num_heads=2, layer_idx=(0, 1, 2, 3), features=16, out_channels=(16, 16, 32, 32),
            img_size=70, norm_groups=8)


def test_original_layout_keys_and_shapes():
    """Upstream DepthAnythingV2 = torch-hub DINOv2 'pretrained' + non-temporal DPTHead 'depth_head'."""
    shapes = {k: tuple(v.shape) for k, v in build_depth_anything_v2("vitl", device="meta").state_dict().items()}
    assert len(shapes) == 343 + 64
    assert sum(k.startswith("pretrained.") for k in shapes) == 343
    assert sum(k.startswith("depth_head.") for k in shapes) == 64
    assert not any("motion_modules" in k for k in shapes)
    assert shapes["pretrained.pos_embed"] == (1, 1370, 1024)
    assert shapes["pretrained.blocks.23.mlp.fc2.weight"] == (1024, 4096)
    assert shapes["depth_head.projects.1.weight"] == (512, 1024, 1, 1)
    assert shapes["depth_head.resize_layers.0.weight"] == (256, 256, 4, 4)
    assert shapes["depth_head.resize_layers.3.weight"] == (1024, 1024, 3, 3)
    assert shapes["depth_head.scratch.layer4_rn.weight"] == (256, 1024, 3, 3)
    assert shapes["depth_head.scratch.refinenet4.resConfUnit1.conv1.weight"] == (256, 256, 3, 3)
    assert shapes["depth_head.scratch.output_conv2.2.weight"] == (1, 32, 1, 1)


def test_original_checkpoint_round_trips_via_file_folder_env_and_cache(tmp_path, monkeypatch):
    monkeypatch.delenv(DAV2_ENV, raising=False)
    torch.manual_seed(2)
    model = build_depth_anything_v2(**TINY)
    with torch.no_grad():
        model.depth_head.scratch.output_conv2[2].bias.fill_(0.5)
    folder = tmp_path / "ckpt"
    folder.mkdir()
    torch.save(model.state_dict(), folder / DAV2_FILENAME)
    frames = frames_of(3, seed=5)
    want = frame_disparity(model, frames, input_size=28)
    assert want.shape == (3, 36, 64) and want.dtype == np.float32 and want.max() > 0
    for source in (folder / DAV2_FILENAME, folder):
        np.testing.assert_array_equal(frame_disparity(load_depth_anything_v2(source, **TINY), frames, input_size=28),
                                      want)
    monkeypatch.setenv(DAV2_ENV, str(folder))
    np.testing.assert_array_equal(frame_disparity(load_depth_anything_v2(**TINY), frames, input_size=28), want)
    monkeypatch.delenv(DAV2_ENV)
    cache = tmp_path / "hub"
    repo = cache / ("models--" + DAV2_CHECKPOINT_REPO.replace("/", "--"))
    (repo / "refs").mkdir(parents=True)
    (repo / "refs" / "main").write_text("feed")
    (repo / "snapshots" / "feed").mkdir(parents=True)
    (folder / DAV2_FILENAME).rename(repo / "snapshots" / "feed" / DAV2_FILENAME)
    loaded = load_depth_anything_v2(cache_dir=cache, **TINY)
    np.testing.assert_array_equal(frame_disparity(loaded, frames, input_size=28), want)
    with pytest.raises(WeightsUnavailable, match=DAV2_CHECKPOINT_REPO):
        load_depth_anything_v2(cache_dir=tmp_path / "empty-hub", **TINY)


def to_transformers_names(state):
    """Rename an original-layout Depth Anything V2 state dict to transformers' names (4-layer tiny model)."""
    out = {}
    for key, value in state.items():
        if key.startswith("pretrained.blocks."):
            i, rest = key[len("pretrained.blocks."):].split(".", 1)
            e = f"backbone.encoder.layer.{i}."
            if rest.startswith("attn.qkv."):
                part = rest.rsplit(".", 1)[1]
                for name, chunk in zip(("q_proj", "k_proj", "v_proj"), value.chunk(3, dim=0)):
                    out[e + f"attention.{name}.{part}"] = chunk
                continue
            rest = rest.replace("attn.proj", "attention.o_proj").replace("ls1.gamma", "layer_scale1.lambda1")
            out[e + rest.replace("ls2.gamma", "layer_scale2.lambda1")] = value
            continue
        renames = [("pretrained.cls_token", "backbone.embeddings.cls_token"),
                   ("pretrained.mask_token", "backbone.embeddings.mask_token"),
                   ("pretrained.pos_embed", "backbone.embeddings.position_embeddings"),
                   ("pretrained.patch_embed.proj", "backbone.embeddings.patch_embeddings.projection"),
                   ("pretrained.norm", "backbone.layernorm"),
                   ("depth_head.projects.", "neck.reassemble_stage.layers.{}.projection"),
                   ("depth_head.resize_layers.", "neck.reassemble_stage.layers.{}.resize"),
                   ("depth_head.scratch.output_conv1", "head.conv1"),
                   ("depth_head.scratch.output_conv2.0", "head.conv2"),
                   ("depth_head.scratch.output_conv2.2", "head.conv3")]
        for old, new in renames:
            if key.startswith(old):
                rest = key[len(old):]
                if "{}" in new:
                    i, rest = rest.split(".", 1)
                    new, rest = new.format(i), "." + rest
                out[new + rest] = value
                break
        else:
            level = key.split("scratch.")[1]
            if level.startswith("layer"):  # layerK_rn -> convs.K-1
                out[f"neck.convs.{int(level[5]) - 1}.weight"] = value
            else:  # refinenetK -> fusion_stage.layers.4-K (transformers runs the fusion coarse to fine)
                k, rest = int(level[9]), level[11:]
                rest = rest.replace("resConfUnit", "residual_layer").replace("conv1", "convolution1")
                rest = rest.replace("conv2", "convolution2").replace("out_conv", "projection")
                out[f"neck.fusion_stage.layers.{4 - k}.{rest}"] = value
    return out


def test_original_layout_matches_the_transformers_implementation():
    """Our encoder + DPT head against transformers' independent DepthAnythingForDepthEstimation."""
    torch.manual_seed(3)
    ours = build_depth_anything_v2(**TINY)
    with torch.no_grad():
        for p in ours.parameters():
            p.normal_(0, 0.2)
        ours.depth_head.scratch.output_conv2[2].bias.fill_(1.0)
    backbone = transformers.Dinov2Config(hidden_size=32, num_hidden_layers=4, num_attention_heads=2, mlp_ratio=4,
                                         image_size=70, patch_size=14, layer_norm_eps=1e-6,
                                         out_features=["stage1", "stage2", "stage3", "stage4"],
                                         reshape_hidden_states=False)
    config = transformers.DepthAnythingConfig(backbone_config=backbone, patch_size=14, reassemble_hidden_size=32,
                                              neck_hidden_sizes=[16, 16, 32, 32], fusion_hidden_size=16,
                                              head_hidden_size=32)
    ref = transformers.DepthAnythingForDepthEstimation(config).eval()
    ref.load_state_dict(to_transformers_names(ours.state_dict()), strict=True)
    x = torch.randn(2, 3, 70, 70, generator=torch.Generator().manual_seed(6), dtype=torch.float64)
    with torch.no_grad():  # float64, so only a different computation (not rounding) can show
        got, want = ours.double()(x), ref.double()(pixel_values=x).predicted_depth
    assert got.shape == want.shape == (2, 70, 70)
    assert want.abs().max() > 0.1
    torch.testing.assert_close(got, want, rtol=1e-9, atol=1e-9)
