"""The model interface used by the trainer, the densification strategies and the evaluator."""

from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass

import torch
from torch import Tensor, nn

from src.core.cameras import Camera
from src.core.splats import Splats


@dataclass
class AnchorDecode:
    """What one ``splats(camera)`` call of an anchor-based model decoded (Scaffold-GS).

    Each anchor decodes ``k`` child splats; child ``j`` of anchor ``a`` has the flat id ``a * k + j``.

    Attributes:
        anchors: [V] long ids of the anchors decoded for the camera (those in its view frustum).
        children: [M] long flat child ids of the splats returned, in the order of the splat set.
        opacity: [V, k] the decoded anchors' child opacities before the non-positive ones were
            dropped (detached; may be <= 0).
    """

    anchors: Tensor
    children: Tensor
    opacity: Tensor


class SplatModel(nn.Module, ABC):
    """A scene representation that yields splats for a camera.

    Subclasses hold per-splat state (free parameters or canonical query points) and implement the
    densification operations used by :mod:`src.strategy`.
    """

    @abstractmethod
    def splats(self, camera: Camera) -> Splats:
        """Activated splats to render ``camera`` (uses its view direction and time)."""

    def splats_for(self, cameras: list[Camera]) -> list[Splats]:
        """Splats for several cameras; models may share work between them (same time)."""
        return [self.splats(c) for c in cameras]

    @abstractmethod
    def param_groups(self) -> list[dict]:
        """Optimiser parameter groups, each a dict with ``name`` and ``params``."""

    @property
    @abstractmethod
    def n_splats(self) -> int:
        """Current number of splats."""

    def n_params(self) -> int:
        """Number of trainable scalars (free splat parameters and network weights)."""
        return sum(p.numel() for p in self.parameters() if p.requires_grad)

    def bake(self, time: float = 0.0, frame_id: int = 0) -> Splats:
        """A network-free splat set equivalent to this model at ``time`` (view-independent colours)."""
        raise NotImplementedError(f"{type(self).__name__} cannot be baked")

    def networks(self) -> list[nn.Module]:
        """The neural networks evaluated in every step (what ``trainer.compile`` compiles); none by default."""
        return []

    def on_step(self, iteration: int) -> None:
        """Called at the start of every training iteration (e.g. to raise the SH degree)."""

    def bind(self, scene) -> None:
        """Called once before training (and before a checkpoint is resumed) with the :class:`Scene`,
        for models that need its training cameras (Mip-Splatting's 3D filter); nothing by default."""

    def regularisers(self, iteration: int) -> dict[str, Tensor]:
        """Weighted loss terms of the model's own parameters at ``iteration`` (scalar tensors), added to
        the objective's total by the trainer; none by default."""
        return {}

    # -- densification interface (per-splat state) -------------------------------------------
    def canonical_means(self) -> Tensor:
        """[N, 3] per-splat positions the densification acts on."""
        raise NotImplementedError

    def max_scale(self) -> Tensor:
        """[N] largest scale of each splat (world units), for the clone/split decision."""
        raise NotImplementedError

    def opacity_values(self) -> Tensor | None:
        """[N] current opacities if the model stores them per splat (None for fields)."""
        return None

    def densify(self, optimizer: torch.optim.Optimizer, clone: Tensor, split: Tensor, n_split: int,
                generator: torch.Generator) -> None:
        """Clone splats in ``clone`` and replace those in ``split`` by ``n_split`` smaller children."""
        raise NotImplementedError(f"{type(self).__name__} does not support densification")

    def prune(self, optimizer: torch.optim.Optimizer, mask: Tensor) -> None:
        """Remove the splats where ``mask`` is True."""
        raise NotImplementedError(f"{type(self).__name__} does not support pruning")

    def reset_opacity(self, optimizer: torch.optim.Optimizer, value: float) -> None:
        """Clamp stored opacities to at most ``value`` (3DGS opacity reset); no-op for fields."""

    # -- anchor interface (models whose splats are decoded from anchors: Scaffold-GS) ----------
    @property
    def children_per_anchor(self) -> int:
        """Number k of child splats each anchor decodes."""
        raise NotImplementedError(f"{type(self).__name__} has no anchors")

    def anchor_voxel_size(self) -> float:
        """Edge (world units) of the voxel grid the initial anchors were placed on."""
        raise NotImplementedError(f"{type(self).__name__} has no anchors")

    def anchor_means(self) -> Tensor:
        """[A, 3] anchor positions (detached)."""
        raise NotImplementedError(f"{type(self).__name__} has no anchors")

    def child_means(self) -> Tensor:
        """[A, k, 3] positions of every anchor's child splats (detached, whether decoded or not)."""
        raise NotImplementedError(f"{type(self).__name__} has no anchors")

    def anchor_decodes(self) -> list[AnchorDecode]:
        """What the training-mode ``splats`` calls of the current iteration decoded, in call order."""
        raise NotImplementedError(f"{type(self).__name__} has no anchors")

    def grow_anchors(self, optimizer: torch.optim.Optimizer, positions: Tensor, size: float, parents: Tensor,
                     slots: Tensor) -> None:
        """Append anchors at ``positions`` [M, 3] on a voxel grid of edge ``size``; ``parents`` [S] (anchor
        ids) and ``slots`` [S] (indices into ``positions``) say which existing anchors each new one is
        initialised from."""
        raise NotImplementedError(f"{type(self).__name__} has no anchors")

    def prune_anchors(self, optimizer: torch.optim.Optimizer, mask: Tensor) -> None:
        """Remove the anchors where ``mask`` [A] is True (with their children)."""
        raise NotImplementedError(f"{type(self).__name__} has no anchors")
