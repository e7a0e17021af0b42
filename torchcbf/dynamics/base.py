"""The control-affine dynamics base class.

``dx = (f(x) + g(x) u + M w) dt + sigma(x) dW`` with optional bounded disturbance
``|w|_inf <= w_max`` and optional diffusion ``sigma``.
"""

from __future__ import annotations

from collections.abc import Callable

import torch
from torch import Tensor, nn

from torchcbf._checks import as_tensor, check_batch_match, check_last_dim

SigmaSpec = float | Tensor | Callable[[Tensor], Tensor] | None
LimitSpec = float | Tensor | list[float] | tuple[float, ...] | None


class ControlAffine(nn.Module):
    """Control-affine system ``xdot = f(x) + g(x) u (+ M w)``, optionally an SDE.

    Subclasses set ``state_dim`` and ``control_dim`` (through ``super().__init__``) and write
    ``f(x) -> [..., n]`` and ``g(x) -> [..., n, m]``. They may override ``_xdot`` with a
    faster closed form of ``f + g u`` (used by ``forward`` and the integrators).

    Constants given as numbers are stored as float64 buffers (exact under ``.double()``);
    ``.to(dtype)`` casts them and every method casts them to the input's dtype on use.

    Args:
        state_dim: ``n``.
        control_dim: ``m``.
        sigma: diffusion of ``dx = (f + g u) dt + sigma dW``: a scalar (``sigma * I``), a
            vector ``[n]`` (diagonal), a matrix ``[n, q]``, or a callable ``x -> [..., n, q]``.
        u_min, u_max: control limits, scalars or ``[m]`` (``None``: unbounded).
        disturbance_bound: ``w_max``, scalar or ``[p]``; the disturbance is ``|w|_inf <= w_max``.
        disturbance_matrix: ``M`` of shape ``[n, p]`` (identity by default).
    """

    def __init__(
        self,
        state_dim: int,
        control_dim: int,
        *,
        sigma: SigmaSpec = None,
        u_min: LimitSpec = None,
        u_max: LimitSpec = None,
        disturbance_bound: LimitSpec = None,
        disturbance_matrix: Tensor | None = None,
    ) -> None:
        super().__init__()
        if state_dim < 1 or control_dim < 1:
            raise ValueError(
                f"state_dim and control_dim must be >= 1, got {state_dim} and {control_dim}"
            )
        self.state_dim = int(state_dim)
        self.control_dim = int(control_dim)
        self._sigma_fn: Callable[[Tensor], Tensor] | None = None
        self.register_buffer("sigma_matrix", None)
        if callable(sigma) and not isinstance(sigma, Tensor):
            self._sigma_fn = sigma
        elif sigma is not None:
            self.sigma_matrix = _sigma_matrix(sigma, self.state_dim)
        self.register_buffer("u_min", _limit("u_min", u_min, self.control_dim))
        self.register_buffer("u_max", _limit("u_max", u_max, self.control_dim))
        if (
            self.u_min is not None
            and self.u_max is not None
            and bool((self.u_min > self.u_max).any())
        ):
            raise ValueError(f"u_min {self.u_min.tolist()} exceeds u_max {self.u_max.tolist()}")
        self.register_buffer("disturbance_matrix", None)
        self.register_buffer("disturbance_bound", None)
        if disturbance_bound is not None or disturbance_matrix is not None:
            M = (
                torch.eye(self.state_dim, dtype=torch.float64)
                if disturbance_matrix is None
                else as_tensor("disturbance_matrix", disturbance_matrix, dtype=torch.float64)
            )
            if M.dim() != 2 or M.shape[0] != self.state_dim:
                raise ValueError(
                    f"disturbance_matrix must have shape [{self.state_dim}, p], "
                    f"got {tuple(M.shape)}"
                )
            bound = 0.0 if disturbance_bound is None else disturbance_bound
            w_max = _limit("disturbance_bound", bound, M.shape[1])
            if bool((w_max < 0).any()):
                raise ValueError(f"disturbance_bound must be >= 0, got {w_max.tolist()}")
            self.disturbance_matrix = M
            self.disturbance_bound = w_max

    # -- to be written by subclasses -------------------------------------------------------
    def f(self, x: Tensor) -> Tensor:
        """Drift ``f(x)``: ``[..., n] -> [..., n]``."""
        raise NotImplementedError(f"{type(self).__name__} must define f(x)")

    def g(self, x: Tensor) -> Tensor:
        """Control matrix ``g(x)``: ``[..., n] -> [..., n, m]``."""
        raise NotImplementedError(f"{type(self).__name__} must define g(x)")

    def _xdot(self, x: Tensor, u: Tensor) -> Tensor:
        return self.f(x) + (self.g(x) @ u.unsqueeze(-1)).squeeze(-1)

    # -- derived ---------------------------------------------------------------------------
    def forward(self, x: Tensor, u: Tensor, w: Tensor | None = None) -> Tensor:
        """``xdot = f(x) + g(x) u (+ M w)`` for ``x [..., n]``, ``u [..., m]``, ``w [..., p]``."""
        self.check_inputs(x, u)
        xdot = self._xdot(x, u)
        if w is not None:
            xdot = xdot + self.disturbance(x, w)
        return xdot

    def check_inputs(self, x: object, u: object | None = None) -> None:
        """Raise ``TypeError``/``ValueError`` for a state or control of the wrong type or shape."""
        check_last_dim("x", x, self.state_dim)
        if u is not None:
            check_last_dim("u", u, self.control_dim)
            check_batch_match("x", x, "u", u)  # type: ignore[arg-type]

    def disturbance(self, x: Tensor, w: Tensor) -> Tensor:
        """Disturbance term ``M w``: ``w [..., p] -> [..., n]``."""
        if self.disturbance_matrix is None:
            raise ValueError(f"{type(self).__name__} was built without a disturbance_bound")
        M = self.disturbance_matrix.to(x)
        check_last_dim("w", w, M.shape[1])
        return w @ M.mT

    @property
    def has_diffusion(self) -> bool:
        """Whether the model is an SDE (has ``sigma``)."""
        return self._sigma_fn is not None or self.sigma_matrix is not None

    def sigma(self, x: Tensor) -> Tensor | None:
        """Diffusion ``sigma(x) -> [..., n, q]``, or ``None`` for an ODE."""
        if self._sigma_fn is not None:
            return self._sigma_fn(x)
        if self.sigma_matrix is None:
            return None
        s = self.sigma_matrix.to(x)
        return s.expand(*x.shape[:-1], *s.shape)

    def clamp_control(self, u: Tensor) -> Tensor:
        """Clip ``u [..., m]`` to ``[u_min, u_max]`` (unchanged where a limit is ``None``)."""
        lo = None if self.u_min is None else self.u_min.to(u)
        hi = None if self.u_max is None else self.u_max.to(u)
        if lo is None and hi is None:
            return u
        return torch.clamp(u, lo, hi)

    def extra_repr(self) -> str:
        return f"state_dim={self.state_dim}, control_dim={self.control_dim}"


def _limit(name: str, value: LimitSpec, size: int) -> Tensor | None:
    if value is None:
        return None
    t = as_tensor(name, value, dtype=torch.float64)
    if t.dim() == 0:
        t = t.expand(size).clone()
    if t.shape != (size,):
        raise ValueError(f"{name} must be a scalar or have shape [{size}], got {tuple(t.shape)}")
    return t


def _sigma_matrix(sigma: float | Tensor, n: int) -> Tensor:
    s = as_tensor("sigma", sigma, dtype=torch.float64)
    if s.dim() == 0:
        return s * torch.eye(n, dtype=s.dtype)
    if s.dim() == 1:
        if s.shape[0] != n:
            raise ValueError(f"sigma as a vector must have shape [{n}], got {tuple(s.shape)}")
        return torch.diag(s)
    if s.dim() == 2 and s.shape[0] == n:
        return s
    raise ValueError(f"sigma must be a scalar, [{n}], [{n}, q] or a callable, got {tuple(s.shape)}")
