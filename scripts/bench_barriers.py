"""Benchmark: Lie derivatives of 16 barriers over a large batch of states, in one call.

Compares ``barrier.lie`` (batched autograd, and the closed-form path) against a
``torch.func`` formulation (``vmap(jacrev)`` for the gradient, ``vmap(hessian)`` for the
Hessian trace) and a per-row Python loop (timed on a subset, extrapolated to the batch).
The setting is scenario B's: AccelUnicycle with diffusion ``sigma = 0.28 I``.

    python scripts/bench_barriers.py            # 100,000 states, 16 barriers
    python scripts/bench_barriers.py --quick    # 10,000 states
"""

from __future__ import annotations

import argparse
import time
from collections.abc import Callable

import torch
from torch.func import hessian, jacrev, vmap

from torchcbf.barriers import Ball, BarrierStack, Ellipse
from torchcbf.dynamics import AccelUnicycle


def _best(fn: Callable[[], object], repeats: int) -> float:
    fn()  # warm-up
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
    return min(times)


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
    parser.add_argument("--batch", type=int, default=None, help="number of states")
    parser.add_argument("--barriers", type=int, default=16)
    parser.add_argument("--loop-rows", type=int, default=100, help="rows timed in the loop")
    parser.add_argument("--repeats", type=int, default=None)
    parser.add_argument("--threads", type=int, default=None, help="torch.set_num_threads")
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--dtype", default="float32", choices=["float32", "float64"])
    args = parser.parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)
    batch = args.batch or (10_000 if args.quick else 100_000)
    repeats = args.repeats or (2 if args.quick else 3)
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
    for name, barrier in setups.items():
        barrier = barrier.to(device, dtype)
        for with_hessian in (False, True):
            rows: list[tuple[str, float]] = []

            def ours(method: str, wh: bool = with_hessian, b=barrier) -> None:
                with torch.no_grad():
                    b.lie(x, dyn, method=method, hessian=wh)
                sync()

            rows.append(("torchcbf lie (autograd)", _best(lambda: ours("autograd"), repeats)))
            rows.append(("torchcbf lie (analytic)", _best(lambda: ours("analytic"), repeats)))

            def func(wh: bool = with_hessian, b=barrier) -> None:
                with torch.no_grad():
                    _func_terms(b, dyn, x, wh)
                sync()

            rows.append(("torch.func vmap(jacrev/hessian)", _best(func, repeats)))

            sub = x[: args.loop_rows]

            def loop(wh: bool = with_hessian, b=barrier, sub: torch.Tensor = sub) -> None:
                with torch.no_grad():
                    for i in range(sub.shape[0]):
                        b.lie(sub[i], dyn, hessian=wh)
                sync()

            t_loop = _best(loop, 1) * batch / sub.shape[0]
            rows.append(
                (f"per-row loop (x{batch // sub.shape[0]} from {sub.shape[0]} rows)", t_loop)
            )

            ref = rows[0][1]
            print(f"\n{name}, hess_trace={'yes' if with_hessian else 'no'}")
            print(f"  {'method':<44}{'time [ms]':>12}{'vs autograd':>14}")
            for label, sec in rows:
                print(f"  {label:<44}{1e3 * sec:>12.1f}{sec / ref:>13.2f}x")

    # agreement check between the three formulations (first setup, with Hessian)
    barrier = next(iter(setups.values())).to(device, dtype)
    sub = x[:1000]
    with torch.no_grad():
        a = barrier.lie(sub, dyn)
        b = barrier.lie(sub, dyn, method="analytic")
        lfh, lgh, hess = _func_terms(barrier, dyn, sub, True)
    err = max(
        float((a.lfh - lfh).abs().max()),
        float((a.lgh - lgh).abs().max()),
        float((a.hess_trace - hess).abs().max()),
        float((a.lfh - b.lfh).abs().max()),
        float((a.hess_trace - b.hess_trace).abs().max()),
    )
    print(f"\nmax |difference| between formulations on 1,000 states: {err:.2e}")


if __name__ == "__main__":
    main()
