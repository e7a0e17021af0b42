"""CPU backends: proxsuite's dense solver (batched by its own ``solve_in_parallel``) and
qpsolvers (one problem at a time). Both take the standard form ``Gx <= h, Ax = b`` in float64
and return ``(x, s, z, y, status, iterations)`` as float64 CPU tensors."""

from __future__ import annotations

import warnings
from collections.abc import Callable

import numpy as np
import torch
from torch import Tensor

from torchcbf.qp._data import QPData
from torchcbf.qp._kkt import kkt_residuals_ok
from torchcbf.qp.status import Status

_BIG = 1e20
#: iterations of each of the two short runs in which :func:`solve_watched` watches proxsuite's
#: iterates for a direction of unbounded descent
WATCH_ITER = 100
#: tolerance of the watch's descent test: the step between two iterates is an approximate
#: direction, and a row handed on is certified (or solved) by the general path
WATCH_TOL = 1e-3


def _verify(
    x: Tensor, G: Tensor, h: Tensor, A: Tensor, b: Tensor, status: Tensor, eps: float
) -> Tensor:
    """Demote rows reported solved whose answer violates the constraints (to ``MAX_ITER``)."""
    viol = torch.cat(
        (
            (torch.einsum("bmn,bn->bm", G, x) - h).clamp_min(0.0),
            (torch.einsum("bmn,bn->bm", A, x) - b).abs(),
        ),
        -1,
    )
    if viol.shape[-1] == 0:
        bad = ~torch.isfinite(x).all(-1)
    else:
        scale = 1.0 + torch.cat((h.abs(), b.abs()), -1).amax(-1)
        bad = ~(viol.amax(-1) <= 10.0 * eps * scale) | ~torch.isfinite(x).all(-1)
    return torch.where((status == int(Status.SOLVED)) & bad, int(Status.MAX_ITER), status)


class _BoxSplit:
    """One problem's rows ``Gx <= h`` split into proxsuite's box constraints (rows with one
    nonzero entry, the tightest per variable and side) and general one-sided rows (rows of
    zeros with ``h >= 0``, which bound nothing, dropped). proxsuite's dense solver is
    markedly more robust with bounds passed as its box than as rows."""

    def __init__(self, G: np.ndarray, h: np.ndarray) -> None:
        M, n = G.shape
        nz = G != 0
        count = nz.sum(1)
        single = count == 1
        self.general = np.flatnonzero(~single & ~((count == 0) & (h >= 0)))
        rows = np.flatnonzero(single)
        col = nz[rows].argmax(1)
        coef = G[rows, col]
        bound = h[rows] / coef
        self.lb = np.full(n, -_BIG)
        self.ub = np.full(n, _BIG)
        # the row that sets each variable's bound: sort by (variable, bound), take the first
        # upper (smallest bound) and the last lower (largest bound) of each variable
        self.upper_row = np.full(n, -1)
        self.lower_row = np.full(n, -1)
        for side, pick in ((coef > 0, 0), (coef < 0, -1)):
            r, c, v = rows[side], col[side], bound[side]
            if len(r) == 0:
                continue
            order = np.lexsort((v, c))
            r, c, v = r[order], c[order], v[order]
            first = np.flatnonzero(np.r_[True, c[1:] != c[:-1]])
            last = np.r_[first[1:] - 1, len(c) - 1]
            take = first if pick == 0 else last
            if pick == 0:
                self.ub[c[take]] = np.minimum(v[take], _BIG)
                self.upper_row[c[take]] = r[take]
            else:
                self.lb[c[take]] = np.maximum(v[take], -_BIG)
                self.lower_row[c[take]] = r[take]
        self.G = G

    def multipliers(self, z_general: np.ndarray, z_box: np.ndarray) -> np.ndarray:
        """Multipliers ``z [M]`` of the original rows from proxsuite's (general rows, then the
        box: positive at an upper bound, negative at a lower one)."""
        z = np.zeros(self.G.shape[0])
        z[self.general] = np.maximum(z_general, 0.0)
        for rows, sign in ((self.upper_row, 1.0), (self.lower_row, -1.0)):
            j = np.flatnonzero(rows >= 0)
            r = rows[j]
            z[r] = np.maximum(sign * z_box[j], 0.0) / np.abs(self.G[r, j])
        return z


def descends(
    P: np.ndarray,
    q: np.ndarray,
    G: np.ndarray,
    A: np.ndarray,
    lb: np.ndarray,
    ub: np.ndarray,
    free: np.ndarray,
    x: np.ndarray,
    eps_inf: float,
) -> bool:
    """Whether some row's ``x [B, n]`` is a direction of unbounded descent of
    ``x'Px/2 + q'x`` under ``Gx <= h`` (rows ``free`` left out), ``Ax = b`` and the bounds
    (the test of :func:`torchcbf.qp._ipm._descent_direction`, in numpy): a minimiser far along
    a direction where ``P`` is singular to the inputs' rounding, or the step between
    iterates running out along one; the general path reports such rows
    ``DUAL_INFEASIBLE``."""
    qx = (q * x).sum(-1)
    xn = eps_inf * np.abs(x).max(-1)
    thr = -eps_inf * qx
    cand = (qx < 0) & (qx <= -np.abs(q).max(-1) * xn)
    if not cand.any():
        return False
    px = np.abs(np.einsum("bij,bj->bi", P, x)).max(-1)
    cand &= px <= np.minimum(thr, np.abs(P).max((-2, -1)) * xn)
    if A.shape[1]:
        ax = np.abs(np.einsum("ben,bn->be", A, x)).max(-1)
        cand &= ax <= np.minimum(thr, np.abs(A).max((-2, -1)) * xn)
    Gf = np.where(free[..., None], 0.0, G)
    parts = [np.where(np.isfinite(ub), x, -np.inf), np.where(np.isfinite(lb), -x, -np.inf)]
    g_max = (
        np.ones(len(x)) if (np.isfinite(ub).any() or np.isfinite(lb).any()) else np.zeros(len(x))
    )
    if G.shape[1]:
        parts.append(np.einsum("bmn,bn->bm", Gf, x))
        g_max = np.maximum(g_max, np.abs(Gf).max((-2, -1)))
    gx = np.concatenate(parts, -1).max(-1, initial=-np.inf)
    cand &= gx <= np.minimum(thr, g_max * xn)
    return bool(cand.any())


def solve_watched(
    qp: object,
    max_iter: int,
    descending: Callable[[np.ndarray], bool],
    x0: np.ndarray | None = None,
) -> int | None:
    """Solve the initialised proxsuite problem ``qp`` in at most ``max_iter`` iterations (from
    ``x0`` where given) and return the iterations taken, or ``None`` where its iterates run
    along a direction ``d`` with ``descending(d)``.

    proxsuite does not detect every unbounded problem: with ``P`` singular only to rounding it
    runs its whole budget (tens of seconds for a few variables, at up to 1,500 inner
    iterations each), its iterates growing along the recession direction. So it runs
    ``WATCH_ITER`` iterations, then ``WATCH_ITER`` more from where it stopped; where both end
    unsolved and the step between them is a direction of descent it stops there, otherwise it
    goes on from there for the rest of ``max_iter``."""
    from proxsuite import proxqp

    first = min(WATCH_ITER, max_iter)
    second = min(WATCH_ITER, max_iter - first)
    taken = 0
    for run, budget in enumerate((first, second, max_iter - first - second)):
        if budget == 0:
            break
        before = np.array(qp.results.x) if run == 1 else None
        qp.settings.max_iter = budget
        if run == 0 and x0 is not None:
            qp.solve(x0, None, None)
        elif run == 0:
            qp.solve()
        else:
            qp.settings.initial_guess = proxqp.InitialGuess.WARM_START_WITH_PREVIOUS_RESULT
            qp.solve()
        taken += qp.results.info.iter
        if qp.results.info.status != proxqp.PROXQP_MAX_ITER_REACHED:
            break
        if before is not None and descending(qp.results.x - before):
            return None
    return taken


#: how far :func:`row_tolerance` tightens proxsuite's tolerance for the rows scaled down
ROW_TIGHTEN_MAX = 1e3
#: a problem with a longer row has its rows longer than 1 scaled to unit length
ROW_NORM_LIMIT = 1e3


def unit_rows(M: np.ndarray) -> np.ndarray:
    """``[B, r]`` scales of the rows of ``M [B, r, n]``: in a problem with a row longer than
    :data:`ROW_NORM_LIMIT`, every row longer than 1 brought to unit length (proxsuite's
    tolerances are absolute: it never meets 1e-9 on a row of norm 1e16, and runs its whole
    budget); 1 elsewhere (an ordinary problem goes as it is). A row's multiplier is the
    scaled row's times its scale."""
    norms = np.linalg.norm(M, axis=-1)
    long = (norms > ROW_NORM_LIMIT).any(-1, keepdims=True)
    return np.where(long, 1.0 / np.maximum(norms, 1.0), 1.0)


def row_tolerance(eps: float, *scales: np.ndarray) -> np.ndarray:
    """``[B]``: proxsuite's absolute tolerance for each problem whose rows were scaled by
    ``scales`` (:func:`unit_rows`): ``eps`` tightened by the least scale below 1, so a row
    scaled down is met to ``eps`` in its own units (at most :data:`ROW_TIGHTEN_MAX`
    tighter: a row of norm 1e16 is met to ``eps`` relative)."""
    least = np.ones(scales[0].shape[0])
    for s in scales:
        if s.shape[-1]:
            least = np.minimum(least, s.min(-1))
    return eps * np.maximum(least, 1.0 / ROW_TIGHTEN_MAX)


def solve_proxsuite(
    data: QPData,
    *,
    eps: float,
    max_iter: int,
    x0: Tensor | None = None,
    box: bool = False,
    watch: bool = False,
    gap: bool = False,
) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor, Tensor]:
    """Solve every row with ``proxsuite.proxqp.dense``, in parallel (OpenMP threads) where
    there are several rows and threads. With ``box``, rows of ``G`` with one nonzero entry
    go to proxsuite as box constraints (:class:`_BoxSplit`). With ``watch``, rows are
    solved one at a time, each watched for a direction of unbounded descent
    (:func:`solve_watched`); a row that finds one ends ``MAX_ITER``. With ``gap``, a row is
    solved only once its duality gap is within ``eps`` too (absolute, and relative to the
    objective's terms): without it proxsuite stops on feasibility and stationarity alone
    and calls points 1% above the minimum solved; the callers that verify every answer
    themselves leave it off (on a nonconvex row the gap never closes, and proxsuite then
    runs its whole budget)."""
    P, q, G, h, A, b = data
    from proxsuite import proxqp

    B, n = q.shape
    M, me = h.shape[-1], b.shape[-1]
    Pn, qn, Gn, hn, An, bn = (t.detach().cpu().double().numpy() for t in (P, q, G, h, A, b))
    # rows of unit length: proxsuite's tolerances are absolute (multipliers scaled back)
    dg, da = unit_rows(Gn), unit_rows(An)
    Gn, hn, An, bn = Gn * dg[..., None], hn * dg, An * da[..., None], bn * da
    tolerance = row_tolerance(eps, dg, da)
    x0n = None if x0 is None else x0.detach().cpu().double().numpy()
    parallel = x0n is None and B > 1 and torch.get_num_threads() > 1 and not watch
    qps = proxqp.dense.VectorQP() if parallel else []
    it = np.zeros(B, dtype=np.int64)
    no_bounds = np.full((1, n), np.inf)
    splits = []
    for i in range(B):
        split = _BoxSplit(Gn[i], hn[i]) if box else None
        splits.append(split)
        gen = split.general if box else np.arange(M)
        m_in = len(gen)
        qp = proxqp.dense.QP(n, me, m_in, box)
        qp.settings.eps_abs = float(tolerance[i])
        qp.settings.eps_rel = 0.0
        qp.settings.check_duality_gap = gap
        qp.settings.eps_duality_gap_abs = eps
        qp.settings.eps_duality_gap_rel = eps
        qp.settings.max_iter = max_iter
        qp.settings.verbose = False
        if x0n is not None:
            qp.settings.initial_guess = proxqp.InitialGuess.WARM_START
        qp.init(
            Pn[i],
            qn[i],
            An[i] if me > 0 else None,
            bn[i] if me > 0 else None,
            Gn[i][gen] if m_in > 0 else None,
            np.full(m_in, -_BIG) if m_in > 0 else None,
            hn[i][gen] if m_in > 0 else None,
            *((split.lb, split.ub) if box else ()),
        )
        if watch:
            row = slice(i, i + 1)

            def descending(d: np.ndarray, row: slice = row) -> bool:
                return descends(Pn[row], qn[row], Gn[row], An[row], -no_bounds, no_bounds,
                                np.isinf(hn[row]), d[None], WATCH_TOL)  # fmt: skip

            x0i = None if x0n is None else x0n[i]
            taken = solve_watched(qp, max_iter, descending, x0i)
            it[i] = max_iter if taken is None else taken
        elif x0n is not None:
            qp.solve(x0n[i], None, None)
        elif not parallel:
            qp.solve()  # no thread pool to start for one problem or one thread
        qps.append(qp)
    if parallel:
        proxqp.dense.solve_in_parallel(qps, torch.get_num_threads())
    codes = {
        proxqp.PROXQP_SOLVED: Status.SOLVED,
        proxqp.PROXQP_PRIMAL_INFEASIBLE: Status.PRIMAL_INFEASIBLE,
        proxqp.PROXQP_DUAL_INFEASIBLE: Status.DUAL_INFEASIBLE,
        proxqp.PROXQP_MAX_ITER_REACHED: Status.MAX_ITER,
        proxqp.PROXQP_SOLVED_CLOSEST_PRIMAL_FEASIBLE: Status.PRIMAL_INFEASIBLE,
    }
    x = np.zeros((B, n))
    z = np.zeros((B, M))
    y = np.zeros((B, me))
    st = np.zeros(B, dtype=np.int64)
    for i in range(B):
        res = qps[i].results
        x[i] = res.x
        if M > 0:
            zr = np.asarray(res.z)
            if box:
                m_in = len(splits[i].general)
                z[i] = splits[i].multipliers(zr[:m_in], zr[m_in:])
            else:
                z[i] = np.maximum(zr, 0.0)
        if me > 0:
            y[i] = res.y
        st[i] = int(codes.get(res.info.status, Status.MAX_ITER))
        if not watch:
            it[i] = res.info.iter
    return _finish(x, z * dg, y * da, st, it, G, h, A, b, eps)


def _finish(
    x: np.ndarray,
    z: np.ndarray,
    y: np.ndarray,
    st: np.ndarray,
    it: np.ndarray,
    G: Tensor,
    h: Tensor,
    A: Tensor,
    b: Tensor,
    eps: float,
) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor, Tensor]:
    Gc, hc, Ac, bc = (t.detach().cpu().double() for t in (G, h, A, b))
    xt = torch.from_numpy(np.nan_to_num(x, nan=0.0, posinf=0.0, neginf=0.0))
    zt = torch.from_numpy(np.nan_to_num(z, nan=0.0, posinf=0.0, neginf=0.0))
    yt = torch.from_numpy(np.nan_to_num(y, nan=0.0, posinf=0.0, neginf=0.0))
    status = torch.from_numpy(st)
    status = _verify(torch.from_numpy(x), Gc, hc, Ac, bc, status, eps)
    infeasible = (status == int(Status.PRIMAL_INFEASIBLE)) | (status == int(Status.DUAL_INFEASIBLE))
    keep = (~infeasible).unsqueeze(-1)
    xt = torch.where(keep, xt, torch.zeros_like(xt))
    zt = torch.where(keep, zt, torch.zeros_like(zt))
    yt = torch.where(keep, yt, torch.zeros_like(yt))
    s = (hc - torch.einsum("bmn,bn->bm", Gc, xt)).clamp_min(0.0)
    return xt, s, zt, yt, status, torch.from_numpy(it)


#: the tolerance options, from ``eps``, of the solvers whose defaults are looser than the
#: answers are verified to (proxqp 1e-5 absolute, OSQP 1e-3, SCS 1e-4; Clarabel's 1e-8 are
#: kept); a tenth of ``eps``, since their tests are absolute and the verification relative
_TOLERANCES: dict[str, Callable[[float], dict[str, float]]] = {
    "proxqp": lambda eps: {"eps_abs": eps / 10, "eps_rel": 0.0},
    "osqp": lambda eps: {"eps_abs": eps / 10, "eps_rel": eps / 10},
    "scs": lambda eps: {"eps_abs": eps / 10, "eps_rel": eps / 10},
}


#: the least tolerance to which an answer of one of qpsolvers' solvers is verified
OUTSIDE_VERIFY_EPS = 1e-6


def _defaults(eps: float) -> dict[str, float]:
    """No options: the solver's own tolerances."""
    return {}


def solve_qpsolvers(
    solver: str,
    data: QPData,
    *,
    eps: float,
    max_iter: int,
) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor, Tensor]:
    """Solve each row with ``qpsolvers.solve_problem(..., solver=solver)`` (a Python loop).

    Infeasibility is read from the solver's own status string where it exposes one
    (Clarabel, OSQP, proxqp, HiGHS, SCS report 'primal/dual infeasible'); any other failure is
    ``MAX_ITER``. ``eps`` is forwarded as the tolerances of the solvers whose defaults are
    looser (:data:`_TOLERANCES`; the others run to their defaults) and ``max_iter`` is not;
    an answer the solver reports found is ``SOLVED`` only where it is a KKT point to
    ``max(eps, OUTSIDE_VERIFY_EPS)`` (:func:`kkt_residuals_ok`: the solver's own tolerances
    may be looser than ``eps``, a wrong answer is far looser), else ``MAX_ITER``."""
    P, q, G, h, A, b = data
    import qpsolvers

    if solver not in qpsolvers.available_solvers:
        raise ValueError(
            f"backend 'qpsolvers:{solver}': solver not installed; available: "
            f"{sorted(qpsolvers.available_solvers)}"
        )
    del max_iter
    B, n = q.shape
    M, me = h.shape[-1], b.shape[-1]
    Pn, qn, Gn, hn, An, bn = (t.detach().cpu().double().numpy() for t in (P, q, G, h, A, b))
    x = np.zeros((B, n))
    z = np.zeros((B, M))
    y = np.zeros((B, me))
    st = np.zeros(B, dtype=np.int64)
    it = np.zeros(B, dtype=np.int64)
    options = _TOLERANCES.get(solver, _defaults)(eps)
    for i in range(B):
        prob = qpsolvers.Problem(
            Pn[i],
            qn[i],
            Gn[i] if M > 0 else None,
            hn[i] if M > 0 else None,
            An[i] if me > 0 else None,
            bn[i] if me > 0 else None,
        )
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            sol = qpsolvers.solve_problem(prob, solver=solver, **options)
        if sol.found and sol.x is not None:
            x[i] = sol.x
            if M > 0 and sol.z is not None:
                z[i] = np.maximum(sol.z, 0.0)
            if me > 0 and sol.y is not None:
                y[i] = sol.y
            st[i] = int(Status.SOLVED)
        else:
            st[i] = int(_infeasibility_from_extras(sol.extras))
    xt, s, zt, yt, status, iters = _finish(x, z, y, st, it, G, h, A, b, eps)
    given = QPData(*(torch.from_numpy(v) for v in (Pn, qn, Gn, hn, An, bn)))
    verified = kkt_residuals_ok(given, xt, zt, yt, max(eps, OUTSIDE_VERIFY_EPS))
    loose = (status == int(Status.SOLVED)) & ~verified
    return xt, s, zt, yt, torch.where(loose, int(Status.MAX_ITER), status), iters


def _infeasibility_from_extras(extras: dict | None) -> Status:
    text = ""
    if extras:
        for key in ("status", "info"):
            if key in extras:
                val = extras[key]
                text += " " + str(getattr(val, "status", val))
    text = text.lower().replace("_", " ").replace("primalinfeasible", "primal infeasible")
    text = text.replace("dualinfeasible", "dual infeasible")
    if "primal infeasible" in text:
        return Status.PRIMAL_INFEASIBLE
    if "dual infeasible" in text:
        return Status.DUAL_INFEASIBLE
    return Status.MAX_ITER
