"""Splats held as free per-splat parameters: the bookkeeping that 3DGS (:mod:`src.models.gaussians`) and
4D-GS (:mod:`src.models.gs4d`) share.

The parameters are the rows of one ``nn.ParameterDict`` ``params``, one row per splat, with at least
``means`` [N, 3], ``scales`` [N, S] (log; the first three spatial), ``opacities`` [N] (logit) and
the SH colour coefficients. Densification edits every entry's rows together and keeps the Adam moments
of the rows it keeps.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor, nn

from src.models.base import SplatModel
from src.optim.adam import SplatOptimizer, replace_param_rows, swap_param


def logit(p: float) -> float:
    """The inverse of the sigmoid at ``p`` in (0, 1)."""
    return math.log(p / (1.0 - p))


class FreeSplatModel(SplatModel):
    """A :class:`SplatModel` whose splats are the rows of ``params``; subclasses build ``params`` and
    set the SH schedule's ``max_sh_degree``, ``sh_degree_interval`` and ``active_sh_degree``.

    Densification: a subclass provides :meth:`_split_children` (the children of a split); clone, split,
    prune and the opacity reset are shared.
    """

    params: nn.ParameterDict
    max_sh_degree: int
    sh_degree_interval: int
    active_sh_degree: int

    @property
    def n_splats(self) -> int:
        return self.params["means"].shape[0]

    def param_groups(self) -> list[dict]:
        """One group per entry of ``params``, named as the entry."""
        return [{"name": k, "params": [p]} for k, p in self.params.items()]

    def on_step(self, iteration: int) -> None:
        """Raise the active SH degree by one every ``sh_degree_interval`` iterations, up to ``max_sh_degree``."""
        if self.sh_degree_interval > 0:
            self.active_sh_degree = min(self.max_sh_degree, iteration // self.sh_degree_interval)

    def load_state_dict(self, state_dict, strict: bool = True, assign: bool = False):
        """Load a checkpoint whose splat count may differ from the current one (resizes first)."""
        for name in list(self.params.keys()):
            key = f"params.{name}"
            if key in state_dict and state_dict[key].shape != self.params[name].shape:
                self.params[name] = nn.Parameter(torch.empty_like(state_dict[key], device=self.params[name].device))
        return super().load_state_dict(state_dict, strict=strict, assign=assign)

    # -- densification ---------------------------------------------------------------------------
    def canonical_means(self) -> Tensor:
        return self.params["means"].detach()

    def max_scale(self) -> Tensor:
        """[N] largest spatial scale (a 4D splat's time scale is not compared with the scene extent)."""
        return torch.exp(self.params["scales"].detach()[:, :3]).max(dim=1).values

    def opacity_values(self) -> Tensor:
        return torch.sigmoid(self.params["opacities"].detach())

    def _edit(self, optimizer: SplatOptimizer | None, keep: Tensor | None,
              new: dict[str, Tensor] | None) -> None:
        """Keep the rows ``keep`` [N] bool (all if None) of every entry, then append the rows of ``new``
        (entry name -> [M, ...]); the optimiser's moments follow (zero for the new rows)."""
        n_new = 0 if new is None else next(iter(new.values())).shape[0]
        for name in list(self.params.keys()):
            old = self.params[name]
            data = old.data if keep is None else old.data[keep]
            if new is not None:
                data = torch.cat([data, new[name].to(data)])
            self.params[name] = replace_param_rows(optimizer, old, data, keep, n_new)

    def _split_children(self, idx: Tensor, n_split: int, generator: torch.Generator) -> dict[str, Tensor]:
        """The ``n_split`` children of each splat in ``idx`` [M] (entry name -> [n_split · M, ...])."""
        raise NotImplementedError

    def densify(self, optimizer: SplatOptimizer | None, clone: Tensor, split: Tensor, n_split: int,
                generator: torch.Generator) -> None:
        """3DGS clone (copy the splats ``clone`` [N] bool) and split (replace the splats ``split`` [N] bool
        by :meth:`_split_children`)."""
        new = {k: v.data[clone] for k, v in self.params.items()}
        if split.any():
            children = self._split_children(torch.nonzero(split).squeeze(1), n_split, generator)
            new = {k: torch.cat([new[k], children[k]]) for k in new}
        self._edit(optimizer, None, new)
        if split.any():
            keep = torch.ones(self.n_splats, dtype=torch.bool, device=split.device)
            keep[: split.shape[0]][split] = False
            self._edit(optimizer, keep, None)

    def prune(self, optimizer: SplatOptimizer | None, mask: Tensor) -> None:
        self._edit(optimizer, ~mask, None)

    def reset_opacity(self, optimizer: SplatOptimizer | None, value: float) -> None:
        """3DGS opacity reset: opacity = min(opacity, value), Adam moments of opacities zeroed."""
        o = self.params["opacities"]
        self._set_opacities(optimizer, torch.minimum(o.data, torch.full_like(o.data, logit(value))))

    def _set_opacities(self, optimizer: SplatOptimizer | None, logits: Tensor) -> None:
        """Replace the opacity logits [N] by ``logits``, their Adam moments zeroed (an opacity reset)."""
        self.params["opacities"] = swap_param(optimizer, self.params["opacities"],
                                              nn.Parameter(logits.detach().clone()), torch.zeros_like)
