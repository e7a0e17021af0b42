"""Gymnasium environments of the reference scenarios and a safety-filter wrapper (extra
``gym``: ``pip install "torchcbf[gym]"``).

Importing this package registers:

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

ENV_IDS = ("torchcbf/ReachAvoid-v0", "torchcbf/UnicycleEllipses-v0")


def _register() -> None:
    entries = {
        "torchcbf/ReachAvoid-v0": ("reach_avoid", "ReachAvoid", 100),
        "torchcbf/UnicycleEllipses-v0": ("unicycle_ellipses", "UnicycleEllipses", 500),
    }
    for env_id, (module, name, steps) in entries.items():
        if env_id in gymnasium.registry:
            continue
        gymnasium.register(
            id=env_id,
            entry_point=f"torchcbf.envs.{module}:{name}Env",
            vector_entry_point=f"torchcbf.envs.{module}:{name}VectorEnv",
            max_episode_steps=steps,
        )


_register()

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
]
