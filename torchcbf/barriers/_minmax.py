"""Hard and smooth minimum/maximum over the last axis, with their closed-form derivatives."""

from __future__ import annotations

from typing import Literal

import torch
from torch import Tensor

from torchcbf.barriers.lie import AnalyticDerivatives, HessQuad

Mode = Literal["min", "max"]


def reduce(values: Tensor, mode: Mode, smooth: bool, temperature: float) -> Tensor:
    """``[..., c] -> [...]``: ``min``/``max``, or ``-T logsumexp(-v/T)`` / ``T logsumexp(v/T)``."""
    if not smooth:
        return values.amin(-1) if mode == "min" else values.amax(-1)
    sign = -1.0 if mode == "min" else 1.0
    z, shift = _shifted(values, sign)
    temperature = _representable(temperature, values)
    return sign * (shift.squeeze(-1) + temperature * torch.logsumexp(z / temperature, dim=-1))


def _representable(temperature: float, values: Tensor) -> float:
    """``T``, or the least normal number of ``values``' dtype where ``T`` is below it (a
    float32 ``T`` under 1.4e-45 is 0, and ``0 / 0`` NaN): the reduction is then the hard
    one to within ``T log c``, as in float64."""
    return max(temperature, torch.finfo(values.dtype).tiny)


def _shifted(values: Tensor, sign: float) -> tuple[Tensor, Tensor]:
    """``(sign v - c, c)`` with ``c`` the largest of ``sign v`` (detached: the log-sum-exp's
    derivative is the softmax either way), so that ``(sign v - c) / T`` stays finite for a
    subnormal ``T`` where ``v / T`` overflows; rows whose largest is not finite are not
    shifted."""
    z = sign * values
    shift = z.detach().amax(-1, keepdim=True)
    shift = torch.where(torch.isfinite(shift), shift, 0.0)
    return z - shift, shift


def combine(
    values: Tensor,
    dhdx: Tensor,
    dhdt: Tensor,
    hess_quad: HessQuad,
    mode: Mode,
    smooth: bool,
    temperature: float,
) -> AnalyticDerivatives:
    """Derivatives of :func:`reduce` from those of its ``c`` arguments.

    ``values, dhdt [..., c]``, ``dhdx [..., c, n]``, ``hess_quad(S) -> [..., c]``. The hard
    version uses the active argument, and the mean of the active ones at a tie (the
    subgradient autograd of ``amin``/``amax`` gives, so every path agrees); the smooth one
    with weights ``w = softmax(+-v/T)`` has gradient ``sum w_i g_i`` and Hessian
    ``sum w_i H_i +- (sum w_i g_i g_i' - gbar gbar') / T`` (+ for max, - for min).
    """
    if not smooth:
        h = reduce(values, mode, smooth, temperature)
        active = (values == h.unsqueeze(-1)).to(values.dtype)
        w = active / active.sum(-1, keepdim=True).clamp_min(1.0)  # no weight on a NaN row

        def quad(s: Tensor) -> Tensor:
            return (w * hess_quad(s)).sum(-1)

        return AnalyticDerivatives(h, (w.unsqueeze(-1) * dhdx).sum(-2), (w * dhdt).sum(-1), quad)
    sign = -1.0 if mode == "min" else 1.0
    h = reduce(values, mode, smooth, temperature)
    temperature = _representable(temperature, values)
    w = torch.softmax(_shifted(values, sign)[0] / temperature, dim=-1)
    grad = (w.unsqueeze(-1) * dhdx).sum(-2)
    dt = (w * dhdt).sum(-1)

    def smooth_quad(s: Tensor) -> Tensor:
        gs = dhdx @ s  # [..., c, q]: g_i' S
        gbar_s = grad.unsqueeze(-2) @ s  # [..., 1, q]
        spread = (w * (gs**2).sum(-1)).sum(-1) - (gbar_s**2).sum((-2, -1))
        return (w * hess_quad(s)).sum(-1) + sign * spread / temperature

    return AnalyticDerivatives(h, grad, dt, smooth_quad)
