"""Scenario B's elastic filter QP (slack s >= 0 with no upper bound, weights 1, 1e-3 and
~5e5) is SOLVED on every method, dtype and batch size, on states where its slack is large."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from torchcbf.filters import FilterStatus
from torchcbf.qp import Status, solve_qp
from torchcbf.scenarios.unicycle_mppi_cbf import mppi_cbf

#: the QPs of four states (x, y, v, theta; u_nom) of scenario B's default filter, as
#: ``SafetyFilter(..., backend="torch")`` hands them to ``solve_qp``: controls (a, omega)
#: in [-40, 40], the shared slack s in [0, inf); the first three in float32, the last in
#: float64 (its data as float64 numbers)
STATES = (
    (
        (-0.7786715626716614, 5.009431838989258, -0.39316344261169434, -2.102438449859619),
        (-13.70230770111084, -0.17875726521015167),
        (1.0, 0.0010000000474974513, 501000.53125),
        (13.70230770111084, 0.00017875726916827261, 501000.53125),
        (
            (-0.6756170988082886, -0.7372527122497559),
            (-0.7506601810455322, -0.660688579082489),
            (-0.6416013836860657, -0.7670382261276245),
            (0.9776404500007629, -0.21028368175029755),
            (0.9619033932685852, -0.273389607667923),
        ),
        (1975.7841796875, 3516.840087890625, -3252.140380859375, 2133.817138671875,
         3599.51171875),
    ),
    (
        (4.036750316619873, 4.905707836151123, -0.14285452663898468, 0.33462148904800415),
        (-0.7384254932403564, 51.08575439453125),
        (1.0, 0.0010000000474974513, 501000.53125),
        (0.7384254932403564, -0.05108575522899628, 501000.53125),
        (
            (-0.9994475841522217, -0.03323467820882797),
            (-0.999983012676239, 0.0058337426744401455),
            (0.06371129304170609, -0.997968316078186),
            (-0.9950816035270691, 0.09905868023633957),
            (-0.9784210324287415, 0.20662125945091248),
        ),
        (1604.8955078125, 585.6688232421875, -6569.89990234375, 3583.258056640625,
         5696.244140625),
    ),
    (
        (2.9115610122680664, 4.957051753997803, 0.479733943939209, -2.2955334186553955),
        (15.626214027404785, 30.618804931640625),
        (1.0, 0.0010000000474974513, 501000.53125),
        (-15.626214027404785, -0.030618807300925255, 501000.53125),
        (
            (0.9333336353302002, -0.3590102195739746),
            (0.8388045430183411, 0.5444327592849731),
            (-0.7707511782646179, -0.6371363401412964),
            (0.9944388270378113, 0.10531631857156754),
            (0.9599226117134094, 0.280265212059021),
        ),
        (1226.1719970703125, 473.0735778808594, -4145.17822265625, 2590.391845703125,
         3455.688720703125),
    ),
    (
        (4.150567211654581, 4.980525023492691, 0.08459190898331925, -2.208209638482617),
        (-0.20877668818651537, -5.410129810045028),
        (1.0, 0.001, 501000.49999999994),
        (0.20877668818651537, 0.005410129810045028, 501000.49999999994),
        (
            (0.9957723146804652, -0.09185585074402494),
            (0.9984406116046534, -0.05582423397168826),
            (0.7995825420790019, -0.6005562075297207),
            (0.9999997567833597, 0.000697447647673569),
            (0.9994541868454321, 0.033035259907199375),
        ),
        (2404.3290672958615, 794.2380871808703, -17319.51028262873, 3023.8679761174126,
         3560.550148314126),
    ),
)  # fmt: skip


def _qp(dtype: torch.dtype):
    """``(Q, p, G, h, lb, ub)`` of the four QPs, ``[4, ...]``."""
    Q = torch.diag_embed(torch.tensor([s[2] for s in STATES], dtype=torch.float64))
    p = torch.tensor([s[3] for s in STATES], dtype=torch.float64)
    Gu = torch.tensor([s[4] for s in STATES], dtype=torch.float64)
    G = torch.cat((Gu, -torch.ones(*Gu.shape[:2], 1, dtype=torch.float64)), -1)
    h = torch.tensor([s[5] for s in STATES], dtype=torch.float64)
    lb = torch.tensor([-40.0, -40.0, 0.0], dtype=torch.float64).expand(len(STATES), 3)
    ub = torch.tensor([40.0, 40.0, torch.inf], dtype=torch.float64).expand(len(STATES), 3)
    return tuple(t.to(dtype) for t in (Q, p, G, h, lb, ub))


def _reference(Q, p, G, h, lb, ub) -> np.ndarray:
    """Clarabel's minimisers (objective scaled by ``1 / max|Q|``, which it needs here)."""
    import cvxpy as cp

    out = []
    for i in range(Q.shape[0]):
        Qi, pi, Gi, hi, lbi, ubi = (t[i].double().numpy() for t in (Q, p, G, h, lb, ub))
        c = 1.0 / np.abs(Qi).max()
        x = cp.Variable(3)
        cons = [Gi @ x <= hi, x >= lbi, x[:2] <= ubi[:2]]
        obj = 0.5 * cp.quad_form(x, cp.psd_wrap(c * Qi)) + (c * pi) @ x
        cp.Problem(cp.Minimize(obj), cons).solve(solver="CLARABEL")
        out.append(x.value)
    return np.stack(out)


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32], ids=["float64", "float32"])
def test_filter_qp_solved_every_method_and_batch(dtype: torch.dtype) -> None:
    Q, p, G, h, lb, ub = _qp(dtype)
    ref = _reference(Q, p, G, h, lb, ub)
    k = len(STATES)
    for method in ("auto", "active_set", "enumerate", "ipm"):
        for copies in (1, 16, 17):  # 4, 64 and 68 rows: both sides of the small-batch paths
            data = [t.repeat(copies, *(1,) * (t.dim() - 1)) for t in (Q, p, G, h, lb, ub)]
            sol = solve_qp(*data[:4], lb=data[4], ub=data[5], method=method)
            where = f"{method}, {copies * k} rows"
            assert (sol.status == Status.SOLVED).all(), f"{where}: {sol.status.tolist()}"
            x = sol.x.double().numpy().reshape(copies, k, 3)
            # the slack (~1e4) is fixed by one row; the controls sit at their bounds
            err = np.abs(x - ref).max() / (1.0 + np.abs(ref).max())
            assert err <= (1e-6 if dtype == torch.float32 else 1e-8), f"{where}: {err:.2e}"


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32], ids=["float64", "float32"])
def test_scenario_filter_general_path_solves(dtype: torch.dtype) -> None:
    filt = mppi_cbf(method="mppi_scbf", num_seeds=1, num_samples=16, horizon=4,
                    dtype=dtype).safety_filter  # fmt: skip
    filt.backend = "torch"
    x = torch.tensor([s[0] for s in STATES], dtype=dtype)
    u = torch.tensor([s[1] for s in STATES], dtype=dtype)
    with torch.no_grad():
        out = filt(x, u)
    assert out.path.startswith("torch"), out.path
    assert (out.qp_status == Status.SOLVED).all(), out.qp_status.tolist()
    assert (out.status == FilterStatus.RELAXED).all(), out.status.tolist()
