"""2D Gaussian surfels (2DGS, Huang et al., SIGGRAPH 2024): projection and a pure-PyTorch reference renderer.

A surfel k is a planar Gaussian disk: centre p_k, tangent axes t_u, t_v (the first two columns of the
rotation R of its (w, x, y, z) quaternion) with scales s_u, s_v, normal t_w = t_u x t_v (the third
column). A point of its plane is P(u, v) = p_k + s_u t_u u + s_v t_v v, where the Gaussian is
G(u, v) = exp(-(u^2 + v^2) / 2) (Sec. 4.1).

Rendering by explicit ray-splat intersection (Sec. 4.2). With the OpenCV camera (x right, y down,
z forward; world_to_cam = [R_c | t_c]) and K the intrinsics, the homogeneous pixel of P(u, v) is

    (x z, y z, z)^T = T (u, v, 1)^T,   T = K [R_c s_u t_u | R_c s_v t_v | R_c p_k + t_c]  (3 x 3),

rows T_u, T_v, T_w. The pixel (x, y) (pixel (i, j) has its centre at (i + 0.5, j + 0.5)) lies on the
planes h_x = x T_w - T_u and h_y = y T_w - T_v of the (u, v, 1) space; their intersection is
p = h_x x h_y and (u, v) = (p_1 / p_3, p_2 / p_3) (Eqs. 8-10). The third column of T is written as
(c_x z_k, c_y z_k, z_k), c the projected centre (``means2d``) and z_k the centre's camera depth, so that
dL/d(means2d) is the screen-space gradient 3DGS densification uses (the reference code's
"dL/dT[:, 2] x depth" for 2DGS).

Per pixel and surfel, in a stable front-to-back order of the centres' camera depth:

* the pixel must lie in the surfel's pixel rectangle (:func:`surfel_rects`: the bounding box of the
  projected 3-sigma disk, united with the low-pass filter's 3-sigma square around c);
* skipped if p_3 = 0 (the ray is parallel to the surfel plane);
* object-space low-pass filter (Eq. 11): rho = min(u^2 + v^2, |x - c|^2 / sigma^2), sigma = sqrt(2) / 2;
  G = exp(-rho / 2). The depth is the ray-plane intersection's, T_w . (u, v, 1), where the surface
  Gaussian wins, and the centre's depth z_k where the filter wins;
* skipped if that depth is below the near plane 0.2;
* then the 3DGS rules of this project's rasterizers: alpha = min(0.99, o G), skipped below 1/255,
  front-to-back compositing stopping before the surfel that would take T below 1e-4, background
  weighted by T_final.

Outputs per pixel (w_i = alpha_i T_i): colour sum_i w_i c_i + T_final bg, alpha 1 - T_final, depth
sum_i w_i z_i (not normalised by alpha, like every rasterizer here), normals sum_i w_i n_i (world
frame; n_i = +-t_w oriented towards the camera), and the depth distortion sum_{j<i} w_i w_j
(m_i - m_j)^2 (Sec. 4.1, Eq. 13 as the reference code evaluates it: squared, over pairs j < i, of the
NDC-mapped depth m = f / (f - n) (1 - n / z) with n = 0.2, f = 100).

Conventions: OpenCV cameras, wxyz quaternions (normalised here), linear scales (only the first two
columns of ``Splats.scales`` are read), opacities in (0, 1), linear RGB in [0, 1].
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from src.core.cameras import Camera
from src.core.splats import Splats, SurfelRenderOutput
from src.rasterizer.projection import NEAR_PLANE, TILE

ALPHA_MAX = 0.99  # 3DGS clamps alpha to 0.99
ALPHA_MIN = 1.0 / 255.0  # 3DGS skips fragments below 1/255
T_MIN = 1e-4  # 3DGS stops before the splat that takes T below 1e-4
FILTER_SIGMA = math.sqrt(2.0) / 2.0  # 2DGS Eq. 11: object-space low-pass filter, sigma = sqrt(2) / 2 pixel
CUTOFF = 3.0  # 2DGS reference (compute_aabb): the rectangle bounds the 3-sigma disk
DIST_NEAR = 0.2  # 2DGS reference: near plane of the NDC depth mapping in the distortion (near_n)
DIST_FAR = 100.0  # 2DGS reference: far plane of the same mapping (far_n)


@dataclass
class SurfelProjection:
    """Screen-space surfels.

    Attributes:
        transforms: [N, 9] rows T_u, T_v, T_w of T (homogeneous pixel = T (u, v, 1)), differentiable.
        means2d: [N, 2] projected centres c (pixels; pixel centres at i + 0.5), differentiable.
        depths: [N] camera depth z_k of the centres (the sort key; T_w[2]).
        normals: [N, 3] world-frame unit normals oriented towards the camera, differentiable.
        rects: [N, 4] int32 inclusive pixel index ranges (i0, j0, i1, j1) a surfel may touch.
        radii: [N] int32 pixel radius (0 if culled).
        visible: [N] bool: in front of the near plane, not edge-on, finite, touching a pixel.
    """

    transforms: Tensor
    means2d: Tensor
    depths: Tensor
    normals: Tensor
    rects: Tensor
    radii: Tensor
    visible: Tensor


def quat_to_axes(quats: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """The columns (t_u, t_v, t_w), each [N, 3], of the rotation of wxyz quaternions [N, 4] (normalised here)."""
    q = quats / quats.norm(dim=-1, keepdim=True)
    w, x, y, z = q.unbind(-1)
    tu = torch.stack([1 - 2 * (y * y + z * z), 2 * (x * y + w * z), 2 * (x * z - w * y)], dim=-1)
    tv = torch.stack([2 * (x * y - w * z), 1 - 2 * (x * x + z * z), 2 * (y * z + w * x)], dim=-1)
    tw = torch.stack([2 * (x * z + w * y), 2 * (y * z - w * x), 1 - 2 * (x * x + y * y)], dim=-1)
    return tu, tv, tw


@torch.no_grad()
def surfel_rects(transforms: Tensor, means2d: Tensor, width: int, height: int,
                 cutoff: float = CUTOFF, sigma: float = FILTER_SIGMA) -> tuple[Tensor, Tensor]:
    """Pixel rectangles of surfels: the bounding box of the projected ``cutoff``-sigma disk and of the
    low-pass filter's ``cutoff`` x ``sigma`` square around the projected centre.

    The disk u^2 + v^2 <= r^2 (r = cutoff) has the dual conic diag(r^2, r^2, -1); its image is
    C* = T diag(r^2, r^2, -1) T^T and the vertical tangents x of the projected ellipse solve
    C*_00 - 2 x C*_02 + x^2 C*_22 = 0 (the same for y). Where C*_22 >= 0 the disk reaches the camera's
    principal plane (its image is unbounded): the rectangle is the whole image.

    Args:
        transforms: [N, 9] rows of T; means2d: [N, 2] projected centres (pixels).
    Returns:
        (rects [N, 4] int32 inclusive pixel index ranges (i0, j0, i1, j1), clipped to the image (empty
        when i0 > i1 or j0 > j1), radii [N] int32 = ceil of the largest half-extent).
    """
    T = transforms.reshape(-1, 3, 3).double()
    t = torch.tensor([cutoff * cutoff, cutoff * cutoff, -1.0], dtype=T.dtype, device=T.device)
    tu, tv, tw = T[:, 0], T[:, 1], T[:, 2]
    d = (tw * tw * t).sum(-1)  # C*_22
    bounded = d < 0
    d_safe = torch.where(bounded, d, -torch.ones_like(d))
    px = (tu * tw * t).sum(-1) / d_safe
    py = (tv * tw * t).sum(-1) / d_safe
    hx = torch.sqrt(torch.clamp(px * px - (tu * tu * t).sum(-1) / d_safe, min=0.0))
    hy = torch.sqrt(torch.clamp(py * py - (tv * tv * t).sum(-1) / d_safe, min=0.0))
    c = means2d.detach().double()
    rf = cutoff * sigma
    x0 = torch.minimum(px - hx, c[:, 0] - rf)
    x1 = torch.maximum(px + hx, c[:, 0] + rf)
    y0 = torch.minimum(py - hy, c[:, 1] - rf)
    y1 = torch.maximum(py + hy, c[:, 1] + rf)
    big = float(4 * max(width, height) + 16)
    x0 = torch.where(bounded, x0, torch.full_like(x0, -big)).nan_to_num(nan=big).clamp(-big, big)
    x1 = torch.where(bounded, x1, torch.full_like(x1, big)).nan_to_num(nan=-big).clamp(-big, big)
    y0 = torch.where(bounded, y0, torch.full_like(y0, -big)).nan_to_num(nan=big).clamp(-big, big)
    y1 = torch.where(bounded, y1, torch.full_like(y1, big)).nan_to_num(nan=-big).clamp(-big, big)
    # pixel i (centre i + 0.5) is inside iff x0 <= i + 0.5 <= x1
    i0 = torch.ceil(x0 - 0.5).clamp(0, width)
    i1 = torch.floor(x1 - 0.5).clamp(-1, width - 1)
    j0 = torch.ceil(y0 - 0.5).clamp(0, height)
    j1 = torch.floor(y1 - 0.5).clamp(-1, height - 1)
    rects = torch.stack([i0, j0, i1, j1], dim=-1).to(torch.int32)
    radius = torch.maximum(torch.maximum(hx, hy), torch.full_like(hx, rf))
    radius = torch.where(bounded, radius, torch.full_like(radius, float(max(width, height))))
    radii = torch.ceil(radius.nan_to_num(nan=0.0).clamp(0, big)).to(torch.int32)
    return rects, radii


def project_surfels(means: Tensor, quats: Tensor, scales: Tensor, camera: Camera) -> SurfelProjection:
    """Ray-splat intersection matrices T of surfels seen by ``camera`` (see the module docstring).

    Args:
        means: [N, 3] world centres; quats: [N, 4] wxyz (normalised here); scales: [N, 2] or [N, 3]
            linear tangent scales (s_u, s_v; a third column is ignored).
        camera: OpenCV pinhole camera.
    Returns:
        SurfelProjection, differentiable in means, quats and scales through ``transforms``,
        ``means2d`` and ``normals``.
    """
    dt = means.dtype
    w2c = camera.world_to_cam.to(device=means.device, dtype=dt)
    Rc, tc = w2c[:3, :3], w2c[:3, 3]
    tu, tv, tw = quat_to_axes(quats)
    au = (tu * scales[:, 0:1]) @ Rc.T  # [N, 3] camera-frame scaled tangent axes
    av = (tv * scales[:, 1:2]) @ Rc.T
    pc = means @ Rc.T + tc  # [N, 3] camera-frame centres
    z = pc[:, 2]
    front = z > NEAR_PLANE
    zs = torch.where(front, z, torch.ones_like(z))
    fx, fy, cx, cy = camera.fx, camera.fy, camera.cx, camera.cy
    means2d = torch.stack([fx * pc[:, 0] / zs + cx, fy * pc[:, 1] / zs + cy], dim=-1)  # [N, 2]
    row_u = torch.stack([fx * au[:, 0] + cx * au[:, 2], fx * av[:, 0] + cx * av[:, 2], means2d[:, 0] * z], -1)
    row_v = torch.stack([fy * au[:, 1] + cy * au[:, 2], fy * av[:, 1] + cy * av[:, 2], means2d[:, 1] * z], -1)
    row_w = torch.stack([au[:, 2], av[:, 2], z], dim=-1)
    transforms = torch.cat([row_u, row_v, row_w], dim=-1)  # [N, 9]
    with torch.no_grad():
        cos = -(pc * (tw @ Rc.T)).sum(-1)  # > 0: t_w faces the camera
        sign = torch.where(cos > 0, torch.ones_like(cos), -torch.ones_like(cos))
    normals = tw * sign[:, None]  # [N, 3] world frame, towards the camera
    rects, radii = surfel_rects(transforms.detach(), means2d.detach(), camera.width, camera.height)
    with torch.no_grad():
        finite = torch.isfinite(transforms).all(-1) & torch.isfinite(means2d).all(-1)
        visible = front & (cos != 0) & finite & (rects[:, 0] <= rects[:, 2]) & (rects[:, 1] <= rects[:, 3])
        radii = torch.where(visible, radii, torch.zeros_like(radii))
    return SurfelProjection(transforms=transforms, means2d=means2d, depths=z, normals=normals, rects=rects,
                            radii=radii, visible=visible)


def composite_surfels_tile(
    pix: Tensor,  # [P, 2] pixel centres (x, y)
    pix_idx: Tensor,  # [P, 2] int pixel indices (i, j)
    transforms: Tensor,  # [M, 9] depth-sorted
    means2d: Tensor,  # [M, 2]
    rects: Tensor,  # [M, 4] int
    opacities: Tensor,  # [M]
    feats: Tensor,  # [M, F] composited features (colour, normal)
) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Front-to-back compositing of M depth-sorted surfels over P pixels (rules: module docstring).

    Returns:
        (features [P, F], depth [P], distortion [P], final transmittance [P]).
    """
    x, y = pix[:, 0:1], pix[:, 1:2]  # [P, 1]
    tu, tv, tw = transforms[:, 0:3], transforms[:, 3:6], transforms[:, 6:9]  # [M, 3]
    k = x[..., None] * tw[None] - tu[None]  # [P, M, 3] plane h_x
    l = y[..., None] * tw[None] - tv[None]  # [P, M, 3] plane h_y
    p = torch.linalg.cross(k, l, dim=-1)  # [P, M, 3]
    pz = p[..., 2]
    ok = pz != 0
    pz_safe = torch.where(ok, pz, torch.ones_like(pz))
    su, sv = p[..., 0] / pz_safe, p[..., 1] / pz_safe  # [P, M] intersection (u, v)
    rho3d = su * su + sv * sv
    dx = means2d[None, :, 0] - x
    dy = means2d[None, :, 1] - y
    rho2d = (dx * dx + dy * dy) / (FILTER_SIGMA * FILTER_SIGMA)
    surface = rho3d <= rho2d
    rho = torch.where(surface, rho3d, rho2d)
    depth = torch.where(surface, su * tw[None, :, 0] + sv * tw[None, :, 1] + tw[None, :, 2],
                        tw[None, :, 2].expand_as(su))
    inside = ((rects[None, :, 0] <= pix_idx[:, 0:1]) & (pix_idx[:, 0:1] <= rects[None, :, 2])
              & (rects[None, :, 1] <= pix_idx[:, 1:2]) & (pix_idx[:, 1:2] <= rects[None, :, 3]))
    g = torch.exp(-0.5 * rho)
    alpha = torch.clamp(opacities[None, :] * g, max=ALPHA_MAX)
    keep = inside & ok & (depth >= DIST_NEAR) & (alpha >= ALPHA_MIN)
    alpha = torch.where(keep, alpha, torch.zeros_like(alpha))
    with torch.no_grad():  # termination: blend only while T after the surfel stays >= T_MIN (a prefix)
        blend = torch.cumprod(1.0 - alpha, dim=1) >= T_MIN
    alpha = torch.where(blend, alpha, torch.zeros_like(alpha))
    t_incl = torch.cumprod(1.0 - alpha, dim=1)
    t_excl = torch.cat([torch.ones_like(t_incl[:, :1]), t_incl[:, :-1]], dim=1)
    w = alpha * t_excl  # [P, M]
    used = keep & blend
    z = torch.where(used, depth, torch.ones_like(depth))
    m = DIST_FAR / (DIST_FAR - DIST_NEAR) * (1.0 - DIST_NEAR / z)  # [P, M] NDC-mapped depth
    wm, wm2 = w * m, w * m * m
    m1 = torch.cumsum(wm, dim=1) - wm  # exclusive prefix sums
    m2 = torch.cumsum(wm2, dim=1) - wm2
    dist = (w * (m * m * (1.0 - t_excl) + m2 - 2.0 * m * m1)).sum(1)
    return w @ feats, (w * z).sum(1), dist, t_incl[:, -1]


def composite_surfels_ref(proj: SurfelProjection, opacities: Tensor, colors: Tensor, width: int, height: int,
                          background: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
    """Composite projected surfels per 16 x 16 tile with autograd (the oracle of the compiled kernel).

    Args:
        proj: :func:`project_surfels` output; opacities: [N]; colors: [N, C]; background: [C].
    Returns:
        color [H, W, C], alpha [H, W], depth [H, W], normals [H, W, 3], distortion [H, W].
    """
    device, dtype = colors.device, colors.dtype
    C = colors.shape[1]
    vis = torch.nonzero(proj.visible).squeeze(1)
    order = vis[torch.argsort(proj.depths.detach()[vis], stable=True)]
    trans, m2d, rects = proj.transforms[order], proj.means2d[order], proj.rects[order].long()
    opac = opacities[order]
    feats = torch.cat([colors[order], proj.normals[order]], dim=1)  # [M, C + 3]
    nf = C + 3
    out = torch.zeros(height, width, nf, device=device, dtype=dtype)
    depth = torch.zeros(height, width, device=device, dtype=dtype)
    dist = torch.zeros(height, width, device=device, dtype=dtype)
    t_final = torch.ones(height, width, device=device, dtype=dtype)
    for y0 in range(0, height, TILE):
        y1 = min(y0 + TILE, height)
        for x0 in range(0, width, TILE):
            x1 = min(x0 + TILE, width)
            sel = torch.nonzero((rects[:, 0] <= x1 - 1) & (rects[:, 2] >= x0)
                                & (rects[:, 1] <= y1 - 1) & (rects[:, 3] >= y0)).squeeze(1)
            if sel.numel() == 0:
                continue
            jj, ii = torch.meshgrid(torch.arange(y0, y1, device=device), torch.arange(x0, x1, device=device),
                                    indexing="ij")
            idx = torch.stack([ii.reshape(-1), jj.reshape(-1)], dim=-1)  # [P, 2]
            acc, dep, dis, tt = composite_surfels_tile(idx.to(dtype) + 0.5, idx, trans[sel], m2d[sel], rects[sel],
                                                       opac[sel], feats[sel])
            shape = (y1 - y0, x1 - x0)
            out = out.index_put((jj, ii), acc.reshape(*shape, nf))
            depth = depth.index_put((jj, ii), dep.reshape(shape))
            dist = dist.index_put((jj, ii), dis.reshape(shape))
            t_final = t_final.index_put((jj, ii), tt.reshape(shape))
    color = out[..., :C] + t_final[..., None] * background
    return color, 1.0 - t_final, depth, out[..., C:], dist


def render_surfels_ref(splats: Splats, camera: Camera, background: Tensor | None = None) -> SurfelRenderOutput:
    """Render ``splats`` as 2D Gaussian surfels with the pure-PyTorch reference (autograd backward).

    Args:
        splats: N activated splats; ``scales[:, :2]`` are the tangent scales (s_u, s_v).
        camera: OpenCV pinhole camera.
        background: [C] colour weighted by T_final (zeros if None).
    Returns:
        SurfelRenderOutput (colour, alpha, depth, world normals, distortion, means2d, radii).
    """
    splats.validate()
    C = splats.colors.shape[1]
    dtype, device = splats.means.dtype, splats.means.device
    bg = torch.zeros(C, device=device, dtype=dtype) if background is None else background.to(device, dtype)
    proj = project_surfels(splats.means, splats.quats, splats.scales, camera)
    color, alpha, depth, normals, dist = composite_surfels_ref(proj, splats.opacities, splats.colors,
                                                               camera.width, camera.height, bg)
    return SurfelRenderOutput(color=color, alpha=alpha, depth=depth, means2d=proj.means2d, radii=proj.radii,
                              normals=normals, distortion=dist)
