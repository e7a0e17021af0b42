"""Rollout costs for MPPI.

A cost scores whole rollouts: ``cost(states [B, K, H+1, n], controls [B, K, H, m], t0 [B])
-> [B, K]``, where ``states[..., 0, :]`` is the current state at global time ``t0``. Any
callable with that signature works with :class:`~torchcbf.mppi.MPPI`; the classes here build
one from a per-step (stage) and a terminal function. A cost with ``needs_time = True`` is
also given ``dt=`` (rollout state ``k`` is at ``t0 + k dt``): the barrier costs set it for a
time-varying barrier, which they read at each state's time.

Stage convention (as pytorch-mppi): the stage cost of step ``k`` is evaluated on the state
*after* the control, ``stage(x_{k+1}, u_k)`` for ``k = 0..H-1``, summed over time; the
terminal cost is evaluated on ``x_H``. (The current state ``x_0`` is shared by every sample,
so it would not change the weights.)
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import torch
from torch import Tensor, nn

from torchcbf._checks import (
    TracksShadows,
    as_tensor,
    check_finite,
    check_index,
    check_number,
    check_positive_int,
    check_times,
    hooked,
)
from torchcbf.barriers._params import take
from torchcbf.mppi.history import History

Stage = Callable[[Tensor, Tensor], Tensor]
Terminal = Callable[[Tensor], Tensor]


def select(x: Tensor, index: tuple[int, ...] | slice) -> Tensor:
    """``x[..., index]`` for an index made by :func:`state_index` (a view for a slice)."""
    return x[..., index] if isinstance(index, slice) else take(x, index)


def state_index(index: Sequence[int], name: str = "index") -> tuple[int, ...] | slice:
    """Checked state components; a contiguous index becomes a slice (a view, no gather)."""
    idx = check_index(name, index, None)
    if idx == tuple(range(idx[0], idx[0] + len(idx))):
        return slice(idx[0], idx[0] + len(idx))
    return idx


def point_index(center: Tensor, index: Sequence[int]) -> tuple[int, ...] | slice:
    """:func:`state_index` of ``index``, which must name as many components as ``center``
    has entries (``ValueError`` otherwise: a shorter center would broadcast)."""
    idx = state_index(index)
    d = idx.stop - idx.start if isinstance(idx, slice) else len(idx)
    if d != center.numel():
        raise ValueError(f"center has {center.numel()} entries but index names {d}")
    return idx


def constant(name: str, value: object) -> Tensor:
    """A constant vector: tensors keep their dtype, Python numbers become float64 (cast to the
    rollout's dtype at use, so float64 rollouts see exact constants)."""
    if isinstance(value, Tensor):
        return check_finite(name, as_tensor(name, value)).reshape(-1)
    return check_finite(name, as_tensor(name, value, dtype=torch.float64)).reshape(-1)


def squared_distance(x: Tensor, index: tuple[int, ...] | slice, center: Tensor) -> Tensor:
    """``|x[..., index] - center|^2``: ``[..., n] -> [...]`` (``center`` cast to ``x``)."""
    diff = select(x, index) - center.to(device=x.device, dtype=x.dtype)
    return diff.square_().sum(-1)


def root(d2: Tensor) -> Tensor:
    """``sqrt(d2)`` of squared distances with the subgradient 0 at 0 (the square root's
    derivative is infinite there, and a zero upstream gradient times it NaN)."""
    return d2.clamp_min(torch.finfo(d2.dtype).tiny).sqrt()


def time_varying(barrier: object) -> bool:
    """Whether a barrier (any callable) declares itself time-varying (``b(x, t)``)."""
    return bool(getattr(barrier, "time_varying", False))


def untimed(name: str, barrier: object) -> None:
    """Refuse a time-varying barrier where ``name`` has no times to read it at (it would be
    read at ``t = 0``)."""
    if time_varying(barrier):
        raise ValueError(
            f"{name} has no times, and {type(barrier).__name__} is time-varying: it would be "
            "read at t = 0. Call the whole cost with t0= and dt= (as the planner does), or "
            "read it with predicate_at(x, t) or robustness(x, t)"
        )


def rollout_times(states: Tensor, t0: Tensor | float | None, dt: float | None, name: str) -> Tensor:
    """Global times ``[B, T]`` of rollouts ``states [B, K, T, n]`` whose state ``k`` is at
    ``t0 + k dt`` (``t0 [B]``, a number, or ``None`` for 0); ``ValueError`` naming ``name``
    without ``dt``."""
    if dt is None:
        raise ValueError(f"{name} needs dt= (the rollout step) to time its states")
    dt = check_number("dt", dt, low=0.0, strict=True)
    if states.dim() != 4:
        raise ValueError(f"states must have shape [B, K, T, n], got {tuple(states.shape)}")
    check_times("t0", t0)
    t0_t = as_tensor("t0", 0.0 if t0 is None else t0, device=states.device, dtype=states.dtype)
    if t0_t.numel() not in (1, states.shape[0]):
        raise ValueError(
            f"t0 must be a number or have one time per row [{states.shape[0]}], "
            f"got {tuple(t0_t.shape)}"
        )
    steps = torch.arange(states.shape[-2], device=states.device, dtype=states.dtype)
    return (t0_t.reshape(-1, 1) + dt * steps).expand(states.shape[0], states.shape[-2])


class Adds:
    """Costs add: ``a + b`` with a cost module on either side and any callable cost on the
    other is a :class:`SumCost` (a specification plus a goal term, say)."""

    def __add__(self, other: object) -> SumCost:
        if not callable(other):
            return NotImplemented
        return SumCost(self, other)  # type: ignore[arg-type]

    def __radd__(self, other: object) -> SumCost:
        if not callable(other):
            return NotImplemented
        return SumCost(other, self)  # type: ignore[arg-type]


class RolloutCost(Adds, TracksShadows):
    """Base of the stage + terminal costs. Subclasses write ``stage`` (and ``terminal``).

    ``forward(states [B, K, H+1, n], controls [B, K, H, m], t0=None) -> [B, K]`` is
    ``sum_k stage(x_{k+1}, u_k) + terminal(x_H)``. Costs add (:class:`Adds`).
    """

    #: Whether the planner must pass ``dt=`` (a term that reads the rollout's times sets it).
    needs_time: bool = False

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
        goal_t = constant("goal", goal)
        self.index = state_index(range(goal_t.numel()) if index is None else index)
        d = self.index.stop - self.index.start if isinstance(self.index, slice) else len(self.index)
        if d != goal_t.numel():
            raise ValueError(f"goal has {goal_t.numel()} entries but index names {d}")
        self.register_buffer("goal", goal_t)
        self.weight = float(weight)
        self.terminal_weight = float(terminal_weight)

    def stage(self, states: Tensor, controls: Tensor | None) -> Tensor:
        return self.weight * squared_distance(states, self.index, self.goal)

    def terminal(self, states: Tensor) -> Tensor | None:
        if self.terminal_weight == 0.0:
            return None
        return self.terminal_weight * squared_distance(states, self.index, self.goal)


class ObstacleCost(RolloutCost):
    """``k_o / max(|p - center| - radius, eps)`` per step, ``p = x[..., index]`` (scenario A)."""

    def __init__(
        self,
        center: Tensor | Sequence[float],
        radius: float,
        k_o: float = 1.0,
        eps: float = 0.01,
        index: Sequence[int] = (0, 1),
    ) -> None:
        super().__init__()
        center_t = constant("center", center)
        self.index = point_index(center_t, index)
        radius = check_number("radius", radius, low=0.0)
        eps = check_number("eps", eps, low=0.0, strict=True)
        self.register_buffer("center", center_t)
        self.radius, self.eps = radius, eps
        self.k_o = check_number("k_o", k_o, low=0.0)

    def stage(self, states: Tensor, controls: Tensor | None) -> Tensor:
        dist = root(squared_distance(states, self.index, self.center)) - self.radius
        return self.k_o / dist.clamp_min(self.eps)


class BarrierCost(RolloutCost):
    """``weight / max(b(x), eps)`` per step for a barrier ``b: [..., n] -> [...]`` or
    ``[..., k]`` (``b >= 0`` safe; any callable or module), summed over a multi-output
    barrier's ``k`` outputs. Scenario B (docs/scenarios.md) uses the five ellipses,
    weight 2, eps 0.01.

    A barrier whose output has as many dimensions as its input is taken as multi-output.
    A time-varying barrier (``time_varying``: a :class:`~torchcbf.barriers.MovingBall`, a
    ``Ball`` with a velocity) is read at each state's time ``t0 + k dt``: the cost then
    ``needs_time`` and its ``forward`` takes ``dt=`` (the planner passes it).
    """

    def __init__(
        self,
        barrier: Terminal,
        weight: float = 1.0,
        eps: float = 0.01,
    ) -> None:
        super().__init__()
        if not callable(barrier):
            raise TypeError(f"barrier must be callable, got {type(barrier).__name__}")
        self.barrier = barrier
        self.weight = check_number("weight", weight, low=0.0)
        self.eps = check_number("eps", eps, low=0.0, strict=True)

    @property
    def needs_time(self) -> bool:  # type: ignore[override]
        """Whether the barrier is time-varying (``forward`` then needs ``dt=``)."""
        return time_varying(self.barrier)

    def stage(self, states: Tensor, controls: Tensor | None) -> Tensor:
        untimed("BarrierCost.stage", self.barrier)
        return self._penalty(self.barrier(states), states)

    def _penalty(self, h: Tensor, states: Tensor) -> Tensor:
        cost = self.weight / h.clamp_min(self.eps)
        return cost.sum(-1) if h.dim() == states.dim() else cost

    def forward(
        self,
        states: Tensor,
        controls: Tensor,
        t0: Tensor | float | None = None,
        dt: float | None = None,
    ) -> Tensor:
        if not self.needs_time:
            return super().forward(states, controls, t0)
        times = rollout_times(states, t0, dt, "BarrierCost over a time-varying barrier")
        after = states[..., 1:, :]
        return self._penalty(self.barrier(after, times[:, None, 1:]), after).sum(-1)


class DiscreteBarrierCost(Adds, TracksShadows):
    """Penalty on the discrete-time CBF condition ``b(x_{k+1}) >= (1 - gamma) b(x_k)``.

    ``weight * sum_k sum_i relu((1 - gamma) b_i(x_k) - b_i(x_{k+1}))`` over the steps
    ``k = 0..S-1`` of each rollout (``x_0`` the current state; ``S`` is ``steps``, at most
    the horizon ``H``) and the outputs ``i`` of a multi-output barrier: zero for a rollout
    that keeps the condition, growing linearly with each violation (the default weight makes
    it steep). The condition lets ``b`` decay at most
    geometrically towards the boundary; with ``gamma = k dt`` it is the one-step form of
    ``L_f b + k b >= 0`` (the safe set of an exponentially rectified barrier), so rollouts
    that a CBF filter would correct cost more: a planner-side counterpart of the filter.

    It reads consecutive states, so it is a whole-rollout cost: ``forward(states [B, K, H+1,
    n], controls [B, K, H, m], t0=None, dt=None) -> [B, K]``. With an
    :class:`~torchcbf.barriers.Ellipse` or :class:`~torchcbf.barriers.Ball` barrier the
    planner evaluates it in its C kernel. A time-varying barrier is read at each state's
    time ``t0 + k dt`` (the cost then ``needs_time``: the planner passes ``dt=``).

    Args:
        barrier: ``b: [..., n] -> [...]`` or ``[..., k]`` (``b >= 0`` safe; an output with as
            many dimensions as the input is taken as ``k`` outputs).
        gamma: decay per step, ``0 < gamma <= 1``.
        weight: penalty weight, ``>= 0``.
        steps: penalise only the first ``steps`` steps of each rollout (``None``: every
            step); the cost's time shrinks with it.
    """

    def __init__(
        self, barrier: Terminal, *, gamma: float, weight: float = 1e3, steps: int | None = None
    ) -> None:
        super().__init__()
        if not callable(barrier):
            raise TypeError(f"barrier must be callable, got {type(barrier).__name__}")
        if not isinstance(gamma, (int, float)) or not 0.0 < gamma <= 1.0:
            raise ValueError(f"gamma must be in (0, 1], got {gamma!r}")
        self.barrier = barrier
        self.gamma = float(gamma)
        self.weight = check_number("weight", weight, low=0.0)
        self.steps = None if steps is None else check_positive_int("steps", steps)

    needs_time = BarrierCost.needs_time

    def forward(
        self,
        states: Tensor,
        controls: Tensor,
        t0: Tensor | float | None = None,
        dt: float | None = None,
    ) -> Tensor:
        if self.steps is not None:
            states = states[..., : self.steps + 1, :]
        if self.needs_time:
            what = "DiscreteBarrierCost over a time-varying barrier"
            h = self.barrier(states, rollout_times(states, t0, dt, what)[:, None])
        else:
            h = self.barrier(states)
        if h.dim() < states.dim():
            h = h.unsqueeze(-1)
        viol = torch.relu((1.0 - self.gamma) * h[..., :-1, :] - h[..., 1:, :])
        return self.weight * viol.sum((-2, -1))


def _whole_term(cost: RolloutCost) -> bool:
    """Whether a :class:`SumCost` calls this term on the whole rollout: it has forward hooks
    (which must run) or reads the rollout's times."""
    return hooked(cost) or cost.needs_time


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
            flat.extend([*c.terms, *c._plain] if isinstance(c, SumCost) else [c])
        #: the terms that are modules (a term replaced or appended here is scored)
        self.terms = nn.ModuleList([c for c in flat if isinstance(c, nn.Module)])
        self._plain = [c for c in flat if not isinstance(c, nn.Module)]

    def stage(self, states: Tensor, controls: Tensor | None) -> Tensor:
        stepwise = self.stepwise_terms
        total = stepwise[0].stage(states, controls)
        for c in stepwise[1:]:
            total = total + c.stage(states, controls)
        return total

    def terminal(self, states: Tensor) -> Tensor | None:
        total: Tensor | None = None
        for c in self.stepwise_terms:
            term = c.terminal(states)
            if term is not None:
                total = term if total is None else total + term
        return total

    @property
    def stepwise_terms(self) -> list[RolloutCost]:
        """The :class:`RolloutCost` terms (stage and terminal parts added pointwise), but
        those with forward hooks (called whole, so that their hooks run) and those that read
        the rollout's times."""
        return [c for c in self.terms if isinstance(c, RolloutCost) and not _whole_term(c)]

    @property
    def whole_terms(self) -> list[Callable[..., Tensor]]:
        """The other terms, each called on the whole rollout and added after."""
        rolled = [c for c in self.terms if isinstance(c, RolloutCost) and _whole_term(c)]
        return rolled + [c for c in self.terms if not isinstance(c, RolloutCost)] + self._plain

    @property
    def needs_time(self) -> bool:  # type: ignore[override]
        """Whether a term reads the rollout's times (the planner then passes ``dt=``)."""
        return any(getattr(c, "needs_time", False) for c in [*self.terms, *self._plain])

    @property
    def needs_history(self) -> bool:
        """Whether a term is a specification that reads the planner's history."""
        return any(getattr(c, "needs_history", False) for c in [*self.terms, *self._plain])

    def forward(
        self,
        states: Tensor,
        controls: Tensor,
        t0: Tensor | None = None,
        dt: float | None = None,
        history: History | None = None,
    ) -> Tensor:
        stepwise, whole = self.stepwise_terms, self.whole_terms
        total: Tensor | None = super().forward(states, controls, t0) if stepwise else None
        for c in whole:
            if getattr(c, "needs_history", False):
                value = c(states, controls, t0, dt=dt, history=history)
            elif getattr(c, "needs_time", False):
                value = c(states, controls, t0, dt=dt)
            else:
                value = c(states, controls, t0)
            total = value if total is None else total + value
        assert total is not None
        return total


__all__ = [
    "Adds",
    "BarrierCost",
    "DiscreteBarrierCost",
    "ObstacleCost",
    "QuadraticGoal",
    "RolloutCost",
    "StageCost",
    "SumCost",
    "constant",
    "rollout_times",
    "root",
    "select",
    "squared_distance",
    "state_index",
    "time_varying",
    "untimed",
]
