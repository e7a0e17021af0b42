"""Gymnasium environments of the reference scenarios and a safety-filter wrapper (extra
``gym``: ``pip install "torchcbf[gym]"``).

Importing this package registers with Gymnasium the environment of every registered
scenario that declares one (:class:`torchcbf.scenarios.EnvEntry`; :func:`register_envs`
does it again after a user's scenario registers):

- ``torchcbf/ReachAvoid-v0``: scenario A (:mod:`torchcbf.envs.reach_avoid`);
- ``torchcbf/UnicycleEllipses-v0``: scenario B (:mod:`torchcbf.envs.unicycle_ellipses`).

``gymnasium.make(id)`` gives one environment, ``gymnasium.make_vec(id, num_envs=N,
vectorization_mode="vector_entry_point")`` a native vector env that steps all N as one
tensor batch (``device=`` places it), with Gymnasium's next-step autoreset. The unwrapped
envs expose ``dynamics`` and ``barriers``; :class:`SafetyFilterWrapper` filters every action
through a :class:`~torchcbf.filters.SafetyFilter`.
"""

from __future__ import annotations

try:
    import gymnasium
except ImportError as error:  # pragma: no cover - exercised without the extra
    raise ImportError(
        'torchcbf.envs needs Gymnasium >= 1.0: pip install "torchcbf[gym]"'
    ) from error

from torchcbf.envs.base import TorchEnv, TorchVectorEnv
from torchcbf.envs.reach_avoid import ReachAvoidEnv, ReachAvoidVectorEnv
from torchcbf.envs.safety_wrapper import SafetyFilterWrapper, VectorSafetyFilterWrapper
from torchcbf.envs.unicycle_ellipses import UnicycleEllipsesEnv, UnicycleEllipsesVectorEnv
from torchcbf.scenarios import scenarios


def register_envs() -> list[str]:
    """Register with Gymnasium the environment of every registered scenario that has one
    and is not registered yet; returns the ids registered now."""
    added = []
    for entry in scenarios().values():
        env = entry.env
        if env is None or env.id in gymnasium.registry:
            continue
        gymnasium.register(
            id=env.id,
            entry_point=env.entry_point,
            vector_entry_point=env.vector_entry_point,
            max_episode_steps=env.max_episode_steps,
        )
        added.append(env.id)
    return added


register_envs()
#: the ids of the reference scenarios' environments
ENV_IDS = tuple(e.env.id for e in scenarios().values() if e.env is not None)

__all__ = [
    "ENV_IDS",
    "ReachAvoidEnv",
    "ReachAvoidVectorEnv",
    "SafetyFilterWrapper",
    "TorchEnv",
    "TorchVectorEnv",
    "UnicycleEllipsesEnv",
    "UnicycleEllipsesVectorEnv",
    "VectorSafetyFilterWrapper",
    "register_envs",
]
