"""Benchmark the TorchRL environments: environment steps per second, batched, with and
without the safety-filter transform, against peers in the same run.

Rows (scenario B, ``torchcbf/UnicycleEllipses-v0``, a fixed nominal action, one torch
thread by default):

- ``TorchRLEnv``: :class:`~torchcbf.envs.torchrl.TorchRLEnv` stepped with
  ``step_and_maybe_reset`` (TorchRL's loop: resets of ended rows included), N environments;
- ``TorchRLEnv + SafetyFilterTransform``: the same with the shield of
  :func:`~torchcbf.envs.safe_ppo.scenario_filter` (one filter call per step for all N);
- ``gymnasium vector env``: the Gymnasium vector env of the same scenario, NumPy in and out
  (``return_tensors=False``) and tensors (``return_tensors=True``);
- ``TorchRL GymWrapper (1 env)``: TorchRL's Gym wrapper around the single Gymnasium env, a
  Gym round trip per step.

``--sigma 0`` steps the deterministic plant (the process noise draws cost about a third).
Run: ``python scripts/bench_rl_env.py`` (``--quick`` for a short run). Figures taken while the
machine is loaded (the load average is printed) vary between runs; compare ratios within one
run.
"""

from __future__ import annotations

import argparse
import os
import time

import gymnasium
import torch
from torchrl.envs import TransformedEnv
from torchrl.envs.libs.gym import GymWrapper

import torchcbf.envs  # noqa: F401  (registers the ids)
from torchcbf.envs import UnicycleEllipsesVectorEnv
from torchcbf.envs.filter_transform import SafetyFilterTransform
from torchcbf.envs.safe_ppo import scenario_filter
from torchcbf.envs.torchrl import TorchRLEnv

ENV_ID = "torchcbf/UnicycleEllipses-v0"


def _action(n: int) -> torch.Tensor:
    # forward and turning left: the robots move, some meet the obstacles, episodes end
    return torch.tensor([[2.0, 1.0]]).expand(n, 2).contiguous()


def _torchrl(env, n: int, steps: int) -> float:
    td = env.reset()
    action = _action(n)
    for _ in range(3):
        td["action"] = action
        _, td = env.step_and_maybe_reset(td)
    start = time.perf_counter()
    for _ in range(steps):
        td["action"] = action
        _, td = env.step_and_maybe_reset(td)
    return n * steps / (time.perf_counter() - start)


def _gym_vector(n: int, steps: int, sigma: float, tensors: bool) -> float:
    env = UnicycleEllipsesVectorEnv(n, sigma=sigma, return_tensors=tensors)
    env.reset(seed=0)
    action = _action(n) if tensors else _action(n).numpy()
    for _ in range(3):
        env.step(action)
    start = time.perf_counter()
    for _ in range(steps):
        env.step(action)
    return n * steps / (time.perf_counter() - start)


def _gym_wrapper(steps: int, sigma: float) -> float:
    env = GymWrapper(gymnasium.make(ENV_ID, sigma=sigma))
    return _torchrl(env, 1, steps)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--sizes", default="1024,16384,65536")
    parser.add_argument("--filter-sizes", default="1024,16384")
    parser.add_argument("--sigma", type=float, default=0.28)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--quick", action="store_true")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    steps = 10 if args.quick else 40
    print(f"load average {os.getloadavg()}, torch threads {torch.get_num_threads()}")
    print(f"scenario B, sigma = {args.sigma}; environment steps per second")
    print(f"| {'what':44s} | {'N':>6s} | {'steps/s':>10s} | vs gymnasium (NumPy) |")
    print(f"|{'-' * 46}|{'-' * 8}|{'-' * 12}|{'-' * 22}|")

    def row(what: str, n: int, rate: float, ref: float | None) -> None:
        ratio = f"{rate / ref:.2f}x" if ref else ""
        print(f"| {what:44s} | {n:6d} | {rate:10.3g} | {ratio:>20s} |", flush=True)

    for n in [int(v) for v in args.sizes.split(",")]:
        ref = _gym_vector(n, steps, args.sigma, tensors=False)
        row("gymnasium vector env (NumPy)", n, ref, ref)
        row("gymnasium vector env (tensors)", n, _gym_vector(n, steps, args.sigma, True), ref)
        env = TorchRLEnv(ENV_ID, n, seed=0, sigma=args.sigma)
        row("TorchRLEnv", n, _torchrl(env, n, steps), ref)
        if n in [int(v) for v in args.filter_sizes.split(",")]:
            base = TorchRLEnv(ENV_ID, n, seed=0, sigma=args.sigma)
            shielded = TransformedEnv(base, SafetyFilterTransform(scenario_filter(base)))
            rate = _torchrl(shielded, n, max(steps // 4, 3))
            row("TorchRLEnv + SafetyFilterTransform", n, rate, ref)
    row("TorchRL GymWrapper (1 env, Gym round trip)", 1, _gym_wrapper(steps * 20, args.sigma), None)


if __name__ == "__main__":
    main()
