"""Batched closed-loop simulation in one call: :func:`simulate` builds a
:class:`~torchcbf.sim.loop.ClosedLoop` from its parts and runs it (the parts' protocols are
described there)."""

from __future__ import annotations

from collections.abc import Callable, Sequence

from torch import Tensor

from torchcbf.dynamics.base import ControlAffine
from torchcbf.estimation import Estimator, Sensor
from torchcbf.sim.loop import ClosedLoop, Filter, Nominal, Planner
from torchcbf.sim.trajectory import Trajectory


def simulate(
    dynamics: ControlAffine,
    x0: Tensor,
    steps: int,
    dt: float,
    *,
    planner: Planner | None = None,
    nominal: Nominal | None = None,
    safety_filter: Filter | None = None,
    sensor: Sensor | None = None,
    estimator: Estimator | None = None,
    integrator: str = "rk4",
    seed: int | Sequence[int] | Tensor = 0,
    progress: bool = True,
    progress_label: str = "simulate",
    x0_hat: Tensor | None = None,
    P0: Tensor | None = None,
    t0: float = 0.0,
    planner_every: int = 1,
    disturbance: Callable[[Tensor, float], Tensor] | None = None,
    snapshot_steps: Sequence[int] = (),
    differentiable: bool = False,
) -> Trajectory:
    """Run B scenarios of the closed loop for ``steps`` steps of ``dt``: the same as
    ``ClosedLoop(dynamics=..., planner=..., ...).simulate(x0, steps, dt, ...)``.

    Args:
        dynamics, planner, nominal, safety_filter, sensor, estimator, integrator,
            planner_every, disturbance: the loop (:class:`~torchcbf.sim.loop.ClosedLoop`).
        x0: initial true states ``[B, n]`` (or ``[n]`` for one scenario).
        seed, t0, x0_hat, P0, snapshot_steps, progress, progress_label, differentiable: the
            run (:meth:`~torchcbf.sim.loop.ClosedLoop.simulate`).

    Returns:
        A :class:`Trajectory`. A scenario whose state or a component's output goes non-finite
        is flagged in ``failed``/``fail_step`` and frozen; the others run on untouched.
    """
    loop = ClosedLoop(
        dynamics=dynamics,
        planner=planner,
        nominal=nominal,
        safety_filter=safety_filter,
        sensor=sensor,
        estimator=estimator,
        integrator=integrator,
        planner_every=planner_every,
        disturbance=disturbance,
    )
    return loop.simulate(
        x0,
        steps,
        dt,
        seed=seed,
        t0=t0,
        x0_hat=x0_hat,
        P0=P0,
        snapshot_steps=snapshot_steps,
        progress=progress,
        progress_label=progress_label,
        differentiable=differentiable,
    )
