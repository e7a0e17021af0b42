"""The control-affine dynamics base class.

``dx = (f(x) + g(x) u + M w) dt + sigma(x) dW`` with optional bounded disturbance
``|w|_inf <= w_max`` and optional diffusion ``sigma``.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from typing import Any, ClassVar, NamedTuple

import torch
from torch import Tensor, nn

from torchcbf._checks import (
    ClosedForms,
    TracksShadows,
    apply_rules,
    as_limit,
    as_tensor,
    check_batch_match,
    check_bounds,
    check_finite,
    check_int,
    check_last_dim,
    check_same,
    clamp_control,
    limit_shape,
    matrix_shape,
    stale_on,
    to_float64,
)
from torchcbf._constants import DerivedConstants, derive, store

SigmaSpec = float | Tensor | Callable[[Tensor], Tensor] | None
LimitSpec = float | Tensor | list[float] | tuple[float, ...] | None


class DriftDerivatives(NamedTuple):
    """Closed-form derivatives of the drift at ``x [..., n]``: ``jac = df/dx [..., n, n]``
    and ``hess_quad(w [..., k, n], S [..., n, q]) -> sum_i w_i tr(S' d2f_i/dx2 S) [..., k]``
    (see :meth:`ControlAffine.drift_derivatives`)."""

    jac: Tensor
    hess_quad: Callable[[Tensor, Tensor], Tensor]


class NativeModel(NamedTuple):
    """A model the native kernels evaluate in closed form (see
    :meth:`ControlAffine.native_model`): its ``kind`` (a key of
    :data:`torchcbf._native.MODEL_CODES`) and ``dim``, the size that kind is built with (the
    position dimension of the integrators, 0 for the unicycles)."""

    kind: str
    dim: int = 0


#: rows of a batch from which :func:`matvec` sums columns instead of calling ``matmul``
MATVEC_COLUMNS_FROM = 256
#: columns up to which :func:`matvec` sums them (wider ``g`` goes to ``matmul``)
MATVEC_COLUMNS_UP_TO = 8


def matvec(g: Tensor, u: Tensor) -> Tensor:
    """``g u`` for ``g [..., n, m]`` and ``u [..., m]`` (batch dimensions broadcast):
    ``[..., n]``. For a batch of many small matrices it sums ``m`` scaled columns (CPU
    matmul of ``[n, m] x [m, 1]`` blocks is several times slower); a few use ``matmul``."""
    rows = max(g.numel() // max(g.shape[-1] * g.shape[-2], 1), u.numel() // max(u.shape[-1], 1))
    if rows < MATVEC_COLUMNS_FROM or g.shape[-1] > MATVEC_COLUMNS_UP_TO:
        return (g @ u.unsqueeze(-1)).squeeze(-1)
    out = g[..., 0] * u[..., 0:1]
    for j in range(1, g.shape[-1]):
        out = out + g[..., j] * u[..., j : j + 1]
    return out


def matmat(a: Tensor, b: Tensor) -> Tensor:
    """``a b`` for ``a [..., k, n]`` and ``b [..., n, m]`` (batch dimensions broadcast):
    ``[..., k, m]``, as a sum of ``n`` outer products of columns and rows where ``n`` is at
    most :data:`MATVEC_COLUMNS_UP_TO` (a GPU's batched matmul of many tiny blocks runs far
    below its memory bandwidth), else ``matmul``."""
    if a.shape[-1] > MATVEC_COLUMNS_UP_TO:
        return a @ b
    out = a[..., 0:1] * b[..., None, 0, :]
    for j in range(1, a.shape[-1]):
        out = out + a[..., j : j + 1] * b[..., None, j, :]
    return out


class ControlAffine(TracksShadows, DerivedConstants):
    """Control-affine system ``xdot = f(x) + g(x) u (+ M w)``, optionally an SDE.

    Subclasses set ``state_dim`` and ``control_dim`` (through ``super().__init__``) and write
    ``f(x) -> [..., n]`` and ``g(x) -> [..., n, m]``. They may override :meth:`xdot` with a
    faster closed form of ``f + g u`` (used by ``forward``, the integrators and MPPI).

    Constants given as numbers are stored as float64 buffers (exact under ``.double()``);
    ``.to(dtype)`` casts them and every method casts them to the input's dtype on use. A
    tensor constant that requires grad keeps its gradient (an ``nn.Parameter`` is trained
    with the module). NaN constants, NaN limits and ``u_min > u_max`` raise ``ValueError``.

    Args:
        state_dim: ``n``.
        control_dim: ``m``.
        sigma: diffusion of ``dx = (f + g u) dt + sigma dW``: a scalar (``sigma * I``), a
            vector ``[n]`` (diagonal), a matrix ``[n, q]``, or a callable ``x -> [..., n, q]``
            (its values are cast to the state's dtype).
        u_min, u_max: control limits, scalars or ``[m]`` (``None``: unbounded).
        disturbance_bound: ``w_max``, scalar or ``[p]``; the disturbance is ``|w|_inf <= w_max``.
        disturbance_matrix: ``M`` of shape ``[n, p]`` (identity by default).
    """

    #: the fast forms a model may give, each trusted only where the class defining it also
    #: defines what it stands for (see :func:`torchcbf._checks.honour_overrides`): a subclass
    #: that overrides ``f`` alone integrates ``f + g u``, takes its drift derivatives by
    #: autograd and runs on no native kernel
    closed_forms: ClassVar[ClosedForms] = {
        "xdot": (("f", "g"), ()),
        "drift_derivatives": (("f",), ()),
        "native_model": (
            ("f", "g", "xdot", "forward", "__call__", "sigma", "drift_derivatives"),
            (),
        ),
    }

    #: each fast form's answer for a model with forward hooks (a hook changes ``xdot``;
    #: see :func:`torchcbf._checks.unless_hooked`): it runs on no native kernel
    hooked_forms: ClassVar[dict[str, object]] = {"native_model": None}

    def __init_subclass__(cls, **kwargs: Any) -> None:
        super().__init_subclass__(**kwargs)
        apply_rules(cls, ControlAffine)

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
        self.state_dim = check_int("state_dim", state_dim, low=1)
        self.control_dim = check_int("control_dim", control_dim, low=1)
        self._sigma_fn: Callable[[Tensor], Tensor] | None = None
        self.register_buffer("sigma_matrix", None)
        # constants given as a parameter that these casts and shapes change are kept and
        # cast and shaped at each read (torchcbf._constants.derive): they train
        if callable(sigma) and not isinstance(sigma, Tensor):
            self._sigma_fn = sigma
        elif sigma is not None:
            n = self.state_dim
            shape = functools.partial(matrix_shape, size=n, dtype=torch.float64)
            derive(self, "sigma_matrix", sigma, functools.partial(_sigma_matrix, n=n), shape=shape)
        m = self.control_dim
        bound = functools.partial(limit_shape, size=m)
        lo = derive(self, "u_min", u_min, functools.partial(as_limit, "u_min", size=m), shape=bound)
        hi = derive(self, "u_max", u_max, functools.partial(as_limit, "u_max", size=m), shape=bound)
        check_bounds("u_min", lo, "u_max", hi)
        self.register_buffer("disturbance_matrix", None)
        self.register_buffer("disturbance_bound", None)
        if disturbance_bound is not None or disturbance_matrix is not None:
            if disturbance_matrix is None:
                disturbance_matrix = torch.eye(self.state_dim, dtype=torch.float64)
            as_f64 = functools.partial(as_tensor, "disturbance_matrix", dtype=torch.float64)
            M = derive(self, "disturbance_matrix", disturbance_matrix, as_f64, shape=to_float64)
            assert M is not None
            if M.dim() != 2 or M.shape[0] != self.state_dim:
                raise ValueError(
                    f"disturbance_matrix must have shape [{self.state_dim}, p], "
                    f"got {tuple(M.shape)}"
                )
            check_finite("disturbance_matrix", M)
            bound = 0.0 if disturbance_bound is None else disturbance_bound
            p = M.shape[1]
            limit = functools.partial(as_limit, "disturbance_bound", size=p)
            shaped = functools.partial(limit_shape, size=p)
            w_max = derive(self, "disturbance_bound", bound, limit, shape=shaped)
            assert w_max is not None
            check_finite("disturbance_bound", w_max)
            if bool((w_max.detach() < 0).any()):
                raise ValueError(f"disturbance_bound must be >= 0, got {w_max.detach().tolist()}")

    # -- to be written by subclasses -------------------------------------------------------
    def f(self, x: Tensor) -> Tensor:
        """Drift ``f(x)``: ``[..., n] -> [..., n]``."""
        raise NotImplementedError(f"{type(self).__name__} must define f(x)")

    def g(self, x: Tensor) -> Tensor:
        """Control matrix ``g(x)``: ``[..., n] -> [..., n, m]``."""
        raise NotImplementedError(f"{type(self).__name__} must define g(x)")

    @property
    def has_drift_derivatives(self) -> bool:
        """Whether :meth:`drift_derivatives` has closed forms for this model's ``f``
        (closed-form exponential CBFs of relative degree two use them; otherwise those run by
        autograd): a subclass that changes ``f`` does not inherit its parent's derivatives
        (see :attr:`closed_forms`)."""
        return type(self).drift_derivatives is not ControlAffine.drift_derivatives and not (
            stale_on(self, "drift_derivatives", self.closed_forms)
        )

    def native_model(self) -> NativeModel | None:
        """This model as the native kernels know it, or ``None`` (the default: torch code
        runs). Built-in models give it; a subclass that changes ``f``, ``g``, ``xdot``,
        ``forward``, ``sigma`` or ``drift_derivatives`` does not inherit it (see
        :attr:`closed_forms`)."""
        return None

    def drift_derivatives(self, x: Tensor) -> DriftDerivatives:
        """Jacobian and second-derivative contraction of ``f`` at ``x [..., n]`` (see
        :class:`DriftDerivatives`). Optional: override it with closed forms."""
        raise NotImplementedError(f"{type(self).__name__} has no closed-form drift derivatives")

    def xdot(self, x: Tensor, u: Tensor) -> Tensor:
        """``f(x) + g(x) u`` for ``x [..., n]``, ``u [..., m]`` (batch dimensions broadcast),
        without input checks: the extension point for a faster closed form."""
        return self.f(x) + matvec(self.g(x), u)

    # -- derived ---------------------------------------------------------------------------
    def forward(self, x: Tensor, u: Tensor, w: Tensor | None = None) -> Tensor:
        """``xdot = f(x) + g(x) u (+ M w)`` for ``x [..., n]``, ``u [..., m]``, ``w [..., p]``."""
        self.check_inputs(x, u)
        if stale_on(self, "xdot", self.closed_forms):  # the instance's own f or g
            xdot = ControlAffine.xdot(self, x, u)
        else:
            xdot = self.xdot(x, u)
        if w is not None:
            xdot = xdot + self.disturbance(x, w)
        return xdot

    def check_inputs(self, x: object, u: object | None = None) -> None:
        """Raise ``TypeError``/``ValueError`` for a state or control of the wrong type, shape,
        dtype (not floating, or ``u``'s differing from ``x``'s) or device (naming both)."""
        x = check_last_dim("x", x, self.state_dim)
        if not x.is_floating_point():
            raise TypeError(f"x must be a floating-point tensor, got {x.dtype}")
        if u is not None:
            u = check_last_dim("u", u, self.control_dim)
            check_same("x", x, "u", u)
            check_batch_match("x", x, "u", u)

    def disturbance(self, x: Tensor, w: Tensor) -> Tensor:
        """Disturbance term ``M w``: ``w [..., p] -> [..., n]``."""
        if self.disturbance_matrix is None:
            raise ValueError(f"{type(self).__name__} was built without a disturbance_bound")
        M = self.disturbance_matrix.to(x)
        check_last_dim("w", w, M.shape[1])
        check_same("x", x, "w", w)
        check_batch_match("x", x, "w", w)
        return w @ M.mT

    @property
    def has_diffusion(self) -> bool:
        """Whether the model is an SDE (has ``sigma``: given at construction, or a subclass's
        own :meth:`sigma`)."""
        if type(self).sigma is not ControlAffine.sigma:
            return True
        return self._sigma_fn is not None or self.sigma_matrix is not None

    def sigma(self, x: Tensor) -> Tensor | None:
        """Diffusion ``sigma(x) -> [..., n, q]``, or ``None`` for an ODE."""
        if self._sigma_fn is not None:
            s = self._sigma_fn(x)
            if s is None:
                return None
            if not isinstance(s, Tensor):
                raise TypeError(f"sigma(x) must return a tensor, got {type(s).__name__}")
            n = self.state_dim
            if s.dim() != x.dim() + 1 or s.shape[-2] != n or s.shape[:-2] != x.shape[:-1]:
                raise ValueError(
                    f"sigma(x) must return [..., {n}, q] with the batch of x "
                    f"{tuple(x.shape)}, got {tuple(s.shape)} (a constant matrix: expand it "
                    "to the batch, or give sigma as a tensor)"
                )
            return s if s.dtype == x.dtype else s.to(x.dtype)
        if self.sigma_matrix is None:
            return None
        s = self.sigma_matrix.to(x)
        return s.expand(*x.shape[:-1], *s.shape)

    def clamp_control(self, u: Tensor) -> Tensor:
        """Clip ``u [..., m]`` to ``[u_min, u_max]`` (unchanged where a limit is ``None``)."""
        return clamp_control(u, self.u_min, self.u_max)

    def extra_repr(self) -> str:
        return f"state_dim={self.state_dim}, control_dim={self.control_dim}"


#: the family whose rules :func:`torchcbf._checks.reapply_rules` applies to a subclass
ControlAffine.rules_base = ControlAffine


def register_constant(
    module: nn.Module, name: str, value: float | Tensor, *, positive: bool = False
) -> Tensor:
    """Store a model constant (scalar or tensor) on ``module`` by the rules of
    :func:`torchcbf._constants.store`, in float64: a number or a tensor becomes a float64
    buffer (a number exact in it; a model cast to float32 and back keeps the float32
    rounding), an ``nn.Parameter`` is registered as given (trained with the model), a tensor
    that requires grad keeps its gradient. NaN or inf (and, with
    ``positive``, a value ``<= 0``) raises ``ValueError`` naming ``name``."""
    if isinstance(value, bool):
        raise TypeError(f"{name} must be a number or a tensor, got bool")
    t = store(module, name, value, dtype=torch.float64)
    if positive and t.device.type != "meta" and bool((t.detach() <= 0).any()):
        raise ValueError(f"{name} must be positive, got {t.detach().tolist()}")
    return t


def _sigma_matrix(sigma: float | Tensor, n: int) -> Tensor:
    s = check_finite("sigma", as_tensor("sigma", sigma, dtype=torch.float64))
    if s.dim() == 1 and s.shape[0] != n:
        raise ValueError(f"sigma as a vector must have shape [{n}], got {tuple(s.shape)}")
    if s.dim() <= 1 or (s.dim() == 2 and s.shape[0] == n):
        return matrix_shape(s, n)
    raise ValueError(f"sigma must be a scalar, [{n}], [{n}, q] or a callable, got {tuple(s.shape)}")
