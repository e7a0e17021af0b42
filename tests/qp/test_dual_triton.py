"""The Triton kernel of the dual active-set method against its torch implementation (the
same active sets, step counts, answers and backward) and the known optimum of each problem,
on CUDA, or on the CPU in Triton's interpreter (``TRITON_INTERPRET=1`` set before Python
starts); and its compilation for a GPU (no GPU needed), which catches what the interpreter
accepts and the compiler refuses. Skipped where Triton does not import."""

from __future__ import annotations

import pytest
import torch
from _devices import NEEDS_TRITON, RUNS_TRITON, triton_target
from _problems import make_batch

from torchcbf._triton import interpreted
from torchcbf.qp import _dual_native, _dual_triton, solve_qp
from torchcbf.qp._dual import dual_adjoints, dual_engine, solve_dual
from torchcbf.qp._function import MAX_DUAL_CONDITION, condition_estimate

TARGET = triton_target()
pytestmark = [pytest.mark.device, NEEDS_TRITON]
runs = RUNS_TRITON

F64 = torch.float64


def _problems(B: int, n: int, m: int, seed: int, dtype: torch.dtype = F64):
    """Random QPs with known optima, box rows folded into ``G``, some infeasible, a duplicated
    row and all-zero rows (every seventh problem: its known optimum no longer holds); on the
    target device."""
    batch = make_batch(B, n, m, 0, True, seed=seed, frac_infeasible=0.2)
    eye = torch.eye(n, dtype=F64).expand(B, n, n)
    G = torch.cat((batch.G, eye, -eye), -2)
    h = torch.cat((batch.h, batch.ub, -batch.lb), -1)
    G[:, -1] = G[:, 0]
    h[:, -1] = h[:, 0]
    G[::7, 1] = 0.0
    data = (0.5 * (batch.Q + batch.Q.mT), batch.p, G, h, batch.x_star)
    return [t.to(TARGET, dtype) for t in data], batch.kind


def _eps(dtype: torch.dtype) -> float:
    return 1e-9 if dtype == F64 else 1e-5


def _active_conditioning(P, G, active):
    """``[B]`` condition number of each row's active-set matrix ``G_A P^-1 G_A'`` (1 where
    no row is active): how much a different rounding (a fused multiply-add) may move the
    multipliers and the adjoints."""
    P, G = P.double(), G.double()
    M = G @ torch.linalg.solve(P, G.mT)
    a = active.to(M.dtype)
    fill = (torch.diagonal(M, dim1=-2, dim2=-1) * a).amax(-1, keepdim=True).clamp_min(1e-300)
    M = M * a.unsqueeze(-1) * a.unsqueeze(-2) + torch.diag_embed((1 - a) * fill)
    return torch.linalg.cond(M)


def _kkt_error(P, q, G, h, x, z):
    """``[B]`` largest KKT residual of ``(x, z)`` (stationarity, primal and dual feasibility,
    complementarity), relative to the size of the terms."""
    x, z, P, q, G, h = (t.double() for t in (x, z, P, q, G, h))
    slack = h - (G @ x.unsqueeze(-1)).squeeze(-1)
    grad = (P @ x.unsqueeze(-1)).squeeze(-1) + q + (G.mT @ z.unsqueeze(-1)).squeeze(-1)
    scale = 1 + q.abs().amax(-1) + h.abs().amax(-1) + z.abs().amax(-1)
    parts = (grad.abs().amax(-1), (-slack).clamp_min(0).amax(-1), (-z).clamp_min(0).amax(-1),
             (z * slack).abs().amax(-1))  # fmt: skip
    return torch.stack(parts).amax(0) / scale


def _assert_rows_close(a, b, bound, rows):
    """``a`` and ``b`` agree on ``rows`` within ``bound [B]`` times ``1 + |b|`` per row."""
    err = (a - b).abs().flatten(1).amax(-1).double()
    size = 1 + b.abs().flatten(1).amax(-1).double()
    bad = rows & (err > bound * size)
    assert not bool(bad.any()), (bad.nonzero().flatten().tolist(), err[bad], (bound * size)[bad])


@runs
@pytest.mark.parametrize("dtype", [F64, torch.float32])
@pytest.mark.parametrize("shape", [(1, 37, 1, 2), (2, 70, 2, 6), (3, 33, 3, 5), (4, 64, 4, 8)])
def test_answers_match_the_torch_implementation_and_the_known_optimum(shape, dtype):
    _, B, n, m = shape
    (P, q, G, h, x_star), kind = _problems(B, n, m, seed=40 + n, dtype=dtype)
    eps = _eps(dtype)
    ref = solve_dual(P, q, G, h, eps=eps, max_iter=100, engine="torch")
    out = solve_dual(P, q, G, h, eps=eps, max_iter=100, engine="triton")
    assert ref.ok.any() and not ref.ok.all()
    # rounding differs where one side fuses a multiply and an add: a row at the edge of its
    # check, or a degenerate one (a duplicated row), may end otherwise; the same point and,
    # where the active sets agree, the same multipliers, steps and backward
    both = out.ok & ref.ok
    assert int((out.ok != ref.ok).sum()) <= max(1, B // 50)
    tol = 1e-10 if dtype == F64 else 1e-4
    torch.testing.assert_close(out.x[both], ref.x[both], atol=tol, rtol=tol)
    # a row that ends on another active set (a tie broken otherwise) is still optimal with
    # its own multipliers
    same = both & (out.active == ref.active).all(-1)
    other = both & ~same
    assert bool((_kkt_error(P, q, G, h, out.x, out.z)[other] <= 10 * eps).all())
    # where the sets agree: the same multipliers, steps and backward, to the rounding that
    # the active-set matrix's conditioning amplifies
    bound = tol + torch.finfo(dtype).eps * _active_conditioning(P, G, ref.active)
    _assert_rows_close(out.z, ref.z, 10 * bound, same)
    assert torch.equal(out.iterations[same], ref.iterations[same])
    g = torch.Generator().manual_seed(n)
    gx = torch.randn(B, n, generator=g, dtype=F64).to(TARGET, dtype)
    gz = torch.randn(B, G.shape[-2], generator=g, dtype=F64).to(TARGET, dtype)
    adjoints = zip(dual_adjoints(out.factor, out.x, gx, gz),
                   dual_adjoints(ref.factor, ref.x, gx, gz), strict=True)  # fmt: skip
    for a, b in adjoints:
        _assert_rows_close(a, b, 10 * bound, same)
    kept = [k in ("active", "inactive") and i % 7 for i, k in enumerate(kind)]
    known = out.ok & torch.tensor(kept, dtype=torch.bool, device=TARGET)
    assert known.sum() >= B // 2
    ref_tol = 1e-7 if dtype == F64 else 2e-3
    torch.testing.assert_close(out.x[known], x_star[known], atol=ref_tol, rtol=ref_tol)


@runs
def test_rows_that_do_not_iterate_or_run_out_of_steps():
    (P, q, G, h, _), _ = _problems(40, 3, 6, seed=3)
    P = P.clone()
    P[4] = torch.diag(torch.tensor([1.0, 0.0, 1.0], dtype=F64, device=TARGET))
    solved = {}
    for max_iter in (1, 100):
        ref = solve_dual(P, q, G, h, eps=1e-9, max_iter=max_iter, engine="torch")
        out = solve_dual(P, q, G, h, eps=1e-9, max_iter=max_iter, engine="triton")
        assert not out.ok[4]
        assert int((out.ok != ref.ok).sum()) <= 1
        both = out.ok & ref.ok
        assert torch.equal(out.iterations[both], ref.iterations[both])
        assert int(out.iterations.max()) <= max_iter
        solved[max_iter] = int(out.ok.sum())
    assert 0 < solved[1] < solved[100]  # some rows need more than one step


@runs
def test_one_row_and_gradients_through_solve_qp():
    (P, q, G, h, _), kind = _problems(3, 2, 4, seed=9)
    row = kind.index("active")
    args = [t[row : row + 1].clone().requires_grad_() for t in (P, q, G, h)]
    out = solve_dual(*(a.detach() for a in args), eps=1e-9, max_iter=50, engine="triton")
    ref = solve_dual(*(a.detach() for a in args), eps=1e-9, max_iter=50, engine="torch")
    assert out.ok.all()
    torch.testing.assert_close(out.x, ref.x, atol=1e-12, rtol=1e-12)
    if TARGET.type == "cuda":  # solve_qp runs the kernel by itself only on CUDA
        # (a batch this small goes to enumeration unless the active-set method is asked for)
        sol = solve_qp(*args, method="active_set")
        assert sol.path == "active_set_triton"
        cpu = solve_qp(*(a.detach().cpu() for a in args))
        torch.testing.assert_close(sol.x.detach().cpu(), cpu.x, atol=1e-9, rtol=1e-9)
        sol.x.sum().backward()
        assert all(torch.isfinite(a.grad).all() for a in args)


@runs
@pytest.mark.parametrize("dtype", [F64, torch.float32])
@pytest.mark.parametrize("setting", [(16, 1, None), (32, 2, None), (64, 2, None), (32, 1, 128)])
def test_launch_settings_give_the_default_answers(setting, dtype):
    # fewer problems than threads in a program: a problem's tiles spread over threads, and
    # the sums across them may round otherwise; a register cap only spills
    (P, q, G, h, _), _ = _problems(70, 3, 10, seed=12, dtype=dtype)
    eps = _eps(dtype)
    ref = _dual_triton.solve(P, q, G, h, eps=eps, max_iter=100)
    block, warps, maxnreg = setting
    out = _dual_triton.solve(
        P, q, G, h, eps=eps, max_iter=100, block=block, warps=warps, maxnreg=maxnreg
    )
    assert ref.ok.any()
    assert int((out.ok != ref.ok).sum()) <= 1
    both = out.ok & ref.ok
    tol = 1e-10 if dtype == F64 else 1e-4
    torch.testing.assert_close(out.x[:, both], ref.x[:, both], atol=tol, rtol=tol)
    assert bool((_kkt_error(P, q, G, h, out.x.T, out.z.T)[out.ok] <= 10 * eps).all())


@runs
@pytest.mark.parametrize("dtype", [F64, torch.float32])
def test_inputs_at_any_strides_give_the_answers_of_planes(dtype):
    # the kernel reads each tensor at its own strides: contiguous, copied into planes with
    # the batch last, or views into larger tensors in another index order
    (P, q, G, h, _), _ = _problems(45, 3, 7, seed=5, dtype=dtype)
    eps = _eps(dtype)
    ref = _dual_triton.solve(P, q, G, h, eps=eps, max_iter=100, planes=True)
    assert ref.ok.any()
    wide_G = torch.zeros(45, 3, 2 * G.shape[1], dtype=dtype, device=G.device)
    wide_G[:, :, ::2] = G.mT  # G seen as every other column of a wider tensor, transposed
    wide_h = torch.zeros(h.shape[1], 91, dtype=dtype, device=h.device)
    wide_h[:, 1:-1:2] = h.T  # batch last, at an offset that breaks 16-byte alignment
    views = (P.mT.contiguous().mT, q.T.contiguous().T, wide_G[:, :, ::2].mT, wide_h[:, 1:-1:2].T)
    assert not any(t.is_contiguous() for t in views)
    for args in ((P, q, G, h), views):
        out = _dual_triton.solve(*args, eps=eps, max_iter=100)
        for a, b in zip(out, ref, strict=True):
            torch.testing.assert_close(a, b, atol=0.0, rtol=0.0)
    # one problem repeated by stride-0 views: each row the answer of the problem alone
    one = [t[:1].expand(6, *t.shape[1:]) for t in (P, q, G, h)]
    alone = _dual_triton.solve(*(t[:1].contiguous() for t in (P, q, G, h)), eps=eps, max_iter=100)
    out = _dual_triton.solve(*one, eps=eps, max_iter=100)
    for a, b in zip(out, alone, strict=True):
        torch.testing.assert_close(a, b.expand_as(a), atol=0.0, rtol=0.0)


@runs
@pytest.mark.parametrize("dtype", [F64, torch.float32])
def test_the_kernels_condition_estimate_is_the_torch_one(dtype):
    # well and badly conditioned P (a spread of eigenvalues up to 1e12), N = 1 to 4
    for n in (1, 2, 3, 4):
        gen = torch.Generator().manual_seed(n)
        B = 40
        rot, _ = torch.linalg.qr(torch.randn(B, n, n, generator=gen, dtype=F64))
        spread = 10.0 ** (12 * torch.rand(B, n, generator=gen, dtype=F64))
        P = rot @ torch.diag_embed(spread) @ rot.mT
        P = 0.5 * (P + P.mT)
        q = torch.randn(B, n, generator=gen, dtype=F64)
        G = torch.randn(B, 3, n, generator=gen, dtype=F64)
        h = torch.rand(B, 3, generator=gen, dtype=F64)
        args = [t.to(TARGET, dtype) for t in (P, q, G, h)]
        sol = _dual_triton.solve(*args, eps=_eps(dtype), max_iter=100)
        want = condition_estimate(sol.L, batch_first=False)
        pd = torch.isfinite(want) & (want > 0)
        assert pd.sum() >= B // 2
        rtol = 1e-9 if dtype == F64 else 1e-3
        torch.testing.assert_close(sol.condition[pd], want[pd], rtol=rtol, atol=0.0)
        if n > 1 and dtype == F64:  # the cases reach beyond the layer's MAX_DUAL_CONDITION
            assert bool((want[pd] > MAX_DUAL_CONDITION).any())


@runs
def test_engine_choice_and_errors():
    (P, q, G, h, _), _ = _problems(4, 2, 3, seed=1)
    M = G.shape[-2]
    if TARGET.type == "cuda":
        assert dual_engine(q, M) == "triton"
    else:  # the interpreter is for tests: the CPU keeps the C kernel or torch
        assert dual_engine(q, M) == ("c" if _dual_native.available() else "torch")
    assert not _dual_triton.applies(q, 1024)  # a tile too large for the registers
    with pytest.raises(ValueError, match="engine must be one of"):
        solve_dual(P, q, G, h, eps=1e-9, max_iter=10, engine="cuda")
    big_G = G.repeat(1, 40, 1)[:, :257]
    big_h = h.repeat(1, 40)[:, :257]
    with pytest.raises(ValueError, match="engine='triton' needs"):
        solve_dual(P, q, big_G, big_h, eps=1e-9, max_iter=10, engine="triton")
    with pytest.raises(ValueError, match="h must be"):
        _dual_triton.solve(P, q, G, h.T, eps=1e-9, max_iter=5)


@pytest.mark.skipif(interpreted(), reason="the interpreter does not compile")
@pytest.mark.parametrize("real", ["fp32", "fp64"])
def test_kernel_compiles_for_a_gpu_one_problem_per_thread(real):
    import re

    from triton import compile as triton_compile
    from triton.backends.compiler import GPUTarget
    from triton.compiler import ASTSource

    fn = _dual_triton._dual_solve_kernel
    names = ("p", "q", "g", "h", "x", "z", "active", "ok", "iters", "l", "s", "rs", "us", "cond")
    names += ("consts",)
    kinds = [f"*{real}"] * 6 + ["*i8", "*i8", "*i64", f"*{real}", "*i64"] + [f"*{real}"] * 4
    signature = {f"{name}_ptr": kind for name, kind in zip(names, kinds, strict=True)}
    signature.update(B="i32", **dict.fromkeys(_dual_triton.STRIDE_ARGS, "i32"))
    signature.update(max_iter="i32")
    sizes = {"N": 3, "M": 13, "NP": 4, "MP": 16, "BLOCK": _dual_triton.BLOCK}
    signature.update(dict.fromkeys(sizes, "constexpr"))
    # the hints a launch on 10^6 problems gives: pointers aligned to 16 bytes, and B
    # divisible by 16 unless the kernel keeps it unspecialised
    hinted = [
        p.num for p in fn.params if p.name.endswith("_ptr") and not p.do_not_specialize_on_alignment
    ]
    hinted += [p.num for p in fn.params if p.name == "B" and not p.do_not_specialize]
    attrs = {(i,): [["tt.divisibility", 16]] for i in hinted}
    src = ASTSource(fn, signature, constexprs=sizes, attrs=attrs)
    try:
        compiled = triton_compile(src, target=GPUTarget("cuda", 90, 32), options={"num_warps": 1})
    except RuntimeError as err:  # a Triton without its CUDA tool chain
        if "ptxas" in str(err) or "backend" in str(err):
            pytest.skip(f"Triton cannot compile for CUDA here: {err}")
        raise
    assert "_dual_solve_kernel" in compiled.asm["ptx"] and compiled.asm["cubin"]
    # each thread holds one problem: a layout with several problems per thread (vectorised
    # loads along the batch) multiplies the registers a thread needs and spills them
    per_thread = re.findall(r"sizePerThread = \[([\d, ]+)\]", compiled.asm["ttgir"])
    assert per_thread and all(set(p.replace(" ", "").split(",")) == {"1"} for p in per_thread)


@runs
@pytest.mark.parametrize("dtype", [torch.float32, F64])
def test_rows_of_data_that_is_not_finite_are_not_ok(dtype):
    """A NaN the kernel's checks would drop (``tl.max`` skips it) fails them, as in torch:
    an infeasible ``h = -inf``, a NaN in ``h`` or ``G``, a NaN in ``P``'s upper triangle."""
    nan, inf = float("nan"), float("inf")
    P = torch.eye(2, dtype=dtype).expand(4, 2, 2).clone()
    P[3, 0, 1] = nan
    q = torch.full((4, 2), -1.0, dtype=dtype)
    G = torch.eye(2, dtype=dtype).expand(4, 2, 2).clone()
    G[2, 0, 0] = nan
    h = torch.tensor([[-inf, 0.5], [nan, 0.5], [0.5, 0.5], [0.5, 0.5]], dtype=dtype)
    P, q, G, h = (t.to(TARGET) for t in (P, q, G, h))
    fast = solve_dual(P, q, G, h, eps=_eps(dtype), max_iter=50, engine="triton")
    reference = solve_dual(P, q, G, h, eps=_eps(dtype), max_iter=50, engine="torch")
    assert fast.ok.tolist() == reference.ok.tolist() == [False] * 4
