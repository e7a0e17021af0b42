"""A user's subclass behaves as its code says: every built-in shape and model, subclassed to
override one defining method, gives the answers of the general (autograd) path on every path
that can reach it (Lie terms, the filter with its C kernels, MPPI with its rollout kernel),
and a subclass that changes nothing keeps the fast paths."""

from __future__ import annotations

import types
from collections.abc import Callable

import pytest
import torch
from torch import Tensor

from torchcbf import integrators
from torchcbf.barriers import (
    Ball,
    Barrier,
    BarrierStack,
    Box,
    Ellipse,
    HalfSpace,
    Intersection,
    LieFunction,
    MovingBall,
    QuadraticLyapunov,
    Scaled,
    Transformed,
    rectify,
)
from torchcbf.dynamics import (
    AccelUnicycle,
    Bicycle,
    ControlAffine,
    DoubleIntegrator,
    FixedWing,
    Quadrotor,
    SingleIntegrator,
    Unicycle,
    VanDerPol,
)
from torchcbf.filters import SafetyFilter
from torchcbf.mppi import MPPI, BarrierCost, QuadraticGoal

F64 = torch.float64

#: every built-in shape (and composition) on a 2-D position, with its constructor arguments
SHAPES: dict[str, Callable[[], LieFunction]] = {
    "ball": lambda: Ball([0.0, 0.0], 0.5),
    "balls": lambda: Ball([[0.0, 0.0], [1.5, 0.5]], [0.5, 0.3]),
    "ellipse": lambda: Ellipse([0.2, -0.1], [0.6, 0.3], angle=0.4),
    "ellipses": lambda: Ellipse([[0.0, 0.0], [1.0, 1.0]], [[0.5, 0.3], [0.2, 0.4]]),
    "halfspace": lambda: HalfSpace([1.0, 0.5], 2.0),
    "box": lambda: Box([-3.0, -3.0], [3.0, 3.0]),
    "moving_ball": lambda: MovingBall(lambda t: torch.stack([t, 0 * t], -1), 0.4),
    "lyapunov": lambda: QuadraticLyapunov([1.0, 2.0]),
}
#: the compositions, over a fresh shape
WRAPPERS: dict[str, Callable[[LieFunction], LieFunction]] = {
    "scaled": lambda b: Scaled(b, 2.0),
    "transformed": lambda b: Transformed(b, "radius"),
    "stack": lambda b: BarrierStack(b, Ball([2.0, 2.0], 0.2)),
    "intersection": lambda b: Intersection(b, Ball([2.0, 2.0], 0.2)),
}


class Reference(Barrier):
    """``1.5 h - 0.3`` of a function ``h`` by autograd only: no closed forms, no parts."""

    def __init__(self, base: LieFunction) -> None:
        super().__init__()
        self.base = base
        self.time_varying = base.time_varying

    def forward(self, x: Tensor, t: Tensor | float | None = None) -> Tensor:
        return 1.5 * self.base(x, t) - 0.3


def padded(cls: type) -> type:
    """``cls`` with ``forward`` overridden alone (a safety pad)."""

    def forward(self, x, t=None):
        return 1.5 * cls.forward(self, x, t) - 0.3

    return type(f"Padded{cls.__name__}", (cls,), {"forward": forward})


def _states(B: int, n: int, seed: int = 0) -> Tensor:
    return 1.5 + torch.randn(B, n, generator=torch.Generator().manual_seed(seed), dtype=F64)


def _subclassed(make: Callable[[], LieFunction], subclass: Callable[[type], type]):
    """An instance of ``subclass(type(base))`` with ``base``'s state, and ``base``."""
    base = make()
    obj = subclass(type(base)).__new__(subclass(type(base)))
    obj.__dict__.update(base.__dict__)  # same constants, same submodules
    return obj, base


def _make(name: str) -> Callable[[], LieFunction]:
    """A constructor of the shape or composition ``name``."""
    return SHAPES[name] if name in SHAPES else lambda: WRAPPERS[name](Ball([0.0, 0.0], 0.5))


def _private_helpers(name: str) -> list[str]:
    """The private methods of shape ``name`` that torchcbf's classes define (not torch's)."""
    mro = type(_make(name)()).__mro__
    ours = [c for c in mro if c.__module__.startswith("torchcbf")]
    theirs = [c for c in mro if not c.__module__.startswith("torchcbf")]
    found = {n for c in ours for n in vars(c) if n.startswith("_") and not n.startswith("__")}
    return sorted(
        n for n in found if callable(getattr(mro[0], n)) and not any(n in vars(c) for c in theirs)
    )


def _rewriting(helper: str) -> Callable[[type], type]:
    """A subclass of ``cls`` that rewrites the private ``helper`` as a call of its own."""

    def subclass(cls: type) -> type:
        def rewritten(self, *args, **kwargs):
            return getattr(cls, helper)(self, *args, **kwargs)

        return type(f"Own{helper}{cls.__name__}", (cls,), {helper: rewritten})

    return subclass


def _answers_as_reference(fn: LieFunction, base: LieFunction) -> None:
    """``fn`` (``base`` padded as :class:`Reference` pads it) has no fast form, and its
    values, Lie terms and filtered controls are the reference's."""
    dyn = SingleIntegrator(2).double()
    ref = Reference(base)
    assert not fn.has_analytic and not fn.has_second_order
    assert fn.quadric() is None and fn.parts() is None
    x = _states(16, 2)
    torch.testing.assert_close(fn(x), ref(x))
    got, want = fn.lie(x, dyn), ref.lie(x, dyn)
    for field in ("h", "lfh", "lgh", "dhdt", "dhdx"):
        torch.testing.assert_close(getattr(got, field), getattr(want, field), msg=field)
    if isinstance(base, QuadraticLyapunov):
        return
    u = torch.tensor([[-1.0, 0.3]], dtype=F64).expand(16, 2)
    fast = SafetyFilter(dyn, [fn], check_relative_degree=False).double()
    general = SafetyFilter(dyn, [ref], backend="torch", check_relative_degree=False).double()
    with torch.no_grad():
        for rows in (slice(0, 1), slice(0, 16)):
            a, b = fast(x[rows], u[rows]), general(x[rows], u[rows])
            assert a.path.startswith("torch/")
            torch.testing.assert_close(a.h, b.h)
            torch.testing.assert_close(a.u, b.u, atol=1e-7, rtol=1e-7)
            assert torch.equal(a.status, b.status)


@pytest.mark.parametrize("name", [*SHAPES, *WRAPPERS])
def test_a_shape_overriding_forward_alone_answers_as_its_forward(name: str) -> None:
    sub, base = _subclassed(_make(name), padded)
    _answers_as_reference(sub.double(), base.double())


@pytest.mark.parametrize("name", ["ball", "balls", "ellipse", "ellipses"])
def test_a_quadric_subclass_that_changes_nothing_keeps_the_kernels(name: str) -> None:
    dyn = SingleIntegrator(2).double()
    same, base = _subclassed(SHAPES[name], lambda cls: type(f"My{cls.__name__}", (cls,), {}))
    assert same.quadric() is not None
    x, u = _states(4, 2), torch.tensor([[-1.0, 0.3]], dtype=F64).expand(4, 2)
    with torch.no_grad():
        a = SafetyFilter(dyn, [same], check_relative_degree=False).double()(x, u)
        b = SafetyFilter(dyn, [base], backend="torch", check_relative_degree=False).double()(x, u)
    assert a.path == "native/realtime" and b.path.startswith("torch/")
    torch.testing.assert_close(a.u, b.u, atol=1e-9, rtol=1e-9)
    cost = BarrierCost(same)
    planner = MPPI(dyn, cost, horizon=5, num_samples=64, dt=0.1, noise_sigma=1.0, temperature=1.0)
    assert planner(torch.zeros(2, dtype=F64)).path == "fused"
    padded_cost = BarrierCost(_subclassed(SHAPES[name], padded)[0])
    planner = MPPI(
        dyn, padded_cost, horizon=5, num_samples=64, dt=0.1, noise_sigma=1.0, temperature=1.0
    )
    assert planner(torch.zeros(2, dtype=F64)).path == "rollout"


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
@pytest.mark.parametrize(
    "make",
    [
        lambda: Scaled(Ellipse([0.5, 0.2], [0.6, 0.3], angle=0.3), 3.0),
        lambda: Scaled(Ball([[0.5, 0.2], [-0.5, 0.4]], [0.4, 0.2], keep_in=False), [2.0, 0.5]),
        lambda: Ellipse([0.5, 0.2], [0.6, 0.3], keep_in=True),
    ],
    ids=["scaled_ellipse", "scaled_balls", "keep_in_ellipse"],
)
def test_the_rollout_kernel_scores_any_quadric_as_torch_does(make, dtype) -> None:
    """A quadric's scale and radius are folded into the kernel's record: the fused path's
    lowest cost is the torch cost of the rollout it reports (the control cost is zero on the
    first call, whose plan is zero)."""
    dyn = SingleIntegrator(2).to(dtype)
    shape = make().to(dtype)
    cost = BarrierCost(shape, weight=2.0)
    planner = MPPI(dyn, cost, horizon=6, num_samples=64, dt=0.1, noise_sigma=0.5, temperature=1.0)
    out = planner(torch.tensor([-1.0, 0.0], dtype=dtype))
    assert out.path == "fused"
    states = out.best_states[None, None]  # [1, 1, H+1, n]
    want = cost(states, states.new_zeros(1, 1, 6, 2))[0, 0]
    tol = 1e-9 if dtype == torch.float64 else 1e-4
    torch.testing.assert_close(out.cost_min, want, atol=tol, rtol=tol)


#: every built-in model, with the position components a ball barrier is drawn in
MODELS: dict[str, Callable[[], ControlAffine]] = {
    "single_integrator": lambda: SingleIntegrator(2),
    "double_integrator": lambda: DoubleIntegrator(2),
    "unicycle": Unicycle,
    "accel_unicycle": AccelUnicycle,
    "bicycle": Bicycle,
    "van_der_pol": VanDerPol,
    "quadrotor": Quadrotor,
    "fixed_wing": FixedWing,
}


def new_f(cls: type) -> type:
    def f(self, x):
        return cls.f(self, x) + 0.7

    return type(f"Drifting{cls.__name__}", (cls,), {"f": f})


def new_g(cls: type) -> type:
    def g(self, x):
        return 2.0 * cls.g(self, x)

    return type(f"Doubled{cls.__name__}", (cls,), {"g": g})


def _rk4(fn: Callable[[Tensor, Tensor], Tensor], x: Tensor, u: Tensor, dt: float) -> Tensor:
    k1 = fn(x, u)
    k2 = fn(x + 0.5 * dt * k1, u)
    k3 = fn(x + 0.5 * dt * k2, u)
    k4 = fn(x + dt * k3, u)
    return x + dt / 6 * (k1 + 2 * k2 + 2 * k3 + k4)


@pytest.mark.parametrize("override", [new_f, new_g], ids=["f", "g"])
@pytest.mark.parametrize("name", MODELS)
def test_a_model_overriding_f_or_g_alone_integrates_its_own_dynamics(name: str, override) -> None:
    sub, _ = _subclassed(MODELS[name], override)
    sub = sub.double()
    n, m = sub.state_dim, sub.control_dim
    x, u = _states(8, n, seed=1), 0.3 * _states(8, m, seed=2)

    def reference(z: Tensor, v: Tensor) -> Tensor:
        return sub.f(z) + (sub.g(z) @ v.unsqueeze(-1)).squeeze(-1)

    torch.testing.assert_close(sub(x, u), reference(x, u))
    torch.testing.assert_close(sub.xdot(x, u), reference(x, u))
    for method in ("euler", "rk4"):
        got = integrators.step(sub, x, u, 0.05, method=method)
        want = x + 0.05 * reference(x, u) if method == "euler" else _rk4(reference, x, u, 0.05)
        torch.testing.assert_close(got, want)
    assert sub.native_model() is None
    if override is new_f:
        assert not sub.has_drift_derivatives
    goal = QuadraticGoal([1.0, 1.0], index=(0, 1))
    planner = MPPI(sub, goal, horizon=4, num_samples=32, dt=0.05, noise_sigma=0.5, temperature=1.0,
                   keep_rollouts=4, integrator="euler")  # fmt: skip
    out = planner(x[0])
    assert out.path == "torch"
    # the kept rollouts follow the subclass's own dynamics from x0
    first = out.rollouts[:, 1]  # [R, n] after one step from x[0]
    assert first.shape == (4, n)


@pytest.mark.parametrize("name", ["single_integrator", "double_integrator", "unicycle",
                                  "accel_unicycle"])  # fmt: skip
def test_a_native_model_subclass_keeps_the_kernels_unless_it_changes_the_dynamics(
    name: str,
) -> None:
    same, base = _subclassed(MODELS[name], lambda cls: type(f"My{cls.__name__}", (cls,), {}))
    assert same.native_model() == base.native_model() is not None
    goal = QuadraticGoal([1.0, 1.0], index=(0, 1))
    x0 = torch.zeros(same.state_dim, dtype=F64)
    for model, path in ((same, "fused"), (_subclassed(MODELS[name], new_f)[0], "torch")):
        planner = MPPI(model.double(), goal, horizon=4, num_samples=32, dt=0.05,
                       noise_sigma=0.5, temperature=1.0)  # fmt: skip
        assert planner(x0).path == path


@pytest.mark.parametrize("name", ["single_integrator", "unicycle"])
def test_filter_lie_terms_follow_a_model_with_a_new_drift(name: str) -> None:
    """The C Lie kernel knows the parent's drift: a new ``f`` must take torch."""
    sub, _ = _subclassed(MODELS[name], new_f)
    sub = sub.double()
    ball = Ball([0.0, 0.0], 0.5).double()
    x = _states(3, sub.state_dim, seed=4)
    u = torch.zeros(3, sub.control_dim, dtype=F64)
    with torch.no_grad():
        a = SafetyFilter(sub, [ball]).double()(x, u)
        b = SafetyFilter(sub, [ball], backend="torch", lie_method="autograd").double()(x, u)
    assert a.path.startswith("torch/")
    torch.testing.assert_close(a.u, b.u, atol=1e-9, rtol=1e-9)
    torch.testing.assert_close(a.constraint_value, b.constraint_value, atol=1e-9, rtol=1e-9)


@pytest.mark.parametrize("name", ["double_integrator", "accel_unicycle"])
def test_an_exponential_cbf_along_a_model_with_a_new_drift_uses_its_drift(name: str) -> None:
    sub, _ = _subclassed(MODELS[name], new_f)
    sub = sub.double()
    ball = Ball([0.0, 0.0], 0.5).double()
    rect = rectify(ball, sub, form="exponential")
    assert not rect.has_analytic
    x = _states(6, sub.state_dim, seed=5)
    got = rect.lie(x, sub)
    want = rect.lie(x, sub, method="autograd")
    torch.testing.assert_close(got.h, want.h)
    torch.testing.assert_close(got.lgh, want.lgh)
    # the value itself: L_f h + k0 h with the subclass's own f
    xg = x.clone().requires_grad_()
    h = ball(xg)
    (grad,) = torch.autograd.grad(h.sum(), xg)
    lfh = (grad * sub.f(x)).sum(-1)
    k0 = rect.coefficients[0]
    torch.testing.assert_close(rect(x), lfh + k0 * ball(x))


def test_a_model_overriding_sigma_alone_is_an_sde_with_that_diffusion() -> None:
    class Noisy(Unicycle):
        def sigma(self, x: Tensor) -> Tensor:
            scale = 0.2 + 0.1 * x[..., :1, None].abs()
            return scale * torch.eye(3, dtype=x.dtype).expand(*x.shape[:-1], 3, 3)

    model = Noisy().double()
    assert model.has_diffusion and model.native_model() is None
    ball = Ball([0.0, 0.0], 0.5).double()
    x = _states(4, 3, seed=6)
    terms = ball.lie(x, model)
    s = model.sigma(x)
    hess = torch.zeros(4, 3, 3, dtype=F64)
    hess[:, 0, 0] = hess[:, 1, 1] = 2.0  # d2h/dp2 of the ball
    torch.testing.assert_close(terms.hess_trace, (s.mT @ hess @ s).diagonal(0, -2, -1).sum(-1))
    u = torch.zeros(4, 2, dtype=F64)
    with torch.no_grad():
        a = SafetyFilter(model, [ball], mode="stochastic").double()(x, u)
        b = SafetyFilter(model, [ball], mode="stochastic", backend="torch").double()(x, u)
    assert a.path.startswith("torch/")
    torch.testing.assert_close(a.u, b.u, atol=1e-9, rtol=1e-9)


def test_a_model_overriding_forward_alone_runs_no_kernel() -> None:
    class Damped(SingleIntegrator):
        def forward(self, x: Tensor, u: Tensor, w: Tensor | None = None) -> Tensor:
            return super().forward(x, u, w) - 3.0 * x

    model = Damped(2).double()
    assert model.native_model() is None
    x = torch.tensor([1.0, 0.0], dtype=F64)
    for integrator in ("euler", "rk4"):
        got = integrators.step(model, x, torch.zeros(2, dtype=F64), 0.1, method=integrator)
        assert got[0] < 1.0  # the damping acts
    planner = MPPI(model, QuadraticGoal([1.0, 0.0]), horizon=4, num_samples=16, dt=0.1,
                   noise_sigma=1e-12, temperature=1.0, keep_rollouts=1)  # fmt: skip
    out = planner(x)
    assert out.path == "torch" and out.rollouts[0, -1, 0] < 1.0


def test_an_exponential_cbf_overriding_value_loses_its_closed_forms() -> None:
    from torchcbf.barriers import ExponentialBarrier

    class Margin(ExponentialBarrier):
        def value(self, x, t, base=None):
            return super().value(x, t, base) - 0.5 * x[..., 2] ** 2

    model = DoubleIntegrator(2).double()
    cbf = Margin(Ball([1.0, 1.0], 0.5).double(), model, 2, [1.0])
    assert not cbf.has_analytic and cbf.parts() is None
    x = torch.tensor([[0.1, -0.3, 0.4, 0.2]], dtype=F64)
    u = torch.tensor([[2.0, 2.0]], dtype=F64)
    with torch.no_grad():
        a = SafetyFilter(model, [cbf]).double()(x, u)
        b = SafetyFilter(model, [cbf], lie_method="autograd", backend="torch").double()(x, u)
    assert a.path.startswith("torch/")
    torch.testing.assert_close(a.u, b.u, atol=1e-9, rtol=1e-9)
    torch.testing.assert_close(a.h, b.h)


def test_a_shape_overriding_lie_takes_no_kernel() -> None:
    class Shifted(Ball):
        def lie(self, x, dynamics, t=None, *, method="autograd", hessian=True):
            terms = super().lie(x, dynamics, t, method=method, hessian=hessian)
            return terms._replace(h=terms.h - 0.5)

    assert Shifted([0.0, 0.0], 0.5).quadric() is None


def _pad(module, args, out):
    """A forward hook: the same safety pad as :func:`padded`."""
    return 1.5 * out - 0.3


@pytest.mark.parametrize("name", [*SHAPES, *WRAPPERS])
def test_a_shape_with_a_forward_hook_answers_as_its_hooked_call(name: str) -> None:
    """A hook changes what a call computes: the instance gets no closed forms, parts or
    kernels while it has one, and all of them again once it is removed."""
    fn, base = _make(name)().double(), _make(name)().double()
    handle = fn.register_forward_hook(_pad)
    _answers_as_reference(fn, base)
    handle.remove()
    assert (fn.quadric() is None) == (base.quadric() is None)
    assert fn.has_analytic == base.has_analytic and (fn.parts() is None) == (base.parts() is None)


def test_a_global_forward_hook_turns_every_fast_form_off() -> None:
    ball = Ball([0.0, 0.0], 0.5)
    handle = torch.nn.modules.module.register_module_forward_hook(lambda m, a, out: out)
    try:
        assert ball.quadric() is None and not ball.has_analytic
        assert SingleIntegrator(2).native_model() is None
    finally:
        handle.remove()
    assert ball.quadric() is not None and ball.has_analytic
    assert SingleIntegrator(2).native_model() is not None


def test_a_shape_with_a_pre_hook_answers_as_its_hooked_call() -> None:
    dyn = SingleIntegrator(2).double()
    ball, ref_ball = Ball([0.0, 0.0], 0.5).double(), Ball([0.5, 0.0], 0.5).double()
    ball.register_forward_pre_hook(lambda module, args: (args[0] - torch.tensor([0.5, 0.0]),))
    x = _states(8, 2)
    u = torch.tensor([[-1.0, 0.3]], dtype=F64).expand(8, 2)
    with torch.no_grad():
        a = SafetyFilter(dyn, [ball]).double()(x, u)
        b = SafetyFilter(dyn, [ref_ball]).double()(x, u)
    torch.testing.assert_close(a.h, b.h)
    torch.testing.assert_close(a.u, b.u, atol=1e-9, rtol=1e-9)


def test_a_hooked_class_k_function_is_called() -> None:
    from torchcbf.filters import LinearClassK

    dyn = SingleIntegrator(2).double()
    alpha = LinearClassK(1.0)
    alpha.register_forward_hook(lambda module, args, out: 3.0 * out)
    x = _states(8, 2)
    u = torch.tensor([[-1.0, 0.3]], dtype=F64).expand(8, 2)
    with torch.no_grad():
        a = SafetyFilter(dyn, [Ball([0.0, 0.0], 0.5)], alpha=alpha).double()(x, u)
        b = SafetyFilter(dyn, [Ball([0.0, 0.0], 0.5)], alpha=3.0).double()(x, u)
    torch.testing.assert_close(a.u, b.u, atol=1e-9, rtol=1e-9)


def test_mppi_runs_a_hooked_model_or_cost_in_torch_and_sees_a_hook_added_later() -> None:
    def planner(model, cost):
        return MPPI(model, cost, horizon=5, num_samples=64, dt=0.1, noise_sigma=0.5,
                    temperature=1.0, keep_rollouts=2, seed=1)  # fmt: skip

    x0 = torch.tensor([1.0, -1.0], dtype=F64)
    model = SingleIntegrator(2).double()
    goal = QuadraticGoal([2.0, 1.0], weight=1.0, terminal_weight=5.0)
    hooked_plan = planner(model, goal)
    assert hooked_plan(x0).path == "fused"
    handle = model.register_forward_hook(lambda module, args, out: 0.0 * out)  # a frozen plant
    out = hooked_plan(x0)
    assert out.path == "torch"
    torch.testing.assert_close(out.rollouts[:, -1], x0.expand(2, 2))  # the plant did not move
    handle.remove()
    goal.register_forward_hook(lambda module, args, out: -out)  # a cost that pushes away
    out = hooked_plan(x0)
    assert out.path == "rollout"
    states = out.best_states[None, None]
    want = goal(states, states.new_zeros(1, 1, 5, 2), torch.zeros(1, dtype=F64))[0, 0]
    assert want < 0  # the call ran the hook: the planner scored with it
    torch.testing.assert_close(out.cost_min, want)


def test_a_flag_set_as_a_class_value_is_turned_off_by_a_hook_too() -> None:
    class Line(Barrier):
        has_analytic = True  # a flag as a plain class value, with closed forms

        def forward(self, x, t=None):
            return x[..., 0] - 1.0

        def derivatives(self, x, t):
            raise AssertionError("a hooked instance must not use its closed forms")

    line = Line().double()
    assert line.has_analytic
    line.register_forward_hook(lambda module, args, out: 2.0 * out)
    assert not line.has_analytic
    x = _states(4, 2)
    out = SafetyFilter(SingleIntegrator(2), [line]).double()(x, torch.zeros(4, 2, dtype=F64))
    torch.testing.assert_close(out.h[:, 0], 2.0 * (x[:, 0] - 1.0))


def test_a_hooked_term_of_a_sum_of_costs_is_called_with_its_hook() -> None:
    """A sum adds its terms' stage costs pointwise; a term with a forward hook is called
    instead, so its hook runs, on every path."""
    g = torch.Generator().manual_seed(0)
    states = torch.randn(2, 3, 6, 2, generator=g, dtype=F64)
    controls = torch.randn(2, 3, 5, 2, generator=g, dtype=F64)
    goal = QuadraticGoal([1.0, 1.0], weight=1.0, terminal_weight=2.0)
    barrier = BarrierCost(Ball([3.0, 3.0], 0.5))
    plain = (goal(states, controls) + barrier(states, controls)).clone()
    goal.register_forward_hook(lambda module, args, out: 10.0 * out)
    total = goal + barrier
    hooked_goal = goal(states, controls)  # the call runs the hook
    torch.testing.assert_close(hooked_goal, 10.0 * (plain - barrier(states, controls)))
    torch.testing.assert_close(total(states, controls), hooked_goal + barrier(states, controls))
    assert not torch.allclose(total(states, controls), plain)
    planner = MPPI(SingleIntegrator(2).double(), total, horizon=5, num_samples=32, dt=0.1,
                   noise_sigma=0.5, temperature=1.0, seed=2)  # fmt: skip
    out = planner(torch.zeros(2, dtype=F64))
    assert out.path == "rollout"
    best = out.best_states[None, None]
    want = total(best, best.new_zeros(1, 1, 5, 2))[0, 0]
    torch.testing.assert_close(out.cost_min, want)


def _called_padded(cls: type) -> type:
    """``cls`` with ``__call__`` overridden alone (the pad of :func:`padded`)."""

    def __call__(self, *args, **kwargs):
        return 1.5 * super(sub, self).__call__(*args, **kwargs) - 0.3

    sub = type(f"CallPadded{cls.__name__}", (cls,), {"__call__": __call__})
    return sub


@pytest.mark.parametrize("name", [*SHAPES, *WRAPPERS])
def test_a_shape_overriding_call_or_patched_on_the_instance_answers_as_its_call(name) -> None:
    sub, base = _subclassed(_make(name), _called_padded)
    _answers_as_reference(sub.double(), base.double())
    patched, base = _make(name)().double(), _make(name)().double()
    plain = patched.forward
    patched.forward = lambda x, t=None: 1.5 * plain(x, t) - 0.3
    _answers_as_reference(patched, base)
    del patched.forward
    assert (patched.quadric() is None) == (base.quadric() is None)


@pytest.mark.parametrize("how", ["call", "instance", "global_hook"])
def test_a_model_whose_call_changes_integrates_its_call(how: str) -> None:
    """A rewritten ``__call__``, a ``forward`` set on the instance or a global forward hook:
    every integrator, the simulator's step and MPPI's rollouts integrate the call."""
    shift = torch.tensor([0.3, -0.2], dtype=F64)

    class Called(SingleIntegrator):
        def __call__(self, *args, **kwargs):
            return super().__call__(*args, **kwargs) + shift

    handle = None
    if how == "call":
        model = Called(2).double()
    else:
        model = SingleIntegrator(2).double()
        if how == "instance":
            plain = model.forward
            model.forward = lambda x, u, w=None: plain(x, u, w) + shift
        else:
            handle = torch.nn.modules.module.register_module_forward_hook(
                lambda m, a, out: out + shift if m is model else out
            )
    try:
        assert model.native_model() is None
        x = _states(4, 2)
        u = torch.tensor([[-1.0, 0.5]], dtype=F64).expand(4, 2)
        for method in ("euler", "rk4"):
            want = x + 0.1 * model(x, u) if method == "euler" else _rk4(model, x, u, 0.1)
            torch.testing.assert_close(integrators.step(model, x, u, 0.1, method), want)
        # the controls pinned by the limits, so that every rollout is known
        c = [-1.0, 0.5]
        planner = MPPI(model, QuadraticGoal([1.0, 1.0]), horizon=3, num_samples=8, dt=0.1,
                       noise_sigma=0.5, temperature=1.0, keep_rollouts=8, seed=0, u_min=c,
                       u_max=c)  # fmt: skip
        out = planner(x[0])
        assert out.path == "torch"
        states = out.rollouts
        ctrl = torch.tensor(c, dtype=F64).expand_as(states[:, :-1])
        torch.testing.assert_close(
            states[:, 1:], states[:, :-1] + 0.1 * model(states[:, :-1], ctrl)
        )
    finally:
        if handle is not None:
            handle.remove()


def test_a_joint_limit_barrier_follows_the_arms_own_joint_map() -> None:
    pytest.importorskip("pytorch_kinematics")
    from torchcbf.barriers import JointLimitBarrier
    from torchcbf.dynamics import Manipulator

    class Geared(Manipulator):
        def joint_positions(self, x):
            return 2.0 * super().joint_positions(x)

    arm = Geared("planar3").double()
    barrier = JointLimitBarrier(arm, margin=0.1)
    assert not barrier.has_analytic
    assert JointLimitBarrier(Manipulator("planar3"), margin=0.1).has_analytic
    x = 0.2 * torch.ones(3, arm.state_dim, dtype=F64)
    u = torch.full((3, arm.control_dim), -5.0, dtype=F64)
    terms = barrier.lie(x, arm)
    assert torch.equal(terms.lgh[:, 0], torch.tensor([[2.0, 0.0, 0.0]] * 3, dtype=F64))
    with torch.no_grad():
        a = SafetyFilter(arm, [barrier], check_relative_degree=False).double()(x, u)
        b = SafetyFilter(arm, [barrier], lie_method="autograd", backend="torch",
                         check_relative_degree=False).double()(x, u)  # fmt: skip
    torch.testing.assert_close(a.u, b.u, atol=1e-9, rtol=1e-9)


class _OwnLie(Ball):
    """A ball whose own ``lie`` reports ``h - 1`` (and the terms of ``h`` otherwise)."""

    def lie(self, x, dynamics, t=None, *, method="autograd", hessian=True):
        terms = super().lie(x, dynamics, t, method=method, hessian=hessian)
        return terms._replace(h=terms.h - 1.0, lfh=terms.lfh + 0.5)


def test_a_function_with_its_own_lie_is_asked_for_its_terms_beside_others() -> None:
    dyn = SingleIntegrator(2).double()
    mine, far = _OwnLie([0.0, 0.0], 0.5).double(), Ball([40.0, 40.0], 0.5).double()
    x = _states(6, 2)
    u = torch.tensor([[-2.0, 0.3]], dtype=F64).expand(6, 2)
    with torch.no_grad():
        alone = SafetyFilter(dyn, [mine]).double()(x, u)
        both = SafetyFilter(dyn, [mine, far]).double()(x, u)
    torch.testing.assert_close(both.h[:, 0], mine.lie(x, dyn).h)
    torch.testing.assert_close(both.u, alone.u, atol=1e-9, rtol=1e-9)
    # an exponential barrier of relative degree two is built from the function's own terms
    on_position = _OwnLie([0.0, 0.0], 0.5, index=(0, 1)).double()
    double = DoubleIntegrator(2).double()
    rect = rectify(on_position, double, form="exponential", gains=[2.0])
    z = torch.cat([x, torch.randn(6, 2, generator=torch.Generator().manual_seed(1))], -1)
    own = on_position.lie(z, double)
    torch.testing.assert_close(rect(z), own.lfh + own.dhdt + 2.0 * own.h)
    # and so is a high-order barrier's psi_1
    high = rectify(on_position, double, form="high_order", gains=[2.0])
    torch.testing.assert_close(high(z), own.lfh + own.dhdt + 2.0 * own.h)


@pytest.mark.parametrize("which", ["f", "g"])
@pytest.mark.parametrize("name", MODELS)
def test_a_model_with_f_or_g_set_on_the_instance_integrates_its_own_dynamics(
    name: str, which: str
) -> None:
    model = MODELS[name]().double()
    native = model.native_model()
    cls = type(model)
    if which == "f":
        model.f = lambda z: cls.f(model, z) + 0.7
    else:
        model.g = lambda z: 2.0 * cls.g(model, z)
    n, m = model.state_dim, model.control_dim
    x, u = _states(8, n, seed=1), 0.3 * _states(8, m, seed=2)

    def reference(z: Tensor, v: Tensor) -> Tensor:
        return model.f(z) + (model.g(z) @ v.unsqueeze(-1)).squeeze(-1)

    torch.testing.assert_close(model(x, u), reference(x, u))
    for method in ("euler", "rk4"):
        got = integrators.step(model, x, u, 0.05, method=method)
        want = x + 0.05 * reference(x, u) if method == "euler" else _rk4(reference, x, u, 0.05)
        torch.testing.assert_close(got, want)
    assert model.native_model() is None
    if which == "f":
        assert not model.has_drift_derivatives
    goal = QuadraticGoal([1.0, 1.0], index=(0, 1))
    planner = MPPI(model, goal, horizon=4, num_samples=32, dt=0.05, noise_sigma=0.5,
                   temperature=1.0, keep_rollouts=4, integrator="euler")  # fmt: skip
    out = planner(x[0])
    assert out.path == "torch"
    v = out.rollouts[:, 1] - x[0]  # one Euler step of each kept rollout's first control
    assert v.shape == (4, n)
    delattr(model, which)  # the class's own forms are back
    assert model.native_model() == native
    torch.testing.assert_close(model(x, u), cls.xdot(model, x, u))


def test_a_shape_with_lie_set_on_the_instance_is_asked_for_its_terms() -> None:
    """``ball.lie = ...`` is taken as a class's own ``lie`` is (a pad of 0.3 on ``h``)."""

    class PaddedLie(Ball):
        def lie(self, x, dynamics, t=None, **kw):
            terms = Ball.lie(self, x, dynamics, t, **kw)
            return terms._replace(h=terms.h - 0.3)

    dyn = SingleIntegrator(2).double()
    ball, far = Ball([1.0, 0.0], 0.5).double(), Ball([40.0, 40.0], 0.5).double()
    ball.lie = lambda x, dynamics, t=None, **kw: PaddedLie.lie(ball, x, dynamics, t, **kw)
    assert ball.quadric() is None
    x = _states(6, 2)
    u = torch.tensor([[1.0, 0.3]], dtype=F64).expand(6, 2)
    with torch.no_grad():
        got = SafetyFilter(dyn, [ball, far]).double()(x, u)
        want = SafetyFilter(dyn, [PaddedLie([1.0, 0.0], 0.5).double(), far]).double()(x, u)
    torch.testing.assert_close(got.h[:, 0], ball.lie(x, dyn).h)
    torch.testing.assert_close(got.h, want.h)
    torch.testing.assert_close(got.u, want.u, atol=1e-9, rtol=1e-9)


@pytest.mark.parametrize(
    ("name", "helper"),
    [(name, helper) for name in [*SHAPES, *WRAPPERS] for helper in _private_helpers(name)],
)
def test_a_shape_rewriting_a_private_helper_answers_by_autograd(name: str, helper: str) -> None:
    """The closed forms and parts do not call a shape's private helpers (``_diff``,
    ``_one``, ...): a subclass that rewrites one has none of them, and its filter answers as
    autograd of its ``forward`` does."""
    fn, base = _subclassed(_make(name), _rewriting(helper))
    assert not fn.has_analytic and fn.quadric() is None and fn.parts() is None
    dyn = SingleIntegrator(2).double()
    x = _states(8, 2)
    u = torch.tensor([[-1.0, 0.3]], dtype=F64).expand(8, 2)
    got, want = fn.lie(x, dyn), base.lie(x, dyn, method="autograd")
    torch.testing.assert_close(got.lgh, want.lgh)
    if isinstance(base, QuadraticLyapunov):
        return
    general = SafetyFilter(dyn, [base], lie_method="autograd", backend="torch",
                           check_relative_degree=False).double()  # fmt: skip
    with torch.no_grad():
        a = SafetyFilter(dyn, [fn], check_relative_degree=False).double()(x, u)
        b = general(x, u)
    assert a.path.startswith("torch/")
    torch.testing.assert_close(a.u, b.u, atol=1e-7, rtol=1e-7)


@pytest.mark.parametrize(
    ("name", "helper"),
    [(name, helper) for name in [*SHAPES, *WRAPPERS] for helper in _private_helpers(name)],
)
def test_a_private_helper_set_on_the_instance_answers_by_autograd(name: str, helper: str) -> None:
    """``shape._helper = ...`` on one instance (its class untouched) turns its fast forms
    off as a subclass's rewrite does, and turns them back on when deleted."""
    fn = _make(name)()
    fast = (fn.has_analytic, fn.quadric() is not None, fn.parts() is not None)
    setattr(fn, helper, types.MethodType(getattr(type(fn), helper), fn))
    assert not fn.has_analytic and fn.quadric() is None and fn.parts() is None
    dyn = SingleIntegrator(2).double()
    x = _states(8, 2)
    got, want = fn.lie(x, dyn), fn.lie(x, dyn, method="autograd")
    torch.testing.assert_close(got.lgh, want.lgh)
    delattr(fn, helper)
    assert (fn.has_analytic, fn.quadric() is not None, fn.parts() is not None) == fast


def test_a_ball_whose_helper_changes_on_the_instance_is_filtered_as_its_forward() -> None:
    """``ball._diff`` doubled on the instance: every filter path answers as autograd of
    the ball's new ``forward`` (``|2p - c|^2 - r^2``), none with Ball's closed forms."""
    ball = Ball([0.0, 0.0], 0.5).double()
    ball._diff = types.MethodType(lambda self, x, t: 2.0 * Ball._diff(self, x, t), ball)
    dyn = SingleIntegrator(2).double()
    x = torch.tensor([[1.0, 0.2], [0.4, -0.9]], dtype=F64)
    u = torch.tensor([[-2.0, 0.1], [0.5, 1.0]], dtype=F64)

    class Doubled(Barrier):
        def forward(self, x: Tensor, t: Tensor | float | None = None) -> Tensor:
            return (2.0 * x).square().sum(-1) - 0.25

    want = SafetyFilter(dyn, [Doubled()], backend="torch").double()
    with torch.no_grad():
        b = want(x, u)
        for options in ({}, {"backend": "torch"}, {"lie_method": "autograd"}):
            a = SafetyFilter(dyn, [ball], **options).double()(x, u)
            assert not a.path.startswith("native"), options
            torch.testing.assert_close(a.h, b.h)
            torch.testing.assert_close(a.u, b.u, atol=1e-9, rtol=1e-9)


def test_a_mode_whose_condition_is_set_on_the_instance_is_filtered_with_it() -> None:
    """``mode.cbf = ...`` on a Vanilla instance: the filter's kernels do not evaluate
    Vanilla's condition in its place; the answer is the subclass form's on every path."""
    from torchcbf.filters import LinearClassK, Vanilla
    from torchcbf.filters.conditions import cbf_condition

    def margin(terms, alpha, dynamics, x):
        c = cbf_condition(terms, "vanilla", alpha, dynamics, x)
        return c._replace(b=c.b - 0.3)

    class Margin(Vanilla):
        def cbf(self, terms, alpha, dynamics, x):
            return margin(terms, alpha, dynamics, x)

    mode, gain = Vanilla(), LinearClassK(2.0)
    assert mode.affine_cbf(gain) is not None
    mode.cbf = margin
    assert mode.affine_cbf(gain) is None
    dyn, ball = SingleIntegrator(2).double(), Ball([0.0, 0.0], 0.5).double()
    x = torch.tensor([[1.0, 0.2]], dtype=F64)
    u = torch.tensor([[-2.0, 0.1]], dtype=F64)
    with torch.no_grad():
        want = SafetyFilter(dyn, [ball], mode=Margin(), backend="torch").double()(x, u)
        for backend in ("auto", "torch"):
            got = SafetyFilter(dyn, [ball], mode=mode, backend=backend).double()(x, u)
            torch.testing.assert_close(got.u, want.u, atol=1e-12, rtol=1e-12)
    # a = 2p, b = h - 0.3 = 0.49: u = u_nom + lam a
    a, un = torch.tensor([2.0, 0.4], dtype=F64), u[0]
    torch.testing.assert_close(want.u[0], un - (a @ un + 0.49) / (a @ a) * a)


def _replacement(obj: torch.nn.Module, method: str) -> Callable[..., Tensor]:
    """A new ``method`` for the instance ``obj``: a constant drift, a slower ``xdot``, a
    padded ``forward``, a tripled stage cost."""
    fn = getattr(type(obj), method)
    if method == "f":
        return lambda x: torch.ones_like(x)
    if method == "forward":
        return lambda x, t=None: fn(obj, x, t) - 0.2
    scale = 0.5 if method == "xdot" else 3.0
    return types.MethodType(lambda self, *a, **k: scale * fn(self, *a, **k), obj)


@pytest.mark.parametrize("what", ["model.f", "model.xdot", "ball.forward", "goal.stage"])
def test_mppi_sees_a_method_set_on_an_instance_after_its_first_call(what: str) -> None:
    """A planner that has planned once keeps its kernel only while its model and cost keep
    their methods: one set on an instance afterwards gives the torch planner's answer."""

    def planner(model, cost, backend):
        return MPPI(model, cost, horizon=6, num_samples=64, dt=0.1, noise_sigma=0.5,
                    temperature=1.0, seed=3, backend=backend)  # fmt: skip

    def build():
        model = SingleIntegrator(2).double()
        ball = Ball([[0.6, 0.4]], [0.3]).double()
        goal = QuadraticGoal([2.0, 1.0], weight=1.0, terminal_weight=5.0)
        return model, ball, goal, goal + BarrierCost(ball, weight=2.0)

    x0 = torch.tensor([0.0, 0.0], dtype=F64)
    runs = []
    for backend in ("auto", "torch"):
        model, ball, goal, cost = build()
        p = planner(model, cost, backend)
        assert p(x0).path == ("fused" if backend == "auto" else "torch")
        owner, method = what.split(".")
        obj = {"model": model, "ball": ball, "goal": goal}[owner]
        setattr(obj, method, _replacement(obj, method))
        runs.append(p(x0 + 0.01))
    (fast, torch_run) = runs
    assert fast.path != "fused"
    torch.testing.assert_close(fast.u, torch_run.u, atol=1e-9, rtol=1e-9)


def _padding(cls: type) -> type:
    """A class decorator: ``forward`` replaced after the class statement, ``h - 0.3``."""
    inner = cls.forward

    def forward(self, x, t=None):
        return inner(self, x, t) - 0.3

    cls.forward = forward
    return cls


def test_a_class_changed_after_its_statement_answers_as_its_code() -> None:
    """A decorated shape, a shape whose parent's ``__init_subclass__`` skips ``super()``
    and a model whose ``g`` is set on the class afterwards: their instances have none of
    the parent's fast forms, and the filter and the integrators answer as their code."""

    @_padding
    class Padded(Ball):
        pass

    class Registry(Ball):
        def __init_subclass__(cls, **kwargs):  # forgets super().__init_subclass__
            pass

    class Registered(Registry):
        def forward(self, x, t=None):
            return super().forward(x, t) - 0.3

    class Fast(Unicycle):
        pass

    Fast.g = lambda self, x: 2.0 * Unicycle.g(self, x)
    dyn = SingleIntegrator(2).double()
    x = torch.tensor([[1.0, 0.2]], dtype=F64)
    u = torch.tensor([[-2.0, 0.1]], dtype=F64)
    for cls in (Padded, Registered):
        b = cls([0.0, 0.0], 0.5).double()
        assert not b.has_analytic and b.quadric() is None
        with torch.no_grad():
            for backend in ("auto", "torch"):
                out = SafetyFilter(dyn, [b], backend=backend).double()(x, u)
                torch.testing.assert_close(out.h, torch.tensor([[0.49]], dtype=F64))
                a, un = torch.tensor([2.0, 0.4], dtype=F64), u[0]
                torch.testing.assert_close(out.u[0], un - (a @ un + 0.49) / (a @ a) * a)
    model = Fast().double()
    assert model.native_model() is None
    x0 = torch.zeros(1, 3, dtype=F64)
    u0 = torch.tensor([[1.0, 0.0]], dtype=F64)
    got = integrators.step(model, x0, u0, 0.1, method="euler")
    torch.testing.assert_close(got, torch.tensor([[0.2, 0.0, 0.0]], dtype=F64))
    assert Ball([0.0, 0.0], 0.5).quadric() is not None  # the parent keeps its own


#: whether a function's fast form is off
_OFF: dict[str, Callable[[LieFunction], bool]] = {
    "derivatives": lambda f: not f.has_analytic and not f.has_second_order,
    "quadric": lambda f: f.quadric() is None,
    "parts": lambda f: f.parts() is None,
}


@pytest.mark.parametrize(
    ("name", "fast"),
    [(n, f) for n in [*SHAPES, *WRAPPERS] for f in _OFF if not _OFF[f](_make(n)())],
)
def test_a_fast_form_rewritten_alone_is_not_trusted(name: str, fast: str) -> None:
    """A user's subclass that rewrites one fast form a built-in has and keeps its
    ``forward`` does not get that fast form trusted: the function is its ``forward``."""

    def rewrite(cls: type) -> type:
        def own(self, *args, **kwargs):
            return getattr(cls, fast)(self, *args, **kwargs)

        return type(f"Own{fast}{cls.__name__}", (cls,), {fast: own})

    fn, _ = _subclassed(_make(name), rewrite)
    assert _OFF[fast](fn)


@pytest.mark.parametrize("batch", [1, 2000])
def test_a_ball_with_its_own_quadric_or_derivatives_alone_answers_as_its_forward(batch) -> None:
    """A ``Ball`` subclass whose ``quadric`` (twice the radius) or ``derivatives`` (``h -
    0.3``) disagree with the ``forward`` it keeps: every path and batch size answers as
    autograd of that ``forward``."""

    class Bigger(Ball):
        def quadric(self):
            q = super().quadric()
            return q._replace(radius=2.0 * q.radius)

    class Shifted(Ball):
        def derivatives(self, x, t):
            d = super().derivatives(x, t)
            return d._replace(h=d.h - 0.3)

    dyn = SingleIntegrator(2).double()
    x = _states(batch, 2, seed=3) - 1.5
    u = torch.tensor([[-1.0, 0.3]], dtype=F64).expand(batch, 2)
    with torch.no_grad():
        want = SafetyFilter(dyn, [Ball([0.0, 0.0], 0.5).double()], backend="torch",
                            lie_method="autograd").double()(x, u)  # fmt: skip
        for cls in (Bigger, Shifted):
            b = cls([0.0, 0.0], 0.5).double()
            for options in ({}, {"backend": "torch"}):
                got = SafetyFilter(dyn, [b], **options).double()(x, u)
                torch.testing.assert_close(got.h, want.h)
                torch.testing.assert_close(got.u, want.u, atol=1e-9, rtol=1e-9)


def test_a_fast_form_rewritten_alone_beside_a_private_helper_is_not_trusted() -> None:
    """Rewriting a private helper as well (here ``_sign``, unchanged) does not make a
    ``derivatives`` rewritten alone trusted, nor keeps the quadric of the parent."""

    def shifted(self, x, t):
        d = Ball.derivatives(self, x, t)
        return d._replace(h=d.h - 1.0)

    class AloneAndHelper(Ball):
        derivatives = shifted

        def _sign(self):
            return Ball._sign(self)

    b = AloneAndHelper([0.0, 0.0], 1.0)
    assert not b.has_analytic and b.quadric() is None


@pytest.mark.parametrize("name", MODELS)
def test_a_model_with_its_own_xdot_alone_integrates_f_plus_g_u(name: str) -> None:
    """A built-in model's subclass that rewrites ``xdot`` alone (twice the rate) keeps
    ``f`` and ``g``: it integrates ``f + g u`` and runs on no native kernel."""

    base = MODELS[name]()
    kind = type(base)
    fast = type(
        f"Twice{kind.__name__}", (kind,), {"xdot": lambda self, x, u: 2 * kind.xdot(self, x, u)}
    )
    model = fast.__new__(fast)
    model.__dict__.update(base.__dict__)
    model = model.double()
    assert model.native_model() is None
    gen = torch.Generator().manual_seed(1)
    x = torch.randn(3, model.state_dim, generator=gen, dtype=F64)
    u = torch.randn(3, model.control_dim, generator=gen, dtype=F64)
    want = model.f(x) + (model.g(x) @ u.unsqueeze(-1)).squeeze(-1)
    torch.testing.assert_close(model.xdot(x, u), want)
    torch.testing.assert_close(integrators.step(model, x, u, 0.01, method="euler"), x + 0.01 * want)


def test_the_methods_an_instance_shadows_are_tracked_as_set_and_deleted() -> None:
    from torchcbf._checks import shadowed_methods

    ball, model = Ball([0.0, 0.0], 0.5), SingleIntegrator(2)
    assert not shadowed_methods(ball) and not shadowed_methods(model)
    ball._diff = lambda x, t: x
    ball.radius_scale = 2.0  # not a method
    model.f = lambda x: x
    assert set(shadowed_methods(ball)) == {"_diff"} and set(shadowed_methods(model)) == {"f"}
    del ball._diff, model.f
    assert not shadowed_methods(ball) and not shadowed_methods(model)
    plain = torch.nn.Linear(2, 2)  # not tracked: found by a look at its attributes
    plain.extra_repr = lambda: "x"
    assert list(shadowed_methods(plain)) == ["extra_repr"]


def test_an_arm_rewriting_its_transforms_moves_its_link_spheres() -> None:
    """``Manipulator._transforms`` rewritten to shift every frame: link-sphere barriers and
    the filter on that arm answer as on the plain arm with the obstacle shifted back."""
    pytest.importorskip("pytorch_kinematics")
    from torchcbf.barriers import LinkSphereBarrier
    from torchcbf.dynamics import Manipulator

    shift = torch.tensor([0.1, -0.2, 0.05], dtype=F64)

    class Shifted(Manipulator):
        def _transforms(self, x):
            T, batch = super()._transforms(x)
            T = T.clone()
            T[..., :3, 3] = T[..., :3, 3] + shift.to(T)
            return T, batch

    arm, plain = Shifted("planar3").double(), Manipulator("planar3").double()
    center = torch.tensor([0.9, 0.4, 0.0], dtype=F64)
    moved = LinkSphereBarrier(arm, ["link2", "link3"], 0.05, center, 0.2).double()
    back = LinkSphereBarrier(plain, ["link2", "link3"], 0.05, center - shift, 0.2).double()
    gen = torch.Generator().manual_seed(5)
    x = 0.8 * torch.rand(6, arm.state_dim, generator=gen, dtype=F64) - 0.4
    u = torch.full((6, arm.control_dim), 0.7, dtype=F64)
    a, b = moved.lie(x, arm), back.lie(x, plain)
    torch.testing.assert_close(a.h, b.h)
    torch.testing.assert_close(a.lgh, b.lgh)
    torch.testing.assert_close(arm(x, u), plain(x, u))
    with torch.no_grad():
        got = SafetyFilter(arm, [moved], check_relative_degree=False).double()(x, u)
        want = SafetyFilter(plain, [back], check_relative_degree=False).double()(x, u)
    assert bool((got.u != u).any())  # the spheres are near the obstacle: the filter acts
    torch.testing.assert_close(got.u, want.u, atol=1e-9, rtol=1e-9)


def test_a_ball_with_its_own_offset_is_filtered_as_that_ball() -> None:
    """``Ball._diff`` rewritten to move the centre: every path sees the moved ball."""

    class Offset(Ball):
        def _diff(self, x, t):
            return super()._diff(x, t) - 0.25

    dyn = SingleIntegrator(2).double()
    x = _states(8, 2) - 1.0
    u = torch.tensor([[-1.0, 0.3]], dtype=F64).expand(8, 2)
    with torch.no_grad():
        got = SafetyFilter(dyn, [Offset([0.0, 0.0], 0.5)]).double()(x, u)
        want = SafetyFilter(dyn, [Ball([0.25, 0.25], 0.5)]).double()(x, u)
    torch.testing.assert_close(got.h, want.h)
    torch.testing.assert_close(got.u, want.u, atol=1e-9, rtol=1e-9)
