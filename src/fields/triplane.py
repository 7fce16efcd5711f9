"""CNN tri-plane generator of SplatFields (supplementary B.2): fixed noise -> feature planes.

Plain-torch re-implementation of the reference ``VarTriPlaneEncoder`` / ``TimeVAEDecoder`` (a
diffusers-style VAE decoder); no mmcv / mmgen / diffusers.

Per plane (paper defaults): fixed noise [1, 8, 20, 20] -> conv3×3 8→32 -> self-attention -> ResNet
block (20×20×32) -> 4 up blocks of 2 ResNet blocks each, blocks 0..2 followed by nearest ×2 +
conv3×3 (20→40→80→160) -> GN -> SiLU -> conv3×3 32→16: a 16×160×160 plane.

Parameter count per plane (measured, ``tests/test_fields.py``): 206 672 with the paper's mid block
(attention + 1 ResNet block), 225 296 with ``ref_extra_mid_resnet=True`` (the reference's
ResNet→Attn→ResNet mid block; matches the hand count 225 296 of the reference notes §1.5).

Every module takes ``planes`` (P): P independent generators run as ONE network on [1, P·C, H, W]
(plane-major channels) with their parameters stored stacked along dim 0: a conv's weight is
[P·O, I, k, k] (a grouped conv, ``groups=P``), a norm's [P·C] (GroupNorm groups are contiguous channel
blocks, so P·G groups over P·C channels are exactly each plane's G groups over its C channels), the
attention projections [P·C, C] (batched matmuls over the planes), the noise [P, C_noise, r, r]. Plane
p's parameter is chunk p of each stacked one (``stack_generators`` / ``split_plane_state``), so P = 1
is the per-plane reference and P = 3 the same function (``tests/test_triplane_fast.py``, float64).

With channels-last activations (``TriplaneGenerator.channels_last``) oneDNN's convolutions skip
re-ordering their outputs, and GroupNorms with one channel per group run as ``batch_norm`` with batch
statistics over the single image (the same per-channel normalisation, a fast channels-last kernel).

Sub-pixel up-sampling (``subpixel_upsample_conv``): nearest ×2 followed by a 3×3 conv equals one 2×2
conv with 4·C outputs (one kernel per output phase, each a sum of taps of the 3×3 kernel) on the
low-resolution input, interleaved into the ×2 grid: 16 instead of 36 multiply-adds per output pixel and
channel pair, and no up-sampled copy of the input.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import torch
import torch.nn.functional as F
from torch import Tensor, nn


def _gn(channels: int, groups: int, planes: int = 1) -> nn.GroupNorm:
    """GroupNorm of ``planes`` stacked planes of ``channels`` channels in ``groups`` groups each."""
    return nn.GroupNorm(planes * groups, planes * channels, eps=1e-6)  # diffusers default eps


def _normalise(norm: nn.GroupNorm, x: Tensor) -> Tensor:
    """``norm(x)``; on channels-last x [1, C, H, W] with one channel per group, as batch-statistics
    ``batch_norm`` (biased variance, same eps: the same per-channel normalisation, a faster kernel)."""
    if (norm.num_groups == norm.num_channels and x.shape[0] == 1 and x.dim() == 4
            and not x.is_contiguous() and x.is_contiguous(memory_format=torch.channels_last)):
        return F.batch_norm(x, None, None, norm.weight, norm.bias, True, 0.0, norm.eps)
    return norm(x)


class ResnetBlock2D(nn.Module):
    """x + conv(SiLU(GN(conv(SiLU(GN(x)))))): two 3×3 convs, identity skip (in = out channels).

    The second conv is zero-initialised so the block starts as the identity (reference
    ``zero_init_residual``). ``planes`` stacked blocks run as grouped convs on [B, P·C, H, W].
    """

    def __init__(self, channels: int, norm_groups: int = 32, planes: int = 1) -> None:
        super().__init__()
        width = planes * channels
        self.norm1 = _gn(channels, norm_groups, planes)
        self.conv1 = nn.Conv2d(width, width, 3, padding=1, groups=planes)
        self.norm2 = _gn(channels, norm_groups, planes)
        self.conv2 = nn.Conv2d(width, width, 3, padding=1, groups=planes)
        nn.init.zeros_(self.conv2.weight)
        nn.init.zeros_(self.conv2.bias)

    def forward(self, x: Tensor) -> Tensor:
        """x [B, P·C, H, W] -> [B, P·C, H, W]."""
        h = self.conv1(F.silu(_normalise(self.norm1, x)))
        h = self.conv2(F.silu(_normalise(self.norm2, h)))  # dropout(0) of the reference omitted
        return x + h


class SelfAttention2D(nn.Module):
    """Single-head spatial self-attention with a residual: x + proj(softmax(q kᵀ/√C) v), per plane.

    GroupNorm before the q/k/v projections (linear over channels, one token per pixel); the output
    projection is zero-initialised, so the layer starts as the identity. With ``planes`` P the
    projections hold the planes' weights stacked: ``to_q.weight`` [P·C, C] is plane p's [C, C] at rows
    p·C .. (p+1)·C (nn.Linear as the parameter holder; applied per plane as batched matmuls).
    """

    def __init__(self, channels: int, norm_groups: int = 32, planes: int = 1) -> None:
        super().__init__()
        self.planes = planes
        self.norm = _gn(channels, norm_groups, planes)
        self.to_q = nn.Linear(channels, planes * channels)
        self.to_k = nn.Linear(channels, planes * channels)
        self.to_v = nn.Linear(channels, planes * channels)
        self.proj_out = nn.Linear(channels, planes * channels)
        nn.init.zeros_(self.proj_out.weight)
        nn.init.zeros_(self.proj_out.bias)

    def _stacked(self, *layers: nn.Linear) -> tuple[Tensor, Tensor]:
        """The layers' weights as [P, C_in, n·C] (transposed for ``x @ w``) and biases [P, 1, n·C]."""
        P = self.planes
        ws = [m.weight.view(P, -1, m.in_features) for m in layers]  # [P, C, C] each
        bs = [m.bias.view(P, 1, -1) for m in layers]  # [P, 1, C] each
        w, b = (ws[0], bs[0]) if len(layers) == 1 else (torch.cat(ws, dim=1), torch.cat(bs, dim=2))
        return w.transpose(1, 2), b

    def forward(self, x: Tensor) -> Tensor:
        """x [B, P·C, H, W] -> [B, P·C, H, W]."""
        B, PC, H, W = x.shape
        P = self.planes
        C = PC // P
        tokens = _normalise(self.norm, x).reshape(B, P, C, H * W).transpose(2, 3)  # [B, P, HW, C]
        w_qkv, b_qkv = self._stacked(self.to_q, self.to_k, self.to_v)
        q, k, v = (tokens @ w_qkv + b_qkv).split(C, dim=-1)  # [B, P, HW, C] each
        scores = (q @ k.transpose(-1, -2)) / math.sqrt(C)  # [B, P, HW, HW]
        # softmax in >= float32 (the reference upcasts half precision), result in the input dtype
        soft_dtype = torch.float32 if scores.dtype in (torch.float16, torch.bfloat16) else scores.dtype
        attn = torch.softmax(scores, dim=-1, dtype=soft_dtype).to(q.dtype)
        w_out, b_out = self._stacked(self.proj_out)
        out = (attn @ v) @ w_out + b_out  # [B, P, HW, C]
        out = out.reshape(B, P, H * W, C).transpose(2, 3).reshape(B, PC, H, W)
        if not x.is_contiguous() and x.is_contiguous(memory_format=torch.channels_last):
            out = out.contiguous(memory_format=torch.channels_last)
        return x + out


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
    """Nearest-neighbour ×2 up-sampling followed by a 3×3 conv (``planes`` stacked: a grouped conv).

    With ``subpixel=True`` the same function runs as one 2×2 conv at the input resolution
    (``subpixel_upsample_conv``); the parameter is the 3×3 conv either way.
    """

    def __init__(self, channels: int, subpixel: bool = False, planes: int = 1) -> None:
        super().__init__()
        self.planes = planes
        self.conv = nn.Conv2d(planes * channels, planes * channels, 3, padding=1, groups=planes)
        self.subpixel = subpixel

    def forward(self, x: Tensor) -> Tensor:
        """x [B, P·C, H, W] -> [B, P·C, 2H, 2W]."""
        if self.subpixel:
            P = self.planes
            w = self.conv.weight.view(P, -1, *self.conv.weight.shape[1:])  # [P, C, C, 3, 3]
            return subpixel_upsample_conv(x, w, self.conv.bias.view(P, -1), groups=P)
        return self.conv(F.interpolate(x, scale_factor=2.0, mode="nearest"))


class TriplaneGenerator(nn.Module):
    """CNN decoder from a fixed noise image to ``planes`` feature planes [P, out_channels, R, R].

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
        planes: P independent generators as one network, parameters stacked along dim 0 (module
            docstring); 1 is the per-plane reference.
        channels_last: run the activations channels-last (module docstring); the same function. Meant for
            one channel per group: other GroupNorms run channels-last through GroupNorm's slow kernel.
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
        planes: int = 1,
        channels_last: bool = False,
    ) -> None:
        super().__init__()
        self.config = dict(noise_channels=noise_channels, noise_res=noise_res, channels=channels,
                           out_channels=out_channels, n_up_blocks=n_up_blocks, resnets_per_block=resnets_per_block,
                           norm_groups=norm_groups, ref_extra_mid_resnet=ref_extra_mid_resnet,
                           subpixel_upsample=subpixel_upsample)  # the per-plane configuration (seed aside)
        if n_up_blocks < 1:
            raise ValueError("n_up_blocks must be >= 1")
        if planes < 1:
            raise ValueError(f"planes must be >= 1, got {planes}")
        self.planes = planes
        self.channels_last = channels_last
        self.out_channels = out_channels
        self.resolution = noise_res * 2 ** (n_up_blocks - 1)
        g = torch.Generator().manual_seed(int(seed))
        # Fixed (never optimised) noise input, saved in the state dict: [P, C_noise, r, r].
        self.register_buffer("noise", torch.randn(planes, noise_channels, noise_res, noise_res, generator=g))

        P = planes
        self.conv_in = nn.Conv2d(P * noise_channels, P * channels, 3, padding=1, groups=P)
        mid: list[nn.Module] = []
        if ref_extra_mid_resnet:
            mid.append(ResnetBlock2D(channels, norm_groups, P))
        mid += [SelfAttention2D(channels, norm_groups, P), ResnetBlock2D(channels, norm_groups, P)]
        self.mid = nn.Sequential(*mid)
        blocks: list[nn.Module] = []
        for b in range(n_up_blocks):
            layers: list[nn.Module] = [ResnetBlock2D(channels, norm_groups, P) for _ in range(resnets_per_block)]
            if b < n_up_blocks - 1:
                layers.append(Upsample2D(channels, subpixel_upsample, P))
            blocks.append(nn.Sequential(*layers))
        self.up_blocks = nn.ModuleList(blocks)
        self.norm_out = _gn(channels, norm_groups, P)
        self.conv_out = nn.Conv2d(P * channels, P * out_channels, 3, padding=1, groups=P)
        self._init_weights()

    def _init_weights(self) -> None:
        # mmcv kaiming_init defaults on every conv: normal, fan_out, relu gain, bias 0 (per plane: each
        # plane's kernel has the fan of a one-plane conv); then the zero-init of residual branches
        # (second conv of each ResNet block).
        for m in self.modules():
            if isinstance(m, nn.Conv2d):
                for w in m.weight.detach().chunk(self.planes):
                    nn.init.kaiming_normal_(w, mode="fan_out", nonlinearity="relu")
                nn.init.zeros_(m.bias)
        for m in self.modules():
            if isinstance(m, ResnetBlock2D):
                nn.init.zeros_(m.conv2.weight)
                nn.init.zeros_(m.conv2.bias)

    def forward(self) -> Tensor:
        """The feature planes [P, out_channels, R, R] (contiguous; R = ``self.resolution``)."""
        P, _, r, _ = self.noise.shape
        h = self.noise.view(1, -1, r, r)  # [1, P·C_noise, r, r]
        if self.channels_last:
            h = h.contiguous(memory_format=torch.channels_last)
        h = self.conv_in(h)  # [1, P·C, r, r]
        h = self.mid(h)
        for block in self.up_blocks:
            h = block(h)  # [1, P·C, ...] doubling resolution in all blocks but the last
        h = self.conv_out(F.silu(_normalise(self.norm_out, h)))  # [1, P·O, R, R]
        return h.contiguous().view(P, self.out_channels, h.shape[2], h.shape[3])


def stack_generators(generators: Sequence[TriplaneGenerator], channels_last: bool = False) -> TriplaneGenerator:
    """One generator with ``planes = len(generators)`` computing ``torch.cat([g() for g in generators])``.

    The generators must share one configuration (``planes=1`` each); their parameters and noise are
    copied in, stacked along dim 0 (``stack_plane_state``). ``channels_last`` as ``TriplaneGenerator``.
    """
    gens = list(generators)
    if any(g.planes != 1 or g.config != gens[0].config for g in gens):
        raise ValueError("stack_generators expects one-plane generators of one configuration")
    with torch.random.fork_rng(devices=[]):  # its own initialisation is overwritten: leave the global RNG as it was
        stacked = TriplaneGenerator(**gens[0].config, planes=len(gens), channels_last=channels_last)
    stacked.to(device=gens[0].noise.device, dtype=gens[0].noise.dtype)
    stacked.load_state_dict(stack_plane_state([g.state_dict() for g in gens]))
    return stacked


def stack_plane_state(states: Sequence[dict[str, Tensor]]) -> dict[str, Tensor]:
    """P one-plane generator state dicts -> the state dict of their ``planes = P`` stack (cat on dim 0)."""
    keys = states[0].keys()
    if any(s.keys() != keys for s in states):
        raise ValueError("plane state dicts have different keys: not generators of one configuration")
    return {k: torch.cat([s[k] for s in states]) for k in keys}


def split_plane_state(state: dict[str, Tensor], planes: int) -> list[dict[str, Tensor]]:
    """The state dict of a ``planes = P`` generator -> P one-plane state dicts (chunk p of dim 0)."""
    out: list[dict[str, Tensor]] = [{} for _ in range(planes)]
    for k, v in state.items():
        if v.shape[0] % planes:
            raise ValueError(f"{k}: dim 0 of {tuple(v.shape)} is not a multiple of {planes} planes")
        for p, chunk in enumerate(v.chunk(planes)):
            out[p][k] = chunk.clone()
    return out
