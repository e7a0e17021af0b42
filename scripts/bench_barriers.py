"""Benchmark: Lie derivatives of 16 barriers over a large batch of states, in one call.

Compares ``barrier.lie`` (batched autograd, and the closed-form path) against a
``torch.func`` formulation (``vmap(jacrev)`` for the gradient, ``vmap(hessian)`` for the
Hessian trace) and a per-row Python loop (timed on a subset, extrapolated to the batch).
The setting is scenario B's: AccelUnicycle with diffusion ``sigma = 0.28 I``. The answers
of every timed formulation (those of its last timed call) are checked against the
``torch.func`` formulation in float64 on the first 1,000 states (the loop's on its rows):
the largest difference is printed per formulation under each table.

    python scripts/bench_barriers.py            # 100,000 states, 16 barriers
    python scripts/bench_barriers.py --quick    # 10,000 states
"""

from __future__ import annotations

import argparse
import copy
import sys
import time
from collections.abc import Callable

import torch
from torch.func import hessian, jacrev, vmap

from torchcbf._argtypes import positive_int, torch_device
from torchcbf.barriers import Ball, BarrierStack, Ellipse
from torchcbf.dynamics import AccelUnicycle


def _best(fn: Callable[[], object], repeats: int) -> tuple[float, object]:
    """Best wall time of ``fn`` over ``repeats`` calls after a warm-up, and the answer of its
    last call (checked after the timing)."""
    out = fn()  # warm-up
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - start)
    return min(times), out


#: states of the agreement check (the loop's rows: the first of them it timed)
CHECK_ROWS = 1000


def _terms(out: object, rows: int) -> tuple[torch.Tensor, ...]:
    """``(lfh, lgh[, hess_trace])`` of the first ``rows`` states of a formulation's answer:
    a ``LieTerms``, ``_func_terms``' tuple, or the loop's list of one-state ``LieTerms``."""
    if isinstance(out, list):
        per_row = [_terms(o, 1) for o in out[:rows]]
        return tuple(torch.cat(t) for t in zip(*per_row, strict=True))
    if isinstance(out, tuple) and not hasattr(out, "lfh"):
        lfh, lgh, hess = out
    else:
        lfh, lgh, hess = out.lfh, out.lgh, out.hess_trace
    if lfh.dim() == 1:  # one state
        lfh, lgh = lfh.unsqueeze(0), lgh.unsqueeze(0)
        hess = None if hess is None else hess.unsqueeze(0)
    found = (lfh[:rows], lgh[:rows]) + (() if hess is None else (hess[:rows],))
    return tuple(t.double() for t in found)


#: largest relative difference ``|a - r| / (1 + |r|)`` from the float64 reference that a
#: formulation's answers may have: rounding of their dtype, with room
TOLERANCE = {torch.float32: 1e-4, torch.float64: 1e-9}


def _max_difference(out: object, ref: tuple[torch.Tensor, ...]) -> float:
    """Largest relative difference ``|a - r| / (1 + |r|)`` of a formulation's terms from
    the reference's (on the rows the formulation has); ``inf`` when a term the reference
    has is missing."""
    got = _terms(out, ref[0].shape[0])
    if len(got) < len(ref):
        return float("inf")
    rows = got[0].shape[0]
    diffs = [
        float(((g.cpu().double() - r[:rows].cpu()).abs() / (1.0 + r[:rows].cpu().abs())).max())
        for g, r in zip(got, ref, strict=False)
    ]
    return max(diffs)


def _func_terms(barrier, dyn, x: torch.Tensor, with_hessian: bool):
    """lfh, lgh, hess_trace through torch.func on a single-state function, vmapped."""

    def h_row(z: torch.Tensor) -> torch.Tensor:
        return barrier(z)

    jac = vmap(jacrev(h_row))(x)  # [B, k, n]
    lfh = (jac * dyn.f(x).unsqueeze(-2)).sum(-1)
    lgh = jac @ dyn.g(x)
    hess = None
    if with_hessian:
        H = vmap(hessian(h_row))(x)  # [B, k, n, n]
        s = dyn.sigma(x).unsqueeze(-3)  # [B, 1, n, q]
        hess = (s * (H @ s)).sum((-2, -1))
    return lfh, lgh, hess


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--quick", action="store_true", help="10,000 states, fewer repeats")
    parser.add_argument("--batch", type=positive_int, default=None, help="number of states")
    parser.add_argument("--barriers", type=positive_int, default=16)
    parser.add_argument(
        "--loop-rows", type=positive_int, default=100, help="rows timed in the loop"
    )
    parser.add_argument("--repeats", type=positive_int, default=None)
    parser.add_argument(
        "--threads", type=positive_int, default=None, help="torch.set_num_threads (>= 1)"
    )
    parser.add_argument("--device", default="cpu", type=torch_device)
    parser.add_argument("--dtype", default="float32", choices=["float32", "float64"])
    args = parser.parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)
    batch = args.batch if args.batch is not None else (10_000 if args.quick else 100_000)
    repeats = args.repeats if args.repeats is not None else (2 if args.quick else 3)
    dtype = getattr(torch, args.dtype)
    device = torch.device(args.device)
    k = args.barriers

    gen = torch.Generator().manual_seed(0)
    centers = 4 * torch.rand(k, 2, generator=gen) - 2
    radii = 0.2 + 0.5 * torch.rand(k, generator=gen)
    axes = 0.2 + torch.rand(k, 2, generator=gen)
    dyn = AccelUnicycle(sigma=0.28).to(device, dtype)
    x = (3 * torch.randn(batch, 4, generator=gen)).to(device, dtype)
    setups = {
        f"Ball, batched [k={k}]": Ball(centers, radii),
        f"BarrierStack of {k} Ellipses": BarrierStack(
            *[Ellipse(centers[i], axes[i], angle=float(i)) for i in range(k)]
        ),
    }
    sync = torch.cuda.synchronize if device.type == "cuda" else (lambda: None)

    print(
        f"lie() of {k} barriers at {batch:,} states, AccelUnicycle (n=4, m=2, q=4), "
        f"{args.dtype}, {device}, {torch.get_num_threads()} threads, best of {repeats}"
    )
    # the reference of the agreement check: torch.func in float64 on the first states
    dyn64 = copy.deepcopy(dyn).to(torch.float64)
    x64 = x[:CHECK_ROWS].to(torch.float64)
    worst = 0.0
    for name, barrier in setups.items():
        barrier = barrier.to(device, dtype)
        barrier64 = copy.deepcopy(barrier).to(torch.float64)
        for with_hessian in (False, True):
            rows: list[tuple[str, float]] = []
            answers: list[tuple[str, object]] = []

            def ours(method: str, wh: bool = with_hessian, b=barrier) -> object:
                with torch.no_grad():
                    out = b.lie(x, dyn, method=method, hessian=wh)
                sync()
                return out

            for method in ("autograd", "analytic"):
                sec, out = _best(lambda m=method: ours(m), repeats)
                rows.append((f"torchcbf lie ({method})", sec))
                answers.append((method, out))

            def func(wh: bool = with_hessian, b=barrier) -> object:
                with torch.no_grad():
                    out = _func_terms(b, dyn, x, wh)
                sync()
                return out

            sec, out = _best(func, repeats)
            rows.append(("torch.func vmap(jacrev/hessian)", sec))
            answers.append(("torch.func", out))

            sub = x[: args.loop_rows]

            def loop(wh: bool = with_hessian, b=barrier, sub: torch.Tensor = sub) -> list:
                outs = []
                with torch.no_grad():
                    for i in range(sub.shape[0]):
                        outs.append(b.lie(sub[i], dyn, hessian=wh))
                sync()
                return outs

            sec, out = _best(loop, 1)
            t_loop = sec * batch / sub.shape[0]
            rows.append(
                (f"per-row loop (x{batch // sub.shape[0]} from {sub.shape[0]} rows)", t_loop)
            )
            answers.append((f"per-row loop ({min(sub.shape[0], CHECK_ROWS)} rows)", out))

            ref = rows[0][1]
            print(f"\n{name}, hess_trace={'yes' if with_hessian else 'no'}")
            print(f"  {'method':<44}{'time [ms]':>12}{'vs autograd':>14}")
            for label, sec in rows:
                print(f"  {label:<44}{1e3 * sec:>12.1f}{sec / ref:>13.2f}x")
            with torch.no_grad():
                reference = _terms(_func_terms(barrier64, dyn64, x64, with_hessian), CHECK_ROWS)
            diffs = [(label, _max_difference(out, reference)) for label, out in answers]
            worst = max([worst, *(d for _, d in diffs)])
            print(
                f"  max relative difference from torch.func in float64 on {x64.shape[0]:,} states "
                f"({'lfh, lgh, hess_trace' if with_hessian else 'lfh, lgh'}): "
                + ", ".join(f"{label} {d:.2e}" for label, d in diffs)
            )

    print(
        f"\nmax relative difference between formulations on {x64.shape[0]:,} states: "
        f"{worst:.2e} (every timed formulation of every setup, against torch.func in float64; "
        f"{args.dtype} answers)"
    )
    tol = TOLERANCE[getattr(torch, args.dtype)]
    if not worst <= tol:
        print(f"bench_barriers: answers differ by more than {tol:.0e}", file=sys.stderr)
        raise SystemExit(1)


if __name__ == "__main__":
    main()
