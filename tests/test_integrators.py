"""Integrators: convergence order, Euler-Maruyama statistics, seeding, errors."""

from __future__ import annotations

import math

import pytest
import torch

from torchcbf.dynamics import ControlAffine, DoubleIntegrator, SingleIntegrator, VanDerPol
from torchcbf.integrators import euler, euler_maruyama, rk4, step


class _Decay(ControlAffine):
    """xdot = -x + u: with constant u the solution is u + (x0 - u) exp(-t)."""

    def __init__(self) -> None:
        super().__init__(1, 1)

    def f(self, x: torch.Tensor) -> torch.Tensor:
        return -x

    def g(self, x: torch.Tensor) -> torch.Tensor:
        return torch.ones_like(x).unsqueeze(-1)


class _Rotation(ControlAffine):
    """Harmonic oscillator xdot = (x2, -x1): a rotation, solution known in closed form."""

    def __init__(self) -> None:
        super().__init__(2, 1)

    def f(self, x: torch.Tensor) -> torch.Tensor:
        return torch.stack([x[..., 1], -x[..., 0]], -1)

    def g(self, x: torch.Tensor) -> torch.Tensor:
        return torch.zeros(*x.shape[:-1], 2, 1, dtype=x.dtype, device=x.device)


def _error(method: str, dt: float, T: float = 1.0) -> float:
    model = _Rotation()
    x = torch.tensor([1.0, 0.0], dtype=torch.float64)
    u = torch.zeros(1, dtype=torch.float64)
    for _ in range(round(T / dt)):
        x = step(model, x, u, dt, method=method)
    exact = torch.tensor([math.cos(T), -math.sin(T)], dtype=torch.float64)
    return float((x - exact).norm())


@pytest.mark.parametrize(("method", "order"), [("euler", 1), ("rk4", 4)])
def test_convergence_order(method: str, order: int) -> None:
    errors = [_error(method, dt) for dt in (0.1, 0.05, 0.025)]
    ratios = [errors[i] / errors[i + 1] for i in range(2)]
    for r in ratios:
        assert abs(math.log2(r) - order) < 0.15, (errors, ratios)


def test_rk4_matches_exact_solution_with_control(dtype: torch.dtype, device) -> None:
    model = _Decay().to(device=device, dtype=dtype)
    x0 = torch.linspace(-2, 2, 9, dtype=dtype, device=device).unsqueeze(-1)
    u = torch.full_like(x0, 0.5)
    x = x0
    for _ in range(10):
        x = step(model, x, u, 0.1)
    exact = 0.5 + (x0 - 0.5) * math.exp(-1.0)
    tol = 1e-6 if dtype == torch.float64 else 1e-5
    torch.testing.assert_close(x, exact, atol=tol, rtol=tol)


@pytest.mark.parametrize("batch", [(), (4,), (3, 5)])
@pytest.mark.parametrize("method", ["euler", "rk4", "euler_maruyama"])
def test_batched_equals_loop(method: str, batch: tuple[int, ...], device) -> None:
    model = VanDerPol(mu=2.0).to(device=device, dtype=torch.float64)
    gen = torch.Generator().manual_seed(1)
    x = torch.randn(*batch, 2, generator=gen, dtype=torch.float64).to(device)
    u = torch.randn(*batch, 1, generator=gen, dtype=torch.float64).to(device)
    out = step(model, x, u, 0.05, method=method)
    flat_x, flat_u, flat_out = x.reshape(-1, 2), u.reshape(-1, 1), out.reshape(-1, 2)
    for i in range(flat_x.shape[0]):
        torch.testing.assert_close(
            flat_out[i], step(model, flat_x[i], flat_u[i], 0.05, method=method)
        )


def test_euler_maruyama_variance_and_seeding(device) -> None:
    sigma, dt, steps, paths = 0.7, 0.01, 50, 100_000
    model = SingleIntegrator(1, sigma=sigma).to(device=device, dtype=torch.float64)
    state = torch.random.get_rng_state()
    cuda_state = torch.cuda.get_rng_state(device) if device.type == "cuda" else None

    def run(seed: int) -> torch.Tensor:
        gen = torch.Generator(device=device).manual_seed(seed)
        x = torch.zeros(paths, 1, dtype=torch.float64, device=device)
        u = torch.zeros(1, dtype=torch.float64, device=device)
        for _ in range(steps):
            x = step(model, x, u, dt, method="euler_maruyama", generator=gen)
        return x

    x = run(3)
    t = dt * steps
    assert abs(float(x.var()) / (sigma**2 * t) - 1.0) < 0.03
    assert abs(float(x.mean())) < 4 * sigma * math.sqrt(t / paths)
    assert torch.equal(x, run(3))
    assert not torch.equal(x, run(4))
    assert torch.equal(state, torch.random.get_rng_state())
    if cuda_state is not None:
        assert torch.equal(cuda_state, torch.cuda.get_rng_state(device))


def test_euler_maruyama_given_noise_and_no_diffusion() -> None:
    model = DoubleIntegrator(1, sigma=torch.tensor([0.0, 2.0])).double()
    x = torch.zeros(2, dtype=torch.float64)
    z = torch.tensor([0.3, -1.0], dtype=torch.float64)
    out = step(
        model, x, torch.zeros(1, dtype=torch.float64), 0.04, method="euler_maruyama", noise=z
    )
    torch.testing.assert_close(out, torch.tensor([0.0, 0.2 * 2.0 * -1.0], dtype=torch.float64))
    ode = DoubleIntegrator(1)
    torch.testing.assert_close(
        step(ode, torch.ones(2), torch.ones(1), 0.1, method="euler_maruyama"),
        step(ode, torch.ones(2), torch.ones(1), 0.1, method="euler"),
    )


def test_bad_inputs() -> None:
    model = SingleIntegrator(2, sigma=0.1)
    with pytest.raises(ValueError, match="generator= or noise="):
        step(model, torch.zeros(2), torch.zeros(2), 0.1, method="euler_maruyama")
    with pytest.raises(ValueError, match="method must be one of"):
        step(model, torch.zeros(2), torch.zeros(2), 0.1, method="midpoint")
    with pytest.raises(ValueError, match="dt must be a finite number > 0"):
        step(model, torch.zeros(2), torch.zeros(2), -0.1)
    with pytest.raises(ValueError, match=r"x must have shape \[\.\.\., 2\], got \(3,\)"):
        step(model, torch.zeros(3), torch.zeros(2), 0.1)
    with pytest.raises(ValueError, match=r"batch dimensions of x \(4, 2\) and u \(3, 2\)"):
        step(model, torch.zeros(4, 2), torch.zeros(3, 2), 0.1)
    with pytest.raises(TypeError, match="dynamics must be a ControlAffine"):
        step(lambda x, u: x, torch.zeros(2), torch.zeros(2), 0.1)
    with pytest.raises(TypeError, match="u must be a torch.Tensor"):
        step(model, torch.zeros(2), 0.0, 0.1)
    x = torch.zeros(3, 2)
    for noise in (torch.zeros(4, 2), torch.zeros(4, 3, 2)):  # not broadcasting, or widening
        with pytest.raises(ValueError, match=r"broadcast to the step's \(x, u\) \(3,\)"):
            step(model, x, x, 0.1, "euler_maruyama", noise=noise)
    with pytest.raises(TypeError, match="dynamics must be a ControlAffine"):
        euler_maruyama(lambda x, u: x, torch.zeros(2), torch.zeros(2), 0.1, noise=torch.zeros(2))
    with pytest.raises(ValueError, match="u must have shape"):
        euler_maruyama(model, torch.zeros(2), torch.zeros(3), 0.1, noise=torch.zeros(2))


def test_public_integrators_check_inputs_and_run_forward_hooks() -> None:
    import pytest

    from torchcbf.dynamics import SingleIntegrator
    from torchcbf.integrators import euler, rate_form, rk4, unchecked_step

    model = SingleIntegrator(2)
    x = torch.zeros(2)
    for fn in (euler, rk4):
        with pytest.raises(ValueError, match="u must have shape"):
            fn(model, x, torch.zeros(1), 0.1)
        with pytest.raises(TypeError, match="u has dtype torch.float64"):
            fn(model, x, torch.zeros(2, dtype=torch.float64), 0.1)
    calls = []
    handle = model.register_forward_hook(lambda *args: calls.append(1))
    rk4(model, x, torch.ones(2), 0.1)
    handle.remove()
    assert len(calls) == 4  # the hook runs at every stage
    form = rate_form(model)
    torch.testing.assert_close(
        unchecked_step(model, "rk4", x, torch.ones(2), 0.1, form=form),
        rk4(model, x, torch.ones(2), 0.1),
    )
    with pytest.raises(ValueError, match="method must be 'euler' or 'rk4'"):
        unchecked_step(model, "heun", x, torch.ones(2), 0.1, form=form)


class _OwnRate(_Rotation):
    """A closed-form ``xdot`` of its own, not ``f + g u``."""

    def xdot(self, x: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
        return super().xdot(x, u) + 0.5


class _Pendulum(ControlAffine):
    """Two controls, a state-dependent ``g``: the column sums of ``f + g u`` matter."""

    def __init__(self) -> None:
        super().__init__(2, 2)

    def f(self, x: torch.Tensor) -> torch.Tensor:
        return torch.stack([x[..., 1], -torch.sin(x[..., 0])], -1)

    def g(self, x: torch.Tensor) -> torch.Tensor:
        col = torch.stack([torch.cos(x[..., 0]), 1.0 + x[..., 1] ** 2], -1)
        return torch.stack([0.3 * col, col], -1)


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
@pytest.mark.parametrize("method", ["euler", "rk4"])
@pytest.mark.parametrize("model", ["plain", "own xdot", "hooked"])
def test_unchecked_step_in_both_layouts_matches_the_public_step(dtype, method, model) -> None:
    from torchcbf.integrators import rate_form, unchecked_step

    dyn = _OwnRate() if model == "own xdot" else _Pendulum()
    if model == "hooked":
        dyn.register_forward_hook(lambda module, args, out: 0.5 * out)
    form = rate_form(dyn)
    assert form == {"plain": "plain", "own xdot": "xdot", "hooked": "module"}[model]
    gen = torch.Generator().manual_seed(1)
    x = torch.randn(3, 7, dyn.state_dim, generator=gen, dtype=dtype)
    u = torch.randn(3, 7, dyn.control_dim, generator=gen, dtype=dtype)
    ref = step(dyn, x, u, 0.05, method=method)
    tol = {"atol": 1e-12, "rtol": 1e-12} if dtype == torch.float64 else {}
    torch.testing.assert_close(unchecked_step(dyn, method, x, u, 0.05, form=form), ref, **tol)
    xc, uc = x.mT.contiguous(), u.mT.contiguous()  # [3, n, 7]: each component's samples
    out = unchecked_step(dyn, method, xc, uc, 0.05, form=form, component=True)
    assert out.shape == xc.shape
    torch.testing.assert_close(out.mT, ref, **tol)


@pytest.mark.parametrize("integrate", [euler, rk4, euler_maruyama])
def test_a_step_that_is_not_a_positive_number_is_refused(integrate) -> None:
    model = SingleIntegrator(2, sigma=0.1)
    x, u = torch.zeros(1, 2), torch.ones(1, 2)
    kw = {"noise": torch.zeros(1, 2)} if integrate is euler_maruyama else {}
    for dt in (-0.1, 0.0, float("nan"), float("inf")):
        with pytest.raises(ValueError, match="dt"):
            integrate(model, x, u, dt, **kw)
