"""gsplat backend: GPU-only parity with the torch reference (skipped without CUDA)."""

from __future__ import annotations

import pytest
import torch

from src.rasterizer.torch_ref import TorchRefRasterizer
from tests.conftest import random_camera, random_scene

cuda = pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA GPU")


def test_importing_the_backend_does_not_need_gsplat():
    import src.rasterizer.gsplat_backend as gb

    assert gb.GsplatRasterizer.name == "gsplat"
    if not torch.cuda.is_available():
        with pytest.raises(RuntimeError, match="CUDA"):
            gb.GsplatRasterizer()


@cuda
@pytest.mark.cuda
def test_gsplat_matches_reference_away_from_borders():
    pytest.importorskip("gsplat")
    from src.rasterizer.gsplat_backend import GsplatRasterizer

    s = random_scene(2000, seed=0, spread=0.4, scale_range=(0.01, 0.04))
    cam = random_camera(64, 64, seed=1)
    ref = TorchRefRasterizer().render(s, cam, torch.ones(3))
    out = GsplatRasterizer().render(s.to("cuda"), cam.to("cuda"), torch.ones(3, device="cuda"))
    diff = (out.color.cpu() - ref.color).abs()
    assert diff.mean() < 5e-3 and torch.quantile(diff.flatten(), 0.99) < 5e-2
