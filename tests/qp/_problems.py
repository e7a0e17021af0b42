"""Random QP families with known solutions or known infeasibility, and the hard families of
scripts/qp_accuracy.py (test helpers)."""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor


@dataclass
class Batch:
    """One batch of QPs of a fixed shape; ``kind[i]`` is 'active', 'inactive' or 'infeasible'."""

    Q: Tensor
    p: Tensor
    G: Tensor
    h: Tensor
    A: Tensor | None
    b: Tensor | None
    lb: Tensor | None
    ub: Tensor | None
    x_star: Tensor
    kind: list[str]


def make_batch(
    B: int,
    n: int,
    m: int,
    me: int = 0,
    bounds: bool = False,
    *,
    seed: int = 0,
    frac_infeasible: float = 0.25,
    frac_inactive: float = 0.25,
    dtype: torch.dtype = torch.float64,
) -> Batch:
    """Build ``B`` QPs ``[n vars, m inequalities, me equalities, optional box]``.

    Feasible rows are built from a chosen optimum ``x*`` and multipliers (strictly positive on
    the active set, so ``x*`` is the unique solution); infeasible rows contain a contradiction
    (two opposite halfspaces, a halfspace against the box, or one against an equality).
    """
    g = torch.Generator().manual_seed(seed)
    f64 = torch.float64
    L = torch.randn(B, n, n, generator=g, dtype=f64)
    Q = L @ L.mT / n + 0.1 * torch.eye(n, dtype=f64)
    x = torch.randn(B, n, generator=g, dtype=f64)
    G = torch.randn(B, m, n, generator=g, dtype=f64)
    A = torch.randn(B, me, n, generator=g, dtype=f64)
    u = torch.rand(B, generator=g, dtype=f64)
    kinds = []
    for i in range(B):
        if u[i] < frac_infeasible:
            kinds.append("infeasible")
        elif u[i] < frac_infeasible + frac_inactive:
            kinds.append("inactive")
        else:
            kinds.append("active")
    lam = torch.zeros(B, m, dtype=f64)
    gap = 0.1 + torch.rand(B, m, generator=g, dtype=f64)
    h = torch.einsum("bmn,bn->bm", G, x) + gap
    lb = x - 0.1 - torch.rand(B, n, generator=g, dtype=f64) if bounds else None
    ub = x + 0.1 + torch.rand(B, n, generator=g, dtype=f64) if bounds else None
    mu_ub = torch.zeros(B, n, dtype=f64)
    room = n - me
    for i, kind in enumerate(kinds):
        if kind != "active" or room <= 0:
            continue
        k = int(torch.randint(1, min(m, room) + 1, (1,), generator=g))
        rows = torch.randperm(m, generator=g)[:k]
        h[i, rows] = G[i, rows] @ x[i]
        lam[i, rows] = 0.5 + 1.5 * torch.rand(k, generator=g, dtype=f64)
        if bounds and k < room:
            j = int(torch.randint(0, n, (1,), generator=g))
            ub[i, j] = x[i, j]
            mu_ub[i, j] = 0.5 + torch.rand((), generator=g, dtype=f64)
    nu = torch.randn(B, me, generator=g, dtype=f64)
    b = torch.einsum("bmn,bn->bm", A, x)
    p = -(
        torch.einsum("bij,bj->bi", Q, x)
        + torch.einsum("bmn,bm->bn", G, lam)
        + torch.einsum("bmn,bm->bn", A, nu)
        + mu_ub
    )
    for i, kind in enumerate(kinds):
        if kind != "infeasible":
            continue
        mode = int(torch.randint(0, 3, (1,), generator=g))
        a = torch.randn(n, generator=g, dtype=f64)
        if mode == 1 and bounds:
            # halfspace sum(x) >= max over the box + 1
            G[i, 0] = -torch.ones(n, dtype=f64)
            h[i, 0] = -(ub[i].sum() + 1.0)
        elif mode == 2 and me > 0:
            G[i, 0] = A[i, 0]
            h[i, 0] = b[i, 0] - 1.0
        elif m >= 2:
            G[i, 0], G[i, 1] = a, -a
            h[i, 0], h[i, 1] = -1.0, -1.0
        else:
            # one halfspace against the box or an equality, else against itself via A
            if bounds:
                G[i, 0] = -torch.ones(n, dtype=f64)
                h[i, 0] = -(ub[i].sum() + 1.0)
            elif me > 0:
                G[i, 0] = A[i, 0]
                h[i, 0] = b[i, 0] - 1.0
            else:
                kinds[i] = "active_or_inactive"
    out = [Q, p, G, h, A, b, lb, ub, x]
    out = [None if t is None else t.to(dtype) for t in out]
    Q, p, G, h, A, b, lb, ub, x = out
    if me == 0:
        A = b = None
    return Batch(Q, p, G, h, A, b, lb, ub, x, kinds)


#: shapes ``(n, m, equalities, box bounds)`` of the 10,000-QP comparison with cvxpy (the slow
#: test and ``scripts/qp_accuracy.py``); problem ``k`` of the list uses seed ``1000 + k``
TEN_THOUSAND_SHAPES = [
    (n, m, me, bounds)
    for (n, m) in [(2, 1), (2, 6), (3, 4), (4, 8), (6, 12), (8, 20), (10, 32), (12, 64)]
    for me, bounds in [(0, False), (0, True), (1, False), (2, True)]
    if me < n
]


def hard_family(name: str, B: int, g: torch.Generator) -> tuple:
    """``(Q, p, G, h, lb, ub)`` of one of :data:`HARD_FAMILIES`, ``B`` rows, float64, drawn
    from ``g``; ``n = 4``, ``m = 8`` but for the mid-size family."""
    f64 = torch.float64

    def rnd(*shape: int) -> torch.Tensor:
        return torch.randn(*shape, generator=g, dtype=f64)

    n, m = 4, 8
    lb = ub = None
    if name.startswith("cond"):
        cond = float(name.split("=")[1])
        U, _ = torch.linalg.qr(rnd(B, n, n))
        d = torch.logspace(0, -math.log10(cond), n, dtype=f64)
        Q = U @ torch.diag_embed(d.expand(B, n)) @ U.mT
        return Q, rnd(B, n), rnd(B, m, n), torch.rand(B, m, generator=g, dtype=f64), lb, ub
    if name == "mid-size n=25 m=100":
        n, m = 25, 100
    L = rnd(B, n, n)
    Q = L @ L.mT / n + 0.1 * torch.eye(n, dtype=f64)
    p = 3 * rnd(B, n)
    G = rnd(B, m, n)
    x0 = rnd(B, n)
    slack = torch.rand(B, m, generator=g, dtype=f64)
    if name == "half the rows tight at x0":
        slack = torch.where(torch.rand(B, m, generator=g, dtype=f64) < 0.5, 0.0, slack)
    if name == "duplicated rows":
        G = torch.cat((G[:, : m // 2], G[:, : m // 2]), 1)
        slack = torch.cat((slack[:, : m // 2], slack[:, : m // 2]), 1)
    if name == "row scales 1e-6..1e6":
        scale = 10 ** (12 * torch.rand(B, m, 1, generator=g, dtype=f64) - 6)
        G = G * scale
        slack = slack * scale[..., 0]
    h = (G @ x0.unsqueeze(-1)).squeeze(-1) + slack
    if name == "LP in a box (Q = 0)":
        Q = torch.zeros(B, n, n, dtype=f64)
        lb, ub = -2 * torch.ones(B, n, dtype=f64), 2 * torch.ones(B, n, dtype=f64)
        h = h.abs() + 1.0  # the box is the bounded part
    return Q, p, G, h, lb, ub


HARD_FAMILIES = (
    "cond=1e6",
    "cond=1e8",
    "half the rows tight at x0",
    "duplicated rows",
    "row scales 1e-6..1e6",
    "LP in a box (Q = 0)",
    "mid-size n=25 m=100",
)
