"""LightGaussian's training schedule (Fan et al., NeurIPS 2024) on top of 3DGS densification.

One run of ``iterations`` steps, the paper's stages at the same fractions of the run as the reference
schedule (a 30 000-iteration 3DGS, pruned and fine-tuned to 35 000, then distilled to 40 000):

1. 3DGS with adaptive density control (:class:`ADCStrategy`) until the first prune;
2. after each iteration ``round(f * iterations)`` of ``prune_at`` (reference: 30 001 of 40 000 -> 0.75),
   the least significant splats are removed: the k-th prune removes ``prune_ratio * prune_decay^k`` of
   them (reference: 0.66, once), ranked by LightGaussian's global significance over the training views
   (:func:`src.strategy.significance.global_significance`); densification, pruning by opacity and
   opacity resets stop at the first prune, and training goes on as fine-tuning ("recovery");
3. after iteration ``round(distill_at * iterations)`` (reference: 35 000 of 40 000 -> 0.875) the model
   becomes the teacher of a copy with SH colours of degree ``distill_degree``
   (:meth:`src.models.lightgaussian.LightGaussianModel.start_distillation`); from then on every step
   trains on the teacher's renders instead of the images: on ``pseudo_every - 1`` of every
   ``pseudo_every`` steps from a pseudo view, the sampled training camera moved by Gaussian noise of
   standard deviation ``pseudo_std`` (world units; rotation kept), otherwise from the training camera
   (:meth:`step_views`).

The vector quantisation of the result is :mod:`src.compress`.
"""

from __future__ import annotations

from dataclasses import replace

import torch

from src.core.cameras import Camera
from src.data.base import View
from src.models.base import SplatModel
from src.optim.adam import SplatOptimizer
from src.strategy.default import ADCStrategy
from src.strategy.significance import SCORES, global_significance


def schedule_iteration(fraction: float, iterations: int) -> int:
    """The 1-based iteration round(fraction * iterations), at least 1 (the stage runs after it)."""
    return max(1, round(float(fraction) * int(iterations)))


def pseudo_camera(camera: Camera, std: float, generator: torch.Generator) -> Camera:
    """``camera`` with its centre moved by N(0, std^2 I) (world units), the same orientation and intrinsics.

    OpenCV world-to-camera [R | t]: the centre c = -R^T t becomes c + e, so t becomes -R (c + e).
    """
    w2c = camera.world_to_cam
    eps = torch.randn(3, generator=generator, dtype=torch.float64).to(w2c) * std  # [3]
    out = w2c.clone()
    out[:3, 3] = w2c[:3, 3] - w2c[:3, :3] @ eps
    return replace(camera, world_to_cam=out, name=f"{camera.name}~pseudo")


class LightGaussianStrategy(ADCStrategy):
    """3DGS densification, then global-significance pruning, fine-tuning and SH distillation.

    Args:
        iterations: the run's iterations (``trainer.iterations``); ``prune_at`` and ``distill_at`` are
            fractions of it.
        prune_at: fractions of the run after which significance pruning runs (reference: [0.75]).
        prune_ratio: fraction of the splats the first prune removes (reference: 0.66).
        prune_decay: the k-th prune (from 0) removes ``prune_ratio * prune_decay^k`` (reference: 1.0).
        volume_power: beta of the volume term (paper: 0.1).
        score: ``hits`` (pixels hit x opacity, the paper's score) or ``blend`` (alpha T).
        distill_at: fraction of the run after which SH distillation starts (reference: 0.875); None = never.
        distill_degree: SH degree of the student (paper: 3 -> 2).
        pseudo_every: of every this many distillation steps, all but one render a pseudo view (reference: 3).
        pseudo_std: standard deviation of the pseudo views' camera-centre noise, world units (reference: 0.05).
        freeze_opacity: keep opacities fixed while distilling (reference: yes; scales, rotations, centres
            and colours train).
        Other arguments: :class:`ADCStrategy` (its window ends at the first prune).
    """

    def __init__(self, iterations: int = 40_000, prune_at: tuple[float, ...] | list[float] = (0.75,),
                 prune_ratio: float = 0.66, prune_decay: float = 1.0, volume_power: float = 0.1, score: str = "hits",
                 distill_at: float | None = 0.875, distill_degree: int = 2, pseudo_every: int = 3,
                 pseudo_std: float = 0.05, freeze_opacity: bool = True, grad_threshold: float = 2e-4,
                 percent_dense: float = 0.01, start_iter: int = 500, stop_iter: int = 15_000, every: int = 100,
                 prune_opacity: float = 0.005, prune_big_world: float = 0.1, reset_every: int = 3000,
                 reset_value: float = 0.01, n_split: int = 2, max_splats: int | None = None,
                 extent: float = 1.0) -> None:
        self.prune_iters = sorted(schedule_iteration(f, iterations) for f in prune_at)
        if not 0.0 <= prune_ratio < 1.0 or prune_decay < 0:
            raise ValueError(f"prune_ratio={prune_ratio} must be in [0, 1) and prune_decay={prune_decay} >= 0")
        if score not in SCORES:
            raise ValueError(f"score={score!r}: expected one of {SCORES}")
        if pseudo_every < 1 or pseudo_std < 0:
            raise ValueError(f"pseudo_every={pseudo_every} must be >= 1 and pseudo_std={pseudo_std} >= 0")
        first = self.prune_iters[0] if self.prune_iters else stop_iter
        super().__init__(grad_threshold=grad_threshold, percent_dense=percent_dense, start_iter=start_iter,
                         stop_iter=min(stop_iter, first), every=every, prune_opacity=prune_opacity,
                         prune_big_world=prune_big_world, reset_every=reset_every, reset_value=reset_value,
                         n_split=n_split, max_splats=max_splats, extent=extent)
        self.prune_ratio, self.prune_decay = prune_ratio, prune_decay
        self.volume_power, self.score = volume_power, score
        self.distill_iter = None if distill_at is None else schedule_iteration(distill_at, iterations)
        self.distill_degree = distill_degree
        self.pseudo_every, self.pseudo_std = pseudo_every, pseudo_std
        self.freeze_opacity = freeze_opacity
        self._scene = None
        self._rasterizer = None

    def bind(self, scene, rasterizer) -> None:
        """Keep the training views and the rasterizer (significance, teacher renders)."""
        self._scene, self._rasterizer = scene, rasterizer

    def after_step(self, model: SplatModel, optimizer: SplatOptimizer, iteration: int,
                   generator: torch.Generator) -> dict:
        if self.distill_iter is not None and not hasattr(model, "start_distillation"):
            raise TypeError(f"strategy=lightgaussian distils SH colours, which {type(model).__name__} cannot: "
                            "use model=lightgaussian (or strategy.distill_at=null)")
        stats = super().after_step(model, optimizer, iteration, generator)
        it = iteration + 1
        if it in self.prune_iters:
            ratio = self.prune_ratio * self.prune_decay ** self.prune_iters.index(it)
            stats.update(self.prune(model, optimizer, ratio))
        if self.distill_iter is not None and it == self.distill_iter:
            model.start_distillation(optimizer, self.distill_degree, self.freeze_opacity)
            stats["distill_start"] = 1
        return stats

    @torch.no_grad()
    def prune(self, model: SplatModel, optimizer: SplatOptimizer | None, ratio: float) -> dict:
        """Remove the round(ratio * N) splats of lowest global significance over the training views."""
        if self._scene is None or not self._scene.train:
            raise RuntimeError("LightGaussianStrategy.prune needs bind(scene, rasterizer) with training views")
        score = global_significance(model, self._rasterizer, self._scene.train, self.volume_power, self.score).cpu()
        n = model.n_splats
        n_remove = min(n - 1, round(ratio * n))
        if n_remove <= 0:
            return {"pruned": 0, "n_splats": n}
        order = torch.argsort(score, descending=True, stable=True)  # most significant first
        mask = torch.zeros(n, dtype=torch.bool)
        mask[order[n - n_remove:]] = True
        model.prune(optimizer, mask.to(model.canonical_means().device))
        return {"pruned": n_remove, "n_splats": model.n_splats}

    @torch.no_grad()
    def step_views(self, model: SplatModel, views: list[View], iteration: int,
                   generator: torch.Generator) -> list[View]:
        """While distilling: the teacher's renders (colour, and alpha as the mask) of pseudo or training views."""
        if not getattr(model, "distilling", False) or self.distill_iter is None:
            return views
        pseudo = (iteration - self.distill_iter) % self.pseudo_every != 0
        out = []
        for v in views:
            cam = pseudo_camera(v.camera, self.pseudo_std, generator) if pseudo else v.camera
            r = self._rasterizer.render(model.teacher_splats(cam), cam, self._scene.background)
            mask = r.alpha.clamp(0, 1) if v.mask is not None else None
            out.append(View(camera=cam, image=r.color.detach(), mask=mask, image_id=v.image_id))
        return out
