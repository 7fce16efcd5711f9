"""Aligning reconstructed cameras with ground truth: the similarity transform (Umeyama) and its residuals.

A structure-from-motion model is known up to a similarity (scale, rotation, translation) of the world, so
its cameras are compared with the renderer's after the best such transform of their centres.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch


@dataclass(frozen=True)
class Similarity:
    """x -> scale * rot @ x + shift (float64)."""

    scale: float
    rot: torch.Tensor    # [3, 3], a rotation (det +1)
    shift: torch.Tensor  # [3]

    def __call__(self, x: torch.Tensor) -> torch.Tensor:
        """The transform of points ``x`` [N, 3]."""
        return self.scale * x @ self.rot.T + self.shift


def umeyama(src: torch.Tensor, dst: torch.Tensor) -> Similarity:
    """The similarity transform taking ``src`` [N, 3] closest to ``dst`` [N, 3] in least squares (Umeyama 1991)."""
    src, dst = src.double(), dst.double()
    mu_s, mu_d = src.mean(0), dst.mean(0)
    a, b = src - mu_s, dst - mu_d
    u, sing, vt = torch.linalg.svd(b.T @ a)
    d = torch.ones(3, dtype=torch.float64)
    d[2] = torch.sign(torch.linalg.det(u @ vt))
    rot = u @ torch.diag(d) @ vt
    scale = float((sing * d).sum() / (a ** 2).sum())
    return Similarity(scale, rot, mu_d - scale * rot @ mu_s)


def similarity_residual(src: torch.Tensor, dst: torch.Tensor) -> float:
    """Largest distance between ``dst`` [N, 3] and the best similarity transform of ``src`` [N, 3] (Umeyama)."""
    return float((umeyama(src, dst)(src.double()) - dst.double()).norm(dim=1).max())


def rotation_angle_deg(rot: torch.Tensor) -> torch.Tensor:
    """Angle in degrees of rotation matrices ``rot`` [..., 3, 3]."""
    trace = rot.diagonal(dim1=-2, dim2=-1).sum(-1)
    return torch.rad2deg(torch.arccos(((trace - 1) / 2).clamp(-1.0, 1.0)))


def camera_errors(found_c2w: torch.Tensor, true_c2w: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Per-camera (rotation error in degrees, centre error as a fraction of the true cameras' extent) of
    camera-to-world poses ``found_c2w`` [N, 4, 4] against ``true_c2w`` [N, 4, 4] (same axes convention), after the
    similarity transform of the found centres onto the true ones.

    The extent is the largest distance of a true centre from their mean. A camera's orientation in the aligned
    frame is ``sim.rot @ R_found``; its error is the angle of ``R_trueᵀ sim.rot R_found``.
    """
    found, true = found_c2w.double(), true_c2w.double()
    sim = umeyama(found[:, :3, 3], true[:, :3, 3])
    centres = true[:, :3, 3]
    extent = float((centres - centres.mean(0)).norm(dim=1).max())
    pos = (sim(found[:, :3, 3]) - centres).norm(dim=1) / extent
    rel = true[:, :3, :3].transpose(1, 2) @ sim.rot @ found[:, :3, :3]
    return rotation_angle_deg(rel), pos

