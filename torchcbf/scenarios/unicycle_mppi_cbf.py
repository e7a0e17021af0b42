"""Scenario B (docs/scenarios.md): MPPI and stochastic CBFs on a noisy unicycle with
acceleration input among five elliptical obstacles.

Methods (:data:`METHODS`), each run over a batch of noise seeds:

- ``"scbf"``: the stochastic CBF-QP on the proportional controller;
- ``"mppi"``: MPPI alone;
- ``"mppi_scbf"``: MPPI whose control is filtered by the stochastic CBF-QP;
- ``"mppi_rascbf"``: MPPI filtered by the risk-aware stochastic CBF (probability ``rho`` of
  leaving its safe set within the horizon ``T``; in the default configuration 5% for the
  whole run shared by its windows of ``T = 0.07 s``, ``risk_budget``, a safe set inside
  the obstacle-free set, ``risk_form="inside"``, and a margin from each state's own noise,
  ``risk_eta="local"``);
- ``"shield_mppi"``: a barrier-aware MPPI (:class:`~torchcbf.mppi.ShieldMPPI`): its rollouts
  pay a steep penalty for breaking the discrete-time CBF condition of the obstacles over
  their first ``shield_steps`` steps, and
  the control the filter actually applies is written back into the plan, so planner and
  filter stop pulling apart.

Configurations (:data:`CONFIGS`) fix the filter's free parameters (the plant, noise,
obstacles, goal, MPPI and its costs are the same in all three):

- ``"paper"``: the paper's numbers (alpha = 1, beta = 1) on the exponential form
  ``h_e = c_i (L_f b_i + k b_i)``, with the choices the paper leaves open made as
  documented in docs/scenarios.md (k = 20, a 2/3 m equilibrium margin, R = diag(1, 1e-3));
- ``"cbfkit"``: CBFkit's own reading, the sublevel barrier ``B_i = exp(-0.1 b_i)`` with
  ``L B + tr / 2 <= -alpha B + beta`` (alpha = beta = 1) on its exponential rectification
  ``B + 0.3 L_f B``;
- ``"default"``: the project's choice of the free parameters (alpha, the equilibrium margin
  and the own margins of the goal wall and the blocking ellipse, the control bounds), made
  by ``scripts/tune_scenario_b.py`` on tuning seeds 10,000 and up, never on the evaluation
  seeds; the tables are in docs/scenarios.md.

The equilibrium margin ``m``: where the condition is active and the robot at rest,
``h_e = beta / alpha``, i.e. ``b_i = beta / (alpha k c_i)``; with ``c_i = beta min(axes_i) /
(2 alpha k m)`` that is the distance ``m`` from the flat sides of every ellipse (where
``|grad b_i| = 2 / min(axes_i)``). The noise moves the robot around that equilibrium by
about ``sigma / sqrt(2 alpha)`` (an Ornstein-Uhlenbeck process of rate alpha), so a useful
margin needs a large alpha: with alpha = 1 the band (0.2 m) is as wide as the passages'
slack, and the robot either stalls or collides in some seeds (docs/scenarios.md).

Scenario ``b`` uses noise seed ``seed + b`` and MPPI seed ``seed + b``.
"""

from __future__ import annotations

import copy
import math
from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Any

import torch
from torch import Tensor

from torchcbf._checks import check_number, check_positive_int
from torchcbf.barriers import Barrier, Ellipse, Intersection, Scaled, Transformed, rectify
from torchcbf.dynamics import AccelUnicycle
from torchcbf.filters import FilterStatus, RiskAware, SafetyFilter, Stochastic
from torchcbf.filters.risk import noise_bound
from torchcbf.mppi import MPPI, DiscreteBarrierCost, QuadraticGoal, ShieldMPPI, SumCost
from torchcbf.mppi.costs import BarrierCost
from torchcbf.scenarios.base import Scenario
from torchcbf.scenarios.figures import standard_figures
from torchcbf.scenarios.registry import Column, Dimension, EnvEntry, ScenarioEntry, register
from torchcbf.sim import Goal, Trajectory

METHODS = ("scbf", "mppi", "mppi_scbf", "mppi_rascbf", "shield_mppi")
CONFIGS = ("default", "paper", "cbfkit")
RISK_FORMS = ("rectified", "inside")
RISK_ETAS = ("sup", "local")
GOAL = (2.0, 4.0)
CENTERS = ((1.0, 2.0), (3.0, 2.0), (2.0, 5.0), (-1.0, 1.0), (0.5, -1.0))
AXES = ((0.5, 1.5), (0.75, 2.0), (2.0, 0.25), (1.0, 0.75), (0.75, 0.5))
SIGMA = 0.28
X0 = (0.0, 0.0, 0.0, math.pi / 4)
DT, STEPS, ROLLOUT_DT = 0.01, 500, 0.02
FLAT_MARGIN = 2.0 / 3.0
"""Equilibrium margin (m) of the ``paper`` configuration."""
GOAL_WALL = 2
"""Index of the ellipse at (2, 5), whose flat side faces the goal 0.75 m away."""
BLOCKING = 0
"""Index of the ellipse at (1, 2) across the straight line from the start to the goal: the
proportional controller presses the robot along its long side."""


@dataclass(frozen=True)
class FilterParams:
    """The free parameters of scenario B's safety filters (one configuration).

    Attributes:
        form: ``"exponential"`` (``h_e = c_i (L_f b_i + k b_i)`` on the ellipses) or
            ``"cbfkit"`` (``h = 1 - exp(-0.1 b_i)``, rectified as ``h + 0.3 L_f h``).
        alpha, beta: the stochastic condition ``L h + tr / 2 >= -alpha h + beta`` (for
            ``"cbfkit"``: CBFkit's sublevel ``L B + tr / 2 <= -alpha B + beta``).
        rectify_gain: ``k`` of the exponential form.
        margin: equilibrium distance (m) from the flat sides to first order (exactly
            ``a (sqrt(1 + 2 margin / a) - 1)``, ``a`` the short semi-axis); sets ``c_i``.
        goal_wall_margin: the margin of the ellipse :data:`GOAL_WALL` (``None``: ``margin``);
            a robot that has reached the goal hovers between it and the goal.
        blocking_margin: the margin of the ellipse :data:`BLOCKING` (``None``: ``margin``),
            along whose long side a robot led by the proportional controller slides.
        control_weight: diagonal of the QP weight ``R`` on ``(a, omega)``.
        control_limit: bound on ``|a|`` and ``|omega|`` (``None``: unbounded).
        rho: risk-aware methods: probability of leaving the safe set within ``T`` (used when
            ``risk_budget`` is ``None``).
        risk_budget: risk-aware method: a probability for the whole run (``STEPS * DT``)
            shared by its ``STEPS * DT / T`` windows of length ``T``: ``rho = risk_budget T /
            (STEPS * DT)`` (a union bound over consecutive windows; ``None``: ``rho``). Needs a
            fixed ``risk_horizon``.
        risk_horizon: ``T`` (s) of the risk-aware condition; ``None`` chooses it (see
            :func:`risk_horizon`; the paper and cbfkit configurations), 0.07 s in the default
            configuration (with ``risk_budget = 0.05``: ``rho = 7e-4``).
        risk_inflation: risk-aware method: metres added to every semi-axis of the ellipses
            its filter keeps the robot out of (a berth the same in every direction; the
            margin ``Delta`` holds the robot off by a multiple of each semi-axis).
        risk_goal_wall_inflation: risk-aware method: metres added, on top of
            ``risk_inflation``, to the semi-axes of the ellipse :data:`GOAL_WALL` (a robot that
            has reached the goal hovers between it and the goal, at rest, where a unicycle
            parallel to the wall cannot move away from it within a step).
        risk_max_speed: risk-aware method: the top speed (m/s) of the operating states the
            noise bound ``eta`` is taken over (:func:`operating_states`); the bound holds
            only while the robot is no faster (8 m/s in the default configuration, 3 m/s in
            the others).
        risk_form: risk-aware method: its barriers, from the radius form ``r_i`` of the
            ellipses: ``"rectified"``, ``h_i = L_f r_i + k r_i``, or ``"inside"``, the smooth
            minimum ``-tau log(exp(-(L_f r_i + k r_i) / tau) + exp(-k r_i / tau))`` of that
            and ``k r_i``, which is ``<= k r_i``: its safe set lies inside the obstacle-free
            set, so a collision leaves it (the rectified form is positive inside an ellipse
            for a robot moving outwards).
        risk_temperature: ``tau`` of the ``"inside"`` form.
        risk_eta: risk-aware method: ``"sup"``, one noise bound ``eta_i`` per ellipse over
            :func:`operating_states` (a margin ``Delta_i`` that is constant), or ``"local"``,
            each step's own ``|dh_i/dx sigma|`` (:class:`~torchcbf.filters.RiskAware`'s
            ``eta="local"``): a margin that follows the barrier's gradient, so the berth is
            about as wide in metres at the long axes' tips as at the flat sides.
        shield_weight: weight of the shield's discrete-time CBF penalty.
        shield_steps: rollout steps the shield's penalty covers (``None`` or at least the
            horizon: all of them; 10 by the sweep of docs/scenarios.md).
    """

    form: str = "exponential"
    alpha: float = 50.0
    beta: float = 1.0
    rectify_gain: float = 20.0
    margin: float = 0.25
    goal_wall_margin: float | None = 0.4
    blocking_margin: float | None = 0.3
    control_weight: tuple[float, float] = (1.0, 1e-3)
    control_limit: tuple[float, float] | None = (40.0, 40.0)
    rho: float = 0.05
    risk_budget: float | None = None
    risk_horizon: float | None = None
    risk_inflation: float = 0.0
    risk_goal_wall_inflation: float = 0.0
    risk_max_speed: float = 3.0
    risk_form: str = "rectified"
    risk_temperature: float = 0.5
    risk_eta: str = "sup"
    shield_weight: float = 1e3
    shield_steps: int | None = 10


CONFIG_PARAMS: dict[str, FilterParams] = {
    # rho = 5% for the whole run, shared by its windows of T = 0.07 s (rho = 7e-4 per
    # window); the margin from each state's own |dh/dx sigma| ("local"): a berth of about
    # 0.25 m from every side of every ellipse, where one eta per ellipse, set by its flat
    # sides, made it up to 8 times wider at the long axes' tips and sent robots around the
    # outside of the field (scripts/risk_mppi_experiment.py, tuning seeds only); the "inside"
    # form: a collision leaves the filter's safe set (the rectified form stays positive for a
    # robot moving out); risk_max_speed: the speeds of the recorded sup bound ("sup")
    "default": FilterParams(
        risk_budget=0.05,
        risk_horizon=0.07,
        risk_max_speed=8.0,
        risk_form="inside",
        risk_eta="local",
    ),
    "paper": FilterParams(
        alpha=1.0,
        beta=1.0,
        margin=FLAT_MARGIN,
        goal_wall_margin=None,
        blocking_margin=None,
        control_limit=None,
    ),
    "cbfkit": FilterParams(
        form="cbfkit",
        alpha=1.0,
        beta=1.0,
        rectify_gain=1.0 / 0.3,
        goal_wall_margin=None,
        blocking_margin=None,
        control_limit=None,
    ),
}


def obstacles(*, inflation: float | Sequence[float] = 0.0) -> Ellipse:
    """The five ellipses as one barrier ``b(x) -> [..., 5]`` on the position ``(x, y)``;
    ``inflation`` (m; one number, or one per ellipse) is added to their semi-axes."""
    grow = torch.as_tensor(inflation, dtype=torch.float32)
    if grow.dim() == 1:
        if grow.shape[0] != len(AXES):
            raise ValueError(
                f"inflation must be a number or {len(AXES)} numbers, got {list(inflation)}"
            )
        grow = grow.unsqueeze(-1)
    return Ellipse(torch.tensor(CENTERS), torch.tensor(AXES) + grow, index=(0, 1))


def proportional_controller(goal: tuple[float, float] = GOAL):
    """``v_d = min(2, |p - goal|)``, ``a = v_d - v``, ``omega = 10 wrap(heading - theta)``."""

    def control(x: Tensor, t: float) -> Tensor:
        d = x.new_tensor(goal) - x[..., :2]
        heading = torch.atan2(d[..., 1], d[..., 0])
        err = torch.remainder(heading - x[..., 3] + math.pi, 2 * math.pi) - math.pi
        v_d = d.norm(dim=-1).clamp(max=2.0)
        return torch.stack([v_d - x[..., 2], 10.0 * err], -1)

    return control


@dataclass(frozen=True)
class MppiCbfParams:
    """The parameters of scenario B.

    Attributes:
        method: one of :data:`METHODS`.
        config: one of :data:`CONFIGS`: the filter's parameters (:data:`CONFIG_PARAMS`).
        num_samples, horizon: MPPI's ``K`` and ``H`` (the paper: 20,000 and 80).
        planner_every: replan every this many loop steps (2: once per rollout step of
            0.02 s); between replans the loop follows the plan.
        alpha, beta, rectify_gain, margin, goal_wall_margin, blocking_margin, control_weight,
            control_limit, rho, risk_budget, risk_horizon, risk_inflation,
            risk_goal_wall_inflation, risk_max_speed,
            risk_form, risk_temperature, risk_eta, shield_weight, shield_steps: override the
            configuration's value (:class:`FilterParams`; ``None``: the configuration's; a
            ``rho`` given alone replaces the configuration's ``risk_budget``).
        barrier_scale: the scales ``c_i`` of the exponential form (one number or five),
            overriding the ones ``margin`` sets.
        noise_sigma, cost_normalization, zero_noise_samples, shift_fill: MPPI's (the noise
            covariance is ``noise_sigma * I``, CBFkit's ``control_cov``).
    """

    method: str = "mppi_scbf"
    config: str = "default"
    num_samples: int = 20_000
    horizon: int = 80
    planner_every: int = 2
    alpha: float | None = None
    beta: float | None = None
    rectify_gain: float | None = None
    margin: float | None = None
    goal_wall_margin: float | None = None
    blocking_margin: float | None = None
    barrier_scale: float | tuple[float, ...] | None = None
    control_weight: float | tuple[float, float] | None = None
    control_limit: float | tuple[float, float] | None = None
    rho: float | None = None
    risk_budget: float | None = None
    risk_horizon: float | None = None
    risk_inflation: float | None = None
    risk_goal_wall_inflation: float | None = None
    risk_max_speed: float | None = None
    risk_form: str | None = None
    risk_temperature: float | None = None
    risk_eta: str | None = None
    shield_weight: float | None = None
    shield_steps: int | None = None
    noise_sigma: float = 4.0
    cost_normalization: str = "none"
    zero_noise_samples: int = 0
    shift_fill: str = "zero"


def mppi_cbf(
    method: str | None = None,
    *,
    num_seeds: int = 32,
    seed: int = 0,
    device: str | torch.device = "cpu",
    dtype: torch.dtype | None = None,
    **params: Any,
) -> Scenario:
    """Build scenario B with one of :data:`METHODS` (``None``: ``"mppi_scbf"``) for
    ``num_seeds`` noise seeds; ``params``: fields of :class:`MppiCbfParams`.

    Returns:
        A :class:`Scenario` whose ``params`` record every parameter used.
    """
    if method is not None:
        params["method"] = method
    return ENTRY.make(num_seeds=num_seeds, seed=seed, device=device, dtype=dtype, **params)


def build(
    p: MppiCbfParams,
    *,
    num_seeds: int = 32,
    seed: int = 0,
    device: str | torch.device = "cpu",
    dtype: torch.dtype | None = None,
) -> Scenario:
    """Scenario B with the parameters ``p`` for ``num_seeds`` noise seeds."""
    dtype = torch.float32 if dtype is None else dtype
    check_positive_int("num_seeds", num_seeds)
    method, config = p.method, p.config
    num_samples, horizon, planner_every = p.num_samples, p.horizon, p.planner_every
    barrier_scale, noise_sigma = p.barrier_scale, p.noise_sigma
    cost_normalization, zero_noise_samples, shift_fill = (
        p.cost_normalization, p.zero_noise_samples, p.shift_fill,
    )  # fmt: skip
    alpha, beta, rectify_gain, margin = p.alpha, p.beta, p.rectify_gain, p.margin
    goal_wall_margin, blocking_margin = p.goal_wall_margin, p.blocking_margin
    control_weight, control_limit, rho = p.control_weight, p.control_limit, p.rho
    risk_horizon, shield_weight, shield_steps = p.risk_horizon, p.shield_weight, p.shield_steps
    risk_inflation, risk_max_speed = p.risk_inflation, p.risk_max_speed
    risk_form, risk_temperature, risk_budget = p.risk_form, p.risk_temperature, p.risk_budget
    if method not in METHODS:
        raise ValueError(f"method must be one of {METHODS}, got {method!r}")
    if config not in CONFIGS:
        raise ValueError(f"config must be one of {CONFIGS}, got {config!r}")
    overrides = {
        "alpha": alpha,
        "beta": beta,
        "rectify_gain": rectify_gain,
        "margin": margin,
        "goal_wall_margin": goal_wall_margin,
        "blocking_margin": blocking_margin,
        "rho": rho,
        "risk_horizon": risk_horizon,
        "risk_max_speed": risk_max_speed,
        "risk_temperature": risk_temperature,
        "shield_weight": shield_weight,
    }
    if config == "cbfkit":
        # its stochastic CBFs fix their scales (B + 0.3 L_f B) and keep no margins; the
        # margin still sets the risk-aware filter's horizon
        fixed = {
            "barrier_scale": barrier_scale,
            "goal_wall_margin": goal_wall_margin,
            "blocking_margin": blocking_margin,
            "margin": None if method == "mppi_rascbf" else margin,
        }
        given = sorted(name for name, value in fixed.items() if value is not None)
        if given:
            raise ValueError(
                f"config='cbfkit' takes no {', '.join(given)} for method {method!r}: its "
                "barriers fix their scales (B + 0.3 L_f B) and keep no margins (margin sets "
                "the risk-aware filter's horizon only)"
            )
    params = CONFIG_PARAMS[config]
    for name, value in overrides.items():
        if value is not None:  # beta > 0 too: the scales c_i set by the margin are prop. to it
            value = check_number(name, value, low=0.0, strict=True)
            params = replace(params, **{name: value})
    if rho is not None and risk_budget is None:
        params = replace(params, risk_budget=None)
    if risk_budget is not None:
        budget = check_number("risk_budget", risk_budget, low=0.0, strict=True)
        if not budget < 1.0:
            raise ValueError(f"risk_budget must be in (0, 1), got {risk_budget}")
        params = replace(params, risk_budget=budget)
    if params.risk_budget is not None and params.risk_horizon is None:
        raise ValueError("risk_budget needs a fixed risk_horizon (T); got risk_horizon=None")
    if params.risk_horizon is not None and not DT <= params.risk_horizon <= STEPS * DT:
        # shorter than a step the windows are empty; longer than the run there is none, and
        # a budget shared by its windows would give one window more than the whole run's
        raise ValueError(
            f"risk_horizon must lie in [{DT:g}, {STEPS * DT:g}] s (a step to the whole run), "
            f"got {params.risk_horizon:g}"
        )
    if p.risk_goal_wall_inflation is not None:
        wall = check_number("risk_goal_wall_inflation", p.risk_goal_wall_inflation, low=0.0)
        params = replace(params, risk_goal_wall_inflation=wall)
    if risk_inflation is not None:
        params = replace(
            params, risk_inflation=check_number("risk_inflation", risk_inflation, low=0.0)
        )
    if risk_form is not None:
        if risk_form not in RISK_FORMS:
            raise ValueError(f"risk_form must be one of {RISK_FORMS}, got {risk_form!r}")
        params = replace(params, risk_form=risk_form)
    if p.risk_eta is not None:
        if p.risk_eta not in RISK_ETAS:
            raise ValueError(f"risk_eta must be one of {RISK_ETAS}, got {p.risk_eta!r}")
        params = replace(params, risk_eta=p.risk_eta)
    if shield_steps is not None:
        params = replace(params, shield_steps=check_positive_int("shield_steps", shield_steps))
    check_positive_int("planner_every", planner_every)
    if control_weight is not None:
        params = replace(params, control_weight=_pair("control_weight", control_weight))
    if control_limit is not None:
        params = replace(params, control_limit=_pair("control_limit", control_limit))
    if not 0.0 < params.rho < 1.0:
        raise ValueError(f"rho must be in (0, 1), got {params.rho}")
    limits: dict[str, list[float]] = {}
    if params.control_limit is not None:
        limits = {"u_min": [-v for v in params.control_limit], "u_max": list(params.control_limit)}
    plant = AccelUnicycle(sigma=SIGMA, **limits).to(device=device, dtype=dtype)
    nominal_model = AccelUnicycle(**limits).to(device=device, dtype=dtype)
    ellipses = obstacles().to(device=device, dtype=dtype)
    record: dict[str, Any] = {"method": method, "config": config, **asdict(params)}

    planner = None
    if method != "scbf":
        terms = [
            QuadraticGoal(GOAL, weight=2.0, index=(0, 1), terminal_weight=10.0),
            BarrierCost(ellipses, weight=2.0, eps=0.01),
        ]
        if method == "shield_mppi":
            # the discrete-time form of h_e >= 0 (b' >= -k b) over one rollout step
            gamma = min(params.rectify_gain * ROLLOUT_DT, 1.0)
            terms.append(
                DiscreteBarrierCost(
                    ellipses, gamma=gamma, weight=params.shield_weight, steps=params.shield_steps
                )
            )
            record["shield_gamma"] = gamma
        planner = MPPI(
            nominal_model,
            SumCost(*terms),
            horizon=horizon,
            num_samples=num_samples,
            dt=ROLLOUT_DT,
            noise_sigma=noise_sigma * torch.eye(2),
            temperature=0.03,
            control_cost_weight=0.1,
            seed=seed,
            keep_rollouts=min(512, num_samples),
            cost_normalization=cost_normalization,
            zero_noise_samples=zero_noise_samples,
            shift_fill=shift_fill,
        ).to(device=device, dtype=dtype)
        record.update(
            num_samples=num_samples,
            horizon=horizon,
            rollout_dt=ROLLOUT_DT,
            temperature=0.03,
            control_cost_weight=0.1,
            noise_sigma=noise_sigma,
            cost_normalization=cost_normalization,
            planner_every=planner_every,
        )

    safety_filter = None
    extra = None
    if method != "mppi":
        if method == "mppi_rascbf":
            safety_filter, risk = _risk_aware_filter(plant, nominal_model, params)
            record.update(risk)
            window = round(risk["risk_horizon"] / DT)
            margin_of = _margins(safety_filter, risk)

            def extra(traj: Trajectory) -> dict[str, Tensor]:
                return risk_failures(traj.h, margin_of(traj.x[:, :-1]).to(traj.h), window)

        else:
            barriers, scales = _rectified(nominal_model, params, barrier_scale)
            record["barrier_scale"] = scales
            alpha_, beta_ = params.alpha, params.beta
            if params.form == "cbfkit":  # L B + tr/2 <= -a B + b  <=>  L h + tr/2 >= -a h + (a - b)
                beta_ = params.alpha - params.beta
            safety_filter = SafetyFilter(
                plant,
                barriers=barriers,
                mode=Stochastic(beta=beta_),
                alpha=alpha_,
                R=torch.diag(torch.tensor(params.control_weight, dtype=torch.float64)),
            )
        safety_filter = safety_filter.to(device=device, dtype=dtype)
        if method == "shield_mppi":
            # one filter call per control step: the loop's filter feeds its control back
            # into the plan, so the shield does not filter again on replanning steps
            planner = ShieldMPPI(planner, safety_filter, in_loop=True)
            safety_filter = planner.loop_filter

    x0 = torch.tensor(X0, device=device, dtype=dtype).repeat(num_seeds, 1)
    goal_region = Goal(GOAL, 0.25, deadline=STEPS * DT)
    record.update(num_seeds=num_seeds, seed=seed, dt=DT, steps=STEPS, sigma=SIGMA)
    return Scenario(
        name=f"mppi-cbf/{config}/{method}",
        dynamics=plant,
        x0=x0,
        steps=STEPS,
        dt=DT,
        seeds=torch.arange(seed, seed + num_seeds),
        planner=planner,
        nominal=proportional_controller() if method == "scbf" else None,
        safety_filter=safety_filter,
        integrator="euler_maruyama",
        planner_every=planner_every,
        barriers=[ellipses],
        goals=[goal_region],
        metric_goals=[goal_region],
        status_names={int(s): s.name.lower() for s in FilterStatus},
        # the planning call at or before 1 s (2 s / 2 replanning steps by default)
        snapshot_steps=(100 - 100 % planner_every,) if planner is not None else (),
        params=record,
        extra_metrics=extra,
    )


def _rectified(
    model: AccelUnicycle, params: FilterParams, barrier_scale: Any
) -> tuple[list[Barrier], list[float]]:
    """The relative-degree-one barriers (five outputs in all) and the scales ``c_i`` used."""
    k = params.rectify_gain
    if params.form == "cbfkit":
        scales = [0.3] * len(CENTERS)  # B + 0.3 L_f B = 0.3 (L_f B + B / 0.3)
        saturated = Transformed(obstacles(), "exp", rate=0.1)  # 1 - B = 1 - exp(-0.1 b)
        return [rectify(Scaled(saturated, 0.3), model, "exponential", [k])], scales
    # one module for the five ellipses: closed-form derivatives, one pass per call
    scales = _scales(barrier_scale, params)
    return [rectify(Scaled(obstacles(), scales), model, form="exponential", gains=[k])], scales


def _scales(barrier_scale: float | Sequence[float] | None, params: FilterParams) -> list[float]:
    if barrier_scale is None:
        # c_i |grad b_i| k alpha / beta = 1 / margin on the flat sides, |grad b_i| = 2 / min(a_i)
        k, margins = params.rectify_gain, [params.margin] * len(AXES)
        for index, own in (
            (GOAL_WALL, params.goal_wall_margin),
            (BLOCKING, params.blocking_margin),
        ):
            if own is not None:
                margins[index] = own
        return [
            params.beta * min(a) / (2.0 * params.alpha * k * m)
            for a, m in zip(AXES, margins, strict=True)
        ]
    if isinstance(barrier_scale, (int, float)):
        scales = [float(barrier_scale)] * len(CENTERS)
    else:
        scales = [float(v) for v in barrier_scale]
    if len(scales) != len(CENTERS) or not all(v > 0 and math.isfinite(v) for v in scales):
        raise ValueError(
            f"barrier_scale must be a positive number or {len(CENTERS)} positive numbers, "
            f"got {barrier_scale!r}"
        )
    return scales


def operating_states(dtype: torch.dtype = torch.float64, *, max_speed: float = 3.0) -> Tensor:
    """A grid ``[N, 4]`` over where the robot operates: positions in the obstacle field
    ``[-2.5, 5] x [-2, 6.5]`` m, speeds ``[-0.5, max_speed]`` m/s (every 0.5 m/s at most),
    every heading. The risk-aware noise bound ``eta`` is taken over its safe points."""
    max_speed = check_number("max_speed", max_speed, low=0.0, strict=True)
    axes = (
        torch.linspace(-2.5, 5.0, 31, dtype=dtype),
        torch.linspace(-2.0, 6.5, 35, dtype=dtype),
        torch.linspace(-0.5, max_speed, math.ceil((max_speed + 0.5) / 0.5) + 1, dtype=dtype),
        torch.linspace(-math.pi, math.pi, 12, dtype=dtype)[:-1],
    )
    return torch.cartesian_prod(*axes)


def risk_horizon(h0: Tensor, eta: Tensor, rho: float, margin: float) -> float:
    """The risk-aware horizon ``T``: the largest ``T`` for which the start satisfies
    ``h_i(x0) >= Delta_i = sqrt(2 T) eta_i erfinv(1 - rho)`` for every barrier (the bound
    holds only from there), capped where the noise band ``sqrt(2 T) sigma erfinv(1 - rho)``
    reaches the distance ``margin`` (a longer ``T`` asks for a wider berth than the
    passages allow)."""
    z = float(torch.erfinv(torch.tensor(1.0 - rho, dtype=torch.float64)))
    t_start = float(((h0 / (eta * z)) ** 2 / 2).min())
    t_band = (margin / (SIGMA * z)) ** 2 / 2
    return min(t_start, t_band)


def risk_failures(h: Tensor, delta: Tensor, window: int) -> dict[str, Tensor]:
    """Empirical check of the risk-aware bound on the filter's barrier values ``h [B, S, k]``
    with the margins ``delta`` (``[k]``, or ``[B, S, k]``: each step's own margin, for a local
    noise bound).

    A window starts at every step where ``h_i >= delta_i`` for all ``i`` and spans the next
    ``window`` steps (the horizon ``T``); it fails if some ``h_i < 0`` inside it. Windows that
    run past the end are left out.

    Returns (per seed):
        ``risk_failure_from_start`` (bool): the window from step 0 fails;
        ``risk_windows``: the number of windows; ``risk_window_failures``: how many fail;
        ``risk_failure_rate``: their ratio (nan without windows).
    """
    B, S, _ = h.shape
    if delta.dim() == 3 and delta.shape != h.shape:
        raise ValueError(
            f"delta must be [k] or shaped like h {tuple(h.shape)}, got {tuple(delta.shape)}"
        )
    unsafe = (h < 0).any(-1).to(torch.int64)  # [B, S]
    eligible = (h >= delta).all(-1)
    csum = torch.cat([unsafe.new_zeros(B, 1), unsafe.cumsum(-1)], -1)  # [B, S+1]
    starts = torch.arange(max(S - window, 0), device=h.device)
    hits = (csum[:, starts + window + 1] - csum[:, starts]) > 0  # unsafe in [j, j + window]
    valid = eligible[:, : starts.numel()]
    windows = valid.sum(-1)
    failures = (hits & valid).sum(-1)
    first = (csum[:, min(window + 1, S)] > 0) & eligible[:, 0]
    rate = failures.to(h.dtype) / windows.to(h.dtype)
    return {
        "risk_failure_from_start": first,
        "risk_windows": windows,
        "risk_window_failures": failures,
        "risk_failure_rate": torch.where(windows > 0, rate, torch.full_like(rate, math.nan)),
    }


def _risk_aware_filter(
    plant: AccelUnicycle, model: AccelUnicycle, params: FilterParams
) -> tuple[SafetyFilter, dict[str, Any]]:
    """The risk-aware filter on ``h_i = L_f r_i + k r_i`` with ``r_i`` the ellipse radius
    form (bounded gradient), or on its smooth minimum with ``k r_i`` (``risk_form``);
    ``eta_i`` over :func:`operating_states`, ``T`` by :func:`risk_horizon`."""
    k = params.rectify_gain
    f64 = copy.deepcopy(plant).double()
    # |q| - 1: a bounded gradient
    inflation = [params.risk_inflation] * len(AXES)
    inflation[GOAL_WALL] += params.risk_goal_wall_inflation
    radius = Transformed(obstacles(inflation=inflation), "radius")
    barrier = rectify(radius, model, form="exponential", gains=[k])
    if params.risk_form == "inside":
        barrier = Intersection(
            barrier,
            Scaled(radius, k),
            smooth=True,
            temperature=params.risk_temperature,
            elementwise=True,
        )
    barrier64 = copy.deepcopy(barrier).double()
    x0 = torch.tensor(X0, dtype=torch.float64)
    with torch.enable_grad():
        eta = noise_bound(barrier64, f64, operating_states(max_speed=params.risk_max_speed))
    h0 = barrier64(x0).detach()
    rho = params.rho
    if params.risk_budget is not None:
        T = params.risk_horizon
        rho = params.risk_budget * T / (STEPS * DT)
    else:
        T = params.risk_horizon or risk_horizon(h0, eta, rho, params.margin)
        if not DT <= T:  # computed from the margin: a window shorter than a step is empty
            raise ValueError(
                f"the risk-aware horizon T = {T:.3g} s the margin {params.margin:g} m sets is "
                f"shorter than a step ({DT:g} s): widen margin or give risk_horizon"
            )
    local = params.risk_eta == "local"
    safety_filter = SafetyFilter(
        plant,
        barriers=barrier,
        mode=RiskAware(rho=rho, horizon=T, eta="local" if local else eta),
        R=torch.diag(torch.tensor(params.control_weight, dtype=torch.float64)),
    )
    info = {"rho": rho, "risk_horizon": T, "eta": eta.tolist(), "h0": h0.tolist()}
    if local:  # the margin at the start (at rest, pointing at the goal)
        mode = safety_filter.condition
        info["delta"] = mode.margin_at(barrier64, f64, x0.unsqueeze(0))[0].tolist()
    else:
        info["delta"] = safety_filter.cbf_margin.tolist()
    return safety_filter, info


def _margins(safety_filter: SafetyFilter, risk: Mapping[str, Any]):
    """``x [B, S, n] -> Delta [B, S, k]`` (or ``[k]``): the risk-aware margins the filter
    used at those states, for :func:`risk_failures`."""
    mode = safety_filter.condition
    if not mode.local:
        delta = torch.tensor(risk["delta"])
        return lambda x: delta
    (barrier,) = safety_filter.barriers

    def margin_of(x: Tensor) -> Tensor:
        with torch.no_grad():
            return mode.margin_at(barrier, safety_filter.dynamics, x)

    return margin_of


def _pair(name: str, value: float | Sequence[float]) -> tuple[float, float]:
    """A positive number for both controls ``(a, omega)``, or one per control."""
    pair = [float(value)] * 2 if isinstance(value, (int, float)) else [float(v) for v in value]
    if len(pair) != 2 or not all(v > 0 and math.isfinite(v) for v in pair):
        raise ValueError(f"{name} must be a positive number or two positive numbers, got {value!r}")
    return (pair[0], pair[1])


VIEW = {"xlim": (-2.5, 5.0), "ylim": (-2.0, 6.5)}


def figures(
    trajectories: Mapping[str, Trajectory],
    scenario: Scenario,
    out: Path,
    *,
    title: str,
    gif: bool = True,
    first_seed: int = 0,
) -> list[Path]:
    """Every method's paths, the closest-ellipse bands, the rollouts at 2 s and the
    animation (``mppi_cbf_{config}_*``)."""
    config = scenario.params.get("config", "default")
    return standard_figures(
        trajectories, scenario, out, stem=f"mppi_cbf_{config}", title=title, gif=gif,
        first_seed=first_seed, view=VIEW, compare=True,
    )  # fmt: skip


def _omega_weight(w: float) -> tuple[float, float]:
    return (1.0, float(w))


_NO_PLANNER = ("scbf",)
_NO_FILTER = ("mppi",)
_SCALED = ("mppi", "mppi_rascbf")  # no stochastic CBF with scales, alpha and beta

ENTRY = register(
    ScenarioEntry(
        name="mppi-cbf",
        build=build,
        params=MppiCbfParams,
        description=(
            "Scenario B: MPPI, stochastic CBFs and their combinations on a noisy unicycle "
            "among five ellipses, every method over one batch of seeds."
        ),
        # the stochastic CBF's free parameters (the risk-aware filter has neither alpha nor
        # beta nor the scales) and MPPI's noise; the margin is left out: it sets the scales
        # that barrier_scale searches directly
        search_space=(
            Dimension("rectify_gain", "float", 1.0, 100.0, log=True, skip_variants=_NO_FILTER),
            Dimension(
                "barrier_scale",
                "float",
                1e-3,
                1.0,
                log=True,
                skip_variants=_SCALED,
                skip_when=(("config", "cbfkit"),),  # its form fixes the scales
            ),
            Dimension(
                "control_weight_omega",
                "float",
                1e-4,
                1.0,
                log=True,
                argument="control_weight",
                to_argument=_omega_weight,
                skip_variants=_NO_FILTER,
            ),  # fmt: skip
            Dimension("noise_sigma", "float", 1.0, 16.0, log=True, skip_variants=_NO_PLANNER),
            Dimension("alpha", "float", 0.5, 100.0, log=True, skip_variants=_SCALED),
            Dimension("beta", "float", 0.05, 2.0, skip_variants=_SCALED),
        ),
        columns=(
            Column("collisions [95% CI]", "collision"),
            Column("goal by 5 s [95% CI]", "goal_reached"),
            Column("t_goal [s]", "goal0_time", "mean"),
            Column("min b", "min_h", "min"),
            Column("relaxed [%]", "steps_relaxed", "mean", "{:.1f}", 100.0 / STEPS),
            Column("fallback [%]", "steps_fallback", "mean", "{:.1f}", 100.0 / STEPS),
        ),
        figures=figures,
        variant="method",
        choices={"method": METHODS, "config": CONFIGS},
        options={"samples": "num_samples", "horizon": "horizon", "config": "config"},
        units={
            "min_h": "ellipse value b_i (dimensionless; < 0 inside)",
            "goal0_time": "s",
            "goal0_final_distance": "m",
            "seconds": "s",
        },
        num_seeds=32,
        demo={"num_seeds": 8, "num_samples": 1000, "horizon": 80, "config": "default"},
        env=EnvEntry(
            id="torchcbf/UnicycleEllipses-v0",
            entry_point="torchcbf.envs.unicycle_ellipses:UnicycleEllipsesEnv",
            vector_entry_point="torchcbf.envs.unicycle_ellipses:UnicycleEllipsesVectorEnv",
            max_episode_steps=STEPS,
        ),
    )
)
