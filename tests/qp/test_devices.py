"""solve_qp on every device against the CPU: each method, forward and backward, in float64
and float32, with equality rows, bounds, soft rows, infeasible rows and one problem alone.

On the CPU each test runs once (the CPU is its own reference); with a GPU the same problems
are solved on it and every output and gradient is compared with the CPU's."""

from __future__ import annotations

import pytest
import torch
from _devices import device_matches_cpu
from _problems import make_batch

from torchcbf.qp import solve_qp

#: (rtol, atol) of a device against the CPU: different reductions and kernels, the same
#: method; gradients pass through one more solve
TOL = {torch.float64: (1e-8, 1e-8), torch.float32: (2e-3, 2e-3)}

#: (method, equality rows): the dual active-set method takes no equality rows
CASES = [("auto", 1), ("auto", 0), ("active_set", 0), ("enumerate", 1), ("ipm", 1)]


def _solve(batch, device, method, **kw):
    """The batch on ``device`` with gradients to every input, solved; ``x``, the status,
    the multipliers and the gradients of a weighted sum of the solved rows' ``x``."""
    names = ("Q", "p", "G", "h", "A", "b", "lb", "ub")
    inputs = {
        name: getattr(batch, name).to(device).requires_grad_(True)
        for name in names
        if getattr(batch, name) is not None and getattr(batch, name).numel()
    }
    sol = solve_qp(**inputs, method=method, **kw)
    weights = torch.linspace(-1.0, 2.0, sol.x.shape[-1], dtype=sol.x.dtype, device=device)
    solved = (sol.status == 0).unsqueeze(-1)
    loss = torch.where(solved, sol.x * weights, 0.0).sum()
    grads = torch.autograd.grad(loss, list(inputs.values()), allow_unused=True)
    return sol.x.where(solved, 0.0), sol.status, sol.lam.where(solved, 0.0), grads


@pytest.mark.parametrize(("method", "me"), CASES)
@pytest.mark.parametrize("B", [1, 100])
def test_solutions_and_gradients_match_the_cpu(device, dtype, method, me, B):
    infeasible = 0.0 if B == 1 else 0.25  # one problem alone: a solved one
    batch = make_batch(
        B, 4, 8, me, bounds=True, seed=B + me, frac_infeasible=infeasible, dtype=dtype
    )
    rtol, atol = TOL[dtype]
    x, status, _, _ = device_matches_cpu(
        lambda dev: _solve(batch, dev, method), device, dtype, rtol=rtol, atol=atol
    )
    assert x.device.type == torch.device(device).type
    if B > 1:  # the batch holds infeasible rows: their status says so on every device
        assert int((status != 0).sum()) > 0
    assert int((status == 0).sum()) > B // 2


def test_soft_rows_match_the_cpu(device, dtype):
    batch = make_batch(100, 3, 6, 0, bounds=True, seed=7, dtype=dtype)
    soft = torch.tensor([0.0, 5.0, 0.0, 50.0, 0.0, 0.0], dtype=dtype)
    rtol, atol = TOL[dtype]
    device_matches_cpu(
        lambda dev: _solve(batch, dev, "auto", soft=soft.to(dev)),
        device,
        dtype,
        rtol=rtol,
        atol=atol,
    )
