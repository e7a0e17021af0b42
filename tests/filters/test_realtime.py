"""The real-time path of SafetyFilter (a few states, no gradient to carry, one call of the
filter kernel): the same outputs as the general path, and cvxpy's control."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from _filter_reference import solve_reference
from test_safety_filter import MODES, random_states, scene

from torchcbf.filters import FilterStatus, LinearClassK, SafetyFilter, realtime

pytestmark = pytest.mark.skipif(not realtime.available(), reason="C kernel not built")


def _general(filt: SafetyFilter, x: torch.Tensor, u: torch.Tensor):
    """The general path: an input that requires grad (the real-time path carries none)."""
    with torch.enable_grad():
        out = filt(x.clone().requires_grad_(), u)
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
@pytest.mark.parametrize("slack", ["shared", "per_row", "none"])
def test_realtime_path_matches_general_path(
    mode: str, clf: bool, dtype: torch.dtype, slack: str
) -> None:
    xs, us = random_states(realtime.MAX_BATCH, seed=20 + MODES.index(mode))
    filt = scene(mode, dtype, clf=clf, cbf_slack=slack, fallback="brake")
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


def _counting(monkeypatch: pytest.MonkeyPatch) -> list[int]:
    """Calls of the kernel of the real-time path."""
    calls: list[int] = []
    real = realtime.solve

    def counted(*args, **kwargs):
        calls.append(1)
        return real(*args, **kwargs)

    monkeypatch.setattr(realtime, "solve", counted)
    return calls


def test_grad_mode_without_gradients_takes_the_realtime_path(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    calls = _counting(monkeypatch)
    filt = scene("stochastic")
    xs, us = random_states(4, seed=5)
    x, u = torch.tensor(xs), torch.tensor(us)
    with torch.enable_grad():
        out = filt(x, u)
    assert len(calls) == 1 and not out.u.requires_grad
    _same(out, _general(filt, x, u), 1e-9)


@pytest.mark.parametrize("source", ["x", "u_nom", "parameter", "buffer", "closure"])
def test_a_gradient_to_carry_takes_the_general_path(
    source: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    calls = _counting(monkeypatch)
    gain = torch.tensor(2.0, dtype=torch.float64, requires_grad=source in ("buffer", "closure"))
    alpha = {
        "parameter": LinearClassK(2.0, learnable=True),
        "buffer": gain,  # kept as a buffer that requires grad
        "closure": lambda h: gain * h,  # a tensor no module holds
    }.get(source, 2.0)
    filt = scene("vanilla", alpha=alpha)
    xs, us = random_states(2, seed=6)
    x, u = torch.tensor(xs), torch.tensor(us)
    leaf = {"x": x, "u_nom": u}.get(source)
    if leaf is not None:
        leaf.requires_grad_()
    out = filt(x, u)
    assert not calls and out.u.requires_grad
    out.u.sum().backward()
    if leaf is not None:
        grads = [leaf.grad]
    elif source == "parameter":
        grads = [p.grad for p in filt.parameters()]
    else:
        grads = [gain.grad]
    assert all(g is not None and torch.isfinite(g).all() for g in grads)
    with torch.no_grad():  # no_grad: the real-time path, whatever requires grad
        filt(x, u)
    assert len(calls) == 1


def test_a_time_the_barriers_ignore_carries_no_gradient(monkeypatch: pytest.MonkeyPatch) -> None:
    calls = _counting(monkeypatch)
    filt = scene("vanilla")
    xs, us = random_states(2, seed=6)
    t = torch.zeros(2, dtype=torch.float64, requires_grad=True)
    out = filt(torch.tensor(xs), torch.tensor(us), t)
    assert len(calls) == 1 and not out.u.requires_grad


@pytest.mark.parametrize("spread", [1e2, 1e7])
def test_ill_conditioned_weight_agrees_with_general_path(
    spread: float, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A rotated R of condition ``spread``: the kernel keeps rows it conditions well and
    hands the others to the general path; the answers agree either way."""
    c, s = np.cos(0.7), np.sin(0.7)
    rot = torch.tensor([[c, -s], [s, c]], dtype=torch.float64)
    R = rot @ torch.diag(torch.tensor([1.0, 1.0 / spread], dtype=torch.float64)) @ rot.T
    filt = scene("vanilla", clf=False, R=R)
    xs, us = random_states(4, seed=8)
    x, u = torch.tensor(xs), torch.tensor(us)
    real = realtime.solve
    answered: list[bool] = []

    def recorded(*args, **kwargs):
        res = real(*args, **kwargs)
        answered.append(res is not None)
        return res

    monkeypatch.setattr(realtime, "solve", recorded)
    with torch.no_grad():
        out = filt(x, u)
    assert answered == [spread < 1e4]
    _same(out, _general(filt, x, u), 1e-7)
