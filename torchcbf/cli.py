"""The ``torchcbf`` command: run the reference scenarios, write metrics and figures, run the
benchmarks.

    torchcbf reach-avoid [--seeds N --samples K --horizon H --device cpu|cuda --out DIR]
    torchcbf mppi-cbf    [--config default|paper|cbfkit --methods all|scbf,mppi,... --seeds N ...]
    torchcbf demo        both scenarios (B in its default configuration) at sizes that finish
                         in a few minutes on 2 CPU cores
    torchcbf bench       the benchmark scripts (from a source checkout)

Every run prints its settings and a table, and writes ``metrics.json`` (strict JSON: ``null``
where a value is undefined, e.g. the time of a goal never reached) with the settings, the
software versions and the git commit, and the figures (PNG, GIF) to ``--out``.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import torch

from torchcbf.sim import run_info, strict, summarize

BENCHES = ("bench_qp.py", "bench_barriers.py", "bench_filters.py", "bench_mppi.py")
PAPER_SIZE_B = "torchcbf mppi-cbf --config default --seeds 32 --samples 20000 --horizon 80"


def _save(fig: Any, path: Path) -> Path:
    import matplotlib.pyplot as plt

    fig.savefig(path, dpi=120, bbox_inches="tight")
    plt.close(fig)
    return path


def _rate(summary: dict[str, Any], key: str) -> str:
    s = summary.get(key)
    if s is None:
        return "-"
    return f"{s['count']}/{s['n']} [{100 * s['ci95_low']:.0f}-{100 * s['ci95_high']:.0f}%]"


def _num(value: float | None, fmt: str = "{:.3f}") -> str:
    return "-" if value is None else fmt.format(value)


def _rollout_figures(traj: Any, scenario: Any, stem: Path, label: str, **view: Any) -> list[Path]:
    """The MPPI rollouts of the first seed at each snapshot step: ``{stem}_rollouts_t{k}.png``."""
    from torchcbf.viz import plot_rollouts

    paths = []
    for step, snap in traj.planner.items():
        if getattr(snap, "rollouts", None) is None:
            continue
        fig = plot_rollouts(
            snap.rollouts[0],
            snap.rollout_weights[0],
            snap.best_states[0],
            barriers=scenario.barriers,
            goals=scenario.goals,
            executed=traj.x[0, : step + 1],
            title=f"{label}: MPPI rollouts at t = {float(traj.t[step]):.2f} s",
            plan_label="lowest-cost rollout",
            **view,
        )
        paths.append(_save(fig, stem.parent / f"{stem.name}_rollouts_t{step}.png"))
    return paths


# -- scenario A ----------------------------------------------------------------------------
A_HEADER = (
    f"{'scenario':<14} {'spec met [95% CI]':>20} {'collisions [95% CI]':>20} "
    f"{'min clearance [m]':>18} {'wall [s]':>9}"
)


def _reach_avoid(args: argparse.Namespace, out: Path) -> dict[str, Any]:
    from torchcbf.scenarios import reach_avoid
    from torchcbf.viz import animate, plot_trajectories

    scenario = reach_avoid(
        num_seeds=args.seeds,
        num_samples=args.samples,
        horizon=args.horizon,
        seed=args.seed,
        device=args.device,
    )
    print(
        f"\nScenario A (reach-avoid, single integrator): {args.seeds} seeds from {args.seed}, "
        f"MPPI K = {args.samples}, H = {args.horizon}, device {args.device}"
    )
    start = time.perf_counter()
    traj, per_seed = scenario.run(progress=args.progress)
    seconds = time.perf_counter() - start
    summary = summarize(per_seed)
    print(A_HEADER)
    print(
        f"{'reach-avoid':<14} {_rate(summary, 'spec_satisfied'):>20} "
        f"{_rate(summary, 'collision'):>20} {_num(summary['min_h']['min']):>18} "
        f"{seconds:>9.1f}",
        flush=True,
    )
    cpu = traj.to("cpu")
    figures = [
        _save(
            plot_trajectories(cpu, scenario.barriers, scenario.goals, title="reach-avoid"),
            out / "reach_avoid_trajectories.png",
        )
    ]
    figures += _rollout_figures(
        cpu, scenario, out / "reach_avoid", f"reach-avoid, seed {args.seed}"
    )
    if not args.no_gif:
        figures.append(animate(cpu, out / "reach_avoid.gif", scenario.barriers, scenario.goals))
    return {
        "reach-avoid": {
            "settings": {
                "seeds": args.seeds,
                "first_seed": args.seed,
                "num_samples": args.samples,
                "horizon": args.horizon,
            },
            "units": {"min_h": "m (clearance |p - o| - r_o)", "seconds": "s"},
            "summary": summary,
            "per_seed": per_seed,
            "seconds": seconds,
            "figures": [str(p) for p in figures],
        }
    }


# -- scenario B ----------------------------------------------------------------------------
B_HEADER = (
    f"{'method':<12} {'collisions [95% CI]':>20} {'goal by 5 s [95% CI]':>21} "
    f"{'t_goal [s]':>10} {'min b':>7} {'relaxed [%]':>11} {'fallback [%]':>12} {'wall [s]':>9}"
)
CONFIG_NOTES = {
    "default": "filter parameters chosen by scripts/tune_scenario_b.py on seeds >= 10,000",
    "paper": "the paper's alpha = beta = 1: the noise band (about 0.2 m) fills the passages",
    "cbfkit": "CBFkit's sublevel barrier exp(-0.1 b) with alpha = beta = 1",
}


def _steps_pct(summary: dict[str, Any], name: str, steps: int) -> str:
    s = summary.get(f"steps_{name}")
    return "-" if s is None or s["mean"] is None else f"{100 * s['mean'] / steps:.1f}"


def _b_row(method: str, summary: dict[str, Any], steps: int, seconds: float) -> str:
    return (
        f"{method:<12} {_rate(summary, 'collision'):>20} {_rate(summary, 'goal_reached'):>21} "
        f"{_num(summary['goal0_time']['mean'], '{:.2f}'):>10} "
        f"{_num(summary['min_h']['min'], '{:.2f}'):>7} {_steps_pct(summary, 'relaxed', steps):>11} "
        f"{_steps_pct(summary, 'fallback', steps):>12} {seconds:>9.1f}"
    )


def _methods(text: str) -> list[str]:
    from torchcbf.scenarios.unicycle_mppi_cbf import METHODS

    names = list(METHODS) if text == "all" else [m.strip() for m in text.split(",") if m.strip()]
    unknown = [m for m in names if m not in METHODS]
    if unknown or not names:
        raise SystemExit(
            f"torchcbf: --methods must be 'all' or a list from {METHODS}, got {text!r}"
        )
    return names


def _mppi_cbf(args: argparse.Namespace, out: Path) -> dict[str, Any]:
    from torchcbf.scenarios import mppi_cbf
    from torchcbf.scenarios.unicycle_mppi_cbf import DT, STEPS

    methods = _methods(args.methods)
    print(
        f"\nScenario B (MPPI and stochastic CBFs, unicycle), configuration '{args.config}' "
        f"({CONFIG_NOTES[args.config]}): {args.seeds} seeds from {args.seed}, MPPI K = "
        f"{args.samples}, H = {args.horizon}, {STEPS} steps of {DT} s, device {args.device}"
    )
    print("min b: closest approach to an ellipse, b_i = |(p - c_i) / a_i|^2 - 1 (contact at 0)")
    print(B_HEADER, flush=True)
    results: dict[str, Any] = {}
    trajectories: dict[str, Any] = {}
    scenario = None
    for method in methods:
        scenario = mppi_cbf(
            method,
            config=args.config,
            num_seeds=args.seeds,
            num_samples=args.samples,
            horizon=args.horizon,
            seed=args.seed,
            device=args.device,
        )
        start = time.perf_counter()
        traj, per_seed = scenario.run(progress=args.progress)
        seconds = time.perf_counter() - start
        summary = summarize(per_seed)
        print(_b_row(method, summary, scenario.steps, seconds), flush=True)
        trajectories[method] = traj.to("cpu")
        results[f"mppi-cbf/{args.config}/{method}"] = {
            "params": scenario.params,
            "units": {
                "min_h": "ellipse value b_i (dimensionless; < 0 inside)",
                "goal0_time": "s",
                "goal0_final_distance": "m",
                "seconds": "s",
            },
            "summary": summary,
            "per_seed": per_seed,
            "seconds": seconds,
        }
    assert scenario is not None
    figures = _b_figures(trajectories, scenario, out, args)
    for entry in results.values():
        entry["figures"] = [str(p) for p in figures]
    return results


def _b_figures(
    trajectories: dict[str, Any], scenario: Any, out: Path, args: argparse.Namespace
) -> list[Path]:
    from torchcbf.viz import animate_methods, plot_barrier_bands, plot_methods

    view = {"xlim": (-2.5, 5.0), "ylim": (-2.0, 6.5)}
    stem = f"mppi_cbf_{args.config}"
    n = args.seeds
    figures = [
        _save(
            plot_methods(
                trajectories,
                scenario.barriers,
                scenario.goals,
                title=f"scenario B, '{args.config}': {n} seeds per method",
                **view,
            ),
            out / f"{stem}_trajectories.png",
        ),
        _save(
            plot_barrier_bands(
                trajectories,
                scenario.barriers,
                title=f"scenario B, '{args.config}': closest ellipse over time ({n} seeds)",
            ),
            out / f"{stem}_barriers.png",
        ),
    ]
    for method, traj in trajectories.items():
        label = f"{method}, seed {args.seed}"
        figures += _rollout_figures(traj, scenario, out / f"{stem}_{method}", label, **view)
    if not args.no_gif:
        figures.append(
            animate_methods(
                trajectories,
                out / f"{stem}.gif",
                scenario.barriers,
                scenario.goals,
                title=f"scenario B, '{args.config}', seed {args.seed}",
                **view,
            )
        )
    return figures


# -- benchmarks ----------------------------------------------------------------------------
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


# -- command line --------------------------------------------------------------------------
def _positive_int(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"invalid int value: {text!r}") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be a positive integer, got {text}")
    return value


def _scenario_options(p: argparse.ArgumentParser, seeds: int, samples: int, horizon: int) -> None:
    p.add_argument(
        "--seeds", type=_positive_int, default=seeds, help="noise/planner seeds, run as one batch"
    )
    p.add_argument("--seed", type=int, default=0, help="first seed")
    p.add_argument("--samples", type=_positive_int, default=samples, help="MPPI samples K")
    p.add_argument("--horizon", type=_positive_int, default=horizon, help="MPPI horizon H (steps)")
    p.add_argument("--device", default="cpu", choices=["cpu", "cuda"])
    p.add_argument("--out", default="out", help="directory for metrics.json and the figures")
    p.add_argument("--no-progress", dest="progress", action="store_false", help="no progress bars")
    p.add_argument("--no-gif", action="store_true", help="skip the GIF animations")


def _config_options(p: argparse.ArgumentParser, methods: str) -> None:
    p.add_argument(
        "--config",
        default="default",
        choices=["default", "paper", "cbfkit"],
        help="scenario B's filter parameters (see docs/scenarios.md)",
    )
    p.add_argument(
        "--methods",
        default=methods,
        help="'all' or a comma-separated list of scbf, mppi, mppi_scbf, mppi_rascbf, shield_mppi",
    )


def build_parser() -> argparse.ArgumentParser:
    """The ``torchcbf`` argument parser."""
    parser = argparse.ArgumentParser(
        prog="torchcbf", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    sub = parser.add_subparsers(dest="command", required=True)
    fmt = argparse.ArgumentDefaultsHelpFormatter
    a = sub.add_parser(
        "reach-avoid",
        help="scenario A at the paper's sizes",
        description="Scenario A: timed reach-avoid with MPPI on a single integrator.",
        formatter_class=fmt,
    )
    _scenario_options(a, 10, 10_000, 50)
    b = sub.add_parser(
        "mppi-cbf",
        help="scenario B at the paper's sizes",
        description="Scenario B: MPPI, stochastic CBFs and their combinations on a noisy "
        "unicycle among five ellipses, every method over one batch of seeds.",
        formatter_class=fmt,
    )
    _scenario_options(b, 32, 20_000, 80)
    _config_options(b, "all")
    d = sub.add_parser(
        "demo",
        help="both scenarios at sizes that finish in a few minutes",
        description="Scenario A (4 seeds, K = 10,000, H = 50) and scenario B in its default "
        f"configuration, every method (8 seeds, K = 1,000, H = 80). The paper's size of B: "
        f"{PAPER_SIZE_B}.",
        formatter_class=fmt,
    )
    _scenario_options(d, 8, 1000, 80)
    _config_options(d, "all")
    bench = sub.add_parser("bench", help="run the benchmark scripts", formatter_class=fmt)
    bench.add_argument("--quick", action="store_true", help="smaller sizes, fewer repeats")
    bench.add_argument("--device", default="cpu", choices=["cpu", "cuda"])
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.command == "bench":
        return _bench(args)
    if args.device == "cuda" and not torch.cuda.is_available():
        parser.error("--device cuda but CUDA is not available")
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    if args.command == "reach-avoid":
        results = _reach_avoid(args, out)
    elif args.command == "mppi-cbf":
        results = _mppi_cbf(args, out)
    else:
        demo_a = argparse.Namespace(**{**vars(args), "seeds": 4, "samples": 10_000, "horizon": 50})
        results = {**_reach_avoid(demo_a, out), **_mppi_cbf(args, out)}
        print(f"\nThe paper's size of scenario B (32 seeds, K = 20,000): {PAPER_SIZE_B}")
    record = {
        "command": " ".join(sys.argv[1:] if argv is None else argv),
        "run": run_info(args.device),
    }
    text = json.dumps(strict({**record, "results": results}), indent=2, allow_nan=False)
    (out / "metrics.json").write_text(text)
    print(f"metrics: {out / 'metrics.json'}; figures: {out}/*.png, {out}/*.gif")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
