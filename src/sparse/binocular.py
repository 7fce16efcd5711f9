"""Binocular self-consistency of Binocular3DGS (Han, Zhou and Liu, "Binocular-Guided 3D Gaussian
Splatting with View Consistency for Sparse View Synthesis", NeurIPS 2024).

For a training view, a virtual camera is the training camera moved along its own x axis by a baseline
d (a random magnitude up to ``max_baseline`` and a random sign): the two form a rectified stereo pair.
The virtual camera's render is warped back to the training view with the disparity that the training
view's rendered depth z implies, f_x d / z pixels, and compared with the training image (L1 over the
pixels that have a depth and whose source lies inside the virtual image). Gradients reach the virtual
render and, through the disparity, the training view's depth: the splats are pulled to the depth that
makes the two views agree. An edge-aware smoothness of the disparity (the authors' code, weight 0.05)
is added. Opacity decay, the paper's other ingredient, is :mod:`src.sparse.opacity_decay`.

Conventions: OpenCV cameras (x right, y down, z forward), pixel (i, j) centred at (i + 0.5, j + 0.5);
``RenderOutput.depth`` is the accumulated sum z alpha T, so the expected depth is depth / alpha.
"""

from __future__ import annotations

from dataclasses import replace

import torch
import torch.nn.functional as F
from torch import Tensor

from src.core.cameras import Camera
from src.core.splats import RenderOutput
from src.data.base import View
from src.models.base import SplatModel
from src.rasterizer.base import Rasterizer
from src.sparse.base import SparseIngredient, members_of, split_by_member


def shifted_camera(camera: Camera, baseline: float) -> Camera:
    """``camera`` moved by ``baseline`` (world units) along its own x axis, with the same rotation and
    intrinsics: its centre is C + baseline * x_axis, and a point at camera coordinates (X, Y, Z) has
    (X - baseline, Y, Z) in it, so it projects ``camera.fx * baseline / Z`` pixels further left."""
    w2c = camera.world_to_cam.clone()  # [4, 4]
    w2c[0, 3] = w2c[0, 3] - baseline
    return replace(camera, world_to_cam=w2c, name=f"{camera.name}~x{baseline:+.4g}")


def warp_from_shifted(shifted: Tensor, depth: Tensor, fx: float, baseline: float) -> tuple[Tensor, Tensor, Tensor]:
    """Warp the render of :func:`shifted_camera` (``camera``, ``baseline``) back to ``camera``.

    Args:
        shifted: [H, W, C] the shifted camera's render.
        depth: [H, W] positive camera-space depth z of every pixel of the original view.
        fx: the cameras' horizontal focal length (pixels).
        baseline: the shift d along the camera's x axis (world units).

    Returns:
        (warped [H, W, C], inside [H, W] bool, disparity [H, W]): ``warped[v, u]`` is ``shifted`` sampled
        bilinearly at (u + 0.5 - disparity, v + 0.5) with disparity = fx * d / z (pixels); ``inside``
        marks the pixels whose sample lies between the first and the last pixel centre of ``shifted``.
        Differentiable in ``shifted`` and ``depth``.
    """
    h, w = depth.shape
    disparity = fx * baseline / depth  # [H, W] pixels
    u = torch.arange(w, dtype=depth.dtype, device=depth.device) + 0.5  # [W] pixel centres
    v = torch.arange(h, dtype=depth.dtype, device=depth.device) + 0.5  # [H]
    x = u[None, :] - disparity  # [H, W] sample positions in the shifted image (pixels)
    y = v[:, None].expand(h, w)  # [H, W]
    grid = torch.stack([2.0 * x / w - 1.0, 2.0 * y / h - 1.0], dim=-1)[None]  # [1, H, W, 2], align_corners=False
    image = shifted.permute(2, 0, 1)[None].to(depth.dtype)  # [1, C, H, W]
    warped = F.grid_sample(image, grid, mode="bilinear", padding_mode="zeros", align_corners=False)
    inside = (x >= 0.5) & (x <= w - 0.5)  # [H, W]
    return warped[0].permute(1, 2, 0), inside, disparity


def edge_aware_smoothness(disparity: Tensor, image: Tensor) -> Tensor:
    """Mean |d_x disparity| exp(-0.33 |d_x I|) + mean |d_y disparity| exp(-0.33 |d_y I|), scalar.

    Central differences on the interior pixels; the image's differences are summed over its channels.
    ``disparity`` [H, W], ``image`` [H, W, C].
    """
    ddx = 0.5 * (disparity[1:-1, 2:] - disparity[1:-1, :-2])  # [H-2, W-2]
    ddy = 0.5 * (disparity[2:, 1:-1] - disparity[:-2, 1:-1])
    idx = 0.5 * (image[1:-1, 2:] - image[1:-1, :-2]).sum(-1)
    idy = 0.5 * (image[2:, 1:-1] - image[:-2, 1:-1]).sum(-1)
    return (ddx.abs() * torch.exp(-0.33 * idx.abs())).mean() + (ddy.abs() * torch.exp(-0.33 * idy.abs())).mean()


class BinocularConsistency(SparseIngredient):
    """Binocular3DGS's self-consistency loss between each training view and a virtual shifted view.

    Args:
        weight: weight of the masked L1 between the warped virtual render and the training image (the
            authors' code adds it with weight 1).
        max_baseline: the largest |d|, as a fraction of the training camera's distance to the scene
            centre (the normalised origin): the authors draw d uniformly in [0, 0.4] world units with a
            random sign, their Blender cameras 4.03 units from the centre, so 0.1.
        start: the fraction of the run's iterations after which the loss applies (the authors' Blender
            runs: iteration 4 000 of 7 000, so 0.571; 857 of the 1 500 at the CPU scale).
        smooth_weight: weight of :func:`edge_aware_smoothness` of the masked disparity (the authors'
            code: 0.05).
        min_alpha: pixels of the training render with less accumulated opacity carry no depth and are
            left out (no paper value: the authors divide by the unnormalised accumulated depth, which
            sends such pixels' samples outside the image).

    The virtual camera's splats come from the model (``splats_for``), so view-dependent colours are
    evaluated for it; baselines and signs are drawn with the run's generator.
    """

    def __init__(self, weight: float = 1.0, max_baseline: float = 0.1, start: float = 0.571,
                 smooth_weight: float = 0.05, min_alpha: float = 0.5) -> None:
        if weight < 0 or smooth_weight < 0 or max_baseline <= 0 or not 0.0 <= start <= 1.0 or not 0.0 <= min_alpha < 1:
            raise ValueError(f"sparse.binocular: weights must be >= 0, max_baseline > 0, start in [0, 1] and "
                             f"min_alpha in [0, 1) (got weight={weight}, smooth_weight={smooth_weight}, "
                             f"max_baseline={max_baseline}, start={start}, min_alpha={min_alpha})")
        self.weight = float(weight)
        self.max_baseline = float(max_baseline)
        self.start = float(start)
        self.smooth_weight = float(smooth_weight)
        self.min_alpha = float(min_alpha)
        self.start_iter = 0

    def bind(self, model, scene, rasterizer, iterations: int) -> None:
        self.start_iter = round(self.start * int(iterations))

    def baseline(self, camera: Camera, generator: torch.Generator) -> float:
        """A random signed baseline: |d| uniform in [0, max_baseline x the camera's distance to the centre]."""
        u = torch.rand(2, generator=generator, dtype=torch.float64)
        sign = 1.0 if float(u[1]) < 0.5 else -1.0
        return sign * float(u[0]) * self.max_baseline * float(camera.center.double().norm())

    def view_terms(self, member: SplatModel, view: View, render: RenderOutput, rasterizer: Rasterizer,
                   background: Tensor, baseline: float) -> tuple[Tensor, Tensor]:
        """(masked L1, disparity smoothness) of one training view and its virtual view at ``baseline``."""
        cam = shifted_camera(view.camera, baseline)
        virtual = rasterizer.render(member.splats_for([cam])[0], cam, background)  # the virtual view
        alpha = render.alpha  # [H, W]
        valid = alpha.detach() > self.min_alpha  # [H, W] pixels with a depth
        z = render.depth / torch.where(valid, alpha, torch.ones_like(alpha))  # [H, W] expected depth
        valid = valid & (z.detach() > 1e-6)
        z = torch.where(valid, z, torch.ones_like(z))
        warped, inside, disparity = warp_from_shifted(virtual.color, z, view.camera.fx, baseline)
        mask = (valid & inside).to(warped.dtype)  # [H, W]
        l1 = (mask[..., None] * (warped - view.image).abs()).mean()
        smooth = edge_aware_smoothness(disparity * mask, view.image) if self.smooth_weight > 0 else l1.new_zeros(())
        return l1, smooth

    def loss_terms(self, model: SplatModel, views: list[View], renders: list[RenderOutput], rasterizer: Rasterizer,
                   background: Tensor, iteration: int, generator: torch.Generator) -> dict[str, Tensor]:
        """``binocular`` (weighted masked L1) and ``binocular_smooth`` averaged over the step's views, from
        ``start`` on; one virtual view per rendered training view (of each co-trained member)."""
        if iteration < self.start_iter or (self.weight == 0 and self.smooth_weight == 0):
            return {}
        l1s, smooths = [], []
        members = members_of(model)
        for member, vs, rs in zip(members, split_by_member(model, views), split_by_member(model, renders),
                                  strict=True):
            for v, r in zip(vs, rs, strict=True):
                l1, smooth = self.view_terms(member, v, r, rasterizer, background, self.baseline(v.camera, generator))
                l1s.append(l1)
                smooths.append(smooth)
        terms = {"binocular": self.weight * torch.stack(l1s).mean()}
        if self.smooth_weight > 0:
            terms["binocular_smooth"] = self.smooth_weight * torch.stack(smooths).mean()
        return terms
