"""SafetyFilterWrapper on torchcbf's envs (single and vector) and on a user's own env."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest
import torch

gym = pytest.importorskip("gymnasium")
envs = pytest.importorskip("torchcbf.envs")

from torchcbf.barriers import Ball, rectify  # noqa: E402
from torchcbf.dynamics import SingleIntegrator  # noqa: E402
from torchcbf.filters import FilterStatus, SafetyFilter  # noqa: E402
from torchcbf.scenarios import mppi_cbf  # noqa: E402

GOAL1 = np.array([4.0, 4.0], dtype=np.float32)
KW = {"vectorization_mode": "vector_entry_point", "start_noise": 0.3, "max_episode_steps": 40}


def _toward_goal1(obs: np.ndarray) -> np.ndarray:
    """A proportional policy at g1 = (4, 4): its straight path crosses the obstacle."""
    return np.clip(2.0 * (GOAL1 - obs[..., :2]), -5.0, 5.0).astype(np.float32)


def _reach_avoid_filter(env: Any) -> SafetyFilter:
    return SafetyFilter(env.unwrapped.dynamics, barriers=list(env.unwrapped.barriers), alpha=2.0)


def _run(env: Any, steps: int, seed: int = 0) -> tuple[np.ndarray, list[dict], list[np.ndarray]]:
    obs, _ = env.reset(seed=seed)
    collided = np.zeros(env.num_envs, dtype=bool)
    infos, observations = [], [obs]
    for _ in range(steps):
        obs, _, _, _, info = env.step(_toward_goal1(obs))
        collided |= info["collision"]
        infos.append(info)
        observations.append(obs)
    return collided, infos, observations


def test_vector_wrapper_keeps_every_robot_out_of_the_obstacle() -> None:
    n = 8
    plain = gym.make_vec("torchcbf/ReachAvoid-v0", num_envs=n, **KW)
    inner = gym.make_vec("torchcbf/ReachAvoid-v0", num_envs=n, **KW)
    safe = envs.SafetyFilterWrapper(inner, _reach_avoid_filter(inner))
    assert isinstance(safe, envs.VectorSafetyFilterWrapper)
    collided_plain, _, _ = _run(plain, 30)
    collided_safe, infos, observations = _run(safe, 30)
    assert collided_plain.sum() >= n // 2  # the policy alone drives into the obstacle
    assert not collided_safe.any()
    info = infos[0]
    assert info["filter_status"].shape == (n,) and info["filter_h"].shape == (n, 1)
    assert set(np.unique(np.concatenate([i["filter_status"] for i in infos]))) <= {
        int(FilterStatus.SOLVED)
    }
    # filter_h is the barrier at the state the filter saw: the previous observation
    p = observations[5][:, :2]
    np.testing.assert_allclose(
        infos[5]["filter_h"][:, 0], ((p - [3.0, 3.0]) ** 2).sum(-1) - 0.36, atol=1e-4
    )
    np.testing.assert_allclose(infos[5]["action_nominal"], _toward_goal1(observations[5]))


def test_vector_wrapper_equals_single_wrappers_in_a_loop() -> None:
    """One batched filter call per step against a SyncVectorEnv of single wrapped envs."""
    n = 4
    single_filter = _reach_avoid_filter(gym.make("torchcbf/ReachAvoid-v0"))
    looped = gym.make_vec(
        "torchcbf/ReachAvoid-v0", num_envs=n, vectorization_mode="sync", start_noise=0.3,
        max_episode_steps=40, wrappers=[lambda e: envs.SafetyFilterWrapper(e, single_filter)],
    )  # fmt: skip
    inner = gym.make_vec("torchcbf/ReachAvoid-v0", num_envs=n, **KW)
    batched = envs.SafetyFilterWrapper(inner, _reach_avoid_filter(inner))
    _, infos_a, obs_a = _run(batched, 45, seed=4)
    _, infos_b, obs_b = _run(looped, 45, seed=4)
    for k, (a, b) in enumerate(zip(obs_a, obs_b, strict=True)):
        np.testing.assert_allclose(a, b, atol=1e-4, err_msg=f"step {k}")
    compared = 0
    for k, (a, b) in enumerate(zip(infos_a, infos_b, strict=True)):
        # SyncVectorEnv reports a reset's info for a row that autoresets (no filter keys)
        rows = b.get("_filter_status", np.zeros(n, dtype=bool))
        if not rows.any():
            continue
        np.testing.assert_array_equal(
            a["filter_status"][rows], b["filter_status"][rows], err_msg=f"step {k}"
        )
        np.testing.assert_allclose(
            a["filter_h"][rows], b["filter_h"][rows], atol=1e-4, err_msg=f"step {k}"
        )
        compared += int(rows.sum())
    assert compared >= 40 * n


def test_single_wrapper_reports_status_and_h() -> None:
    env = gym.make("torchcbf/UnicycleEllipses-v0")
    scbf = mppi_cbf("scbf", num_seeds=1).safety_filter
    safe = envs.SafetyFilterWrapper(env, scbf)
    assert isinstance(safe, envs.SafetyFilterWrapper)
    safe.reset(seed=0)
    _, _, _, _, info = safe.step(np.array([5.0, 0.0], dtype=np.float32))
    assert isinstance(info["filter_status"], int)
    assert info["filter_h"].shape == (5,) and np.isfinite(info["filter_h"]).all()
    assert "collision" in info and "h" in info  # the env's own info is kept


class _PointEnv(gym.Env):
    """A user's env, in NumPy: a point p' = u, observation (x, y, |p|)."""

    def __init__(self) -> None:
        self.observation_space = gym.spaces.Box(-np.inf, np.inf, shape=(3,), dtype=np.float64)
        self.action_space = gym.spaces.Box(-1.0, 1.0, shape=(2,), dtype=np.float64)
        self.p = np.zeros(2)

    def _obs(self) -> np.ndarray:
        return np.array([*self.p, np.linalg.norm(self.p)])

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        self.p = np.zeros(2)
        return self._obs(), {}

    def step(self, action):
        self.p = self.p + 0.05 * np.clip(action, -1, 1)
        return self._obs(), 0.0, False, False, {}


def test_a_users_env_works_given_a_state_function() -> None:
    robot = SingleIntegrator(2, u_min=-1.0, u_max=1.0).double()
    wall = Ball([1.0, 0.0], 0.5).double()
    filt = SafetyFilter(robot, barriers=[wall], alpha=1.0)
    with pytest.raises(TypeError, match="state_fn"):
        envs.SafetyFilterWrapper(_PointEnv(), filt)
    env = envs.SafetyFilterWrapper(_PointEnv(), filt, state_fn=lambda obs: obs[:2])
    obs, _ = env.reset(seed=0)
    for _ in range(60):
        obs, _, _, _, info = env.step(np.array([1.0, 0.0]))
    assert float(wall(torch.as_tensor(obs[:2]))) >= -1e-9  # stopped before the ball
    assert obs[0] > 0.4  # but drove up to it
    assert info["filter_h"].shape == (1,)
    with pytest.raises(TypeError, match="safety_filter"):
        envs.SafetyFilterWrapper(_PointEnv(), 3.0, state_fn=lambda obs: obs[:2])
    with pytest.raises(TypeError, match="env"):
        envs.SafetyFilterWrapper("not an env", filt)


def test_a_wrapped_env_passes_gymnasiums_checker_and_is_made_again_from_its_spec() -> None:
    """The wrapper records its arguments in the env's spec (holding the same filter), so
    Gymnasium's check_env passes and ``env.spec.make()`` builds the wrapped env again."""
    import warnings

    from gymnasium.utils.env_checker import check_env

    env = gym.make("torchcbf/UnicycleEllipses-v0")
    dyn = env.unwrapped.dynamics
    barriers = [rectify(b, dyn, form="exponential", gains=[5.0]) for b in env.unwrapped.barriers]
    filt = SafetyFilter(dyn, barriers, alpha=5.0)
    safe = envs.SafetyFilterWrapper(env, filt)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # Gymnasium's advice to check the unwrapped env
        check_env(safe, skip_render_check=True)
    again = safe.spec.make()
    assert isinstance(again, envs.SafetyFilterWrapper) and again.safety_filter is filt


@pytest.mark.parametrize("tensor", [False, True])
def test_an_integer_action_steps_the_filters_real_control(tensor) -> None:
    """The filtered control is real: cast to an integer action's dtype it was truncated
    (2.544 applied as 2)."""
    runs = []
    for action in (np.array([5.0, 5.0]), np.array([5, 5])):
        base = gym.make("torchcbf/ReachAvoid-v0")
        env = envs.SafetyFilterWrapper(base, _reach_avoid_filter(base))
        env.reset(seed=0)
        for _ in range(4):
            env.step(np.array([5.0, 5.0]))
        given = torch.as_tensor(action) if tensor else action
        obs, *_, info = env.step(given)
        runs.append((np.asarray(obs), info["filter_status"]))
    np.testing.assert_array_equal(runs[0][0], runs[1][0])


def test_a_non_finite_action_is_refused_behind_the_filter() -> None:
    base = gym.make("torchcbf/ReachAvoid-v0")
    env = envs.SafetyFilterWrapper(base, _reach_avoid_filter(base))
    env.reset(seed=0)
    with pytest.raises(ValueError, match="action must be finite"):
        env.step(np.array([np.nan, 1.0]))
    vec = gym.make_vec("torchcbf/ReachAvoid-v0", num_envs=2, **KW)
    wrapped = envs.SafetyFilterWrapper(vec, _reach_avoid_filter(vec))
    wrapped.reset(seed=0)
    with pytest.raises(ValueError, match="action must be finite"):
        wrapped.step(np.array([[0.0, 0.0], [np.inf, 0.0]]))


@pytest.mark.parametrize("tensor", [False, True])
def test_an_action_of_another_shape_is_taken_as_the_env_takes_it(tensor) -> None:
    """``[[ax, ay]]`` steps as ``[ax, ay]`` (the env reshapes it); a wrong size is named."""
    runs = []
    for action in (np.array([1.0, 0.0]), np.array([[1.0, 0.0]])):
        base = gym.make("torchcbf/ReachAvoid-v0")
        env = envs.SafetyFilterWrapper(base, _reach_avoid_filter(base))
        env.reset(seed=0)
        obs, *_, info = env.step(torch.as_tensor(action) if tensor else action)
        runs.append(np.asarray(obs))
        assert int(info["filter_status"]) == FilterStatus.SOLVED
    np.testing.assert_array_equal(runs[0], runs[1])
    with pytest.raises(ValueError, match=r"action must have shape \(2,\), got \(3,\)"):
        env.step(np.zeros(3))
    vec = gym.make_vec("torchcbf/ReachAvoid-v0", num_envs=2, **KW)
    wrapped = envs.SafetyFilterWrapper(vec, _reach_avoid_filter(vec))
    wrapped.reset(seed=0)
    with pytest.raises(ValueError, match=r"action must have shape \(2, 2\), got \(4,\)"):
        wrapped.step(np.zeros(4))
