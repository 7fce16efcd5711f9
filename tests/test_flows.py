"""Flow heads: identity at init, NaN-free gradients at zero motion, exact SE(3) maths, rigid fitting."""

from __future__ import annotations

import math

import pytest
import torch
import torch.nn.functional as F

from src.fields.flows import (
    DCTFlow,
    OffsetFlow,
    ScaledSE3Flow,
    SE3Flow,
    StaticFlow,
    dct_basis,
    quat_multiply_wxyz,
    quat_to_rotmat_wxyz,
    rotmat_to_quat_wxyz,
    se3_exp,
    skew,
)

H = 16


def _make(name: str):
    return {
        "static": lambda: StaticFlow(),
        "offset": lambda: OffsetFlow(H),
        "dct": lambda: DCTFlow(H, n_frames=10),
        "se3": lambda: SE3Flow(H),
        "scaled_se3": lambda: ScaledSE3Flow(H),
    }[name]()


FLOW_NAMES = ["static", "offset", "dct", "se3", "scaled_se3"]


@pytest.mark.parametrize("name", FLOW_NAMES)
def test_identity_at_init(name):
    torch.manual_seed(0)
    flow = _make(name)
    h, x = torch.randn(50, H), torch.randn(50, 3)
    x_t, R = flow(h, x, frame_id=3, time=3 / 9)
    assert torch.equal(x_t, x)
    if R is not None:
        assert torch.equal(R, torch.eye(3).expand(50, 3, 3))


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("name", ["offset", "dct", "se3", "scaled_se3"])
def test_finite_gradients_at_zero_motion(name, dtype):
    torch.manual_seed(1)
    flow = _make(name).to(dtype)
    h = torch.randn(20, H, dtype=dtype, requires_grad=True)
    x = torch.randn(20, 3, dtype=dtype, requires_grad=True)
    x_t, R = flow(h, x, frame_id=4, time=4 / 9)
    loss = (x_t * torch.randn_like(x_t)).sum()
    if R is not None:
        loss = loss + (R * torch.randn_like(R)).sum()
    loss.backward()
    grads = [p.grad for p in flow.parameters()] + [h.grad, x.grad]
    assert all(g is not None and torch.isfinite(g).all() for g in grads)
    # the last (zero-initialised) layers do receive a gradient at zero motion
    last = {"offset": "offset", "dct": "coefficients", "se3": "branch_w", "scaled_se3": "branch_w"}[name]
    assert getattr(flow, last).weight.grad.abs().sum() > 0


def _twist_matrix(w: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    m = torch.zeros(*w.shape[:-1], 4, 4, dtype=w.dtype)
    m[..., :3, :3] = skew(w)
    m[..., :3, 3] = v
    return m


def test_se3_exp_matches_matrix_exponential_across_the_taylor_threshold():
    torch.manual_seed(2)
    dirs = F.normalize(torch.randn(7, 3, dtype=torch.float64), dim=-1)
    angles = torch.tensor([0.0, 1e-6, 1e-3, 0.29, 0.31, 1.5, 3.0], dtype=torch.float64)
    w = dirs * angles[:, None]
    v = torch.randn(7, 3, dtype=torch.float64)
    R, p = se3_exp(w, v)
    T = torch.linalg.matrix_exp(_twist_matrix(w, v))
    assert torch.allclose(R, T[:, :3, :3], atol=1e-10)
    assert torch.allclose(p, T[:, :3, 3], atol=1e-10)
    # float32 stays accurate near the threshold too
    R32, p32 = se3_exp(w.float(), v.float())
    assert torch.allclose(R32.double(), T[:, :3, :3], atol=1e-5)
    assert torch.allclose(p32.double(), T[:, :3, 3], atol=1e-5)


def test_se3_exp_gradcheck_at_and_near_zero():
    w = torch.tensor([[0.0, 0.0, 0.0], [1e-4, -2e-4, 1e-4], [0.1, 0.2, -0.25], [0.5, -1.0, 0.3]],
                     dtype=torch.float64, requires_grad=True)
    v = torch.randn(4, 3, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda a, b: se3_exp(a, b), (w, v))


def test_quaternion_helpers_roundtrip_and_compose():
    torch.manual_seed(3)
    q = F.normalize(torch.randn(200, 4, dtype=torch.float64), dim=-1)
    # include the identity and 180° rotations (w = 0), the hard cases
    q = torch.cat([q, torch.tensor([[1.0, 0, 0, 0], [0, 1.0, 0, 0], [0, 0, 1.0, 0], [0, 0, 0, 1.0]],
                                   dtype=torch.float64)])
    R = quat_to_rotmat_wxyz(q)
    assert torch.allclose(R @ R.transpose(1, 2), torch.eye(3, dtype=torch.float64).expand_as(R), atol=1e-12)
    q2 = rotmat_to_quat_wxyz(R)
    same = torch.minimum((q2 - q).abs().amax(-1), (q2 + q).abs().amax(-1))  # up to sign
    assert same.max() < 1e-10
    a, b = q[:100], q[100:200]
    assert torch.allclose(quat_to_rotmat_wxyz(quat_multiply_wxyz(a, b)),
                          quat_to_rotmat_wxyz(a) @ quat_to_rotmat_wxyz(b), atol=1e-12)
    # gradient of rotmat_to_quat is finite at the identity
    Ri = torch.eye(3, dtype=torch.float64).expand(2, 3, 3).clone().requires_grad_(True)
    rotmat_to_quat_wxyz(Ri).sum().backward()
    assert torch.isfinite(Ri.grad).all()


def test_dct_basis_orthonormal_and_flow_trajectory():
    B = dct_basis(4, 20, dtype=torch.float64)  # [T, K]
    assert torch.allclose(B.T @ B, torch.eye(4, dtype=torch.float64), atol=1e-12)
    expected = math.sqrt(2 / 20) * math.cos(math.pi / 40 * (2 * 3 + 1) * 2)  # f = 3, k = 2
    assert abs(B[3, 1].item() - expected) < 1e-12

    flow = DCTFlow(H, n_frames=10, n_basis=4, learnable_basis=False)
    assert flow.basis.shape == (20, 4) and not isinstance(flow.basis, torch.nn.Parameter)
    with torch.no_grad():
        flow.coefficients.bias.copy_(torch.arange(12, dtype=torch.float32))  # coeff[:, c, k] = 4c + k
    x = torch.zeros(5, 3)
    h = torch.zeros(5, H)
    coeff = torch.arange(12, dtype=torch.float32).view(3, 4)
    for f in (0, 4, 9):
        x_t, _ = flow(h, x, frame_id=f)
        assert torch.allclose(x_t, (coeff @ flow.basis[f]).expand(5, 3), atol=1e-6)
        x_time, _ = flow(h, x, time=f / 9)  # continuous time hits the same row
        assert torch.allclose(x_time, x_t, atol=1e-6)
    assert isinstance(DCTFlow(H, n_frames=10).basis, torch.nn.Parameter)  # reference: learnable


@pytest.mark.parametrize("cls,s_true", [(SE3Flow, 1.0), (ScaledSE3Flow, 1.3)])
def test_fit_known_rigid_motion(cls, s_true):
    torch.manual_seed(4)
    x = torch.randn(64, 3) * 0.5
    w_true = F.normalize(torch.tensor([0.3, -0.5, 0.8]), dim=0) * 0.7
    v_true = torch.tensor([0.2, -0.1, 0.3])
    R_true, p_true = se3_exp(w_true, v_true)
    target = s_true * x @ R_true.T + p_true
    flow = cls(hidden_dim=1)  # h = 1 for every point: a single free (w, v[, s]) shared by all points
    h = torch.ones(64, 1)
    opt = torch.optim.LBFGS(flow.parameters(), lr=1.0, max_iter=200, line_search_fn="strong_wolfe",
                            tolerance_grad=1e-12, tolerance_change=1e-14)

    def closure():
        opt.zero_grad()
        loss = (flow(h, x)[0] - target).square().mean()
        loss.backward()
        return loss

    for _ in range(3):
        opt.step(closure)
    x_t, R = flow(h, x)
    assert (x_t - target).abs().max() < 1e-4
    assert (R[0] - R_true).abs().max() < 1e-4
