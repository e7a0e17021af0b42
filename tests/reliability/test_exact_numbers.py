"""Python numbers given to class-K gains, HOCBF gains and MPPI's noise and limits stay exact
under ``.double()`` (not rounded through float32); tensors are kept as given."""

from __future__ import annotations

import torch

from torchcbf.barriers import Ball, rectify
from torchcbf.dynamics import DoubleIntegrator, SingleIntegrator
from torchcbf.filters import CubicClassK, LinearClassK, SafetyFilter
from torchcbf.mppi import MPPI, QuadraticGoal


def test_class_k_gains_are_exact_in_float64() -> None:
    assert LinearClassK(0.1).double().gain.item() == 0.1
    assert CubicClassK([0.1, 0.7]).double().gain.tolist() == [0.1, 0.7]
    filt = SafetyFilter(SingleIntegrator(2), [Ball([0.0, 0.0], 0.5)], alpha=0.1).double()
    assert filt.alpha[0].gain.item() == 0.1
    assert LinearClassK(0.1).gain.dtype == torch.get_default_dtype()
    given = torch.tensor(0.1)  # a float32 tensor is the user's own rounding
    assert LinearClassK(given).double().gain.item() == float(given)


def test_hocbf_gains_are_exact_in_float64() -> None:
    ball = Ball([0.0, 0.0], 0.5)
    hocbf = rectify(ball, DoubleIntegrator(2), form="high_order", gains=[0.7]).double()
    assert hocbf.gains.tolist() == [0.7]
    scalar = rectify(ball, DoubleIntegrator(2), form="high_order", gains=0.3).double()
    assert scalar.gains.tolist() == [0.3]


def test_mppi_noise_and_limits_are_exact_in_float64() -> None:
    limits = {"u_min": -0.1, "u_max": 0.7}
    planner = MPPI(SingleIntegrator(2), QuadraticGoal([1.0, 1.0]), horizon=5, num_samples=8,
                   dt=0.1, noise_sigma=0.3, temperature=1.0, **limits).double()  # fmt: skip
    assert planner.noise_cov[0, 0].item() == 0.3
    assert planner.noise_chol[0, 0].item() == 0.3**0.5
    assert planner.noise_cov_inv[0, 0].item() == 1 / 0.3
    assert planner.u_min.tolist() == [-0.1, -0.1] and planner.u_max.tolist() == [0.7, 0.7]
    plain = MPPI(SingleIntegrator(2), QuadraticGoal([1.0, 1.0]), horizon=5, num_samples=8,
                 dt=0.1, noise_sigma=0.3, temperature=1.0)  # fmt: skip
    assert plain.noise_cov.dtype == torch.get_default_dtype()
