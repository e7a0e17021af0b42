"""The pendulum swing-up, pytorch-mppi's test problem, written for torchcbf's planners.

Gymnasium's ``Pendulum-v1`` (``g = 10``, ``m = l = 1``, ``dt = 0.05``): the angle ``theta``
is 0 upright, the torque is clipped to ``[-2, 2]`` and the speed to ``[-8, 8]``. The planner's
model is pytorch-mppi's (its test's ``dynamics`` and ``running_cost``), with the torque and
the speed clipped inside the step, so pytorch-mppi's test planner samples unbounded torques:
build that one with ``PendulumModel(u_min=None, u_max=None)``; ``PendulumModel()`` bounds the
torque to ``[-2, 2]``, and a planner on it clamps its samples there:

- :class:`PendulumModel`, the continuous dynamics ``theta'' = 3 g / (2 l) sin(theta) +
  3 / (m l^2) u`` (for ``n``, ``m`` and the limits; its Euler step is not the clipped one);
- :func:`pendulum_step`, the discrete step the planner rolls out (``MPPI(step=...)``);
- :func:`pendulum_cost`, ``sum_j angle(theta_{j+1})^2 + 0.1 theta'_{j+1}^2`` over the
  rollout;
- :func:`pendulum_reward`, the environment's reward of one step (for the comparison).
"""

from __future__ import annotations

import math
from typing import Any

import torch
from torch import Tensor

from torchcbf.dynamics.base import ControlAffine

GRAVITY, MASS, LENGTH, DT = 10.0, 1.0, 1.0, 0.05
MAX_TORQUE, MAX_SPEED = 2.0, 8.0


class PendulumModel(ControlAffine):
    """``x = (theta, theta')``, ``u = torque``: ``theta'' = 3 g / (2 l) sin(theta) +
    3 / (m l^2) u`` (``theta = 0`` upright)."""

    def __init__(self, **kwargs: Any) -> None:
        kwargs.setdefault("u_min", -MAX_TORQUE)
        kwargs.setdefault("u_max", MAX_TORQUE)
        super().__init__(2, 1, **kwargs)

    def f(self, x: Tensor) -> Tensor:
        gain = 3.0 * GRAVITY / (2.0 * LENGTH)
        return torch.stack([x[..., 1], gain * torch.sin(x[..., 0])], -1)

    def g(self, x: Tensor) -> Tensor:
        g = torch.zeros(*x.shape[:-1], 2, 1, dtype=x.dtype, device=x.device)
        g[..., 1, 0] = 3.0 / (MASS * LENGTH**2)
        return g


def angle_normalize(theta: Tensor) -> Tensor:
    """``theta`` wrapped to ``[-pi, pi)``."""
    return torch.remainder(theta + math.pi, 2 * math.pi) - math.pi


def pendulum_step(x: Tensor, u: Tensor, j: int = 0) -> Tensor:
    """pytorch-mppi's test model: ``x [..., 2]``, ``u [..., 1]`` -> ``[..., 2]`` (the step
    index ``j`` is unused: the dynamics do not depend on time)."""
    theta, speed = x[..., 0], x[..., 1]
    torque = u[..., 0].clamp(-MAX_TORQUE, MAX_TORQUE)
    accel = 3.0 * GRAVITY / (2.0 * LENGTH) * torch.sin(theta) + 3.0 / (MASS * LENGTH**2) * torque
    speed = speed + accel * DT
    theta = theta + speed * DT
    return torch.stack([theta, speed.clamp(-MAX_SPEED, MAX_SPEED)], -1)


def pendulum_cost(states: Tensor, controls: Tensor, t0: Tensor | None = None) -> Tensor:
    """``states [B, K, H+1, 2]`` -> ``[B, K]``: pytorch-mppi's running cost summed over the
    steps after the current state."""
    later = states[..., 1:, :]
    return (angle_normalize(later[..., 0]).square() + 0.1 * later[..., 1].square()).sum(-1)


def pendulum_reward(x: Tensor, u: Tensor) -> Tensor:
    """The environment's reward of applying ``u [..., 1]`` at ``x [..., 2]`` (``[...]``)."""
    torque = u[..., 0].clamp(-MAX_TORQUE, MAX_TORQUE)
    cost = angle_normalize(x[..., 0]).square() + 0.1 * x[..., 1].square() + 0.001 * torque**2
    return -cost
