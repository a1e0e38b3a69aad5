"""LPIPS v0.1 with an AlexNet backbone, without torchvision.

The layout reproduces `lpips.LPIPS(net="alex", version="0.1")`: a fixed scaling layer
(shift [-.030, -.088, -.188], scale [.458, .448, .450]) on inputs in [-1, 1], AlexNet
`features` with torchvision's module indices (so torchvision's checkpoint keys load
directly), taps after the five ReLUs, unit normalisation over channels (eps 1e-10), squared
differences, 1x1 linear layers `lin{k}.model.1.weight` (no bias, Dropout at index 0 as in
lpips), spatial averaging and a sum over taps.

Weights: the linear layers come from the lpips package's `weights/v0.1/alex.pth` (found
without importing lpips, whose import needs torchvision); the backbone comes from an
explicit file, the torch hub cache (`<hub dir>/checkpoints/alexnet-owt-7be5be79.pth`), or a
download of torchvision's checkpoint when allowed.
"""

from __future__ import annotations

import importlib.util
import logging
from pathlib import Path

import torch
from torch import nn

log = logging.getLogger(__name__)

ALEXNET_URL = "https://download.pytorch.org/models/alexnet-owt-7be5be79.pth"
ALEXNET_FILENAME = "alexnet-owt-7be5be79.pth"
TAP_CHANNELS = (64, 192, 384, 256, 256)
#: Index in `features` of the ReLU after which each LPIPS tap is taken.
TAP_LAYERS = (1, 4, 7, 9, 11)


def alexnet_features() -> nn.Sequential:
    """Returns torchvision's AlexNet `features` stack (indices 0-12), randomly initialised."""
    return nn.Sequential(
        nn.Conv2d(3, 64, kernel_size=11, stride=4, padding=2),  # 0
        nn.ReLU(),  # 1
        nn.MaxPool2d(kernel_size=3, stride=2),  # 2
        nn.Conv2d(64, 192, kernel_size=5, padding=2),  # 3
        nn.ReLU(),  # 4
        nn.MaxPool2d(kernel_size=3, stride=2),  # 5
        nn.Conv2d(192, 384, kernel_size=3, padding=1),  # 6
        nn.ReLU(),  # 7
        nn.Conv2d(384, 256, kernel_size=3, padding=1),  # 8
        nn.ReLU(),  # 9
        nn.Conv2d(256, 256, kernel_size=3, padding=1),  # 10
        nn.ReLU(),  # 11
        nn.MaxPool2d(kernel_size=3, stride=2),  # 12, unused by LPIPS; kept for the layout
    )


class NetLinLayer(nn.Module):
    """Dropout then a bias-free 1x1 convolution to one channel, as lpips names it (`model.1.weight`)."""

    def __init__(self, channels: int) -> None:
        super().__init__()
        self.model = nn.Sequential(nn.Dropout(), nn.Conv2d(channels, 1, kernel_size=1, bias=False))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.model(x)


class LPIPSAlex(nn.Module):
    """LPIPS-AlexNet distance: forward(x, y) with x, y (B, 3, H, W) in [-1, 1] returns (B,)."""

    def __init__(self) -> None:
        super().__init__()
        self.register_buffer("shift", torch.tensor([-0.030, -0.088, -0.188]).view(1, 3, 1, 1), persistent=False)
        self.register_buffer("scale", torch.tensor([0.458, 0.448, 0.450]).view(1, 3, 1, 1), persistent=False)
        self.features = alexnet_features()
        for k, ch in enumerate(TAP_CHANNELS):
            self.add_module(f"lin{k}", NetLinLayer(ch))

    def taps(self, x: torch.Tensor) -> list[torch.Tensor]:
        """x: (B, 3, H, W) in [-1, 1]. Returns the five unit-normalised ReLU activations."""
        h = (x - self.shift) / self.scale
        out = []
        for i, layer in enumerate(self.features[: TAP_LAYERS[-1] + 1]):
            h = layer(h)
            if i in TAP_LAYERS:
                norm = torch.sqrt(torch.sum(h * h, dim=1, keepdim=True))
                out.append(h / (norm + 1e-10))
        return out

    def forward(self, x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
        total = 0.0
        for k, (fx, fy) in enumerate(zip(self.taps(x), self.taps(y))):
            lin = getattr(self, f"lin{k}")
            total = total + lin((fx - fy) ** 2).mean(dim=(2, 3), keepdim=True)
        return total.reshape(x.shape[0])


def default_lin_weights_path() -> Path:
    """Returns the path of lpips's `weights/v0.1/alex.pth`; raises FileNotFoundError if lpips is absent."""
    spec = importlib.util.find_spec("lpips")
    if spec is None or not spec.submodule_search_locations:
        raise FileNotFoundError("the lpips package is not installed, so its linear-layer weights "
                                "weights/v0.1/alex.pth are missing; run `pip install --no-deps lpips` "
                                "or pass lin_weights=PATH")
    path = Path(next(iter(spec.submodule_search_locations))) / "weights" / "v0.1" / "alex.pth"
    if not path.is_file():
        raise FileNotFoundError(f"LPIPS linear-layer weights not found at {path}; reinstall lpips "
                                "or pass lin_weights=PATH")
    return path


def load_lin_weights(model: LPIPSAlex, path: str | Path | None = None) -> None:
    """Load lin0..lin4 from an lpips v0.1 `alex.pth`, requiring exactly the keys `lin{k}.model.1.weight`."""
    path = Path(path) if path is not None else default_lin_weights_path()
    state = torch.load(path, map_location="cpu", weights_only=True)
    expected = {f"lin{k}.model.1.weight" for k in range(len(TAP_CHANNELS))}
    if set(state) != expected:
        raise KeyError(f"{path} holds keys {sorted(state)}, expected exactly {sorted(expected)}; "
                       "is it an LPIPS v0.1 AlexNet weight file?")
    own = {k: v for k, v in model.state_dict().items() if k in expected}
    for key in expected:
        if state[key].shape != own[key].shape:
            raise ValueError(f"{path}: {key} has shape {tuple(state[key].shape)}, "
                             f"expected {tuple(own[key].shape)}")
    model.load_state_dict(state, strict=False)


def hub_alexnet_path() -> Path:
    """Returns where torch hub caches torchvision's AlexNet checkpoint."""
    return Path(torch.hub.get_dir()) / "checkpoints" / ALEXNET_FILENAME


def load_backbone_state(path: str | Path | None = None, allow_download: bool = True) -> dict:
    """Returns AlexNet `features.*` weights from `path`, the torch hub cache, or (if allowed) a download."""
    if path is not None:
        path = Path(path)
        if not path.is_file():
            raise FileNotFoundError(f"AlexNet backbone weights not found at {path}")
        state = torch.load(path, map_location="cpu", weights_only=True)
    elif hub_alexnet_path().is_file():
        state = torch.load(hub_alexnet_path(), map_location="cpu", weights_only=True)
    elif allow_download:
        try:
            state = torch.hub.load_state_dict_from_url(ALEXNET_URL, map_location="cpu", progress=False)
        except OSError as err:  # URLError and connection failures are OSErrors
            raise FileNotFoundError(_missing_backbone_message()) from err
    else:
        raise FileNotFoundError(_missing_backbone_message())
    features = {k: v for k, v in state.items() if k.startswith("features.")}
    if not features:
        raise KeyError(f"no 'features.*' keys in the AlexNet checkpoint (keys: {sorted(state)[:5]}...); "
                       "expected torchvision's alexnet-owt-7be5be79.pth")
    return features


def _missing_backbone_message() -> str:
    return (f"AlexNet backbone weights for LPIPS were not found: looked in {hub_alexnet_path()} "
            f"(torch hub cache; set TORCH_HOME to move it) and could not download {ALEXNET_URL}. "
            f"Fetch that file on a machine with network access and copy it to {hub_alexnet_path()}, "
            "or pass backbone_weights=PATH")


def build_lpips_alex(backbone_weights: str | Path | None = None, lin_weights: str | Path | None = None,
                     allow_download: bool = True, random_backbone: bool = False) -> LPIPSAlex:
    """Returns an eval-mode, gradient-free LPIPSAlex with lpips v0.1 linear weights and AlexNet
    ImageNet weights (or a random backbone when `random_backbone`, for tests and benchmarks)."""
    model = LPIPSAlex()
    load_lin_weights(model, lin_weights)
    if random_backbone:
        log.warning("LPIPS AlexNet backbone is randomly initialised; scores are not comparable to LPIPS")
    else:
        backbone = load_backbone_state(backbone_weights, allow_download)
        model.features.load_state_dict({k.removeprefix("features."): v for k, v in backbone.items()}, strict=True)
    model.eval()
    model.requires_grad_(False)
    return model
