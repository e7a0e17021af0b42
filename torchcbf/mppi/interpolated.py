"""Kernel-interpolated MPPI (KMPPI, Miura et al. 2024): sampling a few control points.

The plan is the kernel interpolation of ``S`` control points ``theta [S, m]`` placed at the
support steps ``tau = linspace(0, H-1, S)``: ``U = W theta`` with
``W = k(t, tau) k(tau, tau)^-1 [H, S]`` over the steps ``t = 0 .. H-1`` (it passes through
the control points). Per call:

1. warm start: the plan moves one step (last control zero, or repeated with
   ``shift_fill="last"``) and the control points become the current interpolation
   evaluated one step later, ``theta <- k(tau + 1, tau) k(tau, tau)^-1 theta``;
2. noise ``z_k ~ N(0, Sigma)`` on the control points; sampled points
   ``p_k = clamp(theta + z_k)``, ``z_k = p_k - theta``; sampled sequences
   ``v_k = clamp(W p_k)``;
3. cost ``S_k = cost(rollout of v_k) + gamma sum_j U_j' Sigma^-1 (v_{k,j} - U_j)``;
4. the MPPI weights; ``theta <- theta + sum_k w_k z_k``, ``U <- clamp(W theta)``.

A candidate sequence (``action_sampler``, ``sample_null_action``) is rolled out as given;
its control-point noise is the least-squares fit ``pinv(W) v - theta``. KMPPI runs on the
torch path.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import torch
from torch import Tensor

from torchcbf._checks import check_int
from torchcbf.dynamics.base import ControlAffine
from torchcbf.mppi import _rollout
from torchcbf.mppi.planner import MPPI, _resized, _shifted

#: how far the interpolation may miss its control points (``|W(tau) - I|``, float64)
INTERPOLATION_TOL = 1e-6

TimeKernel = Callable[[Tensor, Tensor], Tensor]


class _RBF:
    """The kernel :func:`rbf_kernel` returns (a class, so that a planner holding it pickles)."""

    def __init__(self, width: float) -> None:
        self.width = float(width)

    def __call__(self, t: Tensor, tau: Tensor) -> Tensor:
        return torch.exp((-0.5 / self.width**2) * (t.unsqueeze(-1) - tau).square())

    def __repr__(self) -> str:
        return f"rbf_kernel(width={self.width})"


def rbf_kernel(width: float = 1.0) -> TimeKernel:
    """``k(t [N], tau [S]) = exp(-(t - tau)^2 / (2 width^2)) -> [N, S]`` (times in steps)."""
    if isinstance(width, bool) or not isinstance(width, (int, float)) or not width > 0:
        raise ValueError(f"width must be a positive number, got {width!r}")
    return _RBF(width)


class KMPPI(MPPI):
    """MPPI over ``S`` kernel-interpolated control points.

    Takes :class:`~torchcbf.mppi.MPPI`'s arguments (``noise_sigma`` is the covariance of the
    control-point noise) and:

    Args:
        num_support_points: ``S`` with ``1 <= S <= H`` (default ``max(H // 2, 1)``, as
            pytorch-mppi).
        kernel: ``k(t [N], tau [S]) -> [N, S]`` over times in steps (default
            :func:`rbf_kernel` of width 1, pytorch-mppi's ``RBFKernel()``); ``k(tau, tau)``
            must be invertible.

    ``forward`` returns ``U = W theta`` as ``plan``; :attr:`control_points` is ``theta [B, S,
    m]``. :meth:`~torchcbf.mppi.MPPI.change_horizon` keeps ``S`` and re-places the control
    points on the new horizon (the current interpolation evaluated at the new support
    steps). :meth:`~torchcbf.mppi.MPPI.correct` writes the plan's first control, which the
    next update replaces by ``W theta``.
    """

    sampling = "kernel"

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
        num_support_points: int | None = None,
        kernel: TimeKernel | None = None,
        **kwargs: Any,
    ) -> None:
        super().__init__(
            dynamics, cost, horizon, num_samples, dt, noise_sigma, temperature,
            control_cost_weight, u_min=u_min, u_max=u_max, integrator=integrator, seed=seed,
            **kwargs,
        )  # fmt: skip
        H = self.horizon
        S = max(H // 2, 1) if num_support_points is None else num_support_points
        what = f"an integer in [1, horizon={H}]"
        S = check_int("num_support_points", S, low=1, what=what)
        if S > H:
            raise ValueError(f"num_support_points must be {what}, got {S}")
        if kernel is not None and not callable(kernel):
            raise TypeError(f"kernel must be callable, got {type(kernel).__name__}")
        self.num_support_points = S
        self.kernel = rbf_kernel() if kernel is None else kernel

    @property
    def control_points(self) -> Tensor | None:
        """``theta [B, S, m]`` (a copy; ``None`` before the first call)."""
        return None if self._key is None else self._theta.clone()

    def support(self, horizon: int, like: Tensor) -> Tensor:
        """The support steps ``tau [S]`` of a horizon (float64 on ``like``'s device)."""
        return torch.linspace(
            0.0, horizon - 1, self.num_support_points, dtype=torch.float64, device=like.device
        )

    def interpolation(self, t: Tensor, tau: Tensor) -> Tensor:
        """``k(t, tau) k(tau, tau)^-1 [N, S]``: the values at the steps ``t [N]`` of the
        interpolation through control points at ``tau [S]`` (float64)."""
        gram = self.kernel(tau, tau)
        cross = self.kernel(t, tau)
        expected = (tau.shape[0], tau.shape[0])
        if gram.shape != expected or cross.shape != (t.shape[0], tau.shape[0]):
            raise ValueError(
                f"kernel(t [N], tau [S]) must return [N, S]; got {tuple(gram.shape)} for "
                f"N = S = {tau.shape[0]}"
            )
        gram, cross = gram.double(), cross.double()  # a kernel may compute in float32
        out, info = torch.linalg.solve_ex(gram, cross, left=False)
        # interpolation through the points: W(tau) = I, lost where k(tau, tau) is singular
        # to rounding (a wide kernel over many points)
        through = torch.linalg.solve_ex(gram, gram, left=False)[0]
        eye = torch.eye(tau.shape[0], dtype=through.dtype, device=through.device)
        if int(info) != 0 or not bool(((through - eye).abs() <= INTERPOLATION_TOL).all()):
            raise ValueError(
                f"the kernel's matrix k(tau, tau) over {tau.shape[0]} support points is singular "
                "to rounding: the plan would not pass through its control points (use fewer "
                "support points or a narrower kernel)"
            )
        return out

    def _allocate(self, B: int, device: torch.device, dtype: torch.dtype) -> None:
        m = self.dynamics.control_dim
        self._theta = torch.zeros(B, self.num_support_points, m, device=device, dtype=dtype)
        self._matrices(self.horizon, self._theta)
        self._scratch: Tensor | None = None

    def _matrices(self, horizon: int, like: Tensor) -> None:
        """``W [H, S]``, its pseudo-inverse and the one-step shift ``[S, S]``."""
        tau = self.support(horizon, like)
        steps = torch.arange(horizon, dtype=torch.float64, device=like.device)
        W = self.interpolation(steps, tau)
        self._W = W.to(like.dtype)
        self._W_pinv = torch.linalg.pinv(W).to(like.dtype)
        self._W_shift = self.interpolation(tau + 1.0, tau).to(like.dtype)

    def _sampling_steps(self) -> int:
        return self.num_support_points

    def _shift(self) -> None:
        self._plan.copy_(_shifted(self._plan, self.shift_fill))
        self._theta = self._W_shift @ self._theta

    def change_horizon(self, horizon: int) -> None:
        horizon = check_int("horizon", horizon, low=1, what="an integer >= 1")
        if horizon < self.num_support_points:
            raise ValueError(
                f"horizon must be >= num_support_points ({self.num_support_points}), got {horizon}"
            )
        super().change_horizon(horizon)

    def _resize(self, horizon: int) -> None:
        old_tau = self.support(self.horizon, self._theta)
        moved = self.interpolation(self.support(horizon, self._theta), old_tau)
        self._theta = moved.to(self._theta.dtype) @ self._theta
        self._matrices(horizon, self._theta)
        self._plan = _resized(self._plan, horizon, self.shift_fill)
        self._plan.copy_(self._clamp(self._W @ self._theta))
        self._scratch = None

    def _perturb(self, x: Tensor, t0: Tensor, eps: Tensor, controls: Tensor) -> Tensor:
        theta = self._theta.unsqueeze(1)
        self._clamp(eps.add_(theta))  # the sampled control points
        controls.copy_(self._W @ eps)
        rows = self._candidates(x, t0, controls)
        self._clamp(controls)
        if rows is not None:
            eps[:, rows] = self._W_pinv @ controls[:, rows]
        eps.sub_(theta)
        B, K, H, m = controls.shape
        if self._scratch is None or self._scratch.shape != controls.shape:
            self._scratch = _rollout.rollout_buffer(controls, B, K, H, m, self.layout)
        return torch.sub(controls, self._plan.unsqueeze(1), out=self._scratch)

    def _update_plan(self, delta: Tensor) -> None:
        self._theta.add_(delta)
        self._plan.copy_(self._clamp(self._W @ self._theta))

    def _kept(self) -> tuple[Tensor, ...]:
        scratch = () if self._scratch is None else (self._scratch,)
        return (*super()._kept(), self._theta, *scratch)

    def _release_graph(self) -> None:
        super()._release_graph()
        self._theta, self._scratch = self._theta.detach().clone(), None

    def extra_repr(self) -> str:
        return f"{super().extra_repr()}, num_support_points={self.num_support_points}"
