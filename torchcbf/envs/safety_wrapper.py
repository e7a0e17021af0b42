"""``SafetyFilterWrapper``: every action of an environment passes a safety filter first.

The wrapper reads the state from the last observation (``state_fn``; torchcbf's own envs
provide it), calls the filter on (state, action), and steps the environment with the
filtered control. ``info`` gains ``filter_status`` (:class:`~torchcbf.filters.FilterStatus`
codes), ``filter_h`` (the barrier values the filter saw) and ``action_nominal`` (the action
before the filter). On a vector env the whole batch is filtered in one call; a
sub-environment that autoresets at this step ignores its (filtered) action, as Gymnasium's
next-step autoreset defines.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

import gymnasium
import numpy as np
import torch
from gymnasium.vector import VectorEnv, VectorWrapper
from torch import Tensor, nn

from torchcbf._checks import check_finite_action, placement

StateFn = Callable[[Any], Any]


def _state_fn(env: Any, state_fn: StateFn | None) -> StateFn:
    if state_fn is not None:
        if not callable(state_fn):
            raise TypeError(f"state_fn must be callable, got {type(state_fn).__name__}")
        return state_fn
    own = getattr(env.unwrapped, "state_from_observation", None)
    if own is None:
        raise TypeError(
            f"state_fn is needed: {type(env.unwrapped).__name__} has no "
            "state_from_observation; pass state_fn=<function from observation to state>"
        )
    return own


class _Filtering:
    """What the single and the vector wrapper share: state, filter call, info."""

    def _setup(
        self,
        env: Any,
        safety_filter: nn.Module,
        state_fn: StateFn | None,
        time_fn: Callable[[Any], Any] | None,
        device: str | torch.device | None,
        dtype: torch.dtype | None,
    ) -> None:
        if not callable(safety_filter):
            raise TypeError(
                f"safety_filter must be a SafetyFilter module, got {type(safety_filter).__name__}"
            )
        if time_fn is not None and not callable(time_fn):
            raise TypeError(f"time_fn must be callable, got {type(time_fn).__name__}")
        self.safety_filter = safety_filter
        self.state_fn = _state_fn(env, state_fn)
        self.time_fn = time_fn
        own_device, own_dtype = placement(safety_filter)
        self.filter_device = torch.device(device) if device is not None else own_device
        self.filter_dtype = dtype if dtype is not None else own_dtype
        self._last_obs: Any = None

    def _filter(self, action: Any) -> tuple[Any, dict[str, Any]]:
        if self._last_obs is None:
            raise RuntimeError("call reset() before step()")
        shape = getattr(self.action_space, "shape", None)  # [m], or [N, m] for a vector env
        given = action if isinstance(action, Tensor) else np.asarray(action)
        if shape is not None and tuple(given.shape) != tuple(shape):
            # as the environment takes it: one env reshapes an action of its size, a vector
            # env refuses any other shape
            count = given.numel() if isinstance(given, Tensor) else given.size
            if isinstance(self.env, VectorEnv) or count != math.prod(shape):
                raise ValueError(f"action must have shape {tuple(shape)}, got {tuple(given.shape)}")
            action = given.reshape(shape)
        kw = {"device": self.filter_device, "dtype": self.filter_dtype}
        x = torch.as_tensor(self.state_fn(self._last_obs), **kw)
        u_nom = torch.as_tensor(np.asarray(action) if not isinstance(action, Tensor) else action)
        # a NaN would reach the filter as a status, and the env as the filter's stand-in
        check_finite_action("action", u_nom)
        u_nom = u_nom.to(**kw)
        t = None if self.time_fn is None else torch.as_tensor(self.time_fn(self._last_obs), **kw)
        with torch.no_grad():
            out = self.safety_filter(x, u_nom, t)
        if isinstance(action, Tensor):
            dtype = action.dtype if action.is_floating_point() else out.u.dtype
            u: Any = out.u.to(device=action.device, dtype=dtype)
            extra = {"filter_status": out.status, "filter_h": out.h, "action_nominal": action}
        else:
            given = np.asarray(action).dtype
            # the filtered control is real: an integer action would truncate it
            u = out.u.cpu().numpy()
            u = u.astype(given if np.issubdtype(given, np.floating) else u.dtype, copy=False)
            extra = {
                "filter_status": out.status.cpu().numpy(),
                "filter_h": out.h.cpu().numpy(),
                "action_nominal": np.asarray(action),
            }
        return u, extra

    def reset(self, **kwargs: Any) -> tuple[Any, dict[str, Any]]:
        """Reset the environment(s) and remember the observation the filter reads."""
        obs, info = self.env.reset(**kwargs)
        self._last_obs = obs
        return obs, info


class SafetyFilterWrapper(_Filtering, gymnasium.Wrapper, gymnasium.utils.RecordConstructorArgs):
    """Filter every action of ``env`` through ``safety_filter`` (a
    :class:`~torchcbf.filters.SafetyFilter` or a module with its call signature).

    Given a :class:`gymnasium.vector.VectorEnv`, returns a :class:`VectorSafetyFilterWrapper`
    (the batch filtered in one call).

    Args:
        env: the environment; its actions are the filter's controls ``u [m]``.
        safety_filter: ``(x [..., n], u_nom [..., m], t) -> FilterOutput``.
        state_fn: observation -> state ``[n]`` (``[N, n]`` for a vector env); default: the
            unwrapped env's ``state_from_observation`` (torchcbf's envs have one).
        time_fn: observation -> time (s) for time-varying barriers; default: ``t = 0``.
        device, dtype: where the filter runs (default: those of its parameters/buffers).

    ``info`` gains ``filter_status`` (an int code; a tensor for a tensor action),
    ``filter_h`` (``[k]`` barrier values at the state the filter saw) and
    ``action_nominal``. An action of the space's size in another shape is reshaped, as the
    env reshapes it. A non-finite action is refused
    (``ValueError``) as the env alone refuses it; the env steps the filter's control in the
    action's dtype where that is floating (else the filter's: an integer action would
    truncate it).
    """

    def __new__(cls, env: Any, *args: Any, **kwargs: Any) -> Any:
        if isinstance(env, VectorEnv):
            return VectorSafetyFilterWrapper(env, *args, **kwargs)
        return super().__new__(cls)

    def __init__(
        self,
        env: gymnasium.Env,
        safety_filter: nn.Module,
        *,
        state_fn: StateFn | None = None,
        time_fn: Callable[[Any], Any] | None = None,
        device: str | torch.device | None = None,
        dtype: torch.dtype | None = None,
    ) -> None:
        if not isinstance(env, gymnasium.Env):
            raise TypeError(f"env must be a gymnasium Env or VectorEnv, got {type(env).__name__}")
        # the env's spec records the wrapper (so env.spec.make() builds it again), holding
        # the same filter and functions rather than copies of them
        gymnasium.utils.RecordConstructorArgs.__init__(
            self, _disable_deepcopy=True, safety_filter=safety_filter, state_fn=state_fn,
            time_fn=time_fn, device=device, dtype=dtype,
        )  # fmt: skip
        gymnasium.Wrapper.__init__(self, env)
        self._setup(env, safety_filter, state_fn, time_fn, device, dtype)

    def step(self, action: Any) -> tuple[Any, Any, bool, bool, dict[str, Any]]:
        """Filter ``action``, step the environment with the result."""
        u, extra = self._filter(action)
        if not isinstance(action, Tensor):
            extra["filter_status"] = int(extra["filter_status"])
        obs, reward, terminated, truncated, info = self.env.step(u)
        self._last_obs = obs
        return obs, reward, terminated, truncated, {**info, **extra}


class VectorSafetyFilterWrapper(_Filtering, VectorWrapper):
    """:class:`SafetyFilterWrapper` for a vector env: actions ``[N, m]`` filtered in one
    batched call; ``info["filter_status"]`` is ``[N]``, ``info["filter_h"]`` ``[N, k]``."""

    def __init__(
        self,
        env: VectorEnv,
        safety_filter: nn.Module,
        *,
        state_fn: StateFn | None = None,
        time_fn: Callable[[Any], Any] | None = None,
        device: str | torch.device | None = None,
        dtype: torch.dtype | None = None,
    ) -> None:
        if not isinstance(env, VectorEnv):
            raise TypeError(f"env must be a gymnasium VectorEnv, got {type(env).__name__}")
        VectorWrapper.__init__(self, env)
        self._setup(env, safety_filter, state_fn, time_fn, device, dtype)

    def step(self, actions: Any) -> tuple[Any, Any, Any, Any, dict[str, Any]]:
        """Filter ``actions [N, m]`` in one call, step the environments with the result."""
        u, extra = self._filter(actions)
        obs, reward, terminated, truncated, info = self.env.step(u)
        self._last_obs = obs
        return obs, reward, terminated, truncated, {**info, **extra}
