"""gradcheck (float64) of the Lie terms w.r.t. the state and the barrier's parameters."""

from __future__ import annotations

import pytest
import torch
from torch import nn
from torch.func import functional_call

from torchcbf.barriers import Ball, Ellipse, NeuralBarrier, rectify
from torchcbf.dynamics import AccelUnicycle, DoubleIntegrator, Unicycle

D = torch.float64


class _Terms(nn.Module):
    """``x -> (lfh, lgh, hess_trace, dhdt)`` of a barrier, so functional_call can swap params."""

    def __init__(self, barrier: nn.Module, dynamics: nn.Module) -> None:
        super().__init__()
        self.barrier = barrier
        self.dynamics = dynamics

    def forward(self, x: torch.Tensor, t: torch.Tensor | None = None):
        terms = self.barrier.lie(x, self.dynamics, t)
        out = [terms.lfh, terms.lgh, terms.dhdt]
        if terms.hess_trace is not None:
            out.append(terms.hess_trace)
        return tuple(out)


def _check(module: _Terms, x: torch.Tensor, params: dict[str, torch.Tensor], t=None) -> None:
    names = list(params)

    def fn(x, *values):
        return functional_call(module, dict(zip(names, values, strict=True)), (x, t))

    inputs = (x.requires_grad_(), *(p.detach().clone().requires_grad_() for p in params.values()))
    assert torch.autograd.gradcheck(fn, inputs, eps=1e-6, atol=1e-6, rtol=1e-5)


def _x(rows: int, n: int, seed: int = 0) -> torch.Tensor:
    return torch.randn(rows, n, generator=torch.Generator().manual_seed(seed), dtype=D)


def test_gradcheck_ball_unicycle_state_and_params(device: torch.device) -> None:
    sigma = torch.tensor([[0.3, 0.1], [0.0, 0.2], [0.5, -0.4]], dtype=D)
    m = _Terms(Ball([1.0, -2.0], 0.7, velocity=[0.3, 0.1]), Unicycle(sigma=sigma)).to(device, D)
    b = m.barrier
    _check(
        m,
        _x(3, 3).to(device),
        {"barrier.center": b.center, "barrier.radius": b.radius, "barrier.velocity": b.velocity},
        t=torch.tensor([0.1, 0.5, 1.0], dtype=D, device=device),
    )


def test_gradcheck_ellipse_with_state_dependent_sigma(device: torch.device) -> None:
    def sigma(x):
        return torch.stack([torch.sin(x) + 2.0, x**2 * 0.1], -1)  # [..., 4, 2]

    ellipse = Ellipse([1.0, 2.0], [0.5, 1.5], angle=0.4)
    m = _Terms(ellipse, AccelUnicycle(sigma=sigma)).to(device, D)
    b = m.barrier
    _check(
        m,
        _x(3, 4, 1).to(device),
        {"barrier.center": b.center, "barrier.axes": b.axes, "barrier.angle": b.angle},
    )


def test_gradcheck_neural_barrier_weights(device: torch.device) -> None:
    torch.manual_seed(0)  # noqa: NPY002 - test network weights only
    net = nn.Sequential(nn.Linear(4, 5), nn.Tanh(), nn.Linear(5, 1)).to(D)
    m = _Terms(
        NeuralBarrier(net, offset=Ball([0.0, 0.5], 0.3).to(D)), AccelUnicycle(sigma=0.28).to(D)
    ).to(device)
    params = {f"barrier.net.{k}": v for k, v in net.named_parameters()}
    params["barrier.offset.center"] = m.barrier.offset.center
    _check(m, _x(2, 4, 2).to(device), params)


@pytest.mark.parametrize("form", ["high_order", "exponential"])
def test_gradcheck_rectified_barrier(form: str, device: torch.device) -> None:
    dyn = DoubleIntegrator(sigma=0.2).to(D)
    ball = Ball([0.5, -0.3], 0.6).to(D)
    rect = rectify(ball, dyn, form=form, gains=[1.5])
    m = _Terms(rect, dyn).to(device)
    params = {"barrier.barrier.center": ball.center, "barrier.barrier.radius": ball.radius}
    gname = "barrier.gains" if form == "high_order" else "barrier.coefficients"
    params[gname] = getattr(rect, gname.split(".")[1])
    _check(m, _x(3, 4, 3).to(device), params)
