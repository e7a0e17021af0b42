"""The ``torchcbf`` command: run the reference scenarios, write metrics and figures, run the
benchmarks.

    torchcbf reach-avoid [--seeds N --samples K --horizon H --device cpu|cuda --out DIR]
    torchcbf mppi-cbf    [--methods scbf,mppi,mppi_scbf --seeds N ...]
    torchcbf demo        both scenarios at sizes that finish in a few minutes on 2 CPU cores
    torchcbf bench       the benchmark scripts (from a source checkout)
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import torch

from torchcbf.sim import summarize

BENCHES = ("bench_qp.py", "bench_barriers.py", "bench_filters.py", "bench_mppi.py")


def _figures(scenario: Any, traj: Any, out: Path, stem: str, gif: bool) -> list[Path]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from torchcbf.viz import animate, plot_barrier_values, plot_rollouts, plot_trajectories

    paths = []
    cpu = traj.to("cpu")
    fig = plot_trajectories(cpu, scenario.barriers, scenario.goals, title=scenario.name)
    paths.append(out / f"{stem}_trajectories.png")
    fig.savefig(paths[-1], dpi=120, bbox_inches="tight")
    plt.close(fig)
    with torch.no_grad():
        h = torch.cat([b(cpu.x).reshape(*cpu.x.shape[:2], -1) for b in scenario.barriers], -1)
    fig = plot_barrier_values(cpu.t, h, title=f"{scenario.name}: min barrier value")
    paths.append(out / f"{stem}_barriers.png")
    fig.savefig(paths[-1], dpi=120, bbox_inches="tight")
    plt.close(fig)
    for step, snap in cpu.planner.items():
        if getattr(snap, "rollouts", None) is None:
            continue
        fig = plot_rollouts(
            snap.rollouts[0],
            snap.rollout_weights[0],
            snap.best_states[0],
            barriers=scenario.barriers,
            goals=scenario.goals,
            executed=cpu.x[0, : step + 1],
            title=f"{scenario.name}: MPPI rollouts at t = {float(cpu.t[step]):.2f} s",
            plan_label="lowest-cost rollout",
        )
        paths.append(out / f"{stem}_rollouts_t{step}.png")
        fig.savefig(paths[-1], dpi=120, bbox_inches="tight")
        plt.close(fig)
    if gif:
        paths.append(animate(cpu, out / f"{stem}.gif", scenario.barriers, scenario.goals))
    return paths


def _row(name: str, summary: dict[str, Any], seconds: float) -> str:
    def rate(key: str) -> str:
        s = summary.get(key)
        return "-" if s is None else f"{100 * s['rate']:.0f}%"

    def mean(key: str, fmt: str = "{:.3f}") -> str:
        s = summary.get(key)
        return "-" if s is None or s["mean"] is None else fmt.format(s["mean"])

    min_h = summary.get("min_h", {}).get("min")
    return (
        f"{name:<22} {rate('collision'):>9} {'-' if min_h is None else f'{min_h:.3f}':>8} "
        f"{rate('goal_reached') if 'goal_reached' in summary else rate('spec_satisfied'):>8} "
        f"{mean('goal0_time', '{:.2f}s'):>9} {seconds:>8.1f}s"
    )


HEADER = f"{'scenario':<22} {'collision':>9} {'min h':>8} {'success':>8} {'t_goal':>9} {'wall':>9}"


def _run(scenario: Any, out: Path, stem: str, progress: bool, gif: bool) -> dict[str, Any]:
    start = time.perf_counter()
    traj, per_seed = scenario.run(progress=progress)
    seconds = time.perf_counter() - start
    summary = summarize(per_seed)
    figures = _figures(scenario, traj, out, stem, gif)
    print(_row(scenario.name, summary, seconds), flush=True)
    return {
        "summary": summary,
        "per_seed": {k: v.detach().cpu().tolist() for k, v in per_seed.items()},
        "seconds": seconds,
        "figures": [str(p) for p in figures],
    }


def _reach_avoid(args: argparse.Namespace, out: Path) -> dict[str, Any]:
    from torchcbf.scenarios import reach_avoid

    scenario = reach_avoid(
        num_seeds=args.seeds,
        num_samples=args.samples or 10_000,
        horizon=args.horizon or 50,
        seed=args.seed,
        device=args.device,
    )
    return {"reach-avoid": _run(scenario, out, "reach_avoid", args.progress, not args.no_gif)}


def _mppi_cbf(args: argparse.Namespace, out: Path) -> dict[str, Any]:
    from torchcbf.scenarios import mppi_cbf

    results = {}
    for method in args.methods.split(","):
        scenario = mppi_cbf(
            method.strip(),
            num_seeds=args.seeds,
            num_samples=args.samples or 20_000,
            horizon=args.horizon or 80,
            seed=args.seed,
            device=args.device,
        )
        results[f"mppi-cbf/{method}"] = _run(
            scenario, out, f"mppi_cbf_{method}", args.progress, not args.no_gif
        )
    return results


def _bench(args: argparse.Namespace) -> int:
    scripts = Path(__file__).resolve().parent.parent / "scripts"
    if not scripts.is_dir():
        print(
            "torchcbf bench runs the scripts/bench_*.py of a source checkout; none found",
            file=sys.stderr,
        )
        return 2
    code = 0
    for name in BENCHES:
        path = scripts / name
        if path.exists():
            cmd = [
                sys.executable,
                str(path),
                *(["--quick"] if args.quick else []),
                "--device",
                args.device,
            ]
            print(f"$ {' '.join(cmd)}", flush=True)
            code |= subprocess.call(cmd)
    return code


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="torchcbf", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    sub = parser.add_subparsers(dest="command", required=True)
    for name, seeds in (("reach-avoid", 10), ("mppi-cbf", 32), ("demo", 0)):
        p = sub.add_parser(name)
        p.add_argument(
            "--seeds", type=int, default=seeds or None, help="noise/planner seeds, run as one batch"
        )
        p.add_argument("--samples", type=int, default=None, help="MPPI samples K")
        p.add_argument("--horizon", type=int, default=None, help="MPPI horizon H")
        p.add_argument("--seed", type=int, default=0, help="first seed")
        p.add_argument("--device", default="cpu", choices=["cpu", "cuda"])
        p.add_argument("--out", default="out", help="directory for metrics.json and figures")
        p.add_argument("--no-progress", dest="progress", action="store_false")
        p.add_argument("--no-gif", action="store_true", help="skip the GIF animation")
        if name == "mppi-cbf":
            p.add_argument("--methods", default="scbf,mppi,mppi_scbf")
    b = sub.add_parser("bench")
    b.add_argument("--quick", action="store_true")
    b.add_argument("--device", default="cpu", choices=["cpu", "cuda"])
    args = parser.parse_args(argv)
    if args.command == "bench":
        return _bench(args)
    if args.device == "cuda" and not torch.cuda.is_available():
        parser.error("--device cuda but CUDA is not available")
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    print(HEADER)
    if args.command == "reach-avoid":
        results = _reach_avoid(args, out)
    elif args.command == "mppi-cbf":
        results = _mppi_cbf(args, out)
    else:
        # Sizes that finish in a few minutes on 2 CPU cores; the paper's sizes are the defaults
        # of the two scenario commands.
        demo_a = argparse.Namespace(
            **{
                **vars(args),
                "seeds": args.seeds or 4,
                "samples": args.samples or 10_000,
                "horizon": args.horizon or 50,
            }
        )
        demo_b = argparse.Namespace(
            **{
                **vars(args),
                "seeds": args.seeds or 8,
                "samples": args.samples or 2_000,
                "horizon": args.horizon or 60,
                "methods": "scbf,mppi,mppi_scbf",
            }
        )
        results = {**_reach_avoid(demo_a, out), **_mppi_cbf(demo_b, out)}
    (out / "metrics.json").write_text(json.dumps(results, indent=2))
    print(f"metrics: {out / 'metrics.json'}; figures: {out}/*.png, {out}/*.gif")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
