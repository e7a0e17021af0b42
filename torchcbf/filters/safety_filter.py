"""The CBF/CLF-QP safety filter: one batched, differentiable QP for a batch of states.

For each state the filter solves, over ``z = [u (m); s (k); delta (c)]``,

    min  1/2 |u - u_nom|_R^2 + P_cbf(s) + 1/2 w_clf rbar |delta|^2
    s.t. (a_i . u + b_i) / n_i + s_i >= 0      for each of the k barrier outputs,
         a_j . u + b_j <= delta_j              for each of the c Lyapunov outputs,
         u_min <= u <= u_max,  s >= 0,  delta >= 0,

with the conditions ``a . u + b`` of :mod:`torchcbf.filters.conditions` for the chosen
mode, ``n_i = max(|a_i|_2, 1e-6)`` (row normalisation: ``s`` is a violation in control
units), and ``rbar = tr(R) / m``.

CBF slacks. Hard constraints (default) share ONE slack ``s = s_i`` for all barrier rows
(so ``z = [u; s; delta]`` has ``m + 1 + c`` entries) with the exact penalty ``P_cbf(s) =
w rbar (s + 1/2 s^2)``: where the hard QP is infeasible, the elastic QP returns the
least-violating control, the one (in the box) minimising the largest normalised violation
``max_i (-(a_i . u + b_i) / n_i)_+`` (then the distance to ``u_nom``), with status
``RELAXED`` (``s > slack_tol``). ``w = cbf_slack_weight * (1 + v)`` (default 1e3), with
``v`` (detached, capped at 1e3) an estimate of the hard multipliers from how far ``u_nom``
is from the box and the CBF half-spaces. Where the hard QP is feasible and its multipliers
stay below ``w``, the exact-penalty theorem makes the two solutions equal (``s = 0``). A
CLF can pull against a CBF harder than that, so with Lyapunov functions (``exact=None``
default, or ``exact=True``) the rows are stacked ``[2B]`` into the SAME
:func:`~torchcbf.qp.solve_qp` call, the last ``B`` as the hard QP (slack column zeroed),
and a row takes the hard solution wherever that one is ``SOLVED``. No host sync either
way; the tests compare both against cvxpy. ``elastic=False`` drops the slack (hard QP
only, infeasible rows fall back). ``relax_cbf=True`` makes the CBF constraints soft
instead: one slack per row, ``P_cbf(s) = 1/2 w rbar |s|^2`` (``w`` default 1e2).

Statuses (:class:`FilterStatus`) per row: ``SOLVED`` (every hard constraint met),
``RELAXED`` (some CBF slack above ``slack_tol``), ``FALLBACK`` (the QP did not return
``SOLVED``, or its data were non-finite: the fallback control is used), ``NON_FINITE``
(non-finite ``x``, ``u_nom`` or ``t`` in the row: fallback used; the row is sanitised
before any computation so the other rows and the gradients are untouched).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from enum import IntEnum
from typing import Any, Literal, NamedTuple

import torch
from torch import Tensor, nn

from torchcbf._checks import as_tensor, broadcast_shapes, check_last_dim
from torchcbf.barriers.lie import LieFunction, LieTerms
from torchcbf.dynamics.base import ControlAffine
from torchcbf.filters.class_k import ClassKSpec, as_class_k
from torchcbf.filters.conditions import (
    MODES,
    Mode,
    as_columns,
    cbf_condition,
    clf_condition,
    concat_terms,
)
from torchcbf.filters.risk import noise_bound, risk_margin

FallbackSpec = Literal["clip", "brake"] | Tensor | Callable[[Tensor, Tensor], Tensor]


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
    """

    u: Tensor
    status: Tensor
    h: Tensor
    slack: Tensor
    clf_value: Tensor
    qp_status: Tensor
    constraint_value: Tensor


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


def _limit(name: str, value: Any, m: int) -> Tensor | None:
    if value is None:
        return None
    t = as_tensor(name, value, dtype=torch.float64)
    if t.dim() == 0:
        t = t.expand(m).clone()
    if t.shape != (m,):
        raise ValueError(f"{name} must be a scalar or have shape [{m}], got {tuple(t.shape)}")
    return t


def _weight_matrix(R: Any, m: int) -> Tensor:
    if R is None:
        return torch.eye(m, dtype=torch.float64)
    t = as_tensor("R", R, dtype=torch.float64)
    if t.dim() == 0:
        t = t * torch.eye(m, dtype=torch.float64)
    elif t.dim() == 1:
        if t.shape != (m,):
            raise ValueError(f"R as a vector must have shape [{m}], got {tuple(t.shape)}")
        t = torch.diag(t)
    if t.shape != (m, m):
        raise ValueError(f"R must be a scalar, [{m}] or [{m}, {m}], got {tuple(t.shape)}")
    if not torch.allclose(t, t.mT) or bool((torch.linalg.eigvalsh(t) <= 0).any()):
        raise ValueError("R must be symmetric positive definite")
    return t


def _like(value: Tensor | None, ref: Tensor) -> Tensor | None:
    """``value`` on the device and dtype of ``ref`` (``None`` stays ``None``)."""
    return None if value is None else value.to(ref)


def _positive(name: str, value: Any) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise TypeError(f"{name} must be a number, got {type(value).__name__}")
    if not (value > 0 and math.isfinite(value)):
        raise ValueError(f"{name} must be finite and positive, got {value}")
    return float(value)


class SafetyFilter(nn.Module):
    """CBF/CLF-QP safety filter (vanilla, robust, stochastic or risk-aware), batched.

    Args:
        dynamics: the control-affine model (its ``u_min``/``u_max`` are the default limits).
        barriers: a barrier or a sequence of barriers (each ``[...]`` or ``[..., k_i]``); the
            k outputs are concatenated in order. Relative degree must be one (see
            :func:`torchcbf.barriers.rectify`).
        lyapunovs: a Lyapunov function or a sequence (``c`` outputs in total).
        mode: ``"vanilla"``, ``"robust"`` (needs ``dynamics.disturbance_bound``),
            ``"stochastic"`` or ``"risk_aware"`` (both need a diffusion ``sigma``); the
            conditions are listed in :mod:`torchcbf.filters.conditions`.
        alpha: class-K function of the CBF conditions: a gain (``alpha(h) = gain h``), gains
            per barrier output (sequence or tensor ``[k]``), a callable/module (e.g.
            :class:`LinearClassK` with ``learnable=True``), or one callable per barrier
            module. Unused in ``risk_aware`` mode.
        clf_rate: decay rate ``c(V)`` of the CLF conditions, same forms (default ``V``).
        R: control weight: scalar, ``[m]`` (diagonal) or ``[m, m]`` SPD (default identity).
        u_min, u_max: override the dynamics' control limits (scalar or ``[m]``).
        relax_cbf: soft CBF constraints (quadratic slack penalty) instead of hard ones.
        cbf_slack_weight: CBF slack weight (default 1e3 for hard, 1e2 for soft constraints).
        clf_slack_weight: weight of the CLF relaxation ``delta`` (default 1e2).
        beta: stochastic-mode margin, scalar or ``[k]`` (default 0; scenario B uses 1).
        rho: risk-aware: probability bound of leaving the safe set within ``horizon``.
        horizon: risk-aware: ``T > 0``.
        eta: risk-aware: noise bound ``|dh/dx sigma| <= eta`` on the safe set, scalar or
            ``[k]``; or ``safe_states`` ``[N, n]`` to compute it with :func:`noise_bound`
            (at construction; one of the two is required).
        clf_rho, clf_eta, clf_gamma: risk-aware CLF: risk (default ``rho``), noise bound of
            ``V`` (default: :func:`noise_bound` over all ``safe_states``), goal level
            ``gamma`` of ``{V <= gamma}`` (default 0).
        fallback: control of rows whose QP failed: ``"clip"`` (``u_nom`` clipped to the
            limits, default), ``"brake"`` (zero clipped to the limits), a tensor ``[m]``,
            or a callable ``(x [B, n], u_nom [B, m]) -> [B, m]``. Wherever the fallback is
            itself non-finite, zero clipped to the limits is used.
        slack_tol: normalised CBF slack ``s`` (control units) above which a row is
            ``RELAXED`` (default 1e-6 in float64, 1e-3 in float32).
        exact: with hard CBF constraints, also solve the hard QP (stacked in the same call)
            and prefer its solution; ``False``: the elastic QP only. Default: ``True`` when
            there are Lyapunov functions (a CLF can pull against a CBF with a multiplier
            beyond the penalty), else ``False``.
        elastic: ``False`` drops the CBF slack variables: one hard QP of ``m + c``
            variables (the fastest form); an infeasible row then gets the fallback
            (status ``FALLBACK``) instead of the least-violating control.
        lie_method: ``"auto"`` (closed forms when a barrier has them, else autograd),
            ``"autograd"`` or ``"analytic"``.
        qp_options: keyword arguments for :func:`torchcbf.qp.solve_qp` (``backend``,
            ``eps``, ``max_iter``, ...).
    """

    def __init__(
        self,
        dynamics: ControlAffine,
        barriers: LieFunction | Sequence[LieFunction] = (),
        lyapunovs: LieFunction | Sequence[LieFunction] = (),
        mode: Mode = "vanilla",
        alpha: ClassKSpec | Sequence[ClassKSpec] = 1.0,
        *,
        clf_rate: ClassKSpec | Sequence[ClassKSpec] = 1.0,
        R: Tensor | float | Sequence[float] | None = None,
        u_min: Tensor | float | Sequence[float] | None = None,
        u_max: Tensor | float | Sequence[float] | None = None,
        relax_cbf: bool = False,
        cbf_slack_weight: float | None = None,
        clf_slack_weight: float = 1e2,
        beta: float | Sequence[float] | Tensor = 0.0,
        rho: float | None = None,
        horizon: float | None = None,
        eta: float | Sequence[float] | Tensor | None = None,
        safe_states: Tensor | None = None,
        clf_rho: float | None = None,
        clf_eta: float | Sequence[float] | Tensor | None = None,
        clf_gamma: float = 0.0,
        fallback: FallbackSpec = "clip",
        slack_tol: float | None = None,
        exact: bool | None = None,
        elastic: bool = True,
        lie_method: Literal["auto", "autograd", "analytic"] = "auto",
        qp_options: dict[str, Any] | None = None,
    ) -> None:
        super().__init__()
        if not isinstance(dynamics, ControlAffine):
            raise TypeError(f"dynamics must be a ControlAffine, got {type(dynamics).__name__}")
        if mode not in MODES:
            raise ValueError(f"mode must be one of {MODES}, got {mode!r}")
        self.dynamics = dynamics
        self.mode = mode
        self.barriers = _modules("barriers", barriers)
        self.lyapunovs = _modules("lyapunovs", lyapunovs)
        if not self.barriers and not self.lyapunovs:
            raise ValueError("barriers and lyapunovs are both empty: nothing to filter")
        if mode == "robust" and dynamics.disturbance_bound is None:
            raise ValueError(
                "mode='robust' needs dynamics built with disturbance_bound= (and optionally "
                "disturbance_matrix=)"
            )
        if mode in ("stochastic", "risk_aware") and not dynamics.has_diffusion:
            raise ValueError(f"mode={mode!r} needs dynamics with a diffusion (sigma=)")
        if lie_method not in ("auto", "autograd", "analytic"):
            raise ValueError(
                f"lie_method must be 'auto', 'autograd' or 'analytic', got {lie_method!r}"
            )
        self.lie_method = lie_method
        m = dynamics.control_dim
        self.alpha = _alphas("alpha", alpha, len(self.barriers))
        self.clf_rate = _alphas("clf_rate", clf_rate, len(self.lyapunovs))
        self.register_buffer("R", _weight_matrix(R, m))
        self.register_buffer("u_min", _limit("u_min", u_min, m))
        self.register_buffer("u_max", _limit("u_max", u_max, m))
        self.relax_cbf = bool(relax_cbf)
        if cbf_slack_weight is None:
            cbf_slack_weight = 1e2 if relax_cbf else 1e3
        self.cbf_slack_weight = _positive("cbf_slack_weight", cbf_slack_weight)
        self.clf_slack_weight = _positive("clf_slack_weight", clf_slack_weight)
        self.register_buffer("beta", as_tensor("beta", beta, dtype=torch.float64))
        if self.beta.dim() > 1:
            raise ValueError(f"beta must be a scalar or [k], got shape {tuple(self.beta.shape)}")
        self._setup_risk(rho, horizon, eta, safe_states, clf_rho, clf_eta, clf_gamma)
        if isinstance(fallback, str):
            if fallback not in ("clip", "brake"):
                raise ValueError(
                    "fallback must be 'clip', 'brake', a tensor [m] or a callable, "
                    f"got {fallback!r}"
                )
            self.register_buffer("_fallback_u", None)
        elif isinstance(fallback, Tensor):
            if fallback.shape != (m,):
                raise ValueError(
                    f"fallback as a tensor must have shape [{m}], got {tuple(fallback.shape)}"
                )
            self.register_buffer("_fallback_u", fallback.detach().clone())
        elif not callable(fallback):
            raise TypeError(f"fallback must be a string, tensor or callable, got {fallback!r}")
        else:
            self.register_buffer("_fallback_u", None)
        self.fallback = fallback if not isinstance(fallback, Tensor) else "tensor"
        if slack_tol is not None:
            slack_tol = _positive("slack_tol", slack_tol)
        self.slack_tol = slack_tol
        self.exact = bool(self.lyapunovs) if exact is None else bool(exact)
        self.elastic = bool(elastic)
        if relax_cbf and not elastic:
            raise ValueError("relax_cbf=True needs elastic=True (the slack variables)")
        self.qp_options = dict(qp_options or {})

    # -- construction helpers ------------------------------------------------------------
    def _setup_risk(
        self,
        rho: float | None,
        horizon: float | None,
        eta: Any,
        safe_states: Tensor | None,
        clf_rho: float | None,
        clf_eta: Any,
        clf_gamma: float,
    ) -> None:
        for name in ("cbf_margin", "clf_margin", "horizon", "clf_gamma"):
            self.register_buffer(name, None)
        if self.mode != "risk_aware":
            return
        if rho is None or not (0 < float(rho) < 1):
            raise ValueError(f"rho must be in (0, 1) for mode='risk_aware', got {rho!r}")
        if horizon is None:
            raise ValueError("horizon (T > 0) is required for mode='risk_aware'")
        T = _positive("horizon", horizon)
        f64 = torch.float64
        if safe_states is not None:
            check_last_dim("safe_states", safe_states, self.dynamics.state_dim)
        if self.barriers:
            if eta is None and safe_states is None:
                raise ValueError(
                    "mode='risk_aware' needs eta= (noise bound |dh/dx sigma| on the safe set) "
                    "or safe_states= (sample states to compute it from)"
                )
            if eta is None:
                parts = [
                    noise_bound(b, self.dynamics, safe_states).reshape(-1) for b in self.barriers
                ]
                eta_t = torch.cat(parts).to(f64)
            else:
                eta_t = as_tensor("eta", eta, dtype=f64)
                if eta_t.dim() > 1 or bool((eta_t < 0).any()):
                    raise ValueError(
                        f"eta must be a non-negative scalar or [k], got {eta_t.tolist()}"
                    )
            self.cbf_margin = risk_margin(eta_t, float(rho), T)
        if self.lyapunovs:
            rho_v = float(rho) if clf_rho is None else float(clf_rho)
            if not 0 < rho_v < 1:
                raise ValueError(f"clf_rho must be in (0, 1), got {clf_rho!r}")
            if clf_eta is None and safe_states is None:
                raise ValueError(
                    "mode='risk_aware' with lyapunovs needs clf_eta= (bound on |dV/dx sigma|) "
                    "or safe_states="
                )
            if clf_eta is None:
                parts = [
                    noise_bound(v, self.dynamics, safe_states, safe_only=False).reshape(-1)
                    for v in self.lyapunovs
                ]
                eta_v = torch.cat(parts).to(f64)
            else:
                eta_v = as_tensor("clf_eta", clf_eta, dtype=f64)
                if eta_v.dim() > 1 or bool((eta_v < 0).any()):
                    raise ValueError(f"clf_eta must be non-negative, got {eta_v.tolist()}")
            self.clf_margin = risk_margin(eta_v, rho_v, T)
            self.clf_gamma = torch.tensor(float(clf_gamma), dtype=f64)
        self.horizon = torch.tensor(T, dtype=f64)

    # -- forward ---------------------------------------------------------------------------
    def _lie(self, fn: LieFunction, x: Tensor, t: Tensor, hessian: bool) -> LieTerms:
        method = self.lie_method
        if method == "auto":
            method = "analytic" if fn.has_analytic else "autograd"
        terms = fn.lie(x, self.dynamics, t, method=method, hessian=hessian)
        return as_columns(terms, x.shape[0])

    def _terms(self, fns: nn.ModuleList, x: Tensor, t: Tensor) -> tuple[LieTerms | None, list[int]]:
        """k-output Lie terms of all ``fns`` concatenated, and each one's number of outputs."""
        if not fns:
            return None, []
        hessian = self.mode in ("stochastic", "risk_aware")
        parts = [self._lie(fn, x, t, hessian) for fn in fns]
        return concat_terms(parts), [p.h.shape[1] for p in parts]

    @staticmethod
    def _class_k(fns: nn.ModuleList, values: Tensor, sizes: list[int]) -> Tensor:
        if len(fns) == 1:
            return fns[0](values)
        return torch.cat([fn(v) for fn, v in zip(fns, values.split(sizes, -1), strict=True)], -1)

    def _limits(self, x: Tensor) -> tuple[Tensor, Tensor]:
        m = self.dynamics.control_dim
        lo = self.u_min if self.u_min is not None else self.dynamics.u_min
        hi = self.u_max if self.u_max is not None else self.dynamics.u_max
        inf = torch.full((m,), math.inf, dtype=x.dtype, device=x.device)
        lo = -inf if lo is None else lo.to(x)
        hi = inf if hi is None else hi.to(x)
        return lo, hi

    def _fallback(self, x: Tensor, u_nom: Tensor, lo: Tensor, hi: Tensor) -> Tensor:
        zero = torch.clamp(torch.zeros_like(u_nom), lo, hi)
        if self.fallback == "clip":
            fb = torch.clamp(u_nom, lo, hi)
        elif self.fallback == "brake":
            fb = zero
        elif self.fallback == "tensor":
            fb = self._fallback_u.to(u_nom).expand_as(u_nom)
        else:
            fb = self.fallback(x, u_nom)
            check_last_dim("fallback(x, u_nom)", fb, u_nom.shape[-1])
            fb = fb.expand_as(u_nom)
        ok = torch.isfinite(fb).all(-1, keepdim=True)
        return torch.where(ok, fb, zero)

    def forward(self, x: Tensor, u_nom: Tensor, t: Tensor | float | None = None) -> FilterOutput:
        """Filter ``u_nom [..., m]`` at states ``x [..., n]`` (batch dims broadcast).

        ``t``: a number or a tensor broadcastable to the batch shape (``None``: 0).
        Returns a :class:`FilterOutput` with the batch shape of ``x`` and ``u_nom``.
        """
        from torchcbf.qp import Status, solve_qp

        dyn = self.dynamics
        n, m = dyn.state_dim, dyn.control_dim
        check_last_dim("x", x, n)
        check_last_dim("u_nom", u_nom, m)
        try:
            batch = broadcast_shapes(x.shape[:-1], u_nom.shape[:-1])
        except RuntimeError:
            raise ValueError(
                f"batch dimensions of x {tuple(x.shape)} and u_nom {tuple(u_nom.shape)} "
                "do not broadcast"
            ) from None
        if not x.is_floating_point() or u_nom.dtype != x.dtype:
            raise TypeError(
                f"x and u_nom must share a floating dtype, got {x.dtype} and {u_nom.dtype}"
            )
        if t is None:
            t = 0.0
        tt = as_tensor("t", t, dtype=x.dtype, device=x.device)
        try:
            tt = torch.broadcast_to(tt, batch)
        except RuntimeError:
            raise ValueError(
                f"t must broadcast to the batch shape {tuple(batch)}, got {tuple(tt.shape)}"
            ) from None
        B = math.prod(batch)
        xb = x.expand(*batch, n).reshape(B, n)
        ub = u_nom.expand(*batch, m).reshape(B, m)
        tb = tt.reshape(B)
        finite = torch.isfinite(xb).all(-1) & torch.isfinite(ub).all(-1) & torch.isfinite(tb)
        fin = finite.unsqueeze(-1)
        xs = torch.where(fin, xb, torch.zeros_like(xb))
        us = torch.where(fin, ub, torch.zeros_like(ub))
        ts = torch.where(finite, tb, torch.zeros_like(tb))

        cbf, cbf_sizes = self._terms(self.barriers, xs, ts)
        clf, clf_sizes = self._terms(self.lyapunovs, xs, ts)
        k = 0 if cbf is None else cbf.h.shape[1]
        c = 0 if clf is None else clf.h.shape[1]
        rows_a, rows_b, norms = [], [], None
        if cbf is not None:
            alpha = lambda h: self._class_k(self.alpha, h, cbf_sizes)  # noqa: E731
            cond = cbf_condition(
                cbf,
                self.mode,
                alpha,
                dyn,
                xs,
                beta=self.beta.to(xs),
                margin=_like(self.cbf_margin, xs),
                horizon=_like(self.horizon, xs),
            )
            self._check_k("beta", self.beta, k)
            self._check_k("eta", self.cbf_margin, k)
            norms = torch.linalg.vector_norm(cond.a, dim=-1).clamp_min(1e-6)
            rows_a.append(cond.a)
            rows_b.append(cond.b)
        if clf is not None:
            rate = lambda v: self._class_k(self.clf_rate, v, clf_sizes)  # noqa: E731
            cond_v = clf_condition(
                clf,
                self.mode,
                rate,
                dyn,
                xs,
                margin=_like(self.clf_margin, xs),
                gamma=_like(self.clf_gamma, xs),
                horizon=_like(self.horizon, xs),
            )
            self._check_k("clf_eta", self.clf_margin, c)
            rows_a.append(cond_v.a)
            rows_b.append(cond_v.b)

        lo, hi = self._limits(xs)
        # slack columns of the CBF rows: one shared (the largest violation) for hard rows,
        # one per row for soft ones, none without elastic rows
        ks = 0 if not (k and self.elastic) else (k if self.relax_cbf else 1)
        Q, p, G, hq, lb, ubd = self._qp(rows_a, rows_b, norms, us, k, c, lo, hi, ks)
        data_ok = torch.isfinite(G).flatten(1).all(-1) & torch.isfinite(hq).all(-1) & finite
        G = torch.where(data_ok[:, None, None], G, torch.zeros_like(G))
        hq = torch.where(data_ok[:, None], hq, torch.ones_like(hq))
        two_pass = bool(ks) and self.exact and not self.relax_cbf
        if two_pass:
            # rows [B:2B]: the hard QP (the slack columns of the CBF rows zeroed; s then
            # decouples and sits at its bound 0), solved in the same call as the elastic one
            G_hard = G.clone()
            G_hard[:, :k, m : m + ks] = 0
            cat = lambda v: torch.cat([v, v], 0)  # noqa: E731
            sol = solve_qp(
                cat(Q),
                cat(p),
                torch.cat([G, G_hard], 0),
                cat(hq),
                lb=cat(lb),
                ub=cat(ubd),
                **self.qp_options,
            )
            good = (sol.status == Status.SOLVED) & torch.isfinite(sol.x).all(-1) & cat(data_ok)
            el_ok, hard_ok = good[:B], good[B:]
            z = torch.where(hard_ok.unsqueeze(-1), sol.x[B:], sol.x[:B])
            qp_status = torch.where(hard_ok, sol.status[B:], sol.status[:B])
            qp_ok = hard_ok | el_ok
        else:
            sol = solve_qp(Q, p, G, hq, lb=lb, ub=ubd, **self.qp_options)
            z, qp_status = sol.x, sol.status
            qp_ok = data_ok & (qp_status == Status.SOLVED) & torch.isfinite(z).all(-1)
        u_qp = z[:, :m]
        s = z[:, m : m + ks]
        delta = z[:, m + ks :]
        fb = self._fallback(xb, ub, lo, hi)
        u = torch.where(qp_ok.unsqueeze(-1), u_qp, fb)

        tol = self.slack_tol
        if tol is None:
            tol = 1e-6 if xs.dtype == torch.float64 else 1e-3
        relaxed = (s > tol).any(-1) if ks else torch.zeros_like(finite)
        status = torch.full_like(qp_status, FilterStatus.SOLVED)
        status = torch.where(relaxed, torch.full_like(status, FilterStatus.RELAXED), status)
        status = torch.where(qp_ok, status, torch.full_like(status, FilterStatus.FALLBACK))
        status = torch.where(finite, status, torch.full_like(status, FilterStatus.NON_FINITE))

        okc = qp_ok.unsqueeze(-1)
        slack_parts, value_parts = [], []
        if k:
            value_parts.append((rows_a[0] @ u.unsqueeze(-1)).squeeze(-1) + rows_b[0])
            slack_parts.append((-value_parts[0]).clamp_min(0))
        if c:
            slack_parts.append(delta.clamp_min(0))
            value_parts.append(-((rows_a[-1] @ u.unsqueeze(-1)).squeeze(-1) + rows_b[-1]))
        slack = torch.cat(slack_parts, -1) if slack_parts else xs.new_zeros(B, 0)
        slack = torch.where(okc, slack, torch.zeros_like(slack))
        cval = torch.cat(value_parts, -1)
        nan = torch.full_like(cval, math.nan)
        cval = torch.where(finite.unsqueeze(-1), cval, nan)
        h = cbf.h if cbf is not None else xs.new_zeros(B, 0)
        h = torch.where(fin, h, torch.full_like(h, math.nan))
        V = clf.h if clf is not None else xs.new_zeros(B, 0)
        V = torch.where(fin, V, torch.full_like(V, math.nan))
        return FilterOutput(
            u=u.reshape(*batch, m),
            status=status.reshape(batch),
            h=h.reshape(*batch, k),
            slack=slack.reshape(*batch, k + c),
            clf_value=V.reshape(*batch, c),
            qp_status=qp_status.reshape(batch),
            constraint_value=cval.reshape(*batch, k + c),
        )

    # -- internals -------------------------------------------------------------------------
    @staticmethod
    def _check_k(name: str, value: Tensor | None, k: int) -> None:
        if value is not None and value.dim() == 1 and value.shape[0] != k:
            raise ValueError(
                f"{name} must be a scalar or have one entry per barrier output ({k}), "
                f"got shape {tuple(value.shape)}"
            )

    @staticmethod
    def _penalty_scale(
        a: Tensor, b: Tensor, norms: Tensor, u_nom: Tensor, lo: Tensor, hi: Tensor
    ) -> Tensor:
        """``1 + v`` per row ``[B, 1]``, detached: ``v`` estimates the hard QP's multipliers
        (in units of ``rbar``) by how far ``u_nom`` is from the box and the CBF half-spaces
        (normalised violation), capped at 1e3."""
        with torch.no_grad():
            viol = (-((a @ u_nom.unsqueeze(-1)).squeeze(-1) + b) / norms).clamp_min(0)
            box = (u_nom - torch.clamp(u_nom, lo, hi)).abs()
            v = viol.amax(-1, keepdim=True) + box.amax(-1, keepdim=True)
            v = torch.nan_to_num(v, nan=0.0, posinf=1e3).clamp_max(1e3)
        return 1.0 + v

    def _qp(
        self,
        rows_a: list[Tensor],
        rows_b: list[Tensor],
        norms: Tensor | None,
        u_nom: Tensor,
        k: int,
        c: int,
        lo: Tensor,
        hi: Tensor,
        ks: int,
    ) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor, Tensor]:
        """QP data ``min 1/2 z'Qz + p'z, Gz <= h, lb <= z <= ub`` for ``z = [u; s; delta]``."""
        B, m = u_nom.shape
        nz = m + ks + c
        R = self.R.to(u_nom)
        rbar = torch.diagonal(R).mean()
        w = u_nom.new_full((B, 1), self.cbf_slack_weight) * rbar
        if k and not self.relax_cbf:
            w = w * self._penalty_scale(rows_a[0], rows_b[0], norms, u_nom, lo, hi)
        lin_s = torch.zeros_like(w) if self.relax_cbf else w
        Q = torch.diag_embed(
            torch.cat(
                [
                    u_nom.new_zeros(B, m),
                    w.expand(B, ks),
                    (self.clf_slack_weight * rbar).expand(B, c),
                ],
                -1,
            )
        )
        Q[:, :m, :m] = R
        p = torch.cat([-(u_nom @ R.mT), lin_s.expand(B, ks), u_nom.new_zeros(B, c)], -1)
        G_parts, h_parts = [], []
        if k:
            a, b = rows_a[0], rows_b[0]
            if ks == k:
                eye = torch.eye(k, dtype=u_nom.dtype, device=u_nom.device).expand(B, k, k)
            else:  # one shared slack (ks = 1) or none (ks = 0)
                eye = u_nom.new_ones(B, k, ks)
            G_parts.append(
                torch.cat([-a / norms.unsqueeze(-1), -eye, u_nom.new_zeros(B, k, c)], -1)
            )
            h_parts.append(b / norms)
        if c:
            a, b = rows_a[-1], rows_b[-1]
            eye = torch.eye(c, dtype=u_nom.dtype, device=u_nom.device).expand(B, c, c)
            G_parts.append(torch.cat([a, u_nom.new_zeros(B, c, ks), -eye], -1))
            h_parts.append(-b)
        G = torch.cat(G_parts, 1)
        hq = torch.cat(h_parts, 1)
        inf = u_nom.new_full((ks + c,), math.inf)
        lb = torch.cat([lo, torch.zeros_like(inf)]).expand(B, nz)
        ub = torch.cat([hi, inf]).expand(B, nz)
        return Q, p, G, hq, lb, ub
