"""The real-time path of SafetyFilter (a few states, grad mode off, numpy into the QP
kernel): the same outputs as the general path, and cvxpy's control."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from _filter_reference import solve_reference
from test_safety_filter import MODES, random_states, scene

from torchcbf.filters import FilterStatus, SafetyFilter
from torchcbf.filters.qp_data import assemble, assemble_numpy
from torchcbf.qp import _dual_native, realtime

pytestmark = pytest.mark.skipif(not _dual_native.available(), reason="C kernel not built")


def _general(filt: SafetyFilter, x: torch.Tensor, u: torch.Tensor):
    """The general path: grad mode on (the real-time path needs it off)."""
    with torch.enable_grad():
        out = filt(x, u)
    return type(out)(*(v.detach() for v in out))


def _same(a, b, tol: float) -> None:
    for name in a._fields:
        va, vb = getattr(a, name), getattr(b, name)
        assert va.shape == vb.shape and va.dtype == vb.dtype, name
        if va.dtype == torch.int64:
            assert torch.equal(va, vb), name
        else:
            torch.testing.assert_close(va, vb, atol=tol, rtol=tol, equal_nan=True, msg=name)


@pytest.mark.parametrize("mode", MODES)
@pytest.mark.parametrize("clf", [False, True])
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_realtime_path_matches_general_path(mode: str, clf: bool, dtype: torch.dtype) -> None:
    xs, us = random_states(realtime.MAX_BATCH, seed=20 + MODES.index(mode))
    filt = scene(mode, dtype, clf=clf)
    x, u = torch.tensor(xs, dtype=dtype), torch.tensor(us, dtype=dtype)
    tol = 1e-9 if dtype == torch.float64 else 1e-4
    with torch.no_grad():
        batch = filt(x, u)
        one = filt(x[0], u[0])
    _same(batch, _general(filt, x, u), tol)
    _same(one, _general(filt, x[0], u[0]), tol)
    assert one.u.shape == (2,) and one.status.shape == ()


@pytest.mark.parametrize("mode", MODES)
def test_realtime_control_matches_cvxpy(mode: str, monkeypatch: pytest.MonkeyPatch) -> None:
    import torchcbf.qp as qp

    calls = []
    real_solve = qp.solve_qp

    def counting_solve(*args, **kwargs):
        calls.append(1)
        return real_solve(*args, **kwargs)

    monkeypatch.setattr(qp, "solve_qp", counting_solve)
    xs, us = random_states(12, seed=40 + MODES.index(mode))
    filt = scene(mode)
    solved = 0
    for i in range(len(xs)):
        calls.clear()
        with torch.no_grad():
            out = filt(torch.tensor(xs[i]), torch.tensor(us[i]))
        ref = solve_reference(xs[i], us[i], mode)
        if ref is None:
            assert int(out.status) == FilterStatus.RELAXED
            continue
        solved += 1
        assert not calls  # answered by the real-time path
        assert int(out.status) == FilterStatus.SOLVED
        assert np.abs(out.u.numpy() - ref).max() <= 1e-6
    assert solved >= 6


@pytest.mark.parametrize("slack", ["shared", "per_row", "none"])
def test_numpy_assembly_equals_torch_assembly(slack: str) -> None:
    g = torch.Generator().manual_seed(3)
    B, k, c, m = 3, 4, 2, 2
    a = torch.randn(B, k, m, generator=g, dtype=torch.float64)
    b = torch.randn(B, k, generator=g, dtype=torch.float64)
    av = torch.randn(B, c, m, generator=g, dtype=torch.float64)
    bv = torch.randn(B, c, generator=g, dtype=torch.float64)
    u = 3 * torch.randn(B, m, generator=g, dtype=torch.float64)
    R = torch.tensor([[2.0, 0.3], [0.3, 1.0]], dtype=torch.float64)
    lo = torch.tensor([-1.0, -torch.inf], dtype=torch.float64)
    hi = torch.tensor([1.0, 2.0], dtype=torch.float64)
    kw = {"slack": slack, "cbf_weight": 7.0, "clf_weight": 3.0}
    qp = assemble((a, b), (av, bv), u, R, lo, hi, **kw)
    Q, p, G, h, ks = assemble_numpy(
        (a.numpy(), b.numpy()), (av.numpy(), bv.numpy()), u.numpy(), R.numpy(), lo.numpy(),
        hi.numpy(), **kw,
    )  # fmt: skip
    assert ks == qp.ks
    np.testing.assert_allclose(Q, qp.Q.numpy(), rtol=1e-14, atol=1e-14)
    np.testing.assert_allclose(p, qp.p.numpy(), rtol=1e-14, atol=1e-14)
    # the general path's rows, then its finite bounds as rows (upper, then lower)
    nz = qp.Q.shape[-1]
    eye = torch.eye(nz, dtype=torch.float64)
    up = torch.isfinite(qp.ub[0]).nonzero().flatten()
    low = torch.isfinite(qp.lb[0]).nonzero().flatten()
    G_ref = torch.cat((qp.G, eye[up].expand(B, -1, -1), -eye[low].expand(B, -1, -1)), 1)
    h_ref = torch.cat((qp.h, qp.ub[:, up], -qp.lb[:, low]), 1)
    np.testing.assert_allclose(G, G_ref.numpy(), rtol=1e-14, atol=1e-14)
    np.testing.assert_allclose(h, h_ref.numpy(), rtol=1e-14, atol=1e-14)


def test_non_finite_state_and_infeasible_hard_qp_take_the_general_path() -> None:
    xs, us = random_states(3, seed=9)
    filt = scene("vanilla")
    x, u = torch.tensor(xs), torch.tensor(us)
    x[1, 0] = float("nan")
    with torch.no_grad():
        out = filt(x, u)
    _same(out, _general(filt, x, u), 1e-12)
    assert out.status[1] == FilterStatus.NON_FINITE
    hard = scene("vanilla", cbf_slack="none", fallback="brake")
    xs, us = random_states(16, seed=1)
    with torch.no_grad():
        out = hard(torch.tensor(xs), torch.tensor(us))
    _same(out, _general(hard, torch.tensor(xs), torch.tensor(us)), 1e-9)
