"""The C kernel of the dual active-set method against its torch implementation (the
reference), directly: the same solutions, multipliers, active sets, certificates and
iteration counts, the same KKT adjoints, identical answers when the batch is split over
threads, and the cases it must not take."""

from __future__ import annotations

import pytest
import torch
from _problems import make_batch

from torchcbf.qp import Status, _dual_native, solve_qp
from torchcbf.qp._dual import dual_adjoints, solve_dual

F64 = torch.float64

pytestmark = pytest.mark.skipif(
    not _dual_native.available(), reason="the C kernel of the dual method was not built"
)


def _problems(B: int, n: int, m: int, seed: int, frac_infeasible: float = 0.25):
    """Random QPs with box rows folded into G (some infeasible), and degenerate rows."""
    batch = make_batch(B, n, m, 0, True, seed=seed, frac_infeasible=frac_infeasible)
    eye = torch.eye(n, dtype=F64).expand(B, n, n)
    G = torch.cat((batch.G, eye, -eye), -2)
    h = torch.cat((batch.h, batch.ub, -batch.lb), -1)
    G[:, -1] = G[:, 0]  # a duplicated row
    h[:, -1] = h[:, 0]
    G[::7, 1] = 0.0  # all-zero rows, some infeasible (0 <= h < 0)
    return 0.5 * (batch.Q + batch.Q.mT), batch.p, G, h


def _both(P, q, G, h, **kw):
    ref = solve_dual(P, q, G, h, eps=1e-9, max_iter=100, engine="torch", **kw)
    out = solve_dual(P, q, G, h, eps=1e-9, max_iter=100, engine="c", **kw)
    return ref, out


@pytest.mark.parametrize("shape", [(1, 3), (2, 6), (3, 8), (4, 8), (6, 20), (8, 30), (12, 40)])
def test_kernel_matches_torch_implementation(shape):
    n, m = shape
    P, q, G, h = _problems(400, n, m, seed=70 + n)
    ref, out = _both(P, q, G, h)
    assert ref.ok.any() and not ref.ok.all()  # both outcomes are exercised
    assert torch.equal(out.ok, ref.ok)
    assert torch.equal(out.active, ref.active)
    # on rows that end infeasible, rounding may pick another blocking row a step earlier
    assert torch.equal(out.iterations[ref.ok], ref.iterations[ref.ok])
    torch.testing.assert_close(out.x, ref.x, atol=1e-10, rtol=1e-10)
    torch.testing.assert_close(out.z, ref.z, atol=1e-9, rtol=1e-9)


def test_not_positive_definite_rows_are_not_ok():
    P, q, G, h = _problems(50, 3, 6, seed=5, frac_infeasible=0.0)
    P = P.clone()
    P[4] = torch.diag(torch.tensor([1.0, 0.0, 1.0], dtype=F64))
    P[9, 0, 0] = -1.0
    ref, out = _both(P, q, G, h)
    assert not out.ok[4] and not out.ok[9]
    assert torch.equal(out.ok, ref.ok)
    assert (out.x[[4, 9]] == 0).all() and (out.z[[4, 9]] == 0).all()


def test_adjoints_match_torch_implementation():
    P, q, G, h = _problems(300, 4, 8, seed=21)
    ref, out = _both(P, q, G, h)
    g = torch.Generator().manual_seed(2)
    gx = torch.randn(300, 4, generator=g, dtype=F64)
    gz = torch.randn(300, G.shape[1], generator=g, dtype=F64)
    w_ref = dual_adjoints(ref.factor, ref.x, gx, gz)
    w_out = dual_adjoints(out.factor, out.x, gx, gz)
    for a, b in zip(w_out, w_ref, strict=True):
        torch.testing.assert_close(a, b, atol=1e-8, rtol=1e-8)
    assert (w_out[0][~out.ok] == 0).all()


@pytest.mark.parametrize("shape", [(3, 5), (12, 40)])
def test_batch_split_over_threads_gives_identical_answers(shape):
    n, m = shape
    M = m + 2 * n  # _problems folds the box into G
    rows = -(-3 * _dual_native.MIN_WORK_PER_THREAD // (n * n + M * n))  # work for 3 threads
    P, q, G, h = _problems(rows, n, m, seed=8)
    threads = torch.get_num_threads()
    try:
        torch.set_num_threads(1)
        one = solve_dual(P, q, G, h, eps=1e-9, max_iter=100, engine="c")
        torch.set_num_threads(3)
        three = solve_dual(P, q, G, h, eps=1e-9, max_iter=100, engine="c")
    finally:
        torch.set_num_threads(threads)
    for a, b in zip(one[:5], three[:5], strict=True):
        assert torch.equal(a, b)


def test_applies_only_to_float64_on_the_cpu_with_at_most_64_variables():
    assert _dual_native.applies(torch.zeros(2, 64, dtype=F64))
    assert not _dual_native.applies(torch.zeros(2, 65, dtype=F64))
    assert not _dual_native.applies(torch.zeros(2, 4, dtype=torch.float32))
    with pytest.raises(ValueError, match="N=65"):
        _dual_native.forward(
            torch.eye(65, dtype=F64).expand(1, 65, 65), torch.zeros(1, 65, dtype=F64),
            torch.zeros(1, 2, 65, dtype=F64), torch.zeros(1, 2, dtype=F64), 1e-9, 10,
        )  # fmt: skip


def test_transposed_and_expanded_g_give_the_right_gradients():
    """A transposed (or expanded) G gives the gradients of a contiguous one."""
    Q = torch.eye(2, dtype=F64)
    h = torch.tensor([1.0, 5.0, 5.0], dtype=F64)
    G_t = torch.tensor([[1.0, 2.0, 1.0], [0.0, 1.0, 3.0]], dtype=F64).T
    grads = []
    for G in (G_t, G_t.contiguous()):
        p = torch.tensor([-2.0, -1.0], dtype=F64, requires_grad=True)
        solve_qp(Q, p, G, h).x.sum().backward()
        grads.append(p.grad)
    torch.testing.assert_close(grads[0], grads[1])
    torch.testing.assert_close(grads[1], torch.tensor([0.0, -1.0], dtype=F64))
    P, q, G, h = _problems(6, 3, 5, seed=3, frac_infeasible=0.0)
    G1, h1 = G[:1].expand(6, -1, -1), h[:1].expand(6, -1)
    out = solve_dual(P, q, G1, h1, eps=1e-9, max_iter=100, engine="c")
    ref = solve_dual(P, q, G1.contiguous(), h1.contiguous(), eps=1e-9, max_iter=100, engine="c")
    gx = torch.ones(6, 3, dtype=F64)
    gz = torch.zeros(6, G.shape[1], dtype=F64)
    for a, b in zip(
        dual_adjoints(out.factor, out.x, gx, gz),
        dual_adjoints(ref.factor, ref.x, gx, gz),
        strict=True,
    ):
        assert torch.equal(a, b)


def test_nearly_dependent_final_active_set_is_not_accepted():
    """Rows 0 and 2 at cosine -(1 - 1.6e-13): pivots are judged against the original
    diagonal, so a nearly dependent active set (a point 2e-3 off) is not accepted; nor is
    enumeration's choice, which passes its own eps checks 0.25 off, by any method."""
    Q = torch.tensor([[5.9529149525052345, 4.477149544721193], [4.477149544721193,
                      5.047085047494767]], dtype=F64)  # fmt: skip
    p = torch.tensor([-1.1989579878000285, 0.3467384696737627], dtype=F64)
    G = torch.tensor([[-3.5452702798252393, -1.1690657557300168],
                      [0.1694659500381488, 0.05588624647478687],
                      [2.3011671170180787, 0.7588196834095134]], dtype=F64)  # fmt: skip
    h = torch.tensor([6.326328822707258, -0.3024061454617175, -4.106300765045831], dtype=F64)
    args = [t.unsqueeze(0) for t in (Q, p, G, h)]
    ref, out = _both(*args)
    assert not ref.ok.any() and not out.ok.any()
    exact = torch.tensor([-1.3907593159, -1.1938688193], dtype=F64)  # 60-digit enumeration
    for method in ("auto", "enumerate", "ipm"):
        sol = solve_qp(Q, p, G, h, method=method)
        assert int(sol.status) != Status.SOLVED or (sol.x - exact).abs().max() < 1e-6, method


def test_max_iter_beyond_a_c_int_is_clamped():
    P, q, G, h = _problems(20, 3, 5, seed=4, frac_infeasible=0.0)
    big = solve_dual(P, q, G, h, eps=1e-9, max_iter=2**32 + 3, engine="c")
    ref = solve_dual(P, q, G, h, eps=1e-9, max_iter=100, engine="c")
    assert big.ok.all() and torch.equal(big.iterations, ref.iterations)


def test_a_library_built_from_another_version_is_refused(monkeypatch, caplog):
    """An editable install not rebuilt after an edit of the C source must not be called."""
    # simulates a kernel built from another version of the source (the loader's check)
    monkeypatch.setattr(_dual_native, "KERNEL_VERSION", _dual_native.KERNEL_VERSION + 1)
    _dual_native._library.cache_clear()
    try:
        assert not _dual_native.available()
        assert "another version" in caplog.text
    finally:
        monkeypatch.undo()
        _dual_native._library.cache_clear()
    assert _dual_native.available()


@pytest.mark.parametrize("shape", [(2, 6), (4, 8), (8, 30)])
def test_infeasible_rows_are_proved_by_a_farkas_certificate(shape):
    """The kernel proves infeasibility only where the interior point method finds it too, for
    most infeasible rows; solve_qp then reports them without re-solving them."""
    n, m = shape
    P, q, G, h = _problems(400, n, m, seed=90 + n, frac_infeasible=0.3)
    out = solve_dual(P, q, G, h, eps=1e-9, max_iter=100, engine="c")
    ref = solve_qp(P, q, G, h, method="ipm")
    truly = ref.status == Status.PRIMAL_INFEASIBLE
    assert not bool((out.ok & out.infeasible).any())
    assert bool(truly[out.infeasible].all())  # never a feasible row
    assert int(out.infeasible.sum()) >= 0.8 * int(truly.sum()) > 0
    assert bool((out.x[out.infeasible] == 0).all())
    default = solve_qp(P, q, G, h)
    assert torch.equal(default.status == Status.PRIMAL_INFEASIBLE, truly)
    assert bool((default.x[truly] == 0).all())


def test_the_kernels_callers_refuse_operands_it_cannot_read():
    """Another dtype or device, or a shape other than the batch's: a named error, never the
    kernel reading or writing past a buffer."""
    from torchcbf.qp import realtime

    f64 = torch.float64
    P = torch.eye(2, dtype=f64).expand(3, 2, 2)
    q = torch.full((3, 2), -1.0, dtype=f64)
    G, h = torch.eye(2, dtype=f64).expand(3, 2, 2), torch.full((3, 2), 0.5, dtype=f64)
    ok = solve_dual(P, q, G, h, eps=1e-9, max_iter=50, engine="c")
    torch.testing.assert_close(ok.x, torch.full((3, 2), 0.5, dtype=f64))
    for bad, message in (
        ((P.float(), q.float(), G.float(), h.float()), "P must be torch.float64"),
        ((P.to("meta"), q.to("meta"), G.to("meta"), h.to("meta")), "P must be a CPU tensor"),
        ((P, q, G[:, :1], h), r"G must have shape \[3, 2, 2\], got \[3, 1, 2\]"),
    ):
        with pytest.raises(ValueError, match=message):
            solve_dual(*bad, eps=1e-9, max_iter=50, engine="c")
    small = realtime.solve_small(P, q, G, h, None, None, 1e-9, 50, (3,))
    torch.testing.assert_close(small.x, ok.x)
    for args, message in (
        ((P, q, G[:, :1], h), r"G must have shape \[3, 2, 2\], got \[3, 1, 2\]"),
        ((P.to("meta"), q, G, h), "P must be a CPU tensor"),
    ):
        with pytest.raises(ValueError, match=message):
            realtime.solve_small(*args, None, None, 1e-9, 50, (3,))
    with pytest.raises(ValueError, match=r"P must have shape \[64, 2, 2\]"):
        realtime.solve_small(P, q, G, h, None, None, 1e-9, 50, (64,))
