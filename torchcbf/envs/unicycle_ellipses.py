"""``torchcbf/UnicycleEllipses-v0``: scenario B as a Gymnasium environment (the scenario is
:mod:`torchcbf.scenarios.unicycle_mppi_cbf`).

A unicycle with acceleration input, state ``(x, y, v, theta)``, control ``(a, omega)``,
driven by the SDE ``dx = (f + g u) dt + sigma dW`` with ``sigma = 0.28 I`` on all four
states (Euler-Maruyama, ``dt = 0.01`` s), starts at the origin heading pi/4 at rest and must
reach the goal disc of radius 0.25 m at (2, 4) among five elliptical obstacles. Episodes
last at most 500 steps (5 s). The control is limited to ``|a| <= control_limit[0]`` m/s^2
and ``|omega| <= control_limit[1]`` rad/s (default (5, 10); the plant model carries the
same limits, so a safety filter built on :attr:`dynamics` respects them).

Observation ``[4]``: the state ``(x, y, v, theta)`` (m, m, m/s, rad), with the heading
wrapped to [-pi, pi).

Reward per step: the progress towards the goal ``|p - g| - |p' - g|`` in metres, plus
``goal_bonus`` at the step that reaches the goal, minus ``collision_penalty`` at the step
that ends inside an obstacle.

Termination: the goal reached (success) or an obstacle entered (collision; with
``terminate_on_collision=False`` the episode goes on and the penalty and the collision flag
mark every step that ends inside). Truncation: the time limit of 500 steps.

The process noise of each step, and the start perturbation ``start_noise`` (m, default 0)
of the position, are standard normal draws that depend only on the episode's seed.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
import torch
from gymnasium import spaces
from gymnasium.vector import AutoresetMode
from torch import Tensor, nn

from torchcbf._checks import check_bool, check_number
from torchcbf.dynamics import AccelUnicycle
from torchcbf.envs.base import TorchEnv, TorchVectorEnv
from torchcbf.integrators import step
from torchcbf.scenarios.unicycle_mppi_cbf import GOAL, SIGMA, obstacles

DT = 0.01
MAX_EPISODE_STEPS = 500
GOAL_RADIUS = 0.25
START = (0.0, 0.0, 0.0, math.pi / 4)


class UnicycleEllipsesVectorEnv(TorchVectorEnv):
    """Scenario B for ``num_envs`` robots stepped as one batch (see the module docstring).

    Args:
        num_envs: number of sub-environments N.
        max_episode_steps: truncation (``make_vec`` passes the registration's 500).
        control_limit: bounds ``(a_max, omega_max)`` of the action space and the plant.
        sigma: diffusion of every state (0: deterministic Euler steps).
        goal_bonus: reward at the step that reaches the goal.
        collision_penalty: subtracted at the step that enters an obstacle.
        terminate_on_collision: end the episode at a collision (default); False
            keeps it running (the cost marks every step inside an obstacle).
        start_noise: standard deviation (m) of the start position around the origin.
        device, dtype: where the batch lives.
        return_tensors: return tensors on ``device`` instead of NumPy arrays.
        autoreset_mode: Gymnasium's ``AutoresetMode``: ``NEXT_STEP`` (default; an ended row
            starts again at the next step), ``SAME_STEP`` (at once, the ended episode's last
            observation in ``info["final_obs"]``) or ``DISABLED`` (reset rows with
            ``reset(options={"reset_mask": ...})``).
        render_mode: ``None`` only (Gymnasium passes it; nothing is rendered: a mode is a
            ``ValueError``, and :mod:`torchcbf.viz` draws trajectories).
    """

    def __init__(
        self,
        num_envs: int = 1,
        *,
        max_episode_steps: int | None = MAX_EPISODE_STEPS,
        control_limit: Sequence[float] = (5.0, 10.0),
        sigma: float = SIGMA,
        goal_bonus: float = 10.0,
        collision_penalty: float = 10.0,
        terminate_on_collision: bool = True,
        start_noise: float = 0.0,
        device: str | torch.device = "cpu",
        dtype: torch.dtype = torch.float32,
        return_tensors: bool = False,
        autoreset_mode: AutoresetMode | str = AutoresetMode.NEXT_STEP,
        render_mode: str | None = None,
    ) -> None:
        super().__init__(
            num_envs,
            max_episode_steps=max_episode_steps,
            device=device,
            dtype=dtype,
            return_tensors=return_tensors,
            autoreset_mode=autoreset_mode,
            render_mode=render_mode,
        )
        if isinstance(control_limit, (Tensor, np.ndarray)):
            control_limit = control_limit.tolist()
        if not isinstance(control_limit, Sequence) or isinstance(control_limit, str):
            raise TypeError(f"control_limit must be two positive numbers, got {control_limit!r}")
        if len(control_limit) != 2:
            raise ValueError(f"control_limit must be two positive numbers, got {control_limit!r}")
        limit = [
            check_number(f"control_limit[{i}]", v, low=0.0, strict=True)
            for i, v in enumerate(control_limit)
        ]
        self.sigma = check_number("sigma", sigma, low=0.0)
        self.goal_bonus = check_number("goal_bonus", goal_bonus, low=0.0)
        self.collision_penalty = check_number("collision_penalty", collision_penalty, low=0.0)
        self.terminate_on_collision = check_bool("terminate_on_collision", terminate_on_collision)
        self.start_noise = check_number("start_noise", start_noise, low=0.0)
        self.dt = DT
        kw = {"device": self.device, "dtype": dtype}
        diffusion = {"sigma": self.sigma} if self.sigma > 0 else {}
        self.dynamics = AccelUnicycle(u_min=[-v for v in limit], u_max=limit, **diffusion).to(**kw)
        self.noise_dim = 4 if self.sigma > 0 else 0
        self.barriers = nn.ModuleList([obstacles().to(**kw)])
        self._goal = torch.tensor(GOAL, **kw)
        self._start_state = torch.tensor(START, **kw)
        self._x = self._start_state.repeat(num_envs, 1)
        inf = np.inf
        observation = spaces.Box(
            low=np.array([-inf, -inf, -inf, -np.pi], dtype=self.np_dtype),
            high=np.array([inf, inf, inf, np.pi], dtype=self.np_dtype),
            dtype=self.np_dtype,
        )
        action = spaces.Box(
            low=-np.array(limit, dtype=self.np_dtype),
            high=np.array(limit, dtype=self.np_dtype),
            dtype=self.np_dtype,
        )
        self._set_spaces(observation, action)

    def _start(self, rows: Tensor, z: Tensor) -> None:
        x0 = self._start_state.expand_as(self._x).clone()
        if self.start_noise > 0:
            x0[:, :2] = x0[:, :2] + self.start_noise * z[:, :2]
        self._x = torch.where(rows[:, None], x0, self._x)

    def _advance(self, u: Tensor, z: Tensor | None) -> tuple[Tensor, Tensor, dict[str, Tensor]]:
        before = (self._x[:, :2] - self._goal).norm(dim=-1)
        if z is None:
            x = step(self.dynamics, self._x, u, self.dt, "euler")
        else:
            x = step(self.dynamics, self._x, u, self.dt, "euler_maruyama", noise=z)
        heading = torch.remainder(x[:, 3] + math.pi, 2 * math.pi) - math.pi
        self._x = torch.cat([x[:, :3], heading[:, None]], dim=-1)
        after = (self._x[:, :2] - self._goal).norm(dim=-1)
        h = self.barriers[0](self._x)
        collision = (h < 0).any(-1)
        success = (after <= GOAL_RADIUS) & ~collision
        reward = before - after + self.goal_bonus * success.to(self.dtype)
        reward = reward - self.collision_penalty * collision.to(self.dtype)
        terminated = success | (collision & self.terminate_on_collision)
        return reward, terminated, {"h": h, "collision": collision, "success": success}

    def _info(self) -> dict[str, Tensor]:
        h = self.barriers[0](self._x)
        reached = (self._x[:, :2] - self._goal).norm(dim=-1) <= GOAL_RADIUS
        return {"h": h, "collision": (h < 0).any(-1), "success": reached}

    def _observe(self) -> Tensor:
        return self._x.clone()


class UnicycleEllipsesEnv(TorchEnv):
    """Scenario B, one robot (``gymnasium.make("torchcbf/UnicycleEllipses-v0")``); keyword
    arguments as :class:`UnicycleEllipsesVectorEnv` (without ``num_envs`` and the time
    limit)."""

    vector_class = UnicycleEllipsesVectorEnv
