"""Two scene models trained side by side (CoR-GS, Zhang et al., ECCV 2024), as one model, one optimiser
and one strategy for the trainer.

The trainer renders a :class:`CoTrainedPair` like any model: :meth:`CoTrainingStrategy.step_views` lays
the step's views out once per member, member after member, :meth:`CoTrainedPair.splats_for` gives each
member its half of the cameras, the objective averages over both members' renders, and
:meth:`CoTrainingStrategy.after_backward` / :meth:`CoTrainingStrategy.after_step` run each member's own
densification on its own renders and optimiser. The checkpoint holds both members (the pair's state
dict, packed as one splat set: :meth:`CoTrainedPair.state_dict`), both optimisers and both strategies'
statistics. Evaluation uses the first member only (``src.trainer.fit.fit_scene`` hands it on after training).
"""

from __future__ import annotations

import torch
from torch import Tensor, nn
from torch.nn.modules.module import _IncompatibleKeys

from src.core.cameras import Camera
from src.core.splats import RenderOutput, Splats
from src.data.base import View
from src.models.base import SplatModel
from src.optim.adam import SplatOptimizer
from src.strategy.base import Strategy

#: Keys of a packed pair state dict besides the members' own: the members' splat counts [2] and, per key
#: of a member's state dict in sorted order, whether it is a per-splat tensor (concatenated) [K] bool.
PAIR_COUNTS, PAIR_PER_SPLAT = "pair.counts", "pair.per_splat"


class CoTrainedPair(SplatModel):
    """Two models of the same configuration trained together; the first is the one evaluated.

    Args:
        first: the evaluated member (its splats and bake are the pair's).
        second: the co-trained member.

    ``n_splats`` and ``n_params`` count both members (what is trained); evaluation takes the first
    member itself (:meth:`src.sparse.corgs.CoRGS.final_model`).
    """

    def __init__(self, first: SplatModel, second: SplatModel) -> None:
        super().__init__()
        self.members = nn.ModuleList([first, second])
        self.method = getattr(first, "method", "")

    @property
    def first(self) -> SplatModel:
        return self.members[0]

    def splats(self, camera: Camera) -> Splats:
        """The first member's splats (what evaluation renders)."""
        return self.first.splats(camera)

    def splats_for(self, cameras: list[Camera]) -> list[Splats]:
        """Splats for the step's cameras laid out once per member, member after member: the first half
        from the first member, the second half from the second."""
        if len(cameras) % len(self.members):
            raise ValueError(f"{len(cameras)} cameras: a co-trained pair renders the step's cameras once per member")
        n = len(cameras) // len(self.members)
        return [s for i, m in enumerate(self.members) for s in m.splats_for(cameras[i * n:(i + 1) * n])]

    def param_groups(self) -> list[dict]:
        """Every member's groups, the second's names prefixed ``second.`` (each member has its own optimiser:
        :func:`src.sparse.base.optimizer_for`)."""
        groups = list(self.first.param_groups())
        groups += [{**g, "name": f"second.{g['name']}"} for g in self.members[1].param_groups()]
        return groups

    @property
    def n_splats(self) -> int:
        return sum(m.n_splats for m in self.members)

    def n_params(self) -> int:
        return sum(m.n_params() for m in self.members)

    def bake(self, time: float = 0.0, frame_id: int = 0) -> Splats:
        return self.first.bake(time=time, frame_id=frame_id)

    def networks(self) -> list[nn.Module]:
        return [net for m in self.members for net in m.networks()]

    def on_step(self, iteration: int) -> None:
        for m in self.members:
            m.on_step(iteration)

    def bind(self, scene) -> None:
        for m in self.members:
            m.bind(scene)

    def regularisers(self, iteration: int) -> dict[str, Tensor]:
        """Both members' terms, halved (the objective averages the members' losses); the second's names
        prefixed ``second.``."""
        out: dict[str, Tensor] = {}
        for i, m in enumerate(self.members):
            for k, v in m.regularisers(iteration).items():
                out[k if i == 0 else f"second.{k}"] = v / len(self.members)
        return out

    def state_dict(self, *args, **kwargs) -> dict[str, Tensor]:
        """Both members as one splat set of ``n_splats`` = N0 + N1 splats, keyed like one member.

        A per-splat tensor (first dimension the member's splat count in both) is the first member's rows
        followed by the second's [N0 + N1, ...]; any other tensor (network weights) is the two stacked
        [2, ...]; :data:`PAIR_COUNTS` and :data:`PAIR_PER_SPLAT` record how. A checkpoint of a pair thus
        has the layout of a checkpoint of one model whose splat count changes during training.
        Arguments of ``nn.Module.state_dict`` are not supported (a new dict of detached tensors).
        """
        parts = [m.state_dict() for m in self.members]
        counts = [m.n_splats for m in self.members]
        keys = sorted(parts[0])
        if sorted(parts[1]) != keys:
            raise RuntimeError("co-trained members have different state dict keys: "
                               f"{sorted(set(parts[0]) ^ set(parts[1]))[:5]}")
        out: dict[str, Tensor] = {}
        per_splat = []
        for k in keys:
            a, b = parts[0][k].detach(), parts[1][k].detach()
            rows = a.ndim >= 1 and b.ndim >= 1 and a.shape[0] == counts[0] and b.shape[0] == counts[1]
            rows = rows and a.shape[1:] == b.shape[1:]
            if not rows and a.shape != b.shape:
                raise RuntimeError(f"co-trained members differ in {k}: {list(a.shape)} and {list(b.shape)}")
            out[k] = torch.cat([a, b]) if rows else torch.stack([a, b])
            per_splat.append(rows)
        out[PAIR_COUNTS] = torch.tensor(counts, dtype=torch.int64)
        out[PAIR_PER_SPLAT] = torch.tensor(per_splat, dtype=torch.bool)
        return out

    def load_state_dict(self, state_dict, strict: bool = True, assign: bool = False):
        """Unpack :meth:`state_dict` and let each member load its part (members that resize on load, 3DGS
        splat counts and SplatFields query points, do)."""
        if PAIR_COUNTS not in state_dict or PAIR_PER_SPLAT not in state_dict:
            raise RuntimeError(f"not the state dict of a co-trained pair (no {PAIR_COUNTS!r})")
        n0 = int(state_dict[PAIR_COUNTS][0])
        flags = [bool(f) for f in state_dict[PAIR_PER_SPLAT].tolist()]
        keys = sorted(k for k in state_dict if k not in (PAIR_COUNTS, PAIR_PER_SPLAT))
        if len(flags) != len(keys):
            raise RuntimeError(f"a co-trained pair's state dict lists {len(flags)} layouts for {len(keys)} keys")
        parts: list[dict[str, Tensor]] = [{}, {}]
        for k, rows in zip(keys, flags, strict=True):
            t = state_dict[k]
            parts[0][k], parts[1][k] = (t[:n0], t[n0:]) if rows else (t[0], t[1])
        missing: list[str] = []
        unexpected: list[str] = []
        for i, (m, part) in enumerate(zip(self.members, parts, strict=True)):
            res = m.load_state_dict(part, strict=strict, assign=assign)
            missing += [f"members.{i}.{k}" for k in res.missing_keys]
            unexpected += [f"members.{i}.{k}" for k in res.unexpected_keys]
        return _IncompatibleKeys(missing, unexpected)


class MemberOptimizers:
    """One :class:`SplatOptimizer` per member of a :class:`CoTrainedPair`, stepped together.

    ``members[i]`` is the optimiser a member's densification edits (its ``densify`` / ``prune`` calls).
    """

    def __init__(self, optimizers: list[SplatOptimizer]) -> None:
        self.members = list(optimizers)

    def set_step(self, step: int) -> dict[str, float]:
        """Every member's schedules at ``step``; returns the first's {name: lr} (the members share them)."""
        lrs = [o.set_step(step) for o in self.members]
        return lrs[0]

    def step(self) -> None:
        for o in self.members:
            o.step()

    def zero_grad(self) -> None:
        for o in self.members:
            o.zero_grad()

    def state_dict(self) -> dict:
        return {"members": [o.state_dict() for o in self.members]}

    def load_state_dict(self, state: dict) -> None:
        parts = state.get("members") if isinstance(state, dict) else None
        if not isinstance(parts, list) or len(parts) != len(self.members):
            raise ValueError(f"expected the optimiser states of {len(self.members)} co-trained models")
        for o, s in zip(self.members, parts, strict=True):
            o.load_state_dict(s)

    def group(self, name: str) -> dict:
        return self.members[0].group(name)


class CoTrainingStrategy(Strategy):
    """Each member's own densification strategy, on its own renders and optimiser.

    Args:
        members: one strategy per member of the :class:`CoTrainedPair` (the run's ``strategy`` config).
    """

    def __init__(self, members: list[Strategy]) -> None:
        super().__init__(members[0].max_splats, members[0].extent)
        self.members = list(members)

    def bind(self, scene, rasterizer) -> None:
        for s in self.members:
            s.bind(scene, rasterizer)

    def step_views(self, model: SplatModel, views: list[View], iteration: int,
                   generator: torch.Generator) -> list[View]:
        """Each member's views of the step (its strategy may replace them), member after member."""
        per = [s.step_views(m, views, iteration, generator) for s, m in zip(self.members, _members(model), strict=True)]
        if len({len(v) for v in per}) != 1:
            raise ValueError("co-trained members must render the same number of views per step")
        return [v for vs in per for v in vs]

    def after_backward(self, model: SplatModel, renders: list[RenderOutput], iteration: int) -> None:
        n = len(renders) // len(self.members)
        for i, (s, m) in enumerate(zip(self.members, _members(model), strict=True)):
            s.after_backward(m, renders[i * n:(i + 1) * n], iteration)

    def after_step(self, model: SplatModel, optimizer, iteration: int, generator: torch.Generator) -> dict:
        """Each member's densification with its own optimiser; the second's counts prefixed ``second.``."""
        stats: dict = {}
        for i, (s, m, o) in enumerate(zip(self.members, _members(model), optimizer.members, strict=True)):
            for k, v in s.after_step(m, o, iteration, generator).items():
                stats[k if i == 0 else f"second.{k}"] = v
        return stats

    def state_dict(self) -> dict:
        return {"members": [s.state_dict() for s in self.members]}

    def load_state_dict(self, state: dict) -> None:
        parts = state.get("members", [{}] * len(self.members))
        for s, part in zip(self.members, parts, strict=True):
            s.load_state_dict(part)


def _members(model: SplatModel) -> list[SplatModel]:
    if not isinstance(model, CoTrainedPair):
        raise TypeError(f"CoTrainingStrategy trains a CoTrainedPair, not a {type(model).__name__}")
    return list(model.members)
