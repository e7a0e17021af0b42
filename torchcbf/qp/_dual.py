"""Batched dual active-set method (Goldfarb-Idnani) for small strictly convex QPs.

Solves ``min 1/2 x'Px + q'x  s.t.  Rx <= r`` (``N`` variables, ``M`` rows, ``P`` positive
definite) for a large batch of small problems, e.g. ``N = 4``, ``M = 8`` at ``B = 4096``.

The method starts at the unconstrained minimiser ``x = -P^{-1} q`` (dual feasible with every
multiplier zero) and repeats, for every row of the batch at once: pick the most violated
constraint ``p``; move ``x`` along the direction that reduces ``p``'s violation while keeping
the active rows ``S`` tight, raising ``lam_p`` and adjusting ``lam_S``; either ``p`` becomes
tight (full step: ``p`` joins ``S``) or an active multiplier reaches zero first (partial step:
that row leaves ``S``, ``p`` stays pending). The dual objective increases at every step, so
no active set repeats and the method ends in finitely many steps at the exact solution. The
active rows stay linearly independent, hence at most ``N`` of them: ``S`` is held in ``N``
slots (an empty slot holds the spare index ``M``).

Each step solves ``W_SS d = W_Sp`` with ``W = R P^{-1} R'`` restricted to the slots (an
``N x N`` system, empty slots padded with the identity) by the unrolled elimination of
:mod:`torchcbf.qp._enum`. Data are stored batch-last ("planes": every scalar entry of every
problem is one contiguous ``[B]`` vector), so each step of the small linear algebra is one
elementwise tensor operation over the whole batch and the cost per step does not depend on
per-matrix kernel launches.

A row finishes when nothing is pending and no inactive row is violated beyond rounding
(judged on each row's own scale; a row already active is never picked again). The
multipliers are then re-solved exactly on the final active set, which removes the rounding
the rank-one updates accumulate, and the point is checked as a KKT point. Rows
where no step restores ``p`` (an infeasible problem, or a degenerate vertex where ``p`` is
tight to rounding) stop there and are judged by the same check. Rows that run out of steps,
have ``P`` not positive definite or fail the final check are reported in ``ok`` and left to
the caller's fallback.
On a CPU the test "is every row done" runs every step (it costs no device synchronisation);
on other devices every ``check_every`` steps.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import torch
from torch import Tensor

from torchcbf.qp import _dual_native, _dual_triton, _kkt
from torchcbf.qp._enum import _eliminate


class DualFactor(NamedTuple):
    """What the backward pass needs: planes of the Cholesky factor, the active slots and the
    gathered columns of ``R'`` and ``P^{-1} R'`` on them."""

    L: Tensor  # [N, N, B] lower Cholesky factor of P
    slots: Tensor  # [N, B] int64 row index per slot (M: empty)
    R_S: Tensor  # [N(component), N(slot), B]
    U_S: Tensor  # [N(component), N(slot), B] = P^{-1} R_S'
    ok: Tensor  # [B] rows solved by this method
    #: [B] condition estimate of P where the implementation computed it (the Triton kernel)
    condition: Tensor | None = None


class NativeFactor(NamedTuple):
    """What the backward pass needs from the C kernel's forward, batch first."""

    G: Tensor  # [B, M, N]
    L: Tensor  # [B, N, N] lower Cholesky factor of P
    slots: Tensor  # [B, N] int64 row index per slot (M: empty)
    ok: Tensor  # [B] rows solved by this method


#: implementations of the method (:func:`dual_engine` picks one)
ENGINES = ("c", "triton", "torch")


def dual_engine(q: Tensor, M: int) -> str:
    """The implementation :func:`solve_dual` runs for ``q [B, N]`` with ``M`` rows: the C
    kernel for float64 on the CPU (where built), the Triton kernel on CUDA (where Triton
    imports and the problem fits its tiles), else torch."""
    if _dual_native.applies(q):
        return "c"
    return "triton" if _dual_triton.applies(q, M) else "torch"


class DualResult(NamedTuple):
    """``x [B,N]``, ``z [B,M]``, ``active [B,M]`` bool, ``ok [B]``, ``iterations [B]``, the
    backward's factor and ``infeasible [B]``: rows proved infeasible by a Farkas certificate
    (the C kernel only; the torch implementation leaves them to the caller's fallback)."""

    x: Tensor
    z: Tensor
    active: Tensor
    ok: Tensor
    iterations: Tensor
    factor: DualFactor | NativeFactor
    infeasible: Tensor


def _cholesky(P: Tensor) -> tuple[Tensor, Tensor]:
    """Lower Cholesky factor of ``P [N, N, B]`` column by column; ``(L, positive_definite)``.

    A pivot below ``1e-13`` times its diagonal entry marks the row not positive definite (the
    factor is then kept finite, not meaningful)."""
    N = P.shape[0]
    L = torch.zeros_like(P)
    pd = torch.ones(P.shape[-1], dtype=torch.bool, device=P.device)
    for j in range(N):
        col = P[j:, j]
        for k in range(j):
            col = torch.addcmul(col, L[j:, k], L[j, k], value=-1.0)
        piv = col[0]
        pd = pd & (piv > 1e-13 * P[j, j].abs())
        d = torch.sqrt(torch.where(pd, piv, 1.0))
        L[j:, j] = col / d
    return L, pd


def _cho_solve(L: Tensor, rhs: Tensor) -> Tensor:
    """Solve ``L L' y = rhs`` for ``L [N, N, B]`` and ``rhs [N, *cols, B]``."""
    N = L.shape[0]
    extra = rhs.dim() - 2
    Lv = L.view(N, N, *([1] * extra), L.shape[-1])
    y: list[Tensor] = []
    for i in range(N):
        acc = rhs[i]
        for k in range(i):
            acc = torch.addcmul(acc, Lv[i, k], y[k], value=-1.0)
        y.append(acc / Lv[i, i])
    out: list[Tensor] = [y[0]] * N
    for i in range(N - 1, -1, -1):
        acc = y[i]
        for k in range(i + 1, N):
            acc = torch.addcmul(acc, Lv[k, i], out[k], value=-1.0)
        out[i] = acc / Lv[i, i]
    return torch.stack(out, 0)


def _slot_system(R_S: Tensor, U_S: Tensor, empty: Tensor) -> Tensor:
    """``W_SS [N, N, B]`` with the identity on empty slots."""
    W = _contract(R_S.unsqueeze(2), U_S.unsqueeze(1))  # [k, l]: R_{S_k} P^{-1} R_{S_l}'
    W.diagonal(dim1=0, dim2=1).add_(empty.T.to(W.dtype))
    return W


class _Data(NamedTuple):
    """Per-problem constants, batch last."""

    Rc: Tensor  # [N, M, B] R' by components
    hr: Tensor  # [M, B]
    UR: Tensor  # [2N, M + 1, B] P^{-1} R' stacked on R' (column M: zero spare)
    tol: Tensor  # [M, B] violation beyond which a row joins the active set
    slots: Tensor  # [N, 1] slot indices
    rank: Tensor  # [N, 1] N - slot index: the first empty slot scores highest
    inv_norm: Tensor  # [M, B] 1 / sqrt(R_i P^{-1} R_i'), to pick the farthest violated row


class _State(NamedTuple):
    """Iterate of the dual active-set method, batch last."""

    x: Tensor  # [N, B]
    lam_S: Tensor  # [N, B] multipliers of the slots
    lam_p: Tensor  # [B] multiplier of the pending row
    S: Tensor  # [N, B] int64 row per slot (M: empty)
    U_S: Tensor  # [N, N, B] P^{-1} R_S' by (component, slot); zero on empty slots
    Hs: Tensor  # [N, N, B] W_SS^{-1}, identity on empty slots
    p: Tensor  # [B] int64 pending (or next) row
    pending: Tensor  # [B] bool
    done: Tensor  # [B] bool
    fail: Tensor  # [B] bool
    iters: Tensor  # [B] int64


def _contract(a: Tensor, b: Tensor) -> Tensor:
    """``sum_c a[c] b[c]`` over the leading dimension (broadcasting the rest).

    Accumulated in place, so the only new tensor has the size of the result (fewer and
    smaller allocations than ``(a * b).sum(0)``: the step is allocator-bound on a CPU)."""
    out = a[0] * b[0]
    for c in range(1, a.shape[0]):
        out.addcmul_(a[c], b[c])
    return out


def _step(data: _Data, st: _State) -> _State:
    """One add-or-drop step for every row that is not done.

    Empty slots have zero columns in ``U_S`` (so ``W_Sp`` is zero there) and ``d`` is masked
    to zero on them, so no update below moves an empty slot."""
    N, B = st.x.shape
    M = data.hr.shape[0]
    x, lam_S, lam_p, S, U_S, Hs, p, pending, done, fail, iters = st
    free = (S == M).to(x.dtype)  # 1.0 on empty slots
    v = _contract(data.Rc, x.unsqueeze(1)) - data.hr  # [M, B] violation R x - r
    # candidates: violated beyond rounding (per row) and not already active; rounding on an
    # active row must never bring it in a second time
    member = x.new_zeros(M + 1, B).scatter_(0, S, 1.0)[:M]
    score = torch.where((v > data.tol) & (member == 0), v * data.inv_norm, -math.inf)
    best, pnew = score.max(0)
    done = done | ~(pending | (best > -math.inf))
    p = torch.where(pending, p, pnew)
    v_p = v.gather(0, p.unsqueeze(0)).squeeze(0)
    UR_p = data.UR.gather(1, p.view(1, 1, B).expand(2 * N, 1, B)).squeeze(1)
    U_p, R_p = UR_p[:N], UR_p[N:]

    W_Sp = _contract(U_S, R_p.unsqueeze(1))  # [N, B]
    W_pp = _contract(U_p, R_p)
    # W_SS^{-1} W_Sp, exactly zero on empty slots (the drop update leaves rounding there)
    d = _contract(Hs, W_Sp.unsqueeze(1)) * (1.0 - free)
    z = W_pp - _contract(W_Sp, d)  # Schur complement: 0 when p depends on the active rows
    dx = _contract(U_S.transpose(0, 1), d.unsqueeze(1)) - U_p  # R_p dx = -z, R_S dx = 0

    # full step (p becomes tight) unless p depends on the active rows or no slot is free;
    # partial step: the first active multiplier to reach zero leaves
    room, first_free = (free * data.rank).max(0)
    t_full = torch.where((z <= 1e-10 * W_pp) | (room == 0), math.inf, v_p / z)
    ratio = torch.where(d > 0, lam_S / d, math.inf)
    t_part, k_drop = ratio.min(0)
    t = torch.minimum(t_full, t_part)
    # no step restores p: the row stops here, and the exact check on the final active set
    # decides (at a degenerate vertex p is tight to rounding and the point is optimal)
    done = done | ~torch.isfinite(t)
    full = ~done & (t_full <= t_part)
    part = ~done & (t_full > t_part)
    t = torch.where(done, 0.0, t)

    x = torch.addcmul(x, dx, t)
    lam_S = torch.addcmul(lam_S, d, t, value=-1.0)
    lam_p = lam_p + t
    e_drop = part & (data.slots == k_drop)
    e_add = full & (data.slots == first_free)
    f_drop, f_add = e_drop.to(x.dtype), e_add.to(x.dtype)
    # inverse updates of W_SS: bordering (add) and its reverse (drop)
    Hk = Hs.gather(0, k_drop.view(1, 1, B).expand(1, N, B)).squeeze(0)
    a_coef = torch.where(full, 1.0 / z, 0.0)
    b_coef = torch.where(part, 1.0 / Hk.gather(0, k_drop.unsqueeze(0)).squeeze(0), 0.0)
    u = d - f_add
    # in place: Hs and U_S belong to the iteration (fresh at the start and after compaction).
    # The slot being filled has its identity entry removed first (so its new diagonal is 1/z,
    # not 1 + 1/z - 1), and the slot being emptied is reset to exact identity afterwards.
    Hs.diagonal(dim1=0, dim2=1).sub_(f_add.T)
    Hs.addcmul_((u * a_coef).unsqueeze(1), u.unsqueeze(0))
    Hs.addcmul_((Hk * b_coef).unsqueeze(1), Hk.unsqueeze(0), value=-1.0)
    kept = 1.0 - f_drop
    Hs.mul_(kept.unsqueeze(1) * kept.unsqueeze(0))
    Hs.diagonal(dim1=0, dim2=1).add_(f_drop.T)
    keep = 1.0 - f_drop - f_add
    U_S.mul_(keep.unsqueeze(0)).addcmul_(U_p.unsqueeze(1), f_add)
    lam_S = torch.addcmul(lam_S * keep, lam_p, f_add)
    lam_p = torch.where(full, 0.0, lam_p)
    S = torch.where(e_drop, M, torch.where(e_add, p, S))
    return _State(x, lam_S, lam_p, S, U_S, Hs, p, part, done, fail, iters + ~done)


def solve_dual(
    P: Tensor,
    q: Tensor,
    G: Tensor,
    h: Tensor,
    *,
    eps: float,
    max_iter: int,
    check_every: int = 5,
    engine: str | None = None,
) -> DualResult:
    """Solve ``min 1/2 x'Px + q'x s.t. Gx <= h`` for ``P [B,N,N], q [B,N], G [B,M,N],
    h [B,M]`` (finite, ``M >= 1``, float64 recommended). See the module docstring; rows with
    ``ok = False`` hold zeros and must be solved by another method.

    ``engine`` picks the implementation (:data:`ENGINES`; ``None``: :func:`dual_engine`):
    ``"c"`` the C kernel of :mod:`torchcbf.qp._dual_native` (the same algorithm, one problem
    at a time), ``"triton"`` one Triton launch (:mod:`torchcbf.qp._dual_triton`, one
    problem per lane; on CUDA, or on the CPU under ``TRITON_INTERPRET=1``), ``"torch"``
    tensor operations.

    When the host checks progress (every step on a CPU, every ``check_every`` steps
    elsewhere) and at most a third of the rows still run, the iteration continues on those rows
    only (finished rows are written back first), so the long tail of a few hard rows costs
    little."""
    B, N = q.shape
    M = h.shape[-1]
    engine = dual_engine(q, M) if engine is None else engine
    if engine not in ENGINES:
        raise ValueError(f"engine must be one of {ENGINES} or None, got {engine!r}")
    if engine == "triton" and not _dual_triton.applies(q, M, explicit=True):
        raise ValueError(
            "engine='triton' needs Triton, float32 or float64 data on CUDA (on the CPU: "
            f"TRITON_INTERPRET=1), at most {_dual_triton.MAX_VARS} variables and "
            f"{_dual_triton.MAX_TILE} entries in the [N, M] tile padded to powers of two; got "
            f"{q.dtype}, N={N}, M={M} on {q.device}"
        )
    if engine == "c":
        x, z, active, slots, L, ok, iters, infeasible = _dual_native.forward(
            P, q, G, h, eps, max_iter
        )
        return DualResult(x, z, active, ok, iters, NativeFactor(G, L, slots, ok), infeasible)
    if engine == "triton":
        sol = _dual_triton.solve(P, q, G, h, eps=eps, max_iter=max_iter)
        factor = DualFactor(sol.L, sol.S, sol.R_S, sol.U_S, sol.ok, sol.condition)
        none = torch.zeros_like(sol.ok)
        return DualResult(sol.x.T, sol.z.T, sol.active.T, sol.ok, sol.iters, factor, none)
    dtype, device = q.dtype, q.device
    Pp = P.permute(1, 2, 0).contiguous()
    L, pd = _cholesky(Pp)
    Rc = G.permute(2, 1, 0).contiguous()  # [N, M, B]: R' by components
    rhs = torch.cat((Rc, q.new_zeros(N, 1, B), -q.T.unsqueeze(1)), 1)
    sol = _cho_solve(L, rhs)  # [P^{-1} R', 0, x_u]
    xu = sol[:, M + 1]
    UR = torch.cat((sol[:, : M + 1], rhs[:, : M + 1]), 0)
    hr = h.T.contiguous()
    row_scale = _kkt.row_scale(G, h, xu.T).T  # [M, B]
    # a row joins while violated beyond rounding, not beyond eps: near a nearly parallel
    # active row a violation of eps can hide an error of sqrt(eps) in x
    add_tol = 1e4 * torch.finfo(dtype).eps * row_scale
    slots = torch.arange(N, device=device).unsqueeze(-1)
    w_diag = _contract(sol[:, :M], Rc)
    inv_norm = torch.where(w_diag > 0, w_diag.clamp_min(1e-300).rsqrt(), 0.0)
    data = _Data(Rc, hr, UR, add_tol, slots, (N - slots).to(dtype), inv_norm)
    S, fail, done, iters = _iterate(data, xu, pd, max_iter, check_every)

    # exact multipliers and primal point on the final active set (the iterates accumulate
    # rounding), then the KKT check with per-row tolerances
    UR_S = UR.gather(1, S.unsqueeze(0).expand(2 * N, N, B))
    U_S, R_S = UR_S[:N], UR_S[N:]
    empty = S == M
    hr_ext = torch.cat((hr, hr.new_zeros(1, B)), 0)
    rhs_S = _contract(R_S, xu.unsqueeze(1)) - hr_ext.gather(0, S)  # R_S x_u - r_S
    piv_tol = 1e-12 if dtype == torch.float64 else 1e-6
    W_SS = _slot_system(R_S, U_S, empty)
    lam_S, nonsing = _eliminate(W_SS, rhs_S, piv_tol)
    lam_S = torch.where(empty, 0.0, lam_S)
    x = xu - _contract(U_S.transpose(0, 1), lam_S.unsqueeze(1))
    # rows are judged on the scale of the point found, not of xu: far outside the feasible
    # set (|xu| >> |x|) x keeps errors of about |xu| mach, which xu's scale passes as rounding
    tiny = torch.finfo(dtype).tiny
    r_S = hr_ext.gather(0, S)
    res_S = torch.where(empty, 0.0, _contract(R_S, x.unsqueeze(1)) - r_S)
    scale_S = _kkt.row_scale(R_S.permute(2, 1, 0), r_S.T, x.T).T  # [N(slot), B]
    worst = (res_S.abs() / scale_S.clamp_min(tiny)).amax(0)
    # one refinement step on the active rows' residual (the C kernel's): W_SS dmu = G_S x -
    # h_S, x -= P^{-1} G_S' dmu, computed from small numbers, restores the lost digits
    dmu, solvable = _eliminate(W_SS, res_S, piv_tol)
    refine = nonsing & solvable & (worst > 1e4 * torch.finfo(dtype).eps)
    dmu = torch.where(refine & ~empty, dmu, 0.0)
    x = x - _contract(U_S.transpose(0, 1), dmu.unsqueeze(1))
    lam_S = lam_S + dmu
    scale = _kkt.row_scale(G, h, x.T).T  # [M, B]
    v = (_contract(Rc, x.unsqueeze(1)) - hr) / scale.clamp_min(tiny)
    v_S = torch.cat((v, v.new_zeros(1, B)), 0).gather(0, S)
    pviol = torch.maximum(v.amax(0), v_S.abs().amax(0))
    stat = _contract(Pp, x.unsqueeze(1)) + q.T + _contract(R_S.transpose(0, 1), lam_S.unsqueeze(1))
    dscale = 1.0 + q.abs().amax(-1) + (R_S.abs().amax(0) * lam_S.abs()).amax(0)
    ok = (
        ~fail
        & done
        & nonsing
        & (pviol <= eps)
        & (lam_S.amin(0) >= -eps * (1.0 + lam_S.abs().amax(0)))
        & (stat.abs().amax(0) <= eps * dscale)
        & torch.isfinite(x).all(0)
    )
    okc = ok.unsqueeze(-1)
    lam = q.new_zeros(M + 1, B).scatter_(0, S, lam_S)
    x_out = torch.where(okc, x.T, 0.0)
    z_out = torch.where(okc, lam[:M].T.clamp_min(0.0), 0.0)
    active = torch.zeros(M + 1, B, dtype=torch.bool, device=device).scatter_(0, S, True)
    active = active[:M].T & okc
    factor = DualFactor(L, S, R_S, U_S, ok)
    return DualResult(x_out, z_out, active, ok, iters, factor, torch.zeros_like(ok))


def _iterate(data: _Data, xu: Tensor, pd: Tensor, max_iter: int, check_every: int) -> _Outcome:
    """The torch steps of :func:`solve_dual` from the unconstrained minimisers ``xu [N, B]``
    (rows where ``pd`` is false do not iterate); the final active slots, failures, finished
    rows and step counts."""
    N, B = xu.shape
    dtype, device = xu.dtype, xu.device
    M = data.hr.shape[0]
    st = _State(
        x=xu.clone(),
        lam_S=xu.new_zeros(N, B),
        lam_p=xu.new_zeros(B),
        S=torch.full((N, B), M, dtype=torch.int64, device=device),
        U_S=xu.new_zeros(N, N, B),
        Hs=torch.eye(N, dtype=dtype, device=device).unsqueeze(-1).repeat(1, 1, B),
        p=torch.zeros(B, dtype=torch.int64, device=device),
        pending=torch.zeros(B, dtype=torch.bool, device=device),
        done=~pd,
        fail=~pd,
        iters=torch.zeros(B, dtype=torch.int64, device=device),
    )
    final = _Outcome(st.S, st.fail, st.done, st.iters)  # full batch
    rows: Tensor | None = None  # global indices of the rows being iterated (None: all)
    sync_each = device.type == "cpu"
    for it in range(max_iter):
        st = _step(data, st)
        if not (sync_each or (it + 1) % check_every == 0):
            continue
        running = int((~st.done).sum())
        width = st.done.shape[0]
        if running == 0 or (3 * running <= width and width >= 64):
            final = _write_back(final, st, rows)
            if running == 0:
                break
            keep = (~st.done).nonzero().squeeze(-1)
            rows = keep if rows is None else rows.index_select(0, keep)
            data = data._replace(
                **{
                    k: getattr(data, k).index_select(-1, keep)
                    for k in ("Rc", "hr", "UR", "tol", "inv_norm")
                }
            )
            st = _State(*(t.index_select(-1, keep) for t in st))
    else:
        final = _write_back(final, st, rows)
    return final


class _Outcome(NamedTuple):
    """The fields of :class:`_State` read after the iteration, for the whole batch."""

    S: Tensor
    fail: Tensor
    done: Tensor
    iters: Tensor


def _write_back(final: _Outcome, st: _State, rows: Tensor | None) -> _Outcome:
    """Copy the iterated rows ``rows`` (all when ``None``) of ``st`` into ``final``."""
    new = _Outcome(st.S, st.fail, st.done, st.iters)
    if rows is None:
        return new
    return _Outcome(*(f.index_copy(-1, rows, s) for f, s in zip(final, new, strict=True)))


def dual_adjoints(
    fac: DualFactor | NativeFactor, x: Tensor, gx: Tensor, gz: Tensor
) -> tuple[Tensor, Tensor]:
    """KKT adjoints ``(w_x [B,N], wz [B,M])`` for output gradients ``gx [B,N]``, ``gz [B,M]``
    (implicit differentiation of the KKT conditions on the active slots; rows not ``ok`` get
    zeros); :func:`torchcbf.qp._kkt.input_gradients` turns them into gradients."""
    if isinstance(fac, NativeFactor):
        return _dual_native.backward(fac.G, fac.L, fac.slots, fac.ok, gx, gz)
    B, N = x.shape
    M = gz.shape[-1]
    S = fac.slots
    empty = S == M
    gz_ext = torch.cat((gz.T, gz.new_zeros(1, B)), 0)
    a = _cho_solve(fac.L, gx.T)  # P^{-1} gx  [N, B]
    rhs = _contract(fac.R_S, a.unsqueeze(1)) - gz_ext.gather(0, S)
    piv_tol = 1e-12 if x.dtype == torch.float64 else 1e-6
    w_lam, _ = _eliminate(_slot_system(fac.R_S, fac.U_S, empty), rhs, piv_tol)
    w_lam = torch.where(empty, 0.0, w_lam)
    w_x = a - _contract(fac.U_S.transpose(0, 1), w_lam.unsqueeze(1))
    good = fac.ok & torch.isfinite(w_x).all(0) & torch.isfinite(w_lam).all(0)
    w_x = torch.where(good, w_x, 0.0).T  # [B, N]
    w_lam = torch.where(good, w_lam, 0.0)
    wz = x.new_zeros(M + 1, B).scatter_(0, S, w_lam)[:M].T  # [B, M]
    return w_x, wz
