"""MPPI, SMPPI and KMPPI against pytorch-mppi on its pendulum, with the same noise.

Both planners are handed the same noise draws each call (their samplers are replaced), so
the closed loops must agree step by step up to rounding: the sampling, the clamping, the
control cost, the weights, the update, the warm start and every option are compared at once.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import pytest
import torch

from torchcbf.mppi import KMPPI, MPPI, SMPPI, rbf_kernel
from torchcbf.mppi.pendulum import PendulumModel, angle_normalize, pendulum_cost, pendulum_step

peer = pytest.importorskip("pytorch_mppi")

K, H, SIGMA, LAMBDA = 100, 15, 10.0, 1.0
F64 = torch.float64


def running_cost(state: torch.Tensor, action: torch.Tensor, *_: object) -> torch.Tensor:
    return angle_normalize(state[..., 0]).square() + 0.1 * state[..., 1].square()


def ours(cls: type[MPPI] = MPPI, **kwargs: object) -> MPPI:
    options = dict(step=lambda x, u, j: pendulum_step(x, u))
    options.update(kwargs)
    return cls(
        PendulumModel(u_min=None, u_max=None).double(), pendulum_cost, horizon=H,
        num_samples=K, dt=0.05, noise_sigma=SIGMA, temperature=LAMBDA,
        control_cost_weight=LAMBDA, **options,
    ).double()  # fmt: skip


def theirs(cls: type = None, **kwargs: object) -> object:
    cls = cls or peer.mppi.MPPI
    kwargs.setdefault("U_init", torch.zeros(H, 1, dtype=F64))
    return cls(
        kwargs.pop("dynamics", lambda s, a: pendulum_step(s, a)), running_cost, 2,
        torch.tensor([[SIGMA]], dtype=F64), num_samples=K, horizon=H, lambda_=LAMBDA, **kwargs,
    )  # fmt: skip


def closed_loop(
    planner: MPPI,
    reference: object,
    *,
    steps: int = 12,
    points: int = H,
    scale: float = 1.0,
    between: Callable[[int], None] | None = None,
) -> None:
    """Run both planners on the same states with the same noise; compare every control."""
    gen = torch.Generator().manual_seed(3)
    draw: dict[str, torch.Tensor] = {}

    def our_noise(eps: torch.Tensor) -> None:
        eps.copy_(scale * draw["z"].unsqueeze(0))

    planner._sample_noise = our_noise  # type: ignore[method-assign]
    reference._sample_noise = lambda shape: draw["z"].clone()  # type: ignore[attr-defined]
    x = torch.tensor([math.pi, 1.0], dtype=F64)
    for i in range(steps):
        if between is not None:
            between(i)
        n = points if not callable(points) else points()
        draw["z"] = math.sqrt(SIGMA) * torch.randn(K, n, 1, generator=gen, dtype=F64)
        expected = reference.command(x)  # type: ignore[attr-defined]
        out = planner(x)
        assert out.path == "torch"
        torch.testing.assert_close(out.u, scale * expected.reshape(1), rtol=1e-9, atol=1e-9)
        torch.testing.assert_close(
            out.plan, scale * reference.get_action_sequence(), rtol=1e-9, atol=1e-9
        )
        x = pendulum_step(x, out.u)


def test_mppi_matches_the_peer() -> None:
    closed_loop(ours(), theirs())


def test_bounded_mppi_matches_the_peer() -> None:
    bound = torch.tensor([1.5], dtype=F64)
    closed_loop(ours(u_min=-bound, u_max=bound), theirs(u_min=-bound, u_max=bound))


def test_step_dependent_dynamics_match_the_peer() -> None:
    def step(x: torch.Tensor, u: torch.Tensor, j: int) -> torch.Tensor:
        return pendulum_step(x, u * (1.0 + 0.1 * j))

    closed_loop(ours(step=step), theirs(dynamics=step, step_dependent_dynamics=True))


def test_noise_abs_cost_matches_the_peer() -> None:
    closed_loop(ours(noise_abs_cost=True), theirs(noise_abs_cost=True))


@pytest.mark.parametrize("scale", [2.0, 0.5])
def test_u_scale_matches_the_peer_in_applied_units(scale: float) -> None:
    # the peer returns the sampled action a; the applied control is scale * a
    closed_loop(ours(u_scale=scale), theirs(u_scale=scale), scale=scale)


def test_action_sampler_and_null_action_match_the_peer() -> None:
    candidates = torch.stack([torch.full((H, 1), 1.0), torch.linspace(-2, 2, H).unsqueeze(-1)]).to(
        F64
    )

    class Sampler(peer.mppi.SpecificActionSampler):
        def sample_trajectories(self, state: torch.Tensor, info: object) -> torch.Tensor:
            return candidates.clone()

    planner = ours(action_sampler=lambda x, t: candidates, sample_null_action=True)
    reference = theirs(specific_action_sampler=Sampler(), sample_null_action=True)
    closed_loop(planner, reference)


def test_change_horizon_matches_the_peer() -> None:
    planner, reference = ours(), theirs()
    lengths = {4: 10, 8: 20}
    current = {"H": H}

    def between(i: int) -> None:
        if i in lengths:
            planner.change_horizon(lengths[i])
            reference.change_horizon(lengths[i])
            current["H"] = lengths[i]

    closed_loop(planner, reference, between=between, points=lambda: current["H"])


@pytest.mark.parametrize(("weight", "delta_t"), [(1.0, 1.0), (5.0, 0.5)])
def test_smppi_matches_the_peer(weight: float, delta_t: float) -> None:
    # rate bounds are left out: pytorch-mppi 0.9.1 clamps the sampled rates but integrates
    # the unclamped ones, so its SMPPI u_min/u_max have no effect (test_smppi_bounds_the_rate)
    planner = ours(SMPPI, smoothness_weight=weight, delta_t=delta_t)
    reference = theirs(peer.mppi.SMPPI, w_action_seq_cost=weight, delta_t=delta_t)
    closed_loop(planner, reference)
    torch.testing.assert_close(planner.rate[0], reference.U, rtol=1e-9, atol=1e-9)


def test_smppi_change_horizon_matches_the_peer() -> None:
    planner, reference = ours(SMPPI), theirs(peer.mppi.SMPPI)
    current = {"H": H}

    def between(i: int) -> None:
        if i in (3, 6):
            new = 9 if i == 3 else 18
            planner.change_horizon(new)
            reference.change_horizon(new)
            current["H"] = new

    closed_loop(planner, reference, between=between, points=lambda: current["H"])


@pytest.mark.parametrize("support", [5, 7])
def test_kmppi_matches_the_peer(support: int) -> None:
    # the peer's RBF kernel divides by 2 sigma^2 + 1e-8
    width = math.sqrt(1.0 + 0.5e-8)
    planner = ours(KMPPI, num_support_points=support, kernel=rbf_kernel(width))
    reference = theirs(peer.mppi.KMPPI, num_support_pts=support)
    closed_loop(planner, reference, points=support)
    torch.testing.assert_close(planner.control_points[0], reference.theta, rtol=1e-9, atol=1e-9)
