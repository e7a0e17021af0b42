"""Gymnasium environments of scenarios A and B: API checks, the native vector env against
Gymnasium's own SyncVectorEnv of single envs, autoreset, seeding and the dynamics."""

from __future__ import annotations

import math
import warnings

import numpy as np
import pytest
import torch

gym = pytest.importorskip("gymnasium")
envs = pytest.importorskip("torchcbf.envs")

from gymnasium.utils.env_checker import check_env  # noqa: E402
from gymnasium.vector import AutoresetMode  # noqa: E402

from torchcbf.barriers import Ball, Ellipse  # noqa: E402
from torchcbf.dynamics import AccelUnicycle, SingleIntegrator  # noqa: E402

IDS = envs.ENV_IDS


@pytest.mark.parametrize("env_id", IDS)
def test_check_env_passes(env_id: str) -> None:
    env = gym.make(env_id)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # Gymnasium's advice on unbounded/unnormalised boxes
        check_env(env.unwrapped)
    obs, _ = env.reset(seed=3)
    assert env.observation_space.contains(obs)


@pytest.mark.parametrize("env_id", IDS)
def test_unwrapped_exposes_dynamics_and_barriers(env_id: str) -> None:
    single = gym.make(env_id).unwrapped
    vector = gym.make_vec(env_id, num_envs=2, vectorization_mode="vector_entry_point")
    for env in (single, vector.unwrapped):
        assert env.barriers[0](torch.zeros(1, env.dynamics.state_dim)).shape[0] == 1
    expected = SingleIntegrator if "ReachAvoid" in env_id else AccelUnicycle
    assert isinstance(single.dynamics, expected)
    assert isinstance(single.barriers[0], Ball if "ReachAvoid" in env_id else Ellipse)
    assert vector.metadata["autoreset_mode"] == AutoresetMode.NEXT_STEP
    obs, _ = vector.reset(seed=0)
    n = single.dynamics.state_dim
    assert torch.equal(single.state_from_observation(obs[0]), torch.as_tensor(obs[0, :n]))


def _rollout(env, actions: np.ndarray, seed: int):
    obs, _ = env.reset(seed=seed)
    out = [(obs, None, None, None)]
    for a in actions:
        obs, reward, term, trunc, _ = env.step(a)
        out.append((obs, reward, term, trunc))
    return out


@pytest.mark.parametrize(
    ("env_id", "kwargs", "scale"),
    [
        ("torchcbf/ReachAvoid-v0", {"start_noise": 0.5, "max_episode_steps": 30}, 5.0),
        ("torchcbf/UnicycleEllipses-v0", {"start_noise": 0.2, "max_episode_steps": 25}, 5.0),
    ],
)
def test_vector_env_equals_sync_vector_env_of_single_envs(env_id, kwargs, scale) -> None:
    """The batched env against Gymnasium's SyncVectorEnv (a Python loop over single envs
    with Gymnasium's own next-step autoreset and time limit)."""
    n, steps = 5, 80
    native = gym.make_vec(env_id, num_envs=n, vectorization_mode="vector_entry_point", **kwargs)
    looped = gym.make_vec(env_id, num_envs=n, vectorization_mode="sync", **kwargs)
    rng = np.random.default_rng(0)
    m = native.single_action_space.shape[0]
    actions = (scale * rng.uniform(-1, 1, size=(steps, n, m))).astype(np.float32)
    actions[:, 0] = np.array([3.0, 3.0] if m == 2 else [5.0, 0.0], dtype=np.float32)
    a = _rollout(native, actions, seed=11)
    b = _rollout(looped, actions, seed=11)
    ends = 0
    for k, ((oa, ra, ta, ua), (ob, rb, tb, ub)) in enumerate(zip(a, b, strict=True)):
        np.testing.assert_allclose(oa, ob, rtol=0, atol=1e-5, err_msg=f"step {k}")
        if k:
            np.testing.assert_allclose(ra, rb, rtol=0, atol=1e-5, err_msg=f"step {k}")
            np.testing.assert_array_equal(ta, tb, err_msg=f"step {k}")
            np.testing.assert_array_equal(ua, ub, err_msg=f"step {k}")
            ends += int(ta.sum() + ua.sum())
    assert ends >= n  # episodes ended and were reset along the way


def test_next_step_autoreset() -> None:
    """A row that terminates is reset by the next step: its action is ignored, it returns
    the first observation, reward 0 and no flags; the other rows step as usual."""
    env = gym.make_vec(
        "torchcbf/ReachAvoid-v0", num_envs=2, vectorization_mode="vector_entry_point"
    )
    obs0, _ = env.reset(seed=0)
    toward_obstacle = np.array([[5.0, 5.0], [0.0, 1.0]], dtype=np.float32)
    steps = 0
    while steps < 20:
        obs, reward, term, trunc, info = env.step(toward_obstacle)
        steps += 1
        if term[0]:
            break
    assert term[0] and info["collision"][0] and not term[1]
    assert reward[0] < -5  # the collision penalty
    obs, reward, term, trunc, info = env.step(toward_obstacle)
    np.testing.assert_array_equal(obs[0], obs0[0])
    assert reward[0] == 0.0 and not term[0] and not trunc[0] and not info["collision"][0]
    assert obs[1, 2] == pytest.approx(0.1 * (steps + 1))  # row 1 went on: its time advanced
    obs, _, _, _, _ = env.step(np.array([[1.0, 0.0], [0.0, 0.0]], dtype=np.float32))
    np.testing.assert_allclose(obs[0, :3], [0.1, 0.0, 0.1], atol=1e-6)  # a fresh episode


def test_same_step_and_disabled_autoreset() -> None:
    """SAME_STEP: the step that ends a row returns the new episode's first observation, the
    ended one's in info['final_obs'], and the flags of the end; DISABLED leaves the row as
    it is until a masked reset. Both follow NEXT_STEP's trajectory until the end."""
    kw = {"num_envs": 2, "vectorization_mode": "vector_entry_point"}
    toward_obstacle = np.array([[5.0, 5.0], [0.0, 1.0]], dtype=np.float32)
    runs = {}
    for mode in ("NextStep", "SameStep", "Disabled"):
        env = gym.make_vec("torchcbf/ReachAvoid-v0", autoreset_mode=mode, **kw)
        assert env.metadata["autoreset_mode"] == AutoresetMode(mode)
        obs0, _ = env.reset(seed=0)
        steps = []
        for _ in range(20):
            steps.append(env.step(toward_obstacle))
            if steps[-1][2][0]:
                break
        runs[mode] = (env, obs0, steps)
    _, obs0, nxt = runs["NextStep"]
    _, _, same = runs["SameStep"]
    assert len(same) == len(nxt)
    obs, reward, term, _, info = same[-1]
    assert term[0] and reward[0] < -5 and info["_final_obs"][0] and not info["_final_obs"][1]
    np.testing.assert_array_equal(info["final_obs"][0], nxt[-1][0][0])  # the last state
    assert info["final_info"]["collision"][0]
    np.testing.assert_array_equal(obs[0], obs0[0])  # the new episode's first observation
    np.testing.assert_array_equal(obs[1], nxt[-1][0][1])
    env, _, disabled = runs["Disabled"]
    np.testing.assert_array_equal(disabled[-1][0], nxt[-1][0])
    obs, _ = env.reset(options={"reset_mask": np.array([True, False])})
    np.testing.assert_array_equal(obs[0], obs0[0])
    with pytest.raises(ValueError, match="autoreset_mode must be"):
        gym.make_vec("torchcbf/ReachAvoid-v0", autoreset_mode="sometimes", **kw)


def test_truncation_at_the_time_limit() -> None:
    env = gym.make_vec(
        "torchcbf/UnicycleEllipses-v0", num_envs=3, vectorization_mode="vector_entry_point",
        sigma=0.0, max_episode_steps=7,
    )  # fmt: skip
    env.reset(seed=0)
    zeros = np.zeros((3, 2), dtype=np.float32)
    for _ in range(6):
        _, _, term, trunc, _ = env.step(zeros)
        assert not trunc.any() and not term.any()
    _, _, term, trunc, _ = env.step(zeros)
    assert trunc.all() and not term.any()
    obs, reward, _, trunc, _ = env.step(zeros)
    assert not trunc.any() and (reward == 0).all()
    np.testing.assert_allclose(obs, np.tile([0, 0, 0, math.pi / 4], (3, 1)), atol=1e-6)


def test_reach_avoid_step_is_the_single_integrator_and_goals_count_in_their_windows() -> None:
    env = gym.make("torchcbf/ReachAvoid-v0").unwrapped
    obs, _ = env.reset(seed=0)
    obs, reward, *_ = env.step(np.array([4.0, -2.0]))
    np.testing.assert_allclose(obs, [0.4, -0.2, 0.1, 0, 0, 0], atol=1e-6)
    # progress toward g1 = (4, 4)
    assert reward == pytest.approx(math.hypot(4, 4) - math.hypot(3.6, 4.2), abs=1e-5)
    # to g1 around the obstacle: along y = 0 then up x = 4
    for _ in range(8):
        obs, reward, term, _, info = env.step(np.array([5.0, 0.0]))
    while obs[1] < 3.6:
        obs, reward, term, _, info = env.step(np.array([0.0, 5.0]))
    assert obs[3] == 1.0 and not term and info["h"][0] > 0  # g1 visited in [0, 3.5] s
    while obs[2] < 3.5 - 1e-6:  # a goal reached outside its window does not count
        obs, reward, term, _, info = env.step(np.array([0.0, 0.0]))
    assert not term and obs[4] == 0.0
    for _ in range(30):  # g2's window closes at 5 s without a visit
        obs, reward, term, _, info = env.step(np.array([0.0, 0.0]))
        if term:
            break
    assert term and not info["success"] and obs[2] == pytest.approx(5.1)


def test_unicycle_noise_is_sigma_sqrt_dt_standard_normal() -> None:
    """One step at rest with zero control: the increment is sigma sqrt(dt) z, z ~ N(0, I)."""
    n = 4096
    env = gym.make_vec(
        "torchcbf/UnicycleEllipses-v0", num_envs=n, vectorization_mode="vector_entry_point",
        dtype=torch.float64,
    )  # fmt: skip
    obs0, _ = env.reset(seed=123)
    obs, *_ = env.step(np.zeros((n, 2)))
    z = (obs - obs0) / (0.28 * math.sqrt(0.01))
    assert np.abs(z.mean(0)).max() < 0.06
    assert np.abs(z.std(0) - 1).max() < 0.05
    assert np.abs(np.corrcoef(z.T) - np.eye(4)).max() < 0.06


def test_seeding_is_reproducible_and_episodes_differ() -> None:
    env = gym.make("torchcbf/UnicycleEllipses-v0")
    u = np.array([1.0, 0.5], dtype=np.float32)

    def run(seed):
        env.reset(seed=seed)
        return np.stack([env.step(u)[0] for _ in range(5)])

    first = run(5)
    np.testing.assert_array_equal(first, run(5))
    assert not np.allclose(first, run(6))
    env.reset(seed=5)
    env.reset()  # the next episode of seed 5
    second_episode = np.stack([env.step(u)[0] for _ in range(5)])
    assert not np.allclose(first, second_episode)


@pytest.mark.parametrize("seed", [2**32, 2**32 + 7, -1])
def test_seeds_outside_32_bits_are_refused(seed) -> None:
    """The noise streams read 32 bits: seed ``s + 2^32`` drew seed ``s``'s episode."""
    env = gym.make("torchcbf/UnicycleEllipses-v0")
    with pytest.raises(ValueError, match="seed must lie in"):
        env.reset(seed=seed)
    vec = gym.make_vec(
        "torchcbf/UnicycleEllipses-v0", num_envs=2, vectorization_mode="vector_entry_point"
    )
    with pytest.raises(ValueError, match="seed must lie in"):
        vec.reset(seed=[3, seed])
    with pytest.raises(ValueError, match="seed must lie in"):
        vec.reset(seed=2**32 - 1)  # the second row would be 2^32
    vec.reset(seed=[3, 2**32 - 1])
    vec.reset(seed=2**32 - 2)
    # one seed per sub-environment as a list, a tensor or an array: the same episodes
    vec = gym.make_vec(
        "torchcbf/UnicycleEllipses-v0", num_envs=2, vectorization_mode="vector_entry_point",
        start_noise=0.3,
    )  # fmt: skip
    first = vec.reset(seed=[3, 9])[0]
    assert not np.array_equal(first, vec.reset(seed=[3, 10])[0])
    np.testing.assert_array_equal(vec.reset(seed=torch.tensor([3, 9]))[0], first)
    np.testing.assert_array_equal(vec.reset(seed=np.array([3, 9]))[0], first)
    with pytest.raises(TypeError, match="integers"):
        vec.reset(seed=np.array([3.0, 9.0]))


@pytest.mark.filterwarnings("ignore:.*not in the possible render_modes")
@pytest.mark.parametrize("env_id", IDS)
def test_render_mode_is_taken_and_a_mode_refused_by_name(env_id) -> None:
    """``gymnasium.make(id, render_mode=...)`` passes the keyword to the environment, which
    failed with a TypeError of an unexpected argument."""
    assert gym.make(env_id, render_mode=None).render_mode is None
    with pytest.raises(ValueError, match="render_mode='rgb_array'"):
        gym.make(env_id, render_mode="rgb_array")
    with pytest.raises(ValueError, match="render_mode='human'"):
        gym.make_vec(
            env_id, num_envs=2, vectorization_mode="vector_entry_point", render_mode="human"
        )


def test_return_tensors_and_float64_match_numpy() -> None:
    kw = {"num_envs": 3, "vectorization_mode": "vector_entry_point", "start_noise": 0.3}
    a = gym.make_vec("torchcbf/UnicycleEllipses-v0", **kw)
    b = gym.make_vec("torchcbf/UnicycleEllipses-v0", return_tensors=True, **kw)
    oa, _ = a.reset(seed=1)
    ob, _ = b.reset(seed=1)
    assert isinstance(ob, torch.Tensor) and ob.dtype == torch.float32
    act = np.full((3, 2), 0.7, dtype=np.float32)
    ra = a.step(act)
    rb = b.step(torch.as_tensor(act))
    np.testing.assert_array_equal(ra[0], rb[0].numpy())
    np.testing.assert_allclose(ra[1], rb[1].numpy(), rtol=1e-6)
    c = gym.make_vec("torchcbf/UnicycleEllipses-v0", dtype=torch.float64, **kw)
    assert c.single_observation_space.dtype == np.float64
    c.reset(seed=1)
    oc = c.step(act)[0]
    assert oc.dtype == np.float64 and c.observation_space.contains(oc)
    np.testing.assert_allclose(oc, ra[0], atol=1e-5)


def test_reset_mask_resets_only_those_rows() -> None:
    env = gym.make_vec(
        "torchcbf/ReachAvoid-v0", num_envs=3, vectorization_mode="vector_entry_point"
    )
    env.reset(seed=0)
    obs, *_ = env.step(np.ones((3, 2), dtype=np.float32))
    obs, _ = env.reset(options={"reset_mask": np.array([True, False, True])})
    np.testing.assert_allclose(obs[:, 0], [0.0, 0.1, 0.0], atol=1e-6)
    with pytest.raises(ValueError, match="reset_mask"):
        env.reset(options={"reset_mask": np.array([1, 0, 1])})


def test_bad_input_names_the_argument() -> None:
    with pytest.raises(ValueError, match="num_envs"):
        envs.ReachAvoidVectorEnv(0)
    with pytest.raises(ValueError, match="control_limit"):
        envs.UnicycleEllipsesVectorEnv(2, control_limit=(1.0, -1.0))
    with pytest.raises(ValueError, match="start_noise"):
        envs.ReachAvoidVectorEnv(2, start_noise=-1.0)
    with pytest.raises(TypeError, match="dtype"):
        envs.ReachAvoidVectorEnv(2, dtype=torch.int32)
    env = envs.ReachAvoidVectorEnv(2)
    with pytest.raises(RuntimeError, match="reset"):
        env.step(np.zeros((2, 2)))
    env.reset(seed=0)
    with pytest.raises(ValueError, match="actions"):
        env.step(np.zeros((3, 2)))
    with pytest.raises(ValueError, match="actions must be finite"):
        env.step(np.full((2, 2), np.nan))
    for bad in (float("nan"), float("inf")):
        with pytest.raises(ValueError, match="actions must be finite"):
            env.step(torch.tensor([[0.0, 0.0], [bad, 0.0]]))
    obs, *_ = env.step(torch.zeros(2, 2))  # the env is untouched by the refused steps
    assert np.isfinite(obs).all()
    with pytest.raises(ValueError, match="seed"):
        env.reset(seed=[1, 2, 3])
    with pytest.raises(TypeError, match="seed must be an int, one per sub-environment"):
        env.reset(seed=1.5)
    with pytest.raises(TypeError, match="control_limit must be two positive numbers"):
        envs.UnicycleEllipsesVectorEnv(2, control_limit=5)
    for limit in (np.array([2.0, 3.0]), torch.tensor([2.0, 3.0])):
        env2 = envs.UnicycleEllipsesVectorEnv(2, control_limit=limit)
        assert env2.dynamics.u_max.tolist() == [2.0, 3.0]
    with pytest.raises(TypeError, match=r"control_limit\[0\] must be a number"):
        envs.UnicycleEllipsesVectorEnv(2, control_limit=("fast", "slow"))
    for kind in (envs.ReachAvoidVectorEnv, envs.UnicycleEllipsesVectorEnv):
        with pytest.raises(TypeError, match="terminate_on_collision must be a bool"):
            kind(2, terminate_on_collision="False")


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
@pytest.mark.parametrize("env_id", IDS)
def test_cuda_vector_env_matches_cpu(env_id: str) -> None:
    kw = {"num_envs": 6, "vectorization_mode": "vector_entry_point", "start_noise": 0.2}
    cpu = gym.make_vec(env_id, **kw)
    cuda = gym.make_vec(env_id, device="cuda", **kw)
    assert cuda.unwrapped.dynamics.f(torch.zeros(1, cuda.unwrapped.dynamics.state_dim,
                                                 device="cuda")).is_cuda  # fmt: skip
    actions = np.random.default_rng(0).uniform(-3, 3, size=(40, 6, 2)).astype(np.float32)
    for a, b in zip(_rollout(cpu, actions, 2), _rollout(cuda, actions, 2), strict=True):
        np.testing.assert_allclose(a[0], b[0], atol=1e-4)
