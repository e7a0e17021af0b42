"""Rollout costs for MPPI.

A cost scores whole rollouts: ``cost(states [B, K, H+1, n], controls [B, K, H, m], t0 [B])
-> [B, K]``, where ``states[..., 0, :]`` is the current state at global time ``t0``. Any
callable with that signature works with :class:`~torchcbf.mppi.MPPI`; the classes here build
one from a per-step (stage) and a terminal function.

Stage convention (as pytorch-mppi): the stage cost of step ``k`` is evaluated on the state
*after* the control, ``stage(x_{k+1}, u_k)`` for ``k = 0..H-1``, summed over time; the
terminal cost is evaluated on ``x_H``. (The current state ``x_0`` is shared by every sample,
so it would not change the weights.)
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import torch
from torch import Tensor, nn

from torchcbf._checks import as_tensor, check_index
from torchcbf.mppi.history import History

Stage = Callable[[Tensor, Tensor], Tensor]
Terminal = Callable[[Tensor], Tensor]


def _select(x: Tensor, index: tuple[int, ...] | slice) -> Tensor:
    return x[..., index] if isinstance(index, slice) else x[..., list(index)]


def _as_index(index: Sequence[int]) -> tuple[int, ...] | slice:
    """A contiguous index becomes a slice (a view, no gather)."""
    idx = check_index("index", index, None)
    if idx == tuple(range(idx[0], idx[0] + len(idx))):
        return slice(idx[0], idx[0] + len(idx))
    return idx


def _const(name: str, value: object) -> Tensor:
    """A constant vector: tensors keep their dtype, Python numbers become float64 (cast to the
    rollout's dtype at use, so float64 rollouts see exact constants)."""
    if isinstance(value, Tensor):
        return as_tensor(name, value).reshape(-1)
    return as_tensor(name, value, dtype=torch.float64).reshape(-1)


def _sq_dist(p: Tensor, c: Tensor) -> Tensor:
    diff = p - c.to(device=p.device, dtype=p.dtype)
    return diff.square_().sum(-1)


class RolloutCost(nn.Module):
    """Base of the stage + terminal costs. Subclasses write ``stage`` (and ``terminal``).

    ``forward(states [B, K, H+1, n], controls [B, K, H, m], t0=None) -> [B, K]`` is
    ``sum_k stage(x_{k+1}, u_k) + terminal(x_H)``. Costs add: ``cost_a + cost_b`` is a
    :class:`SumCost`.
    """

    def stage(self, states: Tensor, controls: Tensor | None) -> Tensor:
        """Per-step cost ``[..., n], [..., m] -> [...]``."""
        raise NotImplementedError(f"{type(self).__name__} must define stage()")

    def terminal(self, states: Tensor) -> Tensor | None:
        """Terminal cost ``[..., n] -> [...]`` or ``None`` (no terminal term)."""
        return None

    def forward(self, states: Tensor, controls: Tensor, t0: Tensor | None = None) -> Tensor:
        cost = self.stage(states[..., 1:, :], controls).sum(-1)
        term = self.terminal(states[..., -1, :])
        return cost if term is None else cost + term

    def __add__(self, other: object) -> SumCost:
        if not callable(other):
            return NotImplemented
        return SumCost(self, other)


class StageCost(RolloutCost):
    """Rollout cost from plain functions: ``stage(states [..., n], controls [..., m]) -> [...]``
    summed over the steps, plus ``terminal(states [..., n]) -> [...]`` on the last state."""

    def __init__(self, stage: Stage, terminal: Terminal | None = None) -> None:
        super().__init__()
        if not callable(stage):
            raise TypeError(f"stage must be callable, got {type(stage).__name__}")
        if terminal is not None and not callable(terminal):
            raise TypeError(f"terminal must be callable or None, got {type(terminal).__name__}")
        self.stage_fn = stage
        self.terminal_fn = terminal

    def stage(self, states: Tensor, controls: Tensor | None) -> Tensor:
        return self.stage_fn(states, controls)

    def terminal(self, states: Tensor) -> Tensor | None:
        return None if self.terminal_fn is None else self.terminal_fn(states)


class QuadraticGoal(RolloutCost):
    """``weight |p - goal|^2`` per step and ``terminal_weight |p - goal|^2`` on ``x_H``,
    with ``p = x[..., index]`` (``goal [d]``, ``index`` of length ``d``; all of ``x`` when
    ``index`` is ``None``)."""

    def __init__(
        self,
        goal: Tensor | Sequence[float],
        weight: float = 1.0,
        index: Sequence[int] | None = None,
        terminal_weight: float = 0.0,
    ) -> None:
        super().__init__()
        goal_t = _const("goal", goal)
        self.index = _as_index(range(goal_t.numel()) if index is None else index)
        d = self.index.stop - self.index.start if isinstance(self.index, slice) else len(self.index)
        if d != goal_t.numel():
            raise ValueError(f"goal has {goal_t.numel()} entries but index names {d}")
        self.register_buffer("goal", goal_t)
        self.weight = float(weight)
        self.terminal_weight = float(terminal_weight)

    def stage(self, states: Tensor, controls: Tensor | None) -> Tensor:
        return self.weight * _sq_dist(_select(states, self.index), self.goal)

    def terminal(self, states: Tensor) -> Tensor | None:
        if self.terminal_weight == 0.0:
            return None
        return self.terminal_weight * _sq_dist(_select(states, self.index), self.goal)


class ObstacleCost(RolloutCost):
    """``k_o / max(|p - center| - radius, eps)`` per step, ``p = x[..., index]`` (SCENARIOS A)."""

    def __init__(
        self,
        center: Tensor | Sequence[float],
        radius: float,
        k_o: float = 1.0,
        eps: float = 0.01,
        index: Sequence[int] = (0, 1),
    ) -> None:
        super().__init__()
        center_t = _const("center", center)
        self.index = _as_index(index)
        if radius < 0 or eps <= 0:
            raise ValueError(f"radius must be >= 0 and eps > 0, got radius={radius}, eps={eps}")
        self.register_buffer("center", center_t)
        self.radius, self.k_o, self.eps = float(radius), float(k_o), float(eps)

    def stage(self, states: Tensor, controls: Tensor | None) -> Tensor:
        dist = _sq_dist(_select(states, self.index), self.center).sqrt() - self.radius
        return self.k_o / dist.clamp_min(self.eps)


def _barrier_values(barrier: Terminal, states: Tensor) -> Tensor:
    """``b(states) -> [..., k]``: a one-output barrier gets a trailing dimension of 1."""
    value = barrier(states)
    return value if value.dim() == states.dim() else value.unsqueeze(-1)


class BarrierCost(RolloutCost):
    """``weight sum_i 1 / max(b_i(x), eps)`` per step for a barrier ``b: [..., n] -> [...]``
    or ``[..., k]`` (``b >= 0`` safe; any callable or module, e.g. the five ellipses of
    scenario B with weight 2, eps 0.01)."""

    def __init__(self, barrier: Terminal, weight: float = 1.0, eps: float = 0.01) -> None:
        super().__init__()
        if not callable(barrier):
            raise TypeError(f"barrier must be callable, got {type(barrier).__name__}")
        if eps <= 0:
            raise ValueError(f"eps must be > 0, got {eps}")
        self.barrier = barrier
        self.weight, self.eps = float(weight), float(eps)

    def stage(self, states: Tensor, controls: Tensor | None) -> Tensor:
        return (self.weight / _barrier_values(self.barrier, states).clamp_min(self.eps)).sum(-1)


class DiscreteBarrierCost(nn.Module):
    """A steep penalty on the discrete-time CBF condition ``b(x_{k+1}) >= (1 - gamma) b(x_k)``
    along the rollout: ``weight sum_k sum_i relu((1 - gamma) b_i(x_k) - b_i(x_{k+1}))``.

    With ``gamma = k dt`` it is the one-step form of ``L_f b + k b >= 0`` (the safe set of an
    exponentially rectified barrier), so rollouts that a CBF filter would correct cost more.

    It reads consecutive states, so it is a whole-rollout cost: ``forward(states [B, K, H+1,
    n], controls, t0=None) -> [B, K]``.

    Args:
        barrier: ``b: [..., n] -> [...]`` or ``[..., k]`` (``b >= 0`` safe).
        gamma: decay per step, ``0 < gamma <= 1``.
        weight: penalty weight (``>= 0``).
    """

    def __init__(self, barrier: Terminal, *, gamma: float, weight: float = 1e3) -> None:
        super().__init__()
        if not callable(barrier):
            raise TypeError(f"barrier must be callable, got {type(barrier).__name__}")
        if not 0.0 < gamma <= 1.0:
            raise ValueError(f"gamma must be in (0, 1], got {gamma}")
        if not weight >= 0.0:
            raise ValueError(f"weight must be >= 0, got {weight}")
        self.barrier = barrier
        self.gamma, self.weight = float(gamma), float(weight)

    def forward(self, states: Tensor, controls: Tensor, t0: Tensor | None = None) -> Tensor:
        b = _barrier_values(self.barrier, states)  # [..., H+1, k]
        violation = ((1.0 - self.gamma) * b[..., :-1, :] - b[..., 1:, :]).clamp_min(0.0)
        return self.weight * violation.sum((-2, -1))


class SumCost(RolloutCost):
    """Sum of costs. Stage/terminal parts of :class:`RolloutCost` terms are added pointwise
    before the one sum over time; other callables are called on the whole rollout."""

    def __init__(self, *costs: Callable[..., Tensor]) -> None:
        super().__init__()
        if not costs:
            raise ValueError("SumCost needs at least one cost")
        flat: list[Callable[..., Tensor]] = []
        for c in costs:
            if not callable(c):
                raise TypeError(f"every cost must be callable, got {type(c).__name__}")
            flat.extend(c.terms if isinstance(c, SumCost) else [c])
        self.terms = nn.ModuleList([c for c in flat if isinstance(c, nn.Module)])
        self._plain = [c for c in flat if not isinstance(c, nn.Module)]
        self._stepwise = [c for c in self.terms if isinstance(c, RolloutCost)]
        self._whole = [c for c in self.terms if not isinstance(c, RolloutCost)] + self._plain

    def stage(self, states: Tensor, controls: Tensor | None) -> Tensor:
        total = self._stepwise[0].stage(states, controls)
        for c in self._stepwise[1:]:
            total = total + c.stage(states, controls)
        return total

    def terminal(self, states: Tensor) -> Tensor | None:
        total: Tensor | None = None
        for c in self._stepwise:
            term = c.terminal(states)
            if term is not None:
                total = term if total is None else total + term
        return total

    @property
    def needs_history(self) -> bool:
        """Whether a term is a specification that reads the planner's history."""
        return any(getattr(c, "needs_history", False) for c in self._whole)

    def forward(
        self,
        states: Tensor,
        controls: Tensor,
        t0: Tensor | None = None,
        dt: float | None = None,
        history: History | None = None,
    ) -> Tensor:
        total: Tensor | None = super().forward(states, controls, t0) if self._stepwise else None
        for c in self._whole:
            if getattr(c, "needs_history", False):
                value = c(states, controls, t0, dt=dt, history=history)
            else:
                value = c(states, controls, t0)
            total = value if total is None else total + value
        assert total is not None
        return total


__all__ = [
    "BarrierCost",
    "DiscreteBarrierCost",
    "ObstacleCost",
    "QuadraticGoal",
    "RolloutCost",
    "StageCost",
    "SumCost",
]
