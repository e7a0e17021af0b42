"""Batched Gymnasium environments on torch tensors: one vector env steps all sub-environments
as one batch on the env's device; the single env is the same code with one row.

Seeding: sub-environment ``i`` of ``reset(seed=s)`` uses seed ``s + i`` (as Gymnasium's
``SyncVectorEnv`` does), and every random draw of an episode is a pure function of (seed,
episode number, step), so a vector env reproduces ``num_envs`` single envs exactly. A reset
without a seed starts the next episode of the same seed (a fresh random seed before the
first seeded reset).

Autoreset (vector env, ``autoreset_mode=``): Gymnasium's next-step mode by default
(``AutoresetMode.NEXT_STEP``): a sub-environment that ends (terminated or truncated) at one
``step`` is reset by the next ``step``, which ignores its action and returns its first
observation, reward 0, and ``terminated = truncated = False``. ``SAME_STEP`` resets it in
the step where it ends (the new episode's observation returned, the ended one's in
``info["final_obs"]`` and ``info["final_info"]``, rows marked by ``info["_final_obs"]``), as
TorchRL's ``GymWrapper`` expects; ``DISABLED`` leaves resets to
``reset(options={"reset_mask": ...})``.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import gymnasium
import numpy as np
import torch
from gymnasium import spaces
from gymnasium.vector import AutoresetMode
from gymnasium.vector.utils import batch_space
from torch import Tensor, nn

from torchcbf._checks import check_finite_action, check_positive_int
from torchcbf._random import seed_rows
from torchcbf.dynamics.base import ControlAffine
from torchcbf.envs import _noise

_SEED_RANGE = 2**31


class TorchVectorEnv(gymnasium.vector.VectorEnv):
    """Base of the batched environments: ``num_envs`` rows stepped as one tensor batch.

    Subclasses set ``dynamics``, ``barriers``, the single spaces (of ``np_dtype``, the
    NumPy twin of ``dtype``) and ``dt``, and implement
    :meth:`_start` (first state of some rows), :meth:`_advance` (one step of every row) and
    :meth:`_observe`. Observations, rewards and flags come back as NumPy arrays, or as
    tensors on the env's device with ``return_tensors=True`` (then actions may be tensors
    too and nothing leaves the device).
    """

    metadata: dict[str, Any] = {"autoreset_mode": AutoresetMode.NEXT_STEP, "render_modes": []}
    dynamics: ControlAffine
    barriers: nn.ModuleList
    dt: float

    def __init__(
        self,
        num_envs: int = 1,
        *,
        max_episode_steps: int | None = None,
        device: str | torch.device = "cpu",
        dtype: torch.dtype = torch.float32,
        return_tensors: bool = False,
        autoreset_mode: AutoresetMode | str = AutoresetMode.NEXT_STEP,
        render_mode: str | None = None,
    ) -> None:
        check_positive_int("num_envs", num_envs)
        if render_mode is not None:  # gymnasium.make passes it to every environment
            raise ValueError(
                f"render_mode={render_mode!r}: torchcbf's environments render nothing "
                "(metadata['render_modes'] is empty); draw their trajectories with torchcbf.viz"
            )
        self.render_mode = None
        try:
            mode = AutoresetMode(autoreset_mode)
        except ValueError:
            names = [m.value for m in AutoresetMode]
            raise ValueError(
                f"autoreset_mode must be an AutoresetMode or one of {names}, got {autoreset_mode!r}"
            ) from None
        self.metadata = {**type(self).metadata, "autoreset_mode": mode}
        if max_episode_steps is not None and (
            isinstance(max_episode_steps, bool)
            or not isinstance(max_episode_steps, int)
            or max_episode_steps < 1
        ):
            raise ValueError(
                f"max_episode_steps must be a positive int or None, got {max_episode_steps!r}"
            )
        if dtype not in (torch.float32, torch.float64):
            raise TypeError(f"dtype must be torch.float32 or torch.float64, got {dtype}")
        self.num_envs = num_envs
        self.max_episode_steps = max_episode_steps
        self.device = torch.device(device)
        self.dtype = dtype
        self.np_dtype = np.float32 if dtype == torch.float32 else np.float64
        self.return_tensors = bool(return_tensors)
        rows = torch.zeros(num_envs, dtype=torch.int64, device=self.device)
        self._seeds = rows.clone()
        self._episodes = rows.clone()
        self._steps = rows.clone()
        self._done = torch.zeros(num_envs, dtype=torch.bool, device=self.device)
        self._seeded = False
        self._started = False

    @property
    def autoreset_mode(self) -> AutoresetMode:
        """How ended sub-environments start again (``metadata["autoreset_mode"]``)."""
        return self.metadata["autoreset_mode"]

    def _set_spaces(self, observation: spaces.Box, action: spaces.Box) -> None:
        self.single_observation_space = observation
        self.single_action_space = action
        self.observation_space = batch_space(observation, self.num_envs)
        self.action_space = batch_space(action, self.num_envs)
        self._u_low = torch.as_tensor(action.low, dtype=self.dtype, device=self.device)
        self._u_high = torch.as_tensor(action.high, dtype=self.dtype, device=self.device)

    # -- the scenario's part -----------------------------------------------------------------

    def _start(self, rows: Tensor, z: Tensor) -> None:
        """Set the first state of the rows where ``rows [N]`` is True; ``z [N, n]`` is a
        standard normal draw of each row's episode."""
        raise NotImplementedError

    def _advance(self, u: Tensor, z: Tensor | None) -> tuple[Tensor, Tensor, dict[str, Tensor]]:
        """Step every row under ``u [N, m]`` (``z [N, q]``: process noise, or None);
        returns ``reward [N]``, ``terminated [N]`` and per-row info tensors."""
        raise NotImplementedError

    def _observe(self) -> Tensor:
        """Observations ``[N, d]`` of the current states."""
        raise NotImplementedError

    def _info(self) -> dict[str, Tensor]:
        """Per-row info of the current states (after a reset)."""
        raise NotImplementedError

    noise_dim: int = 0

    def state_from_observation(self, observation: Tensor | np.ndarray) -> Tensor:
        """The dynamics' state ``[..., n]`` of observations ``[..., d]`` (a tensor on the
        env's device): the observation starts with the state."""
        obs = torch.as_tensor(observation, device=self.device, dtype=self.dtype)
        return obs[..., : self.dynamics.state_dim]

    # -- Gymnasium's API -----------------------------------------------------------------------

    def _draw(self, steps: Tensor | int, dim: int) -> Tensor:
        return _noise.normal(self._seeds, self._episodes, steps, dim, dtype=self.dtype)

    def _reset_rows(self, rows: Tensor, seeds: Tensor | None) -> None:
        """Start a new episode in ``rows``: from ``seeds`` (episode 0) or the next episode."""
        if seeds is not None:
            self._seeds = torch.where(rows, seeds, self._seeds)
            self._episodes = torch.where(rows, 0, self._episodes)
        else:
            self._episodes = torch.where(rows, self._episodes + 1, self._episodes)
        self._steps = torch.where(rows, 0, self._steps)
        self._done = self._done & ~rows
        self._start(rows, self._draw(0, self.dynamics.state_dim))

    def _seed_tensor(self, seed: int | Sequence[int | None] | None) -> Tensor | None:
        if seed is None:
            if self._seeded:
                return None
            drawn = self.np_random.integers(0, _SEED_RANGE, size=self.num_envs)
            return torch.as_tensor(drawn, dtype=torch.int64, device=self.device)
        if isinstance(seed, (int, np.integer)) and not isinstance(seed, bool):
            return seed_rows(int(seed), self.num_envs, self.device, per="sub-environment")
        if isinstance(seed, (Tensor, np.ndarray)):  # no None among them
            return seed_rows(seed, self.num_envs, self.device, per="sub-environment")
        if not isinstance(seed, Sequence) or isinstance(seed, str):
            raise TypeError(
                f"seed must be an int, one per sub-environment (ints or None) or None, "
                f"got {type(seed).__name__}"
            )
        seeds = list(seed)
        if len(seeds) != self.num_envs:
            raise ValueError(
                f"seed as a list needs num_envs = {self.num_envs} entries, got {seeds}"
            )
        fill = self.np_random.integers(0, _SEED_RANGE, size=self.num_envs)
        values = [int(f) if s is None else s for s, f in zip(seeds, fill, strict=True)]
        return seed_rows(values, self.num_envs, self.device, per="sub-environment")

    def reset(
        self,
        *,
        seed: int | Sequence[int | None] | None = None,
        options: dict[str, Any] | None = None,
    ) -> tuple[Any, dict[str, Any]]:
        """Reset every sub-environment (or those of ``options["reset_mask"]`` [N] bool).

        ``seed``: an int (sub-environment ``i`` gets ``seed + i``), one seed per
        sub-environment, or None (the next episode of each one's seed).
        """
        if seed is not None:
            seeds = self._seed_tensor(seed)  # refused before any state changes
        super().reset(seed=seed if isinstance(seed, int) else None)
        rows = torch.ones(self.num_envs, dtype=torch.bool, device=self.device)
        if options is not None and "reset_mask" in options:
            mask = np.asarray(options["reset_mask"])
            if mask.shape != (self.num_envs,) or mask.dtype != np.bool_:
                raise ValueError(
                    f"options['reset_mask'] must be a bool array of shape ({self.num_envs},), "
                    f"got {mask.dtype} {mask.shape}"
                )
            rows = torch.as_tensor(mask, device=self.device)
            if not self._started:
                raise ValueError("options['reset_mask'] needs a full reset first")
        if seed is None:
            seeds = self._seed_tensor(seed)
        self._seeded = True
        with torch.no_grad():
            self._reset_rows(rows, seeds)
        self._started = True
        return self._out_obs(self._observe()), self._out_info(self._info())

    def _actions(self, actions: Any) -> Tensor:
        if isinstance(actions, Tensor):
            check_finite_action("actions", actions)  # as for a NumPy action: refused
            u = actions.to(device=self.device, dtype=self.dtype)
        else:
            array = np.asarray(actions, dtype=np.float64)
            if not np.all(np.isfinite(array)):
                raise ValueError("actions must be finite")
            u = torch.as_tensor(array, device=self.device, dtype=self.dtype)
        m = self.single_action_space.shape[0]
        if u.shape != (self.num_envs, m):
            raise ValueError(
                f"actions must have shape ({self.num_envs}, {m}), got {tuple(u.shape)}"
            )
        return torch.minimum(torch.maximum(u, self._u_low), self._u_high)

    def step(self, actions: Any) -> tuple[Any, Any, Any, Any, dict[str, Any]]:
        """Step every sub-environment; actions ``[N, m]`` are clipped to the action space."""
        if not self._started:
            raise RuntimeError("call reset() before step()")
        with torch.no_grad():
            u = self._actions(actions)
            z = self._draw(self._steps + 1, self.noise_dim) if self.noise_dim else None
            reward, terminated, info = self._advance(u, z)
            self._steps = self._steps + 1
            if self.max_episode_steps is None:
                truncated = torch.zeros_like(terminated)
            else:
                truncated = self._steps >= self.max_episode_steps
            mode = self.metadata["autoreset_mode"]
            if mode == AutoresetMode.NEXT_STEP:
                # rows that ended at the previous step start again now, their action ignored
                restart = self._done
                self._reset_rows(restart, None)
                fresh = self._info()
                info = {k: torch.where(_rows(restart, v), fresh[k], v) for k, v in info.items()}
                reward = torch.where(restart, torch.zeros_like(reward), reward)
                terminated = terminated & ~restart
                truncated = truncated & ~restart
            self._done = terminated | truncated
            obs = self._observe()
            if mode == AutoresetMode.SAME_STEP:
                # rows that end now start again at once: the observation is the new
                # episode's, the last one of the ended episode is in info["final_obs"]
                ended = self._done
                final_obs, final_info = obs, info
                self._reset_rows(ended, None)
                obs, fresh = self._observe(), self._info()
                info = {k: torch.where(_rows(ended, v), fresh[k], v) for k, v in info.items()}
                info["final_obs"] = final_obs
                info["final_info"] = final_info
                info["_final_obs"] = info["_final_info"] = ended
                self._done = torch.zeros_like(ended)
        return (
            self._out_obs(obs),
            reward if self.return_tensors else reward.cpu().numpy().astype(np.float64),
            terminated if self.return_tensors else terminated.cpu().numpy(),
            truncated if self.return_tensors else truncated.cpu().numpy(),
            self._out_info(info),
        )

    def _out_obs(self, obs: Tensor) -> Any:
        if self.return_tensors:
            return obs
        return obs.cpu().numpy().astype(self.single_observation_space.dtype, copy=False)

    def _out_info(self, info: dict[str, Any]) -> dict[str, Any]:
        if self.return_tensors:
            return dict(info)
        return {
            k: self._out_info(v) if isinstance(v, dict) else v.cpu().numpy()
            for k, v in info.items()
        }

    def close_extras(self, **kwargs: Any) -> None:
        """Nothing to release: the batch lives in tensors."""


def _rows(rows: Tensor, value: Tensor) -> Tensor:
    """``rows [N]`` broadcast over the trailing dimensions of ``value [N, ...]``."""
    return rows.reshape(-1, *([1] * (value.dim() - 1)))


class TorchEnv(gymnasium.Env):
    """A single environment: one row of its vector env, without autoreset or truncation
    (``gymnasium.make`` adds the time limit of the registration)."""

    metadata: dict[str, Any] = {"render_modes": []}
    vector_class: type[TorchVectorEnv]

    def __init__(self, **kwargs: Any) -> None:
        self.vector = self.vector_class(1, max_episode_steps=None, **kwargs)
        self.observation_space = self.vector.single_observation_space
        self.action_space = self.vector.single_action_space

    @property
    def dynamics(self) -> ControlAffine:
        """The plant (:class:`~torchcbf.dynamics.ControlAffine`)."""
        return self.vector.dynamics

    @property
    def barriers(self) -> nn.ModuleList:
        """The obstacles as barriers on the state (``h >= 0`` safe)."""
        return self.vector.barriers

    @property
    def dt(self) -> float:
        """Time step in seconds."""
        return self.vector.dt

    def state_from_observation(self, observation: Tensor | np.ndarray) -> Tensor:
        """The dynamics' state ``[..., n]`` of observations ``[..., d]``."""
        return self.vector.state_from_observation(observation)

    def reset(
        self, *, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[np.ndarray, dict[str, Any]]:
        """Start an episode; ``seed`` fixes every random draw of it and of later episodes."""
        if seed is not None:
            seed_rows(seed, 1, self.vector.device, per="environment")
        super().reset(seed=seed)
        vec = self.vector
        if seed is None and vec._seeded:
            seeds = None  # the next episode of the same seed
        else:
            if seed is None:
                seed = int(self.np_random.integers(0, _SEED_RANGE))
            seeds = torch.full_like(vec._seeds, int(seed))
        vec._seeded = True
        with torch.no_grad():
            vec._reset_rows(torch.ones_like(vec._done), seeds)
        vec._started = True
        return self._single(vec._observe()), self._single_info(vec._info())

    def step(self, action: Any) -> tuple[np.ndarray, float, bool, bool, dict[str, Any]]:
        """One step; the action is clipped to the action space."""
        vec = self.vector
        if not vec._started:
            raise RuntimeError("call reset() before step()")
        with torch.no_grad():
            u = vec._actions(np.asarray(action, dtype=np.float64).reshape(1, -1))
            z = vec._draw(vec._steps + 1, vec.noise_dim) if vec.noise_dim else None
            reward, terminated, info = vec._advance(u, z)
            vec._steps = vec._steps + 1
        return (
            self._single(vec._observe()),
            float(reward[0]),
            bool(terminated[0]),
            False,
            self._single_info(info),
        )

    def _single(self, obs: Tensor) -> np.ndarray:
        return obs[0].detach().cpu().numpy().astype(self.observation_space.dtype, copy=False)

    def _single_info(self, info: dict[str, Tensor]) -> dict[str, Any]:
        out: dict[str, Any] = {}
        for key, value in info.items():
            v = value[0].detach().cpu()
            out[key] = v.item() if v.dim() == 0 else v.numpy()
        return out
