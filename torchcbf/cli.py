"""The ``torchcbf`` command: run the registered scenarios, write metrics and figures, sweep
and tune them, run the benchmarks.

    torchcbf NAME        a registered scenario (reach-avoid, mppi-cbf, arm-reach, and any
                         registered by --import MODULE or a package's entry point):
                         [--seeds N --set KEY=VALUE ... --device cpu|cuda --out DIR], its
                         own options (reach-avoid: --samples K --horizon H; mppi-cbf:
                         --config default|paper|cbfkit --methods all|scbf,mppi,...)
    torchcbf demo        scenarios A and B (B in its default configuration) at sizes that
                         finish in a few minutes on 2 CPU cores
    torchcbf sweep       a grid over a scenario's parameters (local or Ray)
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
finished saved, and says how to resume. A sweep whose every configuration failed, or a tune
whose every trial did, exits with code 1, as does a run whose figures failed (its
``metrics.json`` is written, with the error under ``figures_failed``). Every file is
written to a temporary name and renamed.
"""

from __future__ import annotations

import argparse
import functools
import importlib.util
import json
import os
import shlex
import signal
import subprocess
import sys
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import torch

from torchcbf import _io
from torchcbf._argtypes import positive_int
from torchcbf._argtypes import seed as seed_type
from torchcbf._checks import check_device
from torchcbf.sim import Trajectory, run_info, strict

# Benchmarks in the order ``torchcbf bench`` runs them (each a script of scripts/).
BENCHES = ("bench_qp.py", "bench_barriers.py", "bench_filters.py", "bench_mppi.py")
PAPER_SIZE_B = "torchcbf mppi-cbf --config default --seeds 32 --samples 20000 --horizon 80"


INTERRUPTED = 130  # the exit code of a run ended by Ctrl-C (128 + SIGINT)
FAILED = 1  # the exit code of a sweep whose every configuration (a tune whose every trial) failed


def _num(value: float | None, fmt: str = "{:.3f}") -> str:
    return "-" if value is None else fmt.format(value)


class _Parts:
    """The finished units of a scenario run (one per variant: scenario B's methods), each
    saved as it finishes under ``--out/.parts``: its metrics (JSON) and its trajectory
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


def _variants(entry: Any, text: str | None) -> list[Any]:
    """The variant values a run compares (``all`` or a comma-separated list), ``[None]`` for
    a scenario without variants."""
    if entry.variant is None:
        return [None]
    allowed = tuple(entry.choices.get(entry.variant, ()))
    names = list(allowed) if text == "all" else [v.strip() for v in text.split(",") if v.strip()]
    unknown = [v for v in names if allowed and v not in allowed]
    if unknown or not names:
        raise ValueError(f"--{entry.variant}s must be 'all' or a list from {allowed}, got {text!r}")
    repeated = sorted({v for v in names if names.count(v) > 1})
    if repeated:
        raise ValueError(f"--{entry.variant}s names {', '.join(repeated)} more than once")
    return names


def _plan(
    entry: Any, args: argparse.Namespace, sizes: dict[str, Any] | None
) -> tuple[int, dict[str, Any], list[Any]]:
    """What a run of ``entry`` does: its seeds, its parameters (the command line's, then the
    demo's ``sizes``) and the variants it compares (``--set`` of the variant names one)."""
    params = _parameters(entry, args)
    num_seeds = getattr(args, "seeds", None) or entry.num_seeds  # the demo has no --seeds
    if sizes is not None:
        sizes = dict(sizes)
        num_seeds = sizes.pop("num_seeds", num_seeds)
        params.update(sizes)
    text = getattr(args, "variants", None)
    if text is None:  # not given (an empty list given is an error, as ',' is)
        text = "all"
    if entry.variant is not None and entry.variant in params:
        if text != "all":
            raise ValueError(f"give --{entry.variant}s or --set {entry.variant}=..., not both")
        return num_seeds, params, _variants(entry, str(params.pop(entry.variant)))
    return num_seeds, params, _variants(entry, text)


def _unit_key(entry: Any, params: dict[str, Any], variant: Any) -> str:
    """``NAME[/choice-valued options...][/variant]``: the name of a run's unit."""
    values = {**entry.defaults(), **params}
    parts = [entry.name]
    parts += [str(values[key]) for key in entry.options.values() if key in entry.choices]
    return "/".join(parts + ([str(variant)] if variant is not None else []))


def _run_scenario(
    entry: Any, args: argparse.Namespace, parts: _Parts, sizes: dict[str, Any] | None = None
) -> dict[str, Any]:
    """Run ``entry`` with the command's parameters (``sizes`` override them: the demo's),
    one batch per variant; print the table; draw the figures."""
    from torchcbf.sim.metrics import summarize
    from torchcbf.sweep.params import describe

    num_seeds, params, variants = _plan(entry, args, sizes)
    label_width = max(12, *(len(str(v)) for v in variants if v is not None), len(entry.name))
    widths = [max(len(c.header), 15) for c in entry.columns]
    values = {**entry.defaults(), **params}
    shown = describe({**{k: values[k] for k in entry.options.values()}, **params}) or "defaults"
    print(
        f"\n{entry.name}"
        + (f": {entry.description}" if entry.description else "")
        + f"\n{num_seeds} seeds from {args.seed}, "
        f"{shown}, device {args.device}"
    )
    header = " ".join(f"{c.header:>{w}}" for c, w in zip(entry.columns, widths, strict=True))
    label = entry.variant or "scenario"
    print(f"{label:<{label_width}} {header} {'wall [s]':>9}", flush=True)
    results: dict[str, Any] = {}
    trajectories: dict[str, Any] = {}
    for variant in variants:
        run_params = {**params, entry.variant: variant} if variant is not None else params

        def compute(run_params: dict[str, Any] = run_params) -> tuple[dict[str, Any], Any]:
            scenario = entry.make(
                **run_params, num_seeds=num_seeds, seed=args.seed, device=args.device
            )
            start = time.perf_counter()
            traj, per_seed = scenario.run(progress=args.progress)
            seconds = time.perf_counter() - start
            record = {
                "settings": {"seeds": num_seeds, "first_seed": args.seed, **run_params},
                "params": scenario.params,
                "units": dict(entry.units),
                "summary": summarize(per_seed),
                "per_seed": per_seed,
                "seconds": seconds,
            }
            return record, traj

        key = _unit_key(entry, run_params, variant)
        record, traj = parts.unit(key, compute)
        name = str(variant) if variant is not None else entry.name
        trajectories[name] = traj
        cells = " ".join(
            f"{c.cell(record['summary']):>{w}}" for c, w in zip(entry.columns, widths, strict=True)
        )
        print(f"{name:<{label_width}} {cells} {record['seconds']:>9.1f}", flush=True)
        results[key] = record
    folder = parts.run.path
    before = set(os.listdir(folder))
    failure = None
    try:
        figures = _draw(entry, args, params, run_params, num_seeds, trajectories, folder)
    except Exception as error:  # the results stand without their figures: keep them
        failure = f"{type(error).__name__}: {error}"
        print(f"torchcbf {args.command}: the figures of {entry.name} failed: {failure}",
              file=sys.stderr)  # fmt: skip
    finally:
        # the figures drawn so far, in the manifest even where Ctrl-C cut the drawing: an
        # --overwrite removes them with the rest of the run
        drawn = sorted(n for n in set(os.listdir(folder)) - before)
        drawn = [n for n in drawn if not _io.is_temporary(folder / n)]
        parts.run.record(*drawn)
    if failure is not None:
        figures = [folder / n for n in drawn]
    for record in results.values():
        record["figures"] = [str(p) for p in figures]
        if failure is not None:
            record["figures_failed"] = failure
    return results


def _draw(
    entry: Any,
    args: argparse.Namespace,
    params: dict[str, Any],
    run_params: dict[str, Any],
    num_seeds: int,
    trajectories: dict[str, Any],
    folder: Path,
) -> list[Path]:
    """The figures of a finished run of ``entry`` into ``folder`` (figures left open by a
    failure are closed)."""
    import matplotlib.pyplot as plt

    from torchcbf.scenarios.figures import standard_figures

    scenario = entry.make(**run_params, num_seeds=num_seeds, seed=args.seed, device="cpu")
    values = {**entry.defaults(), **params}
    named = {k: values[k] for k in entry.options.values() if k in entry.choices}
    named.update({k: v for k, v in params.items() if k not in named})
    title = ", ".join([entry.name, *(f"{k}={v}" for k, v in named.items())])
    draw = entry.figures or functools.partial(standard_figures, stem=entry.name.replace("-", "_"))
    opened = set(plt.get_fignums())
    try:
        return draw(
            trajectories, scenario, folder, title=title, gif=not args.no_gif,
            first_seed=args.seed,
        )  # fmt: skip
    except BaseException:
        for number in set(plt.get_fignums()) - opened:
            plt.close(number)
        raise


def _parameters(entry: Any, args: argparse.Namespace) -> dict[str, Any]:
    """The parameters the command line sets: its options, then ``--set KEY=VALUE``."""
    from torchcbf.sweep.params import parse_value

    params = {}
    by_flag = {}
    for flag, key in entry.options.items():
        value = getattr(args, _dest(flag), None)
        if value is not None:
            params[key] = value
            by_flag[key] = flag
    by_set: dict[str, str] = {}
    for item in getattr(args, "set", None) or []:
        key, sep, value = item.partition("=")
        key = key.strip()
        if not sep:
            raise ValueError(f"--set takes KEY=VALUE, got {item!r}")
        if key in by_flag:
            raise ValueError(f"give --{by_flag[key]} or --set {key}=..., not both")
        if key in by_set:
            raise ValueError(f"--set {key} given twice ({by_set[key]!r} and {item!r})")
        by_set[key] = item
        try:
            params[key] = parse_value(entry, key, value)
        except ValueError as error:
            raise ValueError(f"--set {item}: {error}") from None
    return params


def _dest(flag: str) -> str:
    return "option_" + flag.replace("-", "_")


# -- command line --------------------------------------------------------------------------
def _common_run_options(p: argparse.ArgumentParser) -> None:
    p.add_argument("--seed", type=seed_type, default=0, help="first seed")
    p.add_argument("--device", default="cpu", choices=["cpu", "cuda"])
    p.add_argument("--out", default="out", help="directory for metrics.json and the figures")
    _add_output_options(p)
    p.add_argument("--no-progress", dest="progress", action="store_false", help="no progress bars")
    p.add_argument("--no-gif", action="store_true", help="skip the GIF animations")


def _option_type(entry: Any, key: str) -> Callable[[str], Any]:
    """A parameter's value read from text, with argparse's message on a bad value."""
    from torchcbf.sweep.params import parse_value

    kinds = [k for k in entry.types()[key] if k in (int, float, str, bool)]
    kind = kinds[0].__name__ if kinds else "value"

    def read(text: str) -> Any:
        try:
            return parse_value(entry, key, text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"invalid {kind} value: {text!r}") from None

    read.__name__ = kind
    return read


def _add_scenario_command(sub: Any, entry: Any) -> None:
    """``torchcbf NAME``: the registered scenario ``entry`` over one batch of seeds."""
    p = sub.add_parser(
        entry.name,
        help=(entry.description.split(": ")[0] if entry.description else entry.name),
        description=entry.description or None,
    )
    p.add_argument(
        "--seeds",
        type=positive_int,
        default=entry.num_seeds,
        help="noise/planner seeds, run as one batch",
    )
    defaults = entry.defaults()
    for flag, key in entry.options.items():
        p.add_argument(
            f"--{flag}",
            dest=_dest(flag),
            metavar=None if entry.choices.get(key) else flag.replace("-", "_").upper(),
            type=_option_type(entry, key),
            choices=entry.choices.get(key),
            default=None,
            help=f"the parameter {key} (default: {defaults[key]})",
        )
    if entry.variant is not None:
        allowed = ", ".join(map(str, entry.choices.get(entry.variant, ())))
        p.add_argument(
            f"--{entry.variant}s",
            dest="variants",
            default="all",
            help=f"'all' or a comma-separated list of {allowed}: one batch and table row each",
        )
    p.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="any other parameter of the scenario (repeatable)",
    )
    _common_run_options(p)


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


def build_parser() -> argparse.ArgumentParser:
    """The ``torchcbf`` argument parser (one command per registered scenario)."""
    from torchcbf.scenarios import scenarios

    parser = argparse.ArgumentParser(
        prog="torchcbf", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    _add_version(parser)
    parser.add_argument(
        "--import",
        dest="imports",
        action="append",
        default=[],
        metavar="MODULE",
        help="import MODULE first (a module that registers scenarios; repeatable)",
    )
    sub = parser.add_subparsers(dest="command", required=True)
    for entry in scenarios().values():
        _add_scenario_command(sub, entry)
    d = sub.add_parser(
        "demo",
        help="the reference scenarios at sizes that finish in a few minutes",
        description="Every registered scenario with demo sizes: scenario A (4 seeds, K = "
        "10,000, H = 50) and scenario B in its default configuration, every method (8 seeds, "
        f"K = 1,000, H = 80). The paper's size of B: {PAPER_SIZE_B}.",
    )
    _common_run_options(d)
    _add_ecosystem_commands(sub)
    _describe_commands(sub)
    return parser


def _imports(argv: Sequence[str]) -> list[str]:
    """The modules named by ``--import`` before the command (read before the parser is
    built, since their scenarios add commands)."""
    found = []
    for i, arg in enumerate(argv):
        if arg == "--import" and i + 1 < len(argv):
            found.append(argv[i + 1])
        elif arg.startswith("--import="):
            found.append(arg.partition("=")[2])
        elif not arg.startswith("-"):
            break
    return found


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


def _scenario_settings(args: argparse.Namespace, plan: list[tuple[Any, Any]]) -> dict:
    """What identifies a scenario run (compared by ``--resume``): per scenario its seeds,
    every parameter resolved (defaults included, so a run is not resumed across a change of
    defaults) and the variants it compares."""
    settings: dict[str, Any] = {"seed": args.seed, "device": args.device, "no_gif": args.no_gif}
    for entry, sizes in plan:
        num_seeds, params, variants = _plan(entry, args, sizes)
        settings[entry.name] = strict(
            {
                "num_seeds": num_seeds,
                "params": {**entry.defaults(), **params},
                "variants": variants,
            }
        )
    return settings


def main(argv: Sequence[str] | None = None) -> int:
    """Run the ``torchcbf`` command; the exit code (130 after Ctrl-C or a SIGTERM, which a
    run answers as it answers Ctrl-C: finished work saved, a command to continue)."""
    try:
        previous = signal.signal(signal.SIGTERM, _terminate)
    except ValueError:  # not the main thread: the signal stays as it is
        previous = None
    try:
        return _main(argv)
    except KeyboardInterrupt:  # before a run started: nothing to save
        print("\ntorchcbf: interrupted", file=sys.stderr)
        return INTERRUPTED
    except BrokenPipeError:  # the reader left (`torchcbf info | head`): nothing more to say
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())  # no second error when Python flushes at exit
        return 1
    finally:
        if previous is not None:
            signal.signal(signal.SIGTERM, previous)


def _terminate(signum: int, frame: object) -> None:
    raise KeyboardInterrupt


def _main(argv: Sequence[str] | None = None) -> int:
    from torchcbf.scenarios import import_scenarios, scenarios

    argv = list(sys.argv[1:] if argv is None else argv)
    for module in _imports(argv):
        try:
            import_scenarios(module)
        except ImportError as error:
            print(f"torchcbf: --import {module}: {error}", file=sys.stderr)
            return 2
    parser = build_parser()
    args = parser.parse_args(argv)
    from torchcbf.sweep.params import check_seeds

    for first, count in (("seed", "seeds"), ("eval_seed", "eval_seeds")):
        start, n = getattr(args, first, None), getattr(args, count, None)
        if start is not None and n is not None:
            try:
                check_seeds(start, n)
            except ValueError as error:
                parser.error(f"argument --{first.replace('_', '-')}: {error}")
    if getattr(args, "device", None) is not None:
        try:
            check_device(args.device)
        except ValueError as error:
            parser.error(f"argument --device: {error}")
    if args.command in ECOSYSTEM_COMMANDS:
        return ECOSYSTEM_COMMANDS[args.command](args, argv)
    from torchcbf.sweep.rundir import OutputError, RunDir

    registry = scenarios()
    if args.command == "demo":
        plan = [(e, dict(e.demo)) for e in registry.values() if e.demo is not None]
    else:
        plan = [(registry[args.command], None)]
    try:
        from torchcbf.sweep.params import check_buildable

        for entry, sizes in plan:  # a bad parameter is refused before any work
            _, params, variants = _plan(entry, args, sizes)
            configs = [{**params, entry.variant: v} if v is not None else params for v in variants]
            check_buildable(entry, configs, seed=args.seed, device=args.device)
    except ValueError as error:
        print(f"torchcbf {args.command}: {error}", file=sys.stderr)
        return 2
    try:
        run = RunDir.claim(
            args.out,
            kind=args.command,
            settings=_scenario_settings(args, plan),
            resume=args.resume,
            overwrite=args.overwrite,
        )
    except OutputError as error:
        print(f"torchcbf {args.command}: {error}", file=sys.stderr)
        return 2
    parts = _Parts(run)
    try:
        results: dict[str, Any] = {}
        for entry, sizes in plan:
            results.update(_run_scenario(entry, args, parts, sizes))
        if args.command == "demo" and any(entry.name == "mppi-cbf" for entry, _ in plan):
            print(f"\nThe paper's size of scenario B (32 seeds, K = 20,000): {PAPER_SIZE_B}")
        record = {"command": " ".join(_run_arguments(argv)), "run": run_info(args.device)}
        metrics_path = run.path / "metrics.json"
        _io.write_json(metrics_path, strict({**record, "results": results}))
    except KeyboardInterrupt:
        saved = f"{len(parts.done)} finished part(s) ({', '.join(parts.done) or 'none'})"
        return _interrupted(args.command, argv, run.path, saved)
    figures = {Path(f).name for entry in results.values() for f in entry.get("figures", [])}
    failed = any("figures_failed" in entry for entry in results.values())
    run.record(metrics_path, *sorted(figures))
    run.finish()
    out = run.path
    kinds = sorted({Path(f).suffix for f in figures})
    shown = ", ".join(f"{out}/*{kind}" for kind in kinds) or "none"
    print(f"metrics: {out / 'metrics.json'}; figures: {shown}")
    return 1 if failed else 0


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
        "over a batch of tuning seeds (--seeds from --seed, default 16 from 10,000: disjoint "
        "from the evaluation seeds) plus a tie-break below one success in mean time to "
        "goal. The best trial and the default configuration are then run on the held-out "
        "evaluation seeds (--eval-seeds from --eval-seed, default twice --seeds from 0); the "
        "best is recommended only if it beats the default there. Writes best.json (best "
        "parameters, the default's, both evaluations and the recommendation), study.csv "
        "and study.png."
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
    from torchcbf.scenarios import scenarios

    p.add_argument("scenario", choices=list(scenarios()), help="a registered scenario")
    p.add_argument(
        "--seeds", type=positive_int, default=seeds, help="seeds per configuration (one batch)"
    )
    p.add_argument("--seed", type=seed_type, default=seed, help="first seed")
    p.add_argument("--engine", default="local", choices=["local", "ray"], help="where to run")
    p.add_argument(
        "--address",
        default=None,
        help="Ray cluster to join (default: start a local one for the run)",
    )
    p.add_argument(
        "--num-cpus",
        type=positive_int,
        default=None,
        help="CPUs of the local Ray cluster (default: all)",
    )
    p.add_argument(
        "--threads", type=positive_int, default=1, help="torch threads per configuration"
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
    _add_engine_options(t, seeds=16, seed=10_000)
    t.add_argument("--trials", type=positive_int, default=20, help="Optuna trials")
    t.add_argument("--eval-seed", type=seed_type, default=0, help="first evaluation seed")
    t.add_argument(
        "--eval-seeds",
        type=positive_int,
        default=None,
        help="evaluation seeds (default: twice --seeds)",
    )
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
    t.add_argument("--sampler-seed", type=seed_type, default=0, help="seed of the TPE sampler")
    t.add_argument(
        "--batch", type=positive_int, default=2, help="trials asked at once (parallel Ray tasks)"
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
        if not wanted:
            print(f"torchcbf bench: --only names no benchmark: {args.only!r}", file=sys.stderr)
            return 2
        unknown = wanted - {p.name for p in scripts}
        if unknown:
            names = ", ".join(p.stem.removeprefix("bench_") for p in scripts) or "none"
            asked = ", ".join(sorted(n.removeprefix("bench_").removesuffix(".py") for n in unknown))
            print(
                f"torchcbf bench: --only: no benchmark named {asked}; found: {names}",
                file=sys.stderr,
            )
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


def _print_rows(
    rows: list[dict[str, Any]], keys: list[str], *, names: list[str] | None = None
) -> None:
    """A table of ``rows``, each named by ``names`` or else by its values of ``keys``."""

    def pct(row: dict[str, Any], name: str) -> str:
        if f"{name}_rate" not in row:
            return "-"
        lo, hi = row[f"{name}_ci95_low"], row[f"{name}_ci95_high"]
        return f"{100 * row[f'{name}_rate']:.0f}% ({100 * lo:.0f}-{100 * hi:.0f})"

    def num(value: Any, fmt: str) -> str:
        return "-" if value is None else fmt.format(value)

    from torchcbf.sweep.params import describe

    if names is None:
        names = [describe({k: row[k] for k in keys if k in row}) or "defaults" for row in rows]
    w = max([len("configuration"), *map(len, names)])
    print(
        f"{'configuration':<{w}} {'success (95% CI)':>17} {'collision (95% CI)':>19} "
        f"{'t_goal [s]':>10} {'min barrier':>11} {'wall [s]':>8}"
    )
    for name, row in zip(names, rows, strict=True):
        if row.get("status", "ok") != "ok":
            print(f"{name:<{w}} failed: {row.get('error')}")
            continue
        print(
            f"{name:<{w}} {pct(row, 'success'):>17} {pct(row, 'collision'):>19} "
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
    if args.engine == "ray" and args.address is not None:
        from torchcbf.sweep.engines import check_address

        try:
            check_address(args.address)  # before the run folder is taken
        except ValueError as error:
            print(f"torchcbf {command}: {error}", file=sys.stderr)
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
    from torchcbf.sweep.params import describe
    from torchcbf.sweep.sweep import fixed_parameters

    print(f"{args.scenario}, {args.seeds} seeds from {args.seed} per configuration; held fixed: "
          f"{describe(fixed_parameters(args.scenario, grid)) or 'nothing'}")  # fmt: skip
    _print_rows(rows, list(grid))
    failed = sum(row["status"] != "ok" for row in rows)
    if failed:
        print(f"{failed} of {len(rows)} configuration(s) failed (status and error in the table)")
    out = Path(args.out)
    print("wrote " + ", ".join(str(out / n) for n in ("sweep.csv", "sweep.json", "sweep.png")))
    return FAILED if rows and failed == len(rows) else 0


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
            eval_seeds=args.eval_seeds,
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
        tuning = result["tuning_seeds"]
        print(
            f"objective on the tuning seeds {tuning['first']}.."
            f"{tuning['first'] + tuning['count'] - 1}: best {best['objective']:.4f}, default "
            f"configuration {_num(default['objective'], '{:.4f}')}"
        )
    evaluation, held_out = result["evaluation"], result["evaluation_seeds"]
    first, count = held_out["first"], held_out["count"]
    print(f"on the held-out evaluation seeds {first}..{first + count - 1}:")
    kinds = [k for k in ("best", "default") if evaluation[k]]
    _print_rows([evaluation[k] for k in kinds], [], names=kinds)
    recommended = result["recommended"]
    if recommended["source"] == "none":
        print(f"recommended: nothing ({recommended['reason']})")
    else:
        print(f"recommended: the {recommended['source']} configuration ({recommended['reason']})")
    out = Path(args.out)
    print(
        "wrote "
        + ", ".join(str(out / n) for n in ("best.json", "study.csv", "study.png", "study.db"))
    )
    return FAILED if best is None else 0


def _info(args: argparse.Namespace, argv: Sequence[str] = ()) -> int:
    from torchcbf._info import format_info, info

    report = info()
    print(json.dumps(report, indent=2) if args.json else format_info(report))
    return 0


ECOSYSTEM_COMMANDS = {"bench": _bench, "info": _info, "sweep": _sweep, "tune": _tune}


if __name__ == "__main__":
    raise SystemExit(main())
