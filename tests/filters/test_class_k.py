"""Class-K functions: values, per-output gains, learnable positive gains, specifications."""

from __future__ import annotations

import pytest
import torch
from torch import nn

from torchcbf.filters import CubicClassK, LinearClassK, PowerClassK, as_class_k


def test_values(dtype: torch.dtype) -> None:
    h = torch.tensor([[-2.0, 0.5, 3.0]], dtype=dtype)
    assert torch.allclose(LinearClassK(2.0).to(dtype)(h), 2 * h)
    assert torch.allclose(CubicClassK(0.5).to(dtype)(h), 0.5 * h**3)
    expected = torch.tensor([[-(2.0**0.5), 0.5**0.5, 3.0**0.5]], dtype=dtype)
    assert torch.allclose(PowerClassK(1.0, power=0.5).to(dtype)(h), expected)
    gains = LinearClassK([1.0, 2.0, 3.0]).to(dtype)
    assert torch.allclose(gains(h), h * torch.tensor([1.0, 2.0, 3.0], dtype=dtype))
    assert gains(h).dtype == dtype


def test_learnable_gain_stays_positive_and_trains() -> None:
    k = LinearClassK(torch.tensor([0.5, 2.0]), learnable=True).double()
    assert [n for n, _ in k.named_parameters()] == ["log_gain"]
    h = torch.tensor([1.0, -1.0], dtype=torch.float64)
    (grad,) = torch.autograd.grad(k(h).sum(), k.log_gain)
    # d (g h) / d log g = g h
    assert torch.allclose(grad, torch.tensor([0.5, -2.0], dtype=torch.float64))
    with torch.no_grad():
        k.log_gain -= 100.0
    assert bool((k.gain > 0).all())


@pytest.mark.parametrize("gain", [1.5, [0.1, 3.0]])
def test_a_learnable_gain_of_python_numbers_is_exact_in_float64(gain) -> None:
    k = LinearClassK(gain, learnable=True).double()
    assert k.log_gain.dtype == torch.float64 and isinstance(k.log_gain, nn.Parameter)
    exact = torch.tensor(gain, dtype=torch.float64)
    assert torch.equal(k.log_gain.detach(), exact.log())
    torch.testing.assert_close(k.gain.detach(), exact, rtol=1e-15, atol=0.0)
    with torch.no_grad():  # a trained gain is kept under a dtype change
        k.log_gain.add_(0.25)
    trained = k.log_gain.detach().clone()
    torch.testing.assert_close(k.float().double().log_gain.detach(), trained, rtol=1e-7, atol=0.0)


def test_as_class_k_specifications() -> None:
    h = torch.tensor([1.0, 2.0])
    assert torch.allclose(as_class_k(3.0)(h), 3 * h)
    assert torch.allclose(as_class_k([1.0, 0.5])(h), torch.tensor([1.0, 1.0]))
    assert torch.allclose(as_class_k(torch.tensor([2.0, 2.0]))(h), 2 * h)
    assert torch.allclose(as_class_k(lambda v: v**3)(h), h**3)
    module = nn.Identity()
    assert as_class_k(module) is module
    with pytest.raises(ValueError, match="alpha"):
        as_class_k(-1.0)
    with pytest.raises(ValueError, match="gain"):
        LinearClassK(0.0)
    with pytest.raises(TypeError, match="alpha"):
        as_class_k("fast")
    with pytest.raises(ValueError, match="power"):
        PowerClassK(1.0, power=-1.0)


@pytest.mark.parametrize("power", [1.0, 1.5, 2.0, 3.0])
def test_a_power_class_k_has_its_derivative_at_zero(power: float) -> None:
    """alpha(h) = gain sign(h) |h|^p: at h = 0 its derivative is gain for p = 1 (sign(h) |h|
    gave 0 there) and 0 above; elsewhere it is autograd's of the formula."""
    alpha = PowerClassK(2.0, power=power).double()
    h = torch.tensor([0.0, 0.3, -0.7], dtype=torch.float64, requires_grad=True)
    (grad,) = torch.autograd.grad(alpha(h).sum(), h)
    want = 2.0 * power * h.detach().abs() ** (power - 1.0)
    want[0] = 2.0 if power == 1.0 else 0.0
    torch.testing.assert_close(grad, want)
    torch.testing.assert_close(alpha(h), 2.0 * torch.sign(h) * h.abs() ** power)
