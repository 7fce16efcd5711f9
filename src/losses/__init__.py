"""Training losses (supplementary eq. A.2) and image-quality measures.

Images are [H, W, C] in [0, 1]. D-SSIM is 1 - SSIM with the 3DGS window (11x11 Gaussian,
sigma 1.5, same padding). Moran's I (B.3-B.6) lives in :mod:`src.losses.moran`.
"""

from src.losses.objective import SplatLoss
from src.losses.ssim import ssim

__all__ = ["SplatLoss", "ssim"]
