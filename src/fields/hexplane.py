"""HexPlane spatio-temporal encoder and deformation decoder of 4DGaussians (Wu et al., CVPR 2024, Sec. 3.3).

A point (x, y, z) at time t is encoded by six learnable 2D feature planes, three spatial (xy, xz, yz)
and three space-time (xt, yt, zt): each plane is sampled bilinearly at the point's projection, the six
[C] features are multiplied elementwise (Hadamard product), and the products of the resolution
levels are concatenated (the paper's eq. 5 / the reference ``interpolate_ms_features``). A small MLP
decodes the feature into offsets of a canonical splat's position, log-scale and wxyz quaternion.

Conventions:

* Plane ``P_ab`` of axes (a, b) is a tensor [C, R_b, R_a]: its columns (W) run along axis a and its
  rows (H) along axis b, so the space-time planes have time along H. It is sampled with
  ``grid_sample(align_corners=True, padding_mode="border")`` at (u, v) = (coordinate a, coordinate b)
  in [-1, 1]: u = -1 is the centre of column 0 and u = 1 the centre of column R_a - 1; points
  outside the box take the border value (as the reference).
* Spatial coordinates are divided by ``bounds`` (the half-size of the box the planes cover); time
  t in [0, 1] is mapped to 2t - 1, so the whole time axis of the planes is used.
* Quaternions are (w, x, y, z); scale offsets are in log space.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
import torch.nn.functional as F
from torch import Tensor, nn

#: The six planes as (axis along W, axis along H); axes 0, 1, 2 = x, y, z and 3 = t.
PLANE_AXES: tuple[tuple[int, int], ...] = ((0, 1), (0, 2), (1, 2), (0, 3), (1, 3), (2, 3))
PLANE_NAMES: tuple[str, ...] = ("xy", "xz", "yz", "xt", "yt", "zt")
SPATIAL_PLANES: tuple[int, ...] = (0, 1, 2)
TIME_PLANES: tuple[int, ...] = (3, 4, 5)


def plane_lookup(plane: Tensor, uv: Tensor) -> Tensor:
    """Bilinear lookup of a feature plane.

    Args:
        plane: [C, H, W] features; column j sits at u = -1 + 2j / (W - 1), row i at v = -1 + 2i / (H - 1).
        uv: [N, 2] sample positions (u along W, v along H) in [-1, 1]; outside, the border value is used.

    Returns:
        [N, C] bilinearly interpolated features (differentiable in ``plane`` and ``uv``).
    """
    grid = uv.to(plane.dtype)[None, :, None, :]  # [1, N, 1, 2]
    out = F.grid_sample(plane[None], grid, mode="bilinear", padding_mode="border", align_corners=True)  # [1, C, N, 1]
    return out[0, :, :, 0].transpose(0, 1)  # [N, C]


def hadamard(features: Sequence[Tensor]) -> Tensor:
    """Elementwise product of equally shaped feature tensors (the planes' [N, C] lookups) -> [N, C]."""
    out = features[0]
    for f in features[1:]:
        out = out * f
    return out


def plane_tv(plane: Tensor) -> Tensor:
    """Total variation of a plane [C, H, W]: 2 (mean (dH)^2 + mean (dW)^2) over first differences.

    The K-Planes / 4DGaussians ``compute_plane_tv`` (squared differences of neighbouring cells, each
    direction averaged over its C (H-1) W or C H (W-1) differences). A scalar tensor.
    """
    dh = plane[:, 1:, :] - plane[:, :-1, :]  # [C, H-1, W]
    dw = plane[:, :, 1:] - plane[:, :, :-1]  # [C, H, W-1]
    return 2.0 * (dh.square().mean() + dw.square().mean())


def time_smoothness(plane: Tensor) -> Tensor:
    """Mean squared second difference along H (time, for a space-time plane [C, T, W]); 0 if T < 3.

    The 4DGaussians / K-Planes ``compute_plane_smoothness``: penalises acceleration of the features
    in time. A scalar tensor.
    """
    if plane.shape[-2] < 3:
        return plane.sum() * 0.0
    d1 = plane[:, 1:, :] - plane[:, :-1, :]  # [C, T-1, W]
    d2 = d1[:, 1:, :] - d1[:, :-1, :]  # [C, T-2, W]
    return d2.square().mean()


def time_l1(plane: Tensor) -> Tensor:
    """Mean |1 - plane| of a space-time plane: pulls it towards 1, the static (time-independent) value."""
    return (1.0 - plane).abs().mean()


class HexPlaneEncoder(nn.Module):
    """Multi-resolution HexPlane: (x, y, z, t) -> [N, feature_dim · len(multires)] features.

    Args:
        resolution: spatial resolution of the first level (4DGaussians: 64).
        multires: spatial resolution multipliers of the levels (4DGaussians D-NeRF: [1, 2] -> 64, 128);
            the temporal resolution is the same at every level (reference).
        time_resolution: cells along time (reference comment: about half the number of frames).
        feature_dim: channels C of every plane (4DGaussians: 32).
        bounds: half-size of the box [-bounds, bounds]^3 the planes cover.
        init_range: spatial planes start uniform in this range; space-time planes start at 1, so the
            encoding is time-independent at first (reference ``init_grid_param``).
    """

    def __init__(self, resolution: int = 64, multires: Sequence[int] = (1, 2), time_resolution: int = 25,
                 feature_dim: int = 32, bounds: float = 1.6, init_range: Sequence[float] = (0.1, 0.5)) -> None:
        super().__init__()
        if resolution < 2 or time_resolution < 2 or feature_dim < 1 or not multires:
            raise ValueError(f"HexPlane needs resolution >= 2, time_resolution >= 2, feature_dim >= 1 and at least "
                             f"one level (got {resolution}, {time_resolution}, {feature_dim}, {list(multires)})")
        if bounds <= 0:
            raise ValueError(f"HexPlane bounds must be > 0, got {bounds}")
        self.resolution, self.multires = int(resolution), tuple(int(m) for m in multires)
        self.time_resolution, self.feature_dim, self.bounds = int(time_resolution), int(feature_dim), float(bounds)
        lo, hi = (float(v) for v in init_range)
        self.levels = nn.ModuleList()
        for m in self.multires:
            size = (self.resolution * m,) * 3 + (self.time_resolution,)  # x, y, z, t
            planes = nn.ParameterList()
            for a, b in PLANE_AXES:
                p = torch.empty(self.feature_dim, size[b], size[a])  # [C, R_b, R_a]
                if b == 3:
                    nn.init.ones_(p)
                else:
                    nn.init.uniform_(p, lo, hi)
                planes.append(nn.Parameter(p))
            self.levels.append(planes)

    @property
    def out_dim(self) -> int:
        """Width of the encoding: feature_dim per level, concatenated."""
        return self.feature_dim * len(self.multires)

    def coordinates(self, xyz: Tensor, time: float | Tensor) -> Tensor:
        """[N, 4] plane coordinates in [-1, 1] (inside the box): (x, y, z) / bounds and 2 t - 1.

        ``time`` is a float (every point at the same time) or an [N] / [N, 1] tensor, in [0, 1].
        """
        t = torch.as_tensor(time, dtype=xyz.dtype, device=xyz.device).reshape(-1, 1).expand(xyz.shape[0], 1)
        return torch.cat([xyz / self.bounds, 2.0 * t - 1.0], dim=-1)

    def forward(self, xyz: Tensor, time: float | Tensor) -> Tensor:
        """xyz [N, 3] world points, time in [0, 1] -> [N, out_dim] (levels concatenated, coarse first)."""
        q = self.coordinates(xyz, time)  # [N, 4]
        feats = []
        for planes in self.levels:
            feats.append(hadamard([plane_lookup(p, q[:, [a, b]]) for (a, b), p in zip(PLANE_AXES, planes,
                                                                                       strict=True)]))
        return torch.cat(feats, dim=-1)

    def regularisers(self, plane_tv_quirk: bool = False) -> dict[str, Tensor]:
        """Unweighted plane regularisers summed over the levels.

        Returns {'plane_tv': TV of the spatial planes, 'time_smooth': second-difference smoothness of
        the space-time planes along time, 'time_l1': mean |1 - P| of the space-time planes}. With
        ``plane_tv_quirk`` the spatial planes get the second difference along their H axis instead of
        the TV, as the reference code's ``_plane_regulation`` does.
        """
        tv = smooth = l1 = None
        for planes in self.levels:
            for i in SPATIAL_PLANES:
                v = time_smoothness(planes[i]) if plane_tv_quirk else plane_tv(planes[i])
                tv = v if tv is None else tv + v
            for i in TIME_PLANES:
                s, a = time_smoothness(planes[i]), time_l1(planes[i])
                smooth = s if smooth is None else smooth + s
                l1 = a if l1 is None else l1 + a
        return {"plane_tv": tv, "time_smooth": smooth, "time_l1": l1}


class DeformationDecoder(nn.Module):
    """A small MLP: HexPlane feature -> (d position, d log-scale, d quaternion wxyz).

    Layout (4DGaussians ``Deformation``): a trunk Linear(in_dim, width) followed by ``depth`` times
    [ReLU, Linear(width, width)], then one head per attribute, each ReLU -> Linear(width, width) ->
    ReLU -> Linear(width, out). Hidden weights are Xavier-uniform (reference ``initialize_weights``).

    Args:
        in_dim: feature width (``HexPlaneEncoder.out_dim``).
        width: hidden width (4DGaussians: 64 for D-NeRF scenes, 128 for real multi-view ones).
        depth: extra trunk layers (4DGaussians D-NeRF: 0).
        zero_init: zero the heads' last layers, so the deformation starts as the identity (default: the
            reference's Xavier init, which trains much faster at the CPU scale; see conf/model/gaussians4d.yaml).
    """

    def __init__(self, in_dim: int, width: int = 64, depth: int = 0, zero_init: bool = False) -> None:
        super().__init__()
        layers: list[nn.Module] = [nn.Linear(in_dim, width)]
        for _ in range(depth):
            layers += [nn.ReLU(), nn.Linear(width, width)]
        self.trunk = nn.Sequential(*layers)

        def head(out: int) -> nn.Sequential:
            return nn.Sequential(nn.ReLU(), nn.Linear(width, width), nn.ReLU(), nn.Linear(width, out))

        self.position, self.scale, self.rotation = head(3), head(3), head(4)
        for m in self.modules():
            if isinstance(m, nn.Linear):
                nn.init.xavier_uniform_(m.weight)
        if zero_init:
            for h in (self.position, self.scale, self.rotation):
                nn.init.zeros_(h[-1].weight)
                nn.init.zeros_(h[-1].bias)

    def forward(self, features: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """features [N, in_dim] -> (d means [N, 3], d log-scales [N, 3], d quaternions [N, 4] (w, x, y, z))."""
        h = self.trunk(features)  # [N, width]
        return self.position(h), self.scale(h), self.rotation(h)
