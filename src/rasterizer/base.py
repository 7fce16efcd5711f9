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
