"""Relative-degree rectification: high-order (HOCBF) and exponential (ECBF) barriers.

A barrier whose control input appears only after ``r`` time derivatives gives a CBF
condition with ``L_g h = 0``; :func:`rectify` turns it into a relative-degree-one barrier.
Everything is built from :class:`LieDerivative` modules (``D h = L_f h + dh/dt``, computed
by nested autograd with ``create_graph``), so the result is itself a :class:`Barrier`:
its own ``lie`` works (``hess_trace`` included) and it differentiates w.r.t. the original
barrier's parameters.
"""

from __future__ import annotations

import functools
import warnings
from collections.abc import Sequence
from typing import ClassVar, Literal

import numpy as np
import torch
from torch import Tensor, nn

from torchcbf._checks import ClosedForms, as_tensor, check_finite, check_int
from torchcbf._constants import DerivedConstants, derive, remember, store
from torchcbf.barriers._params import float_spec
from torchcbf.barriers.base import Barrier
from torchcbf.barriers.lie import (
    AnalyticDerivatives,
    FollowsTime,
    FunctionPart,
    LieFunction,
    LieMethod,
    flat_parts,
    gradient_rows,
    per_output,
    terms_of,
)
from torchcbf.dynamics.base import ControlAffine

Form = Literal["high_order", "exponential"]
GainSpec = float | Sequence[float] | Tensor | None


def _method(fn: LieFunction) -> LieMethod:
    """Closed forms where ``fn`` has them (a plain, differentiable tensor expression, so the
    outer derivatives of the rectified barrier need no nested backward pass through it)."""
    return "analytic" if fn.has_analytic else "autograd"


class LieDerivative(Barrier):
    """The drift derivative ``D h = L_f h + dh/dt`` of a barrier as a new barrier module.

    For a barrier of relative degree ``r > 1``, ``D^k h = L_f^k h`` (plus time terms) is the
    ``k``-th time derivative of ``h`` along any trajectory, for ``k < r``.
    Shapes follow the inner barrier (``[...]`` or ``[..., k]``).
    """

    time_varying = FollowsTime(lambda self: self.barrier.time_varying)

    def __init__(self, barrier: LieFunction, dynamics: ControlAffine) -> None:
        super().__init__()
        self.barrier = barrier
        self.dynamics = dynamics

    def forward(self, x: Tensor, t: Tensor | float | None = None) -> Tensor:
        """``x [..., n] -> D h [...]`` (or ``[..., k]``)."""
        terms = terms_of(
            self.barrier, x, self.dynamics, t, method=_method(self.barrier), hessian=False,
            control=False,
        )  # fmt: skip
        return terms.lfh + terms.dhdt

    def parts(self) -> list[LieFunction] | None:
        if self.barrier.parts() is None or self.barrier.has_analytic:
            return None  # evaluated whole: its k outputs share one evaluation per call
        return [LieDerivative(p, self.dynamics) for p in flat_parts(self.barrier)]


def _gain_tensor(
    module: nn.Module, name: str, gains: GainSpec, count: int, default: float
) -> Tensor:
    """Register ``count`` gains (a number is repeated): Python numbers as a buffer exact
    under ``.double()``, a tensor as a buffer, and one that requires grad (an
    ``nn.Parameter``, a tensor with a graph) kept as given and repeated at each read
    (:func:`~torchcbf._constants.derive`), so that it trains."""
    if gains is None:
        gains = default
    if isinstance(gains, Tensor) and gains.requires_grad:
        check = functools.partial(_gains, name=name, count=count)
        out = derive(module, name, gains, check, shape=functools.partial(_repeated, count=count))
        assert out is not None
        return out
    device, dtype = float_spec(module)
    given = isinstance(gains, Tensor)
    value = _gains(
        as_tensor(name, gains, dtype=dtype if given else torch.float64, device=device),
        name=name,
        count=count,
    ).clone()
    if given:
        module.register_buffer(name, value)
    else:  # Python numbers: exact under .double()
        remember(module, name, value, dtype=dtype, device=device)
    return getattr(module, name)


def _repeated(value: Tensor, *, count: int) -> Tensor:
    """A scalar repeated ``[count]`` (gains checked by :func:`_gains`)."""
    return value.expand(count) if value.dim() == 0 else value


def _gains(value: Tensor, *, name: str, count: int) -> Tensor:
    """``value`` checked and, a scalar, repeated: ``[count]``."""
    check_finite(name, value)
    if value.dim() == 0:
        return _repeated(value, count=count)
    if value.shape != (count,):
        raise ValueError(
            f"{name} must be a number or have {count} entries, got shape {tuple(value.shape)}"
        )
    return value


class HighOrderBarrier(Barrier, DerivedConstants):
    """High-order CBF (Xiao & Belta) with linear class-K gains.

    ``psi_0 = h``, ``psi_i = D psi_{i-1} + alpha_i psi_{i-1}`` for ``i = 1..r-1``; this module
    is ``psi_{r-1}`` (relative degree one). Enforcing ``D psi + L_g psi u >= -alpha_r psi``
    on it keeps every ``psi_i >= 0``, hence ``h >= 0``, from a start where all are ``>= 0``.

    Args:
        barrier: the original barrier (``[...]`` or ``[..., k]``).
        dynamics: the model.
        relative_degree: ``r >= 2``.
        gains: ``alpha_1..alpha_{r-1} > 0``: a number (all equal, default 1) or ``r - 1``
            numbers / a tensor / an ``nn.Parameter`` (then learnable).
    """

    time_varying = FollowsTime(lambda self: self.barrier.time_varying)

    def __init__(
        self,
        barrier: LieFunction,
        dynamics: ControlAffine,
        relative_degree: int,
        gains: GainSpec = None,
    ) -> None:
        super().__init__()
        relative_degree = check_int(
            "relative_degree", relative_degree, low=2, what="an int >= 2 for a high-order barrier"
        )
        self.barrier = barrier
        self.dynamics = dynamics
        self.relative_degree = relative_degree
        g = _gain_tensor(self, "gains", gains, relative_degree - 1, 1.0)
        if bool((g.detach() <= 0).any()):
            raise ValueError(f"gains must be positive, got {g.detach().tolist()}")

    def psi(
        self, x: Tensor, t: Tensor | float | None, order: int, base: LieFunction | None = None
    ) -> Tensor:
        """``psi_order(x, t)`` for ``0 <= order <= r - 1`` (of ``base``, default the barrier)."""
        base = self.barrier if base is None else base
        if order == 0:
            return base(x, t)
        # psi_0 is the barrier itself, whose own ``lie`` (where it has one) gives its terms
        step = base if order == 1 else _Psi(self, order - 1, base)
        terms = terms_of(step, x, self.dynamics, t, hessian=False, control=False)
        return terms.lfh + terms.dhdt + self.gains[order - 1].to(x) * terms.h

    def forward(self, x: Tensor, t: Tensor | float | None = None) -> Tensor:
        """``x [..., n] -> psi_{r-1} [...]`` (or ``[..., k]``)."""
        return self.psi(x, t, self.relative_degree - 1)

    def parts(self) -> list[LieFunction] | None:
        if self.barrier.parts() is None or self.barrier.has_analytic:
            return None  # evaluated whole: its k outputs share one evaluation per call
        r = self.relative_degree
        return [
            FunctionPart(functools.partial(self.psi, order=r - 1, base=p), self.time_varying)
            for p in flat_parts(self.barrier)
        ]


class _Psi(LieFunction):
    """``psi_order`` of a :class:`HighOrderBarrier` as a function (a view, not a copy)."""

    time_varying = FollowsTime(lambda self: self._parent.time_varying)

    def __init__(self, parent: HighOrderBarrier, order: int, base: LieFunction) -> None:
        super().__init__()
        object.__setattr__(self, "_parent", parent)  # not a submodule: no cycle
        object.__setattr__(self, "_base", base)
        self.order = order

    def forward(self, x: Tensor, t: Tensor | float | None = None) -> Tensor:
        return self._parent.psi(x, t, self.order, self._base)


class ExponentialBarrier(Barrier):
    """Exponential CBF (Nguyen & Sreenath) in relative-degree-one form.

    ``h_e = D^{r-1} h + k_{r-2} D^{r-2} h + ... + k_0 h`` (``D = L_f + d/dt``): the polynomial
    ``s^{r-1} + k_{r-2} s^{r-2} + ... + k_0`` must be Hurwitz; with real negative roots
    ``-p_i`` the condition ``dh_e/dt >= -alpha h_e`` keeps ``h >= 0`` from a start where the
    chain of first-order factors is non-negative.

    Args:
        barrier, dynamics, relative_degree: as for :class:`HighOrderBarrier`.
        coefficients: ``[k_0, ..., k_{r-2}]`` (a tensor, or an ``nn.Parameter`` to learn them).
    """

    #: ``forward`` is :meth:`value`: a subclass that changes ``value`` loses the closed forms
    closed_forms: ClassVar[ClosedForms] = {
        **LieFunction.closed_forms,
        "derivatives": (("forward", "value"), ("has_analytic", "has_second_order")),
        "parts": (("forward", "value"), ()),
    }

    time_varying = FollowsTime(lambda self: self.barrier.time_varying)

    def __init__(
        self,
        barrier: LieFunction,
        dynamics: ControlAffine,
        relative_degree: int,
        coefficients: Tensor | Sequence[float],
    ) -> None:
        super().__init__()
        relative_degree = check_int(
            "relative_degree", relative_degree, low=2, what="an int >= 2 for an exponential barrier"
        )
        self.barrier = barrier
        self.dynamics = dynamics
        self.relative_degree = relative_degree
        if isinstance(coefficients, nn.Parameter):
            k = self.register_constant("coefficients", coefficients)
        elif isinstance(coefficients, Tensor):
            device, dtype = float_spec(self)
            k = self.register_constant("coefficients", coefficients.to(device, dtype))
        else:  # Python numbers: in the barrier's dtype, and exact under .double()
            values = [float(c) for c in coefficients]
            device, dtype = float_spec(self)  # the barrier's, before the new buffer counts
            store(self, "coefficients", values)
            exact = torch.tensor(values, dtype=torch.float64)
            self._buffers["coefficients"] = exact.to(device=device, dtype=dtype)
            k = self.coefficients
        if k.shape != (relative_degree - 1,):
            raise ValueError(
                f"coefficients must have {relative_degree - 1} entries [k_0, ..., k_(r-2)], "
                f"got shape {tuple(k.shape)}"
            )
        _check_hurwitz(k.detach())

    def value(self, x: Tensor, t: Tensor | float | None, base: LieFunction | None = None) -> Tensor:
        """``h_e(x, t)`` of ``base`` (default the barrier)."""
        r = self.relative_degree
        chain = [self.barrier if base is None else base]  # D^0 h .. D^{r-2} h
        for _ in range(r - 2):
            chain.append(LieDerivative(chain[-1], self.dynamics))
        terms = terms_of(
            chain[-1], x, self.dynamics, t, method=_method(chain[-1]), hessian=False,
            control=False,
        )  # fmt: skip
        k = self.coefficients.to(x)
        out = terms.lfh + terms.dhdt + k[r - 2] * terms.h  # D^{r-1} h + k_{r-2} D^{r-2} h
        for i in range(r - 2):
            out = out + k[i] * chain[i](x, t)
        return out

    def forward(self, x: Tensor, t: Tensor | float | None = None) -> Tensor:
        """``x [..., n] -> h_e [...]`` (or ``[..., k]``)."""
        return self.value(x, t)

    def parts(self) -> list[LieFunction] | None:
        if self.barrier.parts() is None or self.barrier.has_analytic:
            return None  # evaluated whole: its k outputs share one evaluation per call
        return [
            FunctionPart(functools.partial(self.value, base=p), self.time_varying)
            for p in flat_parts(self.barrier)
        ]

    @property
    def has_analytic(self) -> bool:
        """Closed forms for relative degree two, a time-invariant barrier with second-order
        closed forms and a model with closed-form drift derivatives (otherwise autograd)."""
        return (
            self.relative_degree == 2
            and not self.time_varying
            and self.barrier.has_second_order
            and self.dynamics.has_drift_derivatives
        )

    def derivatives(self, x: Tensor, t: Tensor) -> AnalyticDerivatives:
        """``h_e = L_f h + k_0 h`` with ``grad h_e = H f + J' grad h + k_0 grad h`` and
        ``tr(S' hess(h_e) S) = tr(S' (H'[f] + H J + J' H + sum_i grad_i h hess f_i + k_0 H) S)``
        (``H`` the barrier's Hessian, ``J = df/dx``), from the barrier's second-order closed
        forms and the model's drift derivatives."""
        if not self.has_analytic:
            return super().derivatives(x, t)
        d = self.barrier.derivatives(x, t)
        if d.hess_mat is None or d.hess_dir is None:
            raise ValueError(f"{type(self.barrier).__name__} gave no second-order closed forms")
        hess_dir = d.hess_dir
        f = self.dynamics.f(x)
        drift = self.dynamics.drift_derivatives(x)
        k0 = self.coefficients.to(x)[0]
        single, grad = gradient_rows(d, x)  # grad [..., k, n]
        n = x.shape[-1]
        # the Hessian once, as a matrix [..., (k,) n, n]: H f and H S are then one matmul each
        eye = torch.eye(n, dtype=x.dtype, device=x.device).expand(*x.shape[:-1], n, n)
        H = d.hess_mat(eye)

        def cols(m: Tensor) -> Tensor:  # [..., n, q] against H
            return m if single else m.unsqueeze(-3)

        h_e = per_output((grad * f.unsqueeze(-2)).sum(-1), single) + k0 * d.h
        hf = (H @ cols(f.unsqueeze(-1)))[..., 0]  # [..., (k,) n]
        dhdx = hf + per_output(grad @ drift.jac, single, -2) + k0 * d.dhdx

        mix = 2 * drift.jac + k0 * eye

        def quad(s: Tensor) -> Tensor:
            # tr(S' (H J + J' H + k_0 H) S) = sum(H S * (2 J + k_0 I) S), H symmetric
            first = ((H @ cols(s)) * cols(mix @ s)).sum((-2, -1))
            return hess_dir(f, s) + first + per_output(drift.hess_quad(grad, s), single)

        return AnalyticDerivatives(h_e, dhdx, torch.zeros_like(h_e), quad)


def _check_hurwitz(coefficients: Tensor) -> None:
    if not bool(torch.isfinite(coefficients).all()):
        raise ValueError(f"gains must be finite, got {coefficients.tolist()}")
    poly = np.concatenate([[1.0], coefficients.flip(0).cpu().double().numpy()])
    roots = np.roots(poly)
    if not bool(np.all(roots.real < 0)):
        raise ValueError(
            "exponential-CBF coefficients [k_0, ..., k_(r-2)] must make "
            f"s^(r-1) + ... + k_0 Hurwitz; its roots are {roots.tolist()}"
        )


def coefficients_from_poles(poles: Sequence[float] | Tensor) -> Tensor:
    """``[k_0, ..., k_{r-2}]`` of ``prod_i (s - p_i)`` for real negative poles ``p_i`` (in
    torch's default dtype)."""
    return torch.tensor(_pole_coefficients(poles), dtype=torch.get_default_dtype())


def _pole_coefficients(poles: Sequence[float] | Tensor) -> list[float]:
    """:func:`coefficients_from_poles` as Python numbers, which stay exact under
    ``.double()`` where a float32 tensor would keep its rounding (0.3 as 0.30000001)."""
    p = np.asarray(torch.as_tensor(poles, dtype=torch.float64).reshape(-1), dtype=np.float64)
    if p.size == 0 or not bool(np.all(np.isfinite(p))) or not bool(np.all(p < 0)):
        raise ValueError(f"poles must be finite negative real numbers, got {p.tolist()}")
    coeffs = np.poly(p)  # [1, c_{r-2}, ..., c_0]
    return [float(c) for c in coeffs[1:][::-1]]


#: scale, relative to the first derivative's, below which ``L_g`` of a higher one counts as
#: the round-off of a zero
_FLOOR = 1e-9


def find_relative_degree(
    barrier: LieFunction,
    dynamics: ControlAffine,
    samples: Tensor | int = 256,
    *,
    seed: int = 0,
    scale: float = 2.0,
    tol: float = 1e-6,
    time: Tensor | float | None = None,
) -> int:
    """Relative degree ``r`` of ``barrier`` w.r.t. ``dynamics``, by autograd on sample states.

    ``r`` is the least ``k`` with ``L_g D^{k-1} h`` non-zero at some sample: an entry above
    ``tol`` times its own scale ``sum_i |dD^{k-1}h/dx_i| |g_ij|`` (round-off is far below
    it, whatever the units of ``h``, of each state and of each control), and above ``1e-9``
    times the first derivative's largest scale (the round-off of an exact zero).

    Args:
        samples: states ``[N, n]``, or a number ``N`` of states drawn from
            ``N(0, scale^2 I)`` with ``seed``.
        time: times of the samples for time-varying barriers (default ``U(0, scale)``).

    Raises ``ValueError`` if the control does not appear within ``n`` derivatives, or if the
    outputs of a multi-output barrier have different relative degrees.
    """
    n = dynamics.state_dim
    device, dtype = float_spec(barrier)
    gen = torch.Generator(device=device).manual_seed(seed)
    if isinstance(samples, int):
        if samples < 1:
            raise ValueError(f"samples must be >= 1, got {samples}")
        x = scale * torch.randn(samples, n, generator=gen, device=device, dtype=dtype)
    else:
        x = samples
        dynamics.check_inputs(x)
    if time is None and barrier.time_varying:
        time = scale * torch.rand(x.shape[:-1], generator=gen, device=x.device, dtype=x.dtype)
    psi: LieFunction = barrier
    degree: Tensor | None = None
    with torch.no_grad():
        g_abs = dynamics.g(x).abs()
        first: Tensor | None = None
        for k in range(1, n + 1):
            terms = terms_of(psi, x, dynamics, time, hessian=False)
            lgh = terms.lgh.nan_to_num(0.0, 0.0, 0.0).abs()
            grad = terms.dhdx.nan_to_num(0.0, 0.0, 0.0).abs()
            rows = tuple(range(x.dim() - 1))
            # each entry's own scale sum_i |dpsi/dx_i| |g_ij|, whatever the units of x_i
            if grad.dim() == x.dim():
                ref = (grad.unsqueeze(-2) @ g_abs).squeeze(-2)  # [..., m]
            else:
                ref = grad @ g_abs  # [..., k, m]
            top = ref.amax(dim=(*rows, ref.dim() - 1))  # [] or [k]
            first = top if first is None else first
            # a derivative that is round-off of an exact zero is far below the first one's
            floor = _FLOOR * (first.unsqueeze(-1) if first.dim() else first)
            excess = lgh - tol * torch.maximum(ref, floor)
            found = excess.amax(dim=(*rows, lgh.dim() - 1)) > 0
            if degree is None:
                degree = torch.zeros_like(found, dtype=torch.long)
            degree = torch.where((degree == 0) & found, torch.full_like(degree, k), degree)
            if bool((degree > 0).all()):
                break
            # an output whose derivative does not depend on the state on any sample has no
            # degree to find (differentiating it further only costs: each level's autograd
            # nests the last one's)
            flat = (degree == 0) & (grad.amax(dim=(*rows, grad.dim() - 1)) == 0)
            if bool(flat.any()):
                which = flat.nonzero().flatten().tolist() if flat.dim() else []
                raise ValueError(
                    f"{'outputs ' + str(which) + ' of ' if which else ''}"
                    f"{type(barrier).__name__} do not depend on the state after {k - 1} "
                    "derivatives (d/dx = 0 on every sample): no relative degree; a barrier of "
                    "a frame that never moves (on the base's axis, say) is constant"
                )
            psi = LieDerivative(psi, dynamics)
    assert degree is not None
    if bool((degree == 0).any()):
        raise ValueError(
            f"the control of {type(dynamics).__name__} does not appear within {n} "
            f"derivatives of {type(barrier).__name__} (L_g L_f^k h = 0 on all samples): "
            "not a valid control barrier function for this model"
        )
    values = sorted(set(degree.reshape(-1).tolist()))
    if len(values) > 1:
        raise ValueError(
            f"the outputs of {type(barrier).__name__} have different relative degrees "
            f"{degree.tolist()}; rectify them separately"
        )
    return int(values[0])


def rectify(
    barrier: LieFunction,
    dynamics: ControlAffine,
    form: Form = "high_order",
    gains: GainSpec = None,
    *,
    relative_degree: int | None = None,
    poles: Sequence[float] | Tensor | None = None,
    samples: Tensor | int = 256,
    seed: int = 0,
    tol: float = 1e-6,
) -> LieFunction:
    """A relative-degree-one barrier from ``barrier``, detecting its relative degree.

    Args:
        barrier: the barrier ``h`` (``[...]`` or ``[..., k]``; all outputs of one degree).
        dynamics: the model.
        form: ``"high_order"`` (:class:`HighOrderBarrier`, ``gains`` = ``alpha_1..alpha_{r-1}``,
            default 1) or ``"exponential"`` (:class:`ExponentialBarrier`, ``gains`` =
            ``[k_0, ..., k_{r-2}]``, or ``poles`` = ``r - 1`` negative reals; default all
            poles at -1).
        relative_degree: skip detection and use this ``r``.
        samples, seed, tol: for :func:`find_relative_degree`.

    Returns:
        ``barrier`` itself when ``r = 1``, otherwise a new :class:`Barrier` holding it.
    """
    if form not in ("high_order", "exponential"):
        raise ValueError(f"form must be 'high_order' or 'exponential', got {form!r}")
    if poles is not None and form != "exponential":
        raise ValueError(f"poles are only for form='exponential', got form={form!r}")
    if poles is not None and gains is not None:
        raise ValueError("give poles= or gains=, not both")
    if relative_degree is None:
        r = find_relative_degree(barrier, dynamics, samples, seed=seed, tol=tol)
    else:
        relative_degree = check_int("relative_degree", relative_degree, low=1)
        if relative_degree > dynamics.state_dim:
            raise ValueError(
                f"relative_degree={relative_degree} exceeds the state dimension "
                f"{dynamics.state_dim}"
            )
        r = relative_degree
    if r == 1:  # nothing to build; what was given must still be valid
        if poles is not None:
            _pole_coefficients(poles)
        if gains is not None:
            g = as_tensor("gains", gains).detach()
            if not bool(torch.isfinite(g).all() & (g > 0).all()):
                raise ValueError(f"gains must be finite positive numbers, got {g.tolist()}")
        if gains is not None or poles is not None:
            warnings.warn(
                f"{type(barrier).__name__} has relative degree 1 along "
                f"{type(dynamics).__name__}: it is returned as it is, and the "
                f"{'gains' if gains is not None else 'poles'} given are not used",
                stacklevel=2,
            )
        return barrier
    if form == "high_order":
        return HighOrderBarrier(barrier, dynamics, r, gains)
    if gains is None:
        coefficients = _pole_coefficients([-1.0] * (r - 1) if poles is None else poles)
        if len(coefficients) != r - 1:
            raise ValueError(f"poles must hold r - 1 = {r - 1} values, got {len(coefficients)}")
    else:
        count = gains.numel() if isinstance(gains, Tensor) else np.asarray(gains).size
        if count != r - 1:
            raise ValueError(
                f"gains must hold r - 1 = {r - 1} values for form='exponential' (relative "
                f"degree {r}), got {count}"
            )
        if isinstance(gains, Tensor):
            coefficients = gains
        else:
            coefficients = [float(g) for g in np.asarray(gains, dtype=np.float64).reshape(-1)]
    return ExponentialBarrier(barrier, dynamics, r, coefficients)
