"""Reward shaping along the shortest collision-free path (``torchcbf.envs.shaping``) and the
safe-RL scenario pieces built on it (extra ``rl``)."""

from __future__ import annotations

import math

import pytest
import torch

pytest.importorskip("gymnasium")
pytest.importorskip("torchrl")

from torchrl.envs import TransformedEnv  # noqa: E402

import torchcbf.envs  # noqa: E402,F401  (registers the ids)
from torchcbf.envs.safe_ppo import scenario_filter, scenario_shaping  # noqa: E402
from torchcbf.envs.shaping import DistanceField, GeodesicProgress, geodesic_distance  # noqa: E402
from torchcbf.envs.torchrl import TorchRLEnv  # noqa: E402
from torchcbf.scenarios.unicycle_mppi_cbf import AXES, CENTERS, GOAL  # noqa: E402


def _outside_disc(radius: float):
    return lambda p: p.norm(dim=-1) >= radius


def _no_obstacle(p: torch.Tensor) -> torch.Tensor:
    return torch.ones(p.shape[:-1], dtype=torch.bool)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_field_is_bilinear_and_exact_on_affine_values(dtype):
    xs = torch.arange(5, dtype=dtype)
    ys = torch.arange(4, dtype=dtype)
    values = 2.0 * xs[:, None] * 0.5 - 3.0 * ys[None, :] * 0.5 + 1.0  # affine in (x, y)
    field = DistanceField(values, (0.0, 0.0), 0.5)
    gen = torch.Generator().manual_seed(0)
    p = torch.rand(50, 2, generator=gen, dtype=dtype) * torch.tensor([2.0, 1.5], dtype=dtype)
    expected = 2.0 * p[:, 0] - 3.0 * p[:, 1] + 1.0
    torch.testing.assert_close(field(p), expected)
    # outside the grid: the nearest border point's value
    outside = torch.tensor([[-1.0, 0.0], [10.0, 1.5]], dtype=dtype)
    border = torch.tensor([[0.0, 0.0], [2.0, 1.5]], dtype=dtype)
    torch.testing.assert_close(field(outside), field(border))
    assert field(p.reshape(5, 10, 2)).shape == (5, 10)
    # a point that is not finite has no value (it would index outside the grid)
    odd = torch.tensor([[math.nan, 0.0], [0.5, math.inf], [0.5, 0.5]], dtype=dtype)
    got = field(odd)
    assert got[:2].isnan().all() and torch.equal(got[2:], field(odd[2:]))


def test_free_space_distance_is_the_straight_line_within_the_grid_bias():
    field = geodesic_distance(_no_obstacle, (0.0, 0.0), low=(-2.0, -2.0), high=(2.0, 2.0))
    gen = torch.Generator().manual_seed(1)
    p = torch.rand(200, 2, generator=gen, dtype=torch.float64) * 3.6 - 1.8
    straight = p.norm(dim=-1)
    d = field(p)
    assert bool((d >= straight - 0.06).all())  # the bilinear error near the goal
    assert bool((d <= 1.0824 * straight + 0.06).all())  # 8-neighbour paths: at most +8.24%


def test_distance_around_a_disc_matches_the_tangent_and_arc_path():
    r, a = 1.0, 2.0
    field = geodesic_distance(
        _outside_disc(r), (a, 0.0), low=(-3.0, -3.0), high=(3.0, 3.0), spacing=0.02
    )
    # from (-a, 0) to (a, 0) around the disc: two tangents and the arc between them
    tangent = math.sqrt(a * a - r * r)
    arc = r * (math.pi - 2.0 * math.acos(r / a))
    exact = 2.0 * tangent + arc
    d = float(field(torch.tensor([-a, 0.0], dtype=torch.float64)))
    assert exact - 0.05 <= d <= 1.0824 * exact
    assert d > 2 * a + 0.3  # not the straight line through the disc


def test_field_grows_into_the_obstacle_and_around_the_clearance():
    field = geodesic_distance(
        _outside_disc(1.0), (2.5, 0.0), low=(-3.0, -3.0), high=(3.0, 3.0), clearance=0.3
    )
    rim = field(torch.tensor([-1.35, 0.0], dtype=torch.float64))
    inner = field(torch.tensor([-1.1, 0.0], dtype=torch.float64))
    deep = field(torch.tensor([-0.5, 0.0], dtype=torch.float64))
    assert float(rim) < float(inner) < float(deep)
    assert bool(torch.isfinite(field.values).all())


def test_bad_arguments():
    with pytest.raises(ValueError, match="spacing"):
        geodesic_distance(_no_obstacle, (0.0, 0.0), low=(-1, -1), high=(1, 1), spacing=0.0)
    with pytest.raises(ValueError, match="high > low"):
        geodesic_distance(_no_obstacle, (0.0, 0.0), low=(1, 1), high=(-1, -1))
    with pytest.raises(ValueError, match="goal"):
        geodesic_distance(_outside_disc(1.0), (0.0, 0.0), low=(-2, -2), high=(2, 2))
    with pytest.raises(ValueError, match="clearance"):
        geodesic_distance(_no_obstacle, (0.0, 0.0), low=(-1, -1), high=(1, 1), clearance=-1.0)
    with pytest.raises(ValueError, match="grid"):
        DistanceField(torch.zeros(3), (0.0, 0.0), 1.0)
    with pytest.raises(ValueError, match="finite"):
        DistanceField(torch.full((2, 2), math.inf), (0.0, 0.0), 1.0)
    with pytest.raises(TypeError, match="DistanceField"):
        GeodesicProgress([torch.zeros(2, 2)], (0.0, 0.0))
    field = DistanceField(torch.zeros(2, 2), (0.0, 0.0), 1.0)
    with pytest.raises(ValueError, match="one point per field"):
        GeodesicProgress([field], [(0.0, 0.0), (1.0, 1.0)])


@pytest.mark.parametrize("env_id", ["torchcbf/UnicycleEllipses-v0", "torchcbf/ReachAvoid-v0"])
def test_shaped_reward_swaps_the_straight_progress_for_the_geodesic(env_id):
    kwargs = {"sigma": 0.0} if "Unicycle" in env_id else {}
    plain = TorchRLEnv(env_id, 6, seed=3, **kwargs)
    base = TorchRLEnv(env_id, 6, seed=3, **kwargs)
    shaping = scenario_shaping(base)
    shaped = TransformedEnv(base, shaping)
    spec = plain.full_action_spec["action"]
    gen = torch.Generator().manual_seed(0)
    td_a, td_b = plain.reset(), shaped.reset()
    for _ in range(15):
        u = spec.space.low + (spec.space.high - spec.space.low) * torch.rand(
            spec.shape, generator=gen
        )
        td_a["action"], td_b["action"] = u, u.clone()
        obs = td_a["observation"]
        out_a, td_a = plain.step_and_maybe_reset(td_a)
        out_b, td_b = shaped.step_and_maybe_reset(td_b)
        nxt = out_a["next", "observation"]
        torch.testing.assert_close(out_b["next", "observation"], nxt)
        # the reference: a loop over rows, the current goal read from the observation
        for i in range(6):
            p, q = obs[i, :2].double(), nxt[i, :2].double()
            k = 0 if "Unicycle" in env_id else int(torch.argmin(obs[i, 3:6].to(torch.int8)))
            goal, field = shaping.goals[k], shaping.fields[k]
            change = (field(p) - field(q)) - ((p - goal).norm() - (q - goal).norm())
            expected = out_a["next", "reward"][i, 0].double() + change
            torch.testing.assert_close(
                out_b["next", "reward"][i, 0].double(), expected, atol=1e-5, rtol=1e-5
            )


def test_scenario_b_shaping_path_keeps_clear_of_the_ellipses():
    base = TorchRLEnv("torchcbf/UnicycleEllipses-v0", 1, seed=0, sigma=0.0)
    field = scenario_shaping(base).fields[0]
    # greedy descent of the field from the start reaches the goal outside every ellipse
    p = torch.zeros(2, dtype=torch.float64)
    angles = torch.linspace(0, 2 * math.pi, 65, dtype=torch.float64)[:-1]
    steps = 0.05 * torch.stack([angles.cos(), angles.sin()], dim=-1)
    centers, axes = torch.tensor(CENTERS, dtype=torch.float64), torch.tensor(AXES).double()
    for _ in range(300):
        candidates = p + steps
        p = candidates[field(candidates).argmin()]
        h = (((p - centers) / axes) ** 2).sum(-1) - 1.0
        assert bool((h > 0).all())
        if (p - torch.tensor(GOAL, dtype=torch.float64)).norm() <= 0.25:
            break
    assert float((p - torch.tensor(GOAL, dtype=torch.float64)).norm()) <= 0.25


@pytest.mark.parametrize("env_id", ["torchcbf/UnicycleEllipses-v0", "torchcbf/ReachAvoid-v0"])
def test_shaping_and_filter_leave_the_environments_modules_as_they_were(env_id):
    """Building the scenario's shaping (on a float64 grid) and filter does not cast the
    float32 environment's barriers or plant."""
    base = TorchRLEnv(env_id, 1, seed=0)
    vec = base.vector_env
    before = {k: v.clone() for k, v in (*vec.barriers.state_dict().items(),
                                        *vec.dynamics.state_dict().items())}  # fmt: skip
    scenario_shaping(base)
    scenario_filter(base)
    after = {**vec.barriers.state_dict(), **vec.dynamics.state_dict()}
    assert before.keys() == after.keys() and before
    for key, value in before.items():
        assert after[key].dtype == value.dtype == torch.float32, key
        assert torch.equal(after[key], value), key


def test_scenario_filter_margin_inflates_the_ellipses():
    base = TorchRLEnv("torchcbf/UnicycleEllipses-v0", 1, seed=0, sigma=0.1)
    noisy = scenario_filter(base)  # default: 3 sigma
    exact = scenario_filter(base, margin=0.0)
    # a robot at rest 0.2 m left of ellipse 0 (centre (1, 2), semi-axes (0.5, 1.5)),
    # commanded to drive towards it: the exact filter lets it, the margin of 0.3 m brakes
    x = torch.tensor([[0.3, 2.0, 0.5, 0.0]])
    u = torch.tensor([[5.0, 0.0]])
    assert float(exact(x, u).u[0, 0]) > float(noisy(x, u).u[0, 0])
    assert float(noisy(x, u).u[0, 0]) < 0.0  # braking
    with pytest.raises(ValueError, match="margin"):
        scenario_filter(base, margin=-0.1)
