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


@dataclass
class HardProblem:
    """``B`` rows of one of :data:`HARD_FAMILIES` (float64). ``A, b`` and ``lb, ub`` may be
    ``None``; ``expect`` is what every row is by construction: ``"optimal"``,
    ``"infeasible"`` or ``"unbounded"``; ``x_star [B, n]`` is the exact minimiser where the
    construction knows it, else ``None``."""

    Q: Tensor
    p: Tensor
    G: Tensor
    h: Tensor
    A: Tensor | None
    b: Tensor | None
    lb: Tensor | None
    ub: Tensor | None
    expect: str
    x_star: Tensor | None = None

    def data(self) -> tuple:
        """``(Q, p, G, h, A, b, lb, ub)``, the positional arguments of ``solve_qp``."""
        return self.Q, self.p, self.G, self.h, self.A, self.b, self.lb, self.ub


def _mv(M: Tensor, v: Tensor) -> Tensor:
    return (M @ v.unsqueeze(-1)).squeeze(-1)


def _shuffle_rows(G: Tensor, h: Tensor, g: torch.Generator) -> tuple[Tensor, Tensor]:
    """The rows of ``G x <= h`` in a random order, drawn for every problem of the batch."""
    perm = torch.rand(h.shape, generator=g, dtype=h.dtype).argsort(-1)
    return G.gather(1, perm.unsqueeze(-1).expand_as(G)), h.gather(1, perm)


def _constructed_family(name: str, B: int, g: torch.Generator) -> HardProblem:
    """The families each built around their own known point, direction or contradiction
    (the ones outside :data:`_SHARED_CONSTRUCTION` and the ``cond=`` families)."""
    f64 = torch.float64
    n, m = 4, 8

    def rnd(*shape: int) -> Tensor:
        return torch.randn(*shape, generator=g, dtype=f64)

    def uni(*shape: int) -> Tensor:
        return torch.rand(*shape, generator=g, dtype=f64)

    def pd(k: int) -> Tensor:
        L = rnd(B, k, k)
        return L @ L.mT / k + 0.1 * torch.eye(k, dtype=f64)

    def feasible_rows(x0: Tensor, rows: int) -> tuple[Tensor, Tensor]:
        """``rows`` random rows with a slack in (0, 1) at ``x0``."""
        G = rnd(B, rows, x0.shape[-1])
        return G, _mv(G, x0) + uni(B, rows)

    def integer_direction() -> Tensor:
        """A direction ``d [B, n]`` with small integer entries, not zero."""
        d = torch.randint(-3, 4, (B, n), generator=g).to(f64)
        d[:, 0] = torch.where(d.abs().sum(-1) == 0, 1.0, d[:, 0])
        return d

    def orthogonal_to(d: Tensor, rows: int) -> Tensor:
        """``rows`` random rows orthogonal to ``d`` in exact arithmetic: integer rows
        ``(d.d) v - (v.d) d`` (exact in float64) times a power of two near ``1 / |row|``."""
        v = torch.randint(-5, 6, (B, rows, n), generator=g).to(f64)
        w = (d * d).sum(-1)[:, None, None] * v - (v @ d.unsqueeze(-1)) * d.unsqueeze(-2)
        size = w.abs().amax(-1, keepdim=True).clamp(min=1.0)
        return w * torch.exp2(-torch.round(torch.log2(size)))

    def singular_q(d: Tensor) -> Tensor:
        """A PSD ``Q`` of rank ``n - 1`` with ``Q d = 0`` exactly: ``W W'`` for ``W`` from
        :func:`orthogonal_to` (products and sums of its entries, multiples of powers of two
        of a few bits, are exact), scaled by a power of two to about unit size."""
        W = orthogonal_to(d, n - 1).mT
        Q = W @ W.mT
        size = Q.diagonal(dim1=-2, dim2=-1).mean(-1)[:, None, None]
        return Q * torch.exp2(-torch.round(torch.log2(size)))

    def descent_along(d: Tensor) -> Tensor:
        """A random ``p`` with ``p.d / |d| = -(0.5 .. 1.5)``."""
        u = d / d.norm(dim=-1, keepdim=True)
        p = 3 * rnd(B, n)
        p = p - (p * u).sum(-1, keepdim=True) * u
        return p - (0.5 + uni(B, 1)) * u

    A = b = lb = ub = x_star = None
    if name == "rank-deficient Q in a box":
        L = rnd(B, n, 2)
        Q = L @ L.mT
        p = 3 * rnd(B, n)
        x0 = 1.5 * (2 * uni(B, n) - 1)  # inside the box
        G, h = feasible_rows(x0, m)
        lb, ub = torch.full((B, n), -2.0, dtype=f64), torch.full((B, n), 2.0, dtype=f64)
        return HardProblem(Q, p, G, h, A, b, lb, ub, "optimal")
    if name == "equalities with a box":
        Q, p = pd(n), 3 * rnd(B, n)
        x0 = 0.9 * (2 * uni(B, n) - 1)  # strictly inside [-1, 1]^n
        A = rnd(B, 2, n)
        b = _mv(A, x0)
        G, h = feasible_rows(x0, m)
        lb, ub = torch.full((B, n), -1.0, dtype=f64), torch.full((B, n), 1.0, dtype=f64)
        return HardProblem(Q, p, G, h, A, b, lb, ub, "optimal")
    if name == "degenerate vertex (6 rows tight, 4 variables)":
        # rows 0..5 tight at x*, multipliers > 0 on rows 0 and 1 only, rows 6, 7 slack;
        # then the rows are shuffled. Q is positive definite, so x* is the unique minimiser.
        Q, x_star = pd(n), rnd(B, n)
        G = rnd(B, m, n)
        slack = torch.cat((torch.zeros(B, 6, dtype=f64), 0.1 + uni(B, 2)), -1)
        h = _mv(G, x_star) + slack
        lam = torch.cat((0.5 + uni(B, 2), torch.zeros(B, 6, dtype=f64)), -1)
        p = -_mv(Q, x_star) - _mv(G.mT, lam)
        G, h = _shuffle_rows(G, h, g)
        return HardProblem(Q, p, G, h, A, b, lb, ub, "optimal", x_star)
    if name == "near-parallel rows":
        # rows m/2.. are rows 0..m/2-1 with every entry moved by 1e-9 randn and a right-hand
        # side 1e-9 |randn| looser than their own value at x0 plus the first copy's slack
        Q, p, x0 = pd(n), 3 * rnd(B, n), rnd(B, n)
        G1 = rnd(B, m // 2, n)
        slack = uni(B, m // 2)
        G2 = G1 + 1e-9 * rnd(B, m // 2, n)
        G = torch.cat((G1, G2), 1)
        h = torch.cat((_mv(G1, x0) + slack, _mv(G2, x0) + slack + 1e-9 * rnd(B, m // 2).abs()), 1)
        return HardProblem(Q, p, G, h, A, b, lb, ub, "optimal")
    if name == "relaxed filter rows (weights 1e-3..1e6)":
        # a CBF filter's QP in (u1, u2, s): controls weighted 1e-3..1, a slack weighted
        # 1e3..1e6 in both its terms, unit rows u . a_i + s >= c_i with c_i up to 1e4 (more
        # than the box |u| <= 40 allows), so the slack and the multipliers are large
        w = torch.exp2(torch.round(torch.log2(10 ** (3 * uni(B, 2) - 3))))
        W = torch.exp2(torch.round(torch.log2(10 ** (3 * uni(B, 1) + 3))))
        Q = torch.diag_embed(torch.cat((w, W), -1))
        p = torch.cat((-w * 20 * rnd(B, 2), W), -1)
        a = rnd(B, 5, 2)
        a = a / a.norm(dim=-1, keepdim=True)
        c = torch.sign(rnd(B, 5)) * 10 ** (4 * uni(B, 5))
        G, h = torch.cat((-a, -torch.ones(B, 5, 1, dtype=f64)), -1), -c
        lb = torch.tensor([-40.0, -40.0, 0.0], dtype=f64).expand(B, 3).clone()
        ub = torch.tensor([40.0, 40.0, math.inf], dtype=f64).expand(B, 3).clone()
        return HardProblem(Q, p, G, h, A, b, lb, ub, "optimal")
    if name == "contradicting rows":
        # g x <= c and -g x <= -c - 1 (at random places) among rows feasible at x0, where
        # c = g x0 + slack
        Q, p, x0 = pd(n), 3 * rnd(B, n), rnd(B, n)
        G, h = feasible_rows(x0, m)
        G[:, 1], h[:, 1] = -G[:, 0], -h[:, 0] - 1.0
        G, h = _shuffle_rows(G, h, g)
        return HardProblem(Q, p, G, h, A, b, lb, ub, "infeasible")
    if name == "empty box":
        # a box around x0 with lb > ub in one (random) component; rows feasible at x0
        Q, p, x0 = pd(n), 3 * rnd(B, n), rnd(B, n)
        G, h = feasible_rows(x0, m)
        lb, ub = x0 - 1 - uni(B, n), x0 + 1 + uni(B, n)
        j = torch.randint(0, n, (B, 1), generator=g)
        lb = lb.scatter(1, j, ub.gather(1, j) + 0.1 + uni(B, 1))
        return HardProblem(Q, p, G, h, A, b, lb, ub, "infeasible")
    if name == "inconsistent equalities":
        # two equality rows with the same A row, right-hand sides 0.5 .. 1.5 apart
        Q, p, x0 = pd(n), 3 * rnd(B, n), rnd(B, n)
        a = rnd(B, 1, n)
        A = torch.cat((a, a), 1)
        b0 = _mv(a, x0)
        b = torch.cat((b0, b0 + 0.5 + uni(B, 1)), 1)
        G, h = feasible_rows(x0, m)
        return HardProblem(Q, p, G, h, A, b, lb, ub, "infeasible")
    if name == "free direction":
        # Q PSD with Q d = 0 and every row orthogonal to d (both exactly, in floating point
        # too), p.d < 0: x0 + t d is feasible for all t and the objective falls without bound
        d = integer_direction()
        Q, p, x0 = singular_q(d), descent_along(d), rnd(B, n)
        G = orthogonal_to(d, m)
        h = _mv(G, x0) + uni(B, m)
        return HardProblem(Q, p, G, h, A, b, lb, ub, "unbounded")
    if name == "inequality recession":
        # G d <= 0 (about half the rows G_i d = 0, the others < 0), Q d = 0 (Q = 0 on about a
        # third of the problems, else singular_q), all exactly; p.d < 0
        d = integer_direction()
        Q = singular_q(d)
        Q = torch.where(uni(B, 1, 1) < 1 / 3, 0.0, Q)
        p, x0 = descent_along(d), rnd(B, n)
        # orthogonal rows minus k s d, s the power of two nearest 1 / |d|^2, k in {0 (about
        # half the rows, never the first), 1, 2, 3}: G_i d = -k s |d|^2 (about -k) exactly, and
        # some row limits -d (which sets the family apart from the free direction)
        k = torch.randint(1, 4, (B, m, 1), generator=g).to(f64)
        zero = uni(B, m, 1) < 0.5
        zero[:, 0] = False
        k = torch.where(zero, 0.0, k)
        scale = torch.exp2(-torch.round(torch.log2((d * d).sum(-1))))[:, None, None]
        G = orthogonal_to(d, m) - k * scale * d.unsqueeze(-2)
        h = _mv(G, x0) + uni(B, m)
        return HardProblem(Q, p, G, h, A, b, lb, ub, "unbounded")
    raise ValueError(f"unknown hard family {name!r}")


def hard_family(name: str, B: int, g: torch.Generator) -> HardProblem:
    """``B`` rows of the family ``name`` of :data:`HARD_FAMILIES`, float64, drawn from ``g``;
    ``n = 4``, ``m = 8`` but for the mid-size families. Every row is what the family says by
    construction (:attr:`HardProblem.expect`)."""
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
        p, G, h = rnd(B, n), rnd(B, m, n), torch.rand(B, m, generator=g, dtype=f64)
        return HardProblem(Q, p, G, h, None, None, lb, ub, "optimal")
    if name not in _SHARED_CONSTRUCTION:
        return _constructed_family(name, B, g)
    if name.startswith("mid-size"):
        n, m = (int(s.split("=")[1]) for s in name.split()[1:])
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
    return HardProblem(Q, p, G, h, None, None, lb, ub, "optimal")


#: the families built by the shared construction of :func:`hard_family` (Q = L L'/n + 0.1 I,
#: rows feasible at a random x0), all drawing from ``g`` in the same order
_SHARED_CONSTRUCTION = (
    "half the rows tight at x0",
    "duplicated rows",
    "row scales 1e-6..1e6",
    "LP in a box (Q = 0)",
    "mid-size n=25 m=100",
    "mid-size n=64 m=256",
)

#: the hard families of scripts/qp_accuracy.py; family ``k`` draws from seed ``500 + k`` there,
#: so new families go at the end
HARD_FAMILIES = (
    "cond=1e6",
    "cond=1e8",
    "half the rows tight at x0",
    "duplicated rows",
    "row scales 1e-6..1e6",
    "LP in a box (Q = 0)",
    "mid-size n=25 m=100",
    "cond=1e10",
    "rank-deficient Q in a box",
    "equalities with a box",
    "degenerate vertex (6 rows tight, 4 variables)",
    "near-parallel rows",
    "mid-size n=64 m=256",
    "contradicting rows",
    "empty box",
    "inconsistent equalities",
    "free direction",
    "inequality recession",
    "relaxed filter rows (weights 1e-3..1e6)",
)
