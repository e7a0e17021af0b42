"""Batched closed-loop simulation: planner -> nominal -> safety filter -> plant -> sensor ->
estimator, for B scenarios in lockstep on the device.

Component protocols (any callables or modules that follow them):

- ``planner(x_hat [B, n], t: float)`` returns an object with ``u [B, m]`` and ``plan
  [B, H, m]`` (e.g. :class:`torchcbf.mppi.MPPI`); ``planner.reset()`` is called first if it
  exists. With ``planner_every=k`` it runs every k steps and in between the loop follows its
  plan (index by elapsed time over ``planner.dt`` when the planner has one).
- ``nominal(x_hat, t)`` (no planner) or ``nominal(x_hat, t, u_plan)`` returns ``u_nom [B, m]``.
  Without a nominal controller the planner's control is the nominal one; with neither, the
  safety filter acts on a zero nominal control. At least one of the three is required (a
  loop with none would run on zero control: ValueError).
- ``safety_filter(x_hat, u_nom, t)`` returns an object with ``u``, ``status`` and ``h``
  (e.g. :class:`torchcbf.filters.SafetyFilter`). Without one, ``u_nom`` is clipped to the
  dynamics' control limits.
- ``sensor.measure(x, noise=z) -> y [B, p]`` with ``z`` standard normal ``[B, p]`` (drawn per
  scenario from its seed) and ``sensor.output_dim`` (or ``sensor.expected(x)`` to size it);
  ``estimator.init(x0, P0)``, ``estimator.predict(state, u, dt)``,
  ``estimator.update(state, y)`` on a state with a ``mean [B, n]`` field (e.g.
  :mod:`torchcbf.estimation`). With a sensor and no estimator the controllers see ``y``
  (which must then be a full state); with neither they see the true state.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

import torch
from torch import Tensor
from tqdm.auto import tqdm

from torchcbf._checks import check_last_dim, check_positive
from torchcbf._random import counter_normal
from torchcbf.dynamics.base import ControlAffine
from torchcbf.estimation import Estimator, Sensor
from torchcbf.integrators import METHODS
from torchcbf.integrators import step as integrate
from torchcbf.sim.trajectory import Trajectory

# Streams of the counter-based generator: one per source of noise and step.
_PROCESS, _SENSOR, _STREAMS = 0, 1, 2


def _seeds(seed: int | Sequence[int] | Tensor, batch: int, device: torch.device) -> Tensor:
    if isinstance(seed, int):
        return torch.arange(batch, device=device, dtype=torch.int64) + seed
    seeds = torch.as_tensor(seed, dtype=torch.int64, device=device).reshape(-1)
    if seeds.shape != (batch,):
        raise ValueError(
            f"seed must be an int or hold one seed per scenario ({batch}), got {tuple(seeds.shape)}"
        )
    return seeds


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


def simulate(
    dynamics: ControlAffine,
    x0: Tensor,
    steps: int,
    dt: float,
    *,
    planner: Callable[..., Any] | None = None,
    nominal: Callable[..., Tensor] | None = None,
    safety_filter: Callable[..., Any] | None = None,
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
    """Run B scenarios of the closed loop for ``steps`` steps of ``dt``.

    Args:
        dynamics: the plant (its diffusion, if any, is simulated with Euler-Maruyama
            whatever ``integrator`` says).
        integrator: ``"rk4"`` (default), ``"euler"`` or ``"euler_maruyama"``. The plant stands
            for the real system, so it is integrated accurately; a planner's rollouts are a
            model of it and trade accuracy for samples (:class:`~torchcbf.mppi.MPPI` rolls out
            with ``"euler"``), which is why the two defaults differ.
        x0: initial true states ``[B, n]`` (or ``[n]`` for one scenario).
        seed: an int (scenario b uses ``seed + b``) or one seed per scenario ``[B]``; every
            random draw of scenario b depends only on its seed, so a batch equals its rows
            run alone.
        x0_hat, P0: the estimator's initial mean ``[B, n]`` (default ``x0``) and covariance
            ``[B, n, n]`` or ``[n, n]`` (default: the sensor's noise level, else ``1e-2 I``).
        planner_every: run the planner every this many steps.
        disturbance: ``w = disturbance(x, t) -> [B, p]`` entering as ``M w``.
        progress: show a progress bar (steps per second included), labelled
            ``progress_label``.
        snapshot_steps: steps at which the planner's whole output is kept in
            ``Trajectory.planner``.
        differentiable: keep the autograd graph through the whole loop (to train through
            rollouts: gradients of the trajectory with respect to the controllers', filters'
            and barriers' parameters and ``x0``). Off by default: the loop then runs under
            ``torch.no_grad()``, faster and with no graph kept.

    Returns:
        A :class:`Trajectory`. A scenario whose state or a component's output goes non-finite
        is flagged in ``failed``/``fail_step`` and frozen; the others run on untouched.
    """
    with torch.set_grad_enabled(differentiable and torch.is_grad_enabled()):
        return _simulate(
            dynamics,
            x0,
            steps,
            dt,
            planner=planner,
            nominal=nominal,
            safety_filter=safety_filter,
            sensor=sensor,
            estimator=estimator,
            integrator=integrator,
            seed=seed,
            progress=progress,
            progress_label=progress_label,
            x0_hat=x0_hat,
            P0=P0,
            t0=t0,
            planner_every=planner_every,
            disturbance=disturbance,
            snapshot_steps=snapshot_steps,
        )


def _simulate(
    dynamics: ControlAffine,
    x0: Tensor,
    steps: int,
    dt: float,
    *,
    planner: Callable[..., Any] | None,
    nominal: Callable[..., Tensor] | None,
    safety_filter: Callable[..., Any] | None,
    sensor: Sensor | None,
    estimator: Estimator | None,
    integrator: str,
    seed: int | Sequence[int] | Tensor,
    progress: bool,
    progress_label: str,
    x0_hat: Tensor | None,
    P0: Tensor | None,
    t0: float,
    planner_every: int,
    disturbance: Callable[[Tensor, float], Tensor] | None,
    snapshot_steps: Sequence[int],
) -> Trajectory:
    if not isinstance(dynamics, ControlAffine):
        raise TypeError(f"dynamics must be a ControlAffine module, got {type(dynamics).__name__}")
    check_last_dim("x0", x0, dynamics.state_dim)
    if x0.dim() == 1:
        x0 = x0.unsqueeze(0)
    if x0.dim() != 2:
        raise ValueError(f"x0 must have shape [B, {dynamics.state_dim}], got {tuple(x0.shape)}")
    if not isinstance(steps, int) or steps < 1:
        raise ValueError(f"steps must be a positive int, got {steps!r}")
    dt = check_positive("dt", dt)
    if integrator not in METHODS:
        raise ValueError(f"integrator must be one of {METHODS}, got {integrator!r}")
    if planner_every < 1:
        raise ValueError(f"planner_every must be >= 1, got {planner_every}")
    if planner is None and nominal is None and safety_filter is None:
        raise ValueError(
            "simulate needs a controller: pass planner=, nominal= or safety_filter= (without "
            "any, the loop would run on zero control)"
        )
    method = "euler_maruyama" if dynamics.has_diffusion else integrator

    B, n, m = x0.shape[0], dynamics.state_dim, dynamics.control_dim
    _check_model(dynamics, x0)
    device, dtype = x0.device, x0.dtype
    seeds = _seeds(seed, B, device)
    sigma0 = dynamics.sigma(x0)
    q = None if sigma0 is None else sigma0.shape[-1]

    t = t0 + dt * torch.arange(steps + 1, device=device, dtype=dtype)
    xs = x0.new_zeros(B, steps + 1, n)
    xs_hat = x0.new_zeros(B, steps + 1, n)
    u_noms = x0.new_zeros(B, steps, m)
    us = x0.new_zeros(B, steps, m)
    hs: Tensor | None = None
    statuses: Tensor | None = None
    failed = torch.zeros(B, dtype=torch.bool, device=device)
    fail_step = torch.full((B,), -1, dtype=torch.int64, device=device)
    snapshots: dict[int, Any] = {}
    snapshot_set = set(snapshot_steps)

    def measure(x: Tensor, k: int) -> Tensor:
        p = getattr(sensor, "output_dim", None) or sensor.expected(x).shape[-1]
        z = counter_normal(seeds, _STREAMS * k + _SENSOR, (p,), dtype=dtype)
        return sensor.measure(x, noise=z)

    def mark(ok: Tensor, k: int) -> None:
        nonlocal failed, fail_step
        new = ~ok & ~failed
        fail_step = torch.where(new, torch.full_like(fail_step, k), fail_step)
        failed = failed | new

    def clean(value: Tensor) -> Tensor:
        return torch.where(
            failed.view(-1, *([1] * (value.dim() - 1))), torch.zeros_like(value), value
        )

    est_state = None
    if estimator is not None:
        if sensor is None:
            raise ValueError("an estimator needs a sensor")
        mean0 = x0 if x0_hat is None else x0_hat.to(x0).expand(B, n)
        if P0 is None:
            P0 = 1e-2 * torch.eye(n, device=device, dtype=dtype)
        est_state = estimator.init(mean0, P0.to(x0).expand(B, n, n))
    if planner is not None and hasattr(planner, "reset"):
        planner.reset()

    x = x0.clone()
    plan_out = None
    plan_step = 0
    plan_dt = float(getattr(planner, "dt", dt))
    bar = tqdm(range(steps), disable=not progress, desc=progress_label, unit="step", leave=False)
    for k in bar:
        tk = t0 + k * dt
        xs[:, k] = x
        if est_state is not None:
            x_hat = est_state.mean
        elif sensor is not None:
            x_hat = measure(x, k)
        else:
            x_hat = x
        mark(_finite_rows(x) & _finite_rows(x_hat), k)
        x_hat = clean(x_hat)
        xs_hat[:, k] = x_hat

        u_plan = None
        if planner is not None:
            if k % planner_every == 0:
                plan_out = planner(x_hat, tk)
                plan_step = k
                if k in snapshot_set:
                    snapshots[k] = plan_out
                u_plan = plan_out.u
                _check_shape("planner(x_hat, t).u", u_plan, (B, m))
            else:
                idx = min(int((k - plan_step) * dt / plan_dt + 1e-9), plan_out.plan.shape[-2] - 1)
                u_plan = plan_out.plan[:, idx]
        if nominal is not None:
            u_nom = nominal(x_hat, tk) if u_plan is None else nominal(x_hat, tk, u_plan)
            _check_shape("nominal(x_hat, t)", u_nom, (B, m))
        elif u_plan is not None:
            u_nom = u_plan
        else:
            u_nom = torch.zeros_like(u_noms[:, 0])
        mark(_finite_rows(u_nom), k)
        u_nom = clean(u_nom)

        if safety_filter is not None:
            out = safety_filter(x_hat, u_nom, tk)
            u = out.u
            _check_shape("safety_filter(x_hat, u_nom, t).u", u, (B, m))
            if hs is None:
                hs = x0.new_zeros(B, steps, out.h.reshape(B, -1).shape[-1])
                statuses = torch.zeros(B, steps, dtype=torch.int64, device=device)
            hs[:, k] = out.h.reshape(B, -1)
            statuses[:, k] = out.status
        else:
            u = dynamics.clamp_control(u_nom)
        mark(_finite_rows(u), k)
        u = clean(u)
        u_noms[:, k] = u_nom
        us[:, k] = u

        w = None if disturbance is None else disturbance(x, tk)
        noise = None
        if q is not None:
            noise = counter_normal(seeds, _STREAMS * k + _PROCESS, (q,), dtype=dtype)
        x_next = integrate(dynamics, x, u, dt, method=method, w=w, noise=noise)
        mark(_finite_rows(x_next), k + 1)
        x = torch.where(failed.unsqueeze(-1), x, x_next)

        if est_state is not None:
            est_state = estimator.predict(est_state, u, dt)
            est_state = estimator.update(est_state, measure(x, k + 1))

    xs[:, steps] = x
    if est_state is not None:
        xs_hat[:, steps] = est_state.mean
    elif sensor is not None:
        xs_hat[:, steps] = measure(x, steps)
    else:
        xs_hat[:, steps] = x
    return Trajectory(
        t=t,
        x=xs,
        x_hat=xs_hat,
        u_nom=u_noms,
        u=us,
        h=hs,
        status=statuses,
        failed=failed,
        fail_step=fail_step,
        planner=snapshots,
    )
