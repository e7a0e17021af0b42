"""Scenario B's risk-aware filter: the inflated ellipses and the speed range of its noise
bound."""

from __future__ import annotations

import math

import pytest
import torch

from torchcbf.scenarios.unicycle_mppi_cbf import (
    AXES,
    CENTERS,
    DT,
    SIGMA,
    STEPS,
    mppi_cbf,
    obstacles,
    operating_states,
    risk_failures,
)


def test_obstacles_inflation_adds_to_every_semi_axis() -> None:
    m = 0.2
    grown = obstacles(inflation=m).double()
    for (cx, cy), (a1, a2) in zip(CENTERS, AXES, strict=True):
        on_axes = torch.tensor(
            [[cx + a1 + m, cy, 0.0, 0.0], [cx, cy - a2 - m, 0.0, 0.0]], dtype=torch.float64
        )
        b = grown(on_axes)  # [2, 5]: the vertices of the grown ellipse lie on its boundary
        i = CENTERS.index((cx, cy))
        torch.testing.assert_close(b[:, i], torch.zeros(2, dtype=torch.float64))
    torch.testing.assert_close(obstacles(inflation=0.0).axes, obstacles().axes)


@pytest.mark.parametrize("max_speed", [3.0, 8.0, 0.7])
def test_operating_states_cover_the_speeds(max_speed: float) -> None:
    grid = operating_states(max_speed=max_speed)
    speeds = grid[:, 2].unique()
    assert float(speeds.min()) == -0.5
    assert float(speeds.max()) == pytest.approx(max_speed)
    assert float(speeds.diff().max()) <= 0.5 + 1e-12
    assert grid.shape[-1] == 4
    for bad in (0.0, -1.0, math.inf):
        with pytest.raises(ValueError, match="max_speed"):
            operating_states(max_speed=bad)


def test_risk_filter_noise_bound_covers_its_speeds_on_the_inflated_ellipses() -> None:
    """eta_i bounds |dh_i/dx sigma| (autograd) at safe states with speeds up to
    risk_max_speed, for the radius form of the inflated ellipses; the filter's barrier is
    zero on the inflated boundary at rest."""
    m, v_max = 0.1, 8.0
    sc = mppi_cbf(
        "mppi_rascbf",
        num_seeds=1,
        num_samples=8,
        horizon=4,
        dtype=torch.float64,
        risk_inflation=m,
        risk_max_speed=v_max,
        risk_form="rectified",
    )
    p = sc.params
    assert p["risk_inflation"] == m and p["risk_max_speed"] == v_max
    eta = torch.tensor(p["eta"], dtype=torch.float64)
    narrow = mppi_cbf("mppi_rascbf", num_seeds=1, num_samples=8, horizon=4, dtype=torch.float64)
    assert narrow.params["risk_max_speed"] == 8.0 and narrow.params["risk_inflation"] == 0.0
    (barrier,) = sc.safety_filter.barriers
    gen = torch.Generator().manual_seed(5)
    lo = torch.tensor([-2.5, -2.0, -0.5, -math.pi], dtype=torch.float64)
    hi = torch.tensor([5.0, 6.5, v_max, math.pi], dtype=torch.float64)
    x = lo + (hi - lo) * torch.rand(4000, 4, generator=gen, dtype=torch.float64)
    x.requires_grad_(True)
    h = barrier(x)
    for i in range(h.shape[-1]):
        (grad,) = torch.autograd.grad(h[:, i].sum(), x, retain_graph=True)
        norm = (grad * SIGMA).norm(dim=-1)[h[:, i].detach() >= 0]
        assert float(norm.max()) <= float(eta[i]) * 1.15  # the grid's maximum, up to spacing
    (cx, cy), (a1, _) = CENTERS[0], AXES[0]
    at_rest = torch.tensor([[cx - a1 - m, cy, 0.0, 0.0]], dtype=torch.float64)
    # the axes are built in float32 (0.6 is not exact there), then cast
    assert float(barrier(at_rest)[0, 0]) == pytest.approx(0.0, abs=1e-5)
    for name, bad in (("risk_inflation", -0.1), ("risk_max_speed", 0.0)):
        with pytest.raises(ValueError, match=name):
            mppi_cbf("mppi_rascbf", num_seeds=1, num_samples=8, horizon=4, **{name: bad})


@pytest.mark.slow  # 7-10 s on 2 cores: in the slow suite, which CI runs too
def test_inside_form_lies_inside_the_obstacle_free_set() -> None:
    """The inside form is the smooth minimum of the rectified form and k r_i: at most k r_i
    (so negative in every ellipse, whatever the velocity), -tau log 2 on the boundary at
    rest, and within tau log 2 of the rectified form where that is the smaller by far."""
    tau, k = 0.5, 20.0
    kw = {"num_seeds": 1, "num_samples": 8, "horizon": 4, "dtype": torch.float64}
    inside = mppi_cbf("mppi_rascbf", risk_form="inside", risk_temperature=tau, **kw)
    rectified = mppi_cbf("mppi_rascbf", risk_form="rectified", **kw)
    assert inside.params["risk_form"] == "inside" and inside.params["risk_temperature"] == tau
    assert inside.safety_filter.barriers[0].has_analytic
    (h_in,) = inside.safety_filter.barriers
    (h_re,) = rectified.safety_filter.barriers
    gen = torch.Generator().manual_seed(7)
    lo = torch.tensor([-2.5, -2.0, -0.5, -math.pi], dtype=torch.float64)
    hi = torch.tensor([5.0, 6.5, 8.0, math.pi], dtype=torch.float64)
    x = lo + (hi - lo) * torch.rand(4000, 4, generator=gen, dtype=torch.float64)
    r = torch.sqrt(obstacles().double()(x) + 1) - 1
    hi_, hr = h_in(x), h_re(x)
    assert bool((hi_ <= k * r + 1e-9).all()) and bool((hi_ <= hr + 1e-9).all())
    collided = r < 0
    assert bool(collided.any()) and bool((hr[collided] > 0).any())  # the rectified form: not
    assert bool((hi_[collided] < 0).all())
    far = (k * r - hr) > 20 * tau
    torch.testing.assert_close(hi_[far], hr[far], atol=tau * math.log(2) + 1e-9, rtol=0)
    (cx, cy), (a1, _) = CENTERS[0], AXES[0]
    at_rest = torch.tensor([[cx - a1, cy, 0.0, 0.0]], dtype=torch.float64)
    assert float(h_in(at_rest)[0, 0]) == pytest.approx(-tau * math.log(2), abs=1e-5)
    assert mppi_cbf("mppi_rascbf", risk_form=None, **kw).params["risk_form"] == "inside"
    assert mppi_cbf("mppi_rascbf", config="paper", **kw).params["risk_form"] == "rectified"
    with pytest.raises(ValueError, match="risk_form"):
        mppi_cbf("mppi_rascbf", risk_form="box", **kw)
    with pytest.raises(ValueError, match="risk_temperature"):
        mppi_cbf("mppi_rascbf", risk_temperature=0.0, **kw)


def test_risk_budget_shares_the_run_over_windows_of_the_horizon() -> None:
    """With a budget for the whole run, rho = budget T / (STEPS DT), the filter's condition
    uses it (Delta = sqrt(2T) eta erfinv(1 - rho)) and the record reports it; rho given alone
    replaces the budget; a budget needs a fixed T and lies in (0, 1)."""
    kw = {"num_seeds": 1, "num_samples": 8, "horizon": 4, "dtype": torch.float64}
    sc = mppi_cbf("mppi_rascbf", risk_budget=0.05, risk_horizon=0.03, risk_eta="sup", **kw)
    p = sc.params
    assert p["risk_budget"] == 0.05 and p["risk_horizon"] == 0.03
    assert p["rho"] == pytest.approx(0.05 * 0.03 / (STEPS * DT))
    assert sc.safety_filter.condition.rho == pytest.approx(p["rho"])
    eta = torch.tensor(p["eta"], dtype=torch.float64)
    z = torch.erfinv(torch.tensor(1 - p["rho"], dtype=torch.float64))
    torch.testing.assert_close(
        sc.safety_filter.cbf_margin.double(), math.sqrt(2 * 0.03) * eta * z, rtol=1e-6, atol=0
    )
    plain = mppi_cbf("mppi_rascbf", rho=0.02, risk_horizon=0.03, **kw).params
    assert plain["risk_budget"] is None and plain["rho"] == 0.02
    with pytest.raises(ValueError, match="risk_horizon"):
        mppi_cbf("mppi_rascbf", config="paper", risk_budget=0.05, **kw)
    for bad in (0.0, 1.0, -0.1):
        with pytest.raises(ValueError, match="risk_budget"):
            mppi_cbf("mppi_rascbf", risk_budget=bad, risk_horizon=0.03, **kw)


@pytest.mark.slow  # 7-10 s on 2 cores: in the slow suite, which CI runs too
def test_local_noise_bound_margin_follows_the_state() -> None:
    """``risk_eta="local"``: the filter's margin at a state is sqrt(2T) |dh_i/dx sigma|
    erfinv(1 - rho) there (autograd), the record's ``delta`` is the one at the start, and the
    run's window check uses each step's own margin."""
    kw = {"num_seeds": 2, "num_samples": 8, "horizon": 4, "dtype": torch.float64}
    sc = mppi_cbf("mppi_rascbf", risk_eta="local", **kw)
    p = sc.params
    assert p["risk_eta"] == "local" and sc.safety_filter.condition.local
    assert sc.safety_filter.cbf_margin is None
    (barrier,) = sc.safety_filter.barriers
    rho = torch.tensor(1 - p["rho"], dtype=torch.float64)
    z = math.sqrt(2 * p["risk_horizon"]) * float(torch.erfinv(rho))
    x0 = torch.tensor([0.0, 0.0, 0.0, math.pi / 4], dtype=torch.float64, requires_grad=True)
    h0 = barrier(x0)
    for i in range(h0.shape[-1]):
        (grad,) = torch.autograd.grad(h0[i], x0, retain_graph=True)
        ref = z * SIGMA * float(grad.norm())
        assert p["delta"][i] == pytest.approx(ref, rel=1e-6)
    # along the long axis of the thin ellipse at (2, 5) the sup margin widens the berth:
    # there the local margin is far smaller than the constant one
    sup = mppi_cbf("mppi_rascbf", risk_eta="sup", **kw)
    tip = torch.tensor([[4.3, 5.0, 0.0, 0.0]], dtype=torch.float64)
    local = sc.safety_filter.condition.margin_at(barrier, sc.dynamics, tip)[0, 2].detach()
    assert float(local) < 0.25 * float(sup.safety_filter.cbf_margin[2])
    traj, m = sc.run(progress=False)
    delta = sc.safety_filter.condition.margin_at(barrier, sc.dynamics, traj.x[:, :-1])
    ref = risk_failures(traj.h, delta.detach(), round(p["risk_horizon"] / DT))
    for key in ("risk_windows", "risk_window_failures"):
        torch.testing.assert_close(m[key], ref[key])
    with pytest.raises(ValueError, match="risk_eta"):
        mppi_cbf("mppi_rascbf", risk_eta="max", **kw)


def test_risk_failures_takes_a_margin_per_step() -> None:
    gen = torch.Generator().manual_seed(6)
    h = torch.randn(3, 25, 2, generator=gen, dtype=torch.float64) + 0.6
    delta = 0.4 * torch.rand(3, 25, 2, generator=gen, dtype=torch.float64)
    window = 3
    got = risk_failures(h, delta, window)
    for b in range(3):
        windows = failures = 0
        for j in range(25 - window):
            if bool((h[b, j] >= delta[b, j]).all()):
                windows += 1
                failures += bool((h[b, j : j + window + 1] < 0).any())
        assert int(got["risk_windows"][b]) == windows
        assert int(got["risk_window_failures"][b]) == failures
    with pytest.raises(ValueError, match="delta"):
        risk_failures(h, delta[:, :5], window)


def test_goal_wall_inflation_grows_only_that_ellipse() -> None:
    """``risk_goal_wall_inflation`` adds metres to the semi-axes of the ellipse at (2, 5)
    only (on top of ``risk_inflation``): the filter's barrier is zero on the grown ellipse's
    boundary at rest, and the other ellipses keep theirs."""
    kw = {"num_seeds": 1, "num_samples": 8, "horizon": 4, "dtype": torch.float64}
    sc = mppi_cbf("mppi_rascbf", risk_goal_wall_inflation=0.15, risk_form="rectified", **kw)
    assert sc.params["risk_goal_wall_inflation"] == 0.15
    (barrier,) = sc.safety_filter.barriers
    (wx, wy), (_, wb) = CENTERS[2], AXES[2]
    (cx, cy), (a1, _) = CENTERS[0], AXES[0]
    rest = torch.tensor(
        [[wx, wy - wb - 0.15, 0.0, 0.0], [cx - a1, cy, 0.0, 0.0]], dtype=torch.float64
    )
    h = barrier(rest)
    assert float(h[0, 2]) == pytest.approx(0.0, abs=1e-5)
    assert float(h[1, 0]) == pytest.approx(0.0, abs=1e-5)
    grown = obstacles(inflation=[0.0, 0.0, 0.15, 0.0, 0.0])
    torch.testing.assert_close(grown.axes[2], torch.tensor(AXES[2]) + 0.15)
    torch.testing.assert_close(grown.axes[0], torch.tensor(AXES[0]))
    with pytest.raises(ValueError, match="inflation"):
        obstacles(inflation=[0.1, 0.2])
    with pytest.raises(ValueError, match="risk_goal_wall_inflation"):
        mppi_cbf("mppi_rascbf", risk_goal_wall_inflation=-0.1, **kw)
