"""Accuracy of ``solve_qp`` (torch backend, ``method="auto"``) against cvxpy/Clarabel on the
10,000 random QPs of the slow test (``tests/qp/test_solve.py::test_ten_thousand_vs_cvxpy``):
n in 2..12, m in 1..64, with and without box bounds and equalities, a quarter infeasible.

Prints, per dtype, the largest relative errors in ``x`` and in the objective over the feasible
rows, and how many infeasible rows were flagged (and reported solved: must be 0).

    python scripts/qp_accuracy.py
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests" / "qp"))
from _problems import TEN_THOUSAND_SHAPES, make_batch  # noqa: E402
from conftest import cvxpy_solve  # noqa: E402

from torchcbf.qp import Status, solve_qp  # noqa: E402


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--total", type=int, default=10_000, help="number of QPs per dtype")
    args = parser.parse_args()
    torch.set_num_threads(1)
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


if __name__ == "__main__":
    main()
