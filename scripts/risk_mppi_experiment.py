"""Experiment: a risk-aware MPPI for scenario B worth choosing (tuning seeds only).

Scenario B's ``mppi_rascbf`` filters MPPI with the risk-aware CBF built on the radius form
``r_i = |q_i| - 1`` of the ellipses, rectified as ``h_i = L_f r_i + k r_i`` (or the smooth
minimum of that and ``k r_i``, ``--forms``). Its margin ``Delta_i``
holds the robot, at rest, on ``r_i >= Delta_i / k``: the ellipse scaled by
``1 + Delta_i / k`` in its own coordinates, a berth as wide in ``r`` along the long axes as
along the short ones, so in metres up to ``a_max / a_min`` (8 for the flat ellipse at
(2, 5)) times the berth the noise needs at the flat sides. The planner does not know that
set: it plans through what the filter then refuses.

Variants (each on 32 tuning seeds from ``--seed``, never the evaluation seeds 0-31):

- ``baseline``: the scenario's ``mppi_rascbf``;
- ``margin``: the planner's barrier cost on the filter's margin set (the ellipses scaled by
  ``1 + Delta_i / k``) instead of the ellipses: a planner that knows the risk margin;
- ``shield``: :class:`~torchcbf.mppi.ShieldMPPI` (``in_loop``) with the discrete-time CBF
  penalty on the margin set over the first 10 rollout steps (scenario B's shield on the
  risk margin), the filter's control fed back into the plan;
- ``margin+shield``: both;
- ``wall``: the planner's own costs plus a penalty on entering the margin set (weight 1e3
  on ``relu(-b)`` of the ellipses scaled by ``1 + Delta_i / k``, every rollout step): zero
  outside it, so the cost's minimum near the goal stays where it was;
- each with ``--horizons``: the risk horizon ``T`` (s) instead of the scenario's choice
  (``Delta ~ sqrt(T)``: a shorter horizon, a narrower berth, a bound over a shorter time),
  ``--gains``: the rectification gain ``k`` (the approach speed ``h >= 0`` allows near
  an ellipse grows with it), ``--speeds``: ``v`` adds two risk-aware barriers keeping the
  speed in ``[-0.5, v]`` (the speeds of the grid ``eta`` is taken over),
  ``--max-speeds``: the scenario's ``risk_max_speed``, the top speed of the grid ``eta`` is
  taken over (3 m/s by default; its robots reach 6-7 m/s), and ``--inflations``: the
  scenario's ``risk_inflation``, metres added to every semi-axis of the ellipses the
  filter keeps the robot out of (a berth the same in every direction, where the radius
  form's margin is proportional to the semi-axis), ``--forms``: the scenario's
  ``risk_form`` (``rectified``: ``L_f r_i + k r_i``; ``inside``: its smooth minimum with
  ``k r_i``, a safe set inside the obstacle-free set), ``--temperatures``: that minimum's
  ``risk_temperature``, ``--omega-weights``: the filter's QP weight on ``omega``, and
``--rhos``: the risk level ``rho``, ``--budgets``: the scenario's ``risk_budget``, a
probability for the whole 5 s run shared by its windows of length ``T`` (``rho = budget T /
5 s``; needs ``--horizons``), ``--etas``: the scenario's ``risk_eta``, ``sup`` (one noise
bound per ellipse over the operating states: a constant margin) or ``local`` (each step's
own ``|dh/dx sigma|``: a margin that follows the barrier's gradient, a berth about as wide
in metres at the long axes' tips as at the flat sides).

``--evaluate`` runs the scenario's ``mppi_rascbf`` as configured on any seed block (the
evaluation seeds included) and prints the same columns.

``--cost`` instead times the filters of ``mppi_scbf``, ``mppi_rascbf`` (both forms; the
inside form with both noise bounds) and ``shield_mppi`` on the same states, their closed
loops, and counts filter calls per step.

Per variant: collisions, goals reached, robots leaving the field ``[-2.5, 5] x [-2, 6.5]``,
relaxed filter steps, the risk-aware check (windows from ``h >= Delta`` that leave the
safe set within ``T``; failure rate against ``rho``) and the near misses: seeds whose
closest approach to an ellipse is under 2 cm and under 5 cm (the distance bounded below by
``r_i min(a_i)``, ``r_i = |q_i| - 1`` the radius form), a measure of the lower tail that
collisions, rare on a few hundred seeds, do not give.

Usage::

    python scripts/risk_mppi_experiment.py                           # K = 1,000, seeds 10,000+
    python scripts/risk_mppi_experiment.py --variants margin+shield --horizons 0.1 --seed 10032
    python scripts/risk_mppi_experiment.py --variants baseline --inflations 0 0.1 --max-speeds 8
    python scripts/risk_mppi_experiment.py --variants baseline --forms rectified inside
    python scripts/risk_mppi_experiment.py --variants baseline --horizons 0.1 0.03 --budgets 0.05
    python scripts/risk_mppi_experiment.py --variants baseline --etas sup local --horizons 0.07
    python scripts/risk_mppi_experiment.py --evaluate --seed 0 --seeds 32
    python scripts/risk_mppi_experiment.py --cost --samples 1000
"""

from __future__ import annotations

import argparse
import itertools
import time
from dataclasses import replace

import torch

from torchcbf.barriers import Ellipse, HalfSpace
from torchcbf.filters import RiskAware, SafetyFilter
from torchcbf.mppi import BarrierCost, DiscreteBarrierCost, QuadraticGoal, ShieldMPPI, SumCost
from torchcbf.scenarios.unicycle_mppi_cbf import (
    AXES,
    CENTERS,
    GOAL,
    RISK_ETAS,
    RISK_FORMS,
    ROLLOUT_DT,
    SIGMA,
    mppi_cbf,
    obstacles,
    risk_failures,
)

VARIANTS = ("baseline", "margin", "shield", "margin+shield", "wall")
FIELD = ((-2.5, 5.0), (-2.0, 6.5))


def margin_set(delta: list[float], k: float) -> Ellipse:
    """The filter's margin set at rest: each ellipse scaled by ``1 + Delta_i / k``."""
    scale = torch.tensor([1.0 + d / k for d in delta]).unsqueeze(-1)
    return Ellipse(torch.tensor(CENTERS), torch.tensor(AXES) * scale, index=(0, 1))


def closest_approach(x: torch.Tensor) -> torch.Tensor:
    """Per seed, the smallest lower bound ``r_i min(a_i)`` (m) on the distance to an ellipse
    over the run (``x [B, S, 4]``; negative inside one)."""
    b = obstacles().to(x)(x)  # [B, S, 5]
    r = torch.sqrt(b.clamp_min(-1.0) + 1.0) - 1.0
    short = torch.tensor([min(a) for a in AXES], dtype=x.dtype, device=x.device)
    return (r * short).amin(-1).amin(-1)


def speed_limited(sc, v_max: float) -> SafetyFilter:
    """The scenario's risk-aware filter with the speed kept in ``[-0.5, v_max]`` by two more
    risk-aware barriers (``|dh/dx sigma| = sigma`` for both)."""
    old = sc.safety_filter
    params = sc.params
    speed = HalfSpace(torch.tensor([[1.0], [-1.0]]), torch.tensor([v_max, 0.5]), index=(2,))
    eta = torch.tensor([*params["eta"], SIGMA, SIGMA], dtype=torch.float64)
    return SafetyFilter(
        sc.dynamics,
        barriers=[old.barriers[0], speed.to(sc.x0.dtype)],
        mode=RiskAware(rho=params["rho"], horizon=params["risk_horizon"], eta=eta),
        R=torch.diag(torch.tensor(params["control_weight"], dtype=torch.float64)),
    ).to(sc.x0.dtype)


def with_filter(sc, safety_filter: SafetyFilter):
    """The scenario with another risk-aware filter (its risk check on that filter's
    barriers and margins)."""
    delta = safety_filter.cbf_margin.detach().double()
    window = round(sc.params["risk_horizon"] / sc.dt)

    def extra(traj):
        return risk_failures(traj.h, delta.to(traj.h), window)

    return replace(sc, safety_filter=safety_filter, extra_metrics=extra)


def build(
    variant: str,
    seed: int,
    seeds: int,
    samples: int,
    horizon: float | None,
    gain: float | None = None,
    speed: float | None = None,
    max_speed: float | None = None,
    inflation: float | None = None,
    form: str | None = None,
    temperature: float | None = None,
    omega_weight: float | None = None,
    rho: float | None = None,
    budget: float | None = None,
    eta: str | None = None,
):
    sc = mppi_cbf(
        "mppi_rascbf",
        seed=seed,
        num_seeds=seeds,
        num_samples=samples,
        risk_horizon=horizon,
        rectify_gain=gain,
        risk_max_speed=max_speed,
        risk_inflation=inflation,
        risk_form=form,
        risk_temperature=temperature,
        control_weight=None if omega_weight is None else (1.0, omega_weight),
        rho=rho,
        risk_budget=budget,
        risk_eta=eta,
    )
    if speed is not None:
        sc = with_filter(sc, speed_limited(sc, speed))
    if variant == "baseline":
        return sc
    k, delta = sc.params["rectify_gain"], sc.params["delta"]
    dtype = sc.x0.dtype
    inflated = margin_set(delta, k).to(dtype)
    planner = sc.planner
    terms = [QuadraticGoal(GOAL, weight=2.0, index=(0, 1), terminal_weight=10.0)]
    barrier = inflated if "margin" in variant else sc.barriers[0]
    terms.append(BarrierCost(barrier, weight=2.0, eps=0.01))
    if variant == "wall":  # relu(0 b_k - b_{k+1}): the penetration of the margin set
        terms.append(DiscreteBarrierCost(inflated, gamma=1.0, weight=1e3))
    if "shield" in variant:
        gamma = min(k * ROLLOUT_DT, 1.0)
        terms.append(DiscreteBarrierCost(inflated, gamma=gamma, weight=1e3, steps=10))
    planner.cost = SumCost(*terms).to(dtype)
    safety_filter = sc.safety_filter
    if "shield" in variant:
        planner = ShieldMPPI(planner, safety_filter, in_loop=True)
        safety_filter = planner.loop_filter
    return replace(sc, planner=planner, safety_filter=safety_filter)


def filter_cost(seeds: int, samples: int, repeat: int) -> None:
    """Per-step cost of the filters of ``mppi_scbf``, ``mppi_rascbf`` (both forms, the inside
    one with both noise bounds) and ``shield_mppi``, each method's whole closed loop (the
    planner included) and its filter calls per control step. The filters are timed on the
    same inputs: the states and MPPI controls of ``mppi_scbf``'s run at every tenth step
    (calls interleaved, after a warm-up)."""
    setups = {
        "mppi_scbf": {"method": "mppi_scbf"},
        "mppi_rascbf rectified": {"method": "mppi_rascbf", "risk_form": "rectified"},
        "mppi_rascbf inside sup": {
            "method": "mppi_rascbf",
            "risk_form": "inside",
            "risk_eta": "sup",
        },
        "mppi_rascbf inside local": {
            "method": "mppi_rascbf",
            "risk_form": "inside",
            "risk_eta": "local",
        },
        "shield_mppi": {"method": "shield_mppi"},
    }
    loops: dict[str, tuple[float, float]] = {}
    scenarios = {}
    inputs: list[tuple[torch.Tensor, torch.Tensor]] = []
    for name, kw in setups.items():
        sc = mppi_cbf(seed=10_000, num_seeds=seeds, num_samples=samples, **kw)
        flt = sc.safety_filter
        target = flt.shield.safety_filter if hasattr(flt, "shield") else flt
        calls = 0

        def count(*_: object) -> None:
            nonlocal calls
            calls += 1

        handle = target.register_forward_hook(count)
        start = time.perf_counter()
        traj, _ = sc.run(progress=False)
        loops[name] = (time.perf_counter() - start, calls / sc.steps)
        handle.remove()
        scenarios[name] = sc
        if not inputs:
            inputs = [(traj.x[:, j], traj.u_nom[:, j]) for j in range(0, sc.steps, 10)]
    times: dict[str, list[float]] = {name: [] for name in scenarios}
    paths = {}
    with torch.no_grad():
        for name, sc in scenarios.items():
            for x, u in inputs[:5]:
                paths[name] = sc.safety_filter(x, u, 0.0).path
        for _ in range(max(repeat // len(inputs), 1)):
            for x, u in inputs:
                for name, sc in scenarios.items():
                    start = time.perf_counter()
                    sc.safety_filter(x, u, 0.0)
                    times[name].append(time.perf_counter() - start)
    count_calls = len(times["mppi_scbf"])
    print(f"filter call on {seeds} states of a run (median of {count_calls}, interleaved);")
    print(f"closed loop of {seeds} seeds, K = {samples}, 500 steps; one torch thread")
    print(
        f"{'method':<24}{'path':<26}{'filter us':>10}{'ratio':>7}{'loop s':>8}{'ratio':>7}"
        f"{'calls/step':>11}"
    )
    base_call, base_loop = None, None
    for name in scenarios:
        call = sorted(times[name])[len(times[name]) // 2] * 1e6
        loop, per_step = loops[name]
        base_call = base_call or call
        base_loop = base_loop or loop
        print(
            f"{name:<24}{paths[name]:<26}{call:>10.0f}{call / base_call:>7.2f}{loop:>8.1f}"
            f"{loop / base_loop:>7.2f}{per_step:>11.2f}"
        )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--seed", type=int, default=10_000)
    parser.add_argument("--seeds", type=int, default=32)
    parser.add_argument("--samples", type=int, default=1000)
    parser.add_argument("--variants", nargs="+", choices=VARIANTS, default=list(VARIANTS))
    parser.add_argument("--horizons", nargs="+", type=float, default=[None])
    parser.add_argument("--gains", nargs="+", type=float, default=[None])
    parser.add_argument("--speeds", nargs="+", type=float, default=[None])
    parser.add_argument("--max-speeds", nargs="+", type=float, default=[None])
    parser.add_argument("--inflations", nargs="+", type=float, default=[None])
    parser.add_argument("--cost", action="store_true", help="time the filters and loops instead")
    parser.add_argument("--repeat", type=int, default=200)
    parser.add_argument("--forms", nargs="+", choices=RISK_FORMS, default=[None])
    parser.add_argument("--temperatures", nargs="+", type=float, default=[None])
    parser.add_argument("--omega-weights", nargs="+", type=float, default=[None])
    parser.add_argument("--rhos", nargs="+", type=float, default=[None])
    parser.add_argument("--budgets", nargs="+", type=float, default=[None])
    parser.add_argument("--etas", nargs="+", choices=RISK_ETAS, default=[None])
    parser.add_argument(
        "--evaluate",
        action="store_true",
        help="run the scenario's own mppi_rascbf (no options) on any seeds, e.g. 0-31",
    )
    args = parser.parse_args()
    if args.evaluate:
        tuned = ("horizons", "gains", "speeds", "max_speeds", "inflations", "forms")
        tuned += ("temperatures", "omega_weights", "rhos", "budgets", "etas")
        if any(getattr(args, name) != [None] for name in tuned) or args.cost:
            parser.error("--evaluate runs the configured method: no tuning options, no --cost")
        args.variants = ["baseline"]
    elif args.seed < 10_000:
        parser.error("tune on seeds >= 10,000 (0-31 are the evaluation seeds; --evaluate)")
    torch.set_num_threads(1)
    if args.cost:
        filter_cost(args.seeds, args.samples, args.repeat)
        return
    print(f"seeds {args.seed}..{args.seed + args.seeds - 1}, K = {args.samples}")
    print(
        f"{'eta':<6}{'rho':>8}{'R_w':>6} {'form':<10}{'temp':>5}  {'variant':<15}"
        f"{'speed':>6}{'vmax':>5}{'infl':>5}{'k':>5}{'T s':>6}{'collide':>8}"
        f"{'goal':>6}{'leave':>6}{'relaxed':>8}{'windows':>9}{'fail':>6}{'rate':>8}"
        f"{'<2cm':>5}{'<5cm':>5}{'v top':>6}{'wall s':>8}  colliding seeds"
    )
    grid = itertools.product(
        args.etas,
        args.budgets,
        args.rhos,
        args.omega_weights,
        args.forms,
        args.temperatures,
        args.inflations,
        args.max_speeds,
        args.speeds,
        args.gains,
        args.horizons,
        args.variants,
    )
    for options in grid:
        eta, budget, rho, omega_weight, form, temperature, inflation = options[:7]
        max_speed, speed, gain, horizon, variant = options[7:]
        start = time.perf_counter()
        sc = build(
            variant, args.seed, args.seeds, args.samples, horizon, gain, speed, max_speed,
            inflation, form, temperature, omega_weight, rho, budget, eta,
        )  # fmt: skip
        traj, m = sc.run(progress=False)
        x = traj.x
        (x0, x1), (y0, y1) = FIELD
        out = (x[..., 0] < x0) | (x[..., 0] > x1) | (x[..., 1] < y0) | (x[..., 1] > y1)
        windows = int(m["risk_windows"].sum())
        fails = int(m["risk_window_failures"].sum())
        colliding = (torch.nonzero(m["collision"]).flatten() + args.seed).tolist()
        closest = closest_approach(x)
        print(
            f"{sc.params['risk_eta']:<6}{sc.params['rho']:>8.2g}"
            f"{sc.params['control_weight'][1]:>6g} "
            f"{sc.params['risk_form']:<10}"
            f"{sc.params['risk_temperature']:>5g}  "
            f"{variant:<15}{'-' if speed is None else f'{speed:g}':>6}"
            f"{sc.params['risk_max_speed']:>5g}{sc.params['risk_inflation']:>5g}"
            f"{sc.params['rectify_gain']:>5.0f}"
            f"{sc.params['risk_horizon']:>6.3f}{int(m['collision'].sum()):>8}"
            f"{int(m['goal_reached'].sum()):>6}{int(out.any(-1).sum()):>6}"
            f"{int(m['steps_relaxed'].sum()):>8}{windows:>9}{fails:>6}"
            f"{fails / max(windows, 1):>8.5f}{int((closest < 0.02).sum()):>5}"
            f"{int((closest < 0.05).sum()):>5}{float(x[..., 2].amax()):>6.1f}"
            f"{time.perf_counter() - start:>8.1f}  {colliding}"
        )


if __name__ == "__main__":
    main()
