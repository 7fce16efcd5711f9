"""Deformable-3DGS baseline (Yang et al., CVPR 2024): free canonical splats + a deformation MLP of (x, t).

Canonical splats are 3DGS splats (means, log-scales, wxyz quaternions, logit-opacities, SH); an MLP of
PE(x) and PE(t) predicts per-splat offsets of the position, the quaternion and the log-scale at time t.
The deformation is off during a warm-up (the canonical model first fits all frames).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor

from src.core.cameras import Camera
from src.core.splats import Splats
from src.fields.encoding import PositionalEncoding
from src.fields.mlp import FieldMLP
from src.models.gaussians import GaussianSplatModel


class DeformableGaussianModel(GaussianSplatModel):
    """3DGS splats deformed over time by an MLP (the Deformable-3DGS recipe).

    Args:
        init: [N, 3] canonical centres.
        n_frames: number of frames of the scene (scales the time jitter).
        pe_x: positional-encoding levels of the position (Deformable-3DGS: 10).
        pe_t: levels of time (Deformable-3DGS: 6 for synthetic data).
        depth: hidden layers of the trunk (8), width: neurons (256), skip: the layer after which the input is
            re-concatenated (4).
        warm_up: iterations without deformation (Deformable-3DGS: 3000).
        time_noise / time_noise_until: annealed time jitter (smooth training for monocular data), as in
            :class:`src.models.splatfields.SplatFieldsModel`.
        Other arguments as :class:`GaussianSplatModel`.
    """

    def __init__(self, init: Tensor, n_frames: int = 1, pe_x: int = 10, pe_t: int = 6, depth: int = 8,
                 width: int = 256, skip: int = 4, warm_up: int = 3000, time_noise: float = 0.0,
                 time_noise_until: int = 20_000, method: str = "deformable3dgs", **kwargs: object) -> None:
        super().__init__(init, method=method, **kwargs)
        self.pe_x = PositionalEncoding(pe_x)
        self.pe_t = PositionalEncoding(pe_t)
        in_dim = self.pe_x.out_dim(3) + self.pe_t.out_dim(1)
        # depth trunk layers + 1 output layer (xyz 3, rotation 4, log-scale 3), zero-initialised: identity at start
        self.deform = FieldMLP(in_dim, 10, n_layers=depth + 1, width=width, skips=(skip + 1,), activation="relu",
                               zero_init_output=True)
        self.warm_up = warm_up
        self.time_noise = time_noise
        self.time_noise_until = time_noise_until
        self.n_frames = max(1, int(n_frames))
        self.iteration = 0

    def param_groups(self) -> list[dict]:
        return [*super().param_groups(), {"name": "deform", "params": list(self.deform.parameters())}]

    def networks(self) -> list[torch.nn.Module]:
        """The deformation MLP."""
        return [self.deform]

    def on_step(self, iteration: int) -> None:
        super().on_step(iteration)
        self.iteration = iteration

    def _deltas(self, time: float) -> tuple[Tensor, Tensor, Tensor] | None:
        if self.training and self.iteration < self.warm_up:
            return None
        if self.training and self.time_noise > 0 and self.n_frames > 1:
            decay = max(0.0, 1.0 - self.iteration / max(self.time_noise_until, 1))
            time = time + float(torch.randn(())) * self.time_noise * decay / self.n_frames
        x = self.params["means"].detach()  # the deformation sees canonical positions (as Deformable-3DGS)
        t = torch.full((x.shape[0], 1), float(time), dtype=x.dtype, device=x.device)
        d = self.deform(torch.cat([self.pe_x(x), self.pe_t(t)], dim=-1))
        return d[:, :3], d[:, 3:7], d[:, 7:10]

    def _at_time(self, time: float, camera: Camera | None) -> Splats:
        p = self.params
        means, quats, log_s = p["means"], p["quats"], p["scales"]
        d = self._deltas(time)
        if d is not None:
            means = means + d[0]
            quats = F.normalize(quats, dim=-1) + d[1]
            log_s = log_s + d[2]
        return Splats(means=means, scales=torch.exp(log_s), quats=quats, opacities=torch.sigmoid(p["opacities"]),
                      colors=self.colors(camera, means))

    def splats(self, camera: Camera) -> Splats:
        return self._at_time(camera.time, camera)

    @torch.no_grad()
    def bake(self, time: float = 0.0, frame_id: int = 0) -> Splats:
        """The splat set at ``time`` without the network (DC colours)."""
        s = self._at_time(time, None)
        return Splats(means=s.means.clone(), scales=s.scales.clone(), quats=F.normalize(s.quats, dim=-1),
                      opacities=s.opacities.clone(), colors=s.colors.clone())
