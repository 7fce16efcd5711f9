"""Pick the fastest rasterizer available on this machine."""

from __future__ import annotations

import logging

import torch

from src.rasterizer.base import Rasterizer

log = logging.getLogger(__name__)


def auto_rasterizer() -> Rasterizer:
    """gsplat on CUDA, the compiled ``cpu`` kernel otherwise, ``torch_ref`` (slow) as a last resort."""
    if torch.cuda.is_available():
        try:
            from src.rasterizer.gsplat_backend import GsplatRasterizer

            return GsplatRasterizer()
        except ImportError as e:
            log.warning("CUDA present but gsplat unavailable (%s); trying the cpu kernel", e)
    try:
        from src.rasterizer.cpu import CpuRasterizer

        rast = CpuRasterizer()
        ensure = getattr(rast, "ensure_built", None)
        if ensure is not None:
            ensure()
        return rast
    except Exception as e:
        log.warning("compiled cpu rasterizer unavailable (%s: %s); using the slow torch_ref",
                    type(e).__name__, e)
    from src.rasterizer.torch_ref import TorchRefRasterizer

    return TorchRefRasterizer()
