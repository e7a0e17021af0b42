"""The estimator protocol: PassThrough, batching (4,096 rows = a loop), bad input, non-finite
rows and regularization, dtype/device, gradients."""

from __future__ import annotations

import pytest
import torch
from _devices import device_matches_cpu
from torch import nn

from torchcbf.dynamics import AccelUnicycle, ControlAffine, DoubleIntegrator, Unicycle
from torchcbf.estimation import (
    EKF,
    UKF,
    Estimator,
    EstimatorState,
    EstimatorStatus,
    GaussianSensor,
    HybridEKFUKF,
    PassThrough,
    Perfect,
    RangeBearing,
    Sensor,
)

FILTERS = [EKF, UKF, HybridEKFUKF]


def _unicycle_rb(dtype=torch.float64):
    dyn = Unicycle(sigma=torch.tensor([0.05, 0.05, 0.03], dtype=dtype))
    sensor = RangeBearing(torch.tensor([[4.0, 3.0], [-3.0, 4.0]], dtype=dtype), 0.1, 0.05)
    return dyn, sensor.to(dtype)


def test_protocol_and_perfect_passthrough(dtype):
    """Perfect sensor + PassThrough is perfect state feedback under the simulator protocol."""
    est = PassThrough(state_dim=3)
    sensor = Perfect()
    assert isinstance(est, Estimator)
    x_true = torch.randn(7, 3, dtype=dtype, generator=torch.Generator().manual_seed(0))
    state = est.init(torch.zeros(7, 3, dtype=dtype))
    state = est.predict(state, torch.zeros(7, 2, dtype=dtype), 0.1)
    state = est.update(state, sensor.measure(x_true, torch.Generator()))
    assert torch.equal(state.mean, x_true)
    assert state.cov.shape == (7, 3, 3) and bool((state.cov == 0).all())
    assert state.status.shape == (7,)
    with pytest.raises(ValueError, match="y"):
        est.update(state, torch.zeros(7, 4, dtype=dtype))


@pytest.mark.parametrize("cls", FILTERS, ids=lambda c: c.__name__)
def test_batch_of_4096_equals_loop(cls):
    """One call on 4,096 filters equals the same filters run one by one (unbatched [n])."""
    dyn, sensor = _unicycle_rb()
    est = cls(dyn, sensor)
    gen = torch.Generator().manual_seed(11)
    B = 4096
    x0 = torch.randn(B, 3, generator=gen, dtype=torch.float64) * 0.5
    G = torch.randn(B, 3, 3, generator=gen, dtype=torch.float64) * 0.2
    P0 = G @ G.mT + 0.05 * torch.eye(3, dtype=torch.float64)
    u = torch.randn(B, 2, generator=gen, dtype=torch.float64)
    y = sensor.measure(torch.randn(B, 3, generator=gen, dtype=torch.float64) * 0.5, gen)
    state = est.init(x0, P0)
    for _ in range(2):
        state = est.step(state, u, 0.1, y)
    assert state.mean.shape == (B, 3) and state.cov.shape == (B, 3, 3)
    for b in (0, 1234, B - 1):
        s = est.init(x0[b], P0[b])
        for _ in range(2):
            s = est.step(s, u[b], 0.1, y[b])
        assert s.mean.shape == (3,) and s.cov.shape == (3, 3) and s.status.shape == ()
        assert torch.allclose(s.mean, state.mean[b], atol=1e-12, rtol=0)
        assert torch.allclose(s.cov, state.cov[b], atol=1e-12, rtol=0)


@pytest.mark.parametrize("cls", FILTERS, ids=lambda c: c.__name__)
def test_broadcasting_and_extra_batch_dims(cls):
    dyn, sensor = _unicycle_rb()
    est = cls(dyn, sensor)
    x0 = torch.zeros(2, 5, 3, dtype=torch.float64)
    state = est.init(x0, torch.eye(3, dtype=torch.float64) * 0.1)  # P0 [n, n] broadcast
    state = est.predict(state, torch.tensor([1.0, 0.2], dtype=torch.float64), 0.1)  # u [m]
    assert state.mean.shape == (2, 5, 3) and state.cov.shape == (2, 5, 3, 3)
    state = est.update(state, sensor.expected(torch.zeros(3, dtype=torch.float64)))  # y [p]
    assert state.mean.shape == (2, 5, 3) and state.status.shape == (2, 5)
    assert torch.allclose(state.mean[0, 0], state.mean[1, 4])


@pytest.mark.parametrize("cls", FILTERS, ids=lambda c: c.__name__)
def test_dtype_and_device_follow_inputs(cls, dtype, device):
    dyn, sensor = _unicycle_rb(torch.float64)
    est = cls(dyn, sensor).to(device=device, dtype=dtype)
    state = est.init(
        torch.zeros(4, 3, dtype=dtype, device=device), torch.eye(3, dtype=dtype, device=device)
    )
    gen = torch.Generator(device=device).manual_seed(0)
    y = sensor.to(device=device, dtype=dtype).measure(state.mean, gen)
    state = est.step(state, torch.ones(4, 2, dtype=dtype, device=device), 0.1, y)
    for t in (state.mean, state.cov):
        assert t.dtype == dtype and t.device.type == device.type
        assert bool(torch.isfinite(t).all())
    assert state.status.dtype == torch.int64


def test_bad_input_raises_clear_errors():
    dyn, sensor = _unicycle_rb()
    f64 = torch.float64
    not_pd = torch.diag(torch.tensor([1.0, -0.1, 1.0], dtype=f64))
    with pytest.raises(ValueError, match="Q must be positive definite"):
        EKF(dyn, sensor, Q=not_pd)
    with pytest.raises(ValueError, match="Q must be symmetric"):
        UKF(dyn, sensor, Q=torch.tensor([[1.0, 0.5, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]))
    with pytest.raises(ValueError, match="Q must be positive definite"):
        HybridEKFUKF(dyn, sensor, Q=torch.zeros(3, 3))
    with pytest.raises(ValueError, match="Q must be"):
        EKF(dyn, sensor, Q=torch.eye(4))
    with pytest.raises(ValueError, match="R must be positive definite"):
        EKF(dyn, sensor, R=-torch.eye(4))
    with pytest.raises(ValueError, match="R must be"):
        EKF(dyn, sensor, R=torch.eye(3))
    with pytest.raises(ValueError, match="Q is required"):
        EKF(Unicycle(), sensor)
    with pytest.raises(ValueError, match="PassThrough"):
        EKF(dyn, Perfect())
    with pytest.raises(ValueError, match="sensor expects states of size 2"):
        EKF(dyn, GaussianSensor(std=0.1, state_dim=2))
    with pytest.raises(TypeError, match="dynamics"):
        EKF("unicycle", sensor)
    with pytest.raises(ValueError, match="substeps"):
        EKF(dyn, sensor, substeps=0)
    est = EKF(dyn, sensor)
    x0 = torch.zeros(4, 3, dtype=f64)
    with pytest.raises(ValueError, match="P0 must be positive definite"):
        est.init(x0, not_pd)
    with pytest.raises(ValueError, match=r"P0 must have shape \[\.\.\., 3, 3\]"):
        est.init(x0, torch.eye(2, dtype=f64))
    with pytest.raises(ValueError, match="P0"):
        est.init(x0, torch.eye(3, dtype=f64).expand(5, 3, 3))
    with pytest.raises(ValueError, match="needs the prior covariance"):
        est.init(x0)
    with pytest.raises(ValueError, match=r"x0 must have shape \[\.\.\., 3\]"):
        est.init(torch.zeros(4, 2, dtype=f64), torch.eye(3, dtype=f64))
    state = est.init(x0, torch.eye(3, dtype=f64))
    with pytest.raises(ValueError, match=r"u must have shape \[\.\.\., 2\]"):
        est.predict(state, torch.zeros(4, 3, dtype=f64), 0.1)
    with pytest.raises(ValueError, match="do not broadcast"):
        est.predict(state, torch.zeros(3, 2, dtype=f64), 0.1)
    with pytest.raises(ValueError, match="dt"):
        est.predict(state, torch.zeros(4, 2, dtype=f64), -0.1)
    with pytest.raises(ValueError, match=r"y must have shape \[\.\.\., 4\]"):
        est.update(state, torch.zeros(4, 2, dtype=f64))
    with pytest.raises(TypeError, match="state"):
        est.update((x0,), torch.zeros(4, 4, dtype=f64))
    with pytest.raises(ValueError, match="state.cov"):
        est.update(EstimatorState(x0, torch.eye(3, dtype=f64), state.status), torch.zeros(4, 4))


@pytest.mark.parametrize("cls", FILTERS, ids=lambda c: c.__name__)
def test_device_answers_equal_cpu_answers(cls, dtype, device):
    """Five steps of each filter on the nonlinear range-bearing problem, with measurements
    drawn on the CPU, give the CPU's means, covariances and statuses on every device."""
    gen = torch.Generator().manual_seed(5)
    B, T = 64, 5
    x0 = torch.randn(B, 3, generator=gen, dtype=torch.float64) * 0.5
    us = torch.randn(T, B, 2, generator=gen, dtype=torch.float64)
    ys = [
        _unicycle_rb()[1].measure(torch.randn(B, 3, generator=gen, dtype=torch.float64), gen)
        for _ in range(T)
    ]

    def run(dev: torch.device):
        dyn, sensor = _unicycle_rb()
        est = cls(dyn.to(dev, dtype), sensor.to(dev, dtype))
        f = {"device": dev, "dtype": dtype}
        state = est.init(x0.to(**f), 0.1 * torch.eye(3, **f))
        for k in range(T):
            state = est.step(state, us[k].to(**f), 0.1, ys[k].to(**f))
        return state.mean, state.cov, state.status

    loose = {} if dtype == torch.float64 else {"rtol": 1e-3, "atol": 1e-4}
    mean, cov, status = device_matches_cpu(run, device, dtype, **loose)
    assert bool(torch.isfinite(mean).all()) and bool(torch.isfinite(cov).all())
    assert bool((torch.linalg.eigvalsh(cov.double()) > 0).all())


@pytest.mark.parametrize("cls", FILTERS, ids=lambda c: c.__name__)
def test_non_finite_measurement_row_is_skipped_and_flagged(cls, dtype, device):
    dyn, sensor = _unicycle_rb(dtype)
    dyn, sensor = dyn.to(device), sensor.to(device)
    est = cls(dyn, sensor)
    f = {"dtype": dtype, "device": device}
    state = est.predict(
        est.init(torch.zeros(3, 3, **f), torch.eye(3, **f) * 0.1),
        torch.ones(3, 2, **f),
        0.1,
    )
    y = sensor.expected(torch.full((3, 3), 0.05, **f))
    y[1, 2] = float("nan")
    new = est.update(state, y)
    assert bool(torch.isfinite(new.mean).all() and torch.isfinite(new.cov).all())
    assert new.status.tolist() == [0, int(EstimatorStatus.NON_FINITE), 0]
    assert torch.equal(new.mean[1], state.mean[1]) and torch.equal(new.cov[1], state.cov[1])
    assert not torch.equal(new.mean[0], state.mean[0])
    # predict clears the bits of the previous step
    assert bool((est.predict(new, torch.ones(3, 2, **f), 0.1).status == 0).all())


@pytest.mark.parametrize("cls", FILTERS, ids=lambda c: c.__name__)
def test_a_skipped_measurement_row_leaves_the_gradients_of_the_others_clean(cls):
    # a learned measurement covariance shared by the batch: its gradient from a batch with
    # one NaN measurement is the gradient from the batch without that row
    dyn, sensor = _unicycle_rb()
    x = torch.tensor([[0.1, -0.2, 0.3], [0.5, 0.4, -0.1], [-0.3, 0.2, 0.6]], dtype=torch.float64)
    y = sensor.expected(x + 0.05)
    y[1, 0] = float("nan")

    def grads(rows: list[int]) -> tuple[torch.Tensor, torch.Tensor]:
        std = torch.tensor([0.2, 0.1, 0.3, 0.05], dtype=torch.float64, requires_grad=True)
        m0 = x[rows].clone().requires_grad_()
        est = cls(dyn, sensor, R=torch.diag(std**2))
        state = est.init(m0, torch.eye(3, dtype=torch.float64) * 0.1)
        new = est.update(state, y[rows])
        (new.mean.sum() + new.cov.sum()).backward()
        return std.grad, m0.grad

    g_all, gm_all = grads([0, 1, 2])
    g_two, gm_two = grads([0, 2])
    assert bool(torch.isfinite(g_all).all() and torch.isfinite(gm_all).all())
    torch.testing.assert_close(g_all, g_two, rtol=1e-12, atol=1e-14)
    torch.testing.assert_close(gm_all[[0, 2]], gm_two, rtol=1e-12, atol=1e-14)
    # the skipped row keeps its estimate: d(sum mean)/d m0 = 1, nothing else
    torch.testing.assert_close(gm_all[1], torch.ones(3, dtype=torch.float64))


@pytest.mark.parametrize("cls", FILTERS, ids=lambda c: c.__name__)
@pytest.mark.parametrize("bad", [float("nan"), float("inf"), 1e200], ids=["nan", "inf", "huge"])
def test_a_rejected_prediction_row_leaves_the_gradients_of_the_others_clean(cls, bad):
    """A control that is not finite, or so large the exponential overflows: the row keeps
    its estimate, and a learned process noise shared by the batch gets the gradient of the
    batch without that row (the backward of the overflowed row's own steps forms 0 * inf)."""
    dyn, sensor = _unicycle_rb()
    x = torch.tensor([[0.1, -0.2, 0.3], [0.5, 0.4, -0.1], [-0.3, 0.2, 0.6]], dtype=torch.float64)
    u = torch.tensor([[0.5, 0.1], [bad, 0.2], [0.3, -0.4]], dtype=torch.float64)

    def grads(rows: list[int]) -> tuple[torch.Tensor, torch.Tensor]:
        q = torch.tensor([0.02, 0.03, 0.01], dtype=torch.float64, requires_grad=True)
        m0 = x[rows].clone().requires_grad_()
        est = cls(dyn, sensor, Q=q)
        state = est.init(m0, torch.eye(3, dtype=torch.float64) * 0.1)
        new = est.predict(state, u[rows], 0.2)
        (new.mean.sum() + new.cov.sum()).backward()
        return q.grad, m0.grad, new.status

    g_all, gm_all, status = grads([0, 1, 2])
    g_two, gm_two, _ = grads([0, 2])
    assert status.tolist() == [0, int(EstimatorStatus.NON_FINITE), 0]
    torch.testing.assert_close(g_all, g_two, rtol=1e-12, atol=1e-14)
    torch.testing.assert_close(gm_all[[0, 2]], gm_two, rtol=1e-12, atol=1e-14)
    torch.testing.assert_close(gm_all[1], torch.ones(3, dtype=torch.float64))


@pytest.mark.parametrize("cls", FILTERS, ids=lambda c: c.__name__)
@pytest.mark.parametrize("bad", [float("nan"), float("inf")], ids=["nan", "inf"])
def test_a_control_that_is_not_finite_leaves_the_models_parameters_clean(cls, bad):
    """The model never sees such a control (a stand-in takes its place): its parameters'
    gradient is that of the batch without the row."""

    class Gained(ControlAffine):
        def __init__(self) -> None:
            super().__init__(2, 2, sigma=[0.1, 0.1])
            self.a = nn.Parameter(torch.tensor(1.5, dtype=torch.float64))

        def f(self, x):
            return -0.1 * x

        def g(self, x):
            return self.a * torch.eye(2, dtype=x.dtype).expand(*x.shape[:-1], 2, 2)

    x = torch.tensor([[0.1, 0.2], [0.3, 0.4], [0.5, 0.6]], dtype=torch.float64)
    u = torch.tensor([[0.5, 0.1], [bad, 0.2], [0.3, -0.4]], dtype=torch.float64)
    model = Gained()
    est = cls(model, GaussianSensor(std=0.1, state_dim=2), Q=0.01).double()

    def grad(rows: list[int]) -> torch.Tensor:
        model.a.grad = None
        state = est.init(x[rows], torch.eye(2, dtype=torch.float64) * 0.1)
        new = est.predict(state, u[rows], 0.1)
        (new.mean.sum() + new.cov.sum()).backward()
        return model.a.grad.clone()

    torch.testing.assert_close(grad([0, 1, 2]), grad([0, 2]), rtol=1e-12, atol=1e-14)


def test_priors_that_are_not_finite_are_refused_and_a_scalar_R_needs_a_size():
    dyn, sensor = _unicycle_rb()
    ekf = EKF(dyn, sensor)
    x0 = torch.tensor([[0.0, 0.0, 0.0], [float("nan"), 0.0, 0.0]], dtype=torch.float64)
    with pytest.raises(ValueError, match="x0 must not contain NaN or inf"):
        ekf.init(x0, torch.eye(3, dtype=torch.float64))
    with pytest.raises(ValueError, match="x0 must not contain NaN or inf"):
        PassThrough(state_dim=3).init(x0)
    P0 = torch.eye(3, dtype=torch.float64)
    P0[0, 0] = float("inf")
    with pytest.raises(ValueError, match="P0 must not contain NaN or inf"):
        ekf.init(torch.zeros(2, 3, dtype=torch.float64), P0)

    class Position(Sensor):
        def __init__(self, R=None):
            super().__init__()
            if R is not None:
                self._set_noise(R, lambda v: v)

        def expected(self, x):
            return x[..., :2]

    with pytest.raises(ValueError, match="a scalar R needs the measurement size: Position"):
        EKF(dyn, Position(), Q=0.01, R=0.01)
    # the sensor's own R says the size
    est = EKF(dyn, Position(torch.eye(2) * 0.01), Q=0.01, R=0.05).double()
    state = est.init(torch.zeros(1, 3, dtype=torch.float64), torch.eye(3, dtype=torch.float64))
    new = est.update(state, torch.ones(1, 2, dtype=torch.float64))
    # P = I, H = [I 0], R = 0.05 I: gain 1 / 1.05
    torch.testing.assert_close(new.mean[0, :2], torch.full((2,), 1 / 1.05, dtype=torch.float64))


def test_passthrough_keeps_its_estimate_on_a_measurement_that_is_not_finite():
    est = PassThrough(state_dim=2)
    state = est.init(torch.tensor([[1.0, 2.0], [3.0, 4.0]]))
    new = est.update(state, torch.tensor([[5.0, 6.0], [float("nan"), 7.0]]))
    assert new.mean.tolist() == [[5.0, 6.0], [3.0, 4.0]]
    assert new.status.tolist() == [0, int(EstimatorStatus.NON_FINITE)]
    assert bool(torch.isfinite(new.cov).all())


@pytest.mark.parametrize("cls", [UKF, HybridEKFUKF], ids=lambda c: c.__name__)
def test_indefinite_covariance_is_regularized_not_nan(cls, dtype):
    """A covariance that lost definiteness (e.g. handed in from outside) gets a jitter or a
    diagonal fallback in the sigma points, is flagged, and yields finite numbers."""
    dyn, sensor = _unicycle_rb(dtype)
    est = cls(dyn, sensor)
    P = torch.eye(3, dtype=dtype).repeat(2, 1, 1) * 0.1
    P[1, 0, 1] = P[1, 1, 0] = 0.2  # indefinite in row 1
    if cls is HybridEKFUKF:
        ok = EKF(dyn, sensor).init(torch.zeros(2, 3, dtype=dtype), torch.eye(3, dtype=dtype))
        inner = EstimatorState(ok.mean, P, ok.status)
        state = est.init(torch.zeros(2, 3, dtype=dtype), torch.eye(3, dtype=dtype))
        state = state._replace(ukf=inner, ekf=inner)
    else:
        state = EstimatorState(torch.zeros(2, 3, dtype=dtype), P, torch.zeros(2, dtype=torch.long))
    new = est.predict(state, torch.ones(2, 2, dtype=dtype), 0.1)
    assert bool(torch.isfinite(new.mean).all() and torch.isfinite(new.cov).all())
    assert new.status[0] == 0
    assert new.status[1] & int(EstimatorStatus.REGULARIZED)


@pytest.mark.parametrize("cls", FILTERS, ids=lambda c: c.__name__)
def test_gradcheck_through_predict_and_update(cls, device):
    """Gradients of the posterior w.r.t. the prior mean, the control and the measurement
    (through the autograd Jacobians, the matrix exponentials and the Cholesky factors)."""
    f64 = {"dtype": torch.float64, "device": device}
    dyn = AccelUnicycle(sigma=torch.tensor([0.05, 0.05, 0.1, 0.1])).to(**f64)
    lm = torch.tensor([[4.0, 3.0], [-3.0, 4.0]], dtype=torch.float64)
    sensor = RangeBearing(lm, 0.1, 0.05, heading_index=3).to(**f64)
    est = cls(dyn, sensor)
    P0 = torch.diag(torch.tensor([0.1, 0.1, 0.05, 0.05], **f64))

    def run(x0, u, y):
        state = est.step(est.init(x0, P0), u, 0.1, y)
        return state.mean, state.cov

    g = torch.Generator().manual_seed(0)
    x0 = (torch.randn(2, 4, generator=g, dtype=torch.float64) * 0.2).to(device).requires_grad_()
    u = torch.randn(2, 2, generator=g, dtype=torch.float64).to(device).requires_grad_()
    y = sensor.expected(x0.detach() + 0.05).requires_grad_()
    assert torch.autograd.gradcheck(run, (x0, u, y), atol=1e-6, rtol=1e-5, fast_mode=True)


def test_gradient_flows_to_model_parameters(dtype):
    """A learnable model parameter gets a gradient through the autograd Jacobian F."""

    class Damped(DoubleIntegrator):
        def __init__(self) -> None:
            super().__init__(dim=1, sigma=torch.tensor([[0.0], [0.3]]))
            self.k = torch.nn.Parameter(torch.tensor(0.5))

        def f(self, x):
            return torch.stack([x[..., 1], -self.k * x[..., 1]], -1)

        def _xdot(self, x, u):
            return self.f(x) + torch.cat([torch.zeros_like(u), u], -1)

    dyn = Damped().to(dtype)
    sensor = GaussianSensor(C=torch.tensor([[1.0, 0.0]]), std=0.1).to(dtype)
    est = EKF(dyn, sensor)
    state = est.init(torch.tensor([0.0, 1.0], dtype=dtype), torch.eye(2, dtype=dtype))
    state = est.predict(state, torch.zeros(1, dtype=dtype), 0.5)
    state.cov.trace().backward()
    assert dyn.k.grad is not None and float(dyn.k.grad.abs()) > 0
    # the mean and covariance depend on k: a finite-difference check of d tr(P)/dk
    with torch.no_grad():
        h = 1e-4 if dtype == torch.float64 else 1e-2
        vals = []
        for s in (1, -1):
            dyn.k += s * h
            p = est.predict(
                est.init(torch.tensor([0.0, 1.0], dtype=dtype), torch.eye(2, dtype=dtype)),
                torch.zeros(1, dtype=dtype),
                0.5,
            )
            vals.append(p.cov.trace())
            dyn.k -= s * h
        fd = (vals[0] - vals[1]) / (2 * h)
    assert torch.allclose(dyn.k.grad, fd, rtol=1e-3 if dtype == torch.float64 else 5e-2)


@pytest.mark.parametrize("make", FILTERS)
def test_inference_mode_and_inference_tensors_answer_as_no_grad(make):
    """Autograd records nothing under ``torch.inference_mode``: the Jacobians are taken
    outside it, and tensors made under it are taken as inputs outside it."""
    dyn, sensor = _unicycle_rb()
    est = make(dyn, sensor, Q=0.01).double()
    x0 = torch.tensor([[0.0, 0.0, 0.3], [0.5, -0.2, 1.0]], dtype=torch.float64)
    P0 = 0.1 * torch.eye(3, dtype=torch.float64)
    u = torch.tensor([[1.0, 0.5]], dtype=torch.float64)
    y = torch.tensor([[5.0, -0.7, 5.0, 2.2]], dtype=torch.float64)
    with torch.no_grad():
        want = est.step(est.init(x0, P0), u, 0.5, y)
    with torch.inference_mode():
        got = est.step(est.init(x0, P0), u, 0.5, y)
        made = (est.init(x0, P0), u.clone(), y.clone())  # inference tensors
    again = est.step(made[0], made[1], 0.5, made[2])
    for out in (got, again):
        torch.testing.assert_close(out.mean, want.mean, rtol=1e-12, atol=1e-12)
        torch.testing.assert_close(out.cov, want.cov, rtol=1e-12, atol=1e-12)
        assert torch.equal(out.status, want.status)
    assert not torch.allclose(want.mean, est.predict(est.init(x0, P0), u, 0.5).mean)


def test_passthrough_refuses_a_non_finite_covariance_and_filters_half_precision():
    with pytest.raises(ValueError, match="P0"):
        PassThrough().init(torch.zeros(2), torch.full((2, 2), float("nan")))
    dyn, sensor = _unicycle_rb(torch.float32)
    with pytest.raises(TypeError, match="x0 must be float32 or float64"):
        EKF(dyn, sensor).init(torch.zeros(3, dtype=torch.float16), torch.eye(3).half())
