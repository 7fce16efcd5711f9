"""The regularisers of SuGaR (Guédon and Lepetit, "SuGaR: Surface-Aligned Gaussian Splatting for Efficient 3D
Mesh Reconstruction", CVPR 2024, Sec. 4.1) on top of eq. A.2.

After a 3DGS warm-up, SuGaR adds

* an entropy term on the opacities of the splats a view draws, -o log o - (1 - o) log(1 - o), which pushes
  every opacity to 0 or 1 (:func:`opacity_entropy`), until the low-opacity splats are pruned once
  (:class:`src.strategy.sugar.SugarStrategy`);
* then the surface-alignment regulariser on points p sampled from the splats a view draws near its rendered
  surface: an estimate of the SDF from the rendered depth, f_hat(p) = D(pi(p)) - z(p) (the distance along the
  camera axis between the rendered depth at p's pixel and p's own depth, :func:`sdf_from_depth`), compared
  with the SDF the Gaussians would have if they were flat and opaque, f(p) = s* sqrt(-2 log d(p))
  (:func:`ideal_sdf`; d the density sum_g o_g exp(-0.5 (p - mu_g)^T Sigma_g^-1 (p - mu_g)), s* the smallest
  scale of the closest Gaussian g*), as mean |f(p) - |f_hat(p)|| in units of a tenth of the scene's camera
  extent, each sample's error clamped at 10 x that extent (SuGaR's code);
* the normal term || grad f / |grad f| - n* ||^2, n* the shortest axis of g*, with the direction of grad f
  that of the density's gradient (:func:`density_gradient`), sign-agnostic;
* a flatness push on the smallest scale of each drawn splat (:func:`flatness`; not a term of the paper,
  whose ideal SDF assumes flat Gaussians: a small weight that helps the splats become so).

Conventions: OpenCV cameras (x right, y down, z forward; pixel (i, j) centred at (i + 0.5, j + 0.5)); a point
is in front of a camera beyond the rasterizers' near plane (``NEAR_PLANE``, z > 0.2, SuGaR's ``znear`` test);
``RenderOutput.depth`` the accumulated sum z alpha T (not normalised); activated splats (linear scales,
opacities in (0, 1), (w, x, y, z) quaternions, not necessarily unit); samples are drawn from the run's
``torch.Generator`` (the trainer's checkpoints hold its state).
"""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F
from scipy.spatial import cKDTree
from torch import Tensor

from src.core.cameras import Camera
from src.core.splats import RenderOutput, Splats, shortest_axis
from src.data.base import View
from src.fields.flows import quat_to_rotmat_wxyz
from src.losses.objective import SplatLoss
from src.rasterizer.projection import NEAR_PLANE
from src.utils.validate import ConfigValueError

EPS = 1e-10
SCALE_MIN = 1e-6  # floor of the scales the density divides by: (offset / s)^2 stays finite in float32


def opacity_entropy(opacities: Tensor) -> Tensor:
    """Mean binary entropy -o log o - (1 - o) log(1 - o) of opacities [N] in [0, 1] (~0 at 0 and 1, log 2 at 0.5).

    The logarithms' arguments get 1e-10 (as SuGaR's code), so the gradient stays finite at opacities of
    exactly 0 or 1 (a sigmoid underflows to 0 in float32 below logit -104).
    """
    if opacities.numel() == 0:
        return opacities.new_zeros(())
    o = opacities.clamp(0.0, 1.0)
    return -(o * torch.log(o + EPS) + (1.0 - o) * torch.log(1.0 - o + EPS)).mean()


def depth_map(render: RenderOutput, far: Tensor | float) -> Tensor:
    """[H, W] rendered depth with the uncovered part of each pixel at ``far``: depth + (1 - alpha) far.

    SuGaR's code renders the centres' depths as colours over a background at the largest centre depth: the
    same map. Differentiable in the render's depth and alpha.
    """
    return render.depth + (1.0 - render.alpha) * far


def camera_points(camera: Camera, points: Tensor) -> Tensor:
    """[..., 3] camera-frame coordinates of world points [..., 3] (differentiable in the points)."""
    R = camera.world_to_cam[:3, :3].to(points)
    t = camera.world_to_cam[:3, 3].to(points)
    return points @ R.T + t


def sample_map(image: Tensor, camera: Camera, xyz_cam: Tensor) -> tuple[Tensor, Tensor]:
    """Bilinear samples of ``image`` [H, W] at the projections of camera-frame points ``xyz_cam`` [S, 3].

    Returns (values [S], inside [S] bool: the point lies beyond the near plane (z > ``NEAR_PLANE``) and
    projects between the first and last pixel centres). Differentiable in ``image`` and in the points.
    """
    h, w = image.shape
    z = xyz_cam[:, 2]
    front = z > NEAR_PLANE
    zs = torch.where(front, z, torch.ones_like(z))
    u = camera.fx * xyz_cam[:, 0] / zs + camera.cx  # [S] pixels, centres at i + 0.5
    v = camera.fy * xyz_cam[:, 1] / zs + camera.cy
    inside = front & (u >= 0.5) & (u <= w - 0.5) & (v >= 0.5) & (v <= h - 0.5)
    grid = torch.stack([2.0 * u / w - 1.0, 2.0 * v / h - 1.0], dim=-1)[None, None]  # [1, 1, S, 2]
    values = F.grid_sample(image[None, None].to(xyz_cam.dtype), grid, mode="bilinear", padding_mode="border",
                           align_corners=False)
    return values[0, 0, 0], inside


def sdf_from_depth(points: Tensor, depth: Tensor, camera: Camera) -> tuple[Tensor, Tensor]:
    """SuGaR's SDF estimate f_hat(p) = D(pi(p)) - z(p) of world points ``points`` [S, 3] from a depth map [H, W].

    Positive in front of the rendered surface. Returns (f_hat [S], valid [S] bool, as
    :func:`sample_map`'s ``inside``).
    """
    xyz = camera_points(camera, points)
    map_z, inside = sample_map(depth, camera, xyz)
    return map_z - xyz[:, 2], inside


def local_offsets(points: Tensor, means: Tensor, rotations: Tensor) -> Tensor:
    """[S, K, 3] offsets R_g^T (p - mu_g) of points [S, 3] in the frames of K Gaussians each (means [S, K, 3],
    rotations [S, K, 3, 3] whose columns are the Gaussians' axes)."""
    return (rotations * (points[:, None, :] - means)[..., :, None]).sum(-2)  # sum_j R_ji (p - mu)_j


def gaussian_terms(points: Tensor, means: Tensor, rotations: Tensor, scales: Tensor,
                   opacities: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """Each of K Gaussians' term in the density at points [S, 3] (means [S, K, 3], rotations [S, K, 3, 3],
    linear scales [S, K, 3], opacities [S, K]).

    Returns (contributions o exp(-m^2 / 2) [S, K], squared Mahalanobis distances m^2 [S, K], scaled local
    offsets R^T (p - mu) / s^2 [S, K, 3]); the density d(p) is the sum of the contributions. Scales are
    floored at 1e-6 (world units, far below a pixel here).
    """
    local = local_offsets(points, means, rotations)
    s = scales.clamp_min(SCALE_MIN)
    m2 = ((local / s) ** 2).sum(-1)
    return opacities * torch.exp(-0.5 * m2), m2, local / s**2


def ideal_sdf(density: Tensor, smallest_scale: Tensor) -> Tensor:
    """SuGaR's SDF of flat opaque Gaussians from a density: f = s* sqrt(-2 log d), d clamped to [1e-16, 1].

    For a single opaque Gaussian flat along its normal n, d(p) = exp(-<p - mu, n>^2 / (2 s*^2)) and f(p) is
    |<p - mu, n>|, the distance to its plane. The square root's argument is floored at 1e-10 so the
    gradient stays finite where d reaches 1. ``density`` [S], ``smallest_scale`` [S].

    Where d >= 1 (overlapping opaque Gaussians) f = s* sqrt(1e-10) ~ 0 and the density gets no gradient (the
    clamp at 1 and the floor both cut it); only s* does. A deviation from SuGaR's code, which replaces such
    densities by d / d.detach() (value 1, gradient 1 / d) and takes the square root without a floor, whose
    derivative is unbounded at 1: here those samples pull the surface's Gaussians nowhere.
    """
    d = density.clamp(min=1e-16, max=1.0)
    return smallest_scale * torch.sqrt((-2.0 * torch.log(d)).clamp_min(EPS))


def density_gradient(contributions: Tensor, rotations: Tensor, scaled_local: Tensor) -> Tensor:
    """[S, 3] world-frame gradient of the density, -sum_g c_g Sigma_g^-1 (p - mu_g) = -sum_g c_g R_g (R_g^T (p - mu_g)
    / s_g^2), from :func:`gaussian_terms` (contributions [S, K], scaled offsets [S, K, 3]) and rotations
    [S, K, 3, 3]."""
    world = torch.einsum("skij,skj->ski", rotations, scaled_local)  # [S, K, 3] R (R^T (p - mu) / s^2)
    return -(contributions[..., None] * world).sum(1)


def near_surface(splats: Splats, rotations: Tensor, depth: Tensor, camera: Camera, visible: Tensor,
                 sigmas: float) -> Tensor:
    """[N] bool: drawn splats whose centre lies within ``sigmas`` standard deviations (along the ray to the
    camera) of the rendered depth at its pixel, SuGaR's set of Gaussians to sample from. No gradient."""
    with torch.no_grad():
        xyz = camera_points(camera, splats.means)
        map_z, inside = sample_map(depth, camera, xyz)
        to_cam = F.normalize(camera.center.to(splats.means) - splats.means, dim=-1)  # [N, 3]
        along = torch.einsum("nji,nj->ni", rotations, to_cam)  # ray direction in each splat's frame
        std = (splats.scales * along).norm(dim=-1)  # [N] standard deviation along the ray
        return visible & inside & ((map_z - xyz[:, 2]).abs() < sigmas * std)


def sample_in_splats(splats: Splats, rotations: Tensor, index: Tensor, factor: float,
                     generator: torch.Generator | None = None) -> Tensor:
    """[S, 3] points mu + R (factor s * eps), eps ~ N(0, I), one for each splat in ``index`` [S] (differentiable
    in the splats' means, scales and rotations)."""
    eps = torch.randn(index.shape[0], 3, generator=generator, dtype=splats.means.dtype).to(splats.means.device)
    offsets = factor * splats.scales[index] * eps
    return splats.means[index] + torch.einsum("sij,sj->si", rotations[index], offsets)


def nearest_centres(points: Tensor, means: Tensor, k: int) -> Tensor:
    """[S, k'] indices of the k' = min(k, N) centres ``means`` [N, 3] nearest to ``points`` [S, 3] (no gradient)."""
    k = min(int(k), means.shape[0])
    _, idx = cKDTree(means.detach().cpu().double().numpy()).query(points.detach().cpu().double().numpy(), k=k)
    idx = np.asarray(idx, dtype=np.int64).reshape(points.shape[0], k)
    return torch.from_numpy(idx).to(points.device)


def flatness(scales: Tensor) -> Tensor:
    """Mean over splats of s_min / s_mid (s_mid detached), scales [N, 3]: pushes the smallest scale down alone."""
    if scales.shape[0] == 0:
        return scales.new_zeros(())
    s = torch.sort(scales, dim=-1).values
    return (s[:, 0] / s[:, 1].detach().clamp_min(EPS)).mean()


def surface_terms(render: RenderOutput, camera: Camera, splats: Splats, n_samples: int, sample_scale: float = 1.5,
                  k: int = 16, sigmas: float = 2.0, normal_through_normal_only: bool = True,
                  extent_fraction: float = 0.1, extent: float = 1.0,
                  generator: torch.Generator | None = None) -> tuple[Tensor, Tensor] | None:
    """SuGaR's SDF and normal terms for one view: (mean of min(|f(p) - |f_hat(p)|| / scale, 10 extent),
    mean ||g -+ n*||^2), or None when no drawn splat lies near the rendered surface.

    ``n_samples`` points are drawn with ``generator`` from the splats of :func:`near_surface` (uniformly over
    splats, then p ~ N(mu, (sample_scale s)^2) in the splat's frame); those behind the near plane or
    projecting outside the image are dropped. The density at p sums the ``k`` Gaussians whose centres are
    nearest to p; g* is the one of them with the smallest Mahalanobis distance. The SDF error is divided by
    scale = ``extent_fraction`` x ``extent``, the scene's camera extent (1.1 x the largest distance of a
    training camera from their centroid, :attr:`src.data.base.Scene.extent`, as SuGaR's code), and each
    sample's quotient is clamped at 10 x ``extent`` (SuGaR's code). g is the unit density gradient, detached
    when ``normal_through_normal_only`` (gradients reach n* only, SuGaR's code); ||g -+ n*||^2 = 2 - 2 |g . n*|.
    """
    rotations = quat_to_rotmat_wxyz(splats.quats)  # [N, 3, 3]
    with torch.no_grad():
        z = camera_points(camera, splats.means)[:, 2]
        front = z > NEAR_PLANE
        if not bool(front.any()):
            return None
        far = z[front].max()
    depth = depth_map(render, far)  # [H, W]
    visible = (render.radii > 0) & front
    candidates = torch.nonzero(near_surface(splats, rotations, depth.detach(), camera, visible, sigmas)).squeeze(1)
    if candidates.numel() == 0:
        return None
    pick = torch.randint(candidates.numel(), (int(n_samples),), generator=generator).to(candidates.device)
    points = sample_in_splats(splats, rotations, candidates[pick], sample_scale, generator)  # [S, 3]
    f_hat, valid = sdf_from_depth(points, depth, camera)
    if not bool(valid.any()):
        return None
    points, f_hat = points[valid], f_hat[valid]
    nbr = nearest_centres(points, splats.means, k)  # [S, K]
    rot = rotations[nbr]  # [S, K, 3, 3]
    contrib, m2, scaled = gaussian_terms(points, splats.means[nbr], rot, splats.scales[nbr], splats.opacities[nbr])
    star = nbr.gather(1, m2.argmin(-1, keepdim=True))[:, 0]  # [S] g*
    s_star, _, n_star = shortest_axis(rotations[star], splats.scales[star])  # [S], [S, 3] shortest axis of g*
    f = ideal_sdf(contrib.sum(-1), s_star)
    sdf = ((f - f_hat.abs()).abs() / (extent_fraction * extent)).clamp(max=10.0 * extent).mean()
    g = F.normalize(density_gradient(contrib, rot, scaled), dim=-1)
    if normal_through_normal_only:
        g = g.detach()
    normal = (2.0 - 2.0 * (g * n_star).sum(-1).abs()).mean()
    return sdf, normal


def _check(key: str, value: float, ok: bool, expected: str) -> None:
    """Raise :class:`ConfigValueError` naming ``loss.<key>`` unless ``ok``."""
    if not ok:
        raise ConfigValueError(f"loss.{key}={value!r}: expected {expected}")


class SugarLoss(SplatLoss):
    """eq. A.2 (:class:`SplatLoss`) + SuGaR's regularisers (Sec. 4.1), each in its window of 0-based iterations.

    Args:
        entropy_weight: weight of the opacity entropy (SuGaR's code: 0.1), from ``entropy_from`` until
            ``sdf_from`` (the prune), over the splats each view draws.
        entropy_from: end of the 3DGS warm-up (SuGaR: iteration 7 000 of 15 000); at most ``sdf_from``.
        sdf_from: the surface terms act from here on (SuGaR: 9 000 of 15 000, after the prune).
        sdf_weight: weight of the SDF term (SuGaR's code: ``estimation_factor`` 0.2).
        normal_weight: weight of the normal term (SuGaR's code: ``normal_factor`` 0.2).
        flat_weight: weight of :func:`flatness` of the drawn splats, from ``flat_from`` on (not in the paper:
            0 here; ``+experiment=sugar`` sets 0.01).
        flat_from: first iteration of the flatness push (the end of the warm-up, as ``entropy_from``:
            ``loss/sugar.yaml``).
        n_samples: points sampled per view (SuGaR's code: ``n_samples_for_sdf_regularization`` 1 000 000,
            one view per iteration).
        sample_scale: samples are drawn at this many times each splat's scales (SuGaR's code: 1.5).
        k_neighbours: centres nearest to a sample whose Gaussians make its density (SuGaR's code: 16).
        near_surface_sigmas: sample only splats whose centre is within this many standard deviations of the
            rendered depth (SuGaR's code: 2); > 0.
        normal_through_normal_only: the normal term's gradient reaches only n* (SuGaR's code: true).
        extent_fraction: the SDF error is divided by this fraction of the camera extent (SuGaR's code: 0.1).
        extent: the scene's camera extent (:attr:`src.data.base.Scene.extent`, passed at run time).
        generator: the run's generator, which draws the samples (passed at run time; the trainer's
            checkpoints hold its state, so a resumed run draws the same samples). None: torch's global one.
        **kwargs: the arguments of :class:`SplatLoss`.

    Raises:
        ConfigValueError: a value out of range, naming its ``loss.`` key.
    """

    def __init__(self, entropy_weight: float = 0.1, entropy_from: int = 7000, sdf_from: int = 9000,
                 sdf_weight: float = 0.2, normal_weight: float = 0.2, flat_weight: float = 0.0,
                 flat_from: int = 7000, n_samples: int = 1_000_000, sample_scale: float = 1.5,
                 k_neighbours: int = 16, near_surface_sigmas: float = 2.0, normal_through_normal_only: bool = True,
                 extent_fraction: float = 0.1, extent: float = 1.0, generator: torch.Generator | None = None,
                 **kwargs) -> None:
        super().__init__(**kwargs)
        for key, value in (("entropy_weight", entropy_weight), ("sdf_weight", sdf_weight),
                           ("normal_weight", normal_weight), ("flat_weight", flat_weight)):
            _check(key, value, value >= 0, ">= 0")
        _check("n_samples", n_samples, n_samples >= 1, "an integer >= 1")
        _check("k_neighbours", k_neighbours, k_neighbours >= 1, "an integer >= 1")
        for key, value in (("sample_scale", sample_scale), ("near_surface_sigmas", near_surface_sigmas),
                           ("extent_fraction", extent_fraction)):
            _check(key, value, value > 0, "a number > 0")
        _check("entropy_from", entropy_from, entropy_from <= sdf_from,
               f"at most loss.sdf_from={sdf_from} (the entropy acts from entropy_from until sdf_from)")
        if not extent > 0:
            raise ValueError(f"SugarLoss: the scene's camera extent must be > 0, got {extent}")
        self.entropy_weight, self.sdf_weight = float(entropy_weight), float(sdf_weight)
        self.normal_weight, self.flat_weight = float(normal_weight), float(flat_weight)
        self.entropy_from, self.sdf_from, self.flat_from = int(entropy_from), int(sdf_from), int(flat_from)
        self.n_samples, self.sample_scale, self.k = int(n_samples), float(sample_scale), int(k_neighbours)
        self.sigmas = float(near_surface_sigmas)
        self.through_normal = bool(normal_through_normal_only)
        self.extent_fraction, self.extent = float(extent_fraction), float(extent)
        self.generator = generator

    def __call__(self, renders: list[RenderOutput], views: list[View], splats: list[Splats],
                 iteration: int = 0) -> dict[str, Tensor]:
        """Loss terms of :class:`SplatLoss` plus 'entropy', 'sdf', 'normal', 'flat' while they act, and 'total'."""
        terms = super().__call__(renders, views, splats, iteration=iteration)
        total = terms["total"]
        n = len(renders)
        drawn = [r.radii > 0 for r in renders]  # [N] bool per view: the splats it draws
        if self.entropy_weight > 0 and self.entropy_from <= iteration < self.sdf_from:
            terms["entropy"] = sum(opacity_entropy(s.opacities[m]) for s, m in zip(splats, drawn, strict=True)) / n
            total = total + self.entropy_weight * terms["entropy"]
        if self.flat_weight > 0 and iteration >= self.flat_from:
            terms["flat"] = sum(flatness(s.scales[m]) for s, m in zip(splats, drawn, strict=True)) / n
            total = total + self.flat_weight * terms["flat"]
        if (self.sdf_weight > 0 or self.normal_weight > 0) and iteration >= self.sdf_from:
            found = [surface_terms(r, v.camera, s, self.n_samples, self.sample_scale, self.k, self.sigmas,
                                   self.through_normal, self.extent_fraction, self.extent, self.generator)
                     for r, v, s in zip(renders, views, splats, strict=True)]
            found = [t for t in found if t is not None]
            if found:
                terms["sdf"] = sum(t[0] for t in found) / len(found)
                terms["normal"] = sum(t[1] for t in found) / len(found)
                total = total + self.sdf_weight * terms["sdf"] + self.normal_weight * terms["normal"]
        terms["total"] = total
        return terms
