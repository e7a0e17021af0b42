"""Accuracy of ``solve_qp`` (torch backend, ``method="auto"``) against cvxpy/Clarabel on the
10,000 random QPs of the slow test (``tests/qp/test_solve.py::test_ten_thousand_vs_cvxpy``):
n in 2..12, m in 1..64, with and without box bounds and equalities, a quarter infeasible.

Prints, per dtype, the largest relative errors in ``x`` and in the objective over the feasible
rows, and how many infeasible rows were flagged (and reported solved: must be 0).

Then a table of hard families (float64, ``method="auto"``, tests/qp/_problems.py:
``hard_family``), each row against cvxpy/Clarabel: rotated ill-conditioned ``Q`` (1e6, 1e8,
1e10), rows tight at a known feasible point, duplicated and near-parallel rows, row scales
mixed from 1e-6 to 1e6, linear programs in a box (``Q = 0``), rank-deficient ``Q`` in a box,
equalities with a box, a degenerate vertex with a known solution, mid-size problems, and
families that are infeasible (contradicting rows, an empty box, inconsistent equalities) or
unbounded (a free direction, a recession direction of the rows). Per family: rows, solved
(rows with the expected status), max scaled error in ``x`` (``|x - x_ref| / (1 + |x_ref|)``
against Clarabel and the known solution, over rows both solve), false failures (rows without
the expected status; on feasible families, those Clarabel solves or whose solution is known),
wrong SOLVED (error above 1e-6, or SOLVED on an infeasible or unbounded row) and the time per
QP of the batch solve (on a loaded machine it varies). Rows where Clarabel disagrees with the
family's construction print a warning. ``--seed S`` draws family ``k`` from seed ``S + k``
(default ``500 + k``).

    python scripts/qp_accuracy.py [--families-only] [--rows 64] [--seed S]
"""

from __future__ import annotations

import argparse
import sys
import time
import warnings
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests" / "qp"))
from _problems import HARD_FAMILIES, TEN_THOUSAND_SHAPES, hard_family, make_batch  # noqa: E402
from conftest import cvxpy_solve  # noqa: E402

from torchcbf.qp import Status, solve_qp  # noqa: E402

#: the status a row of each kind of family must get
EXPECTED_STATUS = {
    "optimal": Status.SOLVED,
    "infeasible": Status.PRIMAL_INFEASIBLE,
    "unbounded": Status.DUAL_INFEASIBLE,
}


def _scaled_error(x: np.ndarray, ref: np.ndarray) -> float:
    return float(np.abs(x - ref).max() / (1.0 + np.abs(ref).max()))


def _reference(row: list) -> tuple:
    """Clarabel's ``(x, status)`` for one row; status ``"solver_error"`` where it fails."""
    import cvxpy

    try:
        with warnings.catch_warnings():  # "Solution may be inaccurate": its status says so
            warnings.simplefilter("ignore", UserWarning)
            x, _, st = cvxpy_solve(*row)
    except cvxpy.error.SolverError:
        return None, "solver_error"
    return x, st


def families(rows: int, seed: int | None = None) -> list[tuple]:
    """Print the hard-family table (family ``k`` drawn from seed ``500 + k``, or ``seed + k``)
    and return the failing rows as ``(family, row, status, Clarabel's status, error)``.

    Optimal families: solved counts SOLVED rows; max err is the larger scaled error against
    Clarabel and against the known solution ``x_star`` (where the family knows it); false
    fail counts rows not SOLVED that Clarabel solves or whose solution is known; wrong
    SOLVED counts SOLVED rows more than 1e-6 from the known solution, or else from Clarabel's,
    or that Clarabel calls infeasible or unbounded. Infeasible and unbounded families: solved
    counts rows with the expected status (PRIMAL_INFEASIBLE, DUAL_INFEASIBLE), false fail the
    rows without it, wrong SOLVED the SOLVED rows. After the table, a warning per family where
    Clarabel does not confirm the family's construction on some rows (its ``*_inaccurate``
    statuses count as confirming) or, where the solution is known, is more than 1e-6 from it.
    """
    width = max(len(name) for name in HARD_FAMILIES)
    print(
        f"\n{'family':{width}s} {'expect':>10s} {'rows':>5s} {'solved':>6s} {'max err':>9s} "
        f"{'false fail':>10s} {'wrong SOLVED':>12s} {'us/QP':>8s}"
    )
    failures, notes = [], []
    for k, name in enumerate(HARD_FAMILIES):
        g = torch.Generator().manual_seed((500 if seed is None else seed) + k)
        prob = hard_family(name, rows, g)
        data = prob.data()
        solve_qp(*data)  # warm up
        t0 = time.perf_counter()
        sol = solve_qp(*data)
        per_qp = (time.perf_counter() - t0) / rows
        expected = EXPECTED_STATUS[prob.expect]
        err = ref_off = 0.0
        n_ok = false_fail = wrong = 0
        disagree, off = [], []
        for i in range(rows):
            row = [t[i].numpy() if t is not None else None for t in data]
            x_ref, st = _reference(row)
            if st.removesuffix("_inaccurate") != prob.expect:
                disagree.append((i, st))
            status = int(sol.status[i])
            n_ok += status == expected
            if prob.expect != "optimal":
                false_fail += status != expected
                wrong += status == Status.SOLVED
                if status != expected:
                    failures.append((name, i, Status(status).name, st, None))
                continue
            x_star = None if prob.x_star is None else prob.x_star[i].numpy()
            if x_star is not None and st == "optimal":
                e_ref = _scaled_error(x_ref, x_star)
                ref_off = max(ref_off, e_ref)
                if e_ref > 1e-6:
                    off.append(i)
            if status != Status.SOLVED:
                false_fail += st == "optimal" or x_star is not None
                failures.append((name, i, Status(status).name, st, None))
                continue
            if x_star is None and st != "optimal":
                if st.removesuffix("_inaccurate") in ("infeasible", "unbounded"):
                    wrong += 1
                    failures.append((name, i, Status(status).name, st, None))
                continue
            x = sol.x[i].numpy()
            e_star = None if x_star is None else _scaled_error(x, x_star)
            e_clarabel = _scaled_error(x, x_ref) if st == "optimal" else 0.0
            err = max(err, e_clarabel, e_star or 0.0)
            e = e_clarabel if e_star is None else e_star
            if e > 1e-6:
                wrong += 1
                failures.append((name, i, Status(status).name, st, e))
        err_col = f"{err:9.1e}" if prob.expect == "optimal" else f"{'-':>9s}"
        print(
            f"{name:{width}s} {prob.expect:>10s} {rows:5d} {n_ok:6d} {err_col} {false_fail:10d} "
            f"{wrong:12d} {per_qp * 1e6:8.1f}"
        )
        if disagree:
            said = ", ".join(f"{i}: {st}" for i, st in disagree)
            notes.append(
                f"WARNING: {name}: Clarabel does not confirm {prob.expect!r} on "
                f"{len(disagree)} of {rows} rows ({said})"
            )
        if off:
            notes.append(
                f"WARNING: {name}: Clarabel's x is more than 1e-6 from the known solution on "
                f"{len(off)} of {rows} rows (up to {ref_off:.1e}; rows {off}); wrong SOLVED "
                "is judged against the known solution"
            )
    for line in notes:
        print(line)
    return failures


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--total", type=int, default=10_000, help="number of QPs per dtype")
    parser.add_argument("--rows", type=int, default=64, help="rows per hard family")
    parser.add_argument("--families-only", action="store_true", help="only the hard families")
    parser.add_argument(
        "--seed",
        type=int,
        default=None,
        help="hard family k draws from seed S + k (default: 500 + k)",
    )
    args = parser.parse_args()
    torch.set_num_threads(1)
    if args.families_only:
        families(args.rows, args.seed)
        return
    per = args.total // len(TEN_THOUSAND_SHAPES) + 1
    for dtype in (torch.float64, torch.float32):
        x_err = obj_err = 0.0
        feasible = infeasible = flagged = wrongly_solved = 0
        for k, (n, m, me, bounds) in enumerate(TEN_THOUSAND_SHAPES):
            batch = make_batch(per, n, m, me, bounds, seed=1000 + k, dtype=dtype)
            data = (batch.Q, batch.p, batch.G, batch.h, batch.A, batch.b, batch.lb, batch.ub)
            sol = solve_qp(*data)
            for i in range(per):
                row = [t[i].double().numpy() if t is not None else None for t in data]
                x_ref, obj_ref, _ = cvxpy_solve(*row)
                status = int(sol.status[i])
                if batch.kind[i] == "infeasible":
                    infeasible += 1
                    flagged += status == Status.PRIMAL_INFEASIBLE
                    wrongly_solved += status == Status.SOLVED
                    continue
                feasible += 1
                x = sol.x[i].double().numpy()
                x_err = max(x_err, np.abs(x - x_ref).max() / (1.0 + np.abs(x_ref).max()))
                obj = 0.5 * x @ row[0] @ x + row[1] @ x
                obj_err = max(obj_err, abs(obj - obj_ref) / (1.0 + abs(obj_ref)))
        print(
            f"{str(dtype):<14} feasible {feasible}: max relative error x {x_err:.2e}, "
            f"objective {obj_err:.2e}; infeasible {infeasible}: flagged {flagged}, "
            f"reported solved {wrongly_solved}"
        )
    families(args.rows, args.seed)


if __name__ == "__main__":
    main()
