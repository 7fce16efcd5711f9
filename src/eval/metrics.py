"""Image metrics used for reporting (not for training)."""

from __future__ import annotations

import math

import numpy as np
import torch
from skimage.metrics import structural_similarity
from torch import Tensor


def quantise(img: Tensor) -> Tensor:
    """Round an image in [0, 1] to 8 bits and back (the PNG round trip of the reference protocol)."""
    return torch.round(img.clamp(0, 1) * 255.0) / 255.0


def psnr(a: Tensor, b: Tensor) -> float:
    """PSNR in dB of images in [0, 1]: -10 log10(MSE); inf for identical images."""
    mse = float(((a.double() - b.double()) ** 2).mean())
    return math.inf if mse == 0 else -10.0 * math.log10(mse)


def ssim_eval(a: Tensor, b: Tensor) -> float:
    """SSIM of [H, W, 3] images in [0, 1]: Gaussian window sigma 1.5 (11 taps), population statistics.

    Equals the JAX/Nerfies ``compute_ssim`` used by the reference evaluation (k1 0.01, k2 0.03).
    Images smaller than the 11-pixel window (CI smoke sizes) use the largest odd window that fits.
    """
    x = a.detach().cpu().double().numpy()
    y = b.detach().cpu().double().numpy()
    side = min(x.shape[0], x.shape[1])
    if side < 3:
        return math.nan
    win = None if side >= 11 else (side if side % 2 else side - 1)
    return float(structural_similarity(x, y, data_range=1.0, channel_axis=-1, gaussian_weights=True,
                                       sigma=1.5, use_sample_covariance=False, win_size=win))


def mean_finite(values: list[float]) -> float:
    """Mean of the finite values (nan if none)."""
    v = [x for x in values if math.isfinite(x)]
    return float(np.mean(v)) if v else math.nan
