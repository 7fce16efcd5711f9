"""SplatOptimizer: the fused Adam kernel gives the per-tensor loop's update, also across row edits."""

from __future__ import annotations

import torch
from torch import nn

from src.optim import SplatOptimizer
from src.optim.adam import replace_param_rows


def _train(fused: bool) -> list[torch.Tensor]:
    g = torch.Generator().manual_seed(0)
    rows = nn.Parameter(torch.randn(50, 3, generator=g))
    net = nn.Parameter(torch.randn(8, 8, generator=g))
    net0 = net.detach().clone()
    opt = SplatOptimizer([{"name": "rows", "params": [rows]}, {"name": "net", "params": [net]}],
                         lr={"rows": {"init": 1e-2, "final": 1e-4, "max_steps": 20}, "net": {"init": 1e-3}},
                         fused=fused)
    for step in range(20):
        opt.set_step(step)
        loss = (rows.sin() ** 2).sum() + (net @ net.T).square().mean() + (rows[:8, :] @ net[:3]).sum()
        loss.backward()
        opt.step()
        opt.zero_grad()
        if step == 9:  # densification-style edit: keep 40 rows, append 5 (zero moments)
            keep = torch.arange(50) % 5 != 0
            rows = replace_param_rows(opt, rows, torch.cat([rows.data[keep], torch.ones(5, 3)]), keep, 5)
    return [rows.detach(), net.detach(), net0]


def test_fused_adam_matches_the_loop():
    fused, loop = _train(True), _train(False)
    for a, b in zip(fused, loop, strict=True):
        assert a.shape == b.shape
        torch.testing.assert_close(a, b, rtol=1e-5, atol=1e-6)
    # and the parameters moved (the comparison is not between two untouched copies)
    assert (loop[1] - loop[2]).abs().max() > 1e-3
