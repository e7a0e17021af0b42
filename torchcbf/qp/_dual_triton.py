"""GPU path of the dual active-set method: :func:`torchcbf.qp._dual.solve_dual` in Triton.

The torch implementation takes a pass of some sixty tensor operations per step over the
whole batch (and as many again to factor before the steps and to check after them), and the
host checks every few steps whether every row is done. This kernel solves one problem per
lane in one launch, with no host synchronisation: the Cholesky factor of ``P``, ``P^{-1}
R'`` and the unconstrained minimiser, the add-or-drop steps (:func:`torchcbf.qp._dual._step`)
until the row is done, the exact multipliers on the final active set with one refinement
step, and the KKT check that decides the row, by the torch implementation's formulas in its
order of operations (rounding still differs where one side fuses a multiply and an add, so
on a degenerate row the two may end on different active sets of the same point). It reads
its inputs at their own strides (a thread loads its problem's entries once, with no copy of
the batch into another layout first), writes planes with the batch last (the lanes of a
program touch consecutive addresses) and returns what the torch implementation returns,
the backward's factors included.

Each thread holds one problem as tiles (``R'`` as ``[N, M]``; ``P^{-1} R'`` only while the
rows' scales are formed, then one column per step); the batch size is not a specialised
argument, since a size divisible by 16 lets the compiler vectorise the loads over lanes and
hand each thread four problems (on the filter's QP in float32, 2.6 kB of spills and six
times the instructions per step). Compiled for sm_90 (255 registers a
thread), float32 runs without spilling at ``N = 4``, ``M = 8`` and at the filter's ``N = 3``,
``M = 13``, and spills 88 B to local memory at ``N = 4``, ``M = 16`` (none inside its
steps); float64 spills from ``N = 2``, ``M = 12`` on (48 B there, 0.5 kB at ``N = 4``,
``M = 8``, 0.7 kB at ``N = 3``, ``M = 13``, 1.2 kB at ``N = 4``, ``M = 16``;
``scripts/kernel_resources.py`` reads these on any machine). The kernel serves
problems of up to :data:`MAX_VARS` variables and :data:`MAX_TILE` entries (padded to powers
of two); larger ones take the torch implementation. On the CPU it runs only under
``TRITON_INTERPRET=1`` (the tests).
"""

from __future__ import annotations

import functools
from typing import NamedTuple

import torch
from torch import Tensor

from torchcbf._triton import available, interpreted, on_device, tile, tl, triton

#: most variables, and most entries of a padded ``[N, M]`` tile (beyond these the registers
#: spill heavily and a first call compiles for tens of seconds: at N = 8, M = 16, 22 kB of
#: spills and 21 s on this project's CPU)
MAX_VARS = 4
MAX_TILE = 64
#: problems per program: one warp, one problem per thread
BLOCK = 32
#: warps per program
WARPS = 1
#: the kernel's version (its inputs and outputs, for ``torchcbf info``)
KERNEL_VERSION = 3
#: the kernel's stride arguments, in order: ``P``'s (batch, row, column), ``q``'s, ``G``'s, ``h``'s
STRIDE_ARGS = ("sp", "sp0", "sp1", "sq", "sq0", "sg", "sg0", "sg1", "sh", "sh0")


def applies(q: Tensor, M: int, *, explicit: bool = False) -> bool:
    """Whether the kernel solves a batch with linear terms ``q [B, N]`` and ``M`` rows:
    Triton imports, the data are on CUDA (or, where the kernel is asked for ``explicit``ly,
    on the CPU under ``TRITON_INTERPRET=1``) and the problem fits :data:`MAX_VARS` and
    :data:`MAX_TILE`."""
    interpreter = explicit and q.device.type == "cpu" and interpreted()
    on_device = q.device.type == "cuda" or interpreter
    N = q.shape[-1]
    fits = N <= MAX_VARS and tile(N) * tile(M) <= MAX_TILE
    return available() and on_device and fits and q.dtype in (torch.float32, torch.float64)


class Solution(NamedTuple):
    """The kernel's outputs, batch last: ``x [N, B]`` and ``z [M, B]`` (zeros on rows not
    ``ok``), ``active [M, B]`` and ``ok [B]`` bool, ``iters [B]`` int64, and the backward's
    factors: ``L [N, N, B]`` (Cholesky factor of ``P``), ``S [N, B]`` int64 row per slot
    (``M``: empty), ``R_S`` and ``U_S`` ``[N(component), N(slot), B]`` (the slots' rows of
    ``R'`` and ``P^{-1} R'``, zero on empty slots); ``condition [B]``: ``max_i P_ii
    (P^{-1})_ii`` from ``L``, as :func:`torchcbf.qp._function.condition_estimate` computes it
    (meaningful where ``P`` is positive definite)."""

    x: Tensor
    z: Tensor
    active: Tensor
    ok: Tensor
    iters: Tensor
    L: Tensor
    S: Tensor
    R_S: Tensor
    U_S: Tensor
    condition: Tensor


if triton is not None:

    @triton.jit
    def _pick(X, idx, j, AXIS: tl.constexpr):
        """The entries of ``X`` at per-lane index ``j [BLOCK]`` along ``AXIS`` (``idx``: that
        axis' indices, shaped to broadcast against ``X``); one term is not zero, so exact."""
        return tl.sum(tl.where(idx == j, X, 0.0), axis=AXIS)

    @triton.jit
    def _load_tile(
        ptr, base, live, s0, s1, R: tl.constexpr, C: tl.constexpr, RP: tl.constexpr,
        CP: tl.constexpr, BLOCK: tl.constexpr,
    ):  # fmt: skip
        """Entries ``(i, j)`` at ``ptr + base + i s0 + j s1`` of each lane as a ``[RP, CP,
        BLOCK]`` tile (zero outside ``[R, C]``), loaded one entry at a time: a tile loaded
        through a tile of pointers at strides unknown to the compiler gets a layout that
        spreads a problem over threads (115,896 instructions and 7.7 kB of spills at the
        filter's size in float32, against 5,320 and none with one problem per thread)."""
        ri = tl.arange(0, RP)[:, None, None]
        ci = tl.arange(0, CP)[None, :, None]
        tile = tl.zeros([RP, CP, BLOCK], dtype=ptr.dtype.element_ty)
        for i in tl.static_range(R):
            for j in tl.static_range(C):
                # in int64: an index times a 32-bit stride may pass 2^31 (batch-last inputs)
                off = tl.full([], i, tl.int64) * s0 + tl.full([], j, tl.int64) * s1
                v = tl.load(ptr + base + off, mask=live, other=0.0)
                tile = tl.where((ri == i) & (ci == j), v[None, None, :], tile)
        return tile

    @triton.jit
    def _lower_solve(L, R, NP: tl.constexpr):
        """``L Y = R`` for lower triangular ``L [NP, NP, BLOCK]`` and ``R [NP, X, BLOCK]``
        (components first) by forward substitution."""
        ci = tl.arange(0, NP)
        r3 = ci[:, None, None]
        c2 = ci[:, None]
        Y = tl.zeros_like(R)
        for i in tl.static_range(NP):
            acc = _pick(R, r3, i, 0)
            Li = _pick(L, r3, i, 0)  # row i [NP, BLOCK]
            for k in tl.static_range(i):
                acc = acc - _pick(Li, c2, k, 0)[None, :] * _pick(Y, r3, k, 0)
            Y = tl.where(r3 == i, (acc / _pick(Li, c2, i, 0)[None, :])[None, :, :], Y)
        return Y

    @triton.jit
    def _cho_solve(L, R, NP: tl.constexpr):
        """``L L' Y = R`` for ``L [NP, NP, BLOCK]`` and ``R [NP, X, BLOCK]`` (components
        first), the torch implementation's substitutions in its order."""
        ci = tl.arange(0, NP)
        r3 = ci[:, None, None]
        c2 = ci[:, None]
        Y = _lower_solve(L, R, NP)
        X = tl.zeros_like(R)
        for ii in tl.static_range(NP):
            acc = _pick(Y, r3, NP - 1 - ii, 0)
            Lc = _pick(L, ci[None, :, None], NP - 1 - ii, 1)  # column [NP, BLOCK]
            for k in tl.static_range(NP - ii, NP):
                acc = acc - _pick(Lc, c2, k, 0)[None, :] * _pick(X, r3, k, 0)
            diag = _pick(Lc, c2, NP - 1 - ii, 0)
            X = tl.where(r3 == NP - 1 - ii, (acc / diag[None, :])[None, :, :], X)
        return X

    @triton.jit
    def _solve_sym(W, rhs, piv_tol, NP: tl.constexpr):
        """``W mu = rhs`` for symmetric ``W [NP, NP, BLOCK]``, ``rhs [NP, BLOCK]`` by
        symmetric elimination without pivoting (:func:`torchcbf.qp._enum._eliminate`);
        ``(mu, nonsingular)``: a pivot at most ``piv_tol`` times its diagonal entry is
        singular."""
        ci = tl.arange(0, NP)
        r2 = ci[:, None]
        r3 = ci[:, None, None]
        diag = tl.sum(tl.where(r3 == ci[None, :, None], W, 0.0), axis=1)  # [NP, BLOCK]
        A = W
        b = rhs
        pivots = tl.zeros_like(rhs)
        for j in tl.static_range(NP):
            row = _pick(A, r3, j, 0)  # A[j, :]
            piv = _pick(row, r2, j, 0)
            pivots = tl.where(r2 == j, piv[None, :], pivots)
            f = row * (1.0 / piv)[None, :]
            bj = _pick(b, r2, j, 0)
            A = A - tl.where(r3 > j, f[:, None, :] * row[None, :, :], 0.0)
            b = b - tl.where(r2 > j, f * bj[None, :], 0.0)
        nonsing = tl.min((pivots > piv_tol * diag).to(tl.int32), axis=0) > 0
        mu = tl.zeros_like(rhs)
        for ii in tl.static_range(NP):
            row = _pick(A, r3, NP - 1 - ii, 0)
            acc = _pick(b, r2, NP - 1 - ii, 0)
            for k in tl.static_range(NP - ii, NP):
                acc = acc - _pick(row, r2, k, 0) * _pick(mu, r2, k, 0)
            piv = _pick(pivots, r2, NP - 1 - ii, 0)
            mu = tl.where(r2 == NP - 1 - ii, (acc / piv)[None, :], mu)
        return mu, nonsing

    # B and the strides unspecialised: a batch divisible by 16 (or a batch stride of 1)
    # would let the compiler prove 16-byte runs of lanes in the planes it writes (or the
    # inputs it reads) and vectorise them, giving each thread four problems instead of one
    # (four times the registers; 2.6 kB of spills at the filter's size in float32, sm_90);
    # with the inputs' alignment unspecialised too, one compiled variant serves every layout
    # and view
    @triton.jit(
        do_not_specialize=["B", *STRIDE_ARGS],
        do_not_specialize_on_alignment=["p_ptr", "q_ptr", "g_ptr", "h_ptr"],
    )
    def _dual_solve_kernel(
        p_ptr,  # [B, N, N] at strides (sp, sp0, sp1)
        q_ptr,  # [B, N] at (sq, sq0)
        g_ptr,  # [B, M, N] at (sg, sg0, sg1)
        h_ptr,  # [B, M] at (sh, sh0)
        x_ptr,  # out [N, B]
        z_ptr,  # out [M, B]
        active_ptr,  # out [M, B] int8
        ok_ptr,  # out [B] int8
        iters_ptr,  # out [B] int64
        l_ptr,  # out [N, N, B]
        s_ptr,  # out [N, B] int64
        rs_ptr,  # out [N, N, B]
        us_ptr,  # out [N, N, B]
        cond_ptr,  # out [B]
        consts_ptr,  # [4]: eps, the dtype's eps, the pivot tolerance and its least normal
        B,
        sp,
        sp0,
        sp1,
        sq,
        sq0,
        sg,
        sg0,
        sg1,
        sh,
        sh0,
        max_iter,
        N: tl.constexpr,
        M: tl.constexpr,
        NP: tl.constexpr,
        MP: tl.constexpr,
        BLOCK: tl.constexpr,
    ):
        INF = float("inf")
        # in the data's dtype (a float argument launches as float32: tiny would be 0)
        eps = tl.load(consts_ptr)
        mach = tl.load(consts_ptr + 1)
        piv_tol = tl.load(consts_ptr + 2)
        tiny = tl.load(consts_ptr + 3)
        lane = tl.program_id(0).to(tl.int64) * BLOCK + tl.arange(0, BLOCK)
        live = lane < B
        cn = tl.arange(0, NP)
        cm = tl.arange(0, MP)
        n_ok = cn < N
        m_ok = cm < M
        r2 = cn[:, None]  # [NP, 1]
        r3 = cn[:, None, None]
        c3 = cn[None, :, None]
        eye = r3 == c3  # [NP, NP, 1]
        row_idx = cm[:, None]  # [MP, 1]
        valid = m_ok[:, None]
        nn = (cn[:, None] * N + cn[None, :]).to(tl.int64)
        nn_mask = (n_ok[:, None] & n_ok[None, :])[:, :, None] & live[None, None, :]
        nn_off = nn[:, :, None] * B + lane[None, None, :]
        m_off = cm.to(tl.int64)[:, None] * B + lane[None, :]
        m_mask = m_ok[:, None] & live[None, :]
        n_off = cn.to(tl.int64)[:, None] * B + lane[None, :]
        n_mask = n_ok[:, None] & live[None, :]

        # the inputs at their own strides (no copy into planes), entry by entry; padded
        # components: an identity block of P, zero data (they stay zero)
        P = _load_tile(p_ptr, lane * sp, live, sp0, sp1, N, N, NP, NP, BLOCK)
        P = P + tl.where(eye & (r3 >= N), 1.0, 0.0)
        q = tl.sum(_load_tile(q_ptr, lane * sq, live, sq0, 0, N, 1, NP, 1, BLOCK), axis=1)
        Rc = _load_tile(g_ptr, lane * sg, live, sg1, sg0, N, M, NP, MP, BLOCK)  # R' [NP, MP, BLOCK]
        hr = tl.sum(_load_tile(h_ptr, lane * sh, live, sh0, 0, M, 1, MP, 1, BLOCK), axis=1)
        real = q.dtype

        # Cholesky factor of P, column by column; a pivot at most 1e-13 of its diagonal
        # entry marks the row not positive definite
        L = tl.zeros_like(P)
        pd = live
        for j in tl.static_range(NP):
            Pj = _pick(P, c3, j, 1)  # column j [NP, BLOCK]
            col = Pj
            for k in tl.static_range(j):
                Lk = _pick(L, c3, k, 1)
                col = col - Lk * _pick(Lk, r2, j, 0)[None, :]
            piv = _pick(col, r2, j, 0)
            pd = pd & (piv > 1e-13 * tl.abs(_pick(Pj, r2, j, 0)))
            root = tl.sqrt(tl.where(pd, piv, 1.0))
            L = tl.where(c3 == j, tl.where(r2 >= j, col / root[None, :], 0.0)[:, None, :], L)
        # max_i P_ii (P^{-1})_ii (_function.condition_estimate): squared norms of L's rows
        # and of L^{-1}'s columns (padded components give 1, which never exceeds it)
        Linv = _lower_solve(L, tl.where(eye, 1.0, 0.0).to(real) + tl.zeros_like(L), NP)
        cond = tl.max(tl.sum(L * L, axis=1) * tl.sum(Linv * Linv, axis=0), axis=0)
        tl.store(cond_ptr + lane, cond, mask=live)
        # P^{-1} R' [NP, MP, BLOCK] for the rows' scales only: the steps and the end solve
        # for the columns they use (the same operations per column, so the same values),
        # which keeps a second [NP, MP] tile out of the registers of the loop
        Ui = _cho_solve(L, Rc, NP)
        xu = tl.sum(_cho_solve(L, -q[:, None, :], NP), axis=1)  # [NP, BLOCK]

        xu_max = tl.max(tl.abs(xu), axis=0)
        gmax = tl.max(tl.abs(Rc), axis=0)  # [MP, BLOCK]
        tol = 1e4 * mach * (tl.abs(hr) + gmax * (1.0 + xu_max)[None, :])
        w_diag = tl.sum(Ui * Rc, axis=0)
        inv = tl.where(w_diag > 0, 1.0 / tl.sqrt(tl.maximum(w_diag, 1e-300)), 0.0)

        # the add-or-drop steps (torchcbf.qp._dual._step)
        done = ~pd
        x = xu
        slot = r2
        rank = tl.where(n_ok, N - cn, 0).to(real)[:, None]
        lam_S = tl.zeros([NP, BLOCK], dtype=real)
        lam_p = tl.zeros([BLOCK], dtype=real)
        S = tl.full([NP, BLOCK], M, dtype=tl.int32)
        U_S = tl.zeros([NP, NP, BLOCK], dtype=real)  # (component, slot)
        Hs = tl.where(eye, 1.0, 0.0).to(real) + tl.zeros([NP, NP, BLOCK], dtype=real)
        p = tl.zeros([BLOCK], dtype=tl.int32)
        pending = tl.zeros([BLOCK], dtype=tl.int1)
        iters = tl.zeros([BLOCK], dtype=tl.int32)
        it = tl.full([], 0, dtype=tl.int32)
        running = tl.sum((~done).to(tl.int32), axis=0)
        while (it < max_iter) & (running > 0):
            free = (S == M).to(real)
            v = tl.sum(Rc * x[:, None, :], axis=0) - hr  # [MP, BLOCK]
            member = tl.max((S[:, None, :] == row_idx[None, :, :]).to(tl.int32), axis=0)
            score = tl.where((v > tol) & (member == 0) & valid, v * inv, -INF)
            best = tl.max(score, axis=0)
            p_new = tl.argmax(score, axis=0).to(tl.int32)
            done = done | ~(pending | (best > -INF))
            p = tl.where(pending, p, p_new)
            v_p = _pick(v, row_idx, p[None, :], 0)
            R_p = _pick(Rc, row_idx[None, :, :], p[None, None, :], 1)  # [NP, BLOCK]
            U_p = tl.sum(_cho_solve(L, R_p[:, None, :], NP), axis=1)

            W_Sp = tl.sum(U_S * R_p[:, None, :], axis=0)  # [NP(slot), BLOCK]
            W_pp = tl.sum(U_p * R_p, axis=0)
            d = tl.sum(Hs * W_Sp[:, None, :], axis=0) * (1.0 - free)  # as torch: by columns
            z = W_pp - tl.sum(W_Sp * d, axis=0)
            dx = tl.sum(U_S * d[None, :, :], axis=1) - U_p

            ranked = free * rank
            room = tl.max(ranked, axis=0)
            first_free = tl.argmax(ranked, axis=0).to(tl.int32)
            t_full = tl.where((z <= 1e-10 * W_pp) | (room == 0), INF, v_p / z)
            ratio = tl.where(d > 0, lam_S / d, INF)
            t_part = tl.min(ratio, axis=0)
            k_drop = tl.argmin(ratio, axis=0).to(tl.int32)
            t = tl.where(t_full <= t_part, t_full, t_part)
            nan = (t_full != t_full) | (t_part != t_part)
            done = done | nan | (t == INF)
            full = ~done & (t_full <= t_part)
            part = ~done & (t_full > t_part)
            t = tl.where(done, 0.0, t)

            x = x + dx * t[None, :]
            lam_S = lam_S - d * t[None, :]
            lam_p = lam_p + t
            e_drop = part[None, :] & (slot == k_drop[None, :])
            e_add = full[None, :] & (slot == first_free[None, :])
            f_drop = e_drop.to(real)
            f_add = e_add.to(real)
            Hk = _pick(Hs, r3, k_drop[None, None, :], 0)  # row k_drop [NP, BLOCK]
            Hkk = _pick(Hk, slot, k_drop[None, :], 0)
            a_coef = tl.where(full, 1.0 / z, 0.0)
            b_coef = tl.where(part, 1.0 / Hkk, 0.0)
            u = d - f_add
            Hs = Hs - tl.where(eye, f_add[None, :, :], 0.0)
            Hs = Hs + (u * a_coef[None, :])[:, None, :] * u[None, :, :]
            Hs = Hs - (Hk * b_coef[None, :])[:, None, :] * Hk[None, :, :]
            kept = 1.0 - f_drop
            Hs = Hs * (kept[:, None, :] * kept[None, :, :])
            Hs = Hs + tl.where(eye, f_drop[None, :, :], 0.0)
            keep = 1.0 - f_drop - f_add
            U_S = U_S * keep[None, :, :] + U_p[:, None, :] * f_add[None, :, :]
            lam_S = lam_S * keep + lam_p[None, :] * f_add
            lam_p = tl.where(full, 0.0, lam_p)
            S = tl.where(e_drop, M, tl.where(e_add, p[None, :], S))
            pending = part
            iters = iters + (~done).to(tl.int32)
            it += 1
            running = tl.sum((~done).to(tl.int32), axis=0)

        # exact multipliers and point on the final active set, one refinement step on the
        # active rows' residual, then the KKT check on the answer's scale
        empty = S == M  # [NP, BLOCK]
        sel = S[None, :, :] == row_idx[:, None, :]  # [MP, NP(slot), BLOCK]
        R_S = tl.zeros([NP, NP, BLOCK], dtype=real)
        for k in tl.static_range(NP):
            pick = _pick(sel.to(tl.int32), c3, k, 1)[None, :, :] != 0  # [1, MP, BLOCK]
            R_S = tl.where(c3 == k, tl.sum(tl.where(pick, Rc, 0.0), axis=1)[:, None, :], R_S)
        U_S = _cho_solve(L, R_S, NP)  # P^{-1} R_S (zero on empty slots where P factorised)
        r_S = tl.sum(tl.where(sel, hr[:, None, :], 0.0), axis=0)  # [NP, BLOCK]
        W = tl.zeros([NP, NP, BLOCK], dtype=real)  # W_SS = R_S' U_S, component by component
        for c in tl.static_range(NP):
            W = W + _pick(R_S, r3, c, 0)[:, None, :] * _pick(U_S, r3, c, 0)[None, :, :]
        W = W + tl.where(eye, empty.to(real)[None, :, :], 0.0)
        rhs_S = tl.sum(R_S * xu[:, None, :], axis=0) - r_S
        lam_S, nonsing = _solve_sym(W, rhs_S, piv_tol, NP)
        lam_S = tl.where(empty, 0.0, lam_S)
        x = xu - tl.sum(U_S * lam_S[None, :, :], axis=1)
        res_S = tl.where(empty, 0.0, tl.sum(R_S * x[:, None, :], axis=0) - r_S)
        x_max = tl.max(tl.abs(x), axis=0)
        scale_S = tl.abs(r_S) + tl.max(tl.abs(R_S), axis=0) * (1.0 + x_max)[None, :]
        worst = tl.max(tl.abs(res_S) / tl.maximum(scale_S, tiny), axis=0)
        dmu, solvable = _solve_sym(W, res_S, piv_tol, NP)
        refine = nonsing & solvable & (worst > 1e4 * mach)
        dmu = tl.where(refine[None, :] & ~empty, dmu, 0.0)
        x = x - tl.sum(U_S * dmu[None, :, :], axis=1)
        lam_S = lam_S + dmu
        x_max = tl.max(tl.abs(x), axis=0)
        scale = tl.abs(hr) + gmax * (1.0 + x_max)[None, :]
        v = (tl.sum(Rc * x[:, None, :], axis=0) - hr) / tl.maximum(scale, tiny)
        v = tl.where(v == v, v, INF)  # a NaN (data of inf) fails the check: tl.max skips it
        v_S = tl.sum(tl.where(sel, v[:, None, :], 0.0), axis=0)
        pviol = tl.maximum(tl.max(tl.where(valid, v, -INF), axis=0), tl.max(tl.abs(v_S), axis=0))
        stat = tl.sum(P * x[:, None, :], axis=0) + q + tl.sum(R_S * lam_S[None, :, :], axis=1)
        lam_abs = tl.max(tl.abs(lam_S), axis=0)
        rl = tl.max(tl.max(tl.abs(R_S), axis=0) * tl.abs(lam_S), axis=0)
        dscale = 1.0 + tl.max(tl.abs(q), axis=0) + rl
        finite = tl.min(((x == x) & (tl.abs(x) < INF)).to(tl.int32), axis=0) > 0
        ok = (
            pd
            & done
            & nonsing
            & (pviol <= eps)
            & (tl.min(lam_S, axis=0) >= -eps * (1.0 + lam_abs))
            & (tl.max(tl.where(stat == stat, tl.abs(stat), INF), axis=0) <= eps * dscale)
            & finite
        )

        tl.store(x_ptr + n_off, tl.where(ok[None, :], x, 0.0), mask=n_mask)
        z_m = tl.sum(tl.where(sel, lam_S[None, :, :], 0.0), axis=1)  # [MP, BLOCK]
        tl.store(z_ptr + m_off, tl.where(ok[None, :], tl.maximum(z_m, 0.0), 0.0), mask=m_mask)
        act = tl.max(sel.to(tl.int32), axis=1) > 0
        tl.store(active_ptr + m_off, (act & ok[None, :]).to(tl.int8), mask=m_mask)
        tl.store(ok_ptr + lane, ok.to(tl.int8), mask=live)
        tl.store(iters_ptr + lane, iters.to(tl.int64), mask=live)
        tl.store(l_ptr + nn_off, L, mask=nn_mask)
        tl.store(s_ptr + n_off, S.to(tl.int64), mask=n_mask)
        tl.store(rs_ptr + nn_off, R_S, mask=nn_mask)
        tl.store(us_ptr + nn_off, U_S, mask=nn_mask)


def solve(
    P: Tensor,
    q: Tensor,
    G: Tensor,
    h: Tensor,
    *,
    eps: float,
    max_iter: int,
    block: int = BLOCK,
    warps: int = WARPS,
    maxnreg: int | None = None,
    planes: bool = False,
) -> Solution:
    """Solve ``min 1/2 x'Px + q'x s.t. Gx <= h`` for ``P [B, N, N]``, ``q [B, N]``,
    ``G [B, M, N]``, ``h [B, M]`` (finite, one dtype and device) as
    :func:`torchcbf.qp._dual.solve_dual` does; see :class:`Solution`. ``block`` (problems
    per program, a power of two), ``warps`` and ``maxnreg`` (registers per thread, ``None``:
    the compiler's choice) set the launch and ``planes=True`` copies the inputs into planes
    with the batch last before it (the lanes of a program then read consecutive addresses;
    by default the kernel reads the inputs at their own strides, with no copy); the answers
    do not depend on them (``scripts/device_kernels.py`` times them)."""
    if triton is None:
        raise RuntimeError("torchcbf: the QP's GPU kernel needs Triton, which does not import")
    B, M, N = G.shape
    for name, t, shape in (("P", P, (B, N, N)), ("q", q, (B, N)), ("h", h, (B, M))):
        if t.device != G.device or t.dtype != G.dtype or tuple(t.shape) != shape:
            raise ValueError(
                f"{name} must be a {G.dtype} tensor of shape {list(shape)} on {G.device}, "
                f"got {t.dtype} {list(t.shape)} on {t.device}"
            )
    data = (P, q, G, h)
    if planes:  # each tensor copied batch last, then seen in its own index order again
        data = tuple(t.movedim(0, -1).contiguous().movedim(-1, 0) for t in data)
    strides = [s for t in data for s in t.stride()]
    new = functools.partial(torch.empty, device=G.device)
    x, z = new(N, B, dtype=G.dtype), new(M, B, dtype=G.dtype)
    active, ok = new(M, B, dtype=torch.int8), new(B, dtype=torch.int8)
    iters, S = new(B, dtype=torch.int64), new(N, B, dtype=torch.int64)
    L, R_S, U_S = (new(N, N, B, dtype=G.dtype) for _ in range(3))
    cond = new(B, dtype=G.dtype)
    if B > 0:
        info = torch.finfo(G.dtype)
        piv_tol = 1e-12 if G.dtype == torch.float64 else 1e-6
        consts = G.new_full((4,), eps)  # filled on the device: no copy from the host
        for i, value in enumerate((info.eps, piv_tol, info.tiny), start=1):
            consts[i] = value
        grid = (triton.cdiv(B, block),)
        launch = {} if maxnreg is None else {"maxnreg": maxnreg}
        with on_device(G):
            _dual_solve_kernel[grid](
                *data, x, z, active, ok, iters, L, S, R_S, U_S, cond, consts,
                B, *strides, min(max_iter, 2**31 - 1),
                N=N, M=M, NP=tile(N), MP=tile(M), BLOCK=block, num_warps=warps, **launch,
            )  # fmt: skip
    return Solution(x, z, active.bool(), ok.bool(), iters, L, S, R_S, U_S, cond)
