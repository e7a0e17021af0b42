"""Smooth MPPI (SMPPI, Kim et al. 2022): sampling in the derivative of the action.

The planner keeps two sequences per environment: the applied actions ``A [H, m]`` (the
plan it returns) and their rate of change ``U [H, m]``. Per call:

1. warm start: ``U`` and ``A`` move one step; the last rate is zero and the last action
   repeats;
2. rate noise ``eps_k ~ N(0, Sigma)``; sampled rates ``v_k = clamp(U + eps_k)`` to
   ``du_min``/``du_max``; sampled actions ``a_k = clamp(A + v_k delta_t)`` to
   ``u_min``/``u_max``, and the rate noise recomputed from them,
   ``eps_k = (a_k - A) / delta_t - U``;
3. cost ``S_k = cost(rollout of a_k) + gamma sum_j U_j' Sigma^-1 eps_{k,j}
   + w sum_j |a_{k,j+1} - a_{k,j}|^2`` (the last term is the smoothness cost);
4. the MPPI weights ``w_k``; ``U <- clamp(U + sum_k w_k eps_k)``,
   ``A <- clamp(A + U delta_t)``.

Everything else (weights, temperature, candidates, ``u_scale``, the history of
specifications, batching and seeding) is :class:`~torchcbf.mppi.MPPI`'s. SMPPI runs on the
torch path.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import torch
from torch import Tensor

from torchcbf._checks import as_limit, check_bounds, check_number, check_positive
from torchcbf._constants import remember
from torchcbf.dynamics.base import ControlAffine
from torchcbf.mppi.planner import MPPI, _limit, _resized, _shifted


class SMPPI(MPPI):
    """MPPI sampling the rate of change of the actions, with a smoothness cost.

    Takes :class:`~torchcbf.mppi.MPPI`'s arguments (``noise_sigma`` is the covariance of the
    rate noise; ``u_min``/``u_max`` bound the applied actions) and:

    Args:
        smoothness_weight: ``w >= 0`` of ``w sum_j |a_{j+1} - a_j|^2`` (pytorch-mppi's
            ``w_action_seq_cost``).
        delta_t: ``A <- A + U delta_t`` (pytorch-mppi's ``delta_t``; the default 1 makes
            ``U`` the change of the action per step).
        du_min, du_max: bounds of the rate (scalar or ``[m]``, one-sided when one is given;
            pytorch-mppi's ``u_min``/``u_max`` of SMPPI).

    ``forward`` returns the actions ``A`` as ``plan`` and ``A_0`` as ``u``; :attr:`rate` is
    the rate plan ``U [B, H, m]``.
    """

    _BOUNDS = (*MPPI._BOUNDS, ("du_min", "du_max"))

    sampling = "smooth"

    def __init__(
        self,
        dynamics: ControlAffine,
        cost: Callable[..., Tensor],
        horizon: int,
        num_samples: int,
        dt: float,
        noise_sigma: float | Tensor,
        temperature: float,
        control_cost_weight: float = 0.0,
        *,
        u_min: float | Tensor | None = None,
        u_max: float | Tensor | None = None,
        integrator: str = "euler",
        seed: int = 0,
        smoothness_weight: float = 1.0,
        delta_t: float = 1.0,
        du_min: float | Tensor | None = None,
        du_max: float | Tensor | None = None,
        **kwargs: Any,
    ) -> None:
        super().__init__(
            dynamics, cost, horizon, num_samples, dt, noise_sigma, temperature,
            control_cost_weight, u_min=u_min, u_max=u_max, integrator=integrator, seed=seed,
            **kwargs,
        )  # fmt: skip
        self.smoothness_weight = check_number("smoothness_weight", smoothness_weight, low=0.0)
        self.delta_t = check_positive("delta_t", delta_t)
        m = dynamics.control_dim
        lo = None if du_min is None else _limit("du_min", du_min, m)
        hi = None if du_max is None else _limit("du_max", du_max, m)
        check_bounds("du_min", lo, "du_max", hi)
        for name, value, spec in (("du_min", lo, du_min), ("du_max", hi, du_max)):
            if value is not None and not isinstance(spec, Tensor):
                remember(self, name, as_limit(name, spec, m))  # Python numbers: exact
            else:
                self.register_buffer(name, None if value is None else value.clone())

    @property
    def rate(self) -> Tensor | None:
        """The rate plan ``U [B, H, m]`` (a copy; ``None`` before the first call)."""
        return None if self._key is None else self._rate.clone()

    def _allocate(self, B: int, device: torch.device, dtype: torch.dtype) -> None:
        self._rate = torch.zeros(B, self.horizon, self.dynamics.control_dim, device=device,
                                 dtype=dtype)  # fmt: skip

    def _shift(self) -> None:
        self._rate.copy_(_shifted(self._rate, "zero"))
        self._plan.copy_(_shifted(self._plan, "last"))

    def _resize(self, horizon: int) -> None:
        self._rate = _resized(self._rate, horizon, "zero")
        self._plan = _resized(self._plan, horizon, "last")

    def _clamp_rate(self, v: Tensor) -> Tensor:
        if self.du_min is not None or self.du_max is not None:
            lo = None if self.du_min is None else self.du_min.to(v)
            hi = None if self.du_max is None else self.du_max.to(v)
            v.clamp_(lo, hi)
        return v

    def _perturb(self, x: Tensor, t0: Tensor, eps: Tensor, controls: Tensor) -> Tensor:
        rate, actions = self._rate.unsqueeze(1), self._plan.unsqueeze(1)
        torch.add(eps, rate, out=controls)
        self._clamp_rate(controls)
        controls.mul_(self.delta_t).add_(actions)
        self._candidates(x, t0, controls)
        self._clamp(controls)
        torch.sub(controls, actions, out=eps)
        eps.div_(self.delta_t).sub_(rate)
        return eps

    def _cost_plan(self) -> Tensor:
        return self._rate

    def _extra_cost(self, controls: Tensor) -> Tensor | None:
        if self.smoothness_weight == 0.0:
            return None
        change = controls[:, :, 1:] - controls[:, :, :-1]
        return self.smoothness_weight * change.square().sum((-2, -1))

    def _update_plan(self, delta: Tensor) -> None:
        self._clamp_rate(self._rate.add_(delta))
        self._clamp(self._plan.add_(self._rate, alpha=self.delta_t))

    def _kept(self) -> tuple[Tensor, ...]:
        return (*super()._kept(), self._rate)

    def _release_graph(self) -> None:
        super()._release_graph()
        self._rate = self._rate.detach().clone()

    def extra_repr(self) -> str:
        return (
            f"{super().extra_repr()}, smoothness_weight={self.smoothness_weight}, "
            f"delta_t={self.delta_t}"
        )
