"""Scenario A (docs/scenarios.md) closed loop: timed reach-avoid with MPPI on a single integrator.

Ten seeds run as ten environments of one planner (environment b uses seed b, see the MPPI
RNG scheme). The scenario leaves the weight normalization open: with temperature 0.03 the
sample costs are normalized by their standard deviation (``cost_normalization="std"``); the
plain exponent is nearly greedy and the control-cost noise then decides (7/10 seeds at
K = 10,000 in our runs), range normalization (CBFkit's) averages too much and cuts the g2
hairpin (0/10). Success (the spec's robustness >= 0): every goal reached (|p - g| <= 0.5) at a
sampled time inside its window and |p - o| >= 0.6 at every sampled time.
"""

from __future__ import annotations

import pytest
import torch

from torchcbf.dynamics import SingleIntegrator
from torchcbf.mppi import MPPI, And
from torchcbf.scenarios import reach_avoid_spec

DT, STEPS = 0.1, 100


def scenario_a_spec() -> And:
    return reach_avoid_spec()


def run_scenario_a(num_samples: int, seeds: int, dtype=torch.float32):
    spec = scenario_a_spec()
    dyn = SingleIntegrator(2, u_min=-5.0, u_max=5.0)
    planner = MPPI(dyn, spec, 50, num_samples, DT, 4.0, 0.03, 0.1, seed=0, cost_normalization="std")
    x = torch.zeros(seeds, 2, dtype=dtype)
    xs = [x]
    for k in range(STEPS):
        out = planner(x, t=k * DT)
        x = x + DT * out.u  # x_{k+1} = x_k + u dt
        xs.append(x)
    traj = torch.stack(xs, 1)  # [seeds, 101, 2]
    times = torch.arange(STEPS + 1, dtype=dtype) * DT
    return spec, traj, times


def _check(spec, traj, times, need: int) -> None:
    rob = spec.robustness(traj, times)
    per_term = torch.stack([s.robustness(traj, times) for s in spec.specs], -1)
    # the robustness verdict is the literal success check
    dist_o = (traj - torch.tensor([3.0, 3.0])).norm(dim=-1)
    ok = (dist_o >= 0.6).all(-1)
    for g, (t1, t2) in (((4.0, 4.0), (0, 3.5)), ((6.0, 9.0), (3.6, 5.0)), ((4.0, 1.0), (5.1, 10))):
        inside = (times >= t1 - 1e-5) & (times <= t2 + 1e-5)
        ok &= (((traj - torch.tensor(g)).norm(dim=-1) <= 0.5) & inside).any(-1)
    assert torch.equal(rob >= 0, ok)
    assert int(ok.sum()) >= need, f"successes {int(ok.sum())}/{len(ok)}; per term:\n{per_term}"


def test_scenario_a_small():
    spec, traj, times = run_scenario_a(num_samples=1000, seeds=3)
    _check(spec, traj, times, need=2)


@pytest.mark.slow
def test_scenario_a_full():
    spec, traj, times = run_scenario_a(num_samples=10_000, seeds=10)
    _check(spec, traj, times, need=9)
