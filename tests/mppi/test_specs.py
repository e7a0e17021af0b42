"""Timed reach-avoid specifications: robustness against the boolean success check and a
Python loop; planning costs against a per-sample reference implementation."""

from __future__ import annotations

import math

import pytest
import torch
from _devices import device_matches_cpu
from _host_traffic import HostTraffic

from torchcbf.mppi import Always, And, Avoid, Eventually, History, Or, Reach
from torchcbf.mppi.history import HistoryBuffer
from torchcbf.mppi.specs import plan_of

G1, G2, OBST = (4.0, 4.0), (6.0, 9.0), (3.0, 3.0)


def _tol(dtype: torch.dtype) -> float:
    return 1e-10 if dtype == torch.float64 else 1e-4


def _spec_a() -> And:
    return And(
        Avoid(OBST, 0.6, weight=0.3, eps=0.01),
        Reach(G1, 0.5, (0.0, 3.5), weight=10.0),
        Reach(G2, 0.5, (3.6, 5.0), weight=2.0),
        Reach((4.0, 1.0), 0.5, (5.1, 10.0), weight=1.0),
    )


def _success_loop(traj: torch.Tensor, times: torch.Tensor) -> tuple[bool, float]:
    """Scenario A's success and the robustness value, one trajectory, plain Python."""
    goals = [(G1, 0.0, 3.5), (G2, 3.6, 5.0), ((4.0, 1.0), 5.1, 10.0)]
    ok, rob = True, math.inf
    for g, t1, t2 in goals:
        best = -math.inf
        for x, t in zip(traj.tolist(), times.tolist(), strict=True):
            if t1 - 1e-5 <= t <= t2 + 1e-5:
                best = max(best, 0.5 - math.dist(x, g))
        ok = ok and best >= 0
        rob = min(rob, best)
    worst = min(math.dist(x, OBST) - 0.6 for x in traj.tolist())
    return ok and worst >= 0, min(rob, worst)


def test_robustness_equals_success_check(dtype):
    gen = torch.Generator().manual_seed(1)
    spec = _spec_a()
    times = torch.arange(101, dtype=dtype) * 0.1
    # trajectories through g1 -> g2 -> g3 with noise: some succeed, some do not
    knots = torch.tensor([[0, 0], [4, 4], [6, 9], [4, 1], [4, 1]], dtype=torch.float64)
    base = torch.nn.functional.interpolate(knots.T[None], size=101, mode="linear")[0].T
    trajs = base + 0.6 * torch.randn(64, 101, 2, generator=gen, dtype=torch.float64)
    trajs[:8] = base + 0.05 * torch.randn(8, 101, 2, generator=gen, dtype=torch.float64)
    trajs = trajs.to(dtype)
    rob = spec.robustness(trajs, times)
    assert rob.shape == (64,)
    outcomes = []
    for i in range(64):
        ok, value = _success_loop(trajs[i], times)
        outcomes.append(ok)
        assert bool(rob[i] >= 0) == ok
        assert abs(float(rob[i]) - value) < 10 * _tol(dtype)
    assert any(outcomes) and not all(outcomes)
    # unbatched trajectory, times with the same batch shape
    one = spec.robustness(trajs[3], times)
    assert one.shape == () and float(one) == pytest.approx(float(rob[3]))
    two = spec.robustness(trajs[:2], times.expand(2, 101))
    torch.testing.assert_close(two, rob[:2])


def test_or_and_generic_operators(dtype):
    gen = torch.Generator().manual_seed(2)
    states = torch.randn(5, 7, 2, generator=gen, dtype=torch.float64).to(dtype)
    times = torch.linspace(0, 1, 7, dtype=dtype)
    pred = lambda x: 1.0 - x[..., 0] ** 2  # noqa: E731
    ev = Eventually(pred, (0.2, 0.6))
    al = Always(pred, (0.5, 1.0))
    window_e = (times >= 0.2 - 1e-5) & (times <= 0.6 + 1e-5)
    window_a = (times >= 0.5 - 1e-5) & (times <= 1.0 + 1e-5)
    r_e = pred(states)[:, window_e].amax(-1)
    r_a = pred(states)[:, window_a].amin(-1)
    torch.testing.assert_close(ev.robustness(states, times), r_e)
    torch.testing.assert_close(al.robustness(states, times), r_a)
    torch.testing.assert_close((ev | al).robustness(states, times), torch.maximum(r_e, r_a))
    torch.testing.assert_close((ev & al).robustness(states, times), torch.minimum(r_e, r_a))
    # empty window: Eventually is false, Always is vacuously true
    assert Eventually(pred, (5.0, 6.0)).robustness(states, times)[0] == -math.inf
    assert Always(pred, (5.0, 6.0)).robustness(states, times)[0] == math.inf


def _rollouts(dtype, B=2, K=6, T=11, seed=0):
    gen = torch.Generator().manual_seed(seed)
    return (3.0 * torch.rand(B, K, T, 2, generator=gen, dtype=torch.float64) + 2.5).to(dtype)


def test_default_cost_is_negated_robustness(dtype):
    states = _rollouts(dtype)
    pred = lambda x: 1.0 - (x[..., 0] - 4.0) ** 2  # noqa: E731
    t0 = torch.tensor([0.0, 0.3], dtype=dtype)
    dt = 0.1
    times = t0[:, None] + dt * torch.arange(11, dtype=dtype)
    for spec in (Eventually(pred, (0.2, 0.7)), Always(pred, (0.2, 0.7))):
        cost = spec(states, None, t0, dt=dt)
        want = torch.stack([-spec.robustness(states[b], times[b]) for b in range(2)])
        torch.testing.assert_close(cost, want, atol=_tol(dtype), rtol=_tol(dtype))


def _reach_cost_reference(states, times, hist_x, hist_t, hist_n, g, r, w, t1, t2):
    """Eventually/Reach planning cost, one sample at a time, plain Python."""
    B, K, T, _ = states.shape
    out = torch.zeros(B, K, dtype=torch.float64)
    c = lambda x: w * ((x[0] - g[0]) ** 2 + (x[1] - g[1]) ** 2 - r**2)  # noqa: E731
    inside = lambda t: t1 - 1e-5 <= t <= t2 + 1e-5  # noqa: E731
    for b in range(B):
        hist = [
            (hist_x[b, i].tolist(), float(hist_t[b, i]))
            for i in range(hist_n)
            if inside(float(hist_t[b, i]))
        ]
        h_min = min((c(x) for x, _ in hist), default=math.inf)
        reached = any(math.dist(x, g) <= r for x, _ in hist)
        passed = float(times[b, 0]) > t2 + 1e-5
        for k in range(K):
            if reached or passed:
                out[b, k] = h_min if math.isfinite(h_min) else 0.0
                continue
            roll = [c(states[b, k, j].tolist()) for j in range(T) if inside(float(times[b, j]))]
            roll_min = min(roll) if roll else c(states[b, k, -1].tolist())
            out[b, k] = min(roll_min, h_min)
    return out


@pytest.mark.parametrize(
    "t0, hist_pts",
    [
        ((0.0, 0.0), None),  # window inside the horizon, no history
        ((0.0, 0.2), [(4.0, 4.3), (2.0, 2.0)]),  # env 0 not yet reached, env 1 ...
        ((0.35, 0.35), [(4.1, 4.1), (3.0, 3.0)]),  # env 0 reached inside its window
        ((1.5, 0.9), [(4.0, 5.0), (4.0, 5.0)]),  # window passed (env 0) / not yet passed
        ((-2.0, -1.5), [(0.0, 0.0), (0.0, 0.0)]),  # window beyond the horizon: last state
    ],
)
def test_reach_cost_semantics(dtype, t0, hist_pts):
    states = _rollouts(dtype)
    B, K, T, _ = states.shape
    g, r, w, t1, t2 = (4.0, 4.0), 0.5, 3.0, 0.3, 0.8
    spec = Reach(g, r, (t1, t2), weight=w)
    dt = 0.1
    t0_t = torch.tensor(t0, dtype=dtype)
    times = t0_t[:, None] + dt * torch.arange(T, dtype=dtype)
    N = 8
    hist_x = torch.zeros(B, N, 2, dtype=dtype)
    hist_t = torch.zeros(B, N, dtype=dtype)
    n_rec = 0
    history = None
    if hist_pts is not None:
        n_rec = 3  # three recorded states per env: two before t0 and the current one
        for b in range(B):
            hist_x[b, 0] = torch.tensor(hist_pts[b], dtype=dtype)
            hist_x[b, 1] = torch.tensor(hist_pts[b], dtype=dtype) + 1.0
            hist_x[b, 2] = states[b, 0, 0]
            hist_t[b, :3] = t0_t[b] - torch.tensor([0.1, 0.05, 0.0], dtype=dtype)
        states[:, :, 0] = hist_x[:, 2:3]
        valid = (torch.arange(N) < n_rec).expand(B, N)
        history = History(hist_x, hist_t, valid)
    got = spec(states, None, t0_t, dt=dt, history=history)
    want = _reach_cost_reference(
        states.double(), times.double(), hist_x.double(), hist_t.double(), n_rec, g, r, w, t1, t2
    )
    torch.testing.assert_close(got.double(), want, atol=1e-4, rtol=1e-4)


def test_reached_or_passed_goal_no_longer_pulls(dtype):
    states = _rollouts(dtype)
    spec = Reach((4.0, 4.0), 0.5, (0.3, 0.8), weight=3.0)
    N = 4
    hist_x = torch.zeros(2, N, 2, dtype=dtype)
    hist_x[0, 0] = torch.tensor([4.1, 3.9], dtype=dtype)  # env 0 inside the goal at t = 0.5
    hist_t = torch.full((2, N), 0.5, dtype=dtype)
    valid = torch.zeros(2, N, dtype=torch.bool)
    valid[0, 0] = True
    history = History(hist_x, hist_t, valid)
    cost = spec(states, None, torch.tensor([0.6, 0.9], dtype=dtype), dt=0.1, history=history)
    # env 0: reached -> frozen at its history minimum; env 1: window passed -> constant 0
    want0 = 3.0 * (0.1**2 + 0.1**2 - 0.25)
    torch.testing.assert_close(cost[0], torch.full((6,), want0, dtype=dtype), atol=1e-5, rtol=0)
    assert torch.equal(cost[1], torch.zeros(6, dtype=dtype))


def test_avoid_and_combinations_cost(dtype):
    states = _rollouts(dtype)
    t0 = torch.zeros(2, dtype=dtype)
    avoid = Avoid(OBST, 0.6, weight=0.3, eps=0.01)
    dist = ((states - torch.tensor(OBST, dtype=dtype)) ** 2).sum(-1).sqrt()
    want = (0.3 / (dist - 0.6).clamp_min(0.01)).amax(-1)
    got = avoid(states, None, t0, dt=0.1)
    torch.testing.assert_close(got, want, atol=_tol(dtype), rtol=_tol(dtype))
    # barrier form: the same disc as a callable
    disc = lambda x: ((x - torch.tensor(OBST, dtype=x.dtype)) ** 2).sum(-1).sqrt() - 0.6  # noqa: E731
    got_b = Avoid(barrier=disc, weight=0.3, eps=0.01)(states, None, t0, dt=0.1)
    torch.testing.assert_close(got_b, want, atol=_tol(dtype), rtol=_tol(dtype))
    # windowed: only states with time in [0.5, 0.7] count
    got_w = Avoid(OBST, 0.6, weight=0.3, interval=(0.5, 0.7))(states, None, t0, dt=0.1)
    want_w = (0.3 / (dist[..., 5:8] - 0.6).clamp_min(0.01)).amax(-1)
    torch.testing.assert_close(got_w, want_w, atol=_tol(dtype), rtol=_tol(dtype))
    reach = Reach(G1, 0.5, (0.0, 0.5), weight=2.0)
    r_cost = reach(states, None, t0, dt=0.1)
    torch.testing.assert_close(And(avoid, reach)(states, None, t0, dt=0.1), got + r_cost)
    torch.testing.assert_close(
        Or(avoid, reach)(states, None, t0, dt=0.1), torch.minimum(got, r_cost)
    )


@pytest.mark.parametrize("T", [2, 3, 7])
def test_multi_output_predicates_hold_where_all_outputs_hold(dtype, T):
    """``Avoid(barrier=Ball of k centres)``, ``Always`` and ``Eventually`` with a ``[..., k]``
    predicate equal the same specifications over the loop's minimum of the outputs, also
    when the horizon equals ``k``; a predicate or cost of another shape names the shapes."""
    from torchcbf.barriers import Ball

    gen = torch.Generator().manual_seed(T)
    states = torch.randn(2, 4, T, 2, generator=gen, dtype=dtype)
    t0 = torch.tensor([0.0, 0.1], dtype=dtype)
    balls = Ball([[0.5, 0.5], [1.0, -0.3], [-0.4, 0.2]], torch.tensor([0.2, 0.3, 0.25]))
    balls = balls.to(dtype)
    one = [lambda x, i=i: balls(x)[..., i] for i in range(3)]
    least = lambda x: torch.stack([f(x) for f in one], -1).amin(-1)  # noqa: E731
    times = t0[:, None] + 0.1 * torch.arange(T, dtype=dtype)
    for interval in (None, (0.05, 0.15)):
        got = Avoid(barrier=balls, interval=interval, weight=0.4)(states, None, t0, dt=0.1)
        want = Avoid(barrier=least, interval=interval, weight=0.4)(states, None, t0, dt=0.1)
        torch.testing.assert_close(got, want, atol=0.0, rtol=0.0)
        for cls in (Always, Eventually):
            spec, ref = cls(balls, interval), cls(least, interval)
            got, want = spec(states, None, t0, dt=0.1), ref(states, None, t0, dt=0.1)
            torch.testing.assert_close(got, want)
            rho = spec.robustness(states, times[:, None])
            assert rho.shape == (2, 4)
            torch.testing.assert_close(rho, ref.robustness(states, times[:, None]))
    moving = Ball([[0.5, 0.5], [1.0, -0.3]], [0.2, 0.3], velocity=[[1.0, 0.0], [0.0, 1.0]])
    moving = moving.to(dtype)
    got = Avoid(barrier=moving)(states, None, t0, dt=0.1)
    c = moving.center + moving.velocity * times[:, None, :, None, None]  # [2, 1, T, 2, 2]
    d2 = ((states.unsqueeze(-2) - c) ** 2).sum(-1) - moving.radius**2  # [2, 4, T, 2]
    rho_min = d2.amin((-1, -2))
    torch.testing.assert_close(got, 1.0 / rho_min.clamp_min(0.01))
    shapes = rf"predicate must return .* of shape \(2, 4, {T}, 2\), got \(\)"
    with pytest.raises(ValueError, match=shapes):
        Always(lambda x: x.sum(), None)(states, None, t0, dt=0.1)
    with pytest.raises(ValueError, match="cost maps states"):
        Eventually(least, None, cost=lambda x: x)(states, None, t0, dt=0.1)


def test_bad_specs():
    with pytest.raises(ValueError, match="interval"):
        Reach(G1, 0.5, (3.0, 1.0))
    with pytest.raises(ValueError, match="either"):
        Avoid(OBST, 0.6, barrier=lambda x: x[..., 0])
    with pytest.raises(ValueError, match="either"):
        Avoid()
    with pytest.raises(ValueError, match="radius"):
        Reach(G1, -1.0)
    with pytest.raises(TypeError, match="Spec"):
        And(Reach(G1, 0.5), lambda s, u, t: s)  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="dt"):
        Reach(G1, 0.5)(torch.zeros(1, 2, 3, 2))


# -- on the device fixture's device against the CPU ---------------------------------------------


def _spec_zoo() -> dict[str, object]:
    """Every kind of node: discs, a barrier predicate, urgency, generic Eventually/Always, Or."""
    wall = lambda x: x[..., 1] + 0.5 * x[..., 0] - 1.0  # noqa: E731
    ring = lambda x: 2.0 - ((x[..., :2] - 4.0) ** 2).sum(-1).sqrt()  # noqa: E731
    return {
        "a": _spec_a(),
        "urgent": Reach(G1, 0.5, (0.0, 0.9), weight=3.0, urgency=0.7),
        "barrier": Avoid(barrier=wall, weight=0.3, eps=0.02, interval=(0.2, 0.8)),
        "generic": Or(Eventually(ring, (0.3, 0.6), urgency=0.2), Always(wall, (0.0, 0.5))),
    }


@pytest.mark.parametrize("name", ["a", "urgent", "barrier", "generic"])
def test_robustness_and_gradient_on_device_equal_cpu(name, dtype, device):
    """Robustness of trajectories drawn on the CPU, and its gradient to the states, on the
    device equal the CPU's (times given per trajectory, with windows that cut the horizon)."""
    gen = torch.Generator().manual_seed(3)
    trajs = 5.0 * torch.rand(16, 41, 2, generator=gen, dtype=torch.float64)
    times = (torch.arange(41, dtype=torch.float64) * 0.25).expand(16, 41).clone()
    times[::2] -= 0.3  # some trajectories start earlier: other samples fall in each window

    def run(dev: torch.device):
        spec = _spec_zoo()[name].to(dev)
        x = trajs.to(device=dev, dtype=dtype).requires_grad_()
        rob = spec.robustness(x, times.to(device=dev, dtype=dtype))
        (grad,) = torch.autograd.grad(rob.clamp(-1e3, 1e3).sum(), x)
        return rob.detach(), grad

    rob, grad = device_matches_cpu(run, device, dtype)
    assert bool(torch.isfinite(rob).any()) and bool((grad != 0).any())


@pytest.mark.parametrize("name", ["a", "urgent", "barrier", "generic"])
def test_plan_cost_reading_a_device_history_equals_cpu(name, dtype, device):
    """The MPPI cost of rollouts against a history recorded in a ring buffer on the device
    (wrapped around: more states recorded than slots), with per-environment ``t0``, equals
    the CPU's, and so do its gradients to the rollout states."""
    gen = torch.Generator().manual_seed(4)
    B, K, T = 3, 8, 12
    states = 2.0 + 4.0 * torch.rand(B, K, T, 2, generator=gen, dtype=torch.float64)
    past = 2.0 + 4.0 * torch.rand(7, B, 2, generator=gen, dtype=torch.float64)
    t0 = torch.tensor([0.35, 0.6, 1.2], dtype=torch.float64)

    def run(dev: torch.device):
        f = {"device": dev, "dtype": dtype}
        spec = _spec_zoo()[name].to(dev)
        buffer = HistoryBuffer(5, B, 2, **f)
        for j in range(7):  # two more than the slots: the oldest are overwritten
            buffer.record(past[j].to(**f), (t0 - 0.1 * (6 - j)).to(**f))
        x = states.to(**f).requires_grad_()
        cost = spec(x, None, t0.to(**f), dt=0.1, history=buffer.view())
        (grad,) = torch.autograd.grad(cost.clamp(-1e3, 1e3).sum(), x)
        history = buffer.view()
        return cost.detach(), grad, history.states, history.times, history.valid, buffer.count

    cost, grad, _, _, valid, count = device_matches_cpu(run, device, dtype)
    assert cost.shape == (B, K) and bool(valid.all()) and int(count) == 7
    assert bool(torch.isfinite(cost).all())


def test_spec_cost_planner_batch_equals_per_environment_planners(dtype, device):
    """A planner whose cost is a specification reads each environment's own history on the
    device: a batch of three plans as three one-environment planners seeded ``seed + b`` on
    the same device, over calls whose history fills the goal's window."""
    from torchcbf.dynamics import SingleIntegrator
    from torchcbf.mppi import MPPI

    def planner(seed: int) -> MPPI:
        spec = And(Avoid(OBST, 0.6, weight=0.3), Reach(G1, 0.5, (0.0, 0.4), weight=5.0))
        return MPPI(SingleIntegrator(2), spec, horizon=6, num_samples=32, dt=0.1,
                    noise_sigma=1.0, temperature=0.5, u_min=-2.0, u_max=2.0, seed=seed,
                    history_size=4).to(device=device, dtype=dtype)  # fmt: skip

    gen = torch.Generator().manual_seed(5)
    xs = 3.0 + torch.rand(5, 3, 2, generator=gen, dtype=torch.float64)
    xs[2, 1] = torch.tensor(G1)  # environment 1 reaches the goal inside its window
    xs = xs.to(device=device, dtype=dtype)
    batched = planner(11)
    singles = [planner(11 + b) for b in range(3)]
    tol = {"rtol": 1e-9, "atol": 1e-9} if dtype == torch.float64 else {"rtol": 2e-4, "atol": 2e-4}
    for k in range(5):
        out = batched(xs[k], t=0.1 * k)
        for b in range(3):
            one = singles[b](xs[k, b], t=0.1 * k)
            torch.testing.assert_close(out.plan[b], one.plan, **tol)
            torch.testing.assert_close(out.u[b], one.u, **tol)
    hist = batched.history
    assert hist.states.device.type == device.type and bool(hist.valid.all())
    torch.testing.assert_close(hist.states[1], singles[1].history.states[0])


def test_spec_cost_and_history_make_no_host_traffic() -> None:
    """Recording the history and the MPPI cost of every kind of node run on the meta device
    (no value is read back) and copy nothing from the host (no list index, no Python data)."""
    meta = torch.device("meta")
    specs = [spec.to(meta) for spec in _spec_zoo().values()]
    buffer = HistoryBuffer(4, 2, 2, device=meta, dtype=torch.float64)
    states = torch.zeros(2, 5, 7, 2, device=meta, dtype=torch.float64)
    t0 = torch.zeros(2, device=meta, dtype=torch.float64)
    with HostTraffic() as traffic:
        for _ in range(5):  # past the slots: the ring wraps
            buffer.record(states[:, 0, 0], t0)
        costs = [spec(states, None, t0, dt=0.1, history=buffer.view()) for spec in specs]
    assert not traffic.events, dict(traffic.events)
    assert all(cost.shape == (2, 5) for cost in costs)


def _passing_ball(keep_in: bool = False):
    from torchcbf.barriers import MovingBall

    # the centre moves along x at 1 m/s: over (5, 0) at t = 5
    return MovingBall(lambda t: torch.stack([t, torch.zeros_like(t)], -1), 0.5, keep_in=keep_in)


def test_a_time_varying_predicate_is_read_at_each_states_time() -> None:
    """Always and Eventually of a moving ball read it at the states' times: a robot the ball
    passes over at t = 5 is not safe throughout, and one it covers then is reached."""
    times = torch.arange(11, dtype=torch.float64)
    states = torch.tensor([5.0, 0.0], dtype=torch.float64).expand(11, 2)
    truth = _passing_ball()(states, times)  # 24.75 at t = 0, -0.25 at t = 5
    assert float(Always(_passing_ball()).robustness(states, times)) == float(truth.min())
    inside = _passing_ball(keep_in=True)
    assert float(Eventually(inside).robustness(states, times)) == float(-truth.min())
    # the planning costs too: the rollout parked at (5, 0) from t0 = 0 with dt = 1
    rollout = states.reshape(1, 1, 11, 2)
    cost = Eventually(inside)(rollout, None, 0.0, dt=1.0)
    torch.testing.assert_close(cost, torch.full((1, 1), float(truth.min()), dtype=torch.float64))
    worst = Always(_passing_ball())(rollout, None, 0.0, dt=1.0)
    torch.testing.assert_close(worst, torch.full((1, 1), -float(truth.min()), dtype=torch.float64))
    with pytest.raises(ValueError, match="Always.predicate has no times"):
        Always(_passing_ball()).predicate(states)


def test_avoid_reads_a_moving_barrier_at_the_times_it_is_given() -> None:
    """``rollout_max_cost`` with times equals the worst pointwise cost in the window."""
    times = torch.arange(11, dtype=torch.float64)
    states = torch.tensor([5.0, 0.0], dtype=torch.float64).expand(1, 1, 11, 2)
    window = (times >= 3.0).unsqueeze(0)
    avoid = Avoid(barrier=_passing_ball(), weight=0.3)
    costs = avoid.pointwise_cost_at(states, times)
    expected = costs.masked_fill(~window.unsqueeze(1), -math.inf).amax(-1)
    torch.testing.assert_close(avoid.rollout_max_cost(states, window, times.unsqueeze(0)), expected)
    with pytest.raises(ValueError, match="has no times"):
        avoid.rollout_max_cost(states, window)


def test_a_specification_adds_to_a_cost_on_either_side() -> None:
    from torchcbf.mppi.costs import QuadraticGoal, SumCost

    reach, goal = Reach([1.0, 0.0], 0.3, (0.0, 2.0)), QuadraticGoal([1.0, 0.0])
    states = torch.randn(
        2, 3, 5, 2, dtype=torch.float64, generator=torch.Generator().manual_seed(0)
    )
    controls = torch.zeros(2, 3, 4, 2, dtype=torch.float64)
    expected = reach(states, controls, 0.0, dt=0.1) + goal(states, controls)
    for total in (reach + goal, goal + reach, reach + (lambda x, u, t0=None: goal(x, u))):
        assert isinstance(total, SumCost) and total.needs_history
        torch.testing.assert_close(total(states, controls, 0.0, dt=0.1), expected)
    both = reach + Avoid([0.5, 0.0], 0.1)
    torch.testing.assert_close(
        both(states, controls, 0.0, dt=0.1),
        reach(states, controls, 0.0, dt=0.1)
        + Avoid([0.5, 0.0], 0.1)(states, controls, 0.0, dt=0.1),
    )
    with pytest.raises(TypeError):
        reach + 1.0


def test_a_cost_that_returns_a_view_leaves_the_states_alone() -> None:
    states = torch.linspace(0.0, 1.0, 6, dtype=torch.float64).expand(2, 6).T.reshape(1, 1, 6, 2)
    states = states.clone()
    before = states.clone()
    for spec in (
        Eventually(lambda x: x[..., 0] - 0.5, (0.2, 0.4), cost=lambda x: x[..., 1]),
        Always(lambda x: x[..., 0] - 0.5, (0.2, 0.4), cost=lambda x: x[..., 1]),
    ):
        spec(states, None, 0.0, dt=0.1)
        assert torch.equal(states, before)


def test_spec_arguments_that_would_silence_a_term_are_refused() -> None:
    with pytest.raises(ValueError, match="center has 1 entries but index names 2"):
        Avoid([1.0], 0.5)
    for radius in (math.nan, math.inf, -1.0):
        with pytest.raises(ValueError, match="radius must be a finite number >= 0"):
            Avoid([1.0, 0.0], radius)
    with pytest.raises(ValueError, match="Avoid with a barrier takes no radius"):
        Avoid(barrier=lambda x: x[..., 0], radius=0.5)
    with pytest.raises(ValueError, match="urgency must be a finite number >= 0"):
        Reach([1.0, 0.0], 0.3, urgency=math.inf)
    rollout = torch.zeros(1, 2, 4, 2, dtype=torch.float64)
    reach = Reach([1.0, 0.0], 0.3, (0.0, 1.0))
    with pytest.raises(ValueError, match="dt must be a finite number > 0"):
        reach(rollout, None, 0.0, dt=math.nan)
    with pytest.raises(ValueError, match="t0 must be finite"):
        reach(rollout, None, math.nan, dt=0.1)
    with pytest.raises(ValueError, match=r"t0 must be a number or have one time per row \[1\]"):
        reach(rollout, None, torch.zeros(3), dt=0.1)


def test_a_full_history_warns_where_a_goal_reads_it() -> None:
    """One slot per call: the planner warns once when a goal's term would forget a visit,
    and not for terms that do not read what the history holds as achieved."""
    import warnings

    from torchcbf.dynamics import SingleIntegrator
    from torchcbf.mppi import MPPI, QuadraticGoal

    def planner(cost):
        dyn = SingleIntegrator(2, u_min=-1.0, u_max=1.0)
        return MPPI(dyn, cost, 5, 16, 0.1, torch.eye(2) * 0.25, 0.5, 0.1, history_size=3)

    x = torch.zeros(1, 2)
    goal = planner(Reach([1.0, 0.0], 0.3, (0.0, 10.0)))
    for k in range(3):
        goal(x, t=0.1 * k)
    with pytest.warns(UserWarning, match="history of 3 slots .* is full"):
        goal(x, t=0.3)
    for cost in (QuadraticGoal((1.0, 0.0), 1.0, (0, 1), 1.0), Always(lambda z: z[..., 0] + 1.0)):
        quiet = planner(cost)
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            for k in range(5):
                quiet(x, t=0.1 * k)


class _OneArgumentCost(Eventually):
    """A subclass written against the one-argument ``pointwise_cost``."""

    def pointwise_cost(self, states):
        return (states[..., 0] - 1.0).abs()


def test_a_subclass_with_a_one_argument_pointwise_cost_still_plans() -> None:
    spec = _OneArgumentCost(lambda x: 0.1 - (x[..., 0] - 1.0).abs(), (0.0, 1.0))
    states = torch.linspace(0.0, 2.0, 5).reshape(1, 1, 5, 1).expand(1, 2, 5, 1)
    cost = spec(states.double(), None, 0.0, dt=0.1)
    torch.testing.assert_close(cost, torch.zeros(1, 2, dtype=torch.float64))


def _line_rollouts(dtype: torch.dtype) -> torch.Tensor:
    """Two rollouts of 5 states from the origin: one toward +x (to B), one toward -x."""
    steps = torch.arange(5, dtype=dtype)[:, None] * torch.tensor([0.5, 0.0], dtype=dtype)
    return torch.stack([steps, -steps])[None]  # [1, 2, 5, 2]


def test_or_steers_to_the_children_the_history_has_not_made_fail(dtype):
    """A's window closed unmet (its frozen cost would cap the minimum); an Always child
    broken in the history likewise: the Or ranks rollouts as B alone does. Once the
    history holds B, the Or's cost is constant."""
    states = _line_rollouts(dtype)
    A = Reach((1.0, 0.0), 0.2, (0.0, 0.3))
    B = Reach((3.0, 0.0), 0.2, (0.0, 8.0))
    stay = Always(lambda x: 0.1 - x[..., 1].abs(), (0.0, 0.5))  # |y| <= 0.1 until 0.5 s
    past = torch.tensor([[[0.0, 0.0], [0.0, 0.5]]], dtype=dtype)
    history = History(past, torch.tensor([[0.0, 0.2]], dtype=dtype), torch.ones(1, 2).bool())
    t0 = torch.tensor([1.0], dtype=dtype)
    alone = B(states, None, t0, dt=0.1, history=history)
    assert float(alone[0, 0]) < float(alone[0, 1])
    for failed in (A, stay):
        got = Or(failed, B)(states, None, t0, dt=0.1, history=history)
        torch.testing.assert_close(got, alone)
        assert int(Or(failed, B).outcome(t0[:, None], history)) == 0
        assert int(failed.outcome(t0[:, None], history)) == -1
    at_b = History(torch.tensor([[[3.0, 0.05]]], dtype=dtype), torch.tensor([[0.9]], dtype=dtype),
                   torch.ones(1, 1, dtype=torch.bool))  # fmt: skip
    done = Or(A, B)(states, None, t0, dt=0.1, history=at_b)
    assert float(done[0, 0]) == float(done[0, 1])
    assert int(Or(A, B).outcome(t0[:, None], at_b)) == 1


class _NeverDecided(Reach):
    """A goal whose history never decides (its own ``outcome``)."""

    def outcome(self, times, history):
        return None


class _Routed(Reach):
    """A goal that keeps a route of its own under the name ``plan``."""

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self.plan = ["a", "b"]


class _Doubled(Reach):
    """A goal that counts its planning cost twice (its own ``plan_cost``)."""

    def plan_cost(self, states, times, history):
        return 2 * super().plan_cost(states, times, history)


def test_or_asks_a_child_that_overrides_its_cost_or_outcome_alone(dtype):
    """The Or reads a child's cost and outcome through one call where the child's class
    defines both; a subclass (or an instance) that overrides one is asked for it."""
    states = _line_rollouts(dtype)
    B = Reach((3.0, 0.0), 0.2, (0.0, 8.0))
    past = torch.tensor([[[0.0, 0.0], [0.0, 0.5]]], dtype=dtype)
    history = History(past, torch.tensor([[0.0, 0.2]], dtype=dtype), torch.ones(1, 2).bool())
    t0 = torch.tensor([1.0], dtype=dtype)
    alone = B(states, None, t0, dt=0.1, history=history)
    # A's window closed unmet: an A that does not say so caps the Or's cost with its own
    undecided = _NeverDecided((1.0, 0.0), 0.2, (0.0, 0.3))
    capped = Reach((1.0, 0.0), 0.2, (0.0, 0.3))(states, None, t0, dt=0.1, history=history)
    got = Or(undecided, B)(states, None, t0, dt=0.1, history=history)
    torch.testing.assert_close(got, torch.minimum(capped, alone))
    assert not torch.equal(got, alone)
    shadowed = Reach((1.0, 0.0), 0.2, (0.0, 0.3))
    shadowed.outcome = lambda times, history: None
    torch.testing.assert_close(Or(shadowed, B)(states, None, t0, dt=0.1, history=history), got)
    doubled = _Doubled((3.0, 0.0), 0.2, (0.0, 8.0))
    got = Or(Reach((1.0, 0.0), 0.2, (0.0, 0.3)), doubled)(states, None, t0, dt=0.1, history=history)
    torch.testing.assert_close(got, 2 * alone)
    routed = _Routed((3.0, 0.0), 0.2, (0.0, 8.0))
    torch.testing.assert_close(Or(routed, B)(states, None, t0, dt=0.1, history=history), alone)
    for spec in (B, And(B, Always(lambda x: 0.1 - x[..., 1].abs())), Or(undecided, doubled)):
        times = t0[:, None] + 0.1 * torch.arange(5, dtype=dtype)
        cost, outcome = plan_of(spec, states, times, history)
        torch.testing.assert_close(cost, spec.plan_cost(states, times, history))
        assert torch.equal(outcome, spec.outcome(times, history))


def test_robustness_gradient_at_a_disc_centre_is_finite():
    """A state on the centre (outside the window, or not the extreme one) has no influence,
    though the square root's derivative is infinite there."""
    x = torch.tensor([[[4.0, 4.0], [0.0, 0.0], [3.8, 4.0]]], dtype=torch.float64)
    x.requires_grad_(True)
    times = torch.tensor([0.0, 1.0, 2.0], dtype=torch.float64)
    rob = Reach((4.0, 4.0), 0.5, (1.5, 3.0)).robustness(x, times)
    rob = rob + Avoid((0.0, 0.0), 0.1, interval=(0.0, 0.5)).robustness(x, times)
    (grad,) = torch.autograd.grad(rob.sum(), x)
    want = torch.zeros_like(x)
    want[0, 2, 0] = 1.0  # Reach: -(p - c) / |p - c| at the one state in its window
    want[0, 0] = 1.0 / math.sqrt(2.0)  # Avoid: p / |p| at (4, 4), its one state
    torch.testing.assert_close(grad, want)


def test_float32_window_edges_hold_far_from_time_zero():
    """float32 times near 1,000 s are 6e-5 s apart: a state at a deadline stays in."""
    spec = Reach((0.0, 0.0), 0.5, (1000.0, 1000.8))
    states = torch.zeros(1, 1, 5, 2)
    states[..., :-1, 0] = 5.0  # only the last state, at the deadline, is in the goal
    cost = spec(states, None, torch.tensor([1000.4]), dt=0.1)
    assert float(cost) < 0
    assert float(spec.robustness(states[0], 1000.4 + 0.1 * torch.arange(5.0))) == 0.5


def test_empty_trajectories_and_windows_that_hold_no_time():
    states = torch.zeros(2, 0, 2)
    assert Reach((0.0, 0.0), 0.5).robustness(states, torch.zeros(0)).tolist() == [-math.inf] * 2
    assert Avoid((0.0, 0.0), 0.5).robustness(states, torch.zeros(0)).tolist() == [math.inf] * 2
    for bad in ((math.inf, math.inf), (-math.inf, -math.inf), (2.0, 1.0), (0.0, 1.0, 2.0)):
        with pytest.raises(ValueError, match="interval must be"):
            Reach((0.0, 0.0), 0.5, bad)
    for bad in (5, (None, 1.0)):
        with pytest.raises(TypeError, match="interval must be a pair of numbers"):
            Reach((0.0, 0.0), 0.5, bad)
