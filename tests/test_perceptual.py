"""Perceptual metrics (src/eval/perceptual.py): unavailable → None plus a reason, never a fake number,
and never a download."""

from __future__ import annotations

import pytest
import torch

from src.eval import perceptual


@pytest.fixture(autouse=True)
def fresh_models(monkeypatch, tmp_path):
    """An empty TORCH_HOME (no backbone weights) and no cached models from other tests."""
    monkeypatch.setenv("TORCH_HOME", str(tmp_path / "torch_home"))
    perceptual._lpips_model.cache_clear()
    perceptual._st_lpips_model.cache_clear()
    yield
    perceptual._lpips_model.cache_clear()
    perceptual._st_lpips_model.cache_clear()


def images(size: int = 64) -> tuple[torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(0)
    a = torch.rand(size, size, 3, generator=g)
    return a, (a + 0.1 * torch.rand(size, size, 3, generator=g)).clamp(0, 1)


def test_unavailable_metrics_are_none_with_a_reason():
    out = perceptual.perceptual_metrics(*images())
    assert set(out) == {"lpips", "st_lpips", "reasons"}
    # standard LPIPS needs ImageNet backbone weights in TORCH_HOME, which is empty here
    assert out["lpips"] is None and out["reasons"]["lpips"]
    if out["st_lpips"] is None:  # stlpips-pytorch not installed (or not importable)
        assert out["reasons"]["st_lpips"]
    else:  # it ships its weights: a real value, and no reason
        assert 0.0 <= out["st_lpips"] < 1.0 and "st_lpips" not in out["reasons"]
    assert perceptual.perceptual_status()["lpips"] == out["reasons"]["lpips"]


def test_missing_backbone_weights_are_reported_not_downloaded(monkeypatch):
    """With lpips and torchvision "installed", absent backbone weights still give None: the file check
    comes before anything that could download (the lpips package is never imported)."""
    monkeypatch.setattr(perceptual, "_missing_modules", lambda *names: [])
    model, reason = perceptual._lpips_model("alex")
    assert model is None
    assert str(perceptual.hub_checkpoint("alex")) in reason and "never downloaded" in reason
    assert perceptual.hub_checkpoint("alex").name == "alexnet-owt-7be5be79.pth"
    assert str(perceptual.hub_checkpoint("vgg")).startswith(str(torch.hub.get_dir()))


def test_bad_inputs_raise():
    a, b = images()
    with pytest.raises(ValueError, match="differ in shape"):
        perceptual.perceptual_metrics(a, b[:32])
    with pytest.raises(ValueError, match=r"\[H, W, 3\]"):
        perceptual.perceptual_metrics(a.permute(2, 0, 1), b.permute(2, 0, 1))
    assert perceptual._lpips_model("squeeze")[1].startswith("unknown LPIPS backbone")
