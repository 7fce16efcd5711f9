"""4DGaussians baseline (Wu et al., CVPR 2024): canonical 3DGS splats deformed by a HexPlane field.

Canonical splats are 3DGS splats (means, log-scales, wxyz quaternions, logit-opacities, SH). At time t
a :class:`src.fields.hexplane.HexPlaneEncoder` encodes each canonical centre, and a
:class:`src.fields.hexplane.DeformationDecoder` predicts offsets of the centre, the log-scale and the
quaternion (added to the stored one, then normalised); opacity and colour are not deformed (the
reference's ``no_do`` / ``no_dshs``). During the warm-up (the paper's coarse stage) the canonical
splats are trained alone, without deformation and without the plane regularisers.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
import torch.nn.functional as F
from torch import Tensor

from src.core.cameras import Camera
from src.core.splats import Splats
from src.fields.hexplane import DeformationDecoder, HexPlaneEncoder
from src.models.gaussians import GaussianSplatModel


class HexPlaneGaussianModel(GaussianSplatModel):
    """3DGS splats deformed over time by a HexPlane encoder and a small MLP (the 4DGaussians recipe).

    Args:
        init: [N, 3] canonical centres.
        n_frames: number of frames of the scene (sets the temporal resolution when it is None).
        resolution: spatial plane resolution of the first level (4DGaussians: 64).
        multires: spatial resolution multipliers (4DGaussians D-NeRF: [1, 2]).
        time_resolution: temporal plane resolution; None = max(2, round(n_frames / 2)) (reference:
            about half the number of frames).
        feature_dim: channels per plane (4DGaussians: 32).
        bounds: the planes cover [-bounds, bounds]^3 of the (normalised) scene.
        width, depth: decoder hidden width and extra trunk layers (4DGaussians D-NeRF: 64, 0).
        zero_init: zero the decoder's output layers (the deformation starts as the identity); default False:
            Xavier-uniform as the reference.
        warm_up: iterations without deformation (4DGaussians coarse stage: 3000).
        lambda_plane_tv: weight of the spatial planes' TV (4DGaussians ``plane_tv_weight``: 1e-4).
        lambda_time_smooth: weight of the space-time planes' smoothness in time (``time_smoothness_weight``: 1e-2).
        lambda_time_l1: weight of |1 - P| on the space-time planes (``l1_time_planes``: 1e-4).
        plane_tv_quirk: regularise the spatial planes with the second difference along one axis, as the
            reference code does, instead of the paper's TV.
        network, flow: unused; the empty nodes that ``field=none`` and ``flow=none`` leave in the config.
        Other arguments as :class:`GaussianSplatModel`.

    The canonical centres are not detached before the encoder (as the reference): the deformation's
    gradient also moves them.
    """

    def __init__(self, init: Tensor, n_frames: int = 1, resolution: int = 64, multires: Sequence[int] = (1, 2),
                 time_resolution: int | None = None, feature_dim: int = 32, bounds: float = 1.6, width: int = 64,
                 depth: int = 0, zero_init: bool = False, warm_up: int = 3000, lambda_plane_tv: float = 1e-4,
                 lambda_time_smooth: float = 1e-2, lambda_time_l1: float = 1e-4, plane_tv_quirk: bool = False,
                 sh_degree: int = 3, sh_degree_interval: int = 1000, init_opacity: float = 0.1,
                 init_color: float = 0.5, init_scale_mult: float = 1.0, method: str = "gaussians4d",
                 network: dict | None = None, flow: dict | None = None) -> None:
        super().__init__(init, sh_degree=sh_degree, sh_degree_interval=sh_degree_interval, init_opacity=init_opacity,
                         init_color=init_color, init_scale_mult=init_scale_mult, method=method)
        self.n_frames = max(1, int(n_frames))
        if time_resolution is None:
            time_resolution = max(2, round(self.n_frames / 2))
        self.encoder = HexPlaneEncoder(resolution=resolution, multires=multires, time_resolution=int(time_resolution),
                                       feature_dim=feature_dim, bounds=bounds)
        self.decoder = DeformationDecoder(self.encoder.out_dim, width=width, depth=depth, zero_init=zero_init)
        self.warm_up = int(warm_up)
        self.lambdas = {"plane_tv": float(lambda_plane_tv), "time_smooth": float(lambda_time_smooth),
                        "time_l1": float(lambda_time_l1)}
        self.plane_tv_quirk = bool(plane_tv_quirk)
        self.iteration = 0

    def param_groups(self) -> list[dict]:
        return [*super().param_groups(), {"name": "grid", "params": list(self.encoder.parameters())},
                {"name": "deform", "params": list(self.decoder.parameters())}]

    def networks(self) -> list[torch.nn.Module]:
        """The HexPlane encoder and the deformation decoder."""
        return [self.encoder, self.decoder]

    def on_step(self, iteration: int) -> None:
        super().on_step(iteration)
        self.iteration = iteration

    def deforming(self) -> bool:
        """True when the deformation is applied: always in eval mode, after the warm-up in training."""
        return not self.training or self.iteration >= self.warm_up

    def deformed(self, time: float) -> tuple[Tensor, Tensor, Tensor]:
        """(means [N, 3], unit quaternions wxyz [N, 4], log-scales [N, 3]) of the splats at ``time`` in [0, 1]."""
        p = self.params
        means, quats, log_s = p["means"], p["quats"], p["scales"]
        if self.deforming():
            dx, ds, dq = self.decoder(self.encoder(means, float(time)))
            means, log_s, quats = means + dx, log_s + ds, quats + dq
        return means, F.normalize(quats, dim=-1), log_s

    def _splats(self, deformed: tuple[Tensor, Tensor, Tensor], camera: Camera | None) -> Splats:
        means, quats, log_s = deformed
        return Splats(means=means, scales=torch.exp(log_s), quats=quats,
                      opacities=torch.sigmoid(self.params["opacities"]), colors=self.colors(camera, means))

    def splats(self, camera: Camera) -> Splats:
        return self._splats(self.deformed(camera.time), camera)

    def splats_for(self, cameras: list[Camera]) -> list[Splats]:
        """Splats for several cameras; the deformation is evaluated once per distinct time."""
        cache: dict[float, tuple[Tensor, Tensor, Tensor]] = {}
        out = []
        for c in cameras:
            t = float(c.time)
            if t not in cache:
                cache[t] = self.deformed(t)
            out.append(self._splats(cache[t], c))
        return out

    def regularisers(self, iteration: int) -> dict[str, Tensor]:
        """Weighted plane regularisers {'plane_tv', 'time_smooth', 'time_l1'}, once the deformation is on.

        Empty during the warm-up (the reference adds them in its fine stage only) and for zero weights.
        """
        if iteration < self.warm_up or not any(self.lambdas.values()):
            return {}
        raw = self.encoder.regularisers(plane_tv_quirk=self.plane_tv_quirk)
        return {k: self.lambdas[k] * v for k, v in raw.items() if self.lambdas[k] > 0}

    @torch.no_grad()
    def bake(self, time: float = 0.0, frame_id: int = 0) -> Splats:
        """The splat set at ``time`` (deformation applied in eval mode and after the warm-up; DC colours)."""
        s = self._splats(self.deformed(time), None)
        return Splats(means=s.means.clone(), scales=s.scales.clone(), quats=s.quats.clone(),
                      opacities=s.opacities.clone(), colors=s.colors.clone())
