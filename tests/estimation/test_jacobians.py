"""EKF/UKF on every model, including models whose f or g is constant in x (SingleIntegrator):
the autograd Jacobians against central finite differences, the one-step prediction against
the exact discretisation, and dtype/device mismatches named in the error."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from torchcbf.dynamics import (
    AccelUnicycle,
    Bicycle,
    DoubleIntegrator,
    FixedWing,
    Quadrotor,
    SingleIntegrator,
    Unicycle,
    VanDerPol,
)
from torchcbf.estimation import EKF, UKF, FunctionSensor, GaussianSensor, HybridEKFUKF
from torchcbf.estimation._linalg import discretize, jacobian, matrix_exp, pade_matrix_exp

MODELS = [
    SingleIntegrator(2),
    DoubleIntegrator(2),
    Unicycle(),
    AccelUnicycle(),
    Bicycle(),
    VanDerPol(),
    Quadrotor(),
    FixedWing(),
]
FILTERS = [EKF, UKF, HybridEKFUKF]


def _fd_jacobian(fn, x: torch.Tensor, eps: float = 1e-6) -> torch.Tensor:
    """Central differences, one column per state component: ``[B, k, n]``."""
    cols = []
    for j in range(x.shape[-1]):
        e = torch.zeros_like(x)
        e[:, j] = eps
        cols.append((fn(x + e) - fn(x - e)) / (2 * eps))
    return torch.stack(cols, -1)


@pytest.mark.parametrize("model", MODELS, ids=lambda m: type(m).__name__)
@pytest.mark.parametrize("create_graph", [False, True])
def test_dynamics_jacobian_matches_finite_differences(model, create_graph):
    gen = torch.Generator().manual_seed(0)
    n, m = model.state_dim, model.control_dim
    x = 0.3 * torch.randn(5, n, generator=gen, dtype=torch.float64)
    u = torch.randn(5, m, generator=gen, dtype=torch.float64)
    dyn = model.double()
    value, J = jacobian(lambda z: dyn(z, u), x, create_graph)
    assert torch.allclose(value, dyn(x, u), atol=1e-14)
    J_fd = _fd_jacobian(lambda z: dyn(z, u), x)
    assert J.shape == (5, n, n)
    assert torch.allclose(J, J_fd, atol=1e-7, rtol=1e-7)


def test_sensor_jacobian_constant_and_nonlinear():
    x = torch.randn(4, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(1))
    linear = GaussianSensor(C=torch.tensor([[1.0, 2.0, 0.0]], dtype=torch.float64), std=0.1)
    _, H = jacobian(linear.expected, x, False)
    assert torch.equal(H, linear.C.expand(4, 1, 3))
    constant = FunctionSensor(lambda z: torch.ones_like(z[..., :2]), std=[0.1, 0.1])
    _, H0 = jacobian(constant.expected, x, False)
    assert torch.equal(H0, torch.zeros(4, 2, 3, dtype=torch.float64))
    polar = FunctionSensor(lambda z: torch.stack([z[..., 0] * z[..., 1], z[..., 2] ** 3], -1),
                           std=[0.1, 0.1])  # fmt: skip
    _, Hp = jacobian(polar.expected, x, False)
    assert torch.allclose(Hp, _fd_jacobian(polar.expected, x), atol=1e-8)


@pytest.mark.parametrize("cls", FILTERS)
def test_single_integrator_prediction_is_exact(cls, dtype):
    """xdot = u (f = 0, g = I, constant in x): the prediction is m + dt u, P + dt Q."""
    n, dt, q = 2, 0.1, 0.01
    est = cls(SingleIntegrator(n), GaussianSensor(std=0.1, state_dim=n), Q=q).to(dtype)
    P0 = 0.1 * torch.eye(n, dtype=dtype)
    u = torch.tensor([[1.0, -2.0], [0.0, 0.5], [3.0, 0.0]], dtype=dtype)
    state = est.predict(est.init(torch.zeros(3, n, dtype=dtype), P0), u, dt)
    tol = 1e-12 if dtype == torch.float64 else 1e-6
    assert torch.allclose(state.mean, dt * u, atol=tol)
    expected = (0.1 + dt * q) * torch.eye(n, dtype=dtype).expand(3, n, n)
    assert torch.allclose(state.cov, expected, atol=tol)
    assert bool((state.status == 0).all())
    # and the update runs (H = C, constant)
    y = torch.zeros(3, n, dtype=dtype)
    upd = est.update(state, y)
    assert torch.isfinite(upd.mean).all() and bool((upd.status == 0).all())


@pytest.mark.parametrize("cls", [EKF, UKF])
@pytest.mark.parametrize("model", MODELS[:6], ids=lambda m: type(m).__name__)
def test_ekf_ukf_run_on_every_model(cls, model):
    n = model.state_dim
    dyn = model.double()
    est = cls(dyn, GaussianSensor(std=0.1, state_dim=n), Q=0.01).double()
    gen = torch.Generator().manual_seed(2)
    x0 = 0.2 * torch.randn(4, n, generator=gen, dtype=torch.float64)
    u = 0.1 * torch.randn(4, model.control_dim, generator=gen, dtype=torch.float64)
    state = est.init(x0, 0.1 * torch.eye(n, dtype=torch.float64))
    state = est.step(state, u, 0.05, x0)
    assert torch.isfinite(state.mean).all() and torch.isfinite(state.cov).all()
    assert bool((state.status == 0).all())


def test_ekf_prediction_matches_finite_difference_linearisation():
    """EKF covariance prediction = Phi P Phi' + Qd with Phi = exp(F dt), F by central
    differences and Qd by a fine quadrature of exp(F s) Q exp(F s)'."""
    dyn = VanDerPol(mu=1.5).double()
    dt, q = 0.05, 0.02
    est = EKF(dyn, GaussianSensor(std=0.1, state_dim=2), Q=q).double()
    x = torch.tensor([[0.3, -0.4], [1.0, 0.2]], dtype=torch.float64)
    u = torch.tensor([[0.1], [-0.3]], dtype=torch.float64)
    P = torch.tensor([[0.2, 0.05], [0.05, 0.1]], dtype=torch.float64).expand(2, 2, 2)
    out = est.predict(est.init(x, P), u, dt)
    F = _fd_jacobian(lambda z: dyn(z, u), x)
    Phi = torch.linalg.matrix_exp(F * dt)
    s = torch.linspace(0, dt, 2001, dtype=torch.float64)
    E = torch.linalg.matrix_exp(F[:, None] * s[None, :, None, None])  # [B, S, 2, 2]
    integrand = q * E @ E.mT
    Qd = torch.trapezoid(integrand, s, dim=1)
    expected = Phi @ P @ Phi.mT + Qd
    assert torch.allclose(out.cov, expected, atol=1e-9)


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32], ids=["f64", "f32"])
def test_the_accelerators_matrix_exponential_equals_torchs(dtype):
    """The Pade path of ``matrix_exp`` (the one off the CPU), run here, against
    ``torch.linalg.matrix_exp`` in float64: 1-norms from 1e-6 to 300 (up to 8 squarings),
    to rounding times the norm; a row of NaN stays NaN without touching the others; and
    its gradient equals torch's."""
    gen = torch.Generator().manual_seed(0)
    scales = torch.logspace(-6, 2.5, 12, dtype=torch.float64)
    A = torch.randn(12, 9, 9, generator=gen, dtype=torch.float64) * scales[:, None, None] / 9
    ref = torch.linalg.matrix_exp(A)
    got = pade_matrix_exp(A.to(dtype)).double()
    norm = A.abs().sum(-2).amax(-1)
    err = (got - ref).abs().amax((-2, -1)) / ref.abs().amax((-2, -1))
    unit = 1e-15 if dtype == torch.float64 else 1e-6
    assert bool((err <= 10 * unit * norm.clamp_min(1.0)).all()), (err, norm)
    bad = A.clone()
    bad[3, 1, 2] = torch.nan
    out = pade_matrix_exp(bad)
    assert bool(out[3].isnan().all()) and torch.equal(out[4], pade_matrix_exp(A)[4])
    x = (A[:4] / 4).requires_grad_()
    w = torch.randn(4, 9, 9, generator=gen, dtype=torch.float64)
    (mine,) = torch.autograd.grad((pade_matrix_exp(x) * w).sum(), x)
    (theirs,) = torch.autograd.grad((torch.linalg.matrix_exp(x) * w).sum(), x)
    torch.testing.assert_close(mine, theirs, atol=1e-12, rtol=1e-10)
    assert torch.equal(matrix_exp(A), ref)  # the CPU keeps torch's


@pytest.mark.parametrize("cls", FILTERS)
def test_control_dtype_mismatch_names_both(cls):
    est = cls(SingleIntegrator(2), GaussianSensor(std=0.1, state_dim=2), Q=0.01).double()
    state = est.init(torch.zeros(3, 2, dtype=torch.float64), torch.eye(2, dtype=torch.float64))
    with pytest.raises(TypeError, match=r"u has dtype torch.float32 .*state.mean.*float64"):
        est.predict(state, torch.zeros(3, 2), 0.1)
    with pytest.raises(TypeError, match=r"y has dtype torch.float32"):
        est.update(state, torch.zeros(3, 2))
    with pytest.raises(TypeError, match=r"P0 has dtype torch.float32"):
        est.init(torch.zeros(3, 2, dtype=torch.float64), torch.eye(2))
    with pytest.raises(ValueError, match=r"u is on device meta but state.mean is on device cpu"):
        est.predict(state, torch.zeros(3, 2, dtype=torch.float64, device="meta"), 0.1)


@pytest.mark.parametrize("cls", [EKF, UKF])
def test_prediction_is_differentiable_in_u_for_a_model_constant_in_x(cls):
    """xdot = u: the mean moves by dt u, so d(mean)/du = dt I, even though F = 0."""
    dt = 0.1
    est = cls(SingleIntegrator(2), GaussianSensor(std=0.1, state_dim=2), Q=0.01).double()
    u = torch.tensor([[1.0, -2.0]], dtype=torch.float64, requires_grad=True)
    state = est.init(torch.zeros(1, 2, dtype=torch.float64), torch.eye(2, dtype=torch.float64))
    out = est.predict(state, u, dt)
    (grad,) = torch.autograd.grad(out.mean[0, 0], u)
    assert torch.allclose(grad, torch.tensor([[dt, 0.0]], dtype=torch.float64))


@pytest.mark.parametrize("cls", [EKF, UKF, HybridEKFUKF], ids=lambda c: c.__name__)
def test_a_tensor_held_by_a_users_function_gets_its_gradient(cls):
    # a learned sensor gain and a learned drift held in closures (not module parameters)
    gain = torch.tensor(1.5, dtype=torch.float64, requires_grad=True)
    drift = torch.tensor([0.3, -0.2], dtype=torch.float64, requires_grad=True)

    def run(g, d):
        class Drifting(SingleIntegrator):
            def f(self, x):
                return d.expand_as(x) * torch.cos(x)

        sensor = FunctionSensor(lambda x: g * torch.sin(x), std=0.1, output_dim=2)
        est = cls(Drifting(2), sensor, Q=0.01).double()
        m0 = torch.tensor([[0.2, -0.1], [0.4, 0.3]], dtype=torch.float64)
        state = est.predict(est.init(m0, torch.eye(2, dtype=torch.float64)), m0 * 0, 0.1)
        y = torch.tensor([[1.0, 0.5], [0.2, -0.3]], dtype=torch.float64)
        new = est.update(state, y)
        return new.mean.sum() + new.cov.sum()

    assert torch.autograd.gradcheck(run, (gain, drift), eps=1e-6, atol=1e-7)


def _eigen_discretization(A, xdot, Qc, h):
    """``Phi``, ``dx`` and ``Qd`` of a diagonalisable ``A`` by its eigenvectors, float64."""
    lam, V = np.linalg.eig(A)
    Vi = np.linalg.inv(V)
    Phi = (V * np.exp(lam * h)) @ Vi
    dx = V @ ((np.expm1(lam * h) / lam) * (Vi @ xdot))
    W = Vi @ Qc @ Vi.T
    s = lam[:, None] + lam[None, :]
    Qd = V @ (W * np.expm1(s * h) / s) @ V.T
    return Phi.real, dx.real, Qd.real


@pytest.mark.parametrize("pade", [False, True], ids=["cpu_way", "accelerator_way"])
def test_discretize_mild_and_stiff_rows_of_one_batch(dtype, pade):
    """Rows of one batch from a mild ``F h`` to ``|F h| = 5e4`` (where ``exp(-F' h)``
    overflows in both dtypes): each row's ``Phi``, ``dx`` and ``Qd`` equal the eigenvector
    reference, by either way (the CPU's and the accelerator's, run here); gradients to
    ``F`` pass gradcheck through the doublings."""
    As = [
        np.array([[-0.5, 1.0], [-1.0, -0.3]]),
        np.array([[-1000.0, 30.0], [0.0, -200.0]]),
        np.array([[-40.0, 0.0], [5.0, -3.0]]),
    ]
    hs = 0.2
    xdot = np.array([1.0, -2.0])
    Qc = np.array([[0.3, 0.05], [0.05, 0.2]])
    scales = [1.0, 50.0, 1.0]  # row 1: |F h| = 1e4 after scaling
    F = torch.tensor(np.stack([a * c for a, c in zip(As, scales, strict=True)]), dtype=dtype)
    xd = torch.tensor(xdot, dtype=dtype).expand(3, 2)
    Q = torch.tensor(Qc, dtype=dtype).expand(3, 2, 2)
    Phi, dx, Qd = discretize(F, hs, xd, Q, pade=pade)
    tol = 1e-9 if dtype == torch.float64 else 2e-4
    for b in range(3):
        ref = _eigen_discretization(As[b] * scales[b], xdot, Qc, hs)
        for got, want in zip((Phi[b], dx[b], Qd[b]), ref, strict=True):
            np.testing.assert_allclose(got.double().numpy(), want, atol=tol, rtol=tol)
    if dtype == torch.float64:
        small = (torch.tensor(np.stack(As[1:]), dtype=dtype) / 50.0).requires_grad_()
        fn = lambda f: discretize(f * 50.0, hs, xd[:2], Q[:2], pade=pade)  # noqa: E731
        assert torch.autograd.gradcheck(fn, (small,), eps=1e-7, atol=1e-6, rtol=1e-5)
