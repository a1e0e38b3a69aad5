"""DiffSynth-Studio's sampling numerics for ``wan-2.2`` (its options ``timestep_dtype`` and ``vae_codec``;
``recipe=release`` sets them with ``update_dtype``, whose step is ``wan_sampler.diffsynth_euler_step``).
Imported only when a Wan pipeline is configured.

The authors' release generated with DiffSynth-Studio 2.0.18's ``WanVideoPipeline`` in bfloat16 with
``tiled=True`` and the pipeline's defaults. Besides the schedule (``wan_sampler``), it differs from
diffusers' ``WanImageToVideoPipeline`` in three places, each reproduced here on diffusers' modules:

- **Timestep.** Each scheduler timestep is cast to the pipeline's dtype before the model
  (``timestep.unsqueeze(0).to(dtype=self.torch_dtype)``): in bfloat16, whose steps are 4 between 512
  and 1024, 995.93 reaches the time embedding as 996. ``round_timesteps`` rounds the ``timestep``
  argument of every transformer call to bfloat16 (kept in its own dtype; the first slot's tokens stay 0).
- **Tiled VAE.** ``WanVideoVAE38.encode`` / ``decode`` with ``tiled=True``, ``tile_size`` (30, 52) and
  ``tile_stride`` (15, 26), counted in latent cells (16 pixels each). The tiles start at 0, stride,
  2 x stride, ... along each axis, a start being dropped when the tile before it already reaches the
  edge (``tile_starts``); the last tile is cut at the edge. Each tile is encoded or decoded whole (every
  frame), weighted by a mask that ramps linearly, (1 .. b) / b, over the b = size - stride cells (in
  the output's units) of each side that borders another tile and is 1 elsewhere (the minimum of the row
  and column ramps), accumulated on the CPU in the input's dtype (bfloat16 for the bfloat16
  pipeline), and divided by the summed masks; the decoded video is then clamped to [-1, 1].
  ``tiled_decode`` reproduces the decode; ``TiledEncoder`` the encode of the first frame (the TI2V
  pinned latent), which diffusers' pipeline calls through ``vae.encode``.
- **Frames.** DiffSynth turns the decoded video into 8-bit frames as ``((x + 1) * 127.5).clip(0, 255)``
  in the video's dtype, then ``.to(uint8)``, which truncates (``diffsynth_to_uint8``); our default
  rounds x / 2 + 0.5 in float32 times 255 to the nearest integer.

Two differences remain: diffusers' VAE clamps each decoded tile to [-1, 1] before blending (DiffSynth
clamps after blending, so the two differ only where a tile overshoots [-1, 1] in a blended border),
and the encoded tiles are blended before the per-channel latent normalisation (DiffSynth: after;
equal but for rounding).
"""

from __future__ import annotations

import types

import numpy as np
import torch

TILE_SIZE = (30, 52)    # latent cells (rows, columns): WanVideoPipeline.__call__'s tile_size default
TILE_STRIDE = (15, 26)  # its tile_stride default


def tile_starts(length: int, size: int, stride: int) -> list[int]:
    """DiffSynth's tile starts along one axis: 0, stride, 2 stride, ..., leaving out a start whose preceding
    tile already reaches ``length``."""
    return [s for s in range(0, length, stride) if not (s - stride >= 0 and s - stride + size >= length)]


def ramp(length: int, first: bool, last: bool, border: int) -> torch.Tensor:
    """(length,) float32: 1, ramping (1 .. border) / border up from a side that borders another tile
    (not ``first`` / not ``last``) over ``border`` entries."""
    x = torch.ones(length)
    up = (torch.arange(border) + 1) / border
    if not first:
        x[:border] = up
    if not last:
        x[-border:] = torch.flip(up, dims=(0,))
    return x


def tile_mask(shape, bounds, border, dtype) -> torch.Tensor:
    """(1, 1, 1, H, W) mask of a tile of output ``shape`` (..., H, W); ``bounds`` = (top edge, bottom
    edge, left edge, right edge) of the whole; ``border`` = (rows, columns) of ramp."""
    h = ramp(shape[-2], bounds[0], bounds[1], border[0])
    w = ramp(shape[-1], bounds[2], bounds[3], border[1])
    return torch.minimum(h[:, None], w[None, :])[None, None, None].to(dtype)


def blend_tiles(x: torch.Tensor, code, size, stride, scale: float, out_channels: int, out_frames: int,
                out_dtype) -> torch.Tensor:
    """DiffSynth's tiled encode / decode of ``x`` (1, C, T, H, W): ``code(tile)`` maps an input tile to its
    output; output cells are ``scale`` input cells (16 for the decode, 1/16 for the encode). The blend
    runs on the CPU in ``out_dtype``."""
    _, _, _, height, width = x.shape
    out_h, out_w = round(height * scale), round(width * scale)
    values = torch.zeros((1, out_channels, out_frames, out_h, out_w), dtype=out_dtype)
    weight = torch.zeros((1, 1, out_frames, out_h, out_w), dtype=out_dtype)
    border = (round((size[0] - stride[0]) * scale), round((size[1] - stride[1]) * scale))
    for top in tile_starts(height, size[0], stride[0]):
        for left in tile_starts(width, size[1], stride[1]):
            bottom, right = top + size[0], left + size[1]
            out = code(x[:, :, :, top:bottom, left:right]).to("cpu", out_dtype)
            mask = tile_mask(out.shape, (top == 0, bottom >= height, left == 0, right >= width), border, out_dtype)
            rows = slice(round(top * scale), round(top * scale) + out.shape[-2])
            cols = slice(round(left * scale), round(left * scale) + out.shape[-1])
            values[:, :, :, rows, cols] += out * mask
            weight[:, :, :, rows, cols] += mask
    return values / weight


def _execution_device(module) -> torch.device:
    """Where ``module``'s inputs must be: its offload hook's execution device, else its weights' device."""
    try:
        from diffusers.utils.torch_utils import get_module_execution_device
    except ImportError:  # diffusers before the helper
        for sub in module.modules():
            device = getattr(getattr(sub, "_hf_hook", None), "execution_device", None)
            if device is not None:
                return torch.device(device)
        return next(module.parameters()).device
    return get_module_execution_device(module)


@torch.no_grad()
def tiled_decode(vae, latents: torch.Tensor, size=TILE_SIZE, stride=TILE_STRIDE) -> torch.Tensor:
    """(1, 3, 4T-3, 16H, 16W) video in [-1, 1] from un-normalised latents (1, C, T, H, W), decoded in
    DiffSynth's tiles by ``vae.decode`` (each tile untiled) and blended in the latents' dtype."""
    device = _execution_device(vae)
    factor = vae.config.scale_factor_spatial

    def decode(tile):
        return vae.decode(tile.to(device, vae.dtype), return_dict=False)[0]

    frames = 4 * latents.shape[2] - 3
    return blend_tiles(latents.to("cpu"), decode, size, stride, factor, 3, frames, latents.dtype).clamp_(-1, 1)


class TiledEncoder:
    """Stands in for ``vae.encode`` while installed (``install`` / ``remove``): DiffSynth's tiled encode of
    the pipeline's first frame (tile size and stride in latent cells, as DiffSynth takes them), returning
    the blended latent modes where diffusers' ``retrieve_latents`` looks for ``latents``."""

    def __init__(self, vae, size=TILE_SIZE, stride=TILE_STRIDE):
        self.vae, self.size, self.stride = vae, size, stride

    @torch.no_grad()
    def __call__(self, video: torch.Tensor, return_dict: bool = True):
        vae, factor = self.vae, self.vae.config.scale_factor_spatial
        encode = type(vae).encode  # the class's own (offload hooks included), one tile at a time

        def code(tile):
            return encode(vae, tile.to(video.device), return_dict=True).latent_dist.mode()

        frames = (video.shape[2] + 3) // 4
        size = (self.size[0] * factor, self.size[1] * factor)
        stride = (self.stride[0] * factor, self.stride[1] * factor)
        latents = blend_tiles(video.to("cpu"), code, size, stride, 1 / factor, vae.config.z_dim, frames,
                              video.dtype).to(video.device)
        return types.SimpleNamespace(latents=latents) if return_dict else (latents,)

    @classmethod
    def install(cls, vae, **kwargs) -> "TiledEncoder":
        encoder = cls(vae, **kwargs)
        vae.encode = encoder  # an instance attribute: the class's encode is back after ``remove``
        return encoder

    @staticmethod
    def remove(vae) -> None:
        if isinstance(vae.__dict__.get("encode"), TiledEncoder):
            del vae.encode


def diffsynth_to_uint8(video: torch.Tensor) -> np.ndarray:
    """(T, H, W, 3) uint8 frames from a decoded (1, 3, T, H, W) video in [-1, 1], as DiffSynth's
    ``vae_output_to_video``: ``((x + 1) * 127.5).clip(0, 255)`` in the video's dtype, truncated to uint8."""
    frames = ((video[0] + 1) * 127.5).clip(0, 255).to(torch.uint8)
    return frames.permute(1, 2, 3, 0).cpu().numpy()


def _rounded_timestep(module, args, kwargs):
    timestep = kwargs.get("timestep")
    if timestep is None:
        return None
    return args, {**kwargs, "timestep": timestep.to(torch.bfloat16).to(timestep.dtype)}


def round_timesteps(transformer):
    """Round the ``timestep`` of every call of ``transformer`` to bfloat16 (a forward pre-hook); returns the
    hook's handle (``.remove()``)."""
    return transformer.register_forward_pre_hook(_rounded_timestep, with_kwargs=True)
