"""stages/lift/refine.adam_refine: the refinement loop of both lifts is plain Adam."""

from __future__ import annotations

import torch

from dlacli.stages.lift.refine import adam_refine


def test_adam_refine_is_adam_step_for_step():
    target = torch.linspace(-1.0, 2.0, 7)

    def loss_of(x):
        return ((x - target) ** 2).sum() + x.abs().sum()

    x = torch.zeros(7, requires_grad=True)
    seen = []
    history = adam_refine([x], lambda: loss_of(x), 25, 0.1, lambda step, value: seen.append((step, value)))
    # the same steps written out with torch.optim.Adam (an independent loop)
    y = torch.zeros(7, requires_grad=True)
    opt = torch.optim.Adam([y], lr=0.1)
    want = []
    for _ in range(25):
        opt.zero_grad()
        value = loss_of(y)
        value.backward()
        opt.step()
        want.append(float(value.detach()))
    assert history == want and torch.equal(x.detach(), y.detach())
    assert seen == list(enumerate(history))
    assert history[-1] < 0.7 * history[0]  # it descends
    assert adam_refine([x], lambda: loss_of(x), 0, 0.05) == []
