"""Bad inputs of the safety filter, the planner, specifications, Lie derivatives and rectify:
an error naming the argument, or a documented per-row status, never silence."""

from __future__ import annotations

import math

import pytest
import torch

from torchcbf.barriers import Ball, rectify
from torchcbf.dynamics import DoubleIntegrator, SingleIntegrator
from torchcbf.filters import FilterStatus, SafetyFilter
from torchcbf.mppi import MPPI, Avoid, QuadraticGoal, Reach
from torchcbf.qp import Status


def _filter(**kwargs) -> SafetyFilter:
    return SafetyFilter(SingleIntegrator(2), [Ball([1.0, 0.0], 0.5)], **kwargs)


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"u_min": 1.0, "u_max": -1.0}, "u_min .* exceeds u_max"),
        ({"u_min": math.nan}, "u_min must not contain NaN"),
        ({"u_max": [1.0, math.nan]}, "u_max must not contain NaN"),
        ({"R": [1.0, -1.0]}, "R must be positive definite"),
    ],
)
def test_filter_rejects_limits_and_weights_that_cannot_work(kwargs, match) -> None:
    with pytest.raises(ValueError, match=match):
        _filter(**kwargs)


def test_filter_refuses_a_barrier_the_control_never_reaches() -> None:
    robot = DoubleIntegrator(2)
    with pytest.raises(ValueError, match=r"barriers\[0\].*L_g h = 0.*rectify"):
        SafetyFilter(robot, [Ball([2.0, 0.0], 0.5)])
    SafetyFilter(robot, [rectify(Ball([2.0, 0.0], 0.5), robot, form="exponential")])
    SafetyFilter(robot, [Ball([2.0, 0.0], 0.5)], check_relative_degree=False)


def test_filter_reports_a_non_finite_row_in_qp_status_too() -> None:
    filt = _filter().double()
    x = torch.tensor([[0.0, 0.0], [math.nan, 0.0]], dtype=torch.float64)
    out = filt(x, torch.ones(2, 2, dtype=torch.float64))
    assert out.status.tolist() == [FilterStatus.SOLVED, FilterStatus.NON_FINITE]
    assert out.qp_status.tolist() == [Status.SOLVED, Status.NON_FINITE]


def test_filter_gain_tensor_that_requires_grad_gets_its_gradient() -> None:
    alpha = torch.tensor(2.0, dtype=torch.float64, requires_grad=True)
    filt = SafetyFilter(SingleIntegrator(2).double(), [Ball([1.0, 0.0], 0.5).double()], alpha=alpha)
    x = torch.tensor([[0.2, 0.1]], dtype=torch.float64)
    out = filt(x, torch.tensor([[3.0, 0.0]], dtype=torch.float64))
    out.u.sum().backward()
    assert alpha.grad is not None and float(alpha.grad.abs()) > 0

    def u_sum(gain: float) -> float:  # grad mode: the same solver path as above
        filt = SafetyFilter(
            SingleIntegrator(2).double(), [Ball([1.0, 0.0], 0.5).double()], alpha=gain
        )
        return float(filt(x, torch.tensor([[3.0, 0.0]], dtype=torch.float64)).u.sum())

    eps = 1e-3  # the QP is solved to ~1e-9: a smaller step differences solver noise
    fd = (u_sum(2.0 + eps) - u_sum(2.0 - eps)) / (2 * eps)
    assert float(alpha.grad) == pytest.approx(fd, rel=1e-4)


def test_lie_derivatives_name_a_wrong_dynamics_argument() -> None:
    with pytest.raises(TypeError, match="dynamics must be a ControlAffine"):
        Ball([1.0, 0.0], 0.5).lie(torch.zeros(3, 2), "dyn")  # type: ignore[arg-type]


@pytest.mark.parametrize("form", ["high_order", "exponential"])
def test_rectify_rejects_non_finite_gains(form) -> None:
    with pytest.raises(ValueError, match="must not contain NaN"):
        rectify(Ball([1.0, 0.0], 0.5), DoubleIntegrator(2), form=form, gains=[math.nan])


def test_planner_names_mismatched_devices() -> None:
    planner = MPPI(SingleIntegrator(2), QuadraticGoal([1.0, 0.0]), 5, 16, 0.1, 1.0, 0.1)
    with pytest.raises(ValueError, match="x is on device meta but the planner is on device cpu"):
        planner(torch.zeros(2, device="meta"))


@pytest.mark.parametrize(
    "make",
    [
        lambda: Reach([math.nan, 0.0], 1.0),
        lambda: Avoid([0.0, math.inf], 1.0),
        lambda: QuadraticGoal([math.nan, 0.0]),
    ],
)
def test_specs_and_costs_reject_non_finite_centres(make) -> None:
    with pytest.raises(ValueError, match="must not contain"):
        make()


def test_filter_names_mismatched_devices() -> None:
    filt = _filter()
    with pytest.raises(ValueError, match="x is on device meta, u_nom on cpu and the filter on cpu"):
        filt(torch.zeros(1, 2, device="meta"), torch.zeros(1, 2))
