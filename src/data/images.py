"""Image I/O with OpenImageIO (PNG, EXR, JPEG, ...)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import OpenImageIO as oiio
import torch
import torch.nn.functional as F
from torch import Tensor

from src.data.base import DatasetError


def read_image(path: Path | str) -> Tensor:
    """Read an image as float32 [H, W, C] in [0, 1] (integer formats are divided by their max).

    Raises:
        DatasetError: if the file is missing, unreadable or contains NaN/Inf.
    """
    path = Path(path)
    if not path.is_file():
        raise DatasetError(f"image file not found: {path}")
    # straight (unassociated) alpha: OpenImageIO premultiplies RGBA PNGs by default, and composite()
    # applies alpha itself
    spec = oiio.ImageSpec()
    spec.attribute("oiio:UnassociatedAlpha", 1)
    inp = oiio.ImageInput.open(str(path), spec)
    if inp is None:
        raise DatasetError(f"cannot read image {path}: {oiio.geterror()}")
    try:
        pixels = inp.read_image(format=oiio.FLOAT)
    finally:
        inp.close()
    if pixels is None:
        raise DatasetError(f"cannot decode image {path}: {oiio.geterror()}")
    arr = np.asarray(pixels, dtype=np.float32)
    if arr.ndim == 2:
        arr = arr[..., None]
    if not np.isfinite(arr).all():
        raise DatasetError(f"image {path} contains NaN or Inf values")
    return torch.from_numpy(np.ascontiguousarray(arr))


def write_png(path: Path | str, image: Tensor) -> None:
    """Write [H, W, C] float in [0, 1] (C = 1, 3 or 4; straight alpha) as an 8-bit PNG (rounded, clamped)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    arr = (image.detach().float().clamp(0, 1) * 255.0 + 0.5).to(torch.uint8).cpu().numpy()
    if arr.ndim == 2:
        arr = arr[..., None]
    out = oiio.ImageOutput.create(str(path))
    if out is None:
        raise OSError(f"cannot create {path}: {oiio.geterror()}")
    spec = oiio.ImageSpec(arr.shape[1], arr.shape[0], arr.shape[2], oiio.UINT8)
    spec.attribute("oiio:UnassociatedAlpha", 1)  # the data is straight alpha: store it as is
    out.open(str(path), spec)
    out.write_image(arr)
    out.close()


def resize_premultiplied(rgba: Tensor, size: tuple[int, int]) -> Tensor:
    """Area-resample an [H, W, 4] straight-alpha image to ``size`` = (h, w), premultiplying first."""
    rgb, a = rgba[..., :3], rgba[..., 3:4]
    pre = torch.cat([rgb * a, a], dim=-1).permute(2, 0, 1)[None]
    out = F.interpolate(pre, size=size, mode="area")[0].permute(1, 2, 0)
    a2 = out[..., 3:4]
    rgb2 = torch.where(a2 > 0, out[..., :3] / a2.clamp_min(1e-8), torch.zeros_like(out[..., :3]))
    return torch.cat([rgb2.clamp(0, 1), a2.clamp(0, 1)], dim=-1)


def composite(rgba: Tensor, background: Tensor) -> tuple[Tensor, Tensor]:
    """Composite straight-alpha [H, W, 4] on ``background`` [3]; returns (rgb [H, W, 3], alpha [H, W])."""
    if rgba.shape[-1] == 3:
        return rgba, torch.ones(rgba.shape[:2])
    rgb, a = rgba[..., :3], rgba[..., 3]
    return rgb * a[..., None] + background * (1.0 - a[..., None]), a
