"""Transformed barriers phi(h): closed forms against autograd and hand formulas, the rectified
form against one autograd pass, gradcheck, and the argument errors."""

from __future__ import annotations

import math

import pytest
import torch

from torchcbf.barriers import Ball, Barrier, Ellipse, Transformed, rectify
from torchcbf.dynamics import AccelUnicycle, Unicycle


class _Opaque(Barrier):
    """The inner barrier without closed forms (autograd only)."""

    def __init__(self, inner: Barrier) -> None:
        super().__init__()
        self.inner = inner

    def forward(self, x, t=None):
        return self.inner(x, t)


def _tol(dtype):
    return {"atol": 1e-10, "rtol": 1e-9} if dtype == torch.float64 else {"atol": 2e-4, "rtol": 2e-4}


def _states(count, dim, seed, dtype):
    gen = torch.Generator().manual_seed(seed)
    return (3 * torch.rand(count, dim, generator=gen, dtype=torch.float64) - 1.5).to(dtype)


SHAPES = {
    "one": lambda: Ellipse([0.2, -0.3], [0.5, 1.5], angle=0.4),
    "stack": lambda: Ellipse([[1.0, 2.0], [-0.5, 0.5]], [[0.5, 1.5], [1.0, 0.25]]),
}


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
@pytest.mark.parametrize("form", ["radius", "exp"])
@pytest.mark.parametrize("shape", sorted(SHAPES))
def test_closed_forms_match_autograd_and_hand_formula(dtype, form, shape, device):
    dyn = Unicycle(sigma=0.3).to(device, dtype)
    inner = SHAPES[shape]().to(device, dtype)
    fn = Transformed(inner, form, rate=0.7).to(device, dtype)
    x = _states(13, 3, 0, dtype).to(device)
    ana = fn.lie(x, dyn, method="analytic")
    auto = fn.lie(x, dyn, method="autograd")
    for name in ana._fields:
        torch.testing.assert_close(getattr(ana, name), getattr(auto, name), **_tol(dtype))
    h = inner(x)
    want = torch.sqrt(h + 1) - 1 if form == "radius" else 1 - torch.exp(-0.7 * h)
    torch.testing.assert_close(ana.h, want, **_tol(dtype))
    assert bool(((ana.h >= 0) == (h >= 0)).all())  # the same safe set


@pytest.mark.parametrize("form", ["radius", "exp"])
def test_rectified_transform_uses_closed_forms_and_matches_autograd(form):
    dyn = AccelUnicycle(sigma=0.28).double()
    ell = Ellipse([[1.0, 2.0], [2.0, 5.0]], [[0.5, 1.5], [2.0, 0.25]]).double()
    fast = rectify(Transformed(ell, form, rate=0.1), dyn, "exponential", gains=[20.0])
    slow = rectify(Transformed(_Opaque(ell), form, rate=0.1), dyn, "exponential", gains=[20.0])
    assert fast.barrier.has_analytic and not slow.barrier.has_analytic
    x = _states(11, 4, 2, torch.float64) * torch.tensor([3.0, 3.0, 2.0, 3.0], dtype=torch.float64)
    a, b = fast.lie(x, dyn), slow.lie(x, dyn)
    for name in a._fields:
        torch.testing.assert_close(getattr(a, name), getattr(b, name))
    xg = x[:3].clone().requires_grad_()
    assert torch.autograd.gradcheck(lambda z: fast.lie(z, dyn).hess_trace, (xg,))


def test_radius_of_an_ellipse_is_the_normalised_distance():
    ell = Ellipse([0.0, 0.0], [2.0, 0.5]).double()
    x = torch.tensor([[4.0, 0.0], [0.0, 1.5], [3.0, 4.0]], dtype=torch.float64)
    r = Transformed(ell, "radius")(x)
    want = torch.tensor([1.0, 2.0, math.hypot(1.5, 8.0) - 1.0], dtype=torch.float64)
    torch.testing.assert_close(r, want)


def test_gradients_reach_the_inner_parameters():
    ball = Ball(torch.tensor([0.3, -0.2]), torch.tensor(1.0), learnable=True).double()
    dyn = Unicycle().double()
    fn = Transformed(ball, "radius")
    x = _states(5, 3, 3, torch.float64) + 2.0

    def of_center(c):
        ball.center.data = c
        return fn.lie(x, dyn, method="analytic").lgh

    c0 = ball.center.detach().clone().requires_grad_()
    terms = fn.lie(x, dyn, method="analytic")
    (g,) = torch.autograd.grad(terms.lgh.sum(), ball.center)
    assert torch.isfinite(g).all() and g.abs().sum() > 0
    eps = 1e-6
    for j in range(2):
        dc = torch.zeros(2, dtype=torch.float64)
        dc[j] = eps
        with torch.no_grad():
            up = of_center(c0.detach() + dc).sum()
            down = of_center(c0.detach() - dc).sum()
        torch.testing.assert_close(g[j], (up - down) / (2 * eps), atol=1e-6, rtol=1e-6)


def test_bad_arguments_are_named():
    ell = Ellipse([0.0, 0.0], [1.0, 1.0])
    with pytest.raises(ValueError, match="form"):
        Transformed(ell, "log")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="rate"):
        Transformed(ell, "exp", rate=0.0)
    with pytest.raises(TypeError, match="barrier"):
        Transformed(lambda x: x, "exp")  # type: ignore[arg-type]
