"""A barrier-aware MPPI: the planner learns the control its safety filter applies.

:class:`ShieldMPPI` wraps an :class:`~torchcbf.mppi.MPPI` and a safety filter. Each
planning call's first control is filtered at the current state and the filtered control is
written back into the plan (:meth:`MPPI.correct`), so the plan the loop follows until the
next replan (and a refinement without the warm-start shift) starts from what was applied
instead of from a control the filter turned away. Give the planner a cost that knows the
barriers as well, e.g. :class:`~torchcbf.mppi.DiscreteBarrierCost` (the discrete-time CBF
condition as a steep rollout penalty), and its rollouts stay where the filter has little to
correct: planner and filter stop pulling apart.

In a closed loop that filters every control itself (:func:`torchcbf.sim.simulate` with a
``safety_filter``), build the shield with ``in_loop=True`` and give the loop
:attr:`ShieldMPPI.loop_filter` as its filter: the shield then returns the planner's control
unfiltered, and the loop's filter call after each plan feeds its filtered control back
into the plan. Each control step makes one filter call, where a shield that filters
itself inside such a loop makes two on every replanning step (its own, and the loop's on
the control it already filtered).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from torch import Tensor, nn

from torchcbf._checks import check_bool
from torchcbf.mppi.planner import MPPI, MPPIOutput


class ShieldMPPI(nn.Module):
    """MPPI whose first control is filtered and fed back into its plan.

    Args:
        planner: the MPPI planner.
        safety_filter: ``safety_filter(x [B, n], u [B, m], t) -> output`` with a ``u [B, m]``
            field (e.g. :class:`~torchcbf.filters.SafetyFilter`).
        in_loop: the loop filters (see :attr:`loop_filter`): ``forward`` returns the
            planner's output unfiltered.

    ``forward(x [n] or [B, n], t=0.0) -> MPPIOutput`` is the planner's output with ``u`` the
    filtered control, ``plan[..., 0, :] = u`` and the filter's output in ``filtered`` (with
    ``in_loop``: ``u`` unfiltered, ``filtered`` None, and the plan corrected once the loop
    filter has filtered it). ``dt``, ``reset()`` and ``history`` are the planner's, so the
    wrapper drops into :func:`torchcbf.sim.simulate` as a planner.
    """

    def __init__(
        self, planner: MPPI, safety_filter: Callable[..., Any], *, in_loop: bool = False
    ) -> None:
        super().__init__()
        if not isinstance(planner, MPPI):
            raise TypeError(f"planner must be an MPPI planner, got {type(planner).__name__}")
        if not callable(safety_filter):
            raise TypeError(f"safety_filter must be callable, got {type(safety_filter).__name__}")
        self.planner = planner
        self.safety_filter = safety_filter
        self.in_loop = check_bool("in_loop", in_loop)
        self._pending: Tensor | None = None

    @property
    def dt(self) -> float:
        return self.planner.dt

    @property
    def history(self) -> Any:
        return self.planner.history

    @property
    def loop_filter(self) -> LoopFilter:
        """The safety filter to give the closed loop of an ``in_loop`` shield."""
        if not self.in_loop:
            raise ValueError("loop_filter belongs to a shield built with in_loop=True")
        return LoopFilter(self)

    def reset(self) -> None:
        self.planner.reset()
        self._pending = None

    def forward(self, x: Tensor, t: float | Tensor = 0.0) -> MPPIOutput:
        if not isinstance(x, Tensor):  # before the planner advances its plan
            raise TypeError(
                f"x must be a torch.Tensor (the safety filter takes tensors), got "
                f"{type(x).__name__}: pass torch.as_tensor(x)"
            )
        out = self.planner(x, t)
        if self.in_loop:
            self._pending = out.plan  # the loop filter writes the filtered control into it
            return out
        filtered = self.safety_filter(x, out.u, t)
        self._feed_back(filtered.u, out.plan)
        return out._replace(u=filtered.u, filtered=filtered)

    def _feed_back(self, u: Tensor, plan: Tensor) -> None:
        """The filtered control into the planner's plan and into the returned ``plan``."""
        self.planner.correct(u)
        plan[..., 0, :] = u


class LoopFilter:
    """The safety filter of an ``in_loop`` :class:`ShieldMPPI`: ``filter(x, u, t)`` is the
    shield's filter, and its first call after a planning call writes the filtered control
    into the planner's plan and into the plan that call returned (so the steps that follow
    the plan until the next replan start from it). Not a module: it only refers to the
    shield, whose filter it calls; its other attributes are that filter's."""

    def __init__(self, shield: ShieldMPPI) -> None:
        self.shield = shield

    def __getattr__(self, name: str) -> Any:
        # the shield's filter's attributes (barriers, margins, ...) read through
        if name == "shield":
            raise AttributeError(name)
        return getattr(self.shield.safety_filter, name)

    def __call__(self, x: Tensor, u: Tensor, t: float | Tensor = 0.0) -> Any:
        shield = self.shield
        out = shield.safety_filter(x, u, t)
        if shield._pending is not None:
            shield._feed_back(out.u, shield._pending)
            shield._pending = None
        return out
