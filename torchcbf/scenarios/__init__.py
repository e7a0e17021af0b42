"""The reference scenarios (docs/scenarios.md) as registered builders, used by the CLI,
sweeps, tuning, scripts and tests; a user's own scenario registers the same way
(:mod:`torchcbf.scenarios.registry`)."""

from torchcbf.scenarios.arm_reach import ArmReachParams
from torchcbf.scenarios.base import Scenario
from torchcbf.scenarios.registry import (
    Column,
    Dimension,
    EnvEntry,
    ScenarioEntry,
    get,
    import_scenarios,
    register,
    scenarios,
    unregister,
)
from torchcbf.scenarios.single_integrator_reach_avoid import (
    ReachAvoidParams,
    reach_avoid,
    reach_avoid_spec,
)
from torchcbf.scenarios.unicycle_mppi_cbf import (
    METHODS,
    MppiCbfParams,
    mppi_cbf,
    obstacles,
    proportional_controller,
)

__all__ = [
    "METHODS",
    "ArmReachParams",
    "Column",
    "Dimension",
    "EnvEntry",
    "MppiCbfParams",
    "ReachAvoidParams",
    "Scenario",
    "ScenarioEntry",
    "get",
    "import_scenarios",
    "mppi_cbf",
    "obstacles",
    "proportional_controller",
    "reach_avoid",
    "reach_avoid_spec",
    "register",
    "scenarios",
    "unregister",
]
