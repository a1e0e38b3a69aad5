"""LPIPS-AlexNet without torchvision: layout, weight loading and behaviour (random backbone)."""

import sys
import types

import pytest

torch = pytest.importorskip("torch")

from rigidbench.metrics import lpips_net  # noqa: E402
from rigidbench.metrics.lpips_net import LPIPSAlex, alexnet_features, build_lpips_alex, load_lin_weights  # noqa: E402

# torchvision.models.alexnet().features.state_dict(), written out by hand.
TORCHVISION_ALEXNET_FEATURES = {
    "0.weight": (64, 3, 11, 11), "0.bias": (64,),
    "3.weight": (192, 64, 5, 5), "3.bias": (192,),
    "6.weight": (384, 192, 3, 3), "6.bias": (384,),
    "8.weight": (256, 384, 3, 3), "8.bias": (256,),
    "10.weight": (256, 256, 3, 3), "10.bias": (256,),
}


def lin_file_or_skip():
    try:
        return lpips_net.default_lin_weights_path()
    except FileNotFoundError as err:
        pytest.skip(str(err))


def test_features_have_torchvision_keys_and_shapes():
    feats = alexnet_features()
    assert {k: tuple(v.shape) for k, v in feats.state_dict().items()} == TORCHVISION_ALEXNET_FEATURES
    kinds = [type(m).__name__ for m in feats]
    assert kinds == ["Conv2d", "ReLU", "MaxPool2d", "Conv2d", "ReLU", "MaxPool2d", "Conv2d", "ReLU",
                     "Conv2d", "ReLU", "Conv2d", "ReLU", "MaxPool2d"]
    assert (feats[0].stride, feats[0].padding, feats[2].kernel_size, feats[2].stride) == ((4, 4), (2, 2), 3, 2)


def test_model_state_dict_is_backbone_plus_lin_layers():
    keys = set(LPIPSAlex().state_dict())
    expected = {f"features.{k}" for k in TORCHVISION_ALEXNET_FEATURES}
    expected |= {f"lin{k}.model.1.weight" for k in range(5)}
    assert keys == expected


def test_lin_weights_load_with_strict_keys():
    path = lin_file_or_skip()
    model = build_lpips_alex(random_backbone=True)
    stored = torch.load(path, map_location="cpu", weights_only=True)
    for k in range(5):
        assert torch.equal(getattr(model, f"lin{k}").model[1].weight, stored[f"lin{k}.model.1.weight"])


def test_lin_weights_with_wrong_keys_are_refused(tmp_path):
    bad = tmp_path / "bad.pth"
    torch.save({"lin0.weight": torch.zeros(1, 64, 1, 1)}, bad)
    with pytest.raises(KeyError, match="lin0.model.1.weight"):
        load_lin_weights(LPIPSAlex(), bad)


def test_identical_images_give_zero_and_output_shape():
    lin_file_or_skip()
    torch.manual_seed(0)
    model = build_lpips_alex(random_backbone=True)
    x = torch.rand(3, 3, 64, 96) * 2 - 1
    y = torch.rand(3, 3, 64, 96) * 2 - 1
    with torch.no_grad():
        same = model(x, x.clone())
        diff = model(x, y)
    assert same.shape == (3,)
    assert torch.all(same.abs() < 1e-7)
    assert torch.all(diff > 0)


def test_backbone_loads_from_a_local_checkpoint(tmp_path):
    lin_file_or_skip()
    torch.manual_seed(1)
    source = alexnet_features()
    state = {f"features.{k}": v for k, v in source.state_dict().items()}
    state["classifier.1.weight"] = torch.zeros(4096, 9216)  # present in torchvision's file, ignored
    path = tmp_path / "alexnet-owt-7be5be79.pth"
    torch.save(state, path)
    model = build_lpips_alex(backbone_weights=path)
    assert torch.equal(model.features[10].weight, source[10].weight)
    assert not any(p.requires_grad for p in model.parameters())


def test_missing_backbone_names_where_it_looked(tmp_path, monkeypatch):
    lin_file_or_skip()
    monkeypatch.setattr(torch.hub, "get_dir", lambda: str(tmp_path / "hub"))
    with pytest.raises(FileNotFoundError) as err:
        build_lpips_alex(allow_download=False)
    message = str(err.value)
    assert str(tmp_path / "hub" / "checkpoints" / "alexnet-owt-7be5be79.pth") in message
    assert "download.pytorch.org/models/alexnet-owt-7be5be79.pth" in message


def test_matches_the_lpips_package_with_the_same_backbone(monkeypatch):
    """Run lpips.LPIPS with a stub torchvision that hands it our (random) AlexNet features."""
    lin_file_or_skip()
    torch.manual_seed(2)
    ours = build_lpips_alex(random_backbone=True)
    shared = ours.features

    stub = types.ModuleType("torchvision")
    stub.models = types.SimpleNamespace(alexnet=lambda pretrained=False, **_: types.SimpleNamespace(features=shared))
    monkeypatch.setitem(sys.modules, "torchvision", stub)
    for name in [m for m in sys.modules if m == "lpips" or m.startswith("lpips.")]:
        monkeypatch.delitem(sys.modules, name)
    try:
        lpips = pytest.importorskip("lpips")
        theirs = lpips.LPIPS(net="alex", version="0.1", verbose=False)
    finally:  # do not leave an lpips bound to the stub behind for other tests
        for name in [m for m in sys.modules if m == "lpips" or m.startswith("lpips.")]:
            sys.modules.pop(name)
    x = torch.rand(2, 3, 80, 112) * 2 - 1
    y = torch.rand(2, 3, 80, 112) * 2 - 1
    with torch.no_grad():
        expected = theirs(x, y).reshape(-1)
        got = ours(x, y)
    torch.testing.assert_close(got, expected, rtol=1e-5, atol=1e-7)
