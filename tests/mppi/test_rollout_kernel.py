"""The C kernel of MPPI against the torch implementation: rollouts, every built-in cost term,
the planner update, batch = loop, seeds, noise statistics and the fallback rule."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from torchcbf.barriers import Ball, Ellipse
from torchcbf.dynamics import AccelUnicycle, DoubleIntegrator, SingleIntegrator, Unicycle
from torchcbf.integrators import euler, rk4
from torchcbf.mppi import (
    MPPI,
    BarrierCost,
    DiscreteBarrierCost,
    ObstacleCost,
    QuadraticGoal,
    Reach,
    SumCost,
    _rollout,
)

pytestmark = pytest.mark.skipif(not _rollout.available(), reason="the C kernel was not built")

SIGMA = torch.tensor([[0.8, 0.3], [0.3, 0.5]], dtype=torch.float64)


class Capture(torch.nn.Module):
    """A torch cost wrapping another: the kernel cannot see through it, and it records the
    rollouts it is given."""

    def __init__(self, cost):
        super().__init__()
        self.inner = cost
        self.seen = {}

    def forward(self, states, controls, t0):
        self.seen = {"states": states.clone(), "controls": controls.clone()}
        return self.inner(states, controls, t0)


def _ellipses():
    centers = torch.tensor([[1.0, 2.0], [3.0, 2.0], [-1.0, 1.0]])
    axes = torch.tensor([[0.5, 1.5], [0.75, 2.0], [1.0, 0.75]])
    return Ellipse(centers, axes, index=(0, 1))


def _costs(n: int) -> dict[str, object]:
    goal = QuadraticGoal((2.0, 4.0), weight=2.0, index=(0, 1), terminal_weight=10.0)
    rotated = Ellipse(
        torch.tensor([[1.0, 1.0], [0.0, 2.0]]),
        torch.tensor([[0.6, 0.3], [0.4, 0.9]]),
        index=(1, 0),
        angle=torch.tensor([0.4, -1.1]),
    )
    balls = Ball(torch.tensor([[1.0, 1.0], [2.5, 3.0]]), torch.tensor([0.5, 0.8]))
    keep_in = Ball((1.0, 2.0), 6.0, keep_in=True)
    costs = {
        "goal": goal,
        "obstacle": ObstacleCost((1.0, 1.5), 0.4, k_o=0.3, eps=0.01, index=(1, 0)),
        "ellipses": BarrierCost(_ellipses(), 2.0, 0.01),
        "rotated+balls": SumCost(BarrierCost(rotated, 1.5, 0.05), BarrierCost(balls, 0.7, 0.02)),
        "discrete": DiscreteBarrierCost(_ellipses(), gamma=0.3, weight=50.0),
        "all": SumCost(
            goal,
            BarrierCost(_ellipses(), 2.0, 0.01),
            DiscreteBarrierCost(balls, gamma=0.5, weight=20.0),
            BarrierCost(keep_in, 0.1, 0.01),
        ),
        # a discrete-time term before its barrier's term: evaluated on its own
        "discrete_first": SumCost(
            DiscreteBarrierCost(balls, gamma=0.5, weight=20.0),
            BarrierCost(balls, 0.7, 0.02),
        ),
        # a discrete-time term over other shapes between a barrier term and its own
        "interleaved": SumCost(
            BarrierCost(balls, 0.7, 0.02),
            DiscreteBarrierCost(_ellipses(), gamma=0.3, weight=5.0),
            DiscreteBarrierCost(balls, gamma=0.5, weight=20.0),
        ),
        # one barrier under three terms: its shapes are evaluated once per step and shared
        # (the first discrete-time term in the barrier term's pass)
        "shared": SumCost(
            BarrierCost(balls, 0.7, 0.02),
            DiscreteBarrierCost(balls, gamma=0.5, weight=20.0),
            DiscreteBarrierCost(balls, gamma=0.1, weight=3.0),
        ),
        # penalties over the first steps only (one paired with its barrier term, one alone)
        # and over more steps than the horizon has
        "discrete_steps": SumCost(
            BarrierCost(balls, 0.7, 0.02),
            DiscreteBarrierCost(balls, gamma=0.5, weight=20.0, steps=2),
            DiscreteBarrierCost(_ellipses(), gamma=0.3, weight=5.0, steps=3),
            DiscreteBarrierCost(rotated, gamma=0.2, weight=4.0, steps=50),
        ),
    }
    if n >= 3:
        ball3 = Ball((1.0, 0.5, 2.0), 0.7, index=(0, 1, 2))
        costs["ball3d"] = goal + BarrierCost(ball3, 1.0, 0.01)
    return costs


MODELS = {
    "single": lambda: SingleIntegrator(2),
    "double3": lambda: DoubleIntegrator(3),
    "unicycle": lambda: Unicycle(),
    "accel": lambda: AccelUnicycle(),
}


def _x0(dyn, B, dtype):
    x = torch.zeros(B, dyn.state_dim, dtype=dtype)
    x[:, 0] = 0.2 * torch.arange(B, dtype=dtype) - 0.3
    x[:, 1] = 0.1
    if isinstance(dyn, AccelUnicycle):
        x[:, 2], x[:, 3] = 0.5, math.pi / 4
    if isinstance(dyn, Unicycle):
        x[:, 2] = 0.7
    return x


def _pair(dyn, cost, dtype, *, limits=True, integrator="euler", B=2, K=96, H=7, **kw):
    opts = dict(integrator=integrator, keep_rollouts=5, seed=11, **kw)
    if limits:
        opts.update(u_min=torch.tensor([-1.5, -2.0]), u_max=torch.tensor([2.0, 1.0]))
        if dyn.control_dim == 3:
            opts.update(u_min=-1.5, u_max=1.0)
    m = dyn.control_dim
    cov = SIGMA if m == 2 else 0.6 * torch.eye(m, dtype=torch.float64) + 0.1
    temp = 50.0 if dtype == torch.float32 else 2.0
    fused = MPPI(dyn, cost, H, K, 0.05, cov, temp, 0.2, **opts).to(dtype)
    capture = Capture(cost)
    reference = MPPI(dyn, capture, H, K, 0.05, cov, temp, 0.2, cost_chunk=0, **opts).to(dtype)
    return fused, reference, capture, _x0(dyn, B, dtype)


@pytest.mark.parametrize("model", sorted(MODELS))
@pytest.mark.parametrize("integrator", ["euler", "rk4"])
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_fused_equals_torch_cost(model, integrator, dtype):
    """Every cost term, fused in the kernel, against its torch implementation on the same
    samples; the kernel's rollouts against torchcbf.integrators."""
    dyn = MODELS[model]()
    tol = dict(rtol=1e-12, atol=1e-12) if dtype == torch.float64 else dict(rtol=1e-5, atol=1e-5)
    for name, cost in _costs(dyn.state_dim).items():
        fused, reference, capture, x = _pair(dyn, cost, dtype, integrator=integrator)
        for shift in (True, False):  # the second call has a non-zero plan (control cost)
            a, b = fused(x, shift=shift), reference(x, shift=shift)
            assert fused.path == "fused" and reference.path == "rollout", name
            for field in ("plan", "cost_min", "cost_mean", "ess", "best_states", "rollouts"):
                torch.testing.assert_close(
                    getattr(a, field), getattr(b, field), **tol, msg=f"{name}: {field}"
                )
            assert torch.equal(a.nonfinite, b.nonfinite)
        # the kernel's rollout of the recorded controls equals torchcbf.integrators'
        states, controls = capture.seen["states"], capture.seen["controls"]
        step = euler if integrator == "euler" else rk4
        ref = [states[:, :, 0]]
        for j in range(controls.shape[2]):
            ref.append(step(dyn, ref[-1], controls[:, :, j], 0.05))
        torch.testing.assert_close(states, torch.stack(ref, 2), **tol)


@pytest.mark.parametrize("model", ["single", "unicycle", "accel"])
@pytest.mark.parametrize("steps", [1, 3, 7])
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_fused_penalty_window_equals_torch(model, steps, dtype):
    """Discrete-time penalties over the first steps (H = 7): one paired with its barrier
    term, one alone with another window, against torch on the same samples. The penalties
    differ between neighbouring windows on these rollouts, so an off-by-one would show."""
    dyn = MODELS[model]()
    balls = Ball(torch.tensor([[1.0, 1.0], [2.5, 3.0]]), torch.tensor([0.5, 0.8]))

    def cost_with(s: int, s_alone: int) -> SumCost:
        return SumCost(
            BarrierCost(balls, 0.7, 0.02),
            DiscreteBarrierCost(balls, gamma=0.02, weight=20.0, steps=s),
            DiscreteBarrierCost(_ellipses(), gamma=0.02, weight=5.0, steps=s_alone),
        )

    alone = 8 - steps
    fused, reference, capture, x = _pair(dyn, cost_with(steps, alone), dtype)
    tol = dict(rtol=1e-12, atol=1e-12) if dtype == torch.float64 else dict(rtol=1e-5, atol=1e-5)
    for shift in (True, False):
        a, b = fused(x, shift=shift), reference(x, shift=shift)
        assert fused.path == "fused" and reference.path == "rollout"
        for field in ("plan", "cost_min", "cost_mean", "best_states"):
            torch.testing.assert_close(getattr(a, field), getattr(b, field), **tol, msg=field)
    states, controls = capture.seen["states"], capture.seen["controls"]
    here = cost_with(steps, alone)(states, controls, None)
    for s, s_alone in (
        (steps - 1, alone),
        (steps + 1, alone),
        (steps, alone - 1),
        (steps, alone + 1),
    ):
        if 1 <= s <= 7 and 1 <= s_alone <= 7:
            assert not torch.equal(cost_with(s, s_alone)(states, controls, None), here)


def test_update_matches_direct_formula():
    """The update of both kernel paths (fused cost; rollouts for a torch cost, the control
    cost added by the kernel) against the MPPI formulas on the kernel's own noise
    (float64)."""
    dyn = AccelUnicycle()
    cost = SumCost(
        QuadraticGoal((2.0, 4.0), 2.0, (0, 1), 10.0), BarrierCost(_ellipses(), 2.0, 0.01)
    )
    fused, reference, capture, x = _pair(dyn, cost, torch.float64, B=1, K=200)
    fused(x)
    reference(x)
    plan0 = fused(x, shift=False).plan
    reference(x, shift=False)
    out = fused(x)
    out_ref = reference(x)
    states, v = capture.seen["states"][0], capture.seen["controls"][0]
    shifted = torch.cat([plan0[0, 1:], torch.zeros(1, 2, dtype=torch.float64)])
    eps = v - shifted
    S = cost(states[None], v[None], None)[0]
    S = S + 0.2 * torch.einsum("hm,mn,khn->k", shifted, torch.linalg.inv(SIGMA), eps)
    w = torch.softmax(-S / 2.0, 0)
    lo, hi = torch.tensor([-1.5, -2.0]), torch.tensor([2.0, 1.0])
    plan = (shifted + torch.einsum("k,khm->hm", w, eps)).clamp(lo.double(), hi.double())
    torch.testing.assert_close(out.plan[0], plan, rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(out.cost_min[0], S.min(), rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(out.best_states[0], states[S.argmin()], rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(out.rollouts[0], states[:5], rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(out.rollout_weights[0], w[:5], rtol=1e-10, atol=1e-14)
    assert reference.path == "rollout"
    torch.testing.assert_close(out_ref.plan[0], plan, rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(out_ref.cost_min[0], S.min(), rtol=1e-12, atol=1e-12)


def test_batch_equals_loop_and_seeds_repeat():
    dyn = AccelUnicycle(u_min=-3.0, u_max=3.0)
    cost = QuadraticGoal((2.0, 4.0), 2.0, (0, 1), 10.0) + BarrierCost(_ellipses(), 2.0, 0.01)
    x = _x0(dyn, 3, torch.float32)
    batched = MPPI(dyn, cost, 10, 300, 0.02, 4.0, 0.03, 0.1, seed=5)
    singles = [MPPI(dyn, cost, 10, 300, 0.02, 4.0, 0.03, 0.1, seed=5 + b) for b in range(3)]
    again = MPPI(dyn, cost, 10, 300, 0.02, 4.0, 0.03, 0.1, seed=5)
    first = None
    for _ in range(3):
        out = batched(x)
        assert batched.path == "fused"
        assert torch.equal(again(x).plan, out.plan)  # a seed repeats exactly
        first = out.plan if first is None else first
        for b in range(3):
            one = singles[b](x[b])
            assert torch.equal(out.plan[b], one.plan)
            assert torch.equal(out.best_states[b], one.best_states)
    batched.reset()
    assert torch.equal(batched(x).plan, first)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_kernel_noise_statistics(dtype):
    """Zero-mean noise with covariance Sigma, independent over steps; zero-noise samples."""
    K, H = 20000, 3
    cost = Capture(QuadraticGoal((0.0, 0.0)))
    planner = MPPI(
        SingleIntegrator(2), cost, H, K, 0.1, SIGMA, 1.0, zero_noise_samples=4, cost_chunk=0
    )
    planner(torch.zeros(2, dtype=dtype))
    assert planner.path == "rollout"
    eps = cost.seen["controls"][0].double()  # the first plan is zero
    assert torch.equal(eps[:4], torch.zeros_like(eps[:4]))
    eps = eps[4:]
    flat = eps.reshape(-1, 2)
    torch.testing.assert_close(flat.mean(0), torch.zeros(2, dtype=torch.float64), atol=0.02, rtol=0)
    torch.testing.assert_close(flat.T.cov(), SIGMA, atol=0.03, rtol=0)
    # steps are uncorrelated, and so are neighbouring samples
    corr = torch.corrcoef(torch.stack([eps[:-1, 0, 0], eps[:-1, 1, 0], eps[1:, 0, 0]]))
    assert float(corr[0, 1].abs()) < 0.03 and float(corr[0, 2].abs()) < 0.03
    z = eps[:, :, 0] / SIGMA[0, 0].sqrt()  # standard normal: tail mass as expected
    assert abs(float((z.abs() > 2).double().mean()) - 0.0455) < 0.005


def test_fallback_rule():
    x = torch.tensor([0.0, 0.0, 0.0, 0.3])
    goal = QuadraticGoal((2.0, 4.0), 2.0, (0, 1))

    class MyUnicycle(AccelUnicycle):
        def xdot(self, x, u):
            return 0.5 * super().xdot(x, u)

    def user_cost(states, controls, t0):
        return ((states[..., :2] - 1.0) ** 2).sum((-1, -2))

    cases = [
        (MPPI(AccelUnicycle(), goal, 5, 32, 0.1, 1.0, 1.0), "fused"),
        (MPPI(MyUnicycle(), goal, 5, 32, 0.1, 1.0, 1.0), "torch"),
        (MPPI(AccelUnicycle(), user_cost, 5, 32, 0.1, 1.0, 1.0), "rollout"),
        (MPPI(AccelUnicycle(), goal + user_cost, 5, 32, 0.1, 1.0, 1.0), "rollout"),
        (MPPI(AccelUnicycle(), goal, 5, 32, 0.1, 1.0, 1.0, backend="torch"), "torch"),
        (
            MPPI(SingleIntegrator(2), Reach((1.0, 0.0), 0.2, (0.0, 0.5)), 5, 16, 0.1, 1.0, 1.0),
            "rollout",
        ),
        (
            MPPI(AccelUnicycle(), BarrierCost(lambda s: s[..., 0] + 2.0), 5, 32, 0.1, 1.0, 1.0),
            "rollout",
        ),
    ]
    for planner, path in cases:
        xs = x[:2] if isinstance(planner.dynamics, SingleIntegrator) else x
        out = planner(xs)
        assert planner.path == path
        assert torch.isfinite(out.plan).all()
    # a learnable barrier with gradients enabled runs in torch; without gradients it fuses
    learn = Ellipse((1.0, 2.0), (0.5, 1.5), learnable=True)
    planner = MPPI(AccelUnicycle(), BarrierCost(learn), 5, 32, 0.1, 1.0, 1.0)
    planner(x)
    assert planner.path == "torch"
    with torch.no_grad():
        planner(x)
    assert planner.path == "fused"


def test_nonfinite_samples_are_counted():
    """-inf, +inf and NaN costs get weight zero and are counted."""
    dyn = SingleIntegrator(2)

    def cost(states, controls, t0):
        c = states[..., -1, 0].clone()
        c[..., :3] = -math.inf
        c[..., 3] = math.nan
        c[..., 4] = math.inf
        return c

    planner = MPPI(dyn, cost, 4, 16, 0.1, 1.0, 1.0)
    out = planner(torch.zeros(2))
    assert int(out.nonfinite) == 5 and int(out.status) == 0
    assert torch.isfinite(out.plan).all()


def test_threads_do_not_change_results():
    dyn = AccelUnicycle()
    cost = QuadraticGoal((2.0, 4.0), 2.0, (0, 1), 10.0) + BarrierCost(_ellipses(), 2.0, 0.01)
    x = _x0(dyn, 3, torch.float32)
    threads = torch.get_num_threads()
    plans = []
    try:
        for n in (1, 3):
            torch.set_num_threads(n)
            planner = MPPI(dyn, cost, 8, 1500, 0.02, 4.0, 1.0, 0.1, cost_normalization="std")
            planner(x)
            out = planner(x)
            assert int((out.ess > 100).sum()) == 3  # many samples in the update pass
            plans.append(out.plan)
    finally:
        torch.set_num_threads(threads)
    assert torch.equal(plans[0], plans[1])


def test_rollout_buffers_threads_and_layout():
    """The kernel's rollout buffers: the same with threads splitting an environment, stored
    component-major, and the raw call refuses sample-major buffers."""
    dyn = AccelUnicycle()
    x = _x0(dyn, 3, torch.float32)
    threads = torch.get_num_threads()
    seen = []
    try:
        for n in (1, 2):  # two threads split the 750 samples inside environment 1
            torch.set_num_threads(n)
            capture = Capture(QuadraticGoal((2.0, 4.0), 2.0, (0, 1)))
            planner = MPPI(dyn, capture, 6, 250, 0.02, SIGMA, 1.0, 0.1, seed=4, cost_chunk=0)
            planner(x)
            assert planner.path == "rollout"
            seen.append(capture.seen)
    finally:
        torch.set_num_threads(threads)
    for key in ("states", "controls"):
        assert torch.equal(seen[0][key], seen[1][key])
    ref = [seen[0]["states"][:, :, 0]]
    for j in range(6):
        ref.append(euler(dyn, ref[-1], seen[0]["controls"][:, :, j], 0.02))
    torch.testing.assert_close(seen[0]["states"], torch.stack(ref, 2), rtol=1e-6, atol=1e-6)
    # what the cost receives: [B, K, H+1, n] views with each component's samples contiguous
    for t in planner._rollout_buffers(noise=True):
        assert t.permute(0, 3, 2, 1).is_contiguous() and t.stride(1) == 1
    cfg = planner._configuration(_rollout.encode_model(dyn), None)
    keys = _rollout.draw_keys(planner._generators, x.device)
    with pytest.raises(ValueError, match="component-major"):
        _rollout.run(cfg, 750, x, planner._plan, keys, states=torch.empty(3, 250, 7, 4))


@pytest.mark.parametrize("backend", ["auto", "torch"])
def test_cost_slices_are_component_major(backend):
    """Automatic slices: at least MIN_CHUNK_SAMPLES samples, samples contiguous."""
    from torchcbf.mppi.planner import MIN_CHUNK_SAMPLES

    shapes = []

    def cost(states, controls, t0):
        shapes.append((states.shape[1], states.stride(1), controls.stride(1)))
        return states[..., -1, 0] + controls[..., 0].sum(-1)

    planner = MPPI(AccelUnicycle(), cost, 60, 64, 0.02, 1.0, 1.0, backend=backend)
    planner(_x0(AccelUnicycle(), 8, torch.float32))
    assert planner.path == ("rollout" if backend == "auto" else "torch")
    assert all(k >= MIN_CHUNK_SAMPLES and s == 1 and c == 1 for k, s, c in shapes[:-1])
    assert sum(k for k, _, _ in shapes) == 64


@pytest.mark.parametrize("change", ["in place", "attribute", "through .data", "numpy memory"])
def test_a_changed_cost_is_read_again(change):
    # the kernel's configuration is kept between calls: a change of the cost must reach it,
    # also one that leaves the tensor's in-place version alone (.data, a NumPy array's memory)
    dyn = AccelUnicycle(u_min=-3.0, u_max=3.0)
    x = _x0(dyn, 1, torch.float64)[0]
    shared = np.array([2.0, 4.0])
    goal = QuadraticGoal(torch.from_numpy(shared), 2.0, (0, 1)).double()
    assert np.shares_memory(goal.goal.numpy(), shared)
    fused = MPPI(dyn, goal, 10, 300, 0.02, 4.0, 0.03, 0.1).double()
    by_torch = MPPI(dyn, Capture(goal), 10, 300, 0.02, 4.0, 0.03, 0.1).double()
    for _ in range(2):
        fused(x), by_torch(x)
    if change == "in place":
        with torch.no_grad():
            goal.goal.copy_(torch.tensor([-1.0, 3.0]))
    elif change == "through .data":
        goal.goal.data.copy_(torch.tensor([-1.0, 3.0]))
    elif change == "numpy memory":
        shared[:] = (-1.0, 3.0)
    else:
        goal.weight = 7.0
    for _ in range(2):
        a, b = fused(x), by_torch(x)
        assert fused.path == "fused" and by_torch.path == "rollout"
        torch.testing.assert_close(a.plan, b.plan, rtol=1e-9, atol=1e-9)


def _reference_normals(key: int, k: int, j: int, i: int, H: int, m: int) -> float:
    """The counter-based normal of sample ``k``, step ``j``, component ``i`` written out in
    Python integers (docs/mppi.md, "Randomness")."""
    mask = (1 << 64) - 1
    pairs = (m + 1) // 2
    c = (k * H + j) * pairs + i // 2
    z = (key + (c + 1) * 0x9E3779B97F4A7C15) & mask
    z = ((z ^ (z >> 30)) * 0xBF58476D1CE4E5B9) & mask
    z = ((z ^ (z >> 27)) * 0x94D049BB133111EB) & mask
    h = z ^ (z >> 31)
    u1 = ((h >> 33) + 0.5) * 2.0**-31
    u2 = ((h >> 2) & 0x7FFFFFFF) * 2.0**-31
    r, a = math.sqrt(-2.0 * math.log(u1)), 2.0 * math.pi * u2
    return r * (math.cos(a) if i % 2 == 0 else math.sin(a))


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
@pytest.mark.parametrize("layout", ["component", "sample"])
@pytest.mark.parametrize("m", [1, 3])
def test_normals_equal_the_written_out_generator(dtype, layout, m):
    B, K, H = 2, 70, 3  # more samples than a block of lanes
    keys = torch.tensor([12345, 2**62 + 7], dtype=torch.int64)
    out = _rollout.rollout_buffer(torch.empty(0, dtype=dtype), B, K, H, m, layout)
    _rollout.normals(keys, out, std=2.0)
    picks = [(0, 0, 0, 0), (0, 69, 2, m - 1), (1, 64, 1, 0), (1, 5, 0, m - 1), (1, 33, 2, m // 2)]
    got = torch.tensor([float(out[p]) for p in picks], dtype=torch.float64)
    want = torch.tensor(
        [2.0 * _reference_normals(int(keys[b]), k, j, i, H, m) for b, k, j, i in picks],
        dtype=torch.float64,
    )
    tol = 1e-12 if dtype == torch.float64 else 1e-5
    torch.testing.assert_close(got, want, atol=tol, rtol=tol)
    with pytest.raises(ValueError, match="keys must be int64"):
        _rollout.normals(keys[:1], out)


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
@pytest.mark.parametrize("layout", ["component", "sample"])
@pytest.mark.parametrize(("m", "limits"), [(1, "both"), (2, "upper"), (3, "none")])
def test_perturb_is_clamped_plan_plus_factored_normals(dtype, layout, m, limits):
    B, K, H = 2, 70, 3
    keys = torch.tensor([99, 2**61 + 5], dtype=torch.int64)
    gen = torch.Generator().manual_seed(0)
    plan = torch.randn(B, H, m, generator=gen, dtype=torch.float64).to(dtype)
    chol = torch.linalg.cholesky(torch.eye(m, dtype=torch.float64) + 0.3)
    lo = None if limits in ("none", "upper") else -0.8 * torch.ones(m, dtype=dtype)
    hi = None if limits == "none" else torch.linspace(0.2, 1.0, m, dtype=dtype)
    eps = _rollout.rollout_buffer(torch.empty(0, dtype=dtype), B, K, H, m, layout)
    controls = _rollout.rollout_buffer(torch.empty(0, dtype=dtype), B, K, H, m, layout)
    _rollout.perturb(keys, eps, controls, plan, chol, u_min=lo, u_max=hi)
    z = _rollout.rollout_buffer(torch.empty(0, dtype=torch.float64), B, K, H, m, layout)
    _rollout.normals(keys, z)
    want = plan.double().unsqueeze(1) + z @ chol.mT
    if limits != "none":
        want = want.clamp(None if lo is None else lo.double(), hi.double())
    tol = 1e-12 if dtype == torch.float64 else 2e-6
    torch.testing.assert_close(controls.double(), want, atol=tol, rtol=tol)
    torch.testing.assert_close(eps.double(), want - plan.double().unsqueeze(1), atol=tol, rtol=tol)
    with pytest.raises(ValueError, match="plan must be"):
        _rollout.perturb(keys, eps, controls, plan[:, :1], chol, u_min=lo, u_max=hi)
    with pytest.raises(ValueError, match="controls must be"):
        other = controls.double() if dtype == torch.float32 else controls.float()
        _rollout.perturb(keys, eps, other, plan, chol, u_min=lo, u_max=hi)


class _OwnPerturb(MPPI):
    """MPPI whose sampling is its own method (the same formulas): the two-pass torch path."""

    def _perturb(self, x, t0, eps, controls):
        return super()._perturb(x, t0, eps, controls)


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
@pytest.mark.parametrize(
    "options",
    [
        {},
        {"zero_noise_samples": 3, "sample_null_action": True},
        {"action_sampler": lambda x, t0: torch.ones(2, 6, 2, dtype=x.dtype)},
        {"noise_sigma": torch.tensor([[0.5, 0.2], [0.2, 0.3]])},
    ],
    ids=["plain", "zero noise and null action", "sampler", "covariance"],
)
def test_one_pass_sampling_equals_the_two_pass_torch_sampling(dtype, options):
    def planner(cls):
        kw = {"noise_sigma": 0.4, **options}
        dyn = Unicycle(u_min=torch.tensor([-1.0, -2.0]), u_max=torch.tensor([1.5, 2.0]))
        goal = QuadraticGoal((2.0, 1.0), 1.0, (0, 1), 5.0)
        return cls(dyn, goal, 6, 90, 0.05, kw.pop("noise_sigma"), 0.5, 0.1, seed=4,
                   backend="torch", **kw).to(dtype)  # fmt: skip

    one, two = planner(MPPI), planner(_OwnPerturb)
    x = _x0(Unicycle(), 2, dtype)
    tol = 1e-10 if dtype == torch.float64 else 1e-5
    for step in range(3):
        a, b = one(x, 0.1 * step), two(x, 0.1 * step)
        assert one.path == two.path == "torch"
        torch.testing.assert_close(a.plan, b.plan, atol=tol, rtol=tol)
        torch.testing.assert_close(a.cost_min, b.cost_min, atol=tol, rtol=tol)


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
@pytest.mark.parametrize("model", [SingleIntegrator(2, u_min=-1.0, u_max=1.0), Unicycle()])
def test_torch_path_draws_the_kernels_noise(dtype, model):
    """For one seed the torch path and the kernel paths give the same plans."""
    goal = QuadraticGoal((2.0, 1.0), 1.0, (0, 1), 5.0)
    x = _x0(model, 2, dtype)
    plans = {}
    for name, cost, backend in (
        ("fused", goal, "auto"),
        ("rollout", Capture(goal), "auto"),
        ("torch", goal, "torch"),
    ):
        planner = MPPI(model, cost, 8, 200, 0.1, SIGMA, 0.5, 0.1, seed=3, backend=backend)
        planner = planner.to(dtype)
        outs = [planner(x), planner(x + 0.1)]
        assert planner.path == name
        plans[name] = torch.stack([o.plan for o in outs])
    tol = 1e-10 if dtype == torch.float64 else 2e-5
    torch.testing.assert_close(plans["torch"], plans["fused"], atol=tol, rtol=tol)
    torch.testing.assert_close(plans["rollout"], plans["fused"], atol=tol, rtol=tol)
