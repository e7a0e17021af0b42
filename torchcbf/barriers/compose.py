"""Composition of barriers: stacks (``k`` barriers at once), rescaled and reshaped barriers,
intersections and unions."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Literal

import torch
from torch import Tensor, nn

from torchcbf._checks import as_tensor, check_finite, check_number, several_outputs
from torchcbf._constants import remember
from torchcbf.barriers._minmax import Mode, combine, reduce
from torchcbf.barriers._params import float_spec
from torchcbf.barriers.base import Barrier
from torchcbf.barriers.lie import (
    AnalyticDerivatives,
    FollowsTime,
    LieFunction,
    Quadric,
    gradient_rows,
    per_output,
)


def _as_columns(h: Tensor, x: Tensor) -> Tensor:
    """``[...] -> [..., 1]``; ``[..., k]`` unchanged."""
    return h.unsqueeze(-1) if h.shape == x.shape[:-1] else h


class BarrierStack(Barrier):
    """``k`` barriers as one multi-output barrier: ``h [..., k]`` (children's outputs
    concatenated in order; a child with ``k_i`` outputs contributes ``k_i`` columns).

    ``lie`` then returns every barrier's terms for a batch in one call:
    ``h, lfh, dhdt, hess_trace [..., k]``, ``lgh [..., k, m]``, ``dhdx [..., k, n]``.
    For many shapes of one kind, a batched shape (``Ball(center=[k, d], ...)``) is faster.
    """

    def __init__(self, *barriers: LieFunction) -> None:
        super().__init__()
        if not barriers:
            raise ValueError("BarrierStack needs at least one barrier")
        for i, b in enumerate(barriers):
            if not isinstance(b, LieFunction):
                raise TypeError(f"barriers[{i}] must be a Barrier, got {type(b).__name__}")
        self.barriers = nn.ModuleList(barriers)

    time_varying = FollowsTime(lambda self: any(b.time_varying for b in self.barriers))

    def forward(self, x: Tensor, t: Tensor | float | None = None) -> Tensor:
        """``x [..., n] -> h [..., k]``."""
        return torch.cat([_as_columns(b(x, t), x) for b in self.barriers], -1)

    def parts(self) -> list[LieFunction] | None:
        return list(self.barriers)

    @property
    def has_analytic(self) -> bool:
        return all(b.has_analytic for b in self.barriers)

    @property
    def has_second_order(self) -> bool:
        return all(b.has_second_order for b in self.barriers)

    def derivatives(self, x: Tensor, t: Tensor) -> AnalyticDerivatives:
        return _stack_analytic(self.barriers, x, t)


def _stack_analytic(barriers: nn.ModuleList, x: Tensor, t: Tensor) -> AnalyticDerivatives:
    parts = [b.derivatives(x, t) for b in barriers]
    batch = x.shape[:-1]
    single = [p.h.shape == batch for p in parts]
    h = torch.cat([_as_columns(p.h, x) for p in parts], -1)
    dhdx = torch.cat(
        [p.dhdx.unsqueeze(-2) if s else p.dhdx for p, s in zip(parts, single, strict=True)], -2
    )
    dhdt = torch.cat([_as_columns(p.dhdt, x) for p in parts], -1)

    def quad(s: Tensor) -> Tensor:
        return torch.cat([_as_columns(p.hess_quad(s), x) for p in parts], -1)

    if any(p.hess_mat is None or p.hess_dir is None for p in parts):
        return AnalyticDerivatives(h, dhdx, dhdt, quad)

    def hess_mat(m: Tensor) -> Tensor:
        mats = [p.hess_mat(m) for p in parts]  # type: ignore[misc]
        return torch.cat(
            [v.unsqueeze(-3) if s else v for v, s in zip(mats, single, strict=True)], -3
        )

    def hess_dir(v: Tensor, s: Tensor) -> Tensor:
        return torch.cat([_as_columns(p.hess_dir(v, s), x) for p in parts], -1)  # type: ignore[misc]

    return AnalyticDerivatives(h, dhdx, dhdt, quad, hess_mat, hess_dir)


class _OfOne(Barrier):
    """A barrier made from one inner ``barrier``: closed forms (first and second order)
    where the inner one has them, time-varying where it is."""

    def __init__(self, barrier: LieFunction) -> None:
        super().__init__()
        if not isinstance(barrier, LieFunction):
            raise TypeError(f"barrier must be a Barrier, got {type(barrier).__name__}")
        self.barrier = barrier

    time_varying = FollowsTime(lambda self: self.barrier.time_varying)

    @property
    def has_analytic(self) -> bool:
        return self.barrier.has_analytic

    @property
    def has_second_order(self) -> bool:
        return self.barrier.has_second_order


class Scaled(_OfOne):
    """``scale * h(x, t)`` for constant scales ``> 0`` (a number, or ``[k]`` for a barrier
    with ``k`` outputs): the same safe set, a rescaled CBF condition. Closed-form
    derivatives when ``barrier`` has them."""

    def __init__(self, barrier: LieFunction, scale: float | Sequence[float] | Tensor) -> None:
        super().__init__(barrier)
        if isinstance(scale, bool):
            raise TypeError("scale must be a number or a sequence/tensor of numbers")
        if isinstance(scale, Tensor):
            value = self.register_constant("scale", scale)  # a parameter trains
        else:  # Python numbers: in the inner barrier's dtype, exact under .double()
            device, dtype = float_spec(barrier)
            exact = check_finite("scale", as_tensor("scale", scale, dtype=torch.float64))
            value = remember(self, "scale", exact, dtype=dtype, device=device)
        if value.dim() > 1 or value.numel() == 0 or not bool((value.detach() > 0).all()):
            raise ValueError(f"scale must be positive numbers (scalar or [k]), got {scale!r}")

    def forward(self, x: Tensor, t: Tensor | float | None = None) -> Tensor:
        """``x [..., n] -> scale * h [...]`` (or ``[..., k]``)."""
        h = self.barrier(x, t)
        return self._scales(h, x) * h

    def _scales(self, h: Tensor, x: Tensor) -> Tensor:
        """The scales for the inner values ``h`` at ``x [..., n]``; ``[k]`` scales need
        ``k`` outputs (broadcast over a one-output barrier they would scale the batch)."""
        k = self.scale.numel()
        if self.scale.dim() == 1 and k > 1:
            inner = type(self.barrier).__name__
            if not several_outputs(inner, h, x) or h.shape[-1] != k:
                raise ValueError(
                    f"Scaled has {k} scales, one per output, but {inner} gives "
                    f"{tuple(h.shape)} for states {tuple(x.shape)}"
                )
        if (
            self.scale.dim() == 1
            and k == 1
            and not several_outputs(type(self.barrier).__name__, h, x)
        ):
            return self.scale.to(x).reshape(())  # one scale of one output: a number
        return self.scale.to(x)

    def quadric(self) -> Quadric | None:
        inner = self.barrier.quadric()
        k = self.scale.numel()
        if inner is None or (k > 1 and inner.center.shape[:-1] != (k,)):
            return None  # scales that fit no outputs: forward names them
        scale = self.scale if inner.scale is None else self.scale * inner.scale
        return inner._replace(scale=scale)

    def derivatives(self, x: Tensor, t: Tensor) -> AnalyticDerivatives:
        d = self.barrier.derivatives(x, t)
        c = self._scales(d.h, x)

        def quad(s: Tensor) -> Tensor:
            return c * d.hess_quad(s)

        first = (c * d.h, c.unsqueeze(-1) * d.dhdx, c * d.dhdt, quad)
        if d.hess_mat is None or d.hess_dir is None:
            return AnalyticDerivatives(*first)
        inner_mat, inner_dir = d.hess_mat, d.hess_dir

        def hess_mat(m: Tensor) -> Tensor:
            return c[..., None, None] * inner_mat(m)

        def hess_dir(v: Tensor, s: Tensor) -> Tensor:
            return c * inner_dir(v, s)

        return AnalyticDerivatives(*first, hess_mat, hess_dir)

    def extra_repr(self) -> str:
        return f"scale={self.scale.tolist()}"


TransformForm = Literal["radius", "exp"]


class Transformed(_OfOne):
    """``phi(h(x, t))`` for an increasing ``phi`` with ``phi(0) = 0``: the same safe set, a
    reshaped CBF condition. Closed-form derivatives when ``barrier`` has them.

    Forms:

    - ``"radius"``: ``phi(h) = sqrt(h + 1) - 1``. On a quadratic shape ``h = |q|^2 - 1``
      (an :class:`~torchcbf.barriers.Ellipse`) this is ``|q| - 1``, whose gradient stays
      bounded far from the shape (the risk-aware condition needs a bound on it). For
      barriers with ``h > -1`` (on an ellipse every point but the centre); below, the value
      is NaN, which a safety filter reports per row (``FALLBACK``).
    - ``"exp"``: ``phi(h) = 1 - exp(-rate h)``, bounded above by 1 (CBFkit's sublevel
      barrier ``B = exp(-rate h) <= 1``, read as ``1 - B >= 0``).

    Shapes follow ``barrier`` (``[...]`` or ``[..., k]``).
    """

    FORMS = ("radius", "exp")

    def __init__(self, barrier: LieFunction, form: TransformForm, *, rate: float = 1.0) -> None:
        super().__init__(barrier)
        if form not in self.FORMS:
            raise ValueError(f"form must be one of {self.FORMS}, got {form!r}")
        rate = check_number("rate", rate, low=0.0, strict=True)
        self.form = form
        self.rate = float(rate)

    def _phi(self, h: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """``phi(h)``, ``phi'(h)``, ``phi''(h)``."""
        if self.form == "radius":
            r = torch.sqrt(h + 1.0)
            return r - 1.0, 0.5 / r, -0.25 / (r * r * r)
        e = torch.exp(-self.rate * h)
        return -torch.expm1(-self.rate * h), self.rate * e, -self.rate * self.rate * e

    def _phi3(self, h: Tensor) -> Tensor:
        """The third derivative of ``phi`` at ``h``."""
        if self.form == "radius":
            return 0.375 * (h + 1.0) ** -2.5
        return self.rate**3 * torch.exp(-self.rate * h)

    def forward(self, x: Tensor, t: Tensor | float | None = None) -> Tensor:
        """``x [..., n] -> phi(h) [...]`` (or ``[..., k]``)."""
        return self._phi(self.barrier(x, t))[0]

    def derivatives(self, x: Tensor, t: Tensor) -> AnalyticDerivatives:
        d = self.barrier.derivatives(x, t)
        phi, d1, d2 = self._phi(d.h)
        single, grad = gradient_rows(d, x)  # grad [..., k, n]

        def quad(s: Tensor) -> Tensor:
            # tr(S' (phi'' grad grad' + phi' H) S) = phi'' |S' grad|^2 + phi' tr(S' H S)
            g2 = (grad @ s).square().sum(-1)  # [..., k]
            return d1 * d.hess_quad(s) + d2 * per_output(g2, single)

        first = (phi, d1.unsqueeze(-1) * d.dhdx, d1 * d.dhdt, quad)
        if d.hess_mat is None or d.hess_dir is None:
            return AnalyticDerivatives(*first)
        inner_mat, inner_dir = d.hess_mat, d.hess_dir
        d3 = self._phi3(d.h)

        def hess_mat(m: Tensor) -> Tensor:
            # (phi'' grad grad' + phi' H) M
            outer = grad.unsqueeze(-1) * (grad @ m).unsqueeze(-2)  # [..., k, n, q]
            outer = per_output(outer, single, -3)
            return d1[..., None, None] * inner_mat(m) + d2[..., None, None] * outer

        def hess_dir(v: Tensor, s: Tensor) -> Tensor:
            # d/dv of tr(S' (phi'' g g' + phi' H) S) with g = grad h and gv = g . v:
            # phi3 gv |S'g|^2 + phi2 (2 (S'Hv) . (S'g) + gv tr(S'HS)) + phi1 tr(S' dH[v] S)
            gv = per_output((grad * v.unsqueeze(-2)).sum(-1), single)
            sg = grad @ s  # [..., k, q]
            hv = inner_mat(v.unsqueeze(-1))  # [..., (k,) n, 1]
            hv = hv.unsqueeze(-3) if single else hv
            shv = (hv * s.unsqueeze(-3)).sum(-2)  # rows (S' H v)': [..., k, q]
            g2 = per_output(sg.square().sum(-1), single)
            cross = per_output((shv * sg).sum(-1), single)
            return d3 * gv * g2 + d2 * (2 * cross + gv * d.hess_quad(s)) + d1 * inner_dir(v, s)

        return AnalyticDerivatives(*first, hess_mat, hess_dir)

    def extra_repr(self) -> str:
        return f"form={self.form!r}" + (f", rate={self.rate}" if self.form == "exp" else "")


class _Reduction(Barrier):
    mode: Mode

    def __init__(
        self,
        *barriers: LieFunction,
        smooth: bool = False,
        temperature: float = 0.1,
        elementwise: bool = False,
    ) -> None:
        super().__init__()
        if not barriers:
            raise ValueError(f"{type(self).__name__} needs at least one barrier")
        temperature = check_number("temperature", temperature, low=0.0, strict=True)
        self.stack = BarrierStack(*barriers)
        self.smooth = bool(smooth)
        self.temperature = float(temperature)
        self.elementwise = bool(elementwise)

    time_varying = FollowsTime(lambda self: self.stack.time_varying)

    def _columns(self, values: list[Tensor], x: Tensor) -> tuple[Tensor, bool]:
        """The children's values ``[..., k_i]`` as one tensor ``[..., c]`` (``[..., k, c]``
        when elementwise), and whether every child is scalar (elementwise output ``[...]``)."""
        cols = [_as_columns(v, x) for v in values]
        if not self.elementwise:
            return torch.cat(cols, -1), False
        counts = [c.shape[-1] for c in cols]
        if len(set(counts)) != 1:
            raise ValueError(
                f"{type(self).__name__}(elementwise=True) needs barriers with one output count, "
                f"got {counts}"
            )
        return torch.stack(cols, -1), all(v.shape == x.shape[:-1] for v in values)

    def forward(self, x: Tensor, t: Tensor | float | None = None) -> Tensor:
        """``x [..., n] -> h [...]`` (elementwise: ``[..., k]``, or ``[...]`` for scalar
        barriers)."""
        if not self.elementwise:
            return reduce(self.stack(x, t), self.mode, self.smooth, self.temperature)
        values, scalar = self._columns([b(x, t) for b in self.stack.barriers], x)
        h = reduce(values, self.mode, self.smooth, self.temperature)
        return h.squeeze(-1) if scalar else h

    @property
    def has_analytic(self) -> bool:
        return self.stack.has_analytic

    def derivatives(self, x: Tensor, t: Tensor) -> AnalyticDerivatives:
        if not self.elementwise:
            d = self.stack.derivatives(x, t)
            return combine(
                d.h, d.dhdx, d.dhdt, d.hess_quad, self.mode, self.smooth, self.temperature
            )
        parts = [b.derivatives(x, t) for b in self.stack.barriers]
        h, scalar = self._columns([p.h for p in parts], x)  # [..., k, c]
        dhdx = torch.stack([gradient_rows(p, x)[1] for p in parts], -2)  # [..., k, c, n]
        dhdt = self._columns([p.dhdt for p in parts], x)[0]

        def columns_quad(s: Tensor) -> Tensor:  # s [..., 1, n, q] from the reduction
            return self._columns([p.hess_quad(s.squeeze(-3)) for p in parts], x)[0]

        d = combine(h, dhdx, dhdt, columns_quad, self.mode, self.smooth, self.temperature)
        reduced_quad = d.hess_quad

        def quad(s: Tensor) -> Tensor:
            out = reduced_quad(s.unsqueeze(-3))
            return out.squeeze(-1) if scalar else out

        if scalar:
            return AnalyticDerivatives(
                d.h.squeeze(-1), d.dhdx.squeeze(-2), d.dhdt.squeeze(-1), quad
            )
        return AnalyticDerivatives(d.h, d.dhdx, d.dhdt, quad)

    def extra_repr(self) -> str:
        return f"smooth={self.smooth}, temperature={self.temperature}" + (
            ", elementwise=True" if self.elementwise else ""
        )


class Intersection(_Reduction):
    """Safe where every barrier is: ``h = min_i h_i`` (hard, default) or the smooth
    under-approximation ``h = -T logsumexp(-h_i / T)`` (``smooth=True``, ``temperature=T``),
    which is ``<= min_i h_i`` so its safe set lies inside the intersection.
    Multi-output children contribute every output to one minimum; with
    ``elementwise=True`` children with ``k`` outputs each give ``k`` outputs, output ``j``
    the minimum of the children's outputs ``j`` (``k`` intersections at once)."""

    mode: Mode = "min"


class Union(_Reduction):
    """Safe where any barrier is: ``h = max_i h_i`` (hard) or ``T logsumexp(h_i / T)``
    (``smooth=True``; ``>= max_i h_i``, so the smooth safe set slightly over-approximates the
    union by at most ``T log(c)`` in ``h``). ``elementwise=True`` as for
    :class:`Intersection`."""

    mode: Mode = "max"
