"""EWA projection of 3D Gaussians to screen space, written elementwise.

Elementwise formulas instead of batched 3x3 matmuls: on the CPU, torch's small batched matmuls are
2-4x slower than the same arithmetic on [N] vectors (see the CPU rasterizer study). Differentiable
through torch autograd. Conventions: OpenCV camera, quaternions (w, x, y, z), linear scales.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from src.core.cameras import Camera

NEAR_PLANE = 0.2  # 3DGS in_frustum: splats with camera depth <= 0.2 are culled
FRUSTUM_CLAMP = 1.3  # 3DGS clamps x/z, y/z to 1.3x the half-FoV before the Jacobian
EPS2D = 0.3  # 3DGS low-pass filter added to the 2D covariance diagonal (pixels^2)
# Floor of det(Sigma2D) / det(Sigma2D + eps2d I) in the antialiased (Mip-Splatting 2D Mip filter) mode:
# the opacity factor stays >= sqrt(1e-6) = 1e-3, so such a splat's alpha is < 1/255 (it never blends,
# the render is exact) while the factor's gradient stays finite for degenerate footprints.
AA_RATIO_MIN = 1e-6
TILE = 16  # 3DGS tile size (pixels)


@dataclass
class Projected:
    """Screen-space splats.

    Attributes:
        means2d: [N, 2] pixel coordinates (u, v) of the centres (pixel centres at i + 0.5).
        conics: [N, 3] (a, b, c) of the inverse 2D covariance [[a, b], [b, c]].
        depths: [N] camera-space z.
        radii: [N] int32 pixel radius, 0 if culled.
        visible: [N] bool, not culled.
        compensation: [N] opacity factor sqrt(det(Sigma2D) / det(Sigma2D + eps2d I)) of the
            antialiased mode (Mip-Splatting's 2D Mip filter), None in the 3DGS mode.
    """

    means2d: Tensor
    conics: Tensor
    depths: Tensor
    radii: Tensor
    visible: Tensor
    compensation: Tensor | None = None


def quat_scale_to_cov3d(quats: Tensor, scales: Tensor) -> tuple[Tensor, ...]:
    """Covariance Sigma = R S S^T R^T of splats, as its 6 unique entries.

    Args:
        quats: [N, 4] (w, x, y, z), normalised here.
        scales: [N, 3] linear standard deviations.
    Returns:
        (s00, s01, s02, s11, s12, s22), each [N].
    """
    q = quats / quats.norm(dim=-1, keepdim=True)
    w, x, y, z = q.unbind(-1)
    r00 = 1 - 2 * (y * y + z * z)
    r01 = 2 * (x * y - w * z)
    r02 = 2 * (x * z + w * y)
    r10 = 2 * (x * y + w * z)
    r11 = 1 - 2 * (x * x + z * z)
    r12 = 2 * (y * z - w * x)
    r20 = 2 * (x * z - w * y)
    r21 = 2 * (y * z + w * x)
    r22 = 1 - 2 * (x * x + y * y)
    s0, s1, s2 = scales.unbind(-1)
    # M = R S: columns scaled
    m00, m01, m02 = r00 * s0, r01 * s1, r02 * s2
    m10, m11, m12 = r10 * s0, r11 * s1, r12 * s2
    m20, m21, m22 = r20 * s0, r21 * s1, r22 * s2
    c00 = m00 * m00 + m01 * m01 + m02 * m02
    c01 = m00 * m10 + m01 * m11 + m02 * m12
    c02 = m00 * m20 + m01 * m21 + m02 * m22
    c11 = m10 * m10 + m11 * m11 + m12 * m12
    c12 = m10 * m20 + m11 * m21 + m12 * m22
    c22 = m20 * m20 + m21 * m21 + m22 * m22
    return c00, c01, c02, c11, c12, c22


def project_splats(means: Tensor, quats: Tensor, scales: Tensor, camera: Camera, eps2d: float = EPS2D,
                   antialiased: bool = False) -> Projected:
    """Project 3D Gaussians into ``camera`` with the 3DGS EWA approximation.

    Args:
        means: [N, 3] world centres; quats: [N, 4] wxyz; scales: [N, 3] linear.
        camera: OpenCV pinhole camera with full intrinsics (fx, fy, cx, cy).
        eps2d: variance (pixels^2) added to the 2D covariance diagonal: 3DGS's dilation (0.3), or
            the 2D Mip filter's variance (Mip-Splatting: 0.1) with ``antialiased``.
        antialiased: also return ``compensation`` = sqrt(det(Sigma2D) / det(Sigma2D + eps2d I))
            (floored at sqrt(AA_RATIO_MIN)), the factor the opacities are multiplied by so that the
            filtered splat keeps its integral (Mip-Splatting's 2D Mip filter).
    Returns:
        Projected screen-space splats (differentiable in means, quats, scales).
    """
    w2c = camera.world_to_cam.to(device=means.device, dtype=means.dtype)
    R = w2c[:3, :3]
    tx, ty, tz = _camera_space(means, R, w2c[:3, 3])
    visible = tz > NEAR_PLANE
    tz_safe = torch.where(visible, tz, torch.ones_like(tz))
    a0, b, c0 = _cov2d(_jacobian(tx, ty, tz_safe, camera), R, quat_scale_to_cov3d(quats, scales))
    a = a0 + eps2d
    c = c0 + eps2d
    det = a * c - b * b
    visible = visible & (det > 0)
    det_safe = torch.where(visible, det, torch.ones_like(det))
    conics = torch.stack([c / det_safe, -b / det_safe, a / det_safe], dim=-1)
    compensation = None
    if antialiased:
        det0 = a0 * c0 - b * b
        compensation = torch.sqrt(torch.clamp(det0 / det_safe, min=AA_RATIO_MIN))

    u = camera.fx * tx / tz_safe + camera.cx
    v = camera.fy * ty / tz_safe + camera.cy
    means2d = torch.stack([u, v], dim=-1)
    radii, visible = _radii(means2d, a, c, det, visible, camera)
    return Projected(means2d=means2d, conics=conics, depths=tz, radii=radii, visible=visible,
                     compensation=compensation)


def _camera_space(means: Tensor, R: Tensor, t: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """Camera-space coordinates (x, y, z), each [N], of world ``means`` [N, 3] under R [3, 3], t [3]."""
    px, py, pz = means.unbind(-1)
    tx = R[0, 0] * px + R[0, 1] * py + R[0, 2] * pz + t[0]
    ty = R[1, 0] * px + R[1, 1] * py + R[1, 2] * pz + t[1]
    tz = R[2, 0] * px + R[2, 1] * py + R[2, 2] * pz + t[2]
    return tx, ty, tz


def _jacobian(tx: Tensor, ty: Tensor, tz: Tensor, camera: Camera) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Non-zero entries (j00, j02, j11, j12), each [N], of the perspective map's Jacobian
    J = [[fx/z, 0, -fx x/z^2], [0, fy/z, -fy y/z^2]] at the camera-space points (``tz`` > 0), the
    tangents x/z, y/z clamped to 1.3x the image half-extent on each side (3DGS uses the symmetric FoV)."""
    fx, fy, cx, cy = camera.fx, camera.fy, camera.cx, camera.cy
    lim_x_pos = FRUSTUM_CLAMP * (camera.width - cx) / fx
    lim_x_neg = FRUSTUM_CLAMP * cx / fx
    lim_y_pos = FRUSTUM_CLAMP * (camera.height - cy) / fy
    lim_y_neg = FRUSTUM_CLAMP * cy / fy
    xz = (tx / tz).clamp(-lim_x_neg, lim_x_pos)
    yz = (ty / tz).clamp(-lim_y_neg, lim_y_pos)
    return fx / tz, -fx * xz / tz, fy / tz, -fy * yz / tz


def _cov2d(jac: tuple[Tensor, ...], R: Tensor, cov3d: tuple[Tensor, ...]) -> tuple[Tensor, Tensor, Tensor]:
    """Sigma2D = T Sigma T^T, T = J W (W = R [3, 3]), before the filter: its entries (a, b, c), each [N].

    ``jac``: :func:`_jacobian`'s (j00, j02, j11, j12); ``cov3d``: :func:`quat_scale_to_cov3d`'s six entries.
    """
    j00, j02, j11, j12 = jac
    c00, c01, c02, c11, c12, c22 = cov3d
    t00 = j00 * R[0, 0] + j02 * R[2, 0]
    t01 = j00 * R[0, 1] + j02 * R[2, 1]
    t02 = j00 * R[0, 2] + j02 * R[2, 2]
    t10 = j11 * R[1, 0] + j12 * R[2, 0]
    t11 = j11 * R[1, 1] + j12 * R[2, 1]
    t12 = j11 * R[1, 2] + j12 * R[2, 2]
    u0 = t00 * c00 + t01 * c01 + t02 * c02
    u1 = t00 * c01 + t01 * c11 + t02 * c12
    u2 = t00 * c02 + t01 * c12 + t02 * c22
    v0 = t10 * c00 + t11 * c01 + t12 * c02
    v1 = t10 * c01 + t11 * c11 + t12 * c12
    v2 = t10 * c02 + t11 * c12 + t12 * c22
    a = u0 * t00 + u1 * t01 + u2 * t02
    b = u0 * t10 + u1 * t11 + u2 * t12
    c = v0 * t10 + v1 * t11 + v2 * t12
    return a, b, c


@torch.no_grad()
def _radii(means2d: Tensor, a: Tensor, c: Tensor, det: Tensor, visible: Tensor, camera: Camera
           ) -> tuple[Tensor, Tensor]:
    """(radii [N] int32, visible [N]): 3 sigma of the filtered 2D covariance's larger eigenvalue, 0 for a
    splat that is culled, touches no tile or has a non-finite centre (``means2d`` [N, 2] in pixels)."""
    mid = 0.5 * (a + c)
    lam = mid + torch.sqrt(torch.clamp(mid * mid - det, min=0.1))
    radii = torch.ceil(3.0 * torch.sqrt(lam)).to(torch.int32)
    # tile rectangle in 3DGS pixel coordinates (pixel centres at integers): p = (u, v) - 0.5
    rect = tile_rects(means2d.detach() - 0.5, radii, camera.width, camera.height)
    touches = (rect[:, 2] > rect[:, 0]) & (rect[:, 3] > rect[:, 1])
    visible = visible & touches & torch.isfinite(means2d.detach()).all(-1)
    radii = torch.where(visible, radii, torch.zeros_like(radii))
    return radii, visible


def project_for_render(project, splats, camera: Camera, antialiased: bool, filter_2d: float
                       ) -> tuple[Projected, Tensor]:
    """Project ``splats`` with ``project`` (``project_splats`` or its compiled twin) and return the
    opacities [N] to blend: with ``antialiased`` the 2D Mip filter (variance ``filter_2d``) and its
    opacity compensation, else 3DGS's 0.3 px^2 dilation and the opacities as they are."""
    if antialiased:
        proj = project(splats.means, splats.quats, splats.scales, camera, eps2d=filter_2d, antialiased=True)
        return proj, splats.opacities * proj.compensation
    return project(splats.means, splats.quats, splats.scales, camera, eps2d=EPS2D), splats.opacities


def tile_rects(points: Tensor, radii: Tensor, width: int, height: int) -> Tensor:
    """3DGS ``getRect``: tile index ranges [x0, x1) x [y0, y1) touched by each splat.

    Args:
        points: [N, 2] centres in 3DGS pixel coordinates (pixel centres at integers).
        radii: [N] integer radii.
    Returns:
        [N, 4] int64 (x0, y0, x1, y1), tile indices, clamped to the tile grid.
    """
    gx = math.ceil(width / TILE)
    gy = math.ceil(height / TILE)
    r = radii.to(points.dtype)
    # C casts (int) truncate toward zero; max(0, .) is applied after the cast as in 3DGS.
    x0 = torch.trunc((points[:, 0] - r) / TILE).clamp(0, gx)
    y0 = torch.trunc((points[:, 1] - r) / TILE).clamp(0, gy)
    x1 = torch.trunc((points[:, 0] + r + TILE - 1) / TILE).clamp(0, gx)
    y1 = torch.trunc((points[:, 1] + r + TILE - 1) / TILE).clamp(0, gy)
    out = torch.stack([x0, y0, x1, y1], dim=-1)
    out = torch.nan_to_num(out, nan=0.0)
    return out.to(torch.int64)
