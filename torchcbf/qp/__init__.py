"""Batched differentiable quadratic programs: ``solve_qp`` with torch, proxsuite and qpsolvers
backends, per-row :class:`Status`, and an elastic (soft-constraint) mode."""

from torchcbf.qp.solve import QPSolution, solve_qp
from torchcbf.qp.status import Status

__all__ = ["QPSolution", "Status", "solve_qp"]
