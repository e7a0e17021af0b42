"""Active-set enumeration path of solve_qp: vs cvxpy and the IPM, degenerate problems,
fallback to the IPM, gradients, batching, non-finite rows, float32."""

from __future__ import annotations

import math

import pytest
import torch
from _problems import make_batch
from test_solve import TOL, check_against_cvxpy  # noqa: E402

from torchcbf.qp import Status, solve_qp
from torchcbf.qp._enum import MAX_CANDIDATES_SMALL_BATCH, _table_cpu, num_candidates

F64 = torch.float64
ELIGIBLE = [  # n, m, equalities, box bounds: all take the enumeration path
    (2, 6, 0, True),
    (2, 20, 0, False),
    (3, 8, 0, True),
    (3, 4, 1, True),
    (4, 8, 0, False),
    (4, 6, 1, False),
]


def _args(batch):
    return (batch.Q, batch.p, batch.G, batch.h, batch.A, batch.b, batch.lb, batch.ub)


def test_candidate_count_and_table():
    for M, E, N, pairs in [(8, 0, 4, ()), (14, 0, 3, ((8, 11), (9, 12), (10, 13))), (9, 1, 3, ())]:
        T, valid = _table_cpu(M, E, N, pairs)
        assert T.shape[0] == num_candidates(M, E, N, pairs)
        sets = {tuple(t[v].tolist()) for t, v in zip(T, valid, strict=True)}
        assert len(sets) == T.shape[0]  # no duplicates
        assert all(list(s[:E]) == list(range(E)) for s in sets)  # equalities always in
        assert all(not set(p) <= {i - E for i in s} for s in sets for p in pairs)
    assert num_candidates(8, 0, 4) == 1 + 8 + 28 + 56 + 70
    for n, m, me, bd in ELIGIBLE:
        M = m + (2 * n if bd else 0)
        pairs = tuple((m + j, m + n + j) for j in range(n)) if bd else ()
        assert num_candidates(M, me, n, pairs) <= MAX_CANDIDATES_SMALL_BATCH  # batches of 30


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
@pytest.mark.parametrize("shape", ELIGIBLE)
def test_enumeration_matches_cvxpy_and_ipm(cvx, shape, dtype):
    n, m, me, bounds = shape
    batch = make_batch(30, n, m, me, bounds, seed=100 + 7 * n + m, dtype=dtype)
    sol = solve_qp(*_args(batch), method="enumerate")
    feas = torch.tensor([k != "infeasible" for k in batch.kind])
    assert (sol.iterations[feas] == 0).all()  # the enumeration path solved every feasible row
    check_against_cvxpy(cvx, batch, sol, dtype, range(30))
    ipm = solve_qp(*_args(batch), method="ipm")
    assert torch.equal(ipm.status, sol.status)
    ok = sol.status == Status.SOLVED
    tol = TOL[dtype]
    for f in ("x", "lam", "nu", "lam_lb", "lam_ub"):
        a, b = getattr(sol, f)[ok], getattr(ipm, f)[ok]
        torch.testing.assert_close(a, b, atol=10 * tol, rtol=0)


def test_degenerate_problems(cvx):
    """Duplicated rows, more than n rows active at the optimum, ill-conditioned Q."""
    g = torch.Generator().manual_seed(3)
    rows = []
    # (a) five lines through the optimum x* = (1, 1) of a 2-variable problem
    x_star = torch.tensor([1.0, 1.0], dtype=F64)
    Ga = torch.tensor([[1.0, 0.0], [0.0, 1.0], [1.0, 1.0], [2.0, 1.0], [1.0, 3.0]], dtype=F64)
    rows.append((torch.eye(2, dtype=F64), -torch.tensor([3.0, 4.0], dtype=F64), Ga, Ga @ x_star))
    # (b) duplicated and scaled copies of the active row
    Gb = torch.tensor([[1.0, 2.0], [1.0, 2.0], [2.0, 4.0], [-1.0, 0.5], [0.0, -1.0]], dtype=F64)
    hb = torch.tensor([1.0, 1.0, 2.0, 3.0, 5.0], dtype=F64)
    rows.append((torch.eye(2, dtype=F64), -torch.tensor([2.0, 3.0], dtype=F64), Gb, hb))
    # (c) Q positive definite with condition number 1e7
    U, _ = torch.linalg.qr(torch.randn(2, 2, generator=g, dtype=F64))
    Qc = U @ torch.diag(torch.tensor([1.0, 1e-7], dtype=F64)) @ U.T
    Gc = torch.randn(5, 2, generator=g, dtype=F64)
    rows.append(
        (Qc, torch.randn(2, generator=g, dtype=F64), Gc, torch.rand(5, generator=g).double())
    )
    # (d) a constraint satisfied with equality but with zero multiplier (weakly active)
    Gd = torch.tensor([[1.0, 0.0], [0.0, 1.0], [-1.0, -1.0], [1.0, -1.0], [0.0, -1.0]])
    rows.append(
        (
            torch.eye(2, dtype=F64),
            -torch.tensor([1.0, 0.5]).double(),
            Gd.double(),
            torch.tensor([1.0, 2.0, 5.0, 0.5, 3.0], dtype=F64),
        )
    )
    Q, p, G, h = (torch.stack(t) for t in zip(*rows, strict=True))
    sol = solve_qp(Q, p, G, h, method="enumerate")
    assert (sol.status == Status.SOLVED).all()
    assert (sol.iterations == 0).all()
    for i in range(len(rows)):
        x_ref, obj_ref, st = cvx(*(t[i].numpy() for t in (Q, p, G, h)))
        assert st == "optimal"
        x = sol.x[i].numpy()
        assert abs(x - x_ref).max() <= 1e-6 * (1 + abs(x_ref).max()), (i, x, x_ref)
        # the multipliers are a valid KKT certificate
        stat = Q[i] @ sol.x[i] + p[i] + G[i].T @ sol.lam[i]
        assert stat.abs().max() <= 1e-7 * (1 + p[i].abs().max() + sol.lam[i].abs().max())
        assert (sol.lam[i] >= 0).all()
    torch.testing.assert_close(sol.x[0], x_star)


def test_fallback_rows_use_ipm_and_infeasible_flagged():
    # row 0: Q only positive semidefinite (the Schur complement needs it definite) -> each
    # candidate's own KKT system; row 1: infeasible -> the IPM's certificate; row 2: ordinary
    Q = torch.stack([torch.diag(torch.tensor([1.0, 0.0])), torch.eye(2), torch.eye(2)]).double()
    p = torch.tensor([[0.0, -1.0], [0.0, 0.0], [1.0, 1.0]], dtype=F64)
    G = torch.tensor(
        [[[0.0, 1.0], [1.0, 0.0]], [[1.0, 1.0], [-1.0, -1.0]], [[1.0, 0.0], [0.0, 1.0]]]
    )
    h = torch.tensor([[2.0, 3.0], [-1.0, -1.0], [1.0, -2.0]], dtype=F64)
    sol = solve_qp(Q, p, G.double(), h, method="enumerate")
    assert sol.status.tolist() == [Status.SOLVED, Status.PRIMAL_INFEASIBLE, Status.SOLVED]
    assert sol.iterations[0] == 0 and sol.iterations[2] == 0  # no IPM iterations
    assert float(sol.x[0, 1]) == pytest.approx(2.0, abs=1e-7)
    torch.testing.assert_close(sol.x[2], torch.tensor([-1.0, -2.0], dtype=F64))
    assert (sol.x[1] == 0).all()


def test_more_equality_rows_than_variables_leave_enumeration_no_candidate():
    """k > n consistent equality rows of rank n - 1: enumeration has no candidate set (each
    would hold dependent rows) and hands every row on, without an error."""
    from torchcbf.qp._data import QPData
    from torchcbf.qp._enum import solve_enum

    g = torch.Generator().manual_seed(2)
    B, n, k = 3, 3, 4
    A = torch.randn(B, k, 2, generator=g, dtype=F64) @ torch.randn(B, 2, n, generator=g, dtype=F64)
    x0 = torch.randn(B, n, generator=g, dtype=F64)
    G = torch.randn(B, 5, n, generator=g, dtype=F64)
    P = torch.eye(n, dtype=F64).expand(B, n, n)
    data = QPData(P, torch.ones(B, n, dtype=F64), G, (G @ x0[..., None])[..., 0] + 1.0,
                  A, (A @ x0[..., None])[..., 0])  # fmt: skip
    assert num_candidates(5, k, n) == 0
    out = solve_enum(data, eps=1e-9)
    assert not out.ok.any() and out.x.shape == (B, n) and out.y.shape == (B, k)
    for method in ("enumerate", "auto"):
        sol = solve_qp(P, data.q, G, data.h, A, data.b, method=method)
        assert sol.x.shape == (B, n) and torch.isfinite(sol.x).all()
        assert method == "enumerate" or (sol.status == Status.SOLVED).all()


def test_forced_enumeration_and_method_errors():
    batch = make_batch(10, 5, 7, 0, False, seed=4, frac_infeasible=0.0)
    assert num_candidates(7, 0, 5) > 0
    forced = solve_qp(*_args(batch), method="enumerate")
    ipm = solve_qp(*_args(batch), method="ipm")
    assert (forced.iterations == 0).all() and (ipm.iterations > 0).all()
    torch.testing.assert_close(forced.x, ipm.x, atol=1e-7, rtol=0)
    with pytest.raises(ValueError, match="method"):
        solve_qp(batch.Q, batch.p, method="active")


def test_gradcheck_on_enumeration_path():
    batch = make_batch(3, 3, 4, 1, True, seed=10, frac_infeasible=0.0, frac_inactive=0.34)
    inputs = [t.clone().requires_grad_(True) for t in _args(batch)]
    g = torch.Generator().manual_seed(0)
    wx = torch.randn(3, 3, generator=g, dtype=F64)
    wl = torch.randn(3, 4, generator=g, dtype=F64)

    def f(Q, p, G, h, A, b, lb, ub):
        sol = solve_qp(Q, p, G, h, A, b, lb, ub, method="enumerate")
        assert (sol.status == Status.SOLVED).all() and (sol.iterations == 0).all()
        return (sol.x * wx).sum() + (sol.lam * wl).sum() + sol.nu.sum() + sol.lam_ub.sum()

    assert torch.autograd.gradcheck(f, inputs, eps=1e-6, atol=1e-5, rtol=1e-4)


def test_gradients_equal_ipm_gradients():
    batch = make_batch(16, 4, 8, 0, False, seed=21, frac_infeasible=0.0)
    grads = []
    for method in ("enumerate", "ipm"):
        p = batch.p.clone().requires_grad_(True)
        G = batch.G.clone().requires_grad_(True)
        sol = solve_qp(batch.Q, p, G, batch.h, method=method)
        grads.append(torch.autograd.grad((sol.x**2).sum() + sol.lam.sum(), (p, G)))
    for a, b in zip(*grads, strict=True):
        torch.testing.assert_close(a, b, atol=1e-6, rtol=1e-6)


def test_batch_equals_loop_and_chunks():
    batch = make_batch(12, 3, 5, 1, True, seed=11)
    full = solve_qp(*_args(batch), method="enumerate")
    for i in range(12):
        one = solve_qp(*(t[i] for t in _args(batch)), method="enumerate")
        assert int(one.status) == int(full.status[i])
        torch.testing.assert_close(one.x, full.x[i], atol=1e-12, rtol=0)
        torch.testing.assert_close(one.lam, full.lam[i], atol=1e-12, rtol=0)
    # a batch large enough to be processed in several chunks gives the same rows
    big = make_batch(600, 4, 8, 0, False, seed=12, frac_infeasible=0.0)
    sol = solve_qp(big.Q, big.p, big.G, big.h)
    part = solve_qp(big.Q[:7], big.p[:7], big.G[:7], big.h[:7])
    assert (sol.status == Status.SOLVED).all()
    torch.testing.assert_close(sol.x[:7], part.x, atol=1e-12, rtol=0)
    torch.testing.assert_close(sol.x, big.x_star, atol=1e-7, rtol=0)


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_nonfinite_rows_and_soft_rows(dtype):
    batch = make_batch(6, 2, 4, 0, True, seed=5, frac_infeasible=0.0, dtype=dtype)
    args = list(_args(batch))
    ref = solve_qp(*args)
    args[3] = batch.h.clone()
    args[3][1, 2] = math.nan
    args[0] = batch.Q.clone()
    args[0][4, 0, 1] = math.inf
    sol = solve_qp(*args)
    assert sol.status.tolist() == [0, Status.NON_FINITE, 0, 0, Status.NON_FINITE, 0]
    assert torch.isfinite(sol.x).all() and (sol.x[[1, 4]] == 0).all()
    keep = [0, 2, 3, 5]
    torch.testing.assert_close(sol.x[keep], ref.x[keep])
    # soft rows (2 + 4 variables, 4 + 4 + 4 rows) take the enumeration path too
    soft = torch.full((6, 4), 3.0, dtype=dtype)
    h = batch.h - 1.0
    s_enum = solve_qp(
        batch.Q, batch.p, batch.G, h, lb=batch.lb, ub=batch.ub, soft=soft, method="enumerate"
    )
    s_ipm = solve_qp(
        batch.Q, batch.p, batch.G, h, lb=batch.lb, ub=batch.ub, soft=soft, method="ipm"
    )
    assert (s_enum.status == 0).all() and (s_enum.iterations == 0).all()
    tol = TOL[dtype]
    torch.testing.assert_close(s_enum.x, s_ipm.x, atol=10 * tol, rtol=0)
    torch.testing.assert_close(s_enum.slack, s_ipm.slack, atol=10 * tol, rtol=0)


def test_rows_of_very_different_scales_are_each_judged_on_their_own():
    """Each row's residual is judged on its own scale: a point violating the small row 1 by
    0.85 of its norm is not reported solved."""
    Q = torch.tensor([[114882.83952500708, 10420.946323314654],
                      [10420.946323314654, 946.2853707984577]], dtype=F64)  # fmt: skip
    p = torch.tensor([-2.4512854745807955, -1.574333298559233], dtype=F64)
    G = torch.tensor([[-8.193461267432959, 0.44462893090782063],
                      [9.302038310982304e-08, 1.6775708989503506e-07],
                      [2367165.5074630063, -1289992.5954979705]], dtype=F64)  # fmt: skip
    h = torch.tensor([3.6782018825344354, 5.0435662841192424e-08, -1230044.5251119188], dtype=F64)
    sol = solve_qp(Q, p, G, h, method="enumerate")
    ref = solve_qp(Q, p, G, h, method="ipm")
    assert int(sol.status) == Status.SOLVED == int(ref.status)
    assert ((G @ sol.x - h) / G.norm(dim=-1)).max() < 1e-9
    torch.testing.assert_close(sol.x, ref.x, atol=1e-9, rtol=1e-9)


def test_explicit_enumeration_refuses_too_many_candidate_sets():
    Q = torch.eye(10, dtype=torch.float64)
    p = torch.ones(10, dtype=torch.float64)
    G = torch.ones(50, 10, dtype=torch.float64)
    h = torch.ones(50, dtype=torch.float64)
    with pytest.raises(ValueError, match=r"candidate active sets \(N=10 variables, M=50"):
        solve_qp(Q, p, G, h, method="enumerate")
    # the default method solves the same problem
    assert int(solve_qp(Q, p, G, h).status) == Status.SOLVED


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_enumeration_takes_the_minimiser_not_a_saddle_where_q_is_indefinite(dtype, cvx):
    """``Q = vv'`` rounded to float32 has an eigenvalue of -7e-9: the stationary point of the
    empty active set (far out, objective +3.4e6) is a KKT point too, a saddle. Enumeration
    takes the least objective among its KKT points, the minimiser's (Clarabel's, -9.82)."""
    Q = torch.tensor([[2.4199635982513428, 0.4243291914463043],
                      [0.4243291914463043, 0.07440411299467087]])  # fmt: skip
    assert torch.linalg.eigvalsh(Q.double())[0] < 0
    p = torch.tensor([-7.168409824371338, -1.4811828136444092])
    G = torch.tensor([[-0.012977631762623787, 1.6278356313705444],
                      [3.0782575607299805, 0.9077008962631226],
                      [0.6727232933044434, 1.4134207963943481]])  # fmt: skip
    h = torch.tensor([1.064685344696045, 6.616869926452637, 1.065529465675354])
    sol = solve_qp(*(t.to(dtype) for t in (Q, p, G, h)), method="enumerate")
    assert int(sol.status) == Status.SOLVED
    x = sol.x.double()
    objective = float(0.5 * x @ Q.double() @ x + p.double() @ x)
    _, ref, _ = cvx(*(t.double().numpy() for t in (Q, p, G, h)))
    assert abs(objective - ref) <= 1e-4 * abs(ref), (objective, ref)


@pytest.mark.parametrize("seed", range(4))
def test_an_lp_vertex_of_nearly_parallel_rows_is_solved_on_its_feasible_row(seed):
    """An LP whose vertex is cut by copies of one row, a few 1e-10 apart (and a multiple of
    it): the candidates of the copies are a rounding apart in objective, the lowest one
    slightly infeasible. The minimiser is the least ratio ``h_i / g_i``, solved."""
    gen = torch.Generator().manual_seed(seed)
    g = 0.5 + torch.rand(1, generator=gen, dtype=F64)
    vertex = 1.0 + 3.0 * torch.rand(1, generator=gen, dtype=F64)
    scale = torch.tensor([1.0, 1.0, 1.0, 2.5, 1.0, 1.0], dtype=F64)
    shift = torch.tensor([7e-10, 0.0, 7e-10, 0.0, 0.0, 7e-10], dtype=F64)
    G = (scale * g).view(6, 1)
    h = scale * g * vertex * (1.0 + shift)
    p = -(0.2 + torch.rand(1, generator=gen, dtype=F64))
    sol = solve_qp(torch.zeros(1, 1, dtype=F64), p, G, h)
    assert int(sol.status) == Status.SOLVED, sol.method_names()
    want = (h / G.squeeze(-1)).min()  # to the solver's eps (1e-9 relative)
    torch.testing.assert_close(sol.x.squeeze(), want, atol=1e-9, rtol=1e-9)


def test_a_feasible_point_of_a_zero_objective_is_a_kkt_point_whatever_the_noise():
    """``P = 0``, ``q = 0``: every feasible point is a minimiser, and multipliers computed as
    rounding noise (1e-27) leave a stationarity residual of the same noise, which is no
    reason to refuse the point (the certificate enumeration's answers pass)."""
    from torchcbf.qp._data import QPData
    from torchcbf.qp._kkt import kkt_point

    G = torch.tensor([[-0.97], [-2.41], [-1.28], [0.0058], [-0.97]], dtype=F64)
    x = torch.tensor([[0.4]], dtype=F64)
    h = (G @ x.T).squeeze(-1)  # rows 0, 1 and 4 tight at x, the others loose
    h[2:4] += 0.5
    zero = torch.zeros(1, 0, 1, dtype=F64)
    data = QPData(zero[:, :1, :1].new_zeros(1, 1, 1), zero.new_zeros(1, 1), G[None], h[None],
                  zero, zero[..., 0])  # fmt: skip
    y = torch.zeros(1, 0, dtype=F64)
    for noise in (0.0, 7.6e-28, 1e-25):
        z = torch.tensor([[0.0, noise, 0.0, 0.0, 0.0]], dtype=F64)
        assert bool(kkt_point(data, x, z, y)), noise
    # a multiplier of real size on a loose row is still refused
    z = torch.tensor([[0.0, 0.0, 0.3, 0.0, 0.0]], dtype=F64)
    assert not bool(kkt_point(data, x, z, y))


@pytest.mark.parametrize(("tiny", "pull"), [(1e-300, -1e10), (1e-200, -1e150)])
def test_rows_whose_every_candidate_overflows_are_enumerated_on_their_own_systems(tiny, pull):
    """``P`` of 1e-300 along a direction pulled by 1e10: the unconstrained minimiser
    overflows and no Schur candidate is solvable; each candidate's own KKT system answers
    (the rows went to the interior point method instead)."""
    f64 = torch.float64
    P = torch.diag(torch.tensor([1.0, tiny], dtype=f64))
    q = torch.tensor([0.5, pull], dtype=f64)
    G = torch.tensor([[0.3, 1.0], [1.0, 0.2]], dtype=f64)
    h = torch.tensor([1.0, 2.0], dtype=f64)
    box = torch.ones(2, dtype=f64)
    sol = solve_qp(P, q, G, h, lb=-box, ub=box, method="enumerate")
    assert int(sol.status) == Status.SOLVED and sol.method_names() == ["enumerate"]
    torch.testing.assert_close(sol.x, torch.tensor([-0.5, 1.0], dtype=f64))
