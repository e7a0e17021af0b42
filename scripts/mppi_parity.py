"""Side by side with pytorch-mppi on its own test problem: the pendulum swing-up.

Gymnasium's ``Pendulum-v1`` from the downward state ``(pi, 1)`` (pytorch-mppi's
tests/pendulum.py), K = 100 samples, horizon T = 15, noise variance 10, temperature 1, the
peer's model and running cost (:mod:`torchcbf.mppi.pendulum`; torchcbf rolls it out with
``MPPI(step=pendulum_step)``), the control cost weight equal to the temperature (the
peer's form). Each planner sees the environment's state as a NumPy array, as the peer's
``run_mppi`` hands it, and its control goes to ``env.step`` (torchcbf returns NumPy for a
NumPy state; the peer's tensor is converted).

Rows: the plain planner, each option a pytorch-mppi user carries over (bounds, u_scale,
noise_abs_cost, candidate samples: the null action and full torque either way), SMPPI
(rate noise variance 4, ``delta_t`` 0.5, smoothness weight 0.1, torques bounded to
``[-2, 2]``) and KMPPI (5 control points, RBF kernel of width 1). Per row and planner,
over the seeds: the total reward (mean and range), the runs that swing up and hold
(``|theta| < 0.3`` rad over the last 100 steps) and the mean time per planning call (one
torch thread; a shared machine inflates both planners alike). Noise differs between the
two libraries (each draws from its own generator), so the rows compare outcomes, not
trajectories; the tests (tests/mppi/test_peer.py) compare the trajectories with shared
noise.

Usage::

    python scripts/mppi_parity.py                  # 5 seeds, 500 steps, every row
    python scripts/mppi_parity.py --seeds 2 --steps 200 --only mppi smppi
"""

from __future__ import annotations

import argparse
import math
import time
from collections.abc import Callable
from typing import Any

import numpy as np
import torch

from torchcbf.mppi import KMPPI, MPPI, SMPPI
from torchcbf.mppi.pendulum import (
    PendulumModel,
    angle_normalize,
    pendulum_cost,
    pendulum_step,
)

K, T, SIGMA, LAMBDA = 100, 15, 10.0, 1.0
HOLD_STEPS, HOLD_ANGLE = 100, 0.3


def running_cost(state: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
    return angle_normalize(state[..., 0]).square() + 0.1 * state[..., 1].square()


def bang_bang() -> torch.Tensor:
    """Two candidate sequences: full torque either way over the horizon, ``[2, T, 1]``."""
    return torch.stack([torch.full((T, 1), 2.0), torch.full((T, 1), -2.0)]).double()


# row name -> (options of torchcbf's planner, options of the peer's, class names, scale)
ROWS: dict[str, tuple[dict[str, Any], dict[str, Any], str, float]] = {
    "mppi": ({}, {}, "MPPI", 1.0),
    "bounded": (
        {"u_min": -2.0, "u_max": 2.0},
        {"u_min": torch.tensor([-2.0]), "u_max": torch.tensor([2.0])},
        "MPPI",
        1.0,
    ),
    "u_scale": ({"u_scale": 2.0}, {"u_scale": 2.0}, "MPPI", 2.0),
    "noise_abs_cost": ({"noise_abs_cost": True}, {"noise_abs_cost": True}, "MPPI", 1.0),
    "candidates": ({"sample_null_action": True}, {"sample_null_action": True}, "MPPI", 1.0),
    "smppi": (
        {"smoothness_weight": 0.1, "delta_t": 0.5, "noise_sigma": 4.0, "u_min": -2.0, "u_max": 2.0},
        {
            "w_action_seq_cost": 0.1,
            "delta_t": 0.5,
            "noise_sigma": 4.0,
            "action_min": torch.tensor([-2.0]),
            "action_max": torch.tensor([2.0]),
        },
        "SMPPI",
        1.0,
    ),  # fmt: skip
    "kmppi": ({"num_support_points": 5}, {"num_support_pts": 5}, "KMPPI", 1.0),
}


def ours(row: str, seed: int) -> Callable[[np.ndarray], np.ndarray]:
    options, _, name, _ = ROWS[row]
    options = dict(options)
    cls = {"MPPI": MPPI, "SMPPI": SMPPI, "KMPPI": KMPPI}[name]
    sigma = options.pop("noise_sigma", SIGMA)
    if row == "candidates":
        candidates = bang_bang()
        options["action_sampler"] = lambda x, t: candidates
    planner = cls(
        PendulumModel(u_min=None, u_max=None), pendulum_cost, horizon=T, num_samples=K,
        dt=0.05, noise_sigma=sigma, temperature=LAMBDA, control_cost_weight=LAMBDA,
        seed=seed, step=lambda x, u, j: pendulum_step(x, u), **options,
    ).double()  # fmt: skip

    def act(state: np.ndarray) -> np.ndarray:
        return planner(state).u  # NumPy in, NumPy out

    return act


def theirs(row: str, seed: int) -> Callable[[np.ndarray], np.ndarray]:
    from pytorch_mppi import mppi

    _, options, name, scale = ROWS[row]
    options = {k: (v.double() if isinstance(v, torch.Tensor) else v) for k, v in options.items()}
    sigma = options.pop("noise_sigma", SIGMA)
    cls = {"MPPI": mppi.MPPI, "SMPPI": mppi.SMPPI, "KMPPI": mppi.KMPPI}[name]
    if row == "candidates":
        candidates = bang_bang()

        class Candidates(mppi.SpecificActionSampler):
            def sample_trajectories(self, state: torch.Tensor, info: object) -> torch.Tensor:
                return candidates

        options["specific_action_sampler"] = Candidates()
    torch.manual_seed(seed)  # the peer samples from the global generator
    planner = cls(
        lambda s, a: pendulum_step(s, a), running_cost, 2,
        torch.tensor(sigma, dtype=torch.float64), num_samples=K, horizon=T, lambda_=LAMBDA,
        **options,
    )  # fmt: skip

    def act(state: np.ndarray) -> np.ndarray:
        # the peer returns the sampled action a; the environment gets u = u_scale a
        return scale * planner.command(state).reshape(1).numpy()

    return act


def episode(act: Callable[[np.ndarray], np.ndarray], seed: int, steps: int) -> dict[str, float]:
    import gymnasium

    env = gymnasium.make("Pendulum-v1").unwrapped
    env.reset(seed=seed)
    env.state = np.array([math.pi, 1.0])
    total, angles, elapsed = 0.0, [], 0.0
    for _ in range(steps):
        state = env.state.copy()
        start = time.perf_counter()
        u = act(state)
        elapsed += time.perf_counter() - start
        _, reward, *_ = env.step(np.asarray(u, dtype=np.float32).reshape(1))
        total += float(reward)
        angles.append(abs(float(angle_normalize(torch.tensor(env.state[0])))))
    held = max(angles[-HOLD_STEPS:]) < HOLD_ANGLE
    return {"reward": total, "held": float(held), "ms": 1e3 * elapsed / steps}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--seeds", type=int, default=5)
    parser.add_argument("--steps", type=int, default=500)
    parser.add_argument("--only", nargs="*", choices=list(ROWS), default=list(ROWS))
    args = parser.parse_args()
    if args.steps <= HOLD_STEPS:
        parser.error(f"--steps must exceed {HOLD_STEPS} (the hold window)")
    torch.set_num_threads(1)
    print(f"pendulum swing-up, K = {K}, T = {T}, seeds 0..{args.seeds - 1}, {args.steps} steps")
    header = f"{'row':<15}{'planner':<13}{'reward mean':>12}{'min':>10}{'max':>10}"
    print(header + f"{'held':>7}{'ms/call':>9}")
    for row in args.only:
        for label, make in (("torchcbf", ours), ("pytorch-mppi", theirs)):
            runs = [episode(make(row, s), s, args.steps) for s in range(args.seeds)]
            rewards = [r["reward"] for r in runs]
            held = int(sum(r["held"] for r in runs))
            ms = sum(r["ms"] for r in runs) / len(runs)
            print(
                f"{row:<15}{label:<13}{np.mean(rewards):>12.1f}{min(rewards):>10.1f}"
                f"{max(rewards):>10.1f}{f'{held}/{len(runs)}':>7}{ms:>9.2f}"
            )


if __name__ == "__main__":
    main()
