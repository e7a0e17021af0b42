"""``torchcbf/ReachAvoid-v0``: scenario A as a Gymnasium environment (the scenario is
:mod:`torchcbf.scenarios.single_integrator_reach_avoid`).

A single integrator ``p' = u`` in the plane (``|u_i| <= 5`` m/s, exact zero-order-hold step
of ``dt = 0.1`` s) must visit three goal discs of radius 0.5 m in their time windows,
g1 = (4, 4) in [0, 3.5] s, g2 = (6, 9) in [3.6, 5] s, g3 = (4, 1) in [5.1, 10] s, and never
enter the obstacle disc of radius 0.6 m at (3, 3). Episodes last at most 100 steps (10 s).

Observation ``[6]``: ``(x, y, t, g1, g2, g3)``: the position (m), the time (s) and one flag
per goal (1 once visited inside its window).

Reward per step: the progress towards the current target (the first goal not yet visited),
``|p - c| - |p' - c|`` in metres, plus ``goal_bonus`` for each goal visited at this step,
minus ``collision_penalty`` when the step ends inside the obstacle.

Termination: all three goals visited (success), the obstacle entered (collision; with
``terminate_on_collision=False`` the episode goes on and the penalty and the collision flag
mark every step that ends inside), or a goal's window closed without a visit (the
specification can no longer hold). Truncation: the time limit of 100 steps.

Start: the origin, plus ``start_noise`` (m, default 0) times a standard normal draw of the
episode's seed.
"""

from __future__ import annotations

import numpy as np
import torch
from gymnasium import spaces
from gymnasium.vector import AutoresetMode
from torch import Tensor, nn

from torchcbf._checks import check_bool, check_number
from torchcbf.barriers import Ball
from torchcbf.dynamics import SingleIntegrator
from torchcbf.envs.base import TorchEnv, TorchVectorEnv
from torchcbf.integrators import step
from torchcbf.scenarios.single_integrator_reach_avoid import (
    GOAL_RADIUS,
    GOALS,
    OBSTACLE_CENTER,
    OBSTACLE_RADIUS,
)

DT = 0.1
MAX_EPISODE_STEPS = 100
SPEED_LIMIT = 5.0


class ReachAvoidVectorEnv(TorchVectorEnv):
    """Scenario A for ``num_envs`` robots stepped as one batch (see the module docstring).

    Args:
        num_envs: number of sub-environments N.
        max_episode_steps: truncation (``make_vec`` passes the registration's 100).
        goal_bonus: reward for each goal visited in its window.
        collision_penalty: subtracted at the step that enters the obstacle.
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
        goal_bonus: float = 1.0,
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
        self.goal_bonus = check_number("goal_bonus", goal_bonus, low=0.0)
        self.collision_penalty = check_number("collision_penalty", collision_penalty, low=0.0)
        self.terminate_on_collision = check_bool("terminate_on_collision", terminate_on_collision)
        self.start_noise = check_number("start_noise", start_noise, low=0.0)
        self.dt = DT
        kw = {"device": self.device, "dtype": dtype}
        self.dynamics = SingleIntegrator(2, u_min=-SPEED_LIMIT, u_max=SPEED_LIMIT).to(**kw)
        self.barriers = nn.ModuleList([Ball(OBSTACLE_CENTER, OBSTACLE_RADIUS).to(**kw)])
        self._centers = torch.tensor([c for c, _, _ in GOALS], **kw)
        self._windows = torch.tensor([w for _, w, _ in GOALS], **kw)
        self._x = torch.zeros(num_envs, 2, **kw)
        self._visited = torch.zeros(num_envs, len(GOALS), dtype=torch.bool, device=self.device)
        inf = np.inf
        observation = spaces.Box(
            low=np.array([-inf, -inf, 0.0, 0.0, 0.0, 0.0], dtype=self.np_dtype),
            high=np.array([inf, inf, inf, 1.0, 1.0, 1.0], dtype=self.np_dtype),
            dtype=self.np_dtype,
        )
        action = spaces.Box(-SPEED_LIMIT, SPEED_LIMIT, shape=(2,), dtype=self.np_dtype)
        self._set_spaces(observation, action)

    def _start(self, rows: Tensor, z: Tensor) -> None:
        x0 = self.start_noise * z if self.start_noise > 0 else torch.zeros_like(z)
        self._x = torch.where(rows[:, None], x0, self._x)
        self._visited = self._visited & ~rows[:, None]

    def _target(self) -> Tensor:
        """Centre ``[N, 2]`` of the first goal not yet visited (the last one when all are)."""
        first = torch.argmin(self._visited.to(torch.int8), dim=-1)
        return self._centers[first]

    def _advance(self, u: Tensor, z: Tensor | None) -> tuple[Tensor, Tensor, dict[str, Tensor]]:
        target = self._target()
        before = (self._x - target).norm(dim=-1)
        self._x = step(self.dynamics, self._x, u, self.dt, "rk4")
        t = (self._steps + 1).to(self.dtype) * self.dt
        reward = before - (self._x - target).norm(dim=-1)
        inside = (self._x[:, None, :] - self._centers).norm(dim=-1) <= GOAL_RADIUS
        window = (t[:, None] >= self._windows[:, 0] - 1e-6) & (
            t[:, None] <= self._windows[:, 1] + 1e-6
        )
        new = inside & window & ~self._visited
        self._visited = self._visited | new
        h = self.barriers[0](self._x)
        collision = h < 0
        missed = ((t[:, None] > self._windows[:, 1] + 1e-6) & ~self._visited).any(-1)
        success = self._visited.all(-1) & ~collision
        reward = reward + self.goal_bonus * new.sum(-1).to(self.dtype)
        reward = reward - self.collision_penalty * collision.to(self.dtype)
        terminated = success | (collision & self.terminate_on_collision) | missed
        info = {"h": h[:, None], "collision": collision, "success": success}
        return reward, terminated, info

    def _info(self) -> dict[str, Tensor]:
        h = self.barriers[0](self._x)
        return {"h": h[:, None], "collision": h < 0, "success": self._visited.all(-1)}

    def _observe(self) -> Tensor:
        t = self._steps.to(self.dtype) * self.dt
        return torch.cat([self._x, t[:, None], self._visited.to(self.dtype)], dim=-1)


class ReachAvoidEnv(TorchEnv):
    """Scenario A, one robot (``gymnasium.make("torchcbf/ReachAvoid-v0")``); keyword
    arguments as :class:`ReachAvoidVectorEnv` (without ``num_envs`` and the time limit)."""

    vector_class = ReachAvoidVectorEnv
