"""torchcbf's ``solve_qp`` on a folder of Maros-Meszaros-format QPs, judged against Clarabel
and timed against proxsuite's dense solver in the same run.

Reads every ``.mat`` problem of FOLDER in the format of the qpsolvers/maros_meszaros_qpbenchmark
repository (``data/``; see ``torchcbf.qp.maros_meszaros``), keeps the dense subset (at most
1,000 variables and 1,000 constraints; ``--all`` keeps every problem), and solves each one
per call in float64 with ``solve_qp`` (``--method``, default ``auto``). Clarabel at
tolerance 1e-10 gives the reference; an answer is right when SOLVED with its objective within
1e-6 of Clarabel's (relative to ``max(1, |f*|)``) and no constraint violated by more than
1e-6 (relative). Counts: right, wrong (SOLVED but not right), failed (not SOLVED on a problem
Clarabel solves), false certificates (PRIMAL_INFEASIBLE or DUAL_INFEASIBLE there). proxsuite's
dense solver (eps_abs 1e-9) runs in the same run, judged the same way; the geometric mean of
torchcbf's time over proxsuite's is taken on the problems both answer right. Times are the
median of repeated calls (at least one, up to ``--min-time`` seconds per problem), one torch
thread; on a loaded machine they vary, compare the ratio.

    python scripts/maros_meszaros.py FOLDER [--names QAFIRO,HS21] [--method auto]
"""

from __future__ import annotations

import argparse
import math
import os
import time
from collections import Counter

import numpy as np
import torch

from torchcbf.qp import Status, solve_qp
from torchcbf.qp.maros_meszaros import (
    Problem,
    below_reference,
    clarabel_reference,
    dense_subset,
    judge,
    load_problem,
    proxsuite_dense,
)

TOL = 1e-6


def _median_time(fn, min_time: float) -> tuple[float, object]:
    t0 = time.perf_counter()
    out = fn()
    times = [time.perf_counter() - t0]
    start = time.perf_counter()
    while time.perf_counter() - start < min_time and len(times) < 20:
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return float(np.median(times)), out


def _torch_call(prob: Problem, method: str):
    t = {k: torch.from_numpy(getattr(prob, k)) for k in ("P", "q", "G", "h", "A", "b", "lb", "ub")}
    G = t["G"] if prob.G.shape[0] else None
    h = t["h"] if prob.G.shape[0] else None
    A = t["A"] if prob.A.shape[0] else None
    b = t["b"] if prob.A.shape[0] else None

    def call():
        return solve_qp(t["P"], t["q"], G, h, A, b, t["lb"], t["ub"], method=method)

    return call


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("folder", help="folder of .mat problems")
    parser.add_argument("--names", default="", help="comma-separated problem names to run")
    parser.add_argument("--all", action="store_true", help="every problem, not the dense subset")
    parser.add_argument("--method", default="auto", help="solve_qp's method")
    parser.add_argument("--min-time", type=float, default=0.2, help="seconds of repeats")
    args = parser.parse_args()
    torch.set_num_threads(1)
    names = {s for s in args.names.split(",") if s}
    if args.all:
        probs = [
            load_problem(os.path.join(args.folder, f))
            for f in sorted(os.listdir(args.folder))
            if f.endswith(".mat")
        ]
    else:
        probs = dense_subset(args.folder)
    if names:
        probs = [p for p in probs if p.name in names]
    print(f"{len(probs)} problems from {args.folder}; load average {os.getloadavg()[0]:.2f}")
    print(
        f"{'problem':10s} {'n':>4s} {'m':>4s} {'k':>4s}  {'torchcbf':>22s} {'path':>16s} "
        f"{'ms':>9s}  {'proxsuite':>13s} {'ms':>9s}  {'ratio':>6s}"
    )
    counts, peer_counts = Counter(), Counter()
    ratios, ours_total, peer_total = [], 0.0, 0.0
    below = peer_below = 0
    for prob in probs:
        ref = clarabel_reference(prob)
        t_ours, sol = _median_time(_torch_call(prob, args.method), args.min_time)
        status = Status(int(sol.status))
        certificate = status in (Status.PRIMAL_INFEASIBLE, Status.DUAL_INFEASIBLE)
        ours = judge(prob, sol.x.numpy(), status == Status.SOLVED, certificate, ref, tol=TOL)
        t_peer, peer = _median_time(lambda p=prob: proxsuite_dense(p), args.min_time)
        theirs = judge(
            prob,
            peer.x if peer.x is not None else np.zeros(prob.n),
            peer.status == "optimal",
            peer.status in ("infeasible", "unbounded"),
            ref,
            tol=TOL,
        )
        counts[ours] += 1
        peer_counts[theirs] += 1
        ours_total += t_ours
        peer_total += t_peer
        ratio = ""
        if ours == theirs == "right":
            ratios.append(t_ours / t_peer)
            ratio = f"{t_ours / t_peer:6.2f}"
        label = f"{status.name}:{ours}" if ours != "right" else "right"
        if ours == "right" and below_reference(prob, sol.x.numpy(), ref, tol=TOL):
            label, below = "right (below ref)", below + 1
        if theirs == "right" and below_reference(prob, peer.x, ref, tol=TOL):
            theirs, peer_below = "right (below)", peer_below + 1
        print(
            f"{prob.name:10s} {prob.n:4d} {prob.G.shape[0]:4d} {prob.A.shape[0]:4d}  "
            f"{label:>22s} {sol.path:>16s} {t_ours * 1e3:9.2f}  {theirs:>13s} "
            f"{t_peer * 1e3:9.2f}  {ratio:>6s}",
            flush=True,
        )
    total = len(probs)
    print(
        f"\ntorchcbf ({args.method}): right {counts['right']}/{total} "
        f"({100.0 * counts['right'] / max(total, 1):.1f}%), wrong {counts['wrong']}, failed "
        f"{counts['failed']}, false certificates {counts['false_certificate']}, no reference "
        f"{counts['no_reference']}, right below Clarabel's objective {below}; total "
        f"{ours_total:.2f} s"
    )
    print(
        f"proxsuite dense: right {peer_counts['right']}/{total} "
        f"({100.0 * peer_counts['right'] / max(total, 1):.1f}%), wrong {peer_counts['wrong']}, "
        f"failed {peer_counts['failed']}, false certificates "
        f"{peer_counts['false_certificate']}, right below Clarabel's objective {peer_below}; "
        f"total {peer_total:.2f} s"
    )
    if ratios:
        gm = math.exp(sum(math.log(r) for r in ratios) / len(ratios))
        print(
            f"time torchcbf / proxsuite, geometric mean over the {len(ratios)} problems both "
            f"answer right: {gm:.2f}"
        )


if __name__ == "__main__":
    main()
