"""NeRF-style positional encoding (SplatFields flavour: frequencies 2^0 .. 2^(L-1), no factor π)."""

from __future__ import annotations

import torch
from torch import Tensor, nn


class PositionalEncoding(nn.Module):
    """gamma(x) = [x, sin(2^0 x), cos(2^0 x), ..., sin(2^(L-1) x), cos(2^(L-1) x)].

    Each sin/cos block is applied to all ``d`` input dimensions at once, so the output layout is
    ``[x (d), sin(f0 x) (d), cos(f0 x) (d), sin(f1 x) (d), ...]`` (the reference embedder's order).
    The frequencies are ``2^l`` without the factor π of the original NeRF paper (as the SplatFields
    reference, ``utils/time_utils.py``); there is no coarse-to-fine annealing.

    Args:
        n_levels: number of frequency levels L (supplementary B.2 uses 4 for positions, time and view
            directions). ``L = 0`` is the identity (the raw input is returned unchanged).
        include_input: prepend the raw input (NeRF default, as the reference).
    """

    def __init__(self, n_levels: int, include_input: bool = True) -> None:
        super().__init__()
        if n_levels < 0:
            raise ValueError(f"n_levels must be >= 0, got {n_levels}")
        self.n_levels = int(n_levels)
        self.include_input = bool(include_input)
        # [L] frequencies 2^0 .. 2^(L-1); a buffer so .to(device/dtype) follows the module.
        self.register_buffer(
            "freqs", 2.0 ** torch.arange(self.n_levels, dtype=torch.float32), persistent=False
        )

    def out_dim(self, in_dim: int) -> int:
        """Output width for an input of width ``in_dim``: d + 2·d·L (or d when L = 0)."""
        if self.n_levels == 0:
            return in_dim
        return in_dim * (int(self.include_input) + 2 * self.n_levels)

    def forward(self, x: Tensor) -> Tensor:
        """Encode ``x`` [..., d] -> [..., out_dim(d)]."""
        if self.n_levels == 0:
            return x
        freqs = self.freqs.to(x.dtype)
        xf = x.unsqueeze(-2) * freqs[:, None]  # [..., L, d]
        # [..., L, 2, d]: sin then cos for each level, flattened level-major.
        sc = torch.stack([torch.sin(xf), torch.cos(xf)], dim=-2)
        enc = sc.flatten(-3)  # [..., 2·L·d]
        if self.include_input:
            enc = torch.cat([x, enc], dim=-1)
        return enc

    def extra_repr(self) -> str:
        return f"n_levels={self.n_levels}, include_input={self.include_input}"
