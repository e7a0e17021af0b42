"""``solve_qp``: the batched, differentiable QP layer (public entry point)."""

from __future__ import annotations

import math
from typing import NamedTuple

import torch
from torch import Tensor

from torchcbf._checks import broadcast_shapes
from torchcbf.qp import _dual_native
from torchcbf.qp._enum import (
    MAX_CANDIDATES,
    MAX_CANDIDATES_SMALL_BATCH,
    SMALL_BATCH,
    num_candidates,
)
from torchcbf.qp._function import MAX_ACTIVE_SET_VARS, QPFunction, SolverConfig
from torchcbf.qp._ipm import default_tolerances
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
    - ``slack [..., m]``: elastic violation ``t >= 0`` of each softened row (``Gx <= h + t``);
      zero for hard rows and when ``soft`` is not given.
    """

    x: Tensor
    status: Tensor
    lam: Tensor
    nu: Tensor
    iterations: Tensor
    lam_lb: Tensor
    lam_ub: Tensor
    slack: Tensor


_FLOAT = (torch.float32, torch.float64)
METHODS = ("auto", "active_set", "enumerate", "ipm")


def _tensor(name: str, value: object, dtype: torch.dtype, device: torch.device) -> Tensor:
    if not isinstance(value, Tensor):
        raise TypeError(f"{name} must be a torch.Tensor, got {type(value).__name__}")
    if value.dtype not in _FLOAT:
        raise TypeError(f"{name} must be float32 or float64, got {value.dtype}")
    if value.dtype != dtype:
        raise TypeError(f"{name} has dtype {value.dtype} but Q has dtype {dtype}")
    if value.device != device:
        raise ValueError(f"{name} is on {value.device} but Q is on {device}")
    return value


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


def _row_nonfinite(t: Tensor | None, trailing: int, batch: int) -> Tensor | None:
    if t is None:
        return None
    flat = t.reshape(batch, math.prod(t.shape[t.dim() - trailing :]))
    if flat.shape[-1] == 0:
        return torch.zeros(batch, dtype=torch.bool, device=t.device)
    # the largest magnitude is NaN or inf exactly when some entry is (and is much faster
    # than isfinite().all() on a CPU)
    return ~torch.isfinite(flat.detach().abs().amax(-1))


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
        rows, at most 8 variables after softening) when the data are on the CPU and its C
        kernel is built (see below; e.g. 0.2 ms for one 2-variable, 6-row QP, about 1.3 us
        per QP in a batch of 4096 4-variable, 8-row QPs, forward and backward). Otherwise
        enumeration for batches of at most 64 rows with at most 800 candidate sets (0.6 ms
        for the same single QP), then the dual method where it applies, else enumeration up
        to 256 candidate sets, else the interior point method.

      On the CPU the dual method runs a C kernel (:mod:`torchcbf.qp._dual_native`, the
      same algorithm problem by problem, built at install when a C compiler is present;
      a large batch is split over ``torch.get_num_threads()`` threads). Without it, and on
      other devices, it runs in torch.
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

    Statuses: see :class:`Status`. A row with NaN/inf in its data (infinite bounds excepted)
    is ``NON_FINITE`` with ``x = 0``; ``lb = +inf`` or ``ub = -inf`` is ``PRIMAL_INFEASIBLE``.
    ``eps`` (default ``1e-7`` in float64, ``2e-6`` in float32) is the relative tolerance on
    residuals and duality gap; ``warm_start`` (``x [..., n]`` or a previous solution) seeds
    the primal iterate. ``polish`` (default: on for the torch backend) toggles the active-set
    polishing.

    Raises ``TypeError``/``ValueError`` naming the argument on bad types or shapes.
    """
    if not isinstance(Q, Tensor):
        raise TypeError(f"Q must be a torch.Tensor, got {type(Q).__name__}")
    if Q.dtype not in _FLOAT:
        raise TypeError(f"Q must be float32 or float64, got {Q.dtype}")
    if Q.dim() < 2 or Q.shape[-1] != Q.shape[-2]:
        raise ValueError(f"Q must have shape [..., n, n], got {tuple(Q.shape)}")
    dtype, device = Q.dtype, Q.device
    n = Q.shape[-1]
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
    if not isinstance(max_iter, int) or isinstance(max_iter, bool) or max_iter < 1:
        raise ValueError(f"max_iter must be a positive integer, got {max_iter!r}")
    if not isinstance(check_every, int) or check_every < 1:
        raise ValueError(f"check_every must be a positive integer, got {check_every!r}")
    eps_default, eps_inf = default_tolerances(dtype)
    if eps is None:
        eps = eps_default
    elif not isinstance(eps, (int, float)) or not (0 < eps < 1):
        raise ValueError(f"eps must be a number in (0, 1), got {eps!r}")
    eps = float(eps)
    x0 = warm_start.x if isinstance(warm_start, QPSolution) else warm_start
    if x0 is not None:
        x0 = _tensor("warm_start", x0, dtype, device)
        _check_trailing("warm_start", x0, (n,), str(n))

    # ---- broadcast every input to one flat batch [B, ...] ----
    parts: list[tuple[str, Tensor | None, int]] = [
        ("Q", Q, 2),
        ("p", p, 1),
        ("G", G, 2),
        ("h", h, 1),
        ("A", A, 2),
        ("b", b, 1),
        ("lb", lb, 1),
        ("ub", ub, 1),
        ("soft", soft, 1),
        ("warm_start", x0, 1),
    ]
    shapes = []
    for name, t, k in parts:
        if t is not None:
            shapes.append((name, tuple(t.shape[: t.dim() - k])))
    try:
        batch_shape = broadcast_shapes(*[s for _, s in shapes])
    except RuntimeError:
        desc = ", ".join(f"{nm} {s}" for nm, s in shapes)
        raise ValueError(f"batch dimensions do not broadcast: {desc}") from None
    B = math.prod(batch_shape) if len(batch_shape) > 0 else 1
    if B == 0:  # an empty batch: empty answers of the right shapes

        def empty(*trailing: int, dt: torch.dtype = dtype) -> Tensor:
            return torch.zeros(*batch_shape, *trailing, dtype=dt, device=device)

        none = empty(dt=torch.int64)
        # zero-size outputs stay connected to the inputs, so backward() works on them
        given = [t for t in (Q, p, G, h, A, b, lb, ub, soft) if isinstance(t, Tensor)]
        link = sum((t.sum() for t in given if t.requires_grad), Q.new_zeros(())) * 0.0
        x, lam, nu, slack = (link + empty(k) for k in (n, m, me, m))
        return QPSolution(x, none, lam, nu, none, link + empty(n), link + empty(n), slack)

    def flat(t: Tensor | None, trailing: tuple[int, ...]) -> Tensor | None:
        if t is None:
            return None
        return t.expand(*batch_shape, *trailing).reshape(B, *trailing)

    Qf = flat(Q, (n, n))
    pf = flat(p, (n,))
    Gf = flat(G, (m, n)) if G is not None else Q.new_zeros(B, 0, n)
    hf = flat(h, (m,)) if h is not None else Q.new_zeros(B, 0)
    Af = flat(A, (me, n)) if A is not None else Q.new_zeros(B, 0, n)
    bf = flat(b, (me,)) if b is not None else Q.new_zeros(B, 0)
    lbf, ubf, softf, x0f = flat(lb, (n,)), flat(ub, (n,)), flat(soft, (m,)), flat(x0, (n,))

    # ---- rows with non-finite data: flagged, replaced by a harmless problem ----
    bad = torch.zeros(B, dtype=torch.bool, device=device)
    for t, k in ((Qf, 2), (pf, 1), (Gf, 2), (hf, 1), (Af, 2), (bf, 1)):
        r = _row_nonfinite(t, k, B)
        if r is not None and t.numel() > 0:
            bad = bad | r
    infeasible_bound = torch.zeros_like(bad)
    if lbf is not None:
        bad = bad | torch.isnan(lbf).any(-1)
        infeasible_bound = infeasible_bound | (lbf == math.inf).any(-1)
    if ubf is not None:
        bad = bad | torch.isnan(ubf).any(-1)
        infeasible_bound = infeasible_bound | (ubf == -math.inf).any(-1)
    if softf is not None:
        bad = bad | torch.isnan(softf).any(-1)
    infeasible_bound = infeasible_bound & ~bad
    skip = bad | infeasible_bound
    # on a CPU, asking whether any row is skipped costs no device synchronisation and spares
    # the masks below, which are a large part of a small solve; elsewhere they always run
    masked = device.type != "cpu" or bool(skip.any())
    if masked:
        sk1, sk2 = skip.view(B, 1), skip.view(B, 1, 1)
        eye = torch.eye(n, dtype=dtype, device=device)
        Qf = torch.where(sk2, eye, Qf)
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
        x0f = torch.where(skip.view(B, 1) | ~torch.isfinite(x0f), 0.0, x0f)

    # ---- standard form: symmetrise, soften, box rows -> inequality rows ----
    P = 0.5 * (Qf + Qf.mT)
    q = pf
    Gs, hs, As = Gf, hf, Af
    N = n
    if softf is not None:
        is_soft = (softf > 0) & torch.isfinite(softf)
        w = torch.where(is_soft, softf, torch.ones_like(softf))
        zeros_nm = P.new_zeros(B, n, m)
        P = torch.cat(
            (torch.cat((P, zeros_nm), -1), torch.cat((zeros_nm.mT, torch.diag_embed(w)), -1)), -2
        )
        q = torch.cat((q, w), -1)
        eye_m = torch.eye(m, dtype=dtype, device=device).expand(B, m, m)
        Gs = torch.cat(
            (
                torch.cat((Gf, -torch.diag_embed(is_soft.to(dtype))), -1),
                torch.cat((P.new_zeros(B, m, n), -eye_m), -1),
            ),
            -2,
        )
        hs = torch.cat((hf, P.new_zeros(B, m)), -1)
        As = torch.cat((Af, P.new_zeros(B, me, m)), -1)
        N = n + m
        if x0f is not None:
            t0 = (torch.einsum("bmn,bn->bm", Gf, x0f) - hf).clamp_min(0.0) * is_soft
            x0f = torch.cat((x0f, t0), -1)
    box_rows = []
    box_h = []
    box_start = Gs.shape[-2]
    for bound, sign in ((ubf, 1.0), (lbf, -1.0)):
        if bound is None:
            continue
        finite = torch.isfinite(bound)
        rows = sign * torch.diag_embed(finite.to(dtype))
        if N > n:
            rows = torch.cat((rows, P.new_zeros(B, n, N - n)), -1)
        box_rows.append(rows)
        box_h.append(torch.where(finite, sign * bound, torch.ones_like(bound)))
    if box_rows:
        Gs = torch.cat((Gs, *box_rows), -2)
        hs = torch.cat((hs, *box_h), -1)

    # the dual method's C kernel (CPU) beats enumeration at every batch size, and the closed
    # form too (it is the same single step, and its backward needs no KKT factorisation)
    kernel = device.type == "cpu" and _dual_native.available()
    one_row = m == 1 and me == 0 and lb is None and ub is None and soft is None
    closed_form = backend == "torch" and one_row and not kernel
    if polish is None:
        polish = backend == "torch"
    pairs: tuple[tuple[int, int], ...] = ()
    if lbf is not None and ubf is not None:
        # both bounds of one variable are never active together (rows linearly dependent)
        pairs = tuple((box_start + j, box_start + n + j) for j in range(n))
    M_total = Gs.shape[-2]
    exact = backend == "torch" and not closed_form and M_total + me > 0
    use_dual = exact and method == "active_set" and me == 0
    use_enum = exact and method == "enumerate"
    if exact and method == "auto":
        C = num_candidates(M_total, me, N, pairs) if me <= N else 0
        dual_applies = me == 0 and N <= MAX_ACTIVE_SET_VARS
        if dual_applies and kernel:
            use_dual = True
        elif B <= SMALL_BATCH and 0 < C <= MAX_CANDIDATES_SMALL_BATCH:
            use_enum = True
        elif dual_applies:
            use_dual = True
        else:
            use_enum = 0 < C <= MAX_CANDIDATES
    tensors = [t for _, t, _ in parts if t is not None]
    need_factor = torch.is_grad_enabled() and any(t.requires_grad for t in tensors)
    cfg = SolverConfig(
        backend=backend,
        eps=eps,
        eps_inf=eps_inf,
        max_iter=max_iter,
        check_every=check_every,
        closed_form=closed_form and method != "ipm",
        polish=bool(polish),
        enumerate=use_enum and me <= N,
        active_set=use_dual,
        pairs=pairs,
        need_factor=need_factor,
    )
    if backend.startswith("qpsolvers:") and torch.is_grad_enabled():
        needs = [nm for nm, t, _ in parts if t is not None and t.requires_grad]
        if needs:
            raise ValueError(
                f"backend {backend!r} is forward-only but {', '.join(needs)} require grad; "
                "use backend='torch' or 'proxsuite', or call under torch.no_grad()"
            )
    xs, z, y, status, iters = QPFunction.apply(P, q, Gs, hs, As, bf, cfg, x0f)

    # ---- unpack ----
    ok1 = ~skip.view(B, 1) if masked else None
    if masked:
        status = torch.where(bad, int(Status.NON_FINITE), status)
        status = torch.where(infeasible_bound, int(Status.PRIMAL_INFEASIBLE), status)

    def kept(t: Tensor) -> Tensor:
        return t if ok1 is None else torch.where(ok1, t, 0.0)

    x = kept(xs[:, :n])
    lam = kept(z[:, :m])
    off = m
    slack = P.new_zeros(B, m)
    if softf is not None:
        slack = kept(xs[:, n:].clamp_min(0.0) * is_soft)
        off += m
    zero_n = P.new_zeros(B, n)
    lam_ub = lam_lb = zero_n
    if ubf is not None:
        lam_ub = kept(z[:, off : off + n])
        off += n
    if lbf is not None:
        lam_lb = kept(z[:, off : off + n])
    nu = kept(y)

    def unflat(t: Tensor) -> Tensor:
        return t.reshape((*batch_shape, *t.shape[1:]))

    return QPSolution(
        unflat(x),
        unflat(status),
        unflat(lam),
        unflat(nu),
        unflat(iters),
        unflat(lam_lb),
        unflat(lam_ub),
        unflat(slack),
    )
