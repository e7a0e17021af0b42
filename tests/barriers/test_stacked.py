"""Stacked autograd Lie derivatives of several functions, and the Scaled barrier: against
one lie_derivatives call per function, closed forms, hand formulas and gradcheck."""

from __future__ import annotations

import pytest
import torch

from torchcbf.barriers import Ball, Barrier, Ellipse, HalfSpace, Scaled, rectify
from torchcbf.barriers.lie import lie_derivatives, stacked_lie_derivatives
from torchcbf.dynamics import AccelUnicycle, Unicycle


class _Opaque(Barrier):
    """A barrier without closed forms (autograd only): ``w * h`` of an inner one."""

    def __init__(self, inner: Barrier, w: float, time_varying: bool = False) -> None:
        super().__init__()
        self.inner, self.w, self.time_varying = inner, w, time_varying

    def forward(self, x, t=None):
        out = self.w * self.inner(x)
        if self.time_varying:
            out = out + torch.sin(torch.as_tensor(t, dtype=x.dtype)) * x[..., 0]
        return out


def _tol(dtype):
    return (
        {"atol": 1e-10, "rtol": 1e-10} if dtype == torch.float64 else {"atol": 1e-4, "rtol": 1e-4}
    )


def _functions(dyn):
    ell = Ellipse([1.0, 2.0], [0.5, 1.5])
    return [
        rectify(_Opaque(ell, 1.3), dyn, "exponential", gains=[2.0], relative_degree=2),
        rectify(_Opaque(Ball([0.0, -1.0], 0.7), 0.5), dyn, "high_order", relative_degree=2),
        _Opaque(HalfSpace([1.0, 1.0], 3.0, index=(0, 1)), 2.0, time_varying=True),
        rectify(Ellipse([[3.0, 1.0], [-2.0, 0.0]], [[1.0, 0.5], [0.7, 0.9]]), dyn,
                "exponential", gains=[1.0], relative_degree=2),
    ]  # fmt: skip


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
@pytest.mark.parametrize("grad", [False, True])
def test_stacked_equals_one_call_per_function(dtype, grad, device):
    dyn = AccelUnicycle(sigma=0.3).to(device, dtype)
    fns = [f.to(device, dtype) for f in _functions(dyn)]
    gen = torch.Generator().manual_seed(0)
    x = (2 * torch.randn(7, 4, generator=gen, dtype=torch.float64)).to(device, dtype)
    t = torch.linspace(0, 1, 7, dtype=dtype, device=device)
    ctx = torch.enable_grad() if grad else torch.no_grad()
    with ctx:
        terms, sizes = stacked_lie_derivatives(fns, x, dyn, t)
        ones = [lie_derivatives(f, x, dyn, t) for f in fns]
    assert sizes == [1, 1, 1, 2]
    for name in terms._fields:
        parts = []
        for one in ones:
            v = getattr(one, name)
            parts.append(v if one.h.dim() == 2 else v.unsqueeze(1))
        torch.testing.assert_close(getattr(terms, name), torch.cat(parts, 1), **_tol(dtype))


def test_stacked_gradients_flow_to_states_and_parameters():
    dyn = AccelUnicycle(sigma=0.3).double()
    ball = Ball(torch.tensor([0.0, -1.0]), torch.tensor(0.7), learnable=True).double()
    fns = [rectify(_Opaque(ball, 0.5), dyn, "exponential", gains=[1.5], relative_degree=2),
           rectify(Ellipse([1.0, 2.0], [0.5, 1.5]).double(), dyn, "exponential", gains=[2.0],
                   relative_degree=2)]  # fmt: skip
    x = torch.tensor([[0.3, 0.2, 0.8, 0.4], [1.5, -0.5, 0.3, 2.0]], dtype=torch.float64)

    def of_x(xx):
        terms, _ = stacked_lie_derivatives(fns, xx, dyn)
        return torch.cat([terms.h, terms.lgh.flatten(1), terms.hess_trace], 1)

    assert torch.autograd.gradcheck(of_x, (x.clone().requires_grad_(),))
    terms, _ = stacked_lie_derivatives(fns, x, dyn)
    (g,) = torch.autograd.grad(terms.hess_trace.sum() + terms.lgh.sum(), ball.center)
    ref = lie_derivatives(fns[0], x, dyn)
    (g_ref,) = torch.autograd.grad(ref.hess_trace.sum() + ref.lgh.sum(), ball.center)
    torch.testing.assert_close(g, g_ref)


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_scaled_closed_forms_match_autograd_and_hand_formula(dtype):
    dyn = Unicycle(sigma=0.2).to(dtype)
    inner = Ellipse([[1.0, 2.0], [0.0, -1.0]], [[0.5, 1.5], [1.0, 0.8]], angle=[0.3, -0.2])
    scaled = Scaled(inner, 2.5).to(dtype)
    x = (2 * torch.randn(9, 3, generator=torch.Generator().manual_seed(1), dtype=torch.float64)).to(
        dtype
    )
    ana = scaled.lie(x, dyn, method="analytic")
    auto = scaled.lie(x, dyn, method="autograd")
    base = inner.to(dtype).lie(x, dyn, method="analytic")
    for name in ana._fields:
        torch.testing.assert_close(getattr(ana, name), getattr(auto, name), **_tol(dtype))
        torch.testing.assert_close(getattr(ana, name), 2.5 * getattr(base, name), **_tol(dtype))
    with pytest.raises(ValueError, match="scale"):
        Scaled(inner, -1.0)


def test_rectified_scaled_shape_uses_closed_inner_derivatives():
    dyn = AccelUnicycle(sigma=0.28).double()
    ell = Ellipse([1.0, 2.0], [0.5, 1.5]).double()
    fast = rectify(Scaled(ell, 0.4), dyn, "exponential", gains=[2.0], relative_degree=2)
    slow = rectify(_Opaque(ell, 0.4), dyn, "exponential", gains=[2.0], relative_degree=2)
    x = 2 * torch.randn(11, 4, generator=torch.Generator().manual_seed(4), dtype=torch.float64)
    a, b = fast.lie(x, dyn), slow.lie(x, dyn)
    for name in a._fields:
        torch.testing.assert_close(getattr(a, name), getattr(b, name))
    xg = x[:3].clone().requires_grad_()
    assert torch.autograd.gradcheck(lambda z: fast.lie(z, dyn).hess_trace, (xg,))


def test_extension_points_public_names():
    from torchcbf.barriers.lie import AnalyticDerivatives

    dyn = Unicycle().double()
    x = torch.tensor([[0.5, -0.2, 0.3], [1.0, 2.0, -1.0]], dtype=torch.float64)

    class New(Barrier):  # h = x0 + 2 x1, closed forms under the public name
        has_analytic = True

        def forward(self, x, t=None):
            return x[..., 0] + 2 * x[..., 1]

        def derivatives(self, x, t):
            g = torch.tensor([1.0, 2.0, 0.0], dtype=x.dtype).expand_as(x)
            return AnalyticDerivatives(
                self(x), g, torch.zeros_like(x[..., 0]), lambda s: 0 * s.sum((-2, -1))
            )

    b = New()
    ana, auto = b.lie(x, dyn, method="analytic"), b.lie(x, dyn, method="autograd")
    for name in ("h", "lfh", "lgh", "dhdx"):
        torch.testing.assert_close(getattr(ana, name), getattr(auto, name))
    stack = Ball([[0.0, 0.0], [1.0, 1.0]], [0.5, 0.4])
    assert len(stack.parts()) == 2
    assert Ball([0.0, 0.0], 0.5).parts() is None
    with pytest.raises(ValueError, match="no closed-form derivatives"):
        _Opaque(stack, 1.0).derivatives(x, x[..., 0])


@pytest.mark.parametrize("form", ["exponential", "high_order"])
def test_rectified_k_shape_equals_separate_rectified_shapes(form):
    dyn = AccelUnicycle(sigma=0.28).double()
    centers = torch.tensor([[1.0, 2.0], [3.0, 2.0], [0.0, -1.0]], dtype=torch.float64)
    axes = torch.tensor([[0.5, 1.5], [0.75, 2.0], [1.0, 0.4]], dtype=torch.float64)
    scales = [0.5, 2.0, 1.0]
    whole = rectify(
        Scaled(Ellipse(centers, axes), scales), dyn, form, gains=[1.5], relative_degree=2
    )
    apart = [rectify(Scaled(Ellipse(c, a), s), dyn, form, gains=[1.5], relative_degree=2)
             for c, a, s in zip(centers, axes, scales, strict=True)]  # fmt: skip
    assert whole.parts() is None  # one evaluation for the three outputs
    x = 2 * torch.randn(5, 4, generator=torch.Generator().manual_seed(7), dtype=torch.float64)
    a = lie_derivatives(whole, x, dyn)
    b, sizes = stacked_lie_derivatives(apart, x, dyn)
    assert sizes == [1, 1, 1] and a.h.shape == (5, 3)
    for name in a._fields:
        torch.testing.assert_close(getattr(a, name), getattr(b, name))
    xg = x[:2].clone().requires_grad_()
    assert torch.autograd.gradcheck(lambda z: lie_derivatives(whole, z, dyn).hess_trace, (xg,))
    with pytest.raises(ValueError, match="scale"):
        Scaled(Ellipse(centers, axes), [1.0, -1.0, 1.0])
