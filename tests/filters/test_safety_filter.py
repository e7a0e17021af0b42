"""SafetyFilter: agreement with cvxpy in every mode, statuses, fallbacks, shapes, errors."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from _devices import device_matches_cpu
from _filter_reference import (
    BETA,
    CENTERS,
    CLF_ETA,
    CLF_GAMMA,
    CLF_RATE,
    CLF_W,
    ETA,
    GAINS,
    GOAL,
    HORIZON,
    RADII,
    RHO,
    SIGMA,
    U_MAX,
    U_MIN,
    W_MAX,
    WALL_A,
    WALL_B,
    R,
    least_violation,
    rows,
    solve_reference,
)

from torchcbf.barriers import Ball, HalfSpace, QuadraticLyapunov
from torchcbf.dynamics import SingleIntegrator, Unicycle
from torchcbf.filters import (
    FilterStatus,
    LinearClassK,
    RiskAware,
    Robust,
    SafetyFilter,
    Slack,
    Stochastic,
    Vanilla,
)
from torchcbf.qp import Status

MODES = ["vanilla", "robust", "stochastic", "risk_aware"]


MODE_OBJECTS = {
    "vanilla": lambda: Vanilla(),
    "robust": lambda: Robust(),
    "stochastic": lambda: Stochastic(beta=BETA),
    "risk_aware": lambda: RiskAware(
        RHO, HORIZON, torch.tensor(ETA), clf_eta=CLF_ETA, clf_gamma=CLF_GAMMA
    ),
}


def _tol(dtype: torch.dtype) -> float:
    return 1e-6 if dtype == torch.float64 else 1e-3


def scene(
    mode: str, dtype: torch.dtype = torch.float64, clf: bool = True, **overrides
) -> SafetyFilter:
    kw: dict = {}
    if mode == "robust":
        kw["disturbance_bound"] = W_MAX
    if mode in ("stochastic", "risk_aware"):
        kw["sigma"] = SIGMA
    dyn = Unicycle(u_min=torch.tensor(U_MIN), u_max=torch.tensor(U_MAX), **kw)
    barriers = [
        Ball(torch.tensor(CENTERS), torch.tensor(RADII)),
        HalfSpace(WALL_A, WALL_B, index=(0, 1)),
    ]
    options = dict(
        mode=MODE_OBJECTS[mode](),
        alpha=torch.tensor(GAINS),
        clf_rate=CLF_RATE,
        R=torch.tensor(R),
        slack=Slack(clf_weight=CLF_W),
    )
    options.update(overrides)
    lyap = [QuadraticLyapunov(GOAL)] if clf else []
    return SafetyFilter(dyn, barriers, lyap, **options).to(dtype)


def random_states(count: int, seed: int, margin: float = 0.05) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    out = []
    while len(out) < count:
        x = np.array([rng.uniform(-2.5, 3.0), rng.uniform(-1.0, 2.4), rng.uniform(-np.pi, np.pi)])
        if rows(x, "vanilla")[4].min() > margin:
            out.append(x)
    return np.stack(out), 2.0 * rng.standard_normal((count, 2))


@pytest.mark.parametrize("clf", [True, False], ids=["cbf+clf", "cbf"])
@pytest.mark.parametrize("mode", MODES)
def test_matches_cvxpy_hard_qp(mode: str, clf: bool, dtype: torch.dtype) -> None:
    xs, us = random_states(24, seed=MODES.index(mode))
    filt = scene(mode, dtype, clf=clf)
    # with a CLF the hard and elastic QPs are solved together, without one the elastic alone
    assert filt.slack.exact == clf
    out = filt(torch.tensor(xs, dtype=dtype), torch.tensor(us, dtype=dtype))
    feasible = infeasible = 0
    for i in range(len(xs)):
        ref = solve_reference(xs[i], us[i], mode, clf=clf)
        if ref is None:  # the hard QP is infeasible: the least-violating control
            infeasible += 1
            assert out.status[i] == FilterStatus.RELAXED
            norms = np.maximum(np.linalg.norm(rows(xs[i], mode)[0], axis=1), 1e-6)
            total = (out.slack[i, :3].double().numpy() / norms).max()
            best = least_violation(xs[i], mode)
            assert best > 0 and abs(total - best) <= 1e-3 * (1 + best), (total, best)
            continue
        feasible += 1
        assert out.status[i] == FilterStatus.SOLVED, (i, out.slack[i])
        got = out.u[i].double().numpy()
        assert np.allclose(got, ref, atol=_tol(dtype), rtol=0), (i, got, ref)
    assert feasible >= 12
    # the constraints were active somewhere (the filter did change u_nom)
    assert (out.u - torch.tensor(us, dtype=dtype)).abs().amax() > 0.1


@pytest.mark.parametrize("states", [32, 300])  # 300: past the batched QP's small-batch path
@pytest.mark.parametrize("mode", MODES)
def test_device_answers_equal_cpu_answers(
    mode: str, states: int, dtype: torch.dtype, device
) -> None:
    xs, us = random_states(states, seed=11 + MODES.index(mode))

    def run(dev: torch.device):
        filt = scene(mode, dtype).to(dev)
        x = torch.tensor(xs, dtype=dtype, device=dev)
        out = filt(x, torch.tensor(us, dtype=dtype, device=dev))
        return out.u, out.status, out.h, out.slack

    # float32: the QP's own accuracy, as against cvxpy above
    loose = {} if dtype == torch.float64 else {"rtol": 1e-3, "atol": _tol(dtype)}
    u, status, h, slack = device_matches_cpu(run, device, dtype, **loose)
    assert bool(torch.isfinite(u).all()) and bool(torch.isfinite(slack).all())
    known = (FilterStatus.SOLVED, FilterStatus.RELAXED)
    assert bool(torch.isin(status, torch.tensor(known, device=status.device)).all())
    assert bool((h > 0).all())  # random_states draws safe states


def test_a_filter_of_modules_on_a_device_lives_there(dtype, device) -> None:
    """A filter built from a model and barriers already on the device takes its own buffers
    there (no ``.to`` needed) and answers as one built on the CPU and moved."""
    f = {"device": device, "dtype": dtype}
    dyn = SingleIntegrator(2, u_min=-1.0, u_max=1.0).to(**f)
    filt = SafetyFilter(dyn, Ball(torch.zeros(2, **f), torch.tensor(0.5, **f)), alpha=2.0)
    assert all(t.device.type == torch.device(device).type for t in filt.buffers())
    moved = SafetyFilter(SingleIntegrator(2, u_min=-1.0, u_max=1.0), Ball([0.0, 0.0], 0.5),
                         alpha=2.0).to(**f)  # fmt: skip
    x = torch.tensor([[-1.0, 0.1], [0.2, -0.9]], **f)
    u = torch.tensor([[1.0, 0.0], [0.0, 1.0]], **f)
    torch.testing.assert_close(filt(x, u).u, moved(x, u).u)


def test_constraint_values_and_outputs() -> None:
    xs, us = random_states(16, seed=7)
    filt = scene("vanilla")
    out = filt(torch.tensor(xs), torch.tensor(us))
    for i in range(len(xs)):
        a, b, aV, bV, h = rows(xs[i], "vanilla")
        u = out.u[i].numpy()
        assert np.allclose(out.h[i].numpy(), h, atol=1e-12)
        assert np.allclose(out.constraint_value[i, :3].numpy(), a @ u + b, atol=1e-9)
        assert np.allclose(out.constraint_value[i, 3:].numpy(), -(aV @ u + bV), atol=1e-9)
        assert np.allclose(out.clf_value[i, 0].item(), ((xs[i, :2] - GOAL) ** 2).sum())
    solved = out.status == FilterStatus.SOLVED
    assert bool((out.constraint_value[solved, :3] >= -1e-8).all())
    # the CLF slack makes the relaxed CLF row hold exactly: a.u + b <= delta
    assert torch.allclose((-out.constraint_value[:, 3]).clamp_min(0), out.slack[:, 3], atol=1e-7)
    assert out.slack.shape == (16, 4) and out.qp_status.dtype == torch.int64


def test_infeasible_rows_are_relaxed_least_violating(dtype: torch.dtype) -> None:
    # two walls that leave no room: x <= -1 and x >= 1
    dyn = SingleIntegrator(1, u_min=-1.0, u_max=1.0)
    walls = HalfSpace(torch.tensor([[1.0], [-1.0]]), torch.tensor([-1.0, -1.0]))
    filt = SafetyFilter(dyn, walls, alpha=1.0).to(dtype)
    x = torch.tensor([[0.0], [0.5]], dtype=dtype)
    out = filt(x, torch.zeros(2, 1, dtype=dtype))
    # rows 0 and 1: h = (-1 - x, -1 + x): u >= 1 + x and u <= x - 1 cannot both hold
    assert out.status[:2].tolist() == [FilterStatus.RELAXED] * 2
    # least violation: the largest violation is smallest (1) midway, at u = -x
    assert torch.allclose(out.u[:2, 0], -x[:2, 0], atol=_tol(dtype))
    assert torch.allclose(out.slack[:2], torch.ones_like(out.slack[:2]), atol=_tol(dtype))
    assert bool((out.slack[:2] > 0.5).all())

    assert torch.isfinite(out.u).all()


@pytest.mark.parametrize("backend", ["auto", "torch"])
def test_a_clf_does_not_pull_a_relaxed_row_deeper(
    dtype: torch.dtype, backend: str, device: torch.device
) -> None:
    """States inside a ball, controls too small to leave it (the hard QP infeasible), a goal
    behind the ball: the CBF rows alone give the least violation; a CLF pulling towards the
    goal (V about 11) had the elastic QP drive through the ball's centre (a . u + b of
    -0.22 where -0.10 was possible), RELAXED all the same."""
    dyn = SingleIntegrator(2, u_min=-0.1, u_max=0.1)
    ball = Ball([1.0, 0.0], 0.5)
    angles = torch.linspace(0.0, 2 * math.pi, 9, dtype=dtype, device=device)[:-1]
    x = torch.stack((1.0 + 0.3 * angles.cos(), 0.3 * angles.sin()), -1)
    x = torch.cat((x, torch.tensor([[3.0, 0.0]], dtype=dtype, device=device)))  # outside
    u_nom = torch.zeros_like(x)
    alone = SafetyFilter(dyn, ball, backend=backend).to(device, dtype)(x, u_nom)
    for goal in ([1.0, 3.0], [1.0, -3.0], [4.0, 0.0], [1.0, 0.6]):
        clf = QuadraticLyapunov(goal)
        out = SafetyFilter(dyn, ball, clf, backend=backend).to(device, dtype)(x, u_nom)
        assert (out.status[:-1] == FilterStatus.RELAXED).all()
        assert out.status[-1] == FilterStatus.SOLVED  # the hard QP answers outside the ball
        least = alone.constraint_value[:-1, 0]
        assert (out.constraint_value[:-1, 0] >= least - _tol(dtype)).all(), (goal, out.u)
        assert out.constraint_value[-1, 0] >= 0
        # the CLF's relaxation is reported at the control returned
        V_rate = -out.constraint_value[:, 1]
        torch.testing.assert_close(out.slack[:, 1], V_rate.clamp_min(0), atol=_tol(dtype), rtol=0)


def test_nonfinite_rows_fallback_and_others_untouched(dtype: torch.dtype) -> None:
    xs, us = random_states(6, seed=3)
    filt = scene("vanilla", dtype)
    x = torch.tensor(xs, dtype=dtype)
    u = torch.tensor(us, dtype=dtype)
    clean = filt(x, u)
    x_bad, u_bad = x.clone(), u.clone()
    x_bad[1, 0] = math.nan
    u_bad[3, 1] = math.nan
    out = filt(x_bad, u_bad)
    assert out.status[1] == FilterStatus.NON_FINITE and out.status[3] == FilterStatus.NON_FINITE
    assert torch.isfinite(out.u).all()
    lo, hi = torch.tensor(U_MIN, dtype=dtype), torch.tensor(U_MAX, dtype=dtype)
    assert torch.equal(out.u[1], torch.clamp(u[1], lo, hi))  # fallback "clip"
    assert torch.equal(out.u[3], torch.clamp(torch.zeros(2, dtype=dtype), lo, hi))  # NaN u_nom
    keep = [0, 2, 4, 5]
    assert torch.allclose(out.u[keep], clean.u[keep], atol=_tol(dtype) * 1e-2)
    assert torch.equal(out.status[keep], clean.status[keep])
    assert torch.isnan(out.h[1]).all() and torch.isfinite(out.h[keep]).all()


@pytest.mark.parametrize("path", ["auto", "torch"])
def test_a_row_whose_conditions_are_not_finite_leaves_the_gradients_clean(path: str) -> None:
    """A state at the centre of a radius-form ellipse has a 0/0 derivative: that row falls
    back (qp_status NON_FINITE, its QP was a stand-in), and the gradients of the shared
    learnable centre, axes and class-K gain are those of the batch without it."""
    from torchcbf.barriers import Ellipse, Transformed
    from torchcbf.filters import LinearClassK

    def grads(x, u):
        dyn = SingleIntegrator(2, u_min=-2.0, u_max=2.0)
        ell = Ellipse([1.0, 0.0], [0.5, 0.3], learnable=True)
        gain = LinearClassK(1.0, learnable=True)
        filt = SafetyFilter(dyn, Transformed(ell, "radius"), alpha=gain, backend=path).double()
        out = filt(x, u)
        (out.u[:2] ** 2).sum().backward()
        return out, {n: p.grad.clone() for n, p in filt.named_parameters()}

    x = torch.tensor([[0.0, 0.0], [0.2, 0.1], [1.0, 0.0]], dtype=torch.float64)
    u = torch.tensor([[1.0, 0.0], [1.0, 0.2], [1.0, 0.0]], dtype=torch.float64)
    out, with_centre = grads(x, u)
    _, without = grads(x[:2], u[:2])
    assert out.status.tolist() == [0, 0, FilterStatus.FALLBACK]
    assert int(out.qp_status[2]) == Status.NON_FINITE
    for name, g in without.items():
        assert torch.isfinite(g).all() and bool((g != 0).any()), name
        torch.testing.assert_close(with_centre[name], g, atol=1e-12, rtol=1e-12)


@pytest.mark.parametrize("fallback", ["clip", "brake", "tensor", "callable"])
def test_fallback_on_qp_failure(fallback: str) -> None:
    xs, us = random_states(4, seed=5)
    spec = {
        "clip": "clip",
        "brake": "brake",
        "tensor": torch.tensor([0.5, -0.5]),
        "callable": lambda x, u: -u,
    }[fallback]
    # the general path with a QP that gives up on every row: one interior point iteration,
    # no polishing
    options = {"method": "ipm", "max_iter": 1, "polish": False}
    filt = scene("vanilla", fallback=spec, backend="torch", qp_options=options)
    x, u = torch.tensor(xs), torch.tensor(us)
    out = filt(x, u)
    assert out.path == "torch/ipm"
    assert (out.qp_status == Status.MAX_ITER).all()
    assert (out.status == FilterStatus.FALLBACK).all()
    lo, hi = torch.tensor(U_MIN), torch.tensor(U_MAX)
    expected = {
        "clip": torch.clamp(u, lo, hi),
        "brake": torch.zeros_like(u),
        "tensor": torch.tensor([0.5, -0.5]).expand_as(u),
        "callable": torch.clamp(-u, lo, hi),
    }[fallback]
    assert torch.equal(out.u, expected)
    assert (out.slack == 0).all()


def test_an_unused_callable_fallback_leaves_gradients_alone() -> None:
    """A callable fallback whose derivatives are NaN at a row that does not fall back
    (``x / |x|`` at ``x = 0``) leaves that row's gradient as 'brake' gives it and its own
    parameter untouched; at a row that falls back it is clipped to the limits and its
    parameter gets the gradient of its clipped value."""
    from torchcbf.barriers import Ball
    from torchcbf.dynamics import SingleIntegrator

    f64 = torch.float64
    model = SingleIntegrator(2, u_min=-2.0, u_max=2.0)
    balls = Ball([[1.0, 0.0], [0.0, 1.5]], [0.5, 0.4]).double()
    k = torch.tensor(3.0, dtype=f64, requires_grad=True)
    away = lambda x, u: -k * x / x.norm(dim=-1, keepdim=True)  # noqa: E731
    x = torch.tensor([[0.0, 0.0], [0.3, 0.0], [-1.0, 1.4]], dtype=f64, requires_grad=True)
    u = torch.tensor([[1.0, 0.0], [2.0, 0.0], [0.5, 1.0]], dtype=f64)
    for backend in ("auto", "torch"):
        out = SafetyFilter(model, balls, alpha=1.0, fallback=away, backend=backend)(x, u)
        ref = SafetyFilter(model, balls, alpha=1.0, fallback="brake", backend=backend)(x, u)
        assert out.status.tolist() == ref.status.tolist() == [0, 0, 0]
        (gx, gk) = torch.autograd.grad(out.u.sum(), (x, k), allow_unused=True)
        (gx_ref,) = torch.autograd.grad(ref.u.sum(), (x,))
        torch.testing.assert_close(gx, gx_ref, atol=0.0, rtol=0.0)
        assert gk is None or float(gk) == 0.0
    # the ball's centre with no slack: that row falls back to -k x/|x| = (-3, 0) -> (-2, 0)
    x = torch.tensor([[1.0 + 1e-3, 0.0], [0.3, 0.0]], dtype=f64, requires_grad=True)
    k2 = torch.tensor(1.5, dtype=f64, requires_grad=True)
    soft = lambda x, u: -k2 * x / x.norm(dim=-1, keepdim=True)  # noqa: E731
    for kk, fb, want_u, want_gk in ((k, away, -2.0, 0.0), (k2, soft, -1.5, -1.0)):
        out = SafetyFilter(model, balls, alpha=1.0, fallback=fb, slack="none")(x, u[:2])
        assert out.status.tolist()[0] == FilterStatus.FALLBACK
        torch.testing.assert_close(out.u[0], torch.tensor([want_u, 0.0], dtype=f64))
        (gk,) = torch.autograd.grad(out.u[0, 0], (kk,))
        torch.testing.assert_close(gk, torch.tensor(want_gk, dtype=f64))


def test_a_trainable_fallback_gets_a_gradient_on_every_path_and_batch() -> None:
    """A fallback parameter is trained: the control carries a graph whether or not a row of
    the batch falls back (zero where none does), on every backend."""
    f64 = torch.float64
    model = SingleIntegrator(2, u_min=-2.0, u_max=2.0)
    ball = Ball([1.0, 0.0], 0.5).double()
    fallback = param = torch.nn.Parameter(torch.tensor([0.5, -0.5], dtype=f64))
    x = torch.tensor([[-1.0, 0.0], [1.0, 0.0]], dtype=f64)  # the second at the centre
    u = torch.tensor([[1.0, 0.0], [1.0, 0.0]], dtype=f64)
    for backend in ("auto", "torch"):
        filt = SafetyFilter(model, [ball], alpha=1.0, fallback=fallback, slack="none",
                            backend=backend)  # fmt: skip
        assert any(p is param for p in filt.parameters())
        for part, falls in ((slice(0, 1), False), (slice(0, 2), True)):
            out = filt(x[part], u[part])
            assert out.u.requires_grad, (backend, part)
            # the one-state path keeps serving a batch where no row falls back
            assert out.path.endswith("realtime") == (backend == "auto" and not falls)
            (g,) = torch.autograd.grad(out.u.sum(), (param,))
            assert bool((g != 0).any()) == falls, (backend, part)


def test_a_stochastic_margin_given_as_a_parameter_is_trained() -> None:
    beta = torch.nn.Parameter(torch.tensor(0.1, dtype=torch.float64))
    mode = Stochastic(beta=beta)
    assert [name for name, _ in mode.named_parameters()] == ["beta"] and mode.beta is beta
    assert list(dict(mode.named_buffers())) == []


def test_a_fallback_row_where_the_callable_is_not_finite_leaves_shared_gradients_alone() -> None:
    """Rows that fall back where the callable is NaN (a non-finite state, or its own 0/0)
    get zero clipped to the limits, and rows where it is infinite its value clipped; neither
    puts NaN in the gradient of a parameter the callable shares with the other rows."""
    from torchcbf.barriers import Ball
    from torchcbf.dynamics import SingleIntegrator
    from torchcbf.filters import Stochastic

    f64 = torch.float64
    model = SingleIntegrator(2, u_min=-0.3, u_max=0.3, sigma=0.2)
    k = torch.tensor(0.2, dtype=f64, requires_grad=True)
    centre = torch.tensor([1.0, 0.0], dtype=f64)
    for fallback in (
        lambda x, u: -k * x,
        lambda x, u: k * (x - centre) / (x - centre).norm(dim=-1, keepdim=True),
        lambda x, u: -k / x,  # -inf at (1, 0): clipped to the limit, without a gradient
    ):
        filt = SafetyFilter(
            model, Ball([1.0, 0.0], 0.5), mode=Stochastic(0.1), slack="none", fallback=fallback
        )
        x = torch.tensor([[0.9, 0.1], [math.nan, 0.0], [1.0, 0.0]], dtype=f64)
        u = torch.zeros(3, 2, dtype=f64)
        out = filt(x, u)
        assert out.status.tolist() == [
            FilterStatus.FALLBACK,
            FilterStatus.NON_FINITE,
            FilterStatus.FALLBACK,
        ]
        assert float(out.u[1].abs().max()) == 0.0  # zero clipped to the limits
        (grad,) = torch.autograd.grad(out.u[0, 0], (k,))
        (alone,) = torch.autograd.grad(filt(x[:1], u[:1]).u[0, 0], (k,))
        assert torch.isfinite(grad) and float(grad) == float(alone) != 0.0


def test_a_callable_fallback_without_a_graph_is_called_on_every_row() -> None:
    """A callable that returns a control it holds for the whole batch (a backup controller's
    output, in float64 for a float32 filter) works in grad mode and without it, its control
    cast to the filter's dtype and clipped to the limits."""
    from torchcbf.barriers import Ball
    from torchcbf.dynamics import SingleIntegrator

    model = SingleIntegrator(2, u_min=-2.0, u_max=2.0)
    held = torch.tensor([[3.0, 0.5], [0.0, 0.0]], dtype=torch.float64)
    filt = SafetyFilter(model, Ball([1.0, 0.0], 0.5), fallback=lambda x, u: held, slack="none")
    x = torch.tensor([[1.0, 0.0], [0.3, 0.0]])
    u = torch.tensor([[1.0, 0.0], [2.0, 0.0]])
    for grad in (True, False):
        with torch.set_grad_enabled(grad):
            out = filt(x, u)
        assert out.u.dtype == torch.float32
        assert out.status.tolist()[0] == FilterStatus.FALLBACK
        torch.testing.assert_close(out.u[0], torch.tensor([2.0, 0.5]))


def test_batch_equals_loop_and_shapes() -> None:
    xs, us = random_states(12, seed=11)
    filt = scene("stochastic")
    x, u = torch.tensor(xs), torch.tensor(us)
    out = filt(x, u)
    for i in range(len(xs)):
        one = filt(x[i], u[i])  # unbatched
        assert one.u.shape == (2,) and one.status.shape == () and one.h.shape == (3,)
        assert torch.allclose(one.u, out.u[i], atol=1e-8)
        assert one.status == out.status[i]
        b1 = filt(x[i : i + 1], u[i : i + 1])  # batch of one
        assert b1.u.shape == (1, 2) and torch.allclose(b1.u[0], out.u[i], atol=1e-8)
    grid = filt(x.reshape(3, 4, 3), u.reshape(3, 4, 2), t=0.0)
    assert grid.u.shape == (3, 4, 2) and grid.h.shape == (3, 4, 3) and grid.slack.shape == (3, 4, 4)
    assert torch.allclose(grid.u.reshape(12, 2), out.u, atol=1e-8)
    # u_nom broadcast against a batch of states, t as a tensor
    shared = filt(x, u[0], t=torch.zeros(12, dtype=torch.float64))
    assert shared.u.shape == (12, 2)


def test_time_varying_barrier_uses_t() -> None:
    dyn = SingleIntegrator(2)
    moving = Ball(torch.tensor([0.0, 0.0]), 1.0, velocity=torch.tensor([1.0, 0.0]))
    filt = SafetyFilter(dyn, moving, alpha=1.0).double()
    x = torch.tensor([[3.0, 0.0]], dtype=torch.float64)
    u = torch.zeros(1, 2, dtype=torch.float64)
    for t in (0.0, 1.0, torch.tensor(1.5, dtype=torch.float64)):
        tv = float(t)
        d = 3.0 - tv  # centre at (t, 0): h = d^2 - 1, dh/dt = -2 d, lgh = (2 d, 0)
        out = filt(x, u, t=t)
        u_min = (2 * d - (d**2 - 1)) / (2 * d)  # 2 d u + dh/dt + h >= 0
        assert torch.allclose(out.u[0, 0], torch.tensor(max(u_min, 0.0), dtype=torch.float64))


def test_soft_cbf_and_per_barrier_class_k() -> None:
    dyn = SingleIntegrator(1)
    wall = HalfSpace([1.0], 1.0)  # h = 1 - x
    x = torch.tensor([[0.0]], dtype=torch.float64)
    u = torch.tensor([[3.0]], dtype=torch.float64)
    hard = SafetyFilter(dyn, wall, alpha=2.0).double()(x, u)
    assert torch.allclose(hard.u, torch.tensor([[2.0]], dtype=torch.float64))
    # soft: min 1/2 (u-3)^2 + 1/2 w s^2, u - s <= 2  ->  u = 2 + (1/(1+w))
    soft = SafetyFilter(dyn, wall, alpha=2.0, slack=Slack("per_row", cbf_weight=4.0)).double()
    out = soft(x, u)
    assert torch.allclose(out.u, torch.tensor([[2.2]], dtype=torch.float64), atol=1e-8)
    assert out.status[0] == FilterStatus.RELAXED
    assert torch.allclose(out.slack, torch.tensor([[0.2]], dtype=torch.float64), atol=1e-8)
    # one class-K function per barrier module: cubic on the second wall
    walls = [HalfSpace([1.0], 1.0), HalfSpace([-1.0], 1.0)]
    per = SafetyFilter(dyn, walls, alpha=[LinearClassK(2.0), lambda h: h**3]).double()
    out = per(torch.tensor([[-0.5]], dtype=torch.float64), torch.tensor([[-9.0]]).double())
    # second wall: h = 1 + x = 0.5, -u >= -h^3 -> u >= -0.125
    assert torch.allclose(out.u, torch.tensor([[-0.125]], dtype=torch.float64))


def test_errors_name_the_argument() -> None:
    dyn = Unicycle()
    ball = Ball([0.0, 0.0], 1.0)
    with pytest.raises(ValueError, match="mode"):
        SafetyFilter(dyn, ball, mode="magic")
    with pytest.raises(ValueError, match="eta"):
        SafetyFilter(Unicycle(sigma=0.1), ball, mode=RiskAware(rho=0.1, horizon=1.0))
    with pytest.raises(ValueError, match="rho"):
        SafetyFilter(Unicycle(sigma=0.1), ball, mode=RiskAware(None, horizon=1.0, eta=1.0))
    with pytest.raises(ValueError, match="clf_eta"):
        SafetyFilter(
            Unicycle(sigma=0.1),
            lyapunovs=QuadraticLyapunov([0.0, 0.0]),
            mode=RiskAware(rho=0.1, horizon=1.0),
        )
    with pytest.raises(ValueError, match="disturbance_bound"):
        SafetyFilter(dyn, ball, mode="robust")
    with pytest.raises(ValueError, match="sigma"):
        SafetyFilter(dyn, ball, mode="stochastic")
    with pytest.raises(ValueError, match="both empty"):
        SafetyFilter(dyn)
    with pytest.raises(ValueError, match="R"):
        SafetyFilter(dyn, ball, R=torch.tensor([1.0, -1.0]))
    with pytest.raises(ValueError, match="fallback"):
        SafetyFilter(dyn, ball, fallback="explode")
    with pytest.raises(TypeError, match="barriers"):
        SafetyFilter(dyn, [ball, "wall"])
    with pytest.raises(ValueError, match="alpha"):
        SafetyFilter(dyn, [ball, ball], alpha=[lambda h: h])
    for bad in ({"max_iter": 0}, {"max_iter": 2.5}, {"eps": 0.0}, {"eps": 1.5}):
        with pytest.raises(ValueError, match=r"qp_options\['(max_iter|eps)'\]"):
            SafetyFilter(dyn, ball, qp_options=bad)
    filt = SafetyFilter(dyn, ball)
    with pytest.raises(ValueError, match=r"x must have shape \[\.\.\., 3\]"):
        filt(torch.zeros(4, 2), torch.zeros(4, 2))
    with pytest.raises(ValueError, match="u_nom"):
        filt(torch.zeros(4, 3), torch.zeros(4, 3))
    with pytest.raises(ValueError, match="do not broadcast"):
        filt(torch.zeros(4, 3), torch.zeros(5, 2))
    with pytest.raises(ValueError, match="t must broadcast"):
        filt(torch.zeros(4, 3), torch.zeros(4, 2), t=torch.zeros(3))
    with pytest.raises(ValueError, match="alpha"):
        SafetyFilter(dyn, ball, alpha=[1.0, 2.0])(torch.zeros(4, 3), torch.zeros(4, 2))


@pytest.mark.parametrize("mode", ["vanilla", "robust"])
def test_hard_only_qp_matches_cvxpy_and_falls_back_when_infeasible(mode: str) -> None:
    xs, us = random_states(24, seed=1)
    filt = scene(mode, slack="none")
    out = filt(torch.tensor(xs), torch.tensor(us))
    lo, hi = torch.tensor(U_MIN), torch.tensor(U_MAX)
    for i in range(len(xs)):
        ref = solve_reference(xs[i], us[i], mode)
        if ref is None:
            assert out.status[i] == FilterStatus.FALLBACK
            assert torch.equal(out.u[i], torch.clamp(torch.tensor(us[i]), lo, hi))
        else:
            assert out.status[i] == FilterStatus.SOLVED
            assert np.allclose(out.u[i].numpy(), ref, atol=1e-6, rtol=0)
    # an infeasible row (two walls leaving no room) takes the fallback, never a NaN
    walls = HalfSpace(torch.tensor([[1.0], [-1.0]]), torch.tensor([-1.0, -1.0]))
    hard = SafetyFilter(SingleIntegrator(1), walls, slack="none", fallback="brake").double()
    out = hard(torch.zeros(1, 1, dtype=torch.float64), torch.ones(1, 1, dtype=torch.float64))
    assert out.status[0] == FilterStatus.FALLBACK and out.u[0, 0] == 0.0


def _dense_scene() -> tuple[SingleIntegrator, Ball, torch.Tensor, torch.Tensor]:
    """4,096 states among 8 random balls (the benchmark's scene): it contains near-degenerate
    rows (nearly parallel active constraints)."""
    gen = torch.Generator().manual_seed(0)
    centers = 8 * torch.rand(8, 2, generator=gen, dtype=torch.float64) - 4
    radii = 0.3 + 0.4 * torch.rand(8, generator=gen, dtype=torch.float64)
    ball = Ball(centers, radii)
    dyn = SingleIntegrator(2, u_min=-2.0, u_max=2.0)
    cand = 10 * torch.rand(4 * 4096, 2, generator=gen, dtype=torch.float64) - 5
    x = cand[(ball(cand) > 0.05).all(-1)][:4096]
    return dyn, ball, x, (-2.0 * x).clamp(-2.0, 2.0)


def _ipm_vs_enumeration(elastic: bool) -> float:
    dyn, ball, x, u_nom = _dense_scene()
    kw = {"alpha": 1.0, "slack": "shared" if elastic else "none"}
    ipm = SafetyFilter(dyn, ball, qp_options={"method": "ipm"}, **kw).double()
    exact = SafetyFilter(dyn, ball, qp_options={"method": "enumerate"}, **kw).double()
    with torch.no_grad():
        a, b = ipm(x, u_nom), exact(x, u_nom)
    assert bool((a.status == FilterStatus.SOLVED).all())
    assert bool((b.status == FilterStatus.SOLVED).all())
    return float((a.u - b.u).abs().max())


def test_interior_point_hard_qp_matches_exact_enumeration() -> None:
    """The interior point path verifies near-degenerate rows through its polish instead of
    returning an answer accurate only to about sqrt(eps)."""
    assert _ipm_vs_enumeration(elastic=False) < 1e-8


def test_interior_point_elastic_qp_matches_exact_enumeration() -> None:
    """Unverified interior point rows of the elastic QP are re-solved exactly."""
    assert _ipm_vs_enumeration(elastic=True) < 1e-8


@pytest.mark.parametrize("opening", [5e-4, 1e-3])
def test_a_relaxed_answer_where_the_penalty_weight_binds_has_the_right_jacobian(opening):
    """Two half-spaces whose safe controls form a narrow wedge: the shared slack's weight
    binds and the answer is RELAXED, a function of that weight (which depends on u_nom and
    the rows): its Jacobian to u_nom, x and the rows' offsets is the central difference's."""
    f64 = torch.float64
    th = opening
    A = -torch.tensor([[math.cos(th), math.sin(th)], [-math.cos(th), math.sin(th)]], dtype=f64)

    def answer(u_nom, x, b):
        filt = SafetyFilter(SingleIntegrator(2), HalfSpace(A, b), alpha=1.0).double()
        return filt(x, u_nom)

    u0 = torch.tensor([[0.3, 0.2]], dtype=f64)
    x0 = torch.tensor([[0.05, -0.02]], dtype=f64)
    b0 = torch.tensor([-0.01, -0.01], dtype=f64)
    out = answer(u0, x0, b0)
    assert int(out.status) == FilterStatus.RELAXED
    args = [u0, x0, b0]
    for i in range(3):
        given = [a.clone().requires_grad_(j == i) for j, a in enumerate(args)]
        u = answer(*given).u[0]
        J = torch.stack(
            [torch.autograd.grad(u[r], given[i], retain_graph=True)[0] for r in range(2)]
        )
        e = 1e-6
        cols = []
        for j in range(args[i].numel()):
            d = torch.zeros_like(args[i]).view(-1)
            d[j] = e
            d = d.view_as(args[i])
            hi = [a + d if k == i else a for k, a in enumerate(args)]
            lo = [a - d if k == i else a for k, a in enumerate(args)]
            cols.append((answer(*hi).u[0] - answer(*lo).u[0]) / (2 * e))
        fd = torch.stack(cols, -1).view_as(J)
        torch.testing.assert_close(J, fd, atol=1e-5, rtol=1e-5)
