"""The field heads' input row ``[f, PE(x)]`` written in one pass (``csrc/encoded_row.cpp``).

Every head of a group reads the same row: the backbone feature f [N, F] followed by the positional
encoding of the points x [N, d] (``src.fields.encoding.PositionalEncoding``: ``[x, sin 2^0 x, cos 2^0 x,
..., sin 2^(L-1) x, cos 2^(L-1) x]``), in f's dtype. Through torch this is a product of the frequencies,
sine, cosine, a stack, two concatenations and a cast, forward, and as many operators backward; the
compiled op writes each row once and, backward, reads each row's gradient once for f's and x's gradients.
It runs where it applies (CPU, float32 points, f float32 or bfloat16, eager mode, the extension built);
elsewhere, and with ``fast=False``, the reference is ``src.fields.fused.input_row(f, pe(x))``.
``tests/test_encoded_row.py`` checks that both agree, values and gradients.
"""

from __future__ import annotations

import torch
from torch import Tensor

from src.fields.encoding import PositionalEncoding
from src.fields.fused import input_row
from src.kernels.build import field_op_ready


def row_op_ready() -> bool:
    """True when the input-row op's extension is built and loaded (a failed build warns once: torch's path then)."""
    return field_op_ready("encoded_row")


class _EncodedRow(torch.autograd.Function):
    """[f, PE_L(x)] [N, F + d (1 + 2L)] in f's dtype; gradients to f and x."""

    @staticmethod
    def forward(ctx, f: Tensor, x: Tensor, n_levels: int) -> Tensor:
        row, sc = torch.ops.splatfields_cpu.encoded_row_forward(f.detach().contiguous(), x.detach().contiguous(),
                                                               n_levels)
        ctx.save_for_backward(sc)  # [2, N, L, d] sines and cosines
        ctx.feat_dim = int(f.shape[1])
        return row

    @staticmethod
    def backward(ctx, g: Tensor):
        (sc,) = ctx.saved_tensors
        need_f, need_x = ctx.needs_input_grad[:2]
        g_f, g_x = torch.ops.splatfields_cpu.encoded_row_backward(g.contiguous(), sc, ctx.feat_dim, need_f, need_x)
        return (g_f if need_f else None), (g_x if need_x else None), None


def encoded_row(f: Tensor, x: Tensor, pe: PositionalEncoding, fast: bool = True) -> Tensor:
    """The heads' input row ``[f, pe(x)]`` [N, F + pe.out_dim(d)] in f's dtype (module docstring).

    Args:
        f: [N, F] backbone features (F may be 0).
        x: [N, d] points, float32 (may require gradient).
        pe: the row's positional encoding (with its input included and at least one level for the op).
        fast: the compiled op where it applies; False: ``src.fields.fused.input_row(f, pe(x))``.
    """
    if (fast and f.device.type == "cpu" and x.dtype == torch.float32 and f.dtype in (torch.float32, torch.bfloat16)
            and pe.include_input and 1 <= pe.n_levels <= 16 and 1 <= x.shape[1] <= 8 and f.shape[0] == x.shape[0]
            and not torch.compiler.is_compiling() and row_op_ready()):
        return _EncodedRow.apply(f if f.shape[1] > 0 else f.float(), x, pe.n_levels)  # PE alone: float32, as below
    return input_row(f, pe(x))
