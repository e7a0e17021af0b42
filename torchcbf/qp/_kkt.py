"""Active-set KKT system: polishing of a solver's answer and the implicit-function backward.

For a row with solution ``x``, inequality multipliers ``z`` and equality multipliers ``y``,
the active set is ``{i : z_i > s_i}`` (``s = h - Gx``), i.e. the constraints whose multiplier
dominates their slack. The (symmetric) active-set KKT matrix is

    K = [[P, G_a', A'], [G_a, -diag(1 - a), 0], [A, 0, 0]],   G_a = diag(a) G,

where an inactive row ``i`` is replaced by the identity (its multiplier is pinned to zero).
Polishing solves ``K [x; z; y] = [-q; a h; b]`` and keeps the result only where it is a
verified KKT point (primal feasible, ``z >= 0``): this recovers the digits an interior point
method leaves behind. The backward pass solves ``K w = [dl/dx; a dl/dz; dl/dy]`` with the
same factorisation (OptNet-style implicit differentiation, exact for a nondegenerate active
set). For the backward the active set also holds every row that is tight at ``x`` (slack
zero to rounding, :func:`with_tight_rows`), whatever its multiplier: where ``x`` is
differentiable every tight row stays tight under a small perturbation, so the derivative
lies in the null space of all of them, not only of the rows a method's multipliers happen to
support (at a degenerate vertex several multiplier vectors are valid). Where ``x`` has a kink
(a weakly active row that leaves under some perturbation) this is the one-sided derivative
for perturbations that keep every tight row tight. Dependent tight rows are handled by the
regularised factorisation; where they leave several multiplier vectors valid and a loss
reads those multipliers, the rows affected are solved again for the change that moves the
strictly active rows' multipliers (:func:`kkt_adjoints`).
"""

from __future__ import annotations

from typing import NamedTuple

import torch
from torch import Tensor

from torchcbf.qp._data import QPData
from torchcbf.qp._lu import lu_factor_ex
from torchcbf.qp.status import Status

#: steps of iterative refinement on the regularised factor: the polished answer needs eight
#: (each step cuts the error along a weak curvature lam by delta / (lam + delta), and a P of
#: condition 1e10 has lam / delta = 10); the active-set guesses, judged to eps, and the
#: adjoints three
POLISH_REFINE_STEPS = 8
REFINE_STEPS = 3
#: a refinement step smaller than this fraction of the solution's largest entry (rounding of
#: float64) changes nothing further: the steps stop there
REFINED = 4 * torch.finfo(torch.float64).eps


class KKTFactor(NamedTuple):
    """LU factorisation of the equilibrated, regularised active-set KKT matrix ``D K D``
    (``D = diag(d)``), plus the exact matrix ``K``, the regularisation ``delta [B]`` of the
    equilibrated matrix, and ``weak [B, M]``: the rows of the active set that are only tight
    (their multiplier not above their slack; ``None``: not known). ``LU2, pivots2``: the
    factor with twice the regularisation (:func:`solve_kkt`), or None."""

    K: Tensor
    LU: Tensor
    pivots: Tensor
    active: Tensor
    ok: Tensor
    d: Tensor
    delta: Tensor
    weak: Tensor | None = None
    LU2: Tensor | None = None
    pivots2: Tensor | None = None


def build_kkt(P: Tensor, G: Tensor, A: Tensor, active: Tensor) -> Tensor:
    """Active-set KKT matrix ``[B, n+M+me, n+M+me]`` (see module docstring)."""
    B, n = P.shape[0], P.shape[-1]
    M, me = G.shape[-2], A.shape[-2]
    af = active.to(P.dtype)
    Ga = af.unsqueeze(-1) * G
    zM = P.new_zeros(B, M, me)
    zE = P.new_zeros(B, me, me)
    top = torch.cat((P, Ga.mT, A.mT), -1)
    mid = torch.cat((Ga, torch.diag_embed(af - 1.0), zM), -1)
    bot = torch.cat((A, zM.mT, zE), -1)
    del n
    return torch.cat((top, mid, bot), -2)


#: regularisation of a weak row relative to a strictly active one's where dependent rows
#: leave several multiplier vectors valid (:func:`kkt_adjoints`): the adjoint then moves the
#: strictly active rows' multipliers (the solver's selection: a pinned variable's one bound,
#: an equality rather than an inequality repeating it) and a weak row's by 1e-6 of that
WEAK_WEIGHT = 1e6


def factor_kkt(
    P: Tensor, G: Tensor, A: Tensor, active: Tensor, *, weak: Tensor | None = None
) -> KKTFactor:
    """Factor the active-set KKT matrix, equilibrated (``D K D`` with every row's largest
    entry near one, :func:`_equilibrate`), with a tiny quasi-definite regularisation.
    Without the equilibration the regularisation, relative to the largest entry, swamps the
    small ones: a weight of 5e5 beside one of 1e-3 (a filter's slack and its controls) leaves
    the polished vertex 1e-7 off and uncertified. ``weak [B, M]``: kept for the adjoints of
    dependent rows (:func:`kkt_adjoints`)."""
    K = build_kkt(P, G, A, active)
    d = _equilibrate(K)
    Ks = d.unsqueeze(-1) * K * d.unsqueeze(-2)
    scale = Ks.abs().amax((-2, -1)).clamp_min(1.0)
    delta = (1e-11 if K.dtype == torch.float64 else 1e-6) * scale
    shift = _signs(K, active, P.shape[-1], None) * delta.unsqueeze(-1)
    LU, pivots, ok = _checked_lu(Ks + torch.diag_embed(shift))
    return KKTFactor(K, LU, pivots, active, ok, d, delta, weak)


def backward_factor(
    P: Tensor, G: Tensor, A: Tensor, active: Tensor, backward_set: Tensor
) -> KKTFactor:
    """The backward's factor on ``backward_set [B, M]`` (:func:`with_tight_rows` of the
    solver's ``active`` set), the rows only tight marked weak."""
    return factor_kkt(P, G, A, backward_set, weak=backward_set & ~active)


def _signs(K: Tensor, active: Tensor, n: int, weak: Tensor | None) -> Tensor:
    """The regularisation's pattern ``[B, N]``: ``+1`` on the variables, ``-1`` on the
    active and equality rows (:data:`WEAK_WEIGHT` times that on ``weak`` rows), 0 on the
    inactive ones (pinned by the identity)."""
    rows = active.to(K.dtype)
    if weak is not None:
        rows = rows * torch.where(weak, WEAK_WEIGHT, 1.0)
    me = K.shape[-1] - n - active.shape[-1]
    return torch.cat((K.new_ones(K.shape[0], n), -rows, -K.new_ones(K.shape[0], me)), -1)


def _least_change_factor(fac: KKTFactor, rows: Tensor, n: int) -> KKTFactor:
    """The factors of ``fac``'s ``rows`` with the weak rows regularised more, at ``delta``
    and ``2 delta`` (:func:`solve_kkt` combines them)."""
    K, d, delta = (t.index_select(0, rows) for t in (fac.K, fac.d, fac.delta))
    active = fac.active.index_select(0, rows)
    weak = None if fac.weak is None else fac.weak.index_select(0, rows)
    Ks = d.unsqueeze(-1) * K * d.unsqueeze(-2)
    shift = _signs(K, active, n, weak) * delta.unsqueeze(-1)
    LU, pivots, ok = _checked_lu(Ks + torch.diag_embed(shift))
    LU2, pivots2, ok2 = _checked_lu(Ks + torch.diag_embed(2.0 * shift))
    return KKTFactor(K, LU, pivots, active, ok & ok2, d, delta, weak, LU2, pivots2)


def _checked_lu(K: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """``(LU, pivots, ok [B])`` of ``K [B, N, N]``, where ``ok`` says the factor is usable.

    A batched LU of the linear algebra library can come back broken without saying so
    (:mod:`torchcbf.qp._lu` works around the case known); each row is checked: pivots in
    range, a finite factor, and the solve of ``K 1`` giving back ``1`` to within 0.5 (far
    above the rounding of any factor the regularisation allows). A broken row gets the
    identity permutation, so that solving with it never raises, and ``ok = False``: its
    status says so, not an exception."""
    LU, pivots, info = lu_factor_ex(K)
    N = K.shape[-1]
    in_range = ((pivots >= 1) & (pivots <= N)).all(-1)
    ok = (info == 0) & in_range & torch.isfinite(LU).flatten(-2).all(-1)
    if N == 0:
        return LU, pivots, ok
    identity = torch.arange(1, N + 1, dtype=pivots.dtype, device=pivots.device)
    pivots = torch.where(in_range.unsqueeze(-1), pivots, identity)
    LU = torch.where(ok.view(-1, 1, 1), LU, torch.eye(N, dtype=K.dtype, device=K.device))
    ones = K.new_ones(*K.shape[:-1], 1)
    back = torch.linalg.lu_solve(LU, pivots, K @ ones)
    ok = ok & ((back - 1.0).abs().amax((-2, -1)) <= 0.5)
    return LU, pivots, ok


def _equilibrate(K: Tensor, sweeps: int = 3) -> Tensor:
    """``d [B, N]``, powers of two, with every row and column of ``diag(d) K diag(d)`` of
    largest entry in ``[0.5, 2]`` after a few symmetric Ruiz sweeps (a row of zeros keeps
    ``d = 1``). Powers of two scale without rounding."""
    d = torch.ones(K.shape[:-1], dtype=K.dtype, device=K.device)
    for _ in range(sweeps):
        row = (d.unsqueeze(-1) * K * d.unsqueeze(-2)).abs().amax(-1)
        step = torch.where(row > 0, row.rsqrt(), torch.ones_like(row))
        d = d * torch.exp2(torch.round(torch.log2(step)))
    return d


def solve_kkt(fac: KKTFactor, rhs: Tensor, steps: int = REFINE_STEPS) -> Tensor:
    """Solve ``K w = rhs`` (``rhs [B, N]``) by the equilibrated, regularised factor and
    ``steps`` of iterative refinement on ``K`` itself.

    Where dependent active rows make ``K`` singular and ``rhs`` has a part outside its range
    (a loss on multipliers that are not unique), the regularised solve answers that part
    with ``-1 / delta`` times it, and each refinement step adds as much again. A factor with
    ``LU2`` solves by ``2 K_{2 delta}^-1 - K_delta^-1`` instead, which maps that part to
    zero and the range as ``K``'s inverse to first order (only for such rows: it triples the
    error along a weak curvature, which refinement then corrects more slowly)."""
    d = fac.d.unsqueeze(-1)

    def solve(r: Tensor) -> Tensor:
        w = torch.linalg.lu_solve(fac.LU, fac.pivots, d * r)
        if fac.LU2 is not None:
            w = 2.0 * torch.linalg.lu_solve(fac.LU2, fac.pivots2, d * r) - w
        return d * w

    r = rhs.unsqueeze(-1)
    w = solve(r)
    # on a CPU, asking whether the refinement has reached rounding costs no device
    # synchronisation: the steps stop there
    check = rhs.device.type == "cpu"
    for _ in range(steps):
        step = solve(r - fac.K @ w)
        w = w + step
        if check and not bool((step.abs() > REFINED * w.abs().amax(-2, keepdim=True)).any()):
            break
    return w.squeeze(-1)


def active_set(z: Tensor, s: Tensor) -> Tensor:
    """Constraints whose multiplier exceeds their slack, ``[B, M]`` bool."""
    return z > s


#: slack, relative to :func:`row_scale`, below which a row counts as tight at ``x``: the
#: rounding every exact path leaves in a tight row's residual
TIGHT = 1e4 * torch.finfo(torch.float64).eps


def with_tight_rows(G: Tensor, h: Tensor, x: Tensor, active: Tensor, status: Tensor) -> Tensor:
    """``active [B, M]`` plus the rows tight at ``x`` in ``SOLVED`` rows (see the module
    docstring): the active set of the backward."""
    if G.shape[-2] == 0:
        return active
    slack = h - torch.einsum("bmn,bn->bm", G, x)
    tight = slack <= TIGHT * row_scale(G, h, x)
    return active | (tight & (status == int(Status.SOLVED)).unsqueeze(-1))


def row_scale(R: Tensor, r: Tensor, x: Tensor) -> Tensor:
    """Scale ``|r_i| + max|R_i| (1 + max|x|)`` of each row's residual ``R_i x - r_i`` for
    ``R [B, K, N], r [B, K], x [B, N]`` -> ``[B, K]``. Every exact path judges a row's
    violation on it, so a tiny row next to a huge one still counts."""
    return r.abs() + R.abs().amax(-1) * (1.0 + x.abs().amax(-1, keepdim=True))


def polish(
    data: QPData,
    x: Tensor,
    s: Tensor,
    z: Tensor,
    y: Tensor,
    status: Tensor,
    *,
    eps: float,
) -> tuple[Tensor, Tensor, Tensor, Tensor, KKTFactor, Tensor, Tensor]:
    """Solve the active-set KKT system and keep verified answers. Returns
    ``(x, z, y, status, active, verified, exact)`` (``active [B, M]``: the active set solved
    on); rows whose polished point passes the
    ``eps`` checks (stationarity included) become ``SOLVED`` (also rescuing
    ``MAX_ITER``/``NUMERICAL_ERROR`` rows whose guess is right) and are marked in
    ``verified [B]``. ``exact [B]`` marks the verified rows whose polished point is a KKT
    point to rounding (:func:`kkt_point`). Near nearly parallel active rows a wrong active
    set can pass the ``eps`` checks but not these."""
    P, q, G, h, A, b = data
    M = h.shape[-1]
    candidate = (
        (status == int(Status.SOLVED))
        | (status == int(Status.MAX_ITER))
        | (status == int(Status.NUMERICAL_ERROR))
    )
    # Guesses of the active set, tried in order; a row keeps the first that verifies. The
    # first (multiplier above slack) is almost always right; near-degenerate rows (a weakly
    # active constraint, two nearly parallel ones) can need the slack- or multiplier-based
    # guess, and without a verified polish the interior point answer is only accurate to
    # about sqrt(eps) in x.
    tol = eps**0.5
    guesses = [active_set(z, s)]
    if M > 0:
        guesses.append(s <= tol * (1.0 + s.abs().amax(-1, keepdim=True)))
        guesses.append(z >= tol * (1.0 + z.abs().amax(-1, keepdim=True)))
        # a zero row (an infinite bound, h = +inf) bounds nothing: never active, whatever
        # multiplier the interior point left on it
        bounds = (G != 0).any(-1)
        guesses = [g & bounds for g in guesses]
    chosen = torch.zeros_like(candidate)
    act = torch.zeros_like(guesses[0])
    for guess in guesses:
        trial = guess & candidate.unsqueeze(-1)
        ok_g = _verified(data, trial, eps) & candidate & ~chosen
        act = torch.where(ok_g.unsqueeze(-1), trial, act)
        chosen = chosen | ok_g
    act = torch.where(chosen.unsqueeze(-1), act, guesses[0] & candidate.unsqueeze(-1))
    xp, zp, yp, solved = solve_active(data, act, POLISH_REFINE_STEPS)
    ok = chosen & solved
    keep = ok.unsqueeze(-1)
    x = torch.where(keep, xp, x)
    z = torch.where(keep, zp.clamp_min(0.0), z)
    y = torch.where(keep, yp, y)
    status = torch.where(ok, int(Status.SOLVED), status)
    exact = ok & kkt_point(data, xp, zp, yp)
    return x, z, y, status, act, ok, exact


def solve_active(
    data: QPData,
    act: Tensor,
    steps: int = REFINE_STEPS,
) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """``(x [B,n], z [B,M], y [B,E], ok [B])``: the equality-constrained solution with the
    rows ``act [B, M]`` of ``Gx <= h`` held tight (``z`` zero off ``act``), ``ok`` where the
    factorisation is usable and the solution finite.

    Only the active rows enter the system (gathered, padded to the batch's largest active
    set with rows that pin their multiplier to zero), so its size is
    ``n + max|act| + E``, not ``n + M + E``: a problem with thousands of rows and a handful
    active costs about what the active rows cost. Finding the largest active set is one
    host synchronisation."""
    P, q, G, h, A, b = data
    n, M = q.shape[-1], h.shape[-1]
    counts = act.sum(-1)
    Ka = int(counts.max()) if act.numel() else 0
    if Ka == M:
        Ga, ha, valid, order = G, h, act, None
    else:
        # active rows first, in their order; then the first inactive ones as padding
        order = torch.argsort((~act).to(torch.int8), dim=-1, stable=True)[:, :Ka]
        valid = torch.arange(Ka, device=q.device) < counts.unsqueeze(-1)
        Ga = G.gather(1, order.unsqueeze(-1).expand(-1, -1, n))
        ha = h.gather(1, order)
    fac = factor_kkt(P, Ga, A, valid)
    sol = solve_kkt(fac, torch.cat((-q, ha * valid.to(h.dtype), b), -1), steps)
    xp, za, yp = sol[..., :n], sol[..., n : n + Ka] * valid.to(sol.dtype), sol[..., n + Ka :]
    zp = za if order is None else za.new_zeros(za.shape[0], M).scatter(1, order, za)
    return xp, zp, yp, fac.ok & torch.isfinite(sol).all(-1)


def scaled_violation(G: Tensor, h: Tensor, A: Tensor, b: Tensor, x: Tensor) -> Tensor:
    """``[B]`` the largest violation of ``Gx <= h`` and ``Ax = b`` by ``x``, each row judged
    on its own scale (:func:`row_scale`); 0 without rows."""
    R, r = torch.cat((G, A), -2), torch.cat((h, b), -1)
    res = (torch.einsum("bmn,bn->bm", R, x) - r) / row_scale(R, r, x).clamp_min(
        torch.finfo(x.dtype).tiny
    )
    M = G.shape[-2]
    pad = res.new_zeros(len(res), 1)
    return torch.cat((res[..., :M].clamp_min(0.0), res[..., M:].abs(), pad), -1).amax(-1)


#: machine epsilons of its terms the stationarity of a KKT point to rounding may miss by
#: (:func:`kkt_point`): more than its other tests' 1e4, as its terms can cancel by orders of
#: magnitude (multipliers on rows of 1e12 against an objective gradient of 1e-6); at 1e4 such
#: answers, right to 1e-9, went uncertified, and 3e5 certifies no wrong answer on 3,840
#: problems with rows scaled by 1e10-1e16 and ``P`` of condition up to 1e10
STATIONARY = 3e5


def kkt_point(
    data: QPData,
    x: Tensor,
    z: Tensor,
    y: Tensor,
) -> Tensor:
    """Rows ``[B]`` where ``(x, z, y)`` is a KKT point to rounding (``1e4`` machine
    epsilons): no row violated, no multiplier negative, every row with a positive
    multiplier tight, each row judged on its own scale (:func:`row_scale`), and stationary
    (:func:`stationarity_error`, to :data:`STATIONARY` epsilons). A convex QP's KKT point
    is its minimiser, so this certifies an answer whatever method produced it."""
    P, q, G, h, A, b = data
    rounding = 1e4 * torch.finfo(x.dtype).eps
    slack = (h - torch.einsum("bmn,bn->bm", G, x)) / row_scale(G, h, x).clamp_min(
        torch.finfo(x.dtype).tiny
    )
    zs, scale = multiplier_size(G, z, gradient_size(q, torch.einsum("bij,bj->bi", P, x)))
    loose = (zs > rounding * scale.unsqueeze(-1)) & (slack > rounding)
    negative = (zs < -rounding * scale.unsqueeze(-1)).any(-1)
    return (
        (scaled_violation(G, h, A, b, x) <= rounding)
        & ~negative
        & ~loose.any(-1)
        & (stationarity_error(P, q, G, A, x, z, y) <= STATIONARY * torch.finfo(x.dtype).eps)
    )


def gradient_size(q: Tensor, Px: Tensor) -> Tensor:
    """The objective gradient's size ``max(max|q|, max|Px|) [B]`` for ``q, Px [B, N]``: the
    scale of :func:`multiplier_size` where no multiplier term is larger."""
    return torch.maximum(q.abs().amax(-1), Px.abs().amax(-1))


def multiplier_size(R: Tensor, mult: Tensor, grad: Tensor) -> tuple[Tensor, Tensor]:
    """Each multiplier's size as its term in the stationarity, ``mult_i max|R_i|``
    ``[B, K]``, and the scale it is judged on ``[B]``: the largest such term or objective
    gradient ``grad [B]`` (:func:`gradient_size`), or 1 where all are zero. Scaling the
    objective or a row leaves the ratio alone, so a wrong sign is seen whatever the units
    (an absolute test passes ``-1e-21`` where the true multipliers are ``1e-21``)."""
    size = mult * R.abs().amax(-1)
    scale = torch.maximum(grad, size.abs().amax(-1)) if R.shape[-2] else grad
    return size, torch.where(scale > 0, scale, 1.0)


def kkt_residuals_ok(
    data: QPData,
    x: Tensor,
    z: Tensor,
    y: Tensor,
    eps: float,
) -> Tensor:
    """Rows ``[B]`` where ``(x, z, y)`` is a KKT point to ``eps``: every row violated by at
    most ``eps`` of its own scale (:func:`scaled_violation`), multipliers nonnegative to
    ``eps``, stationary (``|Px + q + G'z + A'y|`` at most ``eps`` of the largest of its
    terms, the interior point method's own test) and complementary (duality gap
    ``z'(h - Gx) + y'(b - Ax)`` at most ``eps`` of its terms). The test an outside solver's
    answer passes before it is reported solved; finite values only."""
    P, q, G, h, A, b = data
    finite = torch.isfinite(x).all(-1) & torch.isfinite(z).all(-1) & torch.isfinite(y).all(-1)
    x, z, y = (torch.nan_to_num(t, nan=0.0, posinf=0.0, neginf=0.0) for t in (x, z, y))
    za = torch.cat((z, z.new_zeros(len(z), 1)), -1)
    zmax = 1.0 + za.abs().amax(-1)
    slack = h - torch.einsum("bmn,bn->bm", G, x)
    eq_res = b - torch.einsum("ben,bn->be", A, x)
    gap = (z * slack).sum(-1) + (y * eq_res).sum(-1)
    gap_scale = (
        1.0
        + (x * torch.einsum("bij,bj->bi", P, x)).sum(-1).abs()
        + (q * x).sum(-1).abs()
        + (z * h).sum(-1).abs()
        + (y * b).sum(-1).abs()
    )
    terms = (
        torch.einsum("bij,bj->bi", P, x),
        q,
        torch.einsum("bmn,bm->bn", G, z),
        torch.einsum("ben,be->bn", A, y),
    )
    dual_res = sum(terms).abs().amax(-1)
    dual_scale = 1.0 + torch.stack([t.abs().amax(-1) for t in terms], -1).amax(-1)
    return (
        finite
        & (scaled_violation(G, h, A, b, x) <= eps)
        & (za.amin(-1) >= -eps * zmax)
        & (dual_res <= eps * dual_scale)
        & (gap.abs() <= eps * gap_scale)
    )


def stationarity_error(
    P: Tensor, q: Tensor, G: Tensor, A: Tensor, x: Tensor, z: Tensor, y: Tensor
) -> Tensor:
    """``max_i |r_i| / s_i [B]`` of ``r = Px + q + G'z + A'y``, each component judged on
    its own terms ``s = |P||x| + |q| + |G|'|z| + |A|'|y|``. The linear solves of the polish
    are regularised (``factor_kkt``), which a weak curvature (``P`` of condition 1e10, or a
    singular ``P`` beside a free direction) leaves visible here and nowhere else."""
    r = (
        torch.einsum("bij,bj->bi", P, x)
        + q
        + torch.einsum("bmn,bm->bn", G, z)
        + torch.einsum("ben,be->bn", A, y)
    )
    objective = torch.einsum("bij,bj->bi", P.abs(), x.abs()) + q.abs()
    s = (
        objective
        + torch.einsum("bmn,bm->bn", G.abs(), z.abs())
        + torch.einsum("ben,be->bn", A.abs(), y.abs())
    )
    # a component whose terms are all rounding noise (a zero multiplier computed as 1e-27)
    # is judged against the largest component's scale; where the objective's gradient is
    # zero (P x = 0, q = 0: every multiplier term is noise) against multipliers of unit size
    # too. Elsewhere nothing absolute: true multipliers of 1e-21 (huge rows, a tiny
    # objective) are no noise.
    rounding = 1e4 * torch.finfo(x.dtype).eps
    flat = objective.amax(-1, keepdim=True) == 0
    unit = torch.where(flat, G.abs().sum(-2) + A.abs().sum(-2), 0.0)
    s = s + rounding * (s.amax(-1, keepdim=True) + unit)
    return (r.abs() / s.clamp_min(torch.finfo(x.dtype).tiny)).amax(-1)


def _verified(data: QPData, act: Tensor, eps: float) -> Tensor:
    """Rows whose equality-constrained solution on ``act`` is primal and dual feasible and
    stationary to ``eps``."""
    P, q, G, h, A, b = data
    M = h.shape[-1]
    xp, zp, yp, ok = solve_active(data, act)
    ok = ok & (stationarity_error(P, q, G, A, xp, zp, yp) <= eps)
    viol = torch.cat(
        (
            (torch.einsum("bmn,bn->bm", G, xp) - h).clamp_min(0.0),
            (torch.einsum("bmn,bn->bm", A, xp) - b).abs(),
        ),
        -1,
    )
    if viol.shape[-1] > 0:
        scale = 1.0 + torch.cat((h.abs(), b.abs()), -1).amax(-1)
        ok = ok & (viol.amax(-1) <= eps * scale)
    if M > 0:
        ok = ok & (zp.amin(-1) >= -eps * (1.0 + zp.abs().amax(-1)))
    return ok


def kkt_adjoints(
    fac: KKTFactor,
    x: Tensor,
    z: Tensor,
    y: Tensor,
    status: Tensor,
    gx: Tensor,
    gz: Tensor,
    gy: Tensor,
) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Adjoints ``(wx [B,n], wz [B,M], wy [B,E], lam [B,M])`` of the active-set KKT system for
    output gradients ``gx, gz, gy`` (``lam``: the multipliers on the active set); see
    :func:`input_gradients`. Rows that are not ``SOLVED`` get zeros."""
    n, M = x.shape[-1], z.shape[-1]
    af = fac.active.to(x.dtype)
    rhs = torch.cat((gx, gz * af, gy), -1)
    w = solve_kkt(fac, rhs)
    # rows where the regularisation took up a part of rhs (K singular there, by dependent
    # active rows, and rhs outside its range): their answer is that part over delta. They
    # are solved again for the least change of the strictly active rows' multipliers; one
    # host synchronisation asks whether any row is one
    absorbed = fac.delta * (w / fac.d)[..., n:].abs().amax(-1)
    dependent = absorbed > 1e-3 * (fac.d * rhs).abs().amax(-1)
    ok = fac.ok
    if bool(dependent.any()):
        rows = dependent.nonzero().squeeze(-1)
        refactored = _least_change_factor(fac, rows, n)
        w = w.index_copy(0, rows, solve_kkt(refactored, rhs.index_select(0, rows)))
        ok = ok.index_copy(0, rows, ok.index_select(0, rows) & refactored.ok)
    good = (status == int(Status.SOLVED)) & ok & torch.isfinite(w).all(-1)
    w = torch.where(good.unsqueeze(-1), w, torch.zeros_like(w))
    return w[..., :n], w[..., n : n + M] * af, w[..., n + M :], z * af


def input_gradients(
    x: Tensor,
    lam: Tensor,
    y: Tensor,
    wx: Tensor,
    wz: Tensor,
    wy: Tensor,
    need: tuple[bool, ...] = (True,) * 6,
) -> tuple[Tensor | None, ...]:
    """Gradients ``(dP, dq, dG, dh, dA, db)`` from the KKT adjoints (``None`` where ``need``
    says an input needs none): ``dP = -(wx x' + x wx')/2``, ``dq = -wx``,
    ``dG = -(lam wx' + wz x')``, ``dh = wz``, ``dA = -(y wx' + wy x')``, ``db = wy``."""

    def outer(a: Tensor, b: Tensor) -> Tensor:
        return a.unsqueeze(-1) * b.unsqueeze(-2)

    dP = -0.5 * (outer(wx, x) + outer(x, wx)) if need[0] else None
    dG = -(outer(lam, wx) + outer(wz, x)) if need[2] else None
    dA = -(outer(y, wx) + outer(wy, x)) if need[4] else None
    return dP, -wx if need[1] else None, dG, wz if need[3] else None, dA, wy if need[5] else None
