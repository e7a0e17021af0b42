"""MPPI(layout=...): a torch cost sees the rollouts in the memory it asks for, and the plans
do not depend on it beyond the rounding of the cost's reductions."""

from __future__ import annotations

import pytest
import torch

from torchcbf.dynamics import AccelUnicycle
from torchcbf.mppi import MPPI

GOAL = torch.tensor([2.0, 4.0])


@pytest.mark.parametrize("backend", ["auto", "torch"])
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32], ids=["float64", "float32"])
def test_both_layouts_give_the_same_plans(backend: str, dtype: torch.dtype) -> None:
    seen: dict[str, set[bool]] = {}
    outs = {}
    for layout in ("component", "sample"):
        seen[layout] = set()

        def cost(states, controls, t0, layout=layout):
            seen[layout].add(states.stride(-1) == 1 and controls.stride(-1) == 1)
            goal = GOAL.to(states)
            return (states[..., :2] - goal).norm(dim=-1).sum(-1) + controls.square().sum((-1, -2))

        planner = MPPI(AccelUnicycle(), cost, horizon=12, num_samples=300, dt=0.05,
                       noise_sigma=1.0, temperature=0.5, seed=3, layout=layout,
                       backend=backend, keep_rollouts=4, cost_chunk=64).to(dtype)  # fmt: skip
        x = torch.zeros(2, 4, dtype=dtype)
        for _ in range(3):
            outs[layout] = planner(x)
        assert outs[layout].path == ("rollout" if backend == "auto" else "torch")
    assert seen == {"component": {False}, "sample": {True}}
    tol = 1e-9 if dtype == torch.float64 else 1e-4
    a, b = outs["component"], outs["sample"]
    torch.testing.assert_close(a.plan, b.plan, atol=tol, rtol=tol)
    torch.testing.assert_close(a.rollouts, b.rollouts, atol=tol, rtol=tol)


def test_layout_is_checked() -> None:
    with pytest.raises(ValueError, match="layout must be one of"):
        MPPI(AccelUnicycle(), lambda s, c, t: s.sum((-1, -2)), horizon=4, num_samples=8,
             dt=0.1, noise_sigma=1.0, temperature=1.0, layout="rows")  # fmt: skip
