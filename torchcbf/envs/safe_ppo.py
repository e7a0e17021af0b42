"""PPO on a torchcbf TorchRL environment, four ways (:data:`METHODS`), for safe-RL comparisons
(``scripts/safe_rl.py``, docs/safe_rl.md):

- ``"ppo"``: PPO on the reward alone (the cost is not seen);
- ``"ppo_lagrangian"``: PPO-Lagrangian: a cost critic on the ``"cost"`` entry (1 at a step
  that ends inside an obstacle), the advantage ``(A_r - lambda A_c) / (1 + lambda)``, and the
  multiplier ``lambda <- max(0, lambda + lr_lambda (J_c - cost_limit))`` after every batch,
  ``J_c`` the batch's cost per step times the episode length (the cost of an episode at the
  batch's rate);
- ``"ppo_shield"``: PPO on the environment wrapped in a
  :class:`~torchcbf.envs.filter_transform.SafetyFilterTransform` (the filter as a shield),
  the reward it learns from lowered by ``shield_penalty`` times the squared correction of
  the sampled action by the shield (scaled by the action bounds): the shield's penalty for
  an unsafe action, so the policy's own action carries the learning signal where the
  shield would otherwise take over;
- ``"ppo_filter_layer"``: the policy's mean is a
  :class:`~torchcbf.envs.filter_policy.FilteredPolicy` (the QP layer last), so PPO's gradient
  passes through the QP, plus ``intervention_weight`` times the squared correction of the
  network's action by the layer (scaled by the action bounds; its gradient also passes the
  QP), on the shielded environment (the sampled exploration noise is filtered too).

The policy is a Gaussian, mean ``tanh(MLP(features))`` times the action bounds (or that
through the filter layer; the last layer starts near zero) with a state-independent standard
deviation; the critics are MLPs; the features are the observation with a heading replaced by
its cosine and sine. Every method sees the same reward, by default shaped
(:func:`scenario_shaping`). Every run is a pure function of its seed (torch's global RNG is
forked and restored).
"""

from __future__ import annotations

import copy
import inspect
import math
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass
from typing import Any

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModule, TensorDictSequential
from torch import Tensor, nn
from torchrl.envs import Compose, EnvBase, RewardSum, Transform, TransformedEnv
from torchrl.envs.utils import ExplorationType, set_exploration_type, step_mdp
from torchrl.modules import IndependentNormal, ProbabilisticActor, ValueOperator
from torchrl.objectives.value import GAE

from torchcbf._checks import check_bool, check_int, check_number, check_positive_int
from torchcbf.barriers import Ellipse, HalfSpace, rectify
from torchcbf.barriers._params import take
from torchcbf.envs.filter_policy import FilteredPolicy
from torchcbf.envs.filter_transform import SafetyFilterTransform, barrier_values
from torchcbf.envs.shaping import GeodesicProgress, geodesic_distance
from torchcbf.envs.torchrl import TorchRLEnv, vector_env_class
from torchcbf.filters import SafetyFilter
from torchcbf.scenarios import single_integrator_reach_avoid as scenario_a
from torchcbf.scenarios import unicycle_mppi_cbf as scenario_b

__all__ = [
    "METHODS",
    "PPOConfig",
    "RunResult",
    "SCENARIO_KWARGS",
    "SUMMARY_FIELDS",
    "config_dict",
    "evaluate",
    "make_env",
    "mean_ci",
    "make_policy",
    "scenario_filter",
    "scenario_shaping",
    "summarize",
    "train",
]

SCENARIO_KWARGS: dict[str, dict[str, Any]] = {
    "torchcbf/UnicycleEllipses-v0": {
        "sigma": 0.05,
        "start_noise": 0.1,
        "terminate_on_collision": False,
        "collision_penalty": 0.0,
    },
}
"""The environment options of a comparison when :class:`PPOConfig` is given none: scenario B
with process noise, episodes that go on through collisions (counted as costs)."""

# arguments of a TorchVectorEnv that TorchRLEnv sets itself
_NOT_OPTIONS = frozenset({"num_envs", "return_tensors", "autoreset_mode", "render_mode"})

METHODS = ("ppo", "ppo_lagrangian", "ppo_shield", "ppo_filter_layer")
SHIELDED = ("ppo_shield", "ppo_filter_layer")


@dataclass(frozen=True)
class PPOConfig:
    """Settings of one PPO run (the same for every method of a comparison).

    Attributes:
        env_id: the torchcbf environment id.
        env_kwargs: the scenario's options as ``((name, value), ...)`` (a dict is kept as
            such pairs); ``None``: :data:`SCENARIO_KWARGS` of ``env_id`` (none for other
            ids), resolved in :attr:`env_options`.
        num_envs: environments stepped as one batch while collecting.
        rollout_steps: steps per environment per batch (``num_envs * rollout_steps`` frames).
        total_frames: the frame budget.
        epochs, minibatch_size: PPO epochs over each batch and the minibatch size.
        lr: Adam's step size (policy and critics).
        gamma, lmbda: discount and GAE's lambda.
        clip: PPO's ratio clip.
        entropy_coef: entropy bonus.
        init_std: the policy's initial standard deviation, a fraction of the bounds.
        hidden: width of the two hidden layers.
        cost_limit, lagrangian_lr: PPO-Lagrangian's bound on the cost of an episode (steps
            inside an obstacle) and the multiplier's step.
        intervention_weight: weight of the filter layer's correction penalty.
        shield_penalty: weight of the shield's correction in the reward ``"ppo_shield"``
            learns from (the reported returns are the environment's).
        eval_episodes: deterministic evaluation episodes (one per environment).
        shaping: the progress reward measured along the shortest collision-free path
            (:func:`scenario_shaping`) instead of the straight line.
        filter_margin: the margin of :func:`scenario_filter` (``None``: its default).
    """

    env_id: str = "torchcbf/UnicycleEllipses-v0"
    env_kwargs: tuple[tuple[str, Any], ...] | dict[str, Any] | None = None
    num_envs: int = 256
    rollout_steps: int = 128
    total_frames: int = 2_000_000
    epochs: int = 4
    minibatch_size: int = 4096
    lr: float = 3e-4
    gamma: float = 0.995
    lmbda: float = 0.95
    clip: float = 0.2
    entropy_coef: float = 0.0
    init_std: float = 0.5
    hidden: int = 64
    cost_limit: float = 0.0
    lagrangian_lr: float = 0.05
    intervention_weight: float = 1.0
    shield_penalty: float = 0.01
    eval_episodes: int = 256
    shaping: bool = True
    filter_margin: float | None = None

    def __post_init__(self) -> None:
        cls = vector_env_class(self.env_id)
        kwargs = self.env_kwargs
        if kwargs is not None:
            try:
                kwargs = tuple(dict(kwargs).items())  # hashable, as the frozen config is
            except (TypeError, ValueError):
                raise TypeError(
                    f"env_kwargs must be ((name, value), ...) or a dict, got {kwargs!r}"
                ) from None
            object.__setattr__(self, "env_kwargs", kwargs)
        accepted = inspect.signature(cls).parameters
        unknown = sorted(k for k in self.env_options if k not in accepted or k in _NOT_OPTIONS)
        if unknown:
            raise ValueError(
                f"env_kwargs {unknown} are not options of {self.env_id!r} "
                f"({cls.__name__} takes {sorted(set(accepted) - _NOT_OPTIONS)})"
            )
        for name in (
            "num_envs",
            "rollout_steps",
            "total_frames",
            "epochs",
            "minibatch_size",
            "hidden",
            "eval_episodes",
        ):
            check_positive_int(name, getattr(self, name))
        for name in ("lr", "clip", "init_std"):
            check_number(name, getattr(self, name), low=0.0, strict=True)
        for name in (
            "entropy_coef",
            "cost_limit",
            "lagrangian_lr",
            "intervention_weight",
            "shield_penalty",
        ):
            check_number(name, getattr(self, name), low=0.0)
        if self.filter_margin is not None:
            check_number("filter_margin", self.filter_margin, low=0.0)
        for name in ("gamma", "lmbda"):
            if not 0.0 <= check_number(name, getattr(self, name)) <= 1.0:
                raise ValueError(f"{name} must lie in [0, 1], got {getattr(self, name)}")
        check_bool("shaping", self.shaping)

    @property
    def env_options(self) -> dict[str, Any]:
        """The options the environment is made with: ``env_kwargs``, or ``env_id``'s
        :data:`SCENARIO_KWARGS` where it is ``None``."""
        if self.env_kwargs is None:
            return dict(SCENARIO_KWARGS.get(self.env_id, {}))
        return dict(self.env_kwargs)


@dataclass
class RunResult:
    """One run: ``curve`` has one row per batch (frames, mean return, goal rate and
    collisions of the episodes that ended in it, the multiplier); ``train`` and ``eval``
    hold totals and rates."""

    method: str
    seed: int
    curve: list[dict[str, float]]
    train: dict[str, float]
    eval: dict[str, float]
    wall_time: float
    frames_per_second: float


SPEED_BOUND = 2.0
"""``|v| <= SPEED_BOUND`` (m/s): a barrier of :func:`scenario_filter` on scenario B."""


MARGIN_PER_SIGMA = 3.0
"""The filter's clearance around scenario B's ellipses per unit of process noise: ``margin =
MARGIN_PER_SIGMA * sigma`` metres (``sigma`` in m/sqrt(s): the spread of the noise over
9 s, or three standard deviations of its spread over 1 s)."""


def scenario_filter(env: TorchRLEnv, *, margin: float | None = None) -> SafetyFilter:
    """A safety filter for a torchcbf environment, on the environment's plant.

    ``torchcbf/UnicycleEllipses-v0``: the exponential CBFs ``L_f b_i + k b_i`` of scenario B's
    ellipses, each semi-axis lengthened by ``margin`` (m; default
    ``MARGIN_PER_SIGMA * sigma``, 0 for the deterministic plant), with
    ``k = a_max / SPEED_BOUND`` and the speed bound ``|v| <= SPEED_BOUND``, ``alpha = 30``,
    ``R = diag(1, 1e-3)``: with ``|a| <= a_max`` the braking the condition asks for (about
    ``k |v|``) stays within the bound, so the QP stays feasible (scenario B's own gain
    ``k = 20`` needs ``|a|`` up to 40 m/s^2). Without noise it keeps the robot out of the
    ellipses; with process noise the margin is the room the noise has before the filter
    pulls the robot back (docs/safe_rl.md measures it).
    ``torchcbf/ReachAvoid-v0``: the obstacle disc, ``alpha = 5`` (exactly safe for the
    single integrator's step of 0.1 s, since ``alpha dt <= 1``).
    """
    vec = env.vector_env
    kw = {"device": vec.device, "dtype": vec.dtype}
    name = type(vec).__name__
    if name == "UnicycleEllipsesVectorEnv":
        if margin is None:
            margin = MARGIN_PER_SIGMA * float(vec.sigma)
        if not (isinstance(margin, (int, float)) and 0 <= margin < math.inf):
            raise ValueError(f"margin must be a number >= 0, got {margin!r}")
        axes = torch.tensor(scenario_b.AXES) + float(margin)
        inflated = Ellipse(torch.tensor(scenario_b.CENTERS), axes, index=(0, 1))
        gain = float(vec.dynamics.u_max[0]) / SPEED_BOUND
        ellipses = rectify(inflated, vec.dynamics, form="exponential", gains=[gain])
        speed = HalfSpace([[1.0], [-1.0]], [SPEED_BOUND, SPEED_BOUND], index=(2,), state_dim=4)
        weight = torch.tensor([1.0, 1e-3], dtype=torch.float64)
        return SafetyFilter(
            vec.dynamics, barriers=[ellipses, speed], alpha=30.0, R=torch.diag(weight)
        ).to(**kw)
    if name == "ReachAvoidVectorEnv":
        return SafetyFilter(vec.dynamics, barriers=list(vec.barriers), alpha=5.0).to(**kw)
    raise ValueError(f"no scenario filter for {name}; build a SafetyFilter on env.dynamics")


def _free(env: TorchRLEnv) -> Callable[[Tensor], Tensor]:
    """Points ``[..., 2]`` -> outside every obstacle of ``env`` (the position is the first two
    state entries, the rest zero)."""
    # a copy: the points' dtype may differ from the environment's, whose barriers stay as
    # they are
    barriers, n = copy.deepcopy(env.barriers), env.dynamics.state_dim

    def free(p: Tensor) -> Tensor:
        x = torch.nn.functional.pad(p, (0, n - 2))
        return (barrier_values(barriers.to(p.dtype), x) >= 0).all(-1)

    return free


SHAPING_CLEARANCE = 0.2
"""Clearance (m) of the shortest paths of scenario B's shaping (0.3 m in scenario A)."""


def scenario_shaping(env: TorchRLEnv) -> GeodesicProgress:
    """The environment's reward with the progress measured along the shortest
    collision-free path to the current goal (:class:`~torchcbf.envs.shaping.GeodesicProgress`)
    instead of the straight line, which crosses an obstacle in both scenarios. The paths
    keep a clearance from the obstacles, and the potential grows inside it (a learner is paid
    for keeping away).

    ``torchcbf/UnicycleEllipses-v0``: one goal; ``torchcbf/ReachAvoid-v0``: the three goals,
    the current one the first not yet visited (the observation's flags).
    """
    vec = env.vector_env
    name = type(vec).__name__
    free = _free(env)
    if name == "UnicycleEllipsesVectorEnv":
        field = geodesic_distance(
            free, scenario_b.GOAL, low=(-3.0, -3.0), high=(6.0, 8.0), clearance=SHAPING_CLEARANCE
        )
        return GeodesicProgress(field, scenario_b.GOAL).to(vec.device)
    if name == "ReachAvoidVectorEnv":
        goals = [g for g, _, _ in scenario_a.GOALS]
        fields = [
            geodesic_distance(
                free, g, low=(-2.0, -2.0), high=(9.0, 11.0), spacing=0.1, clearance=0.3
            )
            for g in goals
        ]

        def target(observation: Tensor) -> Tensor:
            return torch.argmin(observation[..., 3:6].to(torch.int8), dim=-1)

        return GeodesicProgress(fields, goals, target_fn=target).to(vec.device)
    raise ValueError(f"no reward shaping for {name}")


def make_env(config: PPOConfig, method: str, *, num_envs: int, seed: int) -> TransformedEnv:
    """The environment of ``method``: shielded for :data:`SHIELDED`, with the episode return
    summed in ``"episode_reward"``."""
    _check_method(method)
    base = TorchRLEnv(config.env_id, num_envs, seed=seed, **config.env_options)
    transforms: list[Transform] = [RewardSum()]
    if config.shaping:
        transforms.insert(0, scenario_shaping(base))
    if method in SHIELDED:
        transforms.insert(
            0, SafetyFilterTransform(scenario_filter(base, margin=config.filter_margin))
        )
    return TransformedEnv(base, Compose(*transforms))


class _Features(nn.Module):
    """The observation with its angle entries replaced by their cosine and sine (a heading
    wrapped to [-pi, pi) jumps at pi; its cosine and sine do not)."""

    def __init__(self, angles: tuple[int, ...] = ()) -> None:
        super().__init__()
        self.angles = angles

    def forward(self, observation: Tensor) -> Tensor:
        if not self.angles:
            return observation
        keep = [i for i in range(observation.shape[-1]) if i not in self.angles]
        angle = take(observation, self.angles)
        kept = [take(observation, keep)] if keep else []
        return torch.cat([*kept, angle.cos(), angle.sin()], dim=-1)

    def size(self, obs_dim: int) -> int:
        """Entries of the features of an observation of ``obs_dim`` entries."""
        return obs_dim + len(self.angles)


def _features(env: EnvBase) -> _Features:
    base = getattr(env, "base_env", env)
    vec = getattr(base, "vector_env", None)
    if type(vec).__name__ == "UnicycleEllipsesVectorEnv":
        return _Features((3,))  # the heading
    return _Features()


class _Mean(nn.Module):
    """``tanh(MLP(features(observation)))`` times the action bounds."""

    def __init__(self, features: _Features, obs_dim: int, bound: Tensor, hidden: int) -> None:
        super().__init__()
        self.features = features
        self.net = _mlp(features.size(obs_dim), bound.shape[-1], hidden)
        with torch.no_grad():  # start near the zero action: no full-throttle first policy
            self.net[-1].weight.mul_(0.01)
            self.net[-1].bias.zero_()
        self.register_buffer("bound", bound)

    def forward(self, observation: Tensor) -> Tensor:
        return torch.tanh(self.net(self.features(observation))) * self.bound


class _Scale(nn.Module):
    """A state-independent standard deviation, a learned fraction of the bounds."""

    def __init__(self, bound: Tensor, init: float) -> None:
        super().__init__()
        self.log_std = nn.Parameter(torch.full_like(bound, math.log(init)))
        self.register_buffer("bound", bound)

    def forward(self, loc: Tensor) -> Tensor:
        return (self.log_std.exp() * self.bound).expand_as(loc)


class _Unfiltered(nn.Module):
    """The mean as both the action's mean and the nominal one (no filter layer)."""

    def __init__(self, mean: nn.Module) -> None:
        super().__init__()
        self.mean = mean

    def forward(self, observation: Tensor) -> tuple[Tensor, Tensor]:
        loc = self.mean(observation)
        return loc, loc


def _mlp(n_in: int, n_out: int, hidden: int) -> nn.Sequential:
    return nn.Sequential(
        nn.Linear(n_in, hidden), nn.Tanh(), nn.Linear(hidden, hidden), nn.Tanh(),
        nn.Linear(hidden, n_out),
    )  # fmt: skip


def make_policy(
    env: EnvBase, config: PPOConfig, *, safety_filter: nn.Module | None = None
) -> ProbabilisticActor:
    """The Gaussian policy (writes ``"loc"``, ``"loc_nominal"``, ``"scale"``, ``"action"``
    and ``"action_log_prob"``); with ``safety_filter`` its mean is a
    :class:`FilteredPolicy` (``"loc"`` filtered, ``"loc_nominal"`` the network's)."""
    spec = env.full_action_spec["action"]
    bound = spec.space.high[0].clone()
    obs_dim = env.observation_spec["observation"].shape[-1]
    mean = _Mean(_features(env), obs_dim, bound, config.hidden)
    if safety_filter is None:
        head = TensorDictModule(
            _Unfiltered(mean), in_keys=["observation"], out_keys=["loc", "loc_nominal"]
        )
    else:
        state_fn = getattr(env, "state_from_observation", None)
        layer = FilteredPolicy(mean, safety_filter, state_fn=state_fn)
        head = TensorDictModule(
            layer, in_keys=["observation"], out_keys=["loc", "loc_nominal", "policy_status"]
        )
    module = TensorDictSequential(
        head, TensorDictModule(_Scale(bound, config.init_std), ["loc"], ["scale"])
    )
    return ProbabilisticActor(
        module,
        in_keys=["loc", "scale"],
        distribution_class=IndependentNormal,
        return_log_prob=True,
        spec=spec,
    )


def _critic(env: EnvBase, hidden: int, key: str) -> ValueOperator:
    obs_dim = env.observation_spec["observation"].shape[-1]
    features = _features(env)
    net = nn.Sequential(features, _mlp(features.size(obs_dim), 1, hidden))
    return ValueOperator(net, in_keys=["observation"], out_keys=[key])


def _check_method(method: str) -> None:
    if method not in METHODS:
        raise ValueError(f"method must be one of {METHODS}, got {method!r}")


def _collect(
    env: EnvBase, policy: nn.Module, td: TensorDictBase, steps: int
) -> tuple[TensorDictBase, TensorDictBase]:
    """``steps`` steps of every environment: the batch ``[N, steps]`` and the next input."""
    frames = []
    for _ in range(steps):
        policy(td)
        out, td = env.step_and_maybe_reset(td)
        frames.append(out)
    return torch.stack(frames, dim=1).contiguous(), td


#: a run's training environments draw from seed * _SEED_STRIDE on, its held-out evaluation
#: from _EVAL_SEEDS + seed * _SEED_STRIDE
_SEED_STRIDE, _EVAL_SEEDS = 1_000_003, 10**9


def _episode_stats(batch: TensorDictBase) -> dict[str, float]:
    done = batch["next", "done"].squeeze(-1)
    episodes = int(done.sum())
    # steps inside an obstacle count in every batch, whether or not an episode ended in it
    collisions = float(batch["next", "cost"].sum())
    if episodes == 0:
        return {"episodes": 0.0, "return": math.nan, "goal_rate": math.nan,
                "collisions": collisions}  # fmt: skip
    ret = batch["next", "episode_reward"].squeeze(-1)[done]
    goals = batch["next", "success"].squeeze(-1)[done]
    return {
        "episodes": float(episodes),
        "return": float(ret.mean()),
        "goal_rate": float(goals.float().mean()),
        "collisions": collisions,
    }


def train(
    method: str,
    config: PPOConfig,
    *,
    seed: int,
    progress: Callable[[dict[str, float]], None] | None = None,
) -> RunResult:
    """Train ``method`` (:data:`METHODS`) under ``config`` from ``seed``; evaluate the
    deterministic policy on ``config.eval_episodes`` held-out episodes."""
    _check_method(method)
    top = (2**32 - _EVAL_SEEDS - config.eval_episodes) // _SEED_STRIDE  # 32-bit noise streams
    if check_int("seed", seed, low=0) > top:
        raise ValueError(f"seed must lie in [0, {top}] (the environments' seeds derive from it)")
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(seed)
        return _train(method, config, seed, progress)


def _train(
    method: str,
    config: PPOConfig,
    seed: int,
    progress: Callable[[dict[str, float]], None] | None,
) -> RunResult:
    env = make_env(config, method, num_envs=config.num_envs, seed=seed * _SEED_STRIDE)
    layer_filter = None
    if method == "ppo_filter_layer":
        layer_filter = scenario_filter(env.base_env, margin=config.filter_margin)
    policy = make_policy(env, config, safety_filter=layer_filter)
    critic = _critic(env, config.hidden, "state_value")
    gae = GAE(gamma=config.gamma, lmbda=config.lmbda, value_network=critic, average_gae=False)
    params = list(policy.parameters()) + list(critic.parameters())
    cost_critic = cost_gae = None
    if method == "ppo_lagrangian":
        cost_critic = _critic(env, config.hidden, "cost_value")
        cost_gae = GAE(
            gamma=config.gamma, lmbda=config.lmbda, value_network=cost_critic, average_gae=False
        )
        cost_gae.set_keys(
            reward="cost",
            value="cost_value",
            advantage="cost_advantage",
            value_target="cost_value_target",
        )
        params += list(cost_critic.parameters())
    optim = torch.optim.Adam(params, lr=config.lr)
    bound = env.full_action_spec["action"].space.high[0]
    lagrange = 0.0
    frames_per_batch = config.num_envs * config.rollout_steps
    episode_steps = env.base_env.vector_env.max_episode_steps or config.rollout_steps
    batches = max(1, config.total_frames // frames_per_batch)
    curve: list[dict[str, float]] = []
    totals = {"episodes": 0.0, "goals": 0.0, "collisions": 0.0, "interventions": 0.0}
    start = time.perf_counter()
    td = env.reset()
    for index in range(batches):
        with torch.no_grad(), set_exploration_type(ExplorationType.RANDOM):
            batch, td = _collect(env, policy, td, config.rollout_steps)
            if method == "ppo_shield" and config.shield_penalty:
                _penalize_shield(batch, bound, config.shield_penalty)
            gae(batch)
            if cost_gae is not None:
                cost_gae(batch)
        stats = _episode_stats(batch)
        totals["episodes"] += stats["episodes"]
        totals["collisions"] += stats["collisions"]
        if stats["episodes"]:
            totals["goals"] += stats["goal_rate"] * stats["episodes"]
        if method in SHIELDED:
            totals["interventions"] += float(batch["next", "filter_intervention"].sum())
        if method == "ppo_lagrangian":
            episode_cost = stats["collisions"] / frames_per_batch * episode_steps
            step = config.lagrangian_lr * (episode_cost - config.cost_limit)
            lagrange = max(0.0, lagrange + step)
        _update(batch.reshape(-1), policy, critic, cost_critic, optim, config, lagrange, bound)
        row = {"frames": float((index + 1) * frames_per_batch), **stats, "lagrange": lagrange}
        curve.append(row)
        if progress is not None:
            progress(row)
    wall = time.perf_counter() - start
    frames = batches * frames_per_batch
    train_stats = {
        "frames": float(frames),
        "episodes": totals["episodes"],
        "collisions": totals["collisions"],
        "goal_rate": totals["goals"] / max(totals["episodes"], 1.0),
        "intervention_rate": totals["interventions"] / frames,
    }
    eval_env = make_env(
        config, method, num_envs=config.eval_episodes, seed=_EVAL_SEEDS + seed * _SEED_STRIDE
    )
    evaluation = evaluate(eval_env, policy)
    return RunResult(method, seed, curve, train_stats, evaluation, wall, frames / wall)


def _penalize_shield(batch: TensorDictBase, bound: Tensor, weight: float) -> None:
    """Lower ``("next", "reward")`` of ``batch`` by ``weight`` times the squared correction of
    each action by the shield, scaled by the action bounds (``"episode_reward"`` keeps the
    environment's return)."""
    nxt = batch["next"]
    change = (nxt["action_nominal"] - nxt["action_filtered"]) / bound
    penalty = weight * change.square().sum(-1, keepdim=True)
    nxt.set("reward", nxt["reward"] - penalty.to(nxt["reward"].dtype))


def _update(
    data: TensorDictBase,
    policy: ProbabilisticActor,
    critic: ValueOperator,
    cost_critic: ValueOperator | None,
    optim: torch.optim.Optimizer,
    config: PPOConfig,
    lagrange: float,
    bound: Tensor,
) -> None:
    """PPO's clipped update over ``config.epochs`` passes of shuffled minibatches."""
    n = data.shape[0]
    advantage = data["advantage"]
    if cost_critic is not None:
        advantage = (advantage - lagrange * data["cost_advantage"]) / (1.0 + lagrange)
    keys = ["observation", "action", "action_log_prob", "value_target"]
    if cost_critic is not None:
        keys.append("cost_value_target")
    data = data.select(*keys).set("_adv", advantage)
    for _ in range(config.epochs):
        order = torch.randperm(n)
        for chunk in order.split(config.minibatch_size):
            sub = data[chunk]
            adv = sub["_adv"].squeeze(-1)
            # one frame (a batch of B * T = 1 mod the minibatch size): no spread to divide by
            spread = adv.std() if adv.numel() > 1 else adv.new_zeros(())
            adv = (adv - adv.mean()) / (spread + 1e-8)
            dist = policy.get_dist(sub)
            log_prob = dist.log_prob(sub["action"])
            ratio = (log_prob - sub["action_log_prob"]).exp()
            gain = torch.minimum(ratio * adv, ratio.clamp(1 - config.clip, 1 + config.clip) * adv)
            loss = -gain.mean() - config.entropy_coef * dist.entropy().mean()
            value = critic(sub.select("observation"))["state_value"]
            loss = loss + 0.5 * (value - sub["value_target"]).square().mean()
            if cost_critic is not None:
                cost = cost_critic(sub.select("observation"))["cost_value"]
                loss = loss + 0.5 * (cost - sub["cost_value_target"]).square().mean()
            if config.intervention_weight and "policy_status" in sub.keys():
                correction = (sub["loc"] - sub["loc_nominal"]) / bound
                loss = loss + config.intervention_weight * correction.square().sum(-1).mean()
            optim.zero_grad()
            loss.backward()
            nn.utils.clip_grad_norm_([p for g in optim.param_groups for p in g["params"]], 0.5)
            optim.step()


def evaluate(
    env: EnvBase, policy: nn.Module, *, intervention_tol: float = 1e-4, check_every: int = 25
) -> dict[str, float]:
    """One deterministic episode per environment of ``env`` (from its reset): mean return,
    goal rate, collisions, and the rates of steps where the shield (``"filter_intervention"``)
    or the policy's own filter layer (``"loc"`` differs from ``"loc_nominal"``) changed the
    action."""
    n = env.batch_size[0]
    device = env.device
    running = torch.ones(n, dtype=torch.bool, device=device)
    ret = torch.zeros(n, device=device)
    goals = torch.zeros(n, dtype=torch.bool, device=device)
    collisions = torch.zeros(n, device=device)
    zero = torch.zeros((), device=device)
    shield, layer, steps = zero.clone(), zero.clone(), zero.clone()
    index = 0
    with torch.no_grad(), set_exploration_type(ExplorationType.DETERMINISTIC):
        td = env.reset()
        # the totals stay on the device; whether any episode runs is read every few steps
        while index % check_every or bool(running.any()):
            policy(td)
            out = env.step(td)
            nxt = out["next"]
            alive = running.to(ret.dtype)
            ret += nxt["reward"].squeeze(-1).to(ret.dtype) * alive
            goals |= nxt["success"].squeeze(-1) & running
            collisions += nxt["cost"].squeeze(-1).to(ret.dtype) * alive
            steps += alive.sum()
            if "filter_intervention" in nxt.keys():
                shield += (nxt["filter_intervention"].squeeze(-1) & running).sum()
            if "loc_nominal" in out.keys():  # a policy with a filter layer
                change = (out["loc"] - out["loc_nominal"]).abs().amax(-1)
                layer += ((change > intervention_tol) & running).sum()
            running = running & ~nxt["done"].squeeze(-1)
            td = step_mdp(out)
            index += 1
    total = float(steps)
    return {
        "episodes": float(n),
        "return": float(ret.mean()),
        "goal_rate": float(goals.float().mean()),
        "collisions": float((collisions > 0).sum()),
        "shield_intervention_rate": float(shield) / total,
        "layer_intervention_rate": float(layer) / total,
        "steps": total,
    }


def config_dict(config: PPOConfig) -> dict[str, Any]:
    """``config`` as a JSON-ready dict."""
    out = asdict(config)
    out["env_kwargs"] = config.env_options
    return out


# two-sided 95% quantiles of Student's t for 1..30 degrees of freedom
_T975 = (
    12.706, 4.303, 3.182, 2.776, 2.571, 2.447, 2.365, 2.306, 2.262, 2.228,
    2.201, 2.179, 2.160, 2.145, 2.131, 2.120, 2.110, 2.101, 2.093, 2.086,
    2.080, 2.074, 2.069, 2.064, 2.060, 2.056, 2.052, 2.048, 2.045, 2.042,
)  # fmt: skip


def mean_ci(values: list[float]) -> tuple[float, float]:
    """Mean and half-width of its 95% confidence interval (Student's t over the values;
    ``nan`` half-width for one value)."""
    n = len(values)
    if n == 0:
        raise ValueError("mean_ci needs at least one value")
    mean = sum(values) / n
    if n == 1:
        return mean, math.nan
    var = sum((v - mean) ** 2 for v in values) / (n - 1)
    t = _T975[n - 2] if n - 1 <= len(_T975) else 1.96
    return mean, t * math.sqrt(var / n)


#: the quantities :func:`summarize` reports, as (name, where, key)
SUMMARY_FIELDS = (
    ("train collision steps", "train", "collisions"),
    ("train goal rate", "train", "goal_rate"),
    ("train shield interventions", "train", "intervention_rate"),
    ("eval return", "eval", "return"),
    ("eval goal rate", "eval", "goal_rate"),
    ("eval episodes with a collision", "eval", "collisions"),
    ("eval shield interventions", "eval", "shield_intervention_rate"),
    ("eval filter-layer interventions", "eval", "layer_intervention_rate"),
    ("frames/s", "run", "frames_per_second"),
    ("wall time (s)", "run", "wall_time"),
)


def summarize(results: list[RunResult]) -> dict[str, dict[str, tuple[float, float]]]:
    """Per method, every :data:`SUMMARY_FIELDS` quantity as (mean, 95% CI half-width) over
    the seeds of ``results``."""
    out: dict[str, dict[str, tuple[float, float]]] = {}
    for method in dict.fromkeys(r.method for r in results):
        runs = [r for r in results if r.method == method]
        row = {}
        for name, where, key in SUMMARY_FIELDS:
            if where == "run":
                values = [float(getattr(r, key)) for r in runs]
            else:
                values = [float(getattr(r, where)[key]) for r in runs]
            row[name] = mean_ci(values)
        out[method] = row
    return out
