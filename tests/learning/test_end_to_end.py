"""End to end: learn a barrier from sampled occupancy through the filter, then run it in
closed loop (small default version; the five-ellipse reproduction is slow-marked)."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from torchcbf.barriers import Ellipse, NeuralBarrier
from torchcbf.dynamics import SingleIntegrator
from torchcbf.filters import SafetyFilter
from torchcbf.learning import (
    MLP,
    cbf_condition_loss,
    classification_accuracy,
    classification_loss,
    dilate,
    make_generator,
    occupancy_from_barrier,
    sample_free,
    sample_labelled,
    train,
)
from torchcbf.sim import simulate

ROOT = Path(__file__).resolve().parents[2]


def test_learned_ellipse_barrier_classifies_and_keeps_the_loop_safe() -> None:
    truth = Ellipse(torch.tensor([[0.0, 0.0]]), torch.tensor([[1.0, 0.5]]))
    occupied = occupancy_from_barrier(truth)
    train_occ = dilate(occupied, 0.1)  # safety margin: learned {h >= 0} inside free space
    lo, hi = torch.tensor([-2.0, -2.0]), torch.tensor([2.0, 2.0])
    torch.manual_seed(0)
    barrier = NeuralBarrier(MLP(2, (32, 32), activation="silu", low=lo, high=hi))
    dyn = SingleIntegrator(2, u_min=-1.0, u_max=1.0)
    filt = SafetyFilter(dyn, barrier, alpha=2.0)
    goal = torch.tensor([1.9, 0.1])
    nominal = lambda x, t: (2 * (goal - x)).clamp(-1, 1)  # noqa: E731
    gen = make_generator(seed=0)
    data = sample_labelled(train_occ, lo, hi, 20_000, generator=gen)
    opt = torch.optim.Adam(barrier.parameters(), lr=1e-2)
    steps = 250
    sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, steps, eta_min=1e-4)

    def loss_fn(step: int):
        idx = torch.randint(data.x.shape[0], (512,), generator=gen)
        x, safe = data.x[idx], data.safe[idx]
        l_cls = classification_loss(barrier(x), safe, margin=0.05, temperature=0.1)
        xs = x[safe][:64]
        l_cbf = cbf_condition_loss(filt, xs, nominal(xs, 0.0))
        return l_cls + l_cbf, {"cbf": l_cbf}

    res = train(loss_fn, opt, steps, scheduler=sched, progress=False)
    assert res.losses[-1] < 0.2 * res.losses[0]

    test = sample_labelled(train_occ, lo, hi, 5000, seed=5)
    with torch.no_grad():
        h = barrier(test.x)
    assert float(classification_accuracy(h, test.safe)) >= 0.99
    assert not bool(((h >= 0) & occupied(test.x)).any())  # never safe inside the obstacle

    # held-out starts in free space with a margin, half of them straight behind the obstacle
    x0 = sample_free(occupied, lo, hi, 50, margin=0.25, seed=7)
    behind = torch.stack([torch.full((50,), -1.9), torch.linspace(-0.6, 0.6, 50)], -1)
    x0 = torch.cat([x0, behind])
    with torch.no_grad():
        traj = simulate(dyn, x0, 80, 0.05, nominal=nominal, safety_filter=filt, progress=False)
        h_true = truth(traj.x).amin(-1)
        unfiltered = simulate(dyn, behind, 80, 0.05, nominal=nominal, progress=False)
    assert bool((truth(unfiltered.x).amin(-1) < 0).any(-1).all())  # without it they collide
    assert int((h_true < 0).any(-1).sum()) == 0
    assert float(h_true.min()) > 0.0


@pytest.mark.slow
def test_learn_barrier_script_five_ellipses(tmp_path) -> None:
    """The full reproduction: >= 99% held-out accuracy, zero collisions over 1,000 starts."""
    run = subprocess.run(
        [
            sys.executable,
            str(ROOT / "scripts" / "learn_barrier.py"),
            "--out",
            str(tmp_path),
            "--no-progress",
        ],
        capture_output=True,
        text=True,
        timeout=3600,
    )
    assert run.returncode == 0, f"exit {run.returncode}\n{run.stdout}\n{run.stderr}"
    out = run.stdout
    acc = float(re.search(r"held-out accuracy .*?: ([\d.]+)%", out).group(1))
    collisions = int(re.search(r"closed loop: (\d+) collisions over 1000", out).group(1))
    assert acc >= 99.0, out
    assert collisions == 0, out
    assert (tmp_path / "level_set.png").exists() and (tmp_path / "closed_loop.png").exists()
