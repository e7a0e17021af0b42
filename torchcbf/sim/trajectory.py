"""The record of a batch of closed-loop runs."""

from __future__ import annotations

import collections
import dataclasses
import operator
import pickle
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor

from torchcbf import _io

_TUPLE = "__namedtuple__"


def _record(value: Any) -> tuple[str, dict[str, Any]] | None:
    """``(name, fields)`` of a named tuple or a dataclass instance (a planner's output),
    else ``None``."""
    if isinstance(value, tuple) and hasattr(value, "_fields"):
        return type(value).__name__, value._asdict()
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return type(value).__name__, {
            f.name: getattr(value, f.name) for f in dataclasses.fields(value)
        }
    return None


def _restore(value: Any) -> Any:
    """The inverse of :func:`_tagged`: tagged dicts as named tuples of the same name and fields
    (built here, so reading a file never imports or runs code named by it; a dataclass
    comes back as such a named tuple)."""
    if isinstance(value, dict):
        if set(value) == {_TUPLE, "fields"} and isinstance(value["fields"], dict):
            fields = {str(k): _restore(v) for k, v in value["fields"].items()}
            kind = collections.namedtuple(str(value[_TUPLE]), list(fields))  # noqa: PYI024
            return kind(**fields)
        return {k: _restore(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return type(value)(_restore(v) for v in value)
    return value


def _walk(value: Any, leaf: Any, record: Any) -> Any:
    """``value`` with ``leaf`` applied to its tensors, through dicts, lists, tuples, named
    tuples and dataclass instances (those rebuilt by ``record(value, mapped fields)``)."""
    if isinstance(value, Tensor):
        return leaf(value)
    fields = _record(value)
    if fields is not None:
        return record(value, {k: _walk(v, leaf, record) for k, v in fields[1].items()})
    if isinstance(value, dict):
        return {k: _walk(v, leaf, record) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return type(value)(_walk(v, leaf, record) for v in value)
    return value


def _tagged(value: Any, fields: dict[str, Any]) -> dict[str, Any]:
    """A named tuple or dataclass instance as a tagged dict: what
    ``torch.load(weights_only=True)`` reads back (tensors, numbers, strings, lists, tuples,
    dicts)."""
    return {_TUPLE: type(value).__name__, "fields": fields}


def _same_kind(value: Any, fields: dict[str, Any]) -> Any:
    if isinstance(value, tuple):
        return type(value)(**fields)
    return dataclasses.replace(value, **fields)


@dataclass
class Trajectory:
    """B scenarios over T steps of length ``dt``.

    Attributes:
        t: times ``[T+1]``, float64 (exact steps at any start time).
        x: true states ``[B, T+1, n]``.
        x_hat: estimated (or measured) states the controllers saw ``[B, T+1, n]``.
        u_nom: nominal controls ``[B, T, m]`` (planner or nominal controller output).
        u: applied controls ``[B, T, m]``.
        h: barrier values reported by the safety filter ``[B, T, k]`` (``None`` without one;
            NaN from a row's ``fail_step`` on).
        status: safety-filter status per step ``[B, T]`` (``None`` without a filter;
            ``NON_FINITE`` from a row's ``fail_step`` on).
        failed: ``[B]`` bool, a scenario whose state, estimate or a component's output went
            non-finite; from ``fail_step [B]`` on (``-1`` if never) it is frozen.
        planner: snapshots of planner outputs, ``{step: output}`` (on the device it ran on).
    """

    t: Tensor
    x: Tensor
    x_hat: Tensor
    u_nom: Tensor
    u: Tensor
    h: Tensor | None
    status: Tensor | None
    failed: Tensor
    fail_step: Tensor
    planner: dict[int, Any] = field(default_factory=dict)

    @property
    def batch_size(self) -> int:
        return self.x.shape[0]

    @property
    def dt(self) -> float:
        return float(self.t[1] - self.t[0]) if self.t.numel() > 1 else 0.0

    def _map(self, fn) -> Trajectory:
        return Trajectory(
            **{
                f.name: _walk(getattr(self, f.name), fn, _same_kind)
                for f in dataclasses.fields(self)
            }
        )

    def to(self, device: torch.device | str) -> Trajectory:
        """A copy with every tensor on ``device``."""
        return self._map(lambda v: v.to(device))

    def numpy(self) -> dict[str, Any]:
        """Every field as numpy arrays (planner snapshots as dicts of arrays)."""

        def leaf(value: Tensor) -> Any:
            return value.detach().cpu().numpy()

        def record(_: Any, fields: dict[str, Any]) -> dict[str, Any]:
            return fields

        return {
            f.name: _walk(getattr(self, f.name), leaf, record) for f in dataclasses.fields(self)
        }

    def save(self, path: str | Path) -> None:
        """Save with ``torch.save`` (tensors moved to the CPU; planner snapshots as plain
        dicts), written to a temporary name and renamed, so ``path`` is never half-written."""
        data = {
            f.name: _walk(getattr(self, f.name), lambda t: t.to("cpu"), _tagged)
            for f in dataclasses.fields(self)
        }
        with _io.atomic_path(path) as tmp:
            torch.save(data, tmp)

    @classmethod
    def load(cls, path: str | Path, map_location: str | torch.device = "cpu") -> Trajectory:
        """Load a trajectory written by :meth:`save`. Tensors and plain containers only
        (``torch.load(weights_only=True)``): a file holding any other Python object is refused
        with a ValueError, never unpickled, so a file from elsewhere cannot run code.
        Planner snapshots come back as named tuples with the fields they were saved with (a
        dataclass output as a named tuple of its fields)."""
        try:
            data = torch.load(Path(path), map_location=map_location, weights_only=True)
        except pickle.UnpicklingError as error:
            raise ValueError(
                f"{path} is not a trajectory file of tensors only (Trajectory.save writes "
                f"one); refused without unpickling its objects: {error}"
            ) from None
        except (OSError, EOFError, RuntimeError, KeyError) as error:
            if isinstance(error, (FileNotFoundError, IsADirectoryError, PermissionError)):
                raise
            raise ValueError(
                f"{path} is not a file torch.save wrote (empty, truncated or of another "
                f"format): {type(error).__name__}: {error}"
            ) from None
        fields = dataclasses.fields(cls)
        names = {f.name for f in fields}
        needed = {f.name for f in fields if f.default is f.default_factory is dataclasses.MISSING}
        if not isinstance(data, dict) or not needed <= set(data) <= names:
            missing = sorted(needed - set(data)) if isinstance(data, dict) else []
            raise ValueError(
                f"{path} is not a trajectory written by Trajectory.save"
                + (f" (missing {', '.join(missing)})" if missing else "")
            )
        return cls(**{k: _restore(v) for k, v in data.items()})

    def scenario(self, index: int) -> Trajectory:
        """Scenario ``index`` alone (batch of one, its own copies of the rows, so that
        :meth:`save` writes that row only; negative indices count from the end, others
        outside the batch raise ``IndexError``). Planner snapshots hold the whole batch's
        outputs and are not carried over (``planner`` is empty)."""
        B = self.batch_size
        # an int, a NumPy int or a 0-d integer tensor (an argmax); not a bool
        given = index
        ok = not isinstance(index, (bool, np.bool_)) and not (
            isinstance(index, Tensor) and (index.dim() != 0 or index.dtype == torch.bool)
        )
        try:
            index = operator.index(index) if ok else None
        except TypeError:
            index = None
        if index is None:
            raise TypeError(f"index must be an int, got {given!r}")
        if not -B <= index < B:
            raise IndexError(f"scenario {index} is outside a batch of {B}")
        index %= B
        sl = slice(index, index + 1)

        def row(value: Tensor | None) -> Tensor | None:
            return None if value is None else value[sl].clone()

        return Trajectory(
            t=self.t,
            x=row(self.x),
            x_hat=row(self.x_hat),
            u_nom=row(self.u_nom),
            u=row(self.u),
            h=row(self.h),
            status=row(self.status),
            failed=row(self.failed),
            fail_step=row(self.fail_step),
            planner={},
        )
