"""Condition modes of :class:`~torchcbf.filters.SafetyFilter`: one small object per mode.

A mode turns the Lie terms of the barriers and Lyapunov functions into affine conditions
``a . u + b`` (see :mod:`torchcbf.filters.conditions` for the formulas) and holds the
mode's own parameters. The four built-in modes are :class:`Vanilla`, :class:`Robust`,
:class:`Stochastic` (``beta``) and :class:`RiskAware` (``rho``, ``horizon``, ``eta``, ...).

A new mode subclasses :class:`FilterMode` and writes :meth:`~FilterMode.cbf` (and
:meth:`~FilterMode.clf` if it supports Lyapunov functions); docs/filters.md shows one.
"""

from __future__ import annotations

import copy
import numbers
from collections.abc import Callable, Sequence
from typing import Any, ClassVar

import torch
from torch import Tensor, nn
from torch._subclasses.fake_tensor import is_fake

from torchcbf._checks import (
    ClosedForms,
    TracksShadows,
    apply_rules,
    as_tensor,
    behaves_as,
    check_last_dim,
    check_number,
)
from torchcbf._constants import store
from torchcbf.barriers.lie import LieFunction, LieTerms
from torchcbf.barriers.native import Affine
from torchcbf.dynamics.base import ControlAffine
from torchcbf.filters.class_k import LinearClassK
from torchcbf.filters.conditions import Condition, cbf_condition, clf_condition
from torchcbf.filters.risk import local_margin, noise_bound, risk_margin

Gain = Callable[[Tensor], Tensor]


def _check_k(name: str, value: Tensor | None, k: int) -> None:
    if value is not None and value.dim() == 1 and value.shape[0] != k:
        raise ValueError(
            f"{name} must be a scalar or have one entry per barrier output ({k}), "
            f"got shape {tuple(value.shape)}"
        )


def _like(value: Tensor | None, ref: Tensor) -> Tensor | None:
    return None if value is None else value.to(ref)


class FilterMode(TracksShadows):
    """Base of the condition modes. Subclasses set :attr:`name` and write :meth:`cbf`;
    :attr:`needs_hessian` asks the filter for ``hess_trace`` in the Lie terms."""

    name: str = ""
    needs_hessian: bool = False
    #: a filter has bound it (:func:`bind_mode`)
    _bound: bool = False
    #: :meth:`affine_cbf` is trusted only where the class defining it also defines
    #: :meth:`cbf` (see :func:`torchcbf._checks.honour_overrides`)
    closed_forms: ClassVar[ClosedForms] = {"affine_cbf": (("cbf",), ())}
    #: what :meth:`affine_cbf` answers for an instance that shadows :meth:`cbf` or another
    #: method of its class (``mode.cbf = ...``, see :func:`torchcbf._checks.unless_hooked`)
    hooked_forms: ClassVar[dict[str, object]] = {"affine_cbf": None}

    def __init_subclass__(cls, **kwargs: Any) -> None:
        super().__init_subclass__(**kwargs)
        apply_rules(cls, FilterMode)

    def bind(
        self,
        dynamics: ControlAffine,
        barriers: Sequence[LieFunction],
        lyapunovs: Sequence[LieFunction],
    ) -> None:
        """Check the mode against the filter's model and functions (called once, at the
        filter's construction); raise ``ValueError`` if it does not apply."""

    def cbf(self, terms: LieTerms, alpha: Gain, dynamics: ControlAffine, x: Tensor) -> Condition:
        """CBF condition ``a . u + b >= 0`` for ``k``-output terms (``h [B, k]``) at ``x [B, n]``;
        ``alpha`` maps ``h [B, k]`` to ``[B, k]``."""
        raise NotImplementedError

    def clf(self, terms: LieTerms, rate: Gain, dynamics: ControlAffine, x: Tensor) -> Condition:
        """CLF condition ``a . u + b <= 0`` for ``V [B, c]`` (relaxed by the filter)."""
        raise NotImplementedError(f"mode {self.name!r} does not take Lyapunov functions")

    def affine_cbf(self, alpha: nn.Module) -> Affine | None:
        """:meth:`cbf` with the class-K function ``alpha`` as an :class:`Affine` combination
        of the Lie terms, where it is one; ``None`` (the default) otherwise. The filter then
        evaluates the condition of quadric barriers in the Lie terms' C kernel
        (:func:`torchcbf.barriers.native.cbf_conditions`); the two must agree."""
        return None

    def extra_repr(self) -> str:
        return self.name


#: the family whose rules :func:`torchcbf._checks.reapply_rules` applies to a subclass
FilterMode.rules_base = FilterMode


class Vanilla(FilterMode):
    """``L_f h + dh/dt + L_g h u + alpha(h) >= 0``; CLF ``LV + L_g V u + c(V) <= delta``."""

    name = "vanilla"

    def cbf(self, terms: LieTerms, alpha: Gain, dynamics: ControlAffine, x: Tensor) -> Condition:
        return cbf_condition(terms, "vanilla", alpha, dynamics, x)

    def clf(self, terms: LieTerms, rate: Gain, dynamics: ControlAffine, x: Tensor) -> Condition:
        return clf_condition(terms, "vanilla", rate, dynamics, x)

    def affine_cbf(self, alpha: nn.Module) -> Affine | None:
        gain = _linear_gain(alpha)
        return None if gain is None else Affine(gain=gain)


class Robust(FilterMode):
    """Vanilla minus the worst case of the bounded disturbance ``M w`` (needs dynamics built
    with ``disturbance_bound=``)."""

    name = "robust"

    def bind(
        self,
        dynamics: ControlAffine,
        barriers: Sequence[LieFunction],
        lyapunovs: Sequence[LieFunction],
    ) -> None:
        if dynamics.disturbance_bound is None:
            raise ValueError(
                "mode='robust' needs dynamics built with disturbance_bound= (and optionally "
                "disturbance_matrix=)"
            )

    def cbf(self, terms: LieTerms, alpha: Gain, dynamics: ControlAffine, x: Tensor) -> Condition:
        return cbf_condition(terms, "robust", alpha, dynamics, x)

    def clf(self, terms: LieTerms, rate: Gain, dynamics: ControlAffine, x: Tensor) -> Condition:
        return clf_condition(terms, "robust", rate, dynamics, x)


def _linear_gain(alpha: nn.Module) -> Tensor | None:
    """The gain of ``alpha`` where it behaves as :class:`LinearClassK`, else ``None``."""
    return alpha.gain if behaves_as(alpha, LinearClassK, ("forward", "_phi", "gain")) else None


def _needs_diffusion(name: str, dynamics: ControlAffine) -> None:
    if not dynamics.has_diffusion:
        raise ValueError(f"mode={name!r} needs dynamics with a diffusion (sigma=)")


class Stochastic(FilterMode):
    """Adds ``tr(sigma' d2h/dx2 sigma) / 2`` and subtracts the margin ``beta`` (scalar or
    ``[k]``, default 0) from the CBF condition (needs dynamics with ``sigma``)."""

    name = "stochastic"
    needs_hessian = True

    def __init__(self, beta: float | Sequence[float] | Tensor = 0.0) -> None:
        super().__init__()
        # a parameter is trained, a tensor that requires grad keeps its graph
        store(self, "beta", beta, dtype=torch.float64)
        if self.beta.dim() > 1:
            raise ValueError(f"beta must be a scalar or [k], got shape {tuple(self.beta.shape)}")

    def bind(
        self,
        dynamics: ControlAffine,
        barriers: Sequence[LieFunction],
        lyapunovs: Sequence[LieFunction],
    ) -> None:
        _needs_diffusion(self.name, dynamics)

    def cbf(self, terms: LieTerms, alpha: Gain, dynamics: ControlAffine, x: Tensor) -> Condition:
        _check_k("beta", self.beta, terms.h.shape[-1])
        return cbf_condition(terms, "stochastic", alpha, dynamics, x, beta=self.beta.to(x))

    def clf(self, terms: LieTerms, rate: Gain, dynamics: ControlAffine, x: Tensor) -> Condition:
        return clf_condition(terms, "stochastic", rate, dynamics, x)

    def affine_cbf(self, alpha: nn.Module) -> Affine | None:
        gain = _linear_gain(alpha)
        if gain is None:
            return None
        return Affine(trace_weight=0.5, gain=gain, offset=self.beta, offset_scale=-1.0)


def _keep_bound(mode: nn.Module, name: str, eta: object) -> None:
    """Keep a noise bound as given: a tensor by :func:`~torchcbf._constants.store`'s rules
    (a parameter is trained, a tensor that requires grad keeps its graph), anything else as
    the attribute (numbers, sequences, ``None``); checked (:func:`_checked_bound`)."""
    if eta is not None:
        _checked_bound(name, eta)
    if isinstance(eta, Tensor):
        store(mode, name, eta)
    else:
        setattr(mode, name, eta)


def _identity(value: object) -> object:
    """What tells a constant apart from its later values: a small CPU tensor's values (a
    write through ``.data`` or a NumPy view does not bump its version), another tensor's
    storage and version (on a GPU, change it by tensor operations), else the value."""
    if isinstance(value, Tensor):
        v = value.detach()
        if v.device.type == "cpu" and v.numel() <= 64:
            return (v.dtype, tuple(v.reshape(-1).tolist()))
        return (v.data_ptr(), v._version, v.dtype, v.device)
    return value if value is None or isinstance(value, float) else repr(value)


def _checked_bound(name: str, eta: object) -> Tensor:
    """``eta`` as a float64 tensor (scalar or ``[k]``, finite, non-negative), its graph
    kept."""
    bound = as_tensor(name, eta, dtype=torch.float64)
    if bound.dim() > 1 or not bool((bound.detach() >= 0).all() & bound.detach().isfinite().all()):
        raise ValueError(
            f"{name} must be a finite non-negative scalar or [k], got {bound.detach().tolist()}"
        )
    return bound


def _check_risk(name: str, rho: object) -> float:
    """A probability bound in ``(0, 1)`` whose ``erfinv(1 - rho)`` is finite in float64
    (``rho`` at least about 1.1e-16), as a float."""
    if isinstance(rho, Tensor):
        if rho.requires_grad or rho.numel() != 1:
            raise TypeError(f"{name} must be a number (a tensor of one value, without grad)")
        rho = rho.item()
    if isinstance(rho, bool) or not isinstance(rho, numbers.Real) or not 0 < rho < 1:
        raise ValueError(f"{name} must be a number in (0, 1), got {rho!r}")
    if 1.0 - float(rho) == 1.0:
        raise ValueError(f"{name}={rho!r} is 0 to float64 (1 - {name} == 1): give at least 1.2e-16")
    return float(rho)


class RiskAware(FilterMode):
    """Risk-aware conditions: leave the safe set within ``horizon`` with probability at most
    ``rho`` (needs dynamics with ``sigma``); ``alpha`` is unused.

    Args:
        rho: probability bound in ``(0, 1)``.
        horizon: ``T > 0``.
        eta: noise bound ``|dh/dx sigma| <= eta`` on the safe set, scalar or ``[k]``; or
            ``"local"``: each row's own ``|dh/dx(x) sigma(x)|`` at its state, so the margin
            ``Delta(x) = sqrt(2 T) |dh/dx(x) sigma(x)| erfinv(1 - rho)`` follows the noise
            the barrier feels where the robot is (a berth of the same width in state units
            wherever the barrier's gradient changes, where one constant ``eta`` sized by the
            steepest point widens it elsewhere). The bound on leaving ``{h >= 0}`` within
            ``T`` then holds for the windows in which ``|dh/dx sigma|`` stays at most its value
            at the window's start (:func:`~torchcbf.filters.risk.local_margin`); it is a
            local approximation, not the global guarantee of a constant ``eta``. The C
            condition kernel evaluates the margin with the conditions (the norm of
            ``sigma' dh/dx`` it has, :attr:`~torchcbf.barriers.native.Affine.noise_scale`).
            Or
        safe_states: ``[N, n]`` sample states to compute it with :func:`noise_bound` (when
            the filter binds the mode; one of the two is required with barriers).
        clf_rho, clf_eta, clf_gamma: risk-aware CLF: risk (default ``rho``), noise bound of
            ``V`` (default: :func:`noise_bound` over ``safe_states``), goal level ``gamma``
            of ``{V <= gamma}`` (default 0; a number, or a scalar or ``[k]`` tensor, whose
            graph is kept).
    """

    name = "risk_aware"
    needs_hessian = True

    def __init__(
        self,
        rho: float,
        horizon: float,
        eta: float | Sequence[float] | Tensor | None = None,
        *,
        safe_states: Tensor | None = None,
        clf_rho: float | None = None,
        clf_eta: float | Sequence[float] | Tensor | None = None,
        clf_gamma: float = 0.0,
    ) -> None:
        super().__init__()
        self.rho = _check_risk("rho", rho)
        if horizon is None:
            raise ValueError("horizon (T > 0) is required for RiskAware")
        T = check_number("horizon", horizon, low=0.0, strict=True)
        self.register_buffer("horizon", torch.tensor(T, dtype=torch.float64))
        self._scale_of: tuple[float, float, float] | None = None  # (rho, T, local scale)
        if isinstance(eta, str) and eta != "local":
            raise ValueError(f"eta must be a bound (number or [k]) or 'local', got {eta!r}")
        #: each row's margin from its own ``|dh/dx sigma|`` (``eta="local"``)
        self.local = isinstance(eta, str)
        _keep_bound(self, "eta", None if self.local else eta)
        self.safe_states = safe_states
        self.clf_rho = self.rho if clf_rho is None else _check_risk("clf_rho", clf_rho)
        _keep_bound(self, "clf_eta", clf_eta)
        if isinstance(clf_gamma, bool) or not isinstance(clf_gamma, (numbers.Real, Tensor)):
            raise TypeError(
                f"clf_gamma must be a number or a tensor, got {type(clf_gamma).__name__}"
            )
        if isinstance(clf_gamma, Tensor) and clf_gamma.dim() > 1:
            raise ValueError(f"clf_gamma must be a scalar or [k], got {tuple(clf_gamma.shape)}")
        store(self, "clf_gamma", clf_gamma, dtype=torch.float64)  # a tensor keeps its graph
        # noise bounds computed over safe_states when a filter binds the mode
        self.register_buffer("cbf_noise_bound", None)
        self.register_buffer("clf_noise_bound", None)
        self._binds: tuple[bool, bool] = (False, False)  # (barriers, lyapunovs)
        self._margins: dict[str, tuple[tuple, Tensor]] = {}

    def bind(
        self,
        dynamics: ControlAffine,
        barriers: Sequence[LieFunction],
        lyapunovs: Sequence[LieFunction],
    ) -> None:
        _needs_diffusion(self.name, dynamics)
        states = self.safe_states
        if states is not None:
            check_last_dim("safe_states", states, dynamics.state_dim)
        if barriers and not self.local:
            self.cbf_noise_bound = self._noise_bound(
                "eta",
                self.eta,
                barriers,
                dynamics,
                safe_only=True,
                missing="RiskAware needs eta= (noise bound |dh/dx sigma| on the safe "
                "set) or safe_states= (sample states to compute it from)",
            )
        if lyapunovs:
            self.clf_noise_bound = self._noise_bound(
                "clf_eta",
                self.clf_eta,
                lyapunovs,
                dynamics,
                safe_only=False,
                missing="RiskAware with lyapunovs needs clf_eta= (bound on "
                "|dV/dx sigma|) or safe_states=",
            )
        self._binds = (bool(barriers) and not self.local, bool(lyapunovs))

    def _noise_bound(
        self,
        name: str,
        eta: Tensor | float | Sequence[float] | None,
        functions: Sequence[LieFunction],
        dynamics: ControlAffine,
        *,
        safe_only: bool,
        missing: str,
    ) -> Tensor | None:
        """The bound of ``functions`` computed over ``safe_states`` (on its safe points only
        where ``safe_only``) where ``eta`` is not given (``None`` where it is: it is read at
        each call, checked here); ``missing`` is the error where neither is given."""
        if eta is not None:
            _checked_bound(name, eta)
            return None
        if self.safe_states is None:
            raise ValueError(missing)
        parts = [
            noise_bound(fn, dynamics, self.safe_states, safe_only=safe_only).reshape(-1)
            for fn in functions
        ]
        return torch.cat(parts).to(torch.float64)

    @property
    def cbf_margin(self) -> Tensor | None:
        """``Delta [k] = sqrt(2 T) eta erfinv(1 - rho)`` of the barriers from ``eta`` (or the
        bound computed over ``safe_states``), ``rho`` and ``horizon`` as they are now (so a
        trained or edited ``eta`` or ``horizon`` is used, with its gradient); ``None``
        before a filter binds the mode and with ``eta="local"``."""
        if not self._binds[0]:
            return None
        return self._margin("eta", self.eta, self.cbf_noise_bound, self.rho)

    @property
    def clf_margin(self) -> Tensor | None:
        """The CLF's ``Delta`` from ``clf_eta``, ``clf_rho`` and ``horizon`` (as
        :attr:`cbf_margin`); ``None`` without Lyapunov functions."""
        if not self._binds[1]:
            return None
        return self._margin("clf_eta", self.clf_eta, self.clf_noise_bound, self.clf_rho)

    def _margin(self, name: str, eta: object, computed: Tensor | None, rho: float) -> Tensor:
        """``Delta`` of a bound (``eta`` given, else ``computed``); kept until ``eta``, the
        bound, ``rho`` or ``horizon`` changes, and made afresh where one requires grad."""
        source = computed if eta is None else eta
        graph = self.horizon.requires_grad or (isinstance(source, Tensor) and source.requires_grad)
        # traced (torch.compile, or make_fx on fake tensors): the graph makes it each call
        keep = not (graph or torch.compiler.is_compiling() or is_fake(self.horizon))
        if keep:
            key = (name, rho, _identity(self.horizon), _identity(source))
            kept = self._margins.get(name)
            if kept is not None and kept[0] == key:
                return kept[1]
        margin = risk_margin(as_tensor(name, source, dtype=torch.float64), rho, self.horizon)
        if keep:
            self._margins[name] = (key, margin)
        return margin

    def cbf(self, terms: LieTerms, alpha: Gain, dynamics: ControlAffine, x: Tensor) -> Condition:
        if self.local:
            margin = local_margin(terms.dhdx, dynamics.sigma(x), self.rho, self.horizon.to(x))
        else:
            _check_k("eta", self.cbf_margin, terms.h.shape[-1])
            margin = _like(self.cbf_margin, x)
        return cbf_condition(
            terms, "risk_aware", alpha, dynamics, x, margin=margin, horizon=_like(self.horizon, x)
        )

    def _local_scale_number(self, T: float) -> float:
        """``sqrt(2 T) erfinv(1 - rho)`` (:func:`~torchcbf.filters.risk.local_margin` per unit
        of noise) as a number for horizon ``T``, kept until ``rho`` or ``T`` changes (a
        loaded state or a new value in place)."""
        if self._scale_of is None or self._scale_of[:2] != (self.rho, T):
            one = torch.ones((), dtype=torch.float64)
            self._scale_of = (self.rho, T, float(risk_margin(one, self.rho, T)))
        return self._scale_of[2]

    def margin_at(
        self, barrier: LieFunction, dynamics: ControlAffine, x: Tensor, t: Tensor | float = 0.0
    ) -> Tensor:
        """The CBF margin ``Delta`` of ``barrier`` (the filter's barriers, one module) at states
        ``x [..., n]``: ``[..., k]`` (the constant margin broadcast, or the local one)."""
        if not self.local:
            if self.cbf_margin is None:
                raise ValueError("the mode has no CBF margin until a filter binds it")
            margin = self.cbf_margin.to(x)
            if margin.dim() == 0:  # one margin for every output: count them
                h = barrier(x, t)
                margin = margin.expand(h.shape[-1] if h.dim() == x.dim() else 1)
            return margin.expand(*x.shape[:-1], -1)
        terms = barrier.lie(x, dynamics, t, hessian=False)
        dhdx = terms.dhdx if terms.dhdx.dim() == x.dim() + 1 else terms.dhdx.unsqueeze(-2)
        return local_margin(dhdx, dynamics.sigma(x), self.rho, self.horizon.to(x))

    def clf(self, terms: LieTerms, rate: Gain, dynamics: ControlAffine, x: Tensor) -> Condition:
        _check_k("clf_eta", self.clf_margin, terms.h.shape[-1])
        _check_k("clf_gamma", self.clf_gamma, terms.h.shape[-1])
        return clf_condition(
            terms,
            "risk_aware",
            rate,
            dynamics,
            x,
            margin=_like(self.clf_margin, x),
            gamma=_like(self.clf_gamma, x),
            horizon=_like(self.horizon, x),
        )

    def affine_cbf(self, alpha: nn.Module) -> Affine | None:
        margin = None if self.local else self.cbf_margin
        if self.horizon.requires_grad or (margin is None and not self.local):
            return None
        if margin is not None and margin.requires_grad:
            return None  # the kernel does not differentiate the margin
        T = float(self.horizon)
        rate = 1.0 / T
        if self.local:  # Delta(x) = scale |sigma' dh/dx|
            noise = -rate * self._local_scale_number(T)
            return Affine(trace_weight=0.5, gain_scale=rate, noise_scale=noise)
        return Affine(trace_weight=0.5, gain_scale=rate, offset=margin,
                      offset_scale=-rate)  # fmt: skip

    def extra_repr(self) -> str:
        local = ", eta='local'" if self.local else ""
        return f"rho={self.rho}, horizon={float(self.horizon)}{local}"


#: the names ``SafetyFilter(mode=...)`` takes for a mode with its default options
MODE_NAMES = ("vanilla", "robust", "stochastic", "risk_aware")


def bind_mode(
    spec: str | FilterMode,
    dynamics: ControlAffine,
    barriers: Sequence[LieFunction],
    lyapunovs: Sequence[LieFunction],
) -> FilterMode:
    """The mode of ``spec`` (:func:`make_mode`) bound to a filter's model and functions
    (:meth:`FilterMode.bind`). Binding may store what it derives on the mode (the margins of
    :class:`RiskAware`), so a mode another filter holds is copied first; the copy shares the
    original's tensors that require grad."""
    mode = make_mode(spec)
    if mode._bound:
        shared = {id(t): t for t in (*mode.parameters(), *mode.buffers()) if t.requires_grad}
        mode = copy.deepcopy(mode, shared)
    mode.bind(dynamics, barriers, lyapunovs)
    mode._bound = True
    return mode


def make_mode(mode: str | FilterMode) -> FilterMode:
    """``mode`` itself, or the mode of a name with its default options (``"stochastic"``:
    ``beta = 0``; ``"risk_aware"`` has no defaults and needs its object)."""
    if isinstance(mode, FilterMode):
        return mode
    if mode == "vanilla":
        return Vanilla()
    if mode == "robust":
        return Robust()
    if mode == "stochastic":
        return Stochastic()
    if mode == "risk_aware":
        raise ValueError(
            "the risk-aware mode needs its parameters: mode=RiskAware(rho=..., horizon=..., "
            "eta=...)"
        )
    raise ValueError(f"mode must be one of {MODE_NAMES} or a FilterMode, got {mode!r}")
