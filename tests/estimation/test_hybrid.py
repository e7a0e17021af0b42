"""Hybrid EKF-UKF: own filter states, covariance-intersection fusion, Monte Carlo consistency."""

from __future__ import annotations

import torch
from estimation_reference import check_consistency, monte_carlo, run_filter

from torchcbf.dynamics import AccelUnicycle
from torchcbf.estimation import EKF, UKF, EstimatorState, HybridEKFUKF, HybridState, RangeBearing


def _setup(dtype):
    dyn = AccelUnicycle(sigma=torch.tensor([0.05, 0.05, 0.2, 0.2], dtype=dtype))
    lm = torch.tensor([[3.0, 2.0], [-2.0, 3.0]], dtype=dtype)
    sensor = RangeBearing(lm, 0.3, 0.1, heading_index=3)
    gen = torch.Generator().manual_seed(5)
    B, T = 6, 12
    x0 = torch.randn(B, 4, generator=gen, dtype=dtype) * 0.3
    P0 = torch.eye(4, dtype=dtype) * 0.5
    us = torch.randn(T, B, 2, generator=gen, dtype=dtype)
    ys = sensor.expected(torch.randn(T, B, 4, generator=gen, dtype=dtype) * 0.3)
    return dyn, sensor, x0, P0, us, ys


def test_hybrid_keeps_each_filters_own_state(dtype):
    dyn, sensor, x0, P0, us, ys = _setup(dtype)
    _, _, hstate = run_filter(HybridEKFUKF(dyn, sensor), x0, P0, us, ys, 0.1)
    _, _, estate = run_filter(EKF(dyn, sensor), x0, P0, us, ys, 0.1)
    _, _, ustate = run_filter(UKF(dyn, sensor), x0, P0, us, ys, 0.1)
    assert isinstance(hstate, HybridState)
    atol = 1e-12 if dtype == torch.float64 else 1e-5
    for own, ref in ((hstate.ekf, estate), (hstate.ukf, ustate)):
        assert torch.allclose(own.mean, ref.mean, atol=atol)
        assert torch.allclose(own.cov, ref.cov, atol=atol)
    # a large initial uncertainty makes the two filters differ noticeably
    assert float((estate.mean - ustate.mean).abs().max()) > 1e-4


def test_covariance_intersection_fusion(dtype):
    """Fused P^-1 = w Pe^-1 + (1-w) Pu^-1 with w in [0, 1] minimising det P over the grid
    (checked against a fine independent scan), and m = P (w Pe^-1 me + (1-w) Pu^-1 mu)."""
    dyn, sensor, x0, P0, us, ys = _setup(torch.float64)
    h = HybridEKFUKF(dyn, sensor, ci_points=33)
    gen = torch.Generator().manual_seed(1)
    B, n = 8, 4
    G1, G2 = (torch.randn(B, n, n, generator=gen, dtype=torch.float64) for _ in range(2))
    Pe = G1 @ G1.mT + 0.1 * torch.eye(n, dtype=torch.float64)
    Pu = G2 @ G2.mT + 0.1 * torch.eye(n, dtype=torch.float64)
    me, mu = (torch.randn(B, n, generator=gen, dtype=torch.float64) for _ in range(2))
    zero = torch.zeros(B, dtype=torch.long)
    cast = lambda a: a.to(dtype)  # noqa: E731
    out = h.to(dtype)._fuse(
        EstimatorState(cast(me), cast(Pe), zero), EstimatorState(cast(mu), cast(Pu), zero)
    )
    Ie, Iu = torch.linalg.inv(Pe), torch.linalg.inv(Pu)
    ws = torch.linspace(0, 1, 2001, dtype=torch.float64)
    dets = torch.stack([torch.linalg.det(torch.linalg.inv(w * Ie + (1 - w) * Iu)) for w in ws])
    best_det = dets.min(0).values
    fused_det = torch.linalg.det(out.cov.double())
    # the 33-point grid is within a few percent of the continuous optimum
    rel = 1e-6 if dtype == torch.float64 else 1e-3
    assert bool((fused_det >= best_det * (1 - rel)).all())
    assert bool((fused_det <= best_det * 1.05).all())
    min_det = torch.minimum(torch.linalg.det(Pe), torch.linalg.det(Pu))
    assert bool((fused_det <= min_det * (1 + rel)).all())
    # recover w from the information matrix and check the mean formula
    info = torch.linalg.inv(out.cov.double())
    w = ((info - Iu) * (Ie - Iu)).sum((-2, -1)) / ((Ie - Iu) ** 2).sum((-2, -1))
    assert bool(((w >= -rel) & (w <= 1 + rel)).all())
    tol = 1e-8 if dtype == torch.float64 else 2e-3
    assert torch.allclose(info, w[:, None, None] * Ie + (1 - w[:, None, None]) * Iu, atol=tol)
    rhs = w[:, None] * (Ie @ me.unsqueeze(-1)).squeeze(-1)
    rhs = rhs + (1 - w[:, None]) * (Iu @ mu.unsqueeze(-1)).squeeze(-1)
    ref_mean = (out.cov.double() @ rhs.unsqueeze(-1)).squeeze(-1)
    assert torch.allclose(out.mean.double(), ref_mean, atol=tol * 10)


def test_hybrid_monte_carlo_consistent():
    result = monte_carlo(HybridEKFUKF, torch.float64, "unicycle", steps=40)
    mean_nees, lo, hi, inside = check_consistency(result)
    assert lo <= mean_nees <= hi, (mean_nees, lo, hi)
    assert inside >= 0.8
    assert result["rms_est"] < 0.5 * result["rms_meas"]
