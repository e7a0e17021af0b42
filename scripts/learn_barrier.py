"""Learn a barrier for an obstacle field known only through sampled occupancy, then run the
learned CBF-QP filter in closed loop.

The obstacle field is the union of the five ellipses of scenario B (non-convex, no closed
form given to the learner: it only sees labels from an occupancy oracle). The robot is a
single integrator in the plane with |u_i| <= 2, so the learned barrier has relative degree
one. The loss is

    classification (smooth hinge with margins, labels from the occupancy dilated by
    --dilate, on minibatches of a precomputed labelled set)
    + CBF condition at the filter's solution u* (relu(-(L_g h u* + alpha h))) on the
    minibatch's states labelled safe, with the nominal control,

the second back-propagated through the batched QP of the safety filter. Then a goal-seeking
nominal controller is filtered by the learned barrier from held-out starts sampled in free
space (with a margin), and collisions with the TRUE ellipses are counted.

Prints held-out accuracy, collisions, time per training step; writes figures to --out.

    python scripts/learn_barrier.py --out runs/learn_barrier          # full (a few minutes)
    python scripts/learn_barrier.py --quick --out runs/learn_barrier  # smoke run
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import torch

from torchcbf._argtypes import torch_device
from torchcbf.barriers import NeuralBarrier
from torchcbf.dynamics import SingleIntegrator
from torchcbf.filters import SafetyFilter
from torchcbf.learning import (
    MLP,
    cbf_condition_loss,
    classification_accuracy,
    classification_loss,
    dilate,
    load_checkpoint,
    make_generator,
    occupancy_from_barrier,
    sample_free,
    sample_labelled,
    train,
)
from torchcbf.scenarios import obstacles
from torchcbf.sim import simulate

LOW, HIGH = (-3.0, -2.5), (5.0, 6.5)
GOAL = (2.0, 4.0)
U_MAX = 2.0


def nominal_controller(goal: torch.Tensor, gain: float = 1.5):
    """Goal-seeking proportional controller, clipped to the control limits."""

    def control(x: torch.Tensor, t: float) -> torch.Tensor:
        return (gain * (goal.to(x) - x)).clamp(-U_MAX, U_MAX)

    return control


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--steps", type=int, default=1500, help="training steps")
    ap.add_argument("--batch", type=int, default=4096, help="labelled states per step")
    ap.add_argument(
        "--cbf-batch", type=int, default=1024, help="states per step for the CBF-condition loss"
    )
    ap.add_argument("--data", type=int, default=200_000, help="size of the labelled set")
    ap.add_argument("--lr", type=float, default=1e-2)
    ap.add_argument("--device", default="cpu", type=torch_device)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", default=None, help="directory for figures and the checkpoint")
    ap.add_argument("--quick", action="store_true", help="short run (smoke test)")
    ap.add_argument("--threads", type=int, default=1, help="torch intra-op threads (CPU)")
    ap.add_argument("--dilate", type=float, default=0.15, help="safety margin of the labels")
    ap.add_argument("--hinge", type=float, default=0.05, help="classification margin on h")
    ap.add_argument("--temperature", type=float, default=0.1, help="smooth-hinge temperature")
    ap.add_argument("--cbf-weight", type=float, default=1.0)
    ap.add_argument(
        "--cbf-start",
        type=float,
        default=0.5,
        help="fraction of the steps after which the CBF-condition term is added (curriculum: "
        "the QP gradients early on slow the classification down)",
    )
    ap.add_argument("--alpha", type=float, default=2.0, help="class-K gain of the filter")
    ap.add_argument("--starts", type=int, default=1000, help="held-out closed-loop starts")
    ap.add_argument("--start-margin", type=float, default=0.3)
    ap.add_argument("--sim-steps", type=int, default=200)
    ap.add_argument("--dt", type=float, default=0.05)
    ap.add_argument("--test-states", type=int, default=100_000)
    ap.add_argument("--load", default=None, help="skip training: load this checkpoint")
    ap.add_argument("--no-progress", action="store_true")
    args = ap.parse_args()
    if args.steps < 1:
        ap.error(f"--steps must be at least 1, got {args.steps}")
    if args.quick:
        args.steps = min(args.steps, 150)
        args.batch = min(args.batch, 1024)
        args.cbf_batch = min(args.cbf_batch, 256)
        args.data = min(args.data, 50_000)
        args.starts = min(args.starts, 200)
        args.sim_steps = min(args.sim_steps, 120)
        args.test_states = min(args.test_states, 20_000)
    torch.set_num_threads(args.threads)
    device = torch.device(args.device)
    dtype = torch.float32
    progress = not args.no_progress

    truth = obstacles().to(device=device, dtype=dtype)
    occupied = occupancy_from_barrier(truth)  # the oracle: labels only
    train_occ = dilate(occupied, args.dilate)
    lo = torch.tensor(LOW, device=device, dtype=dtype)
    hi = torch.tensor(HIGH, device=device, dtype=dtype)

    torch.manual_seed(args.seed)  # network initialisation only
    net = MLP(2, (64, 64, 64), activation="silu", low=lo, high=hi).to(device=device, dtype=dtype)
    barrier = NeuralBarrier(net)
    dyn = SingleIntegrator(2, u_min=-U_MAX, u_max=U_MAX).to(device=device, dtype=dtype)
    filt = SafetyFilter(dyn, barrier, alpha=args.alpha).to(device=device, dtype=dtype)
    goal = torch.tensor(GOAL, device=device, dtype=dtype)
    nominal = nominal_controller(goal)
    gen = make_generator(seed=args.seed, device=device)
    t0 = time.perf_counter()
    data = sample_labelled(train_occ, lo, hi, args.data, generator=gen)
    print(f"labelled {args.data} states in {time.perf_counter() - t0:.1f} s")

    opt = torch.optim.Adam(barrier.parameters(), lr=args.lr)
    sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, max(args.steps, 1), eta_min=1e-4)

    def loss_fn(step: int):
        idx = torch.randint(args.data, (args.batch,), generator=gen, device=device)
        x, safe = data.x[idx], data.safe[idx]
        h = barrier(x)
        l_cls = classification_loss(h, safe, margin=args.hinge, temperature=args.temperature)
        # the CBF condition must hold on the safe set; imposed inside the obstacles too it
        # fights the classification (raising h there satisfies it trivially)
        if step < args.cbf_start * args.steps:
            l_cbf = h.new_zeros(())
        else:
            xc = x[safe][: args.cbf_batch]
            l_cbf = cbf_condition_loss(filt, xc, nominal(xc, 0.0))
        acc = classification_accuracy(h, safe)
        return l_cls + args.cbf_weight * l_cbf, {"cls": l_cls, "cbf": l_cbf, "acc": acc}

    out = Path(args.out) if args.out else None
    ckpt = None if out is None else out / "barrier.pt"
    if args.load:
        load_checkpoint(args.load, barrier, map_location=device)
        print(f"loaded {args.load}")
    else:
        result = train(
            loss_fn,
            opt,
            args.steps,
            scheduler=sched,
            progress=progress,
            checkpoint=ckpt,
            checkpoint_every=200,
            module=barrier,
            generator=gen,
        )
        metrics = result.metrics
        print(
            f"trained {args.steps} steps, batch {args.batch} labelled + {args.cbf_batch} "
            f"CBF-condition states (from step {int(args.cbf_start * args.steps)}), "
            f"{args.threads} thread(s), device {device}: {result.seconds_per_step * 1e3:.1f} ms "
            f"wall per step on average, final loss "
            f"{result.losses[-1]:.4g} ({', '.join(f'{k} {v:.4g}' for k, v in metrics.items())})"
        )

    # held-out classification (fresh seed), against the training labels (dilated) and the truth
    test = sample_labelled(train_occ, lo, hi, args.test_states, seed=args.seed + 10_000)
    with torch.no_grad():
        h_test = barrier(test.x)
    acc = float(classification_accuracy(h_test, test.safe))
    truly_occ = occupied(test.x)
    unsafe_accepted = int(((h_test >= 0) & truly_occ).sum())
    print(
        f"held-out accuracy (labels dilated by {args.dilate}): {acc * 100:.3f}% over "
        f"{args.test_states} states; truly occupied states with h >= 0: {unsafe_accepted} of "
        f"{int(truly_occ.sum())}"
    )

    # closed loop from held-out starts in free space
    x0 = sample_free(
        occupied, lo, hi, args.starts, margin=args.start_margin, seed=args.seed + 20_000
    )
    t0 = time.perf_counter()
    with torch.no_grad():
        traj = simulate(
            dyn,
            x0,
            args.sim_steps,
            args.dt,
            nominal=nominal,
            safety_filter=filt,
            progress=progress,
        )
        h_true = truth(traj.x).amin(-1)  # [B, T+1]
        h0 = barrier(x0)
    sim_time = time.perf_counter() - t0
    collided = (h_true < 0).any(-1)
    reached = ((traj.x[:, -1] - goal).norm(dim=-1) <= 0.25).float().mean()
    status = traj.status.flatten().bincount(minlength=4).tolist()
    print(
        f"closed loop: {int(collided.sum())} collisions over {args.starts} held-out starts "
        f"(start margin {args.start_margin}); min true h {float(h_true.min()):.4f}; "
        f"starts with learned h < 0: {int((h0 < 0).sum())}; goal reached "
        f"{float(reached) * 100:.1f}%; filter statuses [solved, relaxed, fallback, "
        f"non-finite] {status}; {args.sim_steps} steps in {sim_time:.1f} s"
    )

    if out is not None:
        _figures(out, truth, barrier, traj, goal, lo, hi)
        print(f"figures in {out}")


def _figures(out, truth, barrier, traj, goal, lo, hi) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from torchcbf.sim import Goal
    from torchcbf.viz import draw_unsafe_set, plot_trajectories

    out.mkdir(parents=True, exist_ok=True)
    xlim = (float(lo[0]), float(hi[0]))
    ylim = (float(lo[1]), float(hi[1]))

    def learned_contour(ax) -> None:
        n = 300
        xs = torch.linspace(xlim[0], xlim[1], n, dtype=lo.dtype, device=lo.device)
        ys = torch.linspace(ylim[0], ylim[1], n, dtype=lo.dtype, device=lo.device)
        X, Y = torch.meshgrid(xs, ys, indexing="xy")
        with torch.no_grad():
            H = barrier(torch.stack([X, Y], -1))
        ax.contour(X.cpu(), Y.cpu(), H.cpu(), levels=[0.0], colors=["tab:blue"], linewidths=1.5)
        ax.plot([], [], color="tab:blue", label="learned h = 0")

    fig, ax = plt.subplots(figsize=(6, 6.5))
    draw_unsafe_set(ax, truth, xlim, ylim, label="true obstacles")
    learned_contour(ax)
    ax.set_xlim(*xlim)
    ax.set_ylim(*ylim)
    ax.set_aspect("equal")
    ax.legend(loc="upper left", fontsize=8)
    ax.set_title("learned zero level set over the true obstacles")
    fig.savefig(out / "level_set.png", dpi=120, bbox_inches="tight")
    plt.close(fig)

    fig = plot_trajectories(
        traj.to("cpu") if hasattr(traj, "to") else traj,
        barriers=[truth.cpu()],
        goals=[Goal(center=goal.tolist(), radius=0.25)],
        xlim=xlim,
        ylim=ylim,
        max_paths=100,
        title="closed loop, learned barrier (dots: all held-out starts; 100 paths)",
    )
    learned_contour(fig.axes[0])
    fig.savefig(out / "closed_loop.png", dpi=120, bbox_inches="tight")
    plt.close(fig)


if __name__ == "__main__":
    main()
