"""The rasterizer interface."""

from __future__ import annotations

from abc import ABC, abstractmethod

from torch import Tensor

from src.core.cameras import Camera
from src.core.splats import RenderOutput, Splats


class Rasterizer(ABC):
    """Renders a set of activated splats through a camera. Differentiable in every splat attribute."""

    name: str = "base"

    @abstractmethod
    def render(self, splats: Splats, camera: Camera, background: Tensor | None = None) -> RenderOutput:
        """Render ``splats`` seen by ``camera``.

        Args:
            splats: N activated splats with C colour/feature channels.
            camera: OpenCV pinhole camera.
            background: [C] colour added with weight T_final (zeros if None).

        Returns:
            RenderOutput with color [H, W, C], alpha [H, W], depth [H, W], means2d [N, 2], radii [N].
        """

    def __repr__(self) -> str:
        return f"{type(self).__name__}()"


def check_surfels(surfels: bool, antialiased: bool) -> bool:
    """``surfels`` as a bool; ValueError if combined with ``antialiased`` (2DGS has its own low-pass filter)."""
    if surfels and antialiased:
        raise ValueError("rasterizer.surfels (2DGS) and rasterizer.antialiased (Mip-Splatting) cannot be combined: "
                         "2D Gaussian surfels carry their own object-space low-pass filter")
    return bool(surfels)


def gradient_leaf(values: Tensor, grad_source: Tensor | None = None) -> Tensor:
    """A leaf [N, D] copy of camera 0 of ``values`` [1, N, D] whose ``.grad`` receives camera 0 of
    ``grad_source``'s gradient (default: ``values``') during the backward.

    For a backend whose screen-space tensors lie on the image's autograd graph only as a batch over
    cameras: a slice of them taken after rendering is off the graph and its ``.grad`` would stay empty.
    """
    source = values if grad_source is None else grad_source
    leaf = values[0].detach().clone().requires_grad_(source.requires_grad)  # [N, D]
    if source.requires_grad:

        def _to_leaf(grad: Tensor) -> None:
            leaf.grad = grad.reshape(-1, *leaf.shape)[0].detach().clone()

        source.register_hook(_to_leaf)
    return leaf
