"""Safe RL comparison: PPO four ways on a torchcbf TorchRL environment (docs/safe_rl.md).

Methods (:data:`torchcbf.envs.safe_ppo.METHODS`): unconstrained PPO, PPO-Lagrangian on the
collision cost, PPO with the safety filter as a shield on the environment, and PPO trained
through the filter as the policy's last layer. Every method runs the same seeds, the same
frame budget and the same PPO settings. Printed (and written to ``--out``): per method the
mean and 95% confidence half-width over the seeds of the training collisions, goal rate and
shield interventions, the evaluation return, goal rate, collisions and interventions, the
frames per second and the wall time; a figure of the learning curves.

Run: ``python scripts/safe_rl.py --seeds 3 --out runs/safe_rl`` (scenario B, one torch
thread). ``--env torchcbf/ReachAvoid-v0`` runs scenario A.

``--throughput`` measures environment steps per second instead (scenario B, a fixed
nominal action, batches of ``--sizes``), against peers in the same run:

- ``TorchRLEnv``: :class:`~torchcbf.envs.torchrl.TorchRLEnv` stepped with
  ``step_and_maybe_reset`` (TorchRL's loop: resets of ended rows included);
- ``TorchRLEnv + SafetyFilterTransform``: the same with the shield of
  :func:`~torchcbf.envs.safe_ppo.scenario_filter` (one filter call per step for all N);
- ``gymnasium vector env``: the Gymnasium vector env of the same scenario, NumPy in and out
  and tensors (``return_tensors=True``);
- ``TorchRL GymWrapper (1 env)``: TorchRL's Gym wrapper around the single Gymnasium env, a
  Gym round trip per step.

``--shield-check`` counts the collisions of scenario B's shield
(:func:`~torchcbf.envs.safe_ppo.scenario_filter` with each of ``--check-margins``) on the plant
with process noise ``--sigma``, for three nominal controllers: ``still`` (zero action: the
noise alone moves the robot), ``random`` (Gaussian actions, half the bounds) and
``go-to-goal + noise`` (scenario B's proportional controller plus Gaussian noise of a fifth
of the bounds, which presses the robot along the ellipses).

``--risk-check`` computes, for the same filter's ellipse barriers without a margin on the
plant with process noise ``--sigma``, the risk-aware CBF's noise bound ``eta = max |dh/dx
sigma|`` (:func:`~torchcbf.filters.noise_bound`, over 20,000 random states of the arena with
``|v| <= SPEED_BOUND``) and its margin ``Delta`` (:func:`~torchcbf.filters.risk_margin`) for
risks ``rho`` and horizons ``T``: the risk-aware filter bounds the probability of entering an
ellipse within ``T`` by ``rho`` only from states with ``h >= Delta``. Printed with the barrier
values at the start and the fraction of resting positions of the arena where ``h >= Delta``
holds for every ellipse.

Figures taken while the machine is loaded (the load average is printed) vary between runs;
compare ratios within one run.
"""

from __future__ import annotations

import argparse
import json
import math
import multiprocessing
import os
import time
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import asdict, replace
from pathlib import Path

import gymnasium
import torch
from torchrl.envs import TransformedEnv
from torchrl.envs.libs.gym import GymWrapper

import torchcbf.envs  # noqa: F401  (registers the ids)
from torchcbf._io import save_figure, write_json, write_text
from torchcbf.envs.filter_transform import SafetyFilterTransform
from torchcbf.envs.safe_ppo import (
    METHODS,
    SPEED_BOUND,
    SUMMARY_FIELDS,
    PPOConfig,
    RunResult,
    config_dict,
    scenario_filter,
    summarize,
    train,
)
from torchcbf.envs.torchrl import TorchRLEnv
from torchcbf.envs.unicycle_ellipses import START, UnicycleEllipsesVectorEnv
from torchcbf.filters import noise_bound, risk_margin
from torchcbf.scenarios.unicycle_mppi_cbf import proportional_controller
from torchcbf.sim.records import run_info, strict

LABELS = {
    "ppo": "PPO",
    "ppo_lagrangian": "PPO-Lagrangian",
    "ppo_shield": "PPO + shield",
    "ppo_filter_layer": "PPO through the filter layer",
}


def _table(summary: dict[str, dict[str, tuple[float, float]]]) -> str:
    names = [name for name, _, _ in SUMMARY_FIELDS]
    lines = ["| method | " + " | ".join(names) + " |", "|---" * (len(names) + 1) + "|"]
    for method, row in summary.items():
        cells = []
        for name in names:
            mean, half = row[name]
            digits = 0 if name in ("frames/s", "wall time (s)", "train collision steps") else 3
            cell = f"{mean:.{digits}f}"
            if not math.isnan(half):
                cell += f" ± {half:.{digits}f}"
            cells.append(cell)
        lines.append(f"| {LABELS.get(method, method)} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def _figure(results: list[RunResult], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    keys = (("return", "episode return"), ("goal_rate", "goal rate"), ("collisions", None))
    fig, axes = plt.subplots(1, 3, figsize=(14, 3.8))
    for method in dict.fromkeys(r.method for r in results):
        runs = [r for r in results if r.method == method]
        frames = torch.tensor([row["frames"] for row in runs[0].curve]) / 1e6
        for ax, (key, _) in zip(axes, keys, strict=True):
            values = torch.tensor([[row[key] for row in r.curve] for r in runs])
            if key == "collisions":
                values = values.cumsum(-1)
            else:  # a running mean over 5 batches: episodes end sparsely
                values = _smooth(values, 5)
            mean = values.nanmean(0)
            ax.plot(frames, mean, label=LABELS.get(method, method))
            if len(runs) > 1:
                lo, hi = values.nan_to_num(nan=float(mean.nanmean())).aminmax(dim=0)
                ax.fill_between(frames, lo, hi, alpha=0.2)
    axes[0].set_ylabel("episode return (training)")
    axes[1].set_ylabel("goal rate (training episodes)")
    axes[2].set_ylabel("steps inside an obstacle so far (training)")
    axes[2].set_yscale("symlog")
    for ax in axes:
        ax.set_xlabel("frames (millions)")
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=8)
    fig.suptitle("PPO four ways: mean over seeds, band = min..max over seeds")
    fig.tight_layout()
    save_figure(fig, path, dpi=120)
    plt.close(fig)


def _smooth(values: torch.Tensor, width: int) -> torch.Tensor:
    """Running mean over the last ``width`` batches, ignoring batches without episodes."""
    valid = ~values.isnan()
    filled = values.nan_to_num(0.0).cumsum(-1)
    counts = valid.to(values.dtype).cumsum(-1)
    shifted = torch.nn.functional.pad(filled, (width, 0))[..., :-width]
    shifted_counts = torch.nn.functional.pad(counts, (width, 0))[..., :-width]
    total, count = filled - shifted, counts - shifted_counts
    return torch.where(count > 0, total / count.clamp_min(1), torch.full_like(total, math.nan))


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


def throughput(args: argparse.Namespace) -> None:
    """Environment steps per second (see the module docstring)."""
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


def _check_policy(name: str, n: int, generator: torch.Generator):
    limit = torch.tensor([5.0, 10.0])
    go_to_goal = proportional_controller()

    def act(observation: torch.Tensor) -> torch.Tensor:
        if name == "still":
            return torch.zeros(n, 2)
        noise = torch.randn(n, 2, generator=generator) * limit
        if name == "random":
            return (0.5 * noise).clamp(-limit, limit)
        return (go_to_goal(observation, 0.0) + 0.2 * noise).clamp(-limit, limit)

    return act


def shield_check(args: argparse.Namespace) -> None:
    """Collisions of scenario B's shield on the noisy plant (see the module docstring)."""
    n, steps = args.check_envs, args.check_steps
    margins = [float(v) for v in args.check_margins.split(",")]
    print(f"load average {os.getloadavg()}, torch threads {torch.get_num_threads()}")
    print(
        f"scenario B, sigma = {args.sigma}, start noise {args.start_noise} m; {n} robots x "
        f"{steps} steps of {0.01} s per row (episodes restart when they end)"
    )
    print("| margin (m) | nominal | steps | episodes | collisions | goals | QP not solved |")
    print("|---|---|---|---|---|---|---|")
    for margin in margins:
        for name in ("still", "random", "go-to-goal + noise"):
            base = TorchRLEnv(
                ENV_ID, n, seed=args.seed, sigma=args.sigma, start_noise=args.start_noise
            )
            env = TransformedEnv(base, SafetyFilterTransform(scenario_filter(base, margin=margin)))
            act = _check_policy(name, n, torch.Generator().manual_seed(args.seed))
            zero = torch.zeros((), dtype=torch.int64)
            episodes, collisions, goals, unsolved = (
                zero.clone(),
                zero.clone(),
                zero.clone(),
                zero.clone(),
            )
            td = env.reset()
            with torch.no_grad():
                for _ in range(steps):
                    td["action"] = act(td["observation"])
                    out, td = env.step_and_maybe_reset(td)
                    nxt = out["next"]
                    episodes += nxt["done"].sum()
                    collisions += nxt["cost"].sum().long()
                    goals += nxt["success"].sum()
                    unsolved += (nxt["filter_status"] != 0).sum()
            print(
                f"| {margin:g} | {name} | {n * steps:,} | {int(episodes):,} | "
                f"{int(collisions):,} | {int(goals):,} | {int(unsolved):,} |",
                flush=True,
            )


def risk_check(args: argparse.Namespace) -> None:
    """The risk-aware CBF's noise bound and margins on scenario B (see the module docstring)."""
    env = TorchRLEnv(ENV_ID, 1, seed=0, sigma=args.sigma, dtype=torch.float64)
    ellipses = scenario_filter(env, margin=0.0).barriers[0]
    generator = torch.Generator().manual_seed(args.seed)
    low = torch.tensor([-2.0, -2.0, -SPEED_BOUND, -math.pi], dtype=torch.float64)
    high = torch.tensor([5.0, 7.0, SPEED_BOUND, math.pi], dtype=torch.float64)
    states = low + (high - low) * torch.rand(20_000, 4, generator=generator, dtype=low.dtype)
    eta = noise_bound(ellipses, env.dynamics, states)
    start = ellipses(torch.tensor(START, dtype=torch.float64))
    resting = states.clone()
    resting[:, 2] = 0.0
    h = ellipses(resting)
    free = (h >= 0).all(-1)
    print(f"scenario B, sigma = {args.sigma}; the exponential CBFs of the five ellipses, no margin")
    print("eta = max |dh/dx sigma|: " + ", ".join(f"{v:.1f}" for v in eta.tolist()))
    print("h at the start: " + ", ".join(f"{v:.1f}" for v in start.tolist()))
    columns = ("rho", "T (s)", "Delta per ellipse", "start has h >= Delta", "free resting "
               "positions with h >= Delta")  # fmt: skip
    print("| " + " | ".join(columns) + " |")
    print("|---|---|---|---|---|")
    for rho in (0.1, 0.01):
        for horizon in (1.0, 5.0):
            delta = risk_margin(eta, rho, horizon)
            inside = ((h >= delta).all(-1) & free).sum() / free.sum()
            print(
                f"| {rho:g} | {horizon:g} | "
                + ", ".join(f"{v:.1f}" for v in delta.tolist())
                + f" | {bool((start >= delta).all())} | {float(inside):.3f} |"
            )


def _train_one(method: str, config: PPOConfig, seed: int, threads: int) -> RunResult:
    torch.set_num_threads(threads)
    return train(method, config, seed=seed)


def _report(result: RunResult) -> RunResult:
    ev = result.eval
    print(
        f"seed {result.seed} {result.method}: {result.wall_time:.0f} s training, "
        f"{result.frames_per_second:.0f} frames/s, train collision steps "
        f"{result.train['collisions']:.0f}, eval return {ev['return']:.2f}, goal rate "
        f"{ev['goal_rate']:.3f}, episodes with a collision {ev['collisions']:.0f}",
        flush=True,
    )
    return result


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--env", default="torchcbf/UnicycleEllipses-v0")
    parser.add_argument("--methods", default=",".join(METHODS))
    parser.add_argument("--seeds", type=int, default=3)
    parser.add_argument("--seed", type=int, default=0, help="first seed")
    parser.add_argument("--frames", type=int, default=PPOConfig.total_frames)
    parser.add_argument("--num-envs", type=int, default=PPOConfig.num_envs)
    parser.add_argument("--rollout-steps", type=int, default=PPOConfig.rollout_steps)
    parser.add_argument("--eval-episodes", type=int, default=PPOConfig.eval_episodes)
    parser.add_argument(
        "--sigma", type=float, default=0.05, help="scenario B's process noise (m/sqrt(s))"
    )
    parser.add_argument(
        "--terminate-on-collision",
        action=argparse.BooleanOptionalAction,
        default=False,
        help="end an episode at a collision (default: it goes on, the cost marks each step)",
    )
    parser.add_argument(
        "--collision-penalty", type=float, default=0.0, help="reward penalty per collision step"
    )
    parser.add_argument("--start-noise", type=float, default=0.1, help="start perturbation (m)")
    parser.add_argument(
        "--margin", type=float, default=None, help="scenario B's filter margin (m; default 3 sigma)"
    )
    parser.add_argument(
        "--shield-penalty",
        type=float,
        default=PPOConfig.shield_penalty,
        help="weight of the shield's squared correction in the shielded learner's reward",
    )
    parser.add_argument(
        "--shaping",
        action=argparse.BooleanOptionalAction,
        default=PPOConfig.shaping,
        help="progress along the shortest collision-free path (default) or the straight line",
    )
    parser.add_argument("--threads", type=int, default=1, help="torch threads per run")
    parser.add_argument("--jobs", type=int, default=1, help="runs trained at once (processes)")
    parser.add_argument("--out", default=None, help="folder for results.json and the figure")
    parser.add_argument(
        "--throughput", action="store_true", help="measure environment steps per second only"
    )
    parser.add_argument("--sizes", default="1024,16384,65536", help="--throughput: batch sizes")
    parser.add_argument("--filter-sizes", default="1024,16384", help="--throughput: with filter")
    parser.add_argument("--quick", action="store_true", help="--throughput: fewer steps")
    parser.add_argument(
        "--shield-check",
        action="store_true",
        help="count the shield's collisions on scenario B's plant (--sigma) only",
    )
    parser.add_argument(
        "--risk-check",
        action="store_true",
        help="the risk-aware CBF's noise bound and margins on scenario B's plant (--sigma) only",
    )
    parser.add_argument("--check-margins", default="0,0.15", help="--shield-check: margins (m)")
    parser.add_argument("--check-envs", type=int, default=2048, help="--shield-check: robots")
    parser.add_argument("--check-steps", type=int, default=1500, help="--shield-check: steps")
    args = parser.parse_args()
    methods = [m.strip() for m in args.methods.split(",") if m.strip()]
    for method in methods:
        if method not in METHODS:
            parser.error(f"--methods: {method!r} is not one of {METHODS}")
    torch.set_num_threads(args.threads)
    if args.throughput:
        throughput(args)
        return
    if args.shield_check:
        shield_check(args)
        return
    if args.risk_check:
        risk_check(args)
        return
    env_kwargs: dict[str, float | bool] = {"start_noise": args.start_noise}
    if args.env == PPOConfig.env_id:
        env_kwargs["sigma"] = args.sigma
    env_kwargs["terminate_on_collision"] = args.terminate_on_collision
    env_kwargs["collision_penalty"] = args.collision_penalty
    config = replace(
        PPOConfig(),
        env_id=args.env,
        env_kwargs=tuple(env_kwargs.items()),
        total_frames=args.frames,
        num_envs=args.num_envs,
        rollout_steps=args.rollout_steps,
        eval_episodes=args.eval_episodes,
        shaping=args.shaping,
        filter_margin=args.margin,
        shield_penalty=args.shield_penalty,
    )
    print(f"load average {os.getloadavg()}, torch threads {torch.get_num_threads()}")
    print(json.dumps(config_dict(config)))
    runs = [(seed, m) for seed in range(args.seed, args.seed + args.seeds) for m in methods]
    # the slowest method first, so that parallel workers finish together
    runs.sort(key=lambda run: (-METHODS.index(run[1]), run[0]))
    results: list[RunResult] = []
    start = time.perf_counter()
    if args.jobs == 1:
        for seed, method in runs:
            results.append(_report(_train_one(method, config, seed, args.threads)))
    else:
        context = multiprocessing.get_context("spawn")
        with ProcessPoolExecutor(args.jobs, mp_context=context) as pool:
            futures = [
                pool.submit(_train_one, method, config, seed, args.threads) for seed, method in runs
            ]
            for future in as_completed(futures):
                results.append(_report(future.result()))
    results.sort(key=lambda r: (r.seed, METHODS.index(r.method)))
    total = time.perf_counter() - start
    summary = summarize(results)
    print(_table(summary))
    print(
        f"whole comparison: {total:.0f} s ({args.jobs} process(es)); load average {os.getloadavg()}"
    )
    if args.out is not None:
        out = Path(args.out)
        out.mkdir(parents=True, exist_ok=True)
        record = {
            "config": config_dict(config),
            "seeds": list(range(args.seed, args.seed + args.seeds)),
            "total_seconds": total,
            "jobs": args.jobs,
            "summary": {m: {k: list(v) for k, v in row.items()} for m, row in summary.items()},
            "runs": [asdict(r) for r in results],
        }
        write_json(out / "results.json", strict({**record, "run": run_info()}))
        write_text(out / "table.md", _table(summary) + "\n")
        _figure(results, out / "safe_rl_curves.png")
        print(f"wrote {out / 'results.json'}, {out / 'table.md'}, {out / 'safe_rl_curves.png'}")


if __name__ == "__main__":
    main()
