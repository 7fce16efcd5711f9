"""Divergence guard: stop a run that has failed, with a reason, instead of wasting the sweep's time.

Two kinds of checks: during training (non-finite losses and gradients, a collapsed training PSNR,
splat explosion) and once after evaluation (:meth:`DivergenceGuard.check_final`): a run whose splats
are gone, non-finite, out of every training camera's view, whose renders are flat, or whose test PSNR
is no better than rendering nothing at all (the background) has collapsed, whatever its PSNR.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import torch

from src.eval.metrics import mean_finite, psnr

if TYPE_CHECKING:
    from src.data.base import Scene
    from src.models.base import SplatModel
    from src.rasterizer.base import Rasterizer


class DivergenceError(RuntimeError):
    """Raised by the guard; the run record gets ``status: failed`` and this message as ``reason``."""


class DivergenceGuard:
    """Checks each iteration for non-finite losses/gradients, PSNR collapse and splat explosion.

    Args:
        check_grads: test every parameter gradient for NaN/Inf (cheap relative to an iteration).
        collapse_psnr: fail if the running training PSNR falls below this after ``warmup`` iterations
            (a collapsed render is a flat image, typically < 10 dB on object scenes).
        warmup: iterations before the PSNR test starts.
        ema: smoothing of the running PSNR.
        max_splats: fail if the model holds more splats than this (None = no test).
        min_gain_db: after training, a run fails if its test PSNR is not above the PSNR of the background
            alone on the same views (an empty render), by at least this margin ...
        gain_after: ... once the run has trained this many iterations (short smoke runs may not have
            left the background yet).
        flat_std: after training, fail if every checked render has a pixel standard deviation below this
            (a constant image), or differs from the background by less than this everywhere.
        far_factor: a splat farther than this x the scene extent from a camera is out of its view.
    """

    def __init__(self, check_grads: bool = True, collapse_psnr: float = 8.0, warmup: int = 500,
                 ema: float = 0.9, max_splats: int | None = None, min_gain_db: float = 0.5,
                 gain_after: int = 500, flat_std: float = 1e-3, far_factor: float = 100.0) -> None:
        self.check_grads = check_grads
        self.collapse_psnr = collapse_psnr
        self.warmup = warmup
        self.ema = ema
        self.max_splats = max_splats
        self.min_gain_db = min_gain_db
        self.gain_after = gain_after
        self.flat_std = flat_std
        self.far_factor = far_factor
        self.running_psnr: float | None = None

    def check_loss(self, loss: torch.Tensor, iteration: int) -> None:
        if not torch.isfinite(loss).all():
            raise DivergenceError(f"non-finite loss ({float(loss)}) at iteration {iteration}")

    def check_gradients(self, params, iteration: int) -> None:
        """Fail on a NaN/Inf in any gradient: one fused max-|g| per tensor (NaN and Inf propagate, no
        overflow) and a single host sync, instead of one ``isfinite().all()`` sync per parameter."""
        if not self.check_grads:
            return
        grads = [p.grad for p in params if p.grad is not None and p.grad.numel() > 0]
        if not grads:
            return
        peaks = torch.stack([n.float() for n in torch._foreach_norm(grads, math.inf)])  # [P] max |g| per tensor
        finite = torch.isfinite(peaks)
        if not finite.all():
            bad = grads[int((~finite).nonzero()[0, 0])]
            raise DivergenceError(f"non-finite gradient (shape {tuple(bad.shape)}) at iteration {iteration}")

    def check_psnr(self, value: float, iteration: int) -> None:
        if not math.isfinite(value):
            return
        self.running_psnr = value if self.running_psnr is None else (
            self.ema * self.running_psnr + (1 - self.ema) * value)
        if iteration >= self.warmup and self.running_psnr < self.collapse_psnr:
            raise DivergenceError(
                f"training PSNR collapsed to {self.running_psnr:.2f} dB (< {self.collapse_psnr}) "
                f"at iteration {iteration}")

    def check_splats(self, n: int, iteration: int) -> None:
        if self.max_splats is not None and n > self.max_splats:
            raise DivergenceError(f"{n} splats exceed the cap {self.max_splats} at iteration {iteration}")

    @torch.no_grad()
    def check_final(self, model: SplatModel, rasterizer: Rasterizer, scene: Scene, test_psnr: float,
                    iterations: int, max_views: int = 4) -> float:
        """Raise DivergenceError if the trained ``model`` has collapsed; returns the background PSNR.

        Checks, in order: no splats left; non-finite parameters; no splat centre in front of and
        inside any training camera's image; every render (up to ``max_views`` test views, else training
        views) flat or background-only; test PSNR not ``min_gain_db`` above the background's (only
        after ``gain_after`` iterations). "In view" means in front of the camera closer than
        ``far_factor`` x the scene extent (3DGS's far plane is 100 in normalised units) and inside the image.
        """
        if model.n_splats == 0:
            raise DivergenceError("collapse: no splats left (all pruned)")
        for name, p in model.named_parameters():
            if not torch.isfinite(p).all():
                raise DivergenceError(f"collapse: parameter {name} holds non-finite values")
        visible = 0
        far = self.far_factor * max(float(scene.extent), 1.0)
        for cam in _distinct_cameras(scene):
            means = model.splats(cam).means.detach()
            if not torch.isfinite(means).all():
                raise DivergenceError(f"collapse: non-finite splat centres for camera {cam.name!r}")
            uv, z = cam.project(means)
            in_image = (uv[:, 0] >= 0) & (uv[:, 0] <= cam.width) & (uv[:, 1] >= 0) & (uv[:, 1] <= cam.height)
            inside = (z > 1e-6) & (z < far) & in_image
            visible += int(inside.sum())
        if visible == 0:
            raise DivergenceError("collapse: every splat lies outside every training camera's view")
        views = (scene.test or scene.train)[:max_views]
        bg = scene.background.reshape(1, 1, 3)
        flat = True
        for v in views:
            img = rasterizer.render(model.splats(v.camera), v.camera, scene.background).color
            if not torch.isfinite(img).all():
                raise DivergenceError(f"collapse: non-finite render of view {v.camera.name!r}")
            if float(img.std()) >= self.flat_std and float((img - bg.to(img)).abs().max()) >= self.flat_std:
                flat = False
        if flat:
            raise DivergenceError(f"collapse: the renders of {len(views)} views are flat (constant or background only)")
        background_psnr = _mean_psnr_of_background(scene)
        if (iterations >= self.gain_after and math.isfinite(test_psnr) and math.isfinite(background_psnr)
                and test_psnr < background_psnr + self.min_gain_db):
            raise DivergenceError(
                f"collapse: test PSNR {test_psnr:.2f} dB is no better than an empty render's {background_psnr:.2f} dB "
                f"(the background alone; {self.min_gain_db} dB above it required)")
        return background_psnr


def _distinct_cameras(scene: Scene, limit: int = 16) -> list:
    """Training cameras, one per physical camera (``camera_id``) where known, at most ``limit``."""
    seen, out = set(), []
    for v in scene.train:
        key = v.camera.camera_id if v.camera.camera_id >= 0 else id(v)
        if key not in seen:
            seen.add(key)
            out.append(v.camera)
    return out[:limit]


def _mean_psnr_of_background(scene: Scene) -> float:
    """Mean PSNR (the evaluator's metric) over the test views (training views if none) of the plain background."""
    views = scene.test or scene.train
    return mean_finite([psnr(scene.background.reshape(1, 1, 3).to(v.image).expand_as(v.image), v.image)
                        for v in views])
