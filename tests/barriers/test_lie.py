"""Lie derivatives against hand-derived formulas, a per-row loop and the analytic path."""

from __future__ import annotations

import math
import warnings

import pytest
import torch

from torchcbf.barriers import (
    Ball,
    Barrier,
    BarrierStack,
    Ellipse,
    LieTerms,
    MovingBall,
    NeuralBarrier,
    QuadraticLyapunov,
    Scaled,
    rectify,
)
from torchcbf.barriers.lie import time_tensor
from torchcbf.dynamics import AccelUnicycle, DoubleIntegrator, SingleIntegrator, Unicycle


def _tol(dtype: torch.dtype) -> dict[str, float]:
    return (
        {"atol": 1e-10, "rtol": 1e-10} if dtype == torch.float64 else {"atol": 2e-4, "rtol": 2e-5}
    )


def _states(n: int, rows: int, dtype: torch.dtype, device: torch.device, seed: int = 0):
    gen = torch.Generator().manual_seed(seed)
    return (3 * torch.randn(rows, n, generator=gen, dtype=torch.float64)).to(device, dtype)


def test_ball_unicycle_matches_hand_formula(dtype, device):
    sigma = torch.tensor([[0.3, 0.1], [0.0, 0.2], [0.5, -0.4]])
    dyn = Unicycle(sigma=sigma).to(device, dtype)
    ball = Ball([1.0, -2.0], 0.7).to(device, dtype)
    x = _states(3, 1000, dtype, device)
    terms = ball.lie(x, dyn)
    assert isinstance(terms, LieTerms)
    assert terms._fields[:5] == ("h", "lfh", "lgh", "dhdt", "hess_trace")
    c, r = ball.center, ball.radius
    dx, dy, th = x[:, 0] - c[0], x[:, 1] - c[1], x[:, 2]
    h = dx**2 + dy**2 - r**2
    lgh = torch.stack([2 * dx * torch.cos(th) + 2 * dy * torch.sin(th), torch.zeros_like(dx)], -1)
    s = dyn.sigma_matrix
    hess = (2 * (s[0] ** 2 + s[1] ** 2).sum()).expand(1000)
    torch.testing.assert_close(terms.h, h, **_tol(dtype))
    torch.testing.assert_close(terms.lfh, torch.zeros_like(h), **_tol(dtype))
    torch.testing.assert_close(terms.lgh, lgh, **_tol(dtype))
    torch.testing.assert_close(terms.dhdt, torch.zeros_like(h))
    torch.testing.assert_close(terms.hess_trace, hess, **_tol(dtype))
    dhdx = torch.stack([2 * dx, 2 * dy, torch.zeros_like(dx)], -1)
    torch.testing.assert_close(terms.dhdx, dhdx, **_tol(dtype))
    assert terms.lgh.dtype == dtype and terms.lgh.device.type == device.type


@pytest.mark.parametrize("angle", [None, 0.6])
def test_ellipse_accel_unicycle_matches_hand_formula(dtype, device, angle):
    dyn = AccelUnicycle(sigma=0.28).to(device, dtype)
    ell = Ellipse([1.0, 2.0], [0.5, 1.5], angle=angle).to(device, dtype)
    x = _states(4, 1000, dtype, device, seed=1)
    terms = ell.lie(x, dyn)
    a1, a2 = ell.axes[0], ell.axes[1]
    phi = torch.zeros((), dtype=dtype, device=device) if angle is None else ell.angle
    cp, sp = torch.cos(phi), torch.sin(phi)
    ex, ey = x[:, 0] - ell.center[0], x[:, 1] - ell.center[1]
    q1, q2 = cp * ex + sp * ey, -sp * ex + cp * ey
    h = (q1 / a1) ** 2 + (q2 / a2) ** 2 - 1
    # dh/dp = 2 R diag(1/a^2) q
    w1, w2 = 2 * q1 / a1**2, 2 * q2 / a2**2
    hx, hy = cp * w1 - sp * w2, sp * w1 + cp * w2
    v, th = x[:, 2], x[:, 3]
    lfh = hx * v * torch.cos(th) + hy * v * torch.sin(th)
    # tr(sigma' H sigma) = 0.28^2 tr(H_pp) = 0.28^2 * 2 (1/a1^2 + 1/a2^2) (rotation invariant)
    hess = 0.28**2 * 2 * (1 / a1**2 + 1 / a2**2)
    tol = _tol(dtype)
    torch.testing.assert_close(terms.h, h, **tol)
    torch.testing.assert_close(terms.lfh, lfh, **tol)
    torch.testing.assert_close(terms.lgh, torch.zeros_like(terms.lgh), **tol)
    torch.testing.assert_close(terms.hess_trace, hess.expand(1000), **tol)


def test_moving_ball_dhdt(dtype, device):
    dyn = SingleIntegrator().to(device, dtype)
    ball = Ball([0.5, -1.0], 0.4, velocity=[0.3, -0.7]).to(device, dtype)
    x = _states(2, 1000, dtype, device, seed=2)
    t = torch.rand(1000, generator=torch.Generator().manual_seed(3), dtype=dtype).to(device) * 5
    terms = ball.lie(x, dyn, t)
    c = ball.center + ball.velocity * t[:, None]
    d = x - c
    tol = _tol(dtype)
    torch.testing.assert_close(terms.h, (d**2).sum(-1) - ball.radius**2, **tol)
    torch.testing.assert_close(terms.dhdt, -2 * (d * ball.velocity).sum(-1), **tol)
    torch.testing.assert_close(terms.lgh, 2 * d, **tol)
    # scalar time broadcasts over the batch
    t0 = ball.lie(x, dyn, 1.5).dhdt
    c0 = ball.center + 1.5 * ball.velocity
    torch.testing.assert_close(t0, -2 * ((x - c0) * ball.velocity).sum(-1), **tol)


@pytest.mark.parametrize("method", ["autograd", "analytic"])
def test_a_velocity_set_after_construction_moves_the_ball(dtype, device, method):
    dyn = SingleIntegrator().to(device, dtype)
    built = Ball([0.5, -1.0], 0.4, velocity=[0.3, -0.7]).to(device, dtype)
    later = Ball([0.5, -1.0], 0.4).to(device, dtype)
    assert not later.time_varying
    later.velocity = torch.tensor([0.3, -0.7], dtype=dtype, device=device)
    assert later.time_varying
    x = _states(2, 100, dtype, device, seed=5)
    ref, got = built.lie(x, dyn, 2.0, method=method), later.lie(x, dyn, 2.0, method=method)
    for name in ("h", "lfh", "lgh", "dhdt"):
        torch.testing.assert_close(getattr(got, name), getattr(ref, name), **_tol(dtype))


@pytest.mark.parametrize("wrap", ["scaled", "stack", "rectified"])
def test_wrappers_follow_a_velocity_set_later(dtype, device, wrap):
    """A barrier built on a Ball is time-varying as soon as the ball is."""
    dyn = (DoubleIntegrator(2) if wrap == "rectified" else SingleIntegrator()).to(device, dtype)

    def build(ball):
        if wrap == "scaled":
            return Scaled(ball, 2.0)
        if wrap == "stack":
            return BarrierStack(ball, Ball([0.0, 0.0], 0.3))
        return rectify(ball, dyn, form="exponential", gains=[2.0])

    ref = build(Ball([0.5, -1.0], 0.4, velocity=[0.3, -0.7])).to(device, dtype)
    ball = Ball([0.5, -1.0], 0.4)
    later = build(ball).to(device, dtype)
    assert not later.time_varying
    ball.velocity = torch.tensor([0.3, -0.7], dtype=dtype, device=device)
    assert later.time_varying
    x = _states(dyn.state_dim, 50, dtype, device, seed=6)
    got, want = later.lie(x, dyn, 1.5), ref.lie(x, dyn, 1.5)
    for name in ("h", "lfh", "lgh", "dhdt"):
        torch.testing.assert_close(getattr(got, name), getattr(want, name), **_tol(dtype))


class _Quartic(Barrier):
    """A user's barrier without closed forms: ``h = sum x^4 - 1``."""

    def forward(self, x, t=None):
        return (x**4).sum(-1) - 1.0


class _GradientNorm(Barrier):
    """``h = 1 - |grad V|^2`` for ``V = sum x^4 / 4``, differentiating its own input."""

    def forward(self, x, t=None):
        (dV,) = torch.autograd.grad((x**4).sum() / 4, x, create_graph=True)
        return 1.0 - (dV**2).sum(-1)


def test_grad_mode_keeps_the_graph_where_only_the_diffusion_requires_grad():
    s = torch.tensor(0.7, dtype=torch.float64, requires_grad=True)
    dyn = SingleIntegrator(2, sigma=lambda x: s * torch.eye(2, dtype=x.dtype).expand(
        *x.shape[:-1], 2, 2)).double()  # fmt: skip
    x = _states(2, 5, torch.float64, "cpu", seed=7)
    terms = _Quartic().lie(x, dyn)
    (grad,) = torch.autograd.grad(terms.hess_trace.sum(), s)
    # hess_trace = s^2 tr(H), H = diag(12 x^2)
    torch.testing.assert_close(grad, 2 * s.detach() * (12 * x**2).sum())


def test_grad_mode_takes_a_barrier_that_differentiates_its_own_input():
    dyn = SingleIntegrator(2)
    x = torch.tensor([[0.5, 0.2], [0.9, -0.1]], dtype=torch.float64)
    with torch.no_grad():
        plain = _GradientNorm().lie(x, dyn)
    got = _GradientNorm().lie(x, dyn)
    torch.testing.assert_close(got.lgh, plain.lgh)
    torch.testing.assert_close(got.lgh, -6.0 * x**5)  # d/dx (1 - sum x^6)


def test_a_subclass_may_still_declare_itself_time_varying():
    """A time-varying subclass sets ``time_varying = True`` (LieFunction's contract), also
    on a class whose flag follows its state."""

    class Pulsing(Ball):
        def __init__(self):
            super().__init__([0.0, 0.0], 0.5)
            self.time_varying = True

        def forward(self, x, t=None):
            return super().forward(x, t) - 0.1 * torch.sin(time_tensor(t, x))

    ball = Pulsing()
    assert ball.time_varying and Scaled(ball, 2.0).time_varying
    x = torch.tensor([[1.0, 0.0]], dtype=torch.float64)
    terms = ball.double().lie(x, SingleIntegrator(), torch.zeros(1, dtype=torch.float64))
    torch.testing.assert_close(terms.dhdt, torch.tensor([-0.1], dtype=torch.float64))


def test_a_barrier_that_reads_t_undeclared_gets_its_dhdt_and_a_warning():
    """A disc closing in at 1 m/s (centre ``2 - t``) whose class does not declare
    ``time_varying``: every path of the filter keeps ``dh/dt`` (the safe control backs away),
    and the autograd path warns that the other users of the barrier will not pass ``t``."""
    from torchcbf.filters import SafetyFilter

    class Closing(Barrier):
        def forward(self, x, t=None):
            c = torch.stack([2.0 - time_tensor(t, x), torch.zeros(x.shape[:-1])], -1)
            return ((x[..., :2] - c.to(x)) ** 2).sum(-1) - 0.25

    f64 = torch.float64
    dyn = SingleIntegrator(2).double()
    x, u = torch.zeros(1, 2, dtype=f64), torch.tensor([[1.0, 0.0]], dtype=f64)
    t = torch.tensor([0.5], dtype=f64)
    with pytest.warns(UserWarning, match="Closing reads t but does not declare time_varying"):
        terms = Closing().lie(x, dyn, t)
    torch.testing.assert_close(terms.dhdt, torch.tensor([-3.0], dtype=f64))  # -2 (p - c) . c'
    for grad in (True, False):
        with torch.set_grad_enabled(grad), warnings.catch_warnings():
            warnings.simplefilter("ignore")
            out = SafetyFilter(dyn, [Closing()], alpha=1.0)(x, u, t=t)
        # 3 u_x - 3 + 2 >= 0 is violated by u_nom: the projection u_x = -1/3
        torch.testing.assert_close(out.u, torch.tensor([[-1.0 / 3.0, 0.0]], dtype=f64))


def test_moving_ball_trajectory_dhdt(dtype, device):
    dyn = SingleIntegrator().to(device, dtype)
    ball = MovingBall(lambda t: torch.stack([torch.cos(t), torch.sin(2 * t)], -1), 0.3).to(
        device, dtype
    )
    x = _states(2, 1000, dtype, device, seed=4)
    t = torch.linspace(0, 3, 1000, dtype=dtype, device=device)
    terms = ball.lie(x, dyn, t)
    c = torch.stack([torch.cos(t), torch.sin(2 * t)], -1)
    cdot = torch.stack([-torch.sin(t), 2 * torch.cos(2 * t)], -1)
    torch.testing.assert_close(terms.dhdt, -2 * ((x - c) * cdot).sum(-1), **_tol(dtype))


def _loop_reference(fn, x, dyn, t=None):
    """Single-state autograd, one row at a time (full Hessian for the trace)."""
    rows = []
    for i in range(x.shape[0]):
        xi = x[i].detach().clone().requires_grad_()
        ti = None if t is None else t[i]
        h = fn(xi, ti)
        (dhdx,) = torch.autograd.grad(h, xi, create_graph=True)
        H = torch.autograd.functional.hessian(lambda z, ti=ti: fn(z, ti), xi.detach())
        s = dyn.sigma(xi.detach())
        ht = None if s is None else torch.trace(s.mT @ H @ s)
        rows.append(
            (
                h.detach(),
                (dhdx @ dyn.f(xi.detach())).detach(),
                (dhdx @ dyn.g(xi.detach())).detach(),
                ht,
            )
        )
    h, lfh, lgh, ht = zip(*rows, strict=True)
    return (
        torch.stack(h),
        torch.stack(lfh),
        torch.stack(lgh),
        None if ht[0] is None else torch.stack(ht),
    )


def _state_sigma(x):
    # state-dependent diffusion [..., 4, 2]
    col1 = torch.stack([0.1 + x[..., 2] ** 2, torch.sin(x[..., 0]), 0 * x[..., 0], x[..., 1]], -1)
    col2 = torch.stack([x[..., 3], 0.2 + 0 * x[..., 0], torch.cos(x[..., 1]), 0.1 * x[..., 0]], -1)
    return torch.stack([col1, col2], -1)


@pytest.mark.parametrize("case", ["neural", "ellipse_state_sigma", "moving", "lyapunov"])
def test_batched_lie_matches_row_loop(dtype, case):
    torch.manual_seed(0)  # noqa: NPY002 - weights of the test network only
    gen = torch.Generator().manual_seed(7)
    t = None
    if case == "neural":
        net = torch.nn.Sequential(torch.nn.Linear(4, 16), torch.nn.Tanh(), torch.nn.Linear(16, 1))
        fn = NeuralBarrier(net, offset=Ball([0.0, 1.0], 0.5)).to(dtype)
        dyn = AccelUnicycle(sigma=torch.tensor([0.28, 0.1, 0.3, 0.2])).to(dtype)
    elif case == "ellipse_state_sigma":
        fn = Ellipse([1.0, 2.0], [0.5, 1.5], angle=0.3).to(dtype)
        dyn = AccelUnicycle(sigma=_state_sigma).to(dtype)
    elif case == "moving":
        fn = Ball([0.0, 1.0], 0.5, velocity=[1.0, 0.2]).to(dtype)
        dyn = DoubleIntegrator(sigma=0.3).to(dtype)
        t = torch.rand(200, generator=gen, dtype=dtype)
    else:
        P = torch.tensor([[2.0, 0.3], [0.3, 1.0]])
        fn = QuadraticLyapunov([1.0, -1.0], P, index=(0, 1)).to(dtype)
        dyn = Unicycle(sigma=0.2).to(dtype)
    x = torch.randn(200, dyn.state_dim, generator=gen, dtype=dtype)
    terms = fn.lie(x, dyn, t)
    h, lfh, lgh, ht = _loop_reference(fn, x, dyn, t)
    tol = {"atol": 1e-10, "rtol": 1e-10} if dtype == torch.float64 else {"atol": 1e-4, "rtol": 1e-4}
    torch.testing.assert_close(terms.h.detach(), h, **tol)
    torch.testing.assert_close(terms.lfh.detach(), lfh, **tol)
    torch.testing.assert_close(terms.lgh.detach(), lgh, **tol)
    torch.testing.assert_close(terms.hess_trace.detach(), ht, **tol)


@pytest.mark.parametrize(
    "make",
    [
        lambda: Ball([1.0, -2.0], 0.7, velocity=[0.2, 0.1]),
        lambda: Ball([[1.0, -2.0], [0.0, 0.5], [2.0, 2.0]], [0.7, 0.2, 1.0], keep_in=True),
        lambda: Ellipse([[1.0, 2.0], [3.0, 2.0]], [[0.5, 1.5], [0.75, 2.0]], angle=[0.3, -1.0]),
        lambda: Ellipse([1.0, 2.0], [0.5, 1.5]),
        lambda: QuadraticLyapunov([1.0, 0.5], torch.tensor([[2.0, 0.3], [0.3, 1.0]])),
    ],
)
def test_analytic_matches_autograd(dtype, device, make):
    fn = make().to(device, dtype)
    dyn = AccelUnicycle(sigma=torch.tensor([[0.3, 0.1], [0.2, 0.0], [0.5, 0.1], [0.0, 0.4]]))
    dyn = dyn.to(device, dtype)
    x = _states(4, 500, dtype, device, seed=5)
    t = torch.linspace(0, 2, 500, dtype=dtype, device=device)
    a = fn.lie(x, dyn, t, method="analytic")
    b = fn.lie(x, dyn, t)
    for name in LieTerms._fields:
        torch.testing.assert_close(getattr(a, name), getattr(b, name).detach(), **_tol(dtype))


def test_batch_shapes_and_no_grad_modes(dtype):
    dyn = AccelUnicycle(sigma=0.28).to(dtype)
    ell = Ellipse([1.0, 2.0], [0.5, 1.5]).to(dtype)
    x = _states(4, 6, dtype, torch.device("cpu")).reshape(2, 3, 4)
    full = ell.lie(x, dyn)
    assert full.h.shape == (2, 3) and full.lgh.shape == (2, 3, 2) and full.dhdx.shape == (2, 3, 4)
    single = ell.lie(x[1, 2], dyn)
    assert single.h.shape == () and single.lgh.shape == (2,)
    torch.testing.assert_close(single.hess_trace, full.hess_trace[1, 2])
    with torch.no_grad():
        ng = ell.lie(x, dyn)
    with torch.inference_mode():
        im = ell.lie(x, dyn)
    for terms in (ng, im):
        assert not terms.h.requires_grad and not terms.hess_trace.requires_grad
        torch.testing.assert_close(terms.lfh, full.lfh.detach())
        torch.testing.assert_close(terms.hess_trace, full.hess_trace.detach())
    no_hess = ell.lie(x, dyn, hessian=False)
    assert no_hess.hess_trace is None


def test_multi_output_matches_individual(dtype):
    dyn = AccelUnicycle(sigma=0.28).to(dtype)
    parts = [
        Ellipse([1.0, 2.0], [0.5, 1.5]),
        Ball([[0.0, 0.0], [2.0, 1.0]], [0.4, 0.3]),
        NeuralBarrier(
            torch.nn.Sequential(torch.nn.Linear(4, 8), torch.nn.Tanh(), torch.nn.Linear(8, 1))
        ),
    ]
    stack = BarrierStack(*parts).to(dtype)
    x = _states(4, 50, dtype, torch.device("cpu"), seed=9)
    terms = stack.lie(x, dyn)
    assert (
        terms.h.shape == (50, 4)
        and terms.lgh.shape == (50, 4, 2)
        and terms.dhdx.shape == (50, 4, 4)
    )
    columns = []
    for p in stack.barriers:
        t = p.lie(x, dyn)
        if t.h.dim() == 1:
            t = LieTerms(*(v.unsqueeze(-1) if v.dim() == 1 else v.unsqueeze(-2) for v in t))
        columns.append(t)
    for i, name in enumerate(LieTerms._fields):
        ref = torch.cat([c[i] for c in columns], -1 if name not in ("lgh", "dhdx") else -2)
        torch.testing.assert_close(getattr(terms, name), ref, **_tol(dtype), msg=name)


def test_rotation_invariant_hess_trace_value():
    # independent check of the 0.28 I case: tr(sigma' H sigma) = sigma^2 * tr(H)
    dyn = AccelUnicycle(sigma=0.28).to(torch.float64)
    ell = Ellipse([0.0, 0.0], [2.0, 0.25], angle=math.pi / 5).to(torch.float64)
    terms = ell.lie(torch.zeros(4, dtype=torch.float64), dyn)
    torch.testing.assert_close(
        terms.hess_trace, torch.tensor(0.28**2 * 2 * (1 / 4 + 16), dtype=torch.float64)
    )
