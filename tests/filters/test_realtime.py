"""The real-time path of SafetyFilter (a few states, no gradient to carry, one call of the
filter kernel): the same outputs as the general path, and cvxpy's control; with quadric
barriers, the native Lie terms give the torch closed forms' answers."""

from __future__ import annotations

import functools

import _filter_reference as ref
import numpy as np
import pytest
import torch
from _filter_reference import solve_reference
from test_safety_filter import MODES, random_states, scene

from torchcbf.barriers import (
    Ball,
    Barrier,
    Ellipse,
    ExponentialBarrier,
    QuadraticLyapunov,
    Scaled,
    Transformed,
    native,
    rectify,
)
from torchcbf.dynamics import AccelUnicycle, ControlAffine, DoubleIntegrator, SingleIntegrator
from torchcbf.filters import (
    CubicClassK,
    FilterMode,
    FilterStatus,
    LinearClassK,
    RiskAware,
    Robust,
    SafetyFilter,
    Stochastic,
    Vanilla,
    realtime,
)
from torchcbf.filters.conditions import Condition

pytestmark = pytest.mark.skipif(not realtime.available(), reason="C kernel not built")

#: a batch of a few states, as a controller of several robots filters them
FEW = 16


def _lie(out) -> str:
    """Where the Lie terms of a :class:`FilterOutput` came from (``native``, ``torch``,
    ``mixed``)."""
    return out.path.split("/", 1)[0]


def _qp(out) -> str:
    """What solved the QP of a :class:`FilterOutput` (``realtime`` or a QP path)."""
    return out.path.split("/", 1)[1]


def _general(filt: SafetyFilter, x: torch.Tensor, u: torch.Tensor):
    """The general path: an input that requires grad (the real-time path carries none)."""
    with torch.enable_grad():
        out = filt(x.clone().requires_grad_(), u)
    assert _qp(out) != "realtime", out.path
    return out._replace(**{k: v.detach() for k, v in out._asdict().items() if k != "path"})


def _same(a, b, tol: float) -> None:
    for name in a._fields[:-1]:  # every field but the path
        va, vb = getattr(a, name), getattr(b, name)
        assert va.shape == vb.shape and va.dtype == vb.dtype, name
        if va.dtype == torch.int64:
            assert torch.equal(va, vb), name
        else:
            torch.testing.assert_close(va, vb, atol=tol, rtol=tol, equal_nan=True, msg=name)


@pytest.mark.parametrize("mode", MODES)
@pytest.mark.parametrize("clf", [False, True])
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
@pytest.mark.parametrize("slack", ["shared", "per_row", "none"])
def test_realtime_path_matches_general_path(
    mode: str, clf: bool, dtype: torch.dtype, slack: str
) -> None:
    xs, us = random_states(FEW, seed=20 + MODES.index(mode))
    filt = scene(mode, dtype, clf=clf, slack=slack, fallback="brake")
    x, u = torch.tensor(xs, dtype=dtype), torch.tensor(us, dtype=dtype)
    tol = 1e-9 if dtype == torch.float64 else 1e-4
    with torch.no_grad():
        batch = filt(x, u)
        one = filt(x[0], u[0])
    # the kernel answers unless a hard QP is infeasible on some row (the general path's
    # fallback then serves it)
    fell_back = bool((batch.status == FilterStatus.FALLBACK).any())
    assert (_qp(batch) == "realtime") != fell_back, batch.path
    assert _qp(one) == "realtime", one.path
    _same(batch, _general(filt, x, u), tol)
    _same(one, _general(filt, x[0], u[0]), tol)
    assert one.u.shape == (2,) and one.status.shape == ()


@pytest.mark.parametrize("mode", MODES)
def test_realtime_control_matches_cvxpy(mode: str) -> None:
    xs, us = random_states(12, seed=40 + MODES.index(mode))
    filt = scene(mode)
    solved = 0
    for i in range(len(xs)):
        with torch.no_grad():
            out = filt(torch.tensor(xs[i]), torch.tensor(us[i]))
        ref = solve_reference(xs[i], us[i], mode)
        if ref is None:
            assert int(out.status) == FilterStatus.RELAXED
            continue
        solved += 1
        assert _qp(out) == "realtime", out.path
        assert int(out.status) == FilterStatus.SOLVED
        assert np.abs(out.u.numpy() - ref).max() <= 1e-6
    assert solved >= 6


def test_non_finite_state_and_infeasible_hard_qp_take_the_general_path() -> None:
    xs, us = random_states(3, seed=9)
    filt = scene("vanilla")
    x, u = torch.tensor(xs), torch.tensor(us)
    x[1, 0] = float("nan")
    with torch.no_grad():
        out = filt(x, u)
    assert _qp(out) != "realtime", out.path
    _same(out, _general(filt, x, u), 1e-12)
    assert out.status[1] == FilterStatus.NON_FINITE
    hard = scene("vanilla", slack="none", fallback="brake")
    xs, us = random_states(16, seed=1)
    with torch.no_grad():
        out = hard(torch.tensor(xs), torch.tensor(us))
    _same(out, _general(hard, torch.tensor(xs), torch.tensor(us)), 1e-9)


def test_grad_mode_without_gradients_takes_the_realtime_path() -> None:
    filt = scene("stochastic")
    xs, us = random_states(4, seed=5)
    x, u = torch.tensor(xs), torch.tensor(us)
    with torch.enable_grad():
        out = filt(x, u)
    assert _qp(out) == "realtime" and not out.u.requires_grad, out.path
    _same(out, _general(filt, x, u), 1e-9)


class _Superellipse(Barrier):
    """A user's barrier without closed forms (its Lie terms come from autograd); ``scale``:
    a tensor it reads that no module holds, where given."""

    def __init__(self, scale: torch.Tensor | None = None, learnable: bool = False) -> None:
        super().__init__()
        self.register_constant("center", [2.0, 0.5], learnable=learnable)
        self.scale = scale

    def forward(self, x: torch.Tensor, t=None) -> torch.Tensor:
        d = x[..., :2] - self.center.to(x)
        h = d[..., 0] ** 4 + (d[..., 1] / 0.6) ** 4 - 1.0
        return h if self.scale is None else self.scale * h


class _PointMass(ControlAffine):
    """A user's planar double integrator (``f`` and ``g`` only)."""

    def __init__(self) -> None:
        super().__init__(state_dim=4, control_dim=2, u_min=-2.0, u_max=2.0)

    def f(self, x: torch.Tensor) -> torch.Tensor:
        return torch.cat([x[..., 2:], torch.zeros_like(x[..., 2:])], -1)

    def g(self, x: torch.Tensor) -> torch.Tensor:
        g = x.new_zeros(*x.shape[:-1], 4, 2)
        g[..., 2, 0] = g[..., 3, 1] = 1.0
        return g


def _users_filter(rectified: bool, **kw) -> tuple[SafetyFilter, torch.Tensor, torch.Tensor]:
    gen = torch.Generator().manual_seed(4)
    dyn = SingleIntegrator(2, u_min=-2.0, u_max=2.0) if not rectified else _PointMass()
    barrier = _Superellipse(**kw)
    if rectified:
        barrier = rectify(barrier, dyn, form="exponential", gains=[2.0])
    filt = SafetyFilter(dyn, [barrier]).double()
    n = dyn.state_dim
    x = torch.randn(6, n, generator=gen, dtype=torch.float64) + torch.tensor([0.0, 0.5, 0, 0][:n])
    return filt, x, 3.0 * torch.randn(6, 2, generator=gen, dtype=torch.float64)


@pytest.mark.parametrize("rectified", [False, True])
def test_autograd_lie_terms_in_grad_mode_without_gradients_take_the_realtime_path(
    rectified: bool,
) -> None:
    filt, x, u = _users_filter(rectified)
    with torch.enable_grad():
        out = filt(x, u)
    assert out.path == "torch/realtime" and not out.u.requires_grad
    assert not out.h.requires_grad
    with torch.no_grad():
        _same(out, filt(x, u), 0.0)
    _same(out, _general(filt, x, u), 1e-9)


@pytest.mark.parametrize("rectified", [False, True])
@pytest.mark.parametrize("source", ["captured", "parameter"])
def test_autograd_lie_terms_keep_a_gradient_the_barrier_carries(
    rectified: bool, source: str
) -> None:
    scale = torch.tensor(1.5, dtype=torch.float64, requires_grad=source == "captured")
    filt, x, u = _users_filter(rectified, scale=scale, learnable=source == "parameter")
    out = filt(x, u)
    assert _qp(out) != "realtime" and out.u.requires_grad, out.path
    leaf = scale if source == "captured" else next(filt.parameters())
    (grad,) = torch.autograd.grad((out.u**2).sum() + out.h.sum(), leaf)
    assert torch.isfinite(grad).all() and grad.abs().sum() > 0


@pytest.mark.parametrize("source", ["x", "u_nom", "parameter", "buffer", "closure"])
def test_a_gradient_to_carry_takes_the_general_path(source: str) -> None:
    gain = torch.tensor(2.0, dtype=torch.float64, requires_grad=source in ("buffer", "closure"))
    alpha = {
        "parameter": LinearClassK(2.0, learnable=True),
        "buffer": gain,  # kept as a buffer that requires grad
        "closure": lambda h: gain * h,  # a tensor no module holds
    }.get(source, 2.0)
    filt = scene("vanilla", alpha=alpha)
    xs, us = random_states(2, seed=6)
    x, u = torch.tensor(xs), torch.tensor(us)
    leaf = {"x": x, "u_nom": u}.get(source)
    if leaf is not None:
        leaf.requires_grad_()
    out = filt(x, u)
    assert _qp(out) != "realtime" and out.u.requires_grad, out.path
    out.u.sum().backward()
    if leaf is not None:
        grads = [leaf.grad]
    elif source == "parameter":
        grads = [p.grad for p in filt.parameters()]
    else:
        grads = [gain.grad]
    assert all(g is not None and torch.isfinite(g).all() for g in grads)
    with torch.no_grad():  # no_grad: the real-time path, whatever requires grad
        assert _qp(filt(x, u)) == "realtime"


def test_a_time_the_barriers_ignore_carries_no_gradient() -> None:
    filt = scene("vanilla")
    xs, us = random_states(2, seed=6)
    t = torch.zeros(2, dtype=torch.float64, requires_grad=True)
    out = filt(torch.tensor(xs), torch.tensor(us), t)
    assert _qp(out) == "realtime" and not out.u.requires_grad, out.path


@pytest.mark.parametrize("spread", [1e2, 1e7])
def test_ill_conditioned_weight_agrees_with_general_path(spread: float) -> None:
    """A rotated R of condition ``spread``: the kernel keeps rows it conditions well and
    hands the others to the general path; the answers agree either way."""
    c, s = np.cos(0.7), np.sin(0.7)
    rot = torch.tensor([[c, -s], [s, c]], dtype=torch.float64)
    R = rot @ torch.diag(torch.tensor([1.0, 1.0 / spread], dtype=torch.float64)) @ rot.T
    filt = scene("vanilla", clf=False, R=R)
    xs, us = random_states(4, seed=8)
    x, u = torch.tensor(xs), torch.tensor(us)
    with torch.no_grad():
        out = filt(x, u)
    assert (_qp(out) == "realtime") == (spread < 1e4), out.path
    _same(out, _general(filt, x, u), 1e-7)


def rectified_scene(
    mode: str, dtype: torch.dtype = torch.float64, *, radius: bool = False, **overrides
) -> SafetyFilter:
    """The rectified-ellipse scene of _filter_reference: two rotated, scaled ellipses as
    exponential CBFs (closed forms, native Lie terms) on an accelerating unicycle; with
    ``radius``, the ellipses in their radius form instead of scaled (no reference rows)."""
    kw: dict = {}
    if mode == "robust":
        kw["disturbance_bound"] = ref.ACCEL_W_MAX
    if mode in ("stochastic", "risk_aware"):
        kw["sigma"] = ref.ACCEL_SIGMA
    limits = {"u_min": torch.tensor(ref.ACCEL_U_MIN), "u_max": torch.tensor(ref.ACCEL_U_MAX)}
    plant = AccelUnicycle(**limits, **kw)
    ellipses = Ellipse(
        torch.tensor(ref.ELLIPSE_CENTERS),
        torch.tensor(ref.ELLIPSE_AXES),
        angle=torch.tensor(ref.ELLIPSE_ANGLES),
    )
    # rectified along the noiseless model, filtered along the plant (as scenario B does)
    shape = (
        Transformed(ellipses, "radius") if radius else Scaled(ellipses, ref.ELLIPSE_SCALES.tolist())
    )
    barrier = ExponentialBarrier(shape, AccelUnicycle(), 2, [ref.K0])
    modes = {
        "vanilla": Vanilla(),
        "robust": Robust(),
        "stochastic": Stochastic(beta=ref.BETA),
        "risk_aware": RiskAware(ref.RHO, ref.HORIZON, torch.tensor(ref.ACCEL_ETA)),
    }
    options = dict(mode=modes[mode], alpha=torch.tensor(ref.ELLIPSE_GAINS), R=torch.tensor(ref.R))
    options.update(overrides)
    return SafetyFilter(plant, barrier, **options).to(dtype)


def rectified_states(count: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """States of the rectified scene where both exponential CBFs are positive."""
    rng = np.random.default_rng(seed)
    out = []
    while len(out) < count:
        x = np.array([rng.uniform(-2.0, 4.0), rng.uniform(-1.0, 4.0), rng.uniform(-0.5, 2.0),
                      rng.uniform(-np.pi, np.pi)])  # fmt: skip
        if ref.rectified_rows(x, "vanilla")[2].min() > 0.05:
            out.append(x)
    return np.stack(out), 2.0 * rng.standard_normal((count, 2))


def balls_scene(
    mode: str | FilterMode, dtype: torch.dtype = torch.float64, **overrides
) -> SafetyFilter:
    """Eight balls on a single integrator with box limits (the benchmark's scene)."""
    kw = {"sigma": 0.2} if mode == "stochastic" else {}
    gen = torch.Generator().manual_seed(0)
    ball = Ball(8 * torch.rand(8, 2, generator=gen) - 4, 0.3 + 0.4 * torch.rand(8, generator=gen))
    dyn = SingleIntegrator(2, u_min=-2.0, u_max=2.0, **kw)
    if isinstance(mode, str):
        mode = Stochastic(beta=0.1) if mode == "stochastic" else Vanilla()
    return SafetyFilter(dyn, ball, mode=mode, **overrides).to(dtype)


def balls_states(count: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    filt = balls_scene("vanilla")
    rng = np.random.default_rng(seed)
    x = rng.uniform(-5.0, 5.0, (8 * count, 2))
    with torch.no_grad():
        keep = (filt.barriers[0](torch.tensor(x)) > 0.05).all(-1).numpy()
    x = x[keep][:count]
    return x, np.clip(-2.0 * x, -2.0, 2.0)


SCENES = {
    "balls": (balls_scene, balls_states, ["vanilla", "stochastic"]),
    "rectified_ellipses": (rectified_scene, rectified_states, MODES),
    "rectified_radius": (
        functools.partial(rectified_scene, radius=True),
        rectified_states,
        ["stochastic", "risk_aware"],
    ),
}
SCENE_MODES = [(s, m) for s, (_, _, modes) in SCENES.items() for m in modes]


@pytest.mark.skipif(not native.available(), reason="Lie kernel not built")
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32], ids=["float64", "float32"])
@pytest.mark.parametrize(("scene_name", "mode"), SCENE_MODES)
def test_native_lie_terms_give_the_torch_closed_forms_answers(
    scene_name: str, mode: str, dtype: torch.dtype
) -> None:
    build, states, _ = SCENES[scene_name]
    filt, closed = build(mode, dtype), build(mode, dtype, lie_method="analytic")
    xs, us = states(FEW, seed=60 + MODES.index(mode))
    x, u = torch.tensor(xs, dtype=dtype), torch.tensor(us, dtype=dtype)
    tol = 1e-10 if dtype == torch.float64 else 1e-4
    with torch.no_grad():
        for xb, ub in ((x[0], u[0]), (x, u)):
            out, want = filt(xb, ub), closed(xb, ub)
            assert out.path == "native/realtime"  # the native terms, in the filter's kernel
            assert _lie(want) == "torch"  # lie_method="analytic": the torch closed forms
            _same(out, want, tol)


@pytest.mark.skipif(not native.available(), reason="Lie kernel not built")
@pytest.mark.parametrize("mode", MODES)
def test_rectified_scene_matches_cvxpy(mode: str) -> None:
    filt = rectified_scene(mode)
    xs, us = rectified_states(12, seed=80 + MODES.index(mode))
    solved = 0
    for i in range(len(xs)):
        with torch.no_grad():
            out = filt(torch.tensor(xs[i]), torch.tensor(us[i]))
        assert out.path == "native/realtime"
        np.testing.assert_allclose(out.h.numpy(), ref.rectified_rows(xs[i], mode)[2], atol=1e-12)
        expected = ref.solve_rectified_reference(xs[i], us[i], mode)
        if expected is None:
            assert int(out.status) == FilterStatus.RELAXED
            continue
        solved += 1
        assert int(out.status) == FilterStatus.SOLVED
        assert np.abs(out.u.numpy() - expected).max() <= 1e-6
    assert solved >= 6


@pytest.mark.skipif(not native.available(), reason="Lie kernel not built")
def test_a_state_that_requires_grad_takes_the_torch_path_with_its_gradients() -> None:
    filt = rectified_scene("stochastic")
    xs, us = rectified_states(16, seed=7)
    x, u = torch.tensor(xs), torch.tensor(us)
    with torch.no_grad():
        out = filt(x, u)
    assert out.path == "native/realtime"
    # rows the filter changed, solved: their active set is stable under small perturbations
    rows = ((out.u - u).abs().amax(-1) > 0.05) & (out.status == FilterStatus.SOLVED)
    assert int(rows.sum()) >= 2
    x, u = x[rows][:2].clone().requires_grad_(), u[rows][:2]
    graph = filt(x, u)
    assert _lie(graph) == "torch" and graph.u.requires_grad, graph.path
    torch.testing.assert_close(graph.u.detach(), out.u[rows][:2], atol=1e-10, rtol=0)
    assert torch.autograd.gradcheck(lambda xx: filt(xx, u).u, (x,), eps=1e-6, atol=1e-6, rtol=1e-4)


@pytest.mark.skipif(not native.available(), reason="Lie kernel not built")
def test_a_large_batch_or_a_missing_kernel_takes_the_torch_path(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    filt, closed = (
        rectified_scene("stochastic"),
        rectified_scene("stochastic", lie_method="analytic"),
    )
    xs, us = rectified_states(realtime.MAX_BATCH + 1, seed=9)
    x, u = torch.tensor(xs), torch.tensor(us)
    with torch.no_grad():
        assert filt(x[:2], u[:2]).path == "native/realtime"
        out = filt(x, u)
        assert _lie(out) == "torch", out.path  # beyond MAX_BATCH: the torch closed forms
        _same(out, closed(x, u), 1e-12)
        # simulates a Lie kernel that failed to build (the loader then answers None)
        monkeypatch.setattr(native, "_library", lambda: None)
        out = filt(x[:2], u[:2])
        assert _lie(out) == "torch", out.path
        _same(out, closed(x[:2], u[:2]), 1e-12)


@pytest.mark.skipif(not native.available(), reason="Lie kernel not built")
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32], ids=["float64", "float32"])
@pytest.mark.parametrize(("scene_name", "mode"), [*SCENE_MODES, ("rectified_ellipses", "beta_k")])
def test_affine_conditions_equal_the_modes_torch_conditions(
    scene_name: str, mode: str, dtype: torch.dtype
) -> None:
    build, states, _ = SCENES[scene_name]
    filt = build("stochastic" if mode == "beta_k" else mode, dtype)
    if mode == "beta_k":  # one margin per barrier output
        filt.condition = Stochastic(beta=[0.05, 0.2])
    xs, _ = states(5, seed=90)
    x = torch.tensor(xs, dtype=dtype)
    (alpha,) = filt.alpha
    affine = filt.condition.affine_cbf(alpha)
    if mode == "robust":
        assert affine is None  # the disturbance term is not affine in the kernel's terms
        return
    hessian = filt.condition.needs_hessian
    with torch.no_grad():
        found = native.cbf_conditions(filt.barriers, x, filt.dynamics, affine, hessian=hessian)
        call = native.condition_call(filt.barriers, x, filt.dynamics, affine, hessian=hessian)
        (barrier,) = filt.barriers
        terms = barrier.lie(x, filt.dynamics, torch.zeros(5, dtype=dtype), method="analytic",
                            hessian=hessian)  # fmt: skip
        a, b = filt.condition.cbf(terms, alpha, filt.dynamics, x)
    assert found is not None and call is not None
    h, a_native, b_native, sizes = found
    assert sizes == call.sizes == [terms.h.shape[-1]] and call.h.shape == h.shape
    tol = 1e-12 if dtype == torch.float64 else 1e-5
    for got, want in ((h, terms.h), (a_native, a), (b_native, b)):
        assert got.dtype == dtype and got.shape == want.shape
        torch.testing.assert_close(got, want, atol=tol * (1 + float(want.abs().max())), rtol=tol)


@pytest.mark.skipif(not native.available(), reason="Lie kernel not built")
@pytest.mark.parametrize(
    "alpha",
    ["per_barrier", "cubic", "wrong_size", "wrong_size_per_barrier"],
    ids=lambda v: v.replace("_", "-"),
)
def test_class_k_functions_the_kernel_cannot_take_use_the_torch_condition(alpha: str) -> None:
    gen = torch.Generator().manual_seed(3)
    balls = [Ball(4 * torch.rand(3, 2, generator=gen) - 2, 0.3) for _ in range(2)]
    dyn = SingleIntegrator(2, u_min=-2.0, u_max=2.0)
    spec = {
        "per_barrier": [LinearClassK(1.0), LinearClassK(3.0)],
        "cubic": CubicClassK(2.0),
        "wrong_size": [1.0, 2.0],
        "wrong_size_per_barrier": [LinearClassK(1.0), LinearClassK([1.0, 2.0])],
    }[alpha]
    filt = SafetyFilter(dyn, balls, alpha=spec).double()
    closed = SafetyFilter(dyn, balls, alpha=spec, lie_method="analytic").double()
    x, u = torch.tensor([[2.5, 2.5]], dtype=torch.float64), torch.tensor([[-2.0, -2.0]])
    with torch.no_grad():
        if alpha.startswith("wrong_size"):
            k = 6 if alpha == "wrong_size" else 3
            with pytest.raises(ValueError, match=f"alpha has 2 gains for {k} outputs"):
                filt(x, u.double())
            return
        out = filt(x, u.double())
    assert out.path == "native/realtime"  # the native Lie terms, the mode's torch condition
    _same(out, closed(x, u.double()), 1e-12)


@pytest.mark.skipif(not native.available(), reason="Lie kernel not built")
def test_a_declined_fused_call_gives_the_general_paths_answer(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    filt = rectified_scene("stochastic")
    closed = rectified_scene("stochastic", lie_method="analytic")
    xs, us = rectified_states(3, seed=11)
    x, u = torch.tensor(xs), torch.tensor(us)
    # simulates a Lie kernel of another version: the filter's kernel refuses it, answers 1
    monkeypatch.setattr(native, "KERNEL_VERSION", native.KERNEL_VERSION + 1)
    with torch.no_grad():
        out = filt(x, u)
        _same(out, closed(x, u), 1e-10)
    # the prepared call declined, then the general path with the native conditions
    assert _lie(out) == "native" and _qp(out) != "realtime", out.path


class _Margin(FilterMode):
    """A user's mode: vanilla minus a margin, with its affine form for the kernel."""

    name = "margin"

    def __init__(self, margin: float) -> None:
        super().__init__()
        self.register_buffer("margin", torch.tensor(margin, dtype=torch.float64))

    def cbf(self, terms, alpha, dynamics, x):
        return Condition(terms.lgh, terms.lfh + terms.dhdt + alpha(terms.h) - self.margin.to(x))

    def affine_cbf(self, alpha):
        if type(alpha) is not LinearClassK:
            return None
        return native.Affine(gain=alpha.gain, offset=self.margin, offset_scale=-1.0)


@pytest.mark.skipif(not native.available(), reason="Lie kernel not built")
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32], ids=["float64", "float32"])
def test_a_users_mode_with_an_affine_form_takes_the_kernel(dtype: torch.dtype) -> None:
    filt = balls_scene(_Margin(0.3), dtype, alpha=[2.0] * 8)
    closed = balls_scene(_Margin(0.3), dtype, alpha=[2.0] * 8, lie_method="analytic")
    xs, us = balls_states(4, seed=5)
    x, u = torch.tensor(xs, dtype=dtype), torch.tensor(us, dtype=dtype)
    with torch.no_grad():
        out = filt(x, u)
        assert out.path == "native/realtime"
        _same(out, closed(x, u), 1e-10 if dtype == torch.float64 else 1e-4)


@pytest.mark.skipif(not native.available(), reason="Lie kernel not built")
@pytest.mark.parametrize("slack", ["shared", "per_row", "none"])
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32], ids=["float64", "float32"])
def test_the_fused_call_takes_clf_rows_from_torch(slack: str, dtype: torch.dtype) -> None:
    goal = QuadraticLyapunov(torch.tensor([3.0, -2.0]))
    filt = balls_scene("vanilla", dtype, lyapunovs=goal, slack=slack)
    closed = balls_scene("vanilla", dtype, lyapunovs=goal, slack=slack, lie_method="analytic")
    xs, us = balls_states(FEW, seed=8)
    x, u = torch.tensor(xs, dtype=dtype), torch.tensor(us, dtype=dtype)
    with torch.no_grad():
        out = filt(x, u)
    # the CBF conditions from the Lie kernel, the Lyapunov function's from torch, the QP in
    # the filter's kernel
    assert out.path == "mixed/realtime"
    _same(out, closed(x, u), 1e-9 if dtype == torch.float64 else 1e-4)


class _Tighter(Vanilla):
    """A subclass that changes the condition but not its affine form."""

    def cbf(self, terms, alpha, dynamics, x):
        a, b = super().cbf(terms, alpha, dynamics, x)
        return Condition(a, b - 5.0)


@pytest.mark.skipif(not native.available(), reason="Lie kernel not built")
def test_a_subclass_overriding_cbf_alone_does_not_take_its_parents_affine_form() -> None:
    filt, closed = balls_scene(_Tighter()), balls_scene(_Tighter(), lie_method="analytic")
    xs, us = balls_states(3, seed=6)
    x, u = torch.tensor(xs), torch.tensor(us)
    with torch.no_grad():
        for xb, ub in ((x[0], u[0]), (x, u)):
            out = filt(xb, ub)
            # the native Lie terms, the subclass's torch condition
            assert out.path == "native/realtime"
            _same(out, closed(xb, ub), 1e-10)


@pytest.mark.skipif(not native.available(), reason="Lie kernel not built")
@pytest.mark.parametrize("mode", ["stochastic", "risk_aware"])
def test_a_one_entry_margin_for_several_outputs_is_refused_on_every_batch(mode: str) -> None:
    filt = rectified_scene(mode)
    if mode == "stochastic":
        filt.condition = Stochastic(beta=[0.1])
    else:
        filt.condition = RiskAware(ref.RHO, ref.HORIZON, [0.1])
        filt.condition.bind(filt.dynamics, list(filt.barriers), [])
    xs, us = rectified_states(realtime.MAX_BATCH + 1, seed=12)
    x, u = torch.tensor(xs), torch.tensor(us)
    name = "beta" if mode == "stochastic" else "eta"
    with torch.no_grad():
        for count in (1, realtime.MAX_BATCH + 1):
            with pytest.raises(ValueError, match=name):
                filt(x[:count], u[:count])


@pytest.mark.skipif(not native.available(), reason="Lie kernel not built")
def test_a_horizon_that_requires_grad_keeps_its_gradient() -> None:
    filt = rectified_scene("risk_aware")
    xs, us = rectified_states(1, seed=13)
    filt.condition.horizon.requires_grad_()
    u = torch.tensor(us) + torch.tensor([[30.0, 30.0]])  # pushes into the ellipses
    out = filt(torch.tensor(xs), u)
    assert out.u.requires_grad
    (grad,) = torch.autograd.grad(out.u.sum(), filt.condition.horizon)
    assert torch.isfinite(grad)


@pytest.mark.skipif(not native.available(), reason="Lie kernel not built")
def test_plain_numbers_in_an_affine_form_and_a_mismatched_prepared_call() -> None:
    filt = balls_scene("vanilla")
    x = torch.tensor(balls_states(2, seed=14)[0])
    args = filt.barriers, x, filt.dynamics
    numbers = native.Affine(gain=2.0, offset=0.3, offset_scale=-1.0)
    f64 = torch.float64
    tensors = native.Affine(gain=torch.tensor(2.0, dtype=f64), offset=torch.tensor(0.3, dtype=f64),
                            offset_scale=-1.0)  # fmt: skip
    with torch.no_grad():
        got, want = native.cbf_conditions(*args, numbers), native.cbf_conditions(*args, tensors)
        for g, w in zip(got[:3], want[:3], strict=True):
            torch.testing.assert_close(g, w, atol=1e-14, rtol=0)
        call = native.condition_call(*args, numbers)
        one = torch.zeros(1, 2, dtype=torch.float64)
        options = dict(slack="shared", two_pass=False, cbf_weight=1e3, clf_weight=1e2,
                       eps=1e-9, max_iter=50, slack_tol=1e-6)  # fmt: skip
        with pytest.raises(ValueError, match="prepared condition call"):
            realtime.solve(call, None, one, torch.eye(2, dtype=torch.float64), None, None,
                           **options)  # fmt: skip
        # a batch shape of other than the rows given is not the layout the kernel writes
        a, b = torch.ones(4, 1, 2, dtype=f64), torch.ones(4, 1, dtype=f64)
        u = torch.zeros(4, 2, dtype=f64)
        R = torch.eye(2, dtype=f64)
        assert realtime.solve((a, b), None, u, R, None, None, batch=(1,), **options) is None
        assert realtime.solve((a, b), None, u, R, None, None, batch=(2, 2), **options) is not None


@pytest.mark.skipif(not native.available(), reason="Lie kernel not built")
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32], ids=["float64", "float32"])
def test_noise_scale_of_an_affine_form(dtype) -> None:
    """``b + noise_scale |sigma' dh/dx|`` against the torch Lie terms; without a diffusion the
    kernel declines the form."""
    filt = balls_scene("stochastic").to(dtype)
    x = torch.tensor(balls_states(5, seed=3)[0], dtype=dtype)
    args = filt.barriers, x, filt.dynamics
    plain = native.Affine(trace_weight=0.5, gain=2.0, offset=0.3, offset_scale=-1.0)
    noisy = plain._replace(noise_scale=-1.7)
    with torch.no_grad():
        h, a, b, _ = native.cbf_conditions(*args, plain)
        h2, a2, b2, _ = native.cbf_conditions(*args, noisy)
        (barrier,) = filt.barriers
        terms = barrier.lie(x, filt.dynamics, hessian=False)
    noise = torch.linalg.vector_norm(terms.dhdx @ filt.dynamics.sigma(x), dim=-1)
    tol = {"atol": 1e-12, "rtol": 1e-12} if dtype == torch.float64 else {}
    torch.testing.assert_close(h2, h, **tol)
    torch.testing.assert_close(a2, a, **tol)
    torch.testing.assert_close(b2, b - 1.7 * noise, **tol)
    assert native.cbf_conditions(*args, noisy, hessian=False) is None


@pytest.mark.parametrize("scale", [1e3, 1e20, 1e100])
def test_a_nominal_control_far_beyond_the_limits_gets_no_false_answer(scale: float) -> None:
    """Far outside its limits, ``u_nom`` puts the QP's unconstrained minimiser orders of
    magnitude from the feasible set: every row stays in the limits, a row called SOLVED meets
    its conditions, and the real-time and general paths agree."""
    g = torch.Generator().manual_seed(5)
    dyn = DoubleIntegrator(8, u_min=-1.0, u_max=1.0)
    balls = Ball(torch.randn(6, 2, generator=g, dtype=torch.float64) * 2 + 1,
                 torch.rand(6, generator=g, dtype=torch.float64) + 0.2)  # fmt: skip
    filt = SafetyFilter(dyn, ExponentialBarrier(balls, dyn, 2, (1.5,))).double()
    x = torch.randn(3, 16, generator=g, dtype=torch.float64)
    u_nom = scale * torch.randn(3, 8, generator=g, dtype=torch.float64)
    with torch.no_grad():
        out = filt(x, u_nom)
    with torch.enable_grad():
        gen = filt(x.clone().requires_grad_(), u_nom)
    assert not gen.path.endswith("realtime")
    assert torch.equal(out.status, gen.status)
    for o in (out, gen):
        assert float(o.u.detach().abs().max()) <= 1.0 + 1e-6
        solved = (o.status == FilterStatus.SOLVED).unsqueeze(-1)
        assert bool((o.constraint_value.detach() >= -1e-6).logical_or(~solved).all())
    torch.testing.assert_close(out.u, gen.u.detach(), atol=1e-6, rtol=1e-6)
