"""Learning on the device fixture's device against the CPU: a learned barrier trained a
few steps through the safety filter's QP, the closed-loop loss through differentiable
rollouts, and the occupancy labels; inputs drawn on the CPU and moved."""

from __future__ import annotations

import copy
from typing import NamedTuple

import pytest
import torch
from _devices import device_matches_cpu
from _host_traffic import HostTraffic

from torchcbf.barriers import Ball, Ellipse, NeuralBarrier
from torchcbf.dynamics import SingleIntegrator
from torchcbf.filters import SafetyFilter
from torchcbf.learning import (
    MLP,
    cbf_condition_loss,
    classification_loss,
    closed_loop_loss,
    dilate,
    label_states,
    make_generator,
    occupancy_from_barrier,
    sample_free,
    sample_labelled,
    train,
    uniform_box,
)
from torchcbf.sim import simulate

LOW, HIGH = [-2.0, -2.0], [2.0, 2.0]


def _truth() -> Ellipse:
    return Ellipse(torch.tensor([[0.0, 0.0]]), torch.tensor([[1.0, 0.5]]))


def test_barrier_trained_through_the_qp_on_device_equals_cpu(dtype, device) -> None:
    """Six steps of training a neural barrier on labelled states plus the CBF condition at
    the filter's QP solution (gradients through the QP): the losses, the trained weights and
    the learned barrier's values equal the CPU run's."""
    torch.manual_seed(0)
    net = MLP(2, (16, 16), activation="silu", low=LOW, high=HIGH)
    data = sample_labelled(dilate(occupancy_from_barrier(_truth()), 0.1), LOW, HIGH, 192, seed=1)
    test = uniform_box(LOW, HIGH, 64, seed=2, dtype=torch.float64)
    goal = torch.tensor([1.9, 0.1])

    def run(dev: torch.device):
        f = {"device": dev, "dtype": dtype}
        barrier = NeuralBarrier(copy.deepcopy(net)).to(**f)
        dyn = SingleIntegrator(2, u_min=-1.0, u_max=1.0).to(**f)
        filt = SafetyFilter(dyn, barrier, alpha=2.0).to(**f)
        x, safe = data.x.to(**f), data.safe.to(dev)
        xs = x[safe][:48]
        u_nom = (2.0 * (goal.to(**f) - xs)).clamp(-1.0, 1.0)
        # SGD: Adam's first steps divide by the gradients' size, so a gradient near zero
        # would turn its rounding into a step of the learning rate
        opt = torch.optim.SGD(barrier.parameters(), lr=0.05, momentum=0.9)

        def loss_fn(step: int):
            l_cls = classification_loss(barrier(x), safe, margin=0.05, temperature=0.1)
            l_cbf = cbf_condition_loss(filt, xs, u_nom, margin=1.0)
            return l_cls + l_cbf, {"cbf": l_cbf}

        cbf: list[float] = []
        result = train(loss_fn, opt, 6, progress=False, callback=lambda *a: cbf.append(a[2]["cbf"]))
        with torch.no_grad():
            h = barrier(test.to(**f))
        weights = [p.detach() for p in barrier.parameters()]
        return (
            torch.tensor(result.losses, **f),
            torch.tensor(cbf, **f),
            h,
            *weights,
        )

    loose = {} if dtype == torch.float64 else {"rtol": 1e-3, "atol": 1e-4}
    losses, cbf, *_ = device_matches_cpu(run, device, dtype, **loose)
    assert float(losses[-1]) < float(losses[0])
    assert float(cbf[0]) > float(cbf[-1])  # the condition at the QP's solution was trained


def test_closed_loop_loss_and_gradient_through_rollouts_on_device_equal_cpu(dtype, device):
    """The closed-loop loss of differentiable filtered rollouts and its gradients to a
    controller gain and to the barrier's radius equal the CPU's."""
    x0 = torch.tensor([[-1.5, 0.05], [-1.5, -0.3], [-1.2, 0.6]], dtype=torch.float64)

    def run(dev: torch.device):
        f = {"device": dev, "dtype": dtype}
        gain = torch.tensor(1.5, **f, requires_grad=True)
        radius = torch.tensor(0.5, **f, requires_grad=True)
        goal = torch.tensor([1.5, 0.0], **f)
        dyn = SingleIntegrator(2, u_min=-1.0, u_max=1.0).to(**f)
        filt = SafetyFilter(dyn, Ball(torch.zeros(2, **f), radius), alpha=2.0)
        nominal = lambda x, t: (gain * (goal - x)).clamp(-1.0, 1.0)  # noqa: E731
        traj = simulate(dyn, x0.to(**f), 30, 0.05, nominal=nominal, safety_filter=filt,
                        progress=False, differentiable=True)  # fmt: skip
        truth = Ball([0.0, 0.0], 0.45).to(**f)
        loss = closed_loop_loss(traj, truth, goal=goal, goal_weight=0.5, collision_margin=0.2)
        grads = torch.autograd.grad(loss.total, (gain, radius))
        return *(term.detach() for term in loss), *grads

    loose = {} if dtype == torch.float64 else {"rtol": 1e-3, "atol": 1e-4}
    total, intervention, collision, goal, *grads = device_matches_cpu(run, device, dtype, **loose)
    assert float(intervention) > 0 and float(collision) > 0 and all(float(g) != 0 for g in grads)


def test_occupancy_labels_on_device_equal_cpu(dtype, device) -> None:
    """Labels of states drawn on the CPU, from a barrier's occupancy and its dilation, equal
    the CPU's on the device."""
    x = uniform_box(LOW, HIGH, 4000, seed=3, dtype=torch.float64)

    def run(dev: torch.device):
        occupied = occupancy_from_barrier(_truth().to(device=dev, dtype=dtype))
        xs = x.to(device=dev, dtype=dtype)
        return label_states(xs, occupied), label_states(xs, dilate(occupied, 0.2))

    plain, grown = device_matches_cpu(run, device, dtype)
    assert bool((plain & ~grown).any()) and not bool((grown & ~plain).any())


def test_device_sampling_repeats_and_refuses_a_generator_elsewhere(dtype, device) -> None:
    """Sampling on the device draws from a generator there: a seed repeats exactly, the free
    states are free, and a generator on another device than the box is refused by name."""
    low = torch.tensor(LOW, device=device, dtype=dtype)
    high = torch.tensor(HIGH, device=device, dtype=dtype)
    occupied = occupancy_from_barrier(_truth().to(device=device, dtype=dtype))
    a = sample_free(occupied, low, high, 300, margin=0.1, seed=4)
    b = sample_free(occupied, low, high, 300, margin=0.1, seed=4)
    assert a.device.type == device.type and a.dtype == dtype and torch.equal(a, b)
    assert not bool(occupied(a).any())
    if device.type != "cpu":
        with pytest.raises(ValueError, match="generator is on device cpu"):
            uniform_box(low, high, 10, generator=make_generator(seed=0, device="cpu"))


def test_training_losses_make_no_host_traffic() -> None:
    """A learned barrier's values, the classification loss and the closed-loop loss (goal
    term included) run on the meta device (no value is read back) and copy nothing from the
    host (no list index, no Python data)."""
    meta = torch.device("meta")
    barrier = NeuralBarrier(MLP(2, (8,), low=LOW, high=HIGH)).to(meta)
    x = torch.zeros(16, 2, device=meta)
    safe = torch.zeros(16, dtype=torch.bool, device=meta)

    class Rollouts(NamedTuple):
        x: torch.Tensor
        u: torch.Tensor
        u_nom: torch.Tensor

    rollouts = Rollouts(torch.zeros(4, 6, 3, device=meta), *torch.zeros(2, 4, 5, 2, device=meta))
    goal = torch.zeros(2, device=meta)
    truth = _truth().to(meta)
    with HostTraffic() as traffic:
        l_cls = classification_loss(barrier(x), safe, margin=0.1, temperature=0.1, balanced=True)
        loss = closed_loop_loss(rollouts, truth, goal=goal, goal_weight=1.0, index=(0, 2))
    assert not traffic.events, dict(traffic.events)
    assert l_cls.shape == () and loss.total.device.type == "meta"
