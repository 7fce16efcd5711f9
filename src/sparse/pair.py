"""Two scene models trained side by side (CoR-GS, Zhang et al., ECCV 2024), as one model, one optimiser
and one strategy for the trainer.

The trainer renders a :class:`CoTrainedPair` like any model: :meth:`CoTrainingStrategy.step_views` lays
the step's views out once per member, member after member, :meth:`CoTrainedPair.splats_for` gives each
member its half of the cameras, the objective averages over both members' renders, and
:meth:`CoTrainingStrategy.after_backward` / :meth:`CoTrainingStrategy.after_step` run each member's own
densification on its own renders and optimiser. The checkpoint holds both members (the pair's state
dict), both optimisers and both strategies' statistics. Evaluation uses the first member only.
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


class CoTrainedPair(SplatModel):
    """Two models of the same configuration trained together; the first is the one evaluated.

    Args:
        first: the evaluated member (its splats, bake, splat count and parameters are the run's).
        second: the co-trained member.
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
        return self.first.n_splats

    def n_params(self) -> int:
        return self.first.n_params()

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

    def load_state_dict(self, state_dict, strict: bool = True, assign: bool = False):
        """Each member loads its own part (``members.<i>.``), so members that resize on load (3DGS splat
        counts, SplatFields query points) do."""
        missing: list[str] = []
        unexpected = [k for k in state_dict if not k.startswith("members.")]
        for i, m in enumerate(self.members):
            prefix = f"members.{i}."
            part = {k[len(prefix):]: v for k, v in state_dict.items() if k.startswith(prefix)}
            res = m.load_state_dict(part, strict=strict, assign=assign)
            missing += [prefix + k for k in res.missing_keys]
            unexpected += [prefix + k for k in res.unexpected_keys]
        if strict and unexpected:
            raise RuntimeError(f"unexpected keys in a co-trained pair's state dict: {unexpected[:5]}")
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
