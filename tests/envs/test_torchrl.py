"""TorchRL environments, the safety-filter transform, the filter-layer policy and the PPO
runner (extra ``rl``)."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
import torch

pytest.importorskip("gymnasium")
pytest.importorskip("torchrl")

import gymnasium  # noqa: E402
from tensordict import TensorDict  # noqa: E402
from tensordict.nn import TensorDictModule  # noqa: E402
from torchrl.envs import TransformedEnv  # noqa: E402
from torchrl.envs.utils import check_env_specs, step_mdp  # noqa: E402

import torchcbf.envs  # noqa: E402,F401  (registers the ids)
from torchcbf.barriers import Ball  # noqa: E402
from torchcbf.dynamics import SingleIntegrator  # noqa: E402
from torchcbf.envs import UnicycleEllipsesVectorEnv  # noqa: E402
from torchcbf.envs.filter_policy import FilteredPolicy  # noqa: E402
from torchcbf.envs.filter_transform import FILTER_KEYS, SafetyFilterTransform  # noqa: E402
from torchcbf.envs.safe_ppo import (  # noqa: E402
    METHODS,
    SCENARIO_KWARGS,
    PPOConfig,
    RunResult,
    _penalize_shield,
    config_dict,
    make_env,
    mean_ci,
    scenario_filter,
    summarize,
    train,
)
from torchcbf.envs.torchrl import TorchRLEnv  # noqa: E402
from torchcbf.filters import SafetyFilter  # noqa: E402

IDS = ("torchcbf/UnicycleEllipses-v0", "torchcbf/ReachAvoid-v0")


def _actions(env: TorchRLEnv, steps: int, seed: int) -> torch.Tensor:
    """Random actions ``[steps, N, m]`` inside the bounds (a seeded generator)."""
    spec = env.full_action_spec["action"]
    gen = torch.Generator().manual_seed(seed)
    u = torch.rand(steps, *spec.shape, generator=gen, dtype=spec.dtype)
    return spec.space.low + (spec.space.high - spec.space.low) * u


def _run(env, actions: torch.Tensor):
    """Step with ``actions [S, N, m]`` (``step_and_maybe_reset``); stacked outputs."""
    td = env.reset()
    outs = []
    for u in actions:
        td["action"] = u
        out, td = env.step_and_maybe_reset(td)
        outs.append(out)
    return torch.stack(outs, dim=1)


@pytest.mark.parametrize("env_id", IDS)
@pytest.mark.parametrize("num_envs", [1, 5])
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_specs(env_id, num_envs, dtype):
    env = TorchRLEnv(env_id, num_envs, seed=0, dtype=dtype)
    check_env_specs(env)
    assert env.batch_size == torch.Size([num_envs])
    assert env.full_action_spec["action"].dtype == dtype


def test_steps_the_gymnasium_vector_env_episode():
    """Row i of the TorchRL env and the Gymnasium vector env with the same seed agree
    (noise included) until the first episode ends."""
    n, steps = 4, 60
    env = TorchRLEnv("torchcbf/UnicycleEllipses-v0", n, seed=7)
    vec = UnicycleEllipsesVectorEnv(n, return_tensors=True)
    actions = _actions(env, steps, 0)
    out = _run(env, actions)
    obs, _ = vec.reset(seed=7)
    for t in range(steps):
        obs, reward, terminated, truncated, info = vec.step(actions[t])
        torch.testing.assert_close(out["next", "observation"][:, t], obs)
        torch.testing.assert_close(out["next", "reward"][:, t, 0], reward)
        torch.testing.assert_close(out["next", "h"][:, t], info["h"])
        assert not bool(terminated.any())


@pytest.mark.parametrize("env_id", IDS)
def test_seeding_reproduces_and_rows_are_batch_independent(env_id):
    steps = 120  # ReachAvoid episodes end by then: resets are covered
    big = TorchRLEnv(env_id, 3, seed=11, start_noise=0.1)
    actions = _actions(big, steps, 1)
    a = _run(big, actions)
    again = TorchRLEnv(env_id, 3, seed=11, start_noise=0.1)
    b = _run(again, actions)
    torch.testing.assert_close(a["next", "observation"], b["next", "observation"], rtol=0, atol=0)
    for i in range(3):
        one = TorchRLEnv(env_id, 1, seed=11 + i, start_noise=0.1)
        c = _run(one, actions[:, i : i + 1])
        torch.testing.assert_close(c["next", "observation"][0], a["next", "observation"][i])
        torch.testing.assert_close(c["next", "done"][0], a["next", "done"][i])
    other = _run(TorchRLEnv(env_id, 3, seed=12, start_noise=0.1), actions)
    assert not torch.equal(other["next", "observation"], a["next", "observation"])


def test_set_seed_restarts_the_sequence():
    env = TorchRLEnv("torchcbf/UnicycleEllipses-v0", 2, seed=3)
    actions = _actions(env, 10, 2)
    first = _run(env, actions)["next", "observation"]
    env.set_seed(3)
    torch.testing.assert_close(_run(env, actions)["next", "observation"], first)


def test_seeds_outside_32_bits_are_refused():
    with pytest.raises(ValueError, match="seed must lie in"):
        TorchRLEnv("torchcbf/UnicycleEllipses-v0", 1, seed=2**32 + 5)
    env = TorchRLEnv("torchcbf/UnicycleEllipses-v0", 2, seed=2**32 - 2)
    with pytest.raises(ValueError, match="seed must lie in"):
        env.set_seed(2**32 - 1)  # the second row would be 2^32


def test_partial_reset_resets_only_the_masked_rows():
    env = TorchRLEnv("torchcbf/UnicycleEllipses-v0", 3, seed=0, sigma=0.0)
    td = env.reset()
    for _ in range(20):
        td["action"] = torch.tensor([[5.0, 0.0]] * 3)
        td = step_mdp(env.step(td), keep_other=True)
    moved = td["observation"].clone()
    reset = env.reset(td.set("_reset", torch.tensor([[False], [True], [False]])))
    start = torch.tensor([0.0, 0.0, 0.0, math.pi / 4])
    torch.testing.assert_close(reset["observation"][1], start)
    torch.testing.assert_close(reset["observation"][[0, 2]], moved[[0, 2]])


def test_collision_terminates_with_cost():
    env = TorchRLEnv("torchcbf/ReachAvoid-v0", 1, seed=0)
    td = env.reset()
    costs = []
    for _ in range(20):
        td["action"] = torch.tensor([[3.0, 3.0]])  # straight into the disc at (3, 3)
        out = env.step(td)
        costs.append(float(out["next", "cost"]))
        if bool(out["next", "done"]):
            break
        td = step_mdp(out, keep_other=True)
    assert costs[-1] == 1.0 and sum(costs) == 1.0
    assert bool(out["next", "terminated"]) and float(out["next", "h"].min()) < 0


@pytest.mark.parametrize("env_id", IDS)
def test_collision_without_termination_costs_every_step_inside(env_id):
    kwargs = {"sigma": 0.0} if "Unicycle" in env_id else {}
    ends = TorchRLEnv(env_id, 1, seed=0, **kwargs)
    goes_on = TorchRLEnv(env_id, 1, seed=0, terminate_on_collision=False, **kwargs)
    # scenario A: straight into the disc at (3, 3); B: along the heading into ellipse 0
    action = torch.tensor([[3.0, 3.0]]) if "Reach" in env_id else torch.tensor([[5.0, 0.0]])
    td_a, td_b = ends.reset(), goes_on.reset()
    inside = 0
    for _ in range(30 if "Reach" in env_id else 90):
        td_a["action"], td_b["action"] = action, action
        out_a, out_b = ends.step(td_a), goes_on.step(td_b)
        torch.testing.assert_close(out_a["next", "observation"], out_b["next", "observation"])
        torch.testing.assert_close(out_a["next", "reward"], out_b["next", "reward"])
        cost = float(out_b["next", "cost"])
        inside += int(cost)
        assert bool(out_b["next", "terminated"]) == bool(out_b["next", "success"])
        assert bool(out_a["next", "terminated"]) == (cost == 1.0 or bool(out_a["next", "success"]))
        td_a, td_b = step_mdp(out_a, keep_other=True), step_mdp(out_b, keep_other=True)
    assert inside >= 2  # several steps inside, each with the cost and the penalty


def test_bad_arguments():
    with pytest.raises(TypeError, match="env must be"):
        TorchRLEnv(3)
    with pytest.raises(gymnasium.error.Error):
        TorchRLEnv("torchcbf/NoSuchEnv-v0")
    vec = UnicycleEllipsesVectorEnv(2)
    with pytest.raises(TypeError, match="keyword arguments"):
        TorchRLEnv(vec, sigma=0.0)
    assert TorchRLEnv(vec).batch_size == torch.Size([2])


# -- the transform -------------------------------------------------------------------------


def _shielded(env_id: str, n: int, dtype=torch.float32, **kwargs):
    base = TorchRLEnv(env_id, n, seed=5, dtype=dtype, **kwargs)
    safety_filter = scenario_filter(base)
    return TransformedEnv(base, SafetyFilterTransform(safety_filter)), safety_filter


def test_the_transform_refuses_a_non_finite_action():
    """As the env alone does: behind the filter a NaN became the filter's stand-in control
    and stepped the env, hiding a broken policy."""
    env, _ = _shielded("torchcbf/ReachAvoid-v0", 2)
    td = env.reset()
    td["action"] = torch.tensor([[float("nan"), 1.0], [1.0, 1.0]])
    with pytest.raises(ValueError, match="action must be finite"):
        env.step(td)


@pytest.mark.parametrize("env_id", IDS)
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_transform_matches_a_direct_filter_call(env_id, dtype):
    env, safety_filter = _shielded(env_id, 6, dtype)
    check_env_specs(env)
    base = env.base_env
    td = env.reset()
    for key in FILTER_KEYS:
        assert key in td.keys()
    x0 = base.state_from_observation(td["observation"])
    with torch.no_grad():
        torch.testing.assert_close(td["filter_h"], safety_filter(x0, torch.zeros_like(x0[:, :2])).h)
    gen = torch.Generator().manual_seed(0)
    for _ in range(15):
        u_nom = 4.0 * torch.randn(6, base.dynamics.control_dim, generator=gen, dtype=dtype)
        td["action"] = u_nom
        x = base.state_from_observation(td["observation"])
        with torch.no_grad():
            ref = safety_filter(x, u_nom)
        out = env.step(td)
        nxt = out["next"]
        torch.testing.assert_close(out["action"], u_nom)  # the policy's action stays
        torch.testing.assert_close(nxt["action_nominal"], u_nom)
        torch.testing.assert_close(nxt["action_filtered"], ref.u)
        torch.testing.assert_close(nxt["filter_status"], ref.status)
        torch.testing.assert_close(nxt["filter_h"], ref.h)
        change = (ref.u - u_nom).abs().amax(-1, keepdim=True) > 1e-4
        assert torch.equal(nxt["filter_intervention"], change)
        td = step_mdp(out, keep_other=True)


def test_transform_steps_the_filtered_control():
    """The base env steps with the filtered control: the same as stepping it directly."""
    env, safety_filter = _shielded("torchcbf/ReachAvoid-v0", 3)
    plain = TorchRLEnv("torchcbf/ReachAvoid-v0", 3, seed=5)
    td, td_plain = env.reset(), plain.reset()
    u_nom = torch.tensor([[4.0, 4.0], [5.0, 5.0], [-1.0, 2.0]])
    for _ in range(12):
        td["action"] = u_nom
        out = env.step(td)
        td_plain["action"] = out["next", "action_filtered"]
        out_plain = plain.step(td_plain)
        torch.testing.assert_close(out["next", "observation"], out_plain["next", "observation"])
        td, td_plain = step_mdp(out, keep_other=True), step_mdp(out_plain, keep_other=True)
    assert float(out["next", "h"].min()) >= 0  # the nominal drives into the disc


def test_transform_on_torchrl_gym_wrappers():
    from torchrl.envs.libs.gym import GymWrapper

    single = gymnasium.make("torchcbf/ReachAvoid-v0")
    unwrapped = single.unwrapped
    safety_filter = SafetyFilter(unwrapped.dynamics, barriers=list(unwrapped.barriers), alpha=5.0)
    env = TransformedEnv(
        GymWrapper(single),
        SafetyFilterTransform(safety_filter, state_fn=unwrapped.state_from_observation),
    )
    check_env_specs(env, seed=0)
    td = env.reset()
    td["action"] = torch.tensor([3.0, 3.0])
    for _ in range(10):
        out = env.step(td)
        td = step_mdp(out, keep_other=True)
        td["action"] = torch.tensor([3.0, 3.0])
    assert bool(out["next", "filter_intervention"])
    assert float(out["next", "filter_h"]) >= 0


def test_transform_needs_a_state():
    plain = TorchRLEnv("torchcbf/ReachAvoid-v0", 2, seed=0)
    safety_filter = scenario_filter(plain)
    from torchrl.envs import EnvBase

    class NoState(EnvBase):
        pass

    env = TransformedEnv(plain, SafetyFilterTransform(safety_filter))
    env.reset()  # the env's own state_from_observation
    with pytest.raises(TypeError, match="state_fn must be callable"):
        SafetyFilterTransform(safety_filter, state_fn=3)
    with pytest.raises(ValueError, match="intervention_tol"):
        SafetyFilterTransform(safety_filter, intervention_tol=-1.0)
    assert issubclass(NoState, EnvBase)


# -- the policy layer ------------------------------------------------------------------------


def _layer(dtype=torch.float64):
    dyn = SingleIntegrator(2, u_min=-5.0, u_max=5.0).to(dtype)
    safety_filter = SafetyFilter(dyn, barriers=Ball([1.0, 0.0], 0.5), alpha=2.0).to(dtype)
    torch.manual_seed(0)
    net = torch.nn.Sequential(torch.nn.Linear(2, 8), torch.nn.Tanh(), torch.nn.Linear(8, 2))
    net = net.to(dtype)
    with torch.no_grad():
        net[2].bias.copy_(torch.tensor([3.0, 0.0]))  # push towards the disc
    return FilteredPolicy(net, safety_filter), safety_filter


def test_filtered_policy_is_the_filter_on_the_net():
    policy, safety_filter = _layer(torch.float32)
    x = torch.tensor([[0.0, 0.05], [-2.0, 3.0], [0.2, -0.1]])
    u, u_nom, status = policy(x)
    torch.testing.assert_close(u_nom, policy.net(x))
    ref = safety_filter(x, u_nom)
    torch.testing.assert_close(u, ref.u)
    assert torch.equal(status, ref.status)
    assert not torch.allclose(u[0], u_nom[0])  # the constraint is active in row 0


def test_gradient_flows_through_the_qp_into_the_policy():
    """gradcheck in float64 (observation) and finite differences (a parameter) with an
    active barrier condition."""
    policy, _ = _layer()
    x = torch.tensor([[0.0, 0.05], [0.1, -0.2], [-2.0, 3.0]], dtype=torch.float64)
    u, u_nom, _ = policy(x)
    assert not torch.allclose(u[:2], u_nom[:2])
    obs = x.clone().requires_grad_(True)
    assert torch.autograd.gradcheck(lambda o: policy(o)[0], (obs,), eps=1e-6, atol=1e-5)

    weight = policy.net[0].weight
    loss = policy(x)[0].square().sum()
    (grad,) = torch.autograd.grad(loss, weight)
    eps = 1e-6
    fd = torch.zeros_like(weight)
    with torch.no_grad():
        for i in range(weight.shape[0]):
            for j in range(weight.shape[1]):
                weight[i, j] += eps
                up = policy(x)[0].square().sum()
                weight[i, j] -= 2 * eps
                down = policy(x)[0].square().sum()
                weight[i, j] += eps
                fd[i, j] = (up - down) / (2 * eps)
    torch.testing.assert_close(grad, fd, rtol=1e-4, atol=1e-6)
    # the gradient differs from the unfiltered one: it passed the QP's projection
    (plain,) = torch.autograd.grad(policy.net(x).square().sum(), weight)
    assert not torch.allclose(grad, plain)


def test_filtered_policy_checks_the_state():
    policy, _ = _layer()
    with pytest.raises(ValueError, match="state_fn"):
        policy(torch.zeros(2, 3, dtype=torch.float64))
    with pytest.raises(TypeError, match="safety_filter"):
        FilteredPolicy(torch.nn.Identity(), object())


def test_filtered_policy_as_a_tensordict_module_on_the_env():
    env, safety_filter = _shielded("torchcbf/ReachAvoid-v0", 4)
    base = env.base_env
    net = torch.nn.Sequential(torch.nn.Linear(6, 2))
    layer = FilteredPolicy(net, safety_filter, state_fn=base.state_from_observation)
    module = TensorDictModule(
        layer, in_keys=["observation"], out_keys=["action", "action_net", "policy_status"]
    )
    rollout = env.rollout(8, module)
    # the layer's actions are safe already: the shield leaves them alone
    assert not bool(rollout["next", "filter_intervention"].any())


# -- PPO -----------------------------------------------------------------------------------------


def test_ppo_smoke_run_is_reproducible():
    config = PPOConfig(
        env_id="torchcbf/ReachAvoid-v0",
        env_kwargs=(),
        num_envs=8,
        rollout_steps=8,
        total_frames=128,
        epochs=1,
        minibatch_size=32,
        eval_episodes=2,
    )
    for method in ("ppo_lagrangian", "ppo_shield", "ppo_filter_layer"):
        a = train(method, config, seed=0)
        b = train(method, config, seed=0)
        assert a.eval == b.eval
        assert [r["return"] for r in a.curve] == [r["return"] for r in b.curve] or all(
            np.isnan(r["return"]) for r in a.curve
        )
        assert a.train["frames"] == 128
    assert a.eval["collisions"] == 0  # the filter layer on the shielded env
    with pytest.raises(ValueError, match="method"):
        train("sac", config, seed=0)


def test_ppo_counts_collisions_in_every_batch_and_takes_any_minibatch_and_seed():
    """Batches where no episode ends still count their steps inside an obstacle (the
    Lagrangian multiplier reads them); a minibatch of one frame is no NaN; a seed whose
    environments' seeds pass 32 bits is refused before training; evaluate takes a policy
    without a filter layer."""
    from torchcbf.envs.safe_ppo import _episode_stats, evaluate

    frames = TensorDict(
        {"next": {"done": torch.zeros(2, 3, 1, dtype=torch.bool),
                  "cost": torch.tensor([[[1.0], [0.0], [1.0]], [[0.0], [1.0], [0.0]]]),
                  "episode_reward": torch.zeros(2, 3, 1), "success": torch.zeros(2, 3, 1).bool()}},
        batch_size=[2, 3],
    )  # fmt: skip
    assert _episode_stats(frames)["collisions"] == 3.0
    config = PPOConfig(env_id="torchcbf/ReachAvoid-v0", env_kwargs=(), num_envs=3,
                       rollout_steps=11, total_frames=33, epochs=1, minibatch_size=32,
                       eval_episodes=2)  # fmt: skip
    run = train("ppo_lagrangian", config, seed=0)  # 33 frames: a last minibatch of one
    assert all(torch.isfinite(torch.tensor(v)) for v in (run.eval["return"],))
    with pytest.raises(ValueError, match=r"seed must lie in \[0, 3294\]"):
        train("ppo_lagrangian", config, seed=3500)
    env = make_env(config, "ppo_lagrangian", num_envs=2, seed=5)
    still = TensorDictModule(lambda obs: obs.new_zeros(*obs.shape[:-1], 2),
                             in_keys=["observation"], out_keys=["action"])  # fmt: skip
    assert evaluate(env, still)["layer_intervention_rate"] == 0.0


def test_shield_penalty_lowers_the_learning_reward_by_the_correction():
    config = PPOConfig(env_id="torchcbf/ReachAvoid-v0", env_kwargs=())
    env = make_env(config, "ppo_shield", num_envs=16, seed=3)
    bound = env.full_action_spec["action"].space.high[0]
    torch.manual_seed(0)
    batch = env.rollout(40, break_when_any_done=False)  # random actions, some unsafe
    nxt = batch["next"]
    reward = nxt["reward"].double().clone()
    returns = nxt["episode_reward"].clone()
    nominal = nxt["action_nominal"].double().numpy().reshape(-1, 2)
    filtered = nxt["action_filtered"].double().numpy().reshape(-1, 2)
    scale = bound.double().numpy()
    expected = reward.numpy().reshape(-1).copy()
    for i in range(expected.shape[0]):
        expected[i] -= 0.5 * sum(((nominal[i] - filtered[i]) / scale) ** 2)
    assert bool(nxt["filter_intervention"].any())
    _penalize_shield(batch, bound, 0.5)
    got = batch["next", "reward"].double().numpy().reshape(-1)
    np.testing.assert_allclose(got, expected, rtol=1e-5, atol=1e-6)
    untouched = ~nxt["filter_intervention"].reshape(-1).numpy()
    np.testing.assert_allclose(got[untouched], reward.numpy().reshape(-1)[untouched], atol=1e-8)
    assert torch.equal(batch["next", "episode_reward"], returns)


def test_mean_ci_and_summary():
    mean, half = mean_ci([1.0, 2.0, 3.0])
    assert mean == 2.0 and half == pytest.approx(4.303 / math.sqrt(3), rel=1e-4)
    assert math.isnan(mean_ci([5.0])[1])
    with pytest.raises(ValueError):
        mean_ci([])
    runs = [
        RunResult(
            "ppo",
            seed,
            [],
            {"collisions": c, "goal_rate": 1.0, "intervention_rate": 0.0},
            {
                "return": r,
                "goal_rate": 1.0,
                "collisions": 0.0,
                "shield_intervention_rate": 0.0,
                "layer_intervention_rate": 0.0,
            },
            10.0,
            100.0,
        )
        for seed, (c, r) in enumerate([(2.0, 1.0), (4.0, 3.0)])
    ]
    summary = summarize(runs)
    assert summary["ppo"]["train collision steps"] == mean_ci([2.0, 4.0])
    assert summary["ppo"]["eval return"][0] == 2.0
    assert summary["ppo"]["frames/s"] == (100.0, 0.0)


def test_gym_wrapper_takes_a_same_step_vector_env() -> None:
    """TorchRL's GymWrapper wraps a torchcbf vector env in SAME_STEP autoreset: its specs
    check, and a rollout past the episodes' ends gives the vector env's own steps."""
    from torchrl.envs import GymWrapper

    kw = {"num_envs": 3, "vectorization_mode": "vector_entry_point", "autoreset_mode": "SameStep"}
    wrapped = GymWrapper(gymnasium.make_vec("torchcbf/ReachAvoid-v0", **kw))
    assert tuple(wrapped.batch_size) == (3,)
    check_env_specs(wrapped)
    wrapped.set_seed(0)
    td = wrapped.rollout(120, break_when_any_done=False)
    assert td.shape == (3, 120) and bool(td["next", "done"].any())  # episodes ended, went on
    reference = gymnasium.make_vec("torchcbf/ReachAvoid-v0", **kw)
    obs, _ = reference.reset(seed=0)
    np.testing.assert_allclose(td["observation"][:, 0].numpy(), obs, rtol=1e-6)


@pytest.mark.slow
def test_safe_rl_script_runs_at_tiny_sizes(tmp_path):
    import json
    import subprocess
    import sys
    from pathlib import Path

    script = Path(__file__).resolve().parents[2] / "scripts" / "safe_rl.py"
    common = [sys.executable, str(script), "--env", "torchcbf/ReachAvoid-v0"]
    tiny = ["--seeds", "2", "--frames", "64", "--num-envs", "4", "--rollout-steps", "8"]
    out = tmp_path / "run"
    done = subprocess.run(
        [*common, *tiny, "--eval-episodes", "2", "--jobs", "2", "--out", str(out)],
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert done.returncode == 0, done.stderr
    record = json.loads((out / "results.json").read_text())
    assert [(r["seed"], r["method"]) for r in record["runs"]] == [
        (seed, method) for seed in (0, 1) for method in METHODS
    ]
    assert record["summary"]["ppo_shield"]["train collision steps"] == [0.0, 0.0]
    check = subprocess.run(
        [
            sys.executable,
            str(script),
            "--shield-check",
            "--sigma",
            "0.05",
            "--check-envs",
            "8",
            "--check-steps",
            "20",
            "--check-margins",
            "0.15",
        ],  # fmt: skip
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert check.returncode == 0, check.stderr
    assert check.stdout.count("| 0.15 |") == 3
    risk = subprocess.run(
        [sys.executable, str(script), "--risk-check", "--sigma", "0.28"],
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert risk.returncode == 0, risk.stderr
    rows = [line for line in risk.stdout.splitlines() if line.startswith("| 0.")]
    assert len(rows) == 4


@pytest.mark.parametrize(
    ("field", "value", "message"),
    [
        ("minibatch_size", 0, "minibatch_size must be a positive int"),
        ("lr", 0.0, "lr must be a finite number > 0"),
        ("gamma", 1.5, r"gamma must lie in \[0, 1\]"),
        ("entropy_coef", -0.1, "entropy_coef must be a finite number >= 0"),
        ("filter_margin", float("nan"), "filter_margin must be a finite number >= 0"),
    ],
)
def test_ppo_settings_are_checked_when_made(field, value, message) -> None:
    with pytest.raises(ValueError, match=message):
        PPOConfig(**{field: value})
    with pytest.raises(TypeError, match="num_envs must be a positive int"):
        PPOConfig(num_envs=2.5)


def test_ppo_environment_options_default_per_scenario_and_are_checked() -> None:
    assert PPOConfig().env_options == SCENARIO_KWARGS["torchcbf/UnicycleEllipses-v0"]
    assert PPOConfig(env_id="torchcbf/ReachAvoid-v0").env_options == {}
    config = PPOConfig(env_kwargs={"sigma": 0.1})
    assert config.env_kwargs == (("sigma", 0.1),) and config.env_options == {"sigma": 0.1}
    hash(config)
    # the defaults follow the environment through dataclasses.replace
    other = dataclasses.replace(PPOConfig(), env_id="torchcbf/ReachAvoid-v0")
    assert other.env_options == {} and config_dict(other)["env_kwargs"] == {}
    with pytest.raises(ValueError, match=r"env_kwargs \['sigma'\] are not options of"):
        PPOConfig(env_id="torchcbf/ReachAvoid-v0", env_kwargs={"sigma": 0.1})
    with pytest.raises(ValueError, match=r"env_kwargs \['return_tensors'\]"):
        PPOConfig(env_kwargs={"return_tensors": False})
    with pytest.raises(TypeError, match="env_kwargs must be"):
        PPOConfig(env_kwargs=5)
    with pytest.raises(TypeError, match="env must be a registered torchcbf id"):
        PPOConfig(env_id=3)
