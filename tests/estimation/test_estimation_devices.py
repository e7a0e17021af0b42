"""Sensors and the Kalman filters on the device fixture's device against the CPU: outputs,
statuses and gradients, with every input drawn on the CPU and moved."""

from __future__ import annotations

import math

import pytest
import torch
from _devices import device_matches_cpu
from _host_traffic import HostTraffic

from torchcbf.dynamics import AccelUnicycle
from torchcbf.estimation import (
    EKF,
    UKF,
    EstimatorState,
    EstimatorStatus,
    FunctionSensor,
    GaussianSensor,
    HybridEKFUKF,
    HybridState,
    RangeBearing,
)

FILTERS = [EKF, UKF, HybridEKFUKF]
LANDMARKS = [[4.0, 3.0], [-3.0, 4.0], [0.5, -3.0]]


def _polar(x: torch.Tensor) -> torch.Tensor:
    """Range and bearing of the position from the origin, and the speed."""
    return torch.stack([x[..., :2].norm(dim=-1), torch.atan2(x[..., 1], x[..., 0]), x[..., 2]], -1)


def _sensors() -> dict[str, torch.nn.Module]:
    C = torch.tensor([[1.0, 0.0, 2.0, 0.0], [0.0, -1.0, 0.5, 0.3]])
    R = torch.tensor([[0.04, 0.01], [0.01, 0.09]])
    return {
        "gaussian": GaussianSensor(C=C, R=R),
        "function": FunctionSensor(_polar, std=[0.1, 0.05, 0.2], angle_index=[1], state_dim=4),
        "range_bearing": RangeBearing(LANDMARKS, 0.1, 0.05, heading_index=3),
        "absolute_bearing": RangeBearing(torch.tensor(LANDMARKS), 0.2, 0.1, heading_index=None),
    }


@pytest.mark.parametrize("name", ["gaussian", "function", "range_bearing", "absolute_bearing"])
def test_sensor_outputs_and_gradients_on_device_equal_cpu(name, dtype, device) -> None:
    """``expected``, ``measure`` with given noise (angles wrapped), ``residual`` across the
    wrap and the gradient of the measurement to the state equal the CPU's."""
    gen = torch.Generator().manual_seed(0)
    x = 2.0 * torch.randn(5, 7, 4, generator=gen, dtype=torch.float64)
    x[..., 3] = x[..., 3] * 3.0  # headings well past +-pi
    p = _sensors()[name].expected(x).shape[-1]
    z = torch.randn(5, 7, p, generator=gen, dtype=torch.float64)
    y_other = torch.randn(5, 7, p, generator=gen, dtype=torch.float64) * 4.0

    def run(dev: torch.device):
        f = {"device": dev, "dtype": dtype}
        sensor = _sensors()[name].to(**f)
        xs = x.to(**f).requires_grad_()
        y = sensor.measure(xs, noise=z.to(**f))
        (grad,) = torch.autograd.grad(y.sum(), xs)
        with torch.no_grad():
            expected = sensor.expected(xs)
            residual = sensor.residual(y_other.to(**f), expected)
        return expected, y.detach(), residual, grad

    _, y, residual, grad = device_matches_cpu(run, device, dtype)
    if name != "gaussian":  # the wrapped components stay in [-pi, pi)
        assert bool((residual[..., 1].abs() <= math.pi + 1e-6).all())
    assert bool((grad != 0).any()) and bool(torch.isfinite(y).all())


def test_sensor_draws_from_a_device_generator(dtype, device) -> None:
    """A generator on the device draws the noise there: the same seed repeats it exactly,
    a generator on another device than the state's is refused by name."""
    sensor = _sensors()["range_bearing"].to(device=device, dtype=dtype)
    x = torch.zeros(64, 4, device=device, dtype=dtype)
    y1 = sensor.measure(x, torch.Generator(device=device).manual_seed(3))
    y2 = sensor.measure(x, torch.Generator(device=device).manual_seed(3))
    assert y1.device.type == device.type and y1.shape == (64, 6)
    assert torch.equal(y1, y2) and not torch.equal(y1, sensor.expected(x))
    if device.type != "cpu":
        with pytest.raises(ValueError, match="generator is on device cpu"):
            sensor.measure(x, torch.Generator().manual_seed(3))


def _filter(cls, dev: torch.device, dtype: torch.dtype, **kw):
    dyn = AccelUnicycle(sigma=torch.tensor([0.05, 0.05, 0.1, 0.1]))
    sensor = RangeBearing(LANDMARKS, 0.1, 0.05, heading_index=3)
    return cls(dyn, sensor, substeps=2, **kw).to(device=dev, dtype=dtype)


@pytest.mark.parametrize("cls", FILTERS, ids=lambda c: c.__name__)
@pytest.mark.parametrize("noise", ["from_model", "given"])
def test_filter_steps_and_gradients_on_device_equal_cpu(cls, noise, dtype, device) -> None:
    """Three steps of each filter over a ``[2, 3]`` batch (controls broadcast over the
    leading dimension, one shared ``P0``), with the process noise from the model or given
    with an ``R`` override: means, covariances, statuses and the gradients of the posterior
    to the prior mean, the controls and the measurements equal the CPU's."""
    gen = torch.Generator().manual_seed(1)
    x0 = 0.3 * torch.randn(2, 3, 4, generator=gen, dtype=torch.float64)
    us = torch.randn(3, 3, 2, generator=gen, dtype=torch.float64)  # [T, 3, m]: broadcast
    truth = 0.3 * torch.randn(3, 2, 3, 4, generator=gen, dtype=torch.float64)
    ys = RangeBearing(LANDMARKS, 0.1, 0.05, heading_index=3).double().expected(truth)
    ys = ys + 0.05 * torch.randn(ys.shape, generator=gen, dtype=torch.float64)
    kw = {} if noise == "from_model" else {"Q": [0.01, 0.01, 0.02, 0.05], "R": 0.02}

    def run(dev: torch.device):
        f = {"device": dev, "dtype": dtype}
        est = _filter(cls, dev, dtype, **kw)
        x = x0.to(**f).requires_grad_()
        u = us.to(**f).requires_grad_()
        y = ys.to(**f).requires_grad_()
        state = est.init(x, torch.diag(torch.tensor([0.1, 0.1, 0.05, 0.05], **f)))
        for k in range(3):
            state = est.step(state, u[k], 0.1, y[k])
        loss = state.mean.sin().sum() + state.cov.sum()
        grads = torch.autograd.grad(loss, (x, u, y))
        return state.mean.detach(), state.cov.detach(), state.status, *grads

    loose = {} if dtype == torch.float64 else {"rtol": 1e-3, "atol": 1e-4}
    mean, cov, status, *grads = device_matches_cpu(run, device, dtype, **loose)
    assert mean.shape == (2, 3, 4) and cov.shape == (2, 3, 4, 4) and status.shape == (2, 3)
    assert bool((status == 0).all()) and all(bool((g != 0).any()) for g in grads)


@pytest.mark.parametrize("cls", FILTERS, ids=lambda c: c.__name__)
def test_flagged_rows_on_device_equal_cpu(cls, dtype, device) -> None:
    """A row with an indefinite covariance (regularized, flagged) and a row with a
    non-finite measurement (skipped, flagged) give the CPU's estimates and status bits."""
    P = torch.eye(4, dtype=torch.float64).repeat(3, 1, 1) * 0.1
    P[1, 0, 1] = P[1, 1, 0] = 0.3  # indefinite
    x0 = torch.tensor([[0.1, 0.0, 0.2, 0.3], [0.0, 0.1, 0.0, -0.2], [0.2, 0.2, 0.1, 0.1]])
    truth = x0.double() + 0.05
    y = RangeBearing(LANDMARKS, 0.1, 0.05, heading_index=3).double().expected(truth)
    y[2, 1] = math.nan

    def run(dev: torch.device):
        f = {"device": dev, "dtype": dtype}
        est = _filter(cls, dev, dtype)
        inner = EstimatorState(x0.to(**f), P.to(**f), torch.zeros(3, dtype=torch.long, device=dev))
        if cls is HybridEKFUKF:
            state = est.init(x0.to(**f), torch.eye(4, **f))._replace(ekf=inner, ukf=inner)
        else:
            state = inner
        predicted = est.predict(state, torch.ones(3, 2, **f), 0.1)
        updated = est.update(predicted, y.to(**f))
        return predicted.mean, predicted.status, updated.mean, updated.cov, updated.status

    loose = {} if dtype == torch.float64 else {"rtol": 1e-3, "atol": 1e-4}
    *_, mean, cov, status = device_matches_cpu(run, device, dtype, **loose)
    assert bool(torch.isfinite(mean).all() and torch.isfinite(cov).all())
    assert int(status[2]) & int(EstimatorStatus.NON_FINITE)
    if cls is not EKF:  # the sigma points of the indefinite row need the fallback
        assert int(status[1]) & int(EstimatorStatus.REGULARIZED)


@pytest.mark.parametrize("name", ["gaussian", "function", "range_bearing"])
def test_sensor_left_on_the_cpu_follows_its_input(name, dtype, device) -> None:
    """A sensor that was not moved casts its constants (``C``, ``R_sqrt``, the landmarks and
    the mask of the angle components) to the input: a filter built on it runs on the
    device and answers as on the CPU."""
    gen = torch.Generator().manual_seed(2)
    x = torch.randn(6, 4, generator=gen, dtype=torch.float64)
    x[:, 3] = 4.0  # a heading past pi: the bearings wrap
    sensor = _sensors()[name]
    z = torch.randn(6, sensor.expected(x).shape[-1], generator=gen, dtype=torch.float64)

    def run(dev: torch.device):
        f = {"device": dev, "dtype": dtype}
        y = sensor.measure(x.to(**f), noise=z.to(**f))
        est = EKF(AccelUnicycle(sigma=0.1).to(**f), sensor)
        state = est.init(x.to(**f) + 0.1, 0.05 * torch.eye(4, **f))
        state = est.step(state, torch.ones(6, 2, **f), 0.1, y)
        return y, sensor.residual(y, sensor.expected(x.to(**f))), state.mean, state.cov

    loose = {} if dtype == torch.float64 else {"rtol": 1e-3, "atol": 1e-4}
    device_matches_cpu(run, device, dtype, **loose)
    assert all(buffer.device.type == "cpu" for buffer in sensor.buffers())  # not moved


def test_sensor_calls_never_wait_for_the_device(device) -> None:
    """Measuring (drawn or given noise), the noise-free output and the residual make no host
    synchronisation on an accelerator (its sync debug mode raises on one)."""
    if device.type == "cpu":
        pytest.skip("host synchronisations exist only on an accelerator")
    sensors = [s.to(device) for s in _sensors().values()]
    x = torch.randn(32, 4, generator=torch.Generator().manual_seed(0)).to(device)
    noises = [torch.zeros_like(s.expected(x)) for s in sensors]
    gen = torch.Generator(device=device).manual_seed(0)
    torch.cuda.synchronize()
    torch.cuda.set_sync_debug_mode("error")
    try:
        for sensor, z in zip(sensors, noises, strict=True):
            y = sensor.measure(x, gen)
            sensor.residual(sensor.measure(x, noise=z), y)
    finally:
        torch.cuda.set_sync_debug_mode(0)


@pytest.mark.parametrize("cls", FILTERS, ids=lambda c: c.__name__)
@pytest.mark.parametrize("name", ["gaussian", "function", "range_bearing"])
def test_filter_steps_make_no_host_traffic(cls, name) -> None:
    """Predict and update with each sensor run on the meta device (no value is read back)
    and copy nothing from the host (no list index, no Python data)."""
    meta = torch.device("meta")
    sensor = _sensors()[name].to(meta)
    est = cls(AccelUnicycle(sigma=0.1), sensor).to(meta)
    inner = EstimatorState(
        torch.zeros(3, 4, device=meta),
        torch.eye(4, device=meta).expand(3, 4, 4),
        torch.zeros(3, dtype=torch.long, device=meta),
    )
    # built by hand: init checks that P0 is positive definite, which reads values
    state = HybridState(*inner, inner, inner) if cls is HybridEKFUKF else inner
    y = torch.zeros(3, sensor.output_dim, device=meta)
    with HostTraffic() as traffic:
        state = est.update(est.predict(state, torch.zeros(3, 2, device=meta), 0.1), y)
        sensor.residual(sensor.measure(inner.mean, noise=y), y)
    assert not traffic.events, dict(traffic.events)
    assert state.mean.device.type == "meta" and state.cov.shape == (3, 4, 4)


@pytest.mark.parametrize("cls", FILTERS, ids=lambda c: c.__name__)
def test_filter_steps_never_wait_for_the_device(cls, device) -> None:
    """Predict (its matrix exponential included) and update make no host synchronisation on
    an accelerator (its sync debug mode raises on one)."""
    if device.type == "cpu":
        pytest.skip("host synchronisations exist only on an accelerator")
    sensor = _sensors()["range_bearing"].to(device)
    est = cls(AccelUnicycle(sigma=0.1), sensor).to(device)
    gen = torch.Generator().manual_seed(2)
    x0 = torch.randn(16, 4, generator=gen).to(device)
    state = est.init(x0, torch.eye(4, device=device).expand(16, 4, 4) * 0.1)
    u = torch.zeros(16, 2, device=device)
    y = sensor.expected(x0)
    torch.cuda.synchronize()
    torch.cuda.set_sync_debug_mode("error")
    try:
        est.update(est.predict(state, u, 0.1), y)
    finally:
        torch.cuda.set_sync_debug_mode(0)
