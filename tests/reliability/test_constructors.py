"""Constructors of the public API reject what can never work (NaN, inf, inverted bounds,
non-positive sizes, wrong shapes) with an error naming the argument."""

from __future__ import annotations

import math

import pytest
import torch

from torchcbf import (
    EKF,
    MPPI,
    UKF,
    Ball,
    Bicycle,
    Box,
    DoubleIntegrator,
    Ellipse,
    GaussianSensor,
    HalfSpace,
    MovingBall,
    QuadraticLyapunov,
    Quadrotor,
    SafetyFilter,
    SingleIntegrator,
    VanDerPol,
)
from torchcbf.estimation import FunctionSensor, RangeBearing

NAN, INF = math.nan, math.inf

CASES = [
    # (builder, exception, pattern naming the argument)
    (lambda: Ball([NAN, 0.0], 1.0), ValueError, "center"),
    (lambda: Ball([INF, 0.0], 1.0), ValueError, "center"),
    (lambda: Ball([0.0, 0.0], NAN), ValueError, "radius"),
    (lambda: Ball([0.0, 0.0], INF), ValueError, "radius"),
    (lambda: Ball([0.0, 0.0], -1.0), ValueError, "radius"),
    (lambda: Ball([0.0, 0.0], 1.0, velocity=[NAN, 0.0]), ValueError, "velocity"),
    (lambda: Ball([0.0, 0.0], 1.0, velocity=[1.0]), ValueError, "velocity"),
    (lambda: Ball([[0.0, 0.0]], [1.0, 2.0]), ValueError, "radius"),
    (lambda: Ball([0.0, 0.0], 1.0, index=(0, 5), state_dim=3), ValueError, "index"),
    (lambda: MovingBall(lambda t: t, NAN), ValueError, "radius"),
    (lambda: MovingBall(3.0, 1.0), TypeError, "trajectory"),
    (lambda: Ellipse([0.0, 0.0], [1.0, NAN]), ValueError, "axes"),
    (lambda: Ellipse([0.0, 0.0], [1.0, 0.0]), ValueError, "axes"),
    (lambda: Ellipse([0.0, 0.0], [1.0, 1.0], angle=NAN), ValueError, "angle"),
    (lambda: Ellipse([0.0, 0.0], [1.0]), ValueError, "axes"),
    (lambda: HalfSpace([NAN, 1.0], 0.0), ValueError, r"\ba\b"),
    (lambda: HalfSpace([1.0, 0.0], INF), ValueError, r"\bb\b"),
    (lambda: HalfSpace([0.0, 0.0], 1.0), ValueError, r"\ba\b"),
    (lambda: Box([NAN, 0.0], [1.0, 1.0]), ValueError, "low"),
    (lambda: Box([0.0, 0.0], [1.0, NAN]), ValueError, "high"),
    (lambda: Box([0.0, 2.0], [1.0, 1.0]), ValueError, "low .* below high"),
    (lambda: Box([0.0, 0.0], [1.0, 1.0, 1.0]), ValueError, "low and high"),
    (lambda: Box([0.0, 0.0], [1.0, 1.0], smooth=True, temperature=0.0), ValueError, "temperature"),
    (lambda: Box([0.0, 0.0], [1.0, 1.0], temperature=INF), ValueError, "temperature"),
    (lambda: QuadraticLyapunov([NAN, 0.0]), ValueError, "goal"),
    (
        lambda: QuadraticLyapunov([0.0, 0.0], torch.tensor([[1.0, 0.0], [0.0, NAN]])),
        ValueError,
        "P",
    ),
    (lambda: QuadraticLyapunov([0.0, 0.0], -torch.eye(2)), ValueError, "P"),
    # dynamics
    (lambda: SingleIntegrator(0), ValueError, "state_dim"),
    (lambda: SingleIntegrator(2, u_min=1.0, u_max=-1.0), ValueError, "u_min .* exceeds u_max"),
    (lambda: SingleIntegrator(2, u_min=[-1.0, 2.0], u_max=1.0), ValueError, "u_min.*u_max"),
    (lambda: SingleIntegrator(2, u_min=NAN), ValueError, "u_min"),
    (lambda: SingleIntegrator(2, u_max=[1.0, NAN]), ValueError, "u_max"),
    (lambda: SingleIntegrator(2, u_max=[1.0, 1.0, 1.0]), ValueError, "u_max"),
    (lambda: SingleIntegrator(2, sigma=NAN), ValueError, "sigma"),
    (lambda: SingleIntegrator(2, sigma=[1.0, 1.0, 1.0]), ValueError, "sigma"),
    (lambda: SingleIntegrator(2, disturbance_bound=NAN), ValueError, "disturbance_bound"),
    (lambda: SingleIntegrator(2, disturbance_bound=INF), ValueError, "disturbance_bound"),
    (lambda: SingleIntegrator(2, disturbance_bound=-1.0), ValueError, "disturbance_bound"),
    (
        lambda: SingleIntegrator(2, disturbance_matrix=torch.full((2, 2), NAN)),
        ValueError,
        "disturbance_matrix",
    ),
    (lambda: VanDerPol(mu=NAN), ValueError, "mu"),
    (lambda: VanDerPol(mu=[1.0, 2.0]), ValueError, "mu"),
    (lambda: Bicycle(wheelbase=0.0), ValueError, "wheelbase"),
    (lambda: Bicycle(wheelbase=NAN), ValueError, "wheelbase"),
    (lambda: Quadrotor(mass=-1.0), ValueError, "mass"),
    (lambda: Quadrotor(inertia=(0.01, 0.0, 0.02)), ValueError, "inertia"),
    (lambda: Quadrotor(inertia=(0.01, 0.02)), ValueError, "inertia"),
    (lambda: Quadrotor(gravity=INF), ValueError, "gravity"),
    # sensors and estimators
    (lambda: GaussianSensor(std=NAN, state_dim=2), ValueError, "std"),
    (lambda: GaussianSensor(std=0.0, state_dim=2), ValueError, "std"),
    (lambda: GaussianSensor(std=[0.1, -0.1]), ValueError, "std"),
    (lambda: GaussianSensor(R=torch.tensor([[1.0, 0.0], [0.0, NAN]])), ValueError, "R"),
    (lambda: GaussianSensor(R=-torch.eye(2)), ValueError, "R"),
    (lambda: GaussianSensor(C=torch.tensor([[NAN, 1.0]]), std=0.1), ValueError, "C"),
    (lambda: GaussianSensor(std=0.1), ValueError, "state_dim"),
    (lambda: GaussianSensor(std=0.1, R=torch.eye(2)), ValueError, "std"),
    (lambda: FunctionSensor(lambda x: x, std=[NAN, 0.1]), ValueError, "std"),
    (lambda: FunctionSensor(3.0, std=0.1, output_dim=1), TypeError, "fn"),
    (lambda: RangeBearing([[NAN, 0.0]], 0.1, 0.1), ValueError, "landmarks"),
    (lambda: RangeBearing([[1.0, 0.0]], 0.0, 0.1), ValueError, "std_range"),
    (lambda: RangeBearing([[1.0, 0.0]], 0.1, INF), ValueError, "std_bearing"),
    (
        lambda: EKF(SingleIntegrator(2), GaussianSensor(std=0.1, state_dim=2), Q=NAN),
        ValueError,
        "Q",
    ),
    (
        lambda: EKF(SingleIntegrator(2), GaussianSensor(std=0.1, state_dim=2), Q=-1.0),
        ValueError,
        "Q",
    ),
    (lambda: EKF(SingleIntegrator(2), GaussianSensor(std=0.1, state_dim=2)), ValueError, "Q"),
    (
        lambda: EKF(SingleIntegrator(2), GaussianSensor(std=0.1, state_dim=2), Q=0.1, R=NAN),
        ValueError,
        "R",
    ),
    (
        lambda: UKF(SingleIntegrator(2), GaussianSensor(std=0.1, state_dim=2), Q=0.1, alpha=0.0),
        ValueError,
        "alpha",
    ),
    (
        lambda: EKF(SingleIntegrator(2), GaussianSensor(std=0.1, state_dim=3), Q=0.1),
        ValueError,
        "sensor",
    ),
    (lambda: EKF("model", GaussianSensor(std=0.1, state_dim=2), Q=0.1), TypeError, "dynamics"),
    (
        lambda: EKF(SingleIntegrator(2), GaussianSensor(std=0.1, state_dim=2), Q=0.1, substeps=0),
        ValueError,
        "substeps",
    ),
    # filter and planner (their own validation)
    (
        lambda: SafetyFilter(SingleIntegrator(2), [Ball([0.0, 0.0], 1.0)], mode="bogus"),
        ValueError,
        "mode",
    ),  # fmt: skip
    (lambda: SafetyFilter("model", [Ball([0.0, 0.0], 1.0)]), TypeError, "dynamics"),
    (
        lambda: MPPI(
            SingleIntegrator(2),
            lambda s, u, t: s.sum((-1, -2)),
            horizon=0,
            num_samples=8,
            dt=0.1,
            noise_sigma=1.0,
            temperature=1.0,
        ),
        ValueError,
        "horizon",
    ),  # fmt: skip
    (
        lambda: MPPI(
            SingleIntegrator(2),
            lambda s, u, t: s.sum((-1, -2)),
            horizon=5,
            num_samples=8,
            dt=0.1,
            noise_sigma=NAN,
            temperature=1.0,
        ),
        ValueError,
        "noise_sigma",
    ),  # fmt: skip
    (
        lambda: MPPI(
            SingleIntegrator(2),
            lambda s, u, t: s.sum((-1, -2)),
            horizon=5,
            num_samples=8,
            dt=0.1,
            noise_sigma=1.0,
            temperature=0.0,
        ),
        ValueError,
        "temperature",
    ),  # fmt: skip
    (
        lambda: MPPI(
            DoubleIntegrator(2),
            lambda s, u, t: s.sum((-1, -2)),
            horizon=5,
            num_samples=0,
            dt=0.1,
            noise_sigma=1.0,
            temperature=1.0,
        ),
        ValueError,
        "num_samples",
    ),  # fmt: skip
]


@pytest.mark.parametrize(
    "build, error, pattern", CASES, ids=[f"{i}-{c[2]}" for i, c in enumerate(CASES)]
)
def test_constructor_rejects_bad_argument(build, error, pattern):
    with pytest.raises(error, match=pattern):
        build()
