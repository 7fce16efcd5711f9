"""Local Moran's I of splat attributes (supplementary B.1, Eqs. B.3–B.6) and the Moran loss.

One implementation: :func:`morans_i` is what the evaluation reports (``moran_*`` metrics, centred) and
what :class:`MoranLoss` -- the loss ``SplatLoss`` trains with -- averages over attributes.

For each splat, its neighbourhood X is the splat itself and its N-1 nearest neighbours (N = 5; the
reference's kNN with K = 5 includes the query point). With W_ij = 1/‖loc_i − loc_j‖ for i ≠ j and
W_ii = 0 (Eq. B.5),

    I(X) = N / Σ_ij W_ij · Σ_ij W_ij a_i a_j / Σ_i a_i²                          (Eq. B.4)

the denominator guarded by + 1e-4 (reference ``morans_measure``). I = mean over splats (Eq. B.3) and
over feature dimensions. ``center=True`` subtracts the global mean of each attribute dimension first
(the textbook Moran's I and the reference's evaluation script for scales/rotations/covariances);
the reference's training loss does not centre (``MoranLoss(center=False)``).
``self_weight_quirk=True`` reproduces the reference weights: W_ii = 1e-5 (and pairs closer than 1e-5
also get 1e-5), weights normalised to sum 1.

No pytorch3d: kNN by chunked ``torch.cdist`` (memory bounded by ``max_chunk_elems``).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import torch
from torch import Tensor

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


class MoranLoss:
    """L_Moran = 1 − clamp(mean_attr I_attr, 0, 1) (Eq. B.6), the Moran's I loss of the "3DGS + L_Moran"
    baseline as it trains here (weighted by ``SplatLoss.lambda_moran``, B.1: 0.01).

    The neighbourhoods (kNN of the splat centres) are recomputed every ``every`` calls' iterations or
    when the splat count changes (densification); positions move slowly in between.

    Args:
        attributes: splat attributes to regularise (reference: scales, rotations, opacity, colour).
        k: neighbourhood size N including the splat itself (B.3: 5).
        every: recompute the neighbourhoods every this many iterations.
        center: subtract each attribute's mean as the textbook Moran's I (B.4) and the evaluation do (the
            default, the paper's intent); False = the reference's training loss, which does not centre.
        self_weight_quirk: reference weights (W_ii = 1e-5, normalised) instead of Eq. B.5's W_ii = 0.
    """

    def __init__(self, attributes: Sequence[str] = ("colors", "opacities", "scales", "quats"), k: int = 5,
                 every: int = 100, center: bool = True, self_weight_quirk: bool = False) -> None:
        self.attributes = tuple(attributes)
        self.k = int(k)
        self.every = int(every)
        self.center = bool(center)
        self.self_weight_quirk = bool(self_weight_quirk)
        self._nn: Tensor | None = None
        self._nn_iter = -1

    def neighbours(self, points: Tensor, iteration: int) -> Tensor:
        """kNN indices [N, k] of ``points`` [N, 3], cached for ``every`` iterations at a fixed splat count."""
        stale = self._nn is None or self._nn.shape[0] != points.shape[0] or iteration - self._nn_iter >= self.every
        if stale:
            self._nn = knn_indices(points.detach(), self.k)
            self._nn_iter = iteration
        return self._nn

    def __call__(self, points: Tensor, attributes: Mapping[str, Tensor] | object, iteration: int = 0) -> Tensor:
        """The loss (scalar, unweighted) for splat centres ``points`` [N, 3].

        ``attributes`` maps names to [N] / [N, F] tensors, or is any object with those attributes
        (e.g. ``src.core.Splats``).
        """
        nn_idx = self.neighbours(points, iteration)
        vals = []
        for name in self.attributes:
            value = attributes[name] if isinstance(attributes, Mapping) else getattr(attributes, name)
            vals.append(morans_i(points.detach(), value, k=self.k, center=self.center, neighbours=nn_idx,
                                 self_weight_quirk=self.self_weight_quirk))
        return 1.0 - torch.stack(vals).mean().clamp(0.0, 1.0)
