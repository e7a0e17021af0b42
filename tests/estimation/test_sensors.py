"""Sensors: expected values against closed forms, noise statistics, seeding, wrapping, errors."""

from __future__ import annotations

import math

import pytest
import torch

from torchcbf.estimation import FunctionSensor, GaussianSensor, Perfect, RangeBearing, wrap_angle


def test_gaussian_sensor_expected_and_noise_statistics(dtype, device):
    C = torch.tensor([[1.0, 0.0, 2.0], [0.0, -1.0, 0.5]], dtype=dtype)
    R = torch.tensor([[0.04, 0.01], [0.01, 0.09]], dtype=dtype)
    sensor = GaussianSensor(C=C, R=R).to(device)
    x = torch.tensor([1.0, 2.0, -1.0], dtype=dtype, device=device)
    assert torch.allclose(
        sensor.expected(x), torch.tensor([-1.0, -2.5], dtype=dtype, device=device)
    )
    N = 40000
    gen = torch.Generator(device=device).manual_seed(0)
    y = sensor.measure(x.expand(N, 3), gen)
    assert y.shape == (N, 2) and y.dtype == dtype
    v = (y - sensor.expected(x)).double().cpu()
    assert v.mean(0).abs().max() < 4 * 0.3 / math.sqrt(N)
    assert torch.allclose(v.T @ v / N, R.double(), atol=3e-3)
    # same seed, same draw; explicit noise is used as given
    y2 = sensor.measure(x.expand(N, 3), torch.Generator(device=device).manual_seed(0))
    assert torch.equal(y, y2)
    z = torch.tensor([1.0, -2.0], dtype=dtype, device=device)
    L = torch.linalg.cholesky(R).to(device)
    assert torch.allclose(sensor(x, noise=z), sensor.expected(x) + L @ z)


def test_gaussian_sensor_identity_and_std_forms():
    s = GaussianSensor(std=[0.1, 0.2, 0.3])
    assert s.output_dim == 3 and s.state_dim == 3
    assert torch.allclose(s.R, torch.diag(torch.tensor([0.01, 0.04, 0.09])))
    s = GaussianSensor(std=0.5, state_dim=2)
    assert torch.allclose(s.R, 0.25 * torch.eye(2))
    x = torch.randn(4, 2)
    assert torch.equal(s.expected(x), x)


def test_sensor_errors():
    with pytest.raises(ValueError, match="generator"):
        GaussianSensor(std=0.1, state_dim=2).measure(torch.zeros(2))
    with pytest.raises(ValueError, match="exactly one"):
        GaussianSensor(std=0.1, R=torch.eye(2))
    with pytest.raises(ValueError, match="exactly one"):
        GaussianSensor(state_dim=2)
    with pytest.raises(ValueError, match="state_dim"):
        GaussianSensor(std=0.1)
    with pytest.raises(ValueError, match="std must be positive"):
        GaussianSensor(std=[0.1, 0.0])
    with pytest.raises(ValueError, match="R must be positive definite"):
        GaussianSensor(R=torch.tensor([[1.0, 2.0], [2.0, 1.0]]))
    with pytest.raises(ValueError, match="R must be symmetric"):
        GaussianSensor(R=torch.tensor([[1.0, 0.5], [0.0, 1.0]]))
    with pytest.raises(ValueError, match=r"R must have shape \[2, 2\]"):
        GaussianSensor(C=torch.eye(2), R=torch.eye(3))
    with pytest.raises(ValueError, match=r"x must have shape \[\.\.\., 3\]"):
        GaussianSensor(C=torch.eye(3), std=0.1).expected(torch.zeros(2))
    with pytest.raises(ValueError, match=r"fn\(x\) must return"):
        FunctionSensor(lambda x: x, std=0.1, output_dim=2).expected(torch.zeros(3))
    with pytest.raises(ValueError, match="landmarks"):
        RangeBearing(torch.zeros(3), 0.1, 0.1)
    with pytest.raises(ValueError, match="std_range"):
        RangeBearing(torch.zeros(1, 2), 0.0, 0.1)
    with pytest.raises(ValueError, match="n > 2"):
        RangeBearing(torch.ones(1, 2), 0.1, 0.1).expected(torch.zeros(2))
    with pytest.raises(ValueError, match=r"noise must have shape \[\.\.\., 2\]"):
        GaussianSensor(std=0.1, state_dim=2).measure(torch.zeros(2), noise=torch.zeros(3))


def test_range_bearing_closed_form_and_wrapping(dtype):
    lm = torch.tensor([[3.0, 4.0], [-1.0, 0.0]], dtype=dtype)
    sensor = RangeBearing(lm, 0.1, 0.01).to(dtype)
    x = torch.tensor([[0.0, 0.0, 0.0], [0.0, 0.0, math.pi / 2], [1.0, 1.0, -3.0]], dtype=dtype)
    y = sensor.expected(x)
    assert y.shape == (3, 4)
    for b in range(3):
        px, py, th = x[b].tolist()
        for i, (lx, ly) in enumerate(lm.tolist()):
            r = math.hypot(lx - px, ly - py)
            bearing = math.atan2(ly - py, lx - px) - th
            bearing = (bearing + math.pi) % (2 * math.pi) - math.pi
            assert abs(float(y[b, 2 * i]) - r) < 1e-5
            assert abs(float(y[b, 2 * i + 1]) - bearing) < 1e-5
    assert bool((y[:, 1::2] >= -math.pi).all() and (y[:, 1::2] < math.pi).all())
    # residual wraps only the bearing components
    a = torch.tensor([10.0, math.pi - 0.01, 1.0, -math.pi + 0.02], dtype=dtype)
    b = torch.tensor([4.0, -math.pi + 0.01, 3.0, math.pi - 0.02], dtype=dtype)
    expect = torch.tensor([6.0, -0.02, -2.0, 0.04], dtype=dtype)
    assert torch.allclose(sensor.residual(a, b), expect, atol=1e-5)
    # noisy bearings are wrapped too; AccelUnicycle heading index and absolute bearings
    gen = torch.Generator().manual_seed(0)
    yn = sensor.measure(torch.tensor([0.0, 0.0, math.pi], dtype=dtype).expand(1000, 3), gen)
    assert bool((yn[:, 1::2] >= -math.pi).all() and (yn[:, 1::2] < math.pi).all())
    s4 = RangeBearing(lm, 0.1, 0.01, heading_index=3)
    s_abs = RangeBearing(lm, 0.1, 0.01, heading_index=None)
    x4 = torch.tensor([0.0, 0.0, 5.0, 0.3], dtype=dtype)
    assert torch.allclose(
        s4.expected(x4)[1], torch.atan2(torch.tensor(4.0), torch.tensor(3.0)).to(dtype) - 0.3
    )
    x4_other_heading = x4.clone()
    x4_other_heading[3] = -2.0
    assert torch.allclose(s_abs.expected(x4), s_abs.expected(x4_other_heading))
    assert not torch.allclose(s4.expected(x4), s4.expected(x4_other_heading))


def test_function_sensor_and_perfect():
    sensor = FunctionSensor(
        lambda x: torch.stack([x[..., 0] ** 2, torch.atan2(x[..., 1], x[..., 0])], -1),
        std=[0.1, 0.05],
        angle_index=(1,),
    )
    x = torch.tensor([[1.0, 1.0], [-1.0, 0.0]])
    y = sensor.expected(x)
    assert torch.allclose(y[:, 0], torch.tensor([1.0, 1.0]))
    assert torch.allclose(
        sensor.residual(torch.tensor([0.0, 3.1]), torch.tensor([0.0, -3.1])),
        torch.tensor([0.0, 3.1 + 3.1 - 2 * math.pi]),
    )
    assert sensor.R.shape == (2, 2)
    module = torch.nn.Linear(3, 2)
    s2 = FunctionSensor(module, R=torch.eye(2) * 0.01)
    assert any(p is module.weight for p in s2.parameters())
    p = Perfect()
    x3 = torch.randn(5, 3)
    assert torch.equal(p.measure(x3), x3) and p.R is None


def test_wrap_angle():
    a = torch.tensor([0.0, math.pi, -math.pi, 3 * math.pi + 0.1, -7.0], dtype=torch.float64)
    w = wrap_angle(a)
    assert bool(((w >= -math.pi) & (w < math.pi)).all())
    assert torch.allclose(torch.sin(w), torch.sin(a)) and torch.allclose(torch.cos(w), torch.cos(a))


def test_wrap_angle_just_below_minus_pi_stays_in_range():
    """remainder rounds an angle an ulp below -pi up to 2 pi, which wraps to +pi."""
    for dtype in (torch.float32, torch.float64):
        a = torch.tensor(-math.pi, dtype=dtype)
        below = [torch.nextafter(a, torch.tensor(-10.0, dtype=dtype))]
        for _ in range(5):
            below.append(torch.nextafter(below[-1], torch.tensor(-10.0, dtype=dtype)))
        w = wrap_angle(torch.stack(below))
        assert bool(((w >= -math.pi) & (w < math.pi)).all()), w.tolist()
        assert torch.allclose(torch.cos(w), torch.cos(torch.stack(below)))


def test_sensor_inputs_of_the_wrong_kind():
    s = GaussianSensor(torch.tensor([[0.5, 0.0, 0.0], [0.0, 0.7, 0.7]]), 0.1)
    with pytest.raises(TypeError, match="x must be a floating-point tensor, got torch.int64"):
        s.expected(torch.tensor([[3, 1, 1]]))
    for bad in (5, "seed", torch.Generator):
        with pytest.raises(TypeError, match="generator must be a torch.Generator, got"):
            s.measure(torch.zeros(1, 3), bad)


def test_range_bearing_on_an_empty_batch():
    s = RangeBearing(torch.tensor([[3.0, 1.0], [-2.0, 4.0]]), 0.1, 0.05)
    assert s.expected(torch.zeros(0, 3)).shape == (0, 4)
    assert s.expected(torch.zeros(2, 0, 3)).shape == (2, 0, 4)


def test_measurement_noise_must_broadcast_to_the_states():
    s = GaussianSensor(torch.tensor([[0.5, 0.0, 0.0], [0.0, 0.7, 0.7]]), 0.1)
    x = torch.zeros(2, 3)
    assert s.measure(x, noise=torch.zeros(2)).shape == (2, 2)
    for bad in (torch.zeros(3, 2), torch.zeros(4, 1, 2)):
        with pytest.raises(ValueError, match=r"noise \[\.\.\., 2\] must broadcast to the batch"):
            s.measure(x, noise=bad)
