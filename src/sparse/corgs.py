"""CoR-GS (Zhang, Li, Yu, Huang, Gu, Zheng and Bai, "CoR-GS: Sparse-View 3D Gaussian Splatting via
Co-Regularization", ECCV 2024).

Two models of the run's configuration are trained side by side on the same views (a
:class:`~src.sparse.pair.CoTrainedPair`; they start from the same points and differ by the randomness
of their training: densification's samples, network initialisation). Their disagreement marks
inaccurate reconstruction, and two terms suppress it:

* co-pruning (Sec. 4.1): every ``prune_every`` iterations after ``prune_start``, each model's splats
  without a splat of the other model within a distance tau are removed (the non-matching mask M; the
  splat centres as rendered, so SplatFields' predicted positions, its query points removed with them);
* pseudo-view co-regularisation (Sec. 4.2): at a pseudo camera interpolated between a training camera
  and its nearest training camera, each model's render is pulled towards the other's (held fixed) with
  (1 - lambda) L1 + lambda D-SSIM, lambda = 0.2, weighted lambda_p = 1 against the training-view loss.

After training the first model is the run's (evaluated, written, counted).

Conventions: OpenCV cameras (x right, y down, z forward; ``world_to_cam`` rows of R are the camera axes).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import replace

import torch
from torch import Tensor

from src.core.cameras import Camera
from src.core.splats import RenderOutput
from src.data.base import View
from src.losses.ssim import ssim
from src.models.base import SplatModel
from src.rasterizer.base import Rasterizer
from src.sparse.base import SparseIngredient
from src.sparse.pair import CoTrainedPair, CoTrainingStrategy, MemberOptimizers
from src.strategy.base import Strategy


@torch.no_grad()
def nearest_distances(points: Tensor, others: Tensor, chunk: int = 1024) -> Tensor:
    """[N] Euclidean distance from each of ``points`` [N, 3] to its nearest point of ``others`` [M, 3]
    (inf when ``others`` is empty), computed in chunks of ``chunk`` rows."""
    if others.shape[0] == 0:
        return torch.full((points.shape[0],), math.inf, dtype=points.dtype, device=points.device)
    out = [torch.cdist(points[i:i + chunk], others).min(dim=1).values for i in range(0, points.shape[0], chunk)]
    return torch.cat(out) if out else points.new_zeros(0)


def co_prune_masks(first: Tensor, second: Tensor, threshold: float) -> tuple[Tensor, Tensor]:
    """The non-matching masks M of CoR-GS (Sec. 4.1): ([N] bool, [M] bool), True for each point of
    ``first`` [N, 3] (``second`` [M, 3]) whose nearest point of the other set is farther than ``threshold``."""
    return nearest_distances(first, second) > threshold, nearest_distances(second, first) > threshold


def _axis_angle_matrix(axis: Tensor, angle: float) -> Tensor:
    """[3, 3] rotation by ``angle`` about the unit ``axis`` [3] (Rodrigues)."""
    x, y, z = axis.tolist()
    k = torch.tensor([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]], dtype=axis.dtype)
    return torch.eye(3, dtype=axis.dtype) + math.sin(angle) * k + (1 - math.cos(angle)) * (k @ k)


def interpolate_rotation(ra: Tensor, rb: Tensor, s: float) -> Tensor:
    """[3, 3] the rotation a fraction ``s`` of the way from ``ra`` to ``rb`` along the shortest arc (the
    geodesic, as a quaternion slerp): ra @ exp(s log(ra^T rb))."""
    rel = (ra.T @ rb).double()  # [3, 3]
    cos = float(((rel.trace() - 1.0) / 2.0).clamp(-1.0, 1.0))
    angle = math.acos(cos)
    if angle < 1e-9:
        return ra.clone()
    if math.pi - angle < 1e-6:  # opposite orientations: no unique arc
        return (ra if s < 0.5 else rb).clone()
    axis = torch.stack([rel[2, 1] - rel[1, 2], rel[0, 2] - rel[2, 0], rel[1, 0] - rel[0, 1]]) / (2 * math.sin(angle))
    return (ra.double() @ _axis_angle_matrix(axis, s * angle)).to(ra.dtype)


def pseudo_camera(anchor: Camera, cameras: list[Camera], s: float) -> Camera:
    """A camera a fraction ``s`` in [0, 1] of the way from ``anchor`` to its nearest camera of ``cameras``
    (by centre distance; cameras at the anchor's centre are skipped): centre linearly, orientation along
    the geodesic; intrinsics, image size, time and frame of ``anchor``. ``anchor`` itself when no other
    camera exists."""
    c0 = anchor.center.double()
    others = [c for c in cameras if float((c.center.double() - c0).norm()) > 1e-9]
    if not others:
        return anchor
    near = min(others, key=lambda c: float((c.center.double() - c0).norm()))
    centre = (1 - s) * c0 + s * near.center.double().to(c0.device)  # [3]
    w2c0 = anchor.world_to_cam
    rot = interpolate_rotation(w2c0[:3, :3].double().cpu(), near.world_to_cam[:3, :3].double().cpu(), s)
    w2c = torch.eye(4, dtype=torch.float64)
    w2c[:3, :3] = rot
    w2c[:3, 3] = -rot @ centre.cpu()
    return replace(anchor, world_to_cam=w2c.to(dtype=w2c0.dtype, device=w2c0.device),
                   name=f"pseudo({anchor.name},{near.name},{s:.3f})")


def photometric(a: Tensor, b: Tensor, dssim: float) -> Tensor:
    """(1 - dssim) L1 + dssim (1 - SSIM) between images a, b [H, W, C] (scalar)."""
    out = (1 - dssim) * (a - b).abs().mean()
    if dssim > 0:
        out = out + dssim * (1 - ssim(a, b))
    return out


class CoRGS(SparseIngredient):
    """Co-training of two models with co-pruning and pseudo-view co-regularisation (CoR-GS).

    Args:
        prune_every: co-prune after every this many iterations (1-based ``iteration % prune_every == 0``,
            as the authors' code); 0 disables co-pruning.
        prune_start: co-prune only after this (1-based) iteration (the authors: ``densify_from_iter``).
        prune_threshold: tau, as a fraction of the scene extent (``Scene.extent``).
        coreg_weight: lambda_p of the pseudo-view term (Sec. 4.2: 1.0); 0 disables it.
        coreg_dssim: lambda of its (1 - lambda) L1 + lambda D-SSIM (Sec. 4.2: 0.2).
        coreg_start, coreg_end: the fraction of the run's iterations between which pseudo views are used
            (the authors' code: 2 000 to 10 000 of 10 000 iterations, so 0.2 and 1.0).

    Pseudo views and their interpolation fractions are drawn with the run's generator.
    """

    def __init__(self, prune_every: int = 500, prune_start: int = 500, prune_threshold: float = 0.05,
                 coreg_weight: float = 1.0, coreg_dssim: float = 0.2, coreg_start: float = 0.2,
                 coreg_end: float = 1.0) -> None:
        if prune_every < 0 or prune_threshold <= 0 or coreg_weight < 0 or not 0 <= coreg_dssim <= 1 \
                or not 0 <= coreg_start <= coreg_end <= 1:
            raise ValueError(f"sparse.corgs: prune_every >= 0, prune_threshold > 0, coreg_weight >= 0, coreg_dssim "
                             f"in [0, 1] and 0 <= coreg_start <= coreg_end <= 1 expected (got {prune_every}, "
                             f"{prune_threshold}, {coreg_weight}, {coreg_dssim}, {coreg_start}, {coreg_end})")
        self.prune_every = int(prune_every)
        self.prune_start = int(prune_start)
        self.prune_threshold = float(prune_threshold)
        self.coreg_weight = float(coreg_weight)
        self.coreg_dssim = float(coreg_dssim)
        self.coreg_start, self.coreg_end = float(coreg_start), float(coreg_end)
        self.cameras: list[Camera] = []
        self.extent = 1.0
        self.coreg_iters = (0, 0)

    def prepare(self, model: SplatModel, strategy: Strategy, build_model: Callable[[], SplatModel],
                build_strategy: Callable[[], Strategy]) -> tuple[SplatModel, Strategy]:
        """The run's model and a second one of the same configuration, each with its own strategy."""
        return CoTrainedPair(model, build_model()), CoTrainingStrategy([strategy, build_strategy()])

    def bind(self, model: SplatModel, scene, rasterizer, iterations: int) -> None:
        if not isinstance(model, CoTrainedPair):
            raise TypeError("sparse.corgs trains the CoTrainedPair its prepare() built")
        self.cameras = [v.camera for v in scene.train]
        self.extent = float(scene.extent)
        n = int(iterations)
        self.coreg_iters = (round(self.coreg_start * n), round(self.coreg_end * n))

    def loss_terms(self, model: SplatModel, views: list[View], renders: list[RenderOutput], rasterizer: Rasterizer,
                   background: Tensor, iteration: int, generator: torch.Generator) -> dict[str, Tensor]:
        """``coreg``: lambda_p x the mean over the two models of their photometric distance to the other's
        render (held fixed) at one pseudo view near the step's first training camera."""
        lo, hi = self.coreg_iters
        if self.coreg_weight == 0 or not lo <= iteration < hi:
            return {}
        s = float(torch.rand(1, generator=generator, dtype=torch.float64))
        cam = pseudo_camera(views[0].camera, self.cameras, s)
        images = [rasterizer.render(m.splats_for([cam])[0], cam, background).color for m in model.members]
        terms = [photometric(images[i], images[1 - i].detach(), self.coreg_dssim) for i in range(2)]
        return {"coreg": self.coreg_weight * torch.stack(terms).mean()}

    def prune_due(self, iteration: int) -> bool:
        """Whether the step of 0-based ``iteration`` co-prunes (the authors' 1-based rule)."""
        it = iteration + 1
        return self.prune_every > 0 and it > self.prune_start and it % self.prune_every == 0

    @torch.no_grad()
    def after_step(self, model: SplatModel, optimizer: MemberOptimizers, iteration: int,
                   generator: torch.Generator) -> dict:
        """Co-prune both models when due; the numbers of splats removed (``coprune``, ``second.coprune``)."""
        if not self.prune_due(iteration):
            return {}
        cam = self.cameras[0]  # static positions: any camera gives the same centres
        centres = [m.splats(cam).means.detach() for m in model.members]  # [N_i, 3] as rendered (SplatFields: predicted)
        masks = co_prune_masks(centres[0], centres[1], self.prune_threshold * self.extent)
        stats = {}
        for i, (m, opt, mask) in enumerate(zip(model.members, optimizer.members, masks, strict=True)):
            n = int(mask.sum())
            pruned = n if 0 < n < m.n_splats else 0  # never the whole set
            if pruned:
                m.prune(opt, mask)
            stats["coprune" if i == 0 else "second.coprune"] = pruned
        return stats

    def final_model(self, model: SplatModel) -> SplatModel:
        return model.first if isinstance(model, CoTrainedPair) else model
