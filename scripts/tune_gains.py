"""Tune the class-K gains of a CBF-QP filter by gradient through the filter and rollouts.

Single integrator in the plane (|u_i| <= 2) among the five ellipses of scenario B, a
goal-seeking nominal controller, and one learnable linear gain per ellipse
(``alpha_i(h) = gain_i h``, started conservative). The loss over a batch of differentiable
closed-loop rollouts (:func:`torchcbf.sim.simulate` with ``differentiable=True``) is

    mean |u - u_nom|^2  +  w_goal * mean |p - goal|  +  w_col * mean relu(margin - h_true)

(intervention, a time-to-goal proxy, and a collision penalty on the true ellipses).
Prints before/after metrics on held-out starts: time to goal, goal reached, intervention,
collisions, minimum true h.

    python scripts/tune_gains.py            # ~ a few minutes on one CPU thread
    python scripts/tune_gains.py --quick
"""

from __future__ import annotations

import argparse
import time

import torch

from torchcbf._argtypes import torch_device
from torchcbf.dynamics import SingleIntegrator
from torchcbf.filters import LinearClassK, SafetyFilter
from torchcbf.learning import closed_loop_loss, occupancy_from_barrier, sample_free, train
from torchcbf.scenarios import obstacles
from torchcbf.sim import simulate

LOW, HIGH = (-3.0, -2.5), (5.0, 1.0)  # starts below the field; the goal is inside it
GOAL = (2.0, 4.0)
U_MAX = 2.0


def evaluate(dyn, filt, nominal, x0, steps, dt, truth, goal) -> dict[str, float]:
    with torch.no_grad():
        traj = simulate(dyn, x0, steps, dt, nominal=nominal, safety_filter=filt, progress=False)
        h = truth(traj.x).amin(-1)
        dist = (traj.x - goal).norm(dim=-1)
    reached = dist <= 0.25
    hit = reached.any(-1)
    first = torch.argmax(reached.to(torch.int8), -1).to(traj.x.dtype) * dt
    return {
        "reached %": float(hit.float().mean()) * 100,
        "time to goal (reached) s": float(first[hit].mean()) if bool(hit.any()) else float("nan"),
        "intervention": float(((traj.u - traj.u_nom) ** 2).sum(-1).mean()),
        "collisions": int((h < 0).any(-1).sum()),
        "min true h": float(h.min()),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--steps", type=int, default=40, help="gradient steps")
    ap.add_argument("--batch", type=int, default=64, help="rollouts per step")
    ap.add_argument("--horizon", type=int, default=50, help="rollout steps of --dt")
    ap.add_argument("--dt", type=float, default=0.1)
    ap.add_argument("--gain", type=float, default=0.3, help="initial gain of every ellipse")
    ap.add_argument("--goal-weight", type=float, default=1.0)
    ap.add_argument("--collision-weight", type=float, default=1000.0)
    ap.add_argument("--collision-margin", type=float, default=0.05)
    ap.add_argument("--lr", type=float, default=0.1)
    ap.add_argument("--starts", type=int, default=500, help="held-out starts")
    ap.add_argument("--device", default="cpu", type=torch_device)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--no-progress", action="store_true")
    args = ap.parse_args()
    if args.quick:
        args.steps, args.batch, args.starts = min(args.steps, 8), min(args.batch, 16), 100
    torch.set_num_threads(args.threads)
    device, dtype = torch.device(args.device), torch.float32

    truth = obstacles().to(device=device, dtype=dtype)
    dyn = SingleIntegrator(2, u_min=-U_MAX, u_max=U_MAX).to(device=device, dtype=dtype)
    alpha = LinearClassK(torch.full((5,), args.gain), learnable=True)
    filt = SafetyFilter(dyn, truth, alpha=alpha).to(device=device, dtype=dtype)
    goal = torch.tensor(GOAL, device=device, dtype=dtype)

    def nominal(x: torch.Tensor, t: float) -> torch.Tensor:
        return (1.5 * (goal - x)).clamp(-U_MAX, U_MAX)

    occupied = occupancy_from_barrier(truth)
    lo = torch.tensor(LOW, device=device, dtype=dtype)
    hi = torch.tensor(HIGH, device=device, dtype=dtype)
    held_out = sample_free(occupied, lo, hi, args.starts, margin=0.3, seed=args.seed + 1)
    gen = torch.Generator(device=device).manual_seed(args.seed)
    eval_steps = int(round(8.0 / args.dt))

    before = evaluate(dyn, filt, nominal, held_out, eval_steps, args.dt, truth, goal)

    opt = torch.optim.Adam(alpha.parameters(), lr=args.lr)

    def loss_fn(step: int):
        x0 = sample_free(occupied, lo, hi, args.batch, margin=0.3, generator=gen)
        traj = simulate(
            dyn,
            x0,
            args.horizon,
            args.dt,
            nominal=nominal,
            safety_filter=filt,
            progress=False,
            differentiable=True,
        )
        loss = closed_loop_loss(
            traj,
            truth,
            goal=goal,
            goal_weight=args.goal_weight,
            collision_weight=args.collision_weight,
            collision_margin=args.collision_margin,
        )
        return loss.total, {"interv": loss.intervention, "goal": loss.goal, "col": loss.collision}

    t0 = time.perf_counter()
    res = train(loss_fn, opt, args.steps, progress=not args.no_progress, desc="tune gains")
    wall = time.perf_counter() - t0
    after = evaluate(dyn, filt, nominal, held_out, eval_steps, args.dt, truth, goal)

    print(
        f"tuned {args.steps} steps x {args.batch} rollouts x {args.horizon} steps in {wall:.1f} s "
        f"({res.seconds_per_step:.2f} s/step, {args.threads} thread(s), {device}); "
        f"loss {res.losses[0]:.4g} -> {res.losses[-1]:.4g}"
    )
    print("gains before:", [round(args.gain, 3)] * 5)
    print("gains after: ", [round(g, 3) for g in alpha.gain.detach().cpu().tolist()])
    print(f"held-out starts: {args.starts}, {eval_steps} steps of {args.dt} s")
    print(f"{'metric':<28}{'before':>12}{'after':>12}")
    for key in before:
        print(f"{key:<28}{before[key]:>12.4g}{after[key]:>12.4g}")


if __name__ == "__main__":
    main()
