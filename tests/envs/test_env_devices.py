"""torchcbf's environments, the safety-filter wrapper, the TorchRL environment, its
transforms and the filter-layer policy on the device fixture's device against the CPU,
with fixed seeds and actions drawn on the CPU."""

from __future__ import annotations

import copy

import numpy as np
import pytest
import torch
from _devices import device_matches_cpu
from _host_traffic import HostTraffic

gym = pytest.importorskip("gymnasium")
envs = pytest.importorskip("torchcbf.envs")

from gymnasium.vector import AutoresetMode  # noqa: E402

from torchcbf.filters import SafetyFilter  # noqa: E402

VECTOR = {
    "torchcbf/ReachAvoid-v0": envs.ReachAvoidVectorEnv,
    "torchcbf/UnicycleEllipses-v0": envs.UnicycleEllipsesVectorEnv,
}
#: per scenario: options (noise in the start and, for scenario B, in every step) and the
#: action scale; short episodes so that truncation and autoreset happen within the run
OPTIONS = {
    "torchcbf/ReachAvoid-v0": ({"start_noise": 0.5, "terminate_on_collision": False}, 5.0),
    "torchcbf/UnicycleEllipses-v0": ({"start_noise": 0.2}, 6.0),
}
N, STEPS = 5, 24


def _actions(env_id: str, m: int, seed: int = 0) -> torch.Tensor:
    scale = OPTIONS[env_id][1]
    rng = np.random.default_rng(seed)
    return torch.as_tensor(scale * rng.uniform(-1, 1, size=(STEPS, N, m)))


def _stack(rows: list[dict[str, torch.Tensor]]) -> dict[str, torch.Tensor]:
    return {k: torch.stack([r[k] for r in rows]) for k in rows[0]}


@pytest.mark.parametrize("env_id", list(VECTOR))
@pytest.mark.parametrize("mode", list(AutoresetMode), ids=lambda m: m.name.lower())
def test_vector_env_on_device_equals_cpu(env_id, mode, dtype, device) -> None:
    """A tensor-returning vector env on the device, reset with a seed and stepped with
    the same actions (some beyond the bounds), gives the CPU's observations, rewards,
    flags and infos, through autoresets of every mode and a masked reset."""
    options, _ = OPTIONS[env_id]
    actions = _actions(env_id, 2)

    def run(dev: torch.device):
        env = VECTOR[env_id](N, max_episode_steps=9, device=dev, dtype=dtype,
                             return_tensors=True, autoreset_mode=mode, **options)  # fmt: skip
        obs, info = env.reset(seed=3)
        rows = [{"obs": obs, **info}]
        for k in range(STEPS):
            if mode == AutoresetMode.DISABLED and k % 9 == 8:
                mask = np.arange(N) % 2 == k % 2
                obs, info = env.reset(options={"reset_mask": mask})
            obs, reward, term, trunc, info = env.step(actions[k].to(device=dev, dtype=dtype))
            kept = ("h", "collision", "success", "final_obs", "_final_obs")
            rows.append({"obs": obs, "reward": reward, "terminated": term, "truncated": trunc,
                         **{key: info[key] for key in kept if key in info}})  # fmt: skip
        first = rows.pop(0)
        return first, _stack(rows)

    _, out = device_matches_cpu(run, device, dtype)
    assert bool(out["truncated"].any())  # the episodes of 9 steps end inside the run
    if mode == AutoresetMode.SAME_STEP:
        assert bool(out["_final_obs"].any())


@pytest.mark.parametrize("env_id", list(VECTOR))
def test_numpy_single_env_on_device_equals_cpu(env_id, device) -> None:
    """The Gymnasium single env built on the device returns the CPU's NumPy observations,
    rewards and flags."""
    options, _ = OPTIONS[env_id]
    actions = _actions(env_id, 2, seed=1)[:, 0].numpy().astype(np.float32)

    def run(dev: torch.device):
        env = gym.make(env_id, device=dev, **options).unwrapped
        obs, _ = env.reset(seed=4)
        out = [torch.as_tensor(obs)]
        for a in actions:
            obs, reward, term, _, info = env.step(a)
            out.append(torch.as_tensor(np.append(obs, [reward, term, info["collision"]])))
        # the NumPy answers come back on the CPU: checked here, compared on it
        return torch.stack(out[1:]).to(dev), out[0].to(dev)

    device_matches_cpu(run, device, torch.float32)


def test_vector_env_step_never_waits_for_the_device(device) -> None:
    """With tensors in and out, a step makes no host synchronisation (an accelerator's
    sync debug mode raises on one); a non-finite action there fails asynchronously."""
    if device.type == "cpu":
        pytest.skip("host synchronisations exist only on an accelerator")
    env = envs.UnicycleEllipsesVectorEnv(N, device=device, return_tensors=True)
    env.reset(seed=0)
    actions = _actions("torchcbf/UnicycleEllipses-v0", 2).to(device=device, dtype=env.dtype)
    torch.cuda.synchronize()
    torch.cuda.set_sync_debug_mode("error")
    try:
        for k in range(STEPS):
            env.step(actions[k])
    finally:
        torch.cuda.set_sync_debug_mode(0)


def test_non_finite_tensor_actions_are_refused_on_the_cpu() -> None:
    env = envs.ReachAvoidVectorEnv(2, return_tensors=True)
    env.reset(seed=0)
    with pytest.raises(ValueError, match="actions must be finite"):
        env.step(torch.tensor([[0.0, float("nan")], [0.0, 0.0]]))
    obs, *_ = env.step(torch.zeros(2, 2))
    assert bool(torch.isfinite(obs).all())


@pytest.mark.parametrize("tensors", [True, False], ids=["tensors", "numpy"])
def test_safety_filter_wrapper_on_device_equals_cpu(tensors, dtype, device) -> None:
    """The wrapper filters a batch of actions on the filter's device: with a
    tensor-returning env on the device, or a NumPy env on the CPU whose filter runs on the
    device; observations, filtered controls, statuses and barrier values equal the CPU's."""
    actions = _actions("torchcbf/ReachAvoid-v0", 2, seed=2)
    goal = torch.tensor([4.0, 4.0], dtype=torch.float64)

    def run(dev: torch.device):
        env_device = dev if tensors else "cpu"
        env = envs.ReachAvoidVectorEnv(N, device=env_device, dtype=dtype, start_noise=0.3,
                                       return_tensors=tensors)  # fmt: skip
        filt = SafetyFilter(env.dynamics, barriers=list(env.barriers), alpha=2.0)
        wrapped = envs.SafetyFilterWrapper(env, filt.to(device=dev, dtype=dtype))
        obs, _ = wrapped.reset(seed=5)
        rows = []
        for k in range(12):
            x = torch.as_tensor(obs)[:, :2].to(torch.float64).cpu()
            a = (2.0 * (goal - x)).clamp(-5, 5) + 0.3 * actions[k]  # through the obstacle
            a = a.to(device=dev, dtype=dtype) if tensors else a.numpy().astype(env.np_dtype)
            obs, reward, _, _, info = wrapped.step(a)
            keys = ("filter_status", "filter_h", "action_nominal", "h")
            row = {key: torch.as_tensor(info[key]) for key in keys}
            row.update(obs=torch.as_tensor(obs), reward=torch.as_tensor(reward))
            rows.append({key: value.to(dev) for key, value in row.items()})
        return _stack(rows)

    loose = {} if dtype == torch.float64 else {"rtol": 1e-3, "atol": 1e-4}
    out = device_matches_cpu(run, device, dtype, **loose)
    assert bool(out["filter_h"].amin() > -1e-3)  # kept out of the obstacle
    assert bool((out["obs"][1:, :, :2] - out["obs"][:-1, :, :2]).abs().sum() > 0)


# -- TorchRL (extra ``rl``) ----------------------------------------------------------------------


@pytest.mark.parametrize("env_id", list(VECTOR))
def test_torchrl_env_with_shield_and_shaping_on_device_equals_cpu(env_id, dtype, device) -> None:
    """The TorchRL env on the device with the scenario's safety-filter transform and
    geodesic reward shaping, stepped (and reset where done) with the same actions: every
    entry of every step equals the CPU's."""
    pytest.importorskip("torchrl")
    from tensordict import TensorDict
    from torchrl.envs import Compose, RewardSum, TransformedEnv

    from torchcbf.envs.filter_transform import SafetyFilterTransform
    from torchcbf.envs.safe_ppo import scenario_filter, scenario_shaping
    from torchcbf.envs.torchrl import TorchRLEnv

    options, _ = OPTIONS[env_id]
    # towards the obstacle in front of the start (scenario A: the disc on the way to g1;
    # scenario B: full throttle along the start heading), so that the shield intervenes
    push = torch.tensor([4.0, 4.0] if env_id.endswith("ReachAvoid-v0") else [5.0, 0.0])
    actions = push + 0.3 * _actions(env_id, 2, seed=3)

    def run(dev: torch.device):
        base = TorchRLEnv(env_id, N, device=dev, dtype=dtype, seed=7, max_episode_steps=9,
                          **options)  # fmt: skip
        shield = SafetyFilterTransform(scenario_filter(base))
        env = TransformedEnv(base, Compose(shield, scenario_shaping(base), RewardSum()))
        td = env.reset()
        outs = []
        for k in range(STEPS):
            td["action"] = actions[k].to(device=dev, dtype=dtype)
            out, td = env.step_and_maybe_reset(td)
            outs.append(out["next"].exclude("episode_reward"))
        out = TensorDict.stack(outs).to_dict()
        return {key: value for key, value in out.items() if isinstance(value, torch.Tensor)}

    loose = {} if dtype == torch.float64 else {"rtol": 1e-3, "atol": 1e-4}
    out = device_matches_cpu(run, device, dtype, **loose)
    assert {"reward", "filter_h", "action_filtered", "observation", "done"} <= set(out)
    assert bool(out["done"].any()) and bool(out["filter_intervention"].any())


def test_torchrl_env_refuses_non_finite_actions_on_the_cpu() -> None:
    pytest.importorskip("torchrl")
    from torchcbf.envs.torchrl import TorchRLEnv

    env = TorchRLEnv("torchcbf/ReachAvoid-v0", 2, seed=0)
    td = env.reset()
    td["action"] = torch.tensor([[0.0, float("inf")], [0.0, 0.0]])
    with pytest.raises(ValueError, match="action must be finite"):
        env.step(td)


def test_distance_field_left_on_the_cpu_serves_device_points(dtype, device) -> None:
    """A distance field that was not moved evaluates points on any device (its grid follows
    the points), with the CPU's values and gradients."""
    pytest.importorskip("torchrl")
    from torchcbf.envs.shaping import geodesic_distance

    field = geodesic_distance(lambda p: p.norm(dim=-1) >= 1.0, (2.0, 0.0), low=(-3.0, -3.0),
                              high=(3.0, 3.0), spacing=0.1)  # fmt: skip
    p = 6.0 * torch.rand(200, 2, generator=torch.Generator().manual_seed(0)) - 3.0

    def run(dev: torch.device):
        points = p.to(device=dev, dtype=dtype).requires_grad_()
        d = field(points)
        (grad,) = torch.autograd.grad(d.sum(), points)
        return d.detach(), grad

    d, grad = device_matches_cpu(run, device, dtype)
    assert field.values.device.type == "cpu" and bool((grad != 0).any())


def test_filtered_policy_and_its_gradients_on_device_equal_cpu(dtype, device) -> None:
    """The filter-layer policy's actions, statuses and the gradients of a loss on its
    actions to the network's parameters and the observation equal the CPU's."""
    pytest.importorskip("torchrl")
    from torchcbf.barriers import Ball
    from torchcbf.dynamics import SingleIntegrator
    from torchcbf.envs.filter_policy import FilteredPolicy

    torch.manual_seed(0)
    net = torch.nn.Sequential(torch.nn.Linear(2, 8), torch.nn.Tanh(), torch.nn.Linear(8, 2))
    with torch.no_grad():
        net[2].bias.copy_(torch.tensor([3.0, 0.0]))  # towards the disc
    obs = torch.tensor([[0.0, 0.05], [0.1, -0.2], [-2.0, 3.0], [0.4, 0.4]], dtype=torch.float64)

    def run(dev: torch.device):
        f = {"device": dev, "dtype": dtype}
        dyn = SingleIntegrator(2, u_min=-5.0, u_max=5.0)
        filt = SafetyFilter(dyn, barriers=Ball([1.0, 0.0], 0.5), alpha=2.0).to(**f)
        policy = FilteredPolicy(copy.deepcopy(net).to(**f), filt)
        o = obs.to(**f).requires_grad_()
        u, u_nom, status = policy(o)
        grads = torch.autograd.grad(u.square().sum(), (o, *policy.net.parameters()))
        return u.detach(), u_nom.detach(), status, *grads

    loose = {} if dtype == torch.float64 else {"rtol": 1e-3, "atol": 1e-4}
    u, u_nom, status, *_ = device_matches_cpu(run, device, dtype, **loose)
    assert not torch.allclose(u[:2], u_nom[:2])  # the constraint is active in the first rows


def test_policy_features_on_device_equal_cpu_without_host_sync(dtype, device) -> None:
    """The PPO policy's features (angles replaced by their cosine and sine) equal a
    reference on the CPU, on the device without a host synchronisation."""
    pytest.importorskip("torchrl")
    from torchcbf.envs.safe_ppo import _Features

    obs = torch.randn(7, 5, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    for angles in ((3,), (1, 4)):
        keep = [i for i in range(5) if i not in angles]
        want = torch.cat([obs[:, keep], obs[:, angles].cos(), obs[:, angles].sin()], -1)
        features = _Features(angles)
        x = obs.to(device=device, dtype=dtype)
        if device.type != "cpu":
            torch.cuda.synchronize()
            torch.cuda.set_sync_debug_mode("error")
        try:
            got = features(x)
        finally:
            if device.type != "cpu":
                torch.cuda.set_sync_debug_mode(0)
        assert got.shape == (7, features.size(5))
        torch.testing.assert_close(got.cpu(), want.to(dtype), rtol=1e-6, atol=1e-6)


@pytest.mark.parametrize("env_id", list(VECTOR))
@pytest.mark.parametrize("mode", list(AutoresetMode), ids=lambda m: m.name.lower())
def test_vector_env_steps_make_no_host_traffic(env_id, mode) -> None:
    """Steps with tensors in and out, through autoresets, run on the meta device (no value
    is read back) and copy nothing from the host (no list index, no Python data)."""
    options, _ = OPTIONS[env_id]
    meta = torch.device("meta")
    env = VECTOR[env_id](3, max_episode_steps=2, device=meta, return_tensors=True,
                         autoreset_mode=mode, **options)  # fmt: skip
    env.reset(seed=0)
    u = torch.zeros(3, 2, device=meta)
    with HostTraffic() as traffic:
        for _ in range(5):
            obs, reward, *_ = env.step(u)
    assert not traffic.events, dict(traffic.events)
    assert obs.device.type == "meta" and reward.shape == (3,)
