"""Gradients of the filtered control: gradcheck through an active CBF constraint."""

from __future__ import annotations

import pytest
import torch
from torch import nn

from torchcbf.barriers import Ball, QuadraticLyapunov
from torchcbf.dynamics import SingleIntegrator, Unicycle
from torchcbf.filters import FilterStatus, LinearClassK, SafetyFilter

F64 = torch.float64


def test_gradcheck_barrier_params_class_k_and_u_nom(device: torch.device) -> None:
    dyn = SingleIntegrator(2, u_min=-3.0, u_max=3.0)
    ball = Ball(
        nn.Parameter(torch.tensor([0.0, 0.1], dtype=F64)),
        nn.Parameter(torch.tensor(1.0, dtype=F64)),
    )
    alpha = LinearClassK(0.8, learnable=True)
    filt = SafetyFilter(dyn, ball, alpha=alpha).to(device=device, dtype=F64)
    x = torch.tensor([[-2.0, 0.3], [1.5, -1.0], [0.2, 2.0]], dtype=F64, device=device)
    u_nom = torch.tensor(
        [[2.0, 0.2], [-2.0, 1.0], [0.1, -2.5]], dtype=F64, device=device, requires_grad=True
    )
    out = filt(x, u_nom)
    # every row is active (the filter changed u_nom) and solved
    assert (out.status == FilterStatus.SOLVED).all()
    assert ((out.u - u_nom).abs().amax(-1) > 0.1).all()

    names = ("barriers.0.center", "barriers.0.radius", "alpha.0.log_gain")
    assert set(names) == {n for n, _ in filt.named_parameters()}

    def fn(center: torch.Tensor, radius: torch.Tensor, log_gain: torch.Tensor, un: torch.Tensor):
        params = dict(zip(names, (center, radius, log_gain), strict=True))
        return torch.func.functional_call(filt, params, (x, un)).u

    inputs = tuple(
        dict(filt.named_parameters())[n].detach().clone().requires_grad_() for n in names
    )
    assert torch.autograd.gradcheck(fn, (*inputs, u_nom), eps=1e-6, atol=1e-6, rtol=1e-4)


def test_gradcheck_state_through_lie_terms(device: torch.device) -> None:
    # a unicycle (g depends on the state) with a CLF and a CBF: d u / d x
    dyn = Unicycle(u_min=torch.tensor([-1.0, -2.0]), u_max=torch.tensor([1.5, 2.0]))
    filt = SafetyFilter(dyn, Ball([1.0, 0.0], 0.5), QuadraticLyapunov([3.0, 0.5]), alpha=1.0).to(
        device=device, dtype=F64
    )
    x = torch.tensor(
        [[0.0, 0.1, 0.2], [0.4, -0.6, 0.9]], dtype=F64, device=device, requires_grad=True
    )
    u_nom = torch.tensor([[1.4, 0.0], [1.0, -0.3]], dtype=F64, device=device)
    out = filt(x, u_nom)
    assert (out.status == FilterStatus.SOLVED).all()
    assert torch.autograd.gradcheck(
        lambda xx: filt(xx, u_nom).u, (x,), eps=1e-6, atol=1e-6, rtol=1e-4
    )


def test_gradient_is_zero_where_constraint_inactive_and_flows_to_parameters() -> None:
    dyn = SingleIntegrator(2)
    ball = Ball([0.0, 0.0], 1.0, learnable=True)
    filt = SafetyFilter(dyn, ball, alpha=LinearClassK([1.0], learnable=True)).double()
    x = torch.tensor([[-3.0, 0.0], [-2.0, 0.0]], dtype=F64)
    u_nom = torch.tensor([[-1.0, 0.0], [5.0, 0.0]], dtype=F64, requires_grad=True)
    out = filt(x, u_nom)  # row 0 moves away (inactive), row 1 is clipped by the CBF
    (g,) = torch.autograd.grad(out.u[:, 0].sum(), u_nom, retain_graph=True)
    assert torch.allclose(g[0], torch.tensor([1.0, 0.0], dtype=F64))
    assert torch.allclose(g[1], torch.tensor([0.0, 0.0], dtype=F64), atol=1e-9)
    # row 1: u_x = alpha h / (2 |x|) = (4 - r^2) / 4 with r = 1: d u_x / d r = -r / 2
    grads = torch.autograd.grad(out.u[1, 0], [ball.radius])
    assert torch.allclose(grads[0], torch.tensor(-0.5, dtype=F64), atol=1e-8)


def test_a_batch_of_gradients_on_the_device_equals_the_cpus(device, dtype) -> None:
    """300 states (the batched QP's large-batch path on a GPU): the filtered controls and the
    gradients to the barrier's parameters and to ``u_nom`` equal the CPU's."""
    from _devices import device_matches_cpu

    gen = torch.Generator().manual_seed(5)
    angle = torch.rand(300, generator=gen, dtype=F64) * 6.28
    radius = 1.2 + 2.0 * torch.rand(300, generator=gen, dtype=F64)
    x = torch.stack([radius * angle.cos(), radius * angle.sin()], -1)
    u_nom = -2.0 * x / radius.unsqueeze(-1) + 0.3 * torch.randn(300, 2, generator=gen, dtype=F64)

    def run(dev: torch.device):
        ball = Ball(nn.Parameter(torch.tensor([0.0, 0.1])), nn.Parameter(torch.tensor(1.0)))
        filt = SafetyFilter(SingleIntegrator(2, u_min=-3.0, u_max=3.0), ball, alpha=0.8)
        filt = filt.to(device=dev, dtype=dtype)
        un = u_nom.to(device=dev, dtype=dtype).requires_grad_(True)
        out = filt(x.to(device=dev, dtype=dtype), un)
        loss = (out.u * torch.tensor([1.0, -0.5], dtype=dtype, device=dev)).sum()
        grads = torch.autograd.grad(loss, [un, *filt.parameters()])
        return out.u, out.status, grads

    loose = {} if dtype == F64 else {"rtol": 1e-3, "atol": 1e-3}
    u, status, _ = device_matches_cpu(run, device, dtype, **loose)
    assert int((status == FilterStatus.SOLVED).sum()) > 250
    changed = (u.cpu().double() - u_nom).abs().amax(-1) > 0.1  # the barrier row is active
    assert int(changed.sum()) > 100


def test_forward_mode_and_torch_func_are_refused_by_name() -> None:
    """Reverse mode only: the real-time path would drop a forward-mode tangent."""
    import torch.autograd.forward_ad as fwAD

    filt = SafetyFilter(SingleIntegrator(2), [Ball([1.0, 0.0], 0.5).double()], alpha=1.0)
    x = torch.tensor([[0.0, 0.1]], dtype=torch.float64)
    u = torch.tensor([[1.0, 0.0]], dtype=torch.float64)
    with fwAD.dual_level(), pytest.raises(NotImplementedError, match="forward-mode AD"):
        filt(fwAD.make_dual(x, torch.ones_like(x)), u)
    with pytest.raises(NotImplementedError, match="torch.func transforms"):
        torch.func.jacrev(lambda v: filt(v, u).u)(x)
    # a filter tensor (the ball's centre) with a tangent, through functional_call
    centre = dict(filt.named_buffers())["barriers.0.center"]
    with fwAD.dual_level(), pytest.raises(NotImplementedError, match="forward-mode AD"):
        dual = fwAD.make_dual(centre.clone(), torch.ones_like(centre))
        torch.func.functional_call(filt, {"barriers.0.center": dual}, (x, u))
    with pytest.raises(NotImplementedError, match="torch.func transforms"):
        torch.func.jvp(
            lambda c: torch.func.functional_call(filt, {"barriers.0.center": c}, (x, u)).u,
            (centre,),
            (torch.ones_like(centre),),
        )
    # a tangent on a tensor a class-K closure captures (the one-state path would drop it)
    with fwAD.dual_level():
        gain = fwAD.make_dual(torch.tensor(2.0, dtype=torch.float64), torch.tensor(1.0))
        closure = SafetyFilter(SingleIntegrator(2), [Ball([1.0, 0.0], 0.5).double()],
                               alpha=lambda h: gain * h)  # fmt: skip
        with pytest.raises(NotImplementedError, match="forward-mode AD"):
            closure(x, u)
    jac = torch.autograd.functional.jacobian(lambda v: filt(v, u).u, x)
    assert jac.shape == (1, 2, 1, 2) and bool(torch.isfinite(jac).all())
