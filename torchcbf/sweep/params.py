"""Scenario builders by name, and their keyword arguments read from the command line.

A builder's keyword arguments are read from its signature, so a sweep or a search covers
whatever the builder accepts. A value given as text is converted to a type the argument's
annotation admits (or, without one, the type of its default): ``int``, ``float``, ``bool``
(``true``/``false``), ``str``, a tuple (``a:b``, e.g. ``control_limit=2:4``) and ``none``.
"""

from __future__ import annotations

import inspect
import math
import types
import typing
from collections.abc import Callable, Mapping, Sequence
from typing import Any

from torchcbf.scenarios import Scenario, mppi_cbf, reach_avoid

SCENARIOS: dict[str, Callable[..., Scenario]] = {"reach-avoid": reach_avoid, "mppi-cbf": mppi_cbf}

# Arguments that the sweep itself sets (seeds, placement): not part of a configuration.
RESERVED = ("num_seeds", "seed", "device", "dtype")


def builder(scenario: str) -> Callable[..., Scenario]:
    """The builder of ``scenario`` (a key of :data:`SCENARIOS`)."""
    if scenario not in SCENARIOS:
        raise ValueError(f"scenario must be one of {sorted(SCENARIOS)}, got {scenario!r}")
    return SCENARIOS[scenario]


def builder_defaults(scenario: str) -> dict[str, Any]:
    """The builder's keyword arguments and their defaults, without :data:`RESERVED`."""
    params = inspect.signature(builder(scenario)).parameters
    return {
        name: p.default
        for name, p in params.items()
        if name not in RESERVED
        and p.kind in (p.POSITIONAL_OR_KEYWORD, p.KEYWORD_ONLY)
        and p.default is not inspect.Parameter.empty
    }


def check_keys(scenario: str, keys: Sequence[str]) -> None:
    """Raise a ValueError naming any key that is not a keyword argument of the builder."""
    known = builder_defaults(scenario)
    for key in keys:
        if key in RESERVED:
            raise ValueError(
                f"{key!r} is set by the sweep itself (--seeds, --seed, --device), not in a grid"
            )
        if key not in known:
            raise ValueError(
                f"unknown key {key!r} for scenario {scenario!r}; its keyword arguments are: "
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


def _hint_types(scenario: str, key: str) -> tuple[Any, ...]:
    """The types the builder's annotation of ``key`` admits (empty without an annotation)."""
    try:
        hint = typing.get_type_hints(builder(scenario)).get(key)
    except (NameError, TypeError):
        return ()
    if hint is None:
        return ()
    return typing.get_args(hint) if isinstance(hint, types.UnionType) else (hint,)


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


def parse_value(scenario: str, key: str, text: str) -> Any:
    """The value of ``key`` for the builder of ``scenario``, read from ``text``."""
    check_keys(scenario, [key])
    default = builder_defaults(scenario)[key]
    admitted = _hint_types(scenario, key)
    if str in admitted and not ({int, float, bool, type(None)} & set(admitted)):
        return text.strip()  # a text argument takes the text as it is
    return _coerce(key, _literal(text), default, admitted)


def parse_grid(scenario: str, items: Sequence[str]) -> dict[str, list[Any]]:
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


def jsonable(value: Any) -> Any:
    """A value as strict JSON: mappings with string keys, tuples as lists, non-finite floats
    as None, anything else that is not a JSON scalar as its ``str``."""
    if isinstance(value, Mapping):
        return {str(k): jsonable(v) for k, v in value.items()}
    if isinstance(value, (tuple, list)):
        return [jsonable(v) for v in value]
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if isinstance(value, (bool, int, float, str)) or value is None:
        return value
    return str(value)


def check_buildable(
    scenario: str, configs: Sequence[Mapping[str, Any]], *, seed: int, device: str
) -> None:
    """Build each configuration of ``scenario`` once, on one seed, so that a value its builder
    refuses is a ``ValueError`` naming the configuration before any work."""
    make = builder(scenario)
    for params in configs:
        try:
            make(**params, num_seeds=1, seed=seed, device=device)
        except (TypeError, ValueError) as error:
            raise ValueError(f"configuration {describe(params)}: {error}") from error


def describe(params: Mapping[str, Any]) -> str:
    """``key=value`` pairs as the command line writes them."""
    return " ".join(f"{k}={_text(v)}" for k, v in params.items())
