"""The Triton MPPI kernel against the C kernel (same configuration, same noise keys).

Runs on CUDA where present, else on the CPU under ``TRITON_INTERPRET=1`` (set before
Python starts: ``TRITON_INTERPRET=1 pytest tests/mppi/test_triton.py``); skipped where
Triton is not installed. Each pass of the two kernels is compared with the same keys; whole
planners are compared on the CPU (on CUDA the planner's generators draw other keys than the
CPU's, so there a batched planner is compared with one planner per environment).
"""

from __future__ import annotations

import copy

import pytest
import torch
from _devices import NEEDS_TRITON, RUNS_TRITON, triton_target

from torchcbf.barriers import Ball, Ellipse
from torchcbf.dynamics import AccelUnicycle, DoubleIntegrator, SingleIntegrator, Unicycle
from torchcbf.mppi import (
    MPPI,
    BarrierCost,
    DiscreteBarrierCost,
    ObstacleCost,
    QuadraticGoal,
    SumCost,
    _rollout,
    _triton,
)

TARGET = triton_target()
pytestmark = [
    pytest.mark.device,
    NEEDS_TRITON,
    RUNS_TRITON,
    pytest.mark.skipif(
        not _rollout.available(), reason="the C kernel (the reference) is not built"
    ),
]

#: (rtol, atol) of the Triton kernel against the C kernel: rounding of the same formulas
TOL = {torch.float64: (1e-9, 1e-9), torch.float32: (2e-4, 2e-5)}
MODELS = [
    (AccelUnicycle, "rk4"),
    (Unicycle, "euler"),
    (lambda: DoubleIntegrator(2), "rk4"),
    (lambda: SingleIntegrator(3), "euler"),
]


def _cost() -> SumCost:
    balls = Ball(center=torch.tensor([[2.0, 0.5], [4.0, -0.5]]), radius=0.5)
    ellipse = Ellipse(center=torch.tensor([3.0, 1.0]), axes=torch.tensor([0.6, 0.3]), angle=0.4)
    return SumCost(
        QuadraticGoal(goal=[6.0, 0.0], index=[0, 1], weight=1.0, terminal_weight=5.0),
        BarrierCost(balls, weight=0.1),
        DiscreteBarrierCost(ellipse, gamma=0.3, weight=10.0, steps=7),
        BarrierCost(ellipse, weight=0.05),
        ObstacleCost(center=[5.0, 0.3], radius=0.3),
    )


def _planner(make, integrator: str, dtype: torch.dtype, backend: str, cost=None, **kw) -> MPPI:
    dyn = make()
    m = dyn.control_dim
    return MPPI(
        dyn,
        _cost() if cost is None else cost,
        horizon=12,
        num_samples=300,
        dt=0.1,
        noise_sigma=torch.tensor([[0.5, 0.1], [0.1, 0.4]]) if m == 2 else 0.6,
        temperature=0.5,
        control_cost_weight=0.2,
        u_min=[-1.0] * m,
        u_max=[1.5] * m,
        integrator=integrator,
        seed=3,
        backend=backend,
        zero_noise_samples=1,
        **kw,
    ).to(dtype)


def _plans(planner: MPPI, x: torch.Tensor, calls: int = 3) -> list:
    return [planner(x) for _ in range(calls)]


on_cpu_only = pytest.mark.skipif(
    TARGET is not None and TARGET.type != "cpu",
    reason="the CUDA generators draw other noise keys than the CPU's",
)


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
@pytest.mark.parametrize(("make", "integrator"), MODELS)
def test_kernel_passes_match_the_c_kernel(make, integrator, dtype):
    gen = torch.Generator().manual_seed(1)
    planner = _planner(make, integrator, dtype, "auto")
    n, m = planner.dynamics.state_dim, planner.dynamics.control_dim
    B, K, H = 3, planner.num_samples, planner.horizon
    x = torch.rand(B, n, generator=gen, dtype=dtype) - 0.5
    plan = torch.randn(B, H, m, generator=gen, dtype=dtype) * 0.5
    keys = torch.randint(0, 2**62, (B,), generator=gen)
    wctrl = (plan @ planner.noise_cov_inv.to(plan)).contiguous()
    w = torch.rand(B, K, generator=gen, dtype=dtype)
    w[:, ::3] = 0.0
    pairs = torch.tensor([[0, 5], [2, K - 1], [1, 0]])
    model = _rollout.encode_model(planner.dynamics)
    terms = _rollout.encode_cost(planner.cost, n)
    c_fused = _rollout.Kernel(planner._configuration(model, terms), fused=True)
    c_plain = _rollout.Kernel(planner._configuration(model, None), fused=False)
    t_fused, t_plain = (
        _triton.Kernel(_triton.tables(k.cfg, dtype, TARGET), fused=k.fused)
        for k in (c_fused, c_plain)
    )
    on = {"x": x.to(TARGET), "plan": plan.to(TARGET), "keys": keys.to(TARGET)}
    rtol, atol = TOL[dtype]

    def close(got, want, what):
        torch.testing.assert_close(got.cpu(), want, rtol=rtol, atol=atol, msg=what)

    close(t_fused.costs(**on, wctrl=wctrl.to(TARGET)), c_fused.costs(x, plan, keys, wctrl), "costs")
    close(t_fused.update(**on, w=w.to(TARGET)), c_fused.update(x, plan, keys, w), "update")
    close(t_fused.rows(**on, pairs=pairs.to(TARGET)), c_fused.rows(x, plan, keys, pairs), "rows")
    bufs = [_rollout.component_major(x, B, K, H + 1, n), _rollout.component_major(x, B, K, H, m)]
    ctrl = c_plain.buffers(x, plan, keys, *bufs, wctrl, "component")
    tbufs = [_rollout.component_major(on["x"], B, K, H + 1, n),
             _rollout.component_major(on["x"], B, K, H, m)]  # fmt: skip
    tctrl = t_plain.buffers(**on, states=tbufs[0], controls=tbufs[1],
                            wctrl=wctrl.to(TARGET), layout="component")  # fmt: skip
    close(tctrl, ctrl, "control cost")
    close(tbufs[0], bufs[0], "states")
    close(tbufs[1], bufs[1], "controls")


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_a_batched_planner_plans_each_environment_as_one_planner(dtype):
    x = torch.tensor([[0.0, 0.0, 0.5, 0.1], [1.0, -1.0, 0.0, 2.0]], dtype=dtype, device=TARGET)
    batched = _planner(AccelUnicycle, "rk4", dtype, "triton").to(TARGET)
    outs = _plans(batched, x)
    assert batched.path == "fused" and batched.engine == "triton"
    rtol, atol = TOL[dtype]
    for b in range(2):
        one = _planner(AccelUnicycle, "rk4", dtype, "triton").to(TARGET)
        one.seed = batched.seed + b
        one.reset()
        for out, single in zip(outs, _plans(one, x[b]), strict=True):
            torch.testing.assert_close(single.plan, out.plan[b], rtol=rtol, atol=atol)


@on_cpu_only
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
@pytest.mark.parametrize(("make", "integrator"), MODELS)
def test_fused_plans_match_the_c_kernel(make, integrator, dtype):
    torch.manual_seed(0)
    ref = _planner(make, integrator, dtype, "auto", keep_rollouts=3)
    tri = _planner(make, integrator, dtype, "triton", keep_rollouts=3).to(TARGET)
    n = ref.dynamics.state_dim
    x = (torch.rand(2, n, dtype=dtype) - 0.5) * 0.5
    rtol, atol = TOL[dtype]
    for a, b in zip(_plans(ref, x), _plans(tri, x.to(TARGET)), strict=True):
        assert ref.path == "fused" and tri.path == "fused"
        assert ref.engine == "c" and tri.engine == "triton"
        for name in ("u", "plan", "cost_min", "cost_mean", "ess", "best_states", "rollouts",
                     "rollout_weights"):  # fmt: skip
            torch.testing.assert_close(
                getattr(b, name).cpu(), getattr(a, name), rtol=rtol, atol=atol, msg=name
            )
        assert torch.equal(a.status, b.status.cpu())
        assert torch.equal(a.nonfinite, b.nonfinite.cpu())


@on_cpu_only
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_rollout_path_with_a_torch_cost_matches_the_c_kernel(dtype):
    def cost(states, controls, t):  # a user's cost: torch scores the stored rollouts
        return (states[..., :2] - torch.tensor([3.0, 1.0]).to(states)).square().sum((-1, -2))

    ref = _planner(AccelUnicycle, "rk4", dtype, "auto", cost=cost)
    tri = _planner(AccelUnicycle, "rk4", dtype, "triton", cost=cost).to(TARGET)
    x = torch.tensor([[0.0, 0.0, 0.5, 0.1], [1.0, -1.0, 0.0, 2.0]], dtype=dtype)
    rtol, atol = TOL[dtype]
    for a, b in zip(_plans(ref, x), _plans(tri, x.to(TARGET)), strict=True):
        assert ref.path == "rollout" and tri.path == "rollout"
        torch.testing.assert_close(b.plan.cpu(), a.plan, rtol=rtol, atol=atol)
        torch.testing.assert_close(b.best_states.cpu(), a.best_states, rtol=rtol, atol=atol)


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
@pytest.mark.parametrize(("K", "temperature"), [(5000, 0.03), (300, 0.5), (7, 1e-45), (1, 2.0)])
def test_weights_pass_matches_the_torch_weights(dtype, K, temperature):
    gen = torch.Generator().manual_seed(K)
    planner = _planner(Unicycle, "euler", dtype, "torch")
    planner.temperature = temperature
    cost = torch.randn(6, K, generator=gen, dtype=dtype) * 10.0
    pick = torch.rand(6, K, generator=gen)
    cost[pick < 0.1] = float("nan")
    cost[(pick > 0.1) & (pick < 0.15)] = float("inf")
    cost[(pick > 0.15) & (pick < 0.18)] = -float("inf")
    cost[1] = float("nan")  # no finite cost: status 1, weights 0
    cost[2] = 3.0  # all tied: the first sample is the best
    cost[3] = float("inf")
    cost[3, K // 2] = 1.0  # one finite cost
    cost[4, : K // 2 + 1] = 1e37  # finite in float32; their float32 sum would not be
    want = planner._weights(cost.clone())
    assert torch.isfinite(want.cost_mean[4])
    lam = max(temperature, torch.finfo(dtype).tiny)
    got = _triton.weights(cost.to(TARGET), lam)
    assert len(got) == len(want)
    rtol = 1e-12 if dtype == torch.float64 else 1e-5
    for name, a, b in zip(want._fields, want, got, strict=True):
        assert b.dtype == a.dtype and b.shape == a.shape and b.device == TARGET, name
        if a.is_floating_point():
            torch.testing.assert_close(b.cpu(), a, rtol=rtol, atol=0.0, msg=name)
        else:
            assert torch.equal(b.cpu(), a), name
    assert want.status.tolist() == [0, 1, 0, 0, 0, 0] and want.best[2] == 0


@on_cpu_only
def test_normalised_costs_on_the_triton_path_are_weighted_by_torch():
    ref = _planner(AccelUnicycle, "rk4", torch.float64, "auto", cost_normalization="std")
    tri = _planner(AccelUnicycle, "rk4", torch.float64, "triton", cost_normalization="std")
    x = torch.tensor([[0.0, 0.0, 0.5, 0.1], [1.0, -1.0, 0.0, 2.0]], dtype=torch.float64)
    for a, b in zip(_plans(ref, x, 2), _plans(tri.to(TARGET), x.to(TARGET), 2), strict=True):
        assert tri.path == "fused" and tri.engine == "triton"
        torch.testing.assert_close(b.plan.cpu(), a.plan, rtol=1e-9, atol=1e-9)
        torch.testing.assert_close(b.ess.cpu(), a.ess, rtol=1e-9, atol=1e-9)


@pytest.mark.parametrize(
    ("normalization", "own_cost", "path", "weighed"),
    [
        ("none", False, "fused", True),
        ("none", True, "rollout", True),
        ("std", False, "fused", False),
    ],
)
def test_the_kernel_weighs_the_samples_where_it_can(
    monkeypatch, normalization, own_cost, path, weighed
):
    calls = []
    kernel_weights = _triton.Kernel.weights

    def spy(self, cost, temperature):
        calls.append(tuple(cost.shape))
        return kernel_weights(self, cost, temperature)

    monkeypatch.setattr(_triton.Kernel, "weights", spy)
    cost = (
        (lambda states, controls, t: states[..., :2].square().sum((-1, -2))) if own_cost else None
    )
    planner = _planner(Unicycle, "euler", torch.float64, "triton", cost=cost,
                       cost_normalization=normalization).to(TARGET)  # fmt: skip
    planner(torch.zeros(2, 3, dtype=torch.float64, device=TARGET))
    assert planner.path == path and planner.engine == "triton"
    assert calls == ([(2, planner.num_samples)] if weighed else [])


def test_tables_follow_a_changed_goal():
    goal = QuadraticGoal(goal=[6.0, 0.0], index=[0, 1], weight=1.0)
    ref = _planner(Unicycle, "euler", torch.float64, "auto", cost=copy.deepcopy(goal))
    planner = _planner(Unicycle, "euler", torch.float64, "triton", cost=goal).to(TARGET)
    x = torch.zeros(3, dtype=torch.float64)
    planner(x.to(TARGET))
    first = planner._kernel_cache[1]
    planner(x.to(TARGET))
    ref(x), ref(x)
    assert planner._kernel_cache[1] is first  # nothing changed: the tables are kept
    with torch.no_grad():
        planner.cost.goal.copy_(torch.tensor([-4.0, 2.0]))
        ref.cost.goal.copy_(torch.tensor([-4.0, 2.0]))
    b, a = planner(x.to(TARGET)), ref(x)
    assert planner._kernel_cache[1] is not first
    goal_row = planner._kernel_cache[1].tab.tcent[0, :2].cpu()
    assert torch.equal(goal_row, torch.tensor([-4.0, 2.0], dtype=torch.float64))
    if TARGET.type == "cpu":  # the same keys: the C planner's plan
        torch.testing.assert_close(b.plan.cpu(), a.plan, rtol=1e-9, atol=1e-9)


def test_options_the_kernel_does_not_express_run_in_torch():
    planner = _planner(Unicycle, "euler", torch.float64, "triton", noise_abs_cost=True)
    planner = planner.to(TARGET)
    planner(torch.zeros(3, dtype=torch.float64, device=TARGET))
    assert planner.path == "torch" and planner.engine is None


def test_boundary_checks_name_the_argument():
    planner = _planner(Unicycle, "euler", torch.float64, "triton").to(TARGET)
    x = torch.zeros(1, 3, dtype=torch.float64, device=TARGET)
    planner._ensure_state(1, x.device, x.dtype)
    kernel = planner._kernel(x)
    keys = torch.zeros(1, dtype=torch.int64, device=TARGET)
    plan = torch.zeros(1, 12, 2, dtype=torch.float32, device=TARGET)
    with pytest.raises(ValueError, match="x0 must be a contiguous torch.float32"):
        kernel.costs(x, plan, keys, None)
    with pytest.raises(ValueError, match="keys"):
        kernel.costs(x.float(), plan, keys.int(), None)


on_cuda_only = pytest.mark.skipif(
    TARGET is None or TARGET.type != "cuda", reason="CUDA graphs need a CUDA device"
)


@on_cuda_only
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_a_captured_planner_plans_as_the_uncaptured_one(dtype):
    x = torch.tensor([[0.0, 0.0, 0.5, 0.1], [1.0, -1.0, 0.0, 2.0]], dtype=dtype, device=TARGET)
    plain = _planner(AccelUnicycle, "rk4", dtype, "triton", keep_rollouts=3).to(TARGET)
    graphed = _planner(AccelUnicycle, "rk4", dtype, "triton", keep_rollouts=3, cuda_graph=True).to(
        TARGET
    )
    u = torch.tensor([0.3, -0.2], dtype=dtype, device=TARGET)
    outs, paths = [], []
    for i in range(13):
        for planner in (plain, graphed):
            if i == 3:  # a new goal: new tables, one uncaptured call, then a capture
                with torch.no_grad():
                    planner.cost.terms[0].goal.copy_(torch.tensor([-2.0, 1.0]))
            if i == 5:  # the plan changed in place: the graph reads it
                planner.correct(u)
            if i == 6:  # a number the graph holds: captured again
                planner.temperature = 0.25
        xi = x[0] if i >= 8 else x  # one environment: a new plan tensor, captured again
        shift = i != 11  # a call without the shift runs uncaptured; the graph stays
        B = 1 if xi.dim() == 1 else xi.shape[0]
        t = [0.1 * i, torch.tensor(0.1 * i), torch.full((B,), 0.1 * i)][i % 3]  # copied in
        t = t.to(dtype=dtype, device=TARGET) if isinstance(t, torch.Tensor) else t
        outs.append((plain(xi, t, shift), graphed(xi, t, shift)))
        paths.append(graphed.path)
        for a, b in zip(plain.history, graphed.history, strict=True):  # recorded in the graph
            assert torch.equal(a, b)
    G, F = "fused_graph", "fused"
    assert paths == [F, F, G, F, F, G, F, F, F, F, G, F, G]
    rtol, atol = (1e-12, 1e-12) if dtype == torch.float64 else (1e-6, 1e-6)
    for a, b in outs:  # earlier outputs are not overwritten by later replays
        for name in ("u", "plan", "cost_min", "cost_mean", "ess", "best_states", "rollouts",
                     "rollout_weights"):  # fmt: skip
            torch.testing.assert_close(getattr(b, name), getattr(a, name), rtol=rtol, atol=atol)
        assert torch.equal(a.status, b.status) and torch.equal(a.nonfinite, b.nonfinite)
        assert b.u.shape == a.u.shape
    twin = copy.deepcopy(graphed)  # a copy captures its own graph
    for _ in range(3):
        torch.testing.assert_close(twin(x[0]).plan, plain(x[0]).plan, rtol=rtol, atol=atol)
    assert twin.path == G


@on_cuda_only
def test_cuda_graph_changes_nothing_on_other_paths():
    def cost(states, controls, t):
        return states[..., :2].square().sum((-1, -2))

    planner = _planner(Unicycle, "euler", torch.float32, "triton", cost=cost, cuda_graph=True)
    planner = planner.to(TARGET)
    x = torch.zeros(3, device=TARGET)
    for _ in range(3):
        out = planner(x)
    assert out.path == "rollout" and planner.path == "rollout"


def test_the_kernels_check_the_control_weights_and_the_sample_weights() -> None:
    """A strided ``wctrl`` is read as the C kernel reads it (a copy); one of another shape,
    or sample weights of another batch, are refused by both kernels."""
    f64 = torch.float64
    planner = MPPI(Unicycle(), SumCost(QuadraticGoal([1.0, 0.0], index=[0, 1])), horizon=3,
                   num_samples=8, dt=0.1, noise_sigma=0.5, temperature=1.0,
                   control_cost_weight=0.5, integrator="euler").to(f64)  # fmt: skip
    config = planner._configuration(
        _rollout.encode_model(planner.dynamics), _rollout.encode_cost(planner.cost, 3)
    )
    c_kernel = _rollout.Kernel(config, fused=True)
    kernel = _triton.Kernel(_triton.tables(config, f64, torch.device(TARGET)), fused=True)
    gen = torch.Generator().manual_seed(0)
    x, plan = (
        torch.rand(2, 3, generator=gen, dtype=f64),
        torch.randn(2, 3, 2, generator=gen, dtype=f64),
    )
    keys = torch.randint(0, 2**62, (2,), generator=gen)
    wctrl = torch.randn(2, 2, 3, generator=gen, dtype=f64).transpose(1, 2)  # [B, H, m], strided
    on = (x.to(TARGET), plan.to(TARGET), keys.to(TARGET))
    torch.testing.assert_close(
        kernel.costs(*on, wctrl.to(TARGET)).cpu(),
        c_kernel.costs(x, plan, keys, wctrl),
        rtol=TOL[f64][0],
        atol=TOL[f64][1],
    )
    for k in (kernel, c_kernel):
        args = on if k is kernel else (x, plan, keys)
        with pytest.raises(ValueError, match="wctrl must"):
            k.costs(*args, wctrl[:, :2].contiguous().to(args[0].device))
        with pytest.raises(ValueError, match="weights must"):
            k.update(*args, torch.rand(1, 8, dtype=f64).to(args[0].device))
