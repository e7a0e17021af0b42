"""EKF: exact Kalman filter on linear systems, Monte Carlo consistency, batch = loop, errors."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from estimation_reference import (
    LinearSystem,
    assert_monte_carlo_consistent,
    exact_kalman,
    linear_case,
    run_filter,
)

from torchcbf.dynamics import DoubleIntegrator
from torchcbf.estimation import EKF, UKF, GaussianSensor, HybridEKFUKF

FILTERS = [EKF, UKF, HybridEKFUKF]


def _linear_errors(cls, dtype, device, substeps):
    case = linear_case()
    t = lambda a: torch.as_tensor(a, dtype=dtype, device=device)  # noqa: E731
    dyn = LinearSystem(t(case["A"]), t(case["Bu"])).to(device)
    sensor = GaussianSensor(C=t(case["C"]), R=t(case["R"])).to(device)
    est = cls(dyn, sensor, Q=t(case["Qc"]), substeps=substeps)
    means, covs, _ = run_filter(
        est, t(case["x0"]), t(case["P0"]), t(case["us"]), t(case["ys"]), case["dt"]
    )
    err_m, err_p = 0.0, 0.0
    for b in range(case["x0"].shape[0]):
        ref_m, ref_p = exact_kalman(
            case["A"], case["Bu"], case["Qc"], case["C"], case["R"], case["x0"][b],
            case["P0"][b], case["us"][:, b], case["ys"][:, b], case["dt"],
        )  # fmt: skip
        err_m = max(err_m, np.abs(means[:, b].double().cpu().numpy() - ref_m).max())
        err_p = max(err_p, np.abs(covs[:, b].double().cpu().numpy() - ref_p).max())
    return err_m, err_p


@pytest.mark.parametrize("cls", FILTERS, ids=lambda c: c.__name__)
@pytest.mark.parametrize("substeps", [1, 3])
def test_linear_system_equals_exact_kalman_filter(cls, substeps, dtype, device):
    err_m, err_p = _linear_errors(cls, dtype, device, substeps)
    tol = 1e-9 if dtype == torch.float64 else 2e-4
    assert err_m < tol and err_p < tol, (err_m, err_p)


@pytest.mark.parametrize("cls", FILTERS, ids=lambda c: c.__name__)
def test_double_integrator_default_q_from_sigma(cls, dtype, device):
    """Q from the dynamics' diffusion (positive semidefinite: noise on the velocities only)."""
    sigma = torch.tensor([[0.0, 0.0], [0.0, 0.0], [0.4, 0.0], [0.1, 0.3]], dtype=dtype)
    dyn = DoubleIntegrator(dim=2, sigma=sigma).to(device)
    C = torch.tensor([[1.0, 0.0, 0.0, 0.0], [0.0, 1.0, 0.0, 0.0]], dtype=dtype)
    sensor = GaussianSensor(C=C, std=torch.tensor([0.2, 0.3], dtype=dtype)).to(device)
    est = cls(dyn, sensor)
    gen = torch.Generator().manual_seed(3)
    T, B = 15, 4
    us = torch.randn(T, B, 2, generator=gen, dtype=dtype).to(device)
    ys = torch.randn(T, B, 2, generator=gen, dtype=dtype).to(device)
    x0 = torch.randn(B, 4, generator=gen, dtype=dtype).to(device)
    P0 = torch.eye(4, dtype=dtype, device=device) * 0.5
    means, covs, state = run_filter(est, x0, P0, us, ys, 0.05)
    A = np.zeros((4, 4))
    A[:2, 2:] = np.eye(2)
    Bu = np.zeros((4, 2))
    Bu[2:] = np.eye(2)
    s = sigma.double().numpy()
    tol = 1e-9 if dtype == torch.float64 else 2e-4
    for b in range(B):
        ref_m, ref_p = exact_kalman(
            A, Bu, s @ s.T, C.double().numpy(), np.diag([0.04, 0.09]),
            x0[b].double().cpu().numpy(), P0.double().cpu().numpy(),
            us[:, b].double().cpu().numpy(), ys[:, b].double().cpu().numpy(), 0.05,
        )  # fmt: skip
        assert np.abs(means[:, b].double().cpu().numpy() - ref_m).max() < tol
        assert np.abs(covs[:, b].double().cpu().numpy() - ref_p).max() < tol
    assert bool((state.status == 0).all())


def test_ekf_covariance_stays_spd_and_symmetric(dtype):
    case = linear_case(rows=3, steps=40)
    t = lambda a: torch.as_tensor(a, dtype=dtype)  # noqa: E731
    dyn = LinearSystem(t(case["A"]), t(case["Bu"]))
    # a very precise sensor stresses the update (P shrinks by orders of magnitude)
    sensor = GaussianSensor(C=t(case["C"]), std=1e-4)
    _, covs, state = run_filter(
        EKF(dyn, sensor, Q=t(case["Qc"])), t(case["x0"]), t(case["P0"]), t(case["us"]),
        t(case["ys"]), case["dt"],
    )  # fmt: skip
    assert torch.equal(covs, covs.mT)
    assert bool((torch.linalg.eigvalsh(covs) > 0).all())
    assert bool(torch.isfinite(covs).all())


@pytest.mark.parametrize("model", ["unicycle", "accel_unicycle"])
def test_ekf_monte_carlo_consistent_and_beats_sensor(model, dtype):
    """500 runs in one batch: run-averaged NEES inside its 95% chi-square band."""
    assert_monte_carlo_consistent(EKF, dtype, model)
