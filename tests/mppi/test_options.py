"""The planner's options and variants against hand-written references: which path answers,
u_scale, step=, NumPy states, one-sided bounds, change_horizon, rollout_samples, candidate
samples, and the SMPPI and KMPPI updates against their update formulas written as loops."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from torchcbf.dynamics import DoubleIntegrator, SingleIntegrator
from torchcbf.mppi import KMPPI, MPPI, SMPPI, QuadraticGoal, rbf_kernel

GOAL = torch.tensor([1.0, -0.5])
TOL = {torch.float64: 1e-10, torch.float32: 2e-4}


def goal_cost() -> QuadraticGoal:
    return QuadraticGoal(GOAL, weight=1.0, terminal_weight=5.0)


def quadratic(states: torch.Tensor, controls: torch.Tensor, t0: torch.Tensor) -> torch.Tensor:
    """The goal cost written in Python (scored in torch)."""
    d = states - GOAL.to(states)
    return d.square().sum((-2, -1)) + 4.0 * d[..., -1, :].square().sum(-1)


def planner(cls: type[MPPI] = MPPI, cost=None, dtype=torch.float64, **kwargs) -> MPPI:
    kwargs.setdefault("control_cost_weight", 0.1)
    kwargs.setdefault("noise_sigma", 0.5)
    kwargs.setdefault("temperature", 0.2)
    return cls(
        SingleIntegrator(), goal_cost() if cost is None else cost, horizon=8, num_samples=64,
        dt=0.1, **kwargs,
    ).to(dtype)  # fmt: skip


@pytest.mark.parametrize(
    "option",
    [
        {"step": lambda x, u, j: x + 0.1 * u},
        {"noise_abs_cost": True},
        {"action_sampler": lambda x, t: torch.zeros(2, 8, 2, dtype=x.dtype)},
        {"sample_null_action": True},
        {"noise_mu": 0.2},
    ],
)
def test_options_the_kernel_cannot_express_take_the_torch_path(option: dict) -> None:
    x = torch.zeros(2, dtype=torch.float64)
    assert planner()(x).path == "fused"
    assert planner(cost=quadratic)(x).path == "rollout"
    assert planner(**option)(x).path == "torch"
    assert planner(cost=quadratic, **option)(x).path == "torch"
    for cls in (SMPPI, KMPPI):
        assert planner(cls)(x).path == "torch"


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
@pytest.mark.parametrize("backend", ["auto", "torch"])
def test_u_scale_is_a_scaled_noise_covariance(dtype: torch.dtype, backend: str) -> None:
    scale = torch.tensor([2.0, 0.5], dtype=torch.float64)
    sigma = torch.tensor([[0.5, 0.1], [0.1, 0.3]], dtype=torch.float64)
    scaled = scale.unsqueeze(-1) * sigma * scale
    a = planner(u_scale=scale, noise_sigma=sigma, backend=backend, u_min=-1.0, u_max=1.0)
    b = planner(noise_sigma=scaled, backend=backend, u_min=-1.0, u_max=1.0)
    a, b = a.to(dtype), b.to(dtype)
    x = torch.tensor([[0.0, 0.0], [0.3, -0.2]], dtype=dtype)
    for _ in range(4):
        ua, ub = a(x), b(x)
        assert ua.path == ub.path == ("fused" if backend == "auto" else "torch")
        torch.testing.assert_close(ua.plan, ub.plan, rtol=TOL[dtype], atol=TOL[dtype])
        x = x + 0.1 * ua.u
    with pytest.raises(ValueError, match="u_scale"):
        planner(u_scale=-1.0)
    with pytest.raises(ValueError, match="u_scale"):
        planner(u_scale=[1.0, 2.0, 3.0])


@pytest.mark.parametrize("scale", [None, 2.0])
def test_noise_mu_shifts_the_samples(scale: float | None) -> None:
    mu = torch.tensor([0.5, -0.25], dtype=torch.float64)
    p = planner(noise_mu=mu, u_scale=scale, noise_sigma=0.04)
    seen = recorded(p)
    p(torch.zeros(2, dtype=torch.float64))
    eps = seen[-1].reshape(-1, 2)  # 512 draws per component
    s = 1.0 if scale is None else scale
    # mean s mu, standard deviation s 0.2: within 4 standard errors
    assert bool(((eps.mean(0) - s * mu).abs() < 4 * s * 0.2 / math.sqrt(512)).all())
    with pytest.raises(ValueError, match="noise_mu"):
        planner(noise_mu=[0.0, math.inf])


def test_step_of_the_integrator_gives_the_integrators_plans() -> None:
    a = planner(backend="torch", cost=quadratic)
    b = planner(step=lambda x, u, j: x + 0.1 * u, cost=quadratic)
    x = torch.tensor([0.2, 0.1], dtype=torch.float64)
    for _ in range(3):
        ua, ub = a(x), b(x)
        torch.testing.assert_close(ua.plan, ub.plan, rtol=1e-12, atol=1e-12)
        x = x + 0.1 * ua.u


def test_step_receives_the_step_index() -> None:
    seen: list[int] = []

    def step(x: torch.Tensor, u: torch.Tensor, j: int) -> torch.Tensor:
        seen.append(j)
        return x + 0.1 * u

    planner(step=step)(torch.zeros(2, dtype=torch.float64))
    assert seen == list(range(8))
    with pytest.raises(TypeError, match="step"):
        planner(step=3)


@pytest.mark.parametrize("np_dtype", [np.float64, np.float32])
def test_numpy_states_give_numpy_outputs(np_dtype: type) -> None:
    x = np.array([[0.2, 0.1], [0.0, -0.3]], dtype=np_dtype)
    a, b = planner(), planner()
    out = a(x)
    ref = b(torch.from_numpy(x))
    assert isinstance(out.u, np.ndarray) and out.u.dtype == np_dtype and out.u.shape == (2, 2)
    assert isinstance(out.plan, np.ndarray) and out.plan.shape == (2, 8, 2)
    assert out.path == ref.path
    np.testing.assert_allclose(out.plan, ref.plan.numpy(), rtol=1e-6, atol=1e-6)
    one = planner()(x[0])
    assert one.u.shape == (2,)


def test_a_one_sided_bound_is_one_sided() -> None:
    p = planner(u_max=0.05, noise_sigma=4.0)
    assert p.u_min is None
    x = torch.tensor([-3.0, -3.0], dtype=torch.float64)  # the goal lies up and to the right
    out = p(x)
    assert bool((out.plan <= 0.05).all())
    far = planner(u_max=0.05, noise_sigma=4.0)(torch.tensor([5.0, 5.0], dtype=torch.float64))
    assert float(far.plan.min()) < -0.5  # no lower bound


@pytest.mark.parametrize("cls", [MPPI, SMPPI, KMPPI])
def test_change_horizon_keeps_the_plan_and_plans_on(cls: type[MPPI]) -> None:
    p = planner(cls, backend="torch" if cls is MPPI else "auto")
    x = torch.tensor([0.3, 0.0], dtype=torch.float64)
    p(x)
    before = p._plan.clone()
    p.change_horizon(5)
    if cls is not KMPPI:  # KMPPI re-places its control points on the new horizon
        torch.testing.assert_close(p._plan, before[:, :5])
    assert p(x).plan.shape == (5, 2)
    p.change_horizon(12)
    assert p(x).plan.shape == (12, 2)
    with pytest.raises(ValueError, match="horizon"):
        p.change_horizon(0)


@pytest.mark.parametrize("cls", [MPPI, SMPPI, KMPPI])
def test_setting_horizon_is_change_horizon(cls: type[MPPI]) -> None:
    """``planner.horizon = H`` plans on exactly as ``change_horizon(H)`` does, with its checks."""
    x = torch.tensor([0.3, 0.0], dtype=torch.float64)
    a, b = planner(cls), planner(cls)
    a(x), b(x)
    a.horizon = 5
    b.change_horizon(5)
    assert a.horizon == 5
    torch.testing.assert_close(a(x).plan, b(x).plan, atol=0.0, rtol=0.0)
    with pytest.raises(ValueError, match="horizon"):
        a.horizon = 0
    assert a.horizon == 5


def test_a_step_set_between_calls_is_checked() -> None:
    p = planner()
    x = torch.tensor([0.3, 0.0], dtype=torch.float64)
    p(x)
    for bad in (-0.1, 0.0, float("nan")):
        p.dt = bad
        with pytest.raises(ValueError, match="dt must be"):
            p(x)


def test_a_negated_view_of_the_state_is_planned_from_its_values() -> None:
    """A state whose negative bit is set (its memory holds the values negated) plans as
    the state itself on the fused path, not as its negation."""
    x = torch.tensor([0.3, -0.2], dtype=torch.float64)
    view = torch._neg_view(-x)
    assert view.is_neg() and torch.equal(view, x)
    a, b = planner(), planner()
    got, want = a(view), b(x)
    assert got.path == want.path == "fused"
    torch.testing.assert_close(got.plan, want.plan, atol=0.0, rtol=0.0)


def test_change_horizon_on_the_fused_path() -> None:
    p = planner()
    x = torch.tensor([0.3, 0.0], dtype=torch.float64)
    p(x)
    before = p._plan.clone()
    p.change_horizon(12)
    torch.testing.assert_close(p._plan[:, :8], before)
    assert bool((p._plan[:, 8:] == 0).all())
    out = p(x)
    assert out.path == "fused" and out.plan.shape == (12, 2) and out.best_states.shape == (13, 2)


def test_rollout_samples_of_a_deterministic_model_roll_the_plan_out() -> None:
    p = planner()
    x = torch.tensor([[0.3, 0.0], [0.0, 0.2]], dtype=torch.float64)
    out = p(x)
    roll = p.rollout_samples(x, 3)
    assert roll.shape == (2, 3, 9, 2)
    expected = x.unsqueeze(1) + 0.1 * torch.cat(
        [torch.zeros(2, 1, 2, dtype=x.dtype), out.plan.cumsum(1)], 1
    )
    for r in range(3):
        torch.testing.assert_close(roll[:, r], expected)
    other = torch.ones(8, 2, dtype=torch.float64)
    assert p.rollout_samples(x[0], 1, plan=other).shape == (1, 9, 2)
    with pytest.raises(ValueError, match="plan"):
        planner().rollout_samples(x, 1)


def test_rollout_samples_of_an_sde_draw_its_noise() -> None:
    s = 0.3
    p = MPPI(SingleIntegrator(sigma=s), goal_cost(), horizon=8, num_samples=16, dt=0.1,
             noise_sigma=0.5, temperature=0.2).double()  # fmt: skip
    x = torch.zeros(2, dtype=torch.float64)
    out = p(x)
    roll = p.rollout_samples(x, 4000, seed=1)
    torch.testing.assert_close(p.rollout_samples(x, 4000, seed=1), roll)
    drift = 0.1 * out.plan.sum(0)
    end = roll[:, -1] - drift  # N(0, s^2 H dt) per component
    var = end.var(0)
    expected = s * s * 8 * 0.1
    # 4000 samples: the sample variance is within 4 standard errors (sqrt(2 / N) relative)
    assert bool(((var / expected - 1).abs() < 4 * math.sqrt(2 / 4000)).all())
    assert float(end.mean(0).abs().max()) < 4 * math.sqrt(expected / 4000)


def test_candidates_are_sampled_and_checked() -> None:
    best = torch.full((8, 2), 0.0, dtype=torch.float64)
    best[:, 0], best[:, 1] = 1.0 / 0.8, -0.5 / 0.8  # reaches the goal at the horizon
    p = planner(action_sampler=lambda x, t: best.unsqueeze(0), temperature=1e-6,
                noise_sigma=1e-4, control_cost_weight=0.0)  # fmt: skip
    out = p(torch.zeros(2, dtype=torch.float64))
    # the candidate is the best sample: with a cold temperature the plan becomes it
    torch.testing.assert_close(out.plan, best, rtol=1e-6, atol=1e-6)
    for bad in (torch.zeros(2, 7, 2), torch.zeros(3, 1, 8, 2), torch.zeros(65, 8, 2)):
        p = planner(action_sampler=lambda x, t, bad=bad: bad.double())
        with pytest.raises(ValueError, match="action_sampler"):
            p(torch.zeros(2, dtype=torch.float64))
    p = planner(action_sampler=lambda x, t: np.zeros((1, 8, 2)))
    with pytest.raises(TypeError, match="action_sampler"):
        p(torch.zeros(2, dtype=torch.float64))
    with pytest.raises(ValueError, match="sample_null_action"):
        MPPI(SingleIntegrator(), goal_cost(), horizon=8, num_samples=2, dt=0.1, noise_sigma=0.5,
             temperature=0.2, zero_noise_samples=2, sample_null_action=True)  # fmt: skip


def recorded(p: MPPI) -> list[torch.Tensor]:
    """Record the noise the planner draws."""
    seen: list[torch.Tensor] = []
    draw = p._sample_noise

    def record(eps: torch.Tensor) -> None:
        draw(eps)
        seen.append(eps.clone())

    p._sample_noise = record  # type: ignore[method-assign]
    return seen


def weights(S: torch.Tensor, lam: float) -> torch.Tensor:
    w = torch.exp(-(S - S.min()) / lam)
    return w / w.sum()


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_smppi_update_against_the_formula(dtype: torch.dtype) -> None:
    dt_s, w_s, gamma, lam = 0.5, 2.0, 0.1, 0.2
    model = DoubleIntegrator(dim=1)
    p = SMPPI(model, quadratic_1d, horizon=6, num_samples=12, dt=0.1, noise_sigma=0.7,
              temperature=lam, control_cost_weight=gamma, u_min=-0.6, u_max=0.8,
              smoothness_weight=w_s, delta_t=dt_s, du_min=-0.9, du_max=1.0).to(dtype)  # fmt: skip
    seen = recorded(p)
    x = torch.tensor([0.4, -0.1], dtype=dtype)
    p(x)  # a first call sets U and A away from zero
    U, A = p._rate[0].clone(), p._plan[0].clone()
    p._fresh = True  # compare one update without the warm start
    out = p(x)
    z = seen[-1][0]  # [K, H, 1] as drawn
    K, H = 12, 6
    S = torch.zeros(K, dtype=torch.float64)
    actions, noise = [], []
    for k in range(K):
        v = (U.double() + z[k].double()).clamp(-0.9, 1.0)
        a = (A.double() + v * dt_s).clamp(-0.6, 0.8)
        e = (a - A.double()) / dt_s - U.double()
        xs = [x.double()]
        for j in range(H):
            pos, vel = xs[-1]
            xs.append(torch.stack([pos + 0.1 * vel, vel + 0.1 * a[j, 0]]))
        states = torch.stack(xs).unsqueeze(0).unsqueeze(0)
        S[k] = quadratic_1d(states, a.view(1, 1, H, 1), None)[0, 0]
        S[k] += gamma * (U.double() / 0.7 * e).sum() + w_s * (a[1:] - a[:-1]).square().sum()
        actions.append(a)
        noise.append(e)
    wk = weights(S, lam)
    new_U = (U.double() + sum(wk[k] * noise[k] for k in range(K))).clamp(-0.9, 1.0)
    new_A = (A.double() + new_U * dt_s).clamp(-0.6, 0.8)
    tol = TOL[dtype] * 10
    torch.testing.assert_close(p.rate[0].double(), new_U, rtol=tol, atol=tol)
    torch.testing.assert_close(out.plan.double(), new_A, rtol=tol, atol=tol)
    # the rate bounds hold for every sample (pytorch-mppi 0.9.1 ignores them)
    assert bool((torch.stack(noise) + U.double() <= 1.0 + 1e-6).all())


def quadratic_1d(states: torch.Tensor, controls: torch.Tensor, t0) -> torch.Tensor:
    return (states[..., 0] - 1.0).square().sum(-1) + 0.1 * states[..., 1].square().sum(-1)


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_kmppi_update_against_the_formula(dtype: torch.dtype) -> None:
    gamma, lam, width, Sn, H, K = 0.1, 0.3, 1.5, 5, 9, 12
    model = DoubleIntegrator(dim=1)
    p = KMPPI(model, quadratic_1d, horizon=H, num_samples=K, dt=0.1, noise_sigma=0.7,
              temperature=lam, control_cost_weight=gamma, u_min=-0.6, u_max=0.8,
              num_support_points=Sn, kernel=rbf_kernel(width)).to(dtype)  # fmt: skip
    seen = recorded(p)
    x = torch.tensor([0.4, -0.1], dtype=dtype)
    p(x)
    theta, U = p._theta[0].double().clone(), p._plan[0].double().clone()
    p._fresh = True
    out = p(x)
    z = seen[-1][0].double()  # [K, S, 1]
    tau = [j * (H - 1) / (Sn - 1) for j in range(Sn)]  # 0, 2, 4, 6, 8

    def k(a: float, b: float) -> float:
        return math.exp(-((a - b) ** 2) / (2 * width**2))

    gram = torch.tensor([[k(a, b) for b in tau] for a in tau], dtype=torch.float64)
    cross = torch.tensor([[k(t, b) for b in tau] for t in range(H)], dtype=torch.float64)
    W = cross @ torch.linalg.inv(gram)
    S = torch.zeros(K, dtype=torch.float64)
    pts = []
    for i in range(K):
        p_i = (theta + z[i]).clamp(-0.6, 0.8)
        v = (W @ p_i).clamp(-0.6, 0.8)
        xs = [x.double()]
        for j in range(H):
            pos, vel = xs[-1]
            xs.append(torch.stack([pos + 0.1 * vel, vel + 0.1 * v[j, 0]]))
        states = torch.stack(xs).view(1, 1, H + 1, 2)
        S[i] = quadratic_1d(states, v.view(1, 1, H, 1), None)[0, 0]
        S[i] += gamma * (U / 0.7 * (v - U)).sum()
        pts.append(p_i - theta)
    wk = weights(S, lam)
    new_theta = theta + sum(wk[i] * pts[i] for i in range(K))
    tol = TOL[dtype] * 10
    torch.testing.assert_close(p.control_points[0].double(), new_theta, rtol=tol, atol=tol)
    torch.testing.assert_close(
        out.plan.double(), (W @ new_theta).clamp(-0.6, 0.8), rtol=tol, atol=tol
    )
    # the interpolation passes through the control points at the support steps
    torch.testing.assert_close(W[[0, 2, 4, 6, 8]], torch.eye(Sn, dtype=torch.float64))


@pytest.mark.parametrize("cls", [SMPPI, KMPPI])
def test_variants_batch_equals_loop(cls: type[MPPI]) -> None:
    x = torch.tensor([[0.3, 0.0], [0.0, 0.2], [-0.4, 0.5]], dtype=torch.float64)
    batched = planner(cls, cost=quadratic, seed=5)
    singles = [planner(cls, cost=quadratic, seed=5 + b) for b in range(3)]
    for _ in range(3):
        out = batched(x)
        for b in range(3):
            one = singles[b](x[b])
            torch.testing.assert_close(out.plan[b], one.plan, rtol=1e-12, atol=1e-12)
        x = x + 0.1 * out.u


def test_variants_check_their_options() -> None:
    with pytest.raises(ValueError, match="smoothness_weight"):
        planner(SMPPI, smoothness_weight=-1.0)
    with pytest.raises(ValueError, match="delta_t"):
        planner(SMPPI, delta_t=0.0)
    with pytest.raises(ValueError, match="du_min"):
        planner(SMPPI, du_min=1.0, du_max=0.0)
    with pytest.raises(ValueError, match="num_support_points"):
        planner(KMPPI, num_support_points=9)
    with pytest.raises(ValueError, match="width"):
        rbf_kernel(0.0)
    p = planner(KMPPI, num_support_points=6)
    with pytest.raises(ValueError, match="num_support_points"):
        p.change_horizon(5)


@pytest.mark.parametrize("cls", [MPPI, SMPPI, KMPPI])
def test_every_variant_pickles_after_a_call(cls: type[MPPI]) -> None:
    """A planner (KMPPI with its default kernel too) survives pickling after a call and
    plans on from the same state as the original."""
    import pickle

    p = planner(cls)
    x = torch.tensor([0.2, -0.1], dtype=torch.float64)
    p(x)
    copy = pickle.loads(pickle.dumps(p))
    torch.testing.assert_close(copy(x).u, p(x).u)


def test_a_kernel_whose_gram_is_singular_to_rounding_is_named() -> None:
    """A kernel as wide as the horizon over many points: k(tau, tau) is singular to
    rounding, and the plan would not pass through its control points (W(tau) = I)."""
    model = DoubleIntegrator(dim=1)
    for width, points in ((1e6, 5), (6.0, 15), (math.inf, 5)):
        p = KMPPI(model, quadratic_1d, horizon=15, num_samples=8, dt=0.1, noise_sigma=0.7,
                  temperature=0.3, num_support_points=points, kernel=rbf_kernel(width))  # fmt: skip
        with pytest.raises(ValueError, match="singular to rounding"):
            p(torch.zeros(2))
    fine = KMPPI(model, quadratic_1d, horizon=15, num_samples=8, dt=0.1, noise_sigma=0.7,
                 temperature=0.3, num_support_points=8, kernel=rbf_kernel(6.0))  # fmt: skip
    fine = fine.double()
    fine(torch.zeros(2, dtype=torch.float64))
    tau = fine.support(15, fine._plan)
    eye = torch.eye(8, dtype=torch.float64)
    torch.testing.assert_close(fine.interpolation(tau, tau), eye, atol=1e-6, rtol=0)
    # a kernel computed in float32, well conditioned (about 6e3 over 30 points), is taken
    wide = rbf_kernel(1.4)
    f32 = KMPPI(model, quadratic_1d, horizon=30, num_samples=8, dt=0.1, noise_sigma=0.7,
                temperature=0.3, num_support_points=30,
                kernel=lambda a, b: wide(a.float(), b.float()))  # fmt: skip
    f32(torch.zeros(2))
