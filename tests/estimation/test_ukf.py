"""UKF: Monte Carlo consistency, angle-aware unscented update, sigma-point parameters.

(Equality with the exact Kalman filter on linear systems is in test_ekf.py, for all filters.)
"""

from __future__ import annotations

import math

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

from torchcbf.dynamics import DoubleIntegrator, Unicycle
from torchcbf.estimation import (
    EKF,
    UKF,
    EstimatorState,
    EstimatorStatus,
    GaussianSensor,
    RangeBearing,
)


@pytest.mark.parametrize("model", ["unicycle", "accel_unicycle"])
def test_ukf_monte_carlo_consistent_and_beats_sensor(model, dtype):
    assert_monte_carlo_consistent(UKF, dtype, model)


@pytest.mark.parametrize("alpha,kappa", [(1e-3, 0.0), (0.5, 1.0), (1.0, 3.0 - 3.0)])
def test_sigma_point_parameters_keep_linear_exactness(alpha, kappa):
    """Any admissible (alpha, beta, kappa) is exact on a linear system (float64)."""
    case = linear_case(rows=3, steps=10)
    t = lambda a: torch.as_tensor(a, dtype=torch.float64)  # noqa: E731
    dyn = LinearSystem(t(case["A"]), t(case["Bu"]))
    sensor = GaussianSensor(C=t(case["C"]), R=t(case["R"]))
    ukf = UKF(dyn, sensor, Q=t(case["Qc"]), alpha=alpha, beta=2.0, kappa=kappa)
    means, covs, _ = run_filter(
        ukf, t(case["x0"]), t(case["P0"]), t(case["us"]), t(case["ys"]), case["dt"]
    )
    ref_m, ref_p = exact_kalman(
        case["A"], case["Bu"], case["Qc"], case["C"], case["R"], case["x0"][1], case["P0"][1],
        case["us"][:, 1], case["ys"][:, 1], case["dt"],
    )  # fmt: skip
    # tiny alpha weights the points by 1/alpha^2: cancellation costs ~2*log10(1/alpha) digits
    tol = 1e-5 if alpha < 1e-2 else 1e-9
    assert np.abs(means[:, 1].numpy() - ref_m).max() < tol
    assert np.abs(covs[:, 1].numpy() - ref_p).max() < tol


def test_sigma_point_parameters_set_later_are_used():
    """alpha, beta and kappa set on a built UKF predict as a UKF built with them; a value
    that leaves alpha^2 (n + kappa) <= 0 is refused at the step."""
    dyn = Unicycle(sigma=0.1).double()
    sensor = GaussianSensor(C=torch.eye(3, dtype=torch.float64), std=0.1)
    state = EstimatorState(
        torch.tensor([[0.1, -0.2, 0.3]], dtype=torch.float64),
        torch.diag(torch.tensor([0.2, 0.1, 0.3], dtype=torch.float64)).unsqueeze(0),
        torch.zeros(1, dtype=torch.long),
    )
    u = torch.tensor([[1.0, 0.5]], dtype=torch.float64)
    edited = UKF(dyn, sensor, Q=0.01)
    edited.alpha, edited.beta, edited.kappa = 0.5, 0.0, 1.0
    fresh = UKF(dyn, sensor, Q=0.01, alpha=0.5, beta=0.0, kappa=1.0)
    a, b = edited.predict(state, u, 0.5), fresh.predict(state, u, 0.5)
    torch.testing.assert_close(a.mean, b.mean, rtol=0, atol=0)
    torch.testing.assert_close(a.cov, b.cov, rtol=0, atol=0)
    assert (a.cov - UKF(dyn, sensor, Q=0.01).predict(state, u, 0.5).cov).abs().max() > 1e-3
    edited.kappa = -3.0
    with pytest.raises(ValueError, match="kappa"):
        edited.predict(state, u, 0.5)


def test_bearing_wrap_in_unscented_update(dtype):
    """A landmark straight behind the robot: the predicted bearings straddle +-pi. With the
    residual wrapping the UKF update agrees with the EKF (nearly linear for a small P);
    a naive average of the bearings would put the mean near 0 and throw the estimate off."""
    dyn = Unicycle(sigma=0.01)
    sensor = RangeBearing(torch.tensor([[-5.0, 0.0], [0.0, 5.0]], dtype=dtype), 0.05, 0.01)
    mean = torch.tensor([[0.0, 0.0, 0.0], [0.0, 0.0, 0.002]], dtype=dtype)
    P = torch.diag(torch.tensor([1e-3, 1e-3, 1e-3], dtype=dtype)).expand(2, 3, 3)
    state = EstimatorState(mean, P, torch.zeros(2, dtype=torch.long))
    x_true = torch.tensor([0.01, -0.01, 0.003], dtype=dtype)
    y = sensor.expected(x_true).expand(2, 4)
    assert bool((y[:, 1].abs() > 3.1).all())  # bearing near +-pi
    ekf_state = EKF(dyn, sensor).update(state, y)
    ukf_state = UKF(dyn, sensor).update(state, y)
    assert torch.allclose(ukf_state.mean, ekf_state.mean, atol=2e-3)
    assert float((ukf_state.mean - x_true).abs().max()) < 0.02
    assert torch.allclose(ukf_state.cov, ekf_state.cov, rtol=0.05, atol=1e-6)


def test_invalid_sigma_parameters():
    dyn = Unicycle(sigma=0.1)
    sensor = GaussianSensor(C=torch.eye(3)[:2], std=0.1)
    with pytest.raises(ValueError, match="kappa"):
        UKF(dyn, sensor, kappa=-3.0)
    with pytest.raises(ValueError, match="alpha"):
        UKF(dyn, sensor, alpha=0.0)
    with pytest.raises(ValueError, match="alpha"):
        UKF(dyn, sensor, alpha=math.inf)


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32], ids=["float64", "float32"])
def test_a_precise_measurement_of_a_wide_prior_leaves_a_positive_variance(dtype):
    """The update's covariance is a sum of positive semidefinite terms (Joseph form): a
    measurement far more precise than the prior gives the Kalman variance P R / (P + R)
    where the dtype can hold the ratio, and never a covariance that is not positive
    definite without the REGULARIZED flag (P - K S K' gave negative variances, status OK)."""
    exact_up_to = 1e12 if dtype == torch.float64 else 1e6
    tol = 1e-9 if dtype == torch.float64 else 1e-3
    for P0 in (1e2, 1e4, 1e6, 1e8, 1e10):
        for std in (1e-2, 1e-3, 1e-4, 1e-6, 1e-8):
            C = torch.tensor([[1.0, 0.0]], dtype=torch.float64)
            ukf = UKF(DoubleIntegrator(1), GaussianSensor(C=C, std=std), Q=1e-2).to(dtype)
            state = ukf.init(torch.zeros(1, 2, dtype=dtype), P0 * torch.eye(2, dtype=dtype))
            out = ukf.update(state, torch.full((1, 1), 0.5, dtype=dtype))
            R = std**2
            if P0 / R <= exact_up_to:
                exact = P0 * R / (P0 + R)
                assert float(out.cov[0, 0, 0]) == pytest.approx(exact, rel=tol), (P0, std)
            positive = bool((torch.linalg.eigvalsh(out.cov.double()) > 0).all())
            assert positive or int(out.status) & EstimatorStatus.REGULARIZED, (P0, std)


def test_the_update_of_a_nonlinear_sensor_is_the_textbook_unscented_update():
    """The Joseph-form update equals P - K S K' of the textbook unscented update (sigma
    points x +- sqrt(n + lam) L_i, weights lam/(n+lam) + 1 - alpha^2 + beta and
    1/(2(n+lam))), written here as a loop, for a range sensor (float64)."""
    from torchcbf.estimation import FunctionSensor

    f64 = torch.float64
    sensor = FunctionSensor(lambda x: x[..., :2].norm(dim=-1, keepdim=True), std=0.05,
                            output_dim=1)  # fmt: skip
    ukf = UKF(Unicycle(sigma=0.1), sensor, Q=0.01).double()
    m = torch.tensor([1.0, 0.5, 0.3], dtype=f64)
    P = torch.tensor([[0.3, 0.05, 0.0], [0.05, 0.2, 0.02], [0.0, 0.02, 0.1]], dtype=f64)
    y = torch.tensor([1.3], dtype=f64)
    out = ukf.update(EstimatorState(m[None], P[None], torch.zeros(1, dtype=torch.long)), y[None])
    n, lam = 3, 0.0  # alpha = 1, kappa = 0
    L = torch.linalg.cholesky(P)
    points = [m] + [m + math.sqrt(n + lam) * L[:, i] for i in range(n)]
    points += [m - math.sqrt(n + lam) * L[:, i] for i in range(n)]
    wm = [lam / (n + lam)] + [0.5 / (n + lam)] * (2 * n)
    wc = [lam / (n + lam) + 1 - 1 + 2.0] + [0.5 / (n + lam)] * (2 * n)
    ys = [p[:2].norm().reshape(1) for p in points]
    y_bar = sum(w * v for w, v in zip(wm, ys, strict=True))
    S = sum(w * torch.outer(v - y_bar, v - y_bar) for w, v in zip(wc, ys, strict=True))
    S = S + 0.05**2 * torch.eye(1, dtype=f64)
    Pxy = sum(w * torch.outer(p - m, v - y_bar) for w, p, v in zip(wc, points, ys, strict=True))
    K = Pxy @ torch.linalg.inv(S)
    torch.testing.assert_close(out.mean[0], m + K @ (y - y_bar), atol=1e-12, rtol=1e-12)
    torch.testing.assert_close(out.cov[0], P - K @ S @ K.T, atol=1e-12, rtol=1e-12)


def test_a_clamped_negative_centre_weight_is_flagged():
    """``beta + 1 - alpha^2 < 0``: the linearisation errors' ``D`` is indefinite and clamped,
    a covariance above the textbook one, flagged ``REGULARIZED``; a linear sensor has
    ``D = 0`` and stays unflagged."""
    from torchcbf.estimation import EstimatorStatus, FunctionSensor, GaussianSensor

    f64 = torch.float64

    def h(x):
        return torch.stack([x[..., 0] ** 2 + x[..., 1], torch.sin(x[..., 2]) * x[..., 0]], -1)

    m = torch.tensor([[0.3, -1.1, 0.8]], dtype=f64)
    P = torch.tensor([[0.4, 0.1, 0.0], [0.1, 0.3, 0.05], [0.0, 0.05, 0.2]], dtype=f64)[None]
    state = EstimatorState(m, P, torch.zeros(1, dtype=torch.long))
    y = torch.tensor([[-0.5, 0.4]], dtype=f64)
    plain = UKF(Unicycle(), FunctionSensor(h, std=0.2, output_dim=2), Q=0.01).double()
    wide = UKF(Unicycle(), FunctionSensor(h, std=0.2, output_dim=2), Q=0.01, beta=-2.5).double()
    assert int(plain.update(state, y).status) == 0
    out = wide.update(state, y)
    assert int(out.status) & int(EstimatorStatus.REGULARIZED)
    C = torch.randn(2, 3, generator=torch.Generator().manual_seed(0), dtype=f64)
    linear = UKF(Unicycle(), GaussianSensor(C, 0.2), Q=0.01, beta=-2.5).double()
    rows = EstimatorState(
        torch.randn(500, 3, generator=torch.Generator().manual_seed(1), dtype=f64),
        P.expand(500, 3, 3),
        torch.zeros(500, dtype=torch.long),
    )
    for dtype in (f64, torch.float32):
        cast = EstimatorState(rows.mean.to(dtype), rows.cov.to(dtype), rows.status)
        out = linear.to(dtype).update(cast, y.to(dtype))
        assert not bool(out.status.any())  # D is rounding alone: nothing clamped
