"""Evaluation on held-out views: PSNR, SSIM, Moran's I, baked-render speed.

Protocol (reference code): the last iteration, full images composited on the training background,
renders quantised to 8 bits before scoring (as a PNG round trip), PSNR averaged over images, SSIM with
an 11x11 Gaussian window (sigma 1.5) as in the JAX/Nerfies port (scikit-image's Gaussian SSIM).
"""

from src.eval.evaluator import Evaluator
from src.eval.metrics import psnr, ssim_eval

__all__ = ["Evaluator", "psnr", "ssim_eval"]
