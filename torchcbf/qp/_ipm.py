"""Batched primal-dual interior point method on the homogeneous self-dual embedding.

Solves, for every row of a batch at once and on the inputs' device,

    min 1/2 x'Px + q'x   s.t.   Gx + s = h, s >= 0,   Ax = b,

by Mehrotra predictor-corrector steps on the homogeneous embedding of the QP (the form
used by Clarabel): iterates ``(x, s, z, y, tau, kappa)`` with

    Px + G'z + A'y + q tau = 0,   Gx + s - h tau = 0,   Ax - b tau = 0,
    kappa + q'x + h'z + b'y + x'Px / tau = 0,   s o z = mu e,   tau kappa = mu.

A feasible QP ends with ``tau > 0`` and the solution ``x / tau``; an infeasible one ends with
``tau -> 0`` and the iterates turn into a certificate, which is checked explicitly:

- primal infeasible: ``z >= 0, G'z + A'y ~ 0, h'z + b'y < 0`` (Farkas),
- dual infeasible: ``Px ~ 0, Ax ~ 0, Gx <~ 0, q'x < 0`` (a direction of unbounded descent).

Each Newton step eliminates ``s`` and ``z`` and solves the ``n x n`` normal-equation matrix
``P + G' diag(z/s) G`` by a batched Cholesky factorisation (plus a Schur complement for the
equalities); the embedding needs two right-hand sides per step, both solved with the same
factor. Rows are frozen (step length zero) once their status is decided, which happens on
the device every iteration; the host only looks at the batch every ``check_every``
iterations to stop early, so the loop has no per-iteration synchronisation.
"""

from __future__ import annotations

from typing import NamedTuple

import torch
from torch import Tensor

from torchcbf.qp._data import QPData
from torchcbf.qp._lu import lu_factor_ex
from torchcbf.qp.status import Status


class IPMResult(NamedTuple):
    """Raw solver output, all ``[B, ...]``; ``x, s, z, y`` already divided by ``tau``."""

    x: Tensor
    s: Tensor
    z: Tensor
    y: Tensor
    status: Tensor
    iterations: Tensor


def default_tolerances(dtype: torch.dtype) -> tuple[float, float]:
    """Return ``(eps, eps_inf)``: optimality and infeasibility-certificate tolerances."""
    if dtype == torch.float64:
        return 1e-7, 1e-6
    return 2e-6, 1e-5


def _bmv(M: Tensor, v: Tensor) -> Tensor:
    return (M @ v.unsqueeze(-1)).squeeze(-1)


def _inf_norm(v: Tensor) -> Tensor:
    if v.shape[-1] == 0:
        return v.new_zeros(v.shape[:-1])
    return v.abs().amax(-1)


def not_positive_definite(P: Tensor) -> Tensor:
    """Rows ``[B]`` whose ``P`` is not numerically positive definite (a Cholesky pivot
    missing or below ``1e-13`` of its diagonal entry): only these may be unbounded."""
    L, info = torch.linalg.cholesky_ex(P)
    pivots_ok = L.diagonal(dim1=-2, dim2=-1).square() > 1e-13 * P.diagonal(dim1=-2, dim2=-1).abs()
    return (info != 0) | ~pivots_ok.all(-1)


def _descent_direction(
    x: Tensor,
    qx: Tensor,
    Px: Tensor,
    Ax: Tensor,
    Gx: Tensor,
    qn: Tensor,
    p_max: Tensor,
    a_max: Tensor,
    g_max: Tensor,
    eps_inf: float,
) -> Tensor:
    """Rows where ``x`` is an unbounded descent direction: ``Px = 0, Ax = 0, Gx <= 0`` and
    ``q'x < 0``, each judged against ``q'x`` and against its own data's scale (a weak
    curvature next to a large ``q``, as in ``P = diag(0, 1e-6)``, ``q = -1``, is bounded,
    however large ``x`` grows). Homogeneous in ``x``."""
    thr = -eps_inf * qx
    xn = eps_inf * _inf_norm(x)
    gx_max = Gx.amax(-1) if Gx.shape[-1] > 0 else qx.new_zeros(qx.shape)
    return (
        (qx < 0)
        & (qx <= -qn * xn)
        & (_inf_norm(Px) <= torch.minimum(thr, p_max * xn))
        & (_inf_norm(Ax) <= torch.minimum(thr, a_max * xn))
        & (gx_max <= torch.minimum(thr, g_max * xn))
    )


def unbounded_rows(
    P: Tensor,
    q: Tensor,
    G: Tensor,
    A: Tensor,
    x: Tensor,
    eps_inf: float,
    rounding: float | None = None,
) -> Tensor:
    """Rows ``[B]`` where ``x`` certifies unboundedness (the interior point method's test,
    applied to a point it left behind: its iterates grow along the descent direction), for
    ``P`` singular to rounding (smallest eigenvalue at most ``n`` units of ``rounding``, by
    default the machine epsilon of ``P``'s dtype, of the largest: a singular ``P`` whose
    Cholesky factor kept a rounding-sized pivot counts; data given in float32 and solved in
    float64 pass float32's epsilon, below which its eigenvalues are rounding).
    The iterates grow along the null space of ``P`` but carry the rest of ``x`` along, so
    ``x`` projected on that null space is tried as well."""
    if rounding is None:
        rounding = torch.finfo(P.dtype).eps
    p_max = P.abs().amax((-2, -1))
    g_max, a_max = _inf_norm(G.abs().amax(-1)), _inf_norm(A.abs().amax(-1))
    lam, V = torch.linalg.eigh(P)
    tol = x.shape[-1] * rounding * lam.abs().amax(-1)
    singular = not_positive_definite(P) | (lam[..., 0] <= tol)
    null = (lam <= tol.unsqueeze(-1)).to(x.dtype)
    found = torch.zeros_like(singular)
    for d in (x, _bmv(V, null * _bmv(V.mT, x))):
        qd = (q * d).sum(-1)
        found = found | _descent_direction(
            d, qd, _bmv(P, d), _bmv(A, d), _bmv(G, d), _inf_norm(q), p_max, a_max, g_max, eps_inf
        )
    return singular & found


#: sweeps of the Ruiz equilibration of the data (:func:`_equilibrate`)
RUIZ_SWEEPS = 10


class _Scaling(NamedTuple):
    """``x = D x~``, rows of ``G`` by ``Eg``, of ``A`` by ``Ea``, objective by ``c``."""

    D: Tensor
    Eg: Tensor
    Ea: Tensor
    c: Tensor


def _pow2(v: Tensor) -> Tensor:
    """``v`` rounded to a power of two (scaling by it is exact)."""
    return torch.exp2(torch.round(torch.log2(v)))


def _equilibrate(data: QPData) -> tuple[QPData, _Scaling]:
    """Ruiz equilibration of ``[[P, G', A'], [G, 0, 0], [A, 0, 0]]``: variables and rows
    scaled (powers of two) until every column of the variables and every row has largest
    entry near one, then the objective scaled so that ``P``'s mean column and ``q`` are
    near one. Returns the scaled ``(P, q, G, h, A, b)`` and the :class:`_Scaling`.
    Degenerate problems whose rows and curvatures span many orders of magnitude (linear
    programs in a QP's clothes) otherwise leave the normal equations unsolvable to the
    precision the stopping tests ask for."""
    P, q, G, h, A, b = data
    B, n = q.shape
    D = q.new_ones(B, n)
    Eg = q.new_ones(B, G.shape[-2])
    Ea = q.new_ones(B, A.shape[-2])

    def inv_sqrt(v: Tensor) -> Tensor:
        return torch.where(v > 0, v.clamp(1e-8, 1e8).rsqrt(), torch.ones_like(v))

    for _ in range(RUIZ_SWEEPS):
        Ps = D.unsqueeze(-1) * P * D.unsqueeze(-2)
        Gs = Eg.unsqueeze(-1) * G * D.unsqueeze(-2)
        As = Ea.unsqueeze(-1) * A * D.unsqueeze(-2)
        col = Ps.abs().amax(-2)
        if G.shape[-2] > 0:
            col = torch.maximum(col, Gs.abs().amax(-2))
            Eg = Eg * inv_sqrt(Gs.abs().amax(-1))
        if A.shape[-2] > 0:
            col = torch.maximum(col, As.abs().amax(-2))
            Ea = Ea * inv_sqrt(As.abs().amax(-1))
        D = D * inv_sqrt(col)
    D, Eg, Ea = _pow2(D), _pow2(Eg), _pow2(Ea)
    Ps = D.unsqueeze(-1) * P * D.unsqueeze(-2)
    qs = D * q
    mean_col = Ps.abs().amax(-2).mean(-1)
    cost = torch.maximum(mean_col, _inf_norm(qs))
    c = torch.where(cost > 0, 1.0 / cost.clamp(1e-4, 1e4), torch.ones_like(cost))
    c = _pow2(c)
    scaled = QPData(
        c.view(-1, 1, 1) * Ps,
        c.unsqueeze(-1) * qs,
        Eg.unsqueeze(-1) * G * D.unsqueeze(-2),
        Eg * h,
        Ea.unsqueeze(-1) * A * D.unsqueeze(-2),
        Ea * b,
    )
    return scaled, _Scaling(D, Eg, Ea, c)


#: regularisation of the equality block of the Newton system, relative to its largest
#: entry (refined away, :data:`REFINE_STEPS`)
EQ_REG = 1e-10
#: iterative refinement steps on the Newton system with equality rows
REFINE_STEPS = 2


class _KKT:
    """Factorisation of ``[[P, G', A'], [G, -diag(1/d), 0], [A, 0, 0]]`` for a batch: ``z``
    eliminated (``H = P + G' diag(d) G``); without equality rows ``H`` by Cholesky, with
    them the quasi-definite ``[[H, A'], [A, -delta I]]`` by LU, refined against ``delta = 0``
    (dependent or nearly dependent equalities and a singular ``H`` on the free variables of a
    linear program leave it solvable, where a Schur complement ``A H^-1 A'`` is not)."""

    def __init__(self, P: Tensor, G: Tensor, A: Tensor, d: Tensor, reg: Tensor) -> None:
        self.G, self.A, self.d = G, A, d
        H = P + G.mT @ (d.unsqueeze(-1) * G)
        # static regularisation, scaled by the data (not by z/s, which would blur the step)
        H = H + torch.diag_embed(reg.expand(H.shape[:-1]))
        self.has_eq = A.shape[-2] > 0
        if not self.has_eq:
            self.L, info = torch.linalg.cholesky_ex(H)
            self.ok = info == 0
            return
        n, E = H.shape[-1], A.shape[-2]
        K = torch.cat(
            (torch.cat((H, A.mT), -1), torch.cat((A, A.new_zeros(A.shape[0], E, E)), -1)), -2
        )
        delta = EQ_REG * A.abs().amax((-2, -1)).clamp_min(1.0)
        shift = torch.cat((K.new_zeros(K.shape[0], n), -delta.unsqueeze(-1).expand(-1, E)), -1)
        self.K = K
        self.LU, self.pivots, info = lu_factor_ex(K + torch.diag_embed(shift))
        self.ok = (info == 0) & torch.isfinite(self.LU).flatten(-2).all(-1)
        eye = torch.eye(n + E, dtype=K.dtype, device=K.device)
        self.LU = torch.where(self.ok.view(-1, 1, 1), self.LU, eye)
        self.pivots = torch.where(
            self.ok.unsqueeze(-1),
            self.pivots,
            torch.arange(1, n + E + 1, dtype=self.pivots.dtype, device=K.device),
        )

    def solve(self, rx: Tensor, rz: Tensor, ry: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """Solve for ``(dx, dz, dy)``; right-hand sides ``[B, *, k]`` (k columns)."""
        d = self.d.unsqueeze(-1)
        rt = rx + self.G.mT @ (d * rz)
        if self.has_eq:
            n = rt.shape[-2]
            r = torch.cat((rt, ry), -2)
            w = torch.linalg.lu_solve(self.LU, self.pivots, r)
            for _ in range(REFINE_STEPS):
                w = w + torch.linalg.lu_solve(self.LU, self.pivots, r - self.K @ w)
            dx, dy = w[..., :n, :], w[..., n:, :]
        else:
            dy = ry
            dx = torch.cholesky_solve(rt, self.L)
        dz = d * (self.G @ dx - rz)
        return dx, dz, dy


def _max_step(v: Tensor, dv: Tensor) -> Tensor:
    """Largest ``alpha`` in ``(0, 1]`` with ``v + alpha dv >= 0`` for ``v > 0``, per row."""
    if v.shape[-1] == 0:
        return v.new_ones(v.shape[:-1])
    ratio = torch.where(dv < 0, -v / dv, torch.ones_like(v))
    return ratio.amin(-1).clamp(max=1.0)


_COMPACT_FRACTION = 0.5


def _write_back(full: list[Tensor] | None, idx: Tensor, state: tuple[Tensor, ...]) -> list[Tensor]:
    """Scatter the working rows ``idx`` of ``state`` into the full-batch tensors."""
    if full is None:
        return [t.clone() for t in state]
    return [f.index_copy(0, idx, t) for f, t in zip(full, state, strict=True)]


class _StepData(NamedTuple):
    inv_tau: Tensor
    c: Tensor
    h: Tensor
    b: Tensor
    den: Tensor
    x2: Tensor
    z2: Tensor
    y2: Tensor
    s: Tensor
    z: Tensor
    kappa: Tensor


def _direction(
    sd: _StepData, x1: Tensor, z1: Tensor, y1: Tensor, d_t: Tensor, d_s: Tensor, d_k: Tensor
) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor, Tensor]:
    """Recover the full step from the reduced solves (eliminating tau, s and kappa)."""
    num = -d_t + d_k * sd.inv_tau - (sd.c * x1).sum(-1) - (sd.h * z1).sum(-1) - (sd.b * y1).sum(-1)
    dtau = num / sd.den
    dx = x1 + dtau.unsqueeze(-1) * sd.x2
    dz = z1 + dtau.unsqueeze(-1) * sd.z2
    dy = y1 + dtau.unsqueeze(-1) * sd.y2
    dsv = -d_s / sd.z - (sd.s / sd.z) * dz
    dkappa = -(d_k + sd.kappa * dtau) * sd.inv_tau
    return dx, dz, dy, dsv, dtau, dkappa


def _step_length(
    s: Tensor, ds: Tensor, z: Tensor, dz: Tensor, tau: Tensor, dt: Tensor, kappa: Tensor, dk: Tensor
) -> Tensor:
    """Largest step in ``(0, 1]`` keeping ``s, z, tau, kappa`` nonnegative, per row."""
    return torch.minimum(
        torch.minimum(_max_step(s, ds), _max_step(z, dz)),
        torch.minimum(
            _max_step(tau.unsqueeze(-1), dt.unsqueeze(-1)),
            _max_step(kappa.unsqueeze(-1), dk.unsqueeze(-1)),
        ),
    )


def solve_ipm(
    data: QPData,
    *,
    eps: float,
    eps_inf: float,
    max_iter: int,
    check_every: int = 5,
    x0: Tensor | None = None,
) -> IPMResult:
    """Solve a batch of QPs (see module docstring). Shapes: ``P [B,n,n], q [B,n],
    G [B,M,n], h [B,M], A [B,me,n], b [B,me]``; ``x0 [B,n]`` optionally seeds the primal
    iterate. Inputs must be finite; no gradient flows through this function."""
    P, q, G, h, A, b = data
    B, n = q.shape
    M = h.shape[-1]
    dtype, device = q.dtype, q.device
    (P, q, G, h, A, b), scaling = _equilibrate(data)
    if x0 is not None:
        x0 = x0 / scaling.D
    reg_rel = 1e-12 if dtype == torch.float64 else 1e-6
    d_reg = 1e-13 if dtype == torch.float64 else 1e-6
    data_scale = torch.maximum(
        P.abs().amax((-2, -1)), G.abs().amax((-2, -1)) if M > 0 else P.new_zeros(B)
    )
    reg = (reg_rel * data_scale.clamp_min(1.0)).unsqueeze(-1)

    # Initial point: the solution of the regularised KKT system with unit scaling.
    ones = h.new_ones(B, M)
    kkt = _KKT(P, G, A, ones, reg)
    x, z, y = kkt.solve(-q.unsqueeze(-1), h.unsqueeze(-1), b.unsqueeze(-1))
    x, z, y = x.squeeze(-1), z.squeeze(-1), y.squeeze(-1)
    if x0 is not None:
        x = x0.to(dtype)
        z = _bmv(G, x) - h
    s = -z
    if M > 0:
        shift_s = (-s.amin(-1, keepdim=True)).clamp_min(0.0) + 1.0
        shift_z = (-z.amin(-1, keepdim=True)).clamp_min(0.0) + 1.0
        s = torch.where(s.amin(-1, keepdim=True) > 0, s, s + shift_s)
        z = torch.where(z.amin(-1, keepdim=True) > 0, z, z + shift_z)
    tau = q.new_ones(B)
    kappa = q.new_ones(B)
    bad0 = ~kkt.ok | ~torch.isfinite(x).all(-1) | ~torch.isfinite(z).all(-1)
    x = torch.where(bad0.unsqueeze(-1), torch.zeros_like(x), x)
    z = torch.where(bad0.unsqueeze(-1), torch.ones_like(z), z)
    s = torch.where(bad0.unsqueeze(-1), torch.ones_like(s), s)
    y = torch.where(bad0.unsqueeze(-1), torch.zeros_like(y), y)

    status = torch.full((B,), int(Status.MAX_ITER), dtype=torch.int64, device=device)
    status = torch.where(bad0, int(Status.NUMERICAL_ERROR), status)
    active = ~bad0
    iterations = torch.zeros(B, dtype=torch.int64, device=device)

    qn = _inf_norm(q)
    hn = torch.maximum(_inf_norm(h), _inf_norm(b))
    # largest entry of every row of G and A, to weigh the rows a Farkas certificate combines
    g_rows = G.abs().amax(-1) if n > 0 else G.new_zeros(B, M)  # [B, M]
    a_rows = A.abs().amax(-1) if n > 0 else A.new_zeros(B, A.shape[-2])  # [B, E]
    # a zero row that asks 0 <= h_i < 0 or 0 = b_i != 0 is its own certificate (the
    # weighted Farkas test below cannot see it: its multiplier weighs nothing)
    tol = (eps * (1.0 + hn)).unsqueeze(-1)
    contradiction = ((g_rows == 0) & (h < -tol)).any(-1) | ((a_rows == 0) & (b.abs() > tol)).any(-1)
    status = torch.where(active & contradiction, int(Status.PRIMAL_INFEASIBLE), status)
    active = active & ~contradiction
    # largest entries of P, G and A, the scales of an unboundedness certificate
    p_max = P.abs().amax((-2, -1)) if n > 0 else P.new_zeros(B)
    g_max = _inf_norm(g_rows)
    a_max = _inf_norm(a_rows)
    # a strictly convex QP is never dual infeasible: only rows whose P is not positive
    # definite may take the certificate (with a large q it fires falsely, e.g. P = 1,
    # q = -1e8, -10 <= x <= 1)
    may_be_unbounded = not_positive_definite(P)
    Gt, At = G.mT, A.mT
    idx = torch.arange(B, device=device)
    full: list[Tensor] | None = None

    for it in range(max_iter + 1):
        Px = _bmv(P, x)
        Gx = _bmv(G, x)
        Ax = _bmv(A, x)
        Gtz = _bmv(Gt, z) + _bmv(At, y)
        xPx = (x * Px).sum(-1)
        qx = (q * x).sum(-1)
        hz = (h * z).sum(-1) + (b * y).sum(-1)
        rx = Px + Gtz + q * tau.unsqueeze(-1)
        rz = Gx + s - h * tau.unsqueeze(-1)
        ry = Ax - b * tau.unsqueeze(-1)
        rt = kappa + qx + hz + xPx / tau

        # ---- termination tests, on the device, for the rows still running ----
        inv_tau = 1.0 / tau
        pres = torch.maximum(_inf_norm(rz), _inf_norm(ry)) * inv_tau
        dres = _inf_norm(rx) * inv_tau
        pscale = torch.maximum(
            hn, torch.maximum(torch.maximum(_inf_norm(Gx), _inf_norm(Ax)), _inf_norm(s)) * inv_tau
        )
        dscale = torch.maximum(qn, torch.maximum(_inf_norm(Px), _inf_norm(Gtz)) * inv_tau)
        xPx_n = xPx * inv_tau * inv_tau
        pobj = 0.5 * xPx_n + qx * inv_tau
        dobj = -0.5 * xPx_n - hz * inv_tau
        gap = (pobj - dobj).abs()
        converged = (
            (pres <= eps * (1.0 + pscale))
            & (dres <= eps * (1.0 + dscale))
            & (gap <= eps * (1.0 + torch.minimum(pobj.abs(), dobj.abs())))
        )
        # Farkas: the multipliers (z >= 0, y) combine the rows into G'z + A'y = 0 and
        # h'z + b'y < 0, each judged against the rows they weigh: |z_i| max_j |G_ij| and
        # |z_i h_i| (a large h on its own, as in x <= -1e6, is no contradiction)
        row_w = torch.maximum(_inf_norm(g_rows * z), _inf_norm(a_rows * y))
        rhs_w = torch.maximum(_inf_norm(h * z), _inf_norm(b * y))
        pinf = (
            (hz < 0)
            & (_inf_norm(Gtz) <= -eps_inf * hz)
            & (_inf_norm(Gtz) <= eps_inf * row_w)
            & (hz <= -eps_inf * rhs_w)
        )
        # unbounded descent: a direction x with Px = 0, Ax = 0, Gx <= 0 and q'x < 0, each
        # judged against q'x and against its own data's scale (a weak curvature next to a
        # large q, as in P = diag(0, 1e-6), q = -1, is bounded, however large x grows)
        dinf = may_be_unbounded & _descent_direction(
            x, qx, Px, Ax, Gx, qn, p_max, a_max, g_max, eps_inf
        )
        status = torch.where(active & converged, int(Status.SOLVED), status)
        status = torch.where(active & ~converged & pinf, int(Status.PRIMAL_INFEASIBLE), status)
        status = torch.where(
            active & ~converged & ~pinf & dinf, int(Status.DUAL_INFEASIBLE), status
        )
        active = active & ~(converged | pinf | dinf)
        if it == max_iter:
            break
        if it % check_every == 0:
            n_active = int(active.sum())  # the only host synchronisation of the loop
            if n_active == 0:
                break
            if n_active <= _COMPACT_FRACTION * active.shape[0] and active.shape[0] >= 64:
                # drop finished rows from the working set so the tail of slow rows is cheap
                state = (x, s, z, y, tau, kappa, status, iterations)
                full = _write_back(full, idx, state)
                keep = active.nonzero().squeeze(-1)
                idx = idx[keep]
                rows = (P, q, G, h, A, b, reg, qn, hn, g_rows, a_rows, may_be_unbounded)
                P, q, G, h, A, b, reg, qn, hn, g_rows, a_rows, may_be_unbounded = (
                    t[keep] for t in rows
                )
                p_max, g_max, a_max = (t[keep] for t in (p_max, g_max, a_max))
                Gt, At = G.mT, A.mT
                x, s, z, y, tau, kappa, status, iterations = (t[keep] for t in state)
                inv_tau, rx, rz, ry, rt = (t[keep] for t in (inv_tau, rx, rz, ry, rt))
                active = active[keep]
        iterations = iterations + active.to(torch.int64)

        # ---- Newton step (predictor-corrector) ----
        mu = ((s * z).sum(-1) + tau * kappa) / (M + 1)
        # z/s capped (a dual regularisation of the (2,2) block) so the factorisation survives
        # tau -> 0 on infeasible rows; the residuals stay exact, so the cap only slows the
        # final digits, which are recovered by the polishing step.
        d = z / (s + d_reg * z)
        kkt = _KKT(P, G, A, d, reg)
        xi = x * inv_tau.unsqueeze(-1)
        c = q + 2.0 * _bmv(P, xi)

        # second system K [x2; z2; y2] = [-q; h; b] and the affine first system, together
        ds_aff_rhs = s  # d_s / z with d_s = s o z
        rhs_x = torch.stack((-q, -rx), -1)
        rhs_z = torch.stack((h, -rz + ds_aff_rhs), -1)
        rhs_y = torch.stack((b, -ry), -1)
        sx, sz, sy = kkt.solve(rhs_x, rhs_z, rhs_y)
        x2, z2, y2 = sx[..., 0], sz[..., 0], sy[..., 0]
        xd = x2 - xi
        den = -(kappa * inv_tau + (xd * _bmv(P, xd)).sum(-1) + (z2 * z2 * s / z).sum(-1))

        sd = _StepData(inv_tau, c, h, b, den, x2, z2, y2, s, z, kappa)
        dxa, dza, dya, dsa, dta, dka = _direction(
            sd, sx[..., 1], sz[..., 1], sy[..., 1], rt, s * z, tau * kappa
        )
        alpha_aff = _step_length(s, dsa, z, dza, tau, dta, kappa, dka)
        sigma = (1.0 - alpha_aff).pow(3)
        sm = (sigma * mu).unsqueeze(-1)
        one_m = (1.0 - sigma).unsqueeze(-1)
        d_s = s * z - sm + dsa * dza
        d_k = tau * kappa - sigma * mu + dta * dka
        cx, cz, cy = kkt.solve(
            (-one_m * rx).unsqueeze(-1),
            (-one_m * rz + d_s / z).unsqueeze(-1),
            (-one_m * ry).unsqueeze(-1),
        )
        dx, dz, dy, dsv, dt, dk = _direction(
            sd, cx.squeeze(-1), cz.squeeze(-1), cy.squeeze(-1), (1.0 - sigma) * rt, d_s, d_k
        )
        alpha = _step_length(s, dsv, z, dz, tau, dt, kappa, dk)
        # a 0.9 step fraction keeps the iterates centred (0.99 made Mehrotra zig-zag on some
        # rows); near the end, where the affine step is nearly full, step further.
        frac = torch.where(alpha_aff > 0.9, 0.99, 0.9)
        alpha = (frac * alpha).clamp(max=1.0)
        step_ok = (
            kkt.ok
            & torch.isfinite(alpha)
            & torch.isfinite(dx).all(-1)
            & torch.isfinite(dz).all(-1)
            & torch.isfinite(dsv).all(-1)
            & torch.isfinite(dy).all(-1)
            & torch.isfinite(dt)
            & torch.isfinite(dk)
            & (alpha > 0)
        )
        status = torch.where(active & ~step_ok, int(Status.NUMERICAL_ERROR), status)
        active = active & step_ok
        a = torch.where(active, alpha, torch.zeros_like(alpha))
        a = torch.nan_to_num(a, nan=0.0)
        a1 = a.unsqueeze(-1)
        x = x + a1 * torch.nan_to_num(dx)
        z = z + a1 * torch.nan_to_num(dz)
        s = s + a1 * torch.nan_to_num(dsv)
        y = y + a1 * torch.nan_to_num(dy)
        tau = tau + a * torch.nan_to_num(dt)
        kappa = kappa + a * torch.nan_to_num(dk)

    if full is not None:
        x, s, z, y, tau, kappa, status, iterations = _write_back(
            full, idx, (x, s, z, y, tau, kappa, status, iterations)
        )
    inv = (1.0 / tau).unsqueeze(-1)
    solved_like = (
        (status == int(Status.SOLVED))
        | (status == int(Status.MAX_ITER))
        | (status == int(Status.NUMERICAL_ERROR))
    )
    keep = solved_like.unsqueeze(-1)
    x = torch.where(keep, x * inv, torch.zeros_like(x))
    s = torch.where(keep, s * inv, torch.zeros_like(s))
    z = torch.where(keep, z * inv, torch.zeros_like(z))
    y = torch.where(keep, y * inv, torch.zeros_like(y))
    # back to the caller's variables, rows and objective
    inv_c = (1.0 / scaling.c).unsqueeze(-1)
    x = x * scaling.D
    s = s / scaling.Eg
    z = z * scaling.Eg * inv_c
    y = y * scaling.Ea * inv_c
    finite = (
        torch.isfinite(x).all(-1)
        & torch.isfinite(z).all(-1)
        & torch.isfinite(s).all(-1)
        & torch.isfinite(y).all(-1)
    )
    status = torch.where(finite, status, int(Status.NUMERICAL_ERROR))
    fin = finite.unsqueeze(-1)
    x = torch.where(fin, x, torch.zeros_like(x))
    s = torch.where(fin, s, torch.zeros_like(s))
    z = torch.where(fin, z, torch.zeros_like(z))
    y = torch.where(fin, y, torch.zeros_like(y))
    return IPMResult(x, s, z, y, status, iterations)
