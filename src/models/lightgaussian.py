"""3DGS with LightGaussian's spherical-harmonics distillation state (Fan et al., NeurIPS 2024, Sec. 3.3).

At the start of distillation the model keeps a frozen copy of itself, the *teacher* (its splats with the SH
coefficients up to the degree it had reached), and truncates its own SH coefficients to a lower degree,
the *student*. Training then matches the student's renders to the teacher's (the targets come from
:class:`src.strategy.lightgaussian.LightGaussianStrategy`). The teacher is held in buffers, so checkpoints
carry it and a resumed run goes on distilling from the same teacher; the student's degree follows from the
shape of its stored coefficients. As in the reference code, the opacities can be frozen while distilling.

Conventions: raw parameters are log-scales, logit opacities and (w, x, y, z) quaternions; colours are
max(0, SH + 0.5) for the view direction from the camera centre to the splat (:mod:`src.models.sh`).
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from src.core.cameras import Camera
from src.core.splats import Splats
from src.models.gaussians import GaussianSplatModel
from src.models.sh import eval_sh
from src.optim.adam import SplatOptimizer, swap_param

#: Teacher buffers: ``teacher_<name>`` holds the raw parameter ``name`` (``sh``: sh0 and shN together).
TEACHER_KEYS = ("means", "scales", "quats", "opacities", "sh")


def sh_degree_of(n_coeffs: int) -> int:
    """SH degree d of a coefficient set with ``n_coeffs`` = (d + 1)^2 entries per channel."""
    d = math.isqrt(n_coeffs) - 1
    if (d + 1) ** 2 != n_coeffs:
        raise ValueError(f"{n_coeffs} SH coefficients per channel is not a square (d + 1)^2")
    return d


def sh_colors(coeffs: Tensor, degree: int, means: Tensor, camera: Camera) -> Tensor:
    """[N, 3] colours max(0, SH_degree(dir) + 0.5) of coefficients [N, K, 3] seen from ``camera``.

    ``dir`` is the unit vector from the camera centre to each of ``means`` [N, 3] (world coordinates).
    """
    if degree == 0:
        return torch.clamp_min(eval_sh(0, coeffs, coeffs[:, 0]) + 0.5, 0.0)
    dirs = F.normalize(means - camera.center.to(means), dim=-1)
    return torch.clamp_min(eval_sh(degree, coeffs, dirs) + 0.5, 0.0)


class LightGaussianModel(GaussianSplatModel):
    """:class:`GaussianSplatModel` that can distil its SH colours into a lower degree.

    Args: those of :class:`GaussianSplatModel` (``init`` [N, 3] centres, ``sh_degree``, ...).
    """

    def __init__(self, init: Tensor, **kwargs: object) -> None:
        super().__init__(init, **kwargs)
        # [distilling, opacities frozen] as 0/1: a buffer, so checkpoints carry the distillation state
        self.register_buffer("distill_state", torch.zeros(2, dtype=torch.uint8))

    @property
    def distilling(self) -> bool:
        """True once :meth:`start_distillation` ran (the teacher exists)."""
        return bool(self.distill_state[0])

    @property
    def stored_sh_degree(self) -> int:
        """The SH degree the stored coefficients (sh0 and shN) can represent."""
        return sh_degree_of(self.params["shN"].shape[1] + 1)

    @property
    def teacher_sh_degree(self) -> int:
        """SH degree of the teacher's colours (-1 before distillation)."""
        return sh_degree_of(self.teacher_sh.shape[1]) if self.distilling else -1

    def on_step(self, iteration: int) -> None:
        super().on_step(iteration)
        self.active_sh_degree = min(self.active_sh_degree, self.stored_sh_degree)

    def splats(self, camera: Camera) -> Splats:
        """Activated splats; the opacities carry no gradient while they are frozen for distillation."""
        s = super().splats(camera)
        if bool(self.distill_state[1]):
            s.opacities = s.opacities.detach()
        return s

    @torch.no_grad()
    def start_distillation(self, optimizer: SplatOptimizer | None, degree: int, freeze_opacity: bool = True) -> None:
        """Freeze the current splats as the teacher and truncate the SH colours to ``degree`` (the student).

        The teacher keeps the coefficients up to the active degree; the student's ``shN`` loses the bands
        above ``degree`` (their Adam moments go with them). Calling it again is a no-op.
        """
        if self.distilling:
            return
        if degree < 0:
            raise ValueError(f"distillation SH degree must be >= 0, got {degree}")
        p = self.params
        k_teacher = (self.active_sh_degree + 1) ** 2
        coeffs = torch.cat([p["sh0"], p["shN"]], dim=1)[:, :k_teacher]  # [N, K_teacher, 3]
        raw = {"means": p["means"], "scales": p["scales"], "quats": p["quats"], "opacities": p["opacities"],
               "sh": coeffs}
        for k in TEACHER_KEYS:
            self.register_buffer(f"teacher_{k}", raw[k].detach().clone())
        k_student = (degree + 1) ** 2 - 1
        if p["shN"].shape[1] > k_student:
            p["shN"] = _replace_param_columns(optimizer, p["shN"], k_student)
        self.max_sh_degree = min(self.max_sh_degree, degree)
        self.active_sh_degree = min(self.active_sh_degree, degree)
        self.distill_state[0] = 1
        self.distill_state[1] = int(bool(freeze_opacity))

    @torch.no_grad()
    def teacher_splats(self, camera: Camera) -> Splats:
        """The teacher's activated splats seen from ``camera`` (view-dependent colours at its degree)."""
        if not self.distilling:
            raise RuntimeError("no teacher: start_distillation has not run")
        means = self.teacher_means
        return Splats(means=means, scales=torch.exp(self.teacher_scales), quats=self.teacher_quats,
                      opacities=torch.sigmoid(self.teacher_opacities),
                      colors=sh_colors(self.teacher_sh, self.teacher_sh_degree, means, camera))

    def load_state_dict(self, state_dict, strict: bool = True, assign: bool = False):
        """Load a checkpoint, also one taken while distilling (teacher buffers, truncated SH)."""
        for k in TEACHER_KEYS:
            key = f"teacher_{k}"
            if key in state_dict:
                self.register_buffer(key, torch.empty_like(state_dict[key], device=self.params["means"].device))
        out = super().load_state_dict(state_dict, strict=strict, assign=assign)
        self.max_sh_degree = min(self.max_sh_degree, self.stored_sh_degree)
        self.active_sh_degree = min(self.active_sh_degree, self.stored_sh_degree)
        return out


def _replace_param_columns(optimizer: SplatOptimizer | None, old: nn.Parameter, k: int) -> nn.Parameter:
    """A parameter holding ``old[:, :k]``, swapped into ``optimizer`` with its Adam moments sliced alike."""
    return swap_param(optimizer, old, nn.Parameter(old.data[:, :k].detach().clone()), lambda v: v[:, :k].clone())
