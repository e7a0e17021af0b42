"""Scenario B's elastic filter QP over random states: false failures and path agreement.

The default filter of scenario B (``mppi_cbf(method="mppi_scbf")``) solves, per state, a
QP in two controls and one slack ``s >= 0`` without upper bound; it is always feasible, so
every row whose ``qp_status`` is not SOLVED is a false failure. States are drawn uniformly
over the field and beyond it (x in [-3, 6], y in [-3, 7], v in [-3, 3], theta in [-pi, pi]),
nominal controls from a normal of standard deviation ``--u-std`` (seeded). Per dtype, per
filter backend (``"auto"``: the C real-time path for up to 1,024 states per call, the
general path beyond; ``"torch"``: the general path) and per number of states in one call
(``--chunks``), the script prints the false failures, the states whose status differs from
the general path's on the whole batch, the largest difference of the controls from it on
states both solve, and which paths answered.

    python scripts/qp_filter_sweep.py [--states 10000] [--seed 0] [--chunks 1,16,1024,all]
"""

from __future__ import annotations

import argparse
import math
import os

import torch

from torchcbf.qp import Status
from torchcbf.scenarios.unicycle_mppi_cbf import mppi_cbf


def draw_states(count: int, u_std: float, seed: int, dtype: torch.dtype):
    """``(x [count, 4], u_nom [count, 2])`` drawn as the module docstring says."""
    g = torch.Generator().manual_seed(seed)
    lo = torch.tensor([-3.0, -3.0, -3.0, -math.pi], dtype=torch.float64)
    hi = torch.tensor([6.0, 7.0, 3.0, math.pi], dtype=torch.float64)
    x = lo + (hi - lo) * torch.rand(count, 4, generator=g, dtype=torch.float64)
    u = u_std * torch.randn(count, 2, generator=g, dtype=torch.float64)
    return x.to(dtype), u.to(dtype)


def _run(filt, x: torch.Tensor, u: torch.Tensor, backend: str, chunk: int):
    """The filter's ``(qp_status, u, paths)`` on chunks of ``chunk`` states with ``backend``."""
    filt.backend = backend
    outs = [filt(x[i : i + chunk], u[i : i + chunk]) for i in range(0, x.shape[0], chunk)]
    paths = sorted({o.path for o in outs})
    return torch.cat([o.qp_status for o in outs]), torch.cat([o.u for o in outs]), paths


def sweep(dtype: torch.dtype, count: int, u_std: float, seed: int, chunks: list[int]) -> None:
    filt = mppi_cbf(num_seeds=1, num_samples=16, horizon=4, dtype=dtype).safety_filter
    x, u = draw_states(count, u_std, seed, dtype)
    name = str(dtype).removeprefix("torch.")
    runs = {}
    with torch.no_grad():
        for backend in ("auto", "torch"):
            for chunk in chunks:
                runs[backend, chunk] = _run(filt, x, u, backend, chunk)
    ref_status, ref_u, _ = runs["torch", count]
    for (backend, chunk), (status, uu, paths) in runs.items():
        fail = status != int(Status.SOLVED)
        both = ~fail & (ref_status == int(Status.SOLVED))
        du = float((uu - ref_u).abs().amax(-1)[both].max()) if bool(both.any()) else 0.0
        print(
            f"{name:8s} backend={backend:5s} chunks of {chunk:6d}: false failures "
            f"{int(fail.sum()):4d} / {count}; status differs from the general path's whole "
            f"batch on {int((status != ref_status).sum())}; max |u - u_ref| {du:.1e}; "
            f"paths {', '.join(paths)}"
        )
        bad = fail.nonzero().squeeze(-1)[:5].tolist()
        if bad:
            print(f"    first failing states {bad}, statuses {status[bad].tolist()}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--states", type=int, default=10_000, help="number of random states")
    parser.add_argument("--seed", type=int, default=0, help="seed of the states")
    parser.add_argument("--u-std", type=float, default=20.0, help="std of the nominal controls")
    parser.add_argument(
        "--chunks", default="1,16,1024,all", help="states per call, comma-separated (all: one call)"
    )
    args = parser.parse_args()
    torch.set_num_threads(1)
    print(f"# threads 1, load average {os.getloadavg()[0]:.2f}")
    chunks = [args.states if c == "all" else int(c) for c in args.chunks.split(",")]
    if args.states not in chunks:
        chunks.append(args.states)
    for dtype in (torch.float32, torch.float64):
        sweep(dtype, args.states, args.u_std, args.seed, chunks)


if __name__ == "__main__":
    main()
