"""Adam over named parameter groups with 3DGS-style exponential learning-rate decay."""

from __future__ import annotations

import math
import warnings
from collections.abc import Callable
from dataclasses import dataclass

import torch
from torch import Tensor, nn


@dataclass
class LRSchedule:
    """Log-linear decay from ``init`` to ``final`` over ``max_steps`` (3DGS ``get_expon_lr_func``).

    With ``delay_steps`` > 0 the rate starts at ``delay_mult`` x and eases in with a sine ramp.
    ``scale_by_extent`` multiplies both ends by the scene extent (3DGS position LR).
    ``final`` None keeps the rate constant.
    """

    init: float
    final: float | None = None
    max_steps: int = 30_000
    delay_steps: int = 0
    delay_mult: float = 1.0
    scale_by_extent: bool = False

    def __call__(self, step: int, extent: float = 1.0) -> float:
        s = extent if self.scale_by_extent else 1.0
        if self.final is None or self.max_steps <= 0:
            return self.init * s
        if self.init <= 0:
            return 0.0
        if self.delay_steps > 0:
            delay = self.delay_mult + (1 - self.delay_mult) * math.sin(
                0.5 * math.pi * min(max(step / self.delay_steps, 0.0), 1.0))
        else:
            delay = 1.0
        t = min(max(step / self.max_steps, 0.0), 1.0)
        return delay * math.exp(math.log(self.init * s) * (1 - t) + math.log(self.final * s) * t)


class SplatOptimizer:
    """Adam with one group per named parameter set and a schedule per name.

    Args:
        groups: model parameter groups [{"name": str, "params": [tensors]}].
        lr: {name: LRSchedule kwargs}; a name missing here raises a KeyError naming it.
        eps: Adam epsilon (1e-15, as 3DGS and the SplatFields reference).
        betas: Adam betas.
        extent: scene extent for schedules with ``scale_by_extent``.
        fused: use torch's fused Adam kernel (same update to float rounding; on the CPU 4.5x faster
            than the default per-tensor loop over SplatFields4D's 8.5M ResField parameters, measured
            in one run). Falls back to the loop, with a warning, where torch has no fused kernel.
    """

    def __init__(self, groups: list[dict], lr: dict, eps: float = 1e-15,
                 betas: tuple[float, float] = (0.9, 0.999), extent: float = 1.0,
                 fused: bool = True) -> None:
        self.schedules: dict[str, LRSchedule] = {}
        torch_groups = []
        for g in groups:
            name = g["name"]
            if name not in lr:
                raise KeyError(f"optim.lr has no schedule for parameter group '{name}' (have {sorted(lr)})")
            sched = LRSchedule(**lr[name])
            self.schedules[name] = sched
            torch_groups.append({"name": name, "params": list(g["params"]), "lr": sched(0, extent)})
        self.extent = extent
        try:
            self.optimizer = torch.optim.Adam(torch_groups, lr=0.0, eps=eps, betas=tuple(betas),
                                              fused=fused or None)
        except RuntimeError as e:  # e.g. an old torch without the CPU kernel
            warnings.warn(f"optim.fused=true unavailable ({e}); using the per-tensor Adam loop", stacklevel=2)
            self.optimizer = torch.optim.Adam(torch_groups, lr=0.0, eps=eps, betas=tuple(betas))

    def set_step(self, step: int) -> dict[str, float]:
        """Apply every schedule at ``step``; returns {name: lr}."""
        out = {}
        for g in self.optimizer.param_groups:
            g["lr"] = self.schedules[g["name"]](step, self.extent)
            out[g["name"]] = g["lr"]
        return out

    def step(self) -> None:
        self.optimizer.step()

    def zero_grad(self) -> None:
        self.optimizer.zero_grad(set_to_none=True)

    def state_dict(self) -> dict:
        return self.optimizer.state_dict()

    def load_state_dict(self, state: dict) -> None:
        self.optimizer.load_state_dict(state)

    def group(self, name: str) -> dict:
        for g in self.optimizer.param_groups:
            if g["name"] == name:
                return g
        raise KeyError(name)


def swap_param(optimizer: SplatOptimizer | None, old: nn.Parameter, new: nn.Parameter,
               moment: Callable[[Tensor], Tensor]) -> nn.Parameter:
    """Put ``new`` in ``old``'s place in ``optimizer``; Adam's moments become ``moment(old_moment)``."""
    if optimizer is None:
        return new
    opt = optimizer.optimizer
    for g in opt.param_groups:
        for i, p in enumerate(g["params"]):
            if p is old:
                state = opt.state.pop(old, None)
                if state:
                    for k in ("exp_avg", "exp_avg_sq"):
                        state[k] = moment(state[k])
                    opt.state[new] = state
                g["params"][i] = new
                return new
    return new


def replace_param_rows(optimizer: SplatOptimizer | None, old: nn.Parameter, new_data: Tensor,
                       keep: Tensor | None, n_appended: int) -> nn.Parameter:
    """Swap ``old`` for a parameter holding ``new_data`` and keep Adam's moments consistent.

    ``new_data`` must equal ``old[keep]`` (all rows if ``keep`` is None) followed by ``n_appended``
    new rows; their Adam moments are zero.
    """
    def moment(v: Tensor) -> Tensor:
        v = v if keep is None else v[keep]
        if n_appended:
            v = torch.cat([v, torch.zeros((n_appended, *v.shape[1:]), dtype=v.dtype, device=v.device)])
        return v

    return swap_param(optimizer, old, nn.Parameter(new_data.detach().clone().requires_grad_(True)), moment)
