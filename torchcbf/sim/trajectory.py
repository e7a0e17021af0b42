"""The record of a batch of closed-loop runs."""

from __future__ import annotations

import collections
import dataclasses
import pickle
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch
from torch import Tensor

from torchcbf import _io

_TUPLE = "__namedtuple__"


def _plain(value: Any) -> Any:
    """``value`` with named tuples as tagged dicts: what ``torch.load(weights_only=True)``
    reads back (tensors, numbers, strings, lists, tuples, dicts)."""
    if isinstance(value, tuple) and hasattr(value, "_fields"):
        fields = {k: _plain(v) for k, v in value._asdict().items()}
        return {_TUPLE: type(value).__name__, "fields": fields}
    if isinstance(value, dict):
        return {k: _plain(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return type(value)(_plain(v) for v in value)
    return value


def _restore(value: Any) -> Any:
    """The inverse of :func:`_plain`: tagged dicts as named tuples of the same name and fields
    (built here, so reading a file never imports or runs code named by it)."""
    if isinstance(value, dict):
        if set(value) == {_TUPLE, "fields"} and isinstance(value["fields"], dict):
            fields = {str(k): _restore(v) for k, v in value["fields"].items()}
            kind = collections.namedtuple(str(value[_TUPLE]), list(fields))  # noqa: PYI024
            return kind(**fields)
        return {k: _restore(v) for k, v in value.items()}
    if isinstance(value, list):
        return [_restore(v) for v in value]
    return value


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
        def apply(value: Any) -> Any:
            if isinstance(value, Tensor):
                return fn(value)
            if isinstance(value, tuple) and hasattr(value, "_fields"):
                return type(value)(*(apply(v) for v in value))
            if isinstance(value, dict):
                return {k: apply(v) for k, v in value.items()}
            return value

        return Trajectory(
            **{f.name: apply(getattr(self, f.name)) for f in dataclasses.fields(self)}
        )

    def to(self, device: torch.device | str) -> Trajectory:
        """A copy with every tensor on ``device``."""
        return self._map(lambda v: v.to(device))

    def numpy(self) -> dict[str, Any]:
        """Every field as numpy arrays (planner snapshots as dicts of arrays)."""

        def conv(value: Any) -> Any:
            if isinstance(value, Tensor):
                return value.detach().cpu().numpy()
            if isinstance(value, tuple) and hasattr(value, "_fields"):
                return {k: conv(v) for k, v in value._asdict().items()}
            if isinstance(value, dict):
                return {k: conv(v) for k, v in value.items()}
            return value

        return {f.name: conv(getattr(self, f.name)) for f in dataclasses.fields(self)}

    def save(self, path: str | Path) -> None:
        """Save with ``torch.save`` (tensors moved to the CPU; planner snapshots as plain
        dicts), written to a temporary name and renamed, so ``path`` is never half-written."""
        cpu = self.to("cpu")
        data = {f.name: _plain(getattr(cpu, f.name)) for f in dataclasses.fields(self)}
        with _io.atomic_path(path) as tmp:
            torch.save(data, tmp)

    @classmethod
    def load(cls, path: str | Path, map_location: str | torch.device = "cpu") -> Trajectory:
        """Load a trajectory written by :meth:`save`. Tensors and plain containers only
        (``torch.load(weights_only=True)``): a file holding any other Python object is refused
        with a ValueError, never unpickled, so a file from elsewhere cannot run code.
        Planner snapshots come back as named tuples with the fields they were saved with."""
        try:
            data = torch.load(Path(path), map_location=map_location, weights_only=True)
        except pickle.UnpicklingError as error:
            raise ValueError(
                f"{path} is not a trajectory file of tensors only (Trajectory.save writes "
                f"one); refused without unpickling its objects: {error}"
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
        """Scenario ``index`` alone (batch of one; negative indices count from the end,
        others outside the batch raise ``IndexError``)."""
        B = self.batch_size
        if not -B <= index < B:
            raise IndexError(f"scenario {index} is outside a batch of {B}")
        index %= B
        sl = slice(index, index + 1)
        return Trajectory(
            t=self.t,
            x=self.x[sl],
            x_hat=self.x_hat[sl],
            u_nom=self.u_nom[sl],
            u=self.u[sl],
            h=None if self.h is None else self.h[sl],
            status=None if self.status is None else self.status[sl],
            failed=self.failed[sl],
            fail_step=self.fail_step[sl],
            planner={},
        )
