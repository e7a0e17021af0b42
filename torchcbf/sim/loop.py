"""The closed loop as an object: planner -> nominal -> safety filter -> plant -> sensor ->
estimator, its parts typed by the protocols below, run for B scenarios in lockstep.

Any callable or module with the right signature is a part (MPPI and the safety filters of
the library are; so are plain functions):

- :class:`Planner`: ``planner(x_hat [B, n], t) -> PlanOutput`` (``u [B, m]`` and ``plan
  [B, H, m]``); ``planner.reset()`` is called before a run if it exists. With
  ``planner_every=k`` it runs every k steps and in between the loop follows its plan (index
  by elapsed time over ``planner.dt`` when the planner has one).
- :class:`Nominal`: ``nominal(x_hat, t)`` without a planner, ``nominal(x_hat, t, u_plan)``
  with one, ``-> u_nom [B, m]``; a stateful one's ``reset()`` is called before a run too
  (a roadmap controller's progress along its path), so that running a loop twice gives
  the same trajectories. Without a nominal controller the planner's control is the
  nominal one; with neither, the safety filter acts on a zero nominal control.
- :class:`Filter`: ``safety_filter(x_hat, u_nom, t) -> FilterResult`` (``u``, ``status``,
  ``h``). Without one, ``u_nom`` is clipped to the dynamics' control limits.
- a :class:`~torchcbf.estimation.Sensor` (``measure(x, noise=z)``, ``output_dim`` or
  ``expected(x)``) and an :class:`~torchcbf.estimation.Estimator` (``init``, ``predict``,
  ``update`` on a state with a ``mean``). With a sensor and no estimator the controllers
  see ``y`` (which must then be a full state); with neither they see the true state.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any, Protocol, runtime_checkable

import torch
from torch import Tensor
from tqdm.auto import tqdm

from torchcbf._checks import (
    check_finite,
    check_last_dim,
    check_number,
    check_positive_int,
    check_same,
    check_tensor,
    per_row,
)
from torchcbf._random import counter_normal, seed_rows
from torchcbf.dynamics.base import ControlAffine
from torchcbf.estimation import Estimator, EstimatorStatus, Sensor
from torchcbf.filters import FilterStatus
from torchcbf.integrators import METHODS
from torchcbf.integrators import step as integrate
from torchcbf.sim.trajectory import Trajectory

# Streams of the counter-based generator: one per source of noise and step.
_PROCESS, _SENSOR, _STREAMS = 0, 1, 2


class PlanOutput(Protocol):
    """What a planner returns: the control to apply now and the whole plan."""

    u: Tensor  # [B, m]
    plan: Tensor  # [B, H, m]


@runtime_checkable
class Planner(Protocol):
    def __call__(self, x_hat: Tensor, t: float) -> PlanOutput: ...


@runtime_checkable
class Nominal(Protocol):
    def __call__(self, x_hat: Tensor, t: float, *u_plan: Tensor) -> Tensor: ...


class FilterResult(Protocol):
    """What a safety filter returns: the filtered control, a status and barrier values."""

    u: Tensor  # [B, m]
    status: Tensor  # [B]
    h: Tensor  # [B, k]


@runtime_checkable
class Filter(Protocol):
    def __call__(self, x_hat: Tensor, u_nom: Tensor, t: float) -> FilterResult: ...


@dataclass(kw_only=True)
class ClosedLoop:
    """A plant and the parts that control it (see the module docstring).

    Attributes:
        dynamics: the plant (its diffusion, if any, is simulated with Euler-Maruyama
            whatever ``integrator`` says).
        planner, nominal, safety_filter: the controllers; at least one of them.
        sensor, estimator: what the controllers see (an estimator needs a sensor).
        integrator: ``"rk4"`` (default), ``"euler"`` or ``"euler_maruyama"``. The plant stands
            for the real system, so it is integrated accurately; a planner's rollouts are a
            model of it and trade accuracy for samples (:class:`~torchcbf.mppi.MPPI` rolls
            out with ``"euler"``), which is why the two defaults differ.
        planner_every: run the planner every this many steps.
        disturbance: ``w = disturbance(x, t) -> [B, p]`` entering as ``M w``.
    """

    dynamics: ControlAffine
    planner: Planner | None = None
    nominal: Nominal | None = None
    safety_filter: Filter | None = None
    sensor: Sensor | None = None
    estimator: Estimator | None = None
    integrator: str = "rk4"
    planner_every: int = 1
    disturbance: Callable[[Tensor, float], Tensor] | None = field(default=None, repr=False)

    def __post_init__(self) -> None:
        if not isinstance(self.dynamics, ControlAffine):
            raise TypeError(
                f"dynamics must be a ControlAffine module, got {type(self.dynamics).__name__}"
            )
        if self.integrator not in METHODS:
            raise ValueError(f"integrator must be one of {METHODS}, got {self.integrator!r}")
        if (
            isinstance(self.planner_every, bool)
            or not isinstance(self.planner_every, int)
            or (self.planner_every < 1)
        ):
            raise ValueError(f"planner_every must be a positive int, got {self.planner_every!r}")
        if self.planner is None and self.nominal is None and self.safety_filter is None:
            raise ValueError(
                "a closed loop needs a controller: planner=, nominal= or safety_filter= "
                "(without any, it would run on zero control)"
            )
        if self.estimator is not None and self.sensor is None:
            raise ValueError("an estimator needs a sensor")

    def simulate(
        self,
        x0: Tensor,
        steps: int,
        dt: float,
        *,
        seed: int | Sequence[int] | Tensor = 0,
        t0: float = 0.0,
        x0_hat: Tensor | None = None,
        P0: Tensor | None = None,
        snapshot_steps: Sequence[int] = (),
        progress: bool = True,
        progress_label: str = "simulate",
        differentiable: bool = False,
    ) -> Trajectory:
        """Run B scenarios from ``x0 [B, n]`` (or ``[n]``) for ``steps`` steps of ``dt``.

        Args:
            seed: an int (scenario b uses ``seed + b``) or one seed per scenario ``[B]``;
                every random draw of scenario b depends only on its seed, so a batch equals
                its rows run alone (to the rounding of batched linear algebra, which an EKF's
                update amplifies with its covariance's conditioning: 1e-16 in float64 at
                ``P0 = 1e-2 I``, 1e-6 in float32).
            x0_hat, P0: the estimator's initial mean ``[B, n]`` (default ``x0``) and
                covariance ``[B, n, n]`` or ``[n, n]`` (default ``1e-2 I``), finite, in
                ``x0``'s dtype and on its device.
            snapshot_steps: planning steps (multiples of ``planner_every``) at which the
                planner's whole output is kept in ``Trajectory.planner`` (a step the run
                does not reach keeps nothing).
            progress: show a progress bar labelled ``progress_label``.
            differentiable: keep the autograd graph through the whole loop (to train
                through rollouts). Off by default: the loop runs under ``torch.no_grad()``.
                A failed row's values are masked out, but a value that overflowed inside a
                component (a controller's ``-k x^3`` at ``x = 1e200``) can still give that
                component's shared parameters a NaN gradient (``0 * inf`` in its backward):
                check ``failed`` before stepping an optimiser.

        Returns:
            A :class:`Trajectory`. A scenario whose state or a component's output goes
            non-finite is flagged in ``failed``/``fail_step`` and frozen; the others run on.
        """
        check_last_dim("x0", x0, self.dynamics.state_dim)
        if x0.dim() == 1:
            x0 = x0.unsqueeze(0)
        if x0.dim() != 2:
            raise ValueError(
                f"x0 must have shape [B, {self.dynamics.state_dim}], got {tuple(x0.shape)}"
            )
        check_positive_int("steps", steps)
        dt = check_number("dt", dt, low=0.0, strict=True)
        t0 = check_number("t0", t0)
        _check_model(self.dynamics, x0)
        with torch.set_grad_enabled(differentiable and torch.is_grad_enabled()):
            run = _Run(self, x0, steps, dt, seed=seed, t0=t0, snapshot_steps=snapshot_steps)
            run.start(x0_hat, P0)
            bar = tqdm(
                range(steps), disable=not progress, desc=progress_label, unit="step", leave=False
            )
            for k in bar:
                run.step(k)
            return run.finish()


def _broadcast(name: str, value: object, like: Tensor, shape: tuple[int, ...]) -> Tensor:
    """``value`` (a tensor in ``like``'s dtype and device, finite) broadcast to ``shape``;
    a clear error naming ``name`` otherwise."""
    value = check_tensor(name, value)
    check_same("x0", like, name, value)
    check_finite(name, value)
    try:
        return value.expand(shape)
    except RuntimeError:
        raise ValueError(
            f"{name} must broadcast to {list(shape)}, got {tuple(value.shape)}"
        ) from None


class _Run:
    """One simulation of a :class:`ClosedLoop`: its buffers and one method per stage of a
    step, in the order a step runs them."""

    def __init__(
        self,
        loop: ClosedLoop,
        x0: Tensor,
        steps: int,
        dt: float,
        *,
        seed: int | Sequence[int] | Tensor,
        t0: float,
        snapshot_steps: Sequence[int],
    ) -> None:
        self.loop, self.steps, self.dt, self.t0 = loop, steps, dt, t0
        dyn = loop.dynamics
        self.method = "euler_maruyama" if dyn.has_diffusion else loop.integrator
        B, n, m = x0.shape[0], dyn.state_dim, dyn.control_dim
        self.B, self.n, self.m = B, n, m
        self.device, self.dtype = x0.device, x0.dtype
        self.seeds = seed_rows(seed, B, x0.device, per="scenario")
        sigma0 = dyn.sigma(x0)
        self.q = None if sigma0 is None else sigma0.shape[-1]
        # float64 whatever the states' dtype: float32 times lose the step where t0 is large
        self.t = t0 + dt * torch.arange(steps + 1, device=x0.device, dtype=torch.float64)
        self.xs = x0.new_zeros(B, steps + 1, n)
        self.xs_hat = x0.new_zeros(B, steps + 1, n)
        self.u_noms = x0.new_zeros(B, steps, m)
        self.us = x0.new_zeros(B, steps, m)
        self.hs: Tensor | None = None
        self.statuses: Tensor | None = None
        self.failed = torch.zeros(B, dtype=torch.bool, device=x0.device)
        self.fail_step = torch.full((B,), -1, dtype=torch.int64, device=x0.device)
        self.snapshots: dict[int, Any] = {}
        self.snapshot_set = set(snapshot_steps)
        every = loop.planner_every
        for k in self.snapshot_set:
            if isinstance(k, bool) or not isinstance(k, int) or k < 0:
                raise ValueError(f"snapshot_steps must be non-negative steps, got {k!r}")
            if loop.planner is not None and k < steps and k % every:
                raise ValueError(
                    f"snapshot step {k} is not a planning step (the planner runs every {every} "
                    f"steps): take {k - k % every} or {k - k % every + every}"
                )
        self.x = x0.clone()
        self.est_state: Any = None
        self.plan_out: Any = None
        self.plan_step = 0
        self.plan_dt = float(getattr(loop.planner, "dt", dt))

    # -- before the first step ------------------------------------------------------------
    def start(self, x0_hat: Tensor | None, P0: Tensor | None) -> None:
        loop, x0, B, n = self.loop, self.x, self.B, self.n
        if loop.estimator is not None:
            mean0 = x0 if x0_hat is None else _broadcast("x0_hat", x0_hat, x0, (B, n))
            if P0 is None:
                P0 = 1e-2 * torch.eye(n, device=self.device, dtype=self.dtype)
            self.est_state = loop.estimator.init(mean0, _broadcast("P0", P0, x0, (B, n, n)))
        elif loop.sensor is not None:
            p = getattr(loop.sensor, "output_dim", None) or loop.sensor.expected(x0).shape[-1]
            if p != n:
                raise ValueError(
                    f"without an estimator the controllers see the measurement, which must then "
                    f"be a full state of size {n}: {type(loop.sensor).__name__} measures {p} "
                    f"value{'s' if p != 1 else ''} (add an estimator)"
                )
        for part in (loop.planner, loop.nominal):
            reset = getattr(part, "reset", None)
            if callable(reset):
                reset()

    # -- one step, in order -----------------------------------------------------------------
    def step(self, k: int) -> None:
        tk = self.t0 + k * self.dt
        self.xs[:, k] = self.x
        x_hat = self.observe(k)
        u_plan = self.plan(x_hat, tk, k)
        u_nom = self.nominal(x_hat, tk, u_plan, k)
        u = self.filter(x_hat, u_nom, tk, k)
        self.advance(u, tk, k)

    def observe(self, k: int) -> Tensor:
        """What the controllers see: the estimate, the measurement or the true state."""
        if self.est_state is not None:
            x_hat = self.est_state.mean
        elif self.loop.sensor is not None:
            x_hat = self.measure(self.x, k)
        else:
            x_hat = self.x
        self.mark(_finite_rows(self.x) & _finite_rows(x_hat), k)
        x_hat = self.clean(x_hat)
        self.xs_hat[:, k] = x_hat
        return x_hat

    def plan(self, x_hat: Tensor, tk: float, k: int) -> Tensor | None:
        """The planner's control: a new plan every ``planner_every`` steps, else the plan's
        entry for the elapsed time."""
        planner = self.loop.planner
        if planner is None:
            return None
        if k % self.loop.planner_every == 0:
            self.plan_out = planner(x_hat, tk)
            self.plan_step = k
            if k in self.snapshot_set:
                self.snapshots[k] = self.plan_out
            _check_shape("planner(x_hat, t).u", self.plan_out.u, (self.B, self.m))
            return self.plan_out.u
        elapsed = (k - self.plan_step) * self.dt / self.plan_dt
        idx = min(int(elapsed + 1e-9), self.plan_out.plan.shape[-2] - 1)
        return self.plan_out.plan[:, idx]

    def nominal(self, x_hat: Tensor, tk: float, u_plan: Tensor | None, k: int) -> Tensor:
        """The nominal control: the nominal controller's, the planner's, or zero."""
        nominal = self.loop.nominal
        if nominal is not None:
            u_nom = nominal(x_hat, tk) if u_plan is None else nominal(x_hat, tk, u_plan)
            _check_shape("nominal(x_hat, t)", u_nom, (self.B, self.m))
        elif u_plan is not None:
            u_nom = u_plan
        else:
            u_nom = torch.zeros_like(self.u_noms[:, 0])
        self.mark(_finite_rows(u_nom), k)
        u_nom = self.clean(u_nom)
        self.u_noms[:, k] = u_nom
        return u_nom

    def filter(self, x_hat: Tensor, u_nom: Tensor, tk: float, k: int) -> Tensor:
        """The applied control: the safety filter's (its ``h`` and status recorded), or the
        nominal clipped to the control limits."""
        safety_filter = self.loop.safety_filter
        if safety_filter is None:
            u = self.loop.dynamics.clamp_control(u_nom)
        else:
            out = safety_filter(x_hat, u_nom, tk)
            u = out.u
            _check_shape("safety_filter(x_hat, u_nom, t).u", u, (self.B, self.m))
            h = out.h.reshape(self.B, math.prod(out.h.shape[1:]))  # an empty batch too
            if self.hs is None:
                self.hs = self.x.new_zeros(self.B, self.steps, h.shape[-1])
                self.statuses = torch.zeros(
                    self.B, self.steps, dtype=torch.int64, device=self.device
                )
        self.mark(_finite_rows(u), k)
        if safety_filter is not None:
            # a row failed by this step (its state, estimate, nominal or control) fed the
            # filter a zero stand-in or got no control: nothing of the filter is recorded
            failed = self.failed
            self.hs[:, k] = torch.where(failed.unsqueeze(-1), math.nan, h)
            self.statuses[:, k] = torch.where(failed, int(FilterStatus.NON_FINITE), out.status)
        u = self.clean(u)
        self.us[:, k] = u
        return u

    def advance(self, u: Tensor, tk: float, k: int) -> None:
        """Integrate the plant over one step (frozen rows stay), then update the estimate."""
        loop = self.loop
        w = None if loop.disturbance is None else loop.disturbance(self.x, tk)
        noise = None
        if self.q is not None:
            noise = counter_normal(self.seeds, _STREAMS * k + _PROCESS, (self.q,), dtype=self.dtype)
        x_next = integrate(loop.dynamics, self.x, u, self.dt, method=self.method, w=w, noise=noise)
        self.mark(_finite_rows(x_next), k + 1)
        self.x = torch.where(self.failed.unsqueeze(-1), self.x, x_next)
        if self.est_state is not None:
            state = loop.estimator.predict(self.est_state, u, self.dt)
            self.est_state = loop.estimator.update(state, self.measure(self.x, k + 1))
            # a non-finite measurement (or step) kept the old estimate: the row runs blind
            bits = self.est_state.status & int(EstimatorStatus.NON_FINITE)
            self.mark(bits == 0, k + 1)

    # -- after the last step ----------------------------------------------------------------
    def finish(self) -> Trajectory:
        steps = self.steps
        self.xs[:, steps] = self.x
        self.observe(steps)  # the last sample as every other: marked and cleaned
        return Trajectory(
            t=self.t,
            x=self.xs,
            x_hat=self.xs_hat,
            u_nom=self.u_noms,
            u=self.us,
            h=self.hs,
            status=self.statuses,
            failed=self.failed,
            fail_step=self.fail_step,
            planner=self.snapshots,
        )

    # -- helpers ----------------------------------------------------------------------------
    def measure(self, x: Tensor, k: int) -> Tensor:
        sensor = self.loop.sensor
        p = getattr(sensor, "output_dim", None) or sensor.expected(x).shape[-1]
        z = counter_normal(self.seeds, _STREAMS * k + _SENSOR, (p,), dtype=self.dtype)
        return sensor.measure(x, noise=z)

    def mark(self, ok: Tensor, k: int) -> None:
        """Flag the rows that are not ``ok`` (first time: at step ``k``)."""
        new = ~ok & ~self.failed
        self.fail_step = torch.where(new, torch.full_like(self.fail_step, k), self.fail_step)
        self.failed = self.failed | new

    def clean(self, value: Tensor) -> Tensor:
        """``value`` with the failed rows zeroed (a frozen row feeds no NaN forward)."""
        return torch.where(per_row(self.failed, value), torch.zeros_like(value), value)


def _check_shape(what: str, value: Any, shape: tuple[int, ...]) -> None:
    """A ValueError naming the component whose output has the wrong shape."""
    got = tuple(value.shape) if isinstance(value, Tensor) else type(value).__name__
    if got != shape:
        raise ValueError(f"{what} must be a tensor of shape [B, m] = {list(shape)}, got {got}")


def _check_model(dynamics: ControlAffine, x0: Tensor) -> None:
    """``f`` and ``g`` of the plant give ``[B, n]`` and ``[B, n, m]`` on ``x0`` (ValueError
    naming the model's method otherwise)."""
    B, n, m = x0.shape[0], dynamics.state_dim, dynamics.control_dim
    name = type(dynamics).__name__
    with torch.no_grad():
        for method, shape in (("f", (B, n)), ("g", (B, n, m))):
            value = getattr(dynamics, method)(x0)
            got = tuple(value.shape) if isinstance(value, Tensor) else type(value).__name__
            if got != shape:
                raise ValueError(
                    f"dynamics.{method}(x) of {name} must have shape {list(shape)} for x0 of "
                    f"shape {[B, n]} (state_dim {n}, control_dim {m}), got {got}"
                )


def _finite_rows(value: Tensor) -> Tensor:
    return torch.isfinite(value).flatten(1).all(-1)
