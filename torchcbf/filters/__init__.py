"""CBF/CLF-QP safety filters: vanilla, robust, stochastic and risk-aware, batched and
differentiable (one :func:`torchcbf.qp.solve_qp` call per batch of states)."""

from torchcbf.filters.class_k import (
    CubicClassK,
    LinearClassK,
    PowerClassK,
    as_class_k,
)
from torchcbf.filters.conditions import Condition, cbf_condition, clf_condition
from torchcbf.filters.fallback import Fallback
from torchcbf.filters.modes import FilterMode, RiskAware, Robust, Stochastic, Vanilla
from torchcbf.filters.qp_data import Slack
from torchcbf.filters.risk import local_margin, noise_bound, risk_margin
from torchcbf.filters.safety_filter import FilterOutput, FilterStatus, SafetyFilter

__all__ = [
    "Condition",
    "CubicClassK",
    "Fallback",
    "FilterMode",
    "FilterOutput",
    "FilterStatus",
    "LinearClassK",
    "PowerClassK",
    "RiskAware",
    "Robust",
    "SafetyFilter",
    "Slack",
    "Stochastic",
    "Vanilla",
    "as_class_k",
    "cbf_condition",
    "clf_condition",
    "local_margin",
    "noise_bound",
    "risk_margin",
]
