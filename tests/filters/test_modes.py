"""Condition modes as objects, the deprecated keyword aliases, and the fallback policy."""

from __future__ import annotations

import pytest
import torch
from _filter_reference import BETA, CLF_ETA, CLF_GAMMA, ETA, HORIZON, RHO
from test_safety_filter import MODES, random_states, scene

from torchcbf.barriers import Ball
from torchcbf.dynamics import SingleIntegrator
from torchcbf.filters import (
    Fallback,
    FilterMode,
    RiskAware,
    Robust,
    SafetyFilter,
    Stochastic,
    Vanilla,
)
from torchcbf.filters.conditions import Condition

OBJECTS = {
    "vanilla": lambda: Vanilla(),
    "robust": lambda: Robust(),
    "stochastic": lambda: Stochastic(beta=BETA),
    "risk_aware": lambda: RiskAware(
        RHO, HORIZON, torch.tensor(ETA), clf_eta=CLF_ETA, clf_gamma=CLF_GAMMA
    ),
}


@pytest.mark.parametrize("mode", MODES)
def test_mode_object_equals_mode_name(mode: str) -> None:
    xs, us = random_states(8, seed=3)
    x, u = torch.tensor(xs), torch.tensor(us)
    with pytest.warns(DeprecationWarning):
        by_name = scene(mode)(x, u)
    keep = ("alpha", "clf_rate", "R", "clf_slack_weight")
    filt = scene(mode)
    obj = SafetyFilter(
        filt.dynamics, list(filt.barriers), list(filt.lyapunovs), mode=OBJECTS[mode](),
        **{k: getattr(filt, k) if k != "alpha" else filt.alpha[0] for k in keep if k != "clf_rate"},
        clf_rate=filt.clf_rate[0],
    )  # fmt: skip
    out = obj(x, u)
    assert out.path == by_name.path
    for a, b in zip(out[:-1], by_name[:-1], strict=True):
        torch.testing.assert_close(a, b, equal_nan=True)
    assert obj.mode == mode and isinstance(obj.condition, FilterMode)


def test_deprecated_booleans_map_to_cbf_slack() -> None:
    dyn = SingleIntegrator(2, u_min=-1.0, u_max=1.0)
    ball = Ball([1.0, 0.0], 0.5)
    with pytest.warns(DeprecationWarning, match="cbf_slack='per_row'"):
        soft = SafetyFilter(dyn, ball, relax_cbf=True)
    with pytest.warns(DeprecationWarning):
        hard = SafetyFilter(dyn, ball, elastic=False)
    assert soft.cbf_slack == "per_row" and soft.relax_cbf and soft.elastic
    assert hard.cbf_slack == "none" and not hard.elastic
    assert SafetyFilter(dyn, ball).cbf_slack == "shared"
    with pytest.raises(ValueError, match="cbf_slack must be one of"):
        SafetyFilter(dyn, ball, cbf_slack="some")
    with pytest.raises(ValueError, match="not both"):
        SafetyFilter(dyn, ball, cbf_slack="none", elastic=False)
    with pytest.raises(TypeError, match="unexpected keyword arguments \\['gamma'\\]"):
        SafetyFilter(dyn, ball, gamma=1.0)
    with pytest.raises(ValueError, match="belong to the mode object"):
        SafetyFilter(dyn, ball, mode=Vanilla(), beta=1.0)


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
    with pytest.raises(ValueError, match="shape \\[2\\]"):
        Fallback(torch.zeros(3), 2)
    with pytest.raises(TypeError, match="fallback must be"):
        Fallback(3, 2)
