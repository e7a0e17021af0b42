"""CBF and CLF conditions as affine functions of the control, per filter mode.

Every condition is written ``a . u + b`` with ``a [B, k, m]`` and ``b [B, k]``:

- a CBF condition holds when ``a . u + b >= 0`` (``a = L_g h``);
- a CLF condition holds when ``a . u + b <= 0`` (``a = L_g V``), relaxed by ``delta >= 0``.

With ``Lh = L_f h + dh/dt``, ``tr = tr(sigma' d2h/dx2 sigma)``, ``rob = sum_j |(dh/dx M)_j|
w_max_j`` (worst case of the bounded disturbance ``M w``, ``|w|_inf <= w_max``):

- ``vanilla``:    CBF ``Lh + alpha(h)``;                    CLF ``LV + c(V)``
- ``robust``:     CBF ``Lh + alpha(h) - rob_h``;            CLF ``LV + c(V) + rob_V``
- ``stochastic``: CBF ``Lh + tr_h / 2 + alpha(h) - beta``;  CLF ``LV + tr_V / 2 + c(V)``
- ``risk_aware``: CBF ``Lh + tr_h / 2 + (h - Delta) / T``;  CLF ``LV + tr_V / 2 +
  (V - gamma + Delta_V) / T``

The risk-aware CLF is the risk-aware CBF of ``h_V = gamma - V`` (the set ``{V <= gamma}``)
with the inequality reversed; ``Delta_V = sqrt(2T) eta_V erfinv(1 - rho_V)``.
"""

from __future__ import annotations

from typing import Literal, NamedTuple

import torch
from torch import Tensor, nn

from torchcbf.barriers.lie import LieTerms
from torchcbf.dynamics.base import ControlAffine

Mode = Literal["vanilla", "robust", "stochastic", "risk_aware"]
MODES: tuple[str, ...] = ("vanilla", "robust", "stochastic", "risk_aware")


class Condition(NamedTuple):
    """An affine condition ``a . u + b`` per row and output: ``a [B, k, m]``, ``b [B, k]``."""

    a: Tensor
    b: Tensor


def as_columns(terms: LieTerms, batch: int) -> LieTerms:
    """Lie terms of a scalar function (``h [B]``) in the k-output form (``h [B, 1]``)."""
    if terms.h.dim() == 2:
        return terms
    col = lambda v: None if v is None else v.unsqueeze(1)  # noqa: E731
    return LieTerms(*(col(v) for v in terms))


def concat_terms(parts: list[LieTerms]) -> LieTerms:
    """Concatenate k-output Lie terms of several functions along the output axis."""
    if len(parts) == 1:
        return parts[0]
    fields = []
    for i, name in enumerate(LieTerms._fields):
        values = [p[i] for p in parts]
        if name == "hess_trace" and any(v is None for v in values):
            fields.append(None)
            continue
        fields.append(torch.cat(values, 1))
    return LieTerms(*fields)


def disturbance_term(terms: LieTerms, dynamics: ControlAffine, x: Tensor) -> Tensor:
    """Worst case of ``dh/dx M w`` over ``|w|_inf <= w_max``: ``|dh/dx M| w_max`` ``[B, k]``."""
    M = dynamics.disturbance_matrix.to(x)
    w_max = dynamics.disturbance_bound.to(x)
    return (terms.dhdx @ M).abs() @ w_max


def _trace(terms: LieTerms) -> Tensor:
    if terms.hess_trace is None:
        return torch.zeros_like(terms.h)
    return terms.hess_trace


def _gain(fn: nn.Module, h: Tensor, name: str, symbol: str, hint: str = "") -> Tensor:
    """``fn(h)``, checked to keep the shape of ``h [B, k]``."""
    out = fn(h)
    if out.shape != h.shape:
        raise ValueError(
            f"{name} must map {symbol} {tuple(h.shape)} to the same shape, got "
            f"{tuple(out.shape)}{hint}"
        )
    return out


def cbf_condition(
    terms: LieTerms,
    mode: Mode,
    alpha: nn.Module,
    dynamics: ControlAffine,
    x: Tensor,
    *,
    beta: Tensor | None = None,
    margin: Tensor | None = None,
    horizon: Tensor | None = None,
) -> Condition:
    """CBF condition ``a . u + b >= 0`` for k-output terms (``h [B, k]``) in ``mode``.

    ``alpha`` maps ``h [B, k]`` to ``[B, k]``; ``beta`` (stochastic), ``margin`` (``Delta``)
    and ``horizon`` (``T``, risk-aware) broadcast against ``[B, k]``.
    """
    drift = terms.lfh + terms.dhdt
    if mode == "risk_aware":
        b = drift + 0.5 * _trace(terms) + (terms.h - margin) / horizon
    else:
        b = drift + _gain(alpha, terms.h, "alpha", "h", " (give one gain per barrier output)")
        if mode == "robust":
            b = b - disturbance_term(terms, dynamics, x)
        elif mode == "stochastic":
            b = b + 0.5 * _trace(terms) - beta
    return Condition(terms.lgh, b)


def clf_condition(
    terms: LieTerms,
    mode: Mode,
    rate: nn.Module,
    dynamics: ControlAffine,
    x: Tensor,
    *,
    margin: Tensor | None = None,
    gamma: Tensor | None = None,
    horizon: Tensor | None = None,
) -> Condition:
    """CLF condition ``a . u + b <= 0`` (relaxed by the caller) for ``V [B, c]`` in ``mode``."""
    drift = terms.lfh + terms.dhdt
    if mode == "risk_aware":
        b = drift + 0.5 * _trace(terms) + (terms.h - gamma + margin) / horizon
    else:
        b = drift + _gain(rate, terms.h, "clf_rate", "V")
        if mode == "robust":
            b = b + disturbance_term(terms, dynamics, x)
        elif mode == "stochastic":
            b = b + 0.5 * _trace(terms)
    return Condition(terms.lgh, b)
