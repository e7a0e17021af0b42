"""Condition modes as objects or names, the slack modes, and the fallback policy."""

from __future__ import annotations

import pytest
import torch
from test_safety_filter import MODES, random_states, scene

from torchcbf.barriers import Ball
from torchcbf.dynamics import SingleIntegrator
from torchcbf.filters import (
    Fallback,
    FilterMode,
    Robust,
    SafetyFilter,
    Slack,
    Stochastic,
    Vanilla,
)
from torchcbf.filters.conditions import Condition


@pytest.mark.parametrize("mode", MODES)
def test_mode_objects_and_names(mode: str) -> None:
    xs, us = random_states(8, seed=3)
    x, u = torch.tensor(xs), torch.tensor(us)
    filt = scene(mode)
    assert filt.mode == mode and isinstance(filt.condition, FilterMode)
    out = filt(x, u)
    assert out.u.shape == u.shape
    if mode in ("vanilla", "robust", "stochastic"):  # a name: the mode's defaults
        by_name = SafetyFilter(
            filt.dynamics, list(filt.barriers), list(filt.lyapunovs), mode=mode,
            alpha=filt.alpha[0], clf_rate=filt.clf_rate[0], R=filt.R,
            slack=filt.slack,
        )  # fmt: skip
        plain = {"vanilla": Vanilla(), "robust": Robust(), "stochastic": Stochastic()}[mode]
        by_object = SafetyFilter(
            filt.dynamics, list(filt.barriers), list(filt.lyapunovs), mode=plain,
            alpha=filt.alpha[0], clf_rate=filt.clf_rate[0], R=filt.R,
            slack=filt.slack,
        )  # fmt: skip
        for a, b in zip(by_name(x, u)[:-1], by_object(x, u)[:-1], strict=True):
            torch.testing.assert_close(a, b, equal_nan=True)
    else:
        with pytest.raises(ValueError, match="needs its parameters"):
            SafetyFilter(filt.dynamics, list(filt.barriers), mode=mode)


def test_slack_modes_and_unknown_keywords() -> None:
    dyn = SingleIntegrator(2, u_min=-1.0, u_max=1.0)
    ball = Ball([1.0, 0.0], 0.5)
    assert SafetyFilter(dyn, ball).slack == Slack("shared", cbf_weight=1e3, exact=False)
    per_row = SafetyFilter(dyn, ball, slack="per_row").slack
    assert per_row.mode == "per_row" and per_row.cbf_weight == 1e2
    assert SafetyFilter(dyn, ball, slack=Slack(exact=True)).slack.two_pass
    with pytest.raises(ValueError, match="slack must be a Slack or one of"):
        SafetyFilter(dyn, ball, slack="some")
    with pytest.raises(ValueError, match="slack mode must be one of"):
        Slack("some")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="slack cbf_weight"):
        Slack(cbf_weight=-1.0)
    with pytest.raises(TypeError, match="slack exact must be a bool"):
        Slack(exact=1)  # type: ignore[arg-type]
    for keyword in ("elastic", "relax_cbf", "beta", "gamma"):  # options of the mode object
        with pytest.raises(TypeError, match=keyword):
            SafetyFilter(dyn, ball, **{keyword: 1.0})
    with pytest.raises(ValueError, match="mode must be one of"):
        SafetyFilter(dyn, ball, mode="careful")


def test_a_custom_mode_object_runs_in_the_filter() -> None:
    class Margin(FilterMode):
        """Vanilla with a constant margin: ``L_g h u + L_f h + alpha(h) - margin >= 0``."""

        name = "margin"

        def cbf(self, terms, alpha, dynamics, x):
            return Condition(terms.lgh, terms.lfh + terms.dhdt + alpha(terms.h) - 0.5)

    dyn = SingleIntegrator(1)
    wall = Ball([2.0], 1.0, index=(0,))  # h = (x - 2)^2 - 1, safe left of x = 1
    filt = SafetyFilter(dyn, wall, mode=Margin()).double()
    x = torch.tensor([[0.0]], dtype=torch.float64)
    out = filt(x, torch.tensor([[5.0]], dtype=torch.float64))
    # h = 3, L_g h = -4: -4 u + 3 - 0.5 >= 0  ->  u <= 0.625
    torch.testing.assert_close(out.u, torch.tensor([[0.625]], dtype=torch.float64))
    assert filt.mode == "margin"


def test_fallback_policy_errors_and_values() -> None:
    lo, hi = torch.tensor([-1.0, -1.0]), torch.tensor([1.0, 1.0])
    x, u = torch.zeros(2, 3), torch.tensor([[3.0, -0.5], [0.2, 0.1]])
    assert torch.equal(Fallback("clip", 2)(x, u, lo, hi), torch.clamp(u, lo, hi))
    assert torch.equal(Fallback("brake", 2)(x, u, lo, hi), torch.zeros(2, 2))
    nan = Fallback(lambda xx, uu: torch.full_like(uu, float("nan")), 2)(x, u, lo, hi)
    assert torch.equal(nan, torch.zeros(2, 2))
    far = Fallback(torch.tensor([5.0, -3.0]), 2)(x, u, lo, hi)  # clipped to the limits
    assert torch.equal(far, torch.tensor([[1.0, -1.0], [1.0, -1.0]]))
    scaled = Fallback(lambda xx, uu: 4.0 * uu, 2)(x, u, lo, hi)
    assert torch.equal(scaled, torch.clamp(4.0 * u, lo, hi))
    with pytest.raises(ValueError, match="shape \\[2\\]"):
        Fallback(torch.zeros(3), 2)
    with pytest.raises(TypeError, match="fallback must be"):
        Fallback(3, 2)


def test_a_callable_diffusion_of_another_dtype_is_cast_on_every_path() -> None:
    """A callable ``sigma`` that returns float64 on float32 states: the stochastic filter
    answers in float32 on both backends, equal to the float32 constant diffusion's answer."""
    from torchcbf.barriers import Ellipse
    from torchcbf.dynamics import SingleIntegrator
    from torchcbf.filters import SafetyFilter, Stochastic

    S = torch.tensor([[0.3, 0.0], [0.1, 0.2]], dtype=torch.float64)
    wide = SingleIntegrator(2, sigma=lambda x: S.expand(*x.shape[:-1], 2, 2))
    plain = SingleIntegrator(2, sigma=S.float())
    ellipse = Ellipse([1.0, 0.5], [0.6, 0.3])
    x = torch.tensor([[0.0, 0.0], [0.2, 1.0]])
    u = torch.tensor([[1.5, 0.3], [1.0, -0.5]])
    assert wide.sigma(x).dtype == torch.float32
    for backend in ("auto", "torch"):
        got = SafetyFilter(wide, [ellipse], mode=Stochastic(), backend=backend)(x, u)
        want = SafetyFilter(plain, [ellipse], mode=Stochastic(), backend=backend)(x, u)
        assert got.u.dtype == torch.float32
        torch.testing.assert_close(got.u, want.u)
        assert got.status.tolist() == want.status.tolist()
    with pytest.raises(TypeError, match="sigma\\(x\\) must return a tensor"):
        SingleIntegrator(2, sigma=lambda x: 0.3).sigma(x)
