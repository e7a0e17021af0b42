"""torchcbf's environments as native TorchRL environments (extra ``rl``:
``pip install "torchcbf[rl]"``).

:class:`TorchRLEnv` is a :class:`torchrl.envs.EnvBase` with ``batch_size = [num_envs]`` on
the environment's device: all sub-environments step as one batch of tensors (no Gymnasium
round trip, no NumPy). The scenario (dynamics, reward, termination, random draws) is that
of the Gymnasium vector env of the same id (:mod:`torchcbf.envs`), so both give the same
episodes for the same seeds.

Keys (TorchRL's conventions): ``"action"`` ``[N, m]`` (clipped to the action spec), and
after a step ``("next", k)`` for ``k`` in ``"observation"`` ``[N, d]``, ``"reward"``
``[N, 1]``, ``"done"``, ``"terminated"``, ``"truncated"`` ``[N, 1]`` (bool), ``"h"``
``[N, k]`` (the obstacles' barrier values, ``h >= 0`` safe), ``"cost"`` ``[N, 1]`` (1.0 at a
step that ends inside an obstacle, the safe-RL constraint cost) and ``"success"`` ``[N, 1]``
(bool: the task done). There is no autoreset: TorchRL resets ended rows through ``"_reset"``
(``env.rollout``, ``step_and_maybe_reset`` and the collectors do).

Seeding: ``set_seed(s)`` (or ``seed=s``) makes the next full reset start sub-environment
``i`` from seed ``s + i``; later resets start each row's next episode of its seed, so a run
is a pure function of the seed, whatever the batch size (row ``i`` of a batch reproduces a
batch-of-one environment seeded ``s + i``).
"""

from __future__ import annotations

import secrets
from typing import Any

import gymnasium
import torch
from gymnasium.envs.registration import load_env_creator
from tensordict import TensorDict, TensorDictBase
from torch import Tensor, nn
from torchrl.data import Bounded, Categorical, Composite, Unbounded
from torchrl.envs import EnvBase

from torchcbf._checks import check_finite_action
from torchcbf._random import seed_rows
from torchcbf.dynamics.base import ControlAffine
from torchcbf.envs.base import TorchVectorEnv

__all__ = ["TorchRLEnv"]

_SEED_RANGE = 2**31


def vector_env_class(env: str) -> type[TorchVectorEnv]:
    """The :class:`~torchcbf.envs.TorchVectorEnv` class registered under the id ``env``."""
    if not isinstance(env, str):
        raise TypeError(
            f"env must be a registered torchcbf id (str) or a TorchVectorEnv, "
            f"got {type(env).__name__}"
        )
    spec = gymnasium.spec(env)
    if spec.vector_entry_point is None:
        raise ValueError(f"env {env!r} has no vector entry point: not a torchcbf environment")
    cls = spec.vector_entry_point
    cls = load_env_creator(cls) if isinstance(cls, str) else cls
    if not (isinstance(cls, type) and issubclass(cls, TorchVectorEnv)):
        raise ValueError(f"env {env!r} is not a torchcbf TorchVectorEnv ({cls!r})")
    return cls


def _vector_env(
    env: str | TorchVectorEnv,
    num_envs: int,
    device: str | torch.device,
    dtype: torch.dtype,
    max_episode_steps: int | None,
    kwargs: dict[str, Any],
) -> TorchVectorEnv:
    if isinstance(env, TorchVectorEnv):
        if kwargs:
            raise TypeError(
                f"keyword arguments {sorted(kwargs)} are for an environment id; "
                "an env instance is already built"
            )
        return env
    cls = vector_env_class(env)
    steps = gymnasium.spec(env).max_episode_steps
    steps = steps if max_episode_steps is None else max_episode_steps
    return cls(
        num_envs,
        max_episode_steps=steps,
        device=device,
        dtype=dtype,
        return_tensors=True,
        **kwargs,
    )


class TorchRLEnv(EnvBase):
    """A torchcbf environment as a batched TorchRL environment (see the module docstring).

    Args:
        env: a registered id (``"torchcbf/UnicycleEllipses-v0"``,
            ``"torchcbf/ReachAvoid-v0"``) or a built :class:`~torchcbf.envs.TorchVectorEnv`
            (then ``num_envs``, ``device``, ``dtype``, ``max_episode_steps`` are its own).
        num_envs: the batch size N.
        device, dtype: where the batch lives.
        max_episode_steps: truncation (default: the registration's).
        seed: the seed of the first reset (default: a fresh random one).
        **env_kwargs: the scenario's options (``sigma=``, ``start_noise=``, ...).

    Attributes ``dynamics``, ``barriers`` and ``dt`` are the scenario's; a
    :class:`~torchcbf.filters.SafetyFilter` on ``dynamics`` and ``barriers`` is what
    :class:`~torchcbf.envs.filter_transform.SafetyFilterTransform` expects.
    """

    def __init__(
        self,
        env: str | TorchVectorEnv,
        num_envs: int = 1,
        *,
        device: str | torch.device = "cpu",
        dtype: torch.dtype = torch.float32,
        max_episode_steps: int | None = None,
        seed: int | None = None,
        **env_kwargs: Any,
    ) -> None:
        vec = _vector_env(env, num_envs, device, dtype, max_episode_steps, env_kwargs)
        vec.return_tensors = True
        super().__init__(device=vec.device, batch_size=torch.Size([vec.num_envs]))
        self.vector_env = vec
        self._pending_seed: Tensor | None = None
        self._make_specs()
        self._set_seed(int(secrets.randbelow(_SEED_RANGE)) if seed is None else seed)

    # -- the scenario ----------------------------------------------------------------------

    @property
    def dynamics(self) -> ControlAffine:
        """The plant (:class:`~torchcbf.dynamics.ControlAffine`)."""
        return self.vector_env.dynamics

    @property
    def barriers(self) -> nn.ModuleList:
        """The obstacles as barriers on the state (``h >= 0`` safe)."""
        return self.vector_env.barriers

    @property
    def dt(self) -> float:
        """Time step in seconds."""
        return self.vector_env.dt

    @property
    def num_envs(self) -> int:
        """The batch size N."""
        return self.vector_env.num_envs

    def state_from_observation(self, observation: Tensor) -> Tensor:
        """The dynamics' state ``[..., n]`` of observations ``[..., d]``."""
        return self.vector_env.state_from_observation(observation)

    # -- TorchRL's API ---------------------------------------------------------------------

    def _make_specs(self) -> None:
        vec = self.vector_env
        n, dtype, device = vec.num_envs, vec.dtype, vec.device
        d = vec.single_observation_space.shape[0]
        m = vec.single_action_space.shape[0]
        with torch.no_grad():
            k = vec._info()["h"].shape[-1]
        flag = {"n": 2, "shape": (n, 1), "dtype": torch.bool, "device": device}
        self.observation_spec = Composite(
            observation=Unbounded(shape=(n, d), dtype=dtype, device=device),
            h=Unbounded(shape=(n, k), dtype=dtype, device=device),
            cost=Unbounded(shape=(n, 1), dtype=dtype, device=device),
            success=Categorical(**flag),
            shape=(n,),
            device=device,
        )
        self.action_spec = Bounded(
            low=vec._u_low.expand(n, m),
            high=vec._u_high.expand(n, m),
            shape=(n, m),
            dtype=dtype,
            device=device,
        )
        self.reward_spec = Unbounded(shape=(n, 1), dtype=dtype, device=device)
        self.done_spec = Composite(
            done=Categorical(**flag),
            terminated=Categorical(**flag),
            truncated=Categorical(**flag),
            shape=(n,),
            device=device,
        )

    def _set_seed(self, seed: int | None) -> None:
        if seed is None:
            seed = int(secrets.randbelow(_SEED_RANGE))
        if isinstance(seed, bool) or not isinstance(seed, int):
            raise TypeError(f"seed must be an int or None, got {type(seed).__name__}")
        vec = self.vector_env
        self._pending_seed = seed_rows(seed, vec.num_envs, vec.device, per="sub-environment")

    def _reset(self, tensordict: TensorDictBase | None = None, **kwargs: Any) -> TensorDictBase:
        vec = self.vector_env
        mask = None if tensordict is None else tensordict.get("_reset", None)
        if mask is not None:
            rows = mask.reshape(vec.num_envs, -1).any(-1).to(vec.device)
        else:
            rows = torch.ones(vec.num_envs, dtype=torch.bool, device=vec.device)
        seeds = None
        if self._pending_seed is not None and (mask is None or not vec._started):
            seeds, self._pending_seed = self._pending_seed, None
            rows = torch.ones_like(rows)
        elif not vec._started:
            raise RuntimeError("the first reset must reset every sub-environment")
        with torch.no_grad():
            vec._reset_rows(rows, seeds)
            vec._started = vec._seeded = True
            info = vec._info()
            obs = vec._observe()
        false = torch.zeros(vec.num_envs, 1, dtype=torch.bool, device=vec.device)
        return self._output(obs, info, None, false, false)

    def _step(self, tensordict: TensorDictBase) -> TensorDictBase:
        vec = self.vector_env
        with torch.no_grad():
            u = self._action(tensordict.get("action"))
            z = vec._draw(vec._steps + 1, vec.noise_dim) if vec.noise_dim else None
            reward, terminated, info = vec._advance(u, z)
            vec._steps = vec._steps + 1
            if vec.max_episode_steps is None:
                truncated = torch.zeros_like(terminated)
            else:
                truncated = vec._steps >= vec.max_episode_steps
            obs = vec._observe()
        terminated, truncated = terminated[:, None], truncated[:, None]
        return self._output(obs, info, reward[:, None], terminated, truncated)

    def _action(self, action: Tensor) -> Tensor:
        """The action ``[N, m]`` on the env's device and dtype, clipped to the bounds.

        A non-finite action raises ValueError on the CPU; on an accelerator the check is
        asynchronous (``torch._assert_async``: a failure surfaces at a later synchronisation)
        so that a step never waits for the device.
        """
        vec = self.vector_env
        if not isinstance(action, Tensor):
            raise TypeError(f"action must be a tensor, got {type(action).__name__}")
        shape = (vec.num_envs, vec.single_action_space.shape[0])
        if tuple(action.shape) != shape:
            raise ValueError(f"action must have shape {shape}, got {tuple(action.shape)}")
        u = action.to(device=vec.device, dtype=vec.dtype)
        check_finite_action("action", u)
        return torch.minimum(torch.maximum(u, vec._u_low), vec._u_high)

    def _output(
        self,
        obs: Tensor,
        info: dict[str, Tensor],
        reward: Tensor | None,
        terminated: Tensor,
        truncated: Tensor,
    ) -> TensorDictBase:
        collision = info["collision"][:, None]
        out = {
            "observation": obs,
            "h": info["h"],
            "cost": collision.to(obs.dtype),
            "success": info["success"][:, None],
            "done": terminated | truncated,
            "terminated": terminated,
            "truncated": truncated,
        }
        if reward is not None:
            out["reward"] = reward
        return TensorDict(out, batch_size=self.batch_size, device=self.device)
