"""Flow heads for 4D SplatFields: move canonical splat centres to time t (supplementary B.2, Sec. 5.2).

A flow maps a per-splat hidden feature h [N, H] (output of the flow trunk MLP) and the canonical
(deformed) centre x [N, 3] to the centre at time t, x_t [N, 3], and optionally a per-splat rotation
R [N, 3, 3] that the network composes with the splat's canonical rotation. Every flow here is
EXACTLY the identity at initialisation (zero-initialised final layers) and NaN-free in the forward
and backward pass at zero motion.

Also: quaternion helpers in the package convention (w, x, y, z).
"""

from __future__ import annotations

import math
from abc import ABC, abstractmethod

import torch
import torch.nn.functional as F
from torch import Tensor, nn

# --------------------------------------------------------------------------------------------------
# Rotation helpers (quaternions are (w, x, y, z))
# --------------------------------------------------------------------------------------------------


def skew(v: Tensor) -> Tensor:
    """Cross-product matrices [..., 3, 3] of vectors v [..., 3]: skew(a) @ b = a × b."""
    x, y, z = v.unbind(-1)
    o = torch.zeros_like(x)
    return torch.stack([o, -z, y, z, o, -x, -y, x, o], dim=-1).view(*v.shape[:-1], 3, 3)


def quat_multiply_wxyz(q1: Tensor, q2: Tensor) -> Tensor:
    """Hamilton product q1 ⊗ q2 of quaternions [..., 4] (w, x, y, z): the rotation q2 then q1."""
    w1, x1, y1, z1 = q1.unbind(-1)
    w2, x2, y2, z2 = q2.unbind(-1)
    return torch.stack(
        [
            w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2,
            w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
            w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2,
            w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2,
        ],
        dim=-1,
    )


def quat_to_rotmat_wxyz(q: Tensor) -> Tensor:
    """Rotation matrices [..., 3, 3] of (not necessarily unit) quaternions q [..., 4] (w, x, y, z)."""
    q = F.normalize(q, dim=-1)
    w, x, y, z = q.unbind(-1)
    return torch.stack(
        [
            1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
            2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
            2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
        ],
        dim=-1,
    ).view(*q.shape[:-1], 3, 3)


def _sqrt_positive(x: Tensor) -> Tensor:
    """sqrt(max(x, 0)) with a zero (not NaN/inf) gradient where x <= 0."""
    pos = x > 0
    return torch.where(pos, torch.sqrt(torch.where(pos, x, torch.ones_like(x))), torch.zeros_like(x))


def rotmat_to_quat_wxyz(R: Tensor) -> Tensor:
    """Unit quaternions [..., 4] (w, x, y, z) of rotation matrices R [..., 3, 3].

    Computes the four candidate formulas (each divides by one of 4|w|, 4|x|, 4|y|, 4|z|) and keeps the
    best-conditioned one (largest denominator), so it is stable and differentiable everywhere,
    including at R = I. The sign is not canonicalised (q and -q are the same rotation).
    """
    m = R
    m00, m01, m02 = m[..., 0, 0], m[..., 0, 1], m[..., 0, 2]
    m10, m11, m12 = m[..., 1, 0], m[..., 1, 1], m[..., 1, 2]
    m20, m21, m22 = m[..., 2, 0], m[..., 2, 1], m[..., 2, 2]
    # 2|q_i| for i = w, x, y, z: [..., 4]
    q_abs2 = _sqrt_positive(
        torch.stack(
            [
                1.0 + m00 + m11 + m22,
                1.0 + m00 - m11 - m22,
                1.0 - m00 + m11 - m22,
                1.0 - m00 - m11 + m22,
            ],
            dim=-1,
        )
    )
    # Row i: (2 q_i) * q, the quaternion scaled by 2 q_i.  [..., 4, 4]
    cand = torch.stack(
        [
            torch.stack([q_abs2[..., 0] ** 2, m21 - m12, m02 - m20, m10 - m01], dim=-1),
            torch.stack([m21 - m12, q_abs2[..., 1] ** 2, m10 + m01, m02 + m20], dim=-1),
            torch.stack([m02 - m20, m10 + m01, q_abs2[..., 2] ** 2, m21 + m12], dim=-1),
            torch.stack([m10 - m01, m20 + m02, m21 + m12, q_abs2[..., 3] ** 2], dim=-1),
        ],
        dim=-2,
    )
    cand = cand / (2.0 * q_abs2[..., None].clamp_min(0.1))
    best = q_abs2.argmax(dim=-1)  # [...]
    q = torch.gather(cand, -2, best[..., None, None].expand(*best.shape, 1, 4)).squeeze(-2)
    return F.normalize(q, dim=-1)


# Taylor expansions below this rotation angle (radians) for sinθ/θ, (1-cosθ)/θ², (θ-sinθ)/θ³:
# at θ = 0.3 the 4-term series are exact to ~1e-12 and the closed forms lose < 1e-5 (float32).
_SE3_TAYLOR_THRESHOLD = 0.3


def so3_se3_coefficients(
    theta_sq: Tensor, threshold: float = _SE3_TAYLOR_THRESHOLD
) -> tuple[Tensor, Tensor, Tensor]:
    """A = sinθ/θ, B = (1-cosθ)/θ², C = (θ-sinθ)/θ³ from θ² [...], smooth (and finite grad) at θ → 0."""
    small = theta_sq < threshold**2
    t2 = torch.where(small, theta_sq, torch.zeros_like(theta_sq))  # Taylor branch input
    t4, t6 = t2 * t2, t2 * t2 * t2
    a_taylor = 1.0 - t2 / 6.0 + t4 / 120.0 - t6 / 5040.0
    b_taylor = 0.5 - t2 / 24.0 + t4 / 720.0 - t6 / 40320.0
    c_taylor = 1.0 / 6.0 - t2 / 120.0 + t4 / 5040.0 - t6 / 362880.0
    ts2 = torch.where(small, torch.ones_like(theta_sq), theta_sq)  # closed-form branch input (>= thr²)
    th = torch.sqrt(ts2)
    s, c = torch.sin(th), torch.cos(th)
    a_exact = s / th
    b_exact = (1.0 - c) / ts2
    c_exact = (th - s) / (ts2 * th)
    return (
        torch.where(small, a_taylor, a_exact),
        torch.where(small, b_taylor, b_exact),
        torch.where(small, c_taylor, c_exact),
    )


def se3_exp(w: Tensor, v: Tensor) -> tuple[Tensor, Tensor]:
    """Exponential map of screw motions (w, v) [..., 3] each -> (R [..., 3, 3], p [..., 3]).

    With θ = |w|, ŵ = w/θ, v̂ = v/θ (Modern Robotics Eq. 3.88, the reference ``exp_se3``):
    R = I + sinθ [ŵ] + (1-cosθ)[ŵ]² = I + A[w] + B[w]²,
    p = (Iθ + (1-cosθ)[ŵ] + (θ-sinθ)[ŵ]²) v̂ = v + B [w] v + C [w]² v,
    evaluated through ``so3_se3_coefficients`` so there is no division by θ.
    """
    A, B, C = so3_se3_coefficients((w * w).sum(-1))
    W = skew(w)  # [..., 3, 3]
    W2 = W @ W
    eye = torch.eye(3, dtype=w.dtype, device=w.device).expand_as(W)
    R = eye + A[..., None, None] * W + B[..., None, None] * W2
    wv = torch.linalg.cross(w, v, dim=-1)  # [w] v
    wwv = torch.linalg.cross(w, wv, dim=-1)  # [w]² v
    p = v + B[..., None] * wv + C[..., None] * wwv
    return R, p


# --------------------------------------------------------------------------------------------------
# Flows
# --------------------------------------------------------------------------------------------------


class Flow(nn.Module, ABC):
    """Abstract flow: (h [N, H], x [N, 3], frame_id, time) -> (x_t [N, 3], R [N, 3, 3] or None).

    Args:
        hidden_dim: width H of the per-splat hidden feature from the flow trunk (0 if unused).
    """

    #: False for flows that ignore h (the network then builds no flow trunk).
    uses_hidden: bool = True

    def __init__(self, hidden_dim: int = 128) -> None:
        super().__init__()
        self.hidden_dim = int(hidden_dim)

    @abstractmethod
    def forward(
        self, h: Tensor | None, x: Tensor, frame_id: int | None = None, time: float | None = None
    ) -> tuple[Tensor, Tensor | None]:
        """Centres at time t [N, 3] and per-splat rotations [N, 3, 3] (None if the flow has none)."""


def _zero_linear(in_dim: int, out_dim: int) -> nn.Linear:
    lin = nn.Linear(in_dim, out_dim)
    nn.init.zeros_(lin.weight)
    nn.init.zeros_(lin.bias)
    return lin


class StaticFlow(Flow):
    """Identity flow (no parameters): x_t = x."""

    uses_hidden = False

    def __init__(self, hidden_dim: int = 0) -> None:
        super().__init__(hidden_dim)

    def forward(
        self, h: Tensor | None, x: Tensor, frame_id: int | None = None, time: float | None = None
    ) -> tuple[Tensor, None]:
        """x_t = x, no rotation."""
        return x, None


class OffsetFlow(Flow):
    """x_t = x + Linear(h) (the reference's ``offset`` flow, used by run_owlii.sh); zero-init."""

    def __init__(self, hidden_dim: int = 128) -> None:
        super().__init__(hidden_dim)
        self.offset = _zero_linear(hidden_dim, 3)

    def forward(
        self, h: Tensor | None, x: Tensor, frame_id: int | None = None, time: float | None = None
    ) -> tuple[Tensor, None]:
        """x [N, 3] + offset(h) [N, 3]."""
        return x + self.offset(h), None


def dct_basis(n_basis: int, length: int, dtype: torch.dtype = torch.float32) -> Tensor:
    """DCT-II basis without the DC term: B[f, k-1] = sqrt(2/T)·cos(π/(2T)·(2f+1)·k), k = 1..K; [T, K].

    Its columns are orthonormal over f = 0..T-1.
    """
    f = torch.arange(length, dtype=torch.float64)[:, None]
    k = torch.arange(1, n_basis + 1, dtype=torch.float64)[None, :]
    return (math.sqrt(2.0 / length) * torch.cos(math.pi / (2.0 * length) * (2 * f + 1) * k)).to(dtype)


class DCTFlow(Flow):
    """Trajectory in a K-term cosine basis: x_t = x + Σ_k coeff_k(h) · B[f, k] (Sec. 5.2, DynIBaR-style).

    The basis has T = 2·n_frames rows (reference ``init_dct_basis(K, 2·n_frames)``) of which only
    rows 0..n_frames-1 are indexed (as the reference).
    The coefficient layer Linear(H, 3K) is zero-initialised (identity at init).

    Args:
        hidden_dim: trunk width H.
        n_frames: number of frames of the sequence.
        n_basis: K (reference: 4).
        learnable_basis: make the basis a parameter (reference: True).
    """

    def __init__(self, hidden_dim: int = 128, n_frames: int = 100, n_basis: int = 4,
                 learnable_basis: bool = True) -> None:
        super().__init__(hidden_dim)
        if n_frames < 1:
            raise ValueError("DCTFlow needs n_frames >= 1")
        self.n_frames, self.n_basis = int(n_frames), int(n_basis)
        self.coefficients = _zero_linear(hidden_dim, 3 * n_basis)
        basis = dct_basis(n_basis, 2 * n_frames)  # [2·n_frames, K]
        if learnable_basis:
            self.basis = nn.Parameter(basis)
        else:
            self.register_buffer("basis", basis)

    def basis_at(self, frame_id: int | None = None, time: float | None = None) -> Tensor:
        """The basis row [K] of ``frame_id``, or rows linearly interpolated at f = time·(n_frames-1)."""
        if frame_id is not None:
            fid = int(frame_id)
            if not 0 <= fid < self.n_frames:
                raise IndexError(f"frame_id {fid} out of range [0, {self.n_frames})")
            return self.basis[fid]
        if time is None:
            raise ValueError("DCTFlow needs frame_id or time")
        pos = min(max(float(time), 0.0), 1.0) * (self.n_frames - 1)
        k0 = math.floor(pos)
        k1 = min(k0 + 1, self.basis.shape[0] - 1)
        a = pos - k0
        return (1.0 - a) * self.basis[k0] + a * self.basis[k1]

    def forward(
        self, h: Tensor | None, x: Tensor, frame_id: int | None = None, time: float | None = None
    ) -> tuple[Tensor, None]:
        """x + Σ_k coeff[:, :, k]·B[f, k]."""
        coeff = self.coefficients(h).view(-1, 3, self.n_basis)  # [N, 3, K]
        b = self.basis_at(frame_id, time).to(coeff.dtype)  # [K]
        return x + (coeff * b).sum(-1), None


class SE3Flow(Flow):
    """Rigid per-splat screw motion (Nerfies-style, Sec. 5.2): x_t = R x + p with (R, p) = exp(w, v).

    w = Linear_w(h), v = Linear_v(h), both zero-initialised (identity at init). Unlike the reference
    (which divides by θ and adds 1e-5 afterwards, giving NaN at w = 0), the exponential map uses
    Taylor expansions for small θ (``se3_exp``). Returns R so splat rotations follow the motion.
    """

    def __init__(self, hidden_dim: int = 128) -> None:
        super().__init__(hidden_dim)
        self.branch_w = _zero_linear(hidden_dim, 3)
        self.branch_v = _zero_linear(hidden_dim, 3)

    def screw(self, h: Tensor) -> tuple[Tensor, Tensor]:
        """(w [N, 3], v [N, 3]) predicted from h [N, H]."""
        return self.branch_w(h), self.branch_v(h)

    def forward(
        self, h: Tensor | None, x: Tensor, frame_id: int | None = None, time: float | None = None
    ) -> tuple[Tensor, Tensor]:
        """(R x + p [N, 3], R [N, 3, 3])."""
        w, v = self.screw(h)
        R, p = se3_exp(w, v)
        return (R @ x.unsqueeze(-1)).squeeze(-1) + p, R


class ScaledSE3Flow(SE3Flow):
    """SE(3) with a learned per-splat isotropic scale (Sec. 5.2, "scaled SE(3)"): x_t = s·R x + p.

    s = exp(Linear_s(h)) with Linear_s zero-initialised (s = 1 at init). The reference uses
    softplus(·) (0.69 at init) plus an extra offset branch; we keep the exact-identity init instead.
    Returns R (the scale is not applied to the splat scales).
    """

    def __init__(self, hidden_dim: int = 128) -> None:
        super().__init__(hidden_dim)
        self.branch_scale = _zero_linear(hidden_dim, 1)

    def forward(
        self, h: Tensor | None, x: Tensor, frame_id: int | None = None, time: float | None = None
    ) -> tuple[Tensor, Tensor]:
        """(s·R x + p [N, 3], R [N, 3, 3])."""
        w, v = self.screw(h)
        R, p = se3_exp(w, v)
        s = torch.exp(self.branch_scale(h))  # [N, 1]
        return s * (R @ x.unsqueeze(-1)).squeeze(-1) + p, R


FLOWS: dict[str, type[Flow]] = {
    "static": StaticFlow,
    "offset": OffsetFlow,
    "dct": DCTFlow,
    "se3": SE3Flow,
    "scaled_se3": ScaledSE3Flow,
}
