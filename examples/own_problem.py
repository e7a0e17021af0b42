"""Timed reach-avoid on your own model: MPPI settings proposed from the specification.

Three specification and model families, each planned by MPPI with the settings that
``torchcbf.mppi.defaults.propose_settings`` derives from the specification's windows and the
model's limits (docs/own_problem.md):

- ``drag``: a model written for this example (a planar point mass with linear drag, force
  limits of 3 per axis), "reach A within 2 s, then B between 2 and 5 s, avoid a disc";
- ``three``: a single integrator (|v_i| <= 5 m/s), three goals in consecutive windows and a
  disc (the goals and obstacle of scenario A, docs/scenarios.md);
- ``unicycle``: a kinematic unicycle (0 <= v <= 1.5 m/s, |omega| <= 2 rad/s), two goals,
  two discs, one of them on the straight line to the first goal.

For ``drag`` it also runs the proposed planner behind a CBF-QP filter on the disc
(``--filtered``: exponential rectification with gain 8, alpha 8) and the two hand settings a
newcomer tries first (``--baselines``): default spec weights with a horizon of 1 s (shorter
than the windows), and scenario A's settings copied over. Each family runs ``--seeds``
seeds from ``--seed`` as one batch (scenario b uses planner seed ``seed + b``) and prints how
many meet the specification.

    python examples/own_problem.py --seeds 16 --seed 0 --samples 1000 --filtered --baselines
"""

from __future__ import annotations

import argparse
import time

import torch

from torchcbf.barriers import Ball, rectify
from torchcbf.dynamics import ControlAffine, SingleIntegrator, Unicycle
from torchcbf.filters import SafetyFilter
from torchcbf.mppi import MPPI, And, Avoid, Reach
from torchcbf.mppi.defaults import propose_settings
from torchcbf.sim import metrics, simulate


class DragPoint(ControlAffine):
    """A planar point mass with linear drag: ``x = (px, py, vx, vy)``, ``u`` = force/mass."""

    def __init__(self, drag: float = 0.5, **kwargs) -> None:
        super().__init__(state_dim=4, control_dim=2, **kwargs)
        self.drag = drag

    def f(self, x: torch.Tensor) -> torch.Tensor:
        v = x[..., 2:]
        return torch.cat([v, -self.drag * v], dim=-1)

    def g(self, x: torch.Tensor) -> torch.Tensor:
        g = x.new_zeros(*x.shape[:-1], 4, 2)
        g[..., 2, 0] = 1.0
        g[..., 3, 1] = 1.0
        return g


def family(name: str):
    """``(model, spec, x0 [n], dt, steps)`` of a family."""
    if name == "drag":
        model = DragPoint(u_min=[-3.0, -3.0], u_max=[3.0, 3.0])
        spec = And(
            Avoid((1.0, 1.0), 0.4),
            Reach((2.0, 2.0), 0.4, interval=(0.0, 2.0)),
            Reach((4.0, 0.0), 0.4, interval=(2.0, 5.0)),
        )
        return model, spec, torch.zeros(4), 0.05, 100
    if name == "three":
        model = SingleIntegrator(2, u_min=-5.0, u_max=5.0)
        spec = And(
            Avoid((3.0, 3.0), 0.6),
            Reach((4.0, 4.0), 0.5, interval=(0.0, 3.5)),
            Reach((6.0, 9.0), 0.5, interval=(3.6, 5.0)),
            Reach((4.0, 1.0), 0.5, interval=(5.1, 10.0)),
        )
        return model, spec, torch.zeros(2), 0.1, 100
    if name == "unicycle":
        model = Unicycle(u_min=[0.0, -2.0], u_max=[1.5, 2.0])
        spec = And(
            Avoid((2.0, 0.2), 0.5),
            Avoid((3.5, 2.5), 0.5),
            Reach((4.0, 0.0), 0.3, interval=(0.0, 5.0)),
            Reach((4.0, 3.5), 0.3, interval=(5.0, 10.0)),
        )
        return model, spec, torch.zeros(3), 0.05, 200
    raise ValueError(f"unknown family {name!r}")


def success(model, spec, planner, x0, dt, steps, seeds, seed, safety_filter=None) -> int:
    """How many of ``seeds`` closed loops (one batch) meet ``spec``."""
    traj = simulate(
        model, x0.expand(seeds, -1).clone(), steps=steps, dt=dt, planner=planner, seed=seed,
        safety_filter=safety_filter, progress=False,
    )  # fmt: skip
    return int(metrics(traj, spec=spec)["spec_satisfied"].sum())


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--families", default="drag,three,unicycle")
    parser.add_argument("--seeds", type=int, default=16)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--samples", type=int, default=1000)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--baselines", action="store_true", help="also the two hand settings")
    parser.add_argument("--filtered", action="store_true", help="also behind a CBF-QP filter")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    print(f"seeds {args.seed}-{args.seed + args.seeds - 1}, K = {args.samples}")
    print(f"{'family':<10} {'settings':<34} {'H':>4} {'met':>7} {'wall':>6}")
    for name in args.families.split(","):
        model, spec, x0, dt, steps = family(name)
        runs = []
        settings = propose_settings(model, spec, dt=dt, x0=x0)
        runs.append(
            ("proposed", settings.planner(model, num_samples=args.samples, seed=args.seed), None)
        )
        if args.filtered and name == "drag":
            disc = Ball(center=[1.0, 1.0], radius=0.4)
            barrier = rectify(disc, model, form="exponential", gains=[8.0])
            runs.append((
                "proposed + CBF-QP filter",
                settings.planner(model, num_samples=args.samples, seed=args.seed),
                SafetyFilter(model, barriers=[barrier], alpha=8.0),
            ))  # fmt: skip
        if args.baselines and name == "drag":
            runs.append(("spec weights 1, H = 1 s", MPPI(
                model, spec, horizon=20, num_samples=args.samples, dt=dt,
                noise_sigma=torch.eye(2), temperature=1.0, seed=args.seed,
            ), None))  # fmt: skip
            copied = And(
                Avoid((1.0, 1.0), 0.4, weight=0.3, eps=0.01),
                Reach((2.0, 2.0), 0.4, interval=(0.0, 2.0), weight=10.0),
                Reach((4.0, 0.0), 0.4, interval=(2.0, 5.0), weight=2.0),
            )
            runs.append(("scenario A's settings", MPPI(
                model, copied, horizon=50, num_samples=args.samples, dt=dt,
                noise_sigma=4.0 * torch.eye(2), temperature=0.03, control_cost_weight=0.1,
                seed=args.seed, cost_normalization="std",
            ), None))  # fmt: skip
        for label, planner, filt in runs:
            start = time.perf_counter()
            met = success(model, spec, planner, x0, dt, steps, args.seeds, args.seed, filt)
            wall = time.perf_counter() - start
            print(
                f"{name:<10} {label:<34} {planner.horizon:>4} {met:>3} / {args.seeds:<2}"
                f" {wall:>5.0f}s"
            )


if __name__ == "__main__":
    main()
