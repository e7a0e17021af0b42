"""Losses: hand formulas, an analytic reference for the CBF condition at the filter's solution,
gradcheck through the QP w.r.t. a network's weights, and gradients through a rollout."""

from __future__ import annotations

from types import SimpleNamespace

import pytest
import torch

from torchcbf.barriers import Ball, NeuralBarrier
from torchcbf.dynamics import SingleIntegrator
from torchcbf.filters import FilterStatus, LinearClassK, SafetyFilter
from torchcbf.learning import (
    MLP,
    cbf_condition_loss,
    classification_accuracy,
    classification_loss,
    closed_loop_loss,
    condition_violation,
)
from torchcbf.sim import simulate

F64 = torch.float64


def _tol(dtype: torch.dtype) -> float:
    return 1e-7 if dtype == F64 else 2e-3


def test_classification_loss_matches_a_loop(device, dtype) -> None:
    gen = torch.Generator(device=device).manual_seed(0)
    h = torch.randn(50, generator=gen, device=device, dtype=dtype)
    safe = torch.rand(50, generator=gen, device=device) < 0.6
    m, mu = 0.1, 0.3
    ref_s = [max(m - float(v), 0.0) for v, s in zip(h, safe, strict=True) if s]
    ref_u = [max(mu + float(v), 0.0) for v, s in zip(h, safe, strict=True) if not s]
    got = classification_loss(h, safe, margin=m, unsafe_margin=mu)
    assert abs(float(got) - (sum(ref_s) + sum(ref_u)) / 50) < _tol(dtype)
    got_b = classification_loss(h, safe, margin=m, unsafe_margin=mu, balanced=True)
    assert abs(float(got_b) - (sum(ref_s) / len(ref_s) + sum(ref_u) / len(ref_u))) < _tol(dtype)
    # the smooth hinge bounds the hinge from above and tends to it
    smooth = classification_loss(h, safe, margin=m, unsafe_margin=mu, temperature=0.1)
    sharp = classification_loss(h, safe, margin=m, unsafe_margin=mu, temperature=1e-4)
    assert float(smooth) > float(got) and abs(float(sharp) - float(got)) < 1e-3
    acc = classification_accuracy(h, safe)
    ref_acc = sum(bool(v >= 0) == bool(s) for v, s in zip(h, safe, strict=True)) / 50
    assert abs(float(acc) - ref_acc) < 1e-6
    with pytest.raises(ValueError, match="same shape"):
        classification_loss(h, safe[:3])
    with pytest.raises(TypeError, match="bool"):
        classification_loss(h, safe.float())


def test_condition_at_filter_solution_matches_analytic_reference(dtype, device) -> None:
    # single integrator, |u_i| <= 1, h = |x|^2 - 1, alpha = 2: a = 2x, b = 2 h
    dyn = SingleIntegrator(2, u_min=-1.0, u_max=1.0)
    filt = SafetyFilter(dyn, Ball([0.0, 0.0], 1.0), alpha=2.0).to(device, dtype)
    gen = torch.Generator().manual_seed(1)
    x = (torch.rand(400, 2, generator=gen, dtype=F64) * 4 - 2).to(device, dtype)
    u_nom = (torch.rand(400, 2, generator=gen, dtype=F64) * 2 - 1).to(device, dtype)
    out = filt(x, u_nom)
    a, b = 2 * x, 2 * ((x**2).sum(-1) - 1)
    nominal = (a * u_nom).sum(-1) + b
    best = b + a.abs().sum(-1)  # the largest a.u + b over the box
    # inactive rows keep u_nom; feasible active rows meet the condition with equality; the
    # others get the control that violates it least (the box corner)
    ref = torch.where(nominal >= 0, nominal, torch.where(best >= 0, torch.zeros_like(b), best))
    assert bool((best < 0).any()) and bool(((nominal < 0) & (best > 0)).any())
    margin = 0.05
    viol = condition_violation(out, margin)
    assert viol.shape == (400, 1)
    assert torch.allclose(viol[:, 0], torch.relu(margin - ref), atol=_tol(dtype) * 10)
    loss = cbf_condition_loss(filt, x, u_nom, margin=margin)
    assert abs(float(loss) - float(torch.relu(margin - ref).mean())) < _tol(dtype) * 10
    relaxed = out.status == FilterStatus.RELAXED
    assert torch.equal(relaxed, best < -1e-3) or bool((relaxed == (best < 0)).float().mean() > 0.99)


def _small_filter(
    u_max: float = 0.5, device: torch.device | str = "cpu"
) -> tuple[SafetyFilter, torch.Tensor, torch.Tensor]:
    torch.manual_seed(0)
    net = MLP(2, (5,), activation="tanh").double()
    with torch.no_grad():
        net.layers[-1].weight.mul_(0.3)
    barrier = NeuralBarrier(net, offset=Ball([0.0, 0.0], 1.0))
    dyn = SingleIntegrator(2, u_min=-u_max, u_max=u_max)
    filt = SafetyFilter(dyn, barrier, alpha=LinearClassK(1.0, learnable=True))
    filt = filt.to(device=device, dtype=F64)
    x = torch.tensor(
        [[0.2, 0.1], [-0.3, 0.4], [1.1, 0.2], [0.1, -1.2], [2.0, 1.5], [-1.8, -1.9]], dtype=F64
    )
    u_nom = torch.tensor(
        [[0.3, 0.0], [0.0, -0.2], [-0.5, 0.0], [0.0, 0.5], [0.1, 0.1], [0.2, -0.1]], dtype=F64
    )
    return filt, x.to(device), u_nom.to(device)


def test_gradcheck_cbf_condition_loss_wrt_network_weights(device) -> None:
    filt, x, u_nom = _small_filter(device=device)
    out = filt(x, u_nom)
    status = out.status
    cv = out.constraint_value[:, 0]
    # rows of every kind: relaxed (inside, limits too tight), active (met with equality), inactive
    assert bool((status == FilterStatus.RELAXED).any())
    active = (status == FilterStatus.SOLVED) & (cv.abs() < 1e-8)
    assert bool(active.any()) and bool((cv > 1e-3).any())
    names = [n for n, _ in filt.named_parameters()]
    assert any(n.startswith("barriers.0.net.") for n in names) and "alpha.0.log_gain" in names
    params = {n: p.detach().clone().requires_grad_() for n, p in filt.named_parameters()}

    def loss(*values: torch.Tensor) -> torch.Tensor:
        call = lambda xx, uu, tt: torch.func.functional_call(  # noqa: E731
            filt, dict(zip(names, values, strict=True)), (xx, uu, tt)
        )
        return cbf_condition_loss(call, x, u_nom, margin=0.05)

    inputs = tuple(params[n] for n in names)
    grads = torch.autograd.grad(loss(*inputs), inputs)
    assert all(bool(g.abs().sum() > 0) for g in grads)  # every weight gets a gradient
    assert torch.autograd.gradcheck(loss, inputs, eps=1e-6, atol=1e-6, rtol=1e-4)


def test_gradient_through_the_qp_cancels_on_active_rows(device) -> None:
    # On a row where the filter meets the condition with equality, a.u* + b stays 0 when the
    # weights move (u* follows them): d/dtheta is 0 only if the gradient flows through u*.
    filt, x, u_nom = _small_filter(device=device)
    out = filt(x, u_nom)
    row = int(torch.nonzero((out.status == 0) & (out.constraint_value[:, 0].abs() < 1e-8))[0])
    w = filt.barriers[0].net.layers[0].weight
    (g_full,) = torch.autograd.grad(out.constraint_value[row, 0], w, retain_graph=True)
    terms = filt.barriers[0].lie(x[row], filt.dynamics)
    gain = filt.alpha[0].gain
    value = terms.lfh + (terms.lgh * out.u[row].detach()).sum(-1) + gain * terms.h
    assert abs(float((value - out.constraint_value[row, 0]).detach())) < 1e-8  # same condition
    (g_stopped,) = torch.autograd.grad(value, w)
    assert float(g_full.abs().max()) < 1e-8
    assert float(g_stopped.abs().max()) > 1e-3


def test_closed_loop_loss_hand_formula(dtype) -> None:
    x = torch.tensor([[[0.0, 0.0], [1.0, 0.0], [2.0, 0.0]]], dtype=dtype)
    u = torch.tensor([[[1.0, 0.0], [1.0, 1.0]]], dtype=dtype)
    u_nom = torch.tensor([[[1.0, 0.0], [0.0, 1.0]]], dtype=dtype)
    traj = SimpleNamespace(x=x, u=u, u_nom=u_nom)
    ball = Ball([1.0, 0.5], 0.75).to(dtype)  # h = (x-1)^2 + (y-.5)^2 - .5625
    out = closed_loop_loss(
        traj, ball, goal=[2.0, 0.0], goal_weight=0.5, collision_weight=10.0, collision_margin=0.1
    )
    h = torch.tensor([1.25 - 0.5625, 0.25 - 0.5625, 1.25 - 0.5625], dtype=dtype)
    collision = torch.relu(0.1 - h).mean()
    assert abs(float(out.intervention) - 0.5) < _tol(dtype)
    assert abs(float(out.collision) - float(collision)) < _tol(dtype)
    # the goal term is a smoothed norm (sqrt(d^2 + 1e-12)): 1e-6 off at the goal itself
    assert abs(float(out.goal) - 1.0) < max(_tol(dtype), 1e-6)
    assert abs(float(out.total) - (0.5 + 10 * float(collision) + 0.5)) < max(_tol(dtype), 1e-6)
    with pytest.raises(ValueError, match="trajectory"):
        closed_loop_loss(SimpleNamespace(x=x, u=u[:, :1], u_nom=u_nom), ball)


def test_closed_loop_loss_gradient_through_simulate_matches_finite_differences() -> None:
    dyn = SingleIntegrator(2, u_min=-2.0, u_max=2.0)
    ball = Ball([0.0, 0.0], 1.0)
    alpha = LinearClassK(0.7, learnable=True)
    filt = SafetyFilter(dyn, ball, alpha=alpha).double()
    goal = torch.tensor([3.0, 0.3], dtype=F64)
    x0 = torch.tensor([[-3.0, 0.0], [-2.5, 0.6], [0.0, -3.0]], dtype=F64)

    def loss() -> torch.Tensor:
        traj = simulate(
            dyn,
            x0,
            25,
            0.05,
            nominal=lambda x, t: (goal - x).clamp(-2, 2),
            safety_filter=filt,
            progress=False,
            differentiable=True,
        )
        return closed_loop_loss(traj, ball, goal=goal, goal_weight=1.0).total

    value = loss()
    (grad,) = torch.autograd.grad(value, alpha.log_gain)
    eps = 1e-5
    with torch.no_grad():
        alpha.log_gain += eps
        up = loss()
        alpha.log_gain -= 2 * eps
        down = loss()
        alpha.log_gain += eps
    fd = (up - down) / (2 * eps)
    assert abs(float(grad)) > 1e-3  # the gain matters here
    assert abs(float(grad - fd)) < 1e-5 * max(1.0, abs(float(fd)))


def test_classification_loss_refuses_a_temperature_that_is_not_a_number() -> None:
    h, safe = torch.tensor([0.3, -0.2]), torch.tensor([True, False])
    for temperature in (float("nan"), -1.0, float("inf")):
        with pytest.raises(ValueError, match="temperature must be a finite number >= 0"):
            classification_loss(h, safe, temperature=temperature)


def test_losses_over_no_states_are_zero_and_keep_the_graph() -> None:
    """A minibatch without a safe state gives an empty condition set: 0, not NaN."""
    net = NeuralBarrier(MLP(2, (8,)))
    filt = SafetyFilter(SingleIntegrator(2), [net])
    x, u = torch.zeros(0, 2), torch.zeros(0, 2)
    loss = cbf_condition_loss(filt, x, u) + classification_loss(
        net(x), torch.zeros(0, dtype=torch.bool)
    )
    assert float(loss.detach()) == 0.0
    loss.backward()
    assert all(p.grad is None or bool((p.grad == 0).all()) for p in net.parameters())


def test_classification_accuracy_is_exact_under_half_precision() -> None:
    h = torch.ones(1000, dtype=torch.bfloat16)
    safe = torch.ones(1000, dtype=torch.bool)
    safe[:3] = False
    acc = classification_accuracy(h, safe)
    assert acc.dtype == torch.float32 and float(acc) == pytest.approx(0.997, abs=1e-7)


def test_classification_loss_refuses_nan_margins() -> None:
    h, safe = torch.zeros(3), torch.ones(3, dtype=torch.bool)
    for kw in ({"margin": float("nan")}, {"unsafe_margin": float("inf")}):
        with pytest.raises(ValueError, match="margin must be a finite number"):
            classification_loss(h, safe, **kw)
