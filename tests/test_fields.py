"""Field components: positional encoding, MLP heads, tri-plane CNN, backbones, SplatFieldNetwork."""

from __future__ import annotations

import pytest
import torch
import torch.nn.functional as F

from src.fields.backbones import CNNTriplaneBackbone, MLPBackbone, NoBackbone
from src.fields.encoding import PositionalEncoding
from src.fields.flows import DCTFlow, OffsetFlow, ScaledSE3Flow, SE3Flow, se3_exp
from src.fields.mlp import FieldMLP
from src.fields.network import SplatFieldNetwork
from src.fields.resfield import ResFieldLinear
from src.fields.triplane import ResnetBlock2D, SelfAttention2D, TriplaneGenerator


def _n_params(module: torch.nn.Module) -> int:
    return sum(p.numel() for p in module.parameters())


# Small CNN settings for fast tests: 8×4×4 noise -> 8×16×16 planes.
SMALL_CNN = dict(plane_channels=8, noise_channels=4, noise_res=4, channels=8, n_up_blocks=3,
                 resnets_per_block=1, norm_groups=4)
SMALL_HEADS = dict(deform_width=16, color_width=16, scale_width=8, opacity_width=8, rotation_width=8,
                   flow_width=16)


# --------------------------------------------------------------------------------------------------
# Positional encoding
# --------------------------------------------------------------------------------------------------


def test_positional_encoding_layout_and_values():
    pe = PositionalEncoding(4)
    x = torch.tensor([[0.3, -0.7, 0.1]])
    y = pe(x)
    assert pe.out_dim(3) == 3 + 2 * 3 * 4 == y.shape[-1]
    assert torch.equal(y[:, :3], x)
    # level l: sin(2^l x) then cos(2^l x), no factor pi
    for level in range(4):
        off = 3 + 6 * level
        assert torch.allclose(y[:, off:off + 3], torch.sin(2.0**level * x))
        assert torch.allclose(y[:, off + 3:off + 6], torch.cos(2.0**level * x))
    assert torch.equal(PositionalEncoding(0)(x), x) and PositionalEncoding(0).out_dim(3) == 3
    assert PositionalEncoding(2, include_input=False).out_dim(1) == 4


# --------------------------------------------------------------------------------------------------
# FieldMLP
# --------------------------------------------------------------------------------------------------


def test_field_mlp_layers_skips_and_resfield_layers():
    mlp = FieldMLP(10, 3, n_layers=8, width=32, skips=(4,), rank=2, n_frames=5, last_layer_extra_dim=6)
    assert len(mlp.layers) == 8
    fan_in = [layer.in_features for layer in mlp.layers]
    assert fan_in == [10, 32, 32, 32, 32 + 10, 32, 32, 32 + 6]
    # reference default: hidden layers after the first (linear indices 2..6) are ResFields
    assert [layer.is_time_dependent for layer in mlp.layers] == [False, False] + [True] * 5 + [False]
    x, extra = torch.randn(7, 10), torch.randn(7, 6)
    assert mlp(x, frame_id=1, extra=extra).shape == (7, 3)
    assert not torch.allclose(mlp(x, frame_id=1, extra=extra), mlp(x, frame_id=4, extra=extra))
    with pytest.raises(ValueError):
        mlp(x, frame_id=1)  # extra input missing
    static = FieldMLP(10, 3, n_layers=5, width=16, rank=2, n_frames=0)
    assert not any(isinstance(m, ResFieldLinear) and m.is_time_dependent for m in static.layers)
    custom = FieldMLP(10, 3, n_layers=5, width=16, rank=2, n_frames=4, resfield_layers=(0, 4))
    assert [layer.is_time_dependent for layer in custom.layers] == [True, False, False, False, True]


def test_field_mlp_output_act_quirk():
    torch.manual_seed(0)
    plain = FieldMLP(4, 8, n_layers=3, width=16)
    quirk = FieldMLP(4, 8, n_layers=3, width=16, output_act_quirk=True)
    quirk.load_state_dict(plain.state_dict())
    x = torch.randn(200, 4)
    y, yq = plain(x), quirk(x)
    assert (y < 0).any()
    assert torch.allclose(yq, F.leaky_relu(y))  # negative outputs damped ×0.01 as the reference


# --------------------------------------------------------------------------------------------------
# Tri-plane CNN and backbones
# --------------------------------------------------------------------------------------------------


def test_triplane_generator_parameter_counts_and_full_size_output():
    torch.manual_seed(0)
    paper = TriplaneGenerator()  # B.2 defaults
    ref = TriplaneGenerator(ref_extra_mid_resnet=True)
    # paper mid block (Attn -> ResNet): 206 672; reference (ResNet -> Attn -> ResNet): 225 296,
    # equal to the hand count of the reference notes (§1.5, 675 888 for three planes).
    print(f"tri-plane generator params per plane: paper {_n_params(paper)}, reference {_n_params(ref)}")
    assert _n_params(paper) == 206_672
    assert _n_params(ref) == 225_296
    with torch.no_grad():
        plane = paper()
    assert plane.shape == (1, 16, 160, 160) and paper.resolution == 160
    assert torch.isfinite(plane).all() and plane.std() > 0.1


def test_triplane_smaller_config_and_seeded_noise():
    g = TriplaneGenerator(noise_channels=8, noise_res=10, channels=16, out_channels=16, n_up_blocks=4,
                          resnets_per_block=1, norm_groups=8, seed=3)
    with torch.no_grad():
        assert g().shape == (1, 16, 80, 80)
    cfg = dict(noise_channels=8, noise_res=10, channels=16, n_up_blocks=4, norm_groups=8)
    same, other = TriplaneGenerator(**cfg, seed=3), TriplaneGenerator(**cfg, seed=4)
    assert torch.equal(g.noise, same.noise) and not torch.equal(g.noise, other.noise)
    assert "noise" in g.state_dict() and all(p is not g.noise for p in g.parameters())


def test_residual_blocks_start_as_identity():
    torch.manual_seed(1)
    x = torch.randn(2, 8, 5, 5)
    assert torch.equal(ResnetBlock2D(8, 4)(x), x)  # second conv zero-initialised
    assert torch.equal(SelfAttention2D(8, 4)(x), x)  # output projection zero-initialised
    gen = TriplaneGenerator(channels=8, norm_groups=4, noise_res=4, n_up_blocks=2)
    blocks = [m for m in gen.modules() if isinstance(m, (ResnetBlock2D, SelfAttention2D))]
    assert len(blocks) == 2 + 2 * 2  # mid attention + ResNet, 2 up blocks of 2 ResNets
    for m in blocks:  # still identity after the generator's kaiming init pass
        assert torch.equal(m(x), x)
    conv = gen.conv_in.weight  # kaiming normal, fan_out (= 8·3·3), relu gain: std sqrt(2/72)
    assert abs(conv.std().item() - (2 / 72) ** 0.5) < 0.05 and torch.equal(gen.conv_in.bias, torch.zeros(8))


def test_cnn_backbone_plane_axes_and_bilinear_lookup():
    bb = CNNTriplaneBackbone(**SMALL_CNN, refine=False)
    R, C = 16, 8
    # plane p, channel 0 = pixel column index (u), channel 1 = pixel row index (v)
    cols = torch.arange(R, dtype=torch.float32).view(1, R).expand(R, R)
    planes = torch.zeros(3, C, R, R)
    planes[:, 0] = cols
    planes[:, 1] = cols.T
    pts = torch.tensor([[-0.5, 0.25, 0.75], [0.1, -0.3, 0.0]])
    feats = bb.sample(planes, pts).view(2, 3, C)  # [N, plane, C]

    def pix(c):  # align_corners=False: pixel coordinate of a normalised coordinate
        return ((c + 1) * R - 1) / 2

    for p, (a, b) in enumerate([(0, 1), (1, 2), (2, 0)]):  # xy, yz, zx
        assert torch.allclose(feats[:, p, 0], pix(pts[:, a]), atol=1e-5)
        assert torch.allclose(feats[:, p, 1], pix(pts[:, b]), atol=1e-5)
    outside = bb.sample(planes, torch.tensor([[3.0, 3.0, 3.0]]))
    assert torch.equal(outside, torch.zeros_like(outside))  # zero padding


def test_cnn_backbone_full_size_shapes_and_prepare_sample():
    torch.manual_seed(0)
    bb = CNNTriplaneBackbone()
    assert bb.feature_dim == 48 and bb.resolution == 160
    print(f"CNN tri-plane backbone params: {_n_params(bb)}")
    assert _n_params(bb) == 3 * 206_672 + 2 * (48 * 48 + 48)
    pts = torch.rand(64, 3) * 2 - 1
    with torch.no_grad():
        state = bb.prepare()
        assert state.shape == (3, 16, 160, 160)
        assert torch.allclose(bb.sample(state, pts), bb(pts))
    assert bb.sample(state, pts).shape == (64, 48)
    for cls in (NoBackbone, MLPBackbone):
        nb = cls()
        assert nb.feature_dim == 0 and nb(pts).shape == (64, 0) and _n_params(nb) == 0


def test_compiled_backbone_matches_eager_and_keeps_the_state_dict():
    kw = dict(plane_channels=4, noise_channels=2, noise_res=4, channels=8, n_up_blocks=1,
              resnets_per_block=1, norm_groups=4)
    eager, compiled = CNNTriplaneBackbone(**kw), CNNTriplaneBackbone(**kw, compile=True)
    compiled.load_state_dict(eager.state_dict())
    assert compiled.state_dict().keys() == eager.state_dict().keys()
    assert_compiled_matches_eager(eager, compiled, torch.rand(32, 3) * 2 - 1)


def assert_compiled_matches_eager(eager: torch.nn.Module, compiled: torch.nn.Module, pts: torch.Tensor) -> None:
    """Same features [N, C] for ``pts`` [N, 3] and the same gradient of every parameter (float32 tolerances)."""
    a, b = eager(pts), compiled(pts)
    torch.testing.assert_close(b, a, rtol=1e-4, atol=1e-5)
    a.square().sum().backward()
    b.square().sum().backward()
    for (name, pa), pb in zip(eager.named_parameters(), compiled.parameters(), strict=True):
        torch.testing.assert_close(pb.grad, pa.grad, rtol=1e-3, atol=1e-5, msg=name)


# --------------------------------------------------------------------------------------------------
# SplatFieldNetwork
# --------------------------------------------------------------------------------------------------


def _inputs(n=64, seed=0):
    g = torch.Generator().manual_seed(seed)
    x = torch.rand(n, 3, generator=g) * 1.6 - 0.8
    base = torch.rand(n, 3, generator=g) * 0.02 + 0.005
    dirs = F.normalize(torch.randn(n, 3, generator=g), dim=-1)
    return x, base, dirs


def test_static_network_parameter_count_outputs_and_init():
    torch.manual_seed(0)
    net = SplatFieldNetwork(backbone=CNNTriplaneBackbone())
    total = _n_params(net)
    heads = {name: _n_params(getattr(net, f"{name}_mlp"))
             for name in ("deform", "color", "scale", "opacity", "rotation")}
    print(f"static SplatFields params: total {total}, backbone {_n_params(net.backbone)}, heads {heads}")
    # B.2 sizes with the paper's mid block: 887 343 (the reference code's sizes give ~0.994 M).
    assert 850_000 <= total <= 1_050_000
    assert heads == {"deform": 118_787, "color": 85_844, "scale": 22_339, "opacity": 22_209,
                     "rotation": 13_444}

    x, base, dirs = _inputs()
    with torch.no_grad():
        out = net(x, base, viewdirs=dirs)
    assert set(out) == {"means", "scales", "quats", "opacities", "colors", "canonical_deformed"}
    assert out["means"].shape == (64, 3) and out["scales"].shape == (64, 3)
    assert out["quats"].shape == (64, 4) and out["opacities"].shape == (64,)
    assert out["colors"].shape == (64, 3)
    # zero-initialised residual heads: start at the canonical points, kNN scales, identity rotations
    assert torch.equal(out["means"], x) and torch.equal(out["canonical_deformed"], x)
    assert torch.allclose(out["scales"], base)
    assert torch.equal(out["quats"], torch.tensor([1.0, 0, 0, 0]).expand(64, 4))
    assert ((out["opacities"] > 0) & (out["opacities"] < 1)).all()
    assert ((out["colors"] > 0) & (out["colors"] < 1)).all()
    with pytest.raises(ValueError):
        net(x, base)  # view-dependent colour needs view directions


def test_shared_state_and_camera_center():
    torch.manual_seed(0)
    net = SplatFieldNetwork(backbone=CNNTriplaneBackbone(**SMALL_CNN), **SMALL_HEADS)
    x, base, _ = _inputs()
    cam = torch.tensor([0.0, 0.0, -3.0])
    with torch.no_grad():
        state = net.prepare()
        a = net(x, base, camera_center=cam, state=state)
        b = net(x, base, viewdirs=F.normalize(x - cam, dim=-1))
    for k in a:
        assert torch.allclose(a[k], b[k], atol=1e-6)


def _all_grads_nonzero(net: SplatFieldNetwork, run) -> list[str]:
    """Names of parameters without a non-zero gradient after one SGD step (zero-init layers open up)."""
    opt = torch.optim.SGD(net.parameters(), lr=0.1)
    for _ in range(2):
        opt.zero_grad()
        run().backward()
        if _ == 0:
            opt.step()
    return [n for n, p in net.named_parameters() if p.grad is None or not p.grad.abs().sum() > 0]


def _weighted_sum(out: dict[str, torch.Tensor], seed: int = 1) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    return sum((v * torch.randn(v.shape, generator=g)).sum() for k, v in out.items()
               if k != "canonical_deformed")


@pytest.mark.parametrize("flow_cls", [OffsetFlow, DCTFlow, SE3Flow, ScaledSE3Flow])
def test_gradients_reach_every_parameter_dynamic(flow_cls):
    torch.manual_seed(0)
    n_frames = 4
    flow = flow_cls(16, n_frames=n_frames) if flow_cls is DCTFlow else flow_cls(16)
    net = SplatFieldNetwork(backbone=CNNTriplaneBackbone(**SMALL_CNN), **SMALL_HEADS, dynamic=True,
                            n_frames=n_frames, rank=2, flow=flow)
    assert any(isinstance(m, ResFieldLinear) and m.is_time_dependent for m in net.modules())
    x, base, dirs = _inputs(48)

    def run():
        return _weighted_sum(net(x, base, frame_id=2, time=2 / 3, viewdirs=dirs))

    assert _all_grads_nonzero(net, run) == []
    out = net(x, base, frame_id=2, time=2 / 3, viewdirs=dirs)
    assert torch.allclose(out["quats"].norm(dim=-1), torch.ones(48), atol=1e-5)
    assert (out["scales"] > 0).all()


def test_gradients_reach_every_parameter_static_reference_quirks():
    torch.manual_seed(0)
    backbone = CNNTriplaneBackbone(**SMALL_CNN, ref_extra_mid_resnet=True)
    net = SplatFieldNetwork(backbone=backbone, **SMALL_HEADS, view_dependent=False, activation="leaky_relu",
                            output_act_quirk=True, scale_mode="additive_quirk", deform_zero_init=False,
                            rotation_zero_init=False)
    x, base, _ = _inputs(48)
    assert _all_grads_nonzero(net, lambda: _weighted_sum(net(x, base))) == []
    with torch.no_grad():
        out = net(x, base)
    assert (out["scales"] > 0).all()
    assert (out["opacities"] >= 0.5 - 1e-6).all()  # reference bias: sigmoid(leaky(z)) >= ~0.5


def test_time_conditioning_and_static_ignores_time():
    torch.manual_seed(0)
    x, base, dirs = _inputs(32)
    static = SplatFieldNetwork(**SMALL_HEADS, rank=4, n_frames=5)  # static: rank and time ignored
    assert not any(isinstance(m, ResFieldLinear) and m.is_time_dependent for m in static.modules())
    with torch.no_grad():
        a = static(x, base, frame_id=0, time=0.0, viewdirs=dirs)
        b = static(x, base, frame_id=3, time=0.75, viewdirs=dirs)
    assert torch.equal(a["colors"], b["colors"])
    dyn = SplatFieldNetwork(**SMALL_HEADS, dynamic=True, n_frames=5, rank=4, deform_zero_init=False)
    with torch.no_grad():
        a = dyn(x, base, frame_id=0, time=0.0, viewdirs=dirs)
        b = dyn(x, base, frame_id=3, time=0.75, viewdirs=dirs)
    assert not torch.allclose(a["colors"], b["colors"])
    assert not torch.allclose(a["means"], b["means"])
    with pytest.raises(ValueError):
        SplatFieldNetwork(**SMALL_HEADS, dynamic=True, n_frames=5, flow=OffsetFlow(32))  # width mismatch


def test_rigid_flow_moves_means_and_rotates_quaternions():
    torch.manual_seed(0)
    net = SplatFieldNetwork(**SMALL_HEADS, dynamic=True, n_frames=3, flow=SE3Flow(16))
    w = torch.tensor([0.0, 0.0, torch.pi / 2])  # 90° about z
    v = torch.tensor([0.1, -0.2, 0.3])
    with torch.no_grad():
        net.flow.branch_w.bias.copy_(w)
        net.flow.branch_v.bias.copy_(v)
    x, base, dirs = _inputs(16)
    with torch.no_grad():
        out = net(x, base, frame_id=1, time=0.5, viewdirs=dirs)
    R, p = se3_exp(w, v)
    assert torch.allclose(out["means"], x @ R.T + p, atol=1e-6)  # deform zero-init: x_can = x
    q_z90 = torch.tensor([2**-0.5, 0.0, 0.0, 2**-0.5])  # canonical quats are the identity at init
    same = torch.minimum((out["quats"] - q_z90).abs().amax(-1), (out["quats"] + q_z90).abs().amax(-1))
    assert same.max() < 1e-6


def test_reference_parity_configuration_matches_reference_head_sizes():
    """The reference code's head sizes (notes §1.5: 121 859 / 121 859 / 26 499 / 25 601 / 17 220)."""
    ref = SplatFieldNetwork(
        backbone=CNNTriplaneBackbone(ref_extra_mid_resnet=True), deform_pe=6, color_layers=8, color_pe=6,
        color_skips=(4,), scale_layers=6, scale_skips=(3,), opacity_layers=6, opacity_pe=3, opacity_skips=(3,),
        rotation_layers=5, rotation_pe=3, view_dependent=False, activation="leaky_relu", output_act_quirk=True,
        scale_mode="additive_quirk",
    )
    sizes = [_n_params(getattr(ref, f"{h}_mlp")) for h in ("deform", "color", "scale", "opacity", "rotation")]
    assert sizes == [121_859, 121_859, 26_499, 25_601, 17_220]
    assert _n_params(ref) == 993_630  # notes: "Total ≈ 0.994 M including the CNN"
