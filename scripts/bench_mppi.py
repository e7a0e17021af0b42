"""Benchmark: MPPI planning calls, torchcbf vs pytorch-mppi 0.9.1 in the same run.

Problem (scenario B of docs/scenarios.md): AccelUnicycle (x, y, v, theta; a, omega), Euler
rollouts with dt = 0.02, float32; stage cost ``2 |p - goal|^2 + sum_i 2 / max(b_i, 0.01)``
over the five ellipses, terminal ``10 |p - goal|^2``; temperature 0.03; noise covariance
4 I; control-cost weight 0.1 (pytorch-mppi has no separate control-cost weight: its
``lambda_`` = 0.03 plays both roles); no control limits. Every timed call is a full planning
call (sampling, rollouts, costs, weights, update) from x0 = (0, 0, 0, pi/4) with a
warm-started plan.

Lines (each planner runs in its own subprocess, so that memory and thread pools are its own):

- ``batched``: B = 32 environments x K = 2,000 samples, H = 80, the cost written in Python
  as a user would (torchcbf: kernel rollouts + this torch cost), against pytorch-mppi's
  throughput at K = 20,000 on one environment (state-steps per second, B K H / time); the
  same cost under ``compile=True`` (a cold compile cache); and the same batch with the cost
  built from torchcbf's terms (fused).
- ``user``: one environment, K = 20,000, H = 80, the same Python cost: torchcbf's default
  path (kernel rollouts + torch cost), the same with ``layout="sample"`` (each state
  contiguous: slower for this cost, which works on components) and its all-torch path
  (``backend="torch"``).
- ``fused``: one environment, K = 20,000, H = 80, the cost built from torchcbf's cost terms
  (everything in the C kernel).
- ``realtime``: single integrator, K = 1,000, H = 50, goal + ellipse cost (fused) against
  pytorch-mppi with the same cost in Python.
- ``paper``: B = 32, K = 20,000, H = 80, the fused planner of scenario B: time per planning
  call and the projection to the 250 calls of one paper-size run (500 steps, replanning
  every 2).
- ``model``, ``model20k``, ``modelbatch``: the same Python cost on a user-written model
  (:class:`UserUnicycle`: ``f`` and ``g`` only), so everything runs in torch: K = 1,000,
  H = 50; K = 20,000, H = 80; and B = 32 x K = 2,000, H = 80 against pytorch-mppi's
  throughput at K = 20,000; each eager and under ``compile=True`` (one step and the cost).
  The ``step`` lines give torchcbf the model as pytorch-mppi gets it, the Euler step
  :func:`unicycle` (``MPPI(..., step=...)``).
- ``compiled``: one environment, K = 20,000, H = 80, the Python cost under
  ``torch.compile`` (kernel rollouts), twice: in a process with a cold compile cache (the
  first call a user sees on a new machine) and in a second process sharing that cache.

Timing: median of ``--reps`` calls after 2 warm-up calls, with the range; ``first`` is the
first call alone (it compiles, where anything does). Load is flagged
per line: ``LOADED`` when the process got less than 80% of the CPU time its threads could
use (CPU time / (wall time x threads)), ``NOISY`` when the slowest repeat is more than 1.5x
the fastest, ``FAULTS`` when a call took more than 1,000 minor page faults (median): the
allocator handed memory back to the kernel and took it again, which costs a torch cost on
large rollouts up to 2x and varies from call to call (torchcbf raises glibc's thresholds
once, see docs/mppi.md; the peer runs with the defaults). Such figures should be
re-measured. Use ``--threads 1``
(the default) for steady figures on a shared machine: with several intra-op threads on a
loaded machine, every torch op waits for the slowest descheduled thread.

Usage::

    python scripts/bench_mppi.py                       # every line, 1 thread
    python scripts/bench_mppi.py --only fused realtime --reps 9
    python scripts/bench_mppi.py --threads 2 --only compiled
    python scripts/bench_mppi.py --profile             # where the time goes, per path
    python scripts/bench_mppi.py --filtered            # scenario B's filtered closed loops
    python scripts/bench_mppi.py --quick               # a short run: K / 10, 2 calls, no compile

``--quick`` runs every line but ``compiled`` (and no compiled planner of the other lines)
with a tenth of the samples and 2 timed calls (the labels give the sizes run): a
check that every path runs, not figures to quote.

A planner whose process fails gets a ``failed`` row (the tail of its stderr is shown on
stderr); the other planners and lines still run, and the script then exits with status 1.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable

import torch

from torchcbf._argtypes import positive_int, torch_device
from torchcbf.barriers import Ellipse
from torchcbf.dynamics import AccelUnicycle, ControlAffine, SingleIntegrator
from torchcbf.mppi import MPPI, BarrierCost, QuadraticGoal, SumCost

GOAL = (2.0, 4.0)
CENTERS = ((1.0, 2.0), (3.0, 2.0), (2.0, 5.0), (-1.0, 1.0), (0.5, -1.0))
AXES = ((0.5, 1.5), (0.75, 2.0), (2.0, 0.25), (1.0, 0.75), (0.75, 0.5))
DT, TEMPERATURE, GAMMA, SIGMA = 0.02, 0.03, 0.1, 4.0
PAPER_CALLS = 250
#: minor page faults per call above which a figure is flagged
FAULTS_PER_CALL = 1000
LINES = ("batched", "user", "fused", "realtime", "paper", "compiled", "model", "model20k",
         "modelbatch")  # fmt: skip


def user_cost(device: str) -> Callable[[torch.Tensor, torch.Tensor, torch.Tensor], torch.Tensor]:
    """Scenario B's cost written in torch on whole rollouts, as a user would."""
    goal = torch.tensor(GOAL, device=device)
    centers = torch.tensor(CENTERS, device=device)
    axes = torch.tensor(AXES, device=device)

    def cost(states: torch.Tensor, controls: torch.Tensor, t0: torch.Tensor) -> torch.Tensor:
        p = states[..., 1:, :2]
        b = (((p.unsqueeze(-2) - centers) / axes) ** 2).sum(-1) - 1.0
        stage = 2.0 * ((p - goal) ** 2).sum(-1) + (2.0 / b.clamp_min(0.01)).sum(-1)
        terminal = 10.0 * ((states[..., -1, :2] - goal) ** 2).sum(-1)
        return stage.sum(-1) + terminal

    return cost


class UserUnicycle(ControlAffine):
    """AccelUnicycle's dynamics written as a user would: ``f`` and ``g`` only (no closed-form
    ``xdot``, no native description: torch integrates ``f + g u``)."""

    def __init__(self) -> None:
        super().__init__(4, 2)

    def f(self, x: torch.Tensor) -> torch.Tensor:
        v, th = x[..., 2], x[..., 3]
        zero = torch.zeros_like(v)
        return torch.stack([v * torch.cos(th), v * torch.sin(th), zero, zero], -1)

    def g(self, x: torch.Tensor) -> torch.Tensor:
        g = x.new_zeros(*x.shape[:-1], 4, 2)
        g[..., 2, 0] = 1.0
        g[..., 3, 1] = 1.0
        return g


def builtin_cost() -> SumCost:
    """The same cost from torchcbf's terms (fused into the C kernel)."""
    goal = QuadraticGoal(GOAL, weight=2.0, index=(0, 1), terminal_weight=10.0)
    ellipses = Ellipse(torch.tensor(CENTERS), torch.tensor(AXES), index=(0, 1))
    return SumCost(goal, BarrierCost(ellipses, 2.0, 0.01))


def unicycle(x: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
    """The unicycle's Euler step as a pytorch-mppi user writes it: pytorch-mppi's dynamics,
    and torchcbf's ``step`` on the ``:step`` lines."""
    v, th = x[..., 2], x[..., 3]
    xdot = torch.stack([v * torch.cos(th), v * torch.sin(th), u[..., 0], u[..., 1]], -1)
    return x + DT * xdot


def pytorch_mppi(K: int, H: int, nx: int, device: str) -> Callable[[torch.Tensor], object] | None:
    try:
        from pytorch_mppi import MPPI as PMPPI
    except ImportError:
        return None
    goal = torch.tensor(GOAL, device=device)
    centers = torch.tensor(CENTERS, device=device)
    axes = torch.tensor(AXES, device=device)

    def integrator(x: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
        return x + DT * u

    def running_cost(x: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
        p = x[:, :2]
        b = (((p.unsqueeze(1) - centers) / axes) ** 2).sum(-1) - 1.0
        return 2.0 * ((p - goal) ** 2).sum(-1) + (2.0 / b.clamp_min(0.01)).sum(-1)

    def terminal(states: torch.Tensor, actions: torch.Tensor) -> torch.Tensor:
        return 10.0 * ((states[..., -1, :2] - goal) ** 2).sum(-1)

    planner = PMPPI(
        unicycle if nx == 4 else integrator,
        running_cost,
        nx,
        SIGMA * torch.eye(2, device=device),
        num_samples=K,
        horizon=H,
        terminal_state_cost=terminal,
        lambda_=TEMPERATURE,
        device=device,
    )
    return lambda x: planner.command(x)


def torchcbf(
    B: int, K: int, H: int, cost: str, device: str, *, model: str = "accel", **kw: object
) -> Callable[[torch.Tensor], object]:
    dyn = {"accel": AccelUnicycle, "user": UserUnicycle}.get(model, lambda: SingleIntegrator(2))()
    fn = builtin_cost() if cost == "builtin" else user_cost(device)
    planner = MPPI(dyn, fn, H, K, DT, SIGMA, TEMPERATURE, GAMMA, seed=0, **kw).to(device)
    return planner


def x0(B: int, nx: int, device: str) -> torch.Tensor:
    x = torch.tensor([0.0, 0.0, 0.0, math.pi / 4], device=device)[:nx]
    return x if B == 0 else x.repeat(B, 1)


def minor_faults() -> int:
    """Minor page faults of this process so far (0 where the platform does not count them)."""
    try:
        import resource
    except ImportError:  # not on Windows
        return 0
    return resource.getrusage(resource.RUSAGE_SELF).ru_minflt


def timed(step: Callable[[torch.Tensor], object], x: torch.Tensor, reps: int) -> dict:
    if x.is_cuda:  # time the queued GPU work too
        plain = step

        def step(x: torch.Tensor) -> object:
            out = plain(x)
            torch.cuda.synchronize(x.device)
            return out

    t = time.perf_counter()
    step(x)
    first = time.perf_counter() - t
    step(x)
    walls, cpus, faults = [], [], []
    load = os.getloadavg()[0]
    for _ in range(reps):
        f = minor_faults()
        c, t = time.process_time(), time.perf_counter()
        step(x)
        walls.append(time.perf_counter() - t)
        cpus.append(time.process_time() - c)
        faults.append(minor_faults() - f)
    load = max(load, os.getloadavg()[0])
    walls.sort()
    cpus.sort()
    faults.sort()
    return {
        "faults": faults[len(faults) // 2],
        "median": walls[len(walls) // 2],
        "cpu": cpus[len(cpus) // 2],
        "min": walls[0],
        "max": walls[-1],
        "first": first,
        "cpu_share": sum(cpus) / sum(walls) / torch.get_num_threads(),
        "load": load,
    }


QUICK_SCALE = 10  # --quick: samples divided by this
#: lines of the child's stderr shown when a planner fails
STDERR_TAIL = 15


def sizes(name: str, quick: bool = False) -> tuple[int, int, int, int]:
    """``(B, K, H, nx)`` of one planner of one line (``quick``: K / :data:`QUICK_SCALE`)."""
    which, _, who = name.partition(":")
    if which == "batched":
        B, K, H, nx = (1, 20000, 80, 4) if who == "pytorch-mppi" else (32, 2000, 80, 4)
    elif which in ("user", "fused", "compiled"):
        B, K, H, nx = 1, 20000, 80, 4
    elif which == "realtime":
        B, K, H, nx = 1, 1000, 50, 2
    elif which == "model":
        B, K, H, nx = 1, 1000, 50, 4
    elif which == "model20k":
        B, K, H, nx = 1, 20000, 80, 4
    elif which == "modelbatch":
        B, K, H, nx = (1, 20000, 80, 4) if who == "pytorch-mppi" else (32, 2000, 80, 4)
    else:
        B, K, H, nx = 32, 20000, 80, 4
    if quick:
        K = max(K // QUICK_SCALE, 1)
    return B, K, H, nx


def run_one(name: str, reps: int, device: str, quick: bool = False) -> dict:
    """One planner of one line in this process (``quick``: K / :data:`QUICK_SCALE`)."""
    which, _, who = name.partition(":")
    B, K, H, nx = sizes(name, quick)
    if who == "pytorch-mppi":
        step = pytorch_mppi(K, H, nx, device)
        if step is None:
            return {}
        x = x0(0, nx, device)
    else:
        model = "user" if which.startswith("model") else ("accel" if nx == 4 else "single")
        kw: dict[str, object] = {}
        if which == "paper":
            kw["keep_rollouts"] = 512
        if who == "torch":
            kw["backend"] = "torch"
        if who == "sample":
            kw["layout"] = "sample"
        if which == "compiled" or who.endswith("compiled"):
            kw["compile"] = True
        if who.startswith("step"):
            kw["step"] = lambda x, u, j: unicycle(x, u)
        builtin = which in ("fused", "realtime", "paper") or who == "fused"
        cost = "builtin" if builtin else "user"
        step = torchcbf(B, K, H, cost, device, model=model, **kw)
        x = x0(B if which in ("batched", "paper", "modelbatch") else 0, nx, device)
    with torch.no_grad():
        res = timed(step, x, reps)
    res["state_steps"] = B * K * H
    res["path"] = "pytorch-mppi" if who == "pytorch-mppi" else getattr(step, "path", "torch")
    return res


def profile(device: str) -> None:
    """Where the time of one call goes, per path (torch.profiler's top operators, and the
    phases of the fused path)."""
    from torch.profiler import ProfilerActivity
    from torch.profiler import profile as torch_profile

    from torchcbf.mppi import _rollout

    cases = [
        ("all-torch path, user cost, B=1 K=20000 H=80", 1, 20000, "user", "torch", "accel"),
        ("kernel rollout + user cost, B=1 K=20000 H=80", 1, 20000, "user", "auto", "accel"),
        ("fused, B=32 K=20000 H=80", 32, 20000, "builtin", "auto", "accel"),
        ("user model + user cost, B=32 K=2000 H=80", 32, 2000, "user", "auto", "user"),
    ]
    for title, B, K, cost, backend, model in cases:
        planner = torchcbf(B, K, 80, cost, device, model=model, backend=backend, keep_rollouts=512)
        x = x0(B if B > 1 else 0, 4, device)
        with torch.no_grad():
            planner(x)
            phases: dict[str, float] = {}
            original = _rollout.run

            def timed_run(*args: object, _run=original, _phases=phases, **kw: object) -> None:
                t = time.perf_counter()
                _run(*args, **kw)
                if kw.get("cost") is not None:
                    label = "kernel: noise + rollout + cost"
                elif kw.get("wsum") is not None:
                    label = "kernel: update (noise of weighted samples)"
                elif kw.get("pairs") is not None:
                    label = "kernel: re-roll best + kept"
                else:
                    label = "kernel: noise + rollout into buffers"
                _phases[label] = _phases.get(label, 0.0) + time.perf_counter() - t

            _rollout.run = timed_run
            try:
                with torch_profile(activities=[ProfilerActivity.CPU]) as prof:
                    t = time.perf_counter()
                    planner(x)
                    total = time.perf_counter() - t
            finally:
                _rollout.run = original
        print(f"\n== {title}: {total:.4f} s (path {planner.path})")
        for label, s in phases.items():
            print(f"   {label:<45} {s:8.4f} s")
        print(prof.key_averages().table(sort_by="self_cpu_time_total", row_limit=12))
    noise_draws(device)


def noise_draws(device: str, reps: int = 5) -> None:
    """The torch path's noise of B = 32 x K = 2,000 x H = 80 x m = 2 (component-major):
    the kernel's counter-based normals against ``normal_`` from one generator per
    environment (what the torch path drew before, and still draws off the CPU)."""
    from torchcbf.mppi import _rollout

    B, K, H, m = 32, 2000, 80, 2
    buf = torch.empty(B, m, H, K, device=device)
    gens = [torch.Generator(device=device).manual_seed(b) for b in range(B)]

    def torch_normal() -> None:
        for b, gen in enumerate(gens):
            buf[b].normal_(generator=gen)

    lines = [("normal_, one generator per environment", torch_normal)]
    if device == "cpu" and _rollout.available():
        keys = _rollout.draw_keys(gens, buf.device)
        eps = buf.permute(0, 3, 2, 1)
        lines.insert(0, ("kernel counter-based normals", lambda: _rollout.normals(keys, eps)))
    print(f"\n== noise of B={B} x K={K} x H={H} x m={m} ({B * K * H * m / 1e6:.2f} M normals)")
    for label, draw in lines:
        draw()
        t = time.perf_counter()
        for _ in range(reps):
            draw()
        if device != "cpu":
            torch.cuda.synchronize()
        print(f"   {label:<45} {(time.perf_counter() - t) / reps * 1e3:8.1f} ms")


def fmt(res: dict) -> str:
    flags = []
    if res["cpu_share"] < 0.8:
        flags.append("LOADED")
    if res["max"] > 1.5 * res["min"]:
        flags.append("NOISY")
    if res["faults"] > FAULTS_PER_CALL:
        flags.append("FAULTS")
    rate = res["state_steps"] / res["median"] / 1e6
    return (
        f"{res['median']:9.4f} [{res['min']:.4f}-{res['max']:.4f}] {res['cpu']:8.4f} {rate:7.1f} "
        f"{res['first']:7.2f} {res['cpu_share']:5.2f} {res['load']:5.1f} {res['faults']:7d}  "
        f"{' '.join(flags):<12}"
    )


class _TimedFilter:
    """A safety filter that counts its calls and their wall time."""

    def __init__(self, inner: Callable[..., object]) -> None:
        self.inner, self.calls, self.seconds = inner, 0, 0.0

    def __call__(self, x: torch.Tensor, u: torch.Tensor, t: object) -> object:
        start = time.perf_counter()
        out = self.inner(x, u, t)
        self.seconds += time.perf_counter() - start
        self.calls += 1
        return out


def filtered(num_samples: int, steps: int) -> None:
    """Scenario B's filtered methods in closed loop (32 seeds): the scenario's build time
    (the risk-aware filter's noise bound included), filter calls per control step, time per
    filter call and per control step (planner, filter, plant)."""
    from torchcbf.mppi import ShieldMPPI
    from torchcbf.scenarios.unicycle_mppi_cbf import mppi_cbf
    from torchcbf.sim import simulate

    print(f"scenario B closed loop, 32 seeds, K = {num_samples}, {steps} steps, one thread")
    print(f"{'method':<30}{'build s':>9}{'calls/step':>12}{'filter ms':>11}{'step ms':>9}")
    load = os.getloadavg()[0]
    for label, method, in_loop in (
        ("mppi_scbf", "mppi_scbf", None),
        ("mppi_rascbf", "mppi_rascbf", None),
        ("shield_mppi, shield filters", "shield_mppi", False),
        ("shield_mppi, in_loop=True", "shield_mppi", True),
    ):
        start = time.perf_counter()
        sc = mppi_cbf(method, num_seeds=32, num_samples=num_samples)
        build = time.perf_counter() - start
        timed_filter = _TimedFilter(sc.safety_filter)
        planner, loop_filter = sc.planner, timed_filter
        if in_loop is not None:
            planner = ShieldMPPI(sc.planner.planner, timed_filter, in_loop=in_loop)
            loop_filter = planner.loop_filter if in_loop else timed_filter
        start = time.perf_counter()
        with torch.no_grad():
            simulate(sc.dynamics, sc.x0, steps=steps, dt=sc.dt, planner=planner,
                     safety_filter=loop_filter, integrator=sc.integrator,
                     planner_every=sc.planner_every, progress=False)  # fmt: skip
        loop = time.perf_counter() - start
        calls = timed_filter.calls / steps
        per_call = 1e3 * timed_filter.seconds / max(timed_filter.calls, 1)
        print(f"{label:<30}{build:>9.2f}{calls:>12.2f}{per_call:>11.3f}{1e3 * loop / steps:>9.2f}")
    # the risk-aware filter's noise bound over scenario B's operating grid (its build cost)
    from torchcbf.barriers import Transformed, rectify
    from torchcbf.dynamics import AccelUnicycle
    from torchcbf.filters import noise_bound
    from torchcbf.scenarios.unicycle_mppi_cbf import SIGMA, obstacles, operating_states

    plant = AccelUnicycle(sigma=SIGMA).double()
    radius = Transformed(obstacles(), "radius").double()
    barrier = rectify(radius, plant, form="exponential", gains=[1.0])
    grid = operating_states()
    for method in ("autograd", "analytic"):
        start = time.perf_counter()
        noise_bound(barrier, plant, grid, method=method)
        seconds = time.perf_counter() - start
        print(f"noise_bound over {grid.shape[0]} states, {method:<9}{seconds:>7.2f} s")
    load = max(load, os.getloadavg()[0])
    if load > 1.0:
        print(f"LOADED: load average {load:.1f} during the run; compare rows, not absolutes")


def _child_result(out: subprocess.CompletedProcess) -> dict | None:
    """The JSON result a ``--one`` child printed last, or ``None`` if it failed (non-zero
    exit, or no JSON object on its last line)."""
    if out.returncode != 0:
        return None
    lines = out.stdout.strip().splitlines()
    try:
        res = json.loads(lines[-1]) if lines else None
    except json.JSONDecodeError:
        return None
    return res if isinstance(res, dict) else None


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--threads", type=positive_int, default=1, help="torch threads (>= 1)")
    parser.add_argument("--reps", type=positive_int, default=5, help="timed calls per planner")
    parser.add_argument("--device", default="cpu", type=torch_device)
    parser.add_argument("--only", nargs="+", choices=LINES, help="lines to run")
    parser.add_argument(
        "--profile", action="store_true", help="profile one call per path, and the noise draws"
    )
    parser.add_argument(
        "--quick",
        action="store_true",
        help=f"every line but compiled, K / {QUICK_SCALE}, 2 timed calls (a check, not figures)",
    )
    parser.add_argument(
        "--filtered",
        action="store_true",
        help="scenario B's filtered methods in closed loop (K = 1,000, 100 steps)",
    )
    parser.add_argument("--one", help=argparse.SUPPRESS)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    if args.quick:
        args.reps = min(args.reps, 2)
    if args.one:
        print(json.dumps(run_one(args.one, args.reps, args.device, args.quick)))
        return
    if args.profile:
        profile(args.device)
        return
    if args.filtered:
        filtered(100 if args.quick else 1000, 20 if args.quick else 100)
        return
    lines = list(args.only or (line for line in LINES if not (args.quick and line == "compiled")))
    if args.quick:
        print(f"--quick: K / {QUICK_SCALE} in every line, {args.reps} timed calls, no compile")
    plan = {
        "batched": [
            ("batched:pytorch-mppi", "pytorch-mppi K={K} (B=1)"),
            ("batched:auto", "torchcbf B={B} x K={K}"),
            ("batched:compiled", "torchcbf B={B} x K={K} comp."),
            ("batched:fused", "torchcbf B={B} x K={K} terms"),
        ],
        "user": [
            ("user:pytorch-mppi", "pytorch-mppi"),
            ("user:auto", "torchcbf default"),
            ("user:sample", "torchcbf layout=sample"),
            ("user:torch", "torchcbf all-torch"),
        ],
        "fused": [("fused:pytorch-mppi", "pytorch-mppi"), ("fused:auto", "torchcbf fused")],
        "realtime": [
            ("realtime:pytorch-mppi", "pytorch-mppi"),
            ("realtime:auto", "torchcbf fused"),
        ],
        "paper": [("paper:auto", "torchcbf fused B={B}")],
        "model": [
            ("model:pytorch-mppi", "pytorch-mppi"),
            ("model:auto", "torchcbf user model"),
            ("model:compiled", "torchcbf user model comp."),
            ("model:step", "torchcbf user step"),
            ("model:stepcompiled", "torchcbf user step comp."),
        ],
        "model20k": [
            ("model20k:pytorch-mppi", "pytorch-mppi"),
            ("model20k:auto", "torchcbf user model"),
            ("model20k:compiled", "torchcbf user model comp."),
            ("model20k:step", "torchcbf user step"),
            ("model20k:stepcompiled", "torchcbf user step comp."),
        ],
        "modelbatch": [
            ("modelbatch:pytorch-mppi", "pytorch-mppi K={K} (B=1)"),
            ("modelbatch:auto", "torchcbf B={B} x K={K}"),
            ("modelbatch:compiled", "torchcbf B={B} x K={K} comp."),
            ("modelbatch:step", "torchcbf B={B} x K={K} step"),
            ("modelbatch:stepcompiled", "torchcbf B={B} x K={K} step comp."),
        ],
        "compiled": [
            ("user:pytorch-mppi", "pytorch-mppi"),
            ("compiled:auto", "torchcbf compiled, cold"),
            ("compiled:auto", "torchcbf compiled, warm"),
        ],
    }
    print(
        f"torch {torch.__version__}, {args.threads} thread(s), float32, {args.device}, "
        f"{os.cpu_count()} CPUs, load {os.getloadavg()[0]:.1f}"
    )
    print(
        "s/call: median [range] of the timed calls (wall); cpu s: median process CPU time per "
        "call (the steadier figure on a loaded machine); M/s: million state-steps per second "
        "(B K H / median wall); first: the first call; cpu: CPU time / (wall x threads); "
        "load: 1-min load average; faults: minor page faults per call (median); ratio: wall "
        "(CPU time)"
    )
    head = f"{'line':<10} {'planner':<34} {'path':<12} {'s/call':>9} {'[range]':<15}"
    print(
        head + f" {'cpu s':>8} {'M/s':>7} {'first s':>7} {'cpu':>5} {'load':>5} {'faults':>7}  "
        f"{'flags':<12} ratio"
    )
    failed: list[str] = []
    for line in lines:
        ref: dict | None = None
        with tempfile.TemporaryDirectory(prefix="bench-mppi-inductor-") as cache:  # starts cold
            for name, label in plan[line]:
                if args.quick and name.endswith("compiled"):
                    continue  # --quick compiles nothing
                B, K, _, _ = sizes(name, args.quick)
                label = label.format(B=B, K=K)  # the sizes this run uses (--quick: K / 10)
                cmd = [
                    sys.executable,
                    __file__,
                    "--one",
                    name,
                    "--threads",
                    str(args.threads),
                    "--reps",
                    str(args.reps),
                    "--device",
                    args.device,
                    *(["--quick"] if args.quick else []),
                ]
                env = dict(os.environ)
                if "compiled" in name:
                    env["TORCHINDUCTOR_CACHE_DIR"] = cache
                out = subprocess.run(cmd, capture_output=True, text=True, env=env)
                res = _child_result(out)
                if res is None:  # the child failed: say so, show why, go on with the rest
                    failed.append(f"{line}/{label}")
                    print(f"{line:<10} {label:<34} failed (exit status {out.returncode})")
                    tail = (out.stderr or "").rstrip().splitlines()[-STDERR_TAIL:]
                    print(f"--- {name}: last lines of its stderr:", file=sys.stderr)
                    for text in tail or ["(empty)"]:
                        print(f"    {text}", file=sys.stderr)
                    sys.stdout.flush()
                    sys.stderr.flush()
                    continue
                if not res:
                    print(f"{line:<10} {label:<34} not installed, skipped")
                    continue
                ratio = ""
                if res["path"] == "pytorch-mppi":
                    ref = res
                elif ref is not None:
                    wall = (res["state_steps"] / res["median"]) / (
                        ref["state_steps"] / ref["median"]
                    )
                    cpu = (res["state_steps"] / res["cpu"]) / (ref["state_steps"] / ref["cpu"])
                    if line in ("batched", "modelbatch"):
                        ratio = f"throughput {wall:.2f}x ({cpu:.2f}x) pytorch-mppi's"
                    else:
                        ratio = f"time {1 / wall:.3f}x ({1 / cpu:.3f}x) pytorch-mppi's"
                print(f"{line:<10} {label:<34} {res['path']:<12} {fmt(res)}  {ratio}")
                if line == "paper" and not args.quick:
                    total = res["median"] * PAPER_CALLS
                    print(
                        f"{'':<9} projection: {PAPER_CALLS} calls x {res['median']:.3f} s = "
                        f"{total:.0f} s ({total / 60:.1f} min) per MPPI method of the paper-size "
                        f"scenario B run (planner only; {res['cpu'] * PAPER_CALLS:.0f} s CPU time)"
                    )
    if failed:
        print(f"bench_mppi: {len(failed)} planner(s) failed: {', '.join(failed)}", file=sys.stderr)
        sys.exit(1)


if __name__ == "__main__":
    main()
