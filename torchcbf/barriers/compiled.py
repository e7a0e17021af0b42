"""Lie terms of any barrier or Lyapunov functions, compiled with ``torch.compile``.

A user's own function (a superellipse, a smooth polygon, a small network) has no closed
forms, so the general path differentiates it by autograd at every call: on one state that is
a few hundred tensor operations and two backward passes, most of it fixed cost. Here the
whole computation, ``h``, ``dh/dx`` (``torch.func.jacrev``), ``dh/dt`` (of every function
that reads the time), the Hessian trace ``tr(sigma' d2h/dx2 sigma)`` where asked (``jacrev``
of ``jacrev``) and ``L_f h``, ``L_g h`` along the model, is one function of ``(x, t)`` that
``torch.compile`` turns into a few fused loops (through :class:`torchcbf._compile.Compiled`:
an eager run of the same function where the backend fails, with a warning).

It computes values only, without a graph: :class:`~torchcbf.filters.SafetyFilter` asks for
it when no output needs a gradient, and takes the autograd path otherwise. The terms equal
those of :func:`~torchcbf.barriers.lie.stacked_lie_derivatives` to rounding
(tests/barriers/test_compiled.py). The function is compiled for each batch size and dtype
it meets (``dynamic=False``); new values of the state, the time or the functions' constants
reuse the code.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import torch
from torch import Tensor

from torchcbf._compile import Compiled, hook_key, logger, read_key
from torchcbf.barriers.lie import LieFunction, LieTerms
from torchcbf.dynamics.base import ControlAffine


class CompiledLie:
    """Compiled Lie terms of ``fns`` along ``dynamics``, their outputs concatenated.

    Args:
        fns: barrier or Lyapunov functions, each ``[...]`` or ``[..., k_i]``; each must
            accept a state without batch dimensions (``x [n] -> [] or [k]``), as every
            function written with ``...`` indexing does.
        dynamics: the model (``f`` and ``g`` are compiled with the functions).
        hessian: also give ``hess_trace`` (when the model has a diffusion).
        options: keyword arguments of ``torch.compile`` (default ``dynamic=False``).

    It holds references to ``fns`` and ``dynamics`` (the owner's modules, moved and trained
    with it; an owner that replaces one calls :meth:`follow`). ``self(x [B, n], t [B]) ->
    (LieTerms, sizes)`` as :func:`~torchcbf.barriers.lie.stacked_lie_derivatives` returns
    them (``h, lfh, dhdt, hess_trace [B, K]``, ``lgh [B, K, m]``, ``dhdx [B, K, n]``),
    without a graph.
    """

    def __init__(
        self,
        fns: Sequence[LieFunction],
        dynamics: ControlAffine,
        *,
        hessian: bool,
        options: dict[str, Any] | None = None,
    ) -> None:
        self.fns = list(fns)
        self.dynamics = dynamics
        self.sizes: list[int] | None = None
        self.traced_sizes: list[int] = []
        self._hessian_asked = bool(hessian)
        self.hessian = self._hessian_asked and dynamics.has_diffusion
        self._call: Compiled | None = Compiled(self._terms, {"dynamic": False, **(options or {})})

    def follow(self, fns: Sequence[LieFunction], dynamics: ControlAffine) -> None:
        """Hold ``fns`` and ``dynamics`` from now on where they are not those held (an owner
        whose function or model was replaced: the next call traces them)."""
        same = dynamics is self.dynamics and len(fns) == len(self.fns)
        if same and all(a is b for a, b in zip(fns, self.fns, strict=True)):
            return
        self.fns, self.dynamics, self.sizes = list(fns), dynamics, None
        self.hessian = self._hessian_asked and dynamics.has_diffusion

    def evaluate(self, x: Tensor, t: Tensor) -> tuple[LieTerms, list[int]]:
        """The uncompiled function: ``(LieTerms, sizes)`` at ``x [B, n]``, ``t [B]``, for a
        caller that compiles more around it (``vmap`` and ``jacrev``: no graph to ``x``)."""
        sizes = [torch.atleast_1d(fn(x[0], t[0])).shape[-1] for fn in self.fns]
        h, lfh, lgh, dhdt, dhdx, *trace = self._terms(x, t, "")
        return LieTerms(h, lfh, lgh, dhdt, trace[0] if trace else None, dhdx), sizes

    def _values(self, x: Tensor, t: Tensor) -> Tensor:
        """``[K]`` outputs of all functions at one state ``x [n]``, time ``t []``."""
        return torch.cat([torch.atleast_1d(fn(x, t)) for fn in self.fns])

    def _terms(self, x: Tensor, t: Tensor, hooks: str) -> tuple[Tensor, ...]:
        """The terms at ``x [B, n]``, ``t [B]``; ``hooks``: the functions' and the model's
        :func:`~torchcbf._compile.hook_key` (compiled, a new value traces again)."""
        read_key(hooks)
        # each function's number of outputs as this trace sees them: a side effect the
        # compiled code repeats on every call, so a new trace (a count changed) updates it
        self.traced_sizes = [torch.atleast_1d(fn(x[0], t[0])).shape[-1] for fn in self.fns]
        values = torch.func.vmap(self._values)
        h = values(x, t)
        # dh/dt of every function: one that reads t without declaring time_varying too
        dhdx, dhdt = torch.func.vmap(torch.func.jacrev(self._values, argnums=(0, 1)))(x, t)
        f = self.dynamics.f(x)
        g = self.dynamics.g(x)
        lfh = (dhdx @ f.unsqueeze(-1)).squeeze(-1)
        lgh = dhdx @ g
        if not self.hessian:
            return h, lfh, lgh, dhdt, dhdx
        hess = torch.func.vmap(torch.func.jacrev(torch.func.jacrev(self._values)))(x, t)
        s = self.dynamics.sigma(x)  # [B, n, q]
        trace = (s.unsqueeze(1) * (hess @ s.unsqueeze(1))).sum((-2, -1))
        return h, lfh, lgh, dhdt, dhdx, trace

    def __call__(self, x: Tensor, t: Tensor) -> tuple[LieTerms, list[int]] | None:
        """Lie terms at ``x [B, n]``, ``t [B]`` (no graph) and each function's number of
        outputs; ``None`` (from then on, after one warning) where the functions cannot be
        transformed (a function that calls autograd itself, as the high-order and
        exponential CBFs do): the caller then takes the autograd path."""
        if self._call is None:
            return None
        with torch.no_grad():
            try:
                out = self._call(x, t, hook_key(*self.fns, self.dynamics))
            except Exception as err:  # noqa: BLE001 - any failure: the general path answers
                names = ", ".join(type(fn).__name__ for fn in self.fns)
                logger.warning(
                    "torchcbf: the Lie terms of %s cannot be compiled (%s: %s); they take the "
                    "autograd path",
                    names,
                    type(err).__name__,
                    str(err).splitlines()[0] if str(err) else "",
                )
                self._call = None
                return None
            if self._call.compiled is None:  # the backend failed and ran it eagerly
                self._call = None
                return None
            h, lfh, lgh, dhdt, dhdx = out[:5]
            self.sizes = list(self.traced_sizes)
        terms = LieTerms(h, lfh, lgh, dhdt, out[5] if self.hessian else None, dhdx)
        return terms, self.sizes
