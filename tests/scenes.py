"""Writers of tiny synthetic datasets for tests (rendered with the torch reference rasterizer)."""

from __future__ import annotations

import json
import math
from pathlib import Path

import torch

from src.core.cameras import look_at
from src.data.images import write_png
from src.rasterizer.torch_ref import TorchRefRasterizer
from tests.conftest import random_scene


def hemisphere_c2w_gl(n: int, radius: float = 4.0, seed: int = 0) -> list[torch.Tensor]:
    """``n`` Blender/OpenGL camera-to-world matrices on the upper hemisphere looking at the origin."""
    g = torch.Generator().manual_seed(seed)
    out = []
    for _ in range(n):
        az = float(torch.rand(1, generator=g)) * 2 * math.pi
        el = 0.15 + float(torch.rand(1, generator=g)) * 1.2
        eye = torch.tensor([math.cos(az) * math.cos(el), math.sin(az) * math.cos(el), math.sin(el)],
                           dtype=torch.float64) * radius
        w2c_cv = look_at(eye, torch.zeros(3, dtype=torch.float64))
        c2w_cv = torch.linalg.inv(w2c_cv)
        out.append(c2w_cv @ torch.diag(torch.tensor([1.0, -1.0, -1.0, 1.0], dtype=torch.float64)))
    return out


def write_blender_scene(root: Path, n_train: int = 12, n_test: int = 3, size: int = 32, fov: float = 0.69,
                        seed: int = 0) -> Path:
    """A NeRF-synthetic-layout scene of random splats: RGBA PNGs and transforms_{train,val,test}.json."""
    from src.core.cameras import Camera

    root.mkdir(parents=True, exist_ok=True)
    splats = random_scene(300, seed=seed, spread=0.35, scale_range=(0.03, 0.1))
    splats.opacities = splats.opacities.clamp_min(0.6)
    rast = TorchRefRasterizer()
    f = 0.5 * size / math.tan(0.5 * fov)
    for split, n, s in (("train", n_train, seed), ("val", 2, seed + 1), ("test", n_test, seed + 2)):
        frames = []
        for i, c2w_gl in enumerate(hemisphere_c2w_gl(n, seed=s)):
            c2w_cv = c2w_gl @ torch.diag(torch.tensor([1.0, -1.0, -1.0, 1.0], dtype=torch.float64))
            cam = Camera(torch.linalg.inv(c2w_cv).float(), f, f, size / 2, size / 2, size, size)
            with torch.no_grad():
                out = rast.render(splats, cam, torch.zeros(3))
            a = out.alpha.clamp(0, 1)
            rgb = torch.where(a[..., None] > 0, out.color / a[..., None].clamp_min(1e-6), out.color).clamp(0, 1)
            write_png(root / split / f"r_{i}.png", torch.cat([rgb, a[..., None]], dim=-1))
            frames.append({"file_path": f"./{split}/r_{i}", "transform_matrix": c2w_gl.tolist()})
        (root / f"transforms_{split}.json").write_text(json.dumps({"camera_angle_x": fov, "frames": frames}))
    return root
