"""Shared pytest fixtures: small random splat scenes and cameras."""

from __future__ import annotations

from src.kernels.threads import configure_openmp

configure_openmp()  # before anything loads torch's OpenMP runtime (src/kernels/threads.py)

import pytest
import torch

from src.core.cameras import Camera, look_at
from src.core.splats import Splats


def random_scene(n: int, seed: int = 0, dtype: torch.dtype = torch.float32, channels: int = 3,
                 spread: float = 0.5, scale_range: tuple[float, float] = (0.02, 0.12)) -> Splats:
    """N random splats around the origin (anisotropic scales, random rotations)."""
    g = torch.Generator().manual_seed(seed)
    lo, hi = scale_range
    return Splats(
        means=(torch.randn(n, 3, generator=g) * spread).to(dtype),
        scales=(torch.rand(n, 3, generator=g) * (hi - lo) + lo).to(dtype),
        quats=torch.randn(n, 4, generator=g).to(dtype),
        opacities=(torch.rand(n, generator=g) * 0.9 + 0.05).to(dtype),
        colors=torch.rand(n, channels, generator=g).to(dtype),
    )


def random_camera(width: int = 32, height: int = 32, seed: int = 0, dtype=torch.float32) -> Camera:
    """A camera on a sphere of radius ~3 looking at the origin, slightly off-centre principal point."""
    g = torch.Generator().manual_seed(seed)
    d = torch.randn(3, generator=g, dtype=torch.float64)
    eye = d / d.norm() * 3.0
    w2c = look_at(eye, torch.zeros(3, dtype=torch.float64)).to(dtype)
    f = 1.1 * width
    return Camera(w2c, fx=f, fy=f * 1.05, cx=width / 2 + 1.3, cy=height / 2 - 0.7, width=width, height=height)


@pytest.fixture
def tiny_scene():
    return random_scene(12, seed=1, dtype=torch.float64), random_camera(32, 32, seed=2, dtype=torch.float64)


@pytest.fixture(scope="module")
def one_thread():
    """Tiny tensors: one intra-op thread is faster (and kinder to shared cores) than many."""
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


def same_bits(x: torch.Tensor, y: torch.Tensor) -> bool:
    """Bitwise-equal values (NaN == NaN), same shape and dtype."""
    if x.shape != y.shape or x.dtype != y.dtype:
        return False
    eq = x == y
    if x.is_floating_point():
        eq = eq | (x.isnan() & y.isnan())
    return bool(eq.all())


def rel_err(a: torch.Tensor, b: torch.Tensor) -> float:
    """Relative error ||a - b|| / ||b|| in float64."""
    return float((a.double() - b.double()).norm() / b.double().norm().clamp_min(1e-300))
