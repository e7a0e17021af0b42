"""``SafetyFilterTransform``: a TorchRL transform that passes every action through a safety
filter before the environment steps (a shield), in one batched filter call.

The action the policy wrote stays in the root of the TensorDict (it is what the policy's
log-probability refers to); the environment steps with the filtered control, and the step's
``"next"`` TensorDict records what the filter did:

- ``"action_nominal"`` ``[*B, m]``: the action before the filter;
- ``"action_filtered"`` ``[*B, m]``: the control the environment stepped with;
- ``"filter_status"`` ``[*B]`` (int64): :class:`~torchcbf.filters.FilterStatus` codes;
- ``"filter_h"`` ``[*B, k]``: the barrier values the filter saw (at the state before the
  step);
- ``"filter_intervention"`` ``[*B, 1]`` (bool): the filter changed the action by more than
  ``intervention_tol`` (infinity norm, control units).

A reset fills them with the reset state's barrier values, zero actions, status 0 and no
intervention. The transform works on any TorchRL environment whose state the filter can
read from the observation: torchcbf's :class:`~torchcbf.envs.torchrl.TorchRLEnv` and
TorchRL's Gym wrappers of torchcbf's Gymnasium environments (with ``state_fn`` where the
observation is not the state).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import torch
from tensordict import TensorDictBase
from tensordict.utils import NestedKey
from torch import Tensor, nn
from torchrl.data import Categorical, Composite, TensorSpec, Unbounded
from torchrl.envs import Transform

from torchcbf._checks import check_finite_action, placement

__all__ = ["FILTER_KEYS", "SafetyFilterTransform", "barrier_values"]

#: the keys the transform writes into ``"next"``
FILTER_KEYS = (
    "action_nominal",
    "action_filtered",
    "filter_status",
    "filter_h",
    "filter_intervention",
)

StateFn = Callable[[Tensor], Tensor]


def barrier_values(barriers: nn.ModuleList, x: Tensor, t: Tensor | None = None) -> Tensor:
    """All barriers' outputs at ``x [..., n]`` concatenated, ``[..., k]`` (the order of
    :attr:`~torchcbf.filters.FilterOutput.h`)."""
    values = []
    for barrier in barriers:
        h = barrier(x) if t is None else barrier(x, t)
        values.append(h.unsqueeze(-1) if h.dim() == x.dim() - 1 else h)
    return torch.cat(values, dim=-1)


class SafetyFilterTransform(Transform):
    """Filter the action of every step through ``safety_filter`` (see the module docstring).

    Args:
        safety_filter: a :class:`~torchcbf.filters.SafetyFilter` (or a module with its call
            ``(x [..., n], u_nom [..., m], t) -> FilterOutput``) on the environment's plant.
        action_key: the action entry (default ``"action"``).
        observation_key: the entry the state is read from (default ``"observation"``).
        state_fn: observation ``[*B, d]`` -> state ``[*B, n]`` (a tensor function). Default:
            the environment's ``state_from_observation`` when it has one (torchcbf's
            :class:`~torchcbf.envs.torchrl.TorchRLEnv`), else the observation itself, which
            must then have the plant's ``state_dim`` entries.
        time_key: an entry holding the time (s) for time-varying barriers (default: none,
            ``t = 0``).
        intervention_tol: the change of the action (infinity norm) that counts as an
            intervention.
    """

    def __init__(
        self,
        safety_filter: nn.Module,
        *,
        action_key: NestedKey = "action",
        observation_key: NestedKey = "observation",
        state_fn: StateFn | None = None,
        time_key: NestedKey | None = None,
        intervention_tol: float = 1e-4,
    ) -> None:
        if not isinstance(safety_filter, nn.Module):
            raise TypeError(
                f"safety_filter must be a SafetyFilter module, got {type(safety_filter).__name__}"
            )
        if state_fn is not None and not callable(state_fn):
            raise TypeError(f"state_fn must be callable, got {type(state_fn).__name__}")
        if not (isinstance(intervention_tol, (int, float)) and intervention_tol >= 0):
            raise ValueError(f"intervention_tol must be a number >= 0, got {intervention_tol!r}")
        super().__init__(in_keys=[], out_keys=list(FILTER_KEYS))
        self.safety_filter = safety_filter
        self.action_key = action_key
        self.observation_key = observation_key
        self.state_fn = state_fn
        self.time_key = time_key
        self.intervention_tol = float(intervention_tol)

    # -- reading the state -----------------------------------------------------------------

    def _state(self, tensordict: TensorDictBase) -> tuple[Tensor, Tensor | None]:
        device, dtype = placement(self.safety_filter)
        obs = tensordict.get(self.observation_key)
        fn = self.state_fn
        if fn is None:
            parent = self.parent
            base = getattr(parent, "base_env", None) if parent is not None else None
            fn = getattr(base, "state_from_observation", None)
        if fn is not None:
            x = fn(obs)
        else:
            n = self.safety_filter.dynamics.state_dim
            if obs.shape[-1] != n:
                raise ValueError(
                    f"the observation {self.observation_key!r} has {obs.shape[-1]} entries, "
                    f"the plant's state {n}: pass state_fn=<observation -> state>"
                )
            x = obs
        t = None
        if self.time_key is not None:
            t = tensordict.get(self.time_key).to(device=device, dtype=dtype)
            t = t.reshape(x.shape[:-1])
        return x.to(device=device, dtype=dtype), t

    # -- the step ----------------------------------------------------------------------------

    def _inv_call(self, tensordict: TensorDictBase) -> TensorDictBase:
        u_nom = tensordict.get(self.action_key)
        check_finite_action("action", u_nom)  # else the env steps the filter's stand-in
        x, t = self._state(tensordict)
        with torch.no_grad():
            out = self.safety_filter(x, u_nom.to(x), t)
        dtype = u_nom.dtype if u_nom.is_floating_point() else out.u.dtype
        u = out.u.to(device=u_nom.device, dtype=dtype)
        change = (u - u_nom).abs().amax(-1, keepdim=True)
        tensordict.set(self.action_key, u)
        record = {
            "action_nominal": u_nom,
            "action_filtered": u,
            "filter_status": out.status,
            "filter_h": out.h.to(u_nom.dtype),
            "filter_intervention": change > self.intervention_tol,
        }
        for key, value in record.items():
            tensordict.set(("_safety_filter", key), value)
        return tensordict

    def _step(self, tensordict: TensorDictBase, next_tensordict: TensorDictBase) -> TensorDictBase:
        record = tensordict.get("_safety_filter")
        for key in FILTER_KEYS:
            next_tensordict.set(key, record.get(key))
        return next_tensordict

    def _reset(
        self, tensordict: TensorDictBase, tensordict_reset: TensorDictBase
    ) -> TensorDictBase:
        x, t = self._state(tensordict_reset)
        spec = self.parent.full_action_spec[self.action_key]
        zeros = spec.zero()
        with torch.no_grad():
            h = barrier_values(self.safety_filter.barriers, x, t).to(zeros.dtype)
        batch = x.shape[:-1]
        tensordict_reset.set("action_nominal", zeros)
        tensordict_reset.set("action_filtered", zeros.clone())
        tensordict_reset.set(
            "filter_status", torch.zeros(batch, dtype=torch.int64, device=zeros.device)
        )
        tensordict_reset.set("filter_h", h.to(zeros.device))
        tensordict_reset.set(
            "filter_intervention", torch.zeros(*batch, 1, dtype=torch.bool, device=zeros.device)
        )
        return tensordict_reset

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        """Outside an environment (a replay buffer, a module chain) the transform does
        nothing: it acts on the step."""
        return tensordict

    # -- specs -----------------------------------------------------------------------------

    def transform_observation_spec(self, observation_spec: TensorSpec) -> TensorSpec:
        """Add the five recorded entries (see the module docstring)."""
        action = self.parent.full_action_spec[self.action_key]
        batch = observation_spec.shape
        device, dtype = action.device, action.dtype
        k = self._num_barrier_values()
        spec: dict[str, Any] = {
            "action_nominal": Unbounded(shape=action.shape, dtype=dtype, device=device),
            "action_filtered": Unbounded(shape=action.shape, dtype=dtype, device=device),
            "filter_status": Unbounded(shape=batch, dtype=torch.int64, device=device),
            "filter_h": Unbounded(shape=(*batch, k), dtype=dtype, device=device),
            "filter_intervention": Categorical(
                2, shape=(*batch, 1), dtype=torch.bool, device=device
            ),
        }
        if not isinstance(observation_spec, Composite):
            raise TypeError("SafetyFilterTransform needs a Composite observation spec")
        for key, value in spec.items():
            observation_spec[key] = value
        return observation_spec

    def _num_barrier_values(self) -> int:
        device, dtype = placement(self.safety_filter)
        n = self.safety_filter.dynamics.state_dim
        x = torch.zeros(n, device=device, dtype=dtype)
        with torch.no_grad():
            return int(barrier_values(self.safety_filter.barriers, x).shape[-1])
