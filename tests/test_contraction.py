"""The coordinate contraction of unbounded scenes (src/fields/contraction.py) and its use in SplatFieldNetwork.

``mip360``: contract(x) = c(x / r) / 2 with Mip-NeRF 360's c (identity in the unit ball, (2 - 1/|y|) y/|y|
outside), so R^3 lands in the open unit ball; ``none`` is the identity. The field applies it before the
tri-plane lookup and every head's positional encoding; the end-to-end run is +experiment=splatfields3d_unbounded
on a COLMAP model of data/static/plant (tests/colmap_models.py's builder).
"""

from __future__ import annotations

import json
import math

import pytest
import torch

from src.fields.backbones import CNNTriplaneBackbone
from src.fields.contraction import Contraction, contract_mip360
from src.fields.network import SplatFieldNetwork

pytestmark = pytest.mark.usefixtures("one_thread")

SMALL_CNN = dict(plane_channels=8, noise_channels=4, noise_res=4, channels=8, n_up_blocks=3,
                 resnets_per_block=1, norm_groups=4)  # 8 x 16 x 16 planes
SMALL_HEADS = dict(deform_width=16, color_width=16, scale_width=8, opacity_width=8, rotation_width=8,
                   flow_width=16, deform_zero_init=False, view_dependent=False, autocast_bf16=False, head_kernel=False)
FAR = 50.0 / math.sqrt(3.0) * torch.tensor([[1.0, 1.0, 1.0], [-1.0, 1.0, -1.0]])  # [2, 3] two splats at distance 50


def unit_directions(n: int, seed: int = 0, dtype: torch.dtype = torch.float64) -> torch.Tensor:
    """[n, 3] random unit vectors."""
    d = torch.randn(n, 3, generator=torch.Generator().manual_seed(seed), dtype=dtype)
    return d / d.norm(dim=1, keepdim=True)


def radial(t: torch.Tensor, u: torch.Tensor, radius: float = 1.0) -> torch.Tensor:
    """|contract(t u)| [T, n] for distances t [T] along unit directions u [n, 3]."""
    return contract_mip360(t[:, None, None] * u[None], radius).norm(dim=-1)


# -- the map ---------------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("radius", [1.0, 0.5, 3.0])
def test_identity_up_to_the_scale_inside_the_radius(radius):
    u = unit_directions(64)
    x = u * torch.rand(64, 1, generator=torch.Generator().manual_seed(1), dtype=torch.float64) * radius  # |x| <= r
    x = torch.cat([x, torch.zeros(1, 3, dtype=torch.float64), radius * u[:1]])  # the origin and the sphere itself
    torch.testing.assert_close(contract_mip360(x, radius), x / (2 * radius), rtol=1e-15, atol=0)
    x32 = x.float() / radius
    assert torch.equal(contract_mip360(x32), x32 * 0.5)  # radius 1: exactly halved, bit for bit


def test_none_is_the_same_tensor_and_bad_settings_are_refused():
    x = torch.randn(5, 3)
    assert Contraction("none")(x) is x and Contraction("none").is_identity
    assert not Contraction("mip360").is_identity
    with pytest.raises(ValueError, match="expected one of none, mip360"):
        Contraction("sphere")
    with pytest.raises(ValueError, match="must be > 0"):
        Contraction("mip360", radius=0.0)


@pytest.mark.parametrize("radius", [1.0, 2.0])
def test_continuous_and_c1_at_the_boundary(radius):
    """One-sided difference quotients of the radial profile and of the full map agree at |x| = r."""
    u = unit_directions(16, seed=2)
    h = 1e-6 * radius
    t = torch.tensor([radius - h, radius, radius + h], dtype=torch.float64)
    f = radial(t, u, radius)  # [3, 16]
    assert float((f[2] - f[0]).abs().max()) < 2e-6  # continuous
    left, right = (f[1] - f[0]) / h, (f[2] - f[1]) / h  # [16] each
    torch.testing.assert_close(left, torch.full_like(left, 0.5 / radius), rtol=0, atol=1e-5)
    torch.testing.assert_close(right, left, rtol=0, atol=1e-5)
    # the Jacobian along directions across the sphere, from inside and from outside
    x0 = radius * u  # [16, 3] on the sphere
    v = unit_directions(16, seed=3)
    inside = (contract_mip360(x0, radius) - contract_mip360(x0 - h * v, radius)) / h
    outside = (contract_mip360(x0 + h * v, radius) - contract_mip360(x0, radius)) / h
    torch.testing.assert_close(outside, inside, rtol=0, atol=1e-5)


def test_monotone_in_the_radius_and_far_points_land_inside():
    u = unit_directions(32, seed=4)
    t = torch.logspace(-3, 8, 400, dtype=torch.float64)  # 1e-3 .. 1e8
    f = radial(t, u)  # [400, 32]
    assert bool((f[1:] > f[:-1]).all())  # strictly increasing along every ray
    assert float(f.max()) < 1.0 and float((2 * f).max()) < 2.0  # unit ball after the halving; radius 2 before
    torch.testing.assert_close(f[-1], torch.full_like(f[-1], 1 - 0.5e-8), rtol=0, atol=1e-12)  # 1 - r / (2d)
    far = contract_mip360(torch.tensor([[1e6, -1e6, 3e5], [0.0, 0.0, -1e15]]))  # float32
    assert bool(torch.isfinite(far).all()) and float(far.abs().max()) <= 1.0
    torch.testing.assert_close(far[1], torch.tensor([0.0, 0.0, -1.0]))
    torch.testing.assert_close(contract_mip360(FAR).norm(dim=1), torch.full((2,), 1 - 1 / 100))


def test_gradient_matches_finite_differences_in_float64():
    x = torch.cat([unit_directions(6, seed=5) * torch.tensor([[0.3], [0.9], [1.2], [4.0], [50.0], [1e3]],
                                                            dtype=torch.float64),
                   torch.zeros(1, 3, dtype=torch.float64)]).requires_grad_()
    assert torch.autograd.gradcheck(lambda p: contract_mip360(p, 1.0), (x,), eps=1e-7, atol=1e-8)
    assert torch.autograd.gradcheck(lambda p: contract_mip360(p, 2.5), (x,), eps=1e-7, atol=1e-8)
    contract_mip360(x).sum().backward()
    assert bool(torch.isfinite(x.grad).all())  # also at the origin


# -- in the field ------------------------------------------------------------------------------------------------------
def field(contraction: str | None, seed: int = 0, fused: bool = True) -> SplatFieldNetwork:
    """A small SplatFieldNetwork on a CNN tri-plane, built after ``manual_seed(seed)``; ``None``: the default."""
    torch.manual_seed(seed)
    kw = {} if contraction is None else {"contraction": contraction}
    return SplatFieldNetwork(backbone=CNNTriplaneBackbone(**SMALL_CNN), fused=fused, **SMALL_HEADS, **kw)


def points(n: int = 64, seed: int = 6) -> tuple[torch.Tensor, torch.Tensor]:
    """Centres [n, 3] in [-0.9, 0.9]^3 and base scales [n, 3]."""
    g = torch.Generator().manual_seed(seed)
    return torch.rand(n, 3, generator=g) * 1.8 - 0.9, torch.full((n, 3), 0.02)


def with_features(net: SplatFieldNetwork, x: torch.Tensor, base: torch.Tensor) -> tuple[dict, list, list]:
    """``net``'s outputs at ``x``, the points its backbone was asked to sample and the features it returned."""
    seen, feats = [], []
    sample = net.backbone.sample

    def spy(state, pts):
        seen.append(pts)
        feats.append(sample(state, pts))
        return feats[-1]

    net.backbone.sample = spy
    try:
        out = net(x, base)
    finally:
        del net.backbone.sample
    return out, seen, feats


@pytest.mark.parametrize("fused", [True, False])
def test_none_returns_what_the_field_returned_before(fused):
    """contraction=none (the default) is the field as it was: the same outputs for the same seed, and the
    backbone and the position encodings read the centres themselves."""
    x, base = points()
    with torch.no_grad():
        ref, seen, _ = with_features(field(None, fused=fused), x, base)
        out = field("none", fused=fused)(x, base)
    assert seen[0] is x
    for k in ref:
        assert torch.equal(out[k], ref[k]), k
    net = field("none", fused=False)
    encoded = []
    handles = [pe.register_forward_hook(lambda _m, a, _o: encoded.append(a[0]))
               for pe in (net.deform_pe, net.color_pe, net.opacity_pe)]
    with torch.no_grad():
        out = net(x, base)
    for h in handles:
        h.remove()
    assert encoded[0] is x
    assert torch.equal(encoded[1], out["canonical_deformed"]) and torch.equal(encoded[2], encoded[1])


def test_mip360_gives_far_splats_their_own_features():
    """Two splats at distance 50 in different directions: with none both read the zero padding (one feature,
    that of a zero read); with mip360 each reads the planes at its contracted position."""
    _, base = points(2)
    with torch.no_grad():
        zero_read = field("none").backbone.refine(torch.zeros(1, 3 * SMALL_CNN["plane_channels"]))  # [1, 24]
        _, _, (bounded,) = with_features(field("none"), FAR, base)
        net = field("mip360")
        out, (seen,), (unbounded,) = with_features(net, FAR, base)
    torch.testing.assert_close(bounded, zero_read.expand(2, -1))
    torch.testing.assert_close(seen, contract_mip360(FAR))
    assert bool(torch.isfinite(unbounded).all()) and all(bool(torch.isfinite(v).all()) for v in out.values())
    assert float((unbounded[0] - unbounded[1]).abs().max()) > 1e-3  # the two directions differ
    assert float((unbounded - zero_read).abs().amax(dim=1).min()) > 1e-3  # neither is the border's zero read
    assert float((out["colors"][0] - out["colors"][1]).abs().max()) > 0


@pytest.mark.parametrize("fused", [True, False])
def test_mip360_every_position_encoding_reads_contracted_points(fused, monkeypatch):
    """The deform head encodes k(x), every other head k(x_can), on the fused and the reference path."""
    import src.fields.network as network

    x = torch.cat([points(6)[0], FAR])  # [8, 3]
    base = torch.full((8, 3), 0.02)
    net = field("mip360", fused=fused)
    encoded: list[torch.Tensor] = []
    if fused:  # each group's input row [f, PE(points)]
        row = network.encoded_row
        monkeypatch.setattr(network, "encoded_row", lambda f, p, pe: encoded.append(p) or row(f, p, pe))
    else:  # each head's PE
        for pe in (net.deform_pe, net.color_pe, net.opacity_pe, net.scale_pe, net.rotation_pe):
            pe.register_forward_hook(lambda _m, a, _o: encoded.append(a[0]))
    with torch.no_grad():
        out = net(x, base)
    k = net.contraction
    assert len(encoded) == (2 if fused else 5)
    torch.testing.assert_close(encoded[0], k(x), rtol=0, atol=0)
    for e in encoded[1:]:
        torch.testing.assert_close(e, k(out["canonical_deformed"]), rtol=0, atol=0)


def test_gradients_reach_the_centres_through_the_contraction():
    """mip360: the compiled sampler (centres without gradient) and grid_sample (centres with gradient) read the
    same contracted positions; the centres' gradient is finite, non-zero far out, and matches float64 differences."""
    x, base = points(6)
    x = torch.cat([x, FAR, 3.0 * FAR[:1]])  # [9, 3]: inside, at 50 and at 150
    base = torch.full((9, 3), 0.02)
    net = field("mip360", fused=False)
    state = net.prepare().detach()
    with torch.no_grad():
        kernel = net(x, base, state=state)
    xg = x.clone().requires_grad_()
    out = net(xg, base, state=state)
    for k in kernel:
        torch.testing.assert_close(out[k], kernel[k], rtol=1e-5, atol=1e-5)
    (out["colors"].sum() + out["opacities"].sum() + out["scales"].sum()).backward()
    assert bool(torch.isfinite(xg.grad).all()) and bool((xg.grad[6:].abs().sum(dim=1) > 0).all())

    net64 = field("mip360", fused=False).double()
    state64 = net64.prepare().detach()

    def attrs(p: torch.Tensor) -> torch.Tensor:
        o = net64(p, base.double()[5:], state=state64)
        return torch.cat([o["colors"], o["opacities"][:, None], o["scales"]], dim=1)

    assert torch.autograd.gradcheck(attrs, (x.double()[5:].requires_grad_(),), eps=1e-6, atol=1e-5, rtol=1e-4)


def test_model_warns_about_centres_outside_the_planes_without_a_contraction(caplog):
    from src.models.splatfields import SplatFieldsModel

    x, _ = points(40)
    far = torch.cat([x, 3.0 * FAR])  # [42, 3]: 2 of 42 outside [-1, 1]^3
    with caplog.at_level("WARNING", logger="src.models.splatfields"):
        SplatFieldsModel(x, field("none"))
        SplatFieldsModel(far, field("mip360"))
        assert not caplog.records
        SplatFieldsModel(far, field("none"))
    assert "2 of 42 initial centres lie outside [-1, 1]^3" in caplog.text and "contraction=mip360" in caplog.text


# -- end to end --------------------------------------------------------------------------------------------------------
@pytest.mark.slow
def test_smoke_run_on_a_colmap_model(tmp_path):
    from tests.cli_runs import run_cli
    from tests.colmap_models import write_model

    model = write_model(tmp_path / "capture")
    out = tmp_path / "run"
    proc = run_cli("+experiment=splatfields3d_unbounded", "dataset=colmap", f"dataset.root={model}", "init=sfm",
                   "dataset.n_views=3", "threads=1", f"hydra.run.dir={out}", "+ci=smoke")
    assert proc.returncode == 0, proc.stderr[-3000:]
    rec = json.loads((out / "metrics.json").read_text())
    assert rec["status"] == "ok" and rec["experiment"] == "splatfields3d_unbounded" and rec["views"] == [0, 17, 34]
    assert rec["choices"]["init"] == "sfm" and rec["choices"]["dataset"] == "colmap"
    assert "contraction: mip360" in (out / ".hydra" / "config.yaml").read_text()
    assert math.isfinite(rec["metrics"]["psnr"])
