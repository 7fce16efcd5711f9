"""4D-GS baseline (Yang et al., "Real-time Photorealistic Dynamic Scene Representation and Rendering with
4D Gaussian Splatting", ICLR 2024): native 4D Gaussians sliced at the render time.

Each splat is an anisotropic Gaussian in space-time (x, y, z, t): a 4D mean, four log-scales and a 4D
rotation R = L(q_l) R(q_r), the product of the left- and right-multiplication matrices of two unit
quaternions (the isoclinic decomposition of SO(4), Sec. 3.2). Coordinates are identified with the
quaternion t + x i + y j + z k, so q_r = conj(q_l) is the 3D rotation of q_l acting on (x, y, z) alone.

At time t the 4D Gaussian with covariance Sigma4 = R S S^T R^T is conditioned on t (Sec. 3.2, eq. 6):

    mu_{xyz|t}    = mu_xyz + Sigma_{xyz,t} / Sigma_tt * (t - mu_t)
    Sigma_{xyz|t} = Sigma_xyz - Sigma_{xyz,t} Sigma_{t,xyz} / Sigma_tt
    p(t)          = exp(-(t - mu_t)^2 / (2 Sigma_tt))        (multiplies the opacity)

Splats whose marginal p(t) is below ``marginal_threshold`` are culled at that time (the reference's 0.05).
The rasterizers take a 3D splat as (scales, wxyz quaternion), so the conditional covariance is
decomposed by a symmetric eigendecomposition (:func:`covariance_to_scale_quat`).

Colour is the reference's "4D spherindrical harmonics": spherical harmonics of the view direction
times cos(2 pi n (mu_t - t)) for n = 0 .. n_fourier - 1 (the time period is the normalised sequence, 1).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from src.core.cameras import Camera
from src.core.splats import Splats
from src.models.free import FreeSplatModel, logit
from src.models.knn import knn_base_scale
from src.models.sh import eval_sh, rgb_to_sh0

# -- 4D geometry ---------------------------------------------------------------------------------
# Entry (r, c) of L(q) and R(q) in the (x, y, z, t) order is sign[r, c] * q[_MULT_INDEX[r, c]], q = (w, x, y, z):
# the Hamilton products q p and p q of p = t + x i + y j + z k, written out.
_MULT_INDEX = (0, 3, 2, 1, 3, 0, 1, 2, 2, 1, 0, 3, 1, 2, 3, 0)
_LEFT_SIGN = (1, -1, 1, 1, 1, 1, -1, 1, -1, 1, 1, 1, -1, -1, -1, 1)
_RIGHT_SIGN = (1, 1, -1, 1, -1, 1, 1, 1, 1, -1, 1, 1, -1, -1, -1, 1)


def _mult_matrix(q: Tensor, sign: tuple[int, ...]) -> Tensor:
    index = torch.tensor(_MULT_INDEX, device=q.device)
    return (q[:, index] * q.new_tensor(sign)).view(-1, 4, 4)


def left_matrix(q: Tensor) -> Tensor:
    """[N, 4, 4] matrix of p -> q p (Hamilton product) in the (x, y, z, t) order, t the real part of p.

    Args:
        q: [N, 4] quaternions (w, x, y, z), used as given (normalise first for a rotation).
    """
    return _mult_matrix(q, _LEFT_SIGN)


def right_matrix(q: Tensor) -> Tensor:
    """[N, 4, 4] matrix of p -> p q (Hamilton product) in the (x, y, z, t) order, t the real part of p.

    Args:
        q: [N, 4] quaternions (w, x, y, z), used as given (normalise first for a rotation).
    """
    return _mult_matrix(q, _RIGHT_SIGN)


def isoclinic_rotation(q_left: Tensor, q_right: Tensor) -> Tensor:
    """[N, 4, 4] 4D rotation L(q_l) R(q_r) of two quaternions [N, 4] (wxyz, normalised here)."""
    return left_matrix(F.normalize(q_left, dim=-1)) @ right_matrix(F.normalize(q_right, dim=-1))


def condition_on_time(means4: Tensor, rot4: Tensor, scales4: Tensor, time: float | Tensor
                      ) -> tuple[Tensor, Tensor, Tensor]:
    """Slice 4D Gaussians at ``time``: the conditional 3D Gaussians and the time marginals.

    Written with M = R S (Sigma4 = M M^T) so that the conditional covariance is the Gram matrix
    B B^T of B = M_xyz (I - u u^T), u = m_t / |m_t| (m_t the time row of M): positive semi-definite in
    floating point, with no cancellation between Sigma_xyz and the subtracted term.

    Args:
        means4: [N, 4] (x, y, z, t) means.
        rot4: [N, 4, 4] 4D rotations.
        scales4: [N, 4] linear standard deviations along the splat's axes.
        time: the time to slice at (a float or a [N] tensor).
    Returns:
        (means [N, 3], covariances [N, 3, 3], marginals [N]): mu_{xyz|t}, Sigma_{xyz|t}, exp(-dt^2 / 2 Sigma_tt).
    """
    m = rot4 * scales4[:, None, :]  # [N, 4, 4] = R S
    m_xyz, m_t = m[:, :3, :], m[:, 3, :]  # [N, 3, 4], [N, 4]
    var_t = (m_t * m_t).sum(-1)  # [N] Sigma_tt
    cov_xt = (m_xyz * m_t[:, None, :]).sum(-1)  # [N, 3] Sigma_{xyz,t}
    dt = time - means4[:, 3]  # [N]
    means = means4[:, :3] + cov_xt * (dt / var_t)[:, None]
    u = m_t / var_t.sqrt()[:, None]  # [N, 4] unit
    b = m_xyz - (m_xyz * u[:, None, :]).sum(-1, keepdim=True) * u[:, None, :]  # [N, 3, 4]
    cov = b @ b.transpose(1, 2)  # [N, 3, 3]
    marginal = torch.exp(-0.5 * dt * dt / var_t)
    return means, cov, marginal


# -- covariance -> (scales, quaternion) ------------------------------------------------------------
def quat_multiply(a: Tensor, b: Tensor) -> Tensor:
    """[N, 4] Hamilton product a b of quaternions [N, 4] (w, x, y, z)."""
    aw, ax, ay, az = a.unbind(-1)
    bw, bx, by, bz = b.unbind(-1)
    return torch.stack([aw * bw - ax * bx - ay * by - az * bz,
                        aw * bx + ax * bw + ay * bz - az * by,
                        aw * by - ax * bz + ay * bw + az * bx,
                        aw * bz + ax * by - ay * bx + az * bw], dim=-1)


def rotmat_to_quat(rot: Tensor) -> Tensor:
    """[N, 4] unit quaternions (w, x, y, z), w >= 0, of proper rotation matrices [N, 3, 3].

    Each of the four components gives a candidate (4 q_i q); the one of the largest |q_i| is used.
    """
    m = rot
    m00, m01, m02 = m[:, 0, 0], m[:, 0, 1], m[:, 0, 2]
    m10, m11, m12 = m[:, 1, 0], m[:, 1, 1], m[:, 1, 2]
    m20, m21, m22 = m[:, 2, 0], m[:, 2, 1], m[:, 2, 2]
    cand = torch.stack([
        torch.stack([1 + m00 + m11 + m22, m21 - m12, m02 - m20, m10 - m01], -1),
        torch.stack([m21 - m12, 1 + m00 - m11 - m22, m01 + m10, m02 + m20], -1),
        torch.stack([m02 - m20, m01 + m10, 1 - m00 + m11 - m22, m12 + m21], -1),
        torch.stack([m10 - m01, m02 + m20, m12 + m21, 1 - m00 - m11 + m22], -1),
    ], dim=1)  # [N, 4 candidates, 4]
    best = torch.diagonal(cand, dim1=1, dim2=2).argmax(dim=1)  # [N]
    q = F.normalize(cand[torch.arange(len(m), device=m.device), best], dim=-1)
    return torch.where(q[:, :1] < 0, -q, q)


@torch.no_grad()
def proper_eigh(cov: Tensor) -> tuple[Tensor, Tensor]:
    """Eigenvalues [N, 3] (ascending) and a proper rotation [N, 3, 3] of eigenvectors (columns).

    Computed in float64; each eigenvector's largest-magnitude component is made positive, then the
    first column is negated where the determinant is -1, so the result is a rotation (det +1).
    """
    lam, vec = torch.linalg.eigh(cov.detach().double())
    idx = vec.abs().argmax(dim=1, keepdim=True)  # [N, 1, 3]
    vec = vec * torch.gather(vec, 1, idx).sign()
    flip = torch.linalg.det(vec) < 0
    vec[:, :, 0] = torch.where(flip[:, None], -vec[:, :, 0], vec[:, :, 0])
    return lam, vec


def covariance_to_scale_quat(cov: Tensor, gap_damping: float = 1e-4) -> tuple[Tensor, Tensor]:
    """Scales [N, 3] and wxyz quaternions [N, 4] with R diag(s^2) R^T = ``cov`` [N, 3, 3].

    The values come from :func:`proper_eigh` (no autograd); the gradient is the first-order
    perturbation of the eigendecomposition, written as differentiable algebra on A = V^T cov V:
    d(lambda_i) = dA_ii, and the eigenvector frame turns by the small rotation omega with
    [omega]_x[i, j] = dA_ij / (lambda_j - lambda_i). The division is damped as
    dA_ij g / (g^2 + eps^2), eps = ``gap_damping`` * lambda_max, so near-equal eigenvalues (an isotropic
    splat, whose frame is arbitrary) give a bounded gradient instead of an infinite one; 0 = undamped.
    """
    lam, vec = proper_eigh(cov)
    lam = lam.clamp_min(1e-20).to(cov.dtype)  # [N, 3]
    vec = vec.to(cov.dtype)  # [N, 3, 3]
    a = vec.transpose(1, 2) @ cov @ vec  # [N, 3, 3], equals diag(lam) up to rounding
    a = a - a.detach()  # the perturbation only: zero in value, dA in the gradient
    scales = torch.sqrt(lam + torch.diagonal(a, dim1=1, dim2=2))
    eps2 = (gap_damping * lam[:, 2:3]) ** 2  # [N, 1]

    def turn(i: int, j: int) -> Tensor:
        gap = lam[:, j] - lam[:, i]
        return a[:, i, j] * gap / (gap * gap + eps2[:, 0])

    omega = torch.stack([-turn(1, 2), turn(0, 2), -turn(0, 1)], dim=-1)  # [N, 3]
    delta = torch.cat([torch.ones_like(omega[:, :1]), 0.5 * omega], dim=-1)  # [N, 4] = (1, omega / 2)
    quats = quat_multiply(rotmat_to_quat(vec.detach()), delta)
    return scales, quats


# -- the model ----------------------------------------------------------------------------------
@dataclass
class TimeSlice:
    """The splats kept at one time (marginal above the threshold), before colours.

    Attributes:
        index: [M] long ids of the kept splats.
        means: [M, 3] conditional means; scales: [M, 3]; quats: [M, 4] (wxyz).
        opacities: [M] opacity times the time marginal.
        dt: [M] mu_t - t (detached), the time argument of the colour's Fourier terms.
    """

    index: Tensor
    means: Tensor
    scales: Tensor
    quats: Tensor
    opacities: Tensor
    dt: Tensor


class Gaussian4DModel(FreeSplatModel):
    """Free 4D Gaussians (the 4D-GS recipe): space-time means, 4D scales and rotations, 4D colour.

    Args:
        init: [N, 3] initial spatial centres (normalised world coordinates).
        n_frames: number of frames of the sequence (sets the initial time scale).
        sh_degree: maximum SH degree of the view dependence (raised every ``sh_degree_interval`` its).
        n_fourier: Fourier terms cos(2 pi n (mu_t - t)), n = 0 .. n_fourier - 1, per SH coefficient.
        init_opacity, init_color, init_scale_mult: as 3DGS (opacity 0.1, kNN base scale).
        time_scale_frames: initial temporal standard deviation in frame spacings, 1 / (n_frames - 1).
        time_margin: initial mu_t uniform in [-margin, 1 + margin] (the reference: 0.1).
        marginal_threshold: splats whose time marginal is at most this are culled (the reference: 0.05).
        gap_damping: damping of the eigenvector gradient (:func:`covariance_to_scale_quat`).
        method: label of the method in run records.
        network, flow: unused; the nodes ``field=none`` and ``flow=none`` leave in the config (and
            ``network.dynamic``, the flag that marks the model as one of motion).

    Parameters (``params``): means [N, 3], times [N] (mu_t), scales [N, 4] (log, x y z t), quats and
    quats_r [N, 4] (q_l, q_r, wxyz), opacities [N] (logit), sh0 [N, 1, 3] and sh_rest [N, F K - 1, 3]
    (coefficient f K + k: Fourier term f, SH coefficient k; K = (sh_degree + 1)^2).

    In training a call of :meth:`splats` returns all N splats, so that the densification statistics
    line up with the parameters: a culled splat gets opacity 0 and is moved to the camera centre,
    behind the near plane, where every rasterizer reports radius 0 (it is not "visible", as in the
    reference). In evaluation and :meth:`bake` only the kept splats are returned.
    """

    def __init__(self, init: Tensor, n_frames: int = 1, sh_degree: int = 1, sh_degree_interval: int = 1000,
                 n_fourier: int = 2, init_opacity: float = 0.1, init_color: float = 0.5,
                 init_scale_mult: float = 1.0, time_scale_frames: float = 4.0, time_margin: float = 0.1,
                 marginal_threshold: float = 0.05, gap_damping: float = 1e-4, method: str = "gs4d",
                 network: dict | None = None, flow: dict | None = None) -> None:
        super().__init__()
        n = init.shape[0]
        self.method = method
        self.n_frames = max(1, int(n_frames))
        self.max_sh_degree, self.sh_degree_interval, self.active_sh_degree = int(sh_degree), sh_degree_interval, 0
        self.n_fourier = max(1, int(n_fourier))
        self.marginal_threshold = float(marginal_threshold)
        self.gap_damping = float(gap_damping)
        sigma_t = float(time_scale_frames) / max(self.n_frames - 1, 1)
        dev = init.device  # every parameter on the initial points' device (a CUDA run builds on the GPU)
        spatial = torch.log(knn_base_scale(init) * init_scale_mult)[:, None].repeat(1, 3)  # [N, 3]
        identity = torch.tensor([1.0, 0.0, 0.0, 0.0], device=dev).repeat(n, 1)
        k = self.n_fourier * (self.max_sh_degree + 1) ** 2
        self.params = nn.ParameterDict({
            "means": nn.Parameter(init.float().clone()),
            "times": nn.Parameter(torch.rand(n, device=dev) * (1 + 2 * time_margin) - time_margin),
            "scales": nn.Parameter(torch.cat([spatial.float(), torch.full((n, 1), math.log(sigma_t), device=dev)],
                                             dim=1)),
            "quats": nn.Parameter(identity.clone()),
            "quats_r": nn.Parameter(identity.clone()),
            "opacities": nn.Parameter(torch.full((n,), logit(init_opacity), device=dev)),
            "sh0": nn.Parameter(rgb_to_sh0(torch.full((n, 1, 3), float(init_color), device=dev))),
            "sh_rest": nn.Parameter(torch.zeros(n, k - 1, 3, device=dev)),
        })

    # -- slicing and colour ----------------------------------------------------------------------
    def rotations(self) -> Tensor:
        """[N, 4, 4] the splats' 4D rotations."""
        return isoclinic_rotation(self.params["quats"], self.params["quats_r"])

    def time_slice(self, time: float) -> TimeSlice:
        """The splats whose time marginal at ``time`` exceeds the threshold, sliced at ``time``."""
        p = self.params
        means4 = torch.cat([p["means"], p["times"][:, None]], dim=1)  # [N, 4]
        means, cov, marginal = condition_on_time(means4, self.rotations(), torch.exp(p["scales"]), float(time))
        index = torch.nonzero(marginal.detach() > self.marginal_threshold).squeeze(1)  # [M]
        scales, quats = covariance_to_scale_quat(cov[index], self.gap_damping)
        opacities = torch.sigmoid(p["opacities"][index]) * marginal[index]
        dt = (p["times"][index] - float(time)).detach()
        return TimeSlice(index=index, means=means[index], scales=scales, quats=quats, opacities=opacities, dt=dt)

    def colors(self, sl: TimeSlice, camera: Camera | None) -> Tensor:
        """[M, 3] colours of the sliced splats seen from ``camera`` (the DC band only if None)."""
        n_sh = (self.max_sh_degree + 1) ** 2
        coeffs = torch.cat([self.params["sh0"], self.params["sh_rest"]], dim=1)[sl.index]  # [M, F K, 3]
        coeffs = coeffs.view(-1, self.n_fourier, n_sh, 3)  # [M, F, K, 3]
        degree = 0 if camera is None else self.active_sh_degree
        dirs = None
        if degree > 0:
            dirs = F.normalize(sl.means.detach() - camera.center.to(sl.means), dim=-1)  # [M, 3]
        out = torch.zeros_like(sl.means)
        for f in range(self.n_fourier):
            wave = torch.cos(2 * math.pi * f * sl.dt)[:, None]  # [M, 1]
            out = out + wave * eval_sh(degree, coeffs[:, f], dirs if dirs is not None else coeffs[:, f, 0])
        return torch.clamp_min(out + 0.5, 0.0)

    def _splats(self, sl: TimeSlice, camera: Camera) -> Splats:
        colors = self.colors(sl, camera)
        if not self.training:
            return Splats(means=sl.means, scales=sl.scales, quats=sl.quats, opacities=sl.opacities, colors=colors)
        n = self.n_splats
        ref = self.params["means"]
        parked = camera.center.to(ref).expand(n, 3)  # behind the near plane: radius 0, not visible

        def full(values: Tensor, fill: Tensor) -> Tensor:
            return fill.expand(n, *values.shape[1:]).clone().index_copy(0, sl.index, values)

        return Splats(means=full(sl.means, parked), scales=full(sl.scales, ref.new_ones(1, 1)),
                      quats=full(sl.quats, ref.new_tensor([[1.0, 0.0, 0.0, 0.0]])),
                      opacities=full(sl.opacities, ref.new_zeros(1)), colors=full(colors, ref.new_zeros(1, 3)))

    def splats(self, camera: Camera) -> Splats:
        return self._splats(self.time_slice(camera.time), camera)

    def splats_for(self, cameras: list[Camera]) -> list[Splats]:
        """Splats for several cameras; the slice is computed once per distinct time."""
        cache: dict[float, TimeSlice] = {}
        out = []
        for c in cameras:
            t = float(c.time)
            if t not in cache:
                cache[t] = self.time_slice(t)
            out.append(self._splats(cache[t], c))
        return out

    @torch.no_grad()
    def bake(self, time: float = 0.0, frame_id: int = 0) -> Splats:
        """The splats kept at ``time`` as plain 3D splats with DC colours (Fourier terms at ``time``)."""
        sl = self.time_slice(time)
        return Splats(means=sl.means.clone(), scales=sl.scales.clone(), quats=sl.quats.clone(),
                      opacities=sl.opacities.clone(), colors=self.colors(sl, None))

    # -- densification ---------------------------------------------------------------------------
    def _split_children(self, idx: Tensor, n_split: int, generator: torch.Generator) -> dict[str, Tensor]:
        """``n_split`` children of each splat in ``idx``: 4D means sampled from the parent's 4D Gaussian,
        all four scales divided by 0.8 n_split (the reference's split in space and time)."""
        p = {k: v.data for k, v in self.params.items()}
        s4 = torch.exp(p["scales"][idx]).repeat(n_split, 1)  # [M, 4]
        rot = isoclinic_rotation(p["quats"][idx], p["quats_r"][idx]).repeat(n_split, 1, 1)  # [M, 4, 4]
        offsets = rot @ (torch.randn(s4.shape, generator=generator).to(s4) * s4)[:, :, None]  # [M, 4, 1]
        children = {k: v[idx].repeat(n_split, *([1] * (v.ndim - 1))) for k, v in p.items()}
        children["means"] = children["means"] + offsets[:, :3, 0]
        children["times"] = children["times"] + offsets[:, 3, 0]
        children["scales"] = torch.log(s4 / (0.8 * n_split))
        return children
