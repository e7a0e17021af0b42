"""Dynamics models: shapes, dtypes, buffers and values against hand-written formulas."""

from __future__ import annotations

import math

import pytest
import torch

from torchcbf.dynamics import (
    AccelUnicycle,
    Bicycle,
    ControlAffine,
    DoubleIntegrator,
    FixedWing,
    Quadrotor,
    SingleIntegrator,
    Unicycle,
    VanDerPol,
)

MODELS = {
    "single": lambda **kw: SingleIntegrator(3, **kw),
    "double": lambda **kw: DoubleIntegrator(2, **kw),
    "unicycle": lambda **kw: Unicycle(**kw),
    "accel_unicycle": lambda **kw: AccelUnicycle(**kw),
    "bicycle": lambda **kw: Bicycle(wheelbase=0.7, **kw),
    "vanderpol": lambda **kw: VanDerPol(mu=1.5, **kw),
    "quadrotor": lambda **kw: Quadrotor(mass=1.3, inertia=(0.02, 0.03, 0.05), **kw),
    "fixed_wing": lambda **kw: FixedWing(**kw),
}


def _reference_xdot(name: str, x: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
    """Each model's equations written out row by row (independent of the library's f and g)."""
    c, s = torch.cos, torch.sin
    if name == "single":
        return u.clone()
    if name == "double":
        return torch.cat([x[..., 2:], u], -1)
    if name == "unicycle":
        th = x[..., 2]
        return torch.stack([u[..., 0] * c(th), u[..., 0] * s(th), u[..., 1]], -1)
    if name == "accel_unicycle":
        v, th = x[..., 2], x[..., 3]
        return torch.stack([v * c(th), v * s(th), u[..., 0], u[..., 1]], -1)
    if name == "bicycle":
        th, de = x[..., 2], x[..., 3]
        v = u[..., 0]
        return torch.stack([v * c(th), v * s(th), v * torch.tan(de) / 0.7, u[..., 1]], -1)
    if name == "vanderpol":
        x1, x2 = x[..., 0], x[..., 1]
        return torch.stack([x2, 1.5 * (1 - x1 * x1) * x2 - x1 + u[..., 0]], -1)
    if name == "fixed_wing":
        v, ga, ps = x[..., 3], x[..., 4], x[..., 5]
        return torch.stack(
            [v * c(ga) * c(ps), v * c(ga) * s(ps), v * s(ga), u[..., 0], u[..., 1], u[..., 2]], -1
        )
    if name == "quadrotor":
        m, J = 1.3, torch.tensor([0.02, 0.03, 0.05], dtype=x.dtype)
        ph, th, ps = x[..., 3], x[..., 4], x[..., 5]
        p, q, r = x[..., 9], x[..., 10], x[..., 11]
        # Rotation matrix R = Rz(psi) Ry(theta) Rx(phi), thrust along the body z axis.
        Rz = _rot(ps, 2)
        Ry = _rot(th, 1)
        Rx = _rot(ph, 0)
        R = Rz @ Ry @ Rx
        acc = R[..., :, 2] * (u[..., 0:1] / m)
        acc = acc - torch.tensor([0.0, 0.0, 9.81], dtype=x.dtype)
        euler_rates = torch.stack(
            [
                p + s(ph) * torch.tan(th) * q + c(ph) * torch.tan(th) * r,
                c(ph) * q - s(ph) * r,
                (s(ph) * q + c(ph) * r) / c(th),
            ],
            -1,
        )
        w = x[..., 9:12]
        Jw = w * J
        wdot = (u[..., 1:4] - torch.linalg.cross(w, Jw)) / J
        return torch.cat([x[..., 6:9], euler_rates, acc, wdot], -1)
    raise KeyError(name)


def _rot(angle: torch.Tensor, axis: int) -> torch.Tensor:
    c, s = torch.cos(angle), torch.sin(angle)
    one, zero = torch.ones_like(c), torch.zeros_like(c)
    if axis == 0:
        rows = [[one, zero, zero], [zero, c, -s], [zero, s, c]]
    elif axis == 1:
        rows = [[c, zero, s], [zero, one, zero], [-s, zero, c]]
    else:
        rows = [[c, -s, zero], [s, c, zero], [zero, zero, one]]
    return torch.stack([torch.stack(r, -1) for r in rows], -2)


@pytest.mark.parametrize("name", list(MODELS))
@pytest.mark.parametrize("batch", [(), (5,), (4, 3)], ids=["none", "B", "BK"])
def test_shapes_and_values(name: str, batch: tuple[int, ...], dtype: torch.dtype, device) -> None:
    model = MODELS[name]().to(device=device, dtype=dtype)
    n, m = model.state_dim, model.control_dim
    gen = torch.Generator(device=device).manual_seed(0)
    x = 0.5 * torch.randn(*batch, n, generator=gen, device=device, dtype=dtype)
    u = torch.randn(*batch, m, generator=gen, device=device, dtype=dtype)
    f, g = model.f(x), model.g(x)
    assert f.shape == (*batch, n) and g.shape == (*batch, n, m)
    assert f.dtype == dtype and g.dtype == dtype and f.device.type == device.type
    xdot = model(x, u)
    ref = _reference_xdot(name, x.cpu().double(), u.cpu().double())
    atol = 1e-12 if dtype == torch.float64 else 1e-4
    torch.testing.assert_close(xdot.cpu().double(), ref, atol=atol, rtol=atol)
    # forward's fast closed form agrees with f + g u
    torch.testing.assert_close(xdot, f + (g @ u.unsqueeze(-1)).squeeze(-1), atol=atol, rtol=atol)
    # the rate is the caller's own tensor: writing into it leaves u (and x) as they were
    u_before, x_before = u.clone(), x.clone()
    xdot.add_(1.0)
    assert torch.equal(u, u_before) and torch.equal(x, x_before)


@pytest.mark.parametrize("name", list(MODELS))
def test_to_dtype_moves_buffers(name: str) -> None:
    model = MODELS[name](u_min=-1.0, u_max=2.0, sigma=0.1, disturbance_bound=0.3).double()
    for buf_name, buf in model.named_buffers():
        assert buf.dtype == torch.float64, buf_name
    assert model.u_min.shape == (model.control_dim,)
    assert torch.all(model.u_max == 2.0)
    model = model.float()
    assert all(b.dtype == torch.float32 for _, b in model.named_buffers())


def test_sigma_forms(device) -> None:
    f64 = {"dtype": torch.float64, "device": device}
    x = torch.randn(7, 4, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    x = x.to(device)
    scalar = AccelUnicycle(sigma=0.28).to(**f64).sigma(x)
    torch.testing.assert_close(scalar, 0.28 * torch.eye(4, **f64).expand(7, 4, 4))
    vec = AccelUnicycle(sigma=torch.tensor([0.1, 0.2, 0.3, 0.4])).to(**f64).sigma(x)
    torch.testing.assert_close(vec[0], torch.diag(torch.tensor([0.1, 0.2, 0.3, 0.4], **f64)))
    mat = AccelUnicycle(sigma=torch.ones(4, 2)).to(device).sigma(x.float())
    assert mat.shape == (7, 4, 2) and mat.device.type == device.type

    def state_sigma(state: torch.Tensor) -> torch.Tensor:
        return torch.diag_embed(state.abs())

    fn = AccelUnicycle(sigma=state_sigma)
    assert fn.has_diffusion and torch.equal(fn.sigma(x), torch.diag_embed(x.abs()))
    assert not AccelUnicycle().has_diffusion and AccelUnicycle().sigma(x) is None


def test_disturbance_and_clamp(device) -> None:
    M = torch.tensor([[1.0], [0.0]])
    model = SingleIntegrator(
        2, disturbance_bound=0.5, disturbance_matrix=M, u_min=[-1, -2], u_max=[1, 2]
    ).to(device)
    d = {"device": device}
    x, u, w = torch.zeros(3, 2, **d), torch.ones(3, 2, **d), torch.full((3, 1), 0.25, **d)
    torch.testing.assert_close(model(x, u, w), torch.tensor([[1.25, 1.0]], **d).expand(3, 2))
    torch.testing.assert_close(
        model.clamp_control(torch.tensor([5.0, -5.0], **d)), torch.tensor([1.0, -2.0], **d)
    )
    assert model.disturbance_bound.shape == (1,)
    tensor_bound = SingleIntegrator(2, disturbance_bound=torch.tensor([0.1, 0.2]))
    assert tensor_bound.disturbance_bound.tolist() == pytest.approx([0.1, 0.2])


def test_user_subclass_only_f_and_g() -> None:
    class Pendulum(ControlAffine):
        def __init__(self) -> None:
            super().__init__(2, 1)

        def f(self, x: torch.Tensor) -> torch.Tensor:
            return torch.stack([x[..., 1], -torch.sin(x[..., 0])], -1)

        def g(self, x: torch.Tensor) -> torch.Tensor:
            return x.new_tensor([[0.0], [1.0]]).expand(*x.shape[:-1], 2, 1)

    model = Pendulum()
    x = torch.tensor([[math.pi / 2, 0.5]])
    torch.testing.assert_close(model(x, torch.tensor([[2.0]])), torch.tensor([[0.5, 1.0]]))


def test_bad_inputs_name_argument_and_shapes() -> None:
    model = Unicycle()
    with pytest.raises(ValueError, match=r"x must have shape \[\.\.\., 3\], got \(5, 4\)"):
        model(torch.zeros(5, 4), torch.zeros(5, 2))
    with pytest.raises(ValueError, match=r"u must have shape \[\.\.\., 2\]"):
        model(torch.zeros(5, 3), torch.zeros(5, 3))
    with pytest.raises(ValueError, match=r"x \(5, 3\) and u \(4, 2\)"):
        model(torch.zeros(5, 3), torch.zeros(4, 2))
    with pytest.raises(TypeError, match="x must be a torch.Tensor"):
        model([0.0, 0.0, 0.0], torch.zeros(2))
    with pytest.raises(ValueError, match="u_min"):
        Unicycle(u_min=[1.0, 2.0, 3.0])
    with pytest.raises(ValueError, match="exceeds u_max"):
        Unicycle(u_min=1.0, u_max=-1.0)
    with pytest.raises(ValueError, match="sigma"):
        Unicycle(sigma=torch.ones(2))
    with pytest.raises(ValueError, match="wheelbase"):
        Bicycle(wheelbase=-1.0)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize(
    ("g_shape", "u_shape"),
    [((3, 2), (5, 2)), ((300, 4, 3), (300, 3)), ((4, 3), (2, 300, 3)), ((7, 50, 2, 1), (50, 1))],
)
def test_matvec_equals_matmul_and_differentiates(g_shape, u_shape, dtype):
    from torchcbf.dynamics.base import matvec

    gen = torch.Generator().manual_seed(0)
    g = torch.randn(g_shape, generator=gen, dtype=dtype)
    u = torch.randn(u_shape, generator=gen, dtype=dtype)
    ref = (g @ u.unsqueeze(-1)).squeeze(-1)
    torch.testing.assert_close(matvec(g, u), ref)


def test_matvec_gradients_on_the_column_path():
    from torchcbf.dynamics.base import MATVEC_COLUMNS_FROM, matvec

    gen = torch.Generator().manual_seed(1)
    g = torch.randn(MATVEC_COLUMNS_FROM, 2, 2, generator=gen, dtype=torch.float64)
    u = torch.randn(MATVEC_COLUMNS_FROM, 2, generator=gen, dtype=torch.float64)
    torch.autograd.gradcheck(matvec, (g.requires_grad_(True), u.requires_grad_(True)))


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize(
    ("a_shape", "b_shape"),
    [((3, 2), (5, 2, 4)), ((300, 8, 2), (300, 2, 2)), ((8, 3), (2, 300, 3, 1)),
     ((40, 5, 9), (40, 9, 2))],
)  # fmt: skip
def test_matmat_equals_matmul_and_differentiates(a_shape, b_shape, dtype):
    from torchcbf.dynamics.base import matmat

    gen = torch.Generator().manual_seed(2)
    a = torch.randn(a_shape, generator=gen, dtype=dtype)
    b = torch.randn(b_shape, generator=gen, dtype=dtype)
    torch.testing.assert_close(matmat(a, b), a @ b)
    if dtype == torch.float64:
        a, b = a[..., :4, :].requires_grad_(True), b.requires_grad_(True)
        torch.autograd.gradcheck(matmat, (a, b))


def test_a_diffusion_callable_must_give_one_matrix_per_state() -> None:
    def per_row_diagonal(x: torch.Tensor) -> torch.Tensor:
        return 0.1 * torch.ones_like(x)  # [B, n]: not [B, n, q]

    model = SingleIntegrator(3, sigma=per_row_diagonal)
    with pytest.raises(ValueError, match=r"sigma\(x\) must return \[\.\.\., 3, q\]"):
        model.sigma(torch.zeros(3, 3))
    good = SingleIntegrator(3, sigma=lambda x: 0.1 * torch.eye(3).expand(*x.shape[:-1], 3, 3))
    assert good.sigma(torch.zeros(5, 3)).shape == (5, 3, 3)


def test_a_disturbance_batch_that_does_not_match_the_states_is_named() -> None:
    model = SingleIntegrator(3, disturbance_bound=[0.1, 0.1, 0.1])
    x, u, w = torch.zeros(3, 3), torch.zeros(3, 3), torch.zeros(5, 3)
    with pytest.raises(ValueError, match=r"batch dimensions of x \(3, 3\) and w \(5, 3\)"):
        model(x, u, w)


def test_model_sizes_take_numpy_ints() -> None:
    import numpy as np

    model = DoubleIntegrator(np.int64(2))
    assert model.state_dim == 4 and type(model.state_dim) is int
