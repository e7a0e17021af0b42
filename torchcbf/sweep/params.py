"""A scenario's parameters read from the command line, checked and described.

The parameters of a registered scenario are the fields of its parameters dataclass
(:class:`torchcbf.scenarios.ScenarioEntry`), so a sweep or a search covers whatever the
scenario declares. A value given as text is converted to a type the field's annotation
admits (or, without one, the type of its default): ``int``, ``float``, ``bool``
(``true``/``false``), ``str``, a tuple (``a:b``, e.g. ``control_limit=2:4``) and ``none``.
"""

from __future__ import annotations

import numbers
import typing
from collections.abc import Callable, Mapping, Sequence
from typing import Any

import numpy as np

from torchcbf.scenarios import Scenario, ScenarioEntry, get
from torchcbf.scenarios.registry import RUN_KEYWORDS as RESERVED

ScenarioName = str | ScenarioEntry


def builder(scenario: ScenarioName) -> Callable[..., Scenario]:
    """``make(**params, num_seeds=..., seed=..., device=...)`` of ``scenario`` (a registered
    name or a :class:`~torchcbf.scenarios.ScenarioEntry`)."""
    return get(scenario).make


def builder_defaults(scenario: ScenarioName) -> dict[str, Any]:
    """The scenario's parameters and their defaults."""
    return get(scenario).defaults()


def check_seeds(first: int, count: int, name: str = "seed") -> int:
    """Seeds ``first .. first + count - 1`` (``name``: the first one's argument) lie in
    ``[0, 2^32)`` (the scenarios' noise streams are 32-bit): ``ValueError`` saying which
    pass the bounds; the first as an int."""
    if not isinstance(first, numbers.Integral) or isinstance(first, (bool, np.bool_)):
        raise TypeError(f"{name} must be an int, got {type(first).__name__}")
    first = int(first)
    if first < 0 or first + count > 2**32:
        raise ValueError(
            f"seeds {first}..{first + count - 1} pass the bounds [0, 2^32 - 1] (the noise "
            "streams are 32-bit)"
        )
    return first


def check_keys(scenario: ScenarioName, keys: Sequence[str]) -> None:
    """Raise a ValueError naming any key that is not a parameter of the scenario."""
    entry = get(scenario)
    known = entry.defaults()
    for key in keys:
        if key in RESERVED:
            raise ValueError(
                f"{key!r} is set by the run itself (--seeds, --seed, --device), not as a parameter"
            )
        if key not in known:
            raise ValueError(
                f"unknown key {key!r} for scenario {entry.name!r}; its parameters are: "
                f"{', '.join(sorted(known))}"
            )


def _literal(text: str) -> Any:
    text = text.strip()
    low = text.lower()
    if low == "none":
        return None
    if low in ("true", "false"):
        return low == "true"
    if ":" in text:
        return tuple(_literal(part) for part in text.split(":"))
    for kind in (int, float):
        try:
            return kind(text)
        except ValueError:
            pass
    return text


def _is_sequence(kind: Any) -> bool:
    origin = typing.get_origin(kind) or kind
    return isinstance(origin, type) and issubclass(origin, (tuple, list, Sequence))


def _coerce(key: str, value: Any, default: Any, admitted: tuple[Any, ...]) -> Any:
    """``value`` as a type the builder admits for ``key``: from its annotation when it has
    one (``admitted``), else from the type of its default (int widens to float)."""
    kinds = admitted or ((type(None),) if default is None else (type(default),))
    if value is None:
        if type(None) in kinds or default is None:
            return None
        raise ValueError(f"{key} does not take none")
    if isinstance(value, bool):
        if bool in kinds:
            return value
        raise ValueError(f"{key} does not take {value!r}")
    if isinstance(value, tuple):
        sequences = [k for k in kinds if _is_sequence(k) and k is not str]
        if not sequences and not (default is None and not admitted):
            raise ValueError(f"{key} takes a single value, got {_text(value)!r}")
        items = typing.get_args(sequences[0]) if sequences else ()
        if float in items:
            return tuple(float(v) if isinstance(v, int) else v for v in value)
        return value
    if isinstance(value, (int, float)):
        if float in kinds:
            return float(value)
        if int in kinds:
            if isinstance(value, float) and not value.is_integer():
                raise ValueError(f"{key} takes an integer, got {value!r}")
            return int(value)
        if default is None and not admitted:
            return value
        raise ValueError(f"{key} does not take a number, got {value!r}")
    if str in kinds or (default is None and not admitted):
        return value
    raise ValueError(f"{key} does not take text, got {value!r}")


def _text(value: Any) -> str:
    if isinstance(value, (tuple, list)):
        return ":".join(_text(v) for v in value)
    return "none" if value is None else str(value)


def parse_value(scenario: ScenarioName, key: str, text: str) -> Any:
    """The value of parameter ``key`` of ``scenario``, read from ``text``."""
    check_keys(scenario, [key])
    entry = get(scenario)
    default = entry.defaults()[key]
    admitted = entry.types()[key]
    if str in admitted and not ({int, float, bool, type(None)} & set(admitted)):
        return text.strip()  # a text argument takes the text as it is
    return _coerce(key, _literal(text), default, admitted)


def parse_grid(scenario: ScenarioName, items: Sequence[str]) -> dict[str, list[Any]]:
    """``["KEY=V1,V2", ...]`` -> ``{KEY: [V1, V2]}`` in the builder's types (a ValueError
    names a malformed item, an unknown key or a value of the wrong type)."""
    grid: dict[str, list[Any]] = {}
    for item in items:
        key, sep, values = item.partition("=")
        key = key.strip()
        if not sep or not key or not values.strip():
            raise ValueError(f"--grid takes KEY=V1,V2,..., got {item!r}")
        if key in grid:
            raise ValueError(f"--grid names {key!r} twice")
        grid[key] = [parse_value(scenario, key, v) for v in values.split(",")]
    return grid


def check_buildable(
    scenario: ScenarioName, configs: Sequence[Mapping[str, Any]], *, seed: int, device: str
) -> None:
    """Build each configuration of ``scenario`` once, on one seed, so that a value its builder
    refuses is a ``ValueError`` naming the configuration before any work."""
    make = get(scenario).make
    for params in configs:
        try:
            make(**params, num_seeds=1, seed=seed, device=device)
        except (TypeError, ValueError) as error:
            raise ValueError(f"configuration {describe(params)}: {error}") from error


def describe(params: Mapping[str, Any]) -> str:
    """``key=value`` pairs as the command line writes them."""
    return " ".join(f"{k}={_text(v)}" for k, v in params.items())
