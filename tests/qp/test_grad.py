"""Gradients of solve_qp: gradcheck in float64 for every input, closed-form agreement."""

from __future__ import annotations

import math

import pytest
import torch
from _problems import make_batch

from torchcbf.qp import Status, solve_qp

F64 = torch.float64


def _problem(seed: int, B: int = 3, n: int = 3, m: int = 4, me: int = 1):
    batch = make_batch(B, n, m, me, True, seed=seed, frac_infeasible=0.0, frac_inactive=0.34)
    return batch


def _loss_weights(B: int, n: int, m: int, seed: int):
    g = torch.Generator().manual_seed(seed)
    return (torch.randn(B, n, generator=g, dtype=F64), torch.randn(B, m, generator=g, dtype=F64))


@pytest.mark.parametrize("backend", ["torch", "proxsuite"])
def test_gradcheck_every_input(backend):
    batch = _problem(10)
    kinds = set(batch.kind)
    assert kinds == {"active", "inactive"}
    inputs = [
        t.clone().requires_grad_(True)
        for t in (batch.Q, batch.p, batch.G, batch.h, batch.A, batch.b, batch.lb, batch.ub)
    ]
    wx, wl = _loss_weights(3, 3, 4, 0)

    def f(Q, p, G, h, A, b, lb, ub):
        sol = solve_qp(Q, p, G, h, A, b, lb, ub, backend=backend)
        assert (sol.status == Status.SOLVED).all()
        return (sol.x * wx).sum() + (sol.lam * wl).sum() + sol.nu.sum() + sol.lam_ub.sum()

    assert torch.autograd.gradcheck(f, inputs, eps=1e-6, atol=1e-5, rtol=1e-4)


def test_gradcheck_box_active_and_soft_weights():
    # box-active problem: unconstrained optimum outside the box
    Q = torch.tensor([[2.0, 0.3], [0.3, 1.0]], dtype=F64)
    p = torch.tensor([-4.0, 1.5], dtype=F64, requires_grad=True)
    lb = torch.tensor([-1.0, -0.5], dtype=F64, requires_grad=True)
    ub = torch.tensor([1.0, 0.5], dtype=F64, requires_grad=True)
    G = torch.tensor([[1.0, 1.0], [-1.0, 2.0]], dtype=F64, requires_grad=True)
    h = torch.tensor([-0.2, 5.0], dtype=F64, requires_grad=True)
    soft = torch.tensor([0.7, 2.0], dtype=F64, requires_grad=True)

    def f(p, lb, ub, G, h, soft):
        sol = solve_qp(Q, p, G, h, lb=lb, ub=ub, soft=soft)
        return torch.cat((sol.x, sol.slack, sol.lam_lb, sol.lam_ub))

    sol = solve_qp(Q, p, G, h, lb=lb, ub=ub, soft=soft)
    assert int(sol.status) == Status.SOLVED
    assert float(sol.slack[0].detach()) > 0.05  # the soft row is violated: its slack is active
    assert float(sol.lam_ub[0].detach()) > 0.05  # and the box is active
    assert torch.autograd.gradcheck(f, (p, lb, ub, G, h, soft), eps=1e-6, atol=1e-5)


def test_closed_form_gradient_matches_formula(kernel):
    """Without the C kernel the closed form runs; with it (CPU) the dual method does."""
    g = torch.Generator().manual_seed(1)
    L = torch.randn(20, 3, 3, generator=g, dtype=F64)
    Q = (L @ L.mT + torch.eye(3, dtype=F64)).requires_grad_(True)
    p = torch.randn(20, 3, generator=g, dtype=F64, requires_grad=True)
    G = torch.randn(20, 1, 3, generator=g, dtype=F64, requires_grad=True)
    h = torch.randn(20, 1, generator=g, dtype=F64, requires_grad=True)
    w = torch.randn(20, 3, generator=g, dtype=F64)

    sol = solve_qp(Q, p, G, h)
    assert (sol.iterations == 0).all() != kernel  # the dual method counts its steps
    grads = torch.autograd.grad((sol.x * w).sum(), (Q, p, G, h))

    # the projection formula written out in torch, differentiated by autograd
    Qs = 0.5 * (Q + Q.mT)
    xu = -torch.linalg.solve(Qs, p)
    gv = G[:, 0]
    Qg = torch.linalg.solve(Qs, gv)
    lam = ((gv * xu).sum(-1) - h[:, 0]).clamp_min(0.0) / (gv * Qg).sum(-1)
    x_ref = xu - lam.unsqueeze(-1) * Qg
    torch.testing.assert_close(sol.x, x_ref)
    ref = torch.autograd.grad((x_ref * w).sum(), (Q, p, G, h))
    active = lam > 0
    assert active.any() and (~active).any()
    for a, r in zip(grads, ref, strict=True):
        torch.testing.assert_close(a, r, atol=1e-9, rtol=1e-7)


def test_gradient_matches_finite_differences_through_ipm():
    batch = _problem(8, B=4, n=4, m=6, me=0)
    h = batch.h.clone().requires_grad_(True)
    sol = solve_qp(batch.Q, batch.p, batch.G, h, lb=batch.lb, ub=batch.ub)
    (gh,) = torch.autograd.grad(sol.x.sum(), h)
    step = 1e-6
    fd = torch.zeros_like(h)
    for j in range(h.shape[1]):
        hp, hm = batch.h.clone(), batch.h.clone()
        hp[:, j] += step
        hm[:, j] -= step
        xp = solve_qp(batch.Q, batch.p, batch.G, hp, lb=batch.lb, ub=batch.ub).x.sum(-1)
        xm = solve_qp(batch.Q, batch.p, batch.G, hm, lb=batch.lb, ub=batch.ub).x.sum(-1)
        fd[:, j] = (xp - xm) / (2 * step)
    torch.testing.assert_close(gh, fd, atol=1e-6, rtol=1e-5)


def test_unsolved_rows_get_zero_gradient_and_float32():
    batch = make_batch(8, 3, 4, 0, False, seed=12, frac_infeasible=0.5, dtype=torch.float32)
    p = batch.p.clone().requires_grad_(True)
    h = batch.h.clone()
    h[0, 0] = float("nan")
    h = h.requires_grad_(True)
    sol = solve_qp(batch.Q, p, batch.G, h)
    assert int(sol.status[0]) == Status.NON_FINITE
    (gp, gh) = torch.autograd.grad(sol.x.sum(), (p, h))
    assert torch.isfinite(gp).all() and torch.isfinite(gh).all()
    bad = sol.status != Status.SOLVED
    assert bad.sum() >= 2
    assert (gp[bad] == 0).all() and (gh[bad] == 0).all()
    assert (gp[~bad] != 0).any()
    # float32 gradients agree with the float64 ones
    p64 = batch.p.double().requires_grad_(True)
    sol64 = solve_qp(batch.Q.double(), p64, batch.G.double(), h.detach().double())
    (g64,) = torch.autograd.grad(sol64.x.sum(), p64)
    torch.testing.assert_close(gp.double(), g64, atol=1e-3, rtol=1e-3)


def _degenerate_faces(B: int, n: int, seed: int):
    """QPs whose solution lies on a face cut by k = 2 independent rows a1, a2 that are tight
    with positive multipliers, plus the tight redundant row a1 + a2; the objective's gradient
    at the solution is carried by the redundant row alone, so a method may support its
    multipliers on that row only. Two inactive rows. The solution moves smoothly with p (it
    stays on the face), so dx/dp is the projection onto the face. Every datum is exact in
    float32 (rows and the point on a grid of quarters), so both dtypes pose the same problem."""
    g = torch.Generator().manual_seed(seed)

    def quarters(*shape):
        return torch.randint(-8, 9, shape, generator=g).to(F64) / 4

    L = torch.randn(B, n, n, generator=g, dtype=F64)
    Q = (L @ L.mT / n + 0.2 * torch.eye(n, dtype=F64)).float().double()
    x_face = quarters(B, n)
    a = quarters(B, 2, n)
    a[:, :, 0] = torch.tensor([1.0, -1.0], dtype=F64)  # independent rows
    a[:, 1, 1] = a[:, 0, 1] + 1.0
    G = torch.cat([a, a.sum(1, keepdim=True), quarters(B, 2, n)], 1)  # [B, 5, n]
    h = (G @ x_face.unsqueeze(-1)).squeeze(-1)
    h[:, 3:] += 2.0 + G[:, 3:].abs().sum(-1) * 4  # inactive near the face point
    p = -(Q @ x_face.unsqueeze(-1)).squeeze(-1) - 0.75 * G[:, 2]
    return Q, p.float().double(), G, h


@pytest.mark.parametrize("method", ["auto", "active_set", "enumerate", "ipm"])
@pytest.mark.parametrize("n", [2, 3, 4])
def test_gradient_at_a_degenerate_face_matches_finite_differences(kernel, method, n):
    B = 6
    Q, p, G, h = _degenerate_faces(B, n, seed=n)
    with torch.no_grad():
        sol = solve_qp(Q, p, G, h, method=method)
    assert bool((sol.status == Status.SOLVED).all())
    slack = h - (G @ sol.x.unsqueeze(-1)).squeeze(-1)
    assert slack[:, :3].abs().max() <= 1e-9 and slack[:, 3:].min() >= 1.0  # on the face
    fd = torch.zeros(B, n, n, dtype=F64)
    step = 1e-6
    with torch.no_grad():
        for j in range(n):
            dp = torch.zeros(n, dtype=F64)
            dp[j] = step
            up = solve_qp(Q, p + dp, G, h, method=method).x
            down = solve_qp(Q, p - dp, G, h, method=method).x
            fd[:, :, j] = (up - down) / (2 * step)
    for dtype in (F64, torch.float32):
        pg = p.to(dtype).requires_grad_()
        out = solve_qp(Q.to(dtype), pg, G.to(dtype), h.to(dtype), method=method)
        jac = torch.stack(
            [torch.autograd.grad(out.x[:, i].sum(), pg, retain_graph=True)[0] for i in range(n)], 1
        )  # [B, n (x), n (p)]
        tol = 1e-6 if dtype == F64 else 1e-4
        torch.testing.assert_close(jac.to(F64), fd, atol=tol, rtol=tol)


def test_gradient_at_a_degenerate_vertex_is_zero(kernel):
    """x1 <= 1, x2 <= 1, x1 + x2 <= 2 all tight at x* = (1, 1) with p = (-3, -3): x* stays
    put under any small change of p, whatever multipliers a method picks."""
    for method in ("auto", "active_set", "enumerate", "ipm"):
        p = torch.tensor([-3.0, -3.0], dtype=F64, requires_grad=True)
        G = torch.tensor([[1.0, 0.0], [0.0, 1.0], [1.0, 1.0]], dtype=F64)
        h = torch.tensor([1.0, 1.0, 2.0], dtype=F64)
        sol = solve_qp(torch.eye(2, dtype=F64), p, G, h, method=method)
        (grad,) = torch.autograd.grad(sol.x @ torch.tensor([1.0, -2.0], dtype=F64), p)
        assert grad.abs().max() <= 1e-12, method


@pytest.mark.parametrize("method", ["auto", "enumerate", "ipm"])
@pytest.mark.parametrize("q_depends", [False, True])
@pytest.mark.parametrize("loss", ["cubic", "linear"])
def test_a_second_derivative_through_the_qp_raises(method, q_depends, loss):
    """The backward reuses the forward's factor: a second derivative would be wrong, so
    backpropagating through a first derivative taken with create_graph=True raises, also
    for a loss linear in ``x`` (whose incoming gradient carries no graph); the first
    derivative itself is the one taken without create_graph, and h's inf rows stay out."""
    f64 = torch.float64
    p = torch.tensor([-3.0, -1.0], dtype=f64, requires_grad=True)
    Q = torch.tensor([[2.0, 0.3], [0.3, 1.0]], dtype=f64)
    if q_depends:
        Q = Q + torch.diag(p.square())
    G = torch.tensor([[1.0, 1.0], [1.0, -1.0]], dtype=f64)
    h = torch.tensor([10.0, math.inf], dtype=f64, requires_grad=True)
    x = solve_qp(Q, p, G, h, method=method).x
    value = (x**3).sum() if loss == "cubic" else x.sum()
    (g,) = torch.autograd.grad(value, p, create_graph=True)
    (plain,) = torch.autograd.grad(value, p, retain_graph=True)
    torch.testing.assert_close(g.detach(), plain, atol=0.0, rtol=0.0)
    with pytest.raises(RuntimeError, match="first derivatives only"):
        g.square().sum().backward()


@pytest.mark.parametrize("method", ["auto", "enumerate", "ipm"])
def test_multipliers_of_dependent_tight_rows_get_the_solvers_selections_derivative(method) -> None:
    """A variable pinned by ``lb = ub``, a zero row and an inequality repeating an equality
    leave several multiplier vectors valid; the adjoint moves the strictly active rows'
    multipliers (the selection the solver returned), not ``1 / delta`` (2e11)."""
    f64 = torch.float64
    Q, p = torch.eye(2, dtype=f64), torch.tensor([-1.0, -1.0], dtype=f64)
    c = torch.tensor(0.3, dtype=f64, requires_grad=True)  # lb1 = ub1 = c: lam_ub1 = 1 - c
    lb = torch.stack([c, torch.tensor(-5.0, dtype=f64)])
    ub = torch.stack([c, torch.tensor(5.0, dtype=f64)])
    sol = solve_qp(Q, p, lb=lb, ub=ub, method=method)
    (grad,) = torch.autograd.grad(sol.lam_ub[0], (c,))
    ub_alone = torch.tensor([0.3, 5.0], dtype=f64, requires_grad=True)
    pinned = solve_qp(Q, p, lb=torch.tensor([0.3, -5.0], dtype=f64), ub=ub_alone, method=method)
    (grad_ub,) = torch.autograd.grad(pinned.lam_ub[0], (ub_alone,))
    assert float(grad_ub[0]) == pytest.approx(-1.0, abs=1e-4)  # lam_ub = 1 - ub where feasible
    assert float(sol.lam_ub[0]) == pytest.approx(0.7) and float(grad) == pytest.approx(
        -1.0, abs=1e-4
    )
    # a zero row 0'x <= 0: its multiplier stays 0 whatever h
    h = torch.tensor([0.5, 0.0], dtype=f64, requires_grad=True)
    G = torch.tensor([[1.0, 0.0], [0.0, 0.0]], dtype=f64)
    (grad,) = torch.autograd.grad(solve_qp(Q, p, G, h, method=method).lam.sum(), (h,))
    torch.testing.assert_close(grad, torch.tensor([-1.0, 0.0], dtype=f64), atol=1e-4, rtol=0)
    # x1 <= c repeating x1 = c: the multipliers sum to 1 - c, in the solver's proportions
    # (all on the equality, or split by the interior point method)
    c = torch.tensor(0.5, dtype=f64, requires_grad=True)
    h3 = torch.stack([c, torch.tensor(5.0, dtype=f64)])
    A = torch.tensor([[1.0, 0.0]], dtype=f64)
    sol = solve_qp(Q, p, torch.eye(2, dtype=f64), h3, A, c.reshape(1), method=method)
    (grad,) = torch.autograd.grad(sol.nu.sum(), (c,))
    assert float(grad) == pytest.approx(-float(sol.nu[0]) / 0.5, abs=1e-4)


@pytest.mark.parametrize("method", ["auto", "enumerate", "ipm"])
@pytest.mark.parametrize("angle", [1e-2, 1e-3, 1e-4])
def test_a_weak_row_nearly_parallel_to_an_active_one_keeps_its_exact_gradient(method, angle):
    """``x1 <= 0.5`` active and ``x1 + e x2 <= 0.5 + e`` tight with a zero multiplier: the
    rows are independent however small ``e``, and ``dx2/dh2 = 1/e`` exactly."""
    f64 = torch.float64
    G = torch.tensor([[1.0, 0.0], [1.0, angle]], dtype=f64)
    h = torch.tensor([0.5, 0.5 + angle], dtype=f64, requires_grad=True)
    sol = solve_qp(
        torch.eye(2, dtype=f64), torch.tensor([-1.0, -1.0], dtype=f64), G, h, method=method
    )
    (grad,) = torch.autograd.grad(sol.x[1], (h,))
    torch.testing.assert_close(
        grad, torch.tensor([-1.0, 1.0], dtype=f64) / angle, rtol=1e-8, atol=0
    )


@pytest.mark.parametrize("method", ["auto", "ipm"])
def test_rows_not_solved_report_no_slack_and_pass_it_no_gradient(method) -> None:
    """Hard rows that contradict each other beside a soft row: the row is infeasible, its
    ``x`` answers no problem, so its slack is 0 with no gradient (a loss on the slack of a
    batch is not pushed by its failed rows)."""
    f64 = torch.float64
    G = torch.tensor([[1.0, 0.0], [-1.0, 0.0], [0.0, 1.0]], dtype=f64)
    h = torch.tensor([[-1.0, -1.0, -2.0], [1.0, 1.0, -2.0]], dtype=f64, requires_grad=True)
    soft = torch.tensor([0.0, 0.0, 0.5], dtype=f64)  # row 2 soft: x1 = -1.5 > -2
    sol = solve_qp(torch.eye(2, dtype=f64), torch.ones(2, dtype=f64), G, h, soft=soft,
                   method=method)  # fmt: skip
    assert sol.status.tolist() == [Status.PRIMAL_INFEASIBLE, Status.SOLVED]
    assert sol.slack[0].tolist() == [0.0, 0.0, 0.0] and float(sol.slack[1, 2]) > 0
    (grad,) = torch.autograd.grad(sol.slack.sum(), h)
    assert grad[0].tolist() == [0.0, 0.0, 0.0] and float(grad[1, 2]) != 0.0


def test_forward_mode_and_batched_transforms_are_refused_by_name() -> None:
    """Reverse mode only: a forward-mode tangent would be dropped, a vmapped solve or a
    batched backward would fail deep inside; each raises at the boundary, naming it."""
    import torch.autograd.forward_ad as fwAD

    f64 = torch.float64
    Q, G, h = torch.eye(2, dtype=f64), torch.ones(1, 2, dtype=f64), torch.ones(1, dtype=f64)
    p = torch.tensor([-1.0, -1.0], dtype=f64)
    for B in (1, 40):  # the small C path and the general one
        with fwAD.dual_level(), pytest.raises(NotImplementedError, match="forward-mode AD"):
            solve_qp(Q, fwAD.make_dual(p.repeat(B, 1), torch.ones(B, 2, dtype=f64)), G, h)
    with pytest.raises(NotImplementedError, match="torch.func transforms"):
        torch.func.vmap(lambda q: solve_qp(Q, q, G, h).x)(p.expand(3, 2))
    q = p.clone().requires_grad_()
    x = solve_qp(Q, q, G, h).x
    with pytest.raises(NotImplementedError, match="batched gradients"):
        torch.autograd.grad(x, q, torch.eye(2, dtype=f64), is_grads_batched=True)
    jac = torch.autograd.functional.jacobian(lambda v: solve_qp(Q, v, G, h).x, p)
    torch.testing.assert_close(jac, torch.tensor([[-0.5, 0.5], [0.5, -0.5]], dtype=f64))
