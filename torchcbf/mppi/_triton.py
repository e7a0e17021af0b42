"""GPU fast path of MPPI: the rollout kernel of :mod:`torchcbf.mppi._rollout` in Triton.

It reads the C kernel's configuration (:func:`torchcbf.mppi._rollout.configuration`) and
evaluates the same formulas with the same counter-based noise: given the same keys it gives
the C kernel's samples, rollouts and costs to rounding (the keys come from the planner's
generators, which draw other numbers on CUDA than on the CPU). Each rollout pass is one launch
over the ``B x K`` samples, one lane per sample, with the loop over the horizon inside the
kernel; the weights pass is one program per environment, looping over its samples:

- :func:`costs`: noise, rollout, built-in cost terms and the control cost; nothing stored;
- :func:`update`: ``sum_k w_k eps_k`` with the noise regenerated, as float64 partial sums per
  block of samples, summed by torch in a fixed order (deterministic);
- :func:`rows`: the rollouts ``[P, H+1, n]`` of chosen ``(b, k)`` pairs (the best sample,
  the kept samples);
- :func:`buffers`: every sample's states and controls in the component-major buffers a
  torch cost reads, and the control cost;
- :func:`weights`: the samples' weights from their costs and the output's figures per
  environment (two launches: a fill of ``-1/lambda`` and the kernel).

Triton is optional (:mod:`torchcbf._triton`; :func:`available` says whether it imports). On
the CPU the kernel runs only under ``TRITON_INTERPRET=1`` (the tests use it).
"""

from __future__ import annotations

import functools
import math
from typing import NamedTuple

import torch
from torch import Tensor

from torchcbf._triton import on_device, tile, tl, triton
from torchcbf.mppi import _rollout

#: samples per program: one warp, one sample per thread (K = 16,384 gives 512 programs,
#: enough to occupy every multiprocessor of a large GPU)
BLOCK = 32
#: warps per program
WARPS = 1
#: the kernel's passes
_COSTS, _UPDATE, _ROWS, _BUFFERS = 0, 1, 2, 3
#: layout of the parameter vector: dt, dt/2, dt/6, gamma, 2 pi, lo[4], hi[4], chol[4 x 4]
_P_LO, _P_HI, _P_L, _NPAR = 5, 9, 13, 29
#: per-term values: weight, extra, eps, radius, first shape, shapes, steps, 1 - extra
_TVAL = 8


#: the configuration this kernel reads (:data:`torchcbf.mppi._rollout.KERNEL_VERSION`)
KERNEL_VERSION = _rollout.KERNEL_VERSION


class Tables(NamedTuple):
    """The kernel's configuration on the device (built once per configuration by
    :func:`tables`) and its compile-time structure."""

    par: Tensor  # [_NPAR]
    tmask: Tensor  # [T, NP] components of each term's point
    tcent: Tensor  # [T, NP] each term's point (goal, obstacle centre) on them
    tval: Tensor  # [T, _TVAL]
    sa: Tensor  # [SP, 4, NP] rows of A: a shape's h = sign (|A (x - c)|^2 - c0)
    sc: Tensor  # [SP, NP] its centre
    sval: Tensor  # [SP, 2] sign, c0
    meta: dict  # the kernel's compile-time arguments
    samples: int  # K
    zero_noise: int


def tables(cfg: _rollout.Configuration, dtype: torch.dtype, device: torch.device) -> Tables:
    """Parse the C kernel's configuration vector (its layout in ``_rollout_kernel.c``) into
    the Triton kernel's dense tables, in ``dtype`` on ``device``."""
    v = cfg.values.tolist()
    L, field = _rollout.LAYOUT, _rollout.field
    hdr, mmax, trec, srec = L["HDR"], L["MMAX"], L["TREC"], L["SREC"]
    model, integrator, n, m, H, dim, zero_noise, has_lo, has_hi, nterms, nshapes = (
        int(field(v, name))
        for name in ("H_MODEL", "H_INTEGRATOR", "H_N", "H_M", "H_H", "H_DIM", "H_ZERO_NOISE",
                     "H_HAS_LO", "H_HAS_HI", "H_NTERMS", "H_NSHAPES")
    )  # fmt: skip
    dt, gamma = field(v, "H_DT"), field(v, "H_GAMMA")
    lo, hi = v[hdr : hdr + mmax], v[hdr + mmax : hdr + 2 * mmax]
    chol = v[hdr + 2 * mmax : hdr + 2 * mmax + mmax * mmax]
    par = [dt, 0.5 * dt, dt / 6.0, gamma, 2.0 * math.pi, *lo, *hi, *chol]
    NP, SP = tile(n), tile(nshapes)
    base = hdr + 2 * mmax + mmax * mmax
    tmask = torch.zeros(max(nterms, 1), NP, dtype=torch.float64)
    tcent = torch.zeros_like(tmask)
    tval = torch.zeros(max(nterms, 1), _TVAL, dtype=torch.float64)
    types = 0
    for t in range(nterms):
        rec = v[base + t * trec : base + (t + 1) * trec]
        kind, d = int(field(rec, "TR_TYPE")), int(field(rec, "TR_D"))
        weight, extra, eps = (field(rec, name) for name in ("TR_WEIGHT", "TR_EXTRA", "TR_EPS"))
        types |= kind << (2 * t)
        for c, center in zip(field(rec, "TR_IDX", d), field(rec, "TR_CENTER", d), strict=True):
            c = int(c)
            if tmask[t, c] != 0:  # a repeated component: the dense tables cannot say it
                raise ValueError("a cost term's index repeats a state component")
            tmask[t, c], tcent[t, c] = 1.0, center
        steps = 0.0
        if kind == _rollout.TERM_DISCRETE_BARRIER:
            steps = H if eps == -1 or eps > H else eps
        radius, shape0, nshape = (
            field(rec, name) for name in ("TR_RADIUS", "TR_SHAPE0", "TR_NSHAPE")
        )
        tval[t] = torch.tensor(
            [weight, extra, eps, radius, shape0, nshape, steps, 1.0 - extra], dtype=torch.float64
        )
    sa = torch.zeros(SP, 4, NP, dtype=torch.float64)
    sc = torch.zeros(SP, NP, dtype=torch.float64)
    sval = torch.zeros(SP, 2, dtype=torch.float64)
    shapes0 = base + nterms * trec
    rows_used = 1
    for s in range(nshapes):
        rec = v[shapes0 + s * srec : shapes0 + (s + 1) * srec]
        kind, d = int(field(rec, "SR_KIND")), int(field(rec, "SR_D"))
        idx = [int(i) for i in field(rec, "SR_IDX", d)]
        if len(set(idx)) != d:
            raise ValueError("a barrier's index repeats a state component")
        ball = kind == _rollout.SHAPE_BALL
        rows_used = max(rows_used, d)
        axes = field(rec, "SR_AXES", d)
        for c, center in zip(idx, field(rec, "SR_CENTER", d), strict=True):
            sc[s, c] = center
        if int(field(rec, "SR_ROTATED")):  # a rotated 2-D ellipse
            angle = field(rec, "SR_ANGLE")
            co, si = math.cos(angle), math.sin(angle)
            ax, ay = axes
            sa[s, 0, idx[0]], sa[s, 0, idx[1]] = co / ax, si / ax
            sa[s, 1, idx[0]], sa[s, 1, idx[1]] = -si / ay, co / ay
        else:
            for i, c in enumerate(idx):
                sa[s, i, c] = 1.0 if ball else 1.0 / axes[i]
        r = field(rec, "SR_RADIUS")
        sval[s] = torch.tensor([field(rec, "SR_SIGN"), r * r if ball else 1.0], dtype=torch.float64)
    meta = dict(
        MODEL=model,
        RK4=integrator == _rollout.INTEGRATOR_CODES["rk4"],
        N=n,
        M=m,
        DIM=dim,
        NP=NP,
        MP=tile(m),
        SP=SP,
        DQ=rows_used,
        NT=nterms,
        TYPES=types,
        HAS_SHAPES=nshapes > 0,
        HAS_DISCRETE=any(((types >> (2 * t)) & 3) == 3 for t in range(nterms)),
        HAS_LO=bool(has_lo),
        HAS_HI=bool(has_hi),
        CLAMP=bool(has_lo or has_hi),
    )
    put = functools.partial(torch.Tensor.to, device=device, dtype=dtype)
    return Tables(
        put(torch.tensor(par, dtype=torch.float64)),
        put(tmask),
        put(tcent),
        put(tval),
        put(sa),
        put(sc),
        put(sval),
        meta,
        int(field(v, "H_K")),
        zero_noise,
    )


# -- the kernel ------------------------------------------------------------------------------
if triton is not None:

    @triton.jit
    def _mix64(z):
        z = (z ^ (z >> 30)) * 0xBF58476D1CE4E5B9
        z = (z ^ (z >> 27)) * 0x94D049BB133111EB
        return z ^ (z >> 31)

    @triton.jit
    def _col(X, cols, i):
        """Component ``i`` ``[BLOCK]`` of ``X [C, BLOCK]`` (each lane's components are in
        its own thread: the sum runs in registers)."""
        return tl.sum(tl.where(cols[:, None] == i, X, 0.0), axis=0)

    @triton.jit
    def _put(X, cols, i, v):
        """``X [C, BLOCK]`` with component ``i`` replaced by ``v [BLOCK]``."""
        return tl.where(cols[:, None] == i, v[None, :], X)

    @triton.jit
    def _xdot(X, U, cols, ucols, MODEL: tl.constexpr, DIM: tl.constexpr):
        """``f(x) + g(x) u`` of the built-in models (codes of :data:`MODEL_CODES`)."""
        K = tl.zeros_like(X)
        if MODEL == 0:  # single integrator
            for i in tl.static_range(DIM):
                K = _put(K, cols, i, _col(U, ucols, i))
        elif MODEL == 1:  # double integrator
            for i in tl.static_range(DIM):
                K = _put(K, cols, i, _col(X, cols, DIM + i))
                K = _put(K, cols, DIM + i, _col(U, ucols, i))
        elif MODEL == 2:  # unicycle
            v = _col(U, ucols, 0)
            th = _col(X, cols, 2)
            K = _put(K, cols, 0, v * tl.cos(th))
            K = _put(K, cols, 1, v * tl.sin(th))
            K = _put(K, cols, 2, _col(U, ucols, 1))
        else:  # accel unicycle
            v = _col(X, cols, 2)
            th = _col(X, cols, 3)
            K = _put(K, cols, 0, v * tl.cos(th))
            K = _put(K, cols, 1, v * tl.sin(th))
            K = _put(K, cols, 2, _col(U, ucols, 0))
            K = _put(K, cols, 3, _col(U, ucols, 1))
        return K

    @triton.jit
    def _shapes_h(X, sa_ptr, sc_ptr, sval_ptr, cols, scols, NP: tl.constexpr, DQ: tl.constexpr):
        """``h [SP, BLOCK]`` of every shape at ``X [NP, BLOCK]`` (``DQ`` rows of ``A``)."""
        grid = scols[:, None] * NP + cols[None, :]  # [SP, NP]
        D = X[None, :, :] - tl.load(sc_ptr + grid)[:, :, None]  # [SP, NP, BLOCK]
        A = tl.load(sa_ptr + scols[:, None] * 4 * NP + cols[None, :])
        q = tl.sum(D * A[:, :, None], 1)
        acc = q * q
        for r in tl.static_range(1, DQ):
            A = tl.load(sa_ptr + (scols[:, None] * 4 + r) * NP + cols[None, :])
            q = tl.sum(D * A[:, :, None], 1)
            acc += q * q
        sign = tl.load(sval_ptr + scols * 2)
        c0 = tl.load(sval_ptr + scols * 2 + 1)
        return sign[:, None] * (acc - c0[:, None])

    @triton.jit
    def _rollout_kernel(
        par_ptr,
        tmask_ptr,
        tcent_ptr,
        tval_ptr,
        sa_ptr,
        sc_ptr,
        sval_ptr,
        x0_ptr,
        plan_ptr,
        wctrl_ptr,
        keys_ptr,
        pairs_ptr,
        w_ptr,
        cost_ptr,
        states_ptr,
        controls_ptr,
        part_ptr,
        count,
        K,
        zero_noise,
        H: tl.constexpr,
        MODEL: tl.constexpr,
        RK4: tl.constexpr,
        N: tl.constexpr,
        M: tl.constexpr,
        DIM: tl.constexpr,
        NP: tl.constexpr,
        MP: tl.constexpr,
        SP: tl.constexpr,
        DQ: tl.constexpr,
        NT: tl.constexpr,
        TYPES: tl.constexpr,
        HAS_SHAPES: tl.constexpr,
        HAS_DISCRETE: tl.constexpr,
        HAS_LO: tl.constexpr,
        HAS_HI: tl.constexpr,
        CLAMP: tl.constexpr,
        HAS_WCTRL: tl.constexpr,
        MODE: tl.constexpr,
        PAIRS: tl.constexpr,
        BLOCK: tl.constexpr,
    ):
        lane = tl.arange(0, BLOCK)
        if PAIRS:
            p = tl.program_id(0).to(tl.int64) * BLOCK + lane
            live = p < count
            b = tl.load(pairs_ptr + 2 * p, mask=live, other=0)
            k = tl.load(pairs_ptr + 2 * p + 1, mask=live, other=0)
        else:
            k = tl.program_id(1).to(tl.int64) * BLOCK + lane
            live = k < K
            b = tl.zeros_like(k) + tl.program_id(0).to(tl.int64)
            p = b * K + k
        cols = tl.arange(0, NP)
        ucols = tl.arange(0, MP)
        scols = tl.arange(0, SP)
        # [component, lane] tensors: a lane's components stay in its thread
        xmask = (cols[:, None] < N) & live[None, :]
        umask = (ucols[:, None] < M) & live[None, :]
        X = tl.load(x0_ptr + b[None, :] * N + cols[:, None], mask=xmask, other=0.0)
        real = X.dtype
        key = tl.load(keys_ptr + b, mask=live, other=0).to(tl.uint64)
        keep = tl.where(k < zero_noise, 0.0, 1.0).to(real)
        ku = k.to(tl.uint64)
        dt = tl.load(par_ptr + 0)
        two_pi = tl.load(par_ptr + 4)
        if HAS_LO:
            lo = tl.load(par_ptr + 5 + ucols, mask=ucols < M, other=0.0)[:, None]
        if HAS_HI:
            hi = tl.load(par_ptr + 9 + ucols, mask=ucols < M, other=0.0)[:, None]
        if MODE == 1:
            w = tl.load(w_ptr + p, mask=live, other=0.0)
        if MODE == 3:
            sidx = (b[None, :] * N + cols[:, None]) * (H + 1) * K + k[None, :]
            tl.store(states_ptr + sidx, X, mask=xmask)
        if MODE == 2:
            tl.store(states_ptr + p[None, :] * (H + 1) * N + cols[:, None], X, mask=xmask)
        zero = tl.zeros([BLOCK], dtype=real)
        stage = zero
        terminal = zero
        whole = zero
        ctrl = zero
        if MODE == 0:  # only the costs pass reads the shapes
            if HAS_DISCRETE:
                Hprev = _shapes_h(X, sa_ptr, sc_ptr, sval_ptr, cols, scols, NP, DQ)
        P: tl.constexpr = (M + 1) // 2
        for j in range(H):
            # standard normals, one Box-Muller pair per hash; eps = L z
            E = tl.zeros([MP, BLOCK], dtype=real)
            for q in tl.static_range(P):
                cnt = ku * (H * P) + (j * P + q + 1)
                hsh = _mix64(key + cnt * 0x9E3779B97F4A7C15)
                u1 = ((hsh >> 33).to(real) + 0.5) * 4.656612873077393e-10
                u2 = ((hsh >> 2) & 0x7FFFFFFF).to(real) * 4.656612873077393e-10
                R = keep * tl.sqrt(-2.0 * tl.log(u1))
                A = two_pi * u2
                L0 = tl.load(par_ptr + 13 + ucols * 4 + 2 * q, mask=ucols < M, other=0.0)
                E += L0[:, None] * (R * tl.cos(A))[None, :]
                if 2 * q + 1 < M:
                    L1 = tl.load(par_ptr + 13 + ucols * 4 + 2 * q + 1, mask=ucols < M, other=0.0)
                    E += L1[:, None] * (R * tl.sin(A))[None, :]
            pj = tl.load(
                plan_ptr + (b[None, :] * H + j) * M + ucols[:, None], mask=umask, other=0.0
            )
            U = pj + E
            if HAS_LO:
                U = tl.where(U < lo, lo, U)
            if HAS_HI:
                U = tl.where(U > hi, hi, U)
            if CLAMP:
                E = U - pj
            if HAS_WCTRL:
                wc = tl.load(
                    wctrl_ptr + (b[None, :] * H + j) * M + ucols[:, None], mask=umask, other=0.0
                )
                ctrl += tl.sum(E * wc, 0)
            if MODE == 1:
                part = tl.sum((w[None, :] * E).to(tl.float64), 1)
                # [B, H, m, blocks]: torch's sum over the blocks then reads contiguous rows
                env = tl.program_id(0).to(tl.int64)
                slot = ((env * H + j) * M + ucols) * tl.num_programs(1) + tl.program_id(1)
                tl.store(part_ptr + slot, part, mask=ucols < M)
            else:
                if MODE == 3:
                    cidx = (b[None, :] * M + ucols[:, None]) * H * K + j * K + k[None, :]
                    tl.store(controls_ptr + cidx, U, mask=umask)
                K1 = _xdot(X, U, cols, ucols, MODEL, DIM)
                if RK4:
                    half = tl.load(par_ptr + 1)
                    sixth = tl.load(par_ptr + 2)
                    K2 = _xdot(X + half * K1, U, cols, ucols, MODEL, DIM)
                    K3 = _xdot(X + half * K2, U, cols, ucols, MODEL, DIM)
                    K4 = _xdot(X + dt * K3, U, cols, ucols, MODEL, DIM)
                    X = X + sixth * (K1 + 2.0 * K2 + 2.0 * K3 + K4)
                else:
                    X = X + dt * K1
                if MODE == 2:
                    ridx = (p[None, :] * (H + 1) + j + 1) * N + cols[:, None]
                    tl.store(states_ptr + ridx, X, mask=xmask)
                if MODE == 3:
                    sidx = (b[None, :] * N + cols[:, None]) * (H + 1) * K + (j + 1) * K + k[None, :]
                    tl.store(states_ptr + sidx, X, mask=xmask)
                if MODE == 0:
                    if HAS_SHAPES:
                        Hcur = _shapes_h(X, sa_ptr, sc_ptr, sval_ptr, cols, scols, NP, DQ)
                    step = zero
                    for t in tl.static_range(NT):
                        # the term's kind, bits 2t..2t+1 of TYPES (constexpr: one branch is
                        # compiled per term)
                        weight = tl.load(tval_ptr + t * 8)
                        extra = tl.load(tval_ptr + t * 8 + 1)
                        eps = tl.load(tval_ptr + t * 8 + 2)
                        if ((TYPES >> (2 * t)) & 3) <= 1:  # goal, obstacle: |p - c|^2
                            tm = tl.load(tmask_ptr + t * NP + cols)
                            tc = tl.load(tcent_ptr + t * NP + cols)
                            dq = (X - tc[:, None]) * tm[:, None]
                            sq = tl.sum(dq * dq, 0)
                            if ((TYPES >> (2 * t)) & 3) == 0:  # goal
                                step += weight * sq
                                last = (j == H - 1) & (extra != 0.0)
                                terminal += tl.where(last, extra * sq, 0.0)
                            else:
                                dist = tl.sqrt(sq) - tl.load(tval_ptr + t * 8 + 3)
                                step += extra / tl.where(dist < eps, eps, dist)
                        else:
                            s0 = tl.load(tval_ptr + t * 8 + 4)
                            ns = tl.load(tval_ptr + t * 8 + 5)
                            inside = (scols >= s0) & (scols < s0 + ns)
                            if ((TYPES >> (2 * t)) & 3) == 2:  # barrier
                                hv = tl.where(Hcur < eps, eps, Hcur)
                                step += tl.sum(tl.where(inside[:, None], weight / hv, 0.0), 0)
                            else:  # discrete-time barrier, over its first `steps` steps
                                g1 = tl.load(tval_ptr + t * 8 + 7)
                                steps = tl.load(tval_ptr + t * 8 + 6)
                                v = g1 * Hprev - Hcur
                                v = tl.where(inside[:, None] & (v > 0), v, 0.0)
                                pen = weight * tl.sum(v, 0)
                                whole += tl.where(j < steps, pen, 0.0)
                    stage += step
                    if HAS_DISCRETE:
                        Hprev = Hcur
        if MODE % 3 == 0:  # the costs and buffers passes
            c = (stage + terminal) + whole
            if HAS_WCTRL:
                c = c + tl.load(par_ptr + 3) * ctrl
            tl.store(cost_ptr + p, c, mask=live)

    @triton.jit
    def _exp_weight(c, cmin, scale, floor):
        """``exp((c - cmin) * scale)`` (``scale = -1/lambda``) where the exponent is at least
        ``floor`` (a normal result), else 0; a non-finite cost is +inf (weight 0)."""
        expo = (tl.where(tl.abs(c) < float("inf"), c, float("inf")) - cmin) * scale
        live = expo >= floor  # false for NaN (a row without a finite cost)
        return tl.where(live, tl.exp(tl.where(live, expo, 0.0)), 0.0)

    @triton.jit
    def _weights_kernel(
        cost_ptr,
        scale_ptr,
        w_ptr,
        min_ptr,
        best_ptr,
        mean_ptr,
        ess_ptr,
        status_ptr,
        nonfinite_ptr,
        K,
        LOG_TINY: tl.constexpr,
        BLOCK: tl.constexpr,
        STEPS: tl.constexpr,
    ):
        """One environment per program: the planner's torch weights (``MPPI._weights``,
        ``cost_normalization="none"``) in three passes over its ``K`` costs, ``STEPS`` blocks
        each (a number known when compiling: the interpreter loops only over those)."""
        b = tl.program_id(0).to(tl.int64)
        lane = tl.arange(0, BLOCK)
        row = cost_ptr + b * K
        real = cost_ptr.dtype.element_ty
        inf = float("inf")
        # the smallest finite cost and its first index; the finite costs' count and sum
        low = tl.full([BLOCK], inf, real)
        at = lane
        count = tl.zeros([BLOCK], tl.int32)
        total = tl.zeros([BLOCK], tl.float64)  # float32 costs near 1e37 would overflow
        for step in range(STEPS):
            k = step * BLOCK + lane
            c = tl.load(row + k, mask=k < K, other=inf)
            finite = tl.abs(c) < inf
            clean = tl.where(finite, c, inf)
            better = clean < low  # strict: a lane keeps its first index of a tie
            low = tl.where(better, clean, low)
            at = tl.where(better, k, at)
            count += finite.to(tl.int32)
            total += tl.where(finite, c, 0.0).to(tl.float64)
        cmin = tl.min(low, 0)
        best = tl.min(tl.where(low == cmin, at, K), 0)
        ok = cmin < inf
        # the weights summed, then written normalised (recomputed rather than read back)
        scale = tl.load(scale_ptr)  # -1 / lambda
        floor = tl.full([], LOG_TINY, real)
        acc = tl.zeros([BLOCK], real)
        for step in range(STEPS):
            k = step * BLOCK + lane
            c = tl.load(row + k, mask=k < K, other=inf)
            acc += _exp_weight(c, cmin, scale, floor)
        norm = tl.maximum(tl.sum(acc, 0), tl.full([], 1.0, real))
        squares = tl.zeros([BLOCK], real)
        for step in range(STEPS):
            k = step * BLOCK + lane
            c = tl.load(row + k, mask=k < K, other=inf)
            w = _exp_weight(c, cmin, scale, floor) / norm
            tl.store(w_ptr + b * K + k, w, mask=k < K)
            squares += w * w
        n = tl.sum(count, 0)
        ssq = tl.maximum(tl.sum(squares, 0), tl.full([], 1e-30, real))
        tl.store(min_ptr + b, cmin)
        tl.store(best_ptr + b, best.to(tl.int64))
        tl.store(mean_ptr + b, (tl.sum(total, 0) / tl.maximum(n, 1).to(tl.float64)).to(real))
        tl.store(ess_ptr + b, tl.where(ok, 1.0 / ssq, 0.0))
        tl.store(status_ptr + b, tl.where(ok, 0, 1).to(tl.int64))
        tl.store(nonfinite_ptr + b, (K - n).to(tl.int64))


# -- calls -----------------------------------------------------------------------------------
def _launch(
    tab: Tables,
    mode: int,
    grid: tuple[int, ...],
    x0: Tensor,
    plan: Tensor,
    keys: Tensor,
    *,
    count: int = 0,
    K: int,
    pairs: Tensor | None = None,
    wctrl: Tensor | None = None,
    weights: Tensor | None = None,
    cost: Tensor | None = None,
    states: Tensor | None = None,
    controls: Tensor | None = None,
    part: Tensor | None = None,
) -> None:
    if triton is None:
        raise RuntimeError("torchcbf: the MPPI GPU kernel needs Triton, which does not import")
    H = plan.shape[1]
    dummy = x0  # pointers the pass does not read (never dereferenced)
    with on_device(x0):
        _rollout_kernel[grid](
            tab.par, tab.tmask, tab.tcent, tab.tval, tab.sa, tab.sc, tab.sval,
            x0, plan, dummy if wctrl is None else wctrl, keys,
            keys if pairs is None else pairs, dummy if weights is None else weights,
            dummy if cost is None else cost, dummy if states is None else states,
            dummy if controls is None else controls, dummy if part is None else part,
            count, K, tab.zero_noise,
            H=H, HAS_WCTRL=wctrl is not None, MODE=mode, PAIRS=pairs is not None, BLOCK=BLOCK,
            num_warps=WARPS, **tab.meta,
        )  # fmt: skip


def _check(
    tab: Tables,
    x0: Tensor,
    plan: Tensor,
    keys: Tensor,
    K: int,
    *,
    wctrl: Tensor | None = None,
    weights: Tensor | None = None,
) -> None:
    """The checks at the kernel's boundary: device, dtype, shape and layout of the inputs
    (``wctrl [B, H, m]`` and ``weights [B, K]`` where a pass reads them)."""
    B, H, m = plan.shape
    n = tab.meta["N"]
    given = [
        ("x0", x0, (B, n), plan.dtype),
        ("plan", plan, (B, H, m), plan.dtype),
        ("keys", keys, (B,), torch.int64),
        ("tables", tab.par, (_NPAR,), plan.dtype),
    ]
    if wctrl is not None:
        given.append(("wctrl", wctrl, (B, H, m), plan.dtype))
    if weights is not None:
        given.append(("weights", weights, (B, K), plan.dtype))
    for name, t, shape, dtype in given:
        if t.device != plan.device:
            raise ValueError(f"{name} is on {t.device}, the plan on {plan.device}")
        if t.dtype != dtype or tuple(t.shape) != shape or not t.is_contiguous():
            raise ValueError(
                f"{name} must be a contiguous {dtype} tensor of shape {list(shape)}, got "
                f"{t.dtype} {list(t.shape)}"
            )
    if m != tab.meta["M"] or K < 1:
        raise ValueError(f"the plan's control size {m} or K={K} does not match the tables")


class Kernel:
    """The Triton kernel bound to one configuration's tables, with the methods of
    :class:`torchcbf.mppi._rollout.Kernel`."""

    name = "triton"

    def __init__(self, tab: Tables, *, fused: bool) -> None:
        self.tab, self.fused = tab, fused

    def costs(self, x: Tensor, plan: Tensor, keys: Tensor, wctrl: Tensor | None) -> Tensor:
        return costs(self.tab, x, plan, keys, self.tab.samples, wctrl)

    def update(self, x: Tensor, plan: Tensor, keys: Tensor, w: Tensor) -> Tensor:
        return update(self.tab, x, plan, keys, w)

    def rows(self, x: Tensor, plan: Tensor, keys: Tensor, pairs: Tensor) -> Tensor:
        return rows(self.tab, x, plan, keys, self.tab.samples, pairs)

    def weights(self, cost: Tensor, temperature: float) -> tuple[Tensor, ...]:
        """:func:`weights` (the C kernel has no such pass)."""
        return weights(cost, temperature)

    def buffers(
        self,
        x: Tensor,
        plan: Tensor,
        keys: Tensor,
        states: Tensor,
        controls: Tensor,
        wctrl: Tensor | None,
        layout: str,
    ) -> Tensor | None:
        if layout != "component":
            raise ValueError(f"the Triton kernel stores component-major buffers, not {layout!r}")
        ctrl = buffers(self.tab, x, plan, keys, states, controls, wctrl)
        return None if wctrl is None else ctrl


def costs(
    tab: Tables, x0: Tensor, plan: Tensor, keys: Tensor, K: int, wctrl: Tensor | None
) -> Tensor:
    """Total cost ``[B, K]`` of every sample (built-in terms and the control cost)."""
    wctrl = None if wctrl is None else wctrl.to(plan.dtype).contiguous()
    _check(tab, x0, plan, keys, K, wctrl=wctrl)
    B = plan.shape[0]
    cost = plan.new_empty(B, K)
    grid = (B, triton.cdiv(K, BLOCK))
    _launch(tab, _COSTS, grid, x0, plan, keys, K=K, wctrl=wctrl, cost=cost)
    return cost


def update(tab: Tables, x0: Tensor, plan: Tensor, keys: Tensor, weights: Tensor) -> Tensor:
    """``sum_k w_k eps_k [B, H, m]`` for ``weights [B, K]``, accumulated in float64."""
    B, H, m = plan.shape
    K = weights.shape[-1]
    weights = weights.to(plan.dtype).contiguous()
    _check(tab, x0, plan, keys, K, weights=weights)
    blocks = triton.cdiv(K, BLOCK)
    part = torch.empty(B, H, m, blocks, dtype=torch.float64, device=plan.device)
    _launch(tab, _UPDATE, (B, blocks), x0, plan, keys, K=K, weights=weights, part=part)
    return part.sum(-1).to(plan.dtype)


def rows(tab: Tables, x0: Tensor, plan: Tensor, keys: Tensor, K: int, pairs: Tensor) -> Tensor:
    """The rollouts ``[P, H+1, n]`` of the samples ``pairs [P, 2]`` of ``(b, k)``."""
    _check(tab, x0, plan, keys, K)
    count = pairs.shape[0]
    states = plan.new_empty(count, plan.shape[1] + 1, tab.meta["N"])
    if count:
        grid = (triton.cdiv(count, BLOCK),)
        pairs = pairs.to(torch.int64).contiguous()
        _launch(tab, _ROWS, grid, x0, plan, keys, K=K, count=count, pairs=pairs, states=states)
    return states


def buffers(
    tab: Tables,
    x0: Tensor,
    plan: Tensor,
    keys: Tensor,
    states: Tensor,
    controls: Tensor,
    wctrl: Tensor | None,
) -> Tensor:
    """Fill the component-major ``states [B, K, H+1, n]`` and ``controls [B, K, H, m]``
    (:func:`torchcbf.mppi._rollout.component_major`) of every sample; return the control
    cost ``gamma sum_j U_j' Sigma^-1 eps_j`` ``[B, K]`` (zeros without ``wctrl``)."""
    B, K = states.shape[:2]
    wctrl = None if wctrl is None else wctrl.to(plan.dtype).contiguous()
    _check(tab, x0, plan, keys, K, wctrl=wctrl)
    H, n, m = plan.shape[1], tab.meta["N"], plan.shape[2]
    for name, t, shape in (
        ("states", states, (B, K, H + 1, n)),
        ("controls", controls, (B, K, H, m)),
    ):
        if (
            t.dtype != plan.dtype
            or tuple(t.shape) != shape
            or not t.permute(0, 3, 2, 1).is_contiguous()
        ):
            raise ValueError(f"{name} must be a component-major {plan.dtype} buffer {list(shape)}")
    cost = plan.new_empty(B, K)
    grid = (B, triton.cdiv(K, BLOCK))
    _launch(
        tab, _BUFFERS, grid, x0, plan, keys, K=K, wctrl=wctrl, cost=cost,
        states=states, controls=controls,
    )  # fmt: skip
    return cost


#: most costs one program of :func:`weights` reads per step of its loops
WEIGHTS_BLOCK = 2048


def weights(cost: Tensor, temperature: float) -> tuple[Tensor, ...]:
    """The planner's weights of ``cost [B, K]`` (float32 or float64) at ``temperature``
    (already floored at the dtype's smallest normal number), for
    ``cost_normalization="none"``: ``w [B, K]``, and per environment the smallest finite
    cost, its first index, the mean finite cost, the effective sample size, the status
    (1: no finite cost) and the number of non-finite costs (the fields of the planner's
    ``_Weights``). Equal to the torch weights up to rounding (other summation order)."""
    if triton is None:
        raise RuntimeError("torchcbf: the MPPI GPU kernel needs Triton, which does not import")
    if cost.dim() != 2 or cost.dtype not in (torch.float32, torch.float64):
        raise ValueError(f"cost must be a float32 or float64 [B, K] tensor, got {cost.dtype} "
                         f"{list(cost.shape)}")  # fmt: skip
    B, K = cost.shape
    cost = cost.contiguous()
    # -1/lambda in the cost's dtype, on the device (a kernel's float argument is float32);
    # filled, not copied from the host, so a CUDA graph can hold it
    scale = cost.new_full((1,), -1.0 / temperature)
    w = torch.empty_like(cost)
    # each output has storage of its own, as the torch weights' have
    cost_min, cost_mean, ess = (cost.new_empty(B) for _ in range(3))
    best, status, nonfinite = (
        torch.empty(B, dtype=torch.int64, device=cost.device) for _ in range(3)
    )
    block = min(tile(K), WEIGHTS_BLOCK)
    if B:
        with on_device(cost):
            _weights_kernel[(B,)](
                cost, scale, w, cost_min, best, cost_mean, ess, status, nonfinite, K,
                LOG_TINY=math.log(torch.finfo(cost.dtype).tiny), BLOCK=block,
                STEPS=triton.cdiv(K, block), num_warps=max(1, min(8, block // 256)),
            )  # fmt: skip
    return w, cost_min, best, cost_mean, ess, status, nonfinite
