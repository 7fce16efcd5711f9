"""Local Moran's I of splat attributes (supplementary B.1, Eqs. B.3–B.6) and the Moran loss.

For each splat, its neighbourhood X is the splat itself and its N-1 nearest neighbours (N = 5; the
reference's kNN with K = 5 includes the query point). With W_ij = 1/‖loc_i − loc_j‖ for i ≠ j and
W_ii = 0 (Eq. B.5),

    I(X) = N / Σ_ij W_ij · Σ_ij W_ij a_i a_j / Σ_i a_i²                          (Eq. B.4)

the denominator guarded by + 1e-4 (reference ``morans_measure``). I = mean over splats (Eq. B.3) and
over feature dimensions. ``center=True`` subtracts the global mean of each attribute dimension first
(the textbook Moran's I and the reference's evaluation script for scales/rotations/covariances);
the reference's training loss does not centre. ``self_weight_quirk=True`` reproduces the reference
weights: W_ii = 1e-5 (and pairs closer than 1e-5 also get 1e-5), weights normalised to sum 1.

No pytorch3d: kNN by chunked ``torch.cdist`` (memory bounded by ``max_chunk_elems``).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import torch
from torch import Tensor, nn

from src.fields.flows import quat_to_rotmat_wxyz

MORAN_EPS = 1e-4  # denominator guard (reference)
MIN_DIST = 1e-5  # distance floor for W_ij = 1/d (coincident points); the reference's threshold


@torch.no_grad()
def knn_indices(points: Tensor, k: int, max_chunk_elems: int = 2**24) -> Tensor:
    """Indices [N, k] of the k nearest points of each point, the point itself first (column 0).

    Exact brute force with ``torch.cdist`` over row chunks of at most ``max_chunk_elems`` distances
    (e.g. 2^24 floats = 64 MB). Ties are broken arbitrarily; the query point is forced first even if
    other points coincide with it.
    """
    n = points.shape[0]
    if not 1 <= k <= n:
        raise ValueError(f"k must be in [1, {n}], got {k}")
    pts = points.detach()
    rows = max(1, max_chunk_elems // max(n, 1))
    out = torch.empty(n, k, dtype=torch.long, device=points.device)
    for start in range(0, n, rows):
        stop = min(start + rows, n)
        d = torch.cdist(pts[start:stop], pts)  # [rows, N]
        ar = torch.arange(stop - start, device=points.device)
        d[ar, ar + start] = -1.0  # self first
        out[start:stop] = torch.topk(d, k, dim=1, largest=False, sorted=True).indices
    return out


def neighbourhood_weights(points: Tensor, neighbours: Tensor, self_weight_quirk: bool = False) -> Tensor:
    """Spatial weights W [N, k, k] of each neighbourhood (Eq. B.5, or the reference's variant)."""
    loc = points.detach()[neighbours]  # [N, k, 3]
    d = torch.cdist(loc, loc)  # [N, k, k]
    k = neighbours.shape[1]
    eye = torch.eye(k, dtype=torch.bool, device=points.device)
    if self_weight_quirk:
        w = torch.where(d > MIN_DIST, 1.0 / d.clamp_min(MIN_DIST), torch.full_like(d, MIN_DIST))
        return w / w.sum(dim=(1, 2), keepdim=True).clamp_min(1e-5)
    w = 1.0 / d.clamp_min(MIN_DIST)
    return w.masked_fill(eye, 0.0)


def morans_i(
    points: Tensor,
    attr: Tensor,
    k: int = 5,
    center: bool = True,
    neighbours: Tensor | None = None,
    self_weight_quirk: bool = False,
    eps: float = MORAN_EPS,
    reduce: bool = True,
) -> Tensor:
    """Moran's I (Eqs. B.3–B.5) of ``attr`` [N] or [N, F] over kNN neighbourhoods of ``points`` [N, 3].

    Differentiable in ``attr`` (the neighbourhoods and weights are not). Returns a scalar (mean over
    splats and feature dimensions), or [N, F] per-neighbourhood values with ``reduce=False``.

    Args:
        k: neighbourhood size N including the splat itself (B.1: 5).
        center: subtract the global mean of each attribute dimension first.
        neighbours: precomputed ``knn_indices(points, k)`` [N, k] (reuse across attributes).
        self_weight_quirk: reference weights (W_ii = 1e-5, normalised to sum 1) instead of Eq. B.5.
        eps: guard added to Σ_i a_i².
    """
    a = attr.unsqueeze(-1) if attr.ndim == 1 else attr.reshape(attr.shape[0], -1)  # [N, F]
    if center:
        a = a - a.mean(dim=0, keepdim=True)
    if neighbours is None:
        neighbours = knn_indices(points, k)
    kk = neighbours.shape[1]
    w = neighbourhood_weights(points, neighbours, self_weight_quirk).to(a.dtype)  # [N, k, k]
    f = a[neighbours]  # [N, k, F]
    w_sum = w.sum(dim=(1, 2))  # [N]
    cross = torch.einsum("nij,nif,njf->nf", w, f, f)  # [N, F]: Σ_ij W_ij a_i a_j
    denom = (f * f).sum(dim=1) + eps  # [N, F]
    i_local = (kk / w_sum)[:, None] * cross / denom  # [N, F]
    return i_local.mean() if reduce else i_local


def covariance_features(scales: Tensor, quats: Tensor) -> Tensor:
    """Upper triangle [N, 6] (Σ00, Σ01, Σ02, Σ11, Σ12, Σ22) of Σ = R S Sᵀ Rᵀ.

    ``scales`` [N, 3] are standard deviations, ``quats`` [N, 4] (w, x, y, z) (normalised here).
    """
    R = quat_to_rotmat_wxyz(quats)  # [N, 3, 3]
    M = R * scales[:, None, :]  # R S
    cov = M @ M.transpose(1, 2)  # [N, 3, 3]
    iu = torch.triu_indices(3, 3, device=cov.device)
    return cov[:, iu[0], iu[1]]


class MoranLoss(nn.Module):
    """L_Moran = λ · Σ_attr (1 − clamp(I_attr, 0, 1)) (Eq. B.6; summed over attributes as the reference).

    Args:
        weight: λ_Moran (B.1: 0.01).
        attributes: splat attributes to regularise (reference: scales, rotations, opacity, colour).
        k: neighbourhood size (B.1: 5).
        center: centre attributes first (default False: the reference's training loss does not).
        self_weight_quirk: reference weights (default False: the paper's W_ii = 0).
    """

    def __init__(
        self,
        weight: float = 0.01,
        attributes: Sequence[str] = ("colors", "opacities", "scales", "quats"),
        k: int = 5,
        center: bool = False,
        self_weight_quirk: bool = False,
    ) -> None:
        super().__init__()
        self.weight = float(weight)
        self.attributes = tuple(attributes)
        self.k = int(k)
        self.center = bool(center)
        self.self_weight_quirk = bool(self_weight_quirk)

    def forward(self, points: Tensor, attributes: Mapping[str, Tensor] | object) -> Tensor:
        """The weighted loss (scalar) for splat centres ``points`` [N, 3].

        ``attributes`` maps names to [N] / [N, F] tensors, or is any object with those attributes
        (e.g. ``src.core.Splats``).
        """
        neighbours = knn_indices(points, self.k)
        total = points.new_zeros(())
        for name in self.attributes:
            value = attributes[name] if isinstance(attributes, Mapping) else getattr(attributes, name)
            i = morans_i(points, value, k=self.k, center=self.center, neighbours=neighbours,
                         self_weight_quirk=self.self_weight_quirk)
            total = total + (1.0 - i.clamp(0.0, 1.0))
        return self.weight * total
