"""Accuracy of ``solve_qp`` (torch backend, ``method="auto"``) against cvxpy/Clarabel on the
10,000 random QPs of the slow test (``tests/qp/test_solve.py::test_ten_thousand_vs_cvxpy``):
n in 2..12, m in 1..64, with and without box bounds and equalities, a quarter infeasible.

Prints, per dtype, the largest relative errors in ``x`` and in the objective over the feasible
rows, and how many infeasible rows were flagged (and reported solved: must be 0).

Then a table of hard families (float64, ``method="auto"``), each against cvxpy/Clarabel:
rotated ill-conditioned ``Q``, rows tight at a known feasible point, duplicated rows, row
scales mixed from 1e-6 to 1e6, linear programs in a box (``Q = 0``) and mid-size problems.
Per family: rows, solved, max scaled error in ``x`` (``|x - x_ref| / (1 + |x_ref|)``, over
rows both solve), false failures (Clarabel solves, we do not), wrong SOLVED (error above
1e-6) and the time per QP of the batch solve (on a loaded machine it varies).

    python scripts/qp_accuracy.py [--families-only] [--rows 64]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests" / "qp"))
from _problems import HARD_FAMILIES, TEN_THOUSAND_SHAPES, hard_family, make_batch  # noqa: E402
from conftest import cvxpy_solve  # noqa: E402

from torchcbf.qp import Status, solve_qp  # noqa: E402


def families(rows: int) -> None:
    """Print the hard-family table."""
    print(
        f"\n{'family':28s} {'rows':>5s} {'solved':>6s} {'max err':>9s} {'false fail':>10s} "
        f"{'wrong SOLVED':>12s} {'us/QP':>8s}"
    )
    for k, name in enumerate(HARD_FAMILIES):
        g = torch.Generator().manual_seed(500 + k)
        Q, p, G, h, lb, ub = hard_family(name, rows, g)
        solve_qp(Q, p, G, h, lb=lb, ub=ub)  # warm up
        t0 = time.perf_counter()
        sol = solve_qp(Q, p, G, h, lb=lb, ub=ub)
        per_qp = (time.perf_counter() - t0) / rows
        err = 0.0
        false_fail = wrong = 0
        for i in range(rows):
            row = [t[i].numpy() if t is not None else None for t in (Q, p, G, h)]
            bnd = [t[i].numpy() if t is not None else None for t in (lb, ub)]
            x_ref, _, st = cvxpy_solve(*row, lb=bnd[0], ub=bnd[1])
            solved = int(sol.status[i]) == Status.SOLVED
            if st != "optimal":
                wrong += solved
                continue
            if not solved:
                false_fail += 1
                continue
            e = np.abs(sol.x[i].numpy() - x_ref).max() / (1.0 + np.abs(x_ref).max())
            err = max(err, e)
            wrong += e > 1e-6
        n_solved = int((sol.status == Status.SOLVED).sum())
        print(
            f"{name:28s} {rows:5d} {n_solved:6d} {err:9.1e} {false_fail:10d} {wrong:12d} "
            f"{per_qp * 1e6:8.1f}"
        )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--total", type=int, default=10_000, help="number of QPs per dtype")
    parser.add_argument("--rows", type=int, default=64, help="rows per hard family")
    parser.add_argument("--families-only", action="store_true", help="only the hard families")
    args = parser.parse_args()
    torch.set_num_threads(1)
    if args.families_only:
        families(args.rows)
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
    families(args.rows)


if __name__ == "__main__":
    main()
