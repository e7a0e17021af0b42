"""Maros-Meszaros-format QP test sets: loading, a Clarabel reference and a judge.

A problem file is a MATLAB ``.mat`` file holding ``P [n, n]`` (sparse), ``q [n]``,
``A [m, n]`` (sparse), ``l, u [m]`` and the sizes ``n, m``, for

    min 1/2 x'Px + q'x   s.t.   l <= A x <= u,

where the last ``n`` rows of ``A`` are the identity (the variable bounds) and ``+-1e20``
stands for no bound (the format of the qpsolvers/maros_meszaros_qpbenchmark repository).
:func:`load_problem` turns it into ``solve_qp``'s form: rows with ``u - l < 1e-10`` become
equalities ``Ax = b``, every other finite side an inequality row of ``Gx <= h``, and the
last ``n`` rows the bounds ``lb <= x <= ub``. :func:`dense_subset` keeps the problems with at
most 1,000 variables and 1,000 constraints (inequality rows, equalities and ``n`` bound
rows), the "dense subset" of qpbenchmark. ``scipy`` reads the files; Clarabel (through
``qpsolvers``) gives the reference answers.
"""

from __future__ import annotations

import math
import os
import warnings
from typing import NamedTuple

import numpy as np

#: magnitude at and beyond which a bound of the file format means "no bound"
NO_BOUND = 9e19
#: the dense subset's limits on variables and constraints
DENSE_MAX_VARS = 1000
DENSE_MAX_CONSTRAINTS = 1000


class Problem(NamedTuple):
    """One QP in ``solve_qp``'s form, as dense float64 numpy arrays (``G``/``h`` and
    ``A``/``b`` with zero rows where the problem has none; ``lb``/``ub`` hold ``-inf``/``+inf``
    where a variable is unbounded)."""

    name: str
    P: np.ndarray
    q: np.ndarray
    G: np.ndarray
    h: np.ndarray
    A: np.ndarray
    b: np.ndarray
    lb: np.ndarray
    ub: np.ndarray

    @property
    def n(self) -> int:
        """Number of variables."""
        return self.q.shape[0]

    @property
    def constraints(self) -> int:
        """Inequality rows plus equalities plus one bound row per variable (qpbenchmark's count)."""
        return self.G.shape[0] + self.A.shape[0] + self.n

    def objective(self, x: np.ndarray) -> float:
        """``1/2 x'Px + q'x``."""
        return float(0.5 * x @ self.P @ x + self.q @ x)

    def violation(self, x: np.ndarray) -> float:
        """Largest constraint violation of ``x``, each row relative to ``1 + |rhs| + |row . x|``
        (the magnitude of the terms it compares)."""
        parts = [np.zeros(1)]
        if self.G.shape[0]:
            gx = self.G @ x
            parts.append((gx - self.h).clip(min=0.0) / (1.0 + np.abs(self.h) + np.abs(gx)))
        if self.A.shape[0]:
            ax = self.A @ x
            parts.append(np.abs(ax - self.b) / (1.0 + np.abs(self.b) + np.abs(ax)))
        lo = np.isfinite(self.lb)
        hi = np.isfinite(self.ub)
        parts.append((self.lb[lo] - x[lo]).clip(min=0.0) / (1.0 + np.abs(self.lb[lo])))
        parts.append((x[hi] - self.ub[hi]).clip(min=0.0) / (1.0 + np.abs(self.ub[hi])))
        return float(max(p.max(initial=0.0) for p in parts))


def load_problem(
    path: str | os.PathLike,
    *,
    max_vars: int | None = None,
    max_constraints: int | None = None,
) -> Problem | None:
    """Read one ``.mat`` file of the format above (see the module docstring); ``None`` where
    the problem has more than ``max_vars`` variables or ``max_constraints`` constraints
    (:attr:`Problem.constraints`; checked before any dense matrix is built)."""
    import scipy.io
    import scipy.sparse as sp

    name = os.path.splitext(os.path.basename(path))[0]
    data = scipy.io.loadmat(path)
    n = int(np.asarray(data["n"]).ravel()[0])
    P = sp.csr_matrix(data["P"], dtype=float)
    q = np.asarray(data["q"], dtype=float).ravel()
    C = sp.csr_matrix(data["A"], dtype=float)
    lo = np.asarray(data["l"], dtype=float).ravel()
    hi = np.asarray(data["u"], dtype=float).ravel()
    if P.shape != (n, n) or q.shape != (n,) or C.shape[1] != n or C.shape[0] < n:
        raise ValueError(
            f"{path}: expected P [{n}, {n}], q [{n}], A [m >= {n}, {n}], got P {P.shape}, "
            f"q {q.shape}, A {C.shape}"
        )
    lo = np.where(lo <= -NO_BOUND, -np.inf, lo)
    hi = np.where(hi >= NO_BOUND, np.inf, hi)
    lb, ub = lo[-n:].copy(), hi[-n:].copy()
    C, lo, hi = C[:-n], lo[:-n], hi[:-n]
    eq = hi - lo < 1e-10
    upper = ~eq & np.isfinite(hi)
    lower = ~eq & np.isfinite(lo)
    rows = int(upper.sum() + lower.sum() + eq.sum()) + n
    if (max_vars is not None and n > max_vars) or (
        max_constraints is not None and rows > max_constraints
    ):
        return None
    Cd = C.toarray()
    G = np.vstack((Cd[upper], -Cd[lower]))
    h = np.concatenate((hi[upper], -lo[lower]))
    Pd = P.toarray()
    return Problem(name, 0.5 * (Pd + Pd.T), q, G, h, Cd[eq], hi[eq], lb, ub)


def dense_subset(
    folder: str | os.PathLike,
    *,
    max_vars: int = DENSE_MAX_VARS,
    max_constraints: int = DENSE_MAX_CONSTRAINTS,
) -> list[Problem]:
    """Every ``.mat`` problem in ``folder`` with at most ``max_vars`` variables and
    ``max_constraints`` constraints (:attr:`Problem.constraints`), sorted by name."""
    out = []
    for fname in sorted(os.listdir(folder)):
        if not fname.endswith(".mat"):
            continue
        prob = load_problem(
            os.path.join(folder, fname), max_vars=max_vars, max_constraints=max_constraints
        )
        if prob is not None:
            out.append(prob)
    return out


class Reference(NamedTuple):
    """A reference solver's answer: ``status`` is ``"optimal"``, ``"infeasible"``,
    ``"unbounded"`` or ``"failed"``; ``x`` and ``objective`` are set when optimal."""

    status: str
    x: np.ndarray | None
    objective: float


def clarabel_reference(prob: Problem, *, eps: float = 1e-10) -> Reference:
    """Clarabel's answer (through ``qpsolvers``) at feasibility and gap tolerances ``eps``."""
    import qpsolvers
    import scipy.sparse as sp

    qp = qpsolvers.Problem(
        sp.csc_matrix(prob.P),
        prob.q,
        sp.csc_matrix(prob.G) if prob.G.shape[0] else None,
        prob.h if prob.G.shape[0] else None,
        sp.csc_matrix(prob.A) if prob.A.shape[0] else None,
        prob.b if prob.A.shape[0] else None,
        prob.lb,
        prob.ub,
    )
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        sol = qpsolvers.solve_problem(
            qp, solver="clarabel", tol_feas=eps, tol_gap_abs=eps, tol_gap_rel=eps,
            tol_infeas_abs=eps, tol_infeas_rel=eps, max_iter=500,
        )  # fmt: skip
    status = str(getattr((sol.extras or {}).get("status", ""), "name", "")).lower()
    status = status or str((sol.extras or {}).get("status", "")).lower()
    if sol.found and sol.x is not None:
        return Reference("optimal", sol.x, prob.objective(sol.x))
    if "primalinfeasible" in status.replace("_", ""):
        return Reference("infeasible", None, math.nan)
    if "dualinfeasible" in status.replace("_", ""):
        return Reference("unbounded", None, math.nan)
    return Reference("failed", None, math.nan)


#: the outcomes :func:`judge` returns
OUTCOMES = ("right", "wrong", "failed", "false_certificate", "no_reference")


def judge(
    prob: Problem, x: np.ndarray, solved: bool, certificate: bool, ref: Reference, *, tol: float
) -> str:
    """Judge one answer against the reference (one of :data:`OUTCOMES`).

    A solved answer is ``"right"`` when it violates no constraint by more than ``tol``
    (:meth:`Problem.violation`) and its objective is at most ``tol`` above the reference's,
    relative to ``max(1, |f*|)``; otherwise ``"wrong"``. (A feasible point further below
    the reference's objective proves the reference suboptimal; :func:`below_reference`
    says which right answers are.) An infeasibility or unboundedness
    certificate on a problem the reference solves is ``"false_certificate"``; any other
    unsolved answer to a problem the reference solves is ``"failed"``. Problems the
    reference does not solve are ``"no_reference"``."""
    if ref.status != "optimal":
        return "no_reference"
    if solved:
        close = prob.objective(x) - ref.objective <= tol * max(1.0, abs(ref.objective))
        return "right" if close and prob.violation(x) <= tol else "wrong"
    return "false_certificate" if certificate else "failed"


def below_reference(prob: Problem, x: np.ndarray, ref: Reference, *, tol: float) -> bool:
    """Whether ``x``'s objective lies more than ``tol`` (relative to ``max(1, |f*|)``) below
    the reference's."""
    return ref.objective - prob.objective(x) > tol * max(1.0, abs(ref.objective))


def proxsuite_dense(prob: Problem, *, eps: float = 1e-9, max_iter: int = 10_000) -> Reference:
    """proxsuite's dense solver (``proxqp.dense``, absolute tolerance ``eps``) on ``prob``,
    bounds passed as rows of its double-sided inequalities (``+-1e20`` for no bound)."""
    from proxsuite import proxqp

    n, me = prob.n, prob.A.shape[0]
    C = np.vstack((prob.G, np.eye(n)))
    lo = np.concatenate((np.full(prob.G.shape[0], -1e20), np.nan_to_num(prob.lb, neginf=-1e20)))
    hi = np.concatenate((prob.h, np.nan_to_num(prob.ub, posinf=1e20)))
    qp = proxqp.dense.QP(n, me, C.shape[0])
    qp.settings.eps_abs = eps
    qp.settings.eps_rel = 0.0
    qp.settings.max_iter = max_iter
    qp.settings.verbose = False
    qp.init(prob.P, prob.q, prob.A if me else None, prob.b if me else None, C, lo, hi)
    qp.solve()
    st = qp.results.info.status
    if st == proxqp.PROXQP_SOLVED:
        x = np.array(qp.results.x)
        return Reference("optimal", x, prob.objective(x))
    if st == proxqp.PROXQP_PRIMAL_INFEASIBLE:
        return Reference("infeasible", None, math.nan)
    if st == proxqp.PROXQP_DUAL_INFEASIBLE:
        return Reference("unbounded", None, math.nan)
    return Reference("failed", None, math.nan)
