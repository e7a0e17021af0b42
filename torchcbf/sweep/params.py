"""Scenario builders by name, and their keyword arguments read from the command line.

A builder's keyword arguments are read from its signature, so a sweep or a search covers
whatever the builder accepts. A value given as text is converted to the type of the
argument's default: ``int``, ``float``, ``bool`` (``true``/``false``), ``str``, a tuple
(``a:b``, e.g. ``control_limit=2:4``) and ``none``.
"""

from __future__ import annotations

import inspect
import math
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


def _coerce(key: str, value: Any, default: Any) -> Any:
    """``value`` as the type of ``default`` (numbers widen int -> float; None is kept)."""
    if value is None or default is None:
        return value
    if isinstance(default, bool):
        if not isinstance(value, bool):
            raise ValueError(f"{key} takes true or false, got {value!r}")
        return value
    if isinstance(default, int):
        if isinstance(value, float) and value.is_integer():
            value = int(value)
        if isinstance(value, bool) or not isinstance(value, int):
            raise ValueError(f"{key} takes an integer, got {value!r}")
        return value
    if isinstance(default, float):
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ValueError(f"{key} takes a number, got {value!r}")
        return float(value)
    if isinstance(default, str):
        return value if isinstance(value, str) else _text(value)
    if isinstance(default, (tuple, list)):
        items = value if isinstance(value, tuple) else (value,)
        if all(isinstance(d, float) for d in default):
            items = tuple(float(v) if isinstance(v, int) else v for v in items)
        return items[0] if len(items) == 1 and not isinstance(value, tuple) else tuple(items)
    return value


def _text(value: Any) -> str:
    if isinstance(value, (tuple, list)):
        return ":".join(_text(v) for v in value)
    return "none" if value is None else str(value)


def parse_value(scenario: str, key: str, text: str) -> Any:
    """The value of ``key`` for the builder of ``scenario``, read from ``text``."""
    check_keys(scenario, [key])
    value = _literal(text)
    default = builder_defaults(scenario)[key]
    if isinstance(default, str):
        return text.strip()
    return _coerce(key, value, default)


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
    """A parameter value as strict JSON (tuples as lists, non-finite floats as None)."""
    if isinstance(value, (tuple, list)):
        return [jsonable(v) for v in value]
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if isinstance(value, (bool, int, float, str)) or value is None:
        return value
    return str(value)


def describe(params: Mapping[str, Any]) -> str:
    """``key=value`` pairs as the command line writes them."""
    return " ".join(f"{k}={_text(v)}" for k, v in params.items())
