"""The ``torchcbf`` command: run the reference scenarios, write metrics and figures, run the
benchmarks.

    torchcbf reach-avoid [--seeds N --samples K --horizon H --device cpu|cuda --out DIR]
    torchcbf mppi-cbf    [--methods scbf,mppi,mppi_scbf --seeds N ...]
    torchcbf demo        both scenarios at sizes that finish in a few minutes on 2 CPU cores
    torchcbf sweep       a grid over a scenario builder's keyword arguments (local or Ray)
    torchcbf tune        Optuna search over a scenario's declared search space (local or Ray)
    torchcbf bench       the benchmark scripts shipped with the package
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import torch

from torchcbf.sim import summarize

# Benchmarks in the order ``torchcbf bench`` runs them (each a script of scripts/).
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


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="torchcbf", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    _add_version(parser)
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
    _add_ecosystem_commands(sub)
    _describe_commands(sub)
    args = parser.parse_args(argv)
    if args.command in ECOSYSTEM_COMMANDS:
        return ECOSYSTEM_COMMANDS[args.command](args)
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


# ---------------------------------------------------------------------------------------------
# sweep, tune, bench, --version and the help texts of every subcommand
# ---------------------------------------------------------------------------------------------


class _HelpFormatter(argparse.ArgumentDefaultsHelpFormatter):
    """Shows each option's default, except for flags and ``None`` or empty defaults (the
    help text says what happens then)."""

    def _get_help_string(self, action: argparse.Action) -> str | None:
        if action.default is None or action.default == [] or action.nargs == 0:
            return action.help
        return super()._get_help_string(action)


# One paragraph per subcommand, shown by ``torchcbf <command> --help``.
DESCRIPTIONS = {
    "reach-avoid": (
        "Scenario A (timed reach-avoid with MPPI on a single integrator) over "
        "a batch of seeds planned as one batch; writes metrics.json and figures to --out. "
        "Without --samples/--horizon: K = 10,000 samples, H = 50 steps."
    ),
    "mppi-cbf": (
        "Scenario B (noisy unicycle among five ellipses: stochastic CBF, MPPI, MPPI + "
        "stochastic CBF) over a batch of noise seeds; writes metrics.json and figures to "
        "--out. Without --samples/--horizon: K = 20,000 samples, H = 80 steps."
    ),
    "demo": (
        "Both scenarios at sizes that finish in a few minutes on 2 CPU cores: scenario A with "
        "4 seeds, K = 10,000, H = 50; scenario B's three methods with 8 seeds, K = 2,000, "
        "H = 60 (--seeds/--samples/--horizon override both)."
    ),
    "sweep": (
        "Run a scenario builder once per point of a grid over its keyword arguments, each "
        "configuration as one batch of --seeds seeds, and write sweep.csv, sweep.json and "
        "sweep.png (rates against the first varied parameter). Values are converted to the "
        "type of the builder's default; 'none', 'true'/'false' and pairs 'a:b' are understood. "
        "Example: torchcbf sweep mppi-cbf --grid method=scbf --grid rectify_gain=5,20 "
        "--seeds 8"
    ),
    "tune": (
        "Optuna search over a scenario's declared search space. Objective: the success rate "
        "over a batch of tuning seeds (from --seed, default 10,000: disjoint from the "
        "evaluation seeds 0, 1, ...) minus a tie-break below one success in mean time to "
        "goal. Writes best.json (best parameters, its objective and the default "
        "configuration's on the same seeds, both re-evaluated on the evaluation seeds), "
        "study.csv and study.png."
    ),
    "bench": (
        "Run the benchmark scripts shipped with the package (scripts/bench_*.py of the source "
        "tree, installed as torchcbf.scripts) one after the other. Peers that are not "
        "installed are skipped by each script with a message. Exits non-zero when no script "
        "is found or one fails."
    ),
}

# Help of options the scenario commands define without one.
OPTION_HELP = {
    "--methods": "comma-separated methods of scenario B to run (each one batch of seeds)",
    "--device": "torch device of the run",
    "--no-progress": "no progress bar",
}


def _add_version(parser: argparse.ArgumentParser) -> None:
    from torchcbf import __version__

    parser.add_argument(
        "--version",
        action="version",
        version=f"torchcbf {__version__} (torch {torch.__version__})",
    )


def _describe_commands(sub: Any) -> None:
    """Give every subcommand its description, the defaults in its help and missing option help."""
    for name, command in sub.choices.items():
        command.formatter_class = _HelpFormatter
        if command.description is None and name in DESCRIPTIONS:
            command.description = DESCRIPTIONS[name]
        for action in command._actions:
            for option in action.option_strings:
                if action.help is None and option in OPTION_HELP:
                    action.help = OPTION_HELP[option]


def _add_engine_options(p: argparse.ArgumentParser, seeds: int, seed: int) -> None:
    p.add_argument("scenario", choices=["reach-avoid", "mppi-cbf"], help="scenario builder")
    p.add_argument("--seeds", type=int, default=seeds, help="seeds per configuration (one batch)")
    p.add_argument("--seed", type=int, default=seed, help="first seed")
    p.add_argument("--engine", default="local", choices=["local", "ray"], help="where to run")
    p.add_argument(
        "--address",
        default=None,
        help="Ray cluster to join (default: start a local one for the run)",
    )
    p.add_argument(
        "--num-cpus", type=int, default=None, help="CPUs of the local Ray cluster (default: all)"
    )
    p.add_argument("--threads", type=int, default=1, help="torch threads per configuration")
    p.add_argument("--device", default="cpu", choices=["cpu", "cuda"], help="torch device")
    p.add_argument("--out", default="out", help="output directory")
    p.add_argument("--no-progress", dest="progress", action="store_false", help="no progress bar")


def _add_ecosystem_commands(sub: Any) -> None:
    s = sub.add_parser("sweep")
    _add_engine_options(s, seeds=8, seed=0)
    s.add_argument(
        "--grid",
        action="append",
        default=[],
        metavar="KEY=V1,V2",
        help="values of one builder keyword (repeat for a product grid; none: the defaults)",
    )
    t = sub.add_parser("tune")
    _add_engine_options(t, seeds=8, seed=10_000)
    t.add_argument("--trials", type=int, default=20, help="Optuna trials")
    t.add_argument("--eval-seed", type=int, default=0, help="first evaluation seed")
    t.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="KEY=V",
        help="a builder keyword held fixed (repeatable), e.g. method=scbf",
    )
    t.add_argument(
        "--params", default=None, help="comma-separated dimensions to search (default: all)"
    )
    t.add_argument("--sampler-seed", type=int, default=0, help="seed of the TPE sampler")
    t.add_argument("--batch", type=int, default=2, help="trials asked at once (parallel Ray tasks)")
    b = sub.add_parser("bench")
    b.add_argument("--quick", action="store_true", help="each script's short run (--quick)")
    b.add_argument("--device", default="cpu", choices=["cpu", "cuda"], help="torch device")
    b.add_argument(
        "--only",
        default=None,
        help="comma-separated benchmarks to run, by name (qp, barriers, filters, mppi)",
    )
    b.add_argument("--list", action="store_true", help="list the benchmark scripts found and exit")


def _bench_scripts() -> list[Path]:
    """The benchmark scripts of the installed package (``torchcbf.scripts``), in run order."""
    folders = []
    spec = importlib.util.find_spec("torchcbf.scripts")
    if spec is not None and spec.submodule_search_locations:
        folders = [Path(p) for p in spec.submodule_search_locations]
    checkout = Path(__file__).resolve().parent.parent / "scripts"
    if not folders and checkout.is_dir():  # a source tree used without installing
        folders = [checkout]
    found = {}
    for folder in folders:
        for path in sorted(folder.glob("bench_*.py")):
            found.setdefault(path.name, path)
    order = {name: i for i, name in enumerate(BENCHES)}
    return sorted(found.values(), key=lambda p: (order.get(p.name, len(order)), p.name))


def _bench(args: argparse.Namespace) -> int:
    scripts = _bench_scripts()
    if args.only is not None:
        wanted = {
            f"bench_{w.strip().removeprefix('bench_').removesuffix('.py')}.py"
            for w in args.only.split(",")
            if w.strip()
        }
        unknown = wanted - {p.name for p in scripts}
        if unknown:
            names = ", ".join(p.stem.removeprefix("bench_") for p in scripts) or "none"
            print(f"--only: no benchmark {sorted(unknown)}; found: {names}", file=sys.stderr)
            return 2
        scripts = [p for p in scripts if p.name in wanted]
    if not scripts:
        print(
            "torchcbf bench: no benchmark scripts found (they install with the package as "
            "torchcbf.scripts; reinstall torchcbf)",
            file=sys.stderr,
        )
        return 2
    if args.list:
        for path in scripts:
            print(f"{path.stem.removeprefix('bench_'):<10} {path}")
        return 0
    failed = []
    for path in scripts:
        cmd = [sys.executable, str(path), *(["--quick"] if args.quick else [])]
        cmd += ["--device", args.device]
        print(f"$ {' '.join(cmd)}", flush=True)
        if subprocess.call(cmd) != 0:
            failed.append(path.name)
    if failed:
        print(f"torchcbf bench: failed: {', '.join(failed)}", file=sys.stderr)
        return 1
    return 0


def _print_rows(rows: list[dict[str, Any]], keys: list[str]) -> None:
    def pct(row: dict[str, Any], name: str) -> str:
        if f"{name}_rate" not in row:
            return "-"
        lo, hi = row[f"{name}_ci95_low"], row[f"{name}_ci95_high"]
        return f"{100 * row[f'{name}_rate']:.0f}% ({100 * lo:.0f}-{100 * hi:.0f})"

    def num(value: Any, fmt: str) -> str:
        return "-" if value is None else fmt.format(value)

    from torchcbf.sweep.params import describe

    print(
        f"{'configuration':<36} {'success (95% CI)':>17} {'collision (95% CI)':>19} "
        f"{'t_goal [s]':>10} {'min barrier':>11} {'wall [s]':>8}"
    )
    for row in rows:
        name = row.get("label") or describe({k: row[k] for k in keys}) or "defaults"
        print(
            f"{name:<36} {pct(row, 'success'):>17} {pct(row, 'collision'):>19} "
            f"{num(row.get('time_to_goal_s'), '{:.2f}'):>10} "
            f"{num(row.get('min_h'), '{:.3f}'):>11} {row['wall_s']:>8.1f}"
        )


def _sweep(args: argparse.Namespace) -> int:
    from torchcbf.sweep import parse_grid, run_sweep, write_sweep

    try:
        grid = parse_grid(args.scenario, args.grid)
        rows = run_sweep(
            args.scenario,
            grid,
            num_seeds=args.seeds,
            seed=args.seed,
            device=args.device,
            engine=args.engine,
            address=args.address,
            num_cpus=args.num_cpus,
            threads=args.threads,
            progress=args.progress,
        )
    except (ValueError, ImportError) as error:
        print(f"torchcbf sweep: {error}", file=sys.stderr)
        return 2
    _print_rows(rows, list(grid))
    paths = write_sweep(
        rows,
        grid,
        args.out,
        scenario=args.scenario,
        num_seeds=args.seeds,
        first_seed=args.seed,
        engine=args.engine,
        device=args.device,
        threads=args.threads,
    )
    print("wrote " + ", ".join(str(p) for p in paths.values()))
    return 0


def _tune(args: argparse.Namespace) -> int:
    from torchcbf.sweep import parse_value, tune, write_tune

    try:
        import optuna

        optuna.logging.set_verbosity(optuna.logging.WARNING)
    except ImportError:
        print('torchcbf tune needs Optuna: pip install "torchcbf[tune]"', file=sys.stderr)
        return 2
    try:
        fixed = {}
        for item in args.set:
            key, sep, value = item.partition("=")
            if not sep:
                raise ValueError(f"--set takes KEY=VALUE, got {item!r}")
            fixed[key.strip()] = parse_value(args.scenario, key.strip(), value)
        result = tune(
            args.scenario,
            trials=args.trials,
            num_seeds=args.seeds,
            seed=args.seed,
            eval_seed=args.eval_seed,
            fixed=fixed,
            params=None if args.params is None else [p.strip() for p in args.params.split(",")],
            sampler_seed=args.sampler_seed,
            batch=args.batch,
            device=args.device,
            engine=args.engine,
            address=args.address,
            num_cpus=args.num_cpus,
            threads=args.threads,
            progress=args.progress,
        )
    except (ValueError, ImportError) as error:
        print(f"torchcbf tune: {error}", file=sys.stderr)
        return 2
    best, default = result["best"], result["default"]
    print(f"best trial {best['trial']}: {best['arguments']}")
    print(
        f"objective on the tuning seeds {args.seed}..{args.seed + args.seeds - 1}: "
        f"best {best['objective']:.4f}, default configuration {default['objective']:.4f}"
    )
    print(f"on the evaluation seeds {args.eval_seed}..{args.eval_seed + args.seeds - 1}:")
    evaluation = result["evaluation"]
    labelled = [{**evaluation[k], "label": k} for k in ("best", "default")]
    _print_rows(labelled, [])
    paths = write_tune(result, args.out, engine=args.engine, device=args.device)
    print("wrote " + ", ".join(str(p) for p in paths.values()))
    return 0


ECOSYSTEM_COMMANDS = {"bench": _bench, "sweep": _sweep, "tune": _tune}


if __name__ == "__main__":
    raise SystemExit(main())
