"""CNN tri-plane generator of SplatFields (supplementary B.2): fixed noise -> one feature plane.

Plain-torch re-implementation of the reference ``VarTriPlaneEncoder`` / ``TimeVAEDecoder`` (a
diffusers-style VAE decoder); no mmcv / mmgen / diffusers.

Per plane (paper defaults): fixed noise [1, 8, 20, 20] -> conv3×3 8→32 -> self-attention -> ResNet
block (20×20×32) -> 4 up blocks of 2 ResNet blocks each, blocks 0..2 followed by nearest ×2 +
conv3×3 (20→40→80→160) -> GN -> SiLU -> conv3×3 32→16: a 16×160×160 plane.

Parameter count per plane (measured, ``tests/test_fields.py``): 206 672 with the paper's mid block
(attention + 1 ResNet block), 225 296 with ``ref_extra_mid_resnet=True`` (the reference's
ResNet→Attn→ResNet mid block; matches the hand count 225 296 of the reference notes §1.5).
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import Tensor, nn


def _gn(channels: int, groups: int) -> nn.GroupNorm:
    return nn.GroupNorm(groups, channels, eps=1e-6)  # diffusers default eps


class ResnetBlock2D(nn.Module):
    """x + conv(SiLU(GN(conv(SiLU(GN(x)))))): two 3×3 convs, identity skip (in = out channels).

    The second conv is zero-initialised so the block starts as the identity (reference
    ``zero_init_residual``).
    """

    def __init__(self, channels: int, norm_groups: int = 32) -> None:
        super().__init__()
        self.norm1 = _gn(channels, norm_groups)
        self.conv1 = nn.Conv2d(channels, channels, 3, padding=1)
        self.norm2 = _gn(channels, norm_groups)
        self.conv2 = nn.Conv2d(channels, channels, 3, padding=1)
        nn.init.zeros_(self.conv2.weight)
        nn.init.zeros_(self.conv2.bias)

    def forward(self, x: Tensor) -> Tensor:
        """x [B, C, H, W] -> [B, C, H, W]."""
        h = self.conv1(F.silu(self.norm1(x)))
        h = self.conv2(F.silu(self.norm2(h)))  # dropout(0) of the reference omitted
        return x + h


class SelfAttention2D(nn.Module):
    """Single-head spatial self-attention with a residual: x + proj(softmax(q kᵀ/√C) v).

    GroupNorm before the q/k/v projections (linear over channels, one token per pixel); the output
    projection is zero-initialised, so the layer starts as the identity.
    """

    def __init__(self, channels: int, norm_groups: int = 32) -> None:
        super().__init__()
        self.norm = _gn(channels, norm_groups)
        self.to_q = nn.Linear(channels, channels)
        self.to_k = nn.Linear(channels, channels)
        self.to_v = nn.Linear(channels, channels)
        self.proj_out = nn.Linear(channels, channels)
        nn.init.zeros_(self.proj_out.weight)
        nn.init.zeros_(self.proj_out.bias)

    def forward(self, x: Tensor) -> Tensor:
        """x [B, C, H, W] -> [B, C, H, W]."""
        B, C, H, W = x.shape
        tokens = self.norm(x).flatten(2).transpose(1, 2)  # [B, HW, C]
        q, k, v = self.to_q(tokens), self.to_k(tokens), self.to_v(tokens)
        scores = (q @ k.transpose(1, 2)) / math.sqrt(C)  # [B, HW, HW]
        # softmax in >= float32 (the reference upcasts half precision), result in the input dtype
        soft_dtype = torch.float32 if scores.dtype in (torch.float16, torch.bfloat16) else scores.dtype
        attn = torch.softmax(scores, dim=-1, dtype=soft_dtype).to(q.dtype)
        out = self.proj_out(attn @ v)  # [B, HW, C]
        return x + out.transpose(1, 2).reshape(B, C, H, W)


class Upsample2D(nn.Module):
    """Nearest-neighbour ×2 up-sampling followed by a 3×3 conv."""

    def __init__(self, channels: int) -> None:
        super().__init__()
        self.conv = nn.Conv2d(channels, channels, 3, padding=1)

    def forward(self, x: Tensor) -> Tensor:
        """x [B, C, H, W] -> [B, C, 2H, 2W]."""
        return self.conv(F.interpolate(x, scale_factor=2.0, mode="nearest"))


class TriplaneGenerator(nn.Module):
    """CNN decoder from a fixed noise image to one feature plane [1, out_channels, R, R].

    Args:
        noise_channels: channels of the fixed noise input (B.2: 8).
        noise_res: spatial size of the noise (B.2: 20).
        channels: working width of the decoder (B.2: 32; reference ``block_out_channels`` all 32).
        out_channels: channels of the plane (B.2: 16).
        n_up_blocks: number of up blocks; all but the last end with a ×2 up-sampler, so the output
            resolution is ``noise_res · 2^(n_up_blocks - 1)`` (B.2: 4 blocks, 20 → 160).
        resnets_per_block: ResNet blocks per up block (B.2: 2; reference ``layers_per_block + 1``).
        norm_groups: GroupNorm groups (reference: 32); must divide ``channels``.
        ref_extra_mid_resnet: add the reference's extra ResNet block before the attention (reference
            mid block ResNet→Attn→ResNet; the paper describes Attn→ResNet). Default False.
        seed: seed of the ``torch.Generator`` that draws the noise buffer (reproducible runs; the
            reference does not seed it).
    """

    def __init__(
        self,
        noise_channels: int = 8,
        noise_res: int = 20,
        channels: int = 32,
        out_channels: int = 16,
        n_up_blocks: int = 4,
        resnets_per_block: int = 2,
        norm_groups: int = 32,
        ref_extra_mid_resnet: bool = False,
        seed: int = 0,
    ) -> None:
        super().__init__()
        if n_up_blocks < 1:
            raise ValueError("n_up_blocks must be >= 1")
        self.out_channels = out_channels
        self.resolution = noise_res * 2 ** (n_up_blocks - 1)
        g = torch.Generator().manual_seed(int(seed))
        # Fixed (never optimised) noise input, saved in the state dict: [1, C_noise, r, r].
        self.register_buffer("noise", torch.randn(1, noise_channels, noise_res, noise_res, generator=g))

        self.conv_in = nn.Conv2d(noise_channels, channels, 3, padding=1)
        mid: list[nn.Module] = []
        if ref_extra_mid_resnet:
            mid.append(ResnetBlock2D(channels, norm_groups))
        mid += [SelfAttention2D(channels, norm_groups), ResnetBlock2D(channels, norm_groups)]
        self.mid = nn.Sequential(*mid)
        blocks: list[nn.Module] = []
        for b in range(n_up_blocks):
            layers: list[nn.Module] = [ResnetBlock2D(channels, norm_groups) for _ in range(resnets_per_block)]
            if b < n_up_blocks - 1:
                layers.append(Upsample2D(channels))
            blocks.append(nn.Sequential(*layers))
        self.up_blocks = nn.ModuleList(blocks)
        self.norm_out = _gn(channels, norm_groups)
        self.conv_out = nn.Conv2d(channels, out_channels, 3, padding=1)
        self._init_weights()

    def _init_weights(self) -> None:
        # mmcv kaiming_init defaults on every conv: normal, fan_out, relu gain, bias 0;
        # then the zero-init of residual branches (second conv of each ResNet block).
        for m in self.modules():
            if isinstance(m, nn.Conv2d):
                nn.init.kaiming_normal_(m.weight, mode="fan_out", nonlinearity="relu")
                nn.init.zeros_(m.bias)
        for m in self.modules():
            if isinstance(m, ResnetBlock2D):
                nn.init.zeros_(m.conv2.weight)
                nn.init.zeros_(m.conv2.bias)

    def forward(self) -> Tensor:
        """The feature plane [1, out_channels, R, R] (R = ``self.resolution``)."""
        h = self.conv_in(self.noise)  # [1, C, r, r]
        h = self.mid(h)
        for block in self.up_blocks:
            h = block(h)  # [1, C, ...] doubling resolution in all blocks but the last
        return self.conv_out(F.silu(self.norm_out(h)))
