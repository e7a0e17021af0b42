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

import contextlib
from collections.abc import Callable
from typing import Literal, NamedTuple

import torch
from torch import Tensor, nn

from torchcbf._checks import as_tensor, check_tensor
from torchcbf.dynamics.base import ControlAffine

LieMethod = Literal["autograd", "analytic"]
HessQuad = Callable[[Tensor], Tensor]


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
    """

    h: Tensor
    dhdx: Tensor
    dhdt: Tensor
    hess_quad: HessQuad


class LieFunction(nn.Module):
    """Base of :class:`~torchcbf.barriers.Barrier` and :class:`~torchcbf.barriers.Lyapunov`.

    Subclasses write ``forward(x [..., n], t=None) -> [...]`` (or ``[..., k]`` for ``k``
    functions evaluated at once). Time-varying subclasses set ``time_varying = True`` and
    receive ``t`` as a tensor broadcastable to the batch shape ``[...]``. Subclasses may add
    closed-form derivatives by overriding :meth:`derivatives` and :attr:`has_analytic`, and
    declare independent pieces with :meth:`parts`.
    """

    time_varying: bool = False

    @property
    def has_analytic(self) -> bool:
        """Whether :meth:`derivatives` (``lie(..., method="analytic")``) is available."""
        return False

    def parts(self) -> list[LieFunction] | None:
        """Independent parts whose outputs, concatenated, are this function's ``[..., k]``
        (``None``: one part). The autograd path differentiates the parts separately, so a
        backward pass for one output only runs through the graph of its own part. Override
        it in a function made of independent pieces (a stack of barriers, ``k`` shapes)."""
        if type(self)._parts is not LieFunction._parts:  # a subclass of the former name
            return self._parts()
        return None

    def derivatives(self, x: Tensor, t: Tensor) -> AnalyticDerivatives:
        """Closed-form ``h``, ``dh/dx``, ``dh/dt`` and the Hessian quadratic form at
        ``x [..., n]``, ``t [...]``. Override it together with :attr:`has_analytic`."""
        if type(self)._analytic is not LieFunction._analytic:  # a subclass of the former name
            return self._analytic(x, t)
        raise ValueError(
            f"{type(self).__name__} has no closed-form derivatives; use method='autograd'"
        )

    def _parts(self) -> list[LieFunction] | None:
        """Former name of :meth:`parts` (kept as an alias)."""
        return self.parts()

    def _analytic(self, x: Tensor, t: Tensor) -> AnalyticDerivatives:
        """Former name of :meth:`derivatives` (kept as an alias)."""
        return self.derivatives(x, t)

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


def time_tensor(t: Tensor | float | None, x: Tensor) -> Tensor:
    """``t`` (``None`` means 0) as a tensor of the batch shape ``x.shape[:-1]``, x's dtype."""
    batch = x.shape[:-1]
    if t is None:
        return x.new_zeros(batch)
    t = as_tensor("t", t, dtype=x.dtype, device=x.device)
    try:
        return torch.broadcast_to(t, batch)
    except RuntimeError:
        raise ValueError(
            f"t must broadcast to the batch shape {tuple(batch)}, got {tuple(t.shape)}"
        ) from None


def _grad(out: Tensor, inputs: tuple[Tensor, ...], create: bool) -> tuple[Tensor, ...]:
    """Gradient of ``out.sum()`` w.r.t. ``inputs``; zeros where ``out`` does not depend on one."""
    if not out.requires_grad:
        return tuple(torch.zeros_like(i) for i in inputs)
    return torch.autograd.grad(
        out.sum(),
        inputs,
        create_graph=create,
        retain_graph=True,
        allow_unused=True,
        materialize_grads=True,
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
        :class:`LieTerms`. When grad mode is on, the graph is kept (``create_graph=True``):
        every term differentiates w.r.t. ``x``, ``t`` and the parameters of ``fn`` and
        ``dynamics``. Under ``torch.no_grad()``/``torch.inference_mode()`` the terms are
        computed all the same and returned detached.
    """
    dynamics.check_inputs(x)
    if method not in ("autograd", "analytic"):
        raise ValueError(f"method must be 'autograd' or 'analytic', got {method!r}")
    diffusion = hessian and dynamics.has_diffusion
    if method == "analytic":
        # closed forms are plain tensor expressions: differentiable in grad mode, no graph
        # otherwise, so they need neither the autograd context nor a detach
        return _analytic_terms(fn, x, dynamics, t, diffusion, control)
    grad_mode = torch.is_grad_enabled()
    inference = torch.is_inference_mode_enabled()
    ctx = torch.inference_mode(False) if inference else contextlib.nullcontext()
    with ctx, torch.enable_grad():
        if inference:
            x = x.clone()
            t = t.clone() if isinstance(t, Tensor) else t
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
    inference = torch.is_inference_mode_enabled()
    diffusion = hessian and dynamics.has_diffusion
    ctx = torch.inference_mode(False) if inference else contextlib.nullcontext()
    with ctx, torch.enable_grad():
        if inference:
            x = x.clone()
            t = t.clone() if isinstance(t, Tensor) else t
        split = [flat_parts(fn) for fn in fns]
        sigma = dynamics.sigma(x) if diffusion else None
        parts = [p for ps in split for p in ps]
        h, dhdx, dhdt, hess, sizes = stacked_terms(parts, x, t, sigma, grad_mode or diffusion)
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
    if parts[0] is fn:
        h, dhdx, dhdt, hess, multi = _part_terms(fn, x, t, sigma, grad_mode or diffusion)
        if not multi:
            h, dhdx, dhdt = h.squeeze(-1), dhdx.squeeze(-2), dhdt.squeeze(-1)
            hess = None if hess is None else hess.squeeze(-1)
    else:
        h, dhdx, dhdt, hess, _ = stacked_terms(parts, x, t, sigma, grad_mode or diffusion)
        multi = True  # a split function is always [..., k]
    return _assemble(h, dhdx, dhdt, hess, x, dynamics, multi, control)


def stacked_terms(
    parts: list[LieFunction],
    x: Tensor,
    t: Tensor | float | None,
    sigma: Tensor | None,
    create: bool,
) -> tuple[Tensor, Tensor, Tensor, Tensor | None, list[int]]:
    """``h, dhdt, hess [..., K]``, ``dhdx [..., K, n]`` of independent functions ``parts``
    (their outputs concatenated), and each part's number of outputs.

    Each scalar part is evaluated on its own copy of the state (a ``[..., J, q, n]`` tensor
    of copies, one per part and per column of ``sigma``), so ONE backward pass gives every
    part's gradient and a second one every Hessian-vector product ``H_j s_l``, whatever the
    number of parts. A part with several outputs is differentiated on its own
    (:func:`_part_terms`). ``create`` keeps the graph of the gradients."""
    J, n = len(parts), x.shape[-1]
    Q = 1 if sigma is None else sigma.shape[-1]
    batch = x.shape[:-1]
    base = x if x.requires_grad else x.detach()
    xr = base[..., None, None, :].expand(*batch, J, Q, n).clone()
    if not xr.requires_grad:
        xr.requires_grad_()
    tt = time_tensor(t, x)
    timed = any(p.time_varying for p in parts)
    tr = tt[..., None, None].expand(*batch, J, Q).clone() if timed else None
    if tr is not None and not tr.requires_grad:
        tr.requires_grad_()
    outs: list[Tensor | None] = []
    total = x.new_zeros(())
    for j, part in enumerate(parts):
        hj = part(xr[..., j, :, :], tr[..., j, :] if tr is not None else tt[..., None])
        if hj.shape == (*batch, Q):
            outs.append(hj)
            total = total + hj.sum()
        else:  # several outputs (or a shape to be checked): its own passes
            outs.append(None)
    inputs = (xr,) if tr is None else (xr, tr)
    grads = _grad(total, inputs, create or sigma is not None)
    g_x = grads[0]  # [..., J, Q, n]: every copy holds its part's gradient
    hess_all = None
    if sigma is not None:
        s_cols = sigma.movedim(-1, -2).unsqueeze(-3)  # [..., 1, Q, n]
        (hv,) = _grad((g_x * s_cols).sum(), (xr,), create)
        hess_all = (hv * s_cols).sum((-2, -1))  # [..., J]
    cols_h, cols_g, cols_t, cols_s, sizes = [], [], [], [], []
    for j, part in enumerate(parts):
        hj = outs[j]
        if hj is None:
            h1, g1, t1, s1, multi = _part_terms(part, x, t, sigma, create)
            sizes.append(h1.shape[-1])
            cols_h.append(h1)
            cols_g.append(g1)
            cols_t.append(t1)
            cols_s.append(s1)
            continue
        sizes.append(1)
        cols_h.append(hj[..., :1])
        cols_g.append(g_x[..., j, :1, :])
        if tr is not None and part.time_varying:
            cols_t.append(grads[1][..., j, :1])
        else:
            cols_t.append(torch.zeros_like(hj[..., :1]))
        cols_s.append(None if hess_all is None else hess_all[..., j : j + 1])
    hess = None if sigma is None else torch.cat(cols_s, -1)  # type: ignore[arg-type]
    return torch.cat(cols_h, -1), torch.cat(cols_g, -2), torch.cat(cols_t, -1), hess, sizes


def flat_parts(fn: LieFunction) -> list[LieFunction]:
    """``fn`` split into independently differentiable parts (see :meth:`LieFunction.parts`)."""
    parts = fn.parts()
    if parts is None:
        return [fn]
    return [q for p in parts for q in flat_parts(p)]


def _part_terms(
    fn: LieFunction,
    x: Tensor,
    t: Tensor | float | None,
    sigma: Tensor | None,
    create: bool,
) -> tuple[Tensor, Tensor, Tensor, Tensor | None, bool]:
    """``h, dhdt, hess [..., k]``, ``dhdx [..., k, n]`` of one part (k = 1 if scalar), and
    whether the part returned ``[..., k]`` (rather than ``[...]``)."""
    # ``xr`` is the variable we differentiate w.r.t.: a clone when ``x`` is itself part of a
    # graph (nested Lie derivatives, learning), so that f, g and sigma evaluated at ``x``
    # are constants for these gradients yet keep their own path to ``x``.
    xr = x.clone() if x.requires_grad else x.detach().requires_grad_()
    tt = time_tensor(t, x)
    if fn.time_varying:
        tr = tt.clone() if tt.requires_grad else tt.detach().requires_grad_()
        inputs: tuple[Tensor, ...] = (xr, tr)
    else:
        tr = tt
        inputs = (xr,)
    h = fn(xr, tr)
    multi = _check_output(fn, h, x)
    outs = h.unbind(-1) if multi else (h,)
    grads = [_grad(hj, inputs, create) for hj in outs]
    dhdx = [gr[0] for gr in grads]
    dhdt = [
        gr[1] if fn.time_varying else torch.zeros_like(hj)
        for gr, hj in zip(grads, outs, strict=True)
    ]
    hess = None
    if sigma is not None:
        sigma_cols = sigma.unbind(-1)
        hess = []
        for dj in dhdx:
            acc = torch.zeros_like(dj[..., 0])
            for s in sigma_cols:
                # sigma is computed at ``x``, not ``xr``: a constant direction in this HVP.
                (hv,) = _grad((dj * s).sum(-1), (xr,), create)
                acc = acc + (hv * s).sum(-1)
            hess.append(acc)
    return (
        h if multi else h.unsqueeze(-1),
        torch.stack(dhdx, -2),
        torch.stack(dhdt, -1),
        None if hess is None else torch.stack(hess, -1),
        multi,
    )


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
    multi = _check_output(fn, d.h, x)
    hess = d.hess_quad(dynamics.sigma(x)) if diffusion else None
    return _assemble(d.h, d.dhdx, d.dhdt, hess, x, dynamics, multi, control)


def _check_output(fn: nn.Module, h: Tensor, x: Tensor) -> bool:
    """Whether ``h`` is ``[..., k]`` (True) or ``[...]`` (False); raise on anything else."""
    check_tensor(f"{type(fn).__name__} output", h)
    batch = x.shape[:-1]
    if h.shape == batch:
        return False
    if h.dim() == x.dim() and h.shape[:-1] == batch:
        return True
    raise ValueError(
        f"{type(fn).__name__} must return [...] or [..., k] for a state of shape "
        f"{tuple(x.shape)}, got {tuple(h.shape)}"
    )


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
    f = dynamics.f(x).unsqueeze(-1)
    lfh = (dhdx @ f).squeeze(-1) if multi else (dhdx.unsqueeze(-2) @ f)[..., 0, 0]
    if control:
        g = dynamics.g(x)
        lgh = dhdx @ g if multi else (dhdx.unsqueeze(-2) @ g).squeeze(-2)
    else:
        lead = (*h.shape, dynamics.control_dim)
        lgh = h.new_zeros(lead)
    return LieTerms(h, lfh, lgh, dhdt, hess, dhdx)
