"""Pick the fastest rasterizer available on this machine."""

from __future__ import annotations

import logging

import torch

from src.rasterizer.base import Rasterizer

log = logging.getLogger(__name__)


def auto_rasterizer(antialiased: bool = False, filter_2d: float = 0.1, surfels: bool = False,
                    device: str = "auto") -> Rasterizer:
    """gsplat on CUDA, the compiled ``cpu`` kernel otherwise, ``torch_ref`` (slow) as a last resort.

    On CUDA without gsplat the fallback is ``torch_ref`` on the GPU (the compiled kernel is CPU-only).
    2D surfels take gsplat's 2DGS path there too; its distortion map has its own loss weight
    (``loss.lambda_dist_l1``, docs/baselines.md, "2DGS on CUDA").

    Args:
        antialiased: Mip-Splatting's 2D Mip filter instead of 3DGS's dilation (every backend).
        filter_2d: the 2D Mip filter's variance in pixels^2 (Mip-Splatting: 0.1).
        surfels: 2D Gaussian surfels by ray-splat intersection (2DGS), in every backend.
        device: the run's device (``auto`` | ``cpu`` | ``cuda[:i]``, the config's ``device``): CUDA
            rasterizers only where the run's tensors live on CUDA.
    """
    from src.rasterizer.torch_ref import TorchRefRasterizer

    aa = {"antialiased": antialiased, "filter_2d": filter_2d, "surfels": surfels}
    on_cuda = torch.cuda.is_available() if device == "auto" else str(device).startswith("cuda")
    if on_cuda:
        try:
            from src.rasterizer.gsplat_backend import GsplatRasterizer

            return GsplatRasterizer(**aa)
        except ImportError as e:
            log.warning("CUDA present but gsplat unavailable (%s); using torch_ref on the GPU "
                        "(pip install -e '.[cuda]' for gsplat)", e)
            return TorchRefRasterizer(**aa)
    try:
        from src.rasterizer.cpu import CpuRasterizer

        rast = CpuRasterizer(**aa)
        ensure = getattr(rast, "ensure_built", None)
        if ensure is not None:
            ensure()
        return rast
    except Exception as e:
        log.warning("compiled cpu rasterizer unavailable (%s: %s); using the slow torch_ref",
                    type(e).__name__, e)
    return TorchRefRasterizer(**aa)
