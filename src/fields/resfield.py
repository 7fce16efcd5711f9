"""ResField linear layer (Mihajlovic et al., ICLR 2024): a linear layer with time-dependent weights.

W_t = W + Σ_r c[t, r] · M_r, i.e. a shared low-rank basis of weight residuals ``M`` [R, out·in]
mixed by per-frame coefficients ``c`` [T, R] (the "vm" factorisation, ``fuse_mode='add'`` of the
reference ``utils/resfields.py``). The bias is not time-dependent.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import Tensor, nn

RESFIELD_MODES = ("lookup", "interpolation")


class ResFieldLinear(nn.Linear):
    """``nn.Linear`` with low-rank per-frame weight residuals.

    With ``rank == 0`` or ``n_frames == 0`` it is exactly ``nn.Linear`` (same parameters, same
    output). Otherwise it owns two extra parameters, both initialised ``0.01·randn`` (reference
    ``resfields.py``): ``coefficients`` [n_frames, rank] and ``matrices`` [rank, out·in].

    Args:
        in_features, out_features, bias: as ``nn.Linear``.
        rank: number of residual basis matrices R (supplementary B.2: 40 for OwlII, 0 otherwise).
        n_frames: number of coefficient rows T (one per frame of the sequence).
        mode: ``"lookup"`` indexes the coefficient row of an integer ``frame_id``;
            ``"interpolation"`` linearly interpolates the rows at a continuous ``time`` in [0, 1],
            frame k sitting at time k / (n_frames - 1) (times outside [0, 1] are clamped).
        init_std: standard deviation of the factor initialisation (reference: 0.01).
    """

    def __init__(
        self,
        in_features: int,
        out_features: int,
        rank: int = 0,
        n_frames: int = 0,
        mode: str = "lookup",
        bias: bool = True,
        init_std: float = 0.01,
    ) -> None:
        super().__init__(in_features, out_features, bias=bias)
        if mode not in RESFIELD_MODES:
            raise ValueError(f"mode must be one of {RESFIELD_MODES}, got {mode!r}")
        self.rank = int(rank)
        self.n_frames = int(n_frames)
        self.mode = mode
        if self.is_time_dependent:
            self.coefficients = nn.Parameter(torch.randn(self.n_frames, self.rank) * init_std)  # [T, R]
            self.matrices = nn.Parameter(
                torch.randn(self.rank, out_features * in_features) * init_std
            )  # [R, out·in]
        else:
            self.register_parameter("coefficients", None)
            self.register_parameter("matrices", None)

    @property
    def is_time_dependent(self) -> bool:
        """True when the layer has per-frame residuals (rank > 0 and n_frames > 0)."""
        return self.rank > 0 and self.n_frames > 0

    def extra_params(self) -> int:
        """Number of parameters beyond ``nn.Linear``: rank·(out·in) + n_frames·rank."""
        if not self.is_time_dependent:
            return 0
        return self.rank * self.out_features * self.in_features + self.n_frames * self.rank

    def _coefficient_row(self, frame_id: int | Tensor | None, time: float | Tensor | None) -> Tensor:
        """The [R] coefficient vector of the requested frame / time."""
        if self.mode == "lookup":
            if frame_id is None:
                raise ValueError("ResFieldLinear(mode='lookup') needs an integer frame_id")
            fid = int(frame_id)
            if not 0 <= fid < self.n_frames:
                raise IndexError(f"frame_id {fid} out of range [0, {self.n_frames})")
            return self.coefficients[fid]
        # interpolation
        if time is None:
            raise ValueError("ResFieldLinear(mode='interpolation') needs a time in [0, 1]")
        t = float(time)
        if self.n_frames == 1:
            return self.coefficients[0]
        pos = min(max(t, 0.0), 1.0) * (self.n_frames - 1)
        k0 = min(math.floor(pos), self.n_frames - 2)
        alpha = pos - k0
        return (1.0 - alpha) * self.coefficients[k0] + alpha * self.coefficients[k0 + 1]

    def weight_at(self, frame_id: int | Tensor | None = None, time: float | Tensor | None = None) -> Tensor:
        """The [out, in] weight W_t of one frame/time (``weight`` itself if not time-dependent), in the masters'
        dtype also under autocast: the residual is a matrix-vector product that reads the whole basis once, where
        autocast would first copy the basis to bf16 (and its gradient back) on every call."""
        if not self.is_time_dependent:
            return self.weight
        c = self._coefficient_row(frame_id, time)  # [R]
        with torch.autocast(self.matrices.device.type, enabled=False):
            delta = (c @ self.matrices).view(self.out_features, self.in_features)  # [out, in]
        return self.weight + delta

    def forward(
        self, x: Tensor, frame_id: int | Tensor | None = None, time: float | Tensor | None = None
    ) -> Tensor:
        """y = x W_tᵀ + b for x [N, in] -> [N, out]; ``frame_id``/``time`` ignored if rank 0."""
        if not self.is_time_dependent:
            return F.linear(x, self.weight, self.bias)
        return F.linear(x, self.weight_at(frame_id, time), self.bias)

    def extra_repr(self) -> str:
        s = super().extra_repr()
        if self.is_time_dependent:
            s += f", rank={self.rank}, n_frames={self.n_frames}, mode={self.mode}"
        return s
