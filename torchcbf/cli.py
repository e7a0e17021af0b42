"""The ``torchcbf`` command: run the reference scenarios, write metrics and figures, run the
benchmarks.

    torchcbf reach-avoid [--seeds N --samples K --horizon H --device cpu|cuda --out DIR]
    torchcbf mppi-cbf    [--config default|paper|cbfkit --methods all|scbf,mppi,... --seeds N ...]
    torchcbf demo        both scenarios (B in its default configuration) at sizes that finish
                         in a few minutes on 2 CPU cores
    torchcbf sweep       a grid over a scenario builder's keyword arguments (local or Ray)
    torchcbf tune        Optuna search over a scenario's declared search space (local or Ray)
    torchcbf bench       the benchmark scripts shipped with the package
    torchcbf info        versions, devices and the C kernels of this installation

Every run prints its settings and a table, and writes ``metrics.json`` (strict JSON: ``null``
where a value is undefined, e.g. the time of a goal never reached) with the settings, the
software versions and the git commit, and the figures (PNG, GIF) to ``--out``.

Every command checks its arguments, its device and its output folder before any work. A
non-empty ``--out`` that is not this command's own run is refused unless ``--overwrite``
(which removes the outputs of earlier torchcbf runs there); ``--resume`` continues an
interrupted run, keeping what finished. Ctrl-C ends a run cleanly (exit code 130) with what
finished saved, and says how to resume. Every file is written to a temporary name and renamed.
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import shlex
import subprocess
import sys
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import torch

from torchcbf import _io
from torchcbf.sim import Trajectory, run_info, strict, summarize

# Benchmarks in the order ``torchcbf bench`` runs them (each a script of scripts/).
BENCHES = ("bench_qp.py", "bench_barriers.py", "bench_filters.py", "bench_mppi.py")
PAPER_SIZE_B = "torchcbf mppi-cbf --config default --seeds 32 --samples 20000 --horizon 80"


INTERRUPTED = 130  # the exit code of a run ended by Ctrl-C (128 + SIGINT)


def _save(fig: Any, path: Path) -> Path:
    return _io.save_figure(fig, path, bbox_inches="tight")


def _save_animation(make: Callable[..., Any], path: Path, *args: Any, **kwargs: Any) -> Path:
    """``make(*args[0:1], tmp, *args[1:], **kwargs)`` writes an animation; renamed to ``path``."""
    with _io.atomic_path(path) as tmp:
        make(args[0], tmp, *args[1:], **kwargs)
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


def _reach_avoid(args: argparse.Namespace, parts: _Parts) -> dict[str, Any]:
    from torchcbf.scenarios import reach_avoid
    from torchcbf.viz import animate, plot_trajectories

    def build(num_seeds: int) -> Any:
        return reach_avoid(
            num_seeds=num_seeds,
            num_samples=args.samples,
            horizon=args.horizon,
            seed=args.seed,
            device=args.device,
        )

    print(
        f"\nScenario A (reach-avoid, single integrator): {args.seeds} seeds from {args.seed}, "
        f"MPPI K = {args.samples}, H = {args.horizon}, device {args.device}"
    )
    print(A_HEADER)

    def compute() -> tuple[dict[str, Any], Any]:
        scenario = build(args.seeds)
        start = time.perf_counter()
        traj, per_seed = scenario.run(progress=args.progress)
        seconds = time.perf_counter() - start
        entry = {
            "settings": {
                "seeds": args.seeds,
                "first_seed": args.seed,
                "num_samples": args.samples,
                "horizon": args.horizon,
            },
            "units": {"min_h": "m (clearance |p - o| - r_o)", "seconds": "s"},
            "summary": summarize(per_seed),
            "per_seed": per_seed,
            "seconds": seconds,
        }
        return entry, traj

    entry, cpu = parts.unit("reach-avoid", compute)
    summary = entry["summary"]
    print(
        f"{'reach-avoid':<14} {_rate(summary, 'spec_satisfied'):>20} "
        f"{_rate(summary, 'collision'):>20} {_num(summary['min_h']['min']):>18} "
        f"{entry['seconds']:>9.1f}",
        flush=True,
    )
    scenario = build(1)  # its obstacles and goals, for the figures
    out = parts.run.path
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
        figures.append(
            _save_animation(
                animate, out / "reach_avoid.gif", cpu, scenario.barriers, scenario.goals
            )
        )
    return {"reach-avoid": {**entry, "figures": [str(p) for p in figures]}}


class _Parts:
    """The finished units of a scenario run (scenario A, each method of B), each saved as it
    finishes under ``--out/.parts``: its metrics (JSON) and its trajectory
    (:meth:`Trajectory.save`). A resumed run loads the units found there instead of running
    them; the figures and ``metrics.json`` are always made from the saved units, so a
    resumed run's outputs equal an uninterrupted one's."""

    def __init__(self, run: Any) -> None:
        from torchcbf.sweep.rundir import PARTS

        self.run = run
        self.folder = run.path / PARTS
        self.folder.mkdir(exist_ok=True)
        _io.remove_stale(self.folder)
        self.done: list[str] = []

    def unit(
        self, name: str, compute: Callable[[], tuple[dict[str, Any], Any]]
    ) -> tuple[dict[str, Any], Trajectory]:
        stem = name.replace("/", "_")
        metrics_path, traj_path = self.folder / f"{stem}.json", self.folder / f"{stem}.pt"
        if not (self.run.resumed and metrics_path.exists() and traj_path.exists()):
            entry, traj = compute()
            traj.to("cpu").save(traj_path)
            _io.write_json(metrics_path, strict(entry))  # last: its presence marks the unit done
        self.done.append(name)
        return json.loads(metrics_path.read_text()), Trajectory.load(traj_path)


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


def _mppi_cbf(args: argparse.Namespace, parts: _Parts) -> dict[str, Any]:
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

    def build(method: str, num_seeds: int) -> Any:
        return mppi_cbf(
            method,
            config=args.config,
            num_seeds=num_seeds,
            num_samples=args.samples,
            horizon=args.horizon,
            seed=args.seed,
            device=args.device,
        )

    for method in methods:

        def compute(method: str = method) -> tuple[dict[str, Any], Any]:
            scenario = build(method, args.seeds)
            start = time.perf_counter()
            traj, per_seed = scenario.run(progress=args.progress)
            seconds = time.perf_counter() - start
            entry = {
                "params": scenario.params,
                "units": {
                    "min_h": "ellipse value b_i (dimensionless; < 0 inside)",
                    "goal0_time": "s",
                    "goal0_final_distance": "m",
                    "seconds": "s",
                },
                "summary": summarize(per_seed),
                "per_seed": per_seed,
                "seconds": seconds,
            }
            return entry, traj

        key = f"mppi-cbf/{args.config}/{method}"
        entry, trajectories[method] = parts.unit(key, compute)
        print(_b_row(method, entry["summary"], STEPS, entry["seconds"]), flush=True)
        results[key] = entry
    scenario = build(methods[-1], 1)  # its obstacles and goals, for the figures
    figures = _b_figures(trajectories, scenario, parts.run.path, args)
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
            _save_animation(
                animate_methods,
                out / f"{stem}.gif",
                trajectories,
                scenario.barriers,
                scenario.goals,
                title=f"scenario B, '{args.config}', seed {args.seed}",
                **view,
            )
        )
    return figures


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
    _add_output_options(p)
    p.add_argument("--no-progress", dest="progress", action="store_false", help="no progress bars")
    p.add_argument("--no-gif", action="store_true", help="skip the GIF animations")


def _add_output_options(p: argparse.ArgumentParser) -> None:
    group = p.add_mutually_exclusive_group()
    group.add_argument(
        "--resume",
        action="store_true",
        help="continue the interrupted run in --out (same arguments), keeping what finished",
    )
    group.add_argument(
        "--overwrite",
        action="store_true",
        help="replace the outputs of an earlier torchcbf run in a non-empty --out",
    )


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
    _add_version(parser)
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
    _add_ecosystem_commands(sub)
    _describe_commands(sub)
    return parser


def _run_arguments(argv: Sequence[str]) -> list[str]:
    """``argv`` without the flags that only say how to treat ``--out`` (what identifies a run)."""
    return [a for a in argv if a not in ("--resume", "--overwrite")]


def _resume_hint(argv: Sequence[str]) -> str:
    """The command line that continues this run."""
    return "torchcbf " + " ".join(shlex.quote(a) for a in [*_run_arguments(argv), "--resume"])


def _interrupted(command: str, argv: Sequence[str], out: Path, saved: str) -> int:
    print(
        f"\ntorchcbf {command}: interrupted; {saved} saved in {out}. Continue with:\n  "
        f"{_resume_hint(argv)}",
        file=sys.stderr,
        flush=True,
    )
    return INTERRUPTED


def _scenario_settings(args: argparse.Namespace) -> dict[str, Any]:
    names = ("seeds", "seed", "samples", "horizon", "device", "no_gif")
    settings = {name: getattr(args, name) for name in names}
    if args.command != "reach-avoid":
        settings.update(config=args.config, methods=_methods(args.methods))
    return settings


def main(argv: Sequence[str] | None = None) -> int:
    """Run the ``torchcbf`` command; the exit code (130 after Ctrl-C)."""
    try:
        return _main(argv)
    except KeyboardInterrupt:  # before a run started: nothing to save
        print("\ntorchcbf: interrupted", file=sys.stderr)
        return INTERRUPTED


def _main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    argv = list(sys.argv[1:] if argv is None else argv)
    args = parser.parse_args(argv)
    if getattr(args, "device", "cpu") == "cuda" and not torch.cuda.is_available():
        parser.error("argument --device: cuda, but CUDA is not available on this machine")
    if args.command in ECOSYSTEM_COMMANDS:
        return ECOSYSTEM_COMMANDS[args.command](args, argv)
    from torchcbf.sweep.rundir import OutputError, RunDir

    try:
        run = RunDir.claim(
            args.out,
            kind=args.command,
            settings=_scenario_settings(args),
            resume=args.resume,
            overwrite=args.overwrite,
        )
    except OutputError as error:
        print(f"torchcbf {args.command}: {error}", file=sys.stderr)
        return 2
    parts = _Parts(run)
    try:
        if args.command == "reach-avoid":
            results = _reach_avoid(args, parts)
        elif args.command == "mppi-cbf":
            results = _mppi_cbf(args, parts)
        else:
            sizes = {"seeds": 4, "samples": 10_000, "horizon": 50}
            demo_a = argparse.Namespace(**{**vars(args), **sizes})
            results = {**_reach_avoid(demo_a, parts), **_mppi_cbf(args, parts)}
            print(f"\nThe paper's size of scenario B (32 seeds, K = 20,000): {PAPER_SIZE_B}")
        record = {"command": " ".join(_run_arguments(argv)), "run": run_info(args.device)}
        metrics_path = run.path / "metrics.json"
        _io.write_json(metrics_path, strict({**record, "results": results}))
    except KeyboardInterrupt:
        saved = f"{len(parts.done)} finished part(s) ({', '.join(parts.done) or 'none'})"
        return _interrupted(args.command, argv, run.path, saved)
    figures = {Path(f).name for entry in results.values() for f in entry.get("figures", [])}
    run.record(metrics_path, *sorted(figures))
    run.finish()
    out = run.path
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


# One paragraph per subcommand of this section, shown by ``torchcbf <command> --help``.
DESCRIPTIONS = {
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
    "info": (
        "Print torchcbf's and torch's versions, the devices torch sees, its threads and every "
        "C kernel: its version, whether it loaded, its file, and what runs without it "
        "(torchcbf.info())."
    ),
    "bench": (
        "Run the benchmark scripts shipped with the package (scripts/bench_*.py of the source "
        "tree, installed as torchcbf.scripts) one after the other. Peers that are not "
        "installed are skipped by each script with a message. Exits non-zero when no script "
        "is found or one fails."
    ),
}

# Help of options the other subcommands define without one.
OPTION_HELP = {"--device": "torch device of the run"}


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
    p.add_argument(
        "--seeds", type=_positive_int, default=seeds, help="seeds per configuration (one batch)"
    )
    p.add_argument("--seed", type=int, default=seed, help="first seed")
    p.add_argument("--engine", default="local", choices=["local", "ray"], help="where to run")
    p.add_argument(
        "--address",
        default=None,
        help="Ray cluster to join (default: start a local one for the run)",
    )
    p.add_argument(
        "--num-cpus",
        type=_positive_int,
        default=None,
        help="CPUs of the local Ray cluster (default: all)",
    )
    p.add_argument(
        "--threads", type=_positive_int, default=1, help="torch threads per configuration"
    )
    p.add_argument("--device", default="cpu", choices=["cpu", "cuda"], help="torch device")
    p.add_argument("--out", default="out", help="output directory")
    _add_output_options(p)
    p.add_argument("--no-progress", dest="progress", action="store_false", help="no progress bar")


def _add_ecosystem_commands(sub: Any) -> None:
    s = sub.add_parser("sweep", help="a grid over a scenario's keyword arguments")
    _add_engine_options(s, seeds=8, seed=0)
    s.add_argument(
        "--grid",
        action="append",
        default=[],
        metavar="KEY=V1,V2",
        help="values of one builder keyword (repeat for a product grid; none: the defaults)",
    )
    t = sub.add_parser("tune", help="Optuna search over a scenario's parameters")
    _add_engine_options(t, seeds=8, seed=10_000)
    t.add_argument("--trials", type=_positive_int, default=20, help="Optuna trials")
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
    t.add_argument(
        "--batch", type=_positive_int, default=2, help="trials asked at once (parallel Ray tasks)"
    )
    b = sub.add_parser("bench", help="run the benchmark scripts")
    b.add_argument("--quick", action="store_true", help="each script's short run (--quick)")
    b.add_argument("--device", default="cpu", choices=["cpu", "cuda"], help="torch device")
    b.add_argument(
        "--only",
        default=None,
        help="comma-separated benchmarks to run, by name (qp, barriers, filters, mppi)",
    )
    b.add_argument("--list", action="store_true", help="list the benchmark scripts found and exit")
    i = sub.add_parser("info", help="versions, devices and the C kernels of this installation")
    i.add_argument("--json", action="store_true", help="print the report as JSON")


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


def _bench(args: argparse.Namespace, argv: Sequence[str] = ()) -> int:
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
        name = row.get("label") or describe({k: row[k] for k in keys if k in row}) or "defaults"
        if row.get("status", "ok") != "ok":
            print(f"{name:<36} failed: {row.get('error')}")
            continue
        print(
            f"{name:<36} {pct(row, 'success'):>17} {pct(row, 'collision'):>19} "
            f"{num(row.get('time_to_goal_s'), '{:.2f}'):>10} "
            f"{num(row.get('min_h'), '{:.3f}'):>11} {row['wall_s']:>8.1f}"
        )


def _engine_options(args: argparse.Namespace) -> dict[str, Any]:
    """Where and how ``sweep`` and ``tune`` run their configurations (their common options)."""
    names = ("device", "engine", "address", "num_cpus", "threads", "progress")
    return {name: getattr(args, name) for name in names}


def _check_engine(command: str, args: argparse.Namespace) -> bool:
    if args.engine == "ray" and importlib.util.find_spec("ray") is None:
        print(f'torchcbf {command}: --engine ray needs Ray: pip install "torchcbf[ray]"',
              file=sys.stderr)  # fmt: skip
        return False
    return True


def _sweep(args: argparse.Namespace, argv: Sequence[str] = ()) -> int:
    from torchcbf.sweep import parse_grid, run_sweep
    from torchcbf.sweep.sweep import JOURNAL, read_journal

    if not _check_engine("sweep", args):
        return 2
    try:
        grid = parse_grid(args.scenario, args.grid)
    except ValueError as error:
        print(f"torchcbf sweep: {error}", file=sys.stderr)
        return 2
    try:
        rows = run_sweep(
            args.scenario,
            grid,
            num_seeds=args.seeds,
            seed=args.seed,
            out=args.out,
            resume=args.resume,
            overwrite=args.overwrite,
            **_engine_options(args),
        )
    except (ValueError, ImportError) as error:
        print(f"torchcbf sweep: {error}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        out = Path(args.out)
        saved = f"{len(read_journal(out / JOURNAL))} finished configuration(s)"
        return _interrupted("sweep", argv, out, saved)
    _print_rows(rows, list(grid))
    failed = sum(row["status"] != "ok" for row in rows)
    if failed:
        print(f"{failed} of {len(rows)} configuration(s) failed (status and error in the table)")
    out = Path(args.out)
    print("wrote " + ", ".join(str(out / n) for n in ("sweep.csv", "sweep.json", "sweep.png")))
    return 0


def _tune(args: argparse.Namespace, argv: Sequence[str] = ()) -> int:
    from torchcbf.sweep import parse_value, tune

    try:
        import optuna

        optuna.logging.set_verbosity(optuna.logging.WARNING)
    except ImportError:
        print('torchcbf tune needs Optuna: pip install "torchcbf[tune]"', file=sys.stderr)
        return 2
    if not _check_engine("tune", args):
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
            out=args.out,
            resume=args.resume,
            overwrite=args.overwrite,
            **_engine_options(args),
        )
    except (ValueError, ImportError) as error:
        print(f"torchcbf tune: {error}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        return _interrupted("tune", argv, Path(args.out), "every finished trial")
    best, default = result["best"], result["default"]
    if result["failed_trials"]:
        print(f"failed trials (error in study.csv): {result['failed_trials']}")
    if best is None:
        print("every trial failed: no best configuration")
    else:
        print(f"best trial {best['trial']}: {best['arguments']}")
        print(
            f"objective on the tuning seeds {args.seed}..{args.seed + args.seeds - 1}: "
            f"best {best['objective']:.4f}, default configuration "
            f"{_num(default['objective'], '{:.4f}')}"
        )
    print(f"on the evaluation seeds {args.eval_seed}..{args.eval_seed + args.seeds - 1}:")
    evaluation = result["evaluation"]
    labelled = [{**evaluation[k], "label": k} for k in ("best", "default") if evaluation[k]]
    _print_rows(labelled, [])
    out = Path(args.out)
    print(
        "wrote "
        + ", ".join(str(out / n) for n in ("best.json", "study.csv", "study.png", "study.db"))
    )
    return 0


def _info(args: argparse.Namespace, argv: Sequence[str] = ()) -> int:
    from torchcbf._info import format_info, info

    report = info()
    print(json.dumps(report, indent=2) if args.json else format_info(report))
    return 0


ECOSYSTEM_COMMANDS = {"bench": _bench, "info": _info, "sweep": _sweep, "tune": _tune}


if __name__ == "__main__":
    raise SystemExit(main())
