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


def _stiff_reference(A: np.ndarray, Qc: np.ndarray, P0: np.ndarray, x0: np.ndarray, dt: float):
    """Mean and covariance after ``dt`` of ``dx = A x dt + dW`` (``E[dW dW'] = Qc dt``) with
    diagonalisable ``A``, by its eigenvectors: ``Qd = V [W_ij (e^{(l_i + l_j) dt} - 1) /
    (l_i + l_j)] V'`` with ``W = V^-1 Qc V^-T``, no matrix exponential."""
    lam, V = np.linalg.eig(A)
    Vi = np.linalg.inv(V)
    Phi = (V * np.exp(lam * dt)) @ Vi
    W = Vi @ Qc @ Vi.T
    s = lam[:, None] + lam[None, :]
    Qd = V @ (W * np.expm1(s * dt) / s) @ V.T
    return (Phi @ x0).real, (Phi @ P0 @ Phi.T + Qd).real


@pytest.mark.parametrize("cls", FILTERS)
def test_stiff_stable_prediction_is_finite_and_exact(cls, dtype, device):
    """A stable linear system far stiffer than the step (``|A dt|`` up to 5e4, where
    ``exp(-A' dt)`` overflows in both dtypes), and a mild one: the prediction equals the
    eigenvector reference, with status 0 (rows of both in one batch: test_jacobians.py)."""
    A_mild = np.array([[-0.5, 1.0], [-1.0, -0.3]])
    A_stiff = np.array([[-1000.0, 30.0], [0.0, -200.0]])
    Qc = np.array([[0.3, 0.05], [0.05, 0.2]])
    x0 = np.array([[1.0, -2.0], [1.5, 0.5], [-0.7, 2.0]])
    P0 = np.array([[0.5, 0.1], [0.1, 0.4]])
    t = lambda a: torch.as_tensor(a, dtype=dtype, device=device)  # noqa: E731
    for A, dt in ((A_mild, 0.1), (A_stiff, 50.0), (A_stiff, 0.5)):
        dyn = LinearSystem(t(A), t(np.eye(2)))
        est = cls(dyn, GaussianSensor(std=0.1, state_dim=2).to(device, dtype), Q=t(Qc))
        P = t(P0).expand(3, 2, 2)
        out = est.predict(est.init(t(x0), P), t(np.zeros((3, 2))), dt)
        assert torch.equal(out.status.cpu(), torch.zeros(3, dtype=torch.int64))
        for b in range(3):
            m_ref, P_ref = _stiff_reference(A, Qc, P0, x0[b], dt)
            scale = 1e-9 if dtype == torch.float64 else 1e-4
            np.testing.assert_allclose(out.mean[b].double().cpu().numpy(), m_ref, atol=scale)
            np.testing.assert_allclose(
                out.cov[b].double().cpu().numpy(), P_ref, rtol=scale, atol=scale * 1e-3
            )
