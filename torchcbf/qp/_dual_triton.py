"""GPU path of the dual active-set method: the steps of :mod:`torchcbf.qp._dual` in Triton.

The torch implementation takes one pass of some sixty tensor operations per step over the
whole batch, and the host checks every few steps whether every row is done. This kernel runs
the same add-or-drop steps (:func:`torchcbf.qp._dual._step`, the same formulas in the same
order) for one problem per lane, with the loop over the steps inside the kernel: one launch
for the iteration, no host synchronisation. Its inputs are the data planes the torch
implementation builds (batch last, so the lanes of a program read consecutive addresses) and
it returns what the torch code after the iteration reads: each row's active slots, whether
it finished and its step count. The exact re-solve on the final active set and the KKT check
that decide each row stay in torch (shared with the torch path).

Each lane holds its problem in registers (``R'`` and ``P^{-1} R'`` as ``[N, M]`` tiles), so
the kernel serves problems up to :data:`MAX_TILE` entries (padded to powers of two); larger
ones take the torch steps. On the CPU it runs only under ``TRITON_INTERPRET=1`` (the tests).
"""

from __future__ import annotations

from typing import NamedTuple

import torch
from torch import Tensor

from torchcbf._triton import available, interpreted, tl, triton

#: most entries of a padded ``[N, M]`` tile (each lane holds two of them in registers)
MAX_TILE = 256
#: problems per program: one warp, one problem per thread
BLOCK = 32
#: warps per program
WARPS = 1
#: the kernel's version (its inputs and outputs, for ``torchcbf info``)
KERNEL_VERSION = 1


def _pow2(v: int) -> int:
    return max(2, 1 << (max(v, 1) - 1).bit_length())


def applies(q: Tensor, M: int, *, explicit: bool = False) -> bool:
    """Whether the kernel iterates a batch with linear terms ``q [B, N]`` and ``M`` rows:
    Triton imports, the data are on CUDA (or, where the kernel is asked for ``explicit``ly,
    on the CPU under ``TRITON_INTERPRET=1``) and the padded tiles fit :data:`MAX_TILE`."""
    interpreter = explicit and q.device.type == "cpu" and interpreted()
    on_device = q.device.type == "cuda" or interpreter
    fits = _pow2(q.shape[-1]) * _pow2(M) <= MAX_TILE
    return available() and on_device and fits and q.dtype in (torch.float32, torch.float64)


class Steps(NamedTuple):
    """The iteration's outcome, batch last: ``S [N, B]`` int64 row per slot (``M``: empty),
    ``done [B]`` bool, ``iters [B]`` int64."""

    S: Tensor
    done: Tensor
    iters: Tensor


if triton is not None:

    @triton.jit
    def _pick(X, idx, j, AXIS: tl.constexpr):
        """The entries of ``X`` at per-lane index ``j [BLOCK]`` along ``AXIS`` (``idx``: that
        axis' indices, shaped to broadcast against ``X``)."""
        return tl.sum(tl.where(idx == j, X, 0.0), axis=AXIS)

    @triton.jit
    def _dual_steps_kernel(
        rc_ptr,  # [N, M, B] R' by components
        u_ptr,  # [N, M, B] P^{-1} R'
        hr_ptr,  # [M, B]
        tol_ptr,  # [M, B]
        inv_ptr,  # [M, B]
        xu_ptr,  # [N, B] unconstrained minimiser
        done_ptr,  # [B] int8: rows that start done
        s_ptr,  # out [N, B] int64
        done_out_ptr,  # out [B] int8
        iters_ptr,  # out [B] int64
        B,
        max_iter,
        N: tl.constexpr,
        M: tl.constexpr,
        NP: tl.constexpr,
        MP: tl.constexpr,
        BLOCK: tl.constexpr,
    ):
        INF = float("inf")
        lane = tl.program_id(0).to(tl.int64) * BLOCK + tl.arange(0, BLOCK)
        live = lane < B
        cn = tl.arange(0, NP)
        cm = tl.arange(0, MP)
        n_ok = cn < N
        m_ok = cm < M
        nm = (cn[:, None] * M + cm[None, :]).to(tl.int64)
        nm_mask = (n_ok[:, None] & m_ok[None, :])[:, :, None] & live[None, None, :]
        nm_off = nm[:, :, None] * B + lane[None, None, :]
        Rc = tl.load(rc_ptr + nm_off, mask=nm_mask, other=0.0)  # [NP, MP, BLOCK]
        Ui = tl.load(u_ptr + nm_off, mask=nm_mask, other=0.0)
        m_off = cm.to(tl.int64)[:, None] * B + lane[None, :]
        m_mask = m_ok[:, None] & live[None, :]
        hr = tl.load(hr_ptr + m_off, mask=m_mask, other=0.0)  # [MP, BLOCK]
        tol = tl.load(tol_ptr + m_off, mask=m_mask, other=0.0)
        inv = tl.load(inv_ptr + m_off, mask=m_mask, other=0.0)
        n_off = cn.to(tl.int64)[:, None] * B + lane[None, :]
        n_mask = n_ok[:, None] & live[None, :]
        x = tl.load(xu_ptr + n_off, mask=n_mask, other=0.0)  # [NP, BLOCK]
        real = x.dtype
        done = (tl.load(done_ptr + lane, mask=live, other=1) != 0) | ~live

        slot = cn[:, None]  # [NP, 1]
        rank = tl.where(n_ok, N - cn, 0).to(real)[:, None]
        eye = (cn[:, None] == cn[None, :])[:, :, None]  # [NP, NP, 1]
        row_idx = cm[:, None]  # [MP, 1]
        valid = m_ok[:, None]
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
            free = (S == M).to(real)  # [NP, BLOCK]
            v = tl.sum(Rc * x[:, None, :], axis=0) - hr  # [MP, BLOCK]
            member = tl.max((S[:, None, :] == row_idx[None, :, :]).to(tl.int32), axis=0)
            score = tl.where((v > tol) & (member == 0) & valid, v * inv, -INF)
            best = tl.max(score, axis=0)
            p_new = tl.argmax(score, axis=0).to(tl.int32)
            done = done | ~(pending | (best > -INF))
            p = tl.where(pending, p, p_new)
            v_p = _pick(v, row_idx, p[None, :], 0)
            U_p = _pick(Ui, row_idx[None, :, :], p[None, None, :], 1)  # [NP, BLOCK]
            R_p = _pick(Rc, row_idx[None, :, :], p[None, None, :], 1)

            W_Sp = tl.sum(U_S * R_p[:, None, :], axis=0)  # [NP(slot), BLOCK]
            W_pp = tl.sum(U_p * R_p, axis=0)
            d = tl.sum(Hs * W_Sp[None, :, :], axis=1) * (1.0 - free)
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
            Hk = _pick(Hs, slot[:, :, None], k_drop[None, None, :], 0)  # row k_drop [NP, BLOCK]
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

        tl.store(s_ptr + n_off, S.to(tl.int64), mask=n_mask)
        tl.store(done_out_ptr + lane, done.to(tl.int8), mask=live)
        tl.store(iters_ptr + lane, iters.to(tl.int64), mask=live)


def steps(
    Rc: Tensor, U: Tensor, hr: Tensor, tol: Tensor, inv_norm: Tensor, xu: Tensor,
    done: Tensor, max_iter: int,
) -> Steps:  # fmt: skip
    """Run up to ``max_iter`` steps of the dual method on every row: ``Rc`` (``R'``) and
    ``U`` (``P^{-1} R'``) ``[N, M, B]``, ``hr``, ``tol``, ``inv_norm`` ``[M, B]`` (the
    fields of :class:`torchcbf.qp._dual._Data`), ``xu [N, B]`` the unconstrained minimisers
    and ``done [B]`` the rows that do not iterate (``P`` not positive definite)."""
    if triton is None:
        raise RuntimeError("torchcbf: the QP's GPU kernel needs Triton, which does not import")
    N, M, B = Rc.shape
    for name, t, shape in (
        ("Rc", Rc, (N, M, B)), ("U", U, (N, M, B)), ("hr", hr, (M, B)), ("tol", tol, (M, B)),
        ("inv_norm", inv_norm, (M, B)), ("xu", xu, (N, B)),
    ):  # fmt: skip
        if t.device != Rc.device or t.dtype != Rc.dtype or tuple(t.shape) != shape:
            raise ValueError(
                f"{name} must be a {Rc.dtype} tensor of shape {list(shape)} on {Rc.device}, "
                f"got {t.dtype} {list(t.shape)} on {t.device}"
            )
    if done.shape != (B,) or done.device != Rc.device:
        raise ValueError(f"done must have shape [{B}] on {Rc.device}, got {list(done.shape)}")
    S = torch.empty(N, B, dtype=torch.int64, device=Rc.device)
    done_out = torch.empty(B, dtype=torch.int8, device=Rc.device)
    iters = torch.empty(B, dtype=torch.int64, device=Rc.device)
    if B > 0:
        grid = (triton.cdiv(B, BLOCK),)
        _dual_steps_kernel[grid](
            Rc.contiguous(), U.contiguous(), hr.contiguous(), tol.contiguous(),
            inv_norm.contiguous(), xu.contiguous(), done.to(torch.int8).contiguous(),
            S, done_out, iters, B, max_iter,
            N=N, M=M, NP=_pow2(N), MP=_pow2(M), BLOCK=BLOCK, num_warps=WARPS,
        )  # fmt: skip
    return Steps(S, done_out.bool(), iters)
