"""DINOv2 ViT-L/14 identity features for IdDrift (paper, appendix B.2).

Weights load with ``transformers`` from the ``path`` argument, the directory in
``RIGIDBENCH_DINOV2``, or the Hugging Face cache (``facebook/dinov2-large``), in that order (see
``perception.weights``); by default no download is attempted, so an offline machine gets a clear
message instead of a network error. IdDrift feeds the network batches of 256 patches.

Run as the published evaluation ran the torch-hub ``dinov2_vitl14`` (RigidBench release,
``eval/score/identity.py``, ``embed_patches``):

- precision: float32 weights under ``torch.autocast(dtype=bfloat16)`` on CUDA (not weights cast to
  bf16: layer norms and the position-embedding interpolation stay float32); float32 on CPU;
- position embeddings: the 37 x 37 grid pretrained at 518 px is resampled to the 16 x 16 grid of a
  224 px input the way torch-hub DINOv2 does (``dinov2/models/vision_transformer.py``,
  ``interpolate_pos_encoding``: bicubic in float32, no antialiasing, ``scale_factor=(16 + 0.1) / 37``),
  not the way ``transformers``' ``Dinov2Embeddings`` does (``size=(16, 16)``, i.e. a scale of
  16 / 37): the two sample the pretrained grid at slightly different places
  (``hub_position_embeddings`` below; the tests compare both).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable

from ..errors import MissingExtra, WeightsUnavailable
from ..extras import available, require
from . import weights
from .device import inference_dtype, resolve_device

DINOV2_MODEL = "facebook/dinov2-large"
DINOV2_ENV = "RIGIDBENCH_DINOV2"
#: torch-hub DINOv2's ``interpolate_offset`` (``dinov2/hub/backbones.py``): added to the target grid
#: size before it is turned into a scale factor ("historical kludge" kept for backward compatibility)
HUB_INTERPOLATE_OFFSET = 0.1


def hub_position_embeddings(position_embeddings, patch_size: int, height: int, width: int, dtype=None):
    """Position embeddings (1, 1+M*M, D) pretrained on an M x M grid, resampled for a height x width
    input as torch-hub DINOv2's ``interpolate_pos_encoding`` does. Returns (1, 1+h0*w0, D) in ``dtype``
    (default: the embeddings' dtype), h0, w0 = height // patch_size, width // patch_size."""
    import math

    import torch
    import torch.nn.functional as F

    dtype = position_embeddings.dtype if dtype is None else dtype
    n = position_embeddings.shape[1] - 1
    h0, w0 = height // patch_size, width // patch_size
    if h0 * w0 == n and height == width:
        return position_embeddings.to(dtype)
    table = position_embeddings.float()
    m = int(math.sqrt(n))
    if m * m != n:
        raise ValueError(f"position embeddings hold {n} patches, not a square grid")
    dim = table.shape[-1]
    grid = F.interpolate(table[:, 1:].reshape(1, m, m, dim).permute(0, 3, 1, 2), mode="bicubic", antialias=False,
                         scale_factor=((h0 + HUB_INTERPOLATE_OFFSET) / m, (w0 + HUB_INTERPOLATE_OFFSET) / m))
    if tuple(grid.shape[-2:]) != (h0, w0):
        raise ValueError(f"resampled position grid is {tuple(grid.shape[-2:])}, expected {(h0, w0)}")
    grid = grid.permute(0, 2, 3, 1).reshape(1, h0 * w0, dim)
    return torch.cat((table[:, :1], grid), dim=1).to(dtype)


def use_hub_position_interpolation(model):
    """Make a ``transformers`` ``Dinov2Model`` resample its position embeddings as torch-hub DINOv2
    does (``hub_position_embeddings``), in place. Returns the model."""
    import types

    embeddings = model.embeddings
    patch = embeddings.patch_embeddings.patch_size
    patch = patch[0] if isinstance(patch, (tuple, list)) else int(patch)

    def interpolate_pos_encoding(self, tokens, height: int, width: int):
        # hub: computed in float32 and cast to the dtype of the tokens it is added to
        return hub_position_embeddings(self.position_embeddings, patch, height, width, dtype=tokens.dtype)

    embeddings.interpolate_pos_encoding = types.MethodType(interpolate_pos_encoding, embeddings)
    return model


def load_dinov2(path: str | None = None, allow_download: bool = False):
    """Returns the pretrained ``Dinov2Model`` (float32, CPU) from ``path``, $RIGIDBENCH_DINOV2 or the cache.
    The weights are looked for before ``transformers`` is imported (5 s), so their absence costs nothing."""
    if weights.locate("dinov2", path) is None and not allow_download:
        raise WeightsUnavailable(weights.missing_message("dinov2", path))
    transformers = require("transformers", "IdDrift (DINOv2 identity features)")
    return weights.load_pretrained(transformers.Dinov2Model, "dinov2", path, allow_download)


def load_identity_features(device: str | None = None, path: str | None = None, allow_download: bool = False,
                           model=None) -> Callable:
    """Return f: (B,3,224,224) ImageNet-normalised float -> (B,D) float32 DINOv2 CLS features.

    ``device`` None picks CUDA when available. The weights stay float32; on CUDA the forward runs
    under bf16 autocast (the published runs' setting), on the CPU in float32. The position
    embeddings are resampled as torch-hub DINOv2 does. ``model`` may be a ready ``Dinov2Model``
    (tests pass a tiny one).
    """
    if model is None:
        model = load_dinov2(path, allow_download)  # raises before any import when the weights are absent
    import contextlib

    import torch

    device = resolve_device(device)
    amp = inference_dtype("dinov2", device)
    model = use_hub_position_interpolation(model.to(device=device, dtype=torch.float32).eval())
    device_type = torch.device(device).type

    @torch.no_grad()
    def features(x: "torch.Tensor") -> "torch.Tensor":
        x = x.to(device=device, dtype=torch.float32)
        if amp == torch.float32:
            precision = contextlib.nullcontext()
        else:  # upstream hands the network a bf16 batch under autocast; the patch conv rounds it the same way
            x = x.to(amp)
            precision = torch.autocast(device_type=device_type, dtype=amp)
        with precision:
            out = model(pixel_values=x)
        return out.pooler_output.float()

    features.parameters = model.parameters  # lets IdDrift prepare patches on the model's device
    return features


# -- the feature networks of the metrics (LPIPS-AlexNet and DINOv2), loaded once per run ------------


@dataclass
class FeatureNets:
    """The learned feature networks the metrics use; a missing one skips its measurement with a reason."""

    lpips: Callable | None = None
    identity: Callable | None = None
    skipped: dict[str, str] = field(default_factory=dict)
    device: str = "cpu"

    @property
    def key(self) -> str:
        """What the scores depend on: which networks are present."""
        return nets_key(self.lpips is not None, self.identity is not None)


def nets_key(lpips: bool, identity: bool) -> str:
    """The input-key fragment of a set of feature networks: which of them are present."""
    return f"lpips={'yes' if lpips else 'no'},iddrift={'yes' if identity else 'no'}"


def load_lpips(allow_download: bool = False):
    """LPIPS-AlexNet with the lpips package's linear layers and the AlexNet backbone from $RIGIDBENCH_ALEXNET
    or the torch hub cache; raises WeightsUnavailable naming what is missing (before importing torch)."""
    lin = weights.locate("lpips-lin")
    if lin is None:
        raise WeightsUnavailable(weights.missing_message("lpips-lin"))
    backbone = weights.locate("alexnet")
    if backbone is None and not allow_download:
        raise WeightsUnavailable(weights.missing_message("alexnet"))
    from ..metrics import lpips_net  # torch
    try:
        return lpips_net.build_lpips_alex(backbone_weights=backbone, lin_weights=lin, allow_download=allow_download)
    except (OSError, KeyError, ValueError) as exc:
        raise WeightsUnavailable(f"{weights.missing_message('alexnet')} (loading failed: {exc})") from None


def load_feature_nets(device: str | None = None, allow_download: bool = False) -> FeatureNets:
    """LPIPS-AlexNet and DINOv2-L identity features from local weights (see ``perception.weights``) on
    ``device`` (None: CUDA when available); a network whose weights are absent is skipped with the reason.
    Without any of the weights nothing heavy is imported (torch, transformers): the check comes first."""
    nets = FeatureNets(device=str(device) if device is not None else "cpu")

    def resolved() -> str:  # torch is imported only once a network is actually loaded
        nets.device = resolve_device(device)
        return nets.device

    try:
        net = load_lpips(allow_download)
        nets.lpips = net.to(resolved())
    except (WeightsUnavailable, MissingExtra) as exc:
        nets.skipped["lpips"] = str(exc)
    try:
        model = load_dinov2(weights.locate("dinov2"), allow_download)
        nets.identity = load_identity_features(device=resolved(), model=model)
    except (WeightsUnavailable, MissingExtra) as exc:  # no weights, or no transformers to run them
        nets.skipped["iddrift"] = str(exc)
    return nets


def feature_nets_key() -> str:
    """The ``FeatureNets.key`` that ``load_feature_nets`` would give here, from which weights are present,
    without loading them (a driver whose workers load the networks elsewhere keys examples with it)."""
    return nets_key(weights.locate("lpips-lin") is not None and weights.locate("alexnet") is not None,
                    weights.locate("dinov2") is not None and available("transformers"))
