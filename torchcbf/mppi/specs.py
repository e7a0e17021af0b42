"""Timed reach-avoid specifications in global time, usable as MPPI costs and as success checks.

The fragment: Boolean combinations (:class:`And`, :class:`Or`) of timed :class:`Always` /
:class:`Eventually` of *state predicates* ``rho(x) [..., n] -> [...]`` (``rho >= 0`` means the
predicate holds). Intervals are in global time (the time of the simulation, not relative to
the evaluation time), closed, with a tolerance ``time_tol`` (1e-5 s, widened to the
rounding of the times' dtype near the window's ends) so that sampled times like ``35 * 0.1``
fall inside ``[0, 3.5]`` in float32. :class:`Reach` and :class:`Avoid` are
the two predicates of scenario A (docs/scenarios.md).

**Robustness** (``robustness(states [..., T, n], times [T] or [..., T]) -> [...]``, positive
= satisfied) is the usual max/min semantics over the sampled times:

- ``Eventually[t1, t2] rho``: ``max rho(x_j)`` over the samples with ``t_j`` in the window
  (``-inf`` when none is);
- ``Always[t1, t2] rho``: ``min rho(x_j)`` over the window (``+inf`` when none is);
- ``And``: minimum, ``Or``: maximum of the children.

For :class:`Reach`, ``rho = r - |p - g|`` and for :class:`Avoid` ``rho = |p - o| - r`` (or the
barrier value ``b(x)``), so ``robustness >= 0`` is exactly "every goal is reached
(``|p - g| <= r``) at some sampled time inside its window and ``|p - o| >= r`` at every
sampled time".

**Cost** (the spec as an MPPI cost, ``spec(states [B, K, T, n], controls, t0 [B], dt=,
history=) -> [B, K]``, the rollout's state ``k`` being at time ``t0 + k dt``). Each temporal
node has a pointwise cost ``c(x)`` (``Reach``: ``weight (|p - g|^2 - r^2)``; ``Avoid``:
``weight / max(rho(x), eps)``; by default ``c = -rho``):

- ``Eventually``: the minimum of ``c`` over the states whose time lies in the window, taken
  from the executed history (:class:`~torchcbf.mppi.History`) for times already past and
  from the rollout for times to come. If the window opens after the rollout's last state,
  the rollout's last state stands in for it (so the robot heads to the goal in time). Once
  the history holds a state inside the window where ``rho >= 0`` (goal reached), or once the
  window has closed (``t0 > t2``), the term is frozen to the history's minimum (``0`` when
  the history has no state in the window): the same value for every sample, so it no longer
  pulls the robot.
- ``Always``: the maximum of ``c`` over the rollout states inside the window (``0`` when none
  is); history states are the same for every sample and are ignored.
- ``And``: the **sum** of the children's costs (a min would only ever push on the currently
  worst term); ``Or``: the minimum over the children the history has not made fail (see
  :meth:`Spec.outcome`), or, once it has made one hold, over those that hold.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from typing import Any, ClassVar

import torch
from torch import Tensor, nn

from torchcbf._checks import (
    ClosedForms,
    TracksShadows,
    apply_rules,
    check_number,
    check_positive,
    several_outputs,
)
from torchcbf.mppi.costs import (
    Adds,
    constant,
    point_index,
    rollout_times,
    root,
    squared_distance,
    time_varying,
    untimed,
)
from torchcbf.mppi.history import History

Predicate = Callable[[Tensor], Tensor]


def _masked(c: Tensor, mask: Tensor, value: float, *, own: bool) -> Tensor:
    """``c`` with ``value`` where ``mask``: in place where ``own`` (a tensor made here), out
    of place where ``c`` is what a user's function returned (a view of the states, say)."""
    return c.masked_fill_(mask, value) if own else c.masked_fill(mask, value)


def _over_time(rho: Tensor, reduce: Callable[..., Tensor], empty: float) -> Tensor:
    """``reduce`` (amax or amin) of ``rho [..., T]`` over time; ``empty`` for no sample."""
    if rho.shape[-1] == 0:
        return rho.new_full(rho.shape[:-1], empty)
    return reduce(rho, -1)


def pointwise(rho: Tensor, states: Tensor, name: str) -> Tensor:
    """A predicate's values ``rho`` of ``states [..., n]`` as ``[...]``: ``[..., k]`` (``k``
    outputs, e.g. a :class:`~torchcbf.barriers.Ball` of several centres) by its minimum, the
    robustness of all ``k`` holding; a shape of neither kind is a ``ValueError``."""
    return rho.amin(-1) if several_outputs(f"the {name}", rho, states) else rho


class Spec(Adds, TracksShadows):
    """Base of the specifications: ``robustness`` and the MPPI cost ``forward``; ``&`` and
    ``|`` combine specifications, ``+`` adds a specification's cost to another cost."""

    #: The planner passes ``dt=`` and ``history=`` to costs that set this.
    needs_history = True
    #: :meth:`_plan` is trusted only where the class defining it also defines what it
    #: stands for (see :func:`torchcbf._checks.honour_overrides`)
    closed_forms: ClassVar[ClosedForms] = {"_plan": (("plan_cost", "outcome"), ())}
    #: what :meth:`_plan` answers for an instance that shadows a method of its class or runs
    #: hooks (see :func:`torchcbf._checks.unless_hooked`)
    hooked_forms: ClassVar[dict[str, object]] = {"_plan": None}

    def __init_subclass__(cls, **kwargs: Any) -> None:
        super().__init_subclass__(**kwargs)
        apply_rules(cls, Spec)

    def robustness(self, states: Tensor, times: Tensor) -> Tensor:
        """Robustness ``[...]`` of trajectories ``states [..., T, n]`` sampled at global
        ``times [T]`` or ``[..., T]``; ``>= 0`` means satisfied."""
        raise NotImplementedError(f"{type(self).__name__} must define robustness()")

    def plan_cost(self, states: Tensor, times: Tensor, history: History | None) -> Tensor:
        """Cost ``[B, K]`` of rollouts ``states [B, K, T, n]`` at ``times [B, T]``."""
        raise NotImplementedError(f"{type(self).__name__} must define plan_cost()")

    def outcome(self, times: Tensor, history: History | None) -> Tensor | None:
        """``[B]``: 1 where the executed ``history`` has made the specification hold
        whatever comes next, -1 where it has made it fail, 0 where the rollouts from
        ``times [B, T]`` still decide; ``None`` where nothing is known (no history, or a
        specification that does not say)."""
        return None

    def _plan(
        self, states: Tensor, times: Tensor, history: History | None
    ) -> tuple[Tensor, Tensor | None] | None:
        """``(plan_cost(...), outcome(...))`` together, as :func:`plan_of` asks: a
        specification that reads the history for both defines this to read it once. It is
        trusted only where the class defining it also defines :meth:`plan_cost` and
        :meth:`outcome` (see :func:`torchcbf._checks.honour_overrides`); ``None`` for an
        instance that shadows a method or runs hooks."""
        return self.plan_cost(states, times, history), self.outcome(times, history)

    def forward(
        self,
        states: Tensor,
        controls: Tensor | None = None,
        t0: Tensor | float | None = None,
        dt: float | None = None,
        history: History | None = None,
    ) -> Tensor:
        """MPPI cost ``[B, K]`` of ``states [B, K, T, n]``, state ``k`` at ``t0 + k dt``."""
        times = rollout_times(states, t0, dt, f"{type(self).__name__} as a cost")
        return self.plan_cost(states, times, history)

    def __and__(self, other: Spec) -> And:
        return And(self, other)

    def __or__(self, other: Spec) -> Or:
        return Or(self, other)


Spec.rules_base = Spec  # type: ignore[attr-defined]


class _Temporal(Spec):
    """A timed temporal operator over a state predicate (base of Always and Eventually)."""

    time_tol: float = 1e-5

    def __init__(
        self,
        predicate: Predicate | None,
        interval: tuple[float, float] | None,
        cost: Predicate | None,
    ) -> None:
        super().__init__()
        if predicate is not None and not callable(predicate):
            raise TypeError(f"predicate must be callable, got {type(predicate).__name__}")
        if cost is not None and not callable(cost):
            raise TypeError(f"cost must be callable or None, got {type(cost).__name__}")
        if interval is None:
            interval = (-math.inf, math.inf)
        try:
            ends = [float(t) for t in interval]
        except (TypeError, ValueError):
            raise TypeError(
                f"interval must be a pair of numbers (t1, t2), got {interval!r}"
            ) from None
        if (
            len(ends) != 2
            or not ends[0] <= ends[1]
            or math.inf in ends[:1]
            or -math.inf in ends[1:]
        ):
            raise ValueError(
                f"interval must be (t1, t2) with t1 <= t2 and a finite time in between, "
                f"got {interval}"
            )
        t1, t2 = ends
        self.interval = (t1, t2)
        self.predicate_fn = predicate
        self.cost_fn = cost

    def predicate(self, states: Tensor) -> Tensor:
        """Pointwise robustness ``rho(x)``: ``[..., n] -> [...]`` (a predicate with ``k``
        outputs ``[..., k]`` holds where all of them hold: their minimum). A time-varying
        predicate (``time_varying``: a :class:`~torchcbf.barriers.MovingBall`) has no time
        to be read at here: :meth:`predicate_at` reads it."""
        if self.predicate_fn is None:
            raise ValueError(f"{type(self).__name__} was built without a predicate")
        untimed(f"{type(self).__name__}.predicate", self.predicate_fn)
        return pointwise(self.predicate_fn(states), states, "predicate")

    def predicate_at(self, states: Tensor, times: Tensor) -> Tensor:
        """``rho`` of ``states [..., n]`` at global ``times`` (broadcasting to
        ``states.shape[:-1]``): a time-varying predicate is read at each state's time."""
        if self.predicate_fn is not None and time_varying(self.predicate_fn):
            return pointwise(self.predicate_fn(states, times), states, "predicate")
        return self.predicate(states)

    def pointwise_cost_at(self, states: Tensor, times: Tensor) -> Tensor:
        """:meth:`pointwise_cost` of ``states [..., n]`` at global ``times`` (broadcasting to
        ``states.shape[:-1]``): ``-rho`` of a time-varying predicate read at the times."""
        if self.cost_fn is None and self.predicate_fn is not None:
            if time_varying(self.predicate_fn):
                return -self.predicate_at(states, times)
        return self.pointwise_cost(states)

    def _rollout_costs(self, states: Tensor, times: Tensor | None) -> Tensor:
        """Pointwise costs ``[B, K, T]`` of rollout ``states [B, K, T, n]``, read at their
        global ``times [B, T]`` where given."""
        if times is None:
            return self.pointwise_cost(states)
        return self.pointwise_cost_at(states, times.unsqueeze(1))

    def _own_costs(self) -> bool:
        """Whether :meth:`pointwise_cost` makes a new tensor (the library's ``-rho``), which
        may be filled in place: a user's ``cost=`` or override may return a view of the
        states."""
        kind = type(self)
        return (
            self.cost_fn is None
            and kind.pointwise_cost is _Temporal.pointwise_cost
            and kind.pointwise_cost_at is _Temporal.pointwise_cost_at
        )

    def pointwise_cost(self, states: Tensor) -> Tensor:
        """Pointwise cost ``c(x)``: ``[..., n] -> [...]`` (``-rho`` by default)."""
        if self.cost_fn is None:
            return -self.predicate(states)
        c = self.cost_fn(states)
        if c.shape != states.shape[:-1]:
            raise ValueError(
                f"{type(self).__name__}'s cost maps states {tuple(states.shape)} to "
                f"{tuple(c.shape)}; it must give one value per state, {tuple(states.shape[:-1])}"
            )
        return c

    def in_window(self, times: Tensor) -> Tensor:
        """Bool mask of the times inside the interval (closed, with :meth:`tolerance`)."""
        t1, t2 = self.interval
        tol = self.tolerance(times)
        return (times >= t1 - tol) & (times <= t2 + tol)

    def tolerance(self, times: Tensor) -> float:
        """``time_tol``, widened to the rounding of times of ``times``' dtype near the
        window's ends (float32 times near 1,000 s are 6e-5 s apart)."""
        ends = [abs(t) for t in self.interval if math.isfinite(t)]
        return self.time_tol + 8 * torch.finfo(times.dtype).eps * max(ends, default=0.0)

    def _passed(self, times: Tensor) -> Tensor:
        """``[B]``: whether the window closed before the first of ``times [B, T]``."""
        return times[:, 0] > self.interval[1] + self.tolerance(times)

    def extra_repr(self) -> str:
        return f"interval={self.interval}"


class Eventually(_Temporal):
    """``F[t1, t2] rho``: the predicate holds at some sampled time in the window.

    Args:
        predicate: ``rho: [..., n] -> [...]``, ``>= 0`` where it holds (or ``[..., k]``:
            it holds where all ``k`` outputs are ``>= 0``).
        interval: ``(t1, t2)`` in global time, ``None`` for all times.
        cost: pointwise planning cost ``c: [..., n] -> [...]`` (default ``-rho``).
        urgency: ``rho_u >= 0``; the planning cost of rollout state ``j`` becomes
            ``c(x_j) + rho_u (t_j - t0)`` (history states unchanged). The pure minimum (0,
            the default) is indifferent to *when* in the window the goal is reached, and the
            MPPI control cost (an effort penalty) then favours reaching it late, at the edge
            of the window; a small urgency breaks that tie in favour of reaching early.
    """

    #: the cost freezes once the history shows the goal reached: a history that wraps
    #: forgets that (the planner warns)
    remembers_history = True

    def __init__(
        self,
        predicate: Predicate | None = None,
        interval: tuple[float, float] | None = None,
        cost: Predicate | None = None,
        urgency: float = 0.0,
    ) -> None:
        super().__init__(predicate, interval, cost)
        self.urgency = check_number("urgency", urgency, low=0.0)

    def robustness(self, states: Tensor, times: Tensor) -> Tensor:
        rho = self.predicate_at(states, times)
        mask = self.in_window(times.to(rho.dtype)).expand(rho.shape)
        return _over_time(rho.masked_fill(~mask, -math.inf), torch.amax, -math.inf)

    def _ramp(self, times: Tensor) -> Tensor | None:
        """``urgency (t_j - t0)``: ``[B, 1, T]``, or None without urgency."""
        if self.urgency == 0.0:
            return None
        return (self.urgency * (times - times[:, :1])).unsqueeze(1)

    def rollout_min_cost(
        self,
        states: Tensor,
        window: Tensor,
        ramp: Tensor | None = None,
        times: Tensor | None = None,
    ) -> tuple[Tensor, Tensor]:
        """Minimum of ``c (+ ramp)`` over the rollout states inside ``window [B, T]``
        (``+inf`` when none is) and the same at the last state: two ``[B, K]`` tensors
        (``times [B, T]``: the states' global times, for a predicate that reads them)."""
        c = self._rollout_costs(states, times)
        own = self._own_costs() or ramp is not None
        if ramp is not None:
            c = c + ramp
        last = c[..., -1].clone()
        return _masked(c, ~window.unsqueeze(1), math.inf, own=own).amin(-1), last

    def plan_cost(self, states: Tensor, times: Tensor, history: History | None) -> Tensor:
        return self._plan_once(states, times, history)[0]

    def _plan(
        self, states: Tensor, times: Tensor, history: History | None
    ) -> tuple[Tensor, Tensor | None] | None:
        return self._plan_once(states, times, history)

    def _plan_once(
        self, states: Tensor, times: Tensor, history: History | None
    ) -> tuple[Tensor, Tensor | None]:
        """The cost and the outcome from one reading of the history."""
        window = self.in_window(times)  # [B, T]
        roll_min, last = self.rollout_min_cost(states, window, self._ramp(times), times)
        roll = torch.where(window.any(-1, keepdim=True), roll_min, last)
        passed = self._passed(times)
        if history is None:
            return torch.where(passed.unsqueeze(-1), torch.zeros_like(roll), roll), None
        h_window = history.valid & self.in_window(history.times)  # [B, N]
        h_cost = self.pointwise_cost_at(history.states, history.times)
        h_min = h_cost.masked_fill(~h_window, math.inf).amin(-1, keepdim=True)
        held = self._held(history, h_window)
        constant = torch.where(torch.isfinite(h_min), h_min, torch.zeros_like(h_min))
        frozen = (held | passed).unsqueeze(-1)
        cost = torch.where(frozen, constant, torch.minimum(roll, h_min))
        return cost, self._settled(held, passed)

    def _held(self, history: History, h_window: Tensor) -> Tensor:
        """``[B]``: whether a state of the history inside the window satisfies the predicate."""
        return (h_window & (self.predicate_at(history.states, history.times) >= 0)).any(-1)

    @staticmethod
    def _settled(held: Tensor, passed: Tensor) -> Tensor:
        """The outcome ``[B]``: held in the history, else failed once the window passed."""
        return torch.where(held, 1, torch.where(passed, -1, 0))

    def outcome(self, times: Tensor, history: History | None) -> Tensor | None:
        if history is None:
            return None
        held = self._held(history, history.valid & self.in_window(history.times))
        return self._settled(held, self._passed(times))


class Always(_Temporal):
    """``G[t1, t2] rho``: the predicate holds at every sampled time in the window.

    Args:
        predicate: ``rho: [..., n] -> [...]``, ``>= 0`` where it holds (or ``[..., k]``:
            it holds where all ``k`` outputs are ``>= 0``).
        interval: ``(t1, t2)`` in global time, ``None`` for all times.
        cost: pointwise planning cost ``c: [..., n] -> [...]`` (default ``-rho``).
    """

    def __init__(
        self,
        predicate: Predicate | None = None,
        interval: tuple[float, float] | None = None,
        cost: Predicate | None = None,
    ) -> None:
        super().__init__(predicate, interval, cost)

    def robustness(self, states: Tensor, times: Tensor) -> Tensor:
        rho = self.predicate_at(states, times)
        mask = self.in_window(times.to(rho.dtype)).expand(rho.shape)
        return _over_time(rho.masked_fill(~mask, math.inf), torch.amin, math.inf)

    def rollout_max_cost(
        self, states: Tensor, window: Tensor, times: Tensor | None = None
    ) -> Tensor:
        """Maximum of ``c`` over the rollout states inside ``window [B, T]``: ``[B, K]``
        (``-inf`` when none is; ``times [B, T]``: the states' global times)."""
        c = self._rollout_costs(states, times)
        return _masked(c, ~window.unsqueeze(1), -math.inf, own=self._own_costs()).amax(-1)

    def plan_cost(self, states: Tensor, times: Tensor, history: History | None) -> Tensor:
        window = self.in_window(times)  # [B, T]
        return self._windowed(self.rollout_max_cost(states, window, times), window)

    def outcome(self, times: Tensor, history: History | None) -> Tensor | None:
        if history is None:
            return None
        h_window = history.valid & self.in_window(history.times)
        broken = (h_window & (self.predicate_at(history.states, history.times) < 0)).any(-1)
        passed = self._passed(times)
        return torch.where(broken, -1, torch.where(passed, 1, 0))

    @staticmethod
    def _windowed(worst: Tensor, window: Tensor) -> Tensor:
        """``worst [B, K]``, or 0 in the rows whose ``window [B, T]`` holds no state."""
        return torch.where(window.any(-1, keepdim=True), worst, torch.zeros_like(worst))


class Reach(Eventually):
    """Reach the disc ``|p - center| <= radius`` at some time in ``interval``.

    ``rho = radius - |p - center|``; planning cost ``weight (|p - center|^2 - radius^2)``
    (scenario A of docs/scenarios.md: ``c_g``, ``weight = k_g``). ``p = x[..., index]``.
    ``urgency``: see :class:`Eventually`. ``Reach`` is :class:`Eventually` over the disc with
    this quadratic planning cost: use it for goal regions, and ``Eventually`` with a
    predicate of your own (and ``cost=``) for any other set.
    """

    def __init__(
        self,
        center: Tensor | Sequence[float],
        radius: float,
        interval: tuple[float, float] | None = None,
        weight: float = 1.0,
        index: Sequence[int] = (0, 1),
        urgency: float = 0.0,
    ) -> None:
        super().__init__(None, interval, None, urgency)
        center_t = constant("center", center)
        self.index = point_index(center_t, index)
        self.register_buffer("center", center_t)
        self.radius = check_positive("radius", radius)
        self.weight = check_positive("weight", weight)

    def predicate(self, states: Tensor) -> Tensor:
        return self.radius - root(squared_distance(states, self.index, self.center))

    def pointwise_cost(self, states: Tensor) -> Tensor:
        return self.weight * (squared_distance(states, self.index, self.center) - self.radius**2)

    def rollout_min_cost(
        self,
        states: Tensor,
        window: Tensor,
        ramp: Tensor | None = None,
        times: Tensor | None = None,
    ) -> tuple[Tensor, Tensor]:
        d2 = squared_distance(states, self.index, self.center)
        if ramp is not None:
            c = d2.mul_(self.weight).add_(ramp - self.weight * self.radius**2)
            last = c[..., -1].clone()
            return c.masked_fill_(~window.unsqueeze(1), math.inf).amin(-1), last
        # c is increasing in |p - g|^2: reduce the squared distance, transform [B, K] only
        last = self.weight * (d2[..., -1] - self.radius**2)
        d2_min = d2.masked_fill_(~window.unsqueeze(1), math.inf).amin(-1)
        return self.weight * (d2_min - self.radius**2), last

    def extra_repr(self) -> str:
        return f"center={self.center.tolist()}, radius={self.radius}, interval={self.interval}"


class Avoid(Always):
    """Stay out of the disc ``|p - center| < radius``, or in ``barrier(x) >= 0``, during
    ``interval`` (all times by default).

    ``rho = |p - center| - radius`` (or ``barrier(x)`` for any callable/module
    ``[..., n] -> [...]``, or the least of its outputs ``[..., k]``: a ``Ball`` of several
    centres avoids them all); planning cost ``weight / max(rho, eps)`` (scenario A: ``c_o``
    with ``weight = k_o = 0.3``, ``eps = 0.01``). A time-varying barrier (``time_varying``:
    a :class:`~torchcbf.barriers.MovingBall`, a ``Ball`` with a velocity) is read at each
    state's global time, in the cost and in :meth:`robustness`.
    """

    def __init__(
        self,
        center: Tensor | Sequence[float] | None = None,
        radius: float | None = None,
        *,
        barrier: Predicate | None = None,
        weight: float = 1.0,
        eps: float = 0.01,
        interval: tuple[float, float] | None = None,
        index: Sequence[int] = (0, 1),
    ) -> None:
        super().__init__(None, interval, None)
        if (barrier is None) == (center is None):
            raise ValueError("Avoid needs either center= and radius= or barrier=, not both")
        self.register_buffer("center", None)
        self.barrier = barrier
        if barrier is not None:
            if not callable(barrier):
                raise TypeError(f"barrier must be callable, got {type(barrier).__name__}")
            if radius is not None:
                raise ValueError("Avoid with a barrier takes no radius (the barrier is the set)")
        else:
            if radius is None:
                raise ValueError("Avoid with a center needs radius >= 0")
            radius = check_number("radius", radius, low=0.0)
            self.center = constant("center", center)
            self.index = point_index(self.center, index)
        self.radius = radius
        self.weight = check_positive("weight", weight)
        self.eps = check_positive("eps", eps)

    def predicate(self, states: Tensor) -> Tensor:
        if self.barrier is not None:
            untimed("Avoid.predicate", self.barrier)
            return pointwise(self.barrier(states), states, "barrier")
        return root(squared_distance(states, self.index, self.center)) - self.radius

    def predicate_at(self, states: Tensor, times: Tensor) -> Tensor:
        if self.barrier is not None and time_varying(self.barrier):
            return pointwise(self.barrier(states, times), states, "barrier")
        return self.predicate(states)

    def pointwise_cost(self, states: Tensor) -> Tensor:
        return self.weight / self.predicate(states).clamp_min(self.eps)

    def pointwise_cost_at(self, states: Tensor, times: Tensor) -> Tensor:
        return self.weight / self.predicate_at(states, times).clamp_min(self.eps)

    def rollout_max_cost(
        self, states: Tensor, window: Tensor, times: Tensor | None = None
    ) -> Tensor:
        # c is decreasing in rho: reduce rho (or |p - o|^2), transform [B, K] only
        outside = ~window.unsqueeze(1)
        if self.barrier is None:
            d2 = squared_distance(states, self.index, self.center)
            return self._cost_of(root(d2.masked_fill_(outside, math.inf).amin(-1)) - self.radius)
        if times is None:
            rho = self.predicate(states)
        else:
            rho = self.predicate_at(states, times.unsqueeze(1))
        return self._cost_of(rho.masked_fill(outside, math.inf).amin(-1))

    def _cost_of(self, rho_min: Tensor) -> Tensor:
        """The planning cost ``[B, K]`` of the worst state, from its ``rho_min [B, K]``
        (``+inf`` where no state is in the window)."""
        return self.weight / rho_min.clamp_min(self.eps)


class _Combination(Spec):
    def __init__(self, *specs: Spec) -> None:
        super().__init__()
        if not specs:
            raise ValueError(f"{type(self).__name__} needs at least one specification")
        for s in specs:
            if not isinstance(s, Spec):
                raise TypeError(f"{type(self).__name__} takes Spec objects, got {type(s).__name__}")
        self.specs = nn.ModuleList(specs)

    def outcome(self, times: Tensor, history: History | None) -> Tensor | None:
        return self._verdict(_stack_outcomes([s.outcome(times, history) for s in self.specs]))

    def _plan(
        self, states: Tensor, times: Tensor, history: History | None
    ) -> tuple[Tensor, Tensor | None] | None:
        return self._plan_once(states, times, history)

    def plan_cost(self, states: Tensor, times: Tensor, history: History | None) -> Tensor:
        return self._plan_once(states, times, history)[0]

    def _plan_once(
        self, states: Tensor, times: Tensor, history: History | None
    ) -> tuple[Tensor, Tensor | None]:
        """The cost and the outcome from one reading of the children's."""
        plans = [plan_of(s, states, times, history) for s in self.specs]
        found = _stack_outcomes([o for _, o in plans])
        return self._combine(torch.stack([c for c, _ in plans]), found), self._verdict(found)

    def _combine(self, costs: Tensor, found: Tensor | None) -> Tensor:
        """The cost ``[B, K]`` from the children's ``costs [C, B, K]`` and outcomes
        ``found [C, B]`` (``None``: none says)."""
        raise NotImplementedError

    def _verdict(self, found: Tensor | None) -> Tensor | None:
        """The outcome ``[B]`` from the children's ``found [C, B]``."""
        raise NotImplementedError


def plan_of(
    spec: Spec, states: Tensor, times: Tensor, history: History | None
) -> tuple[Tensor, Tensor | None]:
    """``(spec.plan_cost(...), spec.outcome(...))``, through :meth:`Spec._plan` where it
    answers."""
    both = spec._plan(states, times, history)
    if both is None:
        return spec.plan_cost(states, times, history), spec.outcome(times, history)
    return both


def _stack_outcomes(found: list[Tensor | None]) -> Tensor | None:
    """The children's outcomes ``[C, B]`` (0 for one that does not say), or ``None`` where
    none says."""
    known = [o for o in found if o is not None]
    if not known:
        return None
    zero = known[0].new_zeros(known[0].shape)
    return torch.stack([zero if o is None else o for o in found])


class And(_Combination):
    """All children hold. Robustness: minimum; cost: sum of the children's costs."""

    def robustness(self, states: Tensor, times: Tensor) -> Tensor:
        out = self.specs[0].robustness(states, times)
        for s in self.specs[1:]:
            out = torch.minimum(out, s.robustness(states, times))
        return out

    def plan_cost(self, states: Tensor, times: Tensor, history: History | None) -> Tensor:
        # alone, no child's outcome is needed
        costs = torch.stack([s.plan_cost(states, times, history) for s in self.specs])
        return self._combine(costs, None)

    _plan = _Combination._plan  # the same sum, with the outcome an Or asks for

    def _combine(self, costs: Tensor, found: Tensor | None) -> Tensor:
        return costs.sum(0)

    def _verdict(self, found: Tensor | None) -> Tensor | None:
        if found is None:
            return None
        return torch.where((found < 0).any(0), -1, torch.where((found > 0).all(0), 1, 0))


class Or(_Combination):
    """Some child holds. Robustness: maximum; cost: minimum of the children's costs, over
    those the executed history has not already made fail (a goal whose window closed unmet
    would otherwise cap the cost with its constant, and nothing would steer to the others);
    once the history makes one hold, the least of those that hold (a constant)."""

    #: its cost reads what the history has settled (an Always broken, a goal reached): a
    #: history that wraps forgets that (the planner warns)
    remembers_history = True

    def robustness(self, states: Tensor, times: Tensor) -> Tensor:
        out = self.specs[0].robustness(states, times)
        for s in self.specs[1:]:
            out = torch.maximum(out, s.robustness(states, times))
        return out

    def _combine(self, costs: Tensor, found: Tensor | None) -> Tensor:
        least = costs.amin(0)
        if found is None:
            return least
        held, failed = (found > 0).unsqueeze(-1), (found < 0).unsqueeze(-1)  # [C, B, 1]
        open_least = costs.masked_fill(failed, math.inf).amin(0)
        held_least = costs.masked_fill(~held, math.inf).amin(0)
        return torch.where(held.any(0), held_least, torch.where(failed.all(0), least, open_least))

    def _verdict(self, found: Tensor | None) -> Tensor | None:
        if found is None:
            return None
        return torch.where((found > 0).any(0), 1, torch.where((found < 0).all(0), -1, 0))
