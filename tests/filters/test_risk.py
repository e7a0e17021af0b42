"""Risk-aware and stochastic filters: noise bound, margin, and Monte Carlo exit rates."""

from __future__ import annotations

import math

import pytest
import torch
from scipy.special import erfinv

from torchcbf.barriers import Ball, Ellipse, HalfSpace, QuadraticLyapunov, Transformed, rectify
from torchcbf.dynamics import AccelUnicycle, SingleIntegrator
from torchcbf.filters import (
    FilterMode,
    RiskAware,
    SafetyFilter,
    Slack,
    Stochastic,
    local_margin,
    noise_bound,
    risk_margin,
)
from torchcbf.integrators import step

F64 = torch.float64


def test_noise_bound_analytic(dtype: torch.dtype) -> None:
    dyn = SingleIntegrator(2, sigma=0.3).to(dtype)
    states = torch.tensor([[0.0, 0.0], [2.0, 0.0], [0.0, -3.0], [0.5, 0.0]], dtype=dtype)
    ball = Ball([0.0, 0.0], 1.0).to(dtype)  # safe outside: |dh/dx sigma| = 2 |p| 0.3
    eta = noise_bound(ball, dyn, states)
    assert eta.shape == () and torch.allclose(eta, torch.tensor(1.8, dtype=dtype))
    # unsafe samples are ignored, a multi-output barrier gives one bound per output
    wall = HalfSpace(torch.tensor([[1.0, 0.0], [0.0, 2.0]]), torch.tensor([1.0, 1.0])).to(dtype)
    eta = noise_bound(wall, dyn, states)
    assert torch.allclose(eta, torch.tensor([0.3, 0.6], dtype=dtype))
    lyap = QuadraticLyapunov([0.0, 0.0]).to(dtype)
    assert torch.allclose(noise_bound(lyap, dyn, states, safe_only=False), eta.new_tensor(1.8))
    with pytest.raises(ValueError, match="safe"):
        noise_bound(ball, dyn, states[[0, 3]])
    with pytest.raises(ValueError, match="SDE"):
        noise_bound(ball, SingleIntegrator(2), states)


def test_noise_bound_closed_forms_match_autograd(dtype: torch.dtype) -> None:
    # a rectified radius-form ellipse barrier (scenario B's risk-aware barrier) has closed
    # forms; the bound must equal autograd's, which the bound took before
    model = AccelUnicycle(sigma=0.2).to(dtype)
    shapes = Ellipse(
        torch.tensor([[1.0, 0.5], [-1.0, 2.0]]), torch.tensor([[0.5, 0.8], [0.7, 0.3]])
    )
    barrier = rectify(Transformed(shapes, "radius"), model, "exponential", gains=[2.0]).to(dtype)
    assert barrier.has_analytic
    gen = torch.Generator().manual_seed(0)
    states = torch.randn(500, 4, generator=gen, dtype=dtype) * torch.tensor(
        [3.0, 3.0, 1.0, 3.0], dtype=dtype
    )
    eta = noise_bound(barrier, model, states)
    with torch.no_grad():
        terms = barrier.lie(states, model, method="autograd", hessian=False)
    norm = torch.linalg.vector_norm(terms.dhdx @ model.sigma(states), dim=-1)
    ref = torch.where(terms.h >= 0, norm, torch.full_like(norm, -math.inf)).amax(0)
    tol = 1e-10 if dtype == F64 else 1e-4
    torch.testing.assert_close(eta, ref, rtol=tol, atol=tol)
    forced = noise_bound(barrier, model, states, method="autograd")
    torch.testing.assert_close(forced, ref, rtol=tol, atol=tol)
    with pytest.raises(ValueError, match="method"):
        noise_bound(barrier, model, states, method="exact")


def test_risk_margin_formula() -> None:
    eta = torch.tensor([0.5, 1.0], dtype=F64)
    got = risk_margin(eta, 0.05, 2.0)
    ref = math.sqrt(4.0) * eta * erfinv(0.95)
    assert torch.allclose(got, ref)


def test_safe_states_give_the_same_filter_as_eta() -> None:
    dyn = SingleIntegrator(1, sigma=0.4)
    wall = HalfSpace([1.0], 1.0)
    states = torch.linspace(-3, 1, 50).unsqueeze(-1)
    a = SafetyFilter(dyn, wall, mode=RiskAware(rho=0.1, horizon=1.0, eta=0.4))
    b = SafetyFilter(dyn, wall, mode=RiskAware(rho=0.1, horizon=1.0, safe_states=states))
    assert torch.allclose(a.cbf_margin.float(), b.cbf_margin.float())
    x, u = torch.tensor([[0.2]]), torch.tensor([[3.0]])
    assert torch.allclose(a(x, u).u, b(x, u).u)


def test_filters_sharing_one_mode_object_keep_their_own_margins() -> None:
    """Binding stores a filter's margins: a second filter given the same mode object binds
    its own copy, and the first filter's margins and answers stay."""
    states = torch.linspace(-3, 1, 50).unsqueeze(-1)
    mode = RiskAware(rho=0.1, horizon=1.0, safe_states=states)
    wall = HalfSpace([1.0], 1.0)
    a = SafetyFilter(SingleIntegrator(1, sigma=0.4), wall, mode=mode)
    x, u = torch.tensor([[0.2]]), torch.tensor([[3.0]])
    margin, answer = a.cbf_margin.clone(), a(x, u).u
    walls = HalfSpace(torch.tensor([[1.0], [2.0]]), torch.tensor([1.0, 3.0]))
    for other in (
        SafetyFilter(SingleIntegrator(1, sigma=0.4), walls, mode=mode),  # two outputs
        SafetyFilter(SingleIntegrator(1, sigma=2.0), wall, mode=mode),  # another noise
    ):
        assert other.condition is not mode and a.condition is mode
        assert torch.equal(a.cbf_margin, margin) and torch.equal(a(x, u).u, answer)
    assert other.cbf_margin.shape == (1,) and float(other.cbf_margin) > float(margin)


def _exit_rate(
    filt: SafetyFilter, h0: float, seed: int, dt: float = 0.02, rows: int = 2000
) -> float:
    """Fraction of Euler-Maruyama paths of ``dx = u dt + sigma dW`` (wall at x = 1, nominal
    control pushing into it) with ``h = 1 - x < 0`` at some step within ``T``."""
    dyn = filt.dynamics
    gen = torch.Generator().manual_seed(seed)
    x = torch.full((rows, 1), 1.0 - h0, dtype=F64)
    u_nom = torch.full((rows, 1), 2.0, dtype=F64)
    left = torch.zeros(rows, dtype=torch.bool)
    with torch.no_grad():
        for _ in range(round(T / dt)):
            u = filt(x, u_nom).u
            x = step(dyn, x, u, dt, "euler_maruyama", generator=gen)
            left |= x[:, 0] > 1.0
    return left.double().mean().item()


SIGMA, T = 0.5, 1.0


def _filters(mode: str | FilterMode, **kw) -> SafetyFilter:
    dyn = SingleIntegrator(1, sigma=SIGMA)
    wall = HalfSpace([1.0], 1.0)  # |dh/dx sigma| = sigma exactly
    # a single CBF without CLF: the elastic QP alone is exact (checked against cvxpy)
    return SafetyFilter(dyn, wall, mode=mode, slack=Slack(exact=False), **kw).double()


H0 = float(risk_margin(torch.tensor(SIGMA, dtype=F64), 0.1, T))  # ~0.82


@pytest.fixture(scope="module")
def vanilla_rate() -> float:
    return _exit_rate(_filters("vanilla", alpha=1.0), H0, seed=1)


def test_risk_aware_exit_probability_below_rho(vanilla_rate: float) -> None:
    filt = _filters(RiskAware(rho=0.1, horizon=T, eta=SIGMA))
    assert torch.allclose(filt.cbf_margin, torch.tensor(H0, dtype=F64))
    rate = _exit_rate(filt, H0, seed=1)  # start on the margin Delta: the tightest start
    # binomial standard error is below 0.007 at 2000 samples
    assert rate <= 0.1, rate
    assert vanilla_rate > rate + 0.1, (vanilla_rate, rate)


def test_stochastic_filter_exits_less_than_vanilla(vanilla_rate: float) -> None:
    rate = _exit_rate(_filters(Stochastic(beta=1.0), alpha=1.0), H0, seed=1)
    assert rate < 0.5 * vanilla_rate and vanilla_rate > 0.2, (rate, vanilla_rate)


@pytest.mark.slow
@pytest.mark.parametrize("rho", [0.02, 0.05, 0.2, 0.5])
def test_risk_aware_exit_probability_several_rho(rho: float) -> None:
    filt = _filters(RiskAware(rho=rho, horizon=T, eta=SIGMA))
    h0 = float(filt.cbf_margin)
    rate = _exit_rate(filt, h0, seed=3, dt=0.01)
    vanilla = _exit_rate(_filters("vanilla", alpha=1.0), h0, seed=3, dt=0.01)
    assert rate <= rho, (rho, rate)
    assert vanilla > rate + 0.1, (vanilla, rate)


def _radius_scene(dtype: torch.dtype, eta: object = "local") -> SafetyFilter:
    """Two radius-form ellipses rectified for the noisy unicycle (scenario B's risk-aware
    barrier): the gradient, so the local noise, changes along each ellipse."""
    model = AccelUnicycle(sigma=0.25)
    shapes = Ellipse(
        torch.tensor([[1.0, 2.0], [2.5, -0.5]]), torch.tensor([[0.4, 1.6], [1.2, 0.3]])
    )
    barrier = rectify(Transformed(shapes, "radius"), model, "exponential", gains=[5.0])
    mode = RiskAware(rho=0.05, horizon=0.2, eta=eta)
    return SafetyFilter(model, barrier, mode=mode, R=torch.diag(torch.tensor([1.0, 0.1]))).to(dtype)


def _unicycle_states(dtype: torch.dtype, rows: int = 24, seed: int = 3) -> torch.Tensor:
    gen = torch.Generator().manual_seed(seed)
    lo = torch.tensor([-1.0, -1.5, -0.5, -math.pi], dtype=dtype)
    hi = torch.tensor([4.0, 4.5, 3.0, math.pi], dtype=dtype)
    return lo + (hi - lo) * torch.rand(rows, 4, generator=gen, dtype=dtype)


def test_local_margin_matches_autograd_per_row(dtype: torch.dtype) -> None:
    filt = _radius_scene(dtype)
    (barrier,) = filt.barriers
    model = filt.dynamics
    x = _unicycle_states(dtype)
    got = filt.condition.margin_at(barrier, model, x).detach()  # [B, 2]
    scale = math.sqrt(2 * 0.2) * float(erfinv(0.95))
    sigma = model.sigma_matrix.double()
    for row in range(x.shape[0]):
        xr = x[row].double().clone().requires_grad_(True)
        h = barrier.double()(xr)
        for i in range(h.shape[-1]):
            (grad,) = torch.autograd.grad(h[i], xr, retain_graph=True)
            ref = scale * float(torch.linalg.vector_norm(grad @ sigma))
            tol = 1e-10 if dtype == F64 else 1e-4
            assert abs(float(got[row, i]) - ref) <= tol * max(1.0, ref)
    # the function itself on hand-made gradients, batched over leading dimensions
    dhdx = torch.tensor([[[3.0, 4.0], [0.0, 0.0]]], dtype=dtype).expand(5, 2, 2, 2)
    sig = (0.5 * torch.eye(2, dtype=dtype)).expand(5, 2, 2, 2)
    out = local_margin(dhdx, sig, 0.1, 2.0)
    assert out.shape == (5, 2, 2)
    expected = torch.tensor([2.5, 0.0], dtype=dtype) * 2.0 * float(erfinv(0.9))
    torch.testing.assert_close(out[0, 0], expected)


def test_local_margin_gradient_is_finite_at_zero() -> None:
    dhdx = torch.zeros(3, 1, 2, dtype=F64, requires_grad=True)
    sig = torch.eye(2, dtype=F64).expand(3, 2, 2)
    local_margin(dhdx, sig, 0.1, 1.0).sum().backward()
    assert torch.equal(dhdx.grad, torch.zeros_like(dhdx))
    x = torch.tensor([[0.3, -0.2]], dtype=F64, requires_grad=True)
    d = torch.cat([x, 2 * x], 0).unsqueeze(0)  # [1, 2, 2]: gradient of the norm
    assert torch.autograd.gradcheck(
        lambda d: local_margin(d, sig[:1], 0.1, 1.0), (d.detach().requires_grad_(True),)
    )


def test_local_eta_filter_equals_constant_eta_filter_row_by_row(dtype: torch.dtype) -> None:
    """At each state the local filter answers what a filter whose constant eta is that
    state's own ``|dh/dx sigma|`` answers (a loop of one-row filters as the reference)."""
    filt = _radius_scene(dtype)
    (barrier,) = filt.barriers
    model = filt.dynamics
    x = _unicycle_states(dtype)
    gen = torch.Generator().manual_seed(4)
    u_nom = 4.0 * torch.randn(x.shape[0], 2, generator=gen, dtype=dtype)
    with torch.no_grad():
        out = filt(x, u_nom)
    # the C condition kernel evaluates the local margin (from the norm of sigma' dh/dx)
    affine = filt.condition.affine_cbf(filt.alpha[0])
    assert affine is not None and affine.noise_scale < 0.0 and affine.offset is None
    assert out.path.endswith("realtime")
    with torch.no_grad():
        terms = barrier.lie(x, model, hessian=False)
    eta = torch.linalg.vector_norm(terms.dhdx @ model.sigma(x), dim=-1)
    tol = 1e-7 if dtype == F64 else 2e-3
    for row in range(x.shape[0]):
        ref = _radius_scene(dtype, eta=eta[row].double())
        one = ref(x[row : row + 1], u_nom[row : row + 1])
        torch.testing.assert_close(out.u[row], one.u[0], rtol=tol, atol=tol)
        assert int(out.status[row]) == int(one.status[0])


def test_local_eta_differentiable_and_constant_eta_keeps_native_path() -> None:
    filt = _radius_scene(F64)
    x = _unicycle_states(F64, rows=6, seed=8)
    u_nom = torch.full((6, 2), 3.0, dtype=F64)
    # the real-time path (no grad) and the general path (grad mode) give the same answers
    with torch.no_grad():
        fast = filt(x, u_nom)
    slow = filt(x.clone().requires_grad_(True), u_nom)
    assert fast.path.endswith("realtime") and not slow.path.endswith("realtime")
    torch.testing.assert_close(fast.u, slow.u.detach(), rtol=1e-7, atol=1e-7)
    torch.testing.assert_close(fast.status, slow.status)
    # gradients through the local margin (the general path answers in grad mode)
    xg = x.clone().requires_grad_(True)
    assert torch.autograd.gradcheck(lambda z: filt(z, u_nom).u, (xg,), atol=1e-6, rtol=1e-5)
    # a constant bound keeps the C condition kernel; the mode says which it is
    fixed = _radius_scene(F64, eta=[2.0, 2.0])
    assert fixed.condition.affine_cbf(fixed.alpha[0]) is not None
    assert "local" in repr(filt.condition) and fixed.condition.local is False


def test_local_eta_errors() -> None:
    with pytest.raises(ValueError, match="eta"):
        RiskAware(rho=0.1, horizon=1.0, eta="global")
    mode = RiskAware(rho=0.1, horizon=1.0, eta=[0.5])
    ball = Ball([0.0, 0.0], 1.0)
    with pytest.raises(ValueError, match="binds"):
        mode.margin_at(ball, SingleIntegrator(2, sigma=0.1), torch.zeros(1, 2))
    with pytest.raises(ValueError, match="sigma"):
        SafetyFilter(SingleIntegrator(2), ball, mode=RiskAware(0.1, 1.0, eta="local"))


def test_a_scalar_eta_margin_is_one_per_output_of_each_state() -> None:
    model = SingleIntegrator(2, sigma=0.2)
    expected = math.sqrt(2.0) * 0.3 * float(erfinv(0.9))
    for barrier, k in ((Ball([1.0, 0.0], 0.5), 1), (Ball([[1.0, 0.0], [0.0, 2.0]], 0.5), 2)):
        filt = SafetyFilter(model, barrier, mode=RiskAware(0.1, 1.0, eta=0.3))
        margin = filt.condition.margin_at(barrier, model, torch.zeros(3, 2))
        torch.testing.assert_close(margin, torch.full((3, k), expected))


def test_the_clf_goal_level_is_checked_and_keeps_its_graph() -> None:
    model = SingleIntegrator(2, u_min=-5.0, u_max=5.0, sigma=0.2)
    lyap = QuadraticLyapunov([2.0, 0.0])
    x, u = torch.zeros(1, 2, dtype=F64), torch.zeros(1, 2, dtype=F64)

    def u_of(gamma):
        mode = RiskAware(0.1, 1.0, clf_eta=0.1, clf_gamma=gamma)
        return SafetyFilter(model, [], lyap, mode=mode)(x, u).u[0, 0]

    gamma = torch.tensor(0.3, dtype=F64, requires_grad=True)
    (grad,) = torch.autograd.grad(u_of(gamma), (gamma,))
    fd = (u_of(0.3 + 1e-6) - u_of(0.3 - 1e-6)) / 2e-6
    torch.testing.assert_close(grad, fd, rtol=1e-6, atol=1e-9)
    for bad, error in ((math.nan, ValueError), (math.inf, ValueError), ("goal", TypeError)):
        with pytest.raises(error, match="clf_gamma"):
            RiskAware(0.1, 1.0, clf_eta=0.1, clf_gamma=bad)
    with pytest.raises(ValueError, match=r"clf_gamma must be a scalar or \[k\]"):
        RiskAware(0.1, 1.0, clf_eta=0.1, clf_gamma=torch.zeros(1, 1))
    with pytest.raises(ValueError, match=r"clf_gamma must be a scalar or have one entry"):
        u_of(torch.tensor([0.0, 1.0, 3.0], dtype=F64))
    torch.testing.assert_close(u_of(torch.tensor([0.3], dtype=F64)), u_of(0.3))


def test_local_eta_horizon_with_gradient_gives_the_same_margin() -> None:
    filt = _radius_scene(F64)
    x = _unicycle_states(F64, rows=5, seed=9)
    u_nom = torch.full((5, 2), 2.0, dtype=F64)
    with torch.no_grad():
        before = filt(x, u_nom).u
    mode = filt.condition
    mode.horizon.requires_grad_(True)
    out = filt(x, u_nom)
    torch.testing.assert_close(out.u.detach(), before)
    (grad,) = torch.autograd.grad(out.u.sum(), mode.horizon)
    assert torch.isfinite(grad)
    assert "local_scale" not in filt.state_dict()  # derived from rho and T, not saved


def test_local_margin_where_the_noise_of_h_vanishes() -> None:
    """A correlated diffusion orthogonal to dh/dx along a ray: |sigma' dh/dx|^2 rounds below
    zero in the kernel at some of its states; one state at a time (the real-time path)
    answers what the general path answers (no NaN, no fallback)."""
    sigma = torch.tensor([[0.1], [0.3]])
    ball = Ball(torch.tensor([[0.0, 0.0]]), torch.tensor([0.5]))
    filt = SafetyFilter(SingleIntegrator(2, sigma=sigma), ball,
                        mode=RiskAware(0.05, 0.2, eta="local")).double()  # fmt: skip
    direction = torch.tensor([[0.3, -0.1]]).double()
    u = torch.tensor([[-1.5, 0.5]], dtype=torch.float64)
    for scale in (1.7, 1.8, 1.9, 2.0, 2.5):
        x = scale * direction
        with torch.no_grad():
            fast = filt(x, u)
        slow = filt(x.clone().requires_grad_(), u)
        assert int(fast.status) == int(slow.status) == 0, (scale, fast.status, fast.path)
        torch.testing.assert_close(fast.u, slow.u.detach(), rtol=1e-7, atol=1e-7)


def test_local_margin_follows_a_loaded_horizon() -> None:
    """The local margin's scale comes from the mode's current horizon: a filter that loads
    another's state answers as that filter does (on both paths)."""
    x = _unicycle_states(F64, rows=8, seed=5)
    u_nom = torch.full((8, 2), 3.0, dtype=F64)
    src, dst = _radius_scene(F64), _radius_scene(F64)
    dst.condition.horizon.fill_(1.0)
    with torch.no_grad():
        dst(x, u_nom)  # the scale of T = 1 in use
        dst.load_state_dict(src.state_dict())
        torch.testing.assert_close(dst(x, u_nom).u, src(x, u_nom).u)
    torch.testing.assert_close(dst(x.clone().requires_grad_(), u_nom).u, src(x, u_nom).u)


def _risk_filter(horizon, eta) -> SafetyFilter:
    dyn = SingleIntegrator(2, u_min=-2.0, u_max=2.0, sigma=0.3).double()
    return SafetyFilter(dyn, Ball([1.0, 0.0], 0.5).double(), mode=RiskAware(0.05, horizon, eta=eta))


def test_a_constant_margin_follows_its_eta_and_horizon() -> None:
    """The margin of a constant eta is made from eta, rho and the horizon as they are at the
    call: its gradient to the horizon is the central difference's, and a trained eta moves
    it (two optimiser steps, each answering as a filter built with the new eta)."""
    x = torch.tensor([[0.0, 0.0], [0.3, 0.3]], dtype=F64)
    u_nom = torch.tensor([[1.0, 1.0], [1.9, 1.1]], dtype=F64)

    def total(T: float) -> float:
        return float(_risk_filter(T, 0.4)(x, u_nom).u[:, 0].sum())

    filt = _risk_filter(0.1, 0.4)
    filt.condition.horizon.requires_grad_(True)
    (dT,) = torch.autograd.grad(filt(x, u_nom).u[:, 0].sum(), filt.condition.horizon)
    e = 1e-6
    assert float(dT) == pytest.approx((total(0.1 + e) - total(0.1 - e)) / (2 * e), rel=1e-6)

    eta = torch.nn.Parameter(torch.tensor(0.4, dtype=F64))
    filt = _risk_filter(0.1, eta)
    opt = torch.optim.SGD([eta], lr=0.05)
    for _ in range(2):
        opt.zero_grad()
        filt(x, u_nom).u.square().sum().backward()
        opt.step()
        fresh = _risk_filter(0.1, float(eta.detach()))
        torch.testing.assert_close(filt.cbf_margin.detach(), fresh.cbf_margin)
        with torch.no_grad():
            torch.testing.assert_close(filt(x, u_nom).u, fresh(x, u_nom).u)
    assert float(eta.detach()) != 0.4


def test_mode_options_that_leave_no_finite_margin_are_refused() -> None:
    """A margin of NaN or inf (beta, eta) or an erfinv(1 - rho) that is inf in float64
    would make every row fall back: refused, naming the option."""
    for build, name in (
        (lambda: Stochastic(beta=float("nan")), "beta"),
        (lambda: Stochastic(beta=[0.1, float("inf")]), "beta"),
        (lambda: RiskAware(0.05, 1.0, eta=float("nan")), "eta"),
        (lambda: RiskAware(0.05, 1.0, eta=float("inf")), "eta"),
        (lambda: RiskAware(1e-17, 1.0, eta=0.1), "rho"),
        (lambda: RiskAware(0.05, 1.0, eta=0.1, clf_rho=0.0), "clf_rho"),
    ):
        with pytest.raises(ValueError, match=name):
            build()


def test_a_tiny_risk_gives_the_same_margin_in_float32_and_float64() -> None:
    """erfinv(1 - rho) is formed in float64: in float32 1 - 1e-8 is 1 and the local margin
    was infinite, so every row of the general path fell back."""
    dhdx = torch.tensor([[[0.6, -0.8]]], dtype=F64)
    sigma = 0.3 * torch.eye(2, dtype=F64).expand(1, 2, 2)
    m32 = local_margin(dhdx.float(), sigma.float(), 1e-8, torch.tensor(1.0))
    m64 = local_margin(dhdx, sigma, 1e-8, torch.tensor(1.0, dtype=F64))
    assert m32.dtype == torch.float32 and torch.isfinite(m32).all()
    want = math.sqrt(2.0) * 0.3 * float(erfinv(1 - 1e-8))
    assert float(m64) == pytest.approx(want, rel=1e-12)
    assert float(m32) == pytest.approx(want, rel=1e-6)
    model = SingleIntegrator(2, sigma=0.3)
    filt = SafetyFilter(model, Ball([1.0, 0.0], 0.5), mode=RiskAware(1e-8, 1.0, eta="local"))
    x, u = torch.tensor([[0.0, 0.0]]), torch.tensor([[1.0, 0.0]])
    out = SafetyFilter(model, Ball([1.0, 0.0], 0.5), mode=RiskAware(1e-8, 1.0, eta="local"),
                       backend="torch")(x, u)  # fmt: skip
    assert int(out.status) == 0 and float(out.u[0, 0]) < 1.0
    torch.testing.assert_close(out.u, filt(x, u).u, atol=1e-5, rtol=1e-5)
