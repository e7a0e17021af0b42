"""Benchmark the CBF-QP safety filter: one state, a batch, peers in the same run.

Scene: a 2-D single integrator with box limits, 8 ball obstacles (one batched ``Ball``),
B states outside the obstacles, a nominal control pushing through them.

One state, user code: a superellipse and a smooth polygon (user-written barriers) on a
user-written unicycle, the filter as built (autograd Lie terms) and with ``compile=True``,
against cbfpy's and CBFJAX's jitted filters of the same functions; first calls are timed
apart.

One state (the real-time path, float64): ``SafetyFilter`` on one state under
``torch.no_grad()`` and with grad enabled, the stochastic filter of scenario B (5 rectified
ellipses, Hessian traces) on one and two states and with grad enabled, scenario B's
risk-aware filter (the smooth minimum of the rectified radius form of the ellipses and a
multiple of the radius form, per ellipse) on one state, and the jitted filters of
cbfpy and CBFJAX (both JAX, qpax) on the same scene; the control agreement with each is
printed too (cbfpy solves to 1e-6; CBFJAX calls qpax at its default tolerance 1e-5 and
iteration cap, which it does not expose: the interior point can stop about 1e-3 inside an
active control bound, and on a few of 4,096 states short of the optimum, which the count of
rows over 1e-2 shows; the proxsuite line checks torchcbf's controls on the same QPs).

CBFJAX's filter is its minimum-intervention, input-constrained QP filter
(``MinIntervInputConstQPSafeControl``, hard CBF rows, the box as rows): the barriers are
its ``Barrier`` objects (the 8 balls as one vector-valued barrier), the model its
``SingleIntegratorDynamics`` or a ``CustomDynamics`` of the user's ``f`` and ``g``. It
takes the nominal control as a function of the state; here that function returns the
controller state it is handed, so each call takes ``(x, u_nom)`` as the other filters do.

Batched, reported per state:

- ``filter (batched)``: ``SafetyFilter.forward`` on the whole batch (Lie terms + QP).
- cbfpy's and CBFJAX's ``jit(vmap)`` of their one-state filters on the same batch (float64).
- ``filter (loop, B=1)``: the same filter called state by state on a subset, extrapolated.
- ``qp only``: our ``solve_qp`` on the filter's QP data (captured from the batched call).
- ``proxsuite qp only``: ``proxsuite.torch.qplayer.QPFunction`` on the same hard QPs
  (``u`` only, CBF rows and the box as ``l <= G u <= u``), and ``proxsuite whole``: Lie
  terms computed once with the barrier's closed forms, rows built, then QPFunction.

Run: ``python scripts/bench_filters.py`` (``--quick`` for a short run, ``--one-state`` for
the real-time one-state lines alone). Figures taken while
the machine is loaded (the load average is printed) vary between runs; compare ratios
within one run.
"""

from __future__ import annotations

import argparse
import math
import os
import statistics
import time
from collections.abc import Callable

import numpy as np
import torch

import torchcbf.qp as qp_module
from torchcbf._argtypes import non_negative_int, positive_int, torch_device
from torchcbf.barriers import Ball, Barrier
from torchcbf.dynamics import ControlAffine, SingleIntegrator
from torchcbf.filters import SafetyFilter


def _sync() -> None:
    if torch.cuda.is_available():
        torch.cuda.synchronize()


def _timeit(fn: Callable[[], object], repeat: int) -> float:
    fn()  # warm up
    _sync()
    best = math.inf
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        _sync()
        best = min(best, time.perf_counter() - t0)
    return best


def _percentiles(fn: Callable[[], object], calls: int) -> tuple[float, float]:
    """(10th percentile, median) of the wall time of ``fn`` in microseconds."""
    for _ in range(10):
        fn()
    times = []
    for _ in range(calls):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    times.sort()
    return 1e6 * times[len(times) // 10], 1e6 * statistics.median(times)


def _cbfpy():
    """``(jax, jax.numpy, cbfpy.CBF, cbfpy.CBFConfig)`` in float64 on the CPU, or ``None``
    when cbfpy is not installed."""
    os.environ.setdefault("JAX_ENABLE_X64", "True")
    os.environ.setdefault("JAX_PLATFORMS", "cpu")
    try:
        import jax
        import jax.numpy as jnp
        from cbfpy import CBF, CBFConfig
    except ImportError:
        return None
    jax.config.update("jax_enable_x64", True)
    return jax, jnp, CBF, CBFConfig


def _cbfpy_filter(centers: np.ndarray, radii: np.ndarray, u_lim: float):
    """cbfpy's filter on the same scene: ``(single, batched)``, both jitted (float64), or
    ``None`` when cbfpy is not installed."""
    found = _cbfpy()
    if found is None:
        return None
    jax, jnp, CBF, CBFConfig = found
    c = jnp.asarray(centers)
    r2 = jnp.asarray(radii) ** 2

    class Config(CBFConfig):
        def __init__(self) -> None:
            lim = u_lim * np.ones(2)
            super().__init__(n=2, m=2, u_min=-lim, u_max=lim, relax_qp=True, solver_tol=1e-6)

        def f(self, z, *args, **kwargs):
            return jnp.zeros(2)

        def g(self, z, *args, **kwargs):
            return jnp.eye(2)

        def h_1(self, z, *args, **kwargs):
            d = z[None, :] - c
            return (d * d).sum(-1) - r2

    cbf = CBF.from_config(Config())
    return jax.jit(cbf.safety_filter), jax.jit(jax.vmap(cbf.safety_filter))


def _cbfjax():
    """``(jax, jax.numpy, cbfjax)`` in float64 on the CPU, or ``None`` when CBFJAX is not
    installed."""
    os.environ.setdefault("JAX_ENABLE_X64", "True")
    os.environ.setdefault("JAX_PLATFORMS", "cpu")
    try:
        import cbfjax
        import jax
        import jax.numpy as jnp
    except ImportError:
        return None
    jax.config.update("jax_enable_x64", True)
    return jax, jnp, cbfjax


def _cbfjax_qp_filter(cbfjax, dynamics, barriers: list, m: int, u_lim: float, multidim: bool):
    """CBFJAX's min-intervention, input-constrained QP filter on ``barriers`` (functions of
    one state), alpha = identity, the nominal control handed in as the controller state."""
    from cbfjax.barriers import Barrier, MultiBarriers
    from cbfjax.safe_controls import MinIntervInputConstQPSafeControl

    parts = [Barrier(barrier_func=h, dynamics=dynamics) for h in barriers]
    return MinIntervInputConstQPSafeControl(
        action_dim=m,
        barrier=MultiBarriers(barriers=parts, dynamics=dynamics, multidim=multidim),
        dynamics=dynamics,
        # a stateful nominal control: (x, state) -> (u_nom, state), with u_nom the state
        desired_control=lambda z, u_nom: (u_nom, u_nom),
        desired_control_init_state=lambda: None,
        control_low=[-u_lim] * m,
        control_high=[u_lim] * m,
    )


def _cbfjax_filter(centers: np.ndarray, radii: np.ndarray, u_lim: float):
    """CBFJAX's filter on the same scene: ``(single, batched)``, both jitted (float64), or
    ``None`` when CBFJAX is not installed."""
    found = _cbfjax()
    if found is None:
        return None
    jax, jnp, cbfjax = found
    c = jnp.asarray(centers)
    r2 = jnp.asarray(radii) ** 2

    def balls(z):
        d = z[None, :] - c
        return (d * d).sum(-1) - r2

    dyn = cbfjax.dynamics.SingleIntegratorDynamics(dim=2)
    filt = _cbfjax_qp_filter(cbfjax, dyn, [balls], 2, u_lim, multidim=True)

    def one(z, u_nom):
        return filt.optimal_control(z, u_nom)[0]

    return jax.jit(one), jax.jit(jax.vmap(one))


def _single_state(calls: int) -> None:
    """The one-state lines: torchcbf's real-time path against cbfpy's jitted filter."""
    dtype = torch.float64
    quarter = max(1, calls // 4)  # calls of the slower scenario B lines
    dyn, ball, filt, x, u_nom = _scene(64, 8, dtype, seed=0)
    x1, u1 = x[0], u_nom[0]
    rows = []
    with torch.no_grad():
        rows.append(("torchcbf vanilla, no_grad", _percentiles(lambda: filt(x1, u1), calls)))
    rows.append(("torchcbf vanilla, grad enabled", _percentiles(lambda: filt(x1, u1), calls)))
    from torchcbf.scenarios.unicycle_mppi_cbf import mppi_cbf

    sc = mppi_cbf(method="scbf", num_seeds=2, dtype=torch.float64)
    xs = sc.x0 + torch.tensor([0.3, 0.2, 0.5, 0.0], dtype=torch.float64)
    us = torch.tensor([[1.0, 0.5], [0.5, -0.2]], dtype=torch.float64)
    with torch.no_grad():
        rows.append(
            (
                "torchcbf stochastic (scenario B), 1 state",
                _percentiles(lambda: sc.safety_filter(xs[0], us[0]), quarter),
                False,
            )
        )
        rows.append(
            (
                "torchcbf stochastic (scenario B), 2 states",
                _percentiles(lambda: sc.safety_filter(xs, us), quarter),
                False,
            )
        )
    rows.append(
        (
            "torchcbf stochastic (scenario B), grad enabled",
            _percentiles(lambda: sc.safety_filter(xs[0], us[0]), quarter),
            False,
        )
    )
    risk = mppi_cbf(method="mppi_rascbf", num_seeds=1, dtype=torch.float64).safety_filter
    with torch.no_grad():
        rows.append(
            (
                "torchcbf risk-aware (scenario B), 1 state",
                _percentiles(lambda: risk(xs[0], us[0]), quarter),
                False,
            )
        )
    with torch.no_grad():
        ref = filt(x[:64], u_nom[:64])
    solved = (ref.status == 0).numpy()
    bases, firsts, agree = {}, {}, {}
    xj, uj = x1.numpy(), u1.numpy()
    for peer_name, label, build in (
        ("cbfpy", "cbfpy (jit, qpax), 1 state", _cbfpy_filter),
        ("CBFJAX", "CBFJAX (jit, qpax), 1 state", _cbfjax_filter),
    ):
        peer = build(ball.center.numpy(), ball.radius.numpy(), 2.0)
        if peer is None:
            continue
        single, _ = peer
        t0 = time.perf_counter()
        np.asarray(single(xj, uj))
        firsts[peer_name] = time.perf_counter() - t0
        timed = _percentiles(lambda f=single: np.asarray(f(xj, uj)), calls)
        rows.append((label, timed))
        bases[peer_name] = timed[1]
        u_peer = np.stack(
            [
                np.asarray(single(a, b))
                for a, b in zip(x[:64].numpy(), u_nom[:64].numpy(), strict=True)
            ]
        )
        agree[peer_name] = float(np.abs(ref.u.numpy() - u_peer)[solved].max())
    print("\n# one state, float64 (p10 / median us per call)")
    _print_rows(rows, bases)
    if bases:
        print(
            "(scenario B rows carry no ratio: the peers are timed on the vanilla rows' scene, "
            "8 balls and a single integrator, not on scenario B's unicycle and 5 ellipses)"
        )
    _print_peers(firsts, agree, f"over the {int(solved.sum())} SOLVED rows of 64 states")


def _print_rows(rows: list, bases: dict[str, float]) -> None:
    """``name p10 median`` and, per installed peer, the median as a multiple of its own: only
    on rows that solve the peers' problem (a row ``(name, times, False)`` solves another one
    and gets no ratio)."""
    for name, (p10, med), *same in rows:
        ratios = ""
        if not same or same[0]:
            ratios = "".join(f"{med / base:8.2f}x {peer}" for peer, base in bases.items())
        print(f"{name:45s} {p10:9.1f} {med:9.1f}  {ratios}".rstrip())


def _print_peers(firsts: dict[str, float], agree: dict[str, float], where: str) -> None:
    """First (compiling) calls and control agreement of the installed peers; a line for
    each peer that is not installed."""
    for peer in ("cbfpy", "CBFJAX"):
        if peer not in firsts:
            print(f"{peer} not installed: its line is skipped")
        else:
            print(
                f"{peer} first (compiling) call: {firsts[peer]:.2f} s; "
                f"max |u_torchcbf - u_{peer}| {where}: {agree[peer]:.1e}"
            )


class _SuperEllipse(Barrier):
    """A user-written barrier: ``sum |(p - c) / a|^4 - 1``."""

    def __init__(self, center: list[float], axes: list[float]) -> None:
        super().__init__()
        self.register_buffer("center", torch.tensor(center, dtype=torch.float64))
        self.register_buffer("axes", torch.tensor(axes, dtype=torch.float64))

    def forward(self, x: torch.Tensor, t: object = None) -> torch.Tensor:
        d = (x[..., :2] - self.center) / self.axes
        return (d.abs() ** 4).sum(-1) - 1.0


class _SmoothPolygon(Barrier):
    """A user-written barrier: outside a box, ``temp * logsumexp((N p - o) / temp)``."""

    def __init__(self, normals: list[list[float]], offsets: list[float], temp: float) -> None:
        super().__init__()
        self.register_buffer("normals", torch.tensor(normals, dtype=torch.float64))
        self.register_buffer("offsets", torch.tensor(offsets, dtype=torch.float64))
        self.temp = temp

    def forward(self, x: torch.Tensor, t: object = None) -> torch.Tensor:
        s = x[..., :2] @ self.normals.mT - self.offsets
        return self.temp * torch.logsumexp(s / self.temp, -1)


class _Rover(ControlAffine):
    """A user-written model: unicycle kinematics, ``x = (p, theta)``, ``u = (v, omega)``."""

    def __init__(self) -> None:
        super().__init__(3, 2, u_min=-2.0, u_max=2.0)

    def f(self, x: torch.Tensor) -> torch.Tensor:
        return torch.zeros_like(x)

    def g(self, x: torch.Tensor) -> torch.Tensor:
        th = x[..., 2]
        z, o = torch.zeros_like(th), torch.ones_like(th)
        rows = [torch.stack([th.cos(), z], -1), torch.stack([th.sin(), z], -1)]
        return torch.stack([*rows, torch.stack([z, o], -1)], -2)


#: the user scene: a superellipse at (2, 0.5) and the box [2.5, 4.5] x [-1, 1] (4 faces)
_SUPER = ([2.0, 0.5], [0.6, 0.4])
_FACES = ([[1.0, 0.0], [-1.0, 0.0], [0.0, 1.0], [0.0, -1.0]], [4.5, -2.5, 1.0, 1.0], 0.1)


def _cbfpy_user_filter():
    """cbfpy's jitted filter on the user scene (float64), or ``None`` without cbfpy."""
    found = _cbfpy()
    if found is None:
        return None
    jax, jnp, CBF, CBFConfig = found
    c, a = (jnp.asarray(v) for v in _SUPER)
    normals, offsets, temp = jnp.asarray(_FACES[0]), jnp.asarray(_FACES[1]), _FACES[2]

    class Config(CBFConfig):
        def __init__(self) -> None:
            lim = 2.0 * np.ones(2)
            super().__init__(n=3, m=2, u_min=-lim, u_max=lim, relax_qp=True, solver_tol=1e-6)

        def f(self, z, *args, **kwargs):
            return jnp.zeros(3)

        def g(self, z, *args, **kwargs):
            th = z[2]
            return jnp.array([[jnp.cos(th), 0.0], [jnp.sin(th), 0.0], [0.0, 1.0]])

        def h_1(self, z, *args, **kwargs):
            d = (z[:2] - c) / a
            poly = temp * jax.scipy.special.logsumexp((normals @ z[:2] - offsets) / temp)
            return jnp.array([(jnp.abs(d) ** 4).sum() - 1.0, poly])

    return jax.jit(CBF.from_config(Config()).safety_filter)


def _cbfjax_user_filter():
    """CBFJAX's jitted filter on the user scene (float64), or ``None`` without CBFJAX."""
    found = _cbfjax()
    if found is None:
        return None
    jax, jnp, cbfjax = found
    c, a = (jnp.asarray(v) for v in _SUPER)
    normals, offsets, temp = jnp.asarray(_FACES[0]), jnp.asarray(_FACES[1]), _FACES[2]

    def g(z):
        th = z[2]
        return jnp.array([[jnp.cos(th), 0.0], [jnp.sin(th), 0.0], [0.0, 1.0]])

    def superellipse(z):
        d = (z[:2] - c) / a
        return (jnp.abs(d) ** 4).sum() - 1.0

    def polygon(z):
        return temp * jax.scipy.special.logsumexp((normals @ z[:2] - offsets) / temp)

    dyn = cbfjax.dynamics.CustomDynamics(
        state_dim=3, action_dim=2, f_func=lambda z: jnp.zeros(3), g_func=g
    )
    filt = _cbfjax_qp_filter(cbfjax, dyn, [superellipse, polygon], 2, 2.0, multidim=False)
    return jax.jit(lambda z, u_nom: filt.optimal_control(z, u_nom)[0])


def _user_state(calls: int) -> None:
    """One state through a filter of user-written barriers on a user-written model: the
    default (autograd Lie terms), ``compile=True``, and cbfpy's and CBFJAX's jitted filters."""
    barriers = [_SuperEllipse(*_SUPER), _SmoothPolygon(*_FACES)]
    x = torch.tensor([0.0, 0.3, 0.1], dtype=torch.float64)
    u = torch.tensor([1.0, 0.0], dtype=torch.float64)
    rows, firsts = [], {}
    for name, kw in (("default", {}), ("compile=True", {"compile": True})):
        filt = SafetyFilter(_Rover(), barriers, **kw)
        with torch.no_grad():
            t0 = time.perf_counter()
            out = filt(x, u)
            firsts[name] = time.perf_counter() - t0
            timed = _percentiles(lambda f=filt: f(x, u), calls)
            rows.append((f"torchcbf {name} ({out.path})", timed))
            x2 = x + 0.01  # new values: no recompile
            t0 = time.perf_counter()
            filt(x2, u)
            firsts[f"{name}, new state"] = time.perf_counter() - t0
    # a few states of the scene (outside both sets), each with the nominal control u
    n_check = 8
    xs = torch.stack(
        [
            torch.linspace(0.0, 1.2, n_check, dtype=torch.float64),
            torch.linspace(0.3, -0.3, n_check, dtype=torch.float64),
            torch.linspace(0.1, -0.5, n_check, dtype=torch.float64),
        ],
        -1,
    )
    us = u.expand(n_check, 2)
    with torch.no_grad():
        ref = SafetyFilter(_Rover(), barriers)(xs, us)
    solved = (ref.status == 0).numpy()
    bases, peer_firsts, agree = {}, {}, {}
    xj, uj = x.numpy(), u.numpy()
    for peer_name, build in (("cbfpy", _cbfpy_user_filter), ("CBFJAX", _cbfjax_user_filter)):
        peer = build()
        if peer is None:
            continue
        t0 = time.perf_counter()
        np.asarray(peer(xj, uj))
        peer_firsts[peer_name] = time.perf_counter() - t0
        timed = _percentiles(lambda f=peer: np.asarray(f(xj, uj)), calls)
        rows.append((f"{peer_name} (jit, qpax)", timed))
        bases[peer_name] = timed[1]
        u_peer = np.stack(
            [np.asarray(peer(a, b)) for a, b in zip(xs.numpy(), us.numpy(), strict=True)]
        )
        agree[peer_name] = float(np.abs(ref.u.numpy() - u_peer)[solved].max())
    print("\n# one state, user-written barriers and model, float64 (p10 / median us per call)")
    _print_rows(rows, bases)
    print("torchcbf first calls (s): " + ", ".join(f"{k} {v:.3f}" for k, v in firsts.items()))
    _print_peers(
        peer_firsts, agree, f"over the {int(solved.sum())} SOLVED rows of {n_check} states"
    )


def _scene(batch: int, k: int, dtype: torch.dtype, seed: int):
    gen = torch.Generator().manual_seed(seed)
    centers = 8 * torch.rand(k, 2, generator=gen, dtype=dtype) - 4
    radii = 0.3 + 0.4 * torch.rand(k, generator=gen, dtype=dtype)
    ball = Ball(centers, radii)
    dyn = SingleIntegrator(2, u_min=-2.0, u_max=2.0)
    filt = SafetyFilter(dyn, ball, alpha=1.0).to(dtype)
    xs = []
    while sum(len(v) for v in xs) < batch:
        cand = 10 * torch.rand(4 * batch, 2, generator=gen, dtype=dtype) - 5
        keep = (ball(cand) > 0.05).all(-1)
        xs.append(cand[keep])
    x = torch.cat(xs)[:batch]
    goal = torch.zeros(2, dtype=dtype)
    u_nom = (2.0 * (goal - x)).clamp(-2.0, 2.0)
    return dyn, ball, filt, x, u_nom


def _capture_qp(filt: SafetyFilter, x: torch.Tensor, u_nom: torch.Tensor) -> tuple | None:
    """The arguments of the filter's :func:`torchcbf.qp.solve_qp` call on ``x`` (None when
    the filter answered without one, through its C path)."""
    captured: list = []
    original = qp_module.solve_qp

    def spy(*args, **kwargs):
        captured.append((args, kwargs))
        return original(*args, **kwargs)

    qp_module.solve_qp = spy
    try:
        filt(x, u_nom)
    finally:
        qp_module.solve_qp = original
    return captured[0] if captured else None


def _proxsuite_whole(ball: Ball, dyn: SingleIntegrator, x: torch.Tensor, u_nom: torch.Tensor):
    from proxsuite.torch.qplayer import QPFunction

    terms = ball.lie(x, dyn, method="analytic", hessian=False)
    B, m = u_nom.shape
    b = terms.lfh + terms.dhdt + terms.h  # alpha = 1: lgh u >= -b
    eye = torch.eye(m, dtype=x.dtype).expand(B, m, m)
    G = torch.cat([terms.lgh, eye], 1)
    inf = torch.full_like(b, 1e20)
    lo = torch.cat([-b, dyn.u_min.to(x).expand(B, m)], 1)
    hi = torch.cat([inf, dyn.u_max.to(x).expand(B, m)], 1)
    Q = torch.eye(m, dtype=x.dtype).expand(B, m, m)
    A = torch.empty(B, 0, m, dtype=x.dtype)
    bb = torch.empty(B, 0, dtype=x.dtype)
    return QPFunction(eps=1e-9, maxIter=1000)(Q, -u_nom, A, bb, G, lo, hi)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--batch", type=positive_int, default=4096)
    parser.add_argument("--barriers", type=positive_int, default=8)
    parser.add_argument("--loop-subset", type=positive_int, default=64)
    parser.add_argument("--repeat", type=positive_int, default=3)
    parser.add_argument("--dtype", choices=["float64", "float32"], default="float64")
    parser.add_argument(
        "--threads", type=non_negative_int, default=0, help="torch threads (0: leave)"
    )
    parser.add_argument("--quick", action="store_true", help="batch 512, subset 16, repeat 1")
    parser.add_argument(
        "--device", default="cpu", type=torch_device, help="device of torchcbf (proxsuite: CPU)"
    )
    parser.add_argument("--calls", type=positive_int, default=2000, help="calls per one-state line")
    parser.add_argument(
        "--one-state", action="store_true", help="the real-time one-state lines alone"
    )
    args = parser.parse_args()
    if args.quick:
        args.batch, args.loop_subset, args.repeat = 512, 16, 1
    if args.threads:
        torch.set_num_threads(args.threads)
    load = os.getloadavg()
    print(
        f"# torch {torch.__version__}, threads {torch.get_num_threads()}, load average "
        f"{load[0]:.2f} {load[1]:.2f} {load[2]:.2f} on {os.cpu_count()} cores"
    )
    _single_state(args.calls if not args.quick else 300)
    if args.one_state:
        return
    _user_state(args.calls if not args.quick else 300)
    dtype = getattr(torch, args.dtype)
    dyn, ball, filt, x_cpu, u_nom_cpu = _scene(args.batch, args.barriers, dtype, seed=0)
    device = torch.device(args.device)
    dyn, ball, filt = dyn.to(device), ball.to(device), filt.to(device)
    x, u_nom = x_cpu.to(device), u_nom_cpu.to(device)
    B = args.batch
    rows: list[tuple[str, float]] = []
    with torch.no_grad():
        out = filt(x, u_nom)
        t_batch = _timeit(lambda: filt(x, u_nom), args.repeat)
        rows.append(("filter (batched)", t_batch / B))
        sub = min(args.loop_subset, B)

        def loop() -> None:
            for i in range(sub):
                filt(x[i : i + 1], u_nom[i : i + 1])

        rows.append(("filter (loop, B=1, extrapolated)", _timeit(loop, 1) / sub))
        hard = SafetyFilter(dyn, ball, alpha=1.0, slack="none").to(device=device, dtype=dtype)
        rows.append(
            (
                "filter (batched, elastic=False: hard QP only)",
                _timeit(lambda: hard(x, u_nom), args.repeat) / B,
            )
        )
        # the default filter may answer through its C path, without a solve_qp call: the QP
        # of the general path (backend="torch") is the one timed alone
        general = SafetyFilter(dyn, ball, alpha=1.0, backend="torch").to(device=device, dtype=dtype)
        captured = _capture_qp(filt, x, u_nom) or _capture_qp(general, x, u_nom)
        if captured is None:
            print("qp only: the filter made no solve_qp call on either path; line skipped")
        else:
            qargs, qkw = captured
            rows.append(
                (
                    "qp only (torchcbf solve_qp, general path's QP)",
                    _timeit(lambda: qp_module.solve_qp(*qargs, **qkw), args.repeat) / B,
                )
            )
        try:
            import proxsuite.torch.qplayer  # noqa: F401

            have_prox = True
        except ImportError:
            have_prox = False
        if have_prox:
            from proxsuite.torch.qplayer import QPFunction

            x, u_nom = x_cpu, u_nom_cpu
            dyn, ball = dyn.cpu(), ball.cpu()
            terms = ball.lie(x, dyn, method="analytic", hessian=False)
            b = terms.lfh + terms.dhdt + terms.h
            m = 2
            eye = torch.eye(m, dtype=dtype).expand(B, m, m)
            G = torch.cat([terms.lgh, eye], 1)
            lo = torch.cat([-b, dyn.u_min.to(x).expand(B, m)], 1)
            hi = torch.cat([torch.full_like(b, 1e20), dyn.u_max.to(x).expand(B, m)], 1)
            Q = eye
            A = torch.empty(B, 0, m, dtype=dtype)
            bb = torch.empty(B, 0, dtype=dtype)
            fn = QPFunction(eps=1e-9, maxIter=1000)
            z = fn(Q, -u_nom, A, bb, G, lo, hi)[0]
            t_qp = _timeit(lambda: fn(Q, -u_nom, A, bb, G, lo, hi), args.repeat)
            rows.append(("proxsuite QPFunction, qp only", t_qp / B))
            t_whole = _timeit(lambda: _proxsuite_whole(ball, dyn, x, u_nom), args.repeat)
            rows.append(("proxsuite whole (lie + rows + QPFunction)", t_whole / B))
            solved = out.status == 0
            diff = (z - out.u.cpu())[solved.cpu()].abs().amax().item()
        else:
            diff = float("nan")
    print(
        f"B={B} states, k={args.barriers} barriers, m=2, {args.dtype}, "
        f"torch threads={torch.get_num_threads()}; statuses: "
        f"{torch.bincount(out.status, minlength=4).tolist()} "
        "(SOLVED, RELAXED, FALLBACK, NON_FINITE)"
    )
    base = rows[0][1]
    print(f"{'method':45s} {'us/state':>10s} {'x batched filter':>17s}")
    for name, t in rows:
        print(f"{name:45s} {1e6 * t:10.2f} {t / base:17.2f}")
    solved_rows = (out.status == 0).cpu().numpy()
    xj, uj = x_cpu.numpy(), u_nom_cpu.numpy()
    for peer_name, build in (("cbfpy", _cbfpy_filter), ("CBFJAX", _cbfjax_filter)):
        peer = build(ball.center.cpu().numpy(), ball.radius.cpu().numpy(), 2.0)
        if peer is None or dtype != torch.float64:
            print(f"{peer_name} not installed (or not float64): its batched line is skipped")
            continue
        _, batched = peer
        t0 = time.perf_counter()
        u_peer = np.asarray(batched(xj, uj))
        first = time.perf_counter() - t0
        t_peer = _timeit(lambda f=batched: np.asarray(f(xj, uj)), args.repeat)
        label = f"{peer_name} jit(vmap) (JAX, qpax)"
        print(
            f"{label:45s} {1e6 * t_peer / B:10.2f} {t_peer / B / base:17.2f}  "
            f"(torchcbf batched is {t_peer / B / base:.1f}x faster)"
        )
        gap = np.abs(out.u.cpu().numpy() - u_peer)[solved_rows].max(-1)
        print(
            f"{peer_name} jit(vmap) first (compiling) call: {first:.2f} s; |u_torchcbf - "
            f"u_{peer_name}| over the {int(solved_rows.sum())} SOLVED rows: max "
            f"{gap.max():.1e}, median {np.median(gap):.1e}, {int((gap > 1e-2).sum())} over 1e-2"
        )
    if not have_prox:
        print("proxsuite not installed: its rows are skipped")
    else:
        print(f"max |u_proxsuite - u_filter| over SOLVED rows: {diff:.2e}")


if __name__ == "__main__":
    main()
