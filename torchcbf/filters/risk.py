"""Quantities of the risk-aware CBF (Black et al., ICRA 2023): noise bound and margin.

For ``dx = (f + g u) dt + sigma dW`` and a barrier with ``|dh/dx sigma| <= eta`` on the safe
set, the condition ``L_f h + L_g h u + 1/2 tr(sigma' d2h/dx2 sigma) >= -(h - Delta) / T``
with ``Delta = sqrt(2 T) eta erfinv(1 - rho)`` bounds the probability of leaving
``{h >= 0}`` within ``T`` by ``rho`` (from a start with ``h >= Delta``).
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from torchcbf._checks import as_tensor, check_last_dim
from torchcbf.barriers.lie import LieFunction
from torchcbf.dynamics.base import ControlAffine


def noise_bound(
    barrier: LieFunction,
    dynamics: ControlAffine,
    states: Tensor,
    t: Tensor | float | None = None,
    *,
    safe_only: bool = True,
    method: str | None = None,
) -> Tensor:
    """``eta = max |dh/dx sigma|_2`` over sample states, per barrier output (the barrier's
    closed-form derivatives where it has them, else autograd).

    Args:
        barrier: ``h(x) -> [...]`` or ``[..., k]`` (a Lyapunov function works too).
        dynamics: an SDE model (``dynamics.sigma(x)`` not ``None``).
        states: sample states ``[N, n]`` (or ``[..., n]``), e.g. a grid over the region of
            interest; the bound is only as good as their coverage.
        t: time for time-varying barriers.
        safe_only: keep only the states where ``h >= 0`` (per output); ``False`` takes all
            (used for Lyapunov functions).
        method: ``None`` (the barrier's closed forms where it has them, else autograd),
            ``"analytic"`` or ``"autograd"`` (see :func:`torchcbf.barriers.lie_derivatives`).

    Returns:
        ``eta`` of shape ``[]`` (scalar barrier) or ``[k]``, detached.

    Raises:
        ValueError: the dynamics has no diffusion, or no sample state is safe for an output.
    """
    check_last_dim("states", states, dynamics.state_dim)
    if not dynamics.has_diffusion:
        raise ValueError(f"noise_bound needs an SDE model; {type(dynamics).__name__} has no sigma")
    # the closed forms where the barrier has them (a rectified radius-form ellipse does):
    # the bound scans a grid of many states, where autograd costs 3-4x more
    if method is None:
        method = "analytic" if barrier.has_analytic else "autograd"
    with torch.no_grad():
        terms = barrier.lie(states, dynamics, t, method=method, hessian=False)
        sigma = dynamics.sigma(states)  # [..., n, q]
        h = terms.h
        multi = h.shape != states.shape[:-1]
        dhdx = terms.dhdx if multi else terms.dhdx.unsqueeze(-2)  # [..., k, n]
        hk = h if multi else h.unsqueeze(-1)  # [..., k]
        norm = torch.linalg.vector_norm(dhdx @ sigma, dim=-1)  # [..., k]
        keep = hk >= 0 if safe_only else torch.isfinite(norm)
        keep = keep & torch.isfinite(norm)
        masked = torch.where(keep, norm, torch.full_like(norm, -math.inf))
        eta = masked.reshape(-1, norm.shape[-1]).amax(0)
    if not bool(torch.isfinite(eta).all()):
        bad = [i for i, v in enumerate(eta.tolist()) if not math.isfinite(v)]
        raise ValueError(
            f"states holds no {'safe (h >= 0) ' if safe_only else ''}sample with a finite "
            f"gradient for barrier output(s) {bad}"
        )
    return eta if multi else eta.squeeze(-1)


def risk_margin(eta: Tensor, rho: float | Tensor, horizon: float | Tensor) -> Tensor:
    """``Delta = sqrt(2 T) eta erfinv(1 - rho)`` (shapes broadcast), in ``eta``'s dtype.
    The factor ``sqrt(2 T) erfinv(1 - rho)`` is formed in float64: in float32 ``1 - rho``
    is 1 for ``rho`` below about 6e-8, and the margin infinite."""
    rho_t = as_tensor("rho", rho, dtype=torch.float64, device=eta.device)
    T = as_tensor("horizon", horizon, dtype=torch.float64, device=eta.device)
    return (torch.sqrt(2 * T) * torch.erfinv(1 - rho_t)).to(eta.dtype) * eta


def local_margin(
    dhdx: Tensor, sigma: Tensor, rho: float | Tensor, horizon: float | Tensor
) -> Tensor:
    """The risk-aware margin from each state's own noise: ``Delta = sqrt(2 T) |dh/dx sigma|
    erfinv(1 - rho)`` with ``dhdx [..., k, n]`` and ``sigma [..., n, q]``; returns ``[..., k]``.

    The bound of a constant ``eta`` holds over a window in which ``|dh/dx sigma|`` stays at
    most its value at the window's start; elsewhere this margin is an approximation. Its
    gradient where ``dh/dx sigma = 0`` is zero (the norm's subgradient), not NaN.
    """
    return risk_margin(torch.linalg.vector_norm(dhdx @ sigma, dim=-1), rho, horizon)
