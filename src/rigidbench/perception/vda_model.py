"""Video Depth Anything as plain torch modules (Chen et al. 2025), laid out so the official
checkpoints (``video_depth_anything_vit{s,b,l}.pth``) load with strict key matching.

Two parts, named as in the checkpoint:

- ``pretrained``: a DINOv2 ViT with patch size 14 in the torch-hub layout (``patch_embed.proj``,
  ``cls_token``, ``pos_embed`` for a 518 px grid, ``mask_token``, ``blocks.N.{norm1,attn.qkv,
  attn.proj,ls1.gamma,norm2,mlp.fc1,mlp.fc2,ls2.gamma}``, final ``norm``).
- ``head``: a DPT head (``projects``, ``resize_layers``, ``scratch.layerK_rn``,
  ``scratch.refinenetK``, ``scratch.output_conv{1,2}``) with four temporal-attention motion
  modules (``motion_modules.0..3``, AnimateDiff style) on the two coarsest reassembled maps and
  on the two coarsest fusion outputs.

``DepthAnythingV2`` is the per-image parent model from the same code base: the same encoder and
DPT head without motion modules, named ``pretrained`` and ``depth_head`` as in
``depth_anything_v2_vit{s,b,l}.pth``.

Shapes in the docstrings: N = batch * frames, T = frames, C = channels, h, w = token grid.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import nn


@dataclass(frozen=True)
class VDAConfig:
    """Architecture hyper-parameters; the defaults are the ViT-L release."""

    embed_dim: int = 1024
    depth: int = 24
    num_heads: int = 16
    mlp_ratio: float = 4.0
    patch_size: int = 14
    img_size: int = 518  # pos_embed grid the encoder was trained at: (518 / 14)^2 + 1 = 1370 tokens
    layer_idx: tuple[int, ...] = (4, 11, 17, 23)
    features: int = 256
    out_channels: tuple[int, int, int, int] = (256, 512, 1024, 1024)
    num_frames: int = 32  # temporal positional-encoding length, i.e. the inference window
    motion_heads: int = 8
    norm_groups: int = 32
    interpolate_offset: float = 0.1


ENCODER_CONFIGS = {
    "vits": dict(embed_dim=384, depth=12, num_heads=6, layer_idx=(2, 5, 8, 11), features=64,
                 out_channels=(48, 96, 192, 384)),
    "vitb": dict(embed_dim=768, depth=12, num_heads=12, layer_idx=(2, 5, 8, 11), features=128,
                 out_channels=(96, 192, 384, 768)),
    "vitl": dict(embed_dim=1024, depth=24, num_heads=16, layer_idx=(4, 11, 17, 23), features=256,
                 out_channels=(256, 512, 1024, 1024)),
}


# ---------------------------------------------------------------------------------------------
# DINOv2 encoder (torch-hub parameter names)
# ---------------------------------------------------------------------------------------------

class PatchEmbed(nn.Module):
    """(N,3,H,W) -> (N, H/p * W/p, D) by a strided convolution named ``proj``."""

    def __init__(self, patch_size: int, embed_dim: int):
        super().__init__()
        self.proj = nn.Conv2d(3, embed_dim, kernel_size=patch_size, stride=patch_size)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.proj(x).flatten(2).transpose(1, 2)


class SelfAttention(nn.Module):
    """Multi-head self-attention with a fused ``qkv`` projection; (N,L,D) -> (N,L,D)."""

    def __init__(self, dim: int, num_heads: int):
        super().__init__()
        self.num_heads = num_heads
        self.qkv = nn.Linear(dim, 3 * dim, bias=True)
        self.proj = nn.Linear(dim, dim, bias=True)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        n, length, dim = x.shape
        q, k, v = self.qkv(x).view(n, length, 3, self.num_heads, dim // self.num_heads).permute(2, 0, 3, 1, 4)
        out = F.scaled_dot_product_attention(q, k, v)
        return self.proj(out.transpose(1, 2).reshape(n, length, dim))


class FeedForwardGELU(nn.Module):
    """Two-layer MLP ``fc1`` -> exact GELU -> ``fc2``."""

    def __init__(self, dim: int, hidden: int):
        super().__init__()
        self.fc1 = nn.Linear(dim, hidden)
        self.fc2 = nn.Linear(hidden, dim)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.fc2(F.gelu(self.fc1(x)))


class LayerScale(nn.Module):
    """Per-channel residual scale ``gamma``."""

    def __init__(self, dim: int):
        super().__init__()
        self.gamma = nn.Parameter(torch.ones(dim))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return x * self.gamma


class EncoderBlock(nn.Module):
    """Pre-norm transformer block with layer scale (DINOv2)."""

    def __init__(self, dim: int, num_heads: int, mlp_ratio: float):
        super().__init__()
        self.norm1 = nn.LayerNorm(dim, eps=1e-6)
        self.attn = SelfAttention(dim, num_heads)
        self.ls1 = LayerScale(dim)
        self.norm2 = nn.LayerNorm(dim, eps=1e-6)
        self.mlp = FeedForwardGELU(dim, int(dim * mlp_ratio))
        self.ls2 = LayerScale(dim)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        x = x + self.ls1(self.attn(self.norm1(x)))
        return x + self.ls2(self.mlp(self.norm2(x)))


class DinoV2Encoder(nn.Module):
    """DINOv2 ViT; ``intermediate(x, idx)`` returns the normed patch tokens of the chosen blocks."""

    def __init__(self, cfg: VDAConfig):
        super().__init__()
        dim = cfg.embed_dim
        self.patch_size = cfg.patch_size
        self.interpolate_offset = cfg.interpolate_offset
        grid = cfg.img_size // cfg.patch_size
        self.patch_embed = PatchEmbed(cfg.patch_size, dim)
        self.cls_token = nn.Parameter(torch.zeros(1, 1, dim))
        self.pos_embed = nn.Parameter(torch.zeros(1, grid * grid + 1, dim))
        self.mask_token = nn.Parameter(torch.zeros(1, dim))  # unused at inference; part of the checkpoint
        self.blocks = nn.ModuleList(EncoderBlock(dim, cfg.num_heads, cfg.mlp_ratio) for _ in range(cfg.depth))
        self.norm = nn.LayerNorm(dim, eps=1e-6)

    def position_embedding(self, rows: int, cols: int, dtype: torch.dtype) -> torch.Tensor:
        """Trained pos_embed resampled (bicubic) to a rows x cols token grid. Returns (1, 1+rows*cols, D)."""
        n_trained = self.pos_embed.shape[1] - 1
        if rows * cols == n_trained and rows == cols:
            return self.pos_embed.to(dtype)
        side = int(math.sqrt(n_trained))
        table = self.pos_embed.float()
        patch = table[:, 1:].reshape(1, side, side, -1).permute(0, 3, 1, 2)
        # The released weights were used with a scale factor (not a target size) nudged by a small
        # offset, which changes the sampling positions slightly; reproduce it for parity.
        scale = ((rows + self.interpolate_offset) / side, (cols + self.interpolate_offset) / side)
        patch = F.interpolate(patch, scale_factor=scale, mode="bicubic", antialias=False)
        if patch.shape[-2:] != (rows, cols):
            raise ValueError(f"position grid {tuple(patch.shape[-2:])} != token grid {(rows, cols)}")
        patch = patch.permute(0, 2, 3, 1).reshape(1, rows * cols, -1)
        return torch.cat([table[:, :1], patch], dim=1).to(dtype)

    def intermediate(self, x: torch.Tensor, layer_idx: tuple[int, ...]) -> list[torch.Tensor]:
        """x: (N,3,H,W) normalised, H and W multiples of the patch size. Returns [(N, h*w, D)] per index."""
        rows, cols = x.shape[-2] // self.patch_size, x.shape[-1] // self.patch_size
        tokens = self.patch_embed(x)
        # no cast: under autocast the fp32 class token promotes the residual stream to fp32, as upstream
        tokens = torch.cat([self.cls_token.expand(tokens.shape[0], -1, -1), tokens], dim=1)
        tokens = tokens + self.position_embedding(rows, cols, tokens.dtype)
        wanted = set(layer_idx)
        outputs = []
        for i, block in enumerate(self.blocks[: max(layer_idx) + 1]):
            tokens = block(tokens)
            if i in wanted:
                outputs.append(self.norm(tokens)[:, 1:])
        return outputs


# ---------------------------------------------------------------------------------------------
# Temporal motion module (AnimateDiff-style attention along time at every spatial position)
# ---------------------------------------------------------------------------------------------

def sinusoid_table(length: int, dim: int) -> torch.Tensor:
    """Fixed sin (even channels) / cos (odd channels) positions. Returns (1, length, dim) float32."""
    position = torch.arange(length, dtype=torch.float32)[:, None]
    freq = torch.exp(torch.arange(0, dim, 2, dtype=torch.float32) * (-math.log(10000.0) / dim))
    table = torch.zeros(1, length, dim)
    table[0, :, 0::2] = torch.sin(position * freq)
    table[0, :, 1::2] = torch.cos(position * freq)
    return table


class SinusoidalPositions(nn.Module):
    """Adds the fixed positional table ``pe`` (a persistent buffer, stored in the checkpoint)."""

    def __init__(self, dim: int, max_len: int):
        super().__init__()
        self.register_buffer("pe", sinusoid_table(max_len, dim))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if x.shape[1] > self.pe.shape[1]:
            raise ValueError(f"{x.shape[1]} frames exceed the temporal window of {self.pe.shape[1]}")
        return x + self.pe[:, : x.shape[1]].to(x.dtype)


class TemporalAttention(nn.Module):
    """Self-attention over frames: (B*S, T, C) -> (B*S, T, C), S spatial positions."""

    def __init__(self, dim: int, heads: int, max_len: int):
        super().__init__()
        self.heads = heads
        self.to_q = nn.Linear(dim, dim, bias=False)
        self.to_k = nn.Linear(dim, dim, bias=False)
        self.to_v = nn.Linear(dim, dim, bias=False)
        self.to_out = nn.ModuleList([nn.Linear(dim, dim), nn.Dropout(0.0)])
        self.pos_encoder = SinusoidalPositions(dim, max_len)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        x = self.pos_encoder(x)
        n, length, dim = x.shape

        def split(t: torch.Tensor) -> torch.Tensor:
            return t.view(n, length, self.heads, dim // self.heads).transpose(1, 2)

        out = F.scaled_dot_product_attention(split(self.to_q(x)), split(self.to_k(x)), split(self.to_v(x)))
        return self.to_out[0](out.transpose(1, 2).reshape(n, length, dim))


class GatedGELU(nn.Module):
    """GEGLU: ``proj`` to 2*hidden, value * gelu(gate)."""

    def __init__(self, dim: int, hidden: int):
        super().__init__()
        self.proj = nn.Linear(dim, 2 * hidden)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        value, gate = self.proj(x).chunk(2, dim=-1)
        return value * F.gelu(gate)


class GatedFeedForward(nn.Module):
    """``net`` = [GEGLU(dim -> 4 dim), dropout, Linear(4 dim -> dim)]."""

    def __init__(self, dim: int, mult: int = 4):
        super().__init__()
        self.net = nn.ModuleList([GatedGELU(dim, mult * dim), nn.Dropout(0.0), nn.Linear(mult * dim, dim)])

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        for layer in self.net:
            x = layer(x)
        return x


class TemporalBlock(nn.Module):
    """Two pre-norm temporal attentions then a GEGLU feed-forward, all residual."""

    def __init__(self, dim: int, heads: int, max_len: int, n_attention: int = 2):
        super().__init__()
        self.attention_blocks = nn.ModuleList(TemporalAttention(dim, heads, max_len) for _ in range(n_attention))
        self.norms = nn.ModuleList(nn.LayerNorm(dim) for _ in range(n_attention))
        self.ff = GatedFeedForward(dim)
        self.ff_norm = nn.LayerNorm(dim)

    def forward(self, x: torch.Tensor, frames: int) -> torch.Tensor:
        """x: (B*T, S, C) tokens of every frame."""
        bt, s, c = x.shape
        b = bt // frames
        for attention, norm in zip(self.attention_blocks, self.norms):
            y = norm(x).view(b, frames, s, c).transpose(1, 2).reshape(b * s, frames, c)
            y = attention(y).view(b, s, frames, c).transpose(1, 2).reshape(bt, s, c)
            x = x + y
        return x + self.ff(self.ff_norm(x))


class TemporalTransformer(nn.Module):
    """GroupNorm -> proj_in -> temporal blocks -> proj_out, plus the input as residual."""

    def __init__(self, channels: int, heads: int, max_len: int, norm_groups: int, n_blocks: int = 1):
        super().__init__()
        self.norm = nn.GroupNorm(norm_groups, channels, eps=1e-6, affine=True)
        self.proj_in = nn.Linear(channels, channels)
        self.transformer_blocks = nn.ModuleList(TemporalBlock(channels, heads, max_len) for _ in range(n_blocks))
        self.proj_out = nn.Linear(channels, channels)

    def forward(self, x: torch.Tensor, frames: int) -> torch.Tensor:
        """x: (B*T, C, h, w) frame-major within each clip. Returns the same shape."""
        bt, c, h, w = x.shape
        y = self.proj_in(self.norm(x).permute(0, 2, 3, 1).reshape(bt, h * w, c))
        for block in self.transformer_blocks:
            y = block(y, frames)
        y = self.proj_out(y).view(bt, h, w, c).permute(0, 3, 1, 2)
        return x + y


class MotionModule(nn.Module):
    """Named wrapper (``temporal_transformer``) as in the checkpoint."""

    def __init__(self, channels: int, heads: int, max_len: int, norm_groups: int):
        super().__init__()
        self.temporal_transformer = TemporalTransformer(channels, heads, max_len, norm_groups)

    def forward(self, x: torch.Tensor, frames: int) -> torch.Tensor:
        return self.temporal_transformer(x, frames)


# ---------------------------------------------------------------------------------------------
# DPT head
# ---------------------------------------------------------------------------------------------

class ResidualConvUnit(nn.Module):
    """x + conv2(relu(conv1(relu(x)))), 3x3 convolutions with bias."""

    def __init__(self, features: int):
        super().__init__()
        self.conv1 = nn.Conv2d(features, features, 3, padding=1)
        self.conv2 = nn.Conv2d(features, features, 3, padding=1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return x + self.conv2(F.relu(self.conv1(F.relu(x))))


class FusionBlock(nn.Module):
    """Fuse a coarser path with a skip map, refine, upsample (bilinear, corners aligned), 1x1 conv."""

    def __init__(self, features: int):
        super().__init__()
        self.out_conv = nn.Conv2d(features, features, 1)
        self.resConfUnit1 = ResidualConvUnit(features)
        self.resConfUnit2 = ResidualConvUnit(features)

    def forward(self, x: torch.Tensor, skip: torch.Tensor | None = None,
                size: tuple[int, int] | None = None) -> torch.Tensor:
        if skip is not None:
            x = x + self.resConfUnit1(skip)
        x = self.resConfUnit2(x)
        if size is None:
            x = F.interpolate(x, scale_factor=2, mode="bilinear", align_corners=True)
        else:
            x = F.interpolate(x, size=size, mode="bilinear", align_corners=True)
        return self.out_conv(x)


class Scratch(nn.Module):
    """The DPT 'scratch' container: per-level 3x3 projections, fusion blocks and the output convs."""

    def __init__(self, out_channels: tuple[int, ...], features: int):
        super().__init__()
        self.layer1_rn = nn.Conv2d(out_channels[0], features, 3, padding=1, bias=False)
        self.layer2_rn = nn.Conv2d(out_channels[1], features, 3, padding=1, bias=False)
        self.layer3_rn = nn.Conv2d(out_channels[2], features, 3, padding=1, bias=False)
        self.layer4_rn = nn.Conv2d(out_channels[3], features, 3, padding=1, bias=False)
        self.refinenet1 = FusionBlock(features)
        self.refinenet2 = FusionBlock(features)
        self.refinenet3 = FusionBlock(features)
        self.refinenet4 = FusionBlock(features)
        self.output_conv1 = nn.Conv2d(features, features // 2, 3, padding=1)
        self.output_conv2 = nn.Sequential(
            nn.Conv2d(features // 2, 32, 3, padding=1), nn.ReLU(),
            nn.Conv2d(32, 1, 1), nn.ReLU(), nn.Identity())


class DPTHead(nn.Module):
    """Four encoder token maps -> one relative-disparity map per frame; ``temporal`` adds the motion modules."""

    def __init__(self, cfg: VDAConfig, temporal: bool = True):
        super().__init__()
        self.temporal = temporal
        oc, feat = cfg.out_channels, cfg.features
        self.projects = nn.ModuleList(nn.Conv2d(cfg.embed_dim, c, 1) for c in oc)
        self.resize_layers = nn.ModuleList([
            nn.ConvTranspose2d(oc[0], oc[0], kernel_size=4, stride=4),
            nn.ConvTranspose2d(oc[1], oc[1], kernel_size=2, stride=2),
            nn.Identity(),
            nn.Conv2d(oc[3], oc[3], kernel_size=3, stride=2, padding=1),
        ])
        self.scratch = Scratch(oc, feat)
        if temporal:
            mm = dict(heads=cfg.motion_heads, max_len=cfg.num_frames, norm_groups=cfg.norm_groups)
            self.motion_modules = nn.ModuleList([
                MotionModule(oc[2], **mm), MotionModule(oc[3], **mm), MotionModule(feat, **mm), MotionModule(feat, **mm)])
        self.patch_size = cfg.patch_size

    def _over_time(self, i: int, x: torch.Tensor, frames: int) -> torch.Tensor:
        return self.motion_modules[i](x, frames) if self.temporal else x

    def forward(self, tokens: list[torch.Tensor], rows: int, cols: int, frames: int) -> torch.Tensor:
        """tokens: 4 x (B*T, rows*cols, D). Returns (B*T, 1, rows*p, cols*p) non-negative."""
        maps = []
        for i, t in enumerate(tokens):
            x = t.transpose(1, 2).reshape(t.shape[0], t.shape[2], rows, cols)
            maps.append(self.resize_layers[i](self.projects[i](x)))
        l1, l2, l3, l4 = maps
        s = self.scratch
        l3 = self._over_time(0, l3, frames)
        l4 = self._over_time(1, l4, frames)
        r1, r2, r3, r4 = s.layer1_rn(l1), s.layer2_rn(l2), s.layer3_rn(l3), s.layer4_rn(l4)
        path = self._over_time(2, s.refinenet4(r4, size=r3.shape[2:]), frames)
        path = self._over_time(3, s.refinenet3(path, r3, size=r2.shape[2:]), frames)
        path = s.refinenet2(path, r2, size=r1.shape[2:])
        path = s.refinenet1(path, r1)
        out = F.interpolate(s.output_conv1(path), (rows * self.patch_size, cols * self.patch_size),
                            mode="bilinear", align_corners=True)
        if not self.temporal:  # Depth Anything V2's head (dpt.py): no precision override
            return s.output_conv2(out)
        # Video Depth Anything (dpt_temporal.py): the last output convolution runs in float32 with
        # autocast off, and its result goes back to the dtype it came in (fp16 under autocast).
        dtype = out.dtype
        with torch.autocast(device_type=out.device.type, enabled=False):
            out = s.output_conv2(out.float())
        return out.to(dtype)


class VideoDepthAnything(nn.Module):
    """DINOv2 encoder + temporal DPT head. forward: (B,T,3,H,W) normalised -> (B,T,H,W) disparity >= 0."""

    def __init__(self, cfg: VDAConfig):
        super().__init__()
        self.config = cfg
        self.pretrained = DinoV2Encoder(cfg)
        self.head = DPTHead(cfg, temporal=True)

    def forward(self, x: torch.Tensor, encoder_batch: int | None = None) -> torch.Tensor:
        b, t, _, h, w = x.shape
        if t > self.config.num_frames:
            raise ValueError(f"{t} frames exceed the model's temporal window of {self.config.num_frames}")
        flat = x.flatten(0, 1)
        step = encoder_batch or flat.shape[0]
        chunks = [self.pretrained.intermediate(flat[i:i + step], self.config.layer_idx)
                  for i in range(0, flat.shape[0], step)]
        tokens = [torch.cat(level, dim=0) for level in zip(*chunks)]
        p = self.config.patch_size
        disparity = self.head(tokens, h // p, w // p, t)
        disparity = F.relu(F.interpolate(disparity, size=(h, w), mode="bilinear", align_corners=True))
        return disparity.squeeze(1).unflatten(0, (b, t))


class DepthAnythingV2(nn.Module):
    """Depth Anything V2 in its original layout (``pretrained`` + ``depth_head``), for ``depth_anything_v2_vit*.pth``.

    forward: (N,3,H,W) normalised, H and W multiples of 14 -> (N,H,W) relative disparity >= 0.
    """

    def __init__(self, cfg: VDAConfig):
        super().__init__()
        self.config = cfg
        self.pretrained = DinoV2Encoder(cfg)
        self.depth_head = DPTHead(cfg, temporal=False)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        p = self.config.patch_size
        tokens = self.pretrained.intermediate(x, self.config.layer_idx)
        return F.relu(self.depth_head(tokens, x.shape[-2] // p, x.shape[-1] // p, 1)).squeeze(1)
