"""Fuzz of the four C kernels through the public API, against the general torch paths.

Families (each case drives one kernel with odd inputs):

- ``qp``: ``solve_qp`` (the dual active-set kernel, and its real-time entry for a few rows)
  against ``method="ipm"`` on float64 copies;
- ``lie``: ``torchcbf.barriers.native.lie_terms`` (the Lie kernel) against
  ``lie_derivatives(..., method="analytic")``;
- ``filter``: ``SafetyFilter`` on a few states without gradient (the filter kernel, with the
  Lie kernel's conditions for quadric barriers) against its general path (a state that
  requires grad);
- ``mppi``: ``MPPI`` with built-in models (the rollout kernel): the fused path against the
  rollout path on the same noise, the stored rollouts against the torch dynamics, and user
  costs that return another dtype, a wrong shape, a strided, expanded or int tensor.

Inputs: dtype mixes, batches of 0, 1 and odd sizes, transposed, expanded and sliced tensors,
NaN/inf entries, extreme scales, sizes at and past the kernels' limits. An outcome is
acceptable when it is a correct answer (where the inputs are valid), a ``ValueError`` or
``TypeError``, or a per-row status; anything else (another exception, a mismatch, a crash or
a sanitizer report) is a finding.

Usage: ``python scripts/fuzz_kernels.py [--seed S] [--cases N] [--family F] [-v]``; prints
one line per finding and a one-line summary, exit status 1 on any finding.
tests/test_kernel_fuzz.py runs a slice of the same cases.
"""

from __future__ import annotations

import argparse
import random
import sys
import traceback
from collections.abc import Callable
from dataclasses import dataclass

import torch
from torch import Tensor

F64, F32 = torch.float64, torch.float32
#: the refusals an odd input may get
ACCEPTED = (ValueError, TypeError)


class Mismatch(AssertionError):
    """A kernel's answer differs from the general path's (or breaks an invariant)."""


@dataclass(frozen=True)
class Case:
    """One fuzz input: ``run()`` raises ``Mismatch`` on a wrong answer. ``valid``: the input
    is well-formed, so a refusal is a finding too; ``refuse``: only a refusal is correct."""

    family: str
    name: str
    run: Callable[[], None]
    valid: bool = True
    refuse: bool = False


def _check(cond: bool, message: str) -> None:
    if not cond:
        raise Mismatch(message)


def _close(a: Tensor, b: Tensor, tol: float, what: str) -> None:
    a, b = a.detach().to(F64), b.detach().to(F64)
    _check(a.shape == b.shape, f"{what}: shape {tuple(a.shape)} != {tuple(b.shape)}")
    same_nan = torch.isnan(a) == torch.isnan(b)
    _check(bool(same_nan.all()), f"{what}: NaN pattern differs")
    a, b = torch.nan_to_num(a, nan=0.0), torch.nan_to_num(b, nan=0.0)
    err = ((a - b).abs() / (1 + b.abs())).max().item() if a.numel() else 0.0
    _check(err <= tol, f"{what}: relative error {err:.3g} > {tol:g}")


def _layout(t: Tensor, how: str) -> Tensor:
    """``t`` with the same values in another memory layout."""
    if how == "transposed" and t.dim() >= 2:
        return t.transpose(-1, -2).contiguous().transpose(-1, -2)
    if how == "sliced":
        wide = torch.stack([t, torch.full_like(t, 1e300 if t.dtype == F64 else 1e30)], -1)
        return wide[..., 0]
    if how == "expanded" and t.dim() >= 1 and t.shape[0] >= 1:
        if bool((t == t[:1]).all()):
            return t[:1].expand_as(t)
    return t


# -- QP: the dual active-set kernel ------------------------------------------------------------
def _qp_problem(B: int, N: int, M: int, seed: int, share: bool):
    g = torch.Generator().manual_seed(seed)
    rows = 1 if share else B
    A = torch.randn(rows, N, N, generator=g, dtype=F64)
    Q = (A @ A.transpose(-1, -2) / N + 0.5 * torch.eye(N, dtype=F64)).expand(B, N, N)
    p = torch.randn(B, N, generator=g, dtype=F64)
    G = torch.randn(B, M, N, generator=g, dtype=F64)
    h = torch.rand(B, M, generator=g, dtype=F64) + 0.1  # x = 0 is feasible
    return Q.contiguous() if not share else Q, p, G, h


def _qp_case(rng: random.Random, i: int) -> Case:
    B = rng.choice([0, 1, 1, 2, 3, 5, 16, 17, 33])
    N = rng.choice([1, 2, 3, 5, 8, 63, 64, 65]) if B <= 5 else rng.choice([1, 2, 3, 7])
    M = rng.choice([1, 2, 3, 6])
    layout = rng.choice(["contiguous", "transposed", "sliced", "expanded"])
    dtypes = rng.choice(["f64", "f64", "f32", "mixed"])
    bounds = rng.choice(["none", "box", "half_inf", "lb_plus_inf"])
    odd = rng.choice(["none", "none", "nan_p", "inf_G", "huge", "tiny"])
    seed = rng.randrange(2**31)
    name = f"qp B={B} N={N} M={M} {layout} {dtypes} bounds={bounds} {odd} seed={seed}"

    def run() -> None:
        Q, p, G, h = _qp_problem(B, N, M, seed, share=layout == "expanded")
        lb = ub = None
        if bounds == "box":
            lb, ub = -torch.ones(B, N, dtype=F64), torch.ones(B, N, dtype=F64)
        elif bounds == "half_inf":
            lb = torch.full((B, N), -torch.inf, dtype=F64)
            ub = torch.full((B, N), 2.0, dtype=F64)
        elif bounds == "lb_plus_inf" and B:
            lb = torch.zeros(B, N, dtype=F64)
            lb[0, 0] = torch.inf
        if B and odd == "nan_p":
            p[B // 2, 0] = torch.nan
        elif B and odd == "inf_G":
            G[0, 0, 0] = torch.inf
        scale = {"huge": 1e150, "tiny": 1e-150}.get(odd, 1.0)
        if dtypes != "f64":
            scale = {"huge": 1e15, "tiny": 1e-15}.get(odd, 1.0)
        Q, p = Q * scale, p * scale
        args = [Q, p, G, h, lb, ub]
        if dtypes == "f32":
            args = [None if a is None else a.to(F32) for a in args]
        elif dtypes == "mixed":
            args[0] = args[0].to(F32)
        ref = _solve(*[None if a is None else a.to(F64) for a in args], method="ipm")
        args = [None if a is None else _layout(a, layout) for a in args]
        with torch.no_grad():
            out = _solve(*args, method="auto")
        _check(out.x.shape == (B, N), f"x shape {tuple(out.x.shape)}")
        _check(out.status.shape == (B,), f"status shape {tuple(out.status.shape)}")
        _check(bool(torch.isfinite(out.x).all()), "non-finite x")
        tol = 1e-5 if out.x.dtype == F64 else 2e-3
        both = (out.status == 0) & (ref.status == 0)
        if odd == "nan_p" and B:
            _check(int(out.status[B // 2]) == int(ref.status[B // 2]) != 0, "NaN row status")
        if bool(both.any()):
            _close(out.x[both], ref.x[both], tol, "x against ipm")
        solved = out.status == 0
        if bool(solved.any()):
            x = out.x[solved].to(F64)
            viol = (G[solved] @ x.unsqueeze(-1)).squeeze(-1) - h[solved]
            _check(bool((viol <= tol * (1 + h[solved].abs())).all()), "solved row infeasible")

    return Case("qp", name, run, valid=dtypes != "mixed")


def _solve(Q, p, G, h, lb, ub, method):
    from torchcbf.qp import solve_qp

    return solve_qp(Q, p, G, h, lb=lb, ub=ub, method=method)


# -- Lie terms and the safety filter -----------------------------------------------------------
def _model(kind: str, size: int, sigma: float | None):
    from torchcbf.dynamics import AccelUnicycle, DoubleIntegrator, SingleIntegrator, Unicycle

    if kind == "single":
        return SingleIntegrator(size, sigma=sigma)
    if kind == "double":
        return DoubleIntegrator(size, sigma=sigma)
    return Unicycle(sigma=sigma) if kind == "unicycle" else AccelUnicycle(sigma=sigma)


def _barriers(kind: str, model, k: int, g: torch.Generator, shape: str):
    """``k`` quadrics (``shape``: balls, ellipses, scaled balls), rectified where the model
    is of relative degree two; ``"intersection"``: the smooth elementwise minimum of those and
    the rescaled shapes, rectified with another gain (``k`` outputs); ``"union"``: the
    maximum of all their outputs (one)."""
    from torchcbf.barriers import Ball, Ellipse, ExponentialBarrier, Intersection, Scaled, Union

    pos = 1 if model.state_dim == 1 else 2
    if kind == "double" and model.state_dim // 2 == 1:
        pos = 1
    index = tuple(range(pos))
    centers = torch.randn(k, pos, generator=g, dtype=F64) * 2 + 3
    if shape == "ellipse" and pos == 2:
        axes = torch.rand(k, pos, generator=g, dtype=F64) + 0.3
        angle = torch.rand(k, generator=g, dtype=F64) * 3
        barrier = Ellipse(centers, axes, index=index, angle=angle)
    else:
        barrier = Ball(centers, torch.rand(k, generator=g, dtype=F64) + 0.2, index=index)
    if shape == "scaled":
        barrier = Scaled(barrier, torch.rand(k, generator=g, dtype=F64) + 0.5)
    other = Scaled(barrier, torch.rand(k, generator=g, dtype=F64) + 0.5)
    if kind in ("double", "accel_unicycle"):
        barrier = ExponentialBarrier(barrier, model, 2, (1.5,))
        other = ExponentialBarrier(other, model, 2, (4.0,))
    if shape == "intersection":
        barrier = Intersection(barrier, other, smooth=True, temperature=0.3, elementwise=True)
    elif shape == "union":
        barrier = Union(barrier, other)
    return barrier


def _outputs(shape: str, k: int) -> int:
    """The number of outputs of :func:`_barriers`'s barrier."""
    return 1 if shape == "union" else k


def _states(model, B: int, g: torch.Generator) -> Tensor:
    x = torch.randn(B, model.state_dim, generator=g, dtype=F64)
    if type(model).__name__ == "AccelUnicycle":
        x[:, 2] = x[:, 2].abs() + 0.1
    return x


def _lie_setup(rng: random.Random):
    kind = rng.choice(["single", "single", "double", "unicycle", "accel_unicycle"])
    size = rng.choice([1, 2, 3, 31, 32, 33]) if kind in ("single", "double") else 0
    if kind == "double":
        size = min(size, 17)
    k = rng.choice([1, 2, 3, 17, 40])
    sigma = rng.choice([None, None, 0.3])
    shape = rng.choice(["ball", "ellipse", "scaled", "intersection", "union"])
    return kind, size, k, sigma, shape


def _lie_case(rng: random.Random, i: int) -> Case:
    kind, size, k, sigma, shape = _lie_setup(rng)
    B = rng.choice([0, 1, 1, 3, 16, 17])
    layout = rng.choice(["contiguous", "transposed", "sliced", "expanded"])
    dtype = rng.choice(["f64", "f32", "f32_model"])
    odd = rng.choice(["none", "none", "nan", "huge"])
    seed = rng.randrange(2**31)
    name = (
        f"lie {kind}({size}) k={k} sigma={sigma} {shape} B={B} {layout} {dtype} {odd} seed={seed}"
    )

    def run() -> None:
        from torchcbf.barriers import native
        from torchcbf.barriers.lie import lie_derivatives

        g = torch.Generator().manual_seed(seed)
        model = _model(kind, size, sigma).to(F64)
        barrier = _barriers(kind, model, k, g, shape).to(F64)
        x = _states(model, B, g)
        if layout == "expanded" and B:
            x = x[:1].expand(B, -1)
        if B and odd == "nan":
            x = x.clone()
            x[0, 0] = torch.nan
        elif odd == "huge":
            x = x * (1e150 if dtype == "f64" else 1e15)
        if dtype == "f32":  # the kernel reads the float32 states: the reference does too
            x = x.to(F32).to(F64)
        ref = lie_derivatives(barrier, x, model, method="analytic")
        xin = x.to(F32) if dtype == "f32" else x
        if dtype == "f32_model":
            model, barrier = model.to(F32), barrier.to(F32)
        xin = _layout(xin, layout)
        with torch.no_grad():
            found = native.lie_terms([barrier], xin, model)
        if found is None:
            return  # the kernel declined: the torch path answers
        terms, sizes = found
        k_out = _outputs(shape, k)
        _check(list(sizes) == [k_out], f"sizes {sizes}")
        tol = 1e-9 if xin.dtype == F64 and dtype != "f32_model" else 1e-3
        if odd == "huge":
            tol = max(tol, 1e-6)
        rows = torch.isfinite(x).all(-1)  # a NaN state's terms: any NaN pattern
        _check(terms.h.shape == (B, k_out), f"h shape {tuple(terms.h.shape)}")
        _close(terms.h[rows], ref.h.reshape(B, -1)[rows], tol, "h")
        _close(terms.lfh[rows], ref.lfh.reshape(B, -1)[rows], tol, "lfh")
        _close(terms.lgh[rows], ref.lgh.reshape(B, k_out, -1)[rows], tol, "lgh")
        if terms.hess_trace is not None and ref.hess_trace is not None:
            trace = ref.hess_trace.reshape(B, -1)[rows]
            _close(terms.hess_trace[rows], trace, tol, "hess_trace")

    return Case("lie", name, run, valid=dtype == "f64" or dtype == "f32")


def _filter_case(rng: random.Random, i: int) -> Case:
    from torchcbf.filters import realtime

    kind, size, k, sigma, shape = _lie_setup(rng)
    B = rng.choice([0, 1, 1, 2, 3, 16, 17, realtime.MAX_BATCH, realtime.MAX_BATCH + 1])
    if B >= realtime.MAX_BATCH:
        k, size = min(k, 3), min(size, 3)
    layout = rng.choice(["contiguous", "transposed", "sliced", "expanded"])
    dtype = rng.choice(["f64", "f64", "f32", "x_f32", "u_f32"])
    slack = rng.choice([None, "shared", "per_row", "none"])
    limits = rng.choice([None, 1.0, 1e300])
    odd = rng.choice(["none", "none", "nan_x", "inf_u", "huge_u"])
    seed = rng.randrange(2**31)
    name = (
        f"filter {kind}({size}) k={k} sigma={sigma} {shape} B={B} {layout} {dtype} "
        f"slack={slack} limits={limits} {odd} seed={seed}"
    )

    def run() -> None:
        from torchcbf.filters import SafetyFilter

        g = torch.Generator().manual_seed(seed)
        model = _model(kind, size, sigma)
        barrier = _barriers(kind, model, k, g, shape)
        m = model.control_dim
        opts = {} if slack is None else {"slack": slack}
        if limits is not None:
            opts.update(u_min=-limits, u_max=limits)
        filt = SafetyFilter(model, barrier, **opts).to(F32 if dtype == "f32" else F64)
        x = _states(model, B, g)
        u = torch.randn(B, m, generator=g, dtype=F64) * 3
        if layout == "expanded" and B:
            x, u = x[:1].expand(B, -1), u[:1].expand(B, -1)
        if B and odd == "nan_x":
            x = x.clone()
            x[B - 1, 0] = torch.nan
        elif B and odd == "inf_u":
            u = u.clone()
            u[0, 0] = torch.inf
        elif odd == "huge_u":
            u = u * 1e200
        if dtype == "f32":
            x, u = x.to(F32), u.to(F32)
        with torch.enable_grad():
            ref = filt(x.clone().requires_grad_(), u)
        xin = x.to(F32) if dtype == "x_f32" else x
        uin = u.to(F32) if dtype == "u_f32" else u
        with torch.no_grad():
            out = filt(_layout(xin, layout), _layout(uin, layout))
        tol = 1e-6 if out.u.dtype == F64 and dtype == "f64" else 2e-3
        _check(out.u.shape == (B, m), f"u shape {tuple(out.u.shape)}")
        _check(bool(torch.isfinite(out.u).all()), "non-finite u")
        same = out.status == ref.status
        if odd == "huge_u":
            # at this scale the QP's rounding depends on the path's Lie terms, so a row one
            # path certifies may fall back on the other; what must hold on both is that no
            # answer called SOLVED or RELAXED is wrong
            from torchcbf.filters import FilterStatus

            fallback = (out.status == FilterStatus.FALLBACK) | (ref.status == FilterStatus.FALLBACK)
            same = same | fallback
            for o in (out, ref):
                solved = (o.status == FilterStatus.SOLVED).unsqueeze(-1)
                # a condition a u + b judged on the scale of |u| (|a| < 1e3 in these scenes)
                scale = 1.0 + 1e3 * o.u.detach().abs().amax(-1, keepdim=True)
                met = (o.constraint_value.detach() >= -tol * scale) | ~solved
                _check(bool(met.all()), "a SOLVED row violates its conditions")
        _check(bool(same.all()), f"status {out.status.tolist()} != {ref.status.tolist()}")
        if odd != "huge_u":
            _close(out.u, ref.u, tol, "u")
        _close(out.h, ref.h, tol, "h")

    return Case("filter", name, run, valid=dtype in ("f64", "f32"))


# -- MPPI: the rollout kernel ------------------------------------------------------------------
def _goal(n: int):
    from torchcbf.mppi import QuadraticGoal

    d = min(n, 2)
    return QuadraticGoal(tuple(1.0 + j for j in range(d)), 2.0, tuple(range(d)), 5.0)


def _mppi_model(kind: str, size: int):
    return _model(kind, size, None)


class _TorchCost(torch.nn.Module):
    """A user cost the kernel cannot see through: ``inner``'s value, returned as ``how`` says;
    it checks the rollouts it is given against the torch dynamics."""

    def __init__(self, inner, how: str, model, integrator: str, dt: float) -> None:
        super().__init__()
        self.inner, self.how, self.model = inner, how, model
        self.integrator, self.dt = integrator, dt
        self.checked = False

    def forward(self, states: Tensor, controls: Tensor, t0) -> Tensor:
        from torchcbf import integrators

        step = integrators.euler if self.integrator == "euler" else integrators.rk4
        x, u = states[..., :-1, :], controls
        nxt = step(self.model, x.reshape(-1, x.shape[-1]), u.reshape(-1, u.shape[-1]), self.dt)
        tol = 1e-9 if states.dtype == F64 else 1e-4
        err = (nxt.reshape(x.shape) - states[..., 1:, :]).abs() / (1 + states[..., 1:, :].abs())
        if err.numel() and not bool((err <= tol).all()):
            raise Mismatch(f"stored rollout differs from the torch dynamics by {err.max():.3g}")
        self.checked = True
        c = self.inner(states, controls, t0)
        how = self.how
        if how == "other_dtype":
            return c.to(F32 if c.dtype == F64 else F64)
        if how == "wrong_shape":
            return c.reshape(-1)
        if how == "extra_dim":
            return c.unsqueeze(-1)
        if how == "expanded":  # every sample costs the same
            return c[:, :1].expand_as(c)
        if how == "strided":
            return torch.stack([c, torch.zeros_like(c)], -1)[..., 0]
        if how == "transposed":
            return c.t().contiguous().t() if c.shape[0] > 1 else c
        if how == "int":
            return c.round().to(torch.int64)
        if how == "nan_some":
            c = c.clone()
            c[:, ::3] = torch.nan
            return c
        if how == "all_inf":
            return torch.full_like(c, torch.inf)
        return c


#: drawn first: a float64 planner whose cost returns float32 (and the converse) on the
#: rollout path, sizes around the kernel's lanes
_MPPI_FIRST = [
    {"kind": "single", "size": 2, "module": "f64", "state": "same", "how": "other_dtype"},
    {"kind": "unicycle", "size": 0, "module": "f64", "state": "same", "how": "other_dtype"},
    {"kind": "single", "size": 2, "module": "f32", "state": "same", "how": "other_dtype"},
]


def _mppi_case(rng: random.Random, i: int) -> Case:
    from torchcbf.mppi import _rollout

    kind = rng.choice(["single", "single", "double", "unicycle", "accel_unicycle"])
    size = 0
    if kind == "single":
        size = rng.choice([1, 2, 3, _rollout.MAX_STATE, _rollout.MAX_STATE + 1])
    elif kind == "double":
        size = rng.choice([1, 2, _rollout.MAX_CONTROL, _rollout.MAX_CONTROL + 1])
    H = rng.choice([1, 2, 5, 11])
    K = rng.choice([1, 7, 64, 65, 300])
    B = rng.choice([1, 1, 2, 3])
    integrator = rng.choice(["euler", "rk4"])
    module = rng.choice(["f64", "f32"])
    state = rng.choice(["same", "same", "other"])
    how = rng.choice(
        ["same", "same", "other_dtype", "other_dtype", "wrong_shape", "extra_dim", "expanded",
         "strided", "transposed", "int", "nan_some", "all_inf"]
    )  # fmt: skip
    layout = rng.choice(["contiguous", "sliced", "expanded", "unbatched"])
    limits = rng.choice([None, 0.5])
    control = rng.choice([0.0, 0.1])
    seed = rng.randrange(2**31)
    if i < len(_MPPI_FIRST):
        first = _MPPI_FIRST[i]
        kind, size, module, state, how = (first[key] for key in ("kind", "size", "module",
                                                                  "state", "how"))  # fmt: skip
        K, layout, control = 300, "contiguous", 0.0
    name = (
        f"mppi {kind}({size}) H={H} K={K} B={B} {integrator} module={module} state={state} "
        f"cost={how} {layout} limits={limits} control={control} seed={seed}"
    )

    def run() -> None:
        from torchcbf.mppi import MPPI

        g = torch.Generator().manual_seed(seed)
        model = _mppi_model(kind, size)
        goal = _goal(model.state_dim)
        dtype = F64 if module == "f64" else F32
        xdtype = dtype if state == "same" else (F32 if dtype == F64 else F64)
        opts = {"integrator": integrator, "seed": seed % 1000}
        if limits is not None:
            opts.update(u_min=-limits, u_max=limits)
        args = (H, K, 0.1, 0.7, 0.5, control)
        x = _states(model, B, g).to(xdtype)
        if layout == "sliced":
            x = _layout(x, "sliced")
        elif layout == "expanded":
            x = x[:1].expand(B, -1)
        elif layout == "unbatched":
            x = x[0]
        user = _TorchCost(goal, how, model.to(xdtype), integrator, 0.1)
        planner = MPPI(model, user, *args, **opts).to(dtype)
        # the reference: the built-in cost on the fused path (same noise), or, where the
        # kernel does not take the model, the torch path
        fused = MPPI(model, goal, *args, **opts).to(dtype)
        out = planner(x)
        ref = fused(x)
        if how in ("wrong_shape", "extra_dim"):
            raise Mismatch(f"a cost of the wrong shape was accepted (path {planner.path})")
        _check(user.checked or planner.path == "torch", "the user cost was not called")
        _check(out.u.shape == ref.u.shape, f"u shape {tuple(out.u.shape)}")
        _check(out.u.dtype == xdtype, f"u dtype {out.u.dtype}, x was {xdtype}")
        _check(bool(torch.isfinite(out.u).all()), f"non-finite u on path {planner.path}")
        if how == "all_inf":
            _check(bool((out.status == 1).all()), "all-inf costs: status not 1")
            return
        if how == "nan_some":
            _check(bool((out.nonfinite > 0).all()), "NaN costs not counted")
            return
        if how == "expanded":
            _check(bool((out.ess > K - 0.5).all()), "equal costs: ess is not K")
            return
        if planner.path == "torch" or fused.path == "torch":
            return  # different noise: no sample-by-sample reference
        # float32 costs and weights: the weights agree to float32 rounding
        rough = how in ("other_dtype", "int") or xdtype == F32
        if how == "int":
            return
        tol = 2e-3 if rough else 1e-8
        _close(out.u, ref.u, tol, f"u ({planner.path} against {fused.path})")
        _close(out.best_states, ref.best_states, tol, "best_states")

    valid = how in ("same", "strided", "transposed", "nan_some", "all_inf", "expanded")
    return Case("mppi", name, run, valid=valid, refuse=how in ("wrong_shape", "extra_dim"))


FAMILIES: dict[str, Callable[[random.Random, int], Case]] = {
    "qp": _qp_case,
    "lie": _lie_case,
    "filter": _filter_case,
    "mppi": _mppi_case,
}


def cases(seed: int = 0, count: int = 40, families: list[str] | None = None) -> list[Case]:
    """``count`` cases of each family (all by default), drawn from ``seed``."""
    out = []
    for family in families or list(FAMILIES):
        rng = random.Random(f"{seed}:{family}")
        out.extend(FAMILIES[family](rng, i) for i in range(count))
    return out


def run_case(case: Case) -> tuple[str, str]:
    """``(outcome, detail)``: outcome ``"ok"`` (a correct answer or an accepted refusal) or
    ``"finding"``."""
    try:
        case.run()
    except ACCEPTED as err:
        if case.valid:
            return "finding", f"valid input refused: {type(err).__name__}: {err}"
        return "ok", f"refused: {type(err).__name__}: {err}"
    except Mismatch as err:
        return "finding", f"mismatch: {err}"
    except Exception as err:  # noqa: BLE001 - every other exception is a finding
        last = traceback.extract_tb(err.__traceback__)[-1]
        where = f"{last.filename.rsplit('/', 1)[-1]}:{last.lineno}"
        return "finding", f"{type(err).__name__} at {where}: {err}"
    if case.refuse:
        return "finding", "an invalid input was not refused"
    return "ok", "answered"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--cases", type=int, default=40, help="cases per family")
    parser.add_argument("--family", action="append", choices=list(FAMILIES))
    parser.add_argument("-v", "--verbose", action="store_true")
    args = parser.parse_args(argv)
    torch.set_num_threads(max(1, min(2, torch.get_num_threads())))
    found: list[tuple[Case, str]] = []
    refused = 0
    todo = cases(args.seed, args.cases, args.family)
    for case in todo:
        if args.verbose:
            print("run", case.name, flush=True)
        outcome, detail = run_case(case)
        if outcome == "finding":
            found.append((case, detail))
            print(f"FINDING [{case.family}] {case.name}: {detail}", flush=True)
        elif detail.startswith("refused"):
            refused += 1
    families = ",".join(args.family or FAMILIES)
    print(
        f"fuzz_kernels: seed {args.seed}, {len(todo)} cases ({families}): "
        f"{len(todo) - len(found)} ok ({refused} refused), {len(found)} findings"
    )
    return 1 if found else 0


if __name__ == "__main__":
    sys.exit(main())
