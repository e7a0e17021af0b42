"""Bad inputs to the public functions and methods: wrong shapes, dtypes and devices raise an
error naming the argument (devices tested with ``meta`` tensors, and CUDA when present);
empty and large batches work; a NaN row stays in its row and is reported per row."""

from __future__ import annotations

import math

import pytest
import torch

from torchcbf import (
    EKF,
    MPPI,
    UKF,
    Ball,
    Box,
    DoubleIntegrator,
    GaussianSensor,
    HybridEKFUKF,
    SafetyFilter,
    SingleIntegrator,
    Unicycle,
    simulate,
    solve_qp,
    step,
)
from torchcbf.estimation import EstimatorStatus, PassThrough
from torchcbf.filters import FilterStatus
from torchcbf.qp import Status

F32, F64 = torch.float32, torch.float64
OTHER_DEVICES = ["meta"] + (["cuda"] if torch.cuda.is_available() else [])


# -- integrators and dynamics --------------------------------------------------------------


@pytest.mark.parametrize("method", ["euler", "rk4", "euler_maruyama"])
def test_step_dtype_mismatch_names_both(method):
    dyn = SingleIntegrator(2)
    with pytest.raises(TypeError, match=r"u has dtype torch.float64 but x has dtype torch.float32"):
        step(dyn, torch.zeros(3, 2), torch.zeros(3, 2, dtype=F64), 0.1, method)
    with pytest.raises(TypeError, match=r"u has dtype torch.float32 but x has dtype torch.float64"):
        dyn(torch.zeros(3, 2, dtype=F64), torch.zeros(3, 2))


def test_step_disturbance_and_noise_dtype_mismatch():
    dyn = SingleIntegrator(2, sigma=0.1, disturbance_bound=1.0)
    x, u = torch.zeros(3, 2), torch.zeros(3, 2)
    with pytest.raises(TypeError, match=r"w has dtype torch.float64"):
        step(dyn, x, u, 0.1, w=torch.zeros(3, 2, dtype=F64))
    with pytest.raises(TypeError, match=r"noise has dtype torch.float64"):
        step(dyn, x, u, 0.1, "euler_maruyama", noise=torch.zeros(3, 2, dtype=F64))
    with pytest.raises(ValueError, match=r"noise must have shape \[\.\.\., 2\]"):
        step(dyn, x, u, 0.1, "euler_maruyama", noise=torch.zeros(3, 5))


@pytest.mark.parametrize("device", OTHER_DEVICES)
def test_step_device_mismatch_names_both_devices(device):
    dyn = SingleIntegrator(2)
    other = torch.device(device)
    with pytest.raises(ValueError, match=rf"u is on device {other}.* x is on device cpu"):
        step(dyn, torch.zeros(3, 2), torch.zeros(3, 2, device=other), 0.1)
    with pytest.raises(ValueError, match=rf"u is on device cpu but x is on device {other}"):
        dyn(torch.zeros(3, 2, device=other), torch.zeros(3, 2))


def test_step_on_meta_follows_the_inputs():
    out = step(Unicycle(), torch.zeros(5, 3, device="meta"), torch.zeros(5, 2, device="meta"), 0.1)
    assert out.device.type == "meta" and out.shape == (5, 3)


@pytest.mark.parametrize(
    "x, u, pattern",
    [
        (torch.zeros(3, 3), torch.zeros(3, 2), r"x must have shape \[\.\.\., 2\]"),
        (torch.zeros(3, 2), torch.zeros(3, 1), r"u must have shape \[\.\.\., 2\]"),
        (torch.zeros(()), torch.zeros(2), r"x must have shape"),
        (torch.zeros(3, 2), torch.zeros(4, 2), r"batch dimensions of x .* and u"),
    ],
)
def test_step_bad_shapes_name_the_argument(x, u, pattern):
    with pytest.raises(ValueError, match=pattern):
        step(SingleIntegrator(2), x, u, 0.1)


@pytest.mark.parametrize("dt", [0.0, -0.1, math.nan, math.inf])
def test_step_bad_dt(dt):
    with pytest.raises(ValueError, match="dt"):
        step(SingleIntegrator(2), torch.zeros(2), torch.zeros(2), dt)


def test_step_non_tensor_and_integer_inputs():
    with pytest.raises(TypeError, match="x must be a torch.Tensor"):
        step(SingleIntegrator(2), [0.0, 0.0], torch.zeros(2), 0.1)
    with pytest.raises(TypeError, match="x must be a floating-point tensor"):
        step(SingleIntegrator(2), torch.zeros(2, dtype=torch.int64), torch.zeros(2), 0.1)
    with pytest.raises(TypeError, match="dynamics"):
        step("model", torch.zeros(2), torch.zeros(2), 0.1)


@pytest.mark.parametrize("batch", [0, 100_000])
def test_step_empty_and_large_batches_match_one_row(batch):
    dyn = DoubleIntegrator(2)
    x = torch.linspace(-1, 1, 4).expand(batch, 4)
    u = torch.tensor([0.3, -0.2]).expand(batch, 2)
    out = step(dyn, x, u, 0.05)
    assert out.shape == (batch, 4)
    if batch:
        one = step(dyn, x[0], u[0], 0.05)
        assert torch.equal(out, one.expand_as(out))


def test_nan_row_stays_in_its_row():
    x = torch.tensor([[math.nan, 0.0, 0.0], [1.0, 2.0, 0.5]])
    u = torch.tensor([[1.0, 0.1], [1.0, 0.1]])
    out = step(Unicycle(), x, u, 0.1)
    assert torch.isnan(out[0, 0]) and torch.isfinite(out[1]).all()
    assert torch.equal(out[1], step(Unicycle(), x[1], u[1], 0.1))


# -- barriers ------------------------------------------------------------------------------


@pytest.mark.parametrize("barrier", [Ball([1.0, 0.0], 0.5), Box([-1.0, -1.0], [1.0, 1.0])])
def test_barrier_bad_states(barrier):
    with pytest.raises(ValueError, match="x must have shape"):
        barrier(torch.zeros(()))
    with pytest.raises(TypeError, match="x must be a torch.Tensor"):
        barrier([0.0, 0.0])
    with pytest.raises(TypeError, match="x must be a floating-point tensor"):
        barrier.lie(torch.zeros(3, 2, dtype=torch.int64), SingleIntegrator(2))
    assert barrier(torch.zeros(0, 2)).shape == (0,)
    assert barrier.lie(torch.zeros(0, 2), SingleIntegrator(2)).lgh.shape == (0, 2)
    meta = barrier.lie(torch.zeros(4, 2, device="meta"), SingleIntegrator(2))
    assert meta.lgh.device.type == "meta" and meta.lgh.shape == (4, 2)


def test_barrier_large_batch_equals_rows():
    ball = Ball([1.0, 0.0], 0.5)
    x = torch.randn(100_000, 2, generator=torch.Generator().manual_seed(0))
    terms = ball.lie(x, SingleIntegrator(2))
    idx = torch.tensor([0, 7, 99_999])
    for i in idx.tolist():
        one = ball.lie(x[i], SingleIntegrator(2))
        assert torch.allclose(terms.lgh[i], one.lgh) and torch.allclose(terms.h[i], one.h)


# -- estimators ----------------------------------------------------------------------------


@pytest.mark.parametrize("cls", [EKF, UKF, HybridEKFUKF])
def test_estimator_bad_inputs(cls):
    est = cls(SingleIntegrator(2), GaussianSensor(std=0.1, state_dim=2), Q=0.01)
    P0 = torch.eye(2)
    with pytest.raises(ValueError, match=r"x0 must have shape \[\.\.\., 2\]"):
        est.init(torch.zeros(3, 3), P0)
    with pytest.raises(ValueError, match="P0"):
        est.init(torch.zeros(3, 2))
    with pytest.raises(ValueError, match="P0"):
        est.init(torch.zeros(3, 2), torch.eye(3))
    with pytest.raises(ValueError, match="P0 must be positive definite"):
        est.init(torch.zeros(3, 2), -P0)
    state = est.init(torch.zeros(3, 2), P0)
    with pytest.raises(ValueError, match=r"u must have shape \[\.\.\., 2\]"):
        est.predict(state, torch.zeros(3, 5), 0.1)
    with pytest.raises(ValueError, match="dt"):
        est.predict(state, torch.zeros(3, 2), math.nan)
    with pytest.raises(ValueError, match=r"y must have shape \[\.\.\., 2\]"):
        est.update(state, torch.zeros(3, 1))
    with pytest.raises(TypeError, match="y has dtype torch.float64"):
        est.update(state, torch.zeros(3, 2, dtype=F64))
    with pytest.raises(ValueError, match="y is on device meta"):
        est.update(state, torch.zeros(3, 2, device="meta"))
    with pytest.raises(TypeError, match="state"):
        est.predict((1, 2), torch.zeros(3, 2), 0.1)


@pytest.mark.parametrize("cls", [EKF, UKF, HybridEKFUKF])
def test_estimator_empty_batch_and_nan_row(cls):
    est = cls(Unicycle(), GaussianSensor(std=0.1, state_dim=3), Q=0.01)
    empty = est.predict(est.init(torch.zeros(0, 3), torch.eye(3)), torch.zeros(0, 2), 0.1)
    assert empty.mean.shape == (0, 3) and empty.cov.shape == (0, 3, 3)
    state = est.init(torch.zeros(3, 3), 0.1 * torch.eye(3))
    state = est.predict(state, torch.tensor([[1.0, 0.1]] * 3), 0.1)
    y = torch.tensor([[0.1, 0.0, 0.0], [math.nan, 0.0, 0.0], [0.1, 0.0, 0.01]])
    out = est.update(state, y)
    assert out.status.tolist()[1] & int(EstimatorStatus.NON_FINITE)
    assert torch.equal(out.mean[1], state.mean[1])  # the flagged row keeps its estimate
    assert torch.isfinite(out.mean).all() and torch.isfinite(out.cov).all()
    assert out.status[[0, 2]].eq(0).all()


def test_passthrough_checks_the_measurement():
    est = PassThrough(2)
    state = est.init(torch.zeros(3, 2))
    with pytest.raises(TypeError, match="y has dtype torch.float64"):
        est.update(state, torch.zeros(3, 2, dtype=F64))
    with pytest.raises(ValueError, match=r"y must have shape \[\.\.\., 2\]"):
        est.update(state, torch.zeros(3, 4))


# -- other modules, as they behave today ---------------------------------------------------


def test_filter_bad_inputs_and_per_row_status():
    flt = SafetyFilter(SingleIntegrator(2), [Ball([2.0, 0.0], 0.5)])
    with pytest.raises(ValueError, match=r"x must have shape \[\.\.\., 2\]"):
        flt(torch.zeros(3, 3), torch.zeros(3, 2))
    with pytest.raises(ValueError, match=r"u_nom must have shape \[\.\.\., 2\]"):
        flt(torch.zeros(3, 2), torch.zeros(3, 3))
    with pytest.raises(TypeError, match="dtype"):
        flt(torch.zeros(3, 2), torch.zeros(3, 2, dtype=F64))
    assert flt(torch.zeros(0, 2), torch.zeros(0, 2)).u.shape == (0, 2)
    out = flt(torch.tensor([[math.nan, 0.0], [0.0, 0.0]]), torch.ones(2, 2))
    assert out.status.tolist() == [int(FilterStatus.NON_FINITE), int(FilterStatus.SOLVED)]
    assert torch.isfinite(out.u).all()
    with pytest.raises(ValueError, match="alpha"):
        SafetyFilter(SingleIntegrator(2), [Ball([2.0, 0.0], 0.5)], alpha=math.nan)


def test_solve_qp_bad_inputs_and_per_row_status():
    Q = torch.eye(2).expand(2, 2, 2)
    with pytest.raises(TypeError, match="p has dtype torch.float64 but Q has dtype torch.float32"):
        solve_qp(Q, torch.zeros(2, 2, dtype=F64))
    with pytest.raises(ValueError, match="p is on cpu but Q is on meta"):
        solve_qp(torch.eye(2, device="meta").expand(2, 2, 2), torch.zeros(2, 2))
    with pytest.raises(ValueError, match=r"p must have shape \[\.\.\., 3\]"):
        solve_qp(torch.eye(3).expand(1, 3, 3), torch.zeros(1, 2))
    assert solve_qp(torch.eye(2).expand(0, 2, 2), torch.zeros(0, 2)).x.shape == (0, 2)
    sol = solve_qp(Q, torch.tensor([[math.nan, 0.0], [1.0, 0.0]]))
    assert sol.status.tolist() == [int(Status.NON_FINITE), int(Status.SOLVED)]
    box = solve_qp(Q[:1], torch.zeros(1, 2), lb=torch.ones(1, 2), ub=-torch.ones(1, 2))
    assert box.status.tolist() == [int(Status.PRIMAL_INFEASIBLE)]


def test_mppi_bad_inputs_and_nan_row():
    def cost(states, controls, t0):
        return (states[..., -1, :] ** 2).sum(-1)

    planner = MPPI(
        SingleIntegrator(2), cost, horizon=5, num_samples=16, dt=0.1, noise_sigma=1.0,
        temperature=1.0,
    )  # fmt: skip
    with pytest.raises(ValueError, match=r"x must have shape \[\.\.\., 2\]"):
        planner(torch.zeros(3))
    out = planner(torch.tensor([[math.nan, 0.0], [0.0, 0.0]]))
    assert out.status[0] != 0 and out.status[1] == 0 and torch.isfinite(out.u).all()
    with pytest.raises(ValueError, match="u_min .* exceeds u_max"):
        MPPI(
            SingleIntegrator(2), cost, horizon=5, num_samples=16, dt=0.1, noise_sigma=1.0,
            temperature=1.0, u_min=1.0, u_max=-1.0,
        )  # fmt: skip


def test_simulate_bad_inputs_and_batches():
    dyn = SingleIntegrator(2)
    zero = lambda x, t: torch.zeros_like(x)  # noqa: E731
    with pytest.raises(ValueError, match=r"x0 must have shape \[\.\.\., 2\]"):
        simulate(dyn, torch.zeros(3, 3), 5, 0.1, nominal=zero, progress=False)
    for steps in (0, -1):
        with pytest.raises(ValueError, match="steps"):
            simulate(dyn, torch.zeros(3, 2), steps, 0.1, nominal=zero, progress=False)
    with pytest.raises(ValueError, match="dt"):
        simulate(dyn, torch.zeros(3, 2), 5, math.nan, nominal=zero, progress=False)
    with pytest.raises(ValueError, match="integrator"):
        simulate(dyn, torch.zeros(3, 2), 5, 0.1, integrator="foo", progress=False)
    with pytest.raises(TypeError, match="u has dtype torch.float64 but x has dtype torch.float32"):
        simulate(
            dyn, torch.zeros(3, 2), 5, 0.1, progress=False,
            nominal=lambda x, t: torch.zeros(3, 2, dtype=F64),
        )  # fmt: skip
    empty = simulate(dyn, torch.zeros(0, 2), 5, 0.1, nominal=zero, progress=False)
    assert empty.x.shape == (0, 6, 2)


def test_generators_on_another_device_are_named():
    gen = torch.Generator(device="cpu")
    x = torch.zeros(3, 2, device="meta")
    with pytest.raises(ValueError, match="generator is on device cpu but x is on device meta"):
        GaussianSensor(std=0.1, state_dim=2).measure(x, gen)
    dyn = SingleIntegrator(2, sigma=0.1)
    with pytest.raises(ValueError, match="generator is on device cpu but x is on device meta"):
        step(dyn, x, torch.zeros(3, 2, device="meta"), 0.1, "euler_maruyama", gen)


def test_limits_that_admit_nothing_are_named():
    with pytest.raises(ValueError, match="u_min must not be inf"):
        SingleIntegrator(2, u_min=math.inf)
    with pytest.raises(ValueError, match="u_max must not be -inf"):
        SingleIntegrator(2, u_max=[1.0, -math.inf])
