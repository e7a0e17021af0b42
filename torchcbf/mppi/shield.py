"""A barrier-aware MPPI: the planner learns the control its safety filter applies.

:class:`ShieldMPPI` wraps an :class:`~torchcbf.mppi.MPPI` and a safety filter. Each call
plans, filters the plan's first control at the current state and writes the filtered control
back into the plan (:meth:`MPPI.correct`), so the plan the loop follows until the next replan
(and a refinement without the warm-start shift) starts from what was applied instead of from
a control the filter turned away. Give the planner a cost
that knows the barriers as well, e.g. :class:`~torchcbf.mppi.DiscreteBarrierCost` (the
discrete-time CBF condition as a steep rollout penalty), and its rollouts stay where the
filter has little to correct: planner and filter stop pulling apart.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from torch import Tensor, nn

from torchcbf.mppi.planner import MPPI, MPPIOutput


class ShieldMPPI(nn.Module):
    """MPPI whose first control is filtered and fed back into its plan.

    Args:
        planner: the MPPI planner.
        safety_filter: ``safety_filter(x [B, n], u [B, m], t) -> output`` with a ``u [B, m]``
            field (e.g. :class:`~torchcbf.filters.SafetyFilter`).

    ``forward(x [n] or [B, n], t=0.0) -> MPPIOutput`` is the planner's output with ``u`` the
    filtered control and ``plan[..., 0, :] = u``. ``dt``, ``reset()`` and ``history`` are the
    planner's, so the wrapper drops into :func:`torchcbf.sim.simulate` as a planner.
    """

    def __init__(self, planner: MPPI, safety_filter: Callable[..., Any]) -> None:
        super().__init__()
        if not isinstance(planner, MPPI):
            raise TypeError(f"planner must be an MPPI planner, got {type(planner).__name__}")
        if not callable(safety_filter):
            raise TypeError(f"safety_filter must be callable, got {type(safety_filter).__name__}")
        self.planner = planner
        self.safety_filter = safety_filter

    @property
    def dt(self) -> float:
        return self.planner.dt

    @property
    def history(self) -> Any:
        return self.planner.history

    def reset(self) -> None:
        self.planner.reset()

    def forward(self, x: Tensor, t: float | Tensor = 0.0) -> MPPIOutput:
        out = self.planner(x, t)
        u = self.safety_filter(x, out.u, t).u
        self.planner.correct(u)
        plan = out.plan.clone()
        plan[..., 0, :] = u
        return out._replace(u=u, plan=plan)
