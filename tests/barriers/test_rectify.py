"""Relative-degree detection, HOCBF/ECBF rectification and closed-loop safety."""

from __future__ import annotations

import pytest
import torch
from torch import nn

from torchcbf.barriers import (
    Ball,
    BarrierStack,
    Ellipse,
    ExponentialBarrier,
    HalfSpace,
    HighOrderBarrier,
    coefficients_from_poles,
    find_relative_degree,
    rectify,
)
from torchcbf.dynamics import AccelUnicycle, DoubleIntegrator, SingleIntegrator
from torchcbf.dynamics.base import ControlAffine
from torchcbf.integrators import rk4

D = torch.float64


def test_relative_degree_detection():
    ball = Ball([0.5, 0.5], 1.0)
    assert find_relative_degree(ball, SingleIntegrator()) == 1
    assert find_relative_degree(ball, DoubleIntegrator()) == 2
    assert find_relative_degree(ball, AccelUnicycle()) == 2
    assert (
        find_relative_degree(Ball([0.0, 0.0, 1.0], 1.0, index=(0, 1, 2)), DoubleIntegrator(3)) == 2
    )
    stack = BarrierStack(Ellipse([[1.0, 2.0], [3.0, 2.0]], [[0.5, 1.5], [0.75, 2.0]]), ball)
    assert find_relative_degree(stack, AccelUnicycle()) == 2
    assert rectify(ball, SingleIntegrator()) is ball


@pytest.mark.parametrize("unit", [1.0, 1e-7, 1e-12, 1e7])
def test_relative_degree_does_not_depend_on_units(unit: float) -> None:
    """A barrier or an input matrix in small or large units has the same relative degree."""
    assert find_relative_degree(HalfSpace([unit, 0.0], 0.0), SingleIntegrator()) == 1
    assert find_relative_degree(HalfSpace([unit, 0.0], 0.0, (0, 1)), DoubleIntegrator()) == 2
    assert find_relative_degree(Ball([0.5, 0.5], 1.0), _Slow(unit)) == 1


class _Slow(ControlAffine):
    """x' = unit * u."""

    def __init__(self, unit: float) -> None:
        super().__init__(2, 2)
        self.unit = unit

    def f(self, x):
        return torch.zeros_like(x)

    def g(self, x):
        return self.unit * torch.eye(2, dtype=x.dtype).expand(*x.shape[:-1], 2, 2)


class _Chain3(ControlAffine):
    """x1' = x2, x2' = x3, x3' = u (each rate times ``rate``: another time unit): position
    has relative degree 3."""

    def __init__(self, rate: float = 1.0) -> None:
        super().__init__(3, 1)
        self.rate = rate

    def f(self, x):
        return self.rate * torch.stack([x[..., 1], x[..., 2], torch.zeros_like(x[..., 0])], -1)

    def g(self, x):
        g = x.new_zeros(*x.shape[:-1], 3, 1)
        g[..., 2, 0] = self.rate
        return g


@pytest.mark.parametrize("unit", [1.0, 1e-3, 1e5, 1e7])
def test_relative_degree_does_not_depend_on_a_components_or_times_unit(unit: float) -> None:
    # h = a p + v on p' = v, v' = u: degree 1 whatever the unit of p
    assert find_relative_degree(HalfSpace([unit, 1.0], 0.0, (0, 1)), DoubleIntegrator(1)) == 1
    if unit <= 1.0:  # rates in milliseconds
        position = HalfSpace([1.0, 0.0, 0.0], 0.0, (0, 1, 2))
        assert find_relative_degree(position, _Chain3(unit)) == 3


class _Uncontrolled(ControlAffine):
    """x1' = x1 (no input), x2' = u: x1 never sees the control."""

    def __init__(self) -> None:
        super().__init__(2, 1)

    def f(self, x):
        return torch.stack([x[..., 0], torch.zeros_like(x[..., 0])], -1)

    def g(self, x):
        g = x.new_zeros(*x.shape[:-1], 2, 1)
        g[..., 1, 0] = 1.0
        return g


def test_relative_degree_three_and_errors():
    h = HalfSpace([-1.0], 0.0, index=(0,))  # h = x1 >= 0
    assert find_relative_degree(h, _Chain3()) == 3
    with pytest.raises(ValueError, match="does not appear"):
        rectify(h, _Uncontrolled())
    mixed = BarrierStack(Ball([0.0, 0.0], 1.0), Ball([0.0, 0.0], 1.0, index=(2, 3)))
    with pytest.raises(ValueError, match="different relative degrees"):
        find_relative_degree(mixed, DoubleIntegrator())
    with pytest.raises(ValueError, match="Hurwitz"):
        rectify(Ball([0.0, 0.0], 1.0), DoubleIntegrator(), "exponential", gains=[-1.0])
    with pytest.raises(ValueError, match="poles"):
        rectify(Ball([0.0, 0.0], 1.0), DoubleIntegrator(), "exponential", poles=[1.0])
    with pytest.raises(ValueError, match="gains"):
        rectify(Ball([0.0, 0.0], 1.0), DoubleIntegrator(), gains=[0.0])
    with pytest.raises(ValueError, match="relative_degree"):
        rectify(Ball([0.0, 0.0], 1.0), DoubleIntegrator(), relative_degree=0)
    ball = Ball([0.0, 0.0], 1.0)
    with pytest.raises(ValueError, match=r"gains must hold r - 1 = 1 values.*got 2"):
        rectify(ball, DoubleIntegrator(), "exponential", gains=[1.0, 2.0])
    with pytest.raises(ValueError, match="poles= or gains=, not both"):
        rectify(ball, DoubleIntegrator(), "exponential", gains=[1.0], poles=[-1.0])
    with pytest.raises(ValueError, match="got form='high_order'"):
        rectify(ball, DoubleIntegrator(), "high_order", poles=[-1.0])


def test_poles_to_coefficients():
    torch.testing.assert_close(coefficients_from_poles([-2.0, -3.0]), torch.tensor([6.0, 5.0]))
    torch.testing.assert_close(coefficients_from_poles([-1.5]), torch.tensor([1.5]))


def test_rectified_values_match_hand_formulas(dtype):
    dyn = DoubleIntegrator().to(dtype)
    ball = Ball([0.5, -0.3], 0.6).to(dtype)
    x = torch.randn(500, 4, generator=torch.Generator().manual_seed(0), dtype=dtype)
    p, v = x[:, :2] - ball.center, x[:, 2:]
    h = (p**2).sum(-1) - ball.radius**2
    hdot = 2 * (p * v).sum(-1)
    hddot_drift = 2 * (v**2).sum(-1)
    # HOCBF, r = 2, alpha_1 = 1.5: psi_1 = hdot + 1.5 h;  L_g psi_1 = 2 p
    hocbf = rectify(ball, dyn, gains=1.5)
    assert isinstance(hocbf, HighOrderBarrier) and hocbf.relative_degree == 2
    terms = hocbf.lie(x, dyn)
    tol = {"atol": 1e-10, "rtol": 1e-10} if dtype == D else {"atol": 1e-4, "rtol": 1e-4}
    torch.testing.assert_close(terms.h.detach(), hdot + 1.5 * h, **tol)
    torch.testing.assert_close(terms.lfh.detach(), hddot_drift + 1.5 * hdot, **tol)
    torch.testing.assert_close(terms.lgh.detach(), 2 * p, **tol)
    # ECBF with poles (-1, ...) gives the same function as an HOCBF with the same gains
    ecbf = rectify(ball, dyn, "exponential", poles=[-1.5])
    assert isinstance(ecbf, ExponentialBarrier)
    torch.testing.assert_close(ecbf(x), hocbf(x), **tol)


def test_third_order_ecbf_equals_hocbf():
    h = HalfSpace([-1.0], 0.0, index=(0,)).to(D)
    dyn = _Chain3().to(D)
    ecbf = rectify(h, dyn, "exponential", poles=[-1.0, -2.0])
    hocbf = rectify(h, dyn, "high_order", gains=[1.0, 2.0])
    x = torch.randn(50, 3, generator=torch.Generator().manual_seed(1), dtype=D)
    # (s + 1)(s + 2) = s^2 + 3 s + 2: h_e = x3 + 3 x2 + 2 x1
    ref = x[:, 2] + 3 * x[:, 1] + 2 * x[:, 0]
    torch.testing.assert_close(ecbf(x), ref)
    torch.testing.assert_close(hocbf(x), ref)
    torch.testing.assert_close(ecbf.lie(x, dyn).lgh, torch.ones(50, 1, dtype=D))


def test_scenario_b_rectified_ellipse_hess_trace():
    dyn = AccelUnicycle(sigma=0.28).to(D)
    ell = Ellipse([[1.0, 2.0], [3.0, 2.0]], [[0.5, 1.5], [0.75, 2.0]]).to(D)
    k0 = 2.0
    rect = rectify(ell, dyn, "exponential", gains=[k0])
    x = 2 * torch.randn(300, 4, generator=torch.Generator().manual_seed(2), dtype=D)
    terms = rect.lie(x, dyn)
    A, B = 1 / ell.axes[:, 0] ** 2, 1 / ell.axes[:, 1] ** 2
    dx = x[:, None, 0] - ell.center[:, 0]
    dy = x[:, None, 1] - ell.center[:, 1]
    v, th = x[:, None, 2], x[:, None, 3]
    h = A * dx**2 + B * dy**2 - 1
    lfh = 2 * A * dx * v * torch.cos(th) + 2 * B * dy * v * torch.sin(th)
    torch.testing.assert_close(terms.h, lfh + k0 * h)
    # Hessian of L_f h has trace -L_f h (the theta-theta entry); of h, 2A + 2B
    torch.testing.assert_close(terms.hess_trace, 0.28**2 * (-lfh + k0 * (2 * A + 2 * B)))
    # L_g h_e = (dh/dp . heading, v * dh/dp . heading-normal)
    lg_a = 2 * A * dx * torch.cos(th) + 2 * B * dy * torch.sin(th)
    lg_w = v * (-2 * A * dx * torch.sin(th) + 2 * B * dy * torch.cos(th))
    torch.testing.assert_close(terms.lgh, torch.stack([lg_a, lg_w], -1))


def test_rectified_differentiates_wrt_barrier_parameters():
    ball = Ball([0.5, -0.3], 0.6, learnable=True).to(D)
    dyn = DoubleIntegrator().to(D)
    rect = rectify(ball, dyn, "exponential")
    assert {n for n, _ in rect.named_parameters()} == {"barrier.center", "barrier.radius"}
    x = torch.randn(10, 4, generator=torch.Generator().manual_seed(3), dtype=D)
    rect.lie(x, dyn).lgh.sum().backward()
    # lgh = 2 (p - c): d/dc sum = -2 * rows per coordinate
    torch.testing.assert_close(ball.center.grad, torch.full((2,), -20.0, dtype=D))
    learn = rectify(ball, dyn, gains=nn.Parameter(torch.tensor([2.0], dtype=D)))
    assert "gains" in dict(learn.named_parameters())


def _filter(terms, u_nom: torch.Tensor, alpha: float) -> torch.Tensor:
    """Closed-form one-constraint CBF-QP: min |u - u_nom|^2 s.t. lfh + lgh u >= -alpha h."""
    lgh = terms.lgh
    viol = -(terms.lfh + (lgh * u_nom).sum(-1) + alpha * terms.h)
    scale = viol.clamp_min(0) / (lgh**2).sum(-1).clamp_min(1e-12)
    return u_nom + scale[..., None] * lgh


def _closed_loop(barrier, dyn, x0, goal, steps=500, dt=0.01, alpha=1.0, filtered=True):
    x = x0
    obstacle = _OBSTACLE.to(x0.dtype)
    h_min = obstacle(x)
    with torch.no_grad():
        for _ in range(steps):
            u = 2.0 * (goal - x[:, :2]) - 2.0 * x[:, 2:]
            if filtered:
                u = _filter(barrier.lie(x, dyn), u, alpha)
            x = rk4(dyn, x, u, dt)
            h_min = torch.minimum(h_min, obstacle(x))
    return h_min


_OBSTACLE = Ball([0.0, 0.0], 1.0)


@pytest.mark.parametrize(("form", "gain"), [("high_order", 1.0), ("exponential", 2.0)])
def test_closed_loop_double_integrator_stays_safe(form, gain):
    dyn = DoubleIntegrator().to(D)
    ball = _OBSTACLE.to(D)
    rect = rectify(ball, dyn, form, gains=[gain])
    gen = torch.Generator().manual_seed(4)
    B = 48
    ang = 2 * torch.pi * torch.rand(B, generator=gen, dtype=D)
    dist = 1.3 + 1.5 * torch.rand(B, generator=gen, dtype=D)
    dirn = torch.stack([torch.cos(ang), torch.sin(ang)], -1)
    p0 = dist[:, None] * dirn
    # safe initial velocity: towards the obstacle, below the psi_1 >= 0 bound
    speed = 0.8 * gain * (dist**2 - 1) / (2 * dist)
    tangent = torch.stack([-dirn[:, 1], dirn[:, 0]], -1)
    v0 = -speed[:, None] * dirn + 0.1 * tangent
    x0 = torch.cat([p0, v0], -1)
    assert bool((rect(x0) >= 0).all()) and bool((ball(x0) > 0).all())
    goal = -2.0 * p0  # straight through the obstacle
    h_min = _closed_loop(rect, dyn, x0, goal)
    assert float(h_min.min()) >= -1e-6
    assert float(h_min.min()) < 0.3  # the filter was active: trajectories came close
    unfiltered = _closed_loop(rect, dyn, x0, goal, filtered=False)
    assert bool((unfiltered < 0).any())  # without it, they collide


def test_an_output_that_does_not_depend_on_the_state_is_named_at_once() -> None:
    """A constant output (a frame that never moves) has no relative degree: rectify and
    the filter say so at once, naming it, instead of differentiating ever deeper (each
    level nests the last one's autograd) or advising a rectification."""
    from torchcbf.barriers import Barrier, BarrierStack
    from torchcbf.filters import SafetyFilter

    class Constant(Barrier):
        def forward(self, x, t=None):
            return torch.full_like(x[..., 0], 0.7)

    stack = BarrierStack(Ball([0.0, 0.0], 1.0), Constant())
    with pytest.raises(ValueError, match=r"outputs \[1\].*do not depend on the state"):
        rectify(stack, DoubleIntegrator())
    with pytest.raises(ValueError, match=r"outputs \[1\]\) does not depend on the state"):
        SafetyFilter(SingleIntegrator(2), [stack])


def test_poles_given_as_numbers_stay_exact_in_float64() -> None:
    """Poles and gains of the same exponential CBF give the same float64 barrier; poles went
    through a float32 tensor (0.3 kept as 0.30000001 after ``.double()``)."""
    dyn = DoubleIntegrator(2).double()
    ball = Ball([1.0, 0.0], 0.5).double()
    by_poles = rectify(ball, dyn, "exponential", poles=[-0.3]).double()
    by_gains = rectify(ball, dyn, "exponential", gains=[0.3]).double()
    x = torch.tensor([[3.0, 4.0, 0.5, -0.2]], dtype=torch.float64)
    assert by_poles.coefficients.tolist() == by_gains.coefficients.tolist()
    assert torch.equal(by_poles(x), by_gains(x))


def test_relative_degree_one_still_checks_what_it_was_given() -> None:
    speed = HalfSpace([1.0, 0.0], 1.0, index=(2, 3))  # v_x <= 1: relative degree 1
    model = DoubleIntegrator(2)
    with pytest.warns(UserWarning, match="HalfSpace has relative degree 1 along DoubleIntegrator"):
        assert rectify(speed, model, "exponential", poles=[-2.0]) is speed
    for kw, message in (
        ({"poles": [1.0]}, "poles must be finite negative real numbers"),
        ({"poles": [float("nan")]}, "poles must be finite negative real numbers"),
        ({"gains": -5.0}, "gains must be finite positive numbers"),
    ):
        with pytest.raises(ValueError, match=message):
            rectify(speed, model, "exponential", **kw)
        with pytest.raises(ValueError, match=message):
            rectify(speed, model, "exponential", relative_degree=1, **kw)


def test_relative_degrees_and_sizes_are_ints() -> None:
    ball = Ball([0.0, 0.0], 1.0)
    for degree in (2.5, 3.0):
        with pytest.raises(TypeError, match="relative_degree must be an int >= 2"):
            HighOrderBarrier(ball, DoubleIntegrator(2), degree)
        with pytest.raises(TypeError, match="relative_degree must be an int >= 2"):
            ExponentialBarrier(ball, DoubleIntegrator(2), degree, [1.0])
    with pytest.raises(TypeError, match="state_dim must be an int >= 1, got 2.5"):
        SingleIntegrator(2.5)
