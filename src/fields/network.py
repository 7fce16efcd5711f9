"""SplatFieldNetwork: the per-splat neural field of SplatFields (supplementary B.2).

Given canonical splat centres x [N, 3] (fixed query points, in [-1, 1]^3 unless contracted) and their
kNN base scales, the network predicts every splat attribute:

    f      = backbone(k(x))                              canonical feature (tri-plane), [N, F]
    x_can  = x + deform_weight · deform(PE(k(x)), f, PE(t))   "deformed" canonical centre (scene units)
    h_in   = [PE(k(x_can)), f, PE(t)]                     input of every other head (the feature is
                                                          the CANONICAL one, as the reference)
    means  = flow(act(trunk(h_in)), x_can, t)            4D only (x_can for static scenes)
    colour = sigmoid(colour(h_in, PE(viewdir) at the last layer)), viewdir from the final means
    scale  = base_scale · exp(scale(h_in))               (scale_mode="exp")
    opac.  = sigmoid(opacity(h_in))
    quat   = q_flow ⊗ normalise(rotation(h_in) + (1, 0, 0, 0))   (q_flow = identity without a
                                                          rotation-carrying flow)

k is the coordinate contraction (``contraction``, ``src.fields.contraction``): the identity by default
(``none``: x itself, the paper's bounded scenes); ``mip360`` maps R^3 into the unit ball for unbounded
scenes. It acts only where positions are encoded (the tri-plane lookup and every head's PE); the
deformation, the flow and the returned means stay in scene units, and gradients reach x through k.

PE(t) (``time_pe_levels``) is appended to every head's input only when ``dynamic``; ResField layers
(``rank`` > 0) are used only when ``dynamic``.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, replace
from types import MappingProxyType
from typing import Any

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from src.fields.backbones import FieldBackbone, NoBackbone
from src.fields.contraction import Contraction
from src.fields.encoded_row import encoded_row
from src.fields.encoding import PositionalEncoding
from src.fields.flows import Flow, quat_multiply_wxyz, rotmat_to_quat_wxyz
from src.fields.fused import HeadInput, head_outputs, head_tail, head_weights, kernel_fits
from src.fields.head_kernel import resolve_head_kernel
from src.fields.mlp import FieldMLP, get_activation
from src.kernels.cpu import resolve_autocast_bf16

SCALE_MODES = ("exp", "additive_quirk")


@dataclass(frozen=True)
class HeadSpec:
    """One MLP head of the field (supplementary B.2).

    Attributes:
        layers: linear layers, the input and output ones included (``FieldMLP``'s ``n_layers``).
        width: neurons of every hidden layer.
        pe: positional-encoding levels of the position the head reads.
        skips: linear indices before which the head's input is re-concatenated (``FieldMLP``).
        zero_init: zero the output layer, so the head's output starts at 0 (the scale head's follows
            ``scale_mode``).
    """

    layers: int
    width: int
    pe: int
    skips: tuple[int, ...] = ()
    zero_init: bool = False


#: The heads and their defaults, B.2's sizes ("the same input as the colour MLP": PE 4 for every head).
HEADS: Mapping[str, HeadSpec] = MappingProxyType({
    "deform": HeadSpec(8, 128, 4, (4,), zero_init=True),  # "Deform MLP ... 8-layer MLP with 128 neurons"
    "color": HeadSpec(6, 128, 4, (3,)),  # "Color Field ... 6-layer MLP with 128 neurons", view direction last
    "scale": HeadSpec(5, 64, 4, (3,)),  # "Scale and Opacity Fields ... 5-layer 64-neuron MLPs"
    "opacity": HeadSpec(5, 64, 4, (3,)),
    "rotation": HeadSpec(4, 64, 4, (), zero_init=True),  # "Rotation Field ... 4-layer MLP", width 64
    "flow": HeadSpec(8, 128, 4, (4,)),  # "Flow Field ... an architecture similar to Deform MLP"
})
#: The flat keywords ``<head>_<field>`` (the config's keys, e.g. ``color_width``) that set one field of a head.
HEAD_KEYWORDS: tuple[str, ...] = (*(f"{h}_{f}" for h in HEADS for f in ("layers", "width", "pe", "skips")),
                                  "deform_zero_init", "rotation_zero_init")


def head_specs(heads: Mapping[str, HeadSpec] | None = None, **fields: Any) -> dict[str, HeadSpec]:
    """Every head's spec: :data:`HEADS`, replaced by the specs in ``heads``, then the flat ``<head>_<field>``
    keywords (:data:`HEAD_KEYWORDS`) applied to them.

    Raises:
        TypeError: a head or keyword that :data:`HEADS` / :data:`HEAD_KEYWORDS` do not hold.
    """
    specs = dict(HEADS)
    for name, spec in (heads or {}).items():
        if name not in specs or not isinstance(spec, HeadSpec):
            raise TypeError(f"heads: expected a HeadSpec for each of {', '.join(HEADS)}, got {name!r}: {spec!r}")
        specs[name] = spec
    for key, value in fields.items():
        if key not in HEAD_KEYWORDS:
            raise TypeError(f"SplatFieldNetwork got an unexpected keyword argument {key!r}")
        name, _, attr = key.partition("_")
        specs[name] = replace(specs[name], **{attr: tuple(value) if attr == "skips" else value})
    return specs


class SplatFieldNetwork(nn.Module):
    """Per-splat field: canonical centres -> activated splat attributes (B.2).

    Head defaults follow supplementary B.2 (:data:`HEADS`; layer counts include input and output
    linears; skip indices are linear indices before which the input is re-concatenated, see
    ``FieldMLP``): deform 8×128 PE 4, colour 6×128 PE 4, scale 5×64, opacity 5×64, rotation 4×64
    (scale/opacity/rotation take "the same input as the colour MLP", so PE 4), flow trunk like deform.
    For parity with the reference code instead use: deform/colour 8×128 PE 6 skip (4,), scale 6×64 PE 4
    skip (3,), opacity 6×64 PE 3 skip (3,), rotation 5×64 PE 3 no skip, flow trunk 8×128 PE 6, time PE
    3, activation leaky_relu, output_act_quirk True, scale_mode additive_quirk, view_dependent False.

    Args:
        backbone: spatial feature backbone (``CNNTriplaneBackbone`` for SplatFields; default
            ``NoBackbone``, the pure-MLP ablation).
        heads: :class:`HeadSpec` by head name (``deform``, ``color``, ``scale``, ``opacity``, ``rotation``,
            ``flow``: the flow trunk); a head left out keeps its :data:`HEADS` default.
        **head_fields: one field of one head as a flat keyword ``<head>_<field>`` (:data:`HEAD_KEYWORDS`,
            the config's keys): ``<head>_layers``, ``<head>_width``, ``<head>_pe``, ``<head>_skips``;
            ``deform_zero_init`` (zero the deform MLP's output layer so x_can = x at init: our choice, the
            reference uses PyTorch's default init, a small random initial offset) and ``rotation_zero_init``
            (every quaternion starts exactly at the identity: our choice; with the default init it starts
            near it). Applied over ``heads``.
        view_dependent: feed PE(view direction) to the colour MLP's last layer (B.2, "akin to NeRF").
            Default True (paper); the reference code's default is False (view-independent colour).
        viewdir_pe: PE levels of the view direction (4).
        n_frames: number of frames (ResField coefficient rows, DCT basis).
        dynamic: 4D model: time PE on every head input, ResField layers, flow.
        time_pe_levels: PE levels of time (B.2: 4; reference code: 3).
        rank: ResField rank of all heads (B.2: 40 for OwlII, 0 for monocular); ignored if static.
        flow: flow head (``src.fields.flows``) applied to x_can, dynamic only; None = no motion
            beyond the time-conditioned deform MLP. Its ``hidden_dim`` must equal the flow trunk's width.
        deform_weight: multiplies the deform residual; 0 disables (and does not build) the deform MLP
            (reference: 0 for DTU front-facing scenes).
        activation: hidden activation of every head (``relu``; the reference uses ``leaky_relu``).
        output_act_quirk: apply LeakyReLU to every head's output layer before its output activation
            (reference behaviour; default False = paper intent).
        scale_mode: ``"exp"``: scale = base_scale · exp(MLP), output layer zero-initialised so the
            scales start at the kNN base (paper intent); ``"additive_quirk"``: scale = MLP + base_scale
            (reference; combined with ``output_act_quirk`` this is leaky(MLP) + base). The additive
            result is passed through |·| (clamped >= 1e-8): the covariance only depends on s², so
            this renders exactly what the reference renders while keeping scales positive.
        fused: evaluate the heads through ``src.fields.fused`` (one wide first-layer product for all
            heads, PE(x_can) encoded once, split skip weights instead of concatenations); False is
            the reference path (same parameters and state dict, equal up to rounding).
        autocast_bf16: run the fused heads' products in bfloat16 (CPU autocast, float32 master weights,
            output linears in float32): ``True``, ``False`` or ``"auto"`` (on where the CPU multiplies
            bfloat16 natively AND a timed matmul shows it faster than float32, ``src.kernels.cpu``, and
            the inputs are float32 on the CPU). Fused path only.
        head_kernel: run each head (input, hidden and output layers) as one AMX-BF16 kernel
            (``src.fields.head_kernel``) when the fused heads run in bf16: ``"auto"`` (where the CPU has AMX),
            ``"on"`` (error without AMX), ``"off"``.
        contraction: coordinate contraction before every encoding of a position (module docstring,
            ``src.fields.contraction``): ``"none"`` (default, the paper: centres assumed in [-1, 1]^3) or
            ``"mip360"`` (Mip-NeRF 360's contraction halved into the unit ball, for unbounded scenes).
        contraction_radius: ``mip360``'s radius r in scene units: identity up to the scale 1 / (2r) within
            it, everything beyond folded into 1/2 <= |k(x)| < 1.
    """

    #: Keywords taken through ``**head_fields`` (``src.utils.instantiate`` checks config keys against them).
    extra_keywords = HEAD_KEYWORDS

    def __init__(
        self,
        backbone: FieldBackbone | None = None,
        heads: Mapping[str, HeadSpec] | None = None,
        *,
        view_dependent: bool = True,
        viewdir_pe: int = 4,
        n_frames: int = 1,
        dynamic: bool = False,
        time_pe_levels: int = 4,  # B.2: time "positionally encoded with 4 levels"
        rank: int = 0,  # B.2: ResFields rank 40 (OwlII), 0 (monocular)
        flow: Flow | None = None,
        deform_weight: float = 1.0,
        activation: str = "relu",
        output_act_quirk: bool = False,
        scale_mode: str = "exp",
        fused: bool = False,
        autocast_bf16: bool | str = False,
        head_kernel: bool | str = False,
        contraction: str = "none",
        contraction_radius: float = 1.0,
        **head_fields: Any,
    ) -> None:
        super().__init__()
        self.contraction = Contraction(contraction, contraction_radius)
        if scale_mode not in SCALE_MODES:
            raise ValueError(f"scale_mode must be one of {SCALE_MODES}, got {scale_mode!r}")
        get_activation(activation)  # validate
        specs = head_specs(heads, **head_fields)
        specs["scale"] = replace(specs["scale"], zero_init=scale_mode == "exp")
        self.backbone = backbone if backbone is not None else NoBackbone()
        self.n_frames = int(n_frames)
        self.dynamic = bool(dynamic)
        self.view_dependent = bool(view_dependent)
        self.deform_weight = float(deform_weight)
        self.scale_mode = scale_mode
        self.output_act_quirk = bool(output_act_quirk)
        self.time_pe = PositionalEncoding(time_pe_levels) if self.dynamic else None
        self._add_heads(specs, viewdir_pe, int(rank) if self.dynamic else 0, activation, flow)
        self._act = get_activation(activation)
        self.fused = bool(fused)
        self.autocast_bf16 = resolve_autocast_bf16(autocast_bf16, "matmul")
        self.head_kernel = self.fused and resolve_head_kernel(head_kernel, self.autocast_bf16)
        # PE(x_can) of the fused path, at the largest level count of the heads that read x_can
        # (a non-persistent buffer only: the state dict is unchanged).
        self._shared_pe = PositionalEncoding(max(pe.n_levels for pe in self._xcan_heads()[1]))
        self.register_buffer("_identity_quat", torch.tensor([1.0, 0.0, 0.0, 0.0]), persistent=False)

    def _add_head(self, name: str, spec: HeadSpec, out_dim: int, shared: dict[str, Any], **kw: Any) -> None:
        """Build head ``name`` as ``<name>_pe`` and ``<name>_mlp``, reading [PE(x), f, PE(t)].

        ``shared``: the ``FieldMLP`` arguments of every head; ``kw``: this head's own, over them.
        """
        pe = PositionalEncoding(spec.pe)
        time_dim = self.time_pe.out_dim(1) if self.time_pe is not None else 0
        in_dim = pe.out_dim(3) + self.backbone.feature_dim + time_dim  # PE(x) ++ feature ++ PE(t)
        args = {"zero_init_output": spec.zero_init, **shared, **kw}
        mlp = FieldMLP(in_dim, out_dim, spec.layers, spec.width, spec.skips, **args)
        setattr(self, f"{name}_pe", pe)
        setattr(self, f"{name}_mlp", mlp)

    def _add_heads(self, specs: dict[str, HeadSpec], viewdir_pe: int, rank: int, activation: str,
                   flow: Flow | None) -> None:
        """The heads in B.2's order (deform, colour, scale, opacity, rotation), the flow and its trunk."""
        shared = dict(activation=activation, rank=rank, n_frames=self.n_frames if rank > 0 else 0,
                      output_act_quirk=self.output_act_quirk)
        if self.deform_weight != 0.0:
            self._add_head("deform", specs["deform"], 3, shared)
        else:
            self.deform_pe, self.deform_mlp = None, None
        self.viewdir_pe = PositionalEncoding(viewdir_pe) if self.view_dependent else None
        vd_dim = self.viewdir_pe.out_dim(3) if self.viewdir_pe is not None else 0
        self._add_head("color", specs["color"], 3, shared, last_layer_extra_dim=vd_dim)
        self._add_head("scale", specs["scale"], 3, shared)
        self._add_head("opacity", specs["opacity"], 1, shared)
        self._add_head("rotation", specs["rotation"], 4, shared)
        self.flow = flow if self.dynamic else None
        width = specs["flow"].width
        if self.flow is not None and self.flow.uses_hidden:
            if self.flow.hidden_dim != width:
                raise ValueError(f"flow.hidden_dim ({self.flow.hidden_dim}) != flow_width ({width})")
            # The trunk's output is a hidden feature: the hidden activation is applied to it in forward.
            self._add_head("flow", specs["flow"], width, shared, output_act_quirk=False)
        else:
            self.flow_pe, self.flow_mlp = None, None

    def prepare(self) -> Any:
        """Per-step backbone state (e.g. the tri-planes), to share across the views of one step."""
        return self.backbone.prepare()

    def forward(
        self,
        canonical: Tensor,
        base_scale: Tensor,
        frame_id: int = 0,
        time: float = 0.0,
        viewdirs: Tensor | None = None,
        state: Any = None,
        camera_center: Tensor | None = None,
    ) -> dict[str, Tensor]:
        """Splat attributes for canonical centres [N, 3] with kNN base scales [N, 3].

        Args:
            canonical: [N, 3] canonical query points (in [-1, 1]^3 unless ``contraction`` maps them there).
            base_scale: [N, 3] (or [N, 1]) positive kNN base scales.
            frame_id, time: the frame to evaluate (used only when ``dynamic``).
            viewdirs: [N, 3] unit directions from the camera centre to the splats; when
                ``view_dependent`` either these or ``camera_center`` are required.
            state: ``prepare()`` output; computed here when None.
            camera_center: [3] camera centre in world coordinates; if ``viewdirs`` is None the view
                directions are normalise(means - camera_center) with the FINAL means (after flow).

        Returns:
            dict with ``means`` [N, 3], ``scales`` [N, 3] (> 0), ``quats`` [N, 4] unit (w, x, y, z),
            ``opacities`` [N] in (0, 1), ``colors`` [N, 3] in (0, 1), ``canonical_deformed`` [N, 3]
            (x_can, before the flow).
        """
        if state is None:
            state = self.prepare()
        if self.fused:
            return self._forward_fused(canonical, base_scale, frame_id, time, viewdirs, state, camera_center)
        n = canonical.shape[0]
        k = self.contraction
        k_canonical = k(canonical)  # [N, 3] the encoded position (``canonical`` itself without contraction)
        feat = self.backbone.sample(state, k_canonical)  # [N, F] canonical feature
        if self.time_pe is not None:
            t = canonical.new_full((n, 1), float(time))
            t_enc = self.time_pe(t)  # [N, 1 + 2·L_t]
        else:
            t_enc = canonical.new_zeros(n, 0)
        fid = int(frame_id) if self.dynamic else None
        tim = float(time) if self.dynamic else None

        def run(pe: PositionalEncoding, mlp: FieldMLP, pts: Tensor, extra: Tensor | None = None) -> Tensor:
            return mlp(torch.cat([pe(pts), feat, t_enc], dim=-1), frame_id=fid, time=tim, extra=extra)

        if self.deform_mlp is not None:
            x_can = canonical + self.deform_weight * run(self.deform_pe, self.deform_mlp, k_canonical)
        else:
            x_can = canonical
        k_x_can = k(x_can)  # [N, 3]

        means, R = x_can, None
        if self.flow is not None:
            h = None
            if self.flow_mlp is not None:
                h = self._act(run(self.flow_pe, self.flow_mlp, k_x_can))  # [N, flow_width]
            means, R = self.flow(h, x_can, frame_id=fid, time=tim)  # [N, 3], [N, 3, 3] | None

        extra = self._viewdir_enc(means, viewdirs, camera_center)
        c = run(self.color_pe, self.color_mlp, k_x_can, extra)  # [N, 3]
        o = run(self.opacity_pe, self.opacity_mlp, k_x_can)  # [N, 1]
        s = run(self.scale_pe, self.scale_mlp, k_x_can)  # [N, 3]
        q = run(self.rotation_pe, self.rotation_mlp, k_x_can)  # [N, 4]
        return self._activate(x_can, means, R, base_scale, c, o, s, q)

    def _xcan_heads(self) -> tuple[list[FieldMLP], list[PositionalEncoding]]:
        """The heads that read [PE(x_can), f, PE(t)] (flow trunk, colour, opacity, scale, rotation)."""
        pairs = [(self.flow_mlp, self.flow_pe), (self.color_mlp, self.color_pe), (self.opacity_mlp, self.opacity_pe),
                 (self.scale_mlp, self.scale_pe), (self.rotation_mlp, self.rotation_pe)]
        pairs = [(m, pe) for m, pe in pairs if m is not None]
        return [m for m, _ in pairs], [pe for _, pe in pairs]

    def _viewdir_enc(self, means: Tensor, viewdirs: Tensor | None, camera_center: Tensor | None) -> Tensor | None:
        """PE of the view directions [N, 3 + 6·L_d] (None when colour is view-independent)."""
        if not self.view_dependent:
            return None
        if viewdirs is None:
            if camera_center is None:
                raise ValueError("view_dependent=True: forward() needs viewdirs or camera_center")
            viewdirs = F.normalize(means - camera_center.to(means).view(1, 3), dim=-1)
        return self.viewdir_pe(viewdirs)

    def _forward_fused(self, canonical: Tensor, base_scale: Tensor, frame_id: int, time: float,
                       viewdirs: Tensor | None, state: Any, camera_center: Tensor | None) -> dict[str, Tensor]:
        """``forward`` through ``src.fields.fused`` (same inputs and outputs as the reference path)."""
        fid = int(frame_id) if self.dynamic else None
        tim = float(time) if self.dynamic else None
        bf16 = self.autocast_bf16 and canonical.device.type == "cpu" and canonical.dtype == torch.float32
        last = torch.float32 if bf16 else None
        kern = bf16 and self.head_kernel and not torch.compiler.is_compiling()
        mlps, pes = self._xcan_heads()
        with torch.autocast("cpu", dtype=torch.bfloat16, enabled=bf16):
            k_canonical = self.contraction(canonical)  # [N, 3] float32: autocast leaves its ops alone
            feat = self.backbone.sample(state, k_canonical)  # [N, F]
            t_enc = self.time_pe(canonical.new_full((1, 1), float(time))) if self.time_pe is not None else None
            fd, td = int(feat.shape[-1]), int(t_enc.shape[-1]) if t_enc is not None else 0
            pe_max = self._shared_pe.out_dim(3)
            weights = [head_weights(m, fid, tim) for m in mlps]
            heads = [HeadInput(m, w, pe.out_dim(3), pe_max, fd, td)
                     for m, w, pe in zip(mlps, weights, pes, strict=True)]
            x_can = canonical
            if self.deform_mlp is not None:
                wd = head_weights(self.deform_mlp, fid, tim)
                dim_d = self.deform_pe.out_dim(3)
                deform = HeadInput(self.deform_mlp, wd, dim_d, dim_d, fd, td)
                (d,) = head_outputs([deform], [wd], encoded_row(feat, k_canonical, self.deform_pe), t_enc,
                                    [kern and kernel_fits(self.deform_mlp)])
                x_can = canonical + self.deform_weight * (d if torch.is_tensor(d) else
                                                          head_tail(self.deform_mlp, wd, d, last_dtype=last))
            # per head its output (kernel) or its input blocks; a view-dependent colour head's last
            # layer reads the view directions, known after the flow: it runs through head_tail
            kernel = [kern and kernel_fits(m) and not (m is self.color_mlp and self.view_dependent) for m in mlps]
            res = head_outputs(heads, weights, encoded_row(feat, self.contraction(x_can), self._shared_pe), t_enc,
                               kernel)
            outs = {}
            for m, w, r in zip(mlps, weights, res, strict=True):
                if m is not self.color_mlp:
                    outs[id(m)] = r if torch.is_tensor(r) else head_tail(m, w, r, last_dtype=last)
        means, R = x_can, None
        if self.flow is not None:
            h = self._act(outs[id(self.flow_mlp)]) if self.flow_mlp is not None else None  # [N, flow_width]
            means, R = self.flow(h, x_can, frame_id=fid, time=tim)
        extra = self._viewdir_enc(means, viewdirs, camera_center)
        ic = mlps.index(self.color_mlp)
        c = res[ic]
        if not torch.is_tensor(c):
            with torch.autocast("cpu", dtype=torch.bfloat16, enabled=bf16):
                c = head_tail(self.color_mlp, weights[ic], c, extra, last_dtype=last)
        return self._activate(x_can, means, R, base_scale, c, outs[id(self.opacity_mlp)], outs[id(self.scale_mlp)],
                              outs[id(self.rotation_mlp)])

    def _activate(self, x_can: Tensor, means: Tensor, R: Tensor | None, base_scale: Tensor, c: Tensor, o: Tensor,
                  s: Tensor, q: Tensor) -> dict[str, Tensor]:
        """Output activations of the raw head outputs c [N, 3], o [N, 1], s [N, 3], q [N, 4]."""
        colors = torch.sigmoid(c)  # [N, 3]
        opacities = torch.sigmoid(o).squeeze(-1)  # [N]
        if self.scale_mode == "exp":
            scales = base_scale * torch.exp(s)
        else:
            scales = (s + base_scale).abs().clamp_min(1e-8)
        quats = F.normalize(q + self._identity_quat.to(x_can.dtype), dim=-1)  # [N, 4] wxyz
        if R is not None:  # the flow's rotation acts after the canonical rotation
            quats = F.normalize(quat_multiply_wxyz(rotmat_to_quat_wxyz(R), quats), dim=-1)
        return {
            "means": means,
            "scales": scales,
            "quats": quats,
            "opacities": opacities,
            "colors": colors,
            "canonical_deformed": x_can,
        }
