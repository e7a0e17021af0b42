"""Closed-loop simulator: batch equals single runs, failure isolation, records, metrics."""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
import pytest
import torch
from _devices import device_matches_cpu

from torchcbf.barriers import Ball, rectify
from torchcbf.dynamics import AccelUnicycle, SingleIntegrator
from torchcbf.estimation import EKF, GaussianSensor
from torchcbf.filters import SafetyFilter
from torchcbf.integrators import step
from torchcbf.sim import (
    ClosedLoop,
    Goal,
    Nominal,
    Trajectory,
    metrics,
    simulate,
    summarize,
    wilson_interval,
)


class _Plan(NamedTuple):
    u: torch.Tensor
    plan: torch.Tensor


class _TowardsOrigin:
    """A toy planner: a constant-velocity plan towards the origin, recording its calls."""

    dt = 0.2

    def __init__(self) -> None:
        self.calls: list[float] = []

    def reset(self) -> None:
        self.calls.clear()

    def __call__(self, x: torch.Tensor, t: float) -> _Plan:
        self.calls.append(t)
        plan = torch.stack([-x * (1.0 + i) for i in range(5)], dim=1)
        return _Plan(plan[:, 0], plan)


def _heading_controller(x: torch.Tensor, t: float) -> torch.Tensor:
    goal = x.new_tensor([2.0, 4.0])
    d = goal - x[..., :2]
    heading = torch.atan2(d[..., 1], d[..., 0])
    err = torch.atan2(torch.sin(heading - x[..., 3]), torch.cos(heading - x[..., 3]))
    v_d = torch.clamp(d.norm(dim=-1), max=2.0)
    return torch.stack([v_d - x[..., 2], 10.0 * err], -1)


def test_batch_equals_single_runs_with_same_seeds() -> None:
    dyn = AccelUnicycle(sigma=0.28).double()
    x0 = torch.tensor([[0.0, 0.0, 0.0, math.pi / 4]], dtype=torch.float64).repeat(4, 1)
    x0[:, 0] += torch.arange(4, dtype=torch.float64) * 0.1
    seeds = [11, 5, 7, 3]
    sensor = GaussianSensor(std=0.05, state_dim=4).double()
    batch = simulate(
        dyn, x0, 40, 0.01, nominal=_heading_controller, sensor=sensor, seed=seeds, progress=False
    )
    for b in range(4):
        single = simulate(
            dyn,
            x0[b : b + 1],
            40,
            0.01,
            nominal=_heading_controller,
            sensor=sensor,
            seed=[seeds[b]],
            progress=False,
        )
        torch.testing.assert_close(batch.x[b], single.x[0], atol=1e-12, rtol=0)
        torch.testing.assert_close(batch.x_hat[b], single.x_hat[0], atol=1e-12, rtol=0)
    again = simulate(
        dyn, x0, 40, 0.01, nominal=_heading_controller, sensor=sensor, seed=seeds, progress=False
    )
    assert torch.equal(batch.x, again.x)
    other = simulate(
        dyn, x0, 40, 0.01, nominal=_heading_controller, sensor=sensor, seed=0, progress=False
    )
    assert not torch.equal(batch.x, other.x)


def test_noise_free_loop_matches_hand_written_loop(dtype: torch.dtype, device) -> None:
    dyn = SingleIntegrator(2, u_min=-0.5, u_max=0.5).to(device=device, dtype=dtype)
    x0 = torch.tensor([[1.0, -2.0], [0.3, 0.1]], device=device, dtype=dtype)
    traj = simulate(dyn, x0, 30, 0.1, nominal=lambda x, t: -2.0 * x, progress=False)
    x = x0
    for k in range(30):
        u = torch.clamp(-2.0 * x, -0.5, 0.5)
        torch.testing.assert_close(traj.u[:, k], u)
        x = step(dyn, x, u, 0.1)
    torch.testing.assert_close(traj.x[:, -1], x)
    assert traj.t.shape == (31,) and traj.x.shape == (2, 31, 2) and traj.u.shape == (2, 30, 2)
    assert traj.h is None and traj.status is None and not bool(traj.failed.any())


@pytest.mark.parametrize("barriers", [1, 2])
def test_an_empty_batch_simulates_nothing(barriers: int) -> None:
    dyn = SingleIntegrator(2, u_min=-0.5, u_max=0.5)
    balls = [Ball([1.0, 0.0], 0.3), Ball([0.0, 1.0], 0.2)][:barriers]
    filt = SafetyFilter(dyn, balls)
    traj = simulate(
        dyn, torch.zeros(0, 2), 5, 0.1, nominal=lambda x, t: -x, safety_filter=filt, progress=False
    )
    assert traj.x.shape == (0, 6, 2) and traj.u.shape == (0, 5, 2)
    assert traj.h.shape == (0, 5, barriers) and traj.status.shape == (0, 5)
    assert traj.failed.shape == (0,)


def test_non_finite_scenario_is_flagged_and_isolated() -> None:
    dyn = SingleIntegrator(2).double()
    x0 = torch.tensor([[1.0, 1.0], [float("nan"), 0.0], [2.0, 0.0]], dtype=torch.float64)

    def nominal(x: torch.Tensor, t: float) -> torch.Tensor:
        u = -x
        if t > 0.45:  # a controller that fails for scenario 2 after a while
            u = u.clone()
            u[2] = float("inf")
        return u

    traj = simulate(dyn, x0, 10, 0.1, nominal=nominal, progress=False)
    assert traj.failed.tolist() == [False, True, True]
    assert traj.fail_step.tolist() == [-1, 0, 5]
    clean = simulate(dyn, x0[:1], 10, 0.1, nominal=lambda x, t: -x, progress=False)
    torch.testing.assert_close(traj.x[0], clean.x[0])
    assert torch.isfinite(traj.x[2]).all() and torch.isfinite(traj.u).all()
    # the failed scenario is frozen at its last finite state
    torch.testing.assert_close(traj.x[2, 6:], traj.x[2, 5].expand(5, 2))


@pytest.mark.parametrize("estimator", [False, True])
def test_a_sensor_that_goes_non_finite_fails_its_row_with_or_without_an_estimator(estimator):
    """``log`` of a coordinate that turns negative: the row is flagged where its measurement
    first is NaN (the estimator would otherwise keep its old estimate, running blind)."""
    from torchcbf.estimation import FunctionSensor

    dyn = SingleIntegrator(2).double()
    sensor = FunctionSensor(lambda x: torch.stack([torch.log(x[..., 0]), x[..., 1]], -1),
                            std=[1e-3, 1e-3], state_dim=2)  # fmt: skip
    x0 = torch.tensor([[1.0, 0.0], [0.25, 0.0]], dtype=torch.float64)
    u = torch.tensor([[0.5, 0.0], [-1.0, 0.0]], dtype=torch.float64)
    kw = {"estimator": EKF(dyn, sensor, Q=1e-4)} if estimator else {}
    traj = simulate(dyn, x0, 6, 0.1, nominal=lambda x, t: u, sensor=sensor, progress=False, **kw)
    assert traj.failed.tolist() == [False, True]
    assert traj.fail_step.tolist() == [-1, 3]


def test_planner_at_lower_rate_follows_its_plan() -> None:
    dyn = SingleIntegrator(2).double()
    planner = _TowardsOrigin()
    x0 = torch.ones(2, 2, dtype=torch.float64)
    traj = simulate(
        dyn, x0, 12, 0.1, planner=planner, planner_every=4, snapshot_steps=[0, 8], progress=False
    )
    assert planner.calls == pytest.approx([0.0, 0.4, 0.8])
    assert set(traj.planner) == {0, 8}
    # steps 0..3 after a replan use plan indices 0, 0, 1, 1 (planner dt 0.2, loop dt 0.1)
    plan0 = traj.planner[0].plan
    torch.testing.assert_close(traj.u[:, 1], plan0[:, 0])
    torch.testing.assert_close(traj.u[:, 2], plan0[:, 1])
    # a nominal controller receives the planner's control
    seen: list[torch.Tensor] = []
    simulate(
        dyn,
        x0,
        3,
        0.1,
        planner=_TowardsOrigin(),
        nominal=lambda x, t, up: seen.append(up) or up,
        progress=False,
    )
    assert len(seen) == 3


def test_trajectory_round_trips(tmp_path) -> None:
    dyn = SingleIntegrator(2)
    traj = simulate(
        dyn, torch.randn(3, 2), 5, 0.1, planner=_TowardsOrigin(), snapshot_steps=[0], progress=False
    )
    path = tmp_path / "traj.pt"
    traj.save(path)
    loaded = Trajectory.load(path)
    assert torch.equal(loaded.x, traj.x) and torch.equal(
        loaded.planner[0].plan, traj.planner[0].plan
    )
    arrays = traj.numpy()
    assert arrays["x"].shape == (3, 6, 2) and arrays["planner"][0]["plan"].shape == (3, 5, 2)
    assert traj.to("cpu").u.device.type == "cpu"
    one = traj.scenario(1)
    assert torch.equal(one.x[0], traj.x[1])
    assert not any(p.name.startswith(".") for p in tmp_path.iterdir())  # no temporary left


class _Payload:
    """Unpickling this object writes a file (as a crafted file could run any command)."""

    def __init__(self, marker) -> None:
        self.marker = marker

    def __reduce__(self):
        return (open, (str(self.marker), "w"))


def test_trajectory_load_refuses_a_crafted_pickle(tmp_path) -> None:
    marker = tmp_path / "ran"
    zero = lambda x, t: torch.zeros_like(x)  # noqa: E731
    traj = simulate(SingleIntegrator(2), torch.zeros(1, 2), 2, 0.1, nominal=zero, progress=False)
    fields = {f: getattr(traj, f) for f in ("t", "x", "x_hat", "u_nom", "u", "h", "status")}
    crafted = {**fields, "failed": traj.failed, "fail_step": traj.fail_step,
               "planner": {0: _Payload(marker)}}  # fmt: skip
    path = tmp_path / "evil.pt"
    torch.save(crafted, path)
    with pytest.raises(ValueError, match="tensors only"):
        Trajectory.load(path)
    assert not marker.exists()


def test_metrics_against_a_loop() -> None:
    dyn = SingleIntegrator(2).double()
    x0 = torch.tensor([[-2.0, 0.05], [-2.0, 1.5], [-2.0, -0.3]], dtype=torch.float64)
    traj = simulate(
        dyn, x0, 40, 0.1, nominal=lambda x, t: x.new_tensor([1.0, 0.0]).expand_as(x), progress=False
    )

    def ball(x: torch.Tensor) -> torch.Tensor:
        return (x**2).sum(-1) - 0.5**2

    goals = [Goal((2.0, 0.0), 0.5, deadline=3.9)]
    m = metrics(traj, barriers=[ball], goals=goals, segment_points=0)  # the samples alone
    for b in range(3):
        hb = [float(ball(traj.x[b, k])) for k in range(41)]
        hit = [k for k, v in enumerate(hb) if v < 0]
        assert bool(m["collision"][b]) == bool(hit)
        assert float(m["min_h"][b]) == pytest.approx(min(hb))
        if hit:
            assert float(m["first_collision_time"][b]) == pytest.approx(0.1 * hit[0])
        else:
            assert math.isnan(float(m["first_collision_time"][b]))
        reached = [
            k
            for k in range(41)
            if float((traj.x[b, k] - traj.x.new_tensor([2.0, 0.0])).norm()) <= 0.5
            and k * 0.1 <= 3.9 + 1e-9
        ]
        assert bool(m["goal0_reached"][b]) == bool(reached)
    assert m["collision"].tolist() == [True, False, True]
    s = summarize(m)
    assert s["collision"]["count"] == 2 and s["collision"]["n"] == 3
    assert s["effort"]["mean"] == pytest.approx(4.0)


def test_wilson_interval_known_values() -> None:
    lo, hi = wilson_interval(0, 32)
    assert lo == 0.0 and hi == pytest.approx(0.1072, abs=1e-3)
    lo, hi = wilson_interval(16, 32)
    assert lo == pytest.approx(0.3363, abs=1e-3) and hi == pytest.approx(0.6637, abs=1e-3)


def test_bad_inputs() -> None:
    dyn = SingleIntegrator(2)
    zero = lambda x, t: torch.zeros_like(x)  # noqa: E731
    with pytest.raises(ValueError, match=r"x0 must have shape \[\.\.\., 2\]"):
        simulate(dyn, torch.zeros(3, 3), 5, 0.1, nominal=zero)
    with pytest.raises(ValueError, match="steps must be a positive int"):
        simulate(dyn, torch.zeros(3, 2), 0, 0.1, nominal=zero)
    with pytest.raises(ValueError, match="integrator must be one of"):
        simulate(dyn, torch.zeros(3, 2), 5, 0.1, integrator="heun")
    with pytest.raises(ValueError, match="an estimator needs a sensor"):
        ekf = EKF(dyn, GaussianSensor(std=0.1, state_dim=2), Q=0.01 * torch.eye(2))
        ClosedLoop(dynamics=dyn, nominal=zero, estimator=ekf)
    with pytest.raises(ValueError, match="one seed per scenario"):
        simulate(dyn, torch.zeros(3, 2), 5, 0.1, nominal=zero, seed=[1, 2])
    with pytest.raises(TypeError, match="dynamics must be a ControlAffine"):
        simulate(object(), torch.zeros(3, 2), 5, 0.1)


def test_no_controller_and_wrong_shapes_name_the_argument() -> None:
    dyn = SingleIntegrator(2)
    x0 = torch.zeros(3, 2)
    with pytest.raises(ValueError, match="a closed loop needs a controller: planner="):
        simulate(dyn, x0, 5, 0.1, progress=False)
    with pytest.raises(ValueError, match=r"nominal\(x_hat, t\) must .* \[3, 2\], got \(3, 1\)"):
        simulate(dyn, x0, 5, 0.1, nominal=lambda x, t: x[:, :1], progress=False)
    with pytest.raises(ValueError, match=r"nominal\(x_hat, t\) must .* got \(2,\)"):
        simulate(dyn, x0, 5, 0.1, nominal=lambda x, t: x[0], progress=False)
    with pytest.raises(ValueError, match=r"nominal\(x_hat, t\) must .* got list"):
        simulate(dyn, x0, 5, 0.1, nominal=lambda x, t: [0.0, 0.0], progress=False)

    class WrongG(SingleIntegrator):
        def g(self, x):
            return super().g(x)[..., :1]  # [B, 2, 1] for control_dim 2

    zero = lambda x, t: torch.zeros_like(x)  # noqa: E731
    with pytest.raises(ValueError, match=r"dynamics.g\(x\) of WrongG must have shape \[3, 2, 2\]"):
        simulate(WrongG(2), x0, 5, 0.1, nominal=zero, progress=False)


def test_differentiable_rollout_matches_finite_differences(device: torch.device) -> None:
    dyn = SingleIntegrator(2).to(device=device, dtype=torch.float64)
    gain = torch.tensor(1.5, dtype=torch.float64, device=device, requires_grad=True)
    x0 = torch.tensor([[1.0, -0.5]], dtype=torch.float64, device=device)

    def final_cost(g: torch.Tensor, differentiable: bool) -> torch.Tensor:
        traj = simulate(
            dyn,
            x0,
            10,
            0.1,
            nominal=lambda x, t: -g * x,
            progress=False,
            differentiable=differentiable,
        )
        return (traj.x[:, -1] ** 2).sum()

    cost = final_cost(gain, True)
    (grad,) = torch.autograd.grad(cost, gain)
    eps = 1e-6
    with torch.no_grad():
        fd = (final_cost(gain + eps, False) - final_cost(gain - eps, False)) / (2 * eps)
    torch.testing.assert_close(grad, fd, atol=1e-7, rtol=1e-6)
    assert not final_cost(gain, False).requires_grad


def test_sensor_and_estimator_close_the_loop(device: torch.device) -> None:
    """With a noisy position sensor, the EKF estimate the controller sees is closer to the
    truth than the raw measurements are (a property of the noise, on every device)."""
    f64 = {"dtype": torch.float64, "device": device}
    dyn = AccelUnicycle(sigma=0.05).to(**f64)
    sensor = GaussianSensor(C=torch.eye(4, **f64)[:2], std=0.2).to(**f64)
    ekf = EKF(dyn, sensor).to(**f64)
    x0 = torch.tensor([0.0, 0.0, 0.5, math.pi / 4], **f64).repeat(64, 1)
    P0 = 1e-4 * torch.eye(4, **f64)
    traj = simulate(
        dyn,
        x0,
        200,
        0.01,
        nominal=_heading_controller,
        sensor=sensor,
        estimator=ekf,
        P0=P0,
        progress=False,
    )
    assert traj.x.device.type == device.type and traj.x_hat.device.type == device.type
    est_err = (traj.x_hat[:, 50:, :2] - traj.x[:, 50:, :2]).norm(dim=-1).pow(2).mean().sqrt()
    assert float(est_err) < 0.5 * 0.2 * math.sqrt(2)
    assert not bool(traj.failed.any())


def test_metrics_rejects_what_is_not_a_trajectory() -> None:
    with pytest.raises(TypeError, match="trajectory must be a Trajectory"):
        metrics("traj")  # type: ignore[arg-type]


@pytest.mark.parametrize("total", [1, 7, 16, 32, 128, 1000])
def test_wilson_interval_contains_the_rate(total: int) -> None:
    for k in range(total + 1):
        lo, hi = wilson_interval(k, total)
        assert 0.0 <= lo <= k / total <= hi <= 1.0


def test_metrics_sees_a_collision_between_two_samples() -> None:
    from torchcbf.barriers import Ball

    dyn = SingleIntegrator(2)
    x0 = torch.tensor([[-5.0, 0.0], [-5.0, 3.0]])  # the second passes 3 m beside the ball
    right = lambda x, t: torch.tensor([2.0, 0.0]).expand_as(x)  # noqa: E731
    traj = simulate(dyn, x0, 2, 5.0, nominal=right, progress=False)  # samples at x = -5, 5, 15
    ball = Ball(torch.tensor([0.0, 0.0]), 1.0)
    assert (ball(traj.x) > 0).all()  # no sample is inside
    m = metrics(traj, barriers=[ball])
    assert m["collision"].tolist() == [True, False]
    assert m["collision_between_samples"].tolist() == [True, False]
    # entered at x = -1: 2 s in; the first segment point inside is x = -5 + 10 * 4/9, t = 20/9
    assert m["first_collision_time"][0].item() == pytest.approx(20 / 9, rel=1e-6)
    assert math.isnan(m["first_collision_time"][1].item())
    assert m["min_h"][0].item() == pytest.approx(24.0)  # over the samples: (5^2 - 1)
    samples_only = metrics(traj, barriers=[ball], segment_points=0)
    assert samples_only["collision"].tolist() == [False, False]
    assert "collision_between_samples" not in samples_only
    with pytest.raises(ValueError, match="segment_points"):
        metrics(traj, barriers=[ball], segment_points=-1)
    # a collision at a sample is not counted as between samples, and its time is the sample's
    inside = simulate(dyn, torch.tensor([[0.0, 0.5]]), 2, 5.0, nominal=right, progress=False)
    m = metrics(inside, barriers=[ball])
    assert m["collision"].tolist() == [True] and m["collision_between_samples"].tolist() == [False]
    assert m["first_collision_time"].tolist() == [0.0]
    # per obstacle: a sample inside one ball does not hide a segment jumping over another
    far = Ball(torch.tensor([5.0, 0.5]), 1.0)  # crossed between x = 0 and 10, no sample in it
    m = metrics(inside, barriers=[ball, far])
    assert m["collision_between_samples"].tolist() == [True]


def test_metrics_read_a_moving_obstacle_at_each_states_time() -> None:
    """A ball crossing the robot's path at 1 m/s: read at t = 0 it stayed 2 m away (min h
    3.91, no collision); at the states' own times the robot meets it at t = 2."""
    from torchcbf.barriers import Ball
    from torchcbf.viz import barrier_traces

    ball = Ball(center=[2.0, -2.0], radius=0.3, velocity=[0.0, 1.0])
    right = lambda x, t: torch.tensor([[1.0, 0.0]]).expand_as(x)  # noqa: E731
    traj = simulate(SingleIntegrator(2), torch.zeros(1, 2), 40, 0.1, nominal=right, progress=False)
    m = metrics(traj, barriers=[ball])
    exact = ball(traj.x[0], traj.t.float())
    assert m["collision"].tolist() == [True]
    torch.testing.assert_close(m["min_h"], exact.min().reshape(1))
    assert m["first_collision_time"][0] < 2.0  # entered before the centres align
    traces = torch.as_tensor(barrier_traces(traj, [ball])[0])
    torch.testing.assert_close(traces, exact, rtol=1e-6, atol=1e-6)


def test_trajectory_load_names_missing_fields(tmp_path) -> None:
    path = tmp_path / "partial.pt"
    torch.save({"t": torch.zeros(2)}, path)
    with pytest.raises(ValueError, match="missing fail_step, failed"):
        Trajectory.load(path)


def _zero(x: torch.Tensor, t: float) -> torch.Tensor:
    return torch.zeros_like(x)


def test_a_file_that_is_no_torch_save_is_a_value_error(tmp_path) -> None:
    for name, content in (("empty.pt", b""), ("text.pt", b"hello"), ("cut.pt", None)):
        path = tmp_path / name
        if content is None:  # a real trajectory file cut in half
            traj = simulate(
                SingleIntegrator(2), torch.zeros(2, 2), 3, 0.1, nominal=_zero, progress=False
            )
            traj.save(path)
            path.write_bytes(path.read_bytes()[: path.stat().st_size // 2])
        else:
            path.write_bytes(content)
        with pytest.raises(ValueError, match="not a file torch.save wrote"):
            Trajectory.load(path)
    with pytest.raises(FileNotFoundError):
        Trajectory.load(tmp_path / "missing.pt")


def test_snapshots_of_dataclasses_and_nested_named_tuples_round_trip(tmp_path) -> None:
    """A planner output may be a dataclass (the protocol asks for ``.u`` and ``.plan``):
    ``save`` wrote it as an object ``load`` then refused; named tuples inside a tuple came
    back as tagged dicts."""
    import dataclasses

    class Stage(NamedTuple):
        mean: torch.Tensor

    @dataclasses.dataclass
    class Plan:
        u: torch.Tensor
        plan: torch.Tensor
        stages: tuple

    traj = simulate(SingleIntegrator(2), torch.zeros(2, 2), 3, 0.1, nominal=_zero, progress=False)
    stages = (Stage(torch.ones(2, 2)), Stage(torch.zeros(2, 2)))
    traj.planner = {0: Plan(torch.ones(2, 2), torch.zeros(2, 4, 2), stages)}
    path = tmp_path / "snap.pt"
    traj.save(path)
    back = Trajectory.load(path).planner[0]
    assert type(back).__name__ == "Plan" and back._fields == ("u", "plan", "stages")
    assert isinstance(back.stages, tuple) and type(back.stages[1]).__name__ == "Stage"
    assert torch.equal(back.stages[0].mean, torch.ones(2, 2))
    as_numpy = traj.numpy()["planner"][0]
    assert isinstance(as_numpy["stages"][0]["mean"], np.ndarray)
    # one scenario's file holds that row only
    one = tmp_path / "one.pt"
    traj.scenario(1).save(one)
    assert one.stat().st_size < path.stat().st_size


def test_the_swept_check_in_slices_equals_the_whole(monkeypatch) -> None:
    import importlib

    from torchcbf.barriers import Ball

    module = importlib.import_module("torchcbf.sim.metrics")
    x = torch.randn(3, 50, 2, generator=torch.Generator().manual_seed(0)).cumsum(1)
    t = torch.linspace(0.0, 1.0, 50)
    ball = [Ball([0.0, 0.0], 2.0)]
    whole, times = module._swept(ball, x, t, 8)
    monkeypatch.setattr(module, "SWEPT_CHUNK_ELEMENTS", 3 * 8 * 2 * 7)  # 7 steps a slice
    sliced, sliced_times = module._swept(ball, x, t, 8)
    assert torch.equal(whole, sliced) and torch.equal(times, sliced_times)
    assert whole.any() and not whole.all()


def test_a_closed_loop_object_runs_the_same_loop_as_simulate(device: torch.device) -> None:
    dyn = SingleIntegrator(2, u_min=-1.0, u_max=1.0).to(device)
    goal = torch.tensor([1.0, 2.0], device=device)
    nominal = lambda x, t: 2.0 * (goal - x)  # noqa: E731
    x0 = torch.randn(4, 2, generator=torch.Generator().manual_seed(0)).to(device)
    loop = ClosedLoop(dynamics=dyn, nominal=nominal, integrator="euler")
    assert isinstance(nominal, Nominal)
    a = loop.simulate(x0, 20, 0.05, progress=False)
    b = simulate(dyn, x0, 20, 0.05, nominal=nominal, integrator="euler", progress=False)
    assert torch.equal(a.x, b.x) and torch.equal(a.u, b.u)
    # the loop by hand: clipped proportional control, Euler steps
    x = x0.clone()
    for _ in range(20):
        x = x + 0.05 * (2.0 * (goal - x)).clamp(-1.0, 1.0)
    torch.testing.assert_close(a.x[:, -1], x)


def test_filtered_loop_on_device_equals_cpu(dtype: torch.dtype, device: torch.device) -> None:
    """A noise-free filtered closed loop (unicycle, two rectified balls on the way to the
    goal, heading controller) gives the CPU's answers on every device."""
    x0 = torch.tensor([[0.0, 0.0, 0.0, math.pi / 4]]).repeat(8, 1)
    x0[:, 1] += torch.linspace(-0.5, 0.5, 8)

    def run(dev: torch.device):
        dyn = AccelUnicycle().to(device=dev, dtype=dtype)
        balls = Ball(torch.tensor([[1.0, 2.0], [1.5, 2.9]]), torch.tensor([0.3, 0.25]))
        # rectified on the CPU: its relative-degree check draws sample states
        barrier = rectify(balls, AccelUnicycle(), form="exponential").to(device=dev, dtype=dtype)
        filt = SafetyFilter(dyn, barrier, alpha=2.0).to(device=dev, dtype=dtype)
        start = x0.to(device=dev, dtype=dtype)
        traj = simulate(
            dyn, start, 60, 0.02, nominal=_heading_controller, safety_filter=filt, progress=False
        )
        return traj.x, traj.u_nom, traj.u, traj.h, traj.status

    loose = {} if dtype == torch.float64 else {"rtol": 1e-3, "atol": 1e-4}
    x, u_nom, u, h, status = device_matches_cpu(run, device, dtype, **loose)
    assert bool(torch.isfinite(x).all()) and bool(h.amin() > -1e-6)
    assert bool((u - u_nom).abs().amax() > 0.1)  # the filter acted


def test_a_frozen_row_records_no_barrier_values_and_is_no_collision() -> None:
    """A row whose nominal control goes NaN freezes; its filter then sees a zero stand-in
    state, so from the next step on nothing of it is recorded (h NaN, status NON_FINITE)
    and the metrics read its recorded steps only: no collision where it never was."""
    from torchcbf.filters import FilterStatus

    ball = Ball([0.0, 0.0], 0.5)

    def nominal(x, t):
        u = torch.ones_like(x)
        if t > 0.25:
            u[1] = math.nan
        return u

    x0 = torch.tensor([[2.0, 0.0], [2.0, 0.0]])
    traj = simulate(
        SingleIntegrator(2),
        x0,
        steps=6,
        dt=0.1,
        nominal=nominal,
        safety_filter=SafetyFilter(SingleIntegrator(2), ball),
        progress=False,
    )
    assert traj.failed.tolist() == [False, True] and int(traj.fail_step[1]) == 3
    # from the failing step on (the filter saw a zero stand-in for the nominal there)
    assert torch.isnan(traj.h[1, 3:]).all() and torch.isfinite(traj.h[1, :3]).all()
    assert (traj.status[1, 3:] == FilterStatus.NON_FINITE).all()
    assert (traj.status[1, :3] != FilterStatus.NON_FINITE).all()
    m = metrics(traj)
    assert m["collision"].tolist() == [False, False]
    torch.testing.assert_close(m["min_h"], torch.tensor([3.75, 3.75]))  # h at the start


def test_times_are_exact_steps_at_a_large_start_time_in_float32() -> None:
    """Times are float64: at t0 = 1e5 float32 times lost the step (dt read 0.0078 for 0.01)
    and a goal reached at its deadline was missed."""
    traj = simulate(SingleIntegrator(1), torch.zeros(1, 1), steps=100, dt=0.01, t0=1e5,
                    nominal=lambda x, t: torch.ones_like(x), progress=False)  # fmt: skip
    assert traj.t.dtype == torch.float64
    assert traj.dt == pytest.approx(0.01, rel=1e-9)
    assert float(metrics(traj)["effort"]) == pytest.approx(1.0, rel=1e-6)
    line = simulate(SingleIntegrator(1), torch.zeros(1, 1), steps=20, dt=0.1,
                    nominal=lambda x, t: torch.ones_like(x), progress=False)  # fmt: skip
    m = metrics(line, goals=[Goal([0.9], 0.001, index=(0,), deadline=0.9)])
    assert bool(m["goal0_reached"]) and float(m["goal0_time"]) == pytest.approx(0.9)


def test_one_scenario_of_a_trajectory_by_index() -> None:
    traj = simulate(SingleIntegrator(2), torch.arange(6.0).reshape(3, 2), steps=2, dt=0.1,
                    nominal=lambda x, t: -x, progress=False)  # fmt: skip
    assert torch.equal(traj.scenario(-1).x, traj.x[2:])
    for index in (3, -4):
        with pytest.raises(IndexError, match="batch of 3"):
            traj.scenario(index)
    for index in (True, 1.0, torch.tensor(True), torch.tensor([1])):
        with pytest.raises(TypeError, match="index must be an int"):
            traj.scenario(index)
    # an argmax (a 0-d integer tensor) and NumPy's ints are indices
    worst = traj.x[:, -1].norm(dim=-1).argmax()
    assert torch.equal(traj.scenario(worst).x, traj.x[2:])
    assert torch.equal(traj.scenario(np.int64(1)).x, traj.x[1:2])


def test_a_stateful_nominal_controller_is_reset_before_each_run() -> None:
    """A nominal controller with reset() (a roadmap controller's progress) is reset as the
    planner is: the same loop run twice gives the same trajectories."""

    class Counting:
        def __init__(self) -> None:
            self.calls = 0

        def reset(self) -> None:
            self.calls = 0

        def __call__(self, x, t):
            self.calls += 1
            return torch.full_like(x, float(self.calls))

    loop = ClosedLoop(dynamics=SingleIntegrator(1), nominal=Counting())
    runs = [loop.simulate(torch.zeros(2, 1), steps=5, dt=0.1, progress=False) for _ in range(2)]
    assert torch.equal(runs[0].x, runs[1].x)


def test_counts_seeds_and_barrier_lists_in_their_usual_forms() -> None:
    """wilson_interval refuses counts that are no counts; a NumPy or one-value tensor seed
    is one integer; metrics takes its barriers as an nn.ModuleList too."""
    import numpy as np
    from torch import nn

    for successes, total in ((3, -2), (5, 3), (-1, 10), (1.5, 3)):
        with pytest.raises(ValueError, match="successes|total"):
            wilson_interval(successes, total)
    loop = dict(steps=3, dt=0.1, nominal=lambda x, t: -x, progress=False)
    dyn = SingleIntegrator(2, sigma=0.1)
    x0 = torch.ones(3, 2)
    want = simulate(dyn, x0, seed=5, **loop).x
    for seed in (np.int64(5), torch.tensor(5)):
        assert torch.equal(simulate(dyn, x0, seed=seed, **loop).x, want)
    # the noise streams are 32-bit: 2^32 would repeat seed 0, so it is refused
    for seed in (-1, 2**32 - 2, torch.tensor([0, 1, 2**32])):
        with pytest.raises(ValueError, match="seed"):
            simulate(dyn, x0, seed=seed, **loop)
    assert simulate(dyn, x0, seed=2**32 - 3, **loop).x.shape == (3, 4, 2)
    traj = simulate(dyn, x0, seed=5, **loop)
    balls = [Ball([0.0, 0.0], 0.5), Ball([2.0, 2.0], 0.3)]
    a = metrics(traj, barriers=nn.ModuleList(balls))
    b = metrics(traj, barriers=balls)
    assert torch.equal(a["min_h"], b["min_h"])


def test_a_snapshot_step_that_is_no_planning_step_is_refused() -> None:
    """With planner_every=3, step 100 has no planner output of its own: refused, naming the
    planning steps around it (it was dropped without a word)."""

    def planner(x, t):
        return _Plan(u=-x, plan=(-x).unsqueeze(1).expand(-1, 4, -1))

    loop = ClosedLoop(dynamics=SingleIntegrator(2), planner=planner, planner_every=3)
    with pytest.raises(ValueError, match="take 99 or 102"):
        loop.simulate(torch.zeros(1, 2), steps=120, dt=0.1, snapshot_steps=(100,), progress=False)
    traj = loop.simulate(torch.zeros(1, 2), steps=120, dt=0.1, snapshot_steps=(99,),
                         progress=False)  # fmt: skip
    assert list(traj.planner) == [99]


def test_metrics_of_an_empty_batch_with_barriers() -> None:
    traj = simulate(SingleIntegrator(2), torch.zeros(0, 2), steps=3, dt=0.1,
                    nominal=lambda x, t: -x, progress=False)  # fmt: skip
    for points in (0, 8):
        m = metrics(traj, barriers=[Ball([1.0, 0.0], 0.3)], segment_points=points)
        assert m["collision"].shape == (0,) and m["min_h"].shape == (0,)


def test_estimator_priors_and_sensor_size_name_the_argument() -> None:
    dyn = SingleIntegrator(2)
    zero = lambda x, t: torch.zeros_like(x)  # noqa: E731
    ekf = EKF(dyn, GaussianSensor(std=0.1, state_dim=2), Q=0.01)
    loop = ClosedLoop(dynamics=dyn, nominal=zero, sensor=ekf.sensor, estimator=ekf)
    x0 = torch.zeros(3, 2)
    with pytest.raises(ValueError, match=r"x0_hat must broadcast to \[3, 2\], got \(4,\)"):
        loop.simulate(x0, 2, 0.1, x0_hat=torch.zeros(4), progress=False)
    with pytest.raises(ValueError, match=r"P0 must broadcast to \[3, 2, 2\], got \(2, 2, 2\)"):
        loop.simulate(x0, 2, 0.1, P0=torch.eye(2).expand(2, 2, 2), progress=False)
    # a prior shared by every row broadcasts
    traj = loop.simulate(x0, 2, 0.1, x0_hat=torch.ones(2), P0=torch.eye(2), progress=False)
    assert torch.equal(traj.x_hat[:, 0], torch.ones(3, 2))
    # without an estimator the measurement stands for the state: it must be one
    partial = ClosedLoop(dynamics=dyn, nominal=zero, sensor=GaussianSensor(torch.ones(1, 2), 0.1))
    with pytest.raises(ValueError, match="must then be a full state of size 2: GaussianSensor"):
        partial.simulate(x0, 2, 0.1, progress=False)


def test_a_start_time_is_a_finite_number_and_the_controllers_see_the_recorded_times() -> None:
    model, x0 = SingleIntegrator(1).double(), torch.zeros(2, 1, dtype=torch.float64)
    seen: list[float] = []

    def nominal(x, t):
        seen.append(t)
        return torch.zeros_like(x)

    traj = simulate(model, x0, 4, 0.01, nominal=nominal, t0=np.float32(1e5), progress=False)
    assert seen == traj.t[:-1].tolist()
    for t0 in (math.nan, math.inf):
        with pytest.raises(ValueError, match="t0 must be a finite number"):
            simulate(model, x0, 2, 0.1, nominal=nominal, t0=t0, progress=False)
    with pytest.raises(TypeError, match="t0 must be a Python number"):
        simulate(model, x0, 2, 0.1, nominal=nominal, t0=torch.zeros(2), progress=False)


def test_the_estimators_priors_are_checked_under_their_own_names() -> None:
    model = SingleIntegrator(2).double()
    sensor = GaussianSensor(std=0.1, state_dim=2).double()
    kw = {"nominal": lambda x, t: -x, "sensor": sensor, "estimator": EKF(model, sensor, Q=0.01)}
    x0 = torch.zeros(2, 2, dtype=torch.float64)
    with pytest.raises(ValueError, match="x0_hat must not contain NaN"):
        simulate(model, x0, 2, 0.1, x0_hat=torch.tensor([math.nan, 0.0]).double(), **kw)
    with pytest.raises(TypeError, match="x0_hat has dtype torch.float32 but x0"):
        simulate(model, x0, 2, 0.1, x0_hat=torch.zeros(2), **kw)
    with pytest.raises(TypeError, match="P0 has dtype torch.float32 but x0"):
        simulate(model, x0, 2, 0.1, P0=torch.eye(2), **kw)


def test_a_failed_rows_last_estimate_is_frozen_like_the_others() -> None:
    model = SingleIntegrator(2, disturbance_bound=1.0).double()
    sensor = GaussianSensor(std=0.1, state_dim=2).double()

    def disturbance(x, t):
        w = torch.zeros_like(x)
        if t > 0.15:
            w[1] = math.inf
        return w

    x0 = torch.tensor([[0.0, 0.0], [1.0, 1.0]], dtype=torch.float64)
    traj = simulate(model, x0, 5, 0.1, nominal=lambda x, t: -x, sensor=sensor,
                    estimator=EKF(model, sensor, Q=0.01), disturbance=disturbance,
                    progress=False)  # fmt: skip
    k = int(traj.fail_step[1])
    assert 0 < k < 5
    assert bool((traj.x_hat[1, k:] == 0).all())


def test_a_measurement_that_fails_at_the_last_step_fails_the_row() -> None:
    from torchcbf.estimation import FunctionSensor

    model = SingleIntegrator(1).double()
    # sqrt(min(x, 0.25) - 0.25) is 0 while x >= 0.25 and NaN below it
    sensor = FunctionSensor(lambda x: x.clamp_max(0.25).sub(0.25).sqrt().add(x), std=[1e-9])
    x0 = torch.tensor([[1.0], [2.0]], dtype=torch.float64)
    traj = simulate(model, x0, 4, 0.25, nominal=lambda x, t: -torch.ones_like(x),
                    sensor=sensor.double(), progress=False)  # fmt: skip
    assert traj.failed.tolist() == [True, False] and traj.fail_step.tolist() == [4, -1]
    assert bool(torch.isfinite(traj.x_hat).all())


def test_a_goal_is_checked_when_made():
    for kwargs, error, message in (
        ({"center": (1.0,), "radius": 0.2}, ValueError, "center has 1 entries but index names 2"),
        ({"center": (1.0, 0.0), "radius": -0.5}, ValueError, "radius must be a finite number"),
        ({"center": (1.0, 0.0), "radius": math.nan}, ValueError, "radius must be a finite"),
        ({"center": (math.nan, 0.0), "radius": 0.2}, ValueError, "center"),
        ({"center": (1.0, 0.0), "radius": 0.2, "deadline": math.nan}, ValueError, "deadline"),
        ({"center": (1.0, 0.0), "radius": 0.2, "index": (0, 0)}, ValueError, "index"),
    ):
        with pytest.raises(error, match=message):
            Goal(**kwargs)
    assert Goal((1.0,), 0.2, index=(0,)).radius == 0.2


def test_metrics_without_barriers_count_no_collision() -> None:
    """A filter of Lyapunov functions alone records ``h [B, T, 0]``; ``barriers=[]``."""
    from torchcbf.barriers import QuadraticLyapunov

    dyn = SingleIntegrator(2, u_min=-1, u_max=1).double()
    clf_only = SafetyFilter(dyn, lyapunovs=[QuadraticLyapunov([0.0, 0.0])])
    x0 = torch.ones(2, 2, dtype=torch.float64)
    for traj, kw in (
        (simulate(dyn, x0, 5, 0.1, safety_filter=clf_only, progress=False), {}),
        (simulate(dyn, x0, 5, 0.1, nominal=lambda x, t: -x, progress=False), {"barriers": []}),
    ):
        out = metrics(traj, **kw)
        assert out["collision"].tolist() == [False, False]
        assert out["min_h"].tolist() == [math.inf, math.inf]
        assert bool(out["first_collision_time"].isnan().all())
