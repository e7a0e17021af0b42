"""``solve_qp``: the batched, differentiable QP layer (public entry point)."""

from __future__ import annotations

import functools
import math
from typing import NamedTuple

import torch
from torch import Tensor

from torchcbf._autograd import refuse_transforms
from torchcbf._checks import broadcast_shapes, isfinite, resolved, rows_finite
from torchcbf.qp import _direct, _dual_native, realtime
from torchcbf.qp._dual import dual_engine
from torchcbf.qp._enum import (
    MAX_CANDIDATES,
    MAX_CANDIDATES_SMALL_BATCH,
    SMALL_BATCH,
    num_candidates,
)
from torchcbf.qp._function import (
    ANSWERED_BY,
    QPFunction,
    SolverConfig,
    dual_applies,
    method_code,
)
from torchcbf.qp._ipm import default_tolerances, not_positive_definite
from torchcbf.qp.status import Status


class QPSolution(NamedTuple):
    """Result of :func:`solve_qp`; every field has the batch shape ``[...]`` of the inputs.

    - ``x [..., n]``: the minimiser (zeros on rows whose status is infeasible or non-finite).
    - ``status [...]`` int64: a :class:`Status` code per row (0 = ``SOLVED``).
    - ``lam [..., m]``: multipliers of ``Gx <= h`` (>= 0).
    - ``nu [..., k]``: multipliers of ``Ax = b`` (stationarity ``Qx + p + G'lam + A'nu + ... = 0``).
    - ``iterations [...]`` int64: interior point iterations (0 for the closed form).
    - ``lam_lb, lam_ub [..., n]``: multipliers of ``x >= lb`` and ``x <= ub`` (>= 0; zero where
      the bound is infinite or absent), so that ``Qx + p + G'lam + A'nu - lam_lb + lam_ub = 0``.
    - ``slack [..., m]``: elastic violation ``t >= 0`` of each softened row (``Gx <= h + t``),
      the least ``x`` needs, ``max(0, G x - h)`` (the optimum's: the penalty grows with
      ``t``); zero for hard rows, when ``soft`` is not given, and on rows not ``SOLVED``
      (their ``x`` answers no problem).
    - ``path``: the route the batch took (see :data:`PATHS`): ``"small_native"`` (a few
      small problems in one call of the dual C kernel, :mod:`torchcbf.qp.realtime`),
      ``"small_proxsuite"`` (a few problems straight to proxsuite's dense solver),
      ``"active_set_native"`` (the dual active set method in C, equality rows eliminated
      first where there are any), ``"active_set_triton"`` (the dual method in one Triton
      launch on CUDA), ``"active_set"``, ``"enumerate"``, ``"closed_form"``,
      ``"ipm"`` (in torch), ``"auto_proxsuite"`` (proxsuite's dense solver, then the interior
      point method), ``"proxsuite"``, ``"qpsolvers:<solver>"``, or ``"empty"`` (no rows).
    - ``method [...]`` int64: the algorithm that answered each row, an index into
      :data:`METHODS_ANSWERED` (``"closed_form"``, ``"active_set"``, ``"enumerate"``,
      ``"ipm"``, ``"proxsuite"``, ``"qpsolvers"``, or ``"none"`` where the status was decided
      from the data before any method ran: ``NON_FINITE``, or ``PRIMAL_INFEASIBLE`` for a
      bound that holds nothing, ``lb = +inf``, ``ub = -inf`` or ``h = -inf``): rows an exact
      method cannot certify are solved again by another (enumeration where the problem is
      small, else the interior point method), and this says which one's answer and status
      the row holds.
    """

    x: Tensor
    status: Tensor
    lam: Tensor
    nu: Tensor
    iterations: Tensor
    lam_lb: Tensor
    lam_ub: Tensor
    slack: Tensor
    path: str = "ipm"
    method: Tensor | None = None

    def method_names(self) -> list[str]:
        """:attr:`method` as names, row-major over the batch shape."""
        if self.method is None:
            return []
        return [METHODS_ANSWERED[i] for i in self.method.reshape(-1).tolist()]


#: the names of :attr:`QPSolution.method`'s codes
METHODS_ANSWERED = ANSWERED_BY
#: the values of :attr:`QPSolution.path` (besides ``"qpsolvers:<solver>"``)
PATHS = ("small_native", "small_proxsuite", "active_set_native", "active_set_triton",
         "active_set", "enumerate", "closed_form", "ipm", "auto_proxsuite", "proxsuite",
         "empty")  # fmt: skip
_FLOAT = (torch.float32, torch.float64)
METHODS = ("auto", "active_set", "enumerate", "ipm")
#: most candidate active sets ``method="enumerate"`` accepts when asked for explicitly (its
#: table and work grow with this count; beyond it the call raises ``ValueError``)
MAX_CANDIDATES_EXPLICIT = 200_000


def _tensor(name: str, value: object, dtype: torch.dtype, device: torch.device) -> Tensor:
    if not isinstance(value, Tensor):
        raise TypeError(f"{name} must be a torch.Tensor, got {type(value).__name__}")
    if value.dtype not in _FLOAT:
        raise TypeError(f"{name} must be float32 or float64, got {value.dtype}")
    if value.dtype != dtype:
        raise TypeError(f"{name} has dtype {value.dtype} but Q has dtype {dtype}")
    if value.device != device:
        raise ValueError(f"{name} is on {value.device} but Q is on {device}")
    return resolved(value)


def _bound(name: str, value: object, n: int, dtype: torch.dtype, device: torch.device) -> Tensor:
    if isinstance(value, (int, float)) and not isinstance(value, bool):
        return torch.full((n,), float(value), dtype=dtype, device=device)
    value = _tensor(name, value, dtype, device)
    if value.dim() == 0:
        return value.expand(n)
    if value.shape[-1] != n:
        raise ValueError(f"{name} must have shape [..., {n}], got {tuple(value.shape)}")
    return value


def _check_trailing(name: str, t: Tensor, trailing: tuple[int, ...], spec: str) -> None:
    k = len(trailing)
    if t.dim() < k or tuple(t.shape[t.dim() - k :]) != trailing:
        raise ValueError(f"{name} must have shape [..., {spec}], got {tuple(t.shape)}")


def _row_block(
    mat_name: str,
    vec_name: str,
    rows_name: str,
    mat: object,
    vec: object,
    n: int,
    dtype: torch.dtype,
    device: torch.device,
) -> tuple[Tensor | None, Tensor | None, int]:
    """Check a block of rows ``mat [..., rows, n]`` with its right-hand side
    ``vec [..., rows]`` (both or neither); returns ``(mat, vec, rows)``."""
    if (mat is None) != (vec is None):
        raise ValueError(f"{mat_name} and {vec_name} must be given together")
    if mat is None:
        return None, None, 0
    mat = _tensor(mat_name, mat, dtype, device)
    if mat.dim() < 2 or mat.shape[-1] != n:
        raise ValueError(
            f"{mat_name} must have shape [..., {rows_name}, {n}], got {tuple(mat.shape)}"
        )
    rows = mat.shape[-2]
    vec = _tensor(vec_name, vec, dtype, device)
    _check_trailing(vec_name, vec, (rows,), str(rows))
    return mat, vec, rows


def check_options(max_iter: object, eps: object, *, where: str = "{}") -> None:
    """Raise ``ValueError`` unless ``max_iter`` is a positive integer and ``eps`` is ``None``
    or a number in (0, 1); ``where`` formats the option's name in the message (e.g.
    ``"qp_options['{}']"`` for options passed on to :func:`solve_qp`)."""
    if not isinstance(max_iter, int) or isinstance(max_iter, bool) or max_iter < 1:
        name = where.format("max_iter")
        raise ValueError(f"{name} must be a positive integer, got {max_iter!r}")
    if eps is not None and (
        isinstance(eps, bool) or not isinstance(eps, (int, float)) or not 0 < eps < 1
    ):
        raise ValueError(f"{where.format('eps')} must be a number in (0, 1), got {eps!r}")


def solve_qp(
    Q: Tensor,
    p: Tensor,
    G: Tensor | None = None,
    h: Tensor | None = None,
    A: Tensor | None = None,
    b: Tensor | None = None,
    lb: Tensor | float | None = None,
    ub: Tensor | float | None = None,
    *,
    backend: str = "torch",
    eps: float | None = None,
    max_iter: int = 50,
    warm_start: Tensor | QPSolution | None = None,
    soft: Tensor | None = None,
    check_every: int = 5,
    polish: bool | None = None,
    method: str = "auto",
) -> QPSolution:
    """Solve ``min 1/2 x'Qx + p'x  s.t.  Gx <= h, Ax = b, lb <= x <= ub`` for a batch.

    Shapes: ``Q [..., n, n]``, ``p [..., n]``, ``G [..., m, n]``, ``h [..., m]``,
    ``A [..., k, n]``, ``b [..., k]``, ``lb, ub [..., n]`` (or a number; entries may be
    ``-inf``/``+inf``), ``soft [..., m]``. Leading batch dimensions broadcast (an input without
    them is shared by every row); with none at all the outputs have no batch dimension.
    ``Q`` is symmetrised as ``(Q + Q')/2``. float32 and float64, any device.

    Backends:

    - ``"torch"`` (default): batched solvers written in torch that stay on the device. The
      interior point method (:mod:`torchcbf.qp._ipm`) is homogeneous, with
      Farkas/unboundedness certificates for infeasible rows, followed by an active-set
      polishing step (:mod:`torchcbf.qp._kkt`); a polished row that is not verified, or
      that violates a row or has a negative multiplier beyond rounding (nearly parallel
      active rows), is re-solved by an exact method below. Convergence is tested on the
      device every iteration; the host checks whether every row is done every
      ``check_every`` iterations. With one inequality and nothing else (no ``A``, bounds
      or ``soft``) and ``Q`` positive definite, the exact projection formula is used
      (except on the CPU with the C kernel below, whose dual method is then faster).

      ``method`` (torch backend only) picks the algorithm; every exact path verifies its
      answer as a KKT point and hands the rows it cannot certify (infeasible, ``Q`` not
      positive definite, degenerate beyond repair) to the interior point method, whose
      certificates then set the status; testing for such rows is one host synchronisation.

      - ``"active_set"``: a batched **dual active-set method** (Goldfarb-Idnani,
        :mod:`torchcbf.qp._dual`) for problems without equality rows (``A`` raises
        ``ValueError``); box bounds count as rows. Exact (the multipliers are re-solved on
        the final active set and every row's residual is judged on that row's own scale),
        typically 2-5 steps per row; ``iterations`` counts its steps. On a CPU the "all
        rows done" test runs every step (it costs no device synchronisation) and finished
        rows are dropped from the iteration; elsewhere every ``check_every`` steps.
      - ``"enumerate"``: **active-set enumeration** (:mod:`torchcbf.qp._enum`): every
        candidate active set of at most ``N - k`` rows (``N`` variables after softening,
        ``k`` equalities) is solved at once and the verified KKT point is kept. Exact, a
        fixed cost and no iterations (``iterations = 0``); the cost grows with the number
        of candidate sets.
      - ``"ipm"``: the interior point method for every row.
      - ``"auto"`` (default): the dual active-set method where it applies (no equality
        rows, at most 64 variables after softening) when the data are on the CPU and its C
        kernel is built (see below); equality rows are first eliminated by a null-space
        basis (:mod:`torchcbf.qp._eliminate`) where at most 64 variables are left and the
        rows of ``A`` are independent (other rows keep their equalities and the path
        below). Otherwise enumeration for batches of
        at most ``SMALL_BATCH`` rows with at most ``MAX_CANDIDATES_SMALL_BATCH`` candidate
        sets, then the dual method in torch (at most ``MAX_ACTIVE_SET_VARS`` = 8
        variables), else enumeration up to
        ``MAX_CANDIDATES`` candidate sets, else the interior point method.

      On the CPU the dual method runs a C kernel (:mod:`torchcbf.qp._dual_native`, the
      same algorithm problem by problem, built at install when a C compiler is present;
      a large batch is split over ``torch.get_num_threads()`` threads). On CUDA, where
      Triton imports, it runs in one Triton launch, one problem per lane
      (:mod:`torchcbf.qp._dual_triton`: at most 4 variables and 64 entries in the ``[N,
      M]`` tile padded to powers of two). Otherwise it runs in torch. A few small QPs (at
      most ``realtime.MAX_BATCH`` rows) that need no gradient go straight from numpy
      arrays into the kernel
      (:mod:`torchcbf.qp.realtime`); a batch the kernel does not certify completely takes
      the general path. ``method="enumerate"`` asked for explicitly refuses problems with
      more than ``MAX_CANDIDATES_EXPLICIT`` candidate sets (``ValueError`` naming the sizes).
      See docs/qp.md for the statuses and fallbacks.
    - ``"proxsuite"``: proxsuite's dense solver, rows solved in parallel by its
      ``solve_in_parallel`` (CPU); its statuses are mapped to :class:`Status` and a row it
      calls solved whose answer violates the constraints is reported ``MAX_ITER``.
    - ``"qpsolvers:<solver>"`` (e.g. ``"qpsolvers:clarabel"``): one ``qpsolvers`` call per
      row, **forward only**: it raises ``ValueError`` if gradients are required (call it under
      ``torch.no_grad()`` or detach the inputs).

    Differentiation (torch and proxsuite backends): implicit differentiation of the KKT
    conditions on the active set ``{i : lam_i > slack_i}``, exact where the active set is
    nondegenerate; rows not ``SOLVED`` get zero gradients. Every tensor input (including
    ``lb``, ``ub`` and ``soft``) receives gradients.

    Elastic mode: ``soft[..., i] > 0`` (finite) turns row ``i`` of ``G`` into
    ``G_i x <= h_i + t_i`` with ``t_i >= 0`` and penalty ``soft_i * (t_i + t_i**2 / 2)`` added
    to the objective; ``soft_i <= 0`` or ``inf`` keeps it hard. The linear part makes the
    penalty exact (``t = 0`` whenever the hard problem is feasible and ``soft_i`` exceeds the
    row's multiplier); the quadratic part keeps the solution unique. ``QPSolution.slack``
    reports ``t``.

    Rows without a bound: ``h_i = +inf`` (as OSQP and proxsuite write it), ``lb = -inf`` and
    ``ub = +inf`` bound nothing; such a row is ignored by every method (its multiplier is
    zero and its ``G`` row and ``h`` get zero gradients). Statuses: see :class:`Status`. A row
    with NaN in its data, or inf anywhere but in ``h`` and the bounds, is ``NON_FINITE`` with
    ``x = 0``; ``h_i = -inf``, ``lb = +inf`` or ``ub = -inf`` is ``PRIMAL_INFEASIBLE``.
    ``eps`` (default ``1e-7`` in float64, ``2e-6`` in float32) is the relative tolerance on
    residuals and duality gap; ``warm_start`` (``x [..., n]`` or a previous solution) seeds
    the primal iterate. ``polish`` (default: on for the torch backend) toggles the active-set
    polishing.

    Raises ``TypeError``/``ValueError`` naming the argument on bad types or shapes.
    """
    if polish is not None and not isinstance(polish, bool):
        raise TypeError(f"polish must be True, False or None, got {polish!r}")
    inp = _validate(Q, p, G, h, A, b, lb, ub, soft, warm_start, backend, method, max_iter,
                    check_every, eps)  # fmt: skip
    if inp.B == 0:
        return _empty_solution(inp)
    tensors = [t for t in inp.given() if t is not None]
    need_grad = torch.is_grad_enabled() and any(t.requires_grad for t in tensors)
    if backend.startswith("qpsolvers:") and need_grad:
        pairs = zip(_NAMES, inp.given(), strict=True)
        needs = [nm for nm, t in pairs if t is not None and t.requires_grad]
        raise ValueError(
            f"backend {backend!r} is forward-only but {', '.join(needs)} require grad; "
            "use backend='torch' or 'proxsuite', or call under torch.no_grad()"
        )
    if not need_grad and backend == "torch" and method in ("auto", "active_set"):
        small = _solve_small(inp, max_iter)
        if small is not None:
            return small
    if not need_grad and backend == "torch" and method == "auto" and _direct_applies(inp):
        direct = _direct.solve_direct(
            inp.Q, inp.p, inp.G, inp.h, inp.A, inp.b, inp.lb, inp.ub, inp.eps, inp.eps_inf,
            inp.batch_shape,
        )  # fmt: skip
        if direct is not None:
            return QPSolution(*direct, "small_proxsuite", _answered(inp, "proxsuite"))
    flat = _flatten(inp)
    std = _standard_form(flat, inp)
    cfg = _config(inp, std, backend, method, polish, max_iter, check_every, need_grad)
    xs, z, y, status, iters, answered = QPFunction.apply(
        std.P, std.q, std.G, std.h, std.A, flat.b, cfg, std.x0
    )
    sol = _unpack(inp, flat, std, xs, z, y, status, iters)
    path = _path(cfg, std.q, std.G.shape[-2])
    if flat.masked:
        decided = flat.bad | flat.infeasible_bound
        answered = torch.where(decided, method_code("none"), answered)
    return sol._replace(path=path, method=answered.reshape(inp.batch_shape))


def _path(cfg: SolverConfig, q: Tensor, M: int) -> str:
    """:attr:`QPSolution.path` of a batch solved with ``cfg`` (linear terms ``q [B, N]``,
    ``M`` inequality rows; the solve runs in float64)."""
    if cfg.method == "outside":
        return cfg.backend
    if cfg.method == "eliminate":  # the reduced problem goes to the C kernel
        return "active_set_native"
    if cfg.method == "active_set":
        engine = dual_engine(q.double(), M)
        return {"c": "active_set_native", "triton": "active_set_triton"}.get(engine, "active_set")
    return cfg.method


_NAMES = ("Q", "p", "G", "h", "A", "b", "lb", "ub", "soft", "warm_start")


class _Inputs(NamedTuple):
    """Checked inputs of :func:`solve_qp` with their sizes and the broadcast batch shape."""

    Q: Tensor
    p: Tensor
    G: Tensor | None
    h: Tensor | None
    A: Tensor | None
    b: Tensor | None
    lb: Tensor | None
    ub: Tensor | None
    soft: Tensor | None
    x0: Tensor | None
    n: int
    m: int
    me: int
    eps: float
    eps_inf: float
    batch_shape: tuple[int, ...]
    B: int

    def given(self) -> tuple[Tensor | None, ...]:
        return (
            self.Q,
            self.p,
            self.G,
            self.h,
            self.A,
            self.b,
            self.lb,
            self.ub,
            self.soft,
            self.x0,
        )


def _validate(
    Q: object,
    p: object,
    G: object,
    h: object,
    A: object,
    b: object,
    lb: object,
    ub: object,
    soft: object,
    warm_start: object,
    backend: object,
    method: object,
    max_iter: object,
    check_every: object,
    eps: object,
) -> _Inputs:
    """Check types, shapes, dtypes, devices and options; broadcast the batch shapes."""
    if not isinstance(Q, Tensor):
        raise TypeError(f"Q must be a torch.Tensor, got {type(Q).__name__}")
    if Q.dtype not in _FLOAT:
        raise TypeError(f"Q must be float32 or float64, got {Q.dtype}")
    if Q.dim() < 2 or Q.shape[-1] != Q.shape[-2] or Q.shape[-1] == 0:
        raise ValueError(f"Q must have shape [..., n, n] with n >= 1, got {tuple(Q.shape)}")
    dtype, device = Q.dtype, Q.device
    n = Q.shape[-1]
    Q = resolved(Q)
    p = _tensor("p", p, dtype, device)
    _check_trailing("p", p, (n,), str(n))
    G, h, m = _row_block("G", "h", "m", G, h, n, dtype, device)
    A, b, me = _row_block("A", "b", "k", A, b, n, dtype, device)
    lb = None if lb is None else _bound("lb", lb, n, dtype, device)
    ub = None if ub is None else _bound("ub", ub, n, dtype, device)
    if soft is not None:
        if G is None:
            raise ValueError("soft requires inequality constraints G, h")
        soft = _tensor("soft", soft, dtype, device)
        _check_trailing("soft", soft, (m,), str(m))
    if not isinstance(backend, str) or not (
        backend in ("torch", "proxsuite") or backend.startswith("qpsolvers:")
    ):
        raise ValueError(
            f"backend must be 'torch', 'proxsuite' or 'qpsolvers:<solver>', got {backend!r}"
        )
    if method not in METHODS:
        raise ValueError(f"method must be one of {METHODS}, got {method!r}")
    if method == "active_set" and A is not None and A.shape[-2] > 0:
        raise ValueError("method='active_set' does not take equality constraints A, b")
    check_options(max_iter, eps)
    if not isinstance(check_every, int) or check_every < 1:
        raise ValueError(f"check_every must be a positive integer, got {check_every!r}")
    eps_default, eps_inf = default_tolerances(dtype)
    if eps is None:
        eps = eps_default
    x0 = warm_start.x if isinstance(warm_start, QPSolution) else warm_start
    if x0 is not None:
        x0 = _tensor("warm_start", x0, dtype, device)
        _check_trailing("warm_start", x0, (n,), str(n))
    trailing = (2, 1, 2, 1, 2, 1, 1, 1, 1, 1)
    values = (Q, p, G, h, A, b, lb, ub, soft, x0)
    refuse_transforms("solve_qp", values)
    shapes = [
        (name, tuple(t.shape[: t.dim() - k]))
        for name, t, k in zip(_NAMES, values, trailing, strict=True)
        if t is not None
    ]
    try:
        batch_shape = tuple(broadcast_shapes(*[s for _, s in shapes]))
    except RuntimeError:
        desc = ", ".join(f"{nm} {s}" for nm, s in shapes)
        raise ValueError(f"batch dimensions do not broadcast: {desc}") from None
    B = math.prod(batch_shape)
    return _Inputs(Q, p, G, h, A, b, lb, ub, soft, x0, n, m, me, float(eps), eps_inf,
                   batch_shape, B)  # fmt: skip


def _empty_solution(inp: _Inputs) -> QPSolution:
    """Empty answers of the right shapes, still connected to the inputs (``backward()`` works)."""
    Q, n, m, me = inp.Q, inp.n, inp.m, inp.me

    def empty(*trailing: int, dt: torch.dtype = Q.dtype) -> Tensor:
        return torch.zeros(*inp.batch_shape, *trailing, dtype=dt, device=Q.device)

    none = empty(dt=torch.int64)
    given = [t for t in inp.given()[:9] if t is not None]
    link = sum((t.sum() for t in given if t.requires_grad), Q.new_zeros(())) * 0.0
    x, lam, nu, slack = (link + empty(k) for k in (n, m, me, m))
    return QPSolution(x, none, lam, nu, none, link + empty(n), link + empty(n), slack, "empty",
                      none)  # fmt: skip


def _answered(inp: _Inputs, name: str) -> Tensor:
    """:attr:`QPSolution.method` of a batch that one method answered entirely."""
    return torch.full(inp.batch_shape, method_code(name), dtype=torch.int64, device=inp.Q.device)


def _rows(t: Tensor | None, inp: _Inputs, trailing: tuple[int, ...]) -> Tensor | None:
    """``t`` holding ``B`` rows of shape ``trailing`` (itself where its batch is already the
    broadcast one, else broadcast); only its memory is read, so no reshape."""
    if t is None or t.shape[: t.dim() - len(trailing)] == inp.batch_shape:
        return t
    return t.expand(*inp.batch_shape, *trailing)


def _solve_small(inp: _Inputs, max_iter: int) -> QPSolution | None:
    """The real-time path (:mod:`torchcbf.qp.realtime`) for a few small QPs without gradients on
    the CPU; ``None`` where it does not apply or the kernel does not certify every row."""
    n, m = inp.n, inp.m
    if (
        inp.B > realtime.MAX_BATCH
        or n > _dual_native.MAX_VARS
        or inp.me >= n
        or inp.soft is not None
        or inp.Q.device.type != "cpu"
        or not _dual_native.available()
    ):
        return None
    if inp.me > 0:
        return _solve_small_eliminated(inp, max_iter)
    G, h = _rows(inp.G, inp, (m, n)), _rows(inp.h, inp, (m,))

    def solve(G: Tensor | None, h: Tensor | None) -> realtime.SmallSolution | None:
        return realtime.solve_small(
            _rows(inp.Q, inp, (n, n)),
            _rows(inp.p, inp, (n,)),
            G,
            h,
            _rows(inp.lb, inp, (n,)),
            _rows(inp.ub, inp, (n,)),
            inp.eps,
            max_iter,
            inp.batch_shape,
            inp.Q.dtype,
        )

    sol = solve(G, h)
    if sol is None and h is not None and bool(torch.isposinf(h).any()):
        # the kernel refuses non-finite data: rows with h = +inf bound nothing (zero rows,
        # where ``0 * G`` keeps a NaN or inf of G for the kernel to refuse); tried only after
        # a refusal, so the common call pays nothing for it
        free = torch.isposinf(h)
        sol = solve(torch.where(free.unsqueeze(-1), 0.0 * G, G), torch.where(free, 1.0, h))
    if sol is None:
        return None
    return QPSolution(*sol, "small_native", _answered(inp, "active_set"))


def _solve_small_eliminated(inp: _Inputs, max_iter: int) -> QPSolution | None:
    """:func:`_solve_small` for problems with equality rows: eliminated in the C kernel
    (:func:`torchcbf.qp.realtime.solve_small` with ``A, b``); ``None`` where some ``A`` is rank
    deficient, some datum is not finite (``h = +inf`` aside) or the kernel does not certify
    every row."""
    n, m, k = inp.n, inp.m, inp.me
    sol = realtime.solve_small(
        _rows(inp.Q, inp, (n, n)), _rows(inp.p, inp, (n,)), _rows(inp.G, inp, (m, n)),
        _rows(inp.h, inp, (m,)), _rows(inp.lb, inp, (n,)), _rows(inp.ub, inp, (n,)), inp.eps,
        max_iter, inp.batch_shape, inp.Q.dtype, A=_rows(inp.A, inp, (k, n)),
        b=_rows(inp.b, inp, (k,)),
    )  # fmt: skip
    if sol is None:
        return None
    return QPSolution(*sol, "small_native", _answered(inp, "active_set"))


def _beyond_kernel(inp: _Inputs) -> bool:
    """Whether the problems lie beyond the dual method's C kernel by their shape (equality
    rows, or more than ``_dual_native.MAX_VARS`` variables): only these are routed to
    proxsuite, so a problem the kernel's shape fits (a safety filter's) is served the same
    way at every batch size."""
    return inp.me > 0 or inp.n > _dual_native.MAX_VARS


def _direct_applies(inp: _Inputs) -> bool:
    """Whether ``method="auto"`` tries proxsuite straight from the inputs
    (:mod:`torchcbf.qp._direct`): at most ``ROUTE_MAX_BATCH`` CPU problems, no elastic rows,
    proxsuite installed, beyond the C kernel's shape (:func:`_beyond_kernel`) or with some
    ``Q`` not positive definite (which the dual method never takes, at any batch size; a
    safety filter's ``Q`` is positive definite)."""
    if not (
        inp.B <= ROUTE_MAX_BATCH
        and inp.soft is None
        and inp.Q.device.type == "cpu"
        and _proxsuite_available()
    ):
        return False
    if _beyond_kernel(inp):
        return True
    Q = inp.Q.detach().double()
    Q = 0.5 * (Q + Q.mT)
    # a row with NaN or inf data is answered NON_FINITE later: the identity stands in for
    # it here (LAPACK refuses a NaN matrix, for the whole batch)
    finite = torch.isfinite(Q).flatten(-2).all(-1)[..., None, None]
    Q = torch.where(finite, Q, torch.eye(Q.shape[-1], dtype=Q.dtype))
    if not bool(not_positive_definite(Q).any()):
        return False
    # a singular Q, which the dual method never takes; not an indefinite one, on which
    # proxsuite (made for convex problems) may run its whole budget: half a minute for
    # three variables unbounded along a direction of negative curvature
    tau = 2.0 * Q.shape[-1] * torch.finfo(Q.dtype).eps * Q.abs().sum(-1).amax(-1)
    return not bool((torch.linalg.eigvalsh(Q)[..., 0] < -tau).any())


class _Flat(NamedTuple):
    """Inputs flattened to one batch ``[B, ...]``, rows with bad data replaced by a harmless
    problem (``skip``), and the masks that say which."""

    Q: Tensor
    p: Tensor
    G: Tensor
    h: Tensor
    A: Tensor
    b: Tensor
    lb: Tensor | None
    ub: Tensor | None
    soft: Tensor | None
    x0: Tensor | None
    bad: Tensor  # [B] non-finite data
    infeasible_bound: Tensor  # [B] lb = +inf, ub = -inf, h = -inf or a row 0'x = b != 0
    masked: bool  # whether some row may be skipped (always off the CPU)


def _flatten(inp: _Inputs) -> _Flat:
    """Broadcast every input to ``[B, ...]`` and neutralise rows with non-finite data."""
    Q, n, m, me, B = inp.Q, inp.n, inp.m, inp.me, inp.B
    dtype, device = Q.dtype, Q.device

    def flat(t: Tensor | None, trailing: tuple[int, ...]) -> Tensor | None:
        if t is None:
            return None
        return t.expand(*inp.batch_shape, *trailing).reshape(B, *trailing)

    Qf, pf = flat(Q, (n, n)), flat(inp.p, (n,))
    Gf = flat(inp.G, (m, n)) if inp.G is not None else Q.new_zeros(B, 0, n)
    hf = flat(inp.h, (m,)) if inp.h is not None else Q.new_zeros(B, 0)
    Af = flat(inp.A, (me, n)) if inp.A is not None else Q.new_zeros(B, 0, n)
    bf = flat(inp.b, (me,)) if inp.b is not None else Q.new_zeros(B, 0)
    lbf, ubf = flat(inp.lb, (n,)), flat(inp.ub, (n,))
    softf, x0f = flat(inp.soft, (m,)), flat(inp.x0, (n,))

    finite = torch.ones(B, dtype=torch.bool, device=device)
    for t, k in ((Qf, 2), (pf, 1), (Gf, 2), (Af, 2), (bf, 1)):
        if t.numel() > 0:
            finite = finite & rows_finite(t, k, B)
    bad = ~finite
    infeasible_bound = torch.zeros_like(bad)
    if hf.numel() > 0:
        Gf, hf, nan_h, empty_row = _free_rows(Gf, hf, B)
        if nan_h is not None:
            bad = bad | nan_h
            infeasible_bound = infeasible_bound | empty_row
    if lbf is not None:
        bad = bad | torch.isnan(lbf).any(-1)
        infeasible_bound = infeasible_bound | (lbf == math.inf).any(-1)
    if ubf is not None:
        bad = bad | torch.isnan(ubf).any(-1)
        infeasible_bound = infeasible_bound | (ubf == -math.inf).any(-1)
    if softf is not None:
        bad = bad | torch.isnan(softf).any(-1)
    if bf.numel() > 0:  # an equality row 0'x = b with b != 0: nothing satisfies it
        infeasible_bound = infeasible_bound | ((Af == 0).all(-1) & (bf != 0)).any(-1)
    infeasible_bound = infeasible_bound & ~bad
    skip = bad | infeasible_bound
    # on a CPU, asking whether any row is skipped costs no device synchronisation and spares
    # the masks below, which are a large part of a small solve; elsewhere they always run
    masked = device.type != "cpu" or bool(skip.any())
    if masked:
        sk1, sk2 = skip.view(B, 1), skip.view(B, 1, 1)
        Qf = torch.where(sk2, torch.eye(n, dtype=dtype, device=device), Qf)
        pf = torch.where(sk1, 0.0, pf)
        Gf = torch.where(sk2, 0.0, Gf)
        hf = torch.where(sk1, 1.0, hf)
        Af = torch.where(sk2, 0.0, Af)
        bf = torch.where(sk1, 0.0, bf)
        if lbf is not None:
            lbf = torch.where(sk1, -math.inf, lbf)
        if ubf is not None:
            ubf = torch.where(sk1, math.inf, ubf)
        if softf is not None:
            softf = torch.where(sk1, 0.0, softf)
    if x0f is not None:
        x0f = torch.where(skip.view(B, 1) | ~isfinite(x0f), 0.0, x0f)
    return _Flat(Qf, pf, Gf, hf, Af, bf, lbf, ubf, softf, x0f, bad, infeasible_bound, masked)


def _free_rows(G: Tensor, h: Tensor, B: int) -> tuple[Tensor, Tensor, Tensor | None, Tensor | None]:
    """Rows of ``G x <= h`` with ``h = +inf`` bound nothing: their ``G`` row becomes zero and
    ``h`` one (always satisfied, multiplier zero, no gradient). Returns ``(G, h, nan [B],
    empty [B])``: rows with a NaN in ``h``, and rows with ``h = -inf`` (nothing satisfies them);
    both ``None`` where every ``h`` is finite (known without a device synchronisation only on
    a CPU; elsewhere the masks always run)."""
    if h.device.type == "cpu" and bool(rows_finite(h, 1, B).all()):
        return G, h, None, None
    free = h == math.inf
    empty = h == -math.inf
    G = torch.where(free.unsqueeze(-1), 0.0, G)
    h = torch.where(free | empty, 1.0, h)
    return G, h, torch.isnan(h).any(-1), empty.any(-1)


class _Standard(NamedTuple):
    """The problem in the solvers' form ``min 1/2 x'Px + q'x, Gx <= h, Ax = b`` over
    ``N`` variables (``n`` plus one slack per row when softened); box bounds are rows."""

    P: Tensor
    q: Tensor
    G: Tensor
    h: Tensor
    A: Tensor
    x0: Tensor | None
    is_soft: Tensor | None
    N: int
    pairs: tuple[tuple[int, int], ...]  # box rows of one variable, never active together


def _standard_form(f: _Flat, inp: _Inputs) -> _Standard:
    """Symmetrise ``Q``, add the elastic slacks, turn box bounds into inequality rows."""
    n, m, me, B = inp.n, inp.m, inp.me, inp.B
    dtype, device = f.Q.dtype, f.Q.device
    P = 0.5 * (f.Q + f.Q.mT)
    q, Gs, hs, As, x0 = f.p, f.G, f.h, f.A, f.x0
    N = n
    is_soft = None
    if f.soft is not None:
        is_soft = (f.soft > 0) & isfinite(f.soft)
        w = torch.where(is_soft, f.soft, torch.ones_like(f.soft))
        zeros_nm = P.new_zeros(B, n, m)
        P = torch.cat(
            (torch.cat((P, zeros_nm), -1), torch.cat((zeros_nm.mT, torch.diag_embed(w)), -1)), -2
        )
        q = torch.cat((q, w), -1)
        eye_m = torch.eye(m, dtype=dtype, device=device).expand(B, m, m)
        Gs = torch.cat(
            (
                torch.cat((f.G, -torch.diag_embed(is_soft.to(dtype))), -1),
                torch.cat((P.new_zeros(B, m, n), -eye_m), -1),
            ),
            -2,
        )
        hs = torch.cat((f.h, P.new_zeros(B, m)), -1)
        As = torch.cat((f.A, P.new_zeros(B, me, m)), -1)
        N = n + m
        if x0 is not None:
            t0 = (torch.einsum("bmn,bn->bm", f.G, x0) - f.h).clamp_min(0.0) * is_soft
            x0 = torch.cat((x0, t0), -1)
    box_start = Gs.shape[-2]
    bounds = [(bound, sign) for bound, sign in ((f.ub, 1.0), (f.lb, -1.0)) if bound is not None]
    if bounds:  # one row per bounded variable and side, written into one buffer
        rows = box_start + n * len(bounds)
        # in float64, the solvers' working precision: the cast made in the same pass
        G_all = Gs.new_empty(B, rows, N, dtype=torch.float64)
        h_all = hs.new_empty(B, rows, dtype=torch.float64)
        G_all[:, :box_start] = Gs
        h_all[:, :box_start] = hs
        G_all[:, box_start:] = 0.0
        for i, (bound, sign) in enumerate(bounds):
            bounded = isfinite(bound)
            r = box_start + i * n
            box = G_all[:, r : r + n, :n].diagonal(dim1=-2, dim2=-1)
            box.copy_(torch.where(bounded, sign, 0.0))
            h_all[:, r : r + n] = torch.where(bounded, sign * bound, 1.0)
        Gs, hs = G_all, h_all
    pairs: tuple[tuple[int, int], ...] = ()
    if f.lb is not None and f.ub is not None:
        pairs = tuple((box_start + j, box_start + n + j) for j in range(n))
    return _Standard(P, q, Gs, hs, As, x0, is_soft, N, pairs)


def _config(
    inp: _Inputs,
    std: _Standard,
    backend: str,
    method: str,
    polish: bool | None,
    max_iter: int,
    check_every: int,
    need_grad: bool,
) -> SolverConfig:
    """Pick the entry of :data:`torchcbf.qp._function.SOLVERS` that solves the batch (see
    :func:`solve_qp`, ``method``) and collect the options."""
    me, N = inp.me, std.N
    M = std.G.shape[-2]
    C = num_candidates(M, me, N, std.pairs, cap=MAX_CANDIDATES_EXPLICIT) if me <= N else 0
    if method == "enumerate" and backend == "torch" and C > MAX_CANDIDATES_EXPLICIT:
        raise ValueError(
            f"method='enumerate' would try more than {MAX_CANDIDATES_EXPLICIT} candidate active "
            f"sets (N={N} variables, M={M} inequality rows incl. bounds, k={me} equalities); "
            "use method='auto', 'active_set' or 'ipm'"
        )
    chosen, fallback = _choose(inp, std, backend, method, C)
    return SolverConfig(
        method=chosen,
        backend=backend,
        eps=inp.eps,
        eps_inf=inp.eps_inf,
        max_iter=max_iter,
        check_every=check_every,
        polish=backend == "torch" if polish is None else bool(polish),
        fallback=fallback,
        pairs=std.pairs,
        need_factor=need_grad,
        rounding=torch.finfo(inp.Q.dtype).eps,
    )


def _choose(inp: _Inputs, std: _Standard, backend: str, method: str, C: int) -> tuple[str, str]:
    """``(method, fallback)``: the solver table's entry for the batch, and the one for the
    rows ``"eliminate"`` cannot reduce (see :func:`solve_qp`, ``method``)."""
    if backend != "torch":
        return "outside", "ipm"
    me, N, B = inp.me, std.N, inp.B
    cpu = inp.Q.device.type == "cpu"
    kernel = cpu and _dual_native.available()
    one_row = inp.m == 1 and me == 0 and inp.lb is None and inp.ub is None and inp.soft is None
    if one_row and not kernel:
        return ("ipm" if method == "ipm" else "closed_form"), "ipm"
    if std.G.shape[-2] + me == 0 or method == "ipm":
        return "ipm", "ipm"
    if method == "active_set":
        return "active_set", "ipm"
    if method == "enumerate":
        return ("enumerate" if me <= N else "ipm"), "ipm"
    # auto
    if me == 0 and dual_applies(N, kernel) and kernel:
        return "active_set", "ipm"
    if B <= ROUTE_MAX_BATCH and _beyond_kernel(inp) and cpu and _proxsuite_available():
        rest = "auto_proxsuite"
    elif B <= SMALL_BATCH and 0 < C <= MAX_CANDIDATES_SMALL_BATCH:
        rest = "enumerate"
    elif me == 0 and dual_applies(N, kernel):
        rest = "active_set"
    elif 0 < C <= MAX_CANDIDATES:
        rest = "enumerate"
    else:
        rest = "ipm"
    # equality rows eliminated where the reduced problem (with some inequality row) fits the
    # dual method's C kernel; N or more of them can only be dependent, and are eliminated on
    # an independent set (at most N - 1 rows) where b lies in their range
    if kernel and std.G.shape[-2] > 0 and me > 0 and dual_applies(N - min(me, N - 1), True):
        return "eliminate", rest
    return rest, "ipm"


#: largest batch ``method="auto"`` routes to proxsuite's dense solver (see :func:`solve_qp`)
ROUTE_MAX_BATCH = 4


@functools.cache
def _proxsuite_available() -> bool:
    """Whether proxsuite's dense solver imports (an installed but broken proxsuite counts
    as missing: ``auto`` then keeps every problem on torchcbf's own methods)."""
    try:
        from proxsuite import proxqp  # noqa: F401
    except ImportError:
        return False
    return True


def _unpack(
    inp: _Inputs,
    f: _Flat,
    std: _Standard,
    xs: Tensor,
    z: Tensor,
    y: Tensor,
    status: Tensor,
    iters: Tensor,
) -> QPSolution:
    """Split the solvers' ``x`` and multipliers back into :class:`QPSolution` fields."""
    n, m, B = inp.n, inp.m, inp.B
    ok1 = None
    if f.masked:
        ok1 = ~(f.bad | f.infeasible_bound).view(B, 1)
        status = torch.where(f.bad, int(Status.NON_FINITE), status)
        status = torch.where(f.infeasible_bound, int(Status.PRIMAL_INFEASIBLE), status)

    def kept(t: Tensor) -> Tensor:
        return t if ok1 is None else torch.where(ok1, t, 0.0)

    x = kept(xs[:, :n])
    lam = kept(z[:, :m])
    off = m
    slack = xs.new_zeros(B, m)
    if std.is_soft is not None:
        # the least slack x needs: the optimum's (the penalty grows with t), exact where an
        # iterative method leaves a weightless slack short of zero
        violation = (f.G @ x.unsqueeze(-1)).squeeze(-1) - f.h
        slack = violation.clamp_min(0.0) * std.is_soft
        # x of a row not solved answers no problem: no slack, and no gradient through G, h
        slack = torch.where((status == int(Status.SOLVED)).view(B, 1), slack, 0.0)
        off += m
    lam_ub = lam_lb = xs.new_zeros(B, n)
    # an infinite bound holds nothing (an outside solver may leave 1e-12 there)
    if f.ub is not None:
        lam_ub = torch.where(f.ub == math.inf, 0.0, kept(z[:, off : off + n]))
        off += n
    if f.lb is not None:
        lam_lb = torch.where(f.lb == -math.inf, 0.0, kept(z[:, off : off + n]))
    nu = kept(y)

    def unflat(t: Tensor) -> Tensor:
        return t.reshape((*inp.batch_shape, *t.shape[1:]))

    return QPSolution(*(unflat(t) for t in (x, status, lam, nu, iters, lam_lb, lam_ub, slack)))
