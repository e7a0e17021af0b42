"""Lie derivatives of scalar (or k-output) functions of the state, by batched autograd.

One routine, :func:`lie_derivatives`, serves barriers and Lyapunov functions alike. For a
function ``h(x, t)`` and dynamics ``dx = (f + g u) dt + sigma dW`` it returns
:class:`LieTerms`: ``h``, ``L_f h = dh/dx f``, ``L_g h = dh/dx g``, ``dh/dt``,
``tr(sigma' d2h/dx2 sigma)`` and ``dh/dx``.

Batching: rows of a batch are independent, so ``d/dx sum_rows h`` gives every row's gradient
in one backward pass. A k-output function (``h [..., k]``) needs one pass per output; a
function that splits into independent parts (:meth:`LieFunction.parts`: the members of a
:class:`~torchcbf.barriers.BarrierStack`, the ``k`` shapes of a batched shape) runs each pass
through its own part's graph only.
The Hessian trace is ``sum_j s_j' H s_j`` over the ``q`` columns ``s_j`` of ``sigma``:
one batched Hessian-vector product per column.
"""

from __future__ import annotations

import warnings
from collections.abc import Callable
from typing import Any, ClassVar, Literal, NamedTuple

import torch
from torch import Tensor

from torchcbf._autograd import needs_graph, recordable, recording
from torchcbf._checks import (
    ClosedForms,
    TracksShadows,
    apply_rules,
    as_tensor,
    check_tensor,
    several_outputs,
    shadowed,
)
from torchcbf._constants import ExactConstants, store
from torchcbf.dynamics.base import ControlAffine, matmat, matvec

LieMethod = Literal["autograd", "analytic"]
#: states x components up to which L_f h and L_g h are formed by broadcasting (fewer ops on a
#: few states) rather than by batched matmuls (faster on large batches)
SMALL_BATCH_ELEMENTS = 256
HessQuad = Callable[[Tensor], Tensor]
HessMat = Callable[[Tensor], Tensor]
HessDir = Callable[[Tensor, Tensor], Tensor]


class LieTerms(NamedTuple):
    """Everything a CBF/CLF condition needs at a batch of states.

    Shapes for a scalar function (``k`` outputs add a ``k`` axis before the last one):
    ``h [...]``, ``lfh [...]``, ``lgh [..., m]``, ``dhdt [...]``, ``hess_trace [...]`` or
    ``None`` (dynamics without diffusion, or ``hessian=False``), ``dhdx [..., n]``.
    With ``k`` outputs: ``h, lfh, dhdt, hess_trace [..., k]``, ``lgh [..., k, m]``,
    ``dhdx [..., k, n]``.
    """

    h: Tensor
    lfh: Tensor
    lgh: Tensor
    dhdt: Tensor
    hess_trace: Tensor | None
    dhdx: Tensor


class AnalyticDerivatives(NamedTuple):
    """Closed-form derivatives a shape may provide (see :meth:`LieFunction.derivatives`).

    ``h [...]`` (or ``[..., k]``), ``dhdx [..., n]`` (or ``[..., k, n]``), ``dhdt`` like ``h``,
    and ``hess_quad(S [..., n, q]) -> tr(S' d2h/dx2 S)`` shaped like ``h``.

    Second order, for functions with :attr:`LieFunction.has_second_order` (the closed-form
    exponential CBF needs them; ``None`` otherwise): ``hess_mat(M [..., n, q]) -> H M``
    ``[..., n, q]`` (or ``[..., k, n, q]``) with ``H = d2h/dx2``, and ``hess_dir(v [..., n],
    S [..., n, q]) -> tr(S' (dH/dx . v) S)`` shaped like ``h`` (the change of ``hess_quad``
    along ``v``; zero for quadratic shapes).
    """

    h: Tensor
    dhdx: Tensor
    dhdt: Tensor
    hess_quad: HessQuad
    hess_mat: HessMat | None = None
    hess_dir: HessDir | None = None


class Quadric(NamedTuple):
    """``k`` quadrics on the position ``p = x[..., index]`` (``d`` components), the form the
    native Lie kernel evaluates (see :meth:`LieFunction.quadric`):
    ``h_j = sign * scale_j * (sum_i (q_ji / a_ji)^2 - r_j^2)`` with body coordinates
    ``q_j = R(angle_j)' (p - c_j)``.

    ``center`` ``[d]`` (one function, ``h [...]``) or ``[k, d]`` (``h [..., k]``); ``axes``
    ``a`` shaped like ``center`` (``None``: all 1); ``radius`` ``r``, ``angle`` (``d = 2``)
    and ``scale`` each ``[]`` or ``[k]`` (``None``: 1, no rotation, 1); ``sign`` +-1.
    """

    index: tuple[int, ...]
    center: Tensor
    axes: Tensor | None = None
    radius: Tensor | None = None
    angle: Tensor | None = None
    scale: Tensor | None = None
    sign: float = 1.0


class FollowsTime:
    """A class's ``time_varying`` derived from its own state at each read (a wrapper is
    time-varying when the function it wraps is; a ``Ball`` when it has a ``velocity``),
    unless an instance sets it (``self.time_varying = True``, as any time-varying subclass
    may)."""

    def __init__(self, derive: Callable[[Any], bool]) -> None:
        self.derive = derive

    def __get__(self, obj: Any, owner: type | None = None) -> Any:
        if obj is None:
            return self
        given = obj.__dict__.get("_time_varying")
        return bool(self.derive(obj)) if given is None else given

    def __set__(self, obj: Any, value: bool) -> None:
        obj.__dict__["_time_varying"] = bool(value)


class LieFunction(TracksShadows, ExactConstants):
    """Base of :class:`~torchcbf.barriers.Barrier` and :class:`~torchcbf.barriers.Lyapunov`.

    Subclasses write ``forward(x [..., n], t=None) -> [...]`` (or ``[..., k]`` for ``k``
    functions evaluated at once) and store their constants with :meth:`register_constant`.
    Time-varying subclasses set ``time_varying = True`` and receive ``t`` as a tensor
    broadcastable to the batch shape ``[...]``. Subclasses may add closed-form derivatives
    by overriding :meth:`derivatives` and :attr:`has_analytic`, and declare independent
    pieces with :meth:`parts`.
    """

    time_varying: bool = False
    #: the closed forms a subclass may give, each trusted only where the class defining it
    #: also defines ``forward`` (see :func:`torchcbf._checks.honour_overrides`): a subclass
    #: that changes ``forward`` alone is differentiated by autograd and split into no parts;
    #: the C kernels read ``quadric`` instead of calling ``lie``. A class whose ``forward``
    #: calls another public method of its own extends this table (and its subclasses are
    #: checked against it).
    closed_forms: ClassVar[ClosedForms] = {
        "derivatives": (("forward", "__call__"), ("has_analytic", "has_second_order")),
        "quadric": (("forward", "__call__", "lie"), ()),
        "parts": (("forward", "__call__"), ()),
    }

    #: each fast form's answer for an instance with forward hooks, which takes the general
    #: path (a hook changes what ``forward`` computes; see :func:`torchcbf._checks.unless_hooked`)
    hooked_forms: ClassVar[dict[str, object]] = {
        "has_analytic": False,
        "has_second_order": False,
        "quadric": None,
        "parts": None,
    }

    def __init_subclass__(cls, **kwargs: Any) -> None:
        super().__init_subclass__(**kwargs)
        apply_rules(cls, LieFunction)

    def register_constant(
        self, name: str, value: object, *, learnable: bool = False, allow_inf: bool = False
    ) -> Tensor:
        """Store the constant ``name`` and return it: an ``nn.Parameter`` when ``value`` is
        one or ``learnable``, else a buffer (so ``.to(device, dtype)`` moves it). A tensor
        that requires grad keeps its gradient; Python numbers stay exact under ``.double()``
        (``0.1``, not ``float32(0.1)``). NaN, and ``inf`` unless ``allow_inf``, raise a
        ``ValueError`` naming ``name``."""
        return store(self, name, value, learnable=learnable, allow_inf=allow_inf)

    @property
    def has_analytic(self) -> bool:
        """Whether :meth:`derivatives` (``lie(..., method="analytic")``) is available."""
        return False

    @property
    def has_second_order(self) -> bool:
        """Whether :meth:`derivatives` also gives ``hess_mat`` and ``hess_dir`` (see
        :class:`AnalyticDerivatives`), for every state and time."""
        return False

    def quadric(self) -> Quadric | None:
        """This function as :class:`Quadric` (its constants as they are now), or ``None``.
        Time-invariant quadric shapes give it (:class:`~torchcbf.barriers.Ball`,
        :class:`~torchcbf.barriers.Ellipse`, :class:`~torchcbf.barriers.Scaled` of one);
        :mod:`torchcbf.barriers.native` then evaluates their Lie terms in C. A subclass that
        changes ``forward`` must override it too."""
        return None

    def parts(self) -> list[LieFunction] | None:
        """Independent parts whose outputs, concatenated, are this function's ``[..., k]``
        (``None``: one part). The autograd path differentiates the parts separately, so a
        backward pass for one output only runs through the graph of its own part. Override
        it in a function made of independent pieces (a stack of barriers, ``k`` shapes)."""
        return None

    def derivatives(self, x: Tensor, t: Tensor) -> AnalyticDerivatives:
        """Closed-form ``h``, ``dh/dx``, ``dh/dt`` and the Hessian quadratic form at
        ``x [..., n]``, ``t [...]``. Override it together with :attr:`has_analytic`."""
        raise ValueError(
            f"{type(self).__name__} has no closed-form derivatives; use method='autograd'"
        )

    def lie(
        self,
        x: Tensor,
        dynamics: ControlAffine,
        t: Tensor | float | None = None,
        *,
        method: LieMethod = "autograd",
        hessian: bool = True,
    ) -> LieTerms:
        """Lie derivatives at ``x [..., n]`` (see :func:`lie_derivatives`)."""
        return lie_derivatives(self, x, dynamics, t, method=method, hessian=hessian)


#: the family whose rules :func:`torchcbf._checks.reapply_rules` applies to a subclass
LieFunction.rules_base = LieFunction


def own_lie(fn: LieFunction) -> bool:
    """Whether ``fn``'s class rewrites :meth:`LieFunction.lie`, or ``fn`` holds its own
    (``fn.lie = ...``; the user's own Lie terms): then every path takes its terms from
    ``fn.lie``, none from a stacked or compiled evaluation of ``fn``'s calls."""
    return type(fn).lie is not LieFunction.lie or shadowed(fn, ("lie",))


def terms_of(
    fn: LieFunction,
    x: Tensor,
    dynamics: ControlAffine,
    t: Tensor | float | None = None,
    *,
    method: LieMethod = "autograd",
    hessian: bool = True,
    control: bool = True,
) -> LieTerms:
    """``fn``'s Lie terms (:func:`lie_derivatives`), from ``fn.lie`` where its class
    rewrites it (:func:`own_lie`; it computes every term, ``control`` or not)."""
    if own_lie(fn):
        return fn.lie(x, dynamics, t, method=method, hessian=hessian)
    return lie_derivatives(fn, x, dynamics, t, method=method, hessian=hessian, control=control)


def time_tensor(t: Tensor | float | None, x: Tensor) -> Tensor:
    """``t`` (``None`` means 0) as a tensor of the batch shape ``x.shape[:-1]``, x's dtype."""
    batch = x.shape[:-1]
    if t is None:
        return x.new_zeros(batch)
    if isinstance(t, Tensor) and t.shape == batch and t.dtype == x.dtype and t.device == x.device:
        return t
    t = as_tensor("t", t, dtype=x.dtype, device=x.device)
    try:
        return torch.broadcast_to(t, batch)
    except RuntimeError:
        raise ValueError(
            f"t must broadcast to the batch shape {tuple(batch)}, got {tuple(t.shape)}"
        ) from None


def _grad(
    out: Tensor, inputs: tuple[Tensor, ...], create: bool, *, materialize: bool = True
) -> tuple[Tensor | None, ...]:
    """Gradient of ``out.sum()`` w.r.t. ``inputs``; zeros (``None`` unless ``materialize``)
    where ``out`` does not depend on one."""
    if not out.requires_grad:
        return tuple(torch.zeros_like(i) if materialize else None for i in inputs)
    return torch.autograd.grad(
        out.sum(),
        inputs,
        create_graph=create,
        retain_graph=True,
        allow_unused=True,
        materialize_grads=materialize,
    )


def _undeclared_time(part: LieFunction) -> None:
    warnings.warn(
        f"{type(part).__name__} reads t but does not declare time_varying = True: its Lie "
        "terms include dh/dt, but metrics, MPPI costs and specs call it without t; declare "
        "it (a class attribute, or self.time_varying = True)",
        stacklevel=4,
    )


def lie_derivatives(
    fn: LieFunction,
    x: Tensor,
    dynamics: ControlAffine,
    t: Tensor | float | None = None,
    *,
    method: LieMethod = "autograd",
    hessian: bool = True,
    control: bool = True,
) -> LieTerms:
    """Lie derivatives of ``fn`` along ``dynamics`` at a batch of states, in one call.

    Args:
        fn: a :class:`LieFunction` with ``fn(x, t) -> [...]`` or ``[..., k]``.
        x: states ``[..., n]`` with ``n = dynamics.state_dim``.
        dynamics: the control-affine model.
        t: time, a number or a tensor broadcastable to ``[...]`` (``None``: 0).
        method: ``"autograd"`` (default, any function) or ``"analytic"`` (closed forms of a
            shape, raises ``ValueError`` for functions without them).
        hessian: compute ``hess_trace`` when the dynamics has a diffusion.
        control: compute ``lgh`` (otherwise it is returned as zeros ``[..., (k,) m]``).

    Returns:
        :class:`LieTerms`. When grad mode is on and something the derivatives depend on
        requires grad (:func:`derivatives_need_graph`), the graph is kept
        (``create_graph=True``): every term differentiates w.r.t. ``x``, ``t`` and the
        parameters of ``fn`` and ``dynamics``. Otherwise (``torch.no_grad()``,
        ``torch.inference_mode()``, or nothing requires grad) the terms are computed all the
        same and returned without a graph (``f`` and ``g`` keep theirs, if any).
    """
    if not isinstance(dynamics, ControlAffine):
        raise TypeError(f"dynamics must be a ControlAffine model, got {type(dynamics).__name__}")
    dynamics.check_inputs(x)
    if method not in ("autograd", "analytic"):
        raise ValueError(f"method must be 'autograd' or 'analytic', got {method!r}")
    diffusion = hessian and dynamics.has_diffusion
    if method == "analytic":
        # closed forms are plain tensor expressions: differentiable in grad mode, no graph
        # otherwise, so they need neither the autograd context nor a detach
        return _analytic_terms(fn, x, dynamics, t, diffusion, control)
    grad_mode = torch.is_grad_enabled()
    with recording():
        x, t = recordable(x), recordable(t)
        terms = _autograd_terms(fn, x, dynamics, t, diffusion, control, grad_mode)
    if not grad_mode:
        terms = LieTerms(*(None if v is None else v.detach() for v in terms))
    return terms


def stacked_lie_derivatives(
    fns: list[LieFunction],
    x: Tensor,
    dynamics: ControlAffine,
    t: Tensor | float | None = None,
    *,
    hessian: bool = True,
) -> tuple[LieTerms, list[int]]:
    """Lie derivatives of several functions at once by autograd, their outputs concatenated:
    ``h, lfh, dhdt, hess_trace [..., K]``, ``lgh [..., K, m]``, ``dhdx [..., K, n]``, and
    each function's number of outputs. The same terms as one :func:`lie_derivatives` call per
    function, in two backward passes for all (see :func:`stacked_terms`) instead of two per
    function. Grad mode, inference mode and graphs as for :func:`lie_derivatives`."""
    dynamics.check_inputs(x)
    grad_mode = torch.is_grad_enabled()
    diffusion = hessian and dynamics.has_diffusion
    with recording():
        x, t = recordable(x), recordable(t)
        split = [flat_parts(fn) for fn in fns]
        sigma = dynamics.sigma(x) if diffusion else None
        parts = [p for ps in split for p in ps]
        keep = grad_mode and derivatives_need_graph(parts, x, t, sigma)
        h, dhdx, dhdt, hess, sizes, _ = stacked_terms(parts, x, t, sigma, keep)
        terms = _assemble(h, dhdx, dhdt, hess, x, dynamics, True, True)
    if not grad_mode:
        terms = LieTerms(*(None if v is None else v.detach() for v in terms))
    per_fn, i = [], 0
    for ps in split:
        per_fn.append(sum(sizes[i : i + len(ps)]))
        i += len(ps)
    return terms, per_fn


def _autograd_terms(
    fn: LieFunction,
    x: Tensor,
    dynamics: ControlAffine,
    t: Tensor | float | None,
    diffusion: bool,
    control: bool,
    grad_mode: bool,
) -> LieTerms:
    sigma = dynamics.sigma(x) if diffusion else None
    parts = flat_parts(fn)
    keep = grad_mode and derivatives_need_graph(parts, x, t, sigma)
    h, dhdx, dhdt, hess, _, flags = stacked_terms(parts, x, t, sigma, keep)
    # one scalar function keeps the shape [...]; a split or k-output one is [..., k]
    multi = parts[0] is not fn or flags[0]
    if not multi:
        h, dhdx, dhdt = h.squeeze(-1), dhdx.squeeze(-2), dhdt.squeeze(-1)
        hess = None if hess is None else hess.squeeze(-1)
    return _assemble(h, dhdx, dhdt, hess, x, dynamics, multi, control)


def stacked_terms(
    parts: list[LieFunction],
    x: Tensor,
    t: Tensor | float | None,
    sigma: Tensor | None,
    create: bool,
) -> tuple[Tensor, Tensor, Tensor, Tensor | None, list[int], list[bool]]:
    """``h, dhdt, hess [..., K]``, ``dhdx [..., K, n]`` of independent functions ``parts``
    (their outputs concatenated), each part's number of outputs, and whether it returned
    ``[..., k]`` (rather than ``[...]``).

    Every output of every part is evaluated on its own copy of the state (one copy per
    output and per column of ``sigma``; a part with ``k`` outputs runs once on ``k`` copies
    and its diagonal is kept), so ONE backward pass gives every gradient and a second one
    every Hessian-vector product ``H_j s_l``, whatever the number of parts and outputs.
    ``create`` keeps the graph of the outputs (otherwise they are returned detached)."""
    n = x.shape[-1]
    Q = 1 if sigma is None else sigma.shape[-1]
    batch = x.shape[:-1]
    nb = len(batch)
    base = x if x.requires_grad else x.detach()
    tt = time_tensor(t, x)

    def copies(v: Tensor, k: int, trailing: tuple[int, ...]) -> Tensor:
        out = v[(..., None, None, *([slice(None)] * len(trailing)))]
        out = out.expand(*batch, k, Q, *trailing).clone()
        return out if out.requires_grad else out.requires_grad_()

    def run(part: LieFunction, k: int) -> tuple[Tensor, Tensor, Tensor]:
        # every part gets a time it can be differentiated in: one that reads t without
        # declaring time_varying still gets its dh/dt (and a warning)
        xk, tk = copies(base, k, (n,)), copies(tt, k, ())
        return part(xk, tk), xk, tk

    leaves: list[Tensor] = []
    multi: list[bool] = []
    t_leaves: list[Tensor] = []
    values: list[Tensor] = []  # [..., k, Q] per part
    total = x.new_zeros(())
    for part in parts:
        h, xk, tk = run(part, 1)
        multi.append(h.shape != (*batch, 1, Q))
        if not multi[-1]:
            hd = h
        elif h.dim() == nb + 3 and h.shape[:-1] == (*batch, 1, Q):
            k = h.shape[-1]
            h, xk, tk = run(part, k)  # [..., k(copies), Q, k(outputs)]: keep the diagonal
            hd = torch.diagonal(h, dim1=nb, dim2=-1).movedim(-1, nb)
        else:
            raise ValueError(
                f"{type(part).__name__} must return [...] or [..., k] for a state of shape "
                f"{tuple(xk.shape)}, got {tuple(h.shape)}"
            )
        check_tensor(f"{type(part).__name__} output", hd)
        leaves.append(xk)
        t_leaves.append(tk)
        values.append(hd)
        total = total + hd.sum()
    grads = _grad(total, (*leaves, *t_leaves), create or sigma is not None, materialize=False)
    g_x = [
        torch.zeros_like(v) if g is None else g
        for g, v in zip(grads[: len(leaves)], leaves, strict=True)
    ]
    g_t = grads[len(leaves) :]
    hess: list[Tensor] | None = None
    if sigma is not None:
        s_cols = sigma.movedim(-1, -2).unsqueeze(-3)  # [..., 1, Q, n]
        inner = sum((g * s_cols).sum() for g in g_x)
        hv = _grad(inner, tuple(leaves), create)  # type: ignore[arg-type]
        hess = [(v * s_cols).sum((-2, -1)) for v in hv]  # [..., k]
    dhdt = []
    for part, hd, gt in zip(parts, values, g_t, strict=True):
        if gt is not None and not part.time_varying:
            _undeclared_time(part)
        dhdt.append(torch.zeros_like(hd[..., 0]) if gt is None else gt[..., 0])
    sizes = [hd.shape[-2] for hd in values]
    out = (
        torch.cat([hd[..., 0] for hd in values], -1),
        torch.cat([g[..., 0, :] for g in g_x], -2),
        torch.cat(dhdt, -1),
        None if hess is None else torch.cat(hess, -1),
    )
    if not create:  # their graph leads only to the copies of the state made here
        out = tuple(None if v is None else v.detach() for v in out)
    return (*out, sizes, multi)


def derivatives_need_graph(
    parts: list[LieFunction], x: Tensor, t: Tensor | float | None, sigma: Tensor | None
) -> bool:
    """Whether the derivatives of ``parts`` at ``x`` (and their Hessian terms along
    ``sigma``) can carry a gradient, in grad mode: ``x``, ``t`` or ``sigma`` requires grad, a
    parameter or buffer of a part does, or a part's value at a constant ``x`` does (a tensor
    it captures, a nested derivative that keeps a graph; a part that cannot be evaluated
    there, one differentiating its own input, counts as one that does). Where none does,
    the terms are computed without a graph: a robot loop in grad mode gets plain tensors, as
    under ``torch.no_grad()``."""
    if x.requires_grad or (isinstance(t, Tensor) and t.requires_grad):
        return True
    if (sigma is not None and sigma.requires_grad) or any(needs_graph(p) for p in parts):
        return True
    tt = time_tensor(t, x)
    try:
        return any(part(x, tt).requires_grad for part in parts)
    except RuntimeError:
        return True


def gradient_rows(d: AnalyticDerivatives, x: Tensor) -> tuple[bool, Tensor]:
    """Whether ``d`` belongs to one scalar function (``h [...]``, for states ``x [..., n]``)
    and its gradient as rows ``[..., k, n]`` either way (``k = 1`` for a scalar function)."""
    single = d.h.shape == x.shape[:-1]
    return single, d.dhdx.unsqueeze(-2) if single else d.dhdx


def per_output(v: Tensor, single: bool, dim: int = -1) -> Tensor:
    """A term with an output axis at ``dim`` (``[..., k]`` at -1, ``[..., k, n]`` at -2) in
    the shape of the function's own terms: the axis dropped for a scalar one (``single``)."""
    return v.squeeze(dim) if single else v


def flat_parts(fn: LieFunction) -> list[LieFunction]:
    """``fn`` split into independently differentiable parts (see :meth:`LieFunction.parts`)."""
    parts = fn.parts()
    if parts is None:
        return [fn]
    return [q for p in parts for q in flat_parts(p)]


class FunctionPart(LieFunction):
    """A callable ``(x, t) -> [...]`` (or ``[..., k]``) as a :class:`LieFunction` (no tensors
    of its own: it reads its owner's parameters when called)."""

    def __init__(self, fn: Callable[[Tensor, Tensor | None], Tensor], time_varying: bool) -> None:
        super().__init__()
        object.__setattr__(self, "_fn", fn)  # a bound method or closure of the owner
        self.time_varying = time_varying

    def forward(self, x: Tensor, t: Tensor | None = None) -> Tensor:
        return self._fn(x, t)


def _analytic_terms(
    fn: LieFunction,
    x: Tensor,
    dynamics: ControlAffine,
    t: Tensor | float | None,
    diffusion: bool,
    control: bool,
) -> LieTerms:
    if not fn.has_analytic:
        raise ValueError(
            f"{type(fn).__name__} has no closed-form derivatives; use method='autograd'"
        )
    d = fn.derivatives(x, time_tensor(t, x))
    check_tensor(f"{type(fn).__name__} output", d.h)
    multi = several_outputs(type(fn).__name__, d.h, x)
    hess = d.hess_quad(dynamics.sigma(x)) if diffusion else None
    return _assemble(d.h, d.dhdx, d.dhdt, hess, x, dynamics, multi, control)


def _assemble(
    h: Tensor,
    dhdx: Tensor,
    dhdt: Tensor,
    hess: Tensor | None,
    x: Tensor,
    dynamics: ControlAffine,
    multi: bool,
    control: bool,
) -> LieTerms:
    f = dynamics.f(x)
    g = dynamics.g(x) if control else None
    if x.numel() <= SMALL_BATCH_ELEMENTS:
        # a few states: broadcast multiply-and-sum, fewer dispatched ops than a batched
        # matmul (but for lgh of k outputs, where one matmul is cheaper than three ops)
        lfh = (dhdx * f.unsqueeze(-2)).sum(-1) if multi else (dhdx * f).sum(-1)
        if g is not None:
            lgh = dhdx @ g if multi else (dhdx.unsqueeze(-1) * g).sum(-2)
    elif x.device.type != "cpu":
        # many states on a GPU: sums of scaled columns (batched matmuls of [k, n] blocks
        # took 4.6 ms of a filter call on 1e6 states on an H200; CPU matmul is faster)
        lfh = matvec(dhdx, f) if multi else (dhdx * f).sum(-1)
        if g is not None:
            lgh = matmat(dhdx, g) if multi else matvec(g.mT, dhdx)
    else:
        f = f.unsqueeze(-1)
        lfh = (dhdx @ f).squeeze(-1) if multi else (dhdx.unsqueeze(-2) @ f)[..., 0, 0]
        if g is not None:
            lgh = dhdx @ g if multi else (dhdx.unsqueeze(-2) @ g).squeeze(-2)
    if g is None:
        lgh = h.new_zeros((*h.shape, dynamics.control_dim))
    return LieTerms(h, lfh, lgh, dhdt, hess, dhdx)
