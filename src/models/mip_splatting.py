"""Mip-Splatting's 3D smoothing filter on the 3DGS model (Yu et al., CVPR 2024, Sec. 5.1).

Each splat is convolved with an isotropic 3D Gaussian low-pass filter whose variance is set by the
highest rate at which any training camera samples the splat's centre:

    nu_k = max over training cameras seeing p_k of f / d_k      (pixels per world unit)
    sigma_k^2 = s / nu_k^2                                      (s = 0.2, the paper's value)

The filtered covariance R S^2 R^T + sigma^2 I equals R diag(s_i^2 + sigma^2) R^T, so the filter is
exactly the splat with scales sqrt(s_i^2 + sigma^2); the opacity is multiplied by
sqrt(det(Sigma) / det(Sigma + sigma^2 I)) = prod_i s_i / sqrt(s_i^2 + sigma^2) so that the filtered
splat keeps its integral (the 3D opacity compensation). The rasterizer is unchanged. The rates are
recomputed from the training cameras every ``filter_every`` iterations and after every change of
the splat set; test views are rendered with the rates of the training cameras.

Conventions: OpenCV cameras, log-scales, logit opacities, (w, x, y, z) quaternions.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from src.core.cameras import Camera
from src.core.splats import Splats
from src.models.gaussians import GaussianSplatModel
from src.optim.adam import SplatOptimizer
from src.rasterizer.projection import NEAR_PLANE


def max_sampling_rate(means: Tensor, cameras: list[Camera], margin: float = 0.15,
                      near: float = NEAR_PLANE) -> Tensor:
    """Maximal sampling rate of each point over the cameras whose view frustum holds it.

    A camera (OpenCV: x right, y down, z forward) samples a point at camera depth z with the rate
    f / z pixels per world unit, f = max(fx, fy). It counts when z > ``near`` and the point
    projects within ``margin`` x the image size of the image (the authors' code: 0.15).

    Args:
        means: [N, 3] points in world coordinates.
        cameras: pinhole cameras (the training views).
        margin: slack around the image, as a fraction of its width / height.
        near: points at camera depth <= near are not seen (3DGS's near plane).
    Returns:
        [N] rate nu >= 0 (pixels per world unit), 0 where no camera sees the point.
    """
    pts = means.detach()
    nu = torch.zeros(pts.shape[0], dtype=pts.dtype, device=pts.device)  # [N]
    for cam in cameras:
        w2c = cam.world_to_cam.to(device=pts.device, dtype=pts.dtype)
        p = pts @ w2c[:3, :3].T + w2c[:3, 3]  # [N, 3] camera coordinates
        z = p[:, 2]
        zs = torch.where(z > near, z, torch.ones_like(z))
        u = cam.fx * p[:, 0] / zs + cam.cx
        v = cam.fy * p[:, 1] / zs + cam.cy
        seen = ((z > near) & (u >= -margin * cam.width) & (u <= (1 + margin) * cam.width)
                & (v >= -margin * cam.height) & (v <= (1 + margin) * cam.height))
        rate = max(cam.fx, cam.fy) / zs
        nu = torch.where(seen, torch.maximum(nu, rate), nu)
    return nu


def filter_variance(nu: Tensor, scale: float) -> Tensor:
    """[N] 3D filter variance sigma^2 = scale / nu^2 (Mip-Splatting Sec. 5.1).

    Points seen by no camera (nu = 0) take the lowest rate among the seen ones (the authors' code);
    if no point is seen, every variance is 0 (no filter).
    """
    seen = nu > 0
    if not bool(seen.any()):
        return torch.zeros_like(nu)
    nu = torch.where(seen, nu, nu[seen].min())
    return scale / (nu * nu)


def smoothed_scales(log_scales: Tensor, variance: Tensor) -> tuple[Tensor, Tensor]:
    """Scales and opacity factor of splats convolved with an isotropic Gaussian of variance ``variance``.

    R diag(s^2) R^T + var I = R diag(s^2 + var) R^T, and the convolved splat keeps its integral
    when its opacity is multiplied by sqrt(det(Sigma) / det(Sigma + var I)) = prod_i s_i / sqrt(s_i^2 + var).

    Args:
        log_scales: [N, 3] log standard deviations; variance: [N] >= 0 (world units^2).
    Returns:
        (scales [N, 3] = sqrt(s^2 + var), factor [N] = prod_i s_i / sqrt(s_i^2 + var) in (0, 1]),
        evaluated in log space (log(s^2 + var) = logaddexp(2 log s, log var)), so that variance 0
        gives the unfiltered splat (factor 1) and the gradients stay finite for any scale.
    """
    log_var = torch.log(variance.to(log_scales))[:, None]  # [N, 1], -inf where 0
    log_s2f = torch.logaddexp(2 * log_scales, log_var)  # [N, 3] log(s^2 + var)
    scales = torch.exp(0.5 * log_s2f)
    log_factor = (log_scales - 0.5 * log_s2f).sum(dim=-1)  # [N] <= 0
    return scales, torch.exp(log_factor)


class MipGaussianSplatModel(GaussianSplatModel):
    """3DGS splats with Mip-Splatting's 3D smoothing filter (Yu et al. 2024, Sec. 5.1).

    The free parameters are those of :class:`GaussianSplatModel` (log-scales, logit opacities: the
    unfiltered splat); rendering and baking apply the filter of the buffer ``filter_var`` [N]
    (world units^2). Densification decisions use the unfiltered scales and opacities, the opacity
    reset clamps the filtered opacity (as the authors' code does).

    Args:
        init: [N, 3] initial centres (normalised world coordinates).
        filter_scale: s of sigma^2 = s / nu^2 (Mip-Splatting: 0.2).
        filter_every: recompute the sampling rates every this many iterations (0: only when the
            splat set changes and at the start).
        frustum_margin: a camera sees a centre that projects within this fraction of the image size
            outside its borders (authors' code: 0.15).
        **kwargs: the arguments of :class:`GaussianSplatModel`.
    """

    def __init__(self, init: Tensor, filter_scale: float = 0.2, filter_every: int = 100,
                 frustum_margin: float = 0.15, **kwargs: object) -> None:
        super().__init__(init, **kwargs)
        if filter_scale < 0 or not math.isfinite(filter_scale):
            raise ValueError(f"filter_scale must be finite and >= 0, got {filter_scale}")
        self.filter_scale = float(filter_scale)
        self.filter_every = int(filter_every)
        self.frustum_margin = float(frustum_margin)
        self.cameras: list[Camera] = []
        self.register_buffer("filter_var", torch.zeros(init.shape[0]))  # [N] sigma^2

    # -- the filter ------------------------------------------------------------------------
    def bind(self, scene) -> None:
        """Take the scene's training cameras and compute the filter from them."""
        self.cameras = [v.camera for v in scene.train]
        self.update_filter()

    @torch.no_grad()
    def update_filter(self) -> None:
        """Recompute ``filter_var`` from the training cameras (kept as is when none are bound)."""
        if not self.cameras:
            return
        means = self.params["means"].detach()
        nu = max_sampling_rate(means, self.cameras, self.frustum_margin)
        self.filter_var = filter_variance(nu, self.filter_scale).to(means)

    def on_step(self, iteration: int) -> None:
        super().on_step(iteration)
        if self.filter_every > 0 and iteration > 0 and iteration % self.filter_every == 0:
            self.update_filter()

    def _filtered(self) -> tuple[Tensor, Tensor]:
        """(scales [N, 3], opacities [N]) of the filtered splats."""
        scales, factor = smoothed_scales(self.params["scales"], self.filter_var)
        return scales, torch.sigmoid(self.params["opacities"]) * factor

    def splats(self, camera: Camera) -> Splats:
        scales, opacities = self._filtered()
        return Splats(means=self.params["means"], scales=scales, quats=self.params["quats"],
                      opacities=opacities, colors=self.colors(camera))

    def bake(self, time: float = 0.0, frame_id: int = 0) -> Splats:
        """The filtered splats with DC colours (a plain 3DGS splat set; the 2D Mip filter stays the
        rasterizer's)."""
        base = super().bake(time, frame_id)
        with torch.no_grad():
            scales, opacities = self._filtered()
        return Splats(means=base.means, scales=scales, quats=base.quats, opacities=opacities, colors=base.colors)

    # -- splat-set edits keep the buffer in step ----------------------------------------------
    def _edit(self, optimizer: SplatOptimizer | None, keep: Tensor | None,
              new: dict[str, Tensor] | None) -> None:
        super()._edit(optimizer, keep, new)
        var = self.filter_var if keep is None else self.filter_var[keep]
        n_new = self.n_splats - var.shape[0]
        self.filter_var = torch.cat([var, var.new_zeros(n_new)])
        self.update_filter()

    @torch.no_grad()
    def relocate(self, optimizer: SplatOptimizer | None, dead: Tensor, targets: Tensor,
                 generator: torch.Generator) -> None:
        super().relocate(optimizer, dead, targets, generator)
        self.filter_var[dead] = self.filter_var[targets]
        self.update_filter()

    def reset_opacity(self, optimizer: SplatOptimizer | None, value: float) -> None:
        """Opacity reset on the filtered opacity: sigmoid(o) x coef = min(sigmoid(o) x coef, value)."""
        with torch.no_grad():
            o = self.params["opacities"]
            _, factor = smoothed_scales(self.params["scales"], self.filter_var)  # [N] in (0, 1]
            over = torch.sigmoid(o.data) * factor > value  # [N] filtered opacity above the value
            target = (value / factor.clamp_min(1e-30)).clamp(max=1 - 1e-6)  # < 1 where over
            new = torch.where(over, torch.log(target) - torch.log1p(-target), o.data)
        self._set_opacities(optimizer, new)

    def load_state_dict(self, state_dict, strict: bool = True, assign: bool = False):
        """Load a checkpoint whose splat count may differ from the current one (resizes first)."""
        var = state_dict.get("filter_var")
        if var is not None and var.shape != self.filter_var.shape:
            self.filter_var = torch.zeros_like(var, device=self.filter_var.device)
        return super().load_state_dict(state_dict, strict=strict, assign=assign)


__all__ = ["MipGaussianSplatModel", "filter_variance", "max_sampling_rate", "smoothed_scales"]
