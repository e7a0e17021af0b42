"""Indexing state components and turning numbers into tensors copy nothing from the host:
checked on the ``meta`` device (no values) inside :class:`_host_traffic.HostTraffic`."""

from __future__ import annotations

import pytest
import torch
from _host_traffic import HostTraffic

from torchcbf._checks import as_tensor
from torchcbf.barriers import Ball, Ellipse
from torchcbf.dynamics import DoubleIntegrator
from torchcbf.mppi import QuadraticGoal

META = torch.device("meta")


@pytest.mark.parametrize("method", ["autograd", "analytic"])
@pytest.mark.parametrize(
    "make",
    [
        lambda: Ball([0.0, 0.0], 0.5, index=(0, 2)),
        lambda: Ellipse([0.0, 0.0], [0.5, 0.3], index=(1, 3)),
    ],
    ids=["ball", "ellipse"],
)
def test_lie_terms_of_a_shape_on_scattered_components_copy_nothing(make, method) -> None:
    shape, model = make().to(META), DoubleIntegrator(2).to(META)
    x = torch.empty(5, 4, device=META)
    with HostTraffic() as traffic:
        terms = shape.lie(x, model, method=method)
    assert not traffic.events, dict(traffic.events)
    assert terms.lgh.shape == (5, 2) and terms.dhdx.shape == (5, 4)


def test_a_cost_on_scattered_components_copies_nothing() -> None:
    goal = QuadraticGoal([1.0, 2.0], index=(0, 2), terminal_weight=3.0).to(META)
    states, controls = torch.empty(2, 3, 6, 4, device=META), torch.empty(2, 3, 5, 2, device=META)
    with HostTraffic() as traffic:
        cost = goal(states, controls)
    assert not traffic.events, dict(traffic.events)
    assert cost.shape == (2, 3)


def test_a_number_becomes_a_tensor_on_the_device_without_a_copy() -> None:
    with HostTraffic() as traffic:
        t = as_tensor("t", 0.25, device=META, dtype=torch.float32)
    assert not traffic.events, dict(traffic.events)
    assert t.device == META and t.shape == () and t.dtype == torch.float32
    assert as_tensor("t", 0.1, dtype=torch.float64).item() == 0.1
    assert as_tensor("t", 3, dtype=torch.float32).item() == 3.0
