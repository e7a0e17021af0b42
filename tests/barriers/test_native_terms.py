"""The native Lie terms (torchcbf.barriers.native): the same terms as the torch closed forms
and as autograd for every model x shape (balls, ellipses, scaled and transformed) x form
(plain, exponential CBF), and for hard and smooth intersections and unions of them; None
wherever the torch path must answer (a gradient to carry, an unsupported function, model or
input, no kernel)."""

from __future__ import annotations

import copy
import logging
from pathlib import Path

import pytest
import torch
from torch import Tensor, nn

from torchcbf._native import load_kernel
from torchcbf.barriers import (
    Ball,
    BarrierStack,
    Box,
    Ellipse,
    ExponentialBarrier,
    HalfSpace,
    Intersection,
    LieFunction,
    MovingBall,
    Scaled,
    Transformed,
    Union,
    native,
)
from torchcbf.barriers.lie import LieTerms, lie_derivatives
from torchcbf.dynamics import (
    AccelUnicycle,
    Bicycle,
    DoubleIntegrator,
    SingleIntegrator,
    Unicycle,
    VanDerPol,
)

pytestmark = pytest.mark.skipif(not native.available(), reason="C kernel not built")

F64 = torch.float64

SHAPES = {
    "ball": lambda: Ball([0.5, 0.2], 0.4),
    "balls_keep_in": lambda: Ball([[0.5, 0.2], [1.0, 1.0], [-1.0, 0.3]], [4.0, 5.0, 4.5],
                                  keep_in=True),
    "ellipse_rotated": lambda: Ellipse([0.2, -0.3], [0.5, 1.5], angle=0.4),
    "ellipses_rotated": lambda: Ellipse(
        [[0.2, -0.3], [1.0, 1.0]], [[0.5, 1.5], [2.0, 1.0]], angle=[0.4, -1.1], index=(1, 0)
    ),
    "ellipse_keep_in": lambda: Ellipse([[0.0, 0.5]], [[6.0, 5.0]], angle=0.3, keep_in=True),
    "ellipsoid": lambda: Ellipse([0.2, -0.3, 0.1], [0.5, 1.5, 0.8], index=(0, 1, 2)),
    "scaled_ball": lambda: Scaled(Ball([0.5, 0.2], 0.4), 0.7),
    "scaled_ellipses": lambda: Scaled(
        Ellipse([[1.0, 2.0], [-0.5, 0.5], [0.3, -1.0]], [[0.5, 1.5], [1.0, 0.3], [0.7, 0.7]]),
        [2.0, 0.5, 0.1],
    ),
    "scaled_twice": lambda: Scaled(Scaled(Ball([[0.5, 0.2], [1.0, 1.0]], 0.4), [2.0, 3.0]), 0.5),
    "radius": lambda: Transformed(Ellipse([0.2, -0.3], [0.5, 1.5], angle=0.4), "radius"),
    "scaled_exp": lambda: Scaled(
        Transformed(Ellipse([[1.0, 2.0], [-0.5, 0.5]], [[0.5, 1.5], [1.0, 0.3]]), "exp", rate=0.3),
        [0.5, 2.0],
    ),
    "exp_of_scaled": lambda: Transformed(
        Scaled(Ball([[0.5, 0.2], [1.0, 1.0]], [0.4, 0.3], keep_in=True), [0.2, 0.1]), "exp",
        rate=0.7,
    ),
}  # fmt: skip
MODELS = {
    "single_integrator": lambda sigma: SingleIntegrator(3, sigma=sigma),
    "double_integrator": lambda sigma: DoubleIntegrator(2, sigma=sigma),
    "unicycle": lambda sigma: Unicycle(sigma=sigma),
    "accel_unicycle": lambda sigma: AccelUnicycle(sigma=sigma),
}
SIGMAS = {
    "none": lambda n: None,
    "scalar": lambda n: 0.3,
    "matrix": lambda n: torch.linspace(-0.4, 0.5, n * 2, dtype=F64).reshape(n, 2),
}


def _states(count: int, n: int, seed: int, dtype: torch.dtype = F64) -> Tensor:
    gen = torch.Generator().manual_seed(seed)
    x = 3 * torch.rand(count, n, generator=gen, dtype=F64) - 1.5
    x[:, :2] += 2.5  # away from the centres
    return x.to(dtype)


def _model(name: str, sigma: str) -> nn.Module:
    n = {"single_integrator": 3, "double_integrator": 4, "unicycle": 3, "accel_unicycle": 4}[name]
    return MODELS[name](SIGMAS[sigma](n))


def _columns(terms: LieTerms, x: Tensor) -> LieTerms:
    """Terms of one function (``h [B]`` or ``[B, k]``) in the k-output form ``[B, k]``."""
    if terms.h.shape != x.shape[:-1]:
        return terms
    return LieTerms(*(None if v is None else v.unsqueeze(1) for v in terms))


def _assert_terms(got: LieTerms, want: LieTerms, dtype: torch.dtype) -> None:
    tol = {"atol": 1e-12, "rtol": 1e-12} if dtype == F64 else {"atol": 1e-4, "rtol": 1e-4}
    for name in LieTerms._fields:
        g, w = getattr(got, name), getattr(want, name)
        if w is None:
            assert g is None, name
            continue
        assert g.dtype == dtype and g.shape == w.shape and not g.requires_grad, name
        scale = 1.0 + float(w.detach().abs().max())
        torch.testing.assert_close(g, w.detach(), atol=tol["atol"] * scale, rtol=tol["rtol"],
                                   msg=name)  # fmt: skip


def _kernel_matches_closed_forms(fns, x, dyn, dtype=F64, sizes=None) -> LieTerms:
    """One kernel call on the list ``fns`` gives each function's number of outputs
    (``sizes``, or those of the closed forms) and the closed forms of each, concatenated;
    returns the kernel's terms."""
    with torch.no_grad():
        found = native.lie_terms(fns, x, dyn)
    assert found is not None
    terms, counts = found
    parts = [_columns(lie_derivatives(f, x, dyn, method="analytic"), x) for f in fns]
    assert counts == (sizes if sizes is not None else [p.h.shape[1] for p in parts])
    want = LieTerms(
        *(
            None if parts[0][i] is None else torch.cat([p[i] for p in parts], 1)
            for i in range(len(LieTerms._fields))
        )
    )
    _assert_terms(terms, want, dtype)
    return terms


@pytest.mark.parametrize("dtype", [F64, torch.float32], ids=["float64", "float32"])
@pytest.mark.parametrize("sigma", list(SIGMAS))
@pytest.mark.parametrize("form", ["plain", "exponential"])
@pytest.mark.parametrize("shape", list(SHAPES))
@pytest.mark.parametrize("model", list(MODELS))
def test_native_terms_match_closed_forms_and_autograd(
    model: str, shape: str, form: str, sigma: str, dtype: torch.dtype
) -> None:
    dyn = _model(model, sigma).to(dtype)
    barrier = SHAPES[shape]().to(dtype)
    if form == "exponential":
        barrier = ExponentialBarrier(barrier, dyn, 2, [2.5]).to(dtype)
        assert barrier.has_analytic
    x = _states(5, dyn.state_dim, seed=len(model) + len(shape), dtype=dtype)
    terms = _kernel_matches_closed_forms([barrier], x, dyn, dtype)
    # autograd in float64, the reference of both
    dyn64, barrier64 = dyn.double(), barrier.double()
    auto = _columns(lie_derivatives(barrier64, x.double(), dyn64, method="autograd"), x)
    _assert_terms(terms, LieTerms(*(None if v is None else v.to(dtype) for v in auto)), dtype)


def test_several_functions_and_stacks_concatenate_in_order() -> None:
    dyn = AccelUnicycle(sigma=0.2).double()
    ellipses = Scaled(Ellipse([[1.0, 2.0], [-0.5, 0.5]], [[0.5, 1.5], [1.0, 0.3]]), [2.0, 0.5])
    fns = [
        Ball([[0.5, 0.2], [1.0, 1.0]], [0.4, 0.3]),
        ExponentialBarrier(ellipses, dyn, 2, [3.0]),
        BarrierStack(
            Ball([0.5, 0.2], 0.4), ExponentialBarrier(Ball([1.0, 1.0], 0.3), dyn, 2, [1.0])
        ),
        ExponentialBarrier(BarrierStack(Ball([0.5, 0.2], 0.4), ellipses), dyn, 2, [2.0]),
    ]
    fns = [f.double() for f in fns]
    x = _states(3, 4, seed=7)
    _kernel_matches_closed_forms(fns, x, dyn, sizes=[2, 2, 2, 3])


def test_without_a_hessian_the_trace_is_none() -> None:
    dyn = AccelUnicycle(sigma=0.2).double()
    x = _states(2, 4, seed=1)
    terms, _ = native.lie_terms([Ball([0.5, 0.2], 0.4).double()], x, dyn, hessian=False)
    assert terms.hess_trace is None
    want = _columns(lie_derivatives(Ball([0.5, 0.2], 0.4).double(), x, dyn, hessian=False), x)
    _assert_terms(terms, want, F64)


def test_constants_are_read_at_every_call() -> None:
    ball = Ball([0.5, 0.2], 0.4).double()
    dyn = SingleIntegrator(2).double()
    x = _states(1, 2, seed=2)
    before = native.lie_terms([ball], x, dyn)[0].h
    with torch.no_grad():
        ball.center.add_(1.0)
    ball.radius = torch.tensor(0.9, dtype=F64)  # a new buffer
    after = native.lie_terms([ball], x, dyn)[0].h
    assert not torch.equal(before, after)
    torch.testing.assert_close(after, ball(x).unsqueeze(1), atol=1e-14, rtol=0)


def test_a_gradient_to_carry_takes_the_torch_path() -> None:
    dyn = AccelUnicycle(sigma=0.2).double()
    learnable = Ball([0.5, 0.2], 0.4, learnable=True).double()
    fixed = ExponentialBarrier(Ellipse([0.5, 0.2], [1.0, 2.0]), dyn, 2, [2.0]).double()
    x = _states(2, 4, seed=3)
    with torch.enable_grad():
        assert native.lie_terms([learnable], x, dyn) is None
        assert native.lie_terms([fixed], x.clone().requires_grad_(), dyn) is None
        assert native.lie_terms([fixed], x, dyn) is not None  # nothing requires grad
        gain = nn.Parameter(torch.tensor([2.0], dtype=F64))
        assert native.lie_terms([ExponentialBarrier(fixed.barrier, dyn, 2, gain)], x, dyn) is None
    with torch.no_grad():  # no graph to build: the kernel answers
        assert native.lie_terms([learnable], x.requires_grad_(), dyn) is not None


class _Drifting(AccelUnicycle):
    """A subclass with another drift: not the model the kernel knows."""

    def f(self, x: Tensor) -> Tensor:
        return super().f(x) + 1.0


class _Shifted(Ball):
    """A subclass that changes ``forward`` alone: its inherited quadric is not its own."""

    def forward(self, x: Tensor, t: Tensor | float | None = None) -> Tensor:
        return super().forward(x, t) + 1.0


def _unsupported_cases() -> dict[str, tuple]:
    acc, x4 = AccelUnicycle(sigma=0.2).double(), _states(2, 4, seed=4)
    ball = Ball([0.5, 0.2], 0.4).double()
    return {
        "half_space": ([HalfSpace([1.0, 0.0], 2.0, index=(0, 1))], x4, acc),
        "box": ([Box([-5.0, -5.0], [5.0, 5.0], index=(0, 1))], x4, acc),
        "transformed_twice": ([Transformed(Transformed(ball, "radius"), "exp")], x4, acc),
        "transformed_rectified": (
            [Transformed(ExponentialBarrier(ball, acc, 2, [1.0]), "exp")],
            x4,
            acc,
        ),
        "scaled_stack_of_transforms": (
            [Scaled(BarrierStack(Transformed(ball, "exp"), Transformed(ball, "radius")), 2.0)],
            x4,
            acc,
        ),
        "moving_ball": ([Ball([0.5, 0.2], 0.4, velocity=[0.1, 0.0])], x4, acc),
        "trajectory": ([MovingBall(lambda t: torch.stack([t, t], -1), 0.4)], x4, acc),
        "one_unsupported_of_two": ([ball, HalfSpace([1.0, 0.0], 2.0, index=(0, 1))], x4, acc),
        "scale_per_output_on_one_shape": ([Scaled(ball, [1.0, 2.0])], x4, acc),
        "relative_degree_three": ([ExponentialBarrier(ball, acc, 3, [1.0, 2.0])], x4, acc),
        "rectified_twice": (
            [ExponentialBarrier(ExponentialBarrier(ball, acc, 2, [1.0]), acc, 2, [1.0])],
            x4,
            acc,
        ),
        "bicycle": ([ball], x4, Bicycle()),
        "van_der_pol": ([ball], _states(2, 2, seed=4), VanDerPol()),
        "subclass_with_own_drift": ([ball], x4, _Drifting()),
        "shape_subclass_with_own_forward": ([_Shifted([0.5, 0.2], 0.4).double()], x4, acc),
        "rectified_along_a_subclass": ([ExponentialBarrier(ball, _Drifting(), 2, [1.0])], x4, acc),
        "callable_sigma": ([ball], x4, AccelUnicycle(sigma=lambda x: 0.1 * x[..., None])),
        "batch_dimensions": ([ball], x4.unsqueeze(0), acc),
        "float16": ([ball], x4.half(), acc),
        "meta_device": ([ball], torch.empty(2, 4, device="meta"), acc),
        "no_functions": ([], x4, acc),
        "index_outside_the_state": ([Ball([0.5, 0.2], 0.4, index=(0, 5))], x4, acc),
    }


@pytest.mark.parametrize("case", list(_unsupported_cases()))
def test_unsupported_cases_return_none(case: str) -> None:
    fns, x, dyn = _unsupported_cases()[case]
    with torch.no_grad():
        assert native.lie_terms(fns, x, dyn) is None


def test_strided_states_and_constants_of_another_dtype_are_read_as_float64() -> None:
    dyn = DoubleIntegrator(2, sigma=0.3).double()
    f32 = torch.float32
    ellipse = Ellipse(torch.tensor([0.2, -0.3], dtype=f32), torch.tensor([0.5, 1.5], dtype=f32),
                      angle=torch.tensor(0.4, dtype=f32))  # fmt: skip
    barrier = ExponentialBarrier(ellipse, dyn, 2, torch.tensor([2.0], dtype=f32))
    x = _states(3, 8, seed=8)[:, ::2]  # not contiguous
    terms, _ = native.lie_terms([barrier], x, dyn)
    # the torch closed forms cast the float32 constants to the state's float64 as well
    want = _columns(lie_derivatives(barrier, x, dyn, method="analytic"), x)
    _assert_terms(terms, want, F64)


def test_callable_sigma_without_hessian_is_native() -> None:
    dyn = AccelUnicycle(sigma=lambda x: 0.1 * x[..., None])
    x = _states(2, 4, seed=5)
    assert native.lie_terms([Ball([0.5, 0.2], 0.4).double()], x, dyn, hessian=False) is not None


def test_a_missing_or_stale_kernel_is_refused(
    monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    directory = Path(native.__file__).parent
    with caplog.at_level(logging.WARNING, logger="torchcbf"):
        stale = load_kernel(
            directory, "_lie_kernel", "torchcbf_lie_version", native.KERNEL_VERSION + 1, "torch"
        )
    assert stale is None and "another version" in caplog.text
    assert load_kernel(directory, "_no_such_kernel", "v", 1, "torch") is None
    # simulates a Lie kernel that failed to build (the loader then answers None)
    monkeypatch.setattr(native, "_library", lambda: None)
    assert not native.available()
    x = _states(1, 2, seed=6)
    assert native.lie_terms([Ball([0.5, 0.2], 0.4).double()], x, SingleIntegrator(2)) is None


# -- intersections and unions --------------------------------------------------------------------
ELLIPSE_CENTERS = [[1.0, 2.0], [3.0, 2.0], [-1.0, 1.0]]
ELLIPSE_AXES = [[0.5, 1.5], [0.75, 2.0], [1.0, 0.75]]


def _radius_children(model: nn.Module, k: float = 20.0) -> list[nn.Module]:
    """The rectified radius form of three ellipses and ``k`` times the radius form."""
    radius = Transformed(Ellipse(ELLIPSE_CENTERS, ELLIPSE_AXES, index=(0, 1)), "radius")
    return [ExponentialBarrier(radius, model, 2, [k]), Scaled(radius, k)]


def _reductions(model: nn.Module) -> dict[str, tuple[dict, list[nn.Module]]]:
    """Reductions (options, children) the kernel describes."""
    balls = Ball([[0.5, 0.2], [1.0, 1.0]], [0.4, 0.3])
    ellipse = Ellipse([0.2, -0.3], [0.5, 1.5], angle=0.4)
    stack = BarrierStack(Ball([1.5, 0.0], 0.6), Transformed(ellipse, "exp", rate=0.5))
    return {
        "radius_elementwise": ({"elementwise": True}, _radius_children(model)),
        "all_outputs": ({}, [balls, ellipse, ExponentialBarrier(ellipse, model, 2, [1.5])]),
        "stacked_children_elementwise": ({"elementwise": True}, [stack, Scaled(balls, [2.0, 0.5])]),
        "scalar_children_elementwise": ({"elementwise": True}, [Ball([0.5, 0.2], 0.4), ellipse]),
        "one_child": ({}, [Scaled(balls, 0.5)]),
    }


@pytest.mark.parametrize("batch", [1, 6])
@pytest.mark.parametrize("dtype", [F64, torch.float32], ids=["float64", "float32"])
@pytest.mark.parametrize("sigma", ["none", "matrix"])
@pytest.mark.parametrize("smooth", [True, False], ids=["smooth", "hard"])
@pytest.mark.parametrize("case", list(_reductions(AccelUnicycle())))
@pytest.mark.parametrize("cls", [Intersection, Union])
def test_reductions_match_closed_forms_and_autograd(
    cls: type, case: str, smooth: bool, sigma: str, dtype: torch.dtype, batch: int
) -> None:
    dyn = _model("accel_unicycle", sigma)
    options, children = _reductions(dyn)[case]
    barrier = cls(*children, smooth=smooth, temperature=0.7, **options)
    dyn, barrier = dyn.to(dtype), barrier.to(dtype)
    assert barrier.has_analytic and native.describes([barrier], dyn)
    x = _states(batch, 4, seed=len(case) + batch, dtype=dtype)
    terms = _kernel_matches_closed_forms([barrier], x, dyn, dtype)
    auto = _columns(lie_derivatives(barrier.double(), x.double(), dyn.double(),
                                    method="autograd"), x)  # fmt: skip
    _assert_terms(terms, LieTerms(*(None if v is None else v.to(dtype) for v in auto)), dtype)


@pytest.mark.parametrize("dtype", [F64, torch.float32], ids=["float64", "float32"])
def test_hard_reductions_average_the_active_columns_at_ties(dtype: torch.dtype) -> None:
    """At a tie of a hard minimum or maximum every path gives the mean of the tied columns'
    terms (the subgradient autograd of amin/amax gives): the kernel, the closed forms and
    autograd agree, and the filter's control does not depend on the path."""
    dyn = AccelUnicycle(sigma=0.2).double()
    ball = Ball([0.5, 0.2], 0.4)
    rect = ExponentialBarrier(ball, dyn, 2, [1.0])
    x = _states(4, 4, seed=11)
    x[:, 2] = 0.0  # at rest the rectified ball equals the ball, with another gradient
    cols = [_columns(lie_derivatives(b.double(), x, dyn), x) for b in (ball, rect)]
    for cls in (Intersection, Union):
        barrier = cls(ball, rect).to(dtype)
        xd, dynd = x.to(dtype), dyn.to(dtype)
        terms, _ = native.lie_terms([barrier], xd, dynd)
        for method in ("analytic", "autograd"):
            want = _columns(lie_derivatives(barrier, xd, dynd, method=method), xd)
            _assert_terms(terms, want, dtype)
        mean = (cols[0].lgh + cols[1].lgh) / 2
        tol = 1e-12 if dtype == F64 else 1e-4
        torch.testing.assert_close(terms.lgh.double(), mean, atol=tol, rtol=tol)
        assert not torch.allclose(cols[0].lgh, cols[1].lgh)  # a real tie of two gradients
    from torchcbf.filters import SafetyFilter

    corner = torch.tensor([[0.9, 0.9]], dtype=F64)  # the x and y faces of the box tie
    u = torch.tensor([[1.0, 1.0]], dtype=F64)
    plane = SingleIntegrator(2, u_min=-2.0, u_max=2.0).double()
    with torch.no_grad():
        answers = [
            SafetyFilter(plane, [Box([-1.0, -1.0], [1.0, 1.0]).double()], alpha=1.0, **kw)(
                corner, u
            ).u
            for kw in ({}, {"backend": "torch"}, {"lie_method": "autograd"})
        ]
    for got in answers:  # both faces: -u_i >= -0.1
        torch.testing.assert_close(got, torch.tensor([[0.1, 0.1]], dtype=F64))


def test_non_finite_values_give_the_closed_forms_values() -> None:
    dyn = AccelUnicycle(sigma=0.2).double()
    x = _states(4, 4, seed=12)
    x[1, 0] = torch.nan
    huge = x.clone()
    huge[2, :] = 1e200  # both balls' values infinite (their gradients finite)
    huge[3, 2] = 1e200  # the second ball's value infinite, the first's finite
    near, far = Ball([0.5, 0.2], 0.4), Ball([1.0, 0.5], 0.3, index=(2, 3))
    for cls in (Intersection, Union):
        for smooth in (True, False):
            cases = [
                (cls(*_radius_children(dyn), smooth=smooth, elementwise=True).double(), x),
                (cls(near, far, smooth=smooth, temperature=0.2).double(), huge),
            ]
            for fn, states in cases:
                terms, _ = native.lie_terms([fn], states, dyn)
                want = _columns(lie_derivatives(fn, states, dyn, method="analytic"), states)
                assert bool(terms.h[1].isnan().all() and want.h[1].isnan().all())
                rows = [0, 2, 3]  # a NaN state's other terms: NaN or not, as it comes
                for name in ("h", "lfh", "lgh", "hess_trace"):
                    got, ref = getattr(terms, name)[rows], getattr(want, name)[rows]
                    assert torch.equal(got.isnan(), ref.isnan()), (cls, smooth, name)
                    torch.testing.assert_close(got.nan_to_num(), ref.nan_to_num(), msg=name)


def test_the_temperature_is_read_at_every_call() -> None:
    dyn = AccelUnicycle(sigma=0.28).double()
    barrier = Intersection(*_radius_children(dyn), smooth=True, temperature=0.5,
                           elementwise=True).double()  # fmt: skip
    x = _states(3, 4, seed=13)
    before = native.lie_terms([barrier], x, dyn)[0]
    barrier.temperature = 2.0
    after = native.lie_terms([barrier], x, dyn)[0]
    assert not torch.equal(before.h, after.h)
    assert not torch.equal(before.hess_trace, after.hess_trace)
    _assert_terms(after, _columns(lie_derivatives(barrier, x, dyn, method="analytic"), x), F64)
    barrier.temperature = 0.0  # the kernel declines; the torch path answers as it does
    assert native.lie_terms([barrier], x, dyn) is None


def test_reductions_in_stacks_and_lists_concatenate_in_order() -> None:
    dyn = AccelUnicycle(sigma=0.2).double()
    inside = Intersection(*_radius_children(dyn), smooth=True, temperature=0.5, elementwise=True)
    union = Union(Ball([0.5, 0.2], 0.4), Ball([[1.0, 1.0], [2.0, 0.0]], [0.3, 0.2]))
    fns = [
        Ball([[0.5, 0.2], [1.0, 1.0]], [0.4, 0.3]),
        inside,
        BarrierStack(Ball([0.5, 0.2], 0.4), union, inside, Scaled(Ball([1.0, 1.0], 0.3), 2.0)),
        union,
    ]
    fns = [f.double() for f in fns]
    x = _states(3, 4, seed=14)
    _kernel_matches_closed_forms(fns, x, dyn, sizes=[2, 3, 6, 1])


class _RewrittenIntersection(Intersection):
    """A subclass with its own ``forward``: the kernel's reduction is not its own."""

    def forward(self, x: Tensor, t: Tensor | float | None = None) -> Tensor:
        return super().forward(x, t) - 0.1


class _OwnColumns(Union):
    """A subclass that changes how ``forward`` gathers the children's values."""

    def _columns(self, values: list[Tensor], x: Tensor) -> tuple[Tensor, bool]:
        cols, scalar = super()._columns(values, x)
        return 2.0 * cols, scalar


def _unsupported_reductions() -> dict[str, LieFunction]:
    acc = AccelUnicycle(sigma=0.2).double()
    ball, two = Ball([0.5, 0.2], 0.4), Ball([[0.5, 0.2], [1.0, 1.0]], [0.4, 0.3])
    smooth = Intersection(ball, two, smooth=True)
    return {
        "own_forward": _RewrittenIntersection(*_radius_children(acc), elementwise=True),
        "own_columns": _OwnColumns(two, Scaled(two, 2.0), elementwise=True),
        "nested": Intersection(smooth, ball),
        "nested_in_a_child_stack": Union(BarrierStack(ball, smooth), two),
        "scaled": Scaled(smooth, 2.0),
        "transformed": Transformed(smooth, "exp"),
        "rectified": ExponentialBarrier(smooth, acc, 2, [1.0]),
        "unsupported_child": Intersection(ball, HalfSpace([1.0, 0.0], 2.0, index=(0, 1))),
        "output_counts_differ": Intersection(ball, two, elementwise=True),
    }


@pytest.mark.parametrize("case", list(_unsupported_reductions()))
def test_unsupported_reductions_return_none(case: str) -> None:
    barrier = _unsupported_reductions()[case].double()
    dyn = AccelUnicycle(sigma=0.2).double()
    with torch.no_grad():
        assert not native.describes([barrier], dyn)
        assert native.lie_terms([barrier], _states(2, 4, seed=15), dyn) is None


@pytest.fixture(scope="module")
def risk_filter() -> nn.Module:
    """Scenario B's risk-aware filter in its default configuration (float64)."""
    from torchcbf.scenarios.unicycle_mppi_cbf import mppi_cbf

    scenario = mppi_cbf("mppi_rascbf", num_seeds=1, num_samples=8, horizon=4, dtype=F64)
    assert scenario.params["risk_form"] == "inside"
    return scenario.safety_filter


@pytest.mark.parametrize("dtype", [F64, torch.float32], ids=["float64", "float32"])
def test_scenario_b_risk_aware_filter_runs_in_the_kernels(
    risk_filter: nn.Module, dtype: torch.dtype
) -> None:
    from torchcbf.filters import RiskAware, SafetyFilter

    filt = copy.deepcopy(risk_filter)
    (barrier,) = filt.barriers
    assert isinstance(barrier, Intersection) and barrier.elementwise and barrier.smooth
    assert native.describes(filt.barriers, filt.dynamics)
    filt = filt.to(dtype)
    x = _states(4, 4, seed=16, dtype=dtype)
    x[:, 2] = x[:, 2].abs() + 0.5
    u = 5 * torch.randn(4, 2, generator=torch.Generator().manual_seed(17)).to(dtype)
    rewritten = _RewrittenIntersection(
        *barrier.stack.barriers, smooth=True, temperature=barrier.temperature, elementwise=True
    )
    for rows in (slice(0, 1), slice(None)):
        with torch.no_grad():
            fast = filt(x[rows], u[rows])
        assert fast.path == "native/realtime"
        with torch.enable_grad():
            ref = filt(x[rows].clone().requires_grad_(), u[rows])  # the general path
        assert ref.path != "native/realtime"
        tol = {"rtol": 1e-4, "atol": 1e-3} if dtype == torch.float32 else {}
        torch.testing.assert_close(fast.h, ref.h.detach(), **tol)
        torch.testing.assert_close(fast.u, ref.u.detach(), **tol)
        torch.testing.assert_close(fast.status, ref.status)
    mode = filt.condition
    eta = "local" if mode.local else mode.eta
    again = RiskAware(rho=mode.rho, horizon=float(mode.horizon), eta=eta)
    other = SafetyFilter(filt.dynamics, barriers=rewritten, mode=again, R=filt.R).to(dtype)
    with torch.no_grad():
        assert other(x, u).path != "native/realtime"  # a subclass's forward: not the kernel's


@pytest.mark.parametrize(
    ("dtype", "temperature"), [(torch.float32, 1e-39), (torch.float32, 1e-46), (F64, 1e-320)]
)
@pytest.mark.parametrize("cls", [Intersection, Union])
def test_a_subnormal_temperature_gives_the_hard_reduction(cls, dtype, temperature) -> None:
    """``v / T`` would overflow (inf and NaN on every path that computes in the dtype): the
    log-sum-exp is shifted by its largest term before the division, and a ``T`` the dtype
    cannot hold (0 in float32) is its least normal number."""
    dyn = SingleIntegrator(2, sigma=0.3).to(dtype)
    balls = (Ball([1.0, 0.5], 0.7), Ball([-1.0, 0.0], 0.5))
    smooth = cls(*balls, smooth=True, temperature=temperature).to(dtype)
    hard = cls(*balls).to(dtype)
    x = torch.tensor([[0.1, 0.2], [2.0, 0.5]], dtype=dtype)
    want = lie_derivatives(hard, x, dyn, method="autograd")
    for method in ("autograd", "analytic"):
        got = lie_derivatives(smooth, x, dyn, method=method)
        torch.testing.assert_close(got.h, want.h)
        torch.testing.assert_close(got.dhdx, want.dhdx)
    terms, _ = native.lie_terms([smooth], x, dyn)
    torch.testing.assert_close(terms.h.reshape(-1), want.h.reshape(-1).to(terms.h))
