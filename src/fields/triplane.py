"""CNN tri-plane generator of SplatFields (supplementary B.2): fixed noise -> one feature plane.

Plain-torch re-implementation of the reference ``VarTriPlaneEncoder`` / ``TimeVAEDecoder`` (a
diffusers-style VAE decoder); no mmcv / mmgen / diffusers.

Per plane (paper defaults): fixed noise [1, 8, 20, 20] -> conv3×3 8→32 -> self-attention -> ResNet
block (20×20×32) -> 4 up blocks of 2 ResNet blocks each, blocks 0..2 followed by nearest ×2 +
conv3×3 (20→40→80→160) -> GN -> SiLU -> conv3×3 32→16: a 16×160×160 plane.

Parameter count per plane (measured, ``tests/test_fields.py``): 206 672 with the paper's mid block
(attention + 1 ResNet block), 225 296 with ``ref_extra_mid_resnet=True`` (the reference's
ResNet→Attn→ResNet mid block; matches the hand count 225 296 of the reference notes §1.5).

Two exact rewrites of the same function (same parameters, same state dict; checked in float64
against the per-plane path by ``tests/test_triplane_fast.py``):

* ``stacked_planes``: the P generators of a tri-plane run as one network on [1, P·C, H, W]
  (plane-major channels): grouped convolutions (``groups=P``) with the per-plane kernels
  concatenated, one GroupNorm with P·G groups (GroupNorm groups are contiguous channel blocks, so the
  P·G groups over P·C channels are exactly the P planes' G groups over C channels, whatever C/G is),
  attention as batched matmuls over the planes. The stacked weights are concatenated from the
  per-plane parameters on every call, so autograd reaches the per-plane parameters.
* sub-pixel up-sampling (``subpixel_upsample``): nearest ×2 followed by a 3×3 conv equals one
  2×2 conv with 4·C outputs (one kernel per output phase, each a sum of taps of the 3×3 kernel) on
  the low-resolution input, interleaved into the ×2 grid: 16 instead of 36 multiply-adds per output
  pixel and channel pair, and no up-sampled copy of the input.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

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


def subpixel_kernels(weight: Tensor) -> Tensor:
    """The four 2×2 phase kernels of ``conv3×3(nearest×2(x))``, from its 3×3 kernel.

    Output pixel (2i + a, 2j + b) of the up-sampled conv reads up-sampled rows 2i + a - 1 .. 2i + a + 1,
    i.e. input rows (i - 1, i, i) for a = 0 and (i, i, i + 1) for a = 1 (columns likewise): phase a's
    row taps are (w0, w1 + w2) over input rows (i - 1, i) and (w0 + w1, w2) over (i, i + 1). The zero
    padding of the up-sampled image is the zero padding of the input (row -1 ↔ row -1, row 2H ↔ row H).

    Args:
        weight: [..., O, I, 3, 3] (leading dims, e.g. planes, are kept).

    Returns:
        [..., 2 (a), 2 (b), O, I, 2, 2]: the kernel of phase (a, b), to be applied to the input padded
        by one pixel with output (r, c) of the 2×2 conv read at r = i + a, c = j + b.
    """

    def fold(w: Tensor, dim: int) -> Tensor:  # [..., 3 at dim, ...] -> [2 (phase), ..., 2 at dim, ...]
        w0, w1, w2 = w.unbind(dim)
        return torch.stack([torch.stack([w0, w1 + w2], dim), torch.stack([w0 + w1, w2], dim)])

    k = fold(fold(weight, -1), -2)  # [2 (a), 2 (b), ..., O, I, 2, 2]
    lead = weight.dim() - 4
    return k.permute(*range(2, 2 + lead), 0, 1, *range(2 + lead, k.dim()))


def subpixel_upsample_conv(x: Tensor, weight: Tensor, bias: Tensor, groups: int = 1) -> Tensor:
    """``conv2d(interpolate(x, ×2, nearest), weight, bias, padding=1, groups=groups)`` computed at low
    resolution (exact up to rounding).

    One 2×2 conv (padding 1) yields the four phases of every output pixel, [B, g·4·O, H+1, W+1] with
    channels ordered (group, a, b, o); output (2i + a, 2j + b) is phase (a, b) at (i + a, j + b), an
    affine map of indices, i.e. one strided view of the conv output, copied once into the output.

    Args:
        x: [B, groups·I, H, W] (contiguous or channels-last).
        weight: [groups, O, I, 3, 3] (one 3×3 kernel per group).
        bias: [groups, O].

    Returns:
        [B, groups·O, 2H, 2W], in channels-last memory format if ``x`` is, else contiguous.
    """
    _, O, I = weight.shape[:3]
    k = subpixel_kernels(weight).reshape(groups * 4 * O, I, 2, 2)  # outputs ordered (group, a, b, o)
    b = bias[:, None].expand(groups, 4, O).reshape(-1)
    y = F.conv2d(x, k, b, padding=1, groups=groups)  # [B, g·4·O, H+1, W+1]
    return _Interleave.apply(y, groups, O)


def _phase_view(y: Tensor, groups: int, O: int) -> Tensor:
    """y [B, g·4·O, H+1, W+1] (channels (g, a, b, o)) viewed as [B, g, O, H, 2 (a), W, 2 (b)]: element
    (n, g, o, i, a, j, b) = y[n, (4g + 2a + b)·O + o, i + a, j + b], an affine map (any memory format)."""
    B, _, H1, W1 = y.shape
    s_n, s_ch, s_r, s_c = y.stride()
    return y.as_strided((B, groups, O, H1 - 1, 2, W1 - 1, 2),
                        (s_n, 4 * O * s_ch, s_ch, s_r, 2 * O * s_ch + s_r, s_c, O * s_ch + s_c), y.storage_offset())


class _Interleave(torch.autograd.Function):
    """Phases [B, g·4·O, H+1, W+1] -> the ×2 image [B, g·O, 2H, 2W] (same memory format); backward
    scatters into a zeroed buffer with the phases' strides (rows/columns no output reads stay zero)."""

    @staticmethod
    def forward(ctx: torch.autograd.function.FunctionCtx, y: Tensor, groups: int, O: int) -> Tensor:  # type: ignore[override]
        B, _, H1, W1 = y.shape
        fmt = torch.channels_last if y.is_contiguous(memory_format=torch.channels_last) else torch.contiguous_format
        out = torch.empty(B, groups * O, 2 * (H1 - 1), 2 * (W1 - 1), dtype=y.dtype, device=y.device, memory_format=fmt)
        out.view(B, groups, O, H1 - 1, 2, W1 - 1, 2).copy_(_phase_view(y, groups, O))
        ctx.geometry = (y.shape, y.stride(), groups, O)  # type: ignore[attr-defined]
        return out

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx: torch.autograd.function.FunctionCtx, grad: Tensor) -> tuple[Tensor, None, None]:  # type: ignore[override]
        shape, stride, groups, O = ctx.geometry  # type: ignore[attr-defined]
        gy = torch.empty_strided(shape, stride, dtype=grad.dtype, device=grad.device).zero_()
        B, _, H1, W1 = shape
        _phase_view(gy, groups, O).copy_(grad.view(B, groups, O, H1 - 1, 2, W1 - 1, 2))
        return gy, None, None


class Upsample2D(nn.Module):
    """Nearest-neighbour ×2 up-sampling followed by a 3×3 conv.

    With ``subpixel=True`` the same function runs as one 2×2 conv at the input resolution
    (``subpixel_upsample_conv``); the parameter is the 3×3 conv either way.
    """

    def __init__(self, channels: int, subpixel: bool = False) -> None:
        super().__init__()
        self.conv = nn.Conv2d(channels, channels, 3, padding=1)
        self.subpixel = subpixel

    def forward(self, x: Tensor) -> Tensor:
        """x [B, C, H, W] -> [B, C, 2H, 2W]."""
        if self.subpixel:
            return subpixel_upsample_conv(x, self.conv.weight[None], self.conv.bias[None])
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
        subpixel_upsample: run each nearest ×2 + 3×3 conv as a 2×2 conv at the low resolution
            (``subpixel_upsample_conv``; same function and parameters). Default False (reference).
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
        subpixel_upsample: bool = False,
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
                layers.append(Upsample2D(channels, subpixel_upsample))
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


# --------------------------------------------------------------------------------------------------
# All planes as one network (grouped convolutions over plane-major channels)
# --------------------------------------------------------------------------------------------------



@dataclass(frozen=True)
class StackOptions:
    """How ``stacked_planes`` lays the stacked network out (each option keeps the function exact).

    Attributes:
        subpixel: sub-pixel form of the up-samplers (``subpixel_upsample_conv``).
        channels_last: keep the activations in channels-last memory format, where oneDNN runs its
            convolutions without re-ordering their outputs; GroupNorms with one channel per group
            then run as ``batch_norm`` with batch statistics (over the single image, per channel:
            the same normalisation, and a fast channels-last kernel where GroupNorm's is slow).
            Ignored unless every GroupNorm has one channel per group.
    """

    subpixel: bool = False
    channels_last: bool = False


def _conv(convs: Sequence[nn.Conv2d], x: Tensor) -> Tensor:
    """The P per-plane ``convs`` as one grouped conv: x [1, P·I, H, W] -> [1, P·O, H, W]."""
    w = torch.cat([m.weight for m in convs])  # [P·O, I, k, k]
    b = torch.cat([m.bias for m in convs])
    return F.conv2d(x, w, b, padding=convs[0].padding, groups=len(convs))


def _norm(norms: Sequence[nn.GroupNorm], x: Tensor, opt: StackOptions) -> Tensor:
    """The P per-plane GroupNorms as one: x [1, P·C, H, W] -> [1, P·C, H, W] (P·G groups).

    GroupNorm groups are contiguous channel blocks, so P·G groups over the P·C stacked channels are
    exactly each plane's G groups over its C channels. With one channel per group (G = C) and
    ``opt.channels_last`` it runs as ``batch_norm`` over the batch of one (batch statistics, biased
    variance, same eps): the same per-channel normalisation.
    """
    n = norms[0]
    w = torch.cat([m.weight for m in norms])
    b = torch.cat([m.bias for m in norms])
    if opt.channels_last and n.num_groups == n.num_channels and x.shape[0] == 1:
        return F.batch_norm(x, None, None, w, b, True, 0.0, n.eps)
    return F.group_norm(x, len(norms) * n.num_groups, w, b, n.eps)


def _resnet(blocks: Sequence[ResnetBlock2D], x: Tensor, opt: StackOptions) -> Tensor:
    """P ``ResnetBlock2D`` at once: x [1, P·C, H, W] -> [1, P·C, H, W]."""
    h = _conv([m.conv1 for m in blocks], F.silu(_norm([m.norm1 for m in blocks], x, opt)))
    h = _conv([m.conv2 for m in blocks], F.silu(_norm([m.norm2 for m in blocks], h, opt)))
    return x + h


def _attention(layers: Sequence[SelfAttention2D], x: Tensor, opt: StackOptions) -> Tensor:
    """P ``SelfAttention2D`` at once (batched over planes): x [1, P·C, H, W] -> [1, P·C, H, W]."""
    P = len(layers)
    _, PC, H, W = x.shape
    C = PC // P
    tokens = _norm([m.norm for m in layers], x, opt).reshape(P, C, H * W).transpose(1, 2)  # [P, HW, C]
    w_qkv = torch.stack([torch.cat([m.to_q.weight, m.to_k.weight, m.to_v.weight]) for m in layers])  # [P, 3C, C]
    b_qkv = torch.stack([torch.cat([m.to_q.bias, m.to_k.bias, m.to_v.bias]) for m in layers])  # [P, 3C]
    q, k, v = torch.baddbmm(b_qkv[:, None], tokens, w_qkv.transpose(1, 2)).split(C, dim=2)  # [P, HW, C] each
    scores = torch.bmm(q, k.transpose(1, 2)) / math.sqrt(C)  # [P, HW, HW]
    soft_dtype = torch.float32 if scores.dtype in (torch.float16, torch.bfloat16) else scores.dtype
    attn = torch.softmax(scores, dim=-1, dtype=soft_dtype).to(q.dtype)
    w_out = torch.stack([m.proj_out.weight for m in layers])  # [P, C, C]
    b_out = torch.stack([m.proj_out.bias for m in layers])  # [P, C]
    out = torch.baddbmm(b_out[:, None], torch.bmm(attn, v), w_out.transpose(1, 2))  # [P, HW, C]
    out = out.transpose(1, 2).reshape(1, PC, H, W)
    if opt.channels_last:
        out = out.contiguous(memory_format=torch.channels_last)
    return x + out


def _upsample(layers: Sequence[Upsample2D], x: Tensor, opt: StackOptions) -> Tensor:
    """P ``Upsample2D`` at once: x [1, P·C, H, W] -> [1, P·C, 2H, 2W]."""
    if opt.subpixel or layers[0].subpixel:
        w = torch.stack([m.conv.weight for m in layers])  # [P, C, C, 3, 3]
        b = torch.stack([m.conv.bias for m in layers])  # [P, C]
        return subpixel_upsample_conv(x, w, b, groups=len(layers))
    return _conv([m.conv for m in layers], F.interpolate(x, scale_factor=2.0, mode="nearest"))


def _apply(layers: Sequence[nn.Module], x: Tensor, opt: StackOptions) -> Tensor:
    """P same-position layers of the P generators at once: x [1, P·C, H, W] -> [1, P·C', H', W']."""
    first = layers[0]
    if isinstance(first, ResnetBlock2D):
        return _resnet(layers, x, opt)  # type: ignore[arg-type]
    if isinstance(first, SelfAttention2D):
        return _attention(layers, x, opt)  # type: ignore[arg-type]
    if isinstance(first, Upsample2D):
        return _upsample(layers, x, opt)  # type: ignore[arg-type]
    raise TypeError(f"no stacked form of {type(first).__name__}")


def stacked_planes(generators: Sequence[TriplaneGenerator], subpixel: bool = False,
                   channels_last: bool = False) -> Tensor:
    """``torch.cat([g() for g in generators])`` computed as one network (exact up to rounding).

    Args:
        generators: P ``TriplaneGenerator`` of the same configuration (their own parameters are used:
            the stacked weights are concatenated on each call, so gradients reach them).
        subpixel: use the sub-pixel form of the up-samplers (also used where a generator was built
            with ``subpixel_upsample=True``).
        channels_last: channels-last activations (``StackOptions.channels_last``).

    Returns:
        The planes [P, out_channels, R, R] (contiguous).
    """
    gens = list(generators)
    P = len(gens)
    one_per_group = all(m.num_groups == m.num_channels for g in gens for m in g.modules()
                        if isinstance(m, nn.GroupNorm))
    opt = StackOptions(subpixel=subpixel, channels_last=channels_last and one_per_group)
    x = torch.cat([g.noise for g in gens], dim=1)  # [1, P·C_noise, r, r]
    if opt.channels_last:
        x = x.contiguous(memory_format=torch.channels_last)
    h = _conv([g.conv_in for g in gens], x)  # [1, P·C, r, r]
    for layers in zip(*(g.mid for g in gens), strict=True):
        h = _apply(layers, h, opt)
    for blocks in zip(*(g.up_blocks for g in gens), strict=True):
        for layers in zip(*blocks, strict=True):
            h = _apply(layers, h, opt)
    h = _conv([g.conv_out for g in gens], F.silu(_norm([g.norm_out for g in gens], h, opt)))  # [1, P·O, R, R]
    return h.contiguous().view(P, -1, h.shape[2], h.shape[3])
