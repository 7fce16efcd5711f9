"""Field MLPs with NeRF-style input skips, optional ResField (time-dependent) layers."""

from __future__ import annotations

from collections.abc import Sequence

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from src.fields.resfield import ResFieldLinear

ACTIVATIONS = ("relu", "leaky_relu", "silu")


def get_activation(name: str):
    """The elementwise activation function called ``name`` (relu, leaky_relu (slope 0.01), silu)."""
    if name == "relu":
        return F.relu
    if name == "leaky_relu":
        return F.leaky_relu  # slope 0.01, the reference's ``act='leaky_relu'``
    if name == "silu":
        return F.silu
    raise ValueError(f"activation must be one of {ACTIVATIONS}, got {name!r}")


class FieldMLP(nn.Module):
    """An MLP ``in_dim -> out_dim`` with ``n_layers`` linear layers in total.

    Layer indexing: linear 0 is the input layer (in_dim -> width), linears 1 .. n_layers-2 are hidden
    (width -> width), linear n_layers-1 is the output layer (width -> out_dim); so ``n_layers = 8``
    is the paper's "8-layer MLP" (supplementary B.2). The hidden activation follows every layer but
    the last.

    Args:
        in_dim: input width (e.g. PE(x) ++ feature ++ PE(t)).
        out_dim: output width.
        n_layers: number of linear layers including input and output (>= 2).
        width: hidden width.
        skips: linear indices i (1 <= i <= n_layers-1) before which the ORIGINAL input is
            concatenated to the hidden state (NeRF skip); that linear then has width + in_dim inputs.
            The reference's ``skips=[3]`` of an 8-linear net corresponds to ``skips=(4,)`` here.
        activation: hidden activation, ``"relu" | "leaky_relu" | "silu"``.
        rank, n_frames: ResField settings (see ``ResFieldLinear``); rank 0 -> static.
        resfield_layers: which linear indices are time-dependent when rank > 0. Default (None) = all
            hidden layers after the first, i.e. indices 2 .. n_layers-2 (reference ``GeneralMLP``:
            the first two linears and the output linear stay ordinary).
        output_act_quirk: apply LeakyReLU (slope 0.01) to the output layer, as the reference does
            (``out_act(act(W_L h))``). Default False: the output layer is linear (paper intent).
        last_layer_extra_dim: width of an extra input (e.g. encoded view direction) concatenated to
            the hidden state right before the LAST linear; pass it as ``extra`` in ``forward``.
        zero_init_output: set the output layer's weight and bias to 0 (the field then starts at a
            known value; callers use it for residual outputs).
    """

    def __init__(
        self,
        in_dim: int,
        out_dim: int,
        n_layers: int,
        width: int,
        skips: Sequence[int] = (),
        activation: str = "relu",
        rank: int = 0,
        n_frames: int = 0,
        resfield_layers: Sequence[int] | None = None,
        output_act_quirk: bool = False,
        last_layer_extra_dim: int = 0,
        zero_init_output: bool = False,
    ) -> None:
        super().__init__()
        if n_layers < 2:
            raise ValueError(f"n_layers counts input and output layers and must be >= 2, got {n_layers}")
        self.in_dim, self.out_dim, self.n_layers, self.width = in_dim, out_dim, n_layers, width
        self.skips = tuple(sorted(int(s) for s in skips))
        for s in self.skips:
            if not 1 <= s <= n_layers - 1:
                raise ValueError(f"skip index {s} must be in [1, {n_layers - 1}]")
        self.activation = activation
        self._act = get_activation(activation)
        self.output_act_quirk = bool(output_act_quirk)
        self.last_layer_extra_dim = int(last_layer_extra_dim)
        if resfield_layers is None:
            resfield_layers = range(2, n_layers - 1)
        self.resfield_layers = tuple(int(i) for i in resfield_layers) if rank > 0 and n_frames > 0 else ()

        layers = []
        for i in range(n_layers):
            fan_in = in_dim if i == 0 else width
            if i in self.skips:
                fan_in += in_dim
            if i == n_layers - 1:
                fan_in += self.last_layer_extra_dim
            fan_out = out_dim if i == n_layers - 1 else width
            r = rank if i in self.resfield_layers else 0
            layers.append(
                ResFieldLinear(fan_in, fan_out, rank=r, n_frames=n_frames if r > 0 else 0)
            )
        self.layers = nn.ModuleList(layers)
        if zero_init_output:
            nn.init.zeros_(self.layers[-1].weight)
            nn.init.zeros_(self.layers[-1].bias)

    def forward(
        self,
        x: Tensor,
        frame_id: int | Tensor | None = None,
        time: float | Tensor | None = None,
        extra: Tensor | None = None,
    ) -> Tensor:
        """x [N, in_dim] (+ extra [N, last_layer_extra_dim]) -> [N, out_dim]."""
        if (extra is None) != (self.last_layer_extra_dim == 0):
            raise ValueError(
                f"extra input of width {self.last_layer_extra_dim} expected, got "
                f"{None if extra is None else tuple(extra.shape)}"
            )
        h = x
        last = self.n_layers - 1
        for i, layer in enumerate(self.layers):
            if i in self.skips:
                h = torch.cat([x, h], dim=-1)  # [N, in_dim + width] (reference order: input first)
            if i == last and extra is not None:
                h = torch.cat([h, extra], dim=-1)  # [N, width + extra]
            h = layer(h, frame_id=frame_id, time=time)
            if i < last:
                h = self._act(h)
        if self.output_act_quirk:
            h = F.leaky_relu(h)  # reference quirk: act() on the output layer before out_act()
        return h
