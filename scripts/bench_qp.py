"""Benchmark torchcbf.qp.solve_qp against peer differentiable QP layers.

torchcbf's torch backend (``method="auto"``) runs the dual active-set method, on the CPU
through its C kernel when that was built (the headline lines also time the same method in
torch, with the kernel switched off), and enumeration or the interior point method where the
dual method does not apply; the headline lines also time ``method="enumerate"`` and
``"ipm"``.
Times forward and forward+backward per QP on random feasible dense QPs
(``min 1/2 x'Qx + p'x  s.t.  Gx <= h``, Q positive definite, some constraints active) for
torchcbf (torch and proxsuite backends), proxsuite's torch ``QPFunction``, qpth's
``QPFunction`` and cvxpylayers (small batches; skipped if not installed). Also prints the
headline lines: fwd+bwd at B=4096, n=4, m=8; forward latency at B=1 (n=2, m=6 and
n=8, m=12, under ``torch.no_grad()``) against proxsuite's dense solver called directly in the
same run; equality-constrained QPs (one QP against proxsuite's dense solver, batches
against qpax, ``--equality-only`` for just these); one rotated cond-1e9 row in a batch
and the time of B=4, n=8 against m up to 4,096 (``--scaling-only``); and forward
throughput at B=1,000,000, n=2, m=6 on --device. Figures taken on a
loaded machine vary: the load average is printed, compare ratios within one run.

Every line that times a peer also checks its answers against torchcbf's (after the timing):
the rows whose ``x`` agree to 1e-5, and for the others whose answer is the worse one (the
objective higher by more than 1e-6, or a constraint violated by more than 1e-6), with
torchcbf's KKT residual computed here from its ``x`` and multipliers; the tolerance settings
of every solver are printed at the top. The equality-constrained and hard-row/growing-m lines
run on the CPU whatever ``--device`` says.

    python scripts/bench_qp.py --quick
    python scripts/bench_qp.py --device cuda
"""

from __future__ import annotations

import argparse
import os
import time
from collections.abc import Callable
from unittest import mock

import numpy as np
import torch

from torchcbf._argtypes import positive_int, torch_device
from torchcbf.qp import Status, _dual_native, solve_qp


def make_problems(B: int, n: int, m: int, device: str, seed: int = 0):
    """Random feasible QPs: the origin is strictly feasible, the unconstrained optimum is not."""
    g = torch.Generator().manual_seed(seed)
    f64 = torch.float64
    L = torch.randn(B, n, n, generator=g, dtype=f64)
    Q = L @ L.mT / n + 0.5 * torch.eye(n, dtype=f64)
    p = 3.0 * torch.randn(B, n, generator=g, dtype=f64)
    G = torch.randn(B, m, n, generator=g, dtype=f64)
    h = 0.2 + torch.rand(B, m, generator=g, dtype=f64)
    return [t.to(device) for t in (Q, p, G, h)]


def timeit(fn: Callable[[], None], min_time: float = 0.3, max_reps: int = 50) -> float:
    """Median wall time of ``fn`` (one warm-up call, then repeats until ``min_time``)."""
    fn()
    times = []
    start = time.perf_counter()
    while len(times) < max_reps and (time.perf_counter() - start < min_time or len(times) < 3):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return float(np.median(times))


def dual_path(device: str) -> str:
    """Which implementation ``method="auto"`` runs the dual active-set method with."""
    if device == "cpu" and _dual_native.available():
        return "dual active set, C kernel"
    return "dual active set, torch"


def _sync(device: str) -> None:
    if device.startswith("cuda"):
        torch.cuda.synchronize()


#: a peer's row agrees with torchcbf's when ``max_i |x_peer,i - x_torchcbf,i|`` is at most this
AGREE_X = 1e-5
#: where they disagree, an answer is the worse one when its objective is higher by more than
#: this (times ``1 + |objective|``) or it violates a constraint by more than this
MARGIN = 1e-6
#: torchcbf's answer counts as a KKT point when its KKT residual (stationarity, primal and
#: dual feasibility, complementarity, over ``1 +`` the row's largest datum), computed here
#: from its ``x`` and multipliers, is at most this
KKT_TOL = 1e-8
#: the tolerance settings each peer runs with in this script, printed beside its answers
SETTINGS = {
    "torchcbf[proxsuite]": "torchcbf's proxsuite backend, eps=1e-7",
    "proxsuite.QPFunction": "eps=1e-9, maxIter=1000",
    "proxsuite dense": "eps_abs=1e-9, eps_rel=0",
    "qpth": "eps=1e-12, maxIter=20, its defaults",
    "qpax": "solver_tol=1e-5, max_iter=30, its defaults",
    "cvxpylayers": "diffcp/SCS defaults",
}


def _tolerances_line() -> str:
    """The tolerance settings of torchcbf and of each peer, as this script runs them."""
    peers = "; ".join(f"{name} {value}" for name, value in SETTINGS.items())
    return (
        f"# tolerances: torchcbf solve_qp eps=1e-7 (its float64 default); {peers}. Answers "
        f"agree when max |x_peer - x_torchcbf| <= {AGREE_X:.0e}"
    )


def _rows(t: object, dims: int, Bp: int | None) -> torch.Tensor:
    """The first ``Bp`` problems of ``t`` (a tensor or array; ``dims`` trailing dimensions
    per problem), float64 on the CPU, with one batch dimension."""
    t = t if isinstance(t, torch.Tensor) else torch.as_tensor(np.array(t))
    t = t.detach().cpu().double()
    return t.reshape(-1, *t.shape[t.dim() - dims :])[:Bp]


def _mv(M: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    return (M @ v.unsqueeze(-1))[..., 0]


def agreement(
    peer: str, sol, x_peer: object, data: tuple, *, short: bool = False, peer_status=None
) -> str:
    """How a peer's answers ``x_peer`` (the first ``Bp`` problems of the batch) compare with
    torchcbf's ``sol`` on the QPs ``data = (Q, p, G, h[, A, b])``: the rows that agree to
    :data:`AGREE_X`; for the others, whose answer is the worse one (objective higher by more
    than :data:`MARGIN`, or a constraint violated by more than it), and on how many torchcbf's
    answer is a KKT point to :data:`KKT_TOL` by this script's own check. Rows torchcbf does
    not report ``SOLVED`` are left out (and counted); ``peer_status`` (a peer with statuses:
    torchcbf's proxsuite backend) counts the disagreeing rows the peer itself does not call
    ``SOLVED``. Vectorised, run after the timing."""
    n = data[1].shape[-1]
    xp = _rows(x_peer, 1, None)
    Bp = xp.shape[0]
    Q, p, G, h = (_rows(t, d, Bp) for t, d in zip(data[:4], (2, 1, 2, 1), strict=True))
    eq = len(data) > 4 and data[4].shape[-2] > 0
    A, b = (_rows(data[4], 2, Bp), _rows(data[5], 1, Bp)) if eq else (None, None)
    x, lam = _rows(sol.x, 1, Bp), _rows(sol.lam, 1, Bp)
    solved = sol.status.detach().cpu().reshape(-1)[:Bp] == Status.SOLVED
    assert xp.shape == x.shape == (Bp, n), (xp.shape, x.shape)
    dx = (xp - x).abs().amax(-1)
    dx = torch.where(torch.isnan(dx), torch.inf, dx)
    close, apart = (dx <= AGREE_X) & solved, (dx > AGREE_X) & solved

    def violation(z: torch.Tensor) -> torch.Tensor:
        v = (_mv(G, z) - h).clamp_min(0).amax(-1)
        if eq:
            v = torch.maximum(v, (_mv(A, z) - b).abs().amax(-1))
        return torch.where(torch.isfinite(z).all(-1), v, torch.inf)

    f_o = 0.5 * (x * _mv(Q, x)).sum(-1) + (p * x).sum(-1)
    f_p = 0.5 * (xp * _mv(Q, xp)).sum(-1) + (p * xp).sum(-1)
    f_p = torch.where(torch.isnan(f_p), torch.inf, f_p)
    bad_o, bad_p = violation(x) > MARGIN, violation(xp) > MARGIN
    tol = MARGIN * (1 + f_o.abs())
    peer_infeasible = apart & bad_p & ~bad_o
    peer_higher = apart & ~bad_p & ~bad_o & (f_p > f_o + tol)
    peer_worse = peer_infeasible | peer_higher
    ours_worse = apart & ((bad_o & ~bad_p) | (~bad_p & ~bad_o & (f_o > f_p + tol)))
    even = apart & ~peer_worse & ~ours_worse & ~bad_o & ~bad_p
    both_infeasible = apart & bad_o & bad_p
    # torchcbf's KKT residual from its x and multipliers
    grad = _mv(Q, x) + p + _mv(G.mT, lam)
    slack = _mv(G, x) - h
    scale = torch.stack([Q.abs().amax((-2, -1)), p.abs().amax(-1), G.abs().amax((-2, -1)),
                         h.abs().amax(-1)], -1).amax(-1)  # fmt: skip
    extra = [slack.clamp_min(0).amax(-1), (-lam).clamp_min(0).amax(-1)]
    extra.append((lam * slack).abs().amax(-1))
    if eq:
        grad = grad + _mv(A.mT, _rows(sol.nu, 1, Bp))
        extra.append((_mv(A, x) - b).abs().amax(-1))
        scale = torch.maximum(scale, torch.maximum(A.abs().amax((-2, -1)), b.abs().amax(-1)))
    res = torch.stack([grad.abs().amax(-1), *extra], -1).amax(-1) / (1 + scale)
    kkt = apart & (res <= KKT_TOL)
    k, n_ok = int(close.sum()), int(solved.sum())
    pw, ow, ev, kk = (int(t.sum()) for t in (peer_worse, ours_worse, even, kkt))
    bi = int(both_infeasible.sum())
    p_hi, p_inf = int(peer_higher.sum()), int(peer_infeasible.sum())
    flagged = ""
    if peer_status is not None:
        unsolved = peer_status.detach().cpu().reshape(-1)[:Bp] != Status.SOLVED
        flagged = f", {int((apart & unsolved).sum())} of them not SOLVED by {peer}'s status"
    if short:
        text = f"{k}/{n_ok}"
        if n_ok > k:
            text += f" ({pw} {peer} worse, {ow} torchcbf worse, {ev} even, {bi} both off{flagged})"
    else:
        worst = float(dx[solved].max()) if n_ok else float("nan")
        text = (
            f"answers ({peer}: {SETTINGS.get(peer, 'defaults')}): {k}/{n_ok} agree with "
            f"torchcbf's to {AGREE_X:.0e} (max |dx| {worst:.1e})"
        )
        if n_ok > k:
            text += (
                f"; of the other {n_ok - k}: {p_hi} where {peer}'s objective is worse by > "
                f"{MARGIN:.0e}, {p_inf} where {peer}'s x violates a row by > {MARGIN:.0e}, "
                f"{ow} where torchcbf's answer is the worse, {ev} where both are feasible and "
                f"their objectives within {MARGIN:.0e}, {bi} where both violate a row; "
                "torchcbf's answer a KKT point "
                f"(residual <= {KKT_TOL:.0e}) on {kk} of the {n_ok - k}{flagged}"
            )
    if n_ok < Bp:
        text += f" ({Bp - n_ok} rows torchcbf did not solve left out)"
    return text


def run_torchcbf(backend: str, device: str, method: str = "auto"):
    def fwd(Q, p, G, h):
        with torch.no_grad():
            sol = solve_qp(Q, p, G, h, backend=backend, method=method)
        _sync(device)
        return sol

    def fwdbwd(Q, p, G, h):
        p = p.detach().requires_grad_(True)
        h = h.detach().requires_grad_(True)
        sol = solve_qp(Q, p, G, h, backend=backend, method=method)
        sol.x.sum().backward()
        _sync(device)

    return fwd, fwdbwd


def run_proxsuite_qpfunction():
    from proxsuite.torch.qplayer import QPFunction

    def call(Q, p, G, h, grad):
        B, n = p.shape
        A = torch.empty(B, 0, n, dtype=p.dtype)
        b = torch.empty(B, 0, dtype=p.dtype)
        lower = torch.full_like(h, -1e20)
        if grad:
            p = p.detach().requires_grad_(True)
        x = QPFunction(maxIter=1000)(Q, p, A, b, G, lower, h)[0]
        if grad:
            x.sum().backward()
        return x.detach()

    return (lambda *a: call(*a, False)), (lambda *a: call(*a, True))


def run_qpth():
    from qpth.qp import QPFunction

    def call(Q, p, G, h, grad):
        e = torch.empty(0, dtype=p.dtype)
        if grad:
            p = p.detach().requires_grad_(True)
            x = QPFunction(verbose=-1)(Q, p, G, h, e, e)
            x.sum().backward()
        else:
            with torch.no_grad():
                x = QPFunction(verbose=-1)(Q, p, G, h, e, e)
        return x.detach()

    return (lambda *a: call(*a, False)), (lambda *a: call(*a, True))


def run_cvxpylayers(n: int, m: int):
    import cvxpy as cp
    from cvxpylayers.torch import CvxpyLayer

    x = cp.Variable(n)
    Lp = cp.Parameter((n, n))
    pp = cp.Parameter(n)
    Gp = cp.Parameter((m, n))
    hp = cp.Parameter(m)
    prob = cp.Problem(cp.Minimize(0.5 * cp.sum_squares(Lp.T @ x) + pp @ x), [Gp @ x <= hp])
    layer = CvxpyLayer(prob, parameters=[Lp, pp, Gp, hp], variables=[x])

    def call(Q, p, G, h, grad):
        L = torch.linalg.cholesky(Q)
        if grad:
            p = p.detach().requires_grad_(True)
        (sol,) = layer(L, p, G, h)
        if grad:
            sol.sum().backward()
        return sol.detach()

    return (lambda *a: call(*a, False)), (lambda *a: call(*a, True))


def proxsuite_dense_direct(Q, p, G, h) -> Callable[[], np.ndarray]:
    """Forward of one QP through proxsuite's dense solver, no torch in the loop (returns
    its ``x``)."""
    from proxsuite import proxqp

    Qn, pn, Gn, hn = (t[0].cpu().numpy() for t in (Q, p, G, h))
    n, m = pn.shape[0], hn.shape[0]
    lower = np.full(m, -1e20)

    def solve() -> np.ndarray:
        qp = proxqp.dense.QP(n, 0, m)
        qp.settings.eps_abs = 1e-9
        qp.init(Qn, pn, None, None, Gn, lower, hn)
        qp.solve()
        return qp.results.x

    return solve


def make_equality_problems(B: int, n: int, m: int, k: int, seed: int = 0):
    """Random feasible QPs with ``k`` equality rows: ``Q`` positive definite, the point
    ``x0`` satisfies ``A x0 = b`` and every inequality with slack, some made tight."""
    g = torch.Generator().manual_seed(seed)
    f64 = torch.float64
    L = torch.randn(B, n, n, generator=g, dtype=f64)
    Q = L @ L.mT / n + 0.5 * torch.eye(n, dtype=f64)
    p = 3.0 * torch.randn(B, n, generator=g, dtype=f64)
    x0 = torch.randn(B, n, generator=g, dtype=f64)
    G = torch.randn(B, m, n, generator=g, dtype=f64)
    h = (G @ x0.unsqueeze(-1)).squeeze(-1) + 0.2 * torch.rand(B, m, generator=g, dtype=f64)
    A = torch.randn(B, k, n, generator=g, dtype=f64)
    b = (A @ x0.unsqueeze(-1)).squeeze(-1)
    return Q, p, G, h, A, b


def proxsuite_equality_direct(Q, p, G, h, A, b) -> Callable[[], np.ndarray]:
    """Forward of one QP with equalities through proxsuite's dense solver (eps 1e-9; returns
    its ``x``)."""
    from proxsuite import proxqp

    Qn, pn, Gn, hn, An, bn = (t.numpy() for t in (Q, p, G, h, A, b))
    n, m, k = pn.shape[0], hn.shape[0], bn.shape[0]
    lower = np.full(m, -1e20)

    def solve() -> np.ndarray:
        qp = proxqp.dense.QP(n, k, m)
        qp.settings.eps_abs = 1e-9
        qp.settings.verbose = False
        qp.init(Qn, pn, An, bn, Gn, lower, hn)
        qp.solve()
        return qp.results.x

    return solve


def qpax_batch(Q, p, G, h, A, b) -> Callable[[], object] | None:
    """qpax (jax, float64, ``jit(vmap(solve_qp))``, its default tolerances) on the batch
    (returns its ``x``); ``None`` if not installed."""
    try:
        import jax
        import jax.numpy as jnp
        import qpax
    except ImportError:
        return None
    jax.config.update("jax_enable_x64", True)
    data = [jnp.asarray(t.numpy()) for t in (Q, p, A, b, G, h)]
    solve = jax.jit(jax.vmap(lambda *a: qpax.solve_qp(*a)[0]))

    def run() -> object:
        return solve(*data).block_until_ready()

    return run


def equality_lines() -> None:
    """One QP with equalities against proxsuite's dense solver, and batches against qpax,
    each with the agreement of the answers; on the CPU whatever ``--device`` says."""
    print(
        "\n# equality-constrained QPs (forward, float64, under torch.no_grad(); CPU lines, "
        "whatever --device says)"
    )
    for n, m, k in ((10, 8, 3), (50, 40, 10)):
        one = tuple(t[0] for t in make_equality_problems(1, n, m, k, seed=n))
        with torch.no_grad():
            sol = solve_qp(*one)
            t1 = timeit(lambda one=one: solve_qp(*one), min_time=1.0, max_reps=2000)
        ours = (
            f"one QP n={n} m={m} k={k}: torchcbf (auto, path {sol.path}, status "
            f"{Status(int(sol.status)).name}) {t1 * 1e6:.1f} us"
        )
        try:
            direct = proxsuite_equality_direct(*one)
        except ImportError:
            print(f"{ours}; proxsuite not installed: skipped")
            continue
        t_px = timeit(direct, min_time=1.0, max_reps=2000)
        print(
            f"{ours}; proxsuite dense (construct + solve) {t_px * 1e6:.1f} us; "
            f"torchcbf/proxsuite {t1 / t_px:.2f}"
        )
        print("  " + agreement("proxsuite dense", sol, direct(), one))
    for B, n, m, k in ((64, 10, 8, 3), (1000, 10, 8, 3), (1000, 4, 6, 2)):
        data = make_equality_problems(B, n, m, k, seed=B + n)
        with torch.no_grad():
            sol = solve_qp(*data)
            t_ours = timeit(lambda data=data: solve_qp(*data), min_time=1.0, max_reps=20) / B
        solved = int((sol.status == Status.SOLVED).sum())
        line = (
            f"B={B} n={n} m={m} k={k}: torchcbf (auto, path {sol.path}) "
            f"{t_ours * 1e6:.2f} us/QP (solved {solved}/{B})"
        )
        run = qpax_batch(*data)
        if run is None:
            print(line + "; qpax not installed")
            continue
        t_qpax = timeit(run, min_time=1.0, max_reps=20) / B
        line += f"; qpax (jit+vmap) {t_qpax * 1e6:.2f} us/QP -> torchcbf/qpax {t_ours / t_qpax:.2f}"
        print(line)
        print("  " + agreement("qpax", sol, run(), data))


def hard_row_and_scaling_lines() -> None:
    """A batch with one rotated cond-1e9 row against the same batch without it, and the
    time of one batch (B=4, n=8) as the number of rows m grows, ``method="ipm"`` and auto;
    on the CPU whatever ``--device`` says."""
    print(
        "\n# one hard row in a batch; time against m (forward, float64, no_grad; CPU lines, "
        "whatever --device says)"
    )
    for B in (64, 1024):
        Q, p, G, h = make_problems(B, 4, 8, "cpu", seed=3)
        hard = Q.clone()
        rot, _ = torch.linalg.qr(torch.randn(4, 4, generator=torch.Generator().manual_seed(1),
                                             dtype=torch.float64))  # fmt: skip
        hard[B // 2] = rot @ torch.diag(torch.tensor([1.0, 1e-3, 1e-6, 1e-9])).double() @ rot.T
        with torch.no_grad():
            easy, hardest = (Q, p, G, h), (hard, p, G, h)
            t_easy = timeit(lambda d=easy: solve_qp(*d), min_time=1.0)
            t_hard = timeit(lambda d=hardest: solve_qp(*d), min_time=1.0)
            st = solve_qp(hard, p, G, h).status
        print(
            f"B={B} n=4 m=8: {t_easy * 1e3:.2f} ms; with one rotated cond-1e9 row "
            f"{t_hard * 1e3:.2f} ms ({t_hard / t_easy:.2f}x), solved "
            f"{int((st == Status.SOLVED).sum())}/{B}"
        )
    for method in ("ipm", "auto"):
        parts = []
        for m in (256, 1024, 2048, 4096):
            Q, p, G, h = make_problems(4, 8, m, "cpu", seed=m)
            with torch.no_grad():
                d, mt = (Q, p, G, h), method
                t = timeit(lambda d=d, mt=mt: solve_qp(*d, method=mt), min_time=0.5, max_reps=3)
                st = solve_qp(Q, p, G, h, method=method).status
            parts.append(f"m={m}: {t * 1e3:.0f} ms ({int((st == Status.SOLVED).sum())}/4)")
        print(f"B=4 n=8 method={method!r}: " + ", ".join(parts))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--quick", action="store_true", help="small subset of the grid")
    parser.add_argument(
        "--device", default="cpu", type=torch_device, help="device for torchcbf (peers: CPU)"
    )
    parser.add_argument(
        "--peer-max-batch", type=positive_int, default=1024, help="largest peer batch"
    )
    parser.add_argument("--no-grid", action="store_true", help="only the headline lines")
    parser.add_argument(
        "--goal-peer-batch", type=positive_int, default=4096, help="peer batch of the B=4096 line"
    )
    parser.add_argument(
        "--big", type=positive_int, default=1_000_000, help="batch of the throughput line"
    )
    parser.add_argument(
        "--threads", type=positive_int, default=None, help="torch.set_num_threads (>= 1)"
    )
    parser.add_argument(
        "--equality-only", action="store_true", help="only the equality-constrained lines"
    )
    parser.add_argument(
        "--scaling-only", action="store_true", help="only the hard-row and growing-m lines"
    )
    args = parser.parse_args()
    dev = args.device
    if args.threads is not None:
        torch.set_num_threads(args.threads)
    if args.equality_only or args.scaling_only:
        load = os.getloadavg()
        print(f"# threads {torch.get_num_threads()}, load average {load[0]:.2f}")
        print(_tolerances_line())
        if args.equality_only:
            equality_lines()
        if args.scaling_only:
            hard_row_and_scaling_lines()
        return

    peers: dict[str, Callable | None] = {}
    notes = []
    try:
        import proxsuite.torch.qplayer  # noqa: F401

        peers["proxsuite.QPFunction"] = run_proxsuite_qpfunction
    except ImportError:
        notes.append("proxsuite.torch not installed: it and torchcbf[proxsuite] skipped")
    try:
        import qpth.qp  # noqa: F401

        peers["qpth"] = run_qpth
    except ImportError:
        notes.append("qpth not installed: skipped")
    try:
        import cvxpylayers.torch  # noqa: F401

        peers["cvxpylayers"] = None
    except ImportError:
        notes.append("cvxpylayers not installed: skipped")
    for note in notes:
        print(f"# {note}")
    load = os.getloadavg() if hasattr(os, "getloadavg") else (float("nan"),) * 3
    print(
        f"# torch {torch.__version__}, threads {torch.get_num_threads()}, device {dev}, "
        f"load average {load[0]:.2f} {load[1]:.2f} {load[2]:.2f}"
    )
    print(_tolerances_line())

    # headline lines first: a fresh process, before the grid's peers have churned the heap
    # (the small batched kernels are sensitive to allocator state on a CPU)
    print("\n# headline lines")
    # 1) fwd+bwd at B=4096, n=4, m=8
    B, n, m = 4096, 4, 8
    Q, p, G, h = make_problems(B, n, m, dev, seed=1)
    _, fb = run_torchcbf("torch", dev)
    t_ours = timeit(lambda: fb(Q, p, G, h), min_time=1.0) / B
    sol = solve_qp(Q, p, G, h)
    solved = float((sol.status == Status.SOLVED).float().mean())
    others = []
    if dual_path(dev).endswith("C kernel"):
        with mock.patch.object(_dual_native, "applies", lambda q: False):
            t_m = timeit(lambda: fb(Q, p, G, h), min_time=1.0) / B
        others.append(f"the same in torch (kernel off): {t_m * 1e6:.2f} us/QP")
    for method in ("enumerate", "ipm"):
        _, fb_m = run_torchcbf("torch", dev, method=method)
        t_m = timeit(lambda fb_m=fb_m: fb_m(Q, p, G, h), min_time=1.0) / B
        others.append(f"method={method!r}: {t_m * 1e6:.2f} us/QP")
    print(
        f"B=4096 n=4 m=8 fwd+bwd torchcbf[torch] (auto: {dual_path(dev)}): "
        f"{t_ours * 1e6:.2f} us/QP (solved {solved:.3f}); " + "; ".join(others)
    )
    Qc, pc, Gc, hc = (t.cpu() for t in (Q, p, G, h))
    for name, maker in peers.items():
        if maker is None:
            continue
        Bp = min(B, args.goal_peer_batch)
        f2, fb2 = maker()
        sl = (Qc[:Bp], pc[:Bp], Gc[:Bp], hc[:Bp])
        t_peer = timeit(lambda fb2=fb2, sl=sl: fb2(*sl), min_time=0.5, max_reps=3) / Bp
        print(
            f"  {name} (B={Bp}): {t_peer * 1e6:.2f} us/QP -> torchcbf is "
            f"{t_peer / t_ours:.1f}x faster"
        )
        print("    " + agreement(name, sol, f2(*sl), sl))

    # hard rows in a batch: about half the rows exactly tight at a known feasible point, and
    # the same construction with every row's slack positive (the batch without them)
    g = torch.Generator().manual_seed(11)
    L = torch.randn(B, n, n, generator=g, dtype=torch.float64)
    Qt = L @ L.mT / n + 0.1 * torch.eye(n, dtype=torch.float64)
    pt = 3 * torch.randn(B, n, generator=g, dtype=torch.float64)
    Gt = torch.randn(B, m, n, generator=g, dtype=torch.float64)
    x0 = torch.randn(B, n, generator=g, dtype=torch.float64)
    slack = torch.rand(B, m, generator=g, dtype=torch.float64)
    zero = torch.rand(B, m, generator=g, dtype=torch.float64) < 0.5
    at_x0 = (Gt @ x0.unsqueeze(-1)).squeeze(-1)
    tight = [t.to(dev) for t in (Qt, pt, Gt, at_x0 + torch.where(zero, 0.0, slack))]
    loose = [t.to(dev) for t in (Qt, pt, Gt, at_x0 + slack)]
    t_tight = timeit(lambda: fb(*tight), min_time=1.0) / B
    t_loose = timeit(lambda: fb(*loose), min_time=1.0) / B
    st = solve_qp(*tight).status
    print(
        f"B=4096 n=4 m=8 fwd+bwd, half the rows tight at a feasible point: "
        f"{t_tight * 1e6:.2f} us/QP ({t_tight / t_loose:.2f}x the same problems with every "
        f"slack positive, {t_loose * 1e6:.2f} us/QP; {t_tight / t_ours:.2f}x the random "
        f"batch), solved {int((st == Status.SOLVED).sum())}/{B}"
    )

    # a few infeasible rows (two contradicting rows each) in the random batch
    Qi, pi, Gi, hi = make_problems(B, n, m, dev, seed=1)
    Gi, hi = Gi.clone(), hi.clone()
    rows = torch.arange(5, B, B // 4)[:4]
    Gi[rows, 1] = -Gi[rows, 0]
    hi[rows, 1] = -hi[rows, 0] - 1.0
    Gr, hr = make_problems(B, n, m, dev, seed=1)[2:]

    def fwd_synced(*data: torch.Tensor) -> None:
        solve_qp(*data)
        _sync(dev)

    with torch.no_grad():
        t_inf = timeit(lambda: fwd_synced(Qi, pi, Gi, hi), min_time=1.0) / B
        t_rnd = timeit(lambda: fwd_synced(Qi, pi, Gr, hr), min_time=1.0) / B
    st = solve_qp(Qi, pi, Gi, hi).status
    print(
        f"B=4096 n=4 m=8 forward, {len(rows)} infeasible rows: {t_inf * 1e6:.2f} us/QP "
        f"({t_inf / t_rnd:.2f}x the same batch without them), "
        f"PRIMAL_INFEASIBLE {int((st == Status.PRIMAL_INFEASIBLE).sum())}/{len(rows)}"
    )

    # mid-size problems, past the 8 variables of the unrolled kernel copies
    for n2, m2, B2 in ((12, 40, 1024), (25, 100, 1024)):
        Q2, p2, G2, h2 = make_problems(B2, n2, m2, dev, seed=n2)
        mid = (Q2, p2, G2, h2)
        t_mid = timeit(lambda mid=mid: fb(*mid), min_time=1.0, max_reps=5) / B2
        with torch.no_grad():
            sol2 = solve_qp(Q2, p2, G2, h2)
        line = (
            f"B={B2} n={n2} m={m2} fwd+bwd torchcbf[torch]: {t_mid * 1e6:.1f} us/QP "
            f"(solved {int((sol2.status == Status.SOLVED).sum())}/{B2})"
        )
        if "proxsuite.QPFunction" not in peers:
            print(line)
            continue
        f2, fb2 = run_proxsuite_qpfunction()
        mid_cpu = tuple(t.cpu() for t in mid)
        t_peer = timeit(lambda fb2=fb2, m=mid_cpu: fb2(*m), min_time=0.5, max_reps=2) / B2
        print(line + f"; proxsuite.QPFunction: {t_peer * 1e6:.1f} us/QP -> {t_peer / t_mid:.1f}x")
        print("  " + agreement("proxsuite.QPFunction", sol2, f2(*mid_cpu), mid_cpu))

    # the safety filter's shape at scale: 2 controls + 1 slack, 8 barrier rows, box bounds
    Q, p, G, h = make_problems(B, 3, 8, dev, seed=5)
    lb = torch.full((3,), -2.0, dtype=Q.dtype, device=dev)
    ub = torch.full((3,), 2.0, dtype=Q.dtype, device=dev)
    line = []
    for method in ("auto", "ipm"):

        def filt_b(method: str = method) -> None:
            pp = p.detach().requires_grad_(True)
            solve_qp(Q, pp, G, h, lb=lb, ub=ub, method=method).x.sum().backward()
            _sync(dev)

        line.append(f"{method}: {timeit(filt_b, min_time=1.0) / B * 1e6:.2f} us/QP")
    print("B=4096 n=3 m=8 + box fwd+bwd (filter shape): " + ", ".join(line))

    # 2) latency of one QP (no batch dimension), forward under torch.no_grad()
    for n1, m1, seed in ((2, 6, 2), (8, 12, 6)):
        one = tuple(t[0] for t in make_problems(1, n1, m1, "cpu", seed=seed))
        fwd, _ = run_torchcbf("torch", "cpu")
        t1 = timeit(lambda fwd=fwd, one=one: fwd(*one), min_time=1.0, max_reps=2000)
        single = []
        for method in ("enumerate", "ipm"):
            fwd_m, _ = run_torchcbf("torch", "cpu", method=method)
            t_m = timeit(lambda f=fwd_m, one=one: f(*one), min_time=1.0, max_reps=200)
            single.append(f"method={method!r}: {t_m * 1e6:.1f} us")
        line = f"one QP n={n1} m={m1} forward torchcbf[torch] (auto: {dual_path('cpu')}): "
        line += f"{t1 * 1e6:.1f} us; " + "; ".join(single)
        if "proxsuite.QPFunction" not in peers:
            print(line)
            continue
        direct = proxsuite_dense_direct(*(t.unsqueeze(0) for t in one))
        t_direct = timeit(direct, min_time=0.5, max_reps=2000)
        line += (
            f"; proxsuite dense (construct + solve): {t_direct * 1e6:.1f} us; "
            f"torchcbf/proxsuite {t1 / t_direct:.2f}"
        )
        print(line)
        print("  " + agreement("proxsuite dense", fwd(*one), direct(), one))
    # a safety-filter-shaped problem: 2 bounded controls + 1 bounded slack, 8 barrier rows
    Q, p, G, h = make_problems(1, 3, 8, "cpu", seed=4)
    lb = torch.full((3,), -2.0, dtype=Q.dtype)
    ub = torch.full((3,), 2.0, dtype=Q.dtype)

    def filt(method: str) -> None:
        with torch.no_grad():
            solve_qp(Q, p, G, h, lb=lb, ub=ub, method=method)

    line = [f"{m}: {timeit(lambda m=m: filt(m), min_time=0.5, max_reps=200) * 1e3:.3f} ms"
            for m in ("auto", "enumerate", "ipm")]  # fmt: skip
    print("B=1 n=3 m=8 + box forward (filter shape, 431 candidates): " + ", ".join(line))

    equality_lines()
    hard_row_and_scaling_lines()

    # 3) throughput at B=big, n=2, m=6 on --device
    B = args.big
    Q, p, G, h = make_problems(B, 2, 6, dev, seed=3)
    fwd, _ = run_torchcbf("torch", dev)
    tb = timeit(lambda: fwd(Q, p, G, h), min_time=0.5, max_reps=3)
    print(f"B={B} n=2 m=6 forward on {dev}: {tb:.3f} s, {B / tb / 1e6:.2f} M QPs/s ")

    if args.quick:
        grid = [(B, n, m) for B in (1, 64, 1024) for n, m in ((2, 5), (4, 10))]
    else:
        grid = [(B, n, m) for B in (1, 64, 1024, 8192) for n in (2, 4, 8) for m in (1, 5, 10, 20)]

    if not args.no_grid:
        if peers:
            print(
                f"\n# answers: rows whose x agrees with torchcbf[torch]'s to {AGREE_X:.0e}, of the "
                f"rows torchcbf solved; where some do not, on how many the peer's answer is worse "
                f"(objective higher by > {MARGIN:.0e} or a row violated by > {MARGIN:.0e}), "
                "torchcbf's is worse, neither (even), or both violate a row (both off); peers' "
                "settings as on the tolerances line"
            )
        hdr = f"{'B':>6} {'n':>2} {'m':>3} {'solver':<22} {'fwd us/QP':>10} {'fwd+bwd us/QP':>14}"
        print(hdr + f" {'time / torchcbf (fwd+bwd)':>24}  answers")
        for B, n, m in grid:
            Q, p, G, h = make_problems(B, n, m, dev)
            Qc, pc, Gc, hc = (t.cpu() for t in (Q, p, G, h))
            fwd, fb = run_torchcbf("torch", dev)
            data = (Q, p, G, h)
            t_f = timeit(lambda fwd=fwd, data=data: fwd(*data)) / B
            t_fb = timeit(lambda fb=fb, data=data: fb(*data)) / B
            sol = fwd(*data)
            print(
                f"{B:>6} {n:>2} {m:>3} {'torchcbf[torch]':<22} {t_f * 1e6:>10.2f} "
                f"{t_fb * 1e6:>14.2f} {'1.0':>24}"
            )
            rows = []
            if "proxsuite.QPFunction" in peers:  # torchcbf's proxsuite backend needs proxsuite
                rows.append(("torchcbf[proxsuite]", lambda: run_torchcbf("proxsuite", "cpu"), 8192))
            for name, maker in peers.items():
                cap = 64 if name == "cvxpylayers" else args.peer_max_batch
                if name == "cvxpylayers":
                    rows.append((name, lambda n=n, m=m: run_cvxpylayers(n, m), cap))
                else:
                    rows.append((name, maker, cap))
            for name, maker, cap in rows:
                Bp = min(B, cap)
                f2, fb2 = maker()
                sl = (Qc[:Bp], pc[:Bp], Gc[:Bp], hc[:Bp])
                try:
                    pf = timeit(lambda f2=f2, sl=sl: f2(*sl), min_time=0.2, max_reps=5) / Bp
                    pfb = timeit(lambda fb2=fb2, sl=sl: fb2(*sl), min_time=0.2, max_reps=5) / Bp
                    out = f2(*sl)
                    if hasattr(out, "status"):  # torchcbf's proxsuite backend: a QPSolution
                        answers = agreement(
                            name, sol, out.x, sl, short=True, peer_status=out.status
                        )
                    else:
                        answers = agreement(name, sol, out, sl, short=True)
                except Exception as err:  # a peer failing must not stop the benchmark
                    print(f"{B:>6} {n:>2} {m:>3} {name:<22} failed: {type(err).__name__}: {err}")
                    continue
                tag = f" (B={Bp})" if Bp != B else ""
                print(
                    f"{B:>6} {n:>2} {m:>3} {name + tag:<22} {pf * 1e6:>10.2f} "
                    f"{pfb * 1e6:>14.2f} {pfb / t_fb:>24.1f}  {answers}"
                )


if __name__ == "__main__":
    main()
