"""Second-order closed forms (hess_mat, hess_dir), the models' drift derivatives and the
closed-form exponential CBF of relative degree two, each against autograd, in float64 and
float32, with gradcheck; and the cases that keep the autograd path."""

from __future__ import annotations

import pytest
import torch

from torchcbf.barriers import (
    Ball,
    BarrierStack,
    Ellipse,
    HalfSpace,
    Scaled,
    Transformed,
    rectify,
)
from torchcbf.dynamics import (
    AccelUnicycle,
    DoubleIntegrator,
    SingleIntegrator,
    Unicycle,
    VanDerPol,
)

DTYPES = [torch.float64, torch.float32]


def _tol(dtype: torch.dtype) -> dict[str, float]:
    return {"atol": 1e-10, "rtol": 1e-9} if dtype == torch.float64 else {"atol": 3e-4, "rtol": 3e-4}


def _states(count: int, dim: int, seed: int, dtype: torch.dtype) -> torch.Tensor:
    gen = torch.Generator().manual_seed(seed)
    x = 3 * torch.rand(count, dim, generator=gen, dtype=torch.float64) - 1.5
    x[:, :2] += 2.5  # positions away from the shapes' centres (radius form: h > -1)
    return x.to(dtype)


SHAPES = {
    "ball": lambda: Ball([0.5, 0.2], 0.4),
    "ball_keep_in": lambda: Ball([[0.5, 0.2], [1.0, 1.0]], [4.0, 5.0], keep_in=True),
    "ellipse": lambda: Ellipse([0.2, -0.3], [0.5, 1.5], angle=0.4),
    "ellipses": lambda: Ellipse([[1.0, 2.0], [-0.5, 0.5]], [[0.5, 1.5], [1.0, 0.25]]),
    "scaled": lambda: Scaled(
        Ellipse([[1.0, 2.0], [-0.5, 0.5]], [[0.5, 1.5], [1.0, 0.3]]), [2.0, 0.5]
    ),
    "radius": lambda: Transformed(Ellipse([0.2, -0.3], [0.5, 1.5], angle=0.4), "radius"),
    "exp": lambda: Scaled(Transformed(Ellipse([[1.0, 2.0]], [[0.5, 1.5]]), "exp", rate=0.3), 0.5),
    "stack": lambda: BarrierStack(
        Ball([0.5, 0.2], 0.4), Transformed(Ellipse([[1.0, 2.0]], [[0.5, 1.5]]), "radius")
    ),
}
MODELS = {
    "accel_unicycle": lambda: AccelUnicycle(sigma=torch.tensor([0.1, 0.2, 0.3, 0.4])),
    "double_integrator": lambda: DoubleIntegrator(2, sigma=0.3),
    "single_integrator": lambda: SingleIntegrator(2, sigma=0.2),
    "unicycle": lambda: Unicycle(sigma=torch.tensor([0.1, 0.2, 0.3])),
}


def _hessians(shape, x: torch.Tensor) -> torch.Tensor:
    """Autograd Hessians of every output at every state: ``[B, k, n, n]``."""

    def h_flat(xi: torch.Tensor) -> torch.Tensor:
        return shape(xi.unsqueeze(0)).reshape(-1)

    rows = []
    for xi in x:
        out = h_flat(xi)
        rows.append(
            torch.stack(
                [
                    torch.autograd.functional.hessian(lambda z, j=j: h_flat(z)[j], xi)
                    for j in range(out.numel())
                ]
            )  # fmt: skip
        )
    return torch.stack(rows)


@pytest.mark.parametrize("name", list(SHAPES))
@pytest.mark.parametrize("dtype", DTYPES)
def test_hess_mat_and_hess_dir_match_autograd(
    name: str, dtype: torch.dtype, device: torch.device
) -> None:
    shape = SHAPES[name]().to(device=device, dtype=dtype)
    assert shape.has_second_order
    n = 4
    x = _states(3, n, seed=1, dtype=dtype).to(device)
    gen = torch.Generator().manual_seed(2)
    m = torch.randn(3, n, 2, generator=gen, dtype=torch.float64).to(device=device, dtype=dtype)
    v = torch.randn(3, n, generator=gen, dtype=torch.float64).to(device=device, dtype=dtype)
    d = shape.derivatives(x, torch.zeros(3, dtype=dtype, device=device))
    H = _hessians(shape.double(), x.double())  # [B, k, n, n]
    want = H @ m.double().unsqueeze(1)
    got = d.hess_mat(m)
    got = got if got.dim() == 4 else got.unsqueeze(1)
    torch.testing.assert_close(got.double(), want, **_tol(dtype))
    # hess_dir(v, S) = d/de tr(S' H(x + e v) S), by autograd through the closed-form quad
    xg = x.double().clone().requires_grad_()
    zero = torch.zeros(3, dtype=torch.float64, device=device)
    quad = shape.double().derivatives(xg, zero).hess_quad(m.double())
    quad = quad if quad.dim() == 2 else quad.unsqueeze(-1)

    def along_v(out: torch.Tensor) -> torch.Tensor:
        if not out.requires_grad:  # a quadratic shape: the Hessian does not change
            return torch.zeros_like(out)
        return (torch.autograd.grad(out.sum(), xg, retain_graph=True)[0] * v.double()).sum(-1)

    want_dir = torch.stack([along_v(quad[:, j]) for j in range(quad.shape[1])], -1)
    got_dir = d.hess_dir(v, m)
    got_dir = got_dir if got_dir.dim() == 2 else got_dir.unsqueeze(-1)
    torch.testing.assert_close(got_dir.double(), want_dir, **_tol(dtype))


@pytest.mark.parametrize("model", list(MODELS))
@pytest.mark.parametrize("dtype", DTYPES)
def test_drift_derivatives_match_autograd(
    model: str, dtype: torch.dtype, device: torch.device
) -> None:
    dyn = MODELS[model]().to(device=device, dtype=dtype)
    assert dyn.has_drift_derivatives
    n = dyn.state_dim
    x = _states(3, n, seed=3, dtype=dtype).to(device)
    gen = torch.Generator().manual_seed(4)
    w = torch.randn(3, 2, n, generator=gen, dtype=torch.float64).to(device=device, dtype=dtype)
    s = torch.randn(3, n, 3, generator=gen, dtype=torch.float64).to(device=device, dtype=dtype)
    d = dyn.drift_derivatives(x)
    f = lambda z: dyn.double().f(z)  # noqa: E731
    jac = torch.stack([torch.autograd.functional.jacobian(f, xi) for xi in x.double()])
    torch.testing.assert_close(d.jac.double(), jac, **_tol(dtype))
    hess = torch.stack(
        [
            torch.stack(
                [torch.autograd.functional.hessian(lambda z, i=i: f(z)[i], xi) for i in range(n)]
            )  # fmt: skip
            for xi in x.double()
        ]
    )  # [B, n(i), n, n]
    quad = torch.einsum("bnq,binm,bmq->bi", s.double(), hess, s.double())  # [B, n(i)]
    want = (w.double() * quad.unsqueeze(1)).sum(-1)
    torch.testing.assert_close(d.hess_quad(w, s).double(), want, **_tol(dtype))


@pytest.mark.parametrize("name", ["ellipses", "scaled", "radius", "exp", "stack", "ball"])
@pytest.mark.parametrize("model", ["accel_unicycle", "double_integrator"])
@pytest.mark.parametrize("dtype", DTYPES)
def test_exponential_barrier_closed_forms_match_autograd(
    name: str, model: str, dtype: torch.dtype, device: torch.device
) -> None:
    dyn = MODELS[model]().to(device=device, dtype=dtype)
    shape = SHAPES[name]().to(device=device, dtype=dtype)
    barrier = rectify(shape, dyn, "exponential", [2.5], relative_degree=2)
    assert barrier.has_analytic
    x = _states(5, dyn.state_dim, seed=5, dtype=dtype).to(device)
    got = barrier.lie(x, dyn, method="analytic")
    want = barrier.lie(x, dyn, method="autograd")
    for field in got._fields:
        torch.testing.assert_close(
            getattr(got, field), getattr(want, field).detach(), **_tol(dtype), msg=field
        )


def test_exponential_barrier_closed_forms_gradcheck() -> None:
    dyn = AccelUnicycle(sigma=0.2).double()
    shape = Transformed(Ellipse([[1.0, 2.0], [0.0, -1.0]], [[0.5, 1.5], [1.0, 0.4]]), "radius")
    coefficients = torch.tensor([1.5], dtype=torch.float64, requires_grad=True)
    barrier = rectify(shape.double(), dyn, "exponential", coefficients, relative_degree=2)
    x = _states(3, 4, seed=6, dtype=torch.float64).requires_grad_()

    def terms(xx: torch.Tensor, k: torch.Tensor) -> tuple[torch.Tensor, ...]:
        barrier.coefficients = k
        out = barrier.lie(xx, dyn, method="analytic")
        return out.h, out.lfh, out.lgh, out.hess_trace

    assert torch.autograd.gradcheck(terms, (x, coefficients))


def test_autograd_path_where_closed_forms_do_not_apply() -> None:
    acc = AccelUnicycle()
    wall = rectify(HalfSpace([1.0, 0.0], 1.0), acc, "exponential", relative_degree=2)
    assert not wall.has_analytic  # no second-order closed forms
    moving = Ball([0.5, 0.2], 0.4, velocity=[0.1, 0.0])
    assert not rectify(moving, acc, "exponential", relative_degree=2).has_analytic
    assert not rectify(Ball([0.5, 0.2], 0.4), VanDerPol(), "exponential",
                       relative_degree=2, ).has_analytic  # fmt: skip

    class Damped(DoubleIntegrator):  # a new f: the parent's drift derivatives do not apply
        def f(self, x):
            return torch.cat([x[..., 2:] - 0.5 * x[..., :2], torch.zeros_like(x[..., 2:])], -1)

    damped = Damped(2)
    assert not damped.has_drift_derivatives
    ball = rectify(Ball([0.5, 0.2], 0.4), damped, "exponential", [2.0], relative_degree=2)
    assert not ball.has_analytic
    third = rectify(Ball([0.5, 0.2], 0.4), acc, "exponential", relative_degree=3)
    assert not third.has_analytic
    with pytest.raises(ValueError, match="closed-form"):
        third.lie(torch.zeros(1, 4), acc, method="analytic")
