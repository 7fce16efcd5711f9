"""Fused evaluation of the field heads that read the same input (the fast path of ``SplatFieldNetwork``).

Every head ``FieldMLP`` reads ``h_in = [PE(x), f, PE(t)]`` at its first linear and again at each skip
linear (``W_skip [h_in, h] = W_x h_in + W_h h``). All those input parts are linear in ``h_in``, so
for a group of heads that share ``h_in`` they are computed by ONE wide product per group:

    U_g = [f, PE_Lmax(x_g)] @ [W_f_g, W_pe_g]ᵀ + (b_g + W_t_g PE(t))    per group g, one product

(f: [N, F] backbone feature; PE once per group, at the group's largest L.) One product per group on
the narrow concatenated input, rather than f for all groups then PE per group, writes each [N, S_g]
output once and needs no gather of the groups' gradients in the backward.
PE(t) is one row per call (all splats share the time), so its part is folded into the bias. A head
with fewer PE levels than the group's maximum reads a prefix of PE_Lmax (the layout is level-major:
[x, sin f0 x, cos f0 x, sin f1 x, ...]); its weight is zero-padded. The hidden and output layers then
run per head, the skip layers as ``addmm(U_skip, h, W_hᵀ)`` without concatenating [N, in + width]
tensors, and every hidden ReLU layer through ``linear_relu`` (bias and ReLU in the product's
epilogue). On CPUs with AMX-BF16 tiles (``model.network.head_kernel``) a head instead runs whole, from
the group's input row ``[f, PE_Lmax(x)]`` to its output, as one kernel (``kernel_layers``,
``src.fields.head_kernel``); ``head_outputs`` sends each head of a group one way or the other. The
parameters are the heads' own (state dicts unchanged); the fused weights are concatenated from them on
every call (a few kB), so gradients reach every head as before.

The slow reference is ``FieldMLP.forward`` on explicit concatenations; ``tests/test_fused_heads.py``
checks that both agree in float64 (values and gradients).
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
import torch.nn.functional as F
from torch import Tensor

from src.fields.head_kernel import HeadLayers, heads_mlp
from src.fields.linear_relu import linear_relu
from src.fields.mlp import FieldMLP


def head_weights(mlp: FieldMLP, frame_id: int | None, time: float | None) -> list[Tensor]:
    """The [out, in] weight of every linear of ``mlp`` at this frame/time (ResField residuals applied)."""
    return [layer.weight_at(frame_id, time) for layer in mlp.layers]


class HeadInput:
    """The input-part columns of one head's first and skip linears: ``[L0, skip_1, ...]`` blocks.

    Args:
        mlp: the head.
        weights: ``head_weights(mlp, ...)``.
        pe_dim: width of the head's PE(x) block; pe_max: width of the group's shared PE block.
        feat_dim: width of the backbone feature f; time_dim: width of PE(t) (0 when static).

    Attributes:
        w_x: [S, F + pe_max] the blocks' weights on the group's ``input_row`` ``[f, PE_Lmax(x)]``.
        w_t: [S, T] their weights on PE(t); b: [S] their biases; sizes: the blocks' widths (sum S).
    """

    def __init__(self, mlp: FieldMLP, weights: list[Tensor], pe_dim: int, pe_max: int, feat_dim: int,
                 time_dim: int) -> None:
        self.mlp = mlp
        self.rows = [0, *mlp.skips]  # linears that read h_in
        w_x, w_t, b = [], [], []
        for i in self.rows:
            w_in = weights[i][:, : mlp.in_dim]  # [out, in_dim]: the input part (reference order: input first)
            w_pe = F.pad(w_in[:, :pe_dim], (0, pe_max - pe_dim))  # [out, pe_max]
            w_x.append(torch.cat([w_in[:, pe_dim: pe_dim + feat_dim], w_pe], dim=1))  # [out, F + pe_max]
            w_t.append(w_in[:, pe_dim + feat_dim: pe_dim + feat_dim + time_dim])  # [out, T]
            b.append(mlp.layers[i].bias)  # the skip linear's bias travels with its input part
        self.sizes = [int(w.shape[0]) for w in w_x]
        self.w_x, self.w_t, self.b = torch.cat(w_x), torch.cat(w_t), torch.cat(b)


def input_row(feat: Tensor, pe: Tensor) -> Tensor:
    """The heads' input row without PE(t): ``[f, PE(x)]`` [N, F + pe_max] in f's dtype (PE alone when F = 0)."""
    return torch.cat([feat, pe.to(feat.dtype)], dim=1) if feat.shape[-1] > 0 else pe


def _input_bias(heads: Sequence[HeadInput], t_enc: Tensor | None) -> Tensor:
    """The biases of the heads' input-reading linears with PE(t)'s part folded in: b + W_t PE(t) [S]."""
    b = torch.cat([h.b for h in heads])  # [S]
    if t_enc is not None and t_enc.shape[-1] > 0:
        b = b + t_enc.reshape(-1) @ torch.cat([h.w_t for h in heads]).t()  # [S]
    return b


def input_layer(heads: Sequence[HeadInput], x: Tensor, t_enc: Tensor | None) -> list[list[Tensor]]:
    """The input part of every first and skip linear of a group of heads, as ONE product.

    ``[f, PE] [W_f, W_pe]ᵀ + (b + W_t PE(t))``, split per head into its ``[L0, skip_1, ...]`` blocks.

    Args:
        heads: the group's heads (all read the same PE(x) block).
        x: [N, F + pe_max] the group's ``input_row``.
        t_enc: [1, T] PE(t) row or None (static).

    Returns:
        per head, its blocks (each [N, W], views of one [N, S] product).
    """
    w = torch.cat([h.w_x for h in heads])  # [S, F + pe_max]
    out = torch.addmm(_input_bias(heads, t_enc), x, w.t())  # [N, S]
    blocks = out.split([s for h in heads for s in h.sizes], dim=1)
    res, k = [], 0
    for h in heads:
        res.append(list(blocks[k: k + len(h.sizes)]))
        k += len(h.sizes)
    return res


def kernel_fits(mlp: FieldMLP) -> bool:
    """True when ``mlp`` can run as one ``head_mlp`` kernel: ReLU, width 32k <= 256, no skip into the output
    linear, at most 256 outputs (a head's few values, or a flow trunk's features), no output quirk. (A head whose
    last layer reads an extra input, the view-dependent colour head, cannot either: the caller checks that.)"""
    last = mlp.n_layers - 1
    return (mlp.activation == "relu" and mlp.n_layers >= 2 and mlp.width % 32 == 0 and mlp.width <= 256
            and last not in mlp.skips and mlp.out_dim <= 256 and not mlp.output_act_quirk)


def kernel_layers(head: HeadInput, weights: list[Tensor], t_enc: Tensor | None) -> HeadLayers:
    """One head's layers as the AMX kernel takes them (``src.fields.head_kernel.heads_mlp``).

    Args:
        head: the head's input-part columns (``HeadInput``; the layout of its group's ``input_row``).
        weights: ``head_weights(head.mlp, ...)``.
        t_enc: [1, T] PE(t) row or None (folded into the input-reading linears' biases).
    """
    mlp = head.mlp
    a = head.w_x.split(head.sizes)  # [W, K] per input-reading linear
    b_in = _input_bias([head], t_enc).split(head.sizes)
    hidden, bias, reads, k = [], [b_in[0]], [0], 1
    for i in range(1, mlp.n_layers - 1):
        if i in mlp.skips:  # W_skip [h_in, h] + b: the h part here, the h_in part and b in a[k] / b_in[k]
            reads.append(k)
            hidden.append(weights[i][:, mlp.in_dim: mlp.in_dim + mlp.width])
            bias.append(b_in[k])
            k += 1
        else:
            reads.append(-1)
            hidden.append(weights[i])
            bias.append(mlp.layers[i].bias)
    return a, hidden, bias, reads, weights[-1], mlp.layers[-1].bias


def head_outputs(heads: Sequence[HeadInput], weights: Sequence[list[Tensor]], x: Tensor, t_enc: Tensor | None,
                 kernel: Sequence[bool]) -> list[Tensor | list[Tensor]]:
    """Per head of a group: its output [N, O] where ``kernel`` (all such heads through ``heads_mlp``, their
    input row's gradients summed in the kernel), else its input blocks (``input_layer``, one product for all
    such heads) for ``head_tail``."""
    dense = [h for h, k in zip(heads, kernel, strict=True) if not k]
    blocks = iter(input_layer(dense, x, t_enc) if dense else [])
    layers = [kernel_layers(h, w, t_enc) for h, w, k in zip(heads, weights, kernel, strict=True) if k]
    outputs = iter(heads_mlp(x, layers) if layers else [])
    return [next(outputs) if k else next(blocks) for k in kernel]


def head_tail(mlp: FieldMLP, weights: list[Tensor], blocks: list[Tensor], extra: Tensor | None = None,
              last_dtype: torch.dtype | None = None) -> Tensor:
    """Finish one head from its input-part pre-activations ``blocks`` (``[L0, skip_1, ...]``, each [N, W]).

    Equals ``mlp(h_in, extra=extra)`` (same activation, output quirk). ``last_dtype``: run the output
    linear in this dtype outside autocast (float32 keeps the outputs accurate under bf16 autocast).
    """
    act = mlp._act
    k, last = 1, mlp.n_layers - 1
    h = act(blocks[0])  # [N, width]
    for i in range(1, mlp.n_layers):
        w = weights[i]
        if i < last and mlp.activation == "relu":  # hidden layer: product, bias, ReLU fused (linear_relu.py)
            if i in mlp.skips:  # W_skip [h_in, h] + b = (W_x h_in + b) + W_h h, the first term in blocks[k]
                h = linear_relu(h, w[:, mlp.in_dim: mlp.in_dim + mlp.width], None, blocks[k])
                k += 1
            else:
                h = linear_relu(h, w, mlp.layers[i].bias)
            continue
        if i == last and last_dtype is not None:
            with torch.autocast(h.device.type, enabled=False):
                h = h.to(last_dtype)
                extra = extra.to(last_dtype) if extra is not None else None
                h = _linear_part(h, w, mlp, blocks, k, i, extra)
        else:
            h = _linear_part(h, w, mlp, blocks, k, i, extra)
        if i in mlp.skips:
            k += 1
        if i < last:
            h = act(h)
    if mlp.output_act_quirk:
        h = F.leaky_relu(h)
    return h


def _linear_part(h: Tensor, w: Tensor, mlp: FieldMLP, blocks: list[Tensor], k: int, i: int,
                 extra: Tensor | None) -> Tensor:
    """Linear i of ``mlp`` on the hidden state h [N, width] (+ its precomputed skip block, + extra)."""
    last = i == mlp.n_layers - 1
    start = mlp.in_dim if i in mlp.skips else 0
    if i in mlp.skips:  # W_skip [h_in, h] + b = (W_x h_in + b) + W_h h, the first term precomputed
        y = torch.addmm(blocks[k].to(h.dtype), h, w[:, start: start + mlp.width].t())
    else:
        y = F.linear(h, w[:, : mlp.width] if last and extra is not None else w, mlp.layers[i].bias)
    if last and extra is not None:
        y = y + F.linear(extra, w[:, start + mlp.width:])  # W_e PE(viewdir)
    return y
