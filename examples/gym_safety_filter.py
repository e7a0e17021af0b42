"""A simple policy on torchcbf's batched Gymnasium envs, with and without a safety filter.

The policy heads for the current goal with a random perturbation (scenario A: the first
goal not yet visited; scenario B: the goal), which drives it through the obstacles. Each
environment is run as one native vector env of ``--num-envs`` robots for ``--steps`` steps
(episodes autoreset), plain and wrapped in ``SafetyFilterWrapper``:

- scenario A: a CBF-QP filter on the single integrator and the obstacle disc;
- scenario B: scenario B's stochastic CBF filter (``torchcbf.scenarios.mppi_cbf("scbf")``),
  which is built without control limits, so the env's limits are set wide enough not to
  clip its output. Scenario B's noise (0.28 on every state) still pushes some robots into
  an obstacle, and the filtered robots mostly stall near the start (see the README's
  analysis of scenario B).

Prints a table of finished episodes, collisions and successes per run.

    pip install -e ".[gym]"
    python examples/gym_safety_filter.py --num-envs 64 --steps 300
"""

from __future__ import annotations

import argparse
import time

import gymnasium as gym
import numpy as np
import torch

import torchcbf.envs  # noqa: F401  (registers the environments)
from torchcbf.envs import SafetyFilterWrapper
from torchcbf.filters import SafetyFilter
from torchcbf.scenarios import mppi_cbf
from torchcbf.scenarios.single_integrator_reach_avoid import GOALS
from torchcbf.scenarios.unicycle_mppi_cbf import GOAL


def reach_avoid_policy(obs: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Toward the first goal not yet visited, plus uniform noise (m/s)."""
    centers = np.array([c for c, _, _ in GOALS])
    target = centers[np.argmin(obs[:, 3:6], axis=1)]
    u = 2.0 * (target - obs[:, :2]) + rng.uniform(-2.0, 2.0, size=(len(obs), 2))
    return np.clip(u, -5.0, 5.0).astype(np.float32)


def unicycle_policy(obs: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Speed up toward 2 m/s and turn toward the goal, plus uniform noise."""
    d = np.asarray(GOAL) - obs[:, :2]
    heading = np.arctan2(d[:, 1], d[:, 0])
    err = np.mod(heading - obs[:, 3] + np.pi, 2 * np.pi) - np.pi
    u = np.stack([2.0 - obs[:, 2], 5.0 * err], axis=1)
    u = u + rng.uniform(-1.0, 1.0, size=u.shape)
    return np.clip(u, [-5.0, -10.0], [5.0, 10.0]).astype(np.float32)


def run(env, policy, steps: int, seed: int) -> dict[str, float]:
    """Roll ``policy`` for ``steps`` steps; count finished episodes, collisions, successes."""
    rng = np.random.default_rng(seed)
    obs, _ = env.reset(seed=seed)
    episodes = collisions = successes = 0
    relaxed = 0
    start = time.perf_counter()
    for _ in range(steps):
        obs, _, terminated, truncated, info = env.step(policy(obs, rng))
        episodes += int((terminated | truncated).sum())
        collisions += int((info["collision"] & terminated).sum())
        successes += int((info["success"] & terminated).sum())
        if "filter_status" in info:
            relaxed += int((info["filter_status"] != 0).sum())
    seconds = time.perf_counter() - start
    return {
        "episodes": episodes,
        "collisions": collisions,
        "successes": successes,
        "not_solved": relaxed,
        "steps_per_s": steps * env.num_envs / seconds,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--num-envs", type=int, default=64, help="robots per vector env")
    parser.add_argument("--steps", type=int, default=300, help="vector env steps per run")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--device", default="cpu")
    args = parser.parse_args()
    torch.set_num_threads(1)
    kw = {"num_envs": args.num_envs, "vectorization_mode": "vector_entry_point"}
    kw |= {"device": args.device, "start_noise": 0.2}
    setups = [
        (
            "torchcbf/ReachAvoid-v0",
            {},
            reach_avoid_policy,
            lambda env: SafetyFilter(env.dynamics, barriers=list(env.barriers), alpha=2.0),
        ),
        (
            "torchcbf/UnicycleEllipses-v0",
            {"control_limit": (50.0, 100.0)},
            unicycle_policy,
            lambda env: mppi_cbf("scbf", num_seeds=1, device=args.device).safety_filter,
        ),
    ]
    print(
        f"{'environment':<30} {'filter':<8} {'episodes':>8} {'collisions':>10} "
        f"{'successes':>9} {'filter steps not solved':>23} {'env steps/s':>11}"
    )
    for env_id, options, policy, make_filter in setups:
        for filtered in (False, True):
            env = gym.make_vec(env_id, **kw, **options)
            if filtered:
                env = SafetyFilterWrapper(env, make_filter(env.unwrapped))
            r = run(env, policy, args.steps, args.seed)
            print(
                f"{env_id:<30} {'yes' if filtered else 'no':<8} {r['episodes']:>8} "
                f"{r['collisions']:>10} {r['successes']:>9} "
                f"{r['not_solved'] if filtered else '-':>23} {r['steps_per_s']:>11.0f}"
            )


if __name__ == "__main__":
    main()
