"""Losses for learning barriers, class-K gains and policies through the safety filter.

Three families, all differentiable end to end (autograd Lie derivatives with
``create_graph``, implicit differentiation of the QP, rollouts through the integrator):

1. :func:`classification_loss`: labelled safe/unsafe states, with margins.
2. :func:`cbf_condition_loss`: the CBF condition ``a . u* + b >= margin`` evaluated at the
   filter's own solution ``u*`` (``a . u + b = L_f h + L_g h u + alpha(h)`` in vanilla
   mode), so the loss sees the control input, its limits, and the QP.
3. :func:`closed_loop_loss`: intervention size, collisions with the true obstacles and
   progress to a goal over a batch of differentiable rollouts
   (:func:`torchcbf.sim.simulate` with ``differentiable=True`` keeps the autograd graph).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import NamedTuple, Protocol

import torch
import torch.nn.functional as F
from torch import Tensor

from torchcbf._checks import as_tensor, check_number, check_tensor
from torchcbf.barriers._params import take


class ConditionOutput(Protocol):
    """What :func:`condition_violation` reads (a :class:`torchcbf.filters.FilterOutput` has
    it): ``h [..., k]`` and ``constraint_value [..., k + ...]``."""

    @property
    def h(self) -> Tensor: ...

    @property
    def constraint_value(self) -> Tensor: ...


class Rollouts(Protocol):
    """What :func:`closed_loop_loss` reads (a :class:`torchcbf.sim.Trajectory` has it)."""

    @property
    def x(self) -> Tensor: ...

    @property
    def u(self) -> Tensor: ...

    @property
    def u_nom(self) -> Tensor: ...


def _check_pair(h: Tensor, safe: Tensor) -> None:
    check_tensor("h", h)
    check_tensor("safe", safe)
    if h.shape != safe.shape:
        raise ValueError(
            f"h and safe must have the same shape, got {tuple(h.shape)} and {tuple(safe.shape)}"
        )
    if safe.dtype != torch.bool:
        raise TypeError(f"safe must be a bool tensor, got {safe.dtype}")


def _margin(name: str, value: float | Tensor) -> float | Tensor:
    """A margin: a finite number, or a tensor (a learned one) used as it is."""
    return value if isinstance(value, Tensor) else check_number(name, value)


def _mean(values: Tensor) -> Tensor:
    """The mean of ``values``, 0 (still in the graph) for none: an empty minibatch adds
    nothing to a loss rather than making it NaN."""
    return values.mean() if values.numel() else values.sum()


def classification_loss(
    h: Tensor,
    safe: Tensor,
    *,
    margin: float = 0.0,
    unsafe_margin: float | None = None,
    temperature: float = 0.0,
    balanced: bool = False,
) -> Tensor:
    """Hinge loss of barrier values against labels: ``relu(margin - h)`` on safe states,
    ``relu(unsafe_margin + h)`` on unsafe ones (``unsafe_margin`` defaults to ``margin``).

    Args:
        h: barrier values ``[...]``.
        safe: labels ``[...]`` (bool).
        temperature: ``T > 0`` replaces ``relu(z)`` by the smooth hinge ``T softplus(z / T)``
            (an upper bound that tends to the hinge as ``T -> 0``): every state keeps a
            gradient pushing it away from the boundary, which trains markedly faster than
            the plain hinge (whose gradient vanishes once a state clears its margin).
        balanced: average each class separately and add the two means; ``False`` (default):
            one mean over all states.

    Returns:
        A scalar tensor (0 for no states).
    """
    _check_pair(h, safe)
    margin = _margin("margin", margin)
    m_unsafe = margin if unsafe_margin is None else _margin("unsafe_margin", unsafe_margin)
    temperature = check_number("temperature", temperature, low=0.0)
    if temperature > 0:
        loss_safe = temperature * F.softplus((margin - h) / temperature)
        loss_unsafe = temperature * F.softplus((m_unsafe + h) / temperature)
    else:
        loss_safe = torch.relu(margin - h)
        loss_unsafe = torch.relu(m_unsafe + h)
    if not balanced:
        return _mean(torch.where(safe, loss_safe, loss_unsafe))
    w = safe.to(h.dtype)
    n_safe = w.sum().clamp_min(1.0)
    n_unsafe = (1 - w).sum().clamp_min(1.0)
    return (loss_safe * w).sum() / n_safe + (loss_unsafe * (1 - w)).sum() / n_unsafe


def classification_accuracy(h: Tensor, safe: Tensor) -> Tensor:
    """Fraction of states with ``(h >= 0) == safe`` (a scalar tensor in at least float32,
    whatever the precision of ``h``; NaN for no states; no gradient)."""
    _check_pair(h, safe)
    return ((h.detach() >= 0) == safe).to(torch.promote_types(h.dtype, torch.float32)).mean()


def condition_violation(output: ConditionOutput, margin: float | Tensor = 0.0) -> Tensor:
    """``relu(margin - (a . u* + b))`` per row and barrier output, ``[..., k]``.

    ``output`` is a :class:`torchcbf.filters.FilterOutput`: its ``constraint_value`` holds
    ``a . u + b`` at the returned control (the CBF rows are its first ``k = h.shape[-1]``
    entries). Rows with a non-finite state (NaN values) contribute zero.
    """
    k = output.h.shape[-1]
    value = output.constraint_value[..., :k]
    viol = torch.relu(margin - value)
    return torch.where(torch.isfinite(viol), viol, torch.zeros_like(viol))


def cbf_condition_loss(
    safety_filter: Callable[..., ConditionOutput],
    x: Tensor,
    u_nom: Tensor,
    t: Tensor | float | None = None,
    *,
    margin: float | Tensor = 0.0,
) -> Tensor:
    """Mean CBF-condition violation at the filter's solution over a batch of states.

    Runs ``out = safety_filter(x [..., n], u_nom [..., m], t)`` (e.g. a
    :class:`torchcbf.filters.SafetyFilter` built on a :class:`~torchcbf.barriers.NeuralBarrier`)
    and returns the mean over rows and barrier outputs of ``relu(margin - (L_f h + L_g h u* +
    alpha(h)))`` (the mode's full condition, see :mod:`torchcbf.filters.conditions`). It is
    zero where the QP met the condition with room ``margin`` and positive where the control
    limits forced a relaxation (``h`` has no valid control there) or the margin is not met.
    Gradients reach the barrier's parameters, the class-K gains and ``u_nom``, both directly
    and through ``u*`` (implicit differentiation of the QP). No states (a minibatch without
    a safe one): 0.
    """
    out = safety_filter(x, u_nom, t)
    return _mean(condition_violation(out, margin))


class ClosedLoopLoss(NamedTuple):
    """Terms of :func:`closed_loop_loss` (scalars): ``total`` (the weighted sum),
    ``intervention``, ``collision`` and ``goal`` (zero when not requested)."""

    total: Tensor
    intervention: Tensor
    collision: Tensor
    goal: Tensor


def closed_loop_loss(
    trajectory: Rollouts,
    true_barrier: Callable[[Tensor], Tensor] | None = None,
    *,
    intervention_weight: float = 1.0,
    collision_weight: float = 100.0,
    collision_margin: float = 0.0,
    goal: Tensor | Sequence[float] | None = None,
    goal_weight: float = 0.0,
    index: Sequence[int] = (0, 1),
) -> ClosedLoopLoss:
    """Loss over a batch of rollouts (a :class:`torchcbf.sim.Trajectory` or anything with
    ``x [B, T+1, n]``, ``u [B, T, m]``, ``u_nom [B, T, m]``).

    - ``intervention``: mean over rows and steps of ``|u - u_nom|^2`` (how much the filter
      changed the nominal control: its conservatism).
    - ``collision``: mean over rows and states of ``sum_k relu(collision_margin - h_k(x))``
      for the true obstacles' barrier ``true_barrier(x) -> [...]`` or ``[..., k]``.
    - ``goal``: mean over rows and states of ``|x[index] - goal|``: the time-integrated
      distance to the goal, a differentiable proxy of the time to reach it.

    ``total = intervention_weight * intervention + collision_weight * collision +
    goal_weight * goal``.
    """
    x, u, u_nom = trajectory.x, trajectory.u, trajectory.u_nom
    check_tensor("trajectory.x", x)
    if (
        x.dim() != 3
        or u.dim() != 3
        or u.shape != u_nom.shape
        or u.shape[:2]
        != (
            x.shape[0],
            x.shape[1] - 1,
        )
    ):
        raise ValueError(
            "trajectory must hold x [B, T+1, n], u and u_nom [B, T, m], got "
            f"{tuple(x.shape)}, {tuple(u.shape)}, {tuple(u_nom.shape)}"
        )
    zero = x.new_zeros(())
    intervention = _mean(((u - u_nom) ** 2).sum(-1))
    collision = zero
    if true_barrier is not None:
        h = true_barrier(x)
        if h.shape == x.shape[:-1]:
            h = h.unsqueeze(-1)
        collision = _mean(torch.relu(collision_margin - h).sum(-1))
    goal_term = zero
    if goal is not None:
        g = as_tensor("goal", goal, dtype=x.dtype, device=x.device)
        idx = list(index)
        if g.shape != (len(idx),):
            raise ValueError(f"goal must have shape [{len(idx)}], got {tuple(g.shape)}")
        # a smoothed norm: differentiable at the goal itself
        p = take(x, idx)
        goal_term = _mean(torch.sqrt(((p - g) ** 2).sum(-1) + 1e-12))
    total = (
        intervention_weight * intervention + collision_weight * collision + goal_weight * goal_term
    )
    return ClosedLoopLoss(total, intervention, collision, goal_term)
