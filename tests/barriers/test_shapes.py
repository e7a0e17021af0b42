"""Shape values, composition, neural barriers, Lyapunov functions and input validation."""

from __future__ import annotations

import math

import pytest
import torch
from torch import nn

from torchcbf.barriers import (
    Ball,
    BarrierStack,
    Box,
    Ellipse,
    HalfSpace,
    Intersection,
    LieTerms,
    NeuralBarrier,
    QuadraticLyapunov,
    Union,
)
from torchcbf.dynamics import AccelUnicycle, DoubleIntegrator, SingleIntegrator


def _x(rows: int, n: int, dtype: torch.dtype, seed: int = 0) -> torch.Tensor:
    return 2 * torch.randn(rows, n, generator=torch.Generator().manual_seed(seed), dtype=dtype)


def test_shape_values(dtype):
    x = _x(100, 4, dtype)
    ball = Ball([1.0, 2.0], 0.5, index=(2, 3)).to(dtype)
    ref = (x[:, 2] - 1) ** 2 + (x[:, 3] - 2) ** 2 - ball.radius**2
    torch.testing.assert_close(ball(x), ref)
    torch.testing.assert_close(Ball([1.0, 2.0], 0.5, index=(2, 3), keep_in=True).to(dtype)(x), -ref)
    hs = HalfSpace([1.0, -2.0, 0.0, 0.5], 0.3).to(dtype)
    torch.testing.assert_close(hs(x), 0.3 - (x[:, 0] - 2 * x[:, 1] + 0.5 * x[:, 3]))
    box = Box([-1.0, -2.0], [1.0, 3.0], index=(0, 1)).to(dtype)
    faces = torch.stack([x[:, 0] + 1, x[:, 1] + 2, 1 - x[:, 0], 3 - x[:, 1]], -1)
    torch.testing.assert_close(box(x), faces.min(-1).values)
    smooth = Box([-1.0, -2.0], [1.0, 3.0], index=(0, 1), smooth=True, temperature=0.05).to(dtype)
    assert bool((smooth(x) <= box(x) + 1e-6).all())
    assert bool((smooth(x) >= box(x) - 0.05 * math.log(4) - 1e-6).all())
    # batched balls: [k, d] centres -> h [..., k]
    many = Ball([[0.0, 0.0], [1.0, 1.0]], [1.0, 2.0]).to(dtype)
    torch.testing.assert_close(many(x)[:, 1], (x[:, 0] - 1) ** 2 + (x[:, 1] - 1) ** 2 - 4)
    # polytope as a stack of half-spaces [k, d]
    poly = HalfSpace([[1.0, 0.0], [0.0, 1.0]], [1.0, 2.0], index=(0, 1)).to(dtype)
    torch.testing.assert_close(poly(x), torch.stack([1 - x[:, 0], 2 - x[:, 1]], -1))


def test_ellipse_scenario_b_form(dtype):
    x = _x(50, 4, dtype, seed=1)
    ell = Ellipse([3.0, 2.0], [0.75, 2.0]).to(dtype)
    torch.testing.assert_close(ell(x), ((x[:, 0] - 3) / 0.75) ** 2 + ((x[:, 1] - 2) / 2.0) ** 2 - 1)
    # a rotation by 90 degrees swaps the axes
    rot = Ellipse([3.0, 2.0], [2.0, 0.75], angle=math.pi / 2).to(dtype)
    torch.testing.assert_close(
        rot(x), ell(x), atol=1e-5 if dtype == torch.float32 else 1e-12, rtol=1e-5
    )


@pytest.mark.parametrize("smooth", [False, True])
@pytest.mark.parametrize("kind", [Intersection, Union])
def test_composition_values_and_analytic(dtype, kind, smooth, device):
    parts = [
        Ball([0.0, 0.0], 1.0),
        Ellipse([1.0, 2.0], [0.5, 1.5]),
        Ball([[2.0, 0.0], [0.0, 3.0]], [0.5, 0.7]),
    ]
    comp = kind(*parts, smooth=smooth, temperature=0.3).to(device, dtype)
    dyn = AccelUnicycle(sigma=torch.tensor([0.28, 0.1, 0.2, 0.3])).to(device, dtype)
    x = _x(300, 4, dtype, seed=2).to(device)
    stacked = BarrierStack(*parts).to(device, dtype)(x)
    if smooth:
        sign = -1.0 if kind is Intersection else 1.0
        ref = sign * 0.3 * torch.logsumexp(sign * stacked / 0.3, -1)
    else:
        ref = stacked.min(-1).values if kind is Intersection else stacked.max(-1).values
    torch.testing.assert_close(comp(x), ref)
    a = comp.lie(x, dyn, method="analytic")
    b = comp.lie(x, dyn)
    tol = {"atol": 1e-9, "rtol": 1e-9} if dtype == torch.float64 else {"atol": 1e-3, "rtol": 1e-4}
    for name in LieTerms._fields:
        torch.testing.assert_close(getattr(a, name), getattr(b, name).detach(), **tol, msg=name)


@pytest.mark.parametrize("smooth", [False, True])
def test_box_analytic_matches_autograd(dtype, smooth, device):
    box = Box([-1.0, -2.0], [1.0, 3.0], index=(0, 1), smooth=smooth, temperature=0.2)
    box = box.to(device, dtype)
    dyn = DoubleIntegrator(sigma=0.3).to(device, dtype)
    x = _x(200, 4, dtype, seed=3).to(device)
    a, b = box.lie(x, dyn, method="analytic"), box.lie(x, dyn)
    for name in LieTerms._fields:
        torch.testing.assert_close(getattr(a, name), getattr(b, name).detach(), msg=name)


def test_neural_barrier_offset_and_outputs(dtype):
    torch.manual_seed(0)  # noqa: NPY002 - test network weights only
    net = nn.Sequential(nn.Linear(2, 8), nn.Tanh(), nn.Linear(8, 1)).to(dtype)
    ball = Ball([0.0, 1.0], 0.5).to(dtype)
    nb = NeuralBarrier(net, offset=ball, scale=0.5)
    x = _x(20, 2, dtype, seed=4)
    torch.testing.assert_close(nb(x), 0.5 * net(x).squeeze(-1) + ball(x))
    multi = NeuralBarrier(nn.Linear(2, 3).to(dtype))
    assert multi(x).shape == (20, 3)
    terms = multi.lie(x, SingleIntegrator().to(dtype))
    torch.testing.assert_close(
        terms.lgh, multi.net.weight.expand(20, 3, 2).detach(), check_stride=False
    )
    timed = NeuralBarrier(nn.Linear(3, 1).to(dtype), time_input=True)
    assert timed.time_varying
    torch.testing.assert_close(
        timed.lie(x, SingleIntegrator().to(dtype), 2.0).dhdt,
        timed.net.weight[0, 2].expand(20).detach(),
    )
    with pytest.raises(ValueError, match="offset"):
        NeuralBarrier(nn.Linear(2, 3).to(dtype), offset=ball)(x)


def test_quadratic_lyapunov(dtype):
    P = torch.tensor([[2.0, 0.5], [0.5, 1.0]], dtype=dtype)
    V = QuadraticLyapunov([1.0, -1.0], P, index=(0, 1)).to(dtype)
    x = _x(30, 4, dtype, seed=5)
    e = x[:, :2] - V.goal
    torch.testing.assert_close(V(x), torch.einsum("bi,ij,bj->b", e, P, e))
    terms = V.lie(x, DoubleIntegrator().to(dtype))
    torch.testing.assert_close(terms.lfh, (2 * e @ P * x[:, 2:]).sum(-1))
    assert float(V(torch.tensor([1.0, -1.0, 3.0, 3.0], dtype=dtype))) == 0.0
    with pytest.raises(ValueError, match="positive definite"):
        QuadraticLyapunov([0.0, 0.0], torch.tensor([[1.0, 0.0], [0.0, -1.0]]))


def test_learnable_and_to(dtype):
    ball = Ball([1.0, 2.0], 0.5, learnable=True)
    assert {n for n, _ in ball.named_parameters()} == {"center", "radius"}
    given = nn.Parameter(torch.tensor([0.0, 1.0]))
    assert Ball(given, 0.3).center is given
    assert [n for n, _ in Ball([1.0, 2.0], 0.5).named_buffers()][:2] == ["center", "radius"]
    ball = ball.to(dtype)
    assert ball.center.dtype == dtype


def test_bad_input_raises():
    dyn = SingleIntegrator()
    ball = Ball([0.0, 0.0], 1.0, index=(0, 3))
    with pytest.raises(ValueError, match="index"):
        ball(torch.zeros(5, 2))
    with pytest.raises(ValueError, match="index"):
        Ball([0.0, 0.0], 1.0, index=(0, 3), state_dim=2)
    with pytest.raises(ValueError, match="radius"):
        Ball([0.0, 0.0], -1.0)
    with pytest.raises(ValueError, match="axes"):
        Ellipse([0.0, 0.0], [1.0, 0.0])
    with pytest.raises(ValueError, match=r"x must have shape \[\.\.\., 2\]"):
        Ball([0.0, 0.0], 1.0).lie(torch.zeros(5, 3), dyn)
    with pytest.raises(ValueError, match="x must have shape"):
        HalfSpace([1.0, 0.0], 1.0)(torch.zeros(5, 3))
    with pytest.raises(ValueError, match="low"):
        Box([1.0, 0.0], [0.0, 1.0])
    with pytest.raises(ValueError, match="center"):
        Ball(torch.zeros(2, 2, 2), 1.0)
    with pytest.raises(ValueError, match="velocity"):
        Ball([0.0, 0.0], 1.0, velocity=[1.0, 2.0, 3.0])
    with pytest.raises(ValueError, match="t must broadcast"):
        Ball([0.0, 0.0], 1.0, velocity=[1.0, 0.0]).lie(torch.zeros(5, 2), dyn, torch.zeros(3))
    with pytest.raises(ValueError, match="method"):
        Ball([0.0, 0.0], 1.0).lie(torch.zeros(5, 2), dyn, method="fd")
    with pytest.raises(ValueError, match="closed-form"):
        NeuralBarrier(nn.Linear(2, 1)).lie(torch.zeros(5, 2), dyn, method="analytic")


def test_learnable_shapes_with_a_velocity_or_an_angle() -> None:
    ball = Ball([0.0, 0.0], 1.0, velocity=[0.5, 0.0], learnable=True)
    assert {n for n, _ in ball.named_parameters()} == {"center", "radius", "velocity"}
    x = torch.tensor([[2.0, 0.0]])
    ball(x, torch.tensor([1.0])).sum().backward()
    assert ball.velocity.grad is not None and float(ball.velocity.grad[0]) != 0.0
    ell = Ellipse([0.0, 0.0], [1.0, 0.5], angle=0.3, learnable=True)
    assert {n for n, _ in ell.named_parameters()} == {"center", "axes", "angle"}
    given = Ellipse([0.0, 0.0], [1.0, 0.5], angle=nn.Parameter(torch.tensor(0.3)))
    assert [n for n, _ in given.named_parameters()] == ["angle"]


def test_state_indices_must_be_distinct_ints() -> None:
    """A repeated component: the closed forms kept one copy of it, autograd both."""
    for make in (
        lambda index: Ball([0.0, 0.0], 1.0, index=index),
        lambda index: Ellipse([0.0, 0.0], [1.0, 0.5], index=index),
        lambda index: HalfSpace([1.0, 1.0], 0.0, index=index),
        lambda index: QuadraticLyapunov(torch.zeros(2), index=index),
    ):
        with pytest.raises(ValueError, match=r"index=\(0, 0\) names a component twice"):
            make((0, 0))
        with pytest.raises(TypeError, match="index must hold ints"):
            make((0.7, 1.9))
    import numpy as np

    assert Ball([0.0, 0.0], 1.0, index=np.array([2, 0])).index == (2, 0)
    assert Ball([0.0, 0.0], 1.0, index=[torch.tensor(2), np.int64(0)]).index == (2, 0)
    assert Ball([0.0, 0.0], 1.0, index=range(1, 3)).index == (1, 2)
    with pytest.raises(TypeError, match="index must hold ints"):
        Ball([0.0, 0.0], 1.0, index=(True, False))
    with pytest.raises(TypeError, match=r"index must be a sequence of ints \(in order\)"):
        Ball([0.0, 0.0], 1.0, index={1, 0})


@pytest.mark.parametrize("method", ["autograd", "analytic"])
def test_constants_replaced_by_another_count_are_followed(method) -> None:
    """Assigning ``k'`` centres (or normals) in place of ``k``: every part is evaluated."""
    dyn = SingleIntegrator()
    x = _x(4, 2, torch.float64)
    three = torch.tensor([[1.0, 0.0], [0.0, 1.0], [-1.0, 0.5]], dtype=torch.float64)
    cases = [
        (Ball(three[:2], 0.5), {"center": three}, Ball(three, 0.5)),
        (Ball(three, 0.5), {"center": three[:1]}, Ball(three[:1], 0.5)),
        (
            Ellipse(three[:2], torch.ones(2, 2)),
            {"center": three, "axes": torch.ones(3, 2)},
            Ellipse(three, torch.ones(3, 2)),
        ),
        (HalfSpace(three[:2], 0.5), {"a": three}, HalfSpace(three, 0.5)),
    ]
    for shape, new, fresh in cases:
        shape.to(torch.float64)
        for name, value in new.items():
            setattr(shape, name, value)
        assert shape.num == fresh.num
        got, want = shape.lie(x, dyn, method=method), fresh.to(torch.float64).lie(x, dyn)
        for a, b in zip(got, want, strict=True):
            if isinstance(a, torch.Tensor):
                torch.testing.assert_close(a, b)


def test_constants_of_different_counts_are_refused_on_every_path() -> None:
    ball = Ball(torch.zeros(2, 2), torch.tensor([0.5, 0.4]))
    x = torch.zeros(1, 2)
    for center, count in ((torch.zeros(3, 2), "the 3 shapes"), (torch.ones(2), "the one shape")):
        ball.center = center
        for call in (
            lambda: ball(x),
            lambda: ball.lie(x, SingleIntegrator(), method="autograd"),
            lambda: ball.lie(x, SingleIntegrator(), method="analytic"),
        ):
            with pytest.raises(ValueError, match=rf"Ball.radius \(2,\) does not match {count}"):
                call()
    assert "k=2" in repr(ball.__class__(torch.zeros(2, 2), 0.5))
    # a per-shape vector left for one shape, or a scalar with an extra axis: refused too
    ellipse = Ellipse(torch.zeros(2), torch.ones(2))
    ellipse.center = torch.zeros(3, 2)
    with pytest.raises(ValueError, match=r"Ellipse.axes \(2,\) does not match the 3 shapes"):
        ellipse.lie(x, SingleIntegrator(), method="autograd")
    assert "k=3" in repr(ellipse)
    moving = Ball(torch.zeros(2, 2), 0.5, velocity=torch.ones(2, 2))
    moving.velocity = torch.ones(2)
    with pytest.raises(ValueError, match=r"Ball.velocity \(2,\) does not match the 2 shapes"):
        moving(x, 0.0)
    wide = Ball(torch.zeros(2, 2), torch.ones(2))
    wide.radius = torch.ones(2, 1)
    with pytest.raises(ValueError, match=r"Ball.radius \(2, 1\) does not match"):
        wide(x)


@pytest.mark.parametrize("method", ["analytic", "autograd"])
def test_a_batched_shape_with_no_shape_has_empty_terms_and_filters_nothing(method) -> None:
    """No obstacle in view this tick (``center [0, 2]``): empty terms on every path, and a
    filter holding it beside another barrier answers as the other alone."""
    from torchcbf.filters import SafetyFilter

    f64 = torch.float64
    model = SingleIntegrator(2)
    x = torch.tensor([[0.5, 1.0], [0.0, 0.2]], dtype=f64)
    empties = (
        Ball(torch.zeros(0, 2, dtype=f64), torch.zeros(0, dtype=f64)),
        Ellipse(torch.zeros(0, 2, dtype=f64), torch.ones(0, 2, dtype=f64)),
        HalfSpace(torch.zeros(0, 2, dtype=f64), torch.zeros(0, dtype=f64)),
    )
    for empty in empties:
        terms = empty.lie(x, model, method=method)
        assert terms.h.shape == (2, 0) and terms.lgh.shape == (2, 0, 2)
    ball = Ball([1.0, 1.0], 0.3).double()
    u = torch.tensor([[1.0, 1.0], [1.0, 1.0]], dtype=f64)
    for backend in ("auto", "torch"):
        got = SafetyFilter(model, [empties[0], ball], alpha=1.0, backend=backend)(x, u)
        want = SafetyFilter(model, [ball], alpha=1.0, backend=backend)(x, u)
        torch.testing.assert_close(got.u, want.u)
