"""Compiled Lie terms of user functions equal the autograd terms, and the filter takes them
outside grad mode only."""

from __future__ import annotations

import logging
import types

import pytest
import torch
from torch import Tensor

from torchcbf.barriers import Ball, Barrier, MovingBall
from torchcbf.barriers.compiled import CompiledLie
from torchcbf.barriers.lie import stacked_lie_derivatives
from torchcbf.dynamics import ControlAffine, Unicycle
from torchcbf.filters import SafetyFilter

#: dynamo's tracing (vmap, jacrev, the user code) without a C++ build: fast in tests
TRACED = {"backend": "aot_eager"}


class SuperEllipse(Barrier):
    """``sum |(p - c) / a|^4 - 1``, a user-written shape without closed forms."""

    def __init__(self, center: list[float], axes: list[float]) -> None:
        super().__init__()
        self.register_buffer("center", torch.tensor(center))
        self.register_buffer("axes", torch.tensor(axes))

    def forward(self, x: Tensor, t: Tensor | float | None = None) -> Tensor:
        d = (x[..., :2] - self.center.to(x)) / self.axes.to(x)
        return (d.abs() ** 4).sum(-1) - 1.0


class SmoothPolygon(Barrier):
    """Outside the box ``|p| <= 1``, smoothly: ``0.1 logsumexp((N p - 1) / 0.1)`` (two outputs:
    the box and a shifted copy)."""

    def __init__(self) -> None:
        super().__init__()
        normals = torch.tensor([[1.0, 0.0], [-1.0, 0.0], [0.0, 1.0], [0.0, -1.0]])
        self.register_buffer("normals", normals)
        self.register_buffer("shifts", torch.tensor([[0.0, 0.0], [3.0, 0.0]]))

    def forward(self, x: Tensor, t: Tensor | float | None = None) -> Tensor:
        p = x[..., None, :2] - self.shifts.to(x)  # [..., 2, 2]
        s = p @ self.normals.to(x).mT - 1.0  # [..., 2, 4]
        return 0.1 * torch.logsumexp(s / 0.1, -1)


class Glider(ControlAffine):
    """A user-written model: unicycle kinematics with a constant drift."""

    def __init__(self, **kwargs) -> None:
        super().__init__(3, 2, **kwargs)

    def f(self, x: Tensor) -> Tensor:
        return torch.zeros_like(x) + torch.tensor([0.2, 0.0, 0.0], dtype=x.dtype)

    def g(self, x: Tensor) -> Tensor:
        th = x[..., 2]
        z, o = torch.zeros_like(th), torch.ones_like(th)
        rows = [
            torch.stack([th.cos(), z], -1),
            torch.stack([th.sin(), z], -1),
            torch.stack([z, o], -1),
        ]
        return torch.stack(rows, -2)


def _functions() -> list:
    return [
        SuperEllipse([2.0, 0.5], [0.6, 0.4]),
        SmoothPolygon(),
        MovingBall(lambda t: torch.stack([t, 0.5 * t], -1), 0.3),
    ]


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32], ids=["float64", "float32"])
@pytest.mark.parametrize("diffusion", [False, True])
def test_compiled_terms_equal_the_autograd_terms(dtype: torch.dtype, diffusion: bool) -> None:
    model = (Glider(sigma=0.3) if diffusion else Glider()).to(dtype)
    fns = [fn.to(dtype) for fn in _functions()]
    x = torch.randn(5, 3, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    x, t = x.to(dtype), torch.linspace(0.0, 1.0, 5, dtype=dtype)
    got, sizes = CompiledLie(fns, model, hessian=True, options=TRACED)(x, t)
    want, want_sizes = stacked_lie_derivatives(fns, x, model, t)
    assert sizes == want_sizes == [1, 2, 1]
    tol = 1e-10 if dtype == torch.float64 else 1e-4
    for name in ("h", "lfh", "lgh", "dhdt", "dhdx", "hess_trace"):
        a, b = getattr(got, name), getattr(want, name)
        if b is None:
            assert a is None, name
            continue
        assert not a.requires_grad, name
        torch.testing.assert_close(a, b, atol=tol, rtol=tol, msg=name)
    assert bool((got.dhdt[:, 3] != 0).all())  # the moving ball's time derivative


def test_the_filter_takes_the_compiled_terms_outside_grad_mode_only() -> None:
    model = Unicycle(u_min=-2.0, u_max=2.0).double()
    fns = [SuperEllipse([2.0, 0.5], [0.6, 0.4]).double(), SmoothPolygon().double()]
    compiled = SafetyFilter(model, fns, compile=TRACED).double()
    general = SafetyFilter(model, fns, backend="torch").double()
    x = torch.tensor([[0.0, 0.3, 0.1], [1.0, -0.5, 2.0], [4.0, 2.0, -1.0]], dtype=torch.float64)
    u = torch.tensor([[1.0, 0.0]], dtype=torch.float64).expand(3, 2)
    with torch.no_grad():
        for rows in (slice(0, 1), slice(0, 3)):
            a, b = compiled(x[rows], u[rows]), general(x[rows], u[rows])
            assert a.path == "compiled/realtime" and b.path.startswith("torch/")
            torch.testing.assert_close(a.u, b.u, atol=1e-9, rtol=1e-9)
            torch.testing.assert_close(a.h, b.h)
        a = compiled(x[0], u[0])  # one state, no batch axis
        assert a.u.shape == (2,) and a.path == "compiled/realtime"
    xg = x.clone().requires_grad_()
    out = compiled(xg, u)
    assert out.path.startswith("torch/") and out.u.requires_grad  # the graph is kept
    out.u.sum().backward()
    assert xg.grad is not None and torch.isfinite(xg.grad).all()


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32], ids=["float64", "float32"])
@pytest.mark.parametrize("mode", ["vanilla", "stochastic"])
def test_compile_true_traces_the_conditions_into_one_graph(
    dtype: torch.dtype, mode: str, caplog: pytest.LogCaptureFixture
) -> None:
    from torchcbf.barriers import QuadraticLyapunov

    model = (Glider(sigma=0.3) if mode == "stochastic" else Glider()).to(dtype)
    fns = [fn.to(dtype) for fn in _functions()]
    clf = QuadraticLyapunov([4.0, 1.0]).to(dtype)
    kw = {"u_min": -2.0, "u_max": 2.0, "alpha": 1.5}
    traced = SafetyFilter(model, fns, [clf], mode, compile=True, **kw).to(dtype)
    general = SafetyFilter(model, fns, [clf], mode, backend="torch", **kw).to(dtype)
    gen = torch.Generator().manual_seed(1)
    x = (torch.randn(6, 3, generator=gen, dtype=torch.float64) - 2.0).to(dtype)
    u = torch.randn(6, 2, generator=gen, dtype=torch.float64).to(dtype)
    t = torch.linspace(0.0, 1.0, 6, dtype=dtype)
    tol = 1e-9 if dtype == torch.float64 else 1e-4
    with torch.no_grad(), caplog.at_level(logging.INFO, logger="torchcbf"):
        for rows in (slice(0, 1), slice(0, 6)):
            a = traced(x[rows], u[rows], t[rows])
            b = general(x[rows], u[rows], t[rows])
            assert a.path.startswith("compiled/") and b.path.startswith("torch/")
            torch.testing.assert_close(a.status, b.status)
            for name in ("u", "h", "clf_value", "constraint_value"):
                want = getattr(b, name)
                torch.testing.assert_close(getattr(a, name), want, atol=tol, rtol=tol, msg=name)
        compiles = traced._traced.compiles  # one per batch size met
        for _ in range(3):  # repeated calls, new states and constants: no new graph
            fns[0].center.add_(0.25)  # a new value: the same graph reads it
            general.barriers[0].center.add_(0.25)
            a, b = traced(x + 0.01, u, t), general(x + 0.01, u, t)
        assert traced._traced.compiles == compiles == 2
    assert not caplog.records  # traced: no fallback to torch.compile
    torch.testing.assert_close(a.h, b.h, atol=tol, rtol=tol)
    torch.testing.assert_close(a.u, b.u, atol=tol, rtol=tol)


def test_new_constants_are_read_without_a_recompile() -> None:
    model = Unicycle().double()
    shape = SuperEllipse([2.0, 0.5], [0.6, 0.4]).double()
    lie = CompiledLie([shape], model, hessian=False, options=TRACED)
    x, t = torch.tensor([[0.0, 0.3, 0.1]], dtype=torch.float64), torch.zeros(1, dtype=torch.float64)
    first = lie(x, t)[0].h.clone()
    shape.center.add_(0.5)
    moved = lie(x, t)[0].h
    assert not torch.equal(first, moved)
    torch.testing.assert_close(moved, shape(x)[..., None])


@pytest.mark.parametrize("compile", [True, {}])
def test_a_velocity_set_after_the_first_call_is_seen(compile) -> None:
    model = Unicycle(u_min=-2.0, u_max=2.0).double()
    ball = Ball([1.0, 0.5], 0.4).double()
    filt = SafetyFilter(model, [ball], compile=compile).double()
    general = SafetyFilter(model, [ball], backend="torch").double()
    x = torch.tensor([[0.2, 0.1, 0.3], [0.9, 0.0, -1.0]], dtype=torch.float64)
    u = torch.tensor([[1.5, 1.0], [1.0, -1.0]], dtype=torch.float64)
    with torch.no_grad():
        filt(x, u, 0.5)
        ball.velocity = torch.tensor([0.8, -0.7], dtype=torch.float64)
        a, b = filt(x, u, 0.5), general(x, u, 0.5)
    assert a.path.startswith("compiled/")
    torch.testing.assert_close(a.u, b.u, atol=1e-9, rtol=1e-9)


@pytest.mark.parametrize("compile", [True, {}])
def test_a_barrier_replaced_after_the_first_call_is_traced(compile) -> None:
    """A barrier the filter's list holds instead of another after a call is the one the
    compiled filter answers with, as a filter built with it."""
    model = Unicycle(u_min=-2.0, u_max=2.0).double()
    fns = [SuperEllipse([2.0, 0.5], [0.6, 0.4]).double(), Ball([0.0, 3.0], 0.5).double()]
    filt = SafetyFilter(model, fns, compile=compile).double()
    x = torch.tensor([[0.2, 0.1, 0.3], [0.9, 0.0, -1.0]], dtype=torch.float64)
    u = torch.tensor([[1.5, 1.0], [1.0, -1.0]], dtype=torch.float64)
    new = SuperEllipse([0.6, 0.4], [0.3, 0.3]).double()
    with torch.no_grad():
        filt(x, u)
        filt.barriers[0] = new
        a = filt(x, u)
        b = SafetyFilter(model, [new, fns[1]], backend="torch").double()(x, u)
    assert a.path.startswith("compiled/")
    torch.testing.assert_close(a.h, b.h, atol=1e-9, rtol=1e-9)
    torch.testing.assert_close(a.u, b.u, atol=1e-9, rtol=1e-9)


def test_a_backend_that_fails_warns_and_the_autograd_path_answers(
    caplog: pytest.LogCaptureFixture,
) -> None:
    def failing(gm, example_inputs):
        raise RuntimeError("no compiler here")

    model = Unicycle().double()
    fns = [SuperEllipse([2.0, 0.5], [0.6, 0.4]).double(), Ball([0.0, 3.0], 0.5).double()]
    x = torch.tensor([[0.0, 0.3, 0.1]], dtype=torch.float64)
    t = torch.zeros(1, dtype=torch.float64)
    with caplog.at_level(logging.WARNING, logger="torchcbf"):
        # answered eagerly this once; the caller takes the autograd path, and says so
        assert CompiledLie(fns, model, hessian=False, options={"backend": failing})(x, t) is None
    assert any("torch.compile failed" in r.getMessage() for r in caplog.records)
    u = torch.tensor([[1.0, 0.5]], dtype=torch.float64)
    with torch.no_grad():
        out = SafetyFilter(model, fns, compile={"backend": failing}).double()(x, u)
        want = SafetyFilter(model, fns, backend="torch").double()(x, u)
    assert out.path.startswith("torch/")
    torch.testing.assert_close(out.u, want.u, atol=1e-12, rtol=1e-12)


def test_compile_option_is_checked() -> None:
    with pytest.raises(TypeError, match="compile must be True, False or a dict"):
        SafetyFilter(Unicycle(), [Ball([0.0, 3.0], 0.5)], compile="yes")


@pytest.mark.parametrize("compile", [TRACED, True], ids=["torch.compile", "traced"])
def test_functions_that_call_autograd_themselves_take_the_autograd_path(
    compile: dict | bool, caplog: pytest.LogCaptureFixture
) -> None:
    from torchcbf.barriers import rectify
    from torchcbf.dynamics import DoubleIntegrator

    model = DoubleIntegrator(2).double()
    hocbf = rectify(SuperEllipse([2.0, 0.5], [0.6, 0.4]).double(), model, form="high_order")
    compiled = SafetyFilter(model, [hocbf], compile=compile).double()
    general = SafetyFilter(model, [hocbf], backend="torch").double()
    x = torch.tensor([[0.0, 0.3, 0.5, 0.1]], dtype=torch.float64)
    u = torch.tensor([[1.0, 0.0]], dtype=torch.float64)
    with caplog.at_level(logging.INFO, logger="torchcbf"), torch.no_grad():
        a, b = compiled(x, u), compiled(x, u)
    messages = [r.getMessage() for r in caplog.records]
    # compile=True tries the traced graph first, then torch.compile; each says so once
    assert sum("cannot be traced" in m for m in messages) == (compile is True)
    assert sum("cannot be compiled" in m for m in messages) == 1
    assert a.path.startswith("torch/") and b.path.startswith("torch/")
    with torch.no_grad():
        torch.testing.assert_close(a.u, general(x, u).u, atol=1e-9, rtol=1e-9)


def test_a_compiled_filter_pickles_and_compiles_again_where_loaded() -> None:
    import pickle

    model = Unicycle().double()
    filt = SafetyFilter(model, [SuperEllipse([2.0, 0.5], [0.6, 0.4]).double()], compile=TRACED)
    x = torch.tensor([[0.0, 0.3, 0.1]], dtype=torch.float64)
    u = torch.tensor([[1.0, 0.0]], dtype=torch.float64)
    with torch.no_grad():
        want = filt.double()(x, u)
        got = pickle.loads(pickle.dumps(filt))(x, u)
    assert got.path == want.path == "compiled/realtime"
    torch.testing.assert_close(got.u, want.u)


GAIN = 1.0


def test_compile_true_sees_changed_globals_strides_and_empty_batches(
    caplog: pytest.LogCaptureFixture,
) -> None:
    global GAIN
    model = Unicycle(u_min=-2.0, u_max=2.0).double()
    moving = MovingBall(lambda t: torch.stack([t, 0.5 * t], -1), 0.3).double()
    shape = SuperEllipse([2.0, 0.5], [0.6, 0.4]).double()
    kw = {"alpha": lambda h: GAIN * h}
    traced = SafetyFilter(model, [shape, moving], compile=True, **kw).double()
    general = SafetyFilter(model, [shape, moving], backend="torch", **kw).double()
    x = torch.tensor([[1.0, 0.4, 0.1], [0.0, -0.5, 2.0]], dtype=torch.float64)
    u = torch.tensor([[1.0, 0.0], [2.0, 1.0]], dtype=torch.float64)
    with torch.no_grad(), caplog.at_level(logging.INFO, logger="torchcbf"):
        calls = [
            {},
            {"t": torch.tensor(0.5, dtype=torch.float64)},  # broadcast: a stride-0 time
            {"t": torch.tensor([0.1, 0.2], dtype=torch.float64)},
        ]
        for gain in (1.0, 10.0):  # a global the class-K function reads
            GAIN = gain
            for extra in calls:
                a, b = traced(x, u, **extra), general(x, u, **extra)
                assert a.path.startswith("compiled/")
                torch.testing.assert_close(a.u, b.u, atol=1e-9, rtol=1e-9)
        GAIN = 1.0
        empty = traced(x[:0], u[:0])
        assert empty.u.shape == (0, 2)
        assert traced(x, u).path.startswith("compiled/")  # still traced after all that
    assert not any("cannot be traced" in r.getMessage() for r in caplog.records)


def test_an_empty_compile_dict_compiles() -> None:
    empty = SafetyFilter(Unicycle(), [SuperEllipse([2.0, 0.5], [0.6, 0.4])], compile={})
    x, u = torch.tensor([[0.0, 0.3, 0.1]]), torch.tensor([[1.0, 0.0]])
    with torch.no_grad():
        assert empty(x, u).path.startswith("compiled/")  # torch.compile's defaults


@pytest.mark.parametrize("compile", [True, TRACED], ids=["traced", "torch.compile"])
def test_a_hook_registered_after_the_first_call_is_seen(compile) -> None:
    fns = [SuperEllipse([2.0, 0.5], [0.8, 0.5]), SmoothPolygon()]
    model = Glider()
    kw = {"u_min": -2.0, "u_max": 2.0, "alpha": 1.5}
    compiled = SafetyFilter(model, fns, compile=compile, **kw).double()
    general = SafetyFilter(model, fns, backend="torch", **kw).double()
    x = torch.tensor([[0.5, 0.2, 0.3], [3.5, -1.0, 1.0]], dtype=torch.float64)
    u = torch.tensor([[1.0, 0.5], [-0.5, 0.2]], dtype=torch.float64)
    with torch.no_grad():
        compiled(x, u)
        handle = fns[0].register_forward_hook(lambda module, args, out: out - 0.3)
        for _ in range(2):  # with the pad, then without it again
            a, b = compiled(x, u), general(x, u)
            assert a.path.startswith("compiled/")
            torch.testing.assert_close(a.h, b.h, atol=1e-9, rtol=1e-9)
            torch.testing.assert_close(a.u, b.u, atol=1e-9, rtol=1e-9)
            handle.remove()


class OwnTerms(SuperEllipse):
    """A superellipse whose class gives its own Lie terms (here twice the true gradient)."""

    def lie(self, x, dynamics, t=None, *, method="autograd", hessian=True):
        own = Barrier.lie(self, x, dynamics, t, method="autograd", hessian=hessian)
        dhdx = 2.0 * own.dhdx
        lgh = (dhdx.unsqueeze(-2) @ dynamics.g(x)).squeeze(-2)
        lfh = (dhdx * dynamics.f(x)).sum(-1)
        return own._replace(lfh=lfh, lgh=lgh, dhdx=dhdx)


@pytest.mark.parametrize("compile", [True, TRACED], ids=["true", "dict"])
@pytest.mark.parametrize("where", ["class", "instance"])
def test_a_barrier_with_its_own_lie_gives_its_terms_to_a_compiled_filter(compile, where) -> None:
    model = Glider().double()
    if where == "class":
        shape = OwnTerms([2.0, 0.5], [0.6, 0.4]).double()
    else:
        shape = SuperEllipse([2.0, 0.5], [0.6, 0.4]).double()
        shape.lie = types.MethodType(OwnTerms.lie, shape)
    reference = SafetyFilter(model, [shape], backend="torch").double()
    compiled = SafetyFilter(model, [shape], compile=compile).double()
    x = torch.tensor([[1.0, 0.4, 0.1], [0.0, -0.5, 2.0]], dtype=torch.float64)
    u = torch.tensor([[3.0, 0.0], [2.0, 1.0]], dtype=torch.float64)
    with torch.no_grad():
        a, b = compiled(x, u), reference(x, u)
    torch.testing.assert_close(a.u, b.u, atol=1e-12, rtol=1e-12)
    assert not a.path.startswith("compiled")
    # the terms are the barrier's own: not those of its forward
    plain = SafetyFilter(model, [SuperEllipse([2.0, 0.5], [0.6, 0.4])], backend="torch").double()
    with torch.no_grad():
        assert not torch.allclose(plain(x, u).u, a.u)


class Growing(Barrier):
    """A barrier with ``count`` outputs (a plain attribute the user may change)."""

    def __init__(self, center: float) -> None:
        super().__init__()
        self.count = 1
        self.center = center

    def forward(self, x: Tensor, t: Tensor | float | None = None) -> Tensor:
        d = ((x[..., None, :2] - self.center) ** 2).sum(-1) - 1.0  # [..., 1]
        return d - 0.1 * torch.arange(self.count, dtype=x.dtype)


def test_a_compiled_filter_follows_a_change_in_the_number_of_outputs() -> None:
    """Counts that change, in total or only between the functions: one class-K function per
    barrier is applied to that barrier's outputs."""
    model = Glider().double()
    fns = [Growing(0.0), Growing(3.0)]
    alpha = [lambda h: 1.0 * h, lambda h: 5.0 * h]
    compiled = SafetyFilter(model, fns, compile=TRACED, alpha=alpha).double()
    reference = SafetyFilter(model, fns, backend="torch", alpha=alpha).double()
    x = torch.tensor([[1.3, 0.0, 0.1]], dtype=torch.float64)
    u = torch.tensor([[-3.0, 0.5]], dtype=torch.float64)
    with torch.no_grad():
        for counts in ((1, 1), (1, 3), (3, 1)):
            fns[0].count, fns[1].count = counts
            a, b = compiled(x, u), reference(x, u)
            assert a.path.startswith("compiled/")
            assert a.constraint_value.shape[-1] == sum(counts)
            torch.testing.assert_close(a.u, b.u, atol=1e-10, rtol=1e-10)


def test_half_precision_states_are_refused_on_every_path() -> None:
    model = Glider()
    for backend in ("auto", "torch"):
        f = SafetyFilter(model, [SuperEllipse([2.0, 0.5], [0.6, 0.4])], backend=backend)
        for dtype in (torch.float16, torch.bfloat16):
            x, u = torch.zeros(3, 3, dtype=dtype), torch.zeros(3, 2, dtype=dtype)
            with pytest.raises(TypeError, match="x must be float32 or float64"):
                f(x, u)
