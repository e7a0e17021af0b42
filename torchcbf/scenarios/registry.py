"""The scenario registry: the fifth extension point.

A scenario is one module that registers a :class:`ScenarioEntry`: its builder, the
dataclass of its parameters (the single home of their defaults), its search space, the
columns of its report table and its figures. The command line (``torchcbf NAME``,
``torchcbf sweep NAME``, ``torchcbf tune NAME``), :func:`torchcbf.sweep.run_sweep`,
:func:`torchcbf.sweep.tune` and the environments read the registry, so a user's scenario,
registered from their own package, gets all of them::

    from torchcbf.scenarios import ScenarioEntry, register

    register(ScenarioEntry(name="my-robot", build=build, params=MyParams, ...))

The command line finds scenarios of installed packages through the entry point group
``torchcbf.scenarios`` (each entry point names a module that registers on import) and
modules named with ``torchcbf --import MODULE``.
"""

from __future__ import annotations

import dataclasses
import functools
import importlib
import importlib.metadata
import os
import re
import sys
import types
import typing
import warnings
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch

from torchcbf._checks import check_number, check_positive_int
from torchcbf.scenarios.base import Scenario

ENTRY_POINT_GROUP = "torchcbf.scenarios"
#: keywords every builder takes besides its parameters: they place and size the batch
RUN_KEYWORDS = ("num_seeds", "seed", "device", "dtype")
#: the command line's own commands, which no scenario may be named
COMMANDS = ("demo", "sweep", "tune", "bench", "info")


@dataclass(frozen=True)
class Dimension:
    """One searched parameter of a scenario.

    ``kind``: ``"float"``, ``"int"`` or ``"categorical"`` (``choices``); ``argument``: the
    parameter it sets (default: ``name``); ``to_argument`` maps the sampled value to the
    parameter's value; ``skip_variants``: values of the scenario's variant parameter (its
    ``method``) for which the dimension has no effect (an MPPI parameter for the filter
    alone, a filter parameter for MPPI alone); ``skip_when``: ``(parameter, value)`` pairs
    under which it has none either (a configuration that fixes it).
    """

    name: str
    kind: str
    low: float | None = None
    high: float | None = None
    log: bool = False
    choices: tuple[Any, ...] = ()
    argument: str | None = None
    to_argument: Callable[[Any], Any] | None = field(default=None, compare=False)
    skip_variants: tuple[str, ...] = ()
    skip_when: tuple[tuple[str, Any], ...] = ()

    def __post_init__(self) -> None:
        if self.kind not in ("float", "int", "categorical"):
            raise ValueError(f"Dimension.kind must be float, int or categorical, got {self.kind!r}")
        if self.kind == "categorical" and not self.choices:
            raise ValueError(f"categorical dimension {self.name!r} needs choices")
        if self.kind != "categorical":
            if self.low is None or self.high is None:
                raise ValueError(f"dimension {self.name!r} needs low and high")
            low = check_number(f"dimension {self.name!r}: low", self.low)
            high = check_number(f"dimension {self.name!r}: high", self.high)
            if low > high:
                raise ValueError(f"dimension {self.name!r}: low {low} > high {high}")
            if self.log and low <= 0:
                raise ValueError(
                    f"dimension {self.name!r} is searched on a log scale: low > 0, got {low}"
                )

    @property
    def keyword(self) -> str:
        """The parameter this dimension sets."""
        return self.argument or self.name

    def suggest(self, trial: Any) -> Any:
        """The value of this dimension drawn by an Optuna ``trial``."""
        if self.kind == "float":
            return trial.suggest_float(self.name, self.low, self.high, log=self.log)
        if self.kind == "int":
            return trial.suggest_int(self.name, int(self.low), int(self.high), log=self.log)
        return trial.suggest_categorical(self.name, list(self.choices))

    def describe(self) -> dict[str, Any]:
        """The dimension as JSON."""
        if self.kind == "categorical":
            return {"kind": self.kind, "choices": list(self.choices), "argument": self.keyword}
        return {
            "kind": self.kind,
            "low": self.low,
            "high": self.high,
            "log": self.log,
            "argument": self.keyword,
        }


@dataclass(frozen=True)
class Column:
    """One column of a scenario's report table, read from a summary
    (:func:`torchcbf.sim.summarize` of the per-seed metrics).

    ``kind``: ``"rate"`` (a boolean metric: count of seeds and its 95% interval), ``"mean"``,
    ``"min"`` or ``"max"`` (of the metric over seeds, formatted with ``fmt`` after
    multiplying by ``scale``).
    """

    header: str
    metric: str
    kind: str = "rate"
    fmt: str = "{:.2f}"
    scale: float = 1.0

    def __post_init__(self) -> None:
        if self.kind not in ("rate", "mean", "min", "max"):
            raise ValueError(f"Column.kind must be rate, mean, min or max, got {self.kind!r}")

    def cell(self, summary: Mapping[str, Any]) -> str:
        """The cell of one run (``-`` where the metric is missing)."""
        entry = summary.get(self.metric)
        if not entry:
            return "-"
        if self.kind == "rate":
            if "rate" not in entry:
                return "-"
            lo, hi = entry["ci95_low"], entry["ci95_high"]
            return f"{entry['count']}/{entry['n']} [{100 * lo:.0f}-{100 * hi:.0f}%]"
        value = entry.get(self.kind)
        return "-" if value is None else self.fmt.format(self.scale * value)


#: ``figures(trajectories, scenario, out, *, title, gif, first_seed) -> [paths]``
Figures = Callable[..., list[Path]]


@dataclass(frozen=True)
class EnvEntry:
    """The Gymnasium environment of a scenario, registered with Gymnasium by
    :mod:`torchcbf.envs` (``entry_point`` and ``vector_entry_point`` as
    ``gymnasium.register`` takes them: ``"module:Class"``)."""

    id: str
    entry_point: str
    vector_entry_point: str | None = None
    max_episode_steps: int | None = None


@dataclass(frozen=True)
class ScenarioEntry:
    """A registered scenario.

    Attributes:
        name: the command-line name (``torchcbf NAME``).
        build: ``build(params, *, num_seeds, seed, device, dtype) -> Scenario``; ``dtype``
            ``None`` takes the builder's own default.
        params: the dataclass of the scenario's parameters; its field defaults are the
            defaults everywhere (command line, sweeps, tuning).
        description: one paragraph for ``torchcbf NAME --help``.
        search_space: what ``torchcbf tune NAME`` searches.
        columns: the report table of ``torchcbf NAME`` (a wall-time column is added).
        figures: ``figures(trajectories, scenario, out, *, title, gif, first_seed) ->
            [paths]`` draws the figures of a finished run into the folder ``out``
            (``trajectories``: ``{variant: Trajectory}`` on the CPU; ``scenario``: one built
            with the run's parameters, for its obstacles and goals). ``None``:
            :func:`torchcbf.scenarios.figures.standard_figures`.
        variant: a parameter whose values a run compares side by side (one table row and
            one batch each; scenario B's ``method``; ``--methods`` on the command line),
            ``None`` for one row.
        choices: the values a parameter may take (the variant's are what ``all`` runs).
        options: command-line flags of ``torchcbf NAME`` -> the parameter each sets
            (``{"samples": "num_samples"}`` gives ``--samples``); any parameter can also be
            set with ``--set KEY=VALUE``.
        units: the unit of a metric, recorded with the results (``{"min_h": "m"}``).
        num_seeds: seeds of ``torchcbf NAME`` by default.
        demo: parameters and ``num_seeds`` of its part in ``torchcbf demo`` (``None``: not
            part of the demo).
        env: its Gymnasium environment, if it has one (:class:`EnvEntry`).
    """

    name: str
    build: Callable[..., Scenario]
    params: type
    description: str = ""
    search_space: tuple[Dimension, ...] = ()
    columns: tuple[Column, ...] = ()
    figures: Figures | None = field(default=None, compare=False)
    variant: str | None = None
    choices: Mapping[str, tuple[Any, ...]] = field(default_factory=dict)
    options: Mapping[str, str] = field(default_factory=dict)
    units: Mapping[str, str] = field(default_factory=dict)
    num_seeds: int = 8
    demo: Mapping[str, Any] | None = None
    env: EnvEntry | None = None

    def __post_init__(self) -> None:
        if not isinstance(self.name, str) or not re.fullmatch(
            r"[A-Za-z0-9][A-Za-z0-9_.-]*", self.name
        ):
            # it names files and folders of every run: no separators, no leading dot
            raise ValueError(
                f"ScenarioEntry.name must be a word (letters, digits, '_', '-', '.'; not "
                f"starting with '.'), got {self.name!r}"
            )
        if self.name in COMMANDS:
            raise ValueError(
                f"ScenarioEntry.name {self.name!r} is a command of torchcbf; the names "
                f"{COMMANDS} are taken"
            )
        if not callable(self.build):
            raise TypeError(f"ScenarioEntry.build must be callable, got {self.build!r}")
        if not (isinstance(self.params, type) and dataclasses.is_dataclass(self.params)):
            raise TypeError(f"ScenarioEntry.params must be a dataclass type, got {self.params!r}")
        known = self.defaults()
        for reserved in RUN_KEYWORDS:
            if reserved in known:
                raise ValueError(
                    f"{self.params.__name__}.{reserved}: {RUN_KEYWORDS} are set by the run, "
                    "not parameters"
                )
        if self.variant is not None and not self.choices.get(self.variant):
            raise ValueError(
                f"ScenarioEntry {self.name!r}: the variant {self.variant!r} needs its values "
                "in choices (what 'all' runs)"
            )
        check_positive_int(f"ScenarioEntry {self.name!r}: num_seeds", self.num_seeds)
        if self.demo is not None and "num_seeds" in self.demo:
            check_positive_int(
                f"ScenarioEntry {self.name!r}: demo['num_seeds']", self.demo["num_seeds"]
            )
        named = [("variant", self.variant)] if self.variant is not None else []
        named += [(f"demo[{key!r}]", key) for key in self.demo or {} if key != "num_seeds"]
        named += [(f"options[{flag!r}]", key) for flag, key in self.options.items()]
        named += [(f"choices[{key!r}]", key) for key in self.choices]
        named += [(f"search_space[{d.name!r}]", d.keyword) for d in self.search_space]
        for where, key in named:
            if key not in known:
                raise ValueError(
                    f"ScenarioEntry {self.name!r}: {where} names {key!r}, which is not a field "
                    f"of {self.params.__name__} ({', '.join(known)})"
                )

    def defaults(self) -> dict[str, Any]:
        """Every parameter and its default."""
        out = {}
        for f in dataclasses.fields(self.params):
            if f.default is not dataclasses.MISSING:
                out[f.name] = f.default
            elif f.default_factory is not dataclasses.MISSING:
                out[f.name] = f.default_factory()
            else:
                raise TypeError(f"{self.params.__name__}.{f.name} needs a default")
        return out

    def types(self) -> dict[str, tuple[Any, ...]]:
        """The types each parameter's annotation admits (empty where it has none)."""
        try:
            hints = typing.get_type_hints(self.params)
        except (NameError, TypeError):
            hints = {}
        out = {}
        for name in self.defaults():
            hint = hints.get(name)
            if hint is None:
                out[name] = ()
            elif typing.get_origin(hint) in (typing.Union, types.UnionType):
                out[name] = typing.get_args(hint)
            else:
                out[name] = (hint,)
        return out

    def parameters(self, **overrides: Any) -> Any:
        """The parameters dataclass with ``overrides`` (a ValueError names unknown keys)."""
        known = self.defaults()
        unknown = [k for k in overrides if k not in known]
        if unknown:
            raise ValueError(
                f"unknown parameter(s) {unknown} of scenario {self.name!r}; its parameters "
                f"are: {', '.join(sorted(known))}"
            )
        for key, allowed in self.choices.items():
            if key in overrides and overrides[key] not in allowed:
                raise ValueError(f"{key} must be one of {tuple(allowed)}, got {overrides[key]!r}")
        return self.params(**overrides)

    def make(
        self,
        *,
        num_seeds: int | None = None,
        seed: int = 0,
        device: str | torch.device = "cpu",
        dtype: torch.dtype | None = None,
        **overrides: Any,
    ) -> Scenario:
        """Build the scenario with its defaults overridden by ``overrides``."""
        return self.build(
            self.parameters(**overrides),
            num_seeds=self.num_seeds if num_seeds is None else num_seeds,
            seed=seed,
            device=device,
            dtype=dtype,
        )


_REGISTRY: dict[str, ScenarioEntry] = {}


def register(entry: ScenarioEntry, *, replace: bool = False) -> ScenarioEntry:
    """Add ``entry`` to the registry (registering the same entry again is a no-op; another
    entry under a taken name needs ``replace=True``). Returns ``entry``."""
    if not isinstance(entry, ScenarioEntry):
        raise TypeError(f"register takes a ScenarioEntry, got {type(entry).__name__}")
    current = _REGISTRY.get(entry.name)
    if current is not None and _same(current, entry):
        replace = True  # the module that registers it was imported again (a reload)
    if current is not None and current != entry and not replace:
        raise ValueError(
            f"a scenario named {entry.name!r} is already registered (pass replace=True)"
        )
    _REGISTRY[entry.name] = entry
    return entry


def _origin(value: Any) -> tuple[str, str]:
    return getattr(value, "__module__", ""), getattr(value, "__qualname__", repr(value))


def _same(a: ScenarioEntry, b: ScenarioEntry) -> bool:
    """Whether ``b`` is ``a`` registered again by its module (the same builder and
    parameters by module and name, the rest equal)."""
    return (
        _origin(a.build) == _origin(b.build)
        and _origin(a.params) == _origin(b.params)
        and dataclasses.replace(a, build=b.build, params=b.params) == b
    )


def unregister(name: str) -> None:
    """Remove the scenario ``name`` from the registry (a KeyError if it is not there)."""
    del _REGISTRY[name]


@functools.cache
def _load_entry_points() -> None:
    for point in importlib.metadata.entry_points(group=ENTRY_POINT_GROUP):
        try:
            point.load()
        except Exception as error:  # one broken package must not break every command
            warnings.warn(
                f"the scenarios of entry point {point.name!r} ({point.value}) did not load: "
                f"{type(error).__name__}: {error}",
                stacklevel=2,
            )


def scenarios() -> dict[str, ScenarioEntry]:
    """Every registered scenario by name, in the order they registered (those of installed
    packages' entry points too); ``torchcbf demo`` runs them in this order."""
    _load_entry_points()
    return dict(_REGISTRY)


def get(scenario: str | ScenarioEntry) -> ScenarioEntry:
    """The entry of ``scenario`` (a name or an entry, returned as it is)."""
    if isinstance(scenario, ScenarioEntry):
        return scenario
    known = scenarios()
    if scenario not in known:
        raise ValueError(f"scenario must be one of {sorted(known)}, got {scenario!r}")
    return known[scenario]


def import_scenarios(module: str) -> None:
    """Import ``module`` (a dotted name, found from the current directory too, as ``python
    -m`` would) so that the scenarios it registers are known."""
    here = os.getcwd()
    if here not in sys.path:
        sys.path.insert(0, here)
    importlib.import_module(module)
