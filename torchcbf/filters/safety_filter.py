"""The CBF/CLF-QP safety filter: one batched, differentiable QP for a batch of states.

The pieces, each in its own module: the condition modes (:mod:`torchcbf.filters.modes`)
turn Lie terms into affine conditions ``a . u + b``; :mod:`torchcbf.filters.qp_data`
assembles the QP over ``z = [u; s; delta]`` (its docstring states it); the fallback policy
(:mod:`torchcbf.filters.fallback`) serves rows whose QP failed. This module ties them
together in :class:`SafetyFilter`.

CBF slacks (``slack``, a :class:`~torchcbf.filters.Slack` or its mode). ``"shared"``
(default): ONE slack ``s`` for all barrier rows with the exact penalty ``w rbar (s +
s^2/2)``: where the hard QP is infeasible, the elastic QP returns the least-violating
control (in the box, minimising the largest normalised violation, then the distance to
``u_nom``), with status ``RELAXED``. ``w = Slack.cbf_weight * (1 + v)`` (default 1e3), with
``v`` (detached, capped) an estimate of the hard multipliers; where the hard QP is feasible
and its multipliers stay below ``w`` the two solutions are equal (``s = 0``). A CLF can
pull against a CBF harder than that, so with Lyapunov functions (``Slack.exact=None``
default, or ``True``) the hard QP is stacked into the SAME :func:`~torchcbf.qp.solve_qp`
call and a row takes the hard solution wherever that one is ``SOLVED``; where it is not, the
elastic QP of the CBF rows alone is in the call too, and a row whose CLF pulled its
violation beyond that one's takes its control. ``"none"``: hard
rows only (infeasible rows fall back). ``"per_row"``: soft CBF rows, one slack each, ``1/2
w rbar |s|^2`` (``w`` default 1e2).

Statuses (:class:`FilterStatus`) per row: ``SOLVED`` (every hard constraint met),
``RELAXED`` (some CBF slack above ``Slack.tol``), ``FALLBACK`` (the QP did not return
``SOLVED``, or its data were non-finite: the fallback control is used), ``NON_FINITE``
(non-finite ``x``, ``u_nom`` or ``t`` in the row: fallback used; the row is sanitised
before any computation so the other rows and the gradients are untouched).

Real-time path: finite states on the CPU, at most ``torchcbf.filters.realtime.MAX_BATCH``,
with the default QP backend, whose conditions carry no gradient (grad mode off, or nothing
they depend on requires grad): one call of a C kernel assembles the QP, solves it by the dual
active-set method and computes the outputs (:mod:`torchcbf.filters.realtime`). A batch the
kernel does not certify completely (or with non-finite conditions) takes the general path,
which gives the same answers (in float32, up to the general path's float32 rounding). On at
most ``MAX_BATCH`` states with ``lie_method="auto"``, the Lie terms of quadric barriers (and
of their exponential CBFs) come from C too (:mod:`torchcbf.barriers.native`), with the
conditions where the mode's are affine in them (:meth:`FilterMode.affine_cbf`), in the same
call as the QP; every other case takes the torch closed forms and autograd.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Sequence
from enum import IntEnum
from typing import Any, Literal, NamedTuple

import torch
from torch import Tensor, nn

import torchcbf.qp as qp_layer
from torchcbf._autograd import forward_mode_active, refuse_transforms
from torchcbf._checks import (
    as_limit,
    as_matrix,
    as_tensor,
    broadcast_shapes,
    check_bounds,
    check_compile,
    check_last_dim,
    follow_parts,
    isfinite,
    limit_shape,
    matrix_shape,
    placement,
    rows_finite,
)
from torchcbf._compile import Traced, TraceError, logger
from torchcbf._constants import DerivedConstants, ExactConstants, derive
from torchcbf.barriers import native
from torchcbf.barriers.compiled import CompiledLie
from torchcbf.barriers.lie import LieFunction, LieTerms, own_lie, stacked_lie_derivatives
from torchcbf.dynamics.base import ControlAffine, matvec
from torchcbf.filters import realtime
from torchcbf.filters.class_k import ClassKSpec, _GainClassK, as_class_k
from torchcbf.filters.conditions import as_columns, concat_terms
from torchcbf.filters.fallback import Fallback, FallbackSpec
from torchcbf.filters.modes import FilterMode, bind_mode
from torchcbf.filters.qp_data import SLACK_MODES, Slack, SlackMode, assemble
from torchcbf.qp import Status
from torchcbf.qp import realtime as qp_realtime
from torchcbf.qp.solve import check_options

__all__ = ["FallbackSpec", "FilterOutput", "FilterStatus", "SafetyFilter"]

#: options of ``qp_options`` the real-time path honours (any other one: the general path)
_REALTIME_QP_OPTIONS = frozenset({"eps", "max_iter", "method", "backend", "check_every", "polish"})


class FilterStatus(IntEnum):
    """Per-row outcome of :class:`SafetyFilter` (``FilterOutput.status``, int64)."""

    SOLVED = 0
    RELAXED = 1
    FALLBACK = 2
    NON_FINITE = 3


class FilterOutput(NamedTuple):
    """Result of :meth:`SafetyFilter.forward` for a batch ``[...]``.

    Fields:
        u: filtered control ``[..., m]`` (never NaN).
        status: :class:`FilterStatus` codes ``[...]`` (int64).
        h: barrier values ``[..., k]`` (all barriers' outputs concatenated; NaN in rows with
            a non-finite state).
        slack: ``[..., k + c]``: CBF violations ``max(0, -(a . u + b))`` at the returned
            ``u`` (in the units of the condition), then the CLF relaxations ``delta_j``
            (zero in fallback rows).
        clf_value: Lyapunov values ``[..., c]``.
        qp_status: the QP's :class:`torchcbf.qp.Status` codes ``[...]`` (int64).
        constraint_value: ``[..., k + c]`` at the returned ``u``: ``a . u + b`` for CBF rows
            and ``-(a . u + b)`` for CLF rows, so ``>= 0`` means the condition holds
            without slack.
        path: what answered, ``"<lie>/<qp>"``: ``<lie>`` is ``native`` (the Lie terms and
            conditions of every function from the C Lie kernel), ``compiled`` (from one
            compiled call, ``compile=True``), ``torch`` (closed forms or autograd in torch) or
            ``mixed``; ``<qp>`` is ``realtime`` (the QP in the
            filter's C kernel, :mod:`torchcbf.filters.realtime`) or the
            :attr:`torchcbf.qp.QPSolution.path` of the general path's QP. A call that takes
            the C kernels end to end says ``native/realtime``.
    """

    u: Tensor
    status: Tensor
    h: Tensor
    slack: Tensor
    clf_value: Tensor
    qp_status: Tensor
    constraint_value: Tensor
    path: str = "torch/ipm"


#: the values of :attr:`SafetyFilter.backend`
BACKENDS = ("auto", "torch")


def _modules(name: str, value: LieFunction | Sequence[LieFunction]) -> nn.ModuleList:
    items = [value] if isinstance(value, nn.Module) else list(value)
    for i, item in enumerate(items):
        if not isinstance(item, LieFunction):
            raise TypeError(
                f"{name}[{i}] must be a Barrier/Lyapunov module, got {type(item).__name__}"
            )
    return nn.ModuleList(items)


def _alphas(name: str, spec: ClassKSpec | Sequence[ClassKSpec], count: int) -> nn.ModuleList:
    """One class-K module for all outputs, or one per function (a sequence of callables)."""
    if isinstance(spec, Sequence) and not isinstance(spec, str) and spec:
        if any(isinstance(s, nn.Module) or callable(s) for s in spec):
            if len(spec) != count:
                raise ValueError(
                    f"{name} as a sequence of functions needs one per barrier ({count}), "
                    f"got {len(spec)}"
                )
            return nn.ModuleList(as_class_k(s, f"{name}[{i}]") for i, s in enumerate(spec))
    return nn.ModuleList([as_class_k(spec, name)])  # type: ignore[arg-type]


def _require_control_authority(
    barriers: list[LieFunction], dynamics: ControlAffine, samples: int = 16
) -> None:
    """Raise if some barrier output has ``L_g h = 0`` at every sample state (see the
    ``check_relative_degree`` argument of :class:`SafetyFilter`)."""
    for i, barrier in enumerate(barriers):
        device, dtype = placement(barrier)
        if device.type == "meta":
            continue
        gen = torch.Generator(device=device).manual_seed(0)
        x = 2.0 * torch.randn(
            samples, dynamics.state_dim, generator=gen, dtype=dtype, device=device
        )
        t = torch.zeros(samples, dtype=dtype, device=device)
        terms = barrier.lie(x, dynamics, t, hessian=False)
        lgh = terms.lgh.detach().nan_to_num(0.0, 0.0, 0.0).abs()  # [N, m] or [N, k, m]
        grad = terms.dhdx.detach().nan_to_num(0.0, 0.0, 0.0).abs()
        if lgh.dim() == 2:
            lgh, grad = lgh.unsqueeze(1), grad.unsqueeze(1)
        g_max = float(dynamics.g(x).detach().abs().amax().clamp_min(1.0))
        reach = lgh.amax(dim=(0, 2))  # [k]
        slope = grad.amax(dim=(0, 2))
        scale = (slope * g_max).clamp_min(1.0)
        constant = (slope == 0).nonzero().flatten().tolist()
        if constant:
            raise ValueError(
                f"barriers[{i}] ({type(barrier).__name__}, outputs {constant}) does not depend "
                f"on the state (dh/dx = 0 on every sample state of {type(dynamics).__name__}): "
                "the filter could never act on it, and no rectification gives it a relative "
                "degree. Leave such outputs out (a frame on the base's axis never moves), or "
                "pass check_relative_degree=False if it is flat only where the samples are."
            )
        dead = (reach <= 1e-9 * scale).nonzero().flatten().tolist()
        if dead:
            raise ValueError(
                f"barriers[{i}] ({type(barrier).__name__}, outputs {dead}) has L_g h = 0 on "
                f"every sample state of {type(dynamics).__name__}: its relative degree is two "
                "or more, so the filter could never change the control. Rectify it, e.g. "
                "rectify(barrier, dynamics, form='exponential'), or pass "
                "check_relative_degree=False if the barrier acts only in a region the samples "
                "miss."
            )


def _check_qp_options(opts: dict[str, Any]) -> dict[str, Any]:
    """``qp_options`` with ``eps`` and ``max_iter`` checked as :func:`~torchcbf.qp.solve_qp`
    checks them (the real-time path reads them without calling it)."""
    check_options(opts.get("max_iter", 1), opts.get("eps"), where="qp_options['{}']")
    return opts


def _slack(slack: Slack | str) -> Slack:
    if isinstance(slack, Slack):
        return slack
    if isinstance(slack, str):
        if slack not in SLACK_MODES:
            raise ValueError(f"slack must be a Slack or one of {SLACK_MODES}, got {slack!r}")
        return Slack(slack)  # type: ignore[arg-type]
    raise TypeError(f"slack must be a Slack or one of {SLACK_MODES}, got {type(slack).__name__}")


class SafetyFilter(ExactConstants, DerivedConstants):
    """CBF/CLF-QP safety filter (vanilla, robust, stochastic or risk-aware), batched.

    Args:
        dynamics: the control-affine model (its ``u_min``/``u_max`` are the default limits).
        barriers: a barrier or a sequence of barriers (each ``[...]`` or ``[..., k_i]``); the
            k outputs are concatenated in order. Relative degree must be one (see
            :func:`torchcbf.barriers.rectify`).
        lyapunovs: a Lyapunov function or a sequence (``c`` outputs in total).
        mode: a :class:`~torchcbf.filters.modes.FilterMode` (``Vanilla()``, ``Robust()``,
            ``Stochastic(beta=...)``, ``RiskAware(rho=..., horizon=..., eta=...)``) or its
            name for its defaults: ``"vanilla"``, ``"robust"``, ``"stochastic"`` (``"risk_aware"``
            has none: it needs its object).
        alpha: class-K function of the CBF conditions: a gain (``alpha(h) = gain h``), gains
            per barrier output (sequence or tensor ``[k]``), a callable/module (e.g.
            :class:`LinearClassK` with ``learnable=True``), or one callable per barrier
            module. Unused in the risk-aware mode.
        clf_rate: decay rate ``c(V)`` of the CLF conditions, same forms (default ``V``).
        R: control weight: scalar, ``[m]`` (diagonal) or ``[m, m]`` SPD (default identity).
        u_min, u_max: override the dynamics' control limits (scalar or ``[m]``).
        slack: how the QP relaxes its conditions: a :class:`Slack` (mode, weights, the
            ``RELAXED`` tolerance, the hard QP beside the elastic one), or its mode
            ``"shared"`` (default), ``"per_row"`` or ``"none"`` (see the module).
        fallback: control of rows whose QP failed (see :class:`Fallback`): ``"clip"``
            (default), ``"brake"``, a tensor ``[m]`` or a callable ``(x, u_nom) -> u``.
        lie_method: ``"auto"`` (closed forms when a function has them, else autograd),
            ``"autograd"`` or ``"analytic"``.
        backend: ``"auto"`` (default: the C kernels where they apply, see the module) or
            ``"torch"`` (the general path: Lie terms in torch, the QP by
            :func:`torchcbf.qp.solve_qp` with ``qp_options``, whose own method may still run
            its dual C kernel: ``qp_options={"method": "ipm"}`` or ``"enumerate"`` keeps it
            all in torch). :attr:`FilterOutput.path` says which answered.
        compile: ``True`` or a dict of ``torch.compile`` keyword arguments: outside grad
            mode (``torch.no_grad()``, ``torch.inference_mode()``), with
            ``lie_method="auto"``, the conditions of the functions no C kernel evaluates (a
            user's own barriers and models) come from compiled code (path
            ``compiled/...``). ``True``: the Lie terms, class-K functions and the mode's
            conditions are traced into one graph, compiled by inductor with a C++ wrapper
            (:class:`torchcbf._compile.Traced`: new values of states and constants reuse
            it; a new batch size, dtype, plain-number attribute, container content,
            submodule, or a changed number that a function captures, a method of a user's
            barrier or model reads as a global, or a ``SimpleNamespace``/dataclass attribute
            holds traces again, as does a forward hook registered or removed; attributes
            added after the first call, and globals read by helper functions, are not seen);
            where that fails, the Lie terms go through ``torch.compile``. A dict: the Lie
            terms through ``torch.compile(**compile)``
            (:class:`torchcbf.barriers.compiled.CompiledLie`). The first call compiles
            (about a second with a warm compile cache, several with a cold one); where
            compiling fails it warns and runs eager. In grad mode the autograd path answers,
            whose terms carry the graph.
        qp_options: keyword arguments for :func:`torchcbf.qp.solve_qp`.
        check_relative_degree: at construction, evaluate ``L_g h`` of every barrier output on
            16 sample states (``N(0, 4 I)``, seeded) and raise ``ValueError`` if it vanishes
            on all of them: a barrier of relative degree two or more (a position barrier on
            an acceleration-controlled model) gives the QP nothing to act on, and the filter
            would return ``u_nom`` unchanged. ``False`` skips the check.
    """

    def __init__(
        self,
        dynamics: ControlAffine,
        barriers: LieFunction | Sequence[LieFunction] = (),
        lyapunovs: LieFunction | Sequence[LieFunction] = (),
        mode: str | FilterMode = "vanilla",
        alpha: ClassKSpec | Sequence[ClassKSpec] = 1.0,
        *,
        clf_rate: ClassKSpec | Sequence[ClassKSpec] = 1.0,
        R: Tensor | float | Sequence[float] | None = None,
        u_min: Tensor | float | Sequence[float] | None = None,
        u_max: Tensor | float | Sequence[float] | None = None,
        slack: Slack | SlackMode = "shared",
        fallback: FallbackSpec = "clip",
        lie_method: Literal["auto", "autograd", "analytic"] = "auto",
        backend: Literal["auto", "torch"] = "auto",
        compile: bool | dict[str, Any] = False,
        qp_options: dict[str, Any] | None = None,
        check_relative_degree: bool = True,
    ) -> None:
        super().__init__()
        if not isinstance(dynamics, ControlAffine):
            raise TypeError(f"dynamics must be a ControlAffine, got {type(dynamics).__name__}")
        self.dynamics = dynamics
        self.barriers = _modules("barriers", barriers)
        self.lyapunovs = _modules("lyapunovs", lyapunovs)
        if not self.barriers and not self.lyapunovs:
            raise ValueError("barriers and lyapunovs are both empty: nothing to filter")
        if check_relative_degree:
            _require_control_authority(list(self.barriers), dynamics)
        self.condition = bind_mode(mode, dynamics, list(self.barriers), list(self.lyapunovs))
        if lie_method not in ("auto", "autograd", "analytic"):
            raise ValueError(
                f"lie_method must be 'auto', 'autograd' or 'analytic', got {lie_method!r}"
            )
        self.lie_method = lie_method
        if backend not in BACKENDS:
            raise ValueError(f"backend must be one of {BACKENDS}, got {backend!r}")
        self.backend = backend
        self._compiled_lie: tuple[CompiledLie | None, CompiledLie | None] | None = None
        self._traced: Traced | None = None
        # whether the C Lie kernel describes the barriers (the traced path's guide; asked
        # again after the traced state changed)
        self._native_known: bool | None = None
        self._traced_lookups = 0
        compile = check_compile(compile)
        if compile is not False:
            opts = compile if isinstance(compile, dict) else None
            hess = self.condition.needs_hessian
            self._compiled_lie = tuple(
                CompiledLie(list(fns), dynamics, hessian=hess, options=opts) if fns else None
                for fns in (self.barriers, self.lyapunovs)
            )  # type: ignore[assignment]
            if opts is None:
                # the filter's caches change between calls and are not read by the graph
                ignore = ("_traced", "_traced_lookups", "_native_known", "_compiled_lie")
                self._traced = Traced(self._compiled_conditions, [self], ignore=ignore)
        m = dynamics.control_dim
        self.alpha = _alphas("alpha", alpha, len(self.barriers))
        self.clf_rate = _alphas("clf_rate", clf_rate, len(self.lyapunovs))
        # Python numbers stay exact under .double(); a parameter (a vector R, a scalar bound)
        # is kept and shaped at each read, so that it trains
        weight = torch.eye(m, dtype=torch.float64) if R is None else R
        as_weight = functools.partial(as_matrix, "R", size=m, dtype=torch.float64)
        shape = functools.partial(matrix_shape, size=m, dtype=torch.float64)
        derive(self, "R", weight, as_weight, shape=shape, exact=not isinstance(R, Tensor))
        bound = functools.partial(limit_shape, size=m)
        for name, limit in (("u_min", u_min), ("u_max", u_max)):
            as_bound = functools.partial(as_limit, name, size=m)
            derive(self, name, limit, as_bound, shape=bound, exact=not isinstance(limit, Tensor))
        lo, hi = self._limit_tensors()
        check_bounds("u_min", lo, "u_max", hi)
        self.slack = _slack(slack).resolved(lyapunovs=bool(self.lyapunovs))
        self.fallback = Fallback(fallback, m)
        self.qp_options = _check_qp_options(dict(qp_options or {}))
        follow_parts(self, [dynamics, *self.barriers, *self.lyapunovs])

    # -- read-only views of the condition --------------------------------------------------
    @property
    def mode(self) -> str:
        """The condition mode's name."""
        return self.condition.name

    @property
    def cbf_margin(self) -> Tensor | None:
        """Risk-aware margin ``Delta`` of the CBF rows (``None`` in other modes, and with
        ``RiskAware(eta="local")``, whose margin depends on the state:
        :meth:`~torchcbf.filters.RiskAware.margin_at`)."""
        return getattr(self.condition, "cbf_margin", None)

    @property
    def clf_margin(self) -> Tensor | None:
        """Risk-aware margin ``Delta_V`` of the CLF rows (``None`` in other modes)."""
        return getattr(self.condition, "clf_margin", None)

    # -- forward ---------------------------------------------------------------------------
    def forward(self, x: Tensor, u_nom: Tensor, t: Tensor | float | None = None) -> FilterOutput:
        """Filter ``u_nom [..., m]`` at states ``x [..., n]`` (batch dims broadcast).

        ``t``: a number or a tensor broadcastable to the batch shape (``None``: 0).
        Returns a :class:`FilterOutput` with the batch shape of ``x`` and ``u_nom``.
        """
        batch, xb, ub, tb = self._inputs(x, u_nom, t)
        conditions = None
        if self._realtime_applies(xb, ub, tb):
            # the conditions as the general path computes them (finite inputs): they carry a
            # graph exactly when some output can have a gradient, whatever its source (an
            # input, a parameter, a tensor captured by a class-K closure); those of quadric
            # barriers as a prepared native call, evaluated by the filter's kernel
            conditions = self._conditions(xb, tb, prepare=True)
            limits = self._limit_tensors()
            grads = torch.is_grad_enabled()
            if not (grads and _carries_grad(conditions, ub, self.R, *limits)):
                out = self._realtime(batch, xb, ub, conditions, limits)
                if out is not None:
                    if grads and self.fallback.trains():
                        # no row fell back: the fallback's gradient is zero, but it has one
                        link = self.fallback.control.reshape(-1)[:0].sum().to(out.u.dtype)
                        out = out._replace(u=out.u + link)
                    return out
            if isinstance(conditions[0], native.ConditionCall):
                conditions = None
        B = xb.shape[0]
        finite = rows_finite(xb, 1, B) & rows_finite(ub, 1, B) & isfinite(tb)
        fin = finite.unsqueeze(-1)
        xs = torch.where(fin, xb, 0.0)
        us = torch.where(fin, ub, 0.0)
        ts = torch.where(finite, tb, 0.0)
        if conditions is None:
            conditions = self._conditions(xs, ts)
        if torch.is_grad_enabled():
            conditions = self._without_nonfinite_rows(conditions, xs, ts)
        cbf, clf, h, V, lie = conditions
        lo, hi = self._limits(xs)
        sl = self.slack
        weights = {"cbf_weight": sl.cbf_weight, "clf_weight": sl.clf_weight}
        qp = assemble(cbf, clf, us, self.R.to(us), lo, hi, slack=sl.mode, **weights)
        z, qp_status, qp_ok, qp_path = self._solve(qp, finite)
        m = us.shape[-1]
        u = self.fallback.select(qp_ok, z[:, :m], xb, ub, lo, hi)
        s = z[:, m : m + qp.ks]
        delta = z[:, m + qp.ks :]
        relaxed = (s > self._slack_tol(xs)).any(-1) if qp.ks else torch.zeros_like(finite)
        # a number, not a filled tensor, as where's other branch: one launch each
        status = torch.where(relaxed, int(FilterStatus.RELAXED), int(FilterStatus.SOLVED))
        status = torch.where(qp_ok, status, int(FilterStatus.FALLBACK))
        status = torch.where(finite, status, int(FilterStatus.NON_FINITE))
        # the QP of a non-finite row was a zero stand-in: report the input's trouble
        qp_status = torch.where(finite, qp_status, int(Status.NON_FINITE))
        slack, cval = _residuals(cbf, clf, u, delta)
        slack = torch.where(qp_ok.unsqueeze(-1), slack, 0.0)
        cval = torch.where(fin, cval, math.nan)
        h = torch.where(fin, h, math.nan)
        V = torch.where(fin, V, math.nan)
        return _output(batch, u, status, h, slack, V, qp_status, cval, f"{lie}/{qp_path}")

    def _without_nonfinite_rows(self, conditions: Any, xs: Tensor, ts: Tensor) -> Any:
        """``conditions`` where every row's are finite; else those of the finite rows made
        again from their states alone, the other rows' values kept without a graph. A row
        whose conditions are not finite (a state where a barrier's derivative is 0/0) falls
        back; its values must not reach a gradient either: the backward of the operation
        that made them multiplies its zero gradient by NaN, and parameters that every row
        shares (a barrier's centre, a class-K gain) would get NaN gradients. One host
        synchronisation, in grad mode only."""
        cbf, clf = conditions[0], conditions[1]
        B = xs.shape[0]
        ok = torch.ones(B, dtype=torch.bool, device=xs.device)
        for cond in (cbf, clf):
            if cond is not None:
                ok = ok & rows_finite(cond[0], 2, B) & rows_finite(cond[1], 1, B)
        if bool(ok.all()):
            return conditions
        keep = ok.nonzero().squeeze(-1)
        again = self._conditions(xs.index_select(0, keep), ts.index_select(0, keep))

        def merged(full: Any, part: Any) -> Any:
            if isinstance(full, Tensor):
                return full.detach().index_put((keep,), part)
            if isinstance(full, tuple):
                return tuple(merged(f, p) for f, p in zip(full, part, strict=True))
            return full  # None, or where the terms came from

        return tuple(merged(f, p) for f, p in zip(conditions, again, strict=True))

    # -- the steps of forward --------------------------------------------------------------
    def _inputs(
        self, x: Tensor, u_nom: Tensor, t: Tensor | float | None
    ) -> tuple[tuple[int, ...], Tensor, Tensor, Tensor]:
        """Check the inputs; return the batch shape and ``x [B, n]``, ``u_nom [B, m]``,
        ``t [B]``."""
        dyn = self.dynamics
        n, m = dyn.state_dim, dyn.control_dim
        check_last_dim("x", x, n)
        check_last_dim("u_nom", u_nom, m)
        refuse_transforms(
            "SafetyFilter", (x, u_nom, t if isinstance(t, Tensor) else None), module=self
        )
        batch = x.shape[:-1]
        if u_nom.shape[:-1] != batch:
            try:
                batch = broadcast_shapes(batch, u_nom.shape[:-1])
            except RuntimeError:
                raise ValueError(
                    f"batch dimensions of x {tuple(x.shape)} and u_nom {tuple(u_nom.shape)} "
                    "do not broadcast"
                ) from None
        if not x.is_floating_point() or u_nom.dtype != x.dtype:
            raise TypeError(
                f"x and u_nom must share a floating dtype, got {x.dtype} and {u_nom.dtype}"
            )
        if x.dtype not in (torch.float32, torch.float64):
            raise TypeError(
                f"x must be float32 or float64 (the QP solves in those), got {x.dtype}: "
                "cast the inputs with .float()"
            )
        if u_nom.device != x.device or x.device != self.R.device:
            raise ValueError(
                f"x is on device {x.device}, u_nom on {u_nom.device} and the filter on "
                f"{self.R.device}: move them to one device (safety_filter.to(x.device))"
            )
        B = math.prod(batch)
        if t is None or isinstance(t, (int, float)):
            tb = x.new_full((B,), 0.0 if t is None else float(t))
        else:
            tt = as_tensor("t", t, dtype=x.dtype, device=x.device)
            try:
                tb = torch.broadcast_to(tt, batch).reshape(B)
            except RuntimeError:
                raise ValueError(
                    f"t must broadcast to the batch shape {tuple(batch)}, got {tuple(tt.shape)}"
                ) from None
        # a view where the batch is already the tensor's own (one op), else a broadcast
        xb = x.reshape(B, n) if x.shape[:-1] == batch else x.expand(*batch, n).reshape(B, n)
        ub = (
            u_nom.reshape(B, m)
            if u_nom.shape[:-1] == batch
            else u_nom.expand(*batch, m).reshape(B, m)
        )
        return tuple(batch), xb, ub, tb

    def _lie(
        self, fns: nn.ModuleList, x: Tensor, t: Tensor, compiled: CompiledLie | None
    ) -> tuple[LieTerms | None, list[int], str]:
        """k-output Lie terms of all ``fns`` concatenated, each one's number of outputs, and
        where they came from (``native``, ``compiled`` or ``torch``). A few states of quadric
        functions: one native call; with ``compile``, outside grad mode, one compiled call;
        functions without closed forms share one stacked autograd call."""
        if not fns:
            return None, [], "torch"
        hessian = self.condition.needs_hessian
        if self._native_applies(x):
            found = native.lie_terms(fns, x, self.dynamics, hessian=hessian)
            if found is not None:
                return *found, "native"
        # a function with its own lie gives its terms itself: no stacked or compiled call
        own = any(own_lie(fn) for fn in fns)
        usable = self.lie_method == "auto" and not torch.is_grad_enabled() and x.shape[0] > 0
        if compiled is not None and usable and not own:
            found = compiled(x, t)
            if found is not None:
                return *found, "compiled"
        methods = [self._lie_method(fn) for fn in fns]
        if len(fns) > 1 and not own and all(m == "autograd" for m in methods):
            terms, sizes = stacked_lie_derivatives(list(fns), x, self.dynamics, t, hessian=hessian)
            return terms, sizes, "torch"
        parts = []
        for fn, method in zip(fns, methods, strict=True):
            terms = fn.lie(x, self.dynamics, t, method=method, hessian=hessian)
            parts.append(as_columns(terms, x.shape[0]))
        return concat_terms(parts), [p.h.shape[1] for p in parts], "torch"

    def _native_cbf(
        self, x: Tensor, prepare: bool
    ) -> tuple[Tensor, tuple[Tensor, Tensor] | native.ConditionCall] | None:
        """``(h [B,k], (a [B,k,m], b [B,k]))`` of the CBF conditions from one native call
        (:func:`torchcbf.barriers.native.cbf_conditions`) where the barriers are quadrics,
        the batch is small and the mode's condition is affine in the Lie terms
        (:meth:`~torchcbf.filters.modes.FilterMode.affine_cbf`); with ``prepare``, the call
        prepared instead (:func:`~torchcbf.barriers.native.condition_call`; its ``h`` is
        written when the filter's kernel makes it). ``None`` where that does not apply."""
        barriers, alphas, mode = self.barriers, self.alpha, self.condition
        # asked first: on another device an affine form might read a number off it
        if not barriers or not self._native_applies(x):
            return None
        alpha, *others = alphas  # iterating a ModuleList is cheaper than its len()
        if others:
            return None
        affine = mode.affine_cbf(alpha)
        if affine is None:
            return None
        args = barriers, x, self.dynamics, affine
        if prepare:
            call = native.condition_call(*args, hessian=mode.needs_hessian)
            return None if call is None else (call.h, call)
        found = native.cbf_conditions(*args, hessian=mode.needs_hessian)
        return None if found is None else (found[0], found[1:3])

    def _native_applies(self, x: Tensor) -> bool:
        """Whether the native Lie terms may answer for ``x [B, n]``: ``lie_method="auto"``
        and at most ``realtime.MAX_BATCH`` CPU states."""
        return (
            self.lie_method == "auto"
            and self.backend == "auto"
            and x.shape[0] <= realtime.MAX_BATCH
            and x.is_cpu
        )

    def _lie_method(self, fn: LieFunction) -> str:
        if self.lie_method == "auto":
            return "analytic" if fn.has_analytic else "autograd"
        return self.lie_method

    @staticmethod
    def _class_k(fns: nn.ModuleList, values: Tensor, sizes: list[int], name: str) -> Tensor:
        if len(fns) == 1:
            (fn,) = fns  # iterating a ModuleList is cheaper than indexing it
            return _apply_class_k(fn, values, name)
        parts = zip(fns, values.split(sizes, -1), strict=True)
        return torch.cat([_apply_class_k(fn, v, name) for fn, v in parts], -1)

    def _conditions(
        self, x: Tensor, t: Tensor, *, prepare: bool = False
    ) -> tuple[
        tuple[Tensor, Tensor] | native.ConditionCall | None,
        tuple[Tensor, Tensor] | None,
        Tensor,
        Tensor,
        str,
    ]:
        """CBF conditions ``(a [B,k,m], b [B,k])``, CLF conditions ``(a [B,c,m], b [B,c])``
        (``None`` without functions), barrier values ``h [B,k]``, Lyapunov values
        ``V [B,c]`` and where the Lie terms came from (``native``, ``torch`` or ``mixed``).
        With ``prepare``, the CBF conditions may be a prepared native call (see
        :meth:`_native_cbf`), for the real-time path."""
        compiled = self._compiled_lies()
        # a function with its own lie gives its terms itself: no traced graph of its calls
        traced = (
            self._traced is not None
            and self.lie_method == "auto"
            and not torch.is_grad_enabled()
            and not any(own_lie(fn) for fn in (*self.barriers, *self.lyapunovs))
        )
        if traced and self._native_known is None:
            self._native_known = native.describes(self.barriers, self.dynamics)
        # barriers the kernel does not describe go straight to the traced graph (it sees a
        # replaced barrier, and the kernel is asked again after one)
        native_cbf = None if traced and not self._native_known else self._native_cbf(x, prepare)
        if native_cbf is None and traced:
            found = self._traced_conditions(x, t)
            if found is not None:
                return found
        if native_cbf:
            cbf_terms, cbf_sizes, cbf_from = None, [], "native"
        else:
            cbf_terms, cbf_sizes, cbf_from = self._lie(self.barriers, x, t, compiled[0])
        clf_terms, clf_sizes, clf_from = self._lie(self.lyapunovs, x, t, compiled[1])
        used = {f for f, on in ((cbf_from, cbf_sizes or native_cbf), (clf_from, clf_sizes)) if on}
        lie = used.pop() if len(used) == 1 else "mixed"
        cbf = clf = None
        h = V = x.new_zeros(x.shape[0], 0)
        if native_cbf is not None:
            h, cbf = native_cbf
        elif cbf_terms is not None:
            alpha = lambda v: self._class_k(self.alpha, v, cbf_sizes, "alpha")  # noqa: E731
            cbf = tuple(self.condition.cbf(cbf_terms, alpha, self.dynamics, x))
            h = cbf_terms.h
        if clf_terms is not None:
            rate = lambda v: self._class_k(self.clf_rate, v, clf_sizes, "clf_rate")  # noqa: E731
            clf = tuple(self.condition.clf(clf_terms, rate, self.dynamics, x))
            V = clf_terms.h
        return cbf, clf, h, V, lie  # type: ignore[return-value]

    def _compiled_lies(self) -> tuple[CompiledLie | None, CompiledLie | None]:
        """The compiled Lie terms of the barriers and of the Lyapunov functions, following the
        functions and the model the filter holds now (a replaced one is traced again;
        functions added where there were none take the autograd path)."""
        if self._compiled_lie is None:
            return None, None
        held = (self.barriers, self.lyapunovs)
        lies = []
        for lie, fns in zip(self._compiled_lie, held, strict=True):
            if lie is not None:
                lie.follow(fns, self.dynamics)
            lies.append(lie if lie is not None and len(fns) > 0 else None)
        return lies[0], lies[1]

    def _compiled_conditions(self, x: Tensor, t: Tensor) -> tuple[Tensor, ...]:
        """``(h, a, b)`` of the CBF rows, then ``(V, a, b)`` of the CLF rows (where there are
        functions) from the compiled Lie terms' own function: what ``compile=True`` traces
        into one graph (:class:`torchcbf._compile.Traced`)."""
        assert self._compiled_lie is not None
        out: list[Tensor] = []
        parts = (
            (self._compiled_lie[0], self.alpha, "alpha", self.condition.cbf),
            (self._compiled_lie[1], self.clf_rate, "clf_rate", self.condition.clf),
        )
        for lie, gains, name, condition in parts:
            if lie is None or not lie.fns:
                continue
            terms, sizes = lie.evaluate(x, t)
            k = lambda v, g=gains, s=sizes, n=name: self._class_k(g, v, s, n)  # noqa: E731
            a, b = condition(terms, k, self.dynamics, x)
            out += [terms.h, a, b]
        return tuple(out)

    def _traced_conditions(
        self, x: Tensor, t: Tensor
    ) -> tuple[Any, Any, Tensor, Tensor, str] | None:
        """:meth:`_conditions` by one call of the traced graph (``None`` where it cannot be
        traced: the Lie terms' own compiled call answers from then on)."""
        assert self._traced is not None
        if x.shape[0] == 0:
            return None
        try:
            flat = iter(self._traced(x, t))
        except TraceError as err:
            logger.info(
                "torchcbf: the filter's conditions cannot be traced into one graph (%s); "
                "torch.compile answers",
                str(err).splitlines()[0] if str(err) else "",
            )
            self._traced = None
            return None
        except Exception as err:  # noqa: BLE001 - this call only: the next path answers
            logger.debug("torchcbf: the traced conditions failed on this call (%s)", err)
            return None
        if self._traced.lookups != self._traced_lookups:  # something changed: ask again
            self._traced_lookups, self._native_known = self._traced.lookups, None
        cbf = clf = None
        h = V = x.new_zeros(x.shape[0], 0)
        if self.barriers:
            h, *cbf = next(flat), next(flat), next(flat)
        if self.lyapunovs:
            V, *clf = next(flat), next(flat), next(flat)
        return (
            None if cbf is None else tuple(cbf),
            None if clf is None else tuple(clf),
            h,
            V,
            "compiled",
        )  # type: ignore[return-value]

    def _limit_tensors(self) -> tuple[Tensor | None, Tensor | None]:
        """The filter's own limits ``[m]``, else the dynamics' (``None``: no limit); one
        number set on either stands for every control."""
        dyn = self.dynamics
        m = dyn.control_dim
        lo, hi = self.u_min, self.u_max
        lo = dyn.u_min if lo is None else lo
        hi = dyn.u_max if hi is None else hi
        if (lo is None or lo.shape == (m,)) and (hi is None or hi.shape == (m,)):
            return lo, hi
        out = []
        for name, bound in (("u_min", lo), ("u_max", hi)):
            if bound is not None and bound.shape != (m,):
                if bound.numel() != 1:
                    raise ValueError(
                        f"{name} must be a number or [{m}], got shape {tuple(bound.shape)}"
                    )
                bound = bound.reshape(1).expand(m)
            out.append(bound)
        return out[0], out[1]

    def _limits(self, x: Tensor) -> tuple[Tensor, Tensor]:
        m = self.dynamics.control_dim
        lo, hi = self._limit_tensors()
        inf = torch.full((m,), math.inf, dtype=x.dtype, device=x.device)
        lo = -inf if lo is None else lo.to(x)
        hi = inf if hi is None else hi.to(x)
        return lo, hi

    def _slack_tol(self, x: Tensor) -> float:
        if self.slack.tol is not None:
            return self.slack.tol
        return 1e-6 if x.dtype == torch.float64 else 1e-3

    def _two_pass(self, ks: int) -> bool:
        return bool(ks) and self.slack.two_pass

    def _solve(self, qp: Any, finite: Tensor) -> tuple[Tensor, Tensor, Tensor, str]:
        """Solve the filter QP: ``(z [B, nz], qp_status [B], qp_ok [B], path)``. Rows with
        non-finite data get a harmless problem and ``qp_ok = False``."""
        G, hq = qp.G, qp.h
        B = hq.shape[0]
        data_ok = finite & rows_finite(G, 2, B) & rows_finite(hq, 1, B)
        # on a CPU, asking whether every row is fine costs no device synchronisation
        if G.device.type != "cpu" or not bool(data_ok.all()):
            G = G.masked_fill(~data_ok[:, None, None], 0.0)
            hq = hq.masked_fill(~data_ok[:, None], 1.0)
        if not self._two_pass(qp.ks):
            sol = qp_layer.solve_qp(qp.Q, qp.p, G, hq, lb=qp.lb, ub=qp.ub, **self.qp_options)
            ok = data_ok & (sol.status == Status.SOLVED) & rows_finite(sol.x, 1, B)
            # a row whose data was not finite had a stand-in QP: report its data's trouble
            status = torch.where(data_ok, sol.status, int(Status.NON_FINITE))
            return sol.x, status, ok, sol.path
        # rows [B:2B]: the hard QP (the slack columns of the CBF rows zeroed; s then
        # decouples and sits at its bound 0), solved in the same call as the elastic one
        k, m = qp.norms.shape[1], self.dynamics.control_dim
        G_hard = G.clone()
        G_hard[:, :k, m : m + qp.ks] = 0
        cat = lambda v: torch.cat([v, v], 0)  # noqa: E731
        sol = qp_layer.solve_qp(cat(qp.Q), cat(qp.p), torch.cat([G, G_hard], 0), cat(hq),
                       lb=cat(qp.lb), ub=cat(qp.ub), **self.qp_options)  # fmt: skip
        good = (sol.status == Status.SOLVED) & rows_finite(sol.x, 1, 2 * B) & cat(data_ok)
        el_ok, hard_ok = good[:B], good[B:]
        z_el, st_el = sol.x[:B], sol.status[:B]
        if G.shape[1] > k:  # Lyapunov functions: their pull bounded where the hard QP fails
            z_el, st_el, el_ok = self._least_violation(
                qp, G, hq, data_ok, hard_ok, z_el, st_el, el_ok
            )
        z = torch.where(hard_ok.unsqueeze(-1), sol.x[B:], z_el)
        qp_status = torch.where(hard_ok, sol.status[B:], st_el)
        qp_status = torch.where(data_ok, qp_status, int(Status.NON_FINITE))
        return z, qp_status, hard_ok | el_ok, sol.path

    def _least_violation(
        self,
        qp: Any,
        G: Tensor,
        hq: Tensor,
        data_ok: Tensor,
        hard_ok: Tensor,
        z_el: Tensor,
        st_el: Tensor,
        el_ok: Tensor,
    ) -> tuple[Tensor, Tensor, Tensor]:
        """The elastic answer ``(z, status, ok)`` where a CLF pulled it beyond the least
        violation of the CBF rows alone (their elastic QP, the CLF rows' controls zeroed and
        delta at 0), on the rows whose hard QP failed: that problem's control there. On the
        CPU only those rows are solved (asking which costs no synchronisation); elsewhere
        every row, without a synchronisation."""
        k, m = qp.norms.shape[1], self.dynamics.control_dim
        rows = (~hard_ok & data_ok).nonzero().squeeze(-1) if G.is_cpu else None
        if rows is not None and rows.numel() == 0:
            return z_el, st_el, el_ok

        def pick(t: Tensor) -> Tensor:
            return t if rows is None else t.index_select(0, rows)

        G_cbf = pick(G).clone()
        G_cbf[:, k:, :m] = 0
        h_cbf = pick(hq).clone()
        h_cbf[:, k:] = 0
        sol = qp_layer.solve_qp(pick(qp.Q), pick(qp.p), G_cbf, h_cbf, lb=pick(qp.lb),
                                ub=pick(qp.ub), **self.qp_options)  # fmt: skip
        n = sol.x.shape[0]
        cbf_ok = (sol.status == Status.SOLVED) & rows_finite(sol.x, 1, n) & pick(data_ok)
        z_sub, ok_sub = pick(z_el), pick(el_ok)
        s_el = z_sub[:, m : m + qp.ks].amax(-1)
        s_cbf = sol.x[:, m : m + qp.ks].amax(-1)
        pulled = cbf_ok & (~ok_sub | (s_el > s_cbf + self._slack_tol(z_el)))
        # the CLF rows' relaxation at that control
        u_cbf = sol.x[:, :m].unsqueeze(-1)
        delta = ((pick(G)[:, k:, :m] @ u_cbf).squeeze(-1) - pick(hq)[:, k:]).clamp_min(0.0)
        z_cbf = torch.cat((sol.x[:, : m + qp.ks], delta), -1)
        z_new = torch.where(pulled.unsqueeze(-1), z_cbf, z_sub)
        st_new = torch.where(pulled, sol.status, pick(st_el))
        ok_new = ok_sub | pulled
        if rows is None:
            return z_new, st_new, ok_new
        return (
            z_el.index_copy(0, rows, z_new),
            st_el.index_copy(0, rows, st_new),
            el_ok.index_copy(0, rows, ok_new),
        )

    # -- the real-time path ----------------------------------------------------------------
    def _realtime_applies(self, xb: Tensor, ub: Tensor, tb: Tensor) -> bool:
        """Whether a call may take the real-time path: few states on the CPU, all finite
        (non-finite rows are sanitised by the general path before any computation), the
        default QP backend and the C kernel built; :meth:`forward` then also asks that no
        output can carry a gradient."""
        opts = self.qp_options
        if (
            self.backend != "auto"
            or forward_mode_active()  # a closure's tangent: the general path's QP refuses it
            or not 1 <= xb.shape[0] <= realtime.MAX_BATCH
            or not xb.is_cpu
            or (opts and not (opts.keys() <= _REALTIME_QP_OPTIONS))
            or opts.get("backend", "torch") != "torch"
            or opts.get("method", "auto") not in ("auto", "active_set")
            or not realtime.available()
        ):
            return False
        return realtime.inputs_finite(xb, ub, tb)

    def _realtime(
        self,
        batch: tuple[int, ...],
        xb: Tensor,
        ub: Tensor,
        conditions: tuple[Any, Any, Tensor, Tensor, str],
        limits: tuple[Tensor | None, Tensor | None],
    ) -> FilterOutput | None:
        """The filter on a few finite states by one call of the C kernel
        (:mod:`torchcbf.filters.realtime`), with the conditions and the limits
        (:meth:`_limit_tensors`) already at hand; ``None`` where the general path must answer
        (non-finite conditions, a row the kernel does not certify)."""
        cbf, clf, h, V, lie = conditions
        opts = self.qp_options
        eps = opts.get("eps")
        res = realtime.solve(
            cbf, clf, ub, self.R, *limits,
            slack=self.slack.mode,
            two_pass=self.slack.two_pass,
            cbf_weight=self.slack.cbf_weight,
            clf_weight=self.slack.clf_weight,
            eps=float(qp_realtime.default_eps(xb.dtype) if eps is None else eps),
            max_iter=opts.get("max_iter", 50),
            slack_tol=self._slack_tol(xb),
            batch=batch,
        )  # fmt: skip
        if res is None:
            return None
        dt = xb.dtype
        u, slack, value = res.u, res.slack, res.value
        if dt is not torch.float64:
            u, slack, value, h = u.to(dt), slack.to(dt), value.to(dt), h.to(dt)
        flat = len(batch) == 1
        return FilterOutput(
            u=u,
            status=res.status,
            h=h if flat else h.reshape(*batch, h.shape[-1]),
            slack=slack,
            clf_value=V if flat else V.reshape(*batch, V.shape[-1]),
            qp_status=torch.zeros_like(res.status),
            constraint_value=value,
            path=f"{lie}/realtime",
        )


def _apply_class_k(fn: nn.Module, values: Tensor, name: str) -> Tensor:
    """``fn(values [B, k])``, after checking that a gain vector has one entry or ``k``."""
    gains = fn.gain.shape if isinstance(fn, _GainClassK) else ()
    if len(gains) == 1 and gains[0] not in (1, values.shape[-1]):
        raise ValueError(
            f"{name} has {gains[0]} gains for {values.shape[-1]} outputs: give one "
            "gain per output, or a scalar"
        )
    return fn(values)


def _carries_grad(conditions: tuple[Any, Any, Tensor, Tensor, str], *more: Tensor | None) -> bool:
    """Whether a condition tensor, ``h``, ``V`` or one of ``more`` requires grad."""
    cbf, clf, h, V, _ = conditions
    if isinstance(cbf, native.ConditionCall):
        cbf = None  # it refuses tensors that require grad (with grad mode on)
    tensors = [h, V, *more, *(cbf or ()), *(clf or ())]
    return any(t is not None and t.requires_grad for t in tensors)


def _residuals(
    cbf: tuple[Tensor, Tensor] | None,
    clf: tuple[Tensor, Tensor] | None,
    u: Tensor,
    delta: Tensor,
) -> tuple[Tensor, Tensor]:
    """``slack [B, k + c]`` (CBF violations, then CLF relaxations) and the condition values
    ``[B, k + c]`` at ``u`` (``>= 0`` where a condition holds without slack)."""
    slack_parts, value_parts = [], []
    if cbf is not None:
        value = matvec(cbf[0], u) + cbf[1]
        value_parts.append(value)
        slack_parts.append((-value).clamp_min(0))
    if clf is not None:
        slack_parts.append(delta.clamp_min(0))
        value_parts.append(-(matvec(clf[0], u) + clf[1]))
    return torch.cat(slack_parts, -1), torch.cat(value_parts, -1)


def _output(
    batch: tuple[int, ...],
    u: Tensor,
    status: Tensor,
    h: Tensor,
    slack: Tensor,
    V: Tensor,
    qp_status: Tensor,
    cval: Tensor,
    path: str,
) -> FilterOutput:
    """Reshape flat ``[B, ...]`` results to the batch shape."""
    return FilterOutput(
        u=u.reshape(*batch, u.shape[-1]),
        status=status.reshape(batch),
        h=h.reshape(*batch, h.shape[-1]),
        slack=slack.reshape(*batch, slack.shape[-1]),
        clf_value=V.reshape(*batch, V.shape[-1]),
        qp_status=qp_status.reshape(batch),
        constraint_value=cval.reshape(*batch, cval.shape[-1]),
        path=path,
    )
