"""Independent references for the estimation tests: an exact linear Kalman filter in NumPy/SciPy
(Van Loan discretization written from scratch), a linear ControlAffine model, a Monte Carlo
truth simulator and NEES statistics."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import torch
from scipy.linalg import expm
from scipy.stats import chi2
from torch import Tensor

from torchcbf.dynamics.base import ControlAffine
from torchcbf.integrators import euler_maruyama


class LinearSystem(ControlAffine):
    """``xdot = A x + B u`` (optionally with a constant diffusion ``sigma``)."""

    def __init__(self, A: Tensor, B: Tensor, **kwargs) -> None:
        super().__init__(A.shape[0], B.shape[1], **kwargs)
        self.register_buffer("A", A)
        self.register_buffer("B", B)

    def f(self, x: Tensor) -> Tensor:
        return x @ self.A.to(x).mT

    def g(self, x: Tensor) -> Tensor:
        return self.B.to(x).expand(*x.shape[:-1], *self.B.shape)


def exact_kalman(
    A: np.ndarray,
    Bu: np.ndarray,
    Qc: np.ndarray,
    C: np.ndarray,
    R: np.ndarray,
    x0: np.ndarray,
    P0: np.ndarray,
    us: np.ndarray,
    ys: np.ndarray,
    dt: float,
) -> tuple[np.ndarray, np.ndarray]:
    """Kalman filter of the sampled linear SDE, one scenario, float64.

    ``Phi = expm(A dt)``; ``Gamma = int_0^dt expm(A s) ds Bu`` from ``expm([[A, Bu], [0, 0]] dt)``;
    ``Qd = Phi (top-right of expm([[-A, Qc], [0, A^T]] dt))`` (Van Loan, 1978).
    ``us [T, m]``, ``ys [T, p]``; returns the posterior means ``[T, n]`` and covariances.
    """
    n, m = Bu.shape
    aug = np.zeros((n + m, n + m))
    aug[:n, :n], aug[:n, n:] = A, Bu
    E = expm(aug * dt)
    Phi, Gamma = E[:n, :n], E[:n, n:]
    vl = np.zeros((2 * n, 2 * n))
    vl[:n, :n], vl[:n, n:], vl[n:, n:] = -A, Qc, A.T
    V = expm(vl * dt)
    Qd = V[n:, n:].T @ V[:n, n:]
    x, P = x0.copy(), P0.copy()
    means, covs = [], []
    for u, y in zip(us, ys, strict=True):
        x = Phi @ x + Gamma @ u
        P = Phi @ P @ Phi.T + Qd
        S = C @ P @ C.T + R
        K = P @ C.T @ np.linalg.inv(S)
        x = x + K @ (y - C @ x)
        P = (np.eye(n) - K @ C) @ P
        P = 0.5 * (P + P.T)
        means.append(x)
        covs.append(P)
    return np.stack(means), np.stack(covs)


def simulate_truth(
    dynamics: ControlAffine,
    x0: Tensor,
    control: Callable[[int], Tensor],
    dt: float,
    steps: int,
    substeps: int,
    generator: torch.Generator,
) -> Tensor:
    """Euler-Maruyama truth sampled every ``dt`` (``substeps`` EM steps each): ``[steps, B, n]``."""
    x, out = x0, []
    for k in range(steps):
        u = control(k)
        for _ in range(substeps):
            x = euler_maruyama(dynamics, x, u, dt / substeps, generator=generator)
        out.append(x)
    return torch.stack(out)


def nees(err: Tensor, cov: Tensor) -> Tensor:
    """``e^T P^-1 e`` for ``err [..., n]`` and ``cov [..., n, n]``."""
    return (err * torch.linalg.solve(cov, err.unsqueeze(-1)).squeeze(-1)).sum(-1)


def chi2_band(n: int, runs: int, level: float = 0.95) -> tuple[float, float]:
    """Two-sided band of the NEES averaged over ``runs`` independent runs of dimension ``n``."""
    lo, hi = chi2.ppf([(1 - level) / 2, (1 + level) / 2], df=n * runs)
    return float(lo) / runs, float(hi) / runs


# -- shared scenarios -------------------------------------------------------------------------


def linear_case(seed: int = 0, rows: int = 4, steps: int = 15) -> dict:
    """A 3-state linear system (oscillator + lag, non-nilpotent A), a 2-output sensor with
    correlated noise, per-row priors, and arbitrary controls and measurements (the Kalman
    recursion is defined for any measurement sequence)."""
    rng = np.random.default_rng(seed)
    A = np.array([[0.0, 1.0, 0.0], [-2.0, -0.3, 1.0], [0.0, 0.0, -0.5]])
    Bu = np.array([[0.0, 0.0], [1.0, 0.0], [0.2, 1.0]])
    Qc = np.array([[0.02, 0.005, 0.0], [0.005, 0.05, 0.01], [0.0, 0.01, 0.03]])
    C = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    R = np.array([[0.05, 0.01], [0.01, 0.08]])
    x0 = rng.normal(size=(rows, 3))
    G = rng.normal(size=(rows, 3, 3))
    P0 = G @ G.transpose(0, 2, 1) * 0.3 + 0.1 * np.eye(3)
    us = rng.normal(size=(steps, rows, 2))
    ys = rng.normal(size=(steps, rows, 2))
    return dict(A=A, Bu=Bu, Qc=Qc, C=C, R=R, x0=x0, P0=P0, us=us, ys=ys, dt=0.1)


def run_filter(estimator, x0: Tensor, P0: Tensor, us: Tensor, ys: Tensor, dt: float):
    """Run predict/update over ``us [T, B, m]``, ``ys [T, B, p]``: means ``[T, B, n]``, covs."""
    state = estimator.init(x0, P0)
    means, covs = [], []
    for u, y in zip(us, ys, strict=True):
        state = estimator.step(state, u, dt, y)
        means.append(state.mean)
        covs.append(state.cov)
    return torch.stack(means), torch.stack(covs), state


def monte_carlo(cls, dtype: torch.dtype, model: str, runs: int = 500, steps: int = 40) -> dict:
    """``runs`` Monte Carlo scenarios in one batch: the truth by Euler-Maruyama (10 substeps
    per filter step), the filter's Q equal to the true diffusion ``sigma sigma^T`` (default
    from the dynamics), the prior drawn from ``N(x0_hat, P0)``.

    ``model``: ``"unicycle"`` (position sensor, std 0.2) or ``"accel_unicycle"``
    (range-bearing to 4 landmarks). Returns the per-step NEES averaged over the runs
    ``[steps]``, the RMS position error of the estimate and of the raw position measurement
    (unicycle) and the status of the last step.
    """
    from torchcbf.dynamics import AccelUnicycle, Unicycle
    from torchcbf.estimation import GaussianSensor, RangeBearing

    gen = torch.Generator().manual_seed(2024)
    dt = 0.1
    if model == "unicycle":
        dyn = Unicycle(sigma=torch.tensor([0.05, 0.05, 0.03], dtype=dtype))
        C = torch.tensor([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]], dtype=dtype)
        sensor = GaussianSensor(C=C, std=torch.tensor(0.2, dtype=dtype))
        x0_hat = torch.tensor([0.0, 0.0, 0.3], dtype=dtype)
        P0 = torch.diag(torch.tensor([0.2, 0.2, 0.1], dtype=dtype) ** 2)

        def control(k: int) -> Tensor:
            return torch.tensor([1.0, 0.4 * np.sin(0.2 * k)], dtype=dtype).expand(runs, 2)

    elif model == "accel_unicycle":
        dyn = AccelUnicycle(sigma=torch.tensor([0.02, 0.02, 0.05, 0.03], dtype=dtype))
        landmarks = torch.tensor([[6.0, 5.0], [-4.0, 6.0], [1.0, -5.0], [9.0, -2.0]], dtype=dtype)
        sensor = RangeBearing(landmarks, 0.1, 0.02, heading_index=3).to(dtype)
        x0_hat = torch.tensor([0.0, 0.0, 0.8, 0.2], dtype=dtype)
        P0 = torch.diag(torch.tensor([0.2, 0.2, 0.1, 0.1], dtype=dtype) ** 2)

        def control(k: int) -> Tensor:
            return torch.tensor([0.2 * np.cos(0.15 * k), 0.3], dtype=dtype).expand(runs, 2)

    else:
        raise ValueError(model)
    est = cls(dyn, sensor)
    n = dyn.state_dim
    z = torch.randn(runs, n, generator=gen, dtype=dtype)
    x_true0 = x0_hat + z @ torch.linalg.cholesky(P0).mT
    truth = simulate_truth(dyn, x_true0, control, dt, steps, 10, gen)
    state = est.init(x0_hat.expand(runs, n), P0)
    nees_t, est_err, meas_err = [], [], []
    for k in range(steps):
        y = sensor.measure(truth[k], gen)
        state = est.step(state, control(k), dt, y)
        e = truth[k] - state.mean
        nees_t.append(nees(e, state.cov).mean())
        est_err.append((e[:, :2] ** 2).sum(-1).mean())
        if model == "unicycle":
            meas_err.append(((y - truth[k, :, :2]) ** 2).sum(-1).mean())
    out = {
        "nees": torch.stack(nees_t).double(),
        "rms_est": float(torch.stack(est_err).mean().sqrt()),
        "status": state.status,
        "n": n,
        "runs": runs,
    }
    if meas_err:
        out["rms_meas"] = float(torch.stack(meas_err).mean().sqrt())
    return out


def check_consistency(result: dict) -> tuple[float, float, float, float]:
    """NEES checks shared by the filter tests: returns (time-mean NEES, band lo, band hi,
    fraction of steps whose run-averaged NEES lies in the 95% band)."""
    lo, hi = chi2_band(result["n"], result["runs"])
    nees_t = result["nees"]
    inside = float(((nees_t >= lo) & (nees_t <= hi)).double().mean())
    return float(nees_t.mean()), lo, hi, inside


def assert_monte_carlo_consistent(cls, dtype: torch.dtype, model: str) -> None:
    """500 runs of ``cls`` in one batch: run-averaged NEES inside its 95% chi-square band,
    every update fine, and the estimate beats the raw sensor (unicycle) or is within 0.1 m
    (accel_unicycle, range-bearing with range noise 0.1 m)."""
    result = monte_carlo(cls, dtype, model)
    mean_nees, lo, hi, inside = check_consistency(result)
    assert lo <= mean_nees <= hi, (mean_nees, lo, hi)
    assert inside >= 0.8, inside  # expected 0.95; steps are correlated in time
    assert bool((result["status"] == 0).all())
    if model == "unicycle":
        assert result["rms_est"] < 0.5 * result["rms_meas"], result
    else:
        assert result["rms_est"] < 0.1, result
