"""Automatic tuning of a scenario's parameters with Optuna (extra ``tune``).

Each scenario declares its search space in its registry entry
(:attr:`torchcbf.scenarios.ScenarioEntry.search_space`: cost weights, temperatures, filter
parameters). A trial runs the scenario on the tuning seeds (``seed .. seed + num_seeds -
1``, from 10,000 by default, 16 of them: :data:`NUM_SEEDS`) as one batch and scores it with
:func:`torchcbf.sweep.evaluate.objective` (success rate, ties broken by the time to goal).
The best configuration and the default are then both evaluated on the evaluation seeds
(``0 ..``, twice as many by default), which the search never saw, and the best is
recommended only if it beats the default there (:func:`recommend`).

Trials are asked ``batch`` at a time from a TPE sampler seeded from ``sampler_seed`` and the
trial's number, and told their results as they finish, before the next batch is asked, so a
study is reproducible and the same on the local and the Ray engine (where the trials of a
batch run in parallel as Ray tasks). A trial that raises is recorded as failed (Optuna's
``FAIL`` state, its error in the row) and the study goes on.

Given a run directory (``out``), the study lives in Optuna's SQLite storage ``study.db``
there: every asked trial, its parameters, and its row once finished, are saved as they
happen, and so are the default configuration's row and the final evaluations. ``resume=True``
opens the same study: trials asked but never finished run again with their recorded
parameters, the rest of the study continues, and the outputs equal an uninterrupted run's.
"""

from __future__ import annotations

import contextlib
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from tqdm.auto import tqdm

from torchcbf import _io
from torchcbf._checks import check_positive_int
from torchcbf.scenarios import Dimension, get
from torchcbf.sim import run_info, strict
from torchcbf.sweep.engines import Outcome, check_engine, ray_session, run_each
from torchcbf.sweep.evaluate import evaluate
from torchcbf.sweep.params import ScenarioName, check_buildable, check_keys, check_seeds
from torchcbf.sweep.rundir import RunDir, owned
from torchcbf.sweep.sweep import write_json, write_table

STORAGE = "study.db"
#: the files a study writes in its run directory (SQLite may add its journal beside the db)
OUTPUTS = (STORAGE, f"{STORAGE}-journal", "study.csv", "best.json", "study.png")
STUDY_NAME = "torchcbf-tune"

TUNING_SEED = 10_000
#: tuning seeds per trial by default: with 16 seeds a configuration that succeeds in 90% of
#: seeds ranks above one that succeeds in 65% in about 19 studies of 20 (binomial: a
#: difference of 4 successes, 1.8 standard deviations), with 8 seeds in about 9 of 10
NUM_SEEDS = 16


def search_space(
    scenario: ScenarioName,
    names: Sequence[str] | None = None,
    fixed: Mapping[str, Any] | None = None,
) -> list[Dimension]:
    """The dimensions of ``scenario``'s search space that its variant and parameters (from
    ``fixed`` or the defaults) use (``Dimension.skip_variants``, ``skip_when``), restricted
    to ``names`` if given, without those whose parameter is in ``fixed``."""
    entry = get(scenario)
    if not entry.search_space:
        raise ValueError(f"scenario {entry.name!r} declares no search space")
    params = {**entry.defaults(), **(fixed or {})}
    variant = None if entry.variant is None else params[entry.variant]
    dims = [
        d
        for d in entry.search_space
        if variant not in d.skip_variants and not any(params.get(k) == v for k, v in d.skip_when)
    ]
    if names is not None:
        known = {d.name for d in dims}
        unused = sorted({d.name for d in entry.search_space} & set(names) - known)
        if unused:
            raise ValueError(
                f"parameter(s) {unused} of {entry.name!r} have no effect with these settings "
                f"(its variant or configuration fixes them); searched here: "
                f"{', '.join(sorted(known))}"
            )
        unknown = [n for n in names if n not in known]
        if unknown:
            raise ValueError(
                f"unknown parameter(s) {unknown} in the search space of {entry.name!r}; "
                f"it has: {', '.join(sorted(known))}"
            )
        dims = [d for d in dims if d.name in names]
    dims = [d for d in dims if d.keyword not in (fixed or {})]
    if not dims:
        raise ValueError(f"nothing to search for {entry.name!r}: every dimension is fixed")
    return dims


def _arguments(dims: Sequence[Dimension], values: Mapping[str, Any]) -> dict[str, Any]:
    out = {}
    for d in dims:
        v = values[d.name]
        out[d.keyword] = d.to_argument(v) if d.to_argument is not None else v
    return out


def tune_settings(
    scenario: ScenarioName,
    *,
    trials: int,
    num_seeds: int,
    seed: int,
    eval_seed: int,
    eval_seeds: int,
    fixed: Mapping[str, Any],
    params: Sequence[str] | None,
    sampler_seed: int,
    batch: int,
    device: str,
    threads: int,
) -> dict[str, Any]:
    """What makes two studies the same run (compared by ``resume``; the engine may differ):
    the search space and the defaults included, so a study is not resumed across a change
    of either."""
    entry = get(scenario)
    dims = search_space(entry, params, fixed)
    return {
        "scenario": entry.name,
        "space": {d.name: d.describe() for d in dims},
        "defaults": strict(entry.defaults()),
        "trials": trials,
        "num_seeds": num_seeds,
        "seed": seed,
        "eval_seed": eval_seed,
        "eval_seeds": eval_seeds,
        "fixed": strict(dict(fixed)),
        "params": None if params is None else list(params),
        "sampler_seed": sampler_seed,
        "batch": batch,
        "device": str(device),
        "threads": threads,
    }


def _sampler(optuna: Any, sampler_seed: int, number: int, trials: int, part: int = 0) -> Any:
    """The TPE sampler that draws part ``part`` (0: the ask, ``i + 1``: dimension ``i``) of
    trial ``number``: seeded from ``sampler_seed``, the number and the part, so a resumed
    study draws what an uninterrupted one would, even for a trial cut off between two of its
    parameters."""
    import numpy as np

    seed = int(np.random.SeedSequence([sampler_seed, number, part]).generate_state(1)[0])
    return optuna.samplers.TPESampler(seed=seed, n_startup_trials=min(10, trials))


def _suggest_all(
    optuna: Any, study: Any, trial: Any, dims: Sequence[Dimension], **seeds: int
) -> None:
    """Draw every dimension of ``trial`` not drawn yet, each with its own seeded sampler."""
    for i, d in enumerate(dims):
        if d.name not in trial.params:
            study.sampler = _sampler(optuna, part=i + 1, **seeds)
            d.suggest(trial)


def _outcome_row(outcome: Outcome) -> dict[str, Any]:
    if outcome.ok:
        return {**strict(outcome.value), "status": "ok"}
    return {"status": "failed", "error": outcome.error}


def _sqlite_url(path: Path) -> str:
    """The SQLAlchemy address of the SQLite file ``path``, escaped (a ``?`` or ``%`` in a
    folder's name would otherwise be read as the address's query or an escape)."""
    from sqlalchemy.engine import URL

    return URL.create("sqlite", database=str(path)).render_as_string(hide_password=False)


def tune(
    scenario: ScenarioName,
    *,
    trials: int = 20,
    num_seeds: int = NUM_SEEDS,
    seed: int = TUNING_SEED,
    eval_seed: int = 0,
    eval_seeds: int | None = None,
    fixed: Mapping[str, Any] | None = None,
    params: Sequence[str] | None = None,
    sampler_seed: int = 0,
    batch: int = 2,
    device: str = "cpu",
    engine: str = "local",
    address: str | None = None,
    num_cpus: int | None = None,
    threads: int = 1,
    progress: bool = True,
    out: str | Path | RunDir | None = None,
    resume: bool = False,
    overwrite: bool = False,
) -> dict[str, Any]:
    """Search ``scenario``'s space (:func:`search_space`) for ``trials`` trials, then compare
    the best trial's configuration with the default on held-out evaluation seeds.

    Args:
        scenario: a registered name or a :class:`~torchcbf.scenarios.ScenarioEntry` (a
            user's own scenario needs no registration).
        num_seeds: tuning seeds per trial, run as one batch (:data:`NUM_SEEDS` says why 16).
        seed: first tuning seed; ``eval_seed``: first evaluation seed, ``eval_seeds`` of them
            (default: twice ``num_seeds``); the two ranges must not overlap.
        fixed: builder keywords held fixed (e.g. ``{"method": "scbf"}``).
        params: the dimensions to search (default: all of the space the builder accepts).
        sampler_seed: seed of Optuna's TPE sampler.
        batch: trials asked before their results are told (run in parallel on Ray).
        out: a run directory (path or claimed :class:`RunDir`) for the study's SQLite
            storage and :func:`write_tune`'s files; ``resume``/``overwrite`` as
            :meth:`RunDir.claim` says.

    Returns:
        ``{"best": ..., "default": ..., "evaluation": ..., "recommended": ..., "trials":
        [rows], ...}``: the best parameters and objective, the default configuration's
        objective on the same tuning seeds, both re-run on the evaluation seeds, and one row
        per trial (``status`` ``"ok"``, or ``"failed"`` with its ``error``). ``best`` is None
        when every trial failed. ``recommended`` is the best trial's configuration only when
        its objective on the evaluation seeds is above the default's; otherwise it is the
        default, and its ``reason`` says so (a search on few seeds can rank a lucky
        configuration first).
    """
    try:
        import optuna
    except ImportError as error:
        raise ImportError('tune needs Optuna: pip install "torchcbf[tune]"') from error
    entry = get(scenario)
    name = entry.name
    fixed = dict(fixed or {})
    check_keys(entry, list(fixed))
    check_engine(engine)
    eval_seeds = 2 * num_seeds if eval_seeds is None else eval_seeds
    for key, value in (("trials", trials), ("num_seeds", num_seeds), ("batch", batch),
                       ("eval_seeds", eval_seeds)):  # fmt: skip
        check_positive_int(key, value)
    seed = check_seeds(seed, num_seeds)
    eval_seed = check_seeds(eval_seed, eval_seeds, "eval_seed")
    if seed < eval_seed + eval_seeds and eval_seed < seed + num_seeds:
        raise ValueError(
            f"tuning seeds {seed}..{seed + num_seeds - 1} and evaluation seeds "
            f"{eval_seed}..{eval_seed + eval_seeds - 1} overlap"
        )
    dims = search_space(entry, params, fixed)
    check_buildable(entry, [fixed], seed=seed, device=device)
    settings = tune_settings(
        entry,
        trials=trials,
        num_seeds=num_seeds,
        seed=seed,
        eval_seed=eval_seed,
        eval_seeds=eval_seeds,
        fixed=fixed,
        params=params,
        sampler_seed=sampler_seed,
        batch=batch,
        device=device,
        threads=threads,
    )
    run = out
    if out is not None and not isinstance(out, RunDir):
        run = RunDir.claim(out, kind="tune", settings=settings, resume=resume,
                           overwrite=overwrite, outputs=OUTPUTS)  # fmt: skip
    with owned(run, out):
        storage: Any = None
        if run is not None:
            storage = optuna.storages.RDBStorage(_sqlite_url(run.path / STORAGE))
        study = optuna.create_study(
            direction="maximize",
            sampler=_sampler(optuna, sampler_seed, 0, trials),
            storage=storage,
            study_name=STUDY_NAME,
            load_if_exists=True,
        )
        common = {"device": device, "threads": threads}

        def call(arguments: Mapping[str, Any], first_seed: int, count: int = num_seeds) -> dict:
            return {
                "scenario": entry,
                "params": {**fixed, **arguments},
                "seed": first_seed,
                "num_seeds": count,
                **common,
            }

        options = {"engine": engine, "address": address, "num_cpus": num_cpus, "progress": False}

        def evaluate_once(
            key: str, arguments: Mapping[str, Any], first_seed: int, count: int = num_seeds
        ) -> dict:
            """The row of one configuration, kept in the study so a resumed run reuses it."""
            if key not in study.user_attrs:
                outcomes: list[Outcome] = []
                run_each(
                    evaluate,
                    [call(arguments, first_seed, count)],
                    lambda i, o: outcomes.append(o),
                    **options,
                )
                study.set_user_attr(key, _outcome_row(outcomes[0]))
            return dict(study.user_attrs[key])

        session = ray_session(address, num_cpus) if engine == "ray" else contextlib.nullcontext()
        desc = f"tune {name} ({engine})"
        with session, tqdm(total=trials + 3, desc=desc, disable=not progress) as bar:
            default_row = evaluate_once("default_row", {}, seed)
            bar.update(1)
            for start in range(0, trials, batch):
                numbers = range(start, min(start + batch, trials))
                known = {t.number: t for t in study.get_trials(deepcopy=False)}
                for number in numbers:
                    seeds = {"sampler_seed": sampler_seed, "number": number, "trials": trials}
                    if number not in known:  # asked in order: every earlier trial exists
                        study.sampler = _sampler(optuna, **seeds)
                        trial = study.ask()
                        if trial.number != number:
                            raise RuntimeError(
                                f"the study asked trial {trial.number}, not {number}"
                            )
                        _suggest_all(optuna, study, trial, dims, **seeds)
                    elif not known[number].state.is_finished() and set(known[number].params) != {
                        d.name for d in dims
                    }:  # cut off while its parameters were drawn: the rest are drawn now
                        trial = optuna.trial.Trial(study, known[number]._trial_id)
                        _suggest_all(optuna, study, trial, dims, **seeds)
                known = {t.number: t for t in study.get_trials(deepcopy=False)}
                pending = [n for n in numbers if not known[n].state.is_finished()]
                bar.update(len(numbers) - len(pending))
                arguments = [_arguments(dims, known[n].params) for n in pending]

                def finished(i: int, outcome: Outcome, pending: list[int] = pending) -> None:
                    number = pending[i]
                    study.set_user_attr(f"row_{number}", _outcome_row(outcome))
                    if outcome.ok:
                        study.tell(number, outcome.value["objective"])
                    else:
                        study.tell(number, state=optuna.trial.TrialState.FAIL)
                    bar.update(1)
                    if run is not None:
                        write_table(_trial_rows(study, trials), run.path / "study.csv")

                run_each(evaluate, [call(a, seed) for a in arguments], finished, **options)
            rows = _trial_rows(study, trials)
            complete = [
                t
                for t in study.get_trials(deepcopy=False)
                if t.number < trials and t.value is not None
            ]
            best = max(complete, key=lambda t: (t.value, -t.number)) if complete else None
            best_arguments = _arguments(dims, best.params) if best is not None else None
            evaluation = {"best": None, "default": None}
            if best is not None:
                evaluation["best"] = evaluate_once(
                    f"evaluation_best_{best.number}", best_arguments, eval_seed, eval_seeds
                )
            evaluation["default"] = evaluate_once("evaluation_default", {}, eval_seed, eval_seeds)
            bar.update(2)
        defaults = {**entry.defaults(), **fixed}
        make = entry.make

        def resolved(arguments: Mapping[str, Any]) -> dict[str, Any]:
            """Every parameter the scenario used (``Scenario.params``), where it records them."""
            built = make(**arguments, num_seeds=1, seed=seed, device=device)
            params = getattr(built, "params", None) or {}
            return {k: v for k, v in params.items() if k not in ("num_seeds", "seed")}

        result = {
            "scenario": name,
            "fixed": fixed,
            "space": {d.name: d.describe() for d in dims},
            "tuning_seeds": {"first": seed, "count": num_seeds},
            "evaluation_seeds": {"first": eval_seed, "count": eval_seeds},
            "sampler": {"name": "TPESampler", "seed": sampler_seed, "batch": batch},
            "objective": "success rate + tie-break / (2 seeds) (torchcbf.sweep.evaluate)",
            "best": None
            if best is None
            else {
                "trial": best.number,
                "params": best.params,
                "arguments": {**fixed, **best_arguments},
                "resolved": resolved({**fixed, **best_arguments}),
                "objective": best.value,
            },
            "default": {
                "arguments": defaults,
                "resolved": resolved(fixed),
                "objective": default_row.get("objective"),
            },
            "evaluation": evaluation,
            "recommended": recommend(
                evaluation, None if best is None else {**fixed, **best_arguments}, defaults
            ),
            "failed_trials": [r["trial"] for r in rows if r["status"] == "failed"],
            "trials": rows,
        }
        if run is not None:
            paths = write_tune(
                result, run.path, engine=engine, device=device, torch_threads=threads
            )
            run.record(STORAGE, *paths.values())
            run.finish()
        return result


def recommend(
    evaluation: Mapping[str, Any],
    best_arguments: Mapping[str, Any] | None,
    default_arguments: Mapping[str, Any],
) -> dict[str, Any]:
    """The configuration to use: the best trial's only when its objective on the evaluation
    seeds is above the default's, otherwise the default (``source``, ``arguments`` and the
    ``reason``, with both evaluation objectives); ``source`` ``"none"`` (``arguments``
    None) where neither ran on the evaluation seeds."""
    best, default = evaluation.get("best"), evaluation.get("default")
    ok = [r is not None and r.get("status") == "ok" for r in (best, default)]
    best_obj = best.get("objective") if ok[0] else None
    default_obj = default.get("objective") if ok[1] else None
    common = {"best_objective": best_obj, "default_objective": default_obj}
    if best_arguments is None or best_obj is None:
        reason = "no trial succeeded" if best_arguments is None else "the best trial failed to run"
        if default_obj is None:  # nothing that ran on the evaluation seeds to recommend
            return {"source": "none", "arguments": None,
                    "reason": f"{reason}, and the default failed on the evaluation seeds",
                    **common}  # fmt: skip
        return {"source": "default", "arguments": dict(default_arguments), "reason": reason,
                **common}  # fmt: skip
    if default_obj is None or best_obj > default_obj:
        reason = (
            "the default failed on the evaluation seeds"
            if default_obj is None
            else "the best trial beats the default on the evaluation seeds"
        )
        return {"source": "best", "arguments": dict(best_arguments), "reason": reason, **common}
    return {
        "source": "default",
        "arguments": dict(default_arguments),
        "reason": (
            "the best trial is not better than the default on the evaluation seeds "
            f"({best_obj:.4f} <= {default_obj:.4f}): keep the default"
        ),
        **common,
    }


def _trial_rows(study: Any, trials: int) -> list[dict[str, Any]]:
    """One row per finished trial, by number: its parameters and its evaluation row."""
    rows = []
    attrs = study.user_attrs
    for t in sorted(study.get_trials(deepcopy=False), key=lambda t: t.number):
        row = attrs.get(f"row_{t.number}")
        if t.number >= trials or not t.state.is_finished() or row is None:
            continue
        rows.append(
            {
                "trial": t.number,
                **{k: strict(v) for k, v in t.params.items()},
                **row,
            }
        )
    return rows


def plot_study(
    rows: Sequence[Mapping[str, Any]], default_objective: float | None, path: Path
) -> Path:
    """Objective per trial, the best so far, and the default configuration's objective
    (failed trials left out)."""
    import matplotlib.pyplot as plt  # the user's backend stays (no display: Agg)

    rows = [r for r in rows if r.get("objective") is not None]
    x = [r["trial"] for r in rows]
    y = [r["objective"] for r in rows]
    best = [max(y[: i + 1]) for i in range(len(y))]
    fig, ax = plt.subplots(figsize=(6, 3.6))
    ax.plot(x, y, "o", label="trial")
    ax.step(x, best, where="post", label="best so far")
    if default_objective is not None:
        ax.axhline(default_objective, color="gray", ls="--", label="default configuration")
    ax.set_xlabel("trial")
    ax.set_ylabel("objective (success rate + tie-break)")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    return _io.save_figure(fig, path)


def write_tune(result: Mapping[str, Any], out: str | Path, **info: Any) -> dict[str, Path]:
    """Write ``best.json`` (everything but the trial rows), ``study.csv`` (one row per
    trial) and ``study.png`` into ``out`` (each file atomically)."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    summary = {k: v for k, v in result.items() if k != "trials"}
    rows = result["trials"]
    return {
        "json": write_json({"run": run_info(**info), **strict(summary)}, out / "best.json"),
        "csv": write_table(rows, out / "study.csv"),
        "figure": plot_study(rows, result["default"]["objective"], out / "study.png"),
    }
