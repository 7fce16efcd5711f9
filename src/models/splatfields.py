"""SplatFields: splat attributes predicted by neural fields at canonical query points (Sec. 4, B.2).

The per-splat state is only a set of canonical centres and their kNN base scales (buffers, not
trained); every rendered attribute comes from :class:`src.fields.network.SplatFieldNetwork`.
Conventions: normalised scene coordinates in [-1, 1]^3 (anywhere in R^3 with ``network.contraction=mip360``,
which the fields apply before encoding a position: unbounded scenes, ``src.fields.contraction``),
quaternions (w, x, y, z), linear scales.
"""

from __future__ import annotations

import inspect
import logging
from collections.abc import Callable

import torch
from torch import Tensor

from src.core.cameras import Camera
from src.core.splats import Splats
from src.fields.network import SplatFieldNetwork
from src.models.base import SplatModel
from src.models.knn import knn_base_scale
from src.models.mip_splatting import filter_variance, max_sampling_rate

log = logging.getLogger(__name__)


class SplatFieldsModel(SplatModel):
    """Neural splat fields over canonical points.

    Args:
        init: [N, 3] canonical centres (visual hull samples or a 3DGS run's centres).
        network: the field network, or a partial of it (``_partial_: true`` in the config) that is
            completed here with the scene's ``n_frames`` and the ``flow``.
        flow: flow model (or a partial taking ``n_frames``/``hidden_dim``) for dynamic scenes; None = static.
        n_frames: number of frames of the scene (1 = static). Passed as a number by ``src.run``: Hydra
            would turn a dataclass argument (e.g. the Scene) into a config node.
        method: label in run records.
        clone_mode: how densification clones a query point. ``jitter`` (default, the paper's intent of
            adding detail): the clone is moved by N(0, clone_jitter x its base scale), so it is a new
            query point; ``exact_quirk``: an exact copy, as the reference code does, which through a
            deterministic field renders the same splat twice (doubled opacity).
        clone_jitter: clone displacement in units of the base scale (``jitter`` mode).
        max_splats: never hold more canonical points than this (initial points are subsampled).
        time_noise: annealed time jitter of Deformable-3DGS's smooth training (monocular data): the
            training time is t + N(0, 1) * time_noise * (1 / n_frames) * max(0, 1 - it / time_noise_until).
            0 disables it.
        time_noise_until: iteration at which the jitter reaches zero.
        filter_3d: s of Mip-Splatting's 3D smoothing filter (Yu et al. 2024, Sec. 5.1) applied to the
            predicted splats: variance s / nu^2, nu the highest sampling rate of the splat's centre over
            the training cameras (``bind``); 0 (default, the paper) = no filter.
        frustum_margin: a training camera sees a centre within this fraction of the image size
            outside its borders (the 3D filter's rate; Mip-Splatting's code: 0.15).
    """

    def __init__(self, init: Tensor, network: SplatFieldNetwork | Callable[..., SplatFieldNetwork],
                 flow: object | None = None, n_frames: int = 1, method: str = "splatfields3d",
                 clone_mode: str = "jitter", clone_jitter: float = 0.5, max_splats: int | None = None,
                 time_noise: float = 0.0, time_noise_until: int = 20_000, filter_3d: float = 0.0,
                 frustum_margin: float = 0.15, **_: object) -> None:
        super().__init__()
        n_frames = max(1, int(n_frames))
        if not isinstance(network, torch.nn.Module):
            kwargs = {"n_frames": n_frames}
            if flow is not None:
                if not isinstance(flow, torch.nn.Module):
                    fkw = {"n_frames": n_frames} if "n_frames" in inspect.signature(flow).parameters else {}
                    flow = flow(**fkw)
                kwargs["flow"] = flow
            network = network(**kwargs)
        self.n_frames = n_frames
        self.time_noise = time_noise
        self.time_noise_until = time_noise_until
        self.iteration = 0
        if clone_mode not in ("jitter", "exact_quirk"):
            raise ValueError(f"model.clone_mode={clone_mode!r}: expected 'jitter' or 'exact_quirk'")
        if max_splats is not None and init.shape[0] > max_splats:
            init = init[torch.randperm(init.shape[0], generator=torch.Generator().manual_seed(0))[:max_splats]]
        self.method = method
        self.network = network
        self.clone_mode = clone_mode
        self.clone_jitter = clone_jitter
        self.register_buffer("canonical", init.float().clone())  # [N, 3]
        self.register_buffer("base_scale", knn_base_scale(init.float())[:, None].repeat(1, 3))  # [N, 3]
        self._warn_if_unbounded()
        self._last: dict[str, Tensor] = {}
        if not filter_3d >= 0:
            raise ValueError(f"model.filter_3d must be >= 0, got {filter_3d}")
        self.filter_3d = float(filter_3d)
        self.frustum_margin = float(frustum_margin)
        self.cameras: list[Camera] = []

    @property
    def n_splats(self) -> int:
        return self.canonical.shape[0]

    def _warn_if_unbounded(self) -> None:
        """Warn when more than 1 % of the centres lie outside [-1, 1]^3 and the fields do not contract them:
        the tri-planes read zero there (one feature for all of them)."""
        contraction = getattr(self.network, "contraction", None)
        if contraction is None or not contraction.is_identity or self.n_splats == 0:
            return
        outside = int((self.canonical.abs() > 1).any(dim=1).sum())
        if outside > 0.01 * self.n_splats:
            log.warning("%d of %d initial centres lie outside [-1, 1]^3, where the tri-planes read zero: for an "
                        "unbounded scene use model.network.contraction=mip360 (+experiment=splatfields3d_unbounded)",
                        outside, self.n_splats)

    def param_groups(self) -> list[dict]:
        return [{"name": "network", "params": [p for p in self.network.parameters() if p.requires_grad]}]

    def networks(self) -> list[torch.nn.Module]:
        """The field network (backbone, heads and flow): one module, compiled whole by ``trainer.compile``."""
        return [self.network]

    def on_step(self, iteration: int) -> None:
        self.iteration = iteration

    def _time(self, camera: Camera) -> float:
        """The time fed to the fields: the camera's, jittered while training if ``time_noise`` > 0."""
        t = camera.time
        if self.training and self.time_noise > 0 and self.n_frames > 1:
            decay = max(0.0, 1.0 - self.iteration / max(self.time_noise_until, 1))
            t = t + float(torch.randn(())) * self.time_noise * decay / self.n_frames
        return t

    def _predict(self, camera: Camera, state) -> dict[str, Tensor]:
        return self.network(self.canonical, self.base_scale, frame_id=camera.frame_id, time=self._time(camera),
                            camera_center=camera.center.to(self.canonical), state=state)

    def bind(self, scene) -> None:
        """Keep the scene's training cameras (the sampling rates of the 3D filter)."""
        self.cameras = [v.camera for v in scene.train]

    def _smoothed(self, out: dict[str, Tensor]) -> dict[str, Tensor]:
        """``out`` with the 3D smoothing filter applied (unchanged when ``filter_3d`` is 0 or no cameras).

        R diag(s^2) R^T + var I = R diag(s^2 + var) R^T: scales sqrt(s^2 + var) [N, 3] and opacity
        x prod_i s_i / sqrt(s_i^2 + var) (the filtered splat keeps its integral), var [N] = s_f / nu^2
        from the current centres (detached; the rate is a property of the cameras, not a gradient path).
        """
        if self.filter_3d <= 0 or not self.cameras:
            return out
        nu = max_sampling_rate(out["means"].detach(), self.cameras, self.frustum_margin)  # [N]
        var = filter_variance(nu, self.filter_3d).to(out["scales"])[:, None]  # [N, 1]
        s2 = out["scales"] * out["scales"]  # [N, 3]
        scales = torch.sqrt(s2 + var)
        factor = torch.prod(out["scales"] / scales, dim=-1)  # [N] in (0, 1]
        return {**out, "scales": scales, "opacities": out["opacities"] * factor}

    def _to_splats(self, out: dict[str, Tensor]) -> Splats:
        self._last = {"opacities": out["opacities"].detach(), "scales": out["scales"].detach()}
        out = self._smoothed(out)
        return Splats(means=out["means"], scales=out["scales"], quats=out["quats"], opacities=out["opacities"],
                      colors=out["colors"])

    def splats(self, camera: Camera) -> Splats:
        return self._to_splats(self._predict(camera, self.network.prepare()))

    def splats_for(self, cameras: list[Camera], state: object = None) -> list[Splats]:
        """Splats for several cameras: the tri-plane CNN runs once (``state``: its precomputed
        ``network.prepare()`` output, computed here when None), and with view-independent colour the
        heads run once per distinct time (the views of one training step share it)."""
        if state is None:
            state = self.network.prepare()
        if getattr(self.network, "view_dependent", False):
            return [self._to_splats(self._predict(c, state)) for c in cameras]
        cache: dict[tuple[int, float], Splats] = {}
        out = []
        for c in cameras:
            key = (c.frame_id, c.time)
            if key not in cache:
                cache[key] = self._to_splats(self._predict(c, state))
            out.append(cache[key])
        return out

    @torch.no_grad()
    def bake(self, time: float = 0.0, frame_id: int = 0) -> Splats:
        """Evaluate the fields once and return a plain splat set (exact for view-independent colour)."""
        if getattr(self.network, "view_dependent", False):
            raise NotImplementedError("view-dependent colour cannot be baked into RGB splats exactly")
        out = self._smoothed(self.network(self.canonical, self.base_scale, frame_id=frame_id, time=time,
                                          state=self.network.prepare()))
        return Splats(means=out["means"].clone(), scales=out["scales"].clone(),
                      quats=torch.nn.functional.normalize(out["quats"], dim=-1), opacities=out["opacities"].clone(),
                      colors=out["colors"].clone())

    def load_state_dict(self, state_dict, strict: bool = True, assign: bool = False):
        """Load a checkpoint whose number of canonical points may differ (resizes the buffers first)."""
        for name in ("canonical", "base_scale"):
            if name in state_dict and state_dict[name].shape != getattr(self, name).shape:
                setattr(self, name, torch.empty_like(state_dict[name], device=getattr(self, name).device))
        return super().load_state_dict(state_dict, strict=strict, assign=assign)

    # -- densification: add / remove / move query points -----------------------------------
    def canonical_means(self) -> Tensor:
        return self.canonical

    def max_scale(self) -> Tensor:
        s = self._last.get("scales")
        if s is None or s.shape[0] != self.n_splats:
            s = self.base_scale
        return s.max(dim=1).values

    def opacity_values(self) -> Tensor | None:
        o = self._last.get("opacities")
        return o if o is not None and o.shape[0] == self.n_splats else None

    def densify(self, optimizer, clone: Tensor, split: Tensor, n_split: int, generator: torch.Generator) -> None:
        """Clone (jittered, or exact in ``exact_quirk`` mode) and split canonical points (base scale / 1.6)."""
        x, s = self.canonical, self.base_scale
        new_x = [x[~split]]
        new_s = [s[~split]]
        if clone.any():
            cx, cs = x[clone], s[clone]
            if self.clone_mode == "jitter":
                cx = cx + torch.randn(cx.shape, generator=generator).to(cx) * cs * self.clone_jitter
            new_x.append(cx)
            new_s.append(cs)
        if split.any():
            px, ps = x[split].repeat(n_split, 1), s[split].repeat(n_split, 1)
            new_x.append(px + torch.randn(px.shape, generator=generator).to(px) * ps)
            new_s.append(ps / (0.8 * n_split))
        self.canonical = torch.cat(new_x)
        self.base_scale = torch.cat(new_s)
        self._last = {}

    def _near(self, targets: Tensor, generator: torch.Generator) -> tuple[Tensor, Tensor]:
        """New query points near ``targets``: jittered by ``clone_jitter`` x base scale (never duplicates)."""
        x, s = self.canonical[targets], self.base_scale[targets]
        jitter = max(self.clone_jitter, 1e-3)
        return x + torch.randn(x.shape, generator=generator).to(x) * s * jitter, s.clone()

    @torch.no_grad()
    def relocate(self, optimizer, dead: Tensor, targets: Tensor, generator: torch.Generator) -> None:
        """Move dead query points next to live ones (the field decides their attributes)."""
        x, s = self._near(targets, generator)
        self.canonical[dead] = x
        self.base_scale[dead] = s
        self._last = {}

    @torch.no_grad()
    def add_from(self, optimizer, targets: Tensor, generator: torch.Generator) -> None:
        x, s = self._near(targets, generator)
        self.canonical = torch.cat([self.canonical, x])
        self.base_scale = torch.cat([self.base_scale, s])
        self._last = {}

    def prune(self, optimizer, mask: Tensor) -> None:
        self.canonical = self.canonical[~mask]
        self.base_scale = self.base_scale[~mask]
        self._last = {}
