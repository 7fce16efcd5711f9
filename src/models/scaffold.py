"""Scaffold-GS: neural Gaussians decoded from anchors on a voxel grid (Lu et al., CVPR 2024, Sec. 3).

The initial points are snapped to a voxel grid; each occupied voxel centre becomes an *anchor* with a
feature vector f (32 dims), a log-scaling l (6: three for its offsets, three for its splats) and k
learnable offsets O (k = 10). For a camera with centre c, an anchor at x decodes k child splats from
the input [f, d, delta], d = (x - c) / |x - c| the view direction and delta = |x - c| the distance:

    opacity_j = tanh(MLP_alpha)_j               children with opacity <= 0 are not rendered
    colour_j  = sigmoid(MLP_c)_j                RGB, per view (no spherical harmonics)
    scale_j   = exp(l[3:]) * sigmoid(MLP_cov[:3])_j,   quat_j = normalise(MLP_cov[3:7])_j  (w, x, y, z)
    mean_j    = x + O_j * exp(l[:3])

Only anchors in the camera's view frustum are decoded. ``n_splats`` counts anchors (the per-anchor
tensors are what a checkpoint's first dimensions hold); a view renders at most k x that many splats.
Anchors are grown and pruned by :class:`src.strategy.anchor.AnchorStrategy` through the anchor
interface of :class:`src.models.base.SplatModel`.

Conventions: normalised world coordinates, OpenCV cameras, log-scalings, (w, x, y, z) quaternions.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from src.core.cameras import Camera
from src.core.splats import Splats
from src.models.base import AnchorDecode, SplatModel
from src.models.knn import knn_base_scale
from src.optim.adam import SplatOptimizer, replace_param_rows
from src.rasterizer.projection import NEAR_PLANE

#: The per-anchor parameters, in the order of their optimiser groups (the positions are a buffer: Scaffold-GS
#: trains them with learning rate 0).
ANCHOR_PARAMS = ("offsets", "features", "scaling")
#: The decoders, each with its own optimiser group.
DECODERS = ("mlp_opacity", "mlp_cov", "mlp_color")


def voxelize(points: Tensor, size: float) -> Tensor:
    """[A, 3] centres of the voxels of edge ``size`` that hold at least one of ``points`` [N, 3].

    A voxel is indexed by round(p / size) and its centre is that index x size (a grid through the
    origin), sorted by index so the result does not depend on the order of the points.
    """
    cells = torch.unique(torch.round(points.detach() / size).long(), dim=0)  # [A, 3]
    return cells.to(points.dtype) * size


def median_knn_distance(points: Tensor) -> float:
    """Median over ``points`` [N, 3] of the RMS distance to the 3 nearest others (the voxel size
    Scaffold-GS derives from its initial points when none is given)."""
    return float(torch.median(knn_base_scale(points.float())))


def _mlp(n_in: int, hidden: int, n_out: int, head: nn.Module | None) -> nn.Sequential:
    """Linear -> ReLU -> Linear [-> head]: the decoders' shape (one hidden layer, Scaffold-GS Sec. 3.2)."""
    layers: list[nn.Module] = [nn.Linear(n_in, hidden), nn.ReLU(), nn.Linear(hidden, n_out)]
    if head is not None:
        layers.append(head)
    return nn.Sequential(*layers)


class ScaffoldGSModel(SplatModel):
    """Anchors with features, scalings and offsets; MLPs decode k neural Gaussians per anchor and view.

    Args:
        init: [N, 3] initial points (normalised world coordinates), snapped to the voxel grid.
        feature_dim: anchor feature size (paper: 32); also the decoders' hidden width, as in the paper.
        n_offsets: children per anchor k (paper: 10).
        voxel_size: voxel edge in world units; None or <= 0: the median kNN distance of ``init``.
        use_distance: feed the camera distance to the decoders as well as the view direction.
        lambda_volume: weight of the volume regulariser mean_i prod(scale_i) over the rendered
            children (Scaffold-GS: 0.01), a model-side loss term (:meth:`regularisers`).
        method: label in run records.
    """

    def __init__(self, init: Tensor, feature_dim: int = 32, n_offsets: int = 10, voxel_size: float | None = None,
                 use_distance: bool = True, lambda_volume: float = 0.01, method: str = "scaffold_gs",
                 **_: object) -> None:
        super().__init__()
        if n_offsets < 1 or feature_dim < 1:
            raise ValueError(f"model.n_offsets and model.feature_dim must be >= 1, got {n_offsets}, {feature_dim}")
        points = init.detach().float()
        size = float(voxel_size) if voxel_size is not None and voxel_size > 0 else median_knn_distance(points)
        if not (math.isfinite(size) and size > 0):
            raise ValueError(f"model.voxel_size: cannot place anchors on a voxel grid of size {size}")
        self.method = method
        self.k = int(n_offsets)
        self.use_distance = bool(use_distance)
        self.lambda_volume = float(lambda_volume)
        self.register_buffer("voxel", torch.tensor(size))  # [] voxel edge (kept in checkpoints)
        anchors = voxelize(points, size)  # [A, 3]
        log_scale = torch.log(knn_base_scale(anchors))[:, None].repeat(1, 6)  # [A, 6]
        self.register_buffer("anchors", anchors)  # [A, 3]
        self.params = nn.ParameterDict({
            "offsets": nn.Parameter(torch.zeros(anchors.shape[0], self.k, 3)),
            "features": nn.Parameter(torch.zeros(anchors.shape[0], feature_dim)),
            "scaling": nn.Parameter(log_scale),
        })
        n_in = feature_dim + 3 + int(self.use_distance)
        self.mlp_opacity = _mlp(n_in, feature_dim, self.k, nn.Tanh())
        self.mlp_cov = _mlp(n_in, feature_dim, 7 * self.k, None)
        self.mlp_color = _mlp(n_in, feature_dim, 3 * self.k, nn.Sigmoid())
        self.cameras: list[Camera] = []
        self._decodes: list[AnchorDecode] = []
        self._scales: list[Tensor] = []

    # -- SplatModel ------------------------------------------------------------------------
    @property
    def n_splats(self) -> int:
        """Number of anchors (each decodes up to k splats per view)."""
        return self.anchors.shape[0]

    def param_groups(self) -> list[dict]:
        groups = [{"name": k, "params": [self.params[k]]} for k in ANCHOR_PARAMS]
        return groups + [{"name": k, "params": list(getattr(self, k).parameters())} for k in DECODERS]

    def networks(self) -> list[nn.Module]:
        return [getattr(self, k) for k in DECODERS]

    def bind(self, scene) -> None:
        """Keep the training cameras (the views :meth:`bake` decodes each anchor for)."""
        self.cameras = [v.camera for v in scene.train]

    def on_step(self, iteration: int) -> None:
        """A new iteration: forget the previous one's decodes."""
        self._decodes, self._scales = [], []

    def splats(self, camera: Camera) -> Splats:
        """The children of the anchors in ``camera``'s frustum, decoded for its view, opacity > 0."""
        idx = self.visible_anchors(camera)  # [V]
        center = camera.center.to(self.anchors)
        splats, children, opacity = self.decode(idx, center)
        if self.training and torch.is_grad_enabled():
            self._decodes.append(AnchorDecode(anchors=idx, children=children, opacity=opacity.detach()))
            self._scales.append(splats.scales)
        return splats

    def regularisers(self, iteration: int) -> dict[str, Tensor]:
        """Scaffold-GS's volume term lambda x mean_i prod(scale_i) over the children rendered this iteration."""
        scales = [s for s in self._scales if s.shape[0] > 0]
        if self.lambda_volume <= 0 or not scales:
            return {}
        volume = sum(s.prod(dim=-1).mean() for s in scales) / len(scales)
        return {"volume": self.lambda_volume * volume}

    # -- decoding --------------------------------------------------------------------------
    @torch.no_grad()
    def visible_anchors(self, camera: Camera) -> Tensor:
        """[V] ids of the anchors in ``camera``'s view frustum, ascending.

        An anchor is in it when its centre lies beyond the near plane and its footprint, a disc of
        3 x its largest offset scaling projected at its depth, touches the image (Scaffold-GS culls
        the anchors as Gaussians of their offset scaling).
        """
        uv, z = camera.project(self.anchors)  # [A, 2], [A]
        front = z > NEAR_PLANE
        sigma = torch.exp(self.params["scaling"][:, :3]).amax(dim=1)  # [A]
        r = 3.0 * sigma * max(camera.fx, camera.fy) / torch.where(front, z, torch.ones_like(z))  # [A] px
        u, v = uv[:, 0], uv[:, 1]
        inside = (u >= -r) & (u <= camera.width + r) & (v >= -r) & (v <= camera.height + r)
        return torch.nonzero(front & inside).squeeze(1)

    def decode(self, idx: Tensor, center: Tensor) -> tuple[Splats, Tensor, Tensor]:
        """Decode the children of anchors ``idx`` [V] seen from ``center`` ([3], or [V, 3] per anchor).

        Returns (splats of the children with opacity > 0, their flat child ids [M], the opacities [V, k]
        of all children).
        """
        p = self.params
        x, s = self.anchors[idx], torch.exp(p["scaling"][idx])  # [V, 3], [V, 6]
        view = x - center  # [V, 3]
        dist = view.norm(dim=1, keepdim=True).clamp_min(1e-8)  # [V, 1]
        inputs = [p["features"][idx], view / dist] + ([dist] if self.use_distance else [])
        h = torch.cat(inputs, dim=1)  # [V, F + 3 (+ 1)]
        opacity = self.mlp_opacity(h)  # [V, k] in (-1, 1)
        keep = (opacity > 0).reshape(-1)  # [V * k]
        children = (idx[:, None] * self.k + torch.arange(self.k, device=idx.device)).reshape(-1)[keep]  # [M]
        cov = self.mlp_cov(h).reshape(-1, self.k, 7)[keep.reshape(-1, self.k)]  # [M, 7]
        color = self.mlp_color(h).reshape(-1, self.k, 3)[keep.reshape(-1, self.k)]  # [M, 3]
        rows = torch.nonzero(keep).squeeze(1) // self.k  # [M] row in idx of each kept child
        means = x[rows] + p["offsets"][idx].reshape(-1, 3)[keep] * s[rows, :3]  # [M, 3]
        scales = s[rows, 3:] * torch.sigmoid(cov[:, :3])  # [M, 3]
        splats = Splats(means=means, scales=scales, quats=F.normalize(cov[:, 3:], dim=-1),
                        opacities=opacity.reshape(-1)[keep], colors=color)
        return splats, children, opacity

    @torch.no_grad()
    def bake(self, time: float = 0.0, frame_id: int = 0) -> Splats:
        """Every anchor's children decoded for the view from its nearest training camera (an approximation:
        Scaffold-GS's splats depend on the view)."""
        if not self.cameras:
            raise NotImplementedError("ScaffoldGSModel.bake needs the training cameras (bind a scene first)")
        anchors = self.anchors
        centers = torch.stack([c.center.to(anchors) for c in self.cameras])  # [C, 3]
        nearest = torch.cdist(anchors, centers).argmin(dim=1)  # [A]
        idx = torch.arange(anchors.shape[0], device=anchors.device)
        splats, _, _ = self.decode(idx, centers[nearest])
        return splats.detach()

    # -- anchor interface ------------------------------------------------------------------
    @property
    def children_per_anchor(self) -> int:
        return self.k

    def anchor_voxel_size(self) -> float:
        return float(self.voxel)

    def anchor_means(self) -> Tensor:
        return self.anchors

    def child_means(self) -> Tensor:
        p = self.params
        scale = torch.exp(p["scaling"].detach()[:, None, :3])  # [A, 1, 3]
        return self.anchors[:, None] + p["offsets"].detach() * scale  # [A, k, 3]

    def anchor_decodes(self) -> list[AnchorDecode]:
        return list(self._decodes)

    def _edit(self, optimizer: SplatOptimizer | None, keep: Tensor | None, new: dict[str, Tensor] | None) -> None:
        """Keep the anchors in ``keep`` [A] (all if None), then append ``new`` (per-anchor tensors by name)."""
        n_new = 0 if new is None else new["anchors"].shape[0]
        anchors = self.anchors if keep is None else self.anchors[keep]
        self.anchors = anchors if new is None else torch.cat([anchors, new["anchors"].to(anchors)])
        for name in ANCHOR_PARAMS:
            old = self.params[name]
            data = old.data if keep is None else old.data[keep]
            if new is not None:
                data = torch.cat([data, new[name].to(data)])
            self.params[name] = replace_param_rows(optimizer, old, data, keep, n_new)
        self._decodes, self._scales = [], []

    @torch.no_grad()
    def grow_anchors(self, optimizer: SplatOptimizer | None, positions: Tensor, size: float, parents: Tensor,
                     slots: Tensor) -> None:
        """New anchors at ``positions`` [M, 3]: zero offsets, every scaling ``size`` and, per channel, the
        largest feature among the parents mapped to them (Scaffold-GS: scatter-max)."""
        m = positions.shape[0]
        if m == 0:
            return
        feats = self.params["features"].data  # [A, F]
        new_feats = feats.new_zeros(m, feats.shape[1]).scatter_reduce(
            0, slots[:, None].expand(-1, feats.shape[1]), feats[parents], reduce="amax", include_self=False)
        new = {"anchors": positions, "offsets": positions.new_zeros(m, self.k, 3), "features": new_feats,
               "scaling": torch.full((m, 6), math.log(size), dtype=positions.dtype, device=positions.device)}
        self._edit(optimizer, None, new)

    def prune_anchors(self, optimizer: SplatOptimizer | None, mask: Tensor) -> None:
        self._edit(optimizer, ~mask, None)

    def load_state_dict(self, state_dict, strict: bool = True, assign: bool = False):
        """Load a checkpoint whose anchor count may differ from the current one (resizes first)."""
        if "anchors" in state_dict and state_dict["anchors"].shape != self.anchors.shape:
            self.anchors = torch.empty_like(state_dict["anchors"], device=self.anchors.device)
        for name in ANCHOR_PARAMS:
            key = f"params.{name}"
            if key in state_dict and state_dict[key].shape != self.params[name].shape:
                self.params[name] = nn.Parameter(torch.empty_like(state_dict[key], device=self.params[name].device))
        self._decodes, self._scales = [], []
        return super().load_state_dict(state_dict, strict=strict, assign=assign)


__all__ = ["ScaffoldGSModel", "median_knn_distance", "voxelize"]
