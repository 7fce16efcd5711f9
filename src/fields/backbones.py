"""Spatial feature backbones: point positions [N, 3] -> per-point features [N, F].

A backbone splits its work in two so that a training step rendering several views of the same
time evaluates the expensive part (e.g. the tri-plane CNN) once:

* ``prepare()`` computes the per-step state (the planes) and returns it;
* ``sample(state, points)`` looks features up for the given points;
* ``forward(points) == sample(prepare(), points)``.

Implementations: ``CNNTriplaneBackbone`` (SplatFields, supplementary B.2), ``NoBackbone`` /
``MLPBackbone`` (feature_dim 0, the "MLP" ablation rows). A hash-grid backbone can be added by
subclassing ``FieldBackbone`` (not implemented).
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from typing import Any

import torch
from torch import Tensor, nn

from src.fields.triplane import TriplaneGenerator, split_plane_state, stack_generators, stack_plane_state
from src.fields.triplane_sample import sample_planes
from src.kernels.cpu import resolve_autocast_bf16


class FieldBackbone(nn.Module, ABC):
    """Abstract backbone mapping points [N, 3] (assumed in [-1, 1]^3) to features [N, feature_dim]."""

    @property
    @abstractmethod
    def feature_dim(self) -> int:
        """Width F of the per-point features."""

    @abstractmethod
    def prepare(self) -> Any:
        """Compute the per-step state shared by all ``sample`` calls of one step (may be None)."""

    @abstractmethod
    def sample(self, state: Any, points: Tensor) -> Tensor:
        """Features [N, feature_dim] of ``points`` [N, 3] given ``state = prepare()``."""

    def forward(self, points: Tensor) -> Tensor:
        """Features [N, feature_dim] of ``points`` [N, 3] (prepare + sample)."""
        return self.sample(self.prepare(), points)


class NoBackbone(FieldBackbone):
    """No spatial features (feature_dim 0): the heads see only the positional encoding."""

    @property
    def feature_dim(self) -> int:
        return 0

    def prepare(self) -> None:
        """Nothing to prepare."""
        return None

    def sample(self, state: Any, points: Tensor) -> Tensor:
        """An empty feature [N, 0]."""
        return points.new_zeros(points.shape[0], 0)


class MLPBackbone(NoBackbone):
    """Alias of ``NoBackbone`` for the ablation "MLP" rows (pure MLP fields on PE(x))."""


# Plane order and the point coordinates (grid x, grid y) each plane is sampled at.
PLANE_AXES: tuple[tuple[int, int], ...] = ((0, 1), (1, 2), (2, 0))  # xy, yz, zx (reference order)


class CNNTriplaneBackbone(FieldBackbone):
    """Three CNN-generated axis-aligned feature planes + a 2-layer refinement MLP (B.2).

    Each point is projected onto the xy, yz and zx planes, bilinearly sampled (``grid_sample`` or its
    compiled form, ``src.fields.triplane_sample``; ``align_corners=False``, zero padding, points assumed
    in [-1, 1]^3 as the reference: no normalisation), the three features are concatenated (3·C) and refined by
    Linear(3C, 3C) → ReLU → Linear(3C, 3C). feature_dim = 3·``plane_channels`` (B.2: 48).

    Args:
        plane_channels, noise_channels, noise_res, channels, n_up_blocks, resnets_per_block,
        norm_groups, ref_extra_mid_resnet: passed to each ``TriplaneGenerator`` (B.2 defaults:
            16, 8, 20, 32, 4, 2, 32, False -> three 16×160×160 planes).
        refine: apply the 2-layer refinement MLP (B.2: "a tiny 2-layer MLP with 48 neurons").
        seed: noise seed; plane p uses ``seed + p``.
        compile: run the plane generation (stacked or per-plane path) through ``torch.compile``
            (compiled on the first ``prepare``; the state dict is unchanged). Measured on this 2-core
            CPU, one 80x80 generator's forward+backward on the per-plane path: 1.6x faster, after
            ~80 s of compilation.
        autocast_bf16: run the generators under bfloat16 autocast (float32 master weights; the planes
            come back in bfloat16 and ``sample`` reads them in the points' dtype): ``True``, ``False``
            or ``"auto"`` (on where the CPU multiplies bfloat16 natively AND a timed convolution shows
            it faster than float32, ``src.kernels.cpu``, and the weights are float32 on the CPU).
        stack_planes: run the three generators as one network with their parameters stored stacked
            (grouped convolutions over the planes' stacked channels, ``TriplaneGenerator(planes=3)``,
            built by ``src.fields.triplane.stack_generators`` from the per-plane ones): the same
            function as the per-plane generators (the reference path, ``False``). The state dict keeps
            the per-plane layout either way (``generators.{p}.*``), so checkpoints load across the switch.
        stack_channels_last: with ``stack_planes``, keep the activations channels-last (oneDNN's
            convolutions then skip re-ordering their outputs; one-channel-per-group GroupNorms run as
            batch-statistics ``batch_norm``, the same normalisation). Ignored unless every GroupNorm has
            one channel per group (``norm_groups == channels``).
        subpixel_upsample: compute each nearest ×2 + 3×3 conv as a 2×2 conv at the low resolution
            (``src.fields.triplane.subpixel_upsample_conv``): same function and parameters, 2.25×
            fewer FLOPs in those convs. ``False``: the reference up-sample-then-conv.
    """

    def __init__(
        self,
        plane_channels: int = 16,
        noise_channels: int = 8,
        noise_res: int = 20,
        channels: int = 32,
        n_up_blocks: int = 4,
        resnets_per_block: int = 2,
        norm_groups: int = 32,
        ref_extra_mid_resnet: bool = False,
        refine: bool = True,
        seed: int = 0,
        compile: bool = False,
        autocast_bf16: bool | str = False,
        stack_planes: bool = False,
        stack_channels_last: bool = False,
        subpixel_upsample: bool = False,
    ) -> None:
        super().__init__()
        self.autocast_bf16 = resolve_autocast_bf16(autocast_bf16, "conv")
        self.plane_channels = plane_channels
        self.compile = compile
        self.stack_planes = bool(stack_planes)
        self.stack_channels_last = bool(stack_channels_last)
        self._compiled: list | None = None  # the compiled ``_planes`` (a plain list: not a submodule)
        per_plane = [
            TriplaneGenerator(
                noise_channels=noise_channels,
                noise_res=noise_res,
                channels=channels,
                out_channels=plane_channels,
                n_up_blocks=n_up_blocks,
                resnets_per_block=resnets_per_block,
                norm_groups=norm_groups,
                ref_extra_mid_resnet=ref_extra_mid_resnet,
                seed=seed + p,
                subpixel_upsample=subpixel_upsample,
            )
            for p in range(3)
        ]
        # one stacked generator, or the three per-plane ones (the reference)
        channels_last = self.stack_channels_last and norm_groups == channels  # slow channels-last GroupNorm otherwise
        self.generators = nn.ModuleList(
            [stack_generators(per_plane, channels_last=channels_last)] if self.stack_planes else per_plane)
        if self.stack_planes:  # the state dict in the per-plane layout both ways
            self.register_state_dict_post_hook(_split_stacked_state)
            self.register_load_state_dict_pre_hook(_stack_plane_state)
        f = 3 * plane_channels
        self.refine = (
            nn.Sequential(nn.Linear(f, f), nn.ReLU(), nn.Linear(f, f)) if refine else nn.Identity()
        )

    @property
    def feature_dim(self) -> int:
        return 3 * self.plane_channels

    @property
    def resolution(self) -> int:
        """Spatial resolution R of each plane."""
        return self.generators[0].resolution

    def prepare(self) -> Tensor:
        """The three planes stacked: [3, C, R, R] (xy, yz, zx); bfloat16 under ``autocast_bf16``."""
        if self.compile and self._compiled is None:
            self._compiled = [torch.compile(self._planes)]
        noise = self.generators[0].noise
        bf16 = self.autocast_bf16 and noise.device.type == "cpu" and noise.dtype == torch.float32
        with torch.autocast("cpu", dtype=torch.bfloat16, enabled=bf16):
            return self._compiled[0]() if self._compiled is not None else self._planes()

    def _planes(self) -> Tensor:
        """The planes [3, C, R, R] by the configured path (stacked, or one generator per plane)."""
        if self.stack_planes:
            return self.generators[0]()
        return torch.cat([g() for g in self.generators], dim=0)

    def sample(self, state: Tensor, points: Tensor) -> Tensor:
        """Refined tri-plane features [N, 3C] of ``points`` [N, 3] from planes ``state`` [3, C, R, R]."""
        planes = state.to(points.dtype)
        # uv[p, n] = (u, v): u indexes the plane's width, v its height.
        uv = torch.stack([points[:, list(ax)] for ax in PLANE_AXES], dim=0)  # [3, N, 2]
        return self.refine(sample_planes(planes, uv))  # [N, 3·C] (xy, yz, zx) before the refinement


def _split_stacked_state(module: CNNTriplaneBackbone, state: dict[str, Tensor], prefix: str, _meta: Any) -> None:
    """State-dict hook: the stacked generator's entries ``generators.0.*`` [3·…] -> ``generators.{p}.*``."""
    head = prefix + "generators.0."
    stacked = {k[len(head):]: state.pop(k) for k in [k for k in state if k.startswith(head)]}
    for p, plane in enumerate(split_plane_state(stacked, 3)):
        state.update({f"{prefix}generators.{p}.{k}": v for k, v in plane.items()})


def _stack_plane_state(module: CNNTriplaneBackbone, state: dict[str, Tensor], prefix: str, *_: Any) -> None:
    """Load pre-hook: per-plane entries ``generators.{p}.*`` -> the stacked generator's ``generators.0.*``."""
    heads = [f"{prefix}generators.{p}." for p in range(3)]
    if not any(k.startswith(heads[1]) for k in state):
        return  # already stacked (or absent: strict loading reports it)
    planes = [{k[len(h):]: state.pop(k) for k in [k for k in state if k.startswith(h)]} for h in heads]
    state.update({heads[0] + k: v for k, v in stack_plane_state(planes).items()})
