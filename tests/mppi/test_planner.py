"""MPPI planner: LQR limit, batch = loop, RNG discipline, algorithm pieces, bad input."""

from __future__ import annotations

import copy
import logging
import math

import pytest
import torch
from torch._dynamo.utils import counters

from torchcbf import integrators
from torchcbf.dynamics import AccelUnicycle, ControlAffine, DoubleIntegrator, SingleIntegrator
from torchcbf.integrators import rk4
from torchcbf.mppi import MPPI, QuadraticGoal, Reach, StageCost


def _lqr_problem(dtype=torch.float64):
    dt, H = 0.1, 10
    A = torch.tensor([[1.0, dt], [0.0, 1.0]], dtype=dtype)
    Bm = torch.tensor([[0.0], [dt]], dtype=dtype)
    Q = torch.diag(torch.tensor([1.0, 0.1], dtype=dtype))
    R = 0.1 * torch.eye(1, dtype=dtype)
    Qf = 10.0 * Q
    return dt, H, A, Bm, Q, R, Qf


def _lqr_plan(x0, dt, H, A, Bm, Q, R, Qf):
    """Finite-horizon discrete LQR by Riccati recursion (cost on x_1..x_H, Qf on x_H)."""
    P = Q + Qf
    gains = []
    for k in reversed(range(H)):
        Kk = torch.linalg.solve(R + Bm.T @ P @ Bm, Bm.T @ P @ A)
        gains.append(Kk)
        P_next = A.T @ P @ A - A.T @ P @ Bm @ Kk
        P = P_next + (Q if k > 0 else 0.0)
    gains.reverse()
    x, us = x0, []
    for Kk in gains:
        u = -Kk @ x
        us.append(u)
        x = A @ x + Bm @ u
    return torch.stack(us)


def test_riccati_reference_is_the_least_squares_optimum():
    # the reference itself, checked against a dense solve of the same quadratic program
    dt, H, A, Bm, Q, R, Qf = _lqr_problem()
    x0 = torch.tensor([1.0, 0.0], dtype=torch.float64)
    U = _lqr_plan(x0, dt, H, A, Bm, Q, R, Qf).reshape(-1)
    G = torch.zeros(2 * H, H, dtype=torch.float64)
    Phi = torch.zeros(2 * H, 2, dtype=torch.float64)
    for k in range(1, H + 1):
        Phi[2 * (k - 1) : 2 * k] = torch.linalg.matrix_power(A, k)
        for j in range(k):
            G[2 * (k - 1) : 2 * k, j : j + 1] = torch.linalg.matrix_power(A, k - 1 - j) @ Bm
    Qbar = torch.block_diag(*([Q] * (H - 1) + [Q + Qf]))
    U_ls = -torch.linalg.solve(
        G.T @ Qbar @ G + 0.1 * torch.eye(H, dtype=torch.float64), G.T @ Qbar @ Phi @ x0
    )
    torch.testing.assert_close(U, U_ls)


def test_plan_approaches_lqr_as_samples_grow():
    dt, H, A, Bm, Q, R, Qf = _lqr_problem()
    x0 = torch.tensor([1.0, 0.0], dtype=torch.float64)
    u_star = _lqr_plan(x0, dt, H, A, Bm, Q, R, Qf)
    cost = StageCost(
        lambda x, u: (x @ Q * x).sum(-1) + (u @ R * u).sum(-1), lambda x: (x @ Qf * x).sum(-1)
    )
    errors = []
    for K in (30, 300, 3000):
        err = 0.0
        for seed in range(3):
            planner = MPPI(DoubleIntegrator(1), cost, H, K, dt, 0.5, 0.05, seed=seed)
            for _ in range(25):  # iterate at the same state: converges to the optimum
                out = planner(x0, shift=False)
            err += float((out.u - u_star[0]).abs()) / 3
        errors.append(err)
    assert errors[0] > errors[1] > errors[2]
    assert errors[2] < 0.05 * float(u_star[0].abs())


def _planner(seed=0, K=64, H=8, **kw):
    dyn = AccelUnicycle(u_min=-2.0, u_max=2.0)
    cost = QuadraticGoal((2.0, 4.0), 2.0, (0, 1), 10.0)
    sigma = torch.tensor([[1.0, 0.3], [0.3, 0.5]])
    return MPPI(dyn, cost, H, K, 0.02, sigma, 0.5, 0.1, seed=seed, **kw)


def _x0(B, dtype=torch.float64, device="cpu"):
    x = torch.zeros(B, 4, dtype=dtype, device=device)
    x[:, 0] = torch.arange(B, dtype=dtype, device=device) * 0.3
    x[:, 3] = math.pi / 4
    return x


@pytest.mark.parametrize("backend", ["auto", "torch"])
def test_batch_equals_loop(device, dtype, backend):
    B = 3
    x = _x0(B, dtype, device)
    batched = _planner(seed=7, backend=backend).to(device)
    singles = [_planner(seed=7 + b, backend=backend).to(device) for b in range(B)]
    for step in range(3):
        out = batched(x, t=0.1 * step)
        for b in range(B):
            one = singles[b](x[b], t=0.1 * step)
            tol = 1e-12 if dtype == torch.float64 else 1e-5
            torch.testing.assert_close(out.plan[b], one.plan, atol=tol, rtol=tol)
            torch.testing.assert_close(out.cost_min[b], one.cost_min, atol=tol, rtol=tol)
        assert out.plan.shape == (B, 8, 2) and out.u.shape == (B, 2)


@pytest.mark.parametrize("path", ["fused", "rollout", "torch"])
def test_an_empty_batch_plans_nothing(device, dtype, path):
    """x [0, n] gives outputs with B = 0 on every path, and the next batch plans as usual."""
    backend = "torch" if path == "torch" else "auto"
    planner = _planner(keep_rollouts=2, backend=backend).to(device)
    if path != "fused":
        planner = MPPI(
            planner.dynamics, lambda s, u, t: (s[..., -1, :2] ** 2).sum(-1), 8, 64, 0.02, 1.0,
            0.5, 0.1, keep_rollouts=2, backend=backend,
        ).to(device)  # fmt: skip
    for _ in range(2):
        out = planner(_x0(0, dtype, device))
        assert out.u.shape == (0, 2) and out.plan.shape == (0, 8, 2)
        assert out.best_states.shape == (0, 9, 4) and out.rollouts.shape == (0, 2, 9, 4)
        assert out.cost_min.shape == out.ess.shape == out.status.shape == (0,)
    if device == "cpu":
        assert planner.path == path
    out = planner(_x0(2, dtype, device))
    assert out.u.shape == (2, 2) and bool(torch.isfinite(out.u).all())


def test_a_planner_of_modules_on_a_device_lives_there(device, dtype):
    """A planner built from a model and cost already on the device takes its own buffers
    there and plans as one built on the CPU and moved."""
    dyn = AccelUnicycle(u_min=-2.0, u_max=2.0).to(device)
    cost = QuadraticGoal((2.0, 4.0), 2.0, (0, 1), 10.0).to(device)
    sigma = torch.tensor([[1.0, 0.3], [0.3, 0.5]], device=device)
    there = MPPI(dyn, cost, 8, 64, 0.02, sigma, 0.5, 0.1, seed=3)
    assert all(t.device.type == torch.device(device).type for t in there.buffers())
    x = _x0(2, dtype, device)
    torch.testing.assert_close(there(x).plan, _planner(seed=3).to(device)(x).plan)


def test_seeds_and_global_rng():
    x = _x0(1)[0]
    state = torch.random.get_rng_state()
    a, b, c = _planner(seed=1), _planner(seed=1), _planner(seed=2)
    pa, pb, pc = a(x).plan, b(x).plan, c(x).plan
    assert torch.equal(pa, pb)
    assert not torch.allclose(pa, pc)
    # reset re-seeds and forgets the plan: the same sequence of plans again
    a(x)
    a.reset()
    assert torch.equal(a(x).plan, pa)
    assert torch.equal(torch.random.get_rng_state(), state)


def test_noise_covariance_and_clamping():
    """The sampled noise has covariance Sigma; clamped samples have their noise recomputed."""
    sigma = torch.tensor([[1.0, 0.6], [0.6, 2.0]], dtype=torch.float64)
    K, H = 20000, 2
    seen = {}

    def cost(states, controls, t0):
        seen["controls"] = controls.clone()
        return torch.zeros(states.shape[:2], dtype=states.dtype)

    planner = MPPI(SingleIntegrator(2), cost, H, K, 0.1, sigma, 1.0, seed=3, cost_chunk=0)
    planner(torch.zeros(2, dtype=torch.float64))
    eps = seen["controls"].reshape(-1, 2)  # the plan is zero on the first call
    torch.testing.assert_close(eps.T.cov(), sigma, atol=0.05, rtol=0.05)
    # with limits: controls inside the box, and the plan moves by the weighted clamped noise
    lim = MPPI(
        SingleIntegrator(2),
        cost,
        H,
        K,
        0.1,
        sigma,
        1.0,
        u_min=-0.5,
        u_max=0.5,
        seed=3,
        cost_chunk=0,
    )
    out = lim(torch.zeros(2, dtype=torch.float64))
    v = seen["controls"]
    assert float(v.abs().max()) <= 0.5
    torch.testing.assert_close(out.plan, v[0].mean(0))  # equal costs: uniform weights
    # limits default to the dynamics'
    dyn_lim = MPPI(SingleIntegrator(2, u_min=-0.2, u_max=0.3), cost, H, 100, 0.1, 1.0, 1.0)
    dyn_lim(torch.zeros(2))
    assert float(seen["controls"].min()) >= -0.2 - 1e-6
    assert float(seen["controls"].max()) <= 0.3 + 1e-6


@pytest.mark.parametrize("backend", ["auto", "torch"])
def test_weights_control_cost_and_update_reference(backend):
    """One call against a direct implementation of the MPPI update."""
    K, H, lam, gamma = 50, 4, 0.7, 0.3
    sigma = torch.tensor([[0.5, 0.1], [0.1, 0.3]], dtype=torch.float64)
    seen = {}
    goal = torch.tensor([1.0, -1.0], dtype=torch.float64)

    def cost(states, controls, t0):
        seen["states"], seen["controls"] = states.clone(), controls.clone()
        return ((states[..., 1:, :] - goal) ** 2).sum((-1, -2))

    planner = MPPI(
        SingleIntegrator(2),
        cost,
        H,
        K,
        0.1,
        sigma,
        lam,
        gamma,
        u_min=-1.0,
        u_max=1.0,
        seed=0,
        keep_rollouts=5,
        backend=backend,
    )
    x = torch.tensor([0.2, 0.1], dtype=torch.float64)
    planner(x)  # first call: plan = weighted noise
    plan0 = planner(x, shift=False).plan  # refine once more at the same state
    out = planner(x)  # shift, then plan
    shifted = torch.cat([plan0[1:], torch.zeros(1, 2, dtype=torch.float64)])
    v = seen["controls"][0]
    eps = v - shifted
    # rollouts: single-integrator Euler from x
    states = x + 0.1 * torch.cumsum(torch.cat([torch.zeros(K, 1, 2, dtype=v.dtype), v], 1), 1)
    torch.testing.assert_close(seen["states"][0], states)
    S = ((states[:, 1:] - goal) ** 2).sum((-1, -2))
    S = S + gamma * torch.einsum("hm,mn,khn->k", shifted, torch.linalg.inv(sigma), eps)
    w = torch.softmax(-S / lam, 0)
    torch.testing.assert_close(out.plan, (shifted + torch.einsum("k,khm->hm", w, eps)).clamp(-1, 1))
    torch.testing.assert_close(out.u, out.plan[0])
    torch.testing.assert_close(out.cost_min, S.min())
    torch.testing.assert_close(out.cost_mean, S.mean())
    torch.testing.assert_close(out.ess, 1.0 / (w**2).sum())
    torch.testing.assert_close(out.best_states, states[S.argmin()])
    assert out.rollouts.shape == (5, H + 1, 2)
    torch.testing.assert_close(out.rollout_weights, w[:5])
    assert int(out.status) == 0


def test_large_and_nonfinite_costs_are_safe():
    def cost(states, controls, t0):
        c = 1e30 + 1e28 * states[..., -1, 0]
        c[0, :3] = float("nan")
        c[1] = float("inf")  # env 1: no usable sample
        return c

    planner = MPPI(SingleIntegrator(2), cost, 5, 32, 0.1, 1.0, 1e-6, 0.1)
    out = planner(torch.zeros(2, 2))
    assert torch.isfinite(out.plan).all() and torch.isfinite(out.ess).all()
    assert out.status.tolist() == [0, 1]
    assert torch.equal(out.plan[1], torch.zeros(5, 2))  # env 1: plan kept (zero)
    assert float(out.ess[0]) >= 1.0


def test_the_mean_of_large_float32_costs_does_not_overflow():
    """Costs of 1e37 are finite in float32, and so is their mean."""

    def cost(states, controls, t0):
        return torch.full(states.shape[:2], 1e37, dtype=states.dtype)

    planner = MPPI(SingleIntegrator(2), cost, 3, 64, 0.1, 1.0, 1.0)
    out = planner(torch.zeros(1, 2))
    assert out.plan.dtype == torch.float32
    torch.testing.assert_close(out.cost_mean, torch.tensor([1e37]))


@pytest.mark.parametrize("backend", ["auto", "torch"])
def test_rk4_rollouts_match_integrator(backend):
    seen = {}

    def cost(states, controls, t0):
        seen["s"], seen["u"] = states.clone(), controls.clone()
        return torch.zeros(states.shape[:2], dtype=states.dtype)

    dyn = AccelUnicycle()
    planner = MPPI(dyn, cost, 6, 4, 0.05, 1.0, 1.0, integrator="rk4", seed=0, backend=backend)
    x = torch.tensor([0.0, 0.0, 1.0, 0.3], dtype=torch.float64)
    planner(x)
    s, u = seen["s"][0], seen["u"][0]
    ref = [x.expand(4, 4)]
    for j in range(6):
        ref.append(rk4(dyn, ref[-1], u[:, j], 0.05))
    torch.testing.assert_close(s, torch.stack(ref, 1))


def test_history_and_spec_cost():
    spec = Reach((1.0, 0.0), 0.2, (0.0, 0.5), weight=1.0)
    planner = MPPI(SingleIntegrator(2), spec, 5, 16, 0.1, 1.0, 1.0, history_size=4)
    assert planner.history is None
    for k in range(6):
        planner(torch.tensor([0.1 * k, 0.0]), t=0.1 * k)
    hist = planner.history
    assert hist.valid.all() and hist.states.shape == (1, 4, 2)
    assert sorted(hist.times[0].tolist()) == pytest.approx([0.2, 0.3, 0.4, 0.5])
    planner.reset()
    planner(torch.zeros(2), t=0.0)
    assert int(planner.history.valid.sum()) == 1


def _crossing_loop(cost_ball, true_ball, seed: int) -> float:
    """A single integrator from the origin to (4, 0) while a ball crosses its path; the
    closed loop's least ``h`` of ``true_ball`` at the true times."""
    from torchcbf.mppi import BarrierCost

    dt = 0.1
    cost = QuadraticGoal([4.0, 0.0], terminal_weight=5.0) + BarrierCost(cost_ball, eps=0.01)
    planner = MPPI(SingleIntegrator(2), cost, 20, 500, dt, 0.5, 0.05, 0.0, seed=seed,
                   u_min=-1.0, u_max=1.0)  # fmt: skip
    x, least = torch.zeros(1, 2), math.inf
    for k in range(60):
        x = x + dt * planner(x, t=k * dt).u
        least = min(least, float(true_ball(x, torch.tensor([(k + 1) * dt]))))
    assert planner.path == ("rollout" if cost_ball.time_varying else "fused")
    return least


@pytest.mark.parametrize("seed", [0, 1])
def test_a_moving_obstacle_in_a_barrier_cost_is_avoided_where_it_will_be(seed: int) -> None:
    """A BarrierCost reads a time-varying ball at each rollout state's time: the closed loop
    passes behind the crossing ball, where the same ball read at t = 0 is hit."""
    from torchcbf.barriers import Ball

    moving = Ball([2.0, -2.0], 0.6, velocity=[0.0, 1.0])
    assert _crossing_loop(moving, moving, seed) > 0.05
    assert _crossing_loop(Ball([2.0, -2.0], 0.6), moving, seed) < -0.1


def test_a_ball_given_a_velocity_after_a_fused_call_is_planned_in_time():
    """The kept kernel configuration of a static ball is dropped when the ball starts
    moving: the planner scores in torch, with the ball's times, as backend="torch" does."""
    from torchcbf.barriers import Ball
    from torchcbf.mppi import BarrierCost

    plans = []
    for backend in ("auto", "torch"):
        ball = Ball([1.0, 0.2], 0.5)
        cost = QuadraticGoal([2.0, 0.0]) + BarrierCost(ball)
        planner = MPPI(SingleIntegrator(2), cost, 10, 64, 0.1, 0.5, 0.1, seed=3, backend=backend)
        planner(torch.zeros(2), t=0.0)
        ball.velocity = torch.tensor([0.0, -1.0])
        out = planner(torch.zeros(2), t=0.5)
        assert planner.path == ("rollout" if backend == "auto" else "torch")
        plans.append(out.plan)
    torch.testing.assert_close(plans[0], plans[1], atol=1e-5, rtol=1e-5)


def test_shift_fill_last():
    p = _planner(shift_fill="last")
    x = _x0(1)[0]
    first = p(x).plan
    p.zero_noise_samples = 64  # no noise: identical samples, the update keeps the shifted plan
    second = p(x).plan
    torch.testing.assert_close(second[:-1], first[1:])
    torch.testing.assert_close(second[-1], first[-1])


def test_bad_input():
    dyn = SingleIntegrator(2)
    cost = QuadraticGoal((0.0, 0.0))
    with pytest.raises(ValueError, match="horizon"):
        MPPI(dyn, cost, 0, 10, 0.1, 1.0, 1.0)
    with pytest.raises(ValueError, match="temperature"):
        MPPI(dyn, cost, 5, 10, 0.1, 1.0, 0.0)
    with pytest.raises(ValueError, match="noise_sigma"):
        MPPI(dyn, cost, 5, 10, 0.1, torch.tensor([[1.0, 2.0], [2.0, 1.0]]), 1.0)
    with pytest.raises(ValueError, match="noise_sigma"):
        MPPI(dyn, cost, 5, 10, 0.1, torch.tensor([1.0, 2.0, 3.0]), 1.0)
    with pytest.raises(ValueError, match="num_samples"):
        MPPI(dyn, cost, 5, 0, 0.1, 1.0, 1.0)
    with pytest.raises(ValueError, match="dt"):
        MPPI(dyn, cost, 5, 10, -0.1, 1.0, 1.0)
    with pytest.raises(ValueError, match="integrator"):
        MPPI(dyn, cost, 5, 10, 0.1, 1.0, 1.0, integrator="midpoint")
    planner = MPPI(dyn, cost, 5, 10, 0.1, 1.0, 1.0)
    with pytest.raises(ValueError, match="x"):
        planner(torch.zeros(3))
    with pytest.raises(ValueError, match="x"):
        planner(torch.zeros(2, 2, 2))
    with pytest.raises(ValueError, match="cost"):
        MPPI(dyn, lambda s, u, t: s[..., 0, 0, 0], 5, 10, 0.1, 1.0, 1.0)(torch.zeros(2))


def test_compiled_matches_eager():
    pytest.importorskip("torch._dynamo")
    eager = _planner(seed=4, K=32, H=4, backend="torch")
    compiled = _planner(seed=4, K=32, H=4, compile=True, backend="torch")
    x = _x0(2)
    for step in range(2):
        a, b = eager(x, 0.1 * step), compiled(x, 0.1 * step)
        torch.testing.assert_close(a.plan, b.plan, atol=1e-10, rtol=1e-10)
        torch.testing.assert_close(a.cost_min, b.cost_min, atol=1e-10, rtol=1e-10)


def _goal_cost(states, controls, t0):
    """A cost written in Python (not one of torchcbf's terms): kernel rollouts + torch."""
    p = states[..., 1:, :2]
    return ((p - p.new_tensor([2.0, 4.0])) ** 2).sum((-1, -2)) + t0.unsqueeze(-1)


def _user_planner(**kw):
    dyn = AccelUnicycle(u_min=-2.0, u_max=2.0)
    return MPPI(dyn, _goal_cost, 6, 32, 0.02, 1.0, 0.5, 0.1, seed=3, **kw)


def test_compiled_closed_loop_compiles_once():
    pytest.importorskip("torch._dynamo")
    eager, compiled = _user_planner(), _user_planner(compile=True)
    x = _x0(2)
    torch.testing.assert_close(eager(x).plan, compiled(x).plan)
    with torch.compiler.set_stance("fail_on_recompile"):
        for step in range(1, 4):
            x = x + 0.05 * step  # new values of the state, the time and the plan
            a, b = eager(x, 0.1 * step), compiled(x, 0.1 * step)
            torch.testing.assert_close(a.plan, b.plan, atol=1e-10, rtol=1e-10)
            torch.testing.assert_close(a.cost_min, b.cost_min, atol=1e-10, rtol=1e-10)


def test_compiled_planner_deep_copies_with_its_own_compiled_cost():
    pytest.importorskip("torch._dynamo")
    planner = _user_planner(compile=True)
    twin = copy.deepcopy(planner)
    assert twin._score_fn.eager.__self__ is twin
    x = _x0(2)
    torch.testing.assert_close(twin(x).plan, planner(x).plan)


class _UserUnicycle(ControlAffine):
    """AccelUnicycle written with ``f`` and ``g`` only (torch integrates ``f + g u``)."""

    def __init__(self) -> None:
        super().__init__(4, 2)

    def f(self, x):
        v, th = x[..., 2], x[..., 3]
        zero = torch.zeros_like(v)
        return torch.stack([v * torch.cos(th), v * torch.sin(th), zero, zero], -1)

    def g(self, x):
        g = x.new_zeros(*x.shape[:-1], 4, 2)
        g[..., 2, 0] = 1.0
        g[..., 3, 1] = 1.0
        return g


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
@pytest.mark.parametrize(
    "compile",
    [True, {"options": {"force_pointwise_cat": False}}, {"mode": "default"}, {"options": None}],
    ids=["default", "user options", "mode", "no options"],
)
@pytest.mark.parametrize("form", ["f and g", "step function"])
def test_compiled_user_model_matches_eager(dtype, compile, form):
    pytest.importorskip("torch._dynamo")

    def step(x, u, j):
        v, th = x[..., 2], x[..., 3]
        xdot = torch.stack([v * torch.cos(th), v * torch.sin(th), u[..., 0], u[..., 1]], -1)
        return x + 0.02 * xdot

    def planner(**kw):
        if form == "step function":
            kw["step"] = step
        return MPPI(_UserUnicycle(), _goal_cost, 6, 48, 0.02, 1.0, 0.5, 0.1, seed=3, **kw)

    eager, compiled = planner().to(dtype), planner(compile=compile).to(dtype)
    x = _x0(3, dtype)
    tol = 1e-10 if dtype == torch.float64 else 1e-4
    for step in range(2):
        a, b = eager(x, 0.1 * step), compiled(x, 0.1 * step)
        torch.testing.assert_close(a.plan, b.plan, atol=tol, rtol=tol)
        torch.testing.assert_close(a.cost_min, b.cost_min, atol=tol, rtol=tol)


class _DriftedUnicycle(_UserUnicycle):
    """A closed-form ``xdot`` of its own (not ``f + g u``) with a drift ``f`` does not have."""

    def xdot(self, x, u):
        return super().xdot(x, u) + 0.1


_COMPILED_MODELS = ["f and g, euler", "f and g, rk4", "own xdot", "hooked", "timed step function"]


@pytest.mark.parametrize(
    ("model", "layout"),
    [pytest.param(model, "component", id=f"{model}-component") for model in _COMPILED_MODELS]
    + [
        # a compile each: the sample layout of all but the first in the slow suite
        pytest.param(model, "sample", id=f"{model}-sample", marks=[pytest.mark.slow] if i else [])
        for i, model in enumerate(_COMPILED_MODELS)
    ],
)
def test_compiled_rollouts_match_a_loop_and_compile_once(model, layout):
    """The rollouts equal the model integrated step by step in a Python loop, eager and
    compiled; the compiled step is one graph for every step index, traced once, so later
    calls compile nothing."""
    pytest.importorskip("torch._dynamo")
    dyn = _DriftedUnicycle() if model == "own xdot" else _UserUnicycle()
    if model == "hooked":
        dyn.register_forward_hook(lambda module, args, out: out * 0.5)
    integrator = "rk4" if model.endswith("rk4") else "euler"

    def timed(x, u, j):  # time-dependent dynamics: the step reads its index
        return integrators.euler(dyn, x, u, 0.02) + 0.01 * j

    H, K = 5, 24
    seqs = torch.randn(K, H, 2, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    kw = {"step": timed} if model == "timed step function" else {}

    def planner(**extra):
        return MPPI(dyn, _goal_cost, H, K, 0.02, 1.0, 0.5, 0.1, seed=3, layout=layout,
                    integrator=integrator, keep_rollouts=K, action_sampler=lambda x, t: seqs,
                    **kw, **extra)  # fmt: skip

    def loop(x):
        states = [x.unsqueeze(1).expand(2, K, 4)]
        for j in range(H):
            u = seqs[:, j].expand(2, K, 2)
            if kw:
                states.append(timed(states[-1], u, j))
            else:
                states.append(integrators.step(dyn, states[-1], u, 0.02, method=integrator))
        return torch.stack(states, 2)

    x = _x0(2)
    eager, compiled = planner(), planner(compile=True)
    torch.testing.assert_close(eager(x).rollouts, loop(x), atol=1e-12, rtol=1e-12)
    graphs = counters["stats"]["unique_graphs"]
    torch.testing.assert_close(compiled(x).rollouts, loop(x), atol=1e-10, rtol=1e-10)
    if model not in ("hooked", "timed step function"):  # those two break their graphs
        # one graph for the step at every index (the first index is not traced apart) and
        # one for the cost
        assert counters["stats"]["unique_graphs"] - graphs == 2
    with torch.compiler.set_stance("fail_on_recompile"):
        for step in range(1, 3):
            y = x + 0.1 * step
            torch.testing.assert_close(compiled(y, 0.1 * step).rollouts, loop(y), atol=1e-10,
                                       rtol=1e-10)  # fmt: skip


class _GoalCost(torch.nn.Module):
    def forward(self, states, controls, t0):
        return _goal_cost(states, controls, t0)


def _eager_and_compiled() -> tuple[MPPI, MPPI]:
    """Two planners of a user model and cost, the second compiled (5 steps, 24 samples)."""
    pytest.importorskip("torch._dynamo")

    def planner(**extra):
        return MPPI(_UserUnicycle(), _GoalCost(), 5, 24, 0.02, 1.0, 0.5, 0.1, seed=3,
                    keep_rollouts=24, **extra)  # fmt: skip

    return planner(), planner(compile=True)


@pytest.mark.slow  # 7-10 s on 2 cores: in the slow suite, which CI runs too
def test_hooks_added_after_compiling_are_seen():
    """A forward hook registered on the model or the cost after the compiled planner ran
    changes its plans as it changes the eager planner's."""
    eager, compiled = _eager_and_compiled()
    x = _x0(2)
    handles = []
    for step in range(5):
        for p in (eager, compiled):
            if step == 1:  # the model's rate halved
                p.dynamics.register_forward_hook(lambda module, args, out: out * 0.5)
            if step == 2:  # a cost that prefers the other side
                handles.append(p.cost.register_forward_hook(lambda module, args, out: -out))
            if step == 3:  # a second hook on the hooked model
                p.dynamics.register_forward_hook(lambda module, args, out: out + 0.1)
        if step == 4:
            for handle in handles:
                handle.remove()
        a, b = eager(x), compiled(x)
        torch.testing.assert_close(b.rollouts, a.rollouts, atol=1e-10, rtol=1e-10)
        torch.testing.assert_close(b.plan, a.plan, atol=1e-10, rtol=1e-10)


def test_a_drift_set_on_the_model_after_compiling_is_integrated():
    """``model.f = ...`` after the compiled planner ran (and ``del model.f`` later) changes
    its rollouts as it changes the eager planner's."""
    eager, compiled = _eager_and_compiled()
    x = _x0(2)
    for step in range(3):
        for p in (eager, compiled):
            model = p.dynamics
            if step == 1:
                model.f = lambda z, model=model: _UserUnicycle.f(model, z) + 0.7
            if step == 2:
                del model.f
        a, b = eager(x), compiled(x)
        torch.testing.assert_close(b.rollouts, a.rollouts, atol=1e-10, rtol=1e-10)
        if step == 1:  # the drift moves every component of the first step by dt * 0.7
            moved = a.rollouts[..., 1, :] - a.rollouts[..., 0, :]
            assert bool((moved[..., :2].abs() > 0.0139).all())


def test_compile_failure_runs_eager(caplog):
    pytest.importorskip("torch._dynamo")

    def broken(graph, inputs):
        raise RuntimeError("no C++ compiler here")

    eager, planner = _user_planner(), _user_planner(compile={"backend": broken})
    x = _x0(2)
    with caplog.at_level(logging.WARNING, logger="torchcbf"):
        out = planner(x)
    assert "running eager" in caplog.text and "no C++ compiler here" in caplog.text
    torch.testing.assert_close(out.plan, eager(x).plan)
    torch.testing.assert_close(planner(x, 0.1).plan, eager(x, 0.1).plan)


@pytest.mark.parametrize("mode", ["range", "std"])
def test_normalized_weights(mode):
    K, lam = 40, 0.2
    seen = {}

    def cost(states, controls, t0):
        seen["controls"] = controls.clone()
        return 100.0 * (states[..., -1, :] ** 2).sum(-1)

    planner = MPPI(SingleIntegrator(2), cost, 3, K, 0.1, 1.0, lam, cost_normalization=mode)
    x = torch.tensor([1.0, -1.0], dtype=torch.float64)
    out = planner(x)
    v = seen["controls"][0]
    S = 100.0 * ((x + 0.1 * v.sum(1)) ** 2).sum(-1)
    scale = S.max() - S.min() if mode == "range" else S.std(correction=0)
    w = torch.softmax(-(S - S.min()) / scale / lam, 0)
    torch.testing.assert_close(out.plan, torch.einsum("k,khm->hm", w, v))
    torch.testing.assert_close(out.ess, 1.0 / (w**2).sum())


@pytest.mark.parametrize("backend", ["auto", "torch"])
def test_cost_slices_equal_one_call(backend):
    calls = []

    def cost(states, controls, t0):
        calls.append(states.shape[1])
        return ((states[..., 1:, :2] - 1.0) ** 2).sum((-1, -2)) + controls.square().sum((-1, -2))

    x = _x0(2)
    whole = MPPI(AccelUnicycle(), cost, 6, 50, 0.05, 1.0, 0.5, 0.1, cost_chunk=0, backend=backend)
    sliced = MPPI(AccelUnicycle(), cost, 6, 50, 0.05, 1.0, 0.5, 0.1, cost_chunk=7, backend=backend)
    a = whole(x)
    calls.clear()
    b = sliced(x)
    assert calls == [7] * 7 + [1]
    # equal up to the order of the cost's own sums over a slice and over all samples
    torch.testing.assert_close(a.plan, b.plan, rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(a.cost_min, b.cost_min, rtol=1e-12, atol=1e-12)
    with pytest.raises(ValueError, match="cost_chunk"):
        MPPI(AccelUnicycle(), cost, 6, 50, 0.05, 1.0, 0.5, cost_chunk=-1)
    bad = MPPI(AccelUnicycle(), lambda s, u, t: s[..., 0, 0], 6, 50, 0.05, 1.0, 0.5, cost_chunk=7)
    bad(x)  # the right shape per slice
    worse = MPPI(
        AccelUnicycle(), lambda s, u, t: s[:, :3, 0, 0], 6, 50, 0.05, 1.0, 0.5, cost_chunk=7
    )
    with pytest.raises(ValueError, match="cost must return shape"):
        worse(x)


@pytest.mark.parametrize("backend", ["auto", "torch"])
def test_batched_update_and_torch_noise_against_formulas(backend):
    """B = 3 environments: the update and control cost of each against the MPPI formulas
    on the samples the cost saw; the torch path's noise has covariance Sigma."""
    B, K, H, lam, gamma = 3, 4000, 3, 0.7, 0.3
    sigma = torch.tensor([[0.5, 0.1], [0.1, 0.3]], dtype=torch.float64)
    seen = {}

    def cost(states, controls, t0):
        seen["states"], seen["controls"] = states.clone(), controls.clone()
        return states[..., 1:, :].square().sum((-1, -2))

    planner = MPPI(
        SingleIntegrator(2), cost, H, K, 0.1, sigma, lam, gamma, seed=2, cost_chunk=0,
        backend=backend,
    )  # fmt: skip
    x = torch.tensor([[0.2, 0.1], [-1.0, 0.5], [0.3, 2.0]], dtype=torch.float64)
    first = planner(x)
    eps0 = seen["controls"].reshape(-1, 2)  # the first plan is zero
    torch.testing.assert_close(eps0.T.cov(), sigma, atol=0.03, rtol=0)
    out = planner(x, shift=False)
    v, states = seen["controls"], seen["states"]
    eps = v - first.plan.unsqueeze(1)
    S = states[..., 1:, :].square().sum((-1, -2))
    S = S + gamma * torch.einsum("bhm,mn,bkhn->bk", first.plan, torch.linalg.inv(sigma), eps)
    w = torch.softmax(-S / lam, -1)
    torch.testing.assert_close(out.plan, first.plan + torch.einsum("bk,bkhm->bhm", w, eps))
    torch.testing.assert_close(out.cost_min, S.min(-1).values)
    torch.testing.assert_close(out.best_states, states[torch.arange(B), S.argmin(-1)])


class _ConstantInput(ControlAffine):
    """A double integrator whose ``g`` is one constant ``[n, m]`` matrix (it broadcasts)."""

    def __init__(self) -> None:
        super().__init__(2, 1)

    def f(self, x):
        return torch.stack([x[..., 1], torch.zeros_like(x[..., 0])], -1)

    def g(self, x):
        return torch.tensor([[0.0], [1.0]], dtype=x.dtype)


def test_model_whose_g_broadcasts_plans_in_both_layouts():
    def planner(layout):
        return MPPI(_ConstantInput(), lambda s, u, t: (s**2).sum((-1, -2)), 5, 16, 0.1, 1.0,
                    1.0, seed=2, backend="torch", layout=layout, keep_rollouts=16)  # fmt: skip

    x = torch.tensor([1.0, 0.0], dtype=torch.float64)
    a, b = planner("component").double()(x), planner("sample").double()(x)
    torch.testing.assert_close(a.rollouts, b.rollouts, atol=1e-12, rtol=1e-12)
    torch.testing.assert_close(a.plan, b.plan, atol=1e-12, rtol=1e-12)


def test_cuda_graph_is_a_flag_that_changes_nothing_on_the_cpu():
    def make(**kw):
        return MPPI(SingleIntegrator(2), QuadraticGoal([1.0, 1.0]), 10, 64, 0.1, 0.5, 0.3, **kw)

    with pytest.raises(TypeError, match="cuda_graph"):
        make(cuda_graph=1)
    a, b = make(), make(cuda_graph=True)
    x = torch.zeros(2)
    for _ in range(3):
        pa, pb = a(x), b(x)
        assert torch.equal(pa.plan, pb.plan) and pb.path == pa.path


class _CostWithoutStorage(torch.nn.Module):
    """A torch cost holding tensors without storage of their own: a sparse matrix and a
    lazy layer's uninitialised parameters."""

    def __init__(self) -> None:
        super().__init__()
        self.W = torch.eye(2).to_sparse()
        self.net = torch.nn.LazyLinear(1)

    def forward(self, states, controls, t0):
        p = states[..., :2]
        return (p - torch.tensor([1.0, 0.5])).square().sum((-1, -2))


@pytest.mark.parametrize("backend", ["auto", "torch"])
@pytest.mark.parametrize("grad", [False, True])
def test_a_cost_holding_tensors_without_storage_plans(backend, grad):
    x = torch.tensor([0.0, 0.0])
    plain = lambda s, c, t: _CostWithoutStorage.forward(None, s, c, t)  # noqa: E731
    outs, paths = [], []
    # in grad mode the lazy layer's parameters send the planner to torch: the function cost
    # is asked to plan there too
    for cost, own in ((_CostWithoutStorage(), backend), (plain, "torch" if grad else backend)):
        planner = MPPI(SingleIntegrator(2), cost, 8, 64, 0.1, 1.0, 0.5, seed=3, backend=own)
        with torch.set_grad_enabled(grad):
            outs.append([planner(x).u for _ in range(3)])
        paths.append(planner.path)
    expected = "torch" if grad or backend == "torch" else "rollout"
    assert paths == [expected, expected]
    for a, b in zip(*outs, strict=True):
        torch.testing.assert_close(a, b, rtol=0, atol=0)


@pytest.mark.parametrize("backend", ["auto", "torch"])
def test_a_loaded_noise_covariance_is_sampled(backend):
    """``load_state_dict`` from a planner of another noise covariance (isotropic into
    isotropic, correlated into diagonal) plans as that planner: torch's draws (``noise_mu``
    set) follow the loaded covariance."""
    cost = QuadraticGoal([1.0, -1.0])
    for source_sigma, built_sigma in ((4.0, 1.0), ([[1.0, 0.9], [0.9, 4.0]], [1.0, 4.0])):
        planners = [
            MPPI(
                SingleIntegrator(2),
                cost,
                8,
                256,
                0.1,
                sigma,
                0.5,
                seed=0,
                noise_mu=0.0,
                backend=backend,
            )  # fmt: skip
            for sigma in (source_sigma, built_sigma)
        ]
        planners[1].load_state_dict(planners[0].state_dict())
        u = [p(torch.zeros(2)).u for p in planners]
        torch.testing.assert_close(u[0], u[1])


@pytest.mark.parametrize("backend", ["auto", "torch"])
@pytest.mark.parametrize("noise_mu", [None, 0.0])
def test_a_noise_covariance_written_in_place_is_sampled(backend, noise_mu):
    """noise_cov is the planner's noise: written in place (its factors follow), the next
    call plans as a planner built with it, on every sampling route."""
    cost = QuadraticGoal([1.0, -1.0])
    target = torch.tensor([[4.0, 1.0], [1.0, 4.0]])
    kw = {"seed": 0, "noise_mu": noise_mu, "backend": backend}
    made = [
        MPPI(SingleIntegrator(2), cost, 8, 256, 0.1, sigma, 0.5, **kw) for sigma in (1.0, target)
    ]
    made[0].noise_cov.copy_(target)
    u = [p(torch.zeros(2)).u for p in made]
    torch.testing.assert_close(u[0], u[1], atol=1e-5, rtol=1e-5)


@pytest.mark.parametrize("backend", ["auto", "torch"])
@pytest.mark.parametrize("how", ["data", "numpy", "number", "diagonal"])
def test_a_noise_covariance_set_any_way_is_sampled(backend, how):
    """Written through ``.data`` or a NumPy view (seen by value on the CPU), or assigned as a
    number or a diagonal (as the constructor takes it): the next call plans as a planner
    built with it, and so does the call after ``reset()``."""
    cost = QuadraticGoal([1.0, -1.0])
    target = 4.0 if how == "number" else [1.0, 4.0]
    made = [
        MPPI(SingleIntegrator(2), cost, 8, 64, 0.1, sigma, 0.5, seed=0, backend=backend)
        for sigma in (1.0, target)
    ]
    made[0](torch.zeros(2))
    made[0].reset()
    if how == "data":
        made[0].noise_cov.data.mul_(torch.tensor([1.0, 4.0]))
    elif how == "numpy":
        made[0].noise_cov.numpy()[1, 1] = 4.0
    else:
        made[0].noise_cov = torch.tensor(target)
    u = [p(torch.zeros(2)).u for p in made]
    torch.testing.assert_close(u[0], u[1], atol=1e-5, rtol=1e-5)


@pytest.mark.parametrize("how", ["data", "numpy"])
def test_a_noise_covariance_written_between_calls_without_a_version_is_seen(how):
    """A write that keeps the tensor's version, between two calls (no ``reset()``): the
    factors the next call samples with follow it (compared by value on the CPU)."""
    planner = MPPI(SingleIntegrator(2), QuadraticGoal([1.0, -1.0]), 8, 64, 0.1, 1.0, 0.5)
    planner(torch.zeros(2))
    if how == "data":
        planner.noise_cov.data.mul_(torch.tensor([1.0, 4.0]))
    else:
        planner.noise_cov.numpy()[1, 1] = 4.0
    planner(torch.zeros(2))
    torch.testing.assert_close(planner.noise_chol, torch.diag(torch.tensor([1.0, 2.0])))


def test_a_noise_covariance_of_another_dtype_or_a_number_is_taken_in_the_planners():
    planner = MPPI(SingleIntegrator(2), QuadraticGoal([1.0, -1.0]), 8, 64, 0.1, 1.0, 0.5)
    planner.noise_cov = torch.tensor([[1.0, 0.0], [0.0, 4.0]], dtype=torch.float64)
    assert planner.noise_cov.dtype == torch.float32
    planner(torch.zeros(2))
    torch.testing.assert_close(planner.noise_chol, torch.diag(torch.tensor([1.0, 2.0])))
    planner.noise_cov = 9.0
    planner(torch.zeros(2))
    torch.testing.assert_close(planner.noise_chol, 3.0 * torch.eye(2))
    planner.noise_cov = 0.1  # a number is kept exact, as the constructor keeps it
    assert float(planner.double().noise_cov[0, 0]) == 0.1


def test_a_noise_covariance_set_between_calls_is_checked():
    planner = MPPI(SingleIntegrator(2), QuadraticGoal([1.0, -1.0]), 8, 64, 0.1, 1.0, 0.5)
    for bad, message in (
        ([[1.0, 0.9], [0.0, 1.0]], "noise_cov must be symmetric"),
        ([[2.0, 2.0], [2.0, 2.0]], "noise_cov must be positive definite"),
        ([[1.0, 0.0, 0.0]], r"noise_cov must be a scalar, \[2\] or \[2, 2\]"),
    ):
        with pytest.raises(ValueError, match=message):
            planner.noise_cov = torch.tensor(bad)
    planner.noise_cov.copy_(torch.tensor([[1.0, 2.0], [2.0, 1.0]]))
    with pytest.raises(ValueError, match="noise_cov must be positive definite"):
        planner(torch.zeros(2))


def test_a_number_of_samples_set_after_a_call_is_sampled_on_every_path():
    """``num_samples`` (and ``layout``) set between calls: the sample buffers follow, and
    the paths still agree for one seed."""
    plans = []
    for backend in ("auto", "torch"):
        planner = MPPI(SingleIntegrator(2), QuadraticGoal([1.0, -1.0]), 8, 128, 0.1, 1.0, 0.5,
                       seed=0, backend=backend)  # fmt: skip
        planner(torch.zeros(3, 2))
        planner.num_samples = 64
        out = planner(torch.zeros(3, 2))
        planner.layout = "sample"
        plans.append((out.plan, planner(torch.zeros(3, 2)).plan))
    for a, b in zip(*plans, strict=True):
        torch.testing.assert_close(a, b, atol=1e-5, rtol=1e-5)


@pytest.mark.parametrize("backend", ["auto", "torch"])
@pytest.mark.parametrize("variant", ["MPPI", "SMPPI", "KMPPI"])
def test_a_differentiable_call_leaves_no_graph_to_the_next(variant, backend):
    from torchcbf.mppi import KMPPI, SMPPI

    cls = {"MPPI": MPPI, "SMPPI": SMPPI, "KMPPI": KMPPI}[variant]
    planner = cls(
        DoubleIntegrator(2), QuadraticGoal([1.0, 1.0], index=(0, 1)), 6, 40, 0.1, 0.5, 0.5, 0.3,
        u_min=-1.0, u_max=1.0, backend=backend,
    ).double()  # fmt: skip
    x = torch.tensor([[0.0, 0.0, 0.3, 0.1]], dtype=torch.float64)
    x1 = x.clone().requires_grad_()
    first = planner(x1)
    grad = None
    if first.u.requires_grad:  # this call's outputs carry its graph
        (grad,) = torch.autograd.grad(first.u.sum(), x1, retain_graph=True)
        assert bool(torch.isfinite(grad).all())
    for i in range(3):  # later calls on plain states: nothing to differentiate, nothing kept
        out = planner(x + 0.01 * (i + 1))
        assert not out.u.requires_grad and not out.plan.requires_grad
    assert not any(t.requires_grad for t in planner._kept())
    if grad is not None:  # the first call's graph is intact after the later calls
        torch.testing.assert_close(torch.autograd.grad(first.u.sum(), x1)[0], grad)


@pytest.mark.parametrize(
    ("name", "value"),
    [
        ("temperature", -1.0),
        ("temperature", 0.0),
        ("control_cost_weight", -0.5),
        ("cost_normalization", "ranged"),
        ("shift_fill", "lst"),
        ("integrator", "rk5"),
        ("zero_noise_samples", 50),
        ("keep_rollouts", 41),
    ],
)
def test_an_option_set_between_calls_is_checked_as_the_constructor_checks_it(name, value):
    planner = MPPI(
        DoubleIntegrator(2), QuadraticGoal([1.0, 1.0], index=(0, 1)), 6, 40, 0.1, 0.5, 0.5
    )
    x = torch.zeros(4)
    planner(x)
    setattr(planner, name, value)
    with pytest.raises(ValueError, match=name):
        planner(x)
    with pytest.raises(ValueError, match=name):  # the same message at construction
        MPPI(
            DoubleIntegrator(2), QuadraticGoal([1.0, 1.0], index=(0, 1)), 6, 40, 0.1, 0.5,
            **{"temperature": 0.5, name: value},
        )  # fmt: skip


def test_numpy_numbers_are_options_like_python_ones():
    import numpy as np

    kw = {"keep_rollouts": np.int64(3), "zero_noise_samples": np.int32(2)}
    goal = QuadraticGoal([1.0, 1.0], index=(0, 1))
    planner = MPPI(DoubleIntegrator(2), goal, 6, 40, 0.1, 0.5, np.float32(0.5), **kw)
    ref = MPPI(DoubleIntegrator(2), copy.deepcopy(goal), 6, 40, 0.1, 0.5, 0.5, keep_rollouts=3,
               zero_noise_samples=2)  # fmt: skip
    x = torch.zeros(4)
    torch.testing.assert_close(planner(x).plan, ref(x).plan)
    planner.num_samples, planner.temperature = np.int64(64), np.float32(0.3)
    planner.control_cost_weight = np.float64(0.1)
    ref.num_samples, ref.temperature, ref.control_cost_weight = 64, float(np.float32(0.3)), 0.1
    torch.testing.assert_close(planner(x).plan, ref(x).plan)


@pytest.mark.parametrize("layout", ["component", "sample"])
def test_the_plans_gradient_through_a_nonlinear_model_matches_differences(layout):
    """A unicycle's step saves the heading's cosine for its backward: stepping into the
    rollout buffer in place changed it (an autograd error for every nonlinear model)."""
    from torchcbf.dynamics import Unicycle

    def plan(x):
        planner = MPPI(
            Unicycle(), QuadraticGoal([1.0, 1.0], index=(0, 1)), 6, 40, 0.1, 0.3, 0.5, 0.2,
            layout=layout, seed=3,
        ).double()  # fmt: skip
        return planner(x).u

    x = torch.tensor([0.1, -0.2, 0.3], dtype=torch.float64, requires_grad=True)
    (grad,) = torch.autograd.grad(plan(x).sum(), x)
    eye = torch.eye(3, dtype=torch.float64)
    with torch.no_grad():
        diff = torch.stack([(plan(x + 1e-6 * e) - plan(x - 1e-6 * e)).sum() / 2e-6 for e in eye])
    torch.testing.assert_close(grad, diff, rtol=1e-5, atol=1e-7)


@pytest.mark.parametrize("backend", ["auto", "torch"])
def test_a_cost_closure_that_requires_grad_keeps_the_plans_gradient(backend):
    """A cost reading a learnable goal from its closure: the rollout kernel's update cut the
    plan's gradient (zero where differences give [0.26, 0.85]); both paths now agree."""
    goal = torch.tensor([1.0, 0.5], dtype=torch.float64, requires_grad=True)

    def plan(target):
        def cost(states, controls, t0=None):
            return ((states[..., 1:, :] - target) ** 2).sum((-1, -2))

        planner = MPPI(SingleIntegrator(2), cost, 5, 50, 0.1, 0.3, 0.5, 0.2, backend=backend)
        return planner.double()(torch.zeros(2, dtype=torch.float64))

    out = plan(goal)
    assert out.plan.requires_grad
    (grad,) = torch.autograd.grad(out.plan.sum(), goal)
    eye = torch.eye(2, dtype=torch.float64)
    with torch.no_grad():
        diff = torch.stack(
            [(plan(goal + 1e-6 * e).plan - plan(goal - 1e-6 * e).plan).sum() / 2e-6 for e in eye]
        )
    torch.testing.assert_close(grad, diff, rtol=1e-5, atol=1e-8)


def test_a_time_that_is_not_finite_is_refused_or_plans_nothing() -> None:
    """Its windows would all be empty and its obstacles ignored: a number, list or array is
    refused; a row of a tensor reports status 1 and leaves the other rows alone, whatever
    the cost (an Avoid alone gives such a row a finite cost)."""
    import numpy as np

    from torchcbf.mppi import Avoid

    planner = _planner()
    x = torch.zeros(3, planner.dynamics.state_dim, dtype=torch.float64)
    for t in (math.nan, math.inf, [0.0, math.nan, 0.0], np.float32("nan")):
        with pytest.raises(ValueError, match="t must be finite"):
            planner(x, t=t)
    with pytest.raises(TypeError, match="t must be a number or a tensor of times"):
        planner(x, t=True)
    t = torch.tensor([0.0, math.nan, 0.0], dtype=torch.float64)
    out, ref = _planner()(x, t=t), _planner()(x, t=0.0)
    assert out.status.tolist() == [0, 1, 0]
    torch.testing.assert_close(out.u[[0, 2]], ref.u[[0, 2]])
    dyn = AccelUnicycle(u_min=-2.0, u_max=2.0)
    sigma = torch.tensor([[1.0, 0.3], [0.3, 0.5]])
    only_avoid = MPPI(dyn, Avoid([1.0, 0.0], 0.3), 8, 64, 0.02, sigma, 0.5, 0.1, seed=0)
    assert only_avoid(x, t=t).status.tolist() == [0, 1, 0]


@pytest.mark.parametrize("kind", ["MPPI", "SMPPI", "KMPPI"])
@pytest.mark.parametrize("bad", [math.nan, math.inf])
def test_a_candidate_that_is_not_finite_has_no_say_in_the_plan(kind: str, bad: float) -> None:
    from torchcbf.mppi import KMPPI, SMPPI

    cls = {"MPPI": MPPI, "SMPPI": SMPPI, "KMPPI": KMPPI}[kind]
    H, f64 = 4, torch.float64
    candidate = torch.zeros(1, H, 2, dtype=f64)
    candidate[0, 2, 0] = bad
    limits = {"u_min": -1.0, "u_max": 1.0} if math.isnan(bad) else {}
    planner = cls(SingleIntegrator(2), QuadraticGoal([1.0, 1.0]), H, 16, 0.1, 0.5, 0.5,
                  action_sampler=lambda x, t: candidate, **limits).double()  # fmt: skip
    for call in range(3):
        out = planner(torch.zeros(2, dtype=f64), t=0.1 * call)
        assert int(out.status) == 0 and int(out.nonfinite) == 1
        assert bool(torch.isfinite(out.plan).all()) and bool(torch.isfinite(out.u).all())


def test_std_normalisation_of_widely_spread_float32_costs() -> None:
    def cost(states, controls, t0):
        value = torch.full(states.shape[:2], 1e20, dtype=states.dtype)
        value[:, 0], value[:, 1] = 0.0, 1e19
        return value

    weights = [
        MPPI(SingleIntegrator(2), cost, 3, 8, 0.1, 0.5, 0.5, keep_rollouts=8,
             cost_normalization="std").to(dtype)(torch.zeros(2, dtype=dtype)).rollout_weights
        for dtype in (torch.float64, torch.float32)
    ]  # fmt: skip
    torch.testing.assert_close(weights[1], weights[0].float())
    assert float(weights[0][0]) > 0.5


@pytest.mark.parametrize("normalization", ["std", "range"])
def test_normalised_weights_do_not_depend_on_the_costs_scale(normalization) -> None:
    """``(S - min S) / spread`` is scale-free: costs ``k s`` weigh the same for ``s = 1``
    and ``s = 1e200`` (whose squares overflow float64)."""

    def weights(scale: float) -> torch.Tensor:
        def cost(states, controls, t0):
            return scale * torch.arange(states.shape[1], dtype=states.dtype).expand(
                states.shape[:2]
            )

        planner = MPPI(SingleIntegrator(2), cost, 3, 8, 0.1, 0.5, 0.5, keep_rollouts=8,
                       cost_normalization=normalization).double()  # fmt: skip
        return planner(torch.zeros(2, dtype=torch.float64)).rollout_weights

    torch.testing.assert_close(weights(1e200), weights(1.0), rtol=1e-12, atol=1e-15)
    assert float(weights(1.0)[0]) > 0.25  # not the uniform 1/8


def test_limits_flags_and_integers_are_checked_as_given() -> None:
    import numpy as np

    from torchcbf.mppi import SMPPI

    def make(**kw):
        return MPPI(SingleIntegrator(2), QuadraticGoal([1.0, 1.0]), 4, 8, 0.1, 0.4, 1.0, **kw)

    planner = make(u_min=-1.0, u_max=1.0)
    with pytest.raises(ValueError, match="u_max must not contain NaN"):
        planner.u_max = torch.tensor([math.nan, 1.0])
    with pytest.raises(ValueError, match=r"u_min \[2.0, 2.0\] exceeds u_max"):
        planner.u_min = torch.tensor([2.0, 2.0])
    bound = torch.tensor([0.5, 0.5])
    planner.u_max = bound  # a valid bound is taken as given
    assert planner.u_max is bound
    assert float(planner(torch.zeros(2)).u.abs().max()) <= 0.5
    fresh = make(u_min=-1.0, u_max=1.0)
    fresh.u_min, fresh.u_max = torch.tensor(-0.05), torch.tensor([0.5, 0.5])
    assert fresh.u_min.tolist() == pytest.approx([-0.05, -0.05])  # one number for each
    torch.testing.assert_close(
        fresh(torch.zeros(2)).plan, make(u_min=-0.05, u_max=0.5)(torch.zeros(2)).plan
    )
    smooth = SMPPI(SingleIntegrator(2), QuadraticGoal([1.0, 1.0]), 4, 8, 0.1, 0.4, 1.0,
                   du_min=-1.0, du_max=1.0)  # fmt: skip
    with pytest.raises(ValueError, match=r"du_min \[2.0, 2.0\] exceeds du_max"):
        smooth.du_min = torch.tensor([2.0, 2.0])
    with pytest.raises(TypeError, match="compile must be True, False or a dict"):
        make(compile="no")
    assert make(compile=np.False_)._compiled is False
    with pytest.raises(TypeError, match="shift must be a bool"):
        planner(torch.zeros(2), shift="False")
    with pytest.raises(ValueError, match="smoothness_weight must be a finite number >= 0"):
        SMPPI(SingleIntegrator(2), QuadraticGoal([1.0, 1.0]), 4, 8, 0.1, 0.4, 1.0,
              smoothness_weight=math.inf)  # fmt: skip
    assert make(seed=np.int64(1)).seed == 1
    goal = QuadraticGoal([1.0, 1.0])
    assert MPPI(SingleIntegrator(2), goal, np.int64(3), 8, 0.1, 0.4, 1.0).horizon == 3
    # torch's generator reads 32 bits: seed + 2^32 would plan as seed
    for bad in (2**64 - 1, 2**32, -1):
        with pytest.raises(ValueError, match=r"seed must lie in \[0, 2\^32\)"):
            make(seed=bad)
    last = make(seed=2**32 - 1)
    last(torch.zeros(2))  # one environment: seed 2^32 - 1
    with pytest.raises(ValueError, match=r"seed must lie in \[0, 4294967293\] for 3"):
        last(torch.zeros(3, 2))  # its rows would reach 2^32
