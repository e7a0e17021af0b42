"""Objects changed between calls through public attributes: the fast paths read the new
values as the general path does, or stand aside for it, or refuse as it does; never read a
tensor of another shape than they expect (each case read past a buffer under AddressSanitizer
before the boundary checked it)."""

from __future__ import annotations

import pytest
import torch

from torchcbf.barriers import Ball
from torchcbf.dynamics import SingleIntegrator, Unicycle
from torchcbf.filters import LinearClassK, SafetyFilter, Stochastic
from torchcbf.mppi import MPPI
from torchcbf.mppi.costs import QuadraticGoal

F64 = torch.float64
X = torch.tensor([[0.0, 0.0], [0.3, 0.1], [-0.2, 0.4]], dtype=F64)
U = torch.tensor([[1.0, 0.2], [2.0, 0.5], [0.3, 1.9]], dtype=F64)


def _both(build, change, x=X, u=U):
    """The outputs of the filter ``build(backend)`` after one call and ``change(filter)``,
    on the default backend and on the general path."""
    out = {}
    for backend in ("auto", "torch"):
        filt = build(backend)
        filt(x, u)
        change(filt)
        with torch.no_grad():
            out[backend] = filt(x, u)
    return out["auto"], out["torch"]


@pytest.mark.parametrize("where", ["filter", "dynamics"])
@pytest.mark.parametrize("bound", ["0-d view", "[1] view", "0-d"])
def test_a_control_bound_of_one_number_stands_for_every_control(where: str, bound: str) -> None:
    backing = torch.tensor([0.1, 123.0], dtype=F64)  # the bound, then other memory
    value = {"0-d view": backing[0], "[1] view": backing[:1], "0-d": torch.tensor(0.1).double()}

    def build(backend):
        model = SingleIntegrator(2, u_min=-2.0, u_max=2.0).double()
        return SafetyFilter(model, Ball([[5.0, 5.0]], [0.5]), alpha=1.0, backend=backend)

    def change(filt):
        (filt if where == "filter" else filt.dynamics).u_max = value[bound]

    fast, general = _both(build, change, X[:1], torch.tensor([[0.05, 50.0]], dtype=F64))
    torch.testing.assert_close(fast.u, general.u)
    torch.testing.assert_close(fast.u, torch.tensor([[0.05, 0.1]], dtype=F64))
    with pytest.raises(ValueError, match=r"u_max must be a number or \[2\], got shape \(3,\)"):
        change_to = torch.ones(3, dtype=F64)
        filt = build("auto")
        filt.u_max = change_to
        filt(X, U)


def test_conditions_of_another_layout_than_the_kernel_reads_take_the_general_path() -> None:
    def build(backend):
        model = SingleIntegrator(2, u_min=-2.0, u_max=2.0).double()
        balls = Ball([[1.0, 0.0], [0.0, 1.5]], [0.5, 0.4])
        return SafetyFilter(model, balls, alpha=1.0, backend=backend)

    def change(filt):
        filt.barriers[0].center = torch.tensor([0.5, 0.1], dtype=F64)

    # one centre for two radii: refused on every path, before a kernel reads it
    with pytest.raises(ValueError, match=r"Ball.radius \(2,\) does not match the one shape"):
        _both(build, change)

    def more(filt):
        filt.barriers[0].center = torch.tensor([[0.5, 0.1], [3.0, 3.0]], dtype=F64)
        filt.barriers[0].radius = torch.tensor([0.3, 0.2], dtype=F64)

    fast, general = _both(build, more)
    torch.testing.assert_close(fast.u, general.u, atol=1e-12, rtol=0)
    torch.testing.assert_close(fast.constraint_value, general.constraint_value)


def test_a_diffusion_of_another_layout_takes_the_general_path() -> None:
    backing = torch.tensor([0.1, 0.2, 50.0, 60.0], dtype=F64)

    def build(backend):
        model = SingleIntegrator(2, u_min=-2.0, u_max=2.0, sigma=0.3).double()
        balls = Ball([[1.0, 0.0], [0.0, 1.5]], [0.5, 0.4])
        return SafetyFilter(model, balls, alpha=1.0, backend=backend, mode=Stochastic(beta=0.05))

    def change(filt):
        filt.dynamics.sigma_matrix = backing[:2]

    fast, general = _both(build, change)
    torch.testing.assert_close(fast.u, general.u, atol=1e-12, rtol=0)


def _planner(backend: str, goal: QuadraticGoal) -> MPPI:
    planner = MPPI(Unicycle(), goal, horizon=8, num_samples=64, dt=0.1, noise_sigma=0.3,
                   temperature=0.5, u_min=-1.0, u_max=1.0, seed=3, backend=backend)  # fmt: skip
    return planner.double()


@pytest.mark.parametrize("in_place", [False, True])
def test_a_cost_terms_index_list_changed_between_calls_is_read(in_place: bool) -> None:
    x = torch.tensor([[0.0, 0.0, 0.1], [0.2, -0.3, 0.5]], dtype=F64)
    plans = {}
    for backend in ("auto", "torch"):
        goal = QuadraticGoal([2.0, 1.0], index=(0, 1), terminal_weight=5.0)
        planner = _planner(backend, goal)
        goal.index = [0, 1]
        planner(x)
        if in_place:
            goal.index[:] = [1, 0]
        else:
            goal.index = [1, 0]
        plans[backend] = planner(x).plan
    torch.testing.assert_close(plans["auto"], plans["torch"], atol=1e-12, rtol=0)


@pytest.mark.parametrize(
    "chol", [torch.eye(3), torch.ones(2, 2, 2), torch.ones(4), torch.tensor(1.0)]
)
def test_a_noise_factor_of_another_shape_is_refused_on_every_path(chol: torch.Tensor) -> None:
    for backend in ("auto", "torch"):
        planner = _planner(backend, QuadraticGoal([2.0, 1.0], index=(0, 1)))
        planner(torch.zeros(1, 3, dtype=F64))
        planner.noise_chol = chol.double()
        with pytest.raises(ValueError, match=r"chol must be \[2, 2\]"):
            planner(torch.zeros(1, 3, dtype=F64))


def test_a_method_assigned_to_a_users_class_later_is_seen_by_its_next_instance() -> None:
    class MyGoal(QuadraticGoal):
        pass

    class MyK(LinearClassK):
        pass

    x = torch.tensor([[0.0, 0.0, 0.1]], dtype=F64)
    _planner("auto", MyGoal([2.0, 1.0], index=(0, 1)))(x)  # the kernel's answer, cached
    MyGoal.stage = lambda self, s, c: 3.0 * self.weight * (s[..., 0] - 2.0) ** 2
    plans = [_planner(b, MyGoal([2.0, 1.0], index=(0, 1)))(x).plan for b in ("auto", "torch")]
    torch.testing.assert_close(plans[0], plans[1], atol=1e-12, rtol=0)

    def build(backend):
        model = SingleIntegrator(2, u_min=-2.0, u_max=2.0).double()
        return SafetyFilter(model, Ball([1.0, 0.0], 0.5), alpha=MyK(1.0), backend=backend)

    build("auto")(X[:2], U[:2])
    MyK._phi = lambda self, h: h**3
    fast, general = _both(build, lambda filt: None, X[:2], U[:2])
    torch.testing.assert_close(fast.u, general.u, atol=1e-12, rtol=0)
