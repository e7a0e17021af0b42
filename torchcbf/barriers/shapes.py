"""Geometric barriers: balls (fixed or moving), ellipses, half-spaces and boxes.

Every shape stores its constants as buffers, or as ``nn.Parameter`` when given one or built
with ``learnable=True``, so ``.to(device, dtype)`` works and learned shapes train through
the Lie derivatives. Shapes with a leading ``k`` axis on their constants (``center [k, d]``)
are ``k`` barriers evaluated at once: ``h [..., k]``.

``index`` names the state components the shape lives on (``x[..., index]``). It is checked
against the state when one is seen, or at construction when ``state_dim`` is given.
"""

from __future__ import annotations

import functools
from collections.abc import Callable, Sequence

import torch
from torch import Tensor

from torchcbf._checks import check_number
from torchcbf.barriers._minmax import combine, reduce
from torchcbf.barriers._params import StateIndex, embed
from torchcbf.barriers.base import Barrier
from torchcbf.barriers.lie import (
    AnalyticDerivatives,
    FollowsTime,
    FunctionPart,
    LieFunction,
    Quadric,
    time_tensor,
)


def _check_positive_tensor(name: str, value: Tensor) -> None:
    if not bool(torch.isfinite(value).all()) or bool((value <= 0).any()):
        raise ValueError(f"{name} must be finite and positive, got {value.detach().tolist()}")


def _check_centers(name: str, center: Tensor) -> int | None:
    """Number of shapes ``k`` for ``center [k, d]``, or ``None`` for ``center [d]``."""
    if center.dim() not in (1, 2) or center.shape[-1] == 0:
        raise ValueError(f"{name} must have shape [d] or [k, d], got {tuple(center.shape)}")
    return center.shape[0] if center.dim() == 2 else None


def _row(value: Tensor, j: int) -> Tensor:
    """Entry ``j`` of a per-shape constant (``[]`` shared by all shapes, or ``[k, ...]``)."""
    return value[j] if value.dim() > 0 else value


def _split(module: LieFunction, num: int | None) -> list[LieFunction] | None:
    """The ``k`` shapes of a batched shape as parts (one backward pass each); none to split
    for no shape (``k = 0``: the shape answers its empty terms as one part)."""
    if num is None or num == 0:
        return None
    return [
        FunctionPart(functools.partial(module._one, j), module.time_varying) for j in range(num)
    ]


def _check_per_shape(name: str, value: Tensor, k: int | None) -> None:
    """A per-shape scalar: ``[]`` or, for ``k`` shapes, ``[]``/``[k]``."""
    ok = value.dim() == 0 or (k is not None and value.shape == (k,))
    if not ok:
        want = "a scalar" if k is None else f"a scalar or [{k}]"
        raise ValueError(f"{name} must be {want}, got shape {tuple(value.shape)}")


def _rotate_t(cos: Tensor, sin: Tensor, u: Tensor, v: Tensor, dim: int = -1) -> Tensor:
    """Body coordinates ``R(angle)' (u, v)`` stacked along ``dim``."""
    return torch.stack([cos * u + sin * v, -sin * u + cos * v], dim)


def _embed(sel: StateIndex, grad_p: Tensor, n: int) -> Tensor:
    """A gradient w.r.t. the selected components ``[..., d]`` as one w.r.t. the state
    ``[..., n]`` (one padding op when the components are contiguous)."""
    span = sel._slice
    if span is None:
        return sel.scatter(grad_p, n)
    if span.start == 0 and span.stop == n:
        return grad_p
    return torch.nn.functional.pad(grad_p, (span.start, n - span.stop))


def _embed_rows(sel: StateIndex, rows_p: Tensor, n: int) -> Tensor:
    """A matrix over the selected components ``[..., d, q]`` as one over the state
    ``[..., n, q]`` (zero rows elsewhere)."""
    span = sel._slice
    if span is None:
        return embed(rows_p, sel.index, n, -2)
    if span.start == 0 and span.stop == n:
        return rows_p
    return torch.nn.functional.pad(rows_p, (0, 0, span.start, n - span.stop))


class _ShapeStack(Barrier):
    """A shape whose constants may carry a leading ``k`` axis (``self.num``): the ``k`` shapes
    are independent Lie parts, all with closed-form derivatives."""

    _sel: StateIndex
    #: the constants that may carry a leading ``k`` axis, each with its rank for one shape
    #: (the first one counts the shapes)
    _per_shape: tuple[tuple[str, int], ...]

    def _constant(self, name: str) -> Tensor | None:
        """The constant ``name`` as stored now (read from the module's dicts: this runs on
        every evaluation)."""
        value = self._parameters.get(name)
        return self._buffers.get(name) if value is None else value

    def _lead_count(self) -> int | None:
        """The count of the first constant alone (for ``repr``, which must not raise)."""
        lead = self._constant(self._per_shape[0][0])
        return lead.shape[0] if lead is not None and lead.dim() == 2 else None

    @property
    def num(self) -> int | None:
        """The number of shapes ``k`` (``None``: one shape, no ``k`` axis), counted by the
        first constant of ``_per_shape`` as stored now (one replaced by another count is
        followed). Every other one holds ``k`` entries, or is a scalar shared by all."""
        (first, _), *rest = self._per_shape
        lead = self._constant(first)
        k = _check_centers(first, lead)
        for name, rank in rest:
            value = self._constant(name)
            if value is None:
                continue
            dims = rank if k is None else rank + 1
            own = value.dim() == dims and (k is None or value.shape[0] == k)
            if not (own or (rank == 0 and value.dim() == 0)):  # a scalar may be shared
                raise ValueError(
                    f"{type(self).__name__}.{name} {tuple(value.shape)} does not match the "
                    f"{'one shape' if k is None else f'{k} shapes'} of {first} "
                    f"{tuple(lead.shape)}"
                )
        return k

    @property
    def index(self) -> tuple[int, ...]:
        """The state components the shape is drawn in (the position)."""
        return self._sel.index

    def parts(self) -> list[LieFunction] | None:
        """The ``k`` shapes, one part each (by ``_one``, which each shape writes with its
        ``forward``; a shape declares these parts for its own ``forward`` by naming them in
        its body, see :attr:`LieFunction.closed_forms`)."""
        return _split(self, self.num)

    @property
    def has_analytic(self) -> bool:
        return True


class _SignedShapeStack(_ShapeStack):
    """A :class:`_ShapeStack` with a ``keep_in`` flag flipping the sign of ``h``."""

    keep_in: bool

    def _sign(self) -> float:
        return -1.0 if self.keep_in else 1.0

    def extra_repr(self) -> str:
        return f"index={self._sel.index}, keep_in={self.keep_in}, k={self._lead_count()}"


class Ball(_SignedShapeStack):
    """A ball obstacle ``h = |p - c(t)|^2 - r^2`` (keep-out; ``keep_in=True`` flips the sign).

    Args:
        center: ``[d]``, or ``[k, d]`` for ``k`` balls at once (``h [..., k]``).
        radius: ``r > 0``, scalar (or ``[k]``).
        index: the ``d`` state components holding the position ``p`` (default ``(0, 1)``).
        keep_in: safe inside the ball: ``h = r^2 - |p - c|^2``.
        velocity: constant centre velocity, shaped like ``center``: ``c(t) = c + v t`` (the
            barrier becomes time-varying; ``lie`` reports ``dhdt``).
        learnable: store ``center``, ``radius`` (and ``velocity``) as ``nn.Parameter``.
        state_dim: check ``index`` (and the state size) at construction.
    """

    _per_shape = (("center", 1), ("radius", 0), ("velocity", 1))

    def __init__(
        self,
        center: Tensor | Sequence[float],
        radius: Tensor | float,
        index: Sequence[int] = (0, 1),
        *,
        keep_in: bool = False,
        velocity: Tensor | Sequence[float] | None = None,
        learnable: bool = False,
        state_dim: int | None = None,
    ) -> None:
        super().__init__()
        c = self.register_constant("center", center, learnable=learnable)
        k = _check_centers("center", c)
        r = self.register_constant("radius", radius, learnable=learnable)
        _check_per_shape("radius", r, k)
        _check_positive_tensor("radius", r.detach())
        if velocity is None:
            self.register_buffer("velocity", None)  # a velocity assigned later is a buffer
        else:
            v = self.register_constant("velocity", velocity, learnable=learnable)
            if v.shape != c.shape:
                raise ValueError(
                    f"velocity must have the shape of center {tuple(c.shape)}, got {tuple(v.shape)}"
                )
        self.keep_in = bool(keep_in)
        self._sel = StateIndex(index, c.shape[-1], state_dim)

    #: whether the centre moves (``velocity`` set, at construction or later)
    time_varying = FollowsTime(lambda self: self.velocity is not None)

    def _diff(self, x: Tensor, t: Tensor | float | None) -> Tensor:
        p = self._sel(x)
        c = self.center.to(x)
        many = self.num is not None
        if many:
            p = p.unsqueeze(-2)
        if self.velocity is not None:
            tt = time_tensor(t, x)[..., None]
            if many:
                tt = tt[..., None]
            c = c + self.velocity.to(x) * tt
        return p - c

    parts = _ShapeStack.parts

    def forward(self, x: Tensor, t: Tensor | float | None = None) -> Tensor:
        """``x [..., n] -> h [...]`` (or ``[..., k]``)."""
        diff = self._diff(x, t)
        return self._sign() * ((diff**2).sum(-1) - self.radius.to(x) ** 2)

    def _one(self, j: int, x: Tensor, t: Tensor | float | None) -> Tensor:
        """Ball ``j`` of a batched ball: ``[...]``."""
        c = self.center[j].to(x)
        if self.velocity is not None:
            c = c + self.velocity[j].to(x) * time_tensor(t, x)[..., None]
        r = _row(self.radius, j).to(x)
        return self._sign() * (((self._sel(x) - c) ** 2).sum(-1) - r**2)

    @property
    def has_second_order(self) -> bool:
        return True

    def quadric(self) -> Quadric | None:
        if self.velocity is not None:
            return None
        return Quadric(self._sel.index, self.center, radius=self.radius, sign=self._sign())

    def derivatives(self, x: Tensor, t: Tensor) -> AnalyticDerivatives:
        sign = self._sign()
        diff = self._diff(x, t)
        many = self.num is not None
        r = self.radius.to(x)
        h = (diff * diff).sum(-1) - r * r
        grad_p = diff * 2.0
        if sign < 0:
            h, grad_p = -h, -grad_p
        dhdx = _embed(self._sel, grad_p, x.shape[-1])
        if self.velocity is None:
            dhdt = torch.zeros_like(h)
        else:
            dhdt = -2 * sign * (diff * self.velocity.to(x)).sum(-1)

        def quad(s: Tensor) -> Tensor:
            val = 2 * sign * (self._sel.rows(s) ** 2).sum((-2, -1))
            return val.unsqueeze(-1).expand_as(h) if many else val

        def hess_mat(m: Tensor) -> Tensor:  # H = 2 I on the selected components
            out = _embed_rows(self._sel, 2 * sign * self._sel.rows(m), x.shape[-1])
            return out.unsqueeze(-3).expand(*h.shape, *out.shape[-2:]) if many else out

        def hess_dir(v: Tensor, s: Tensor) -> Tensor:
            return torch.zeros_like(h)

        return AnalyticDerivatives(h, dhdx, dhdt, quad, hess_mat, hess_dir)


class MovingBall(Barrier):
    """A ball whose centre follows a trajectory: ``h = |p - c(t)|^2 - r^2``.

    Args:
        trajectory: ``t [...] -> c [..., d]`` (a function or an ``nn.Module``, registered as a
            submodule so its parameters train and move with ``.to``).
        radius: ``r > 0``.
        index, keep_in, learnable, state_dim: as for :class:`Ball`.

    ``dhdt`` is obtained by autograd through ``trajectory``.
    """

    time_varying = True

    def __init__(
        self,
        trajectory: Callable[[Tensor], Tensor],
        radius: Tensor | float,
        index: Sequence[int] = (0, 1),
        *,
        keep_in: bool = False,
        learnable: bool = False,
        state_dim: int | None = None,
    ) -> None:
        super().__init__()
        if not callable(trajectory):
            raise TypeError(f"trajectory must be callable t -> center, got {type(trajectory)}")
        self.trajectory = trajectory
        r = self.register_constant("radius", radius, learnable=learnable)
        _check_per_shape("radius", r, None)
        _check_positive_tensor("radius", r.detach())
        self.keep_in = bool(keep_in)
        self._sel = StateIndex(index, len(tuple(index)), state_dim)

    def forward(self, x: Tensor, t: Tensor | float | None = None) -> Tensor:
        """``x [..., n], t [...] -> h [...]``."""
        p = self._sel(x)
        c = self.trajectory(time_tensor(t, x))
        if c.shape[-1] != p.shape[-1]:
            raise ValueError(
                f"trajectory must return centres [..., {p.shape[-1]}], got {tuple(c.shape)}"
            )
        h = ((p - c) ** 2).sum(-1) - self.radius.to(x) ** 2
        return -h if self.keep_in else h


class Ellipse(_SignedShapeStack):
    """An ellipse (ellipsoid) obstacle ``h = sum_i (q_i / a_i)^2 - 1`` with body coordinates
    ``q = R(angle)' (p - c)`` (keep-out; ``keep_in=True`` flips the sign).

    Without ``angle`` this is scenario B's ``((x-xo)/a1)^2 + ((y-yo)/a2)^2 - 1`` (any ``d``).

    Args:
        center: ``[d]`` or ``[k, d]`` for ``k`` ellipses at once (``h [..., k]``).
        axes: semi-axes ``a > 0``, shaped like ``center``.
        index: the ``d`` state components of the position (default ``(0, 1)``).
        angle: rotation of the body axes (radians, counter-clockwise), scalar or ``[k]``;
            ``d = 2`` only.
        keep_in, learnable, state_dim: as for :class:`Ball`.
    """

    _per_shape = (("center", 1), ("axes", 1), ("angle", 0))

    def __init__(
        self,
        center: Tensor | Sequence[float],
        axes: Tensor | Sequence[float],
        index: Sequence[int] = (0, 1),
        *,
        angle: Tensor | float | None = None,
        keep_in: bool = False,
        learnable: bool = False,
        state_dim: int | None = None,
    ) -> None:
        super().__init__()
        c = self.register_constant("center", center, learnable=learnable)
        _check_centers("center", c)
        a = self.register_constant("axes", axes, learnable=learnable)
        if a.shape != c.shape:
            raise ValueError(
                f"axes must have the shape of center {tuple(c.shape)}, got {tuple(a.shape)}"
            )
        _check_positive_tensor("axes", a.detach())
        if angle is None:
            self.register_buffer("angle", None)
        else:
            if c.shape[-1] != 2:
                raise ValueError(f"angle needs a 2-D ellipse, got center of shape {tuple(c.shape)}")
            ang = self.register_constant("angle", angle, learnable=learnable)
            _check_per_shape("angle", ang, _check_centers("center", c))
        self.keep_in = bool(keep_in)
        self._sel = StateIndex(index, c.shape[-1], state_dim)

    def _rot(self, x: Tensor) -> tuple[Tensor, Tensor]:
        ang = self.angle.to(x)
        if self.num is not None and ang.dim() == 1:
            ang = ang.unsqueeze(-1)  # [k, 1] against [..., k, q]
        return torch.cos(ang), torch.sin(ang)

    def _body(self, v: Tensor, x: Tensor, transpose: bool = True) -> Tensor:
        """``R' v`` (``transpose``) or ``R v`` for ``v [..., 2]`` (or ``[..., k, 2]``)."""
        if self.angle is None:
            return v
        cos, sin = self._rot(x)
        if self.num is not None:
            cos, sin = cos.squeeze(-1), sin.squeeze(-1)
        return _rotate_t(cos, sin if transpose else -sin, v[..., 0], v[..., 1])

    def _q(self, x: Tensor) -> Tensor:
        p = self._sel(x)
        if self.num is not None:
            p = p.unsqueeze(-2)
        return self._body(p - self.center.to(x), x)

    parts = _ShapeStack.parts

    def forward(self, x: Tensor, t: Tensor | float | None = None) -> Tensor:
        """``x [..., n] -> h [...]`` (or ``[..., k]``)."""
        q = self._q(x) / self.axes.to(x)
        return self._sign() * ((q**2).sum(-1) - 1)

    def _one(self, j: int, x: Tensor, t: Tensor | float | None) -> Tensor:
        """Ellipse ``j`` of a batched ellipse: ``[...]``."""
        d = self._sel(x) - self.center[j].to(x)
        if self.angle is not None:
            ang = _row(self.angle, j).to(x)
            cos, sin = torch.cos(ang), torch.sin(ang)
            d = _rotate_t(cos, sin, d[..., 0], d[..., 1])
        return self._sign() * (((d / self.axes[j].to(x)) ** 2).sum(-1) - 1)

    @property
    def has_second_order(self) -> bool:
        return True

    def quadric(self) -> Quadric | None:
        return Quadric(self._sel.index, self.center, self.axes, angle=self.angle, sign=self._sign())

    def derivatives(self, x: Tensor, t: Tensor) -> AnalyticDerivatives:
        sign = self._sign()
        a = self.axes.to(x)
        q = self._q(x)
        many = self.num is not None
        h = sign * (((q / a) ** 2).sum(-1) - 1)
        grad_p = self._body(2 * sign * q / a**2, x, transpose=False)
        dhdx = _embed(self._sel, grad_p, x.shape[-1])

        def body(s: Tensor, transpose: bool = True) -> Tensor:
            """``R' S_p`` (or ``R S`` with ``transpose=False``) ``[..., (1,) d, q]``."""
            sp = self._sel.rows(s) if transpose else s
            if many and transpose:
                sp = sp.unsqueeze(-3)  # [..., 1, d, q]
            if self.angle is None:
                return sp
            cos, sin = self._rot(x)
            return _rotate_t(cos, sin if transpose else -sin, sp[..., 0, :], sp[..., 1, :], -2)

        def quad(s: Tensor) -> Tensor:
            return 2 * sign * ((body(s) / a.unsqueeze(-1)) ** 2).sum((-2, -1))

        def hess_mat(m: Tensor) -> Tensor:  # H_p = 2 R diag(1 / a^2) R'
            hm = body(body(m) * (2 * sign / a.unsqueeze(-1) ** 2), transpose=False)
            out = _embed_rows(self._sel, hm, x.shape[-1])
            return out.expand(*h.shape, *out.shape[-2:]) if many else out

        def hess_dir(v: Tensor, s: Tensor) -> Tensor:
            return torch.zeros_like(h)

        return AnalyticDerivatives(h, dhdx, torch.zeros_like(h), quad, hess_mat, hess_dir)


class HalfSpace(_ShapeStack):
    """The half-space ``{a' p <= b}``: ``h = b - a' p`` (safe where ``a' p <= b``).

    Args:
        a: normal ``[d]`` (pointing out of the safe set), or ``[k, d]`` for ``k`` half-spaces
            (``h [..., k]``, a polytope ``A p <= b`` as a stack).
        b: offset, scalar (or ``[k]``).
        index: the ``d`` state components ``p``; ``None`` (default) means the whole state,
            which must then have size ``d``.
        learnable, state_dim: as for :class:`Ball`.
    """

    _per_shape = (("a", 1), ("b", 0))

    def __init__(
        self,
        a: Tensor | Sequence[float],
        b: Tensor | float,
        index: Sequence[int] | None = None,
        *,
        learnable: bool = False,
        state_dim: int | None = None,
    ) -> None:
        super().__init__()
        av = self.register_constant("a", a, learnable=learnable)
        k = _check_centers("a", av)
        bv = self.register_constant("b", b, learnable=learnable)
        _check_per_shape("b", bv, k)
        if bool((av.detach().abs().sum(-1) == 0).any()):
            raise ValueError("a must be a non-zero normal vector")
        d = av.shape[-1]
        if index is None and state_dim is None:
            state_dim = d
        self._sel = StateIndex(index, d, state_dim)

    parts = _ShapeStack.parts

    def forward(self, x: Tensor, t: Tensor | float | None = None) -> Tensor:
        """``x [..., n] -> h [...]`` (or ``[..., k]``)."""
        p = self._sel(x)
        a = self.a.to(x)
        if self.num is not None:
            return self.b.to(x) - p @ a.mT
        return self.b.to(x) - (p * a).sum(-1)

    def _one(self, j: int, x: Tensor, t: Tensor | float | None) -> Tensor:
        """Half-space ``j`` of a stack: ``[...]``."""
        return _row(self.b, j).to(x) - (self._sel(x) * self.a[j].to(x)).sum(-1)

    def derivatives(self, x: Tensor, t: Tensor) -> AnalyticDerivatives:
        h = self.forward(x)
        a = self.a.to(x)
        grad_p = (-a).expand(*h.shape, a.shape[-1])
        dhdx = _embed(self._sel, grad_p, x.shape[-1])

        def quad(s: Tensor) -> Tensor:
            return torch.zeros_like(h)

        return AnalyticDerivatives(h, dhdx, torch.zeros_like(h), quad)

    def extra_repr(self) -> str:
        return f"index={self._sel.index}, k={self._lead_count()}"


class Box(Barrier):
    """Keep-in box ``low <= p <= high``: ``h = min_i min(p_i - low_i, high_i - p_i)``.

    The hard minimum over the ``2 d`` faces (default) is exact but only piecewise smooth (its
    gradient is that of the closest face, its Hessian zero). ``smooth=True`` uses
    ``-T logsumexp(-faces / T)``, a smooth under-approximation (by at most ``T log(2d)``).

    Args:
        low, high: ``[d]`` corners with ``low < high``.
        index: the ``d`` state components; ``None`` means the whole state (size ``d``).
        smooth, temperature: smooth minimum and its temperature ``T > 0``.
        learnable, state_dim: as for :class:`Ball`.
    """

    def __init__(
        self,
        low: Tensor | Sequence[float],
        high: Tensor | Sequence[float],
        index: Sequence[int] | None = None,
        *,
        smooth: bool = False,
        temperature: float = 0.05,
        learnable: bool = False,
        state_dim: int | None = None,
    ) -> None:
        super().__init__()
        lo = self.register_constant("low", low, learnable=learnable, allow_inf=True)
        hi = self.register_constant("high", high, learnable=learnable, allow_inf=True)
        if lo.dim() != 1 or hi.shape != lo.shape:
            raise ValueError(
                "low and high must both have shape [d], got "
                f"{tuple(lo.shape)} and {tuple(hi.shape)}"
            )
        if bool((lo.detach() >= hi.detach()).any()):
            raise ValueError(
                f"low {lo.detach().tolist()} must be below high {hi.detach().tolist()} everywhere"
            )
        self.smooth = bool(smooth)
        self.temperature = check_number("temperature", temperature, low=0.0, strict=True)
        d = lo.shape[0]
        if index is None and state_dim is None:
            state_dim = d
        self._sel = StateIndex(index, d, state_dim)

    def _faces(self, x: Tensor) -> Tensor:
        p = self._sel(x)
        return torch.cat([p - self.low.to(x), self.high.to(x) - p], -1)

    def forward(self, x: Tensor, t: Tensor | float | None = None) -> Tensor:
        """``x [..., n] -> h [...]``."""
        return reduce(self._faces(x), "min", self.smooth, self.temperature)

    @property
    def has_analytic(self) -> bool:
        return True

    def derivatives(self, x: Tensor, t: Tensor) -> AnalyticDerivatives:
        faces = self._faces(x)
        d = faces.shape[-1] // 2
        eye = torch.eye(d, dtype=x.dtype, device=x.device)
        grad_p = torch.cat([eye, -eye], 0).expand(*faces.shape, d)  # [..., 2d, d]
        dhdx = _embed(self._sel, grad_p, x.shape[-1])
        zeros = torch.zeros_like(faces)

        def quad(s: Tensor) -> Tensor:
            return zeros

        return combine(faces, dhdx, zeros, quad, "min", self.smooth, self.temperature)

    def extra_repr(self) -> str:
        return f"index={self._sel.index}, smooth={self.smooth}"
