"""Splat sets (what a rasterizer draws) and render outputs."""

from __future__ import annotations

from dataclasses import dataclass, fields

import torch
from torch import Tensor


@dataclass
class Splats:
    """A set of N activated 3D Gaussian splats.

    Attributes:
        means: [N, 3] centres in world coordinates.
        scales: [N, 3] positive standard deviations along the splat's local axes (linear, not log).
        quats: [N, 4] rotations as quaternions (w, x, y, z); rasterizers normalise them.
        opacities: [N] opacities in (0, 1) (sigmoid of the logit-opacity).
        colors: [N, C] colours or features to composite (RGB in [0, 1] for C = 3).
    """

    means: Tensor
    scales: Tensor
    quats: Tensor
    opacities: Tensor
    colors: Tensor

    def __len__(self) -> int:
        return self.means.shape[0]

    @property
    def n(self) -> int:
        return self.means.shape[0]

    def detach(self) -> Splats:
        return Splats(**{f.name: getattr(self, f.name).detach() for f in fields(self)})

    def to(self, device=None, dtype=None) -> Splats:
        return Splats(**{f.name: getattr(self, f.name).to(device=device, dtype=dtype) for f in fields(self)})

    def index(self, idx: Tensor) -> Splats:
        """Subset by a boolean mask or index tensor."""
        return Splats(**{f.name: getattr(self, f.name)[idx] for f in fields(self)})

    def validate(self) -> None:
        """Raise ValueError if shapes are inconsistent."""
        n = self.means.shape[0]
        expected = {"means": (n, 3), "scales": (n, 3), "quats": (n, 4), "opacities": (n,)}
        for name, shape in expected.items():
            got = tuple(getattr(self, name).shape)
            if got != shape:
                raise ValueError(f"Splats.{name} has shape {got}, expected {shape}")
        if self.colors.ndim != 2 or self.colors.shape[0] != n:
            raise ValueError(f"Splats.colors has shape {tuple(self.colors.shape)}, expected ({n}, C)")

    @staticmethod
    def empty(channels: int = 3, dtype: torch.dtype = torch.float32) -> Splats:
        return Splats(
            means=torch.zeros(0, 3, dtype=dtype),
            scales=torch.ones(0, 3, dtype=dtype),
            quats=torch.zeros(0, 4, dtype=dtype),
            opacities=torch.zeros(0, dtype=dtype),
            colors=torch.zeros(0, channels, dtype=dtype),
        )


def shortest_axis(rotations: Tensor, scales: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """Each Gaussian's shortest axis: (its scale [...], its index [...] in 0..2, the unit axis [..., 3]).

    ``rotations`` [..., 3, 3] hold the Gaussians' axes as columns (world from local), ``scales`` [..., 3] the
    standard deviations along them; the axis is the column of the smallest scale (a flat splat's normal, up
    to sign). Differentiable in both (the index is not).
    """
    smallest, index = scales.min(-1)
    axis = rotations.gather(-1, index[..., None, None].expand(*index.shape, 3, 1))[..., 0]
    return smallest, index, axis


@dataclass
class RenderOutput:
    """What a rasterizer returns for one camera.

    Attributes:
        color: [H, W, C] composited colour/features including the background term T * bg.
        alpha: [H, W] accumulated opacity 1 - T_final (what the mask loss compares with the mask).
        depth: [H, W] accumulated depth sum_i z_i * alpha_i * T_i (not normalised by alpha).
        means2d: [N, 2] screen-space centres (u, v) in pixels. Call ``retain_grad()`` before backward
            to read the view-space positional gradient that 3DGS densification uses.
        radii: [N] integer pixel radii, 0 for culled splats.
    """

    color: Tensor
    alpha: Tensor
    depth: Tensor
    means2d: Tensor
    radii: Tensor


@dataclass
class SurfelRenderOutput(RenderOutput):
    """What a 2D Gaussian surfel rasterizer returns (2DGS, Huang et al. 2024): :class:`RenderOutput` plus
    the maps its geometry losses read.

    Attributes:
        normals: [H, W, 3] accumulated world-frame surfel normals sum_i n_i * alpha_i * T_i (not
            normalised; each n_i is oriented towards the camera).
        distortion: [H, W] depth distortion: by default sum_{j<i} w_i w_j (m_i - m_j)^2 of the NDC-mapped
            intersection depths m (2DGS Eq. 13, as its reference code evaluates it).
        distortion_form: which distortion ``distortion`` holds: ``"ndc_squared"`` (above; the CPU kernel
            and torch_ref) or ``"depth_l1"`` (sum w_i w_j |z_i - z_j| of raw camera depths, gsplat's
            2DGS kernel). The two differ by orders of magnitude, so each has its own loss weight.
    """

    normals: Tensor
    distortion: Tensor
    distortion_form: str = "ndc_squared"
