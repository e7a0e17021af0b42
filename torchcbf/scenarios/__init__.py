"""The reference scenarios (docs/scenarios.md) as builders, used by the CLI, scripts and tests."""

from torchcbf.scenarios.base import Scenario
from torchcbf.scenarios.single_integrator_reach_avoid import reach_avoid, reach_avoid_spec
from torchcbf.scenarios.unicycle_mppi_cbf import (
    METHODS,
    mppi_cbf,
    obstacles,
    proportional_controller,
)

__all__ = [
    "METHODS",
    "Scenario",
    "mppi_cbf",
    "obstacles",
    "proportional_controller",
    "reach_avoid",
    "reach_avoid_spec",
]
