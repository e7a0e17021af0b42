"""Constants of modules: a tensor that requires grad keeps its gradient (checked against
finite differences), an nn.Parameter trains, and Python numbers are exact in float64 after
``.double()`` (compared with the module built from float64 tensors)."""

from __future__ import annotations

import pytest
import torch
from torch import nn

from torchcbf import (
    EKF,
    Ball,
    Bicycle,
    Box,
    Ellipse,
    GaussianSensor,
    HalfSpace,
    QuadraticLyapunov,
    SingleIntegrator,
    VanDerPol,
)
from torchcbf.barriers import LinkSphereBarrier, Scaled
from torchcbf.estimation import RangeBearing

F64 = torch.float64


def _fd(fn, value: torch.Tensor, eps: float = 1e-6) -> torch.Tensor:
    """Central-difference gradient of the scalar ``fn(value)``."""
    grad = torch.zeros_like(value)
    flat = grad.view(-1)
    for i in range(value.numel()):
        e = torch.zeros_like(value).view(-1)
        e[i] = eps
        e = e.view_as(value)
        flat[i] = (fn(value + e) - fn(value - e)) / (2 * eps)
    return grad


SHAPES = [
    ("Ball", lambda c, r: Ball(c, r), [[1.0, 0.5], 0.7]),
    ("Ellipse", lambda c, a: Ellipse(c, a), [[1.0, 0.5], [0.7, 0.4]]),
    ("HalfSpace", lambda a, b: HalfSpace(a, b), [[1.0, 0.5], 0.7]),
    ("Box", lambda lo, hi: Box(lo, hi, smooth=True), [[-1.0, -0.5], [0.7, 1.2]]),
    (
        "QuadraticLyapunov",
        lambda g, P: QuadraticLyapunov(g, P),
        [[0.3, 0.5], [[2.0, 0.3], [0.3, 1.0]]],
    ),
    ("Scaled", lambda c, s: Scaled(Ball(c, 0.7), s), [[1.0, 0.5], [2.0]]),
]


@pytest.mark.parametrize("name, build, args", SHAPES, ids=[s[0] for s in SHAPES])
def test_tensor_requiring_grad_keeps_its_gradient(name, build, args):
    x = torch.tensor([[0.2, -0.3], [1.5, 0.4]], dtype=F64)
    tensors = [torch.tensor(a, dtype=F64, requires_grad=True) for a in args]
    module = build(*tensors)
    module(x).sum().backward()
    for i, t in enumerate(tensors):
        assert t.grad is not None, f"{name}: argument {i} lost its gradient"
        if t.dim() == 2:  # P of V = e' P e: dV/dP = sum_b e_b e_b' (perturbing one entry of P
            e = x - tensors[0].detach()  # alone would make it asymmetric)
            assert torch.allclose(t.grad, e.mT @ e, atol=1e-12)
            continue

        def value(v, i=i):
            vals = [a.detach() for a in tensors]
            vals[i] = v
            return build(*vals)(x).sum()

        assert torch.allclose(t.grad, _fd(value, t.detach()), atol=1e-6), name


def test_tensor_requiring_grad_keeps_its_gradient_through_double():
    c = torch.tensor([1.0, 0.5], requires_grad=True)
    ball = Ball(c, 0.7).double()
    ball(torch.zeros(1, 2, dtype=F64)).sum().backward()
    assert torch.allclose(c.grad, torch.tensor([2.0, 1.0]))


def test_parameters_and_learnable_train():
    c = nn.Parameter(torch.tensor([1.0, 0.5]))
    ball = Ball(c, 0.7)
    assert ball.center is c and [n for n, _ in ball.named_parameters()] == ["center"]
    learn = Ball([1.0, 0.5], 0.7, learnable=True)
    learn(torch.zeros(1, 2)).sum().backward()
    assert learn.center.grad is not None and learn.radius.grad is not None


def test_dynamics_constants_keep_their_gradient():
    mu = torch.tensor(1.3, dtype=F64, requires_grad=True)
    x = torch.tensor([[0.5, -0.2]], dtype=F64)
    u = torch.tensor([[0.1]], dtype=F64)
    VanDerPol(mu=mu)(x, u).sum().backward()
    # d/dmu of x2' = mu (1 - x1^2) x2 - x1 + u
    assert torch.allclose(mu.grad, (1 - x[0, 0] ** 2) * x[0, 1])
    wheelbase = nn.Parameter(torch.tensor(2.0, dtype=F64))
    model = Bicycle(wheelbase=wheelbase)
    assert [n for n, _ in model.named_parameters()] == ["wheelbase"]
    xb = torch.tensor([[0.0, 0.0, 0.1, 0.3]], dtype=F64)
    model(xb, torch.tensor([[1.0, 0.0]], dtype=F64))[..., 2].sum().backward()
    assert torch.allclose(wheelbase.grad, -torch.tan(xb[0, 3]) / 4.0)
    lo = torch.tensor([-1.0, -2.0], requires_grad=True)
    dyn = SingleIntegrator(2, u_min=lo, u_max=1.0)
    dyn.clamp_control(torch.full((1, 2), -5.0)).sum().backward()
    assert torch.equal(lo.grad, torch.ones(2))


def test_sensor_and_noise_tensors_keep_their_gradient():
    std = torch.tensor([0.1, 0.2], dtype=F64, requires_grad=True)
    sensor = GaussianSensor(std=std)
    est = EKF(SingleIntegrator(2), sensor, Q=0.01).double()
    state = est.init(torch.zeros(1, 2, dtype=F64), torch.eye(2, dtype=F64))
    out = est.update(state, torch.ones(1, 2, dtype=F64))
    out.mean.sum().backward()
    assert std.grad is not None and torch.isfinite(std.grad).all() and bool((std.grad != 0).all())


NUMBERS = [
    ("Ball", lambda T: Ball(T([0.1, 0.2]), T(0.3))),
    ("Ellipse", lambda T: Ellipse(T([0.1, 0.2]), T([0.3, 0.7]), angle=T(0.1))),
    ("HalfSpace", lambda T: HalfSpace(T([0.1, 0.3]), T(0.7))),
    ("Box", lambda T: Box(T([-0.1, -0.3]), T([0.7, 0.9]))),
    ("QuadraticLyapunov", lambda T: QuadraticLyapunov(T([0.1, 0.2]), T([[1.1, 0.1], [0.1, 0.3]]))),
]


@pytest.mark.parametrize("name, build", NUMBERS, ids=[s[0] for s in NUMBERS])
def test_python_numbers_are_exact_after_double(name, build):
    x = torch.tensor([[0.3, -0.7], [1.1, 0.25]], dtype=F64)
    from_numbers = build(lambda v: v).double()
    reference = build(lambda v: torch.tensor(v, dtype=F64))
    assert torch.equal(from_numbers(x), reference(x)), name
    # a float32 module is the float32 rounding of the numbers, as before
    f32 = build(lambda v: v)
    assert torch.equal(f32(x.float()), reference.float()(x.float()))


def test_exact_constants_round_trip_and_edits():
    ball = Ball([0.1, 0.2], 0.3)
    assert ball.center.dtype == torch.get_default_dtype()
    assert ball.double().center[0].item() == 0.1
    assert ball.float().double().center[0].item() == 0.1
    ball = Ball([0.1, 0.2], 0.3)
    with torch.no_grad():
        ball.center += 1.0  # edited: cast as usual, not reset to the constructor's value
    assert ball.double().center[0].item() == pytest.approx(1.1, rel=1e-7)
    learn = Ball([0.1, 0.2], 0.3, learnable=True).double()
    assert learn.center[0].item() == 0.1 and isinstance(learn.center, nn.Parameter)


def test_estimator_noise_numbers_are_exact_after_double():
    est = EKF(SingleIntegrator(2), GaussianSensor(std=0.1, state_dim=2), Q=0.01, R=0.03).double()
    assert est.Q[0, 0].item() == 0.01 and est.R_override[0, 0].item() == 0.03
    assert est.sensor.R[0, 0].item() == 0.1**2
    assert est.sensor.R_sqrt[0, 0].item() == 0.1
    rb = RangeBearing([[0.1, 0.7]], 0.3, 0.05).double()
    assert rb.landmarks[0, 0].item() == 0.1 and rb.R[1, 1].item() == 0.05**2


def test_dynamics_numbers_are_exact():
    dyn = SingleIntegrator(2, u_min=-0.1, u_max=0.3)
    assert dyn.u_min.dtype == F64 and dyn.u_max[0].item() == 0.3
    assert VanDerPol(mu=0.1).mu.item() == 0.1


def test_workspace_numbers_are_exact_after_double():
    pytest.importorskip("pytorch_kinematics")
    from torchcbf.dynamics import Manipulator

    arm = Manipulator("planar3")
    barrier = LinkSphereBarrier(arm, ["link2"], 0.1, [0.3, 0.7, 0.0], 0.2).double()
    assert barrier.radii[0].item() == 0.1 and barrier.obstacle_radius[0].item() == 0.2
    assert barrier.obstacle_center[0, 0].item() == 0.3


def test_neural_barrier_scale_tensor_keeps_its_gradient():
    from torchcbf import NeuralBarrier

    scale = torch.tensor(2.0, dtype=F64, requires_grad=True)
    net = nn.Linear(2, 1).double()
    barrier = NeuralBarrier(net, scale=scale)
    x = torch.tensor([[0.3, -0.1]], dtype=F64)
    barrier(x).sum().backward()
    assert torch.allclose(scale.grad, net(x).sum().detach())
    with pytest.raises(ValueError, match="scale must be a finite number"):
        NeuralBarrier(net, scale=float("nan"))


def test_number_options_refuse_tensors_instead_of_cutting_them():
    from torchcbf import UKF

    with pytest.raises(TypeError, match="alpha must be a Python number"):
        UKF(SingleIntegrator(2), GaussianSensor(std=0.1, state_dim=2), Q=0.1,
            alpha=torch.tensor(0.5, requires_grad=True))  # fmt: skip
    with pytest.raises(TypeError, match="temperature must be a Python number"):
        Box([0.0, 0.0], [1.0, 1.0], smooth=True, temperature=torch.tensor(0.1, requires_grad=True))


def test_mlp_box_is_exact_and_checked():
    from torchcbf.learning import MLP

    net = MLP(2, (4,), low=[-0.1, -0.3], high=[0.7, 0.9]).double()
    assert net.center[0].item() == (0.7 - 0.1) / 2 and net.half_width[1].item() == (0.9 + 0.3) / 2
    with pytest.raises(ValueError, match="low must not contain NaN"):
        MLP(2, (4,), low=[float("nan"), 0.0], high=[1.0, 1.0])
    with pytest.raises(TypeError, match="hidden must be a sequence"):
        MLP(2, 4)
    with pytest.raises(TypeError, match="low is a fixed input normalisation"):
        MLP(2, (4,), low=torch.zeros(2, requires_grad=True), high=[1.0, 1.0])


def _sgd_steps(params, loss_of, steps: int = 2) -> None:
    opt = torch.optim.SGD(params, lr=0.05)
    for _ in range(steps):
        opt.zero_grad()
        loss_of().backward()
        opt.step()


SHAPED = [
    # (name, the module built of a parameter p, the same built of a plain value, p's start)
    ("sigma scalar", lambda p: SingleIntegrator(2, sigma=p), 0.3),
    ("sigma vector", lambda p: SingleIntegrator(2, sigma=p), [0.3, 0.2]),
    ("u_max scalar", lambda p: SingleIntegrator(2, u_min=-1.0, u_max=p), 0.5),
    ("u_max float32", lambda p: SingleIntegrator(2, u_min=-1.0, u_max=p), [0.5, 0.6]),
    ("disturbance_bound", lambda p: SingleIntegrator(2, disturbance_bound=p), 0.1),
    ("R vector", None, [1.0, 0.2]),
    ("sensor std", None, [0.1, 0.2]),
    ("EKF Q vector", None, [0.02, 0.01]),
    ("HOCBF gain", None, 2.0),
]


def _shaped(name: str, value):
    """A module built once of the shaped constant ``value``, as a function giving a float64
    output that depends on it."""
    from torchcbf.barriers import rectify
    from torchcbf.dynamics import DoubleIntegrator
    from torchcbf.filters import Robust, SafetyFilter, Stochastic

    x = torch.tensor([[0.2, 0.1], [0.4, -0.3]], dtype=F64)
    u = torch.tensor([[1.5, 0.2], [2.0, -0.5]], dtype=F64)
    ball = Ball([1.0, 0.0], 0.5).double()
    build = dict((s[0], s[1]) for s in SHAPED)[name]
    if name in ("sensor std", "EKF Q vector"):
        std, Q = (value, 0.01) if name == "sensor std" else ([0.1, 0.1], value)
        est = EKF(SingleIntegrator(2), GaussianSensor(std=std), Q=Q).double()
        state = est.init(x, torch.eye(2, dtype=F64))
        return lambda: est.update(est.predict(state, u, 0.1), x + 0.3).mean
    if name == "HOCBF gain":
        dyn = DoubleIntegrator(2)
        filt = SafetyFilter(dyn, rectify(ball, dyn, "high_order", gains=value)).double()
        x4 = torch.cat([x, torch.ones_like(x)], -1)
        return lambda: filt(x4, u).u
    if name.startswith("sigma"):
        filt = SafetyFilter(build(value), ball, mode=Stochastic()).double()
    elif name.startswith("u_max"):
        filt = SafetyFilter(build(value), ball).double()
    elif name == "disturbance_bound":
        filt = SafetyFilter(build(value), ball, mode=Robust()).double()
    else:
        filt = SafetyFilter(SingleIntegrator(2), ball, R=value).double()
    return lambda: filt(x, u).u


@pytest.mark.parametrize("name", [s[0] for s in SHAPED])
def test_a_parameter_a_module_shapes_trains(name: str) -> None:
    """A parameter the module casts or shapes (a scalar bound expanded, a vector made a
    diagonal matrix, float32 cast to float64) is one of its parameters, trains over two
    optimiser steps, and each answer equals the module built afresh from its value then;
    its gradient is the central difference's."""
    start = dict((s[0], s[2]) for s in SHAPED)[name]
    dtype = torch.float32 if name == "u_max float32" else F64
    p = nn.Parameter(torch.tensor(start, dtype=dtype))
    out = _shaped(name, p)
    (grad,) = torch.autograd.grad(out().square().sum(), p)
    eps, tol = (1e-6, 1e-5) if dtype == F64 else (1e-3, 1e-3)
    with torch.no_grad():
        loss = lambda v: float(_shaped(name, v.to(dtype))().square().sum())  # noqa: E731
        fd = _fd(loss, p.double(), eps)
    torch.testing.assert_close(grad.double(), fd, atol=tol, rtol=tol)
    _sgd_steps([p], lambda: out().square().sum())
    with torch.no_grad():
        exact = 1e-12 if dtype == F64 else 1e-6
        torch.testing.assert_close(
            out(), _shaped(name, p.detach().clone())(), atol=exact, rtol=exact
        )
    assert not torch.equal(p.detach(), torch.tensor(start, dtype=dtype))


def test_a_scalar_parameter_radius_on_arm_links_trains() -> None:
    pytest.importorskip("pytorch_kinematics")
    from torchcbf.dynamics import Manipulator

    arm = Manipulator("planar3").double()
    r = nn.Parameter(torch.tensor(0.1, dtype=F64))
    links = ["link2", "link3"]
    barrier = LinkSphereBarrier(arm, links, r, [0.5, 0.5, 0.0], 0.2).double()
    assert any(t is r for t in barrier.parameters())
    q = torch.tensor([[0.3, -0.2, 0.1]], dtype=F64)
    before = barrier(q).detach()
    _sgd_steps([r], lambda: barrier(q).sum())
    fresh = LinkSphereBarrier(arm, links, float(r.detach()), [0.5, 0.5, 0.0], 0.2).double()
    torch.testing.assert_close(barrier(q).detach(), fresh(q))
    assert not torch.equal(before, barrier(q).detach())


def test_a_scale_of_numbers_takes_its_barriers_dtype_and_stays_exact() -> None:
    ball = Ball([0.3, 0.1], 0.7).double()
    x = torch.tensor([[0.2, -0.3], [1.5, 0.4]], dtype=F64)
    scaled = Scaled(ball, 0.1)
    assert scaled.scale.dtype == F64
    assert torch.equal(scaled(x), 0.1 * ball(x))
    assert torch.equal(Scaled(Ball([0.3, 0.1], 0.7), 0.1).double()(x), 0.1 * ball(x))
