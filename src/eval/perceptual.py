"""Perceptual metrics of a render against its ground truth: LPIPS (Tab. C.4) and ST-LPIPS.

Nothing here downloads anything, and nothing reports a number it did not compute:

* ``lpips``: standard LPIPS v0.1 (Zhang et al. 2018, the metric of the paper's Tab. C.4), through the
  ``lpips`` package. Its linear heads ship in that package, but the backbone is torchvision's ImageNet
  AlexNet/VGG16, which torchvision downloads on first use. Here it is computed only when the backbone
  file is **already** in the torch hub cache, ``$TORCH_HOME/hub/checkpoints/`` (see
  :data:`BACKBONE_FILES`), and ``lpips`` and ``torchvision`` are installed; torch.hub then loads the
  cached file and makes no network access.
* ``st_lpips``: shift-tolerant LPIPS (Ghildyal & Liu 2022) from the ``stlpips-pytorch`` wheel, which
  ships complete networks (backbone + heads). Its numbers are NOT comparable with the paper's LPIPS:
  always label them ``st_lpips``. The package's modules import IPython, torchsummary and torchvision
  without using them for the shift-tolerant AlexNet; when those are missing, empty stand-ins are put in
  ``sys.modules`` for the import only (and removed right after).

A metric that cannot be computed is ``None`` with a reason in ``out["reasons"]``, never a fake value.
Used by :class:`src.eval.Evaluator` (``eval.perceptual``) on the test views.
"""

from __future__ import annotations

import contextlib
import importlib
import importlib.util
import sys
import types
from functools import lru_cache
from pathlib import Path

import torch

# torchvision's ImageNet weights for the LPIPS backbones (the files torch.hub caches under checkpoints/).
BACKBONE_FILES = {"alex": "alexnet-owt-7be5be79.pth", "vgg": "vgg16-397923af.pth"}


def hub_checkpoint(net: str) -> Path:
    """Where torch.hub caches the backbone of ``net`` (``$TORCH_HOME/hub/checkpoints/<file>``)."""
    return Path(torch.hub.get_dir()) / "checkpoints" / BACKBONE_FILES[net]


def _missing_modules(*names: str) -> list[str]:
    return [n for n in names if importlib.util.find_spec(n) is None]


@lru_cache(maxsize=4)
def _lpips_model(net: str) -> tuple[torch.nn.Module | None, str | None]:
    """(model, None) or (None, reason) for standard LPIPS with the ``net`` backbone."""
    if net not in BACKBONE_FILES:
        return None, f"unknown LPIPS backbone {net!r} (choices: {', '.join(BACKBONE_FILES)})"
    missing = _missing_modules("lpips", "torchvision")
    if missing:
        return None, f"package(s) not installed: {', '.join(missing)}"
    weights = hub_checkpoint(net)
    if not weights.is_file():  # checked first, so torchvision never reaches its download branch
        return None, (
            f"ImageNet {net} backbone weights not found at {weights} (put torchvision's "
            f"{BACKBONE_FILES[net]} there or set TORCH_HOME; they are never downloaded)"
        )
    try:
        import lpips

        model = lpips.LPIPS(net=net, verbose=False).eval()
    except Exception as exc:  # a broken install must not stop an evaluation
        return None, f"LPIPS could not be built: {type(exc).__name__}: {exc}"
    return model, None


@contextlib.contextmanager
def _stand_in_modules(names: tuple[str, ...]):
    """Empty modules for ``names`` that are not installed, present only inside the ``with`` block."""
    added = []
    for name in names:
        if name not in sys.modules and importlib.util.find_spec(name) is None:
            module = types.ModuleType(name)
            module.__getattr__ = lambda attr, _n=name: _unavailable(_n, attr)  # type: ignore[method-assign]
            sys.modules[name] = module
            added.append(name)
    try:
        yield
    finally:
        for name in added:
            sys.modules.pop(name, None)


def _unavailable(module: str, attr: str):
    if attr.startswith("__"):
        raise AttributeError(attr)
    return _Unavailable(f"{module}.{attr}")


class _Unavailable:
    """Stand-in object for an attribute of a missing module; fails loudly if actually used."""

    def __init__(self, name: str) -> None:
        self.name = name

    def __getattr__(self, attr: str):
        if attr.startswith("__"):
            raise AttributeError(attr)
        return _Unavailable(f"{self.name}.{attr}")

    def __call__(self, *args, **kwargs):
        raise RuntimeError(f"{self.name} is not installed (stand-in used by src.eval.perceptual)")


@lru_cache(maxsize=2)
def _st_lpips_model(net: str) -> tuple[torch.nn.Module | None, str | None]:
    """(model, None) or (None, reason) for shift-tolerant LPIPS (``stlpips-pytorch``)."""
    if net != "alex":
        return None, "only the shift-tolerant AlexNet variant is supported here"
    if _missing_modules("stlpips_pytorch"):
        return None, "package not installed: stlpips-pytorch"
    try:
        with _stand_in_modules(("IPython", "torchsummary", "torchvision")):
            stlpips = importlib.import_module("stlpips_pytorch.stlpips")
        model = stlpips.LPIPS(net=net, variant="shift_tolerant", verbose=False).eval()
    except Exception as exc:
        return None, f"ST-LPIPS could not be built: {type(exc).__name__}: {exc}"
    return model, None


def _to_nchw(img: torch.Tensor) -> torch.Tensor:
    """[H, W, 3] in [0, 1] → [1, 3, H, W] float32 in [-1, 1] (the LPIPS input convention)."""
    if img.ndim != 3 or img.shape[-1] != 3:
        raise ValueError(f"expected an [H, W, 3] image, got shape {tuple(img.shape)}")
    return img.detach().float().clamp(0, 1).permute(2, 0, 1)[None] * 2 - 1


def _score(model: torch.nn.Module, render: torch.Tensor, gt: torch.Tensor) -> tuple[float | None, str | None]:
    try:
        with torch.no_grad():
            value = model.to(render.device)(_to_nchw(render), _to_nchw(gt))
    except RuntimeError as exc:  # e.g. an image smaller than the backbone's receptive field
        return None, f"failed on a {tuple(render.shape[:2])} image: {exc}"
    return float(value.reshape(-1)[0]), None


def perceptual_metrics(render: torch.Tensor, gt: torch.Tensor, net: str = "alex") -> dict:
    """LPIPS and ST-LPIPS of ``render`` against ``gt`` (both [H, W, 3], values in [0, 1]).

    Returns ``{"lpips": float | None, "st_lpips": float | None, "reasons": {name: why unavailable}}``;
    lower is better for both. ``reasons`` is empty when both were computed.

    Raises:
        ValueError: the images are not [H, W, 3] or their shapes differ.
    """
    if render.shape != gt.shape:
        raise ValueError(f"render {tuple(render.shape)} and gt {tuple(gt.shape)} differ in shape")
    _to_nchw(render)  # validates the layout even when no metric is available
    out: dict = {"lpips": None, "st_lpips": None, "reasons": {}}
    for name, factory in (("lpips", _lpips_model), ("st_lpips", _st_lpips_model)):
        model, reason = factory(net)
        if model is not None:
            out[name], reason = _score(model, render, gt)
        if reason is not None:
            out["reasons"][name] = reason
    return out


def perceptual_status(net: str = "alex") -> dict[str, str | None]:
    """Why each perceptual metric is unavailable (None = available), without scoring anything."""
    return {"lpips": _lpips_model(net)[1], "st_lpips": _st_lpips_model(net)[1]}
