"""SSIM with a Gaussian window (the 3DGS training loss variant, 'same' padding).

:func:`ssim` blurs the five maps SSIM needs (x, y, x², y², xy) of every image of a batch with one
pair of separable depthwise convolutions; :func:`ssim_reference` is the direct form (five blurs per
image) that it is tested against (``tests/test_ssim.py``, values and gradients in float64).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor

C1 = 0.01**2
C2 = 0.03**2


def gaussian_window(size: int = 11, sigma: float = 1.5, dtype=torch.float32, device=None) -> Tensor:
    """[size] normalised 1D Gaussian."""
    x = torch.arange(size, dtype=dtype, device=device) - (size - 1) / 2
    g = torch.exp(-(x**2) / (2 * sigma**2))
    return g / g.sum()


def _blur(t: Tensor, window: int, sigma: float) -> Tensor:
    """Separable Gaussian blur of every channel of t [B, K, H, W] (zero 'same' padding)."""
    k = t.shape[1]
    g = gaussian_window(window, sigma, t.dtype, t.device)
    pad = window // 2
    t = F.conv2d(t, g.view(1, 1, 1, -1).expand(k, 1, 1, window), padding=(0, pad), groups=k)
    return F.conv2d(t, g.view(1, 1, -1, 1).expand(k, 1, window, 1), padding=(pad, 0), groups=k)


def _ssim_map(mu_x: Tensor, mu_y: Tensor, exx: Tensor, eyy: Tensor, exy: Tensor) -> Tensor:
    """The SSIM map from the blurred means and second moments."""
    sxx = exx - mu_x**2
    syy = eyy - mu_y**2
    sxy = exy - mu_x * mu_y
    num = (2 * mu_x * mu_y + C1) * (2 * sxy + C2)
    den = (mu_x**2 + mu_y**2 + C1) * (sxx + syy + C2)
    return num / den


def ssim_per_image(a: Tensor, b: Tensor, window: int = 11, sigma: float = 1.5) -> Tensor:
    """[B] mean SSIM of each pair of images a, b [B, H, W, C] in [0, 1] (one blur call for the batch)."""
    x = a.permute(0, 3, 1, 2)  # [B, C, H, W]
    y = b.permute(0, 3, 1, 2)
    c = x.shape[1]
    blurred = _blur(torch.cat([x, y, x * x, y * y, x * y], dim=1), window, sigma)  # [B, 5C, H, W]
    return _ssim_map(*blurred.split(c, dim=1)).mean(dim=(1, 2, 3))


def ssim(a: Tensor, b: Tensor, window: int = 11, sigma: float = 1.5) -> Tensor:
    """Mean SSIM of two images [H, W, C] in [0, 1], or the mean over a batch [B, H, W, C]
    (separable Gaussian window, zero 'same' padding)."""
    if a.ndim == 3:
        a, b = a[None], b[None]
    return ssim_per_image(a, b, window, sigma).mean()


def ssim_reference(a: Tensor, b: Tensor, window: int = 11, sigma: float = 1.5) -> Tensor:
    """Mean SSIM of two images [H, W, C], each of the five maps blurred on its own (the simple form)."""
    x = a.permute(2, 0, 1)[None]
    y = b.permute(2, 0, 1)[None]

    def blur(t: Tensor) -> Tensor:
        return _blur(t, window, sigma)

    return _ssim_map(blur(x), blur(y), blur(x * x), blur(y * y), blur(x * y)).mean()
