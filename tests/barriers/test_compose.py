"""Elementwise intersections and unions: values against a loop over the outputs, closed-form
Lie terms against autograd (float32 and float64), gradcheck, errors, and the filter seam."""

from __future__ import annotations

import pytest
import torch
from torch import Tensor

from torchcbf.barriers import Ball, Ellipse, Intersection, Scaled, Transformed, Union, rectify
from torchcbf.dynamics import AccelUnicycle, SingleIntegrator
from torchcbf.filters import RiskAware, SafetyFilter

CENTERS = [[1.0, 2.0], [3.0, 2.0], [-1.0, 1.0]]
AXES = [[0.5, 1.5], [0.75, 2.0], [1.0, 0.75]]


def _children(k: float = 20.0) -> tuple[AccelUnicycle, list]:
    """The rectified radius form of three ellipses and ``k`` times the radius form."""
    model = AccelUnicycle(sigma=0.28)
    radius = Transformed(Ellipse(CENTERS, AXES, index=(0, 1)), "radius")
    return model, [rectify(radius, model, "exponential", [k]), Scaled(radius, k)]


def _states(rows: int, dtype: torch.dtype, seed: int = 0) -> Tensor:
    g = torch.Generator().manual_seed(seed)
    x = torch.rand(rows, 4, generator=g, dtype=torch.float64)
    lo = torch.tensor([-2.5, -2.0, -0.5, -3.1], dtype=torch.float64)
    hi = torch.tensor([4.5, 4.5, 6.0, 3.1], dtype=torch.float64)
    return (lo + (hi - lo) * x).to(dtype)


@pytest.mark.parametrize("cls", [Intersection, Union])
@pytest.mark.parametrize("smooth", [True, False])
def test_elementwise_value_is_a_reduction_per_output(cls, smooth: bool) -> None:
    _, children = _children()
    x = _states(64, torch.float64)
    b = cls(*children, smooth=smooth, temperature=0.7, elementwise=True).double()
    h = b(x)
    assert h.shape == (64, 3)
    for j in range(3):  # output j: the reduction of the children's outputs j alone
        cols = torch.stack([c.double()(x)[:, j] for c in children], -1)
        if smooth:
            sign = -1.0 if cls is Intersection else 1.0
            ref = sign * 0.7 * torch.log(torch.exp(sign * cols / 0.7).sum(-1))
        else:
            ref = cols.amin(-1) if cls is Intersection else cols.amax(-1)
        torch.testing.assert_close(h[:, j], ref)


def test_smooth_elementwise_intersection_lies_inside_every_child() -> None:
    _, children = _children()
    x = _states(256, torch.float64, seed=1)
    h = Intersection(*children, smooth=True, temperature=0.5, elementwise=True).double()(x)
    for c in children:
        assert bool((h <= c.double()(x) + 1e-12).all())
    # so its safe set lies inside each child's: inside the obstacle-free set of the radius form
    assert bool((children[1].double()(x)[h >= 0] >= 0).all())


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32], ids=["float64", "float32"])
@pytest.mark.parametrize("cls", [Intersection, Union])
@pytest.mark.parametrize("smooth", [True, False])
def test_elementwise_closed_forms_match_autograd(cls, smooth: bool, dtype: torch.dtype) -> None:
    model, children = _children()
    b = cls(*children, smooth=smooth, temperature=0.5, elementwise=True).to(dtype)
    model = model.to(dtype)
    assert b.has_analytic
    x = _states(48, dtype, seed=2)
    fast = b.lie(x, model, method="analytic")
    ref = b.lie(x, model, method="autograd")
    tol = {"rtol": 1e-4, "atol": 2e-3} if dtype == torch.float32 else {}
    for name in ("h", "lfh", "lgh", "dhdt", "hess_trace", "dhdx"):
        torch.testing.assert_close(getattr(fast, name), getattr(ref, name), **tol, msg=name)


def test_elementwise_scalar_children_give_a_scalar_barrier() -> None:
    model = AccelUnicycle(sigma=0.28).double()
    b = Intersection(
        Ball([0.0, 0.0], 1.0, index=(0, 1)),
        Ball([1.0, 0.5], 0.5, index=(0, 1)),
        smooth=True,
        temperature=0.3,
        elementwise=True,
    ).double()
    x = _states(16, torch.float64, seed=3)
    whole = Intersection(*b.stack.barriers, smooth=True, temperature=0.3).double()
    torch.testing.assert_close(b(x), whole(x))
    fast = b.lie(x, model, method="analytic")
    ref = b.lie(x, model, method="autograd")
    assert fast.h.shape == (16,) and fast.lgh.shape == (16, 2)
    for name in ("h", "lfh", "lgh", "hess_trace"):
        torch.testing.assert_close(getattr(fast, name), getattr(ref, name), msg=name)


def test_elementwise_closed_forms_gradcheck() -> None:
    model, children = _children()
    b = Intersection(*children, smooth=True, temperature=0.5, elementwise=True).double()
    model = model.double()

    def terms(x: Tensor) -> tuple[Tensor, ...]:
        t = b.lie(x, model, method="analytic")
        return t.h, t.lfh, t.lgh, t.hess_trace

    x = _states(4, torch.float64, seed=4).requires_grad_()
    assert torch.autograd.gradcheck(terms, (x,), eps=1e-6, atol=1e-5, rtol=1e-4)


def test_elementwise_needs_one_output_count() -> None:
    three = Ellipse(CENTERS, AXES, index=(0, 1))
    two = Ellipse(CENTERS[:2], AXES[:2], index=(0, 1))
    b = Intersection(three, two, elementwise=True)
    with pytest.raises(ValueError, match=r"one output count, got \[3, 2\]"):
        b(torch.zeros(2, 4))


def test_scales_need_one_output_each() -> None:
    """``[k]`` scales on a barrier of one output (or of another count) are a ValueError on
    every path, also where the batch size equals ``k`` (broadcast, row ``i`` would be
    scaled by ``scale[i]``); a scalar or ``[1]`` scale, or ``k`` scales on ``k`` outputs, work."""
    from torchcbf.dynamics import SingleIntegrator

    model = SingleIntegrator(2).double()
    x = torch.tensor([[2.0, 0.0], [2.0, 0.0]], dtype=torch.float64)
    one = Ball([0.0, 0.0], 1.0).double()
    two = Ball([[0.0, 0.0], [1.0, 0.0]], 1.0).double()
    for inner in (one, Ball([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0]], 1.0).double()):
        bad = Scaled(inner, [1.0, 100.0])
        assert bad.quadric() is None
        with pytest.raises(ValueError, match="Scaled has 2 scales, one per output, but Ball"):
            bad(x)
        for method in ("analytic", "autograd"):
            with pytest.raises(ValueError, match="Scaled has 2 scales"):
                bad.lie(x, model, method=method)
        with pytest.raises(ValueError, match="Scaled has 2 scales"):
            SafetyFilter(model, [bad])(x, torch.zeros(2, 2, dtype=torch.float64))
    torch.testing.assert_close(Scaled(one, [3.0])(x), 3.0 * one(x))
    torch.testing.assert_close(Scaled(two, [3.0, 5.0])(x), torch.tensor([3.0, 5.0]) * two(x))


class _Rewritten(Intersection):
    """The same function written by a user: ``forward`` overridden, so the closed forms of
    :class:`Intersection` are not trusted and autograd answers."""

    def forward(self, x: Tensor, t: Tensor | float | None = None) -> Tensor:
        cols = torch.stack([c(x, t) for c in self.stack.barriers], -1)
        return -self.temperature * torch.logsumexp(-cols / self.temperature, -1)


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32], ids=["float64", "float32"])
def test_risk_aware_filter_on_the_closed_forms_matches_autograd(dtype: torch.dtype) -> None:
    model, children = _children()
    fast = Intersection(*children, smooth=True, temperature=0.5, elementwise=True)
    slow = _Rewritten(*children, smooth=True, temperature=0.5, elementwise=True)
    assert fast.has_analytic and not slow.has_analytic
    eta = torch.tensor([12.0, 8.0, 8.0], dtype=torch.float64)
    R = torch.diag(torch.tensor([1.0, 1e-3], dtype=torch.float64))
    filters = [
        SafetyFilter(model, barriers=b, mode=RiskAware(rho=0.05, horizon=0.1, eta=eta), R=R).to(
            dtype
        )
        for b in (fast, slow)
    ]
    x = _states(32, dtype, seed=5)
    u_nom = 10 * torch.randn(32, 2, generator=torch.Generator().manual_seed(6)).to(dtype)
    a, b = (f(x, u_nom) for f in filters)
    tol = {"rtol": 1e-4, "atol": 1e-3} if dtype == torch.float32 else {}
    torch.testing.assert_close(a.h, b.h, **tol)
    torch.testing.assert_close(a.u, b.u, **tol)
    torch.testing.assert_close(a.status, b.status)


def test_one_scale_in_a_list_scales_a_one_output_barrier_as_a_number() -> None:
    ball = Ball([1.0, 0.0], 0.5)
    model = AccelUnicycle()
    x = torch.tensor([0.2, 0.3, 0.1, 0.5])
    for scale in (2.0, [2.0]):
        s = Scaled(ball, scale)
        assert s(x[:2]).shape == ()
        for method in ("autograd", "analytic"):
            assert s.lie(x[:2], SingleIntegrator(2), method=method).h.shape == ()
    assert Scaled(ball, [2.0]).lie(x, model).lgh.shape == (2,)


def test_smooth_temperatures_and_rates_are_finite_positive_numbers() -> None:
    a, b = Ball([0.0, 0.0], 1.0), Ball([3.0, 0.0], 1.0)
    for cls in (Intersection, Union):
        for bad in (float("inf"), 0.0, -1.0):
            with pytest.raises(ValueError, match="temperature must be a finite number > 0"):
                cls(a, b, smooth=True, temperature=bad)
        with pytest.raises(TypeError, match="temperature must be a Python number"):
            cls(a, b, smooth=True, temperature=torch.tensor(0.1, requires_grad=True))
    with pytest.raises(ValueError, match="rate must be a finite number > 0"):
        Transformed(a, "exp", rate=float("inf"))
