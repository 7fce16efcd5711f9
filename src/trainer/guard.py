"""Divergence guard: stop a run that has failed, with a reason, instead of wasting the sweep's time."""

from __future__ import annotations

import math

import torch


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
    """

    def __init__(self, check_grads: bool = True, collapse_psnr: float = 8.0, warmup: int = 500,
                 ema: float = 0.9, max_splats: int | None = None) -> None:
        self.check_grads = check_grads
        self.collapse_psnr = collapse_psnr
        self.warmup = warmup
        self.ema = ema
        self.max_splats = max_splats
        self.running_psnr: float | None = None

    def check_loss(self, loss: torch.Tensor, iteration: int) -> None:
        if not torch.isfinite(loss).all():
            raise DivergenceError(f"non-finite loss ({float(loss)}) at iteration {iteration}")

    def check_gradients(self, params, iteration: int) -> None:
        if not self.check_grads:
            return
        for p in params:
            if p.grad is not None and not torch.isfinite(p.grad).all():
                raise DivergenceError(f"non-finite gradient (shape {tuple(p.shape)}) at iteration {iteration}")

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
