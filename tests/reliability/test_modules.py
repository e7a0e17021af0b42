"""Bad arguments to the remaining public modules (composition, neural barriers, rectify,
Lyapunov functions, sensors, learning helpers, arms and the roadmap) raise an error naming
the argument."""

from __future__ import annotations

import math

import pytest
import torch
from torch import nn

from torchcbf import (
    Ball,
    DoubleIntegrator,
    GaussianSensor,
    Intersection,
    MovingBall,
    NeuralBarrier,
    QuadraticLyapunov,
    SingleIntegrator,
    Union,
    rectify,
)
from torchcbf.estimation import FunctionSensor, RangeBearing
from torchcbf.learning import MLP, classification_loss, closed_loop_loss, uniform_box

CASES = [
    (lambda: Union(1, 2), TypeError, r"barriers\[0\] must be a Barrier"),
    (
        lambda: Intersection(
            Ball([0.0, 0.0], 1.0), Ball([1.0, 0.0], 1.0), smooth=True, temperature=math.nan
        ),
        ValueError,
        "temperature",
    ),  # fmt: skip
    (
        lambda: MovingBall(lambda t: torch.zeros(*t.shape, 3), 1.0)(torch.zeros(4, 2), 0.0),
        ValueError,
        r"trajectory must return centres \[\.\.\., 2\]",
    ),
    (lambda: NeuralBarrier(lambda x: x), TypeError, "net must be an nn.Module"),
    (lambda: NeuralBarrier(nn.Linear(2, 1), offset=3.0), TypeError, "offset"),
    (
        lambda: rectify(Ball([2.0, 0.0], 0.5), DoubleIntegrator(2), form="foo"),
        ValueError,
        "form must be",
    ),
    (
        lambda: rectify(Ball([2.0, 0.0], 0.5), DoubleIntegrator(2), gains=-1.0),
        ValueError,
        "gains must be positive",
    ),
    (
        lambda: QuadraticLyapunov([0.0, 0.0]).lie(torch.zeros(3, 5), SingleIntegrator(2)),
        ValueError,
        r"x must have shape \[\.\.\., 2\]",
    ),
    (
        lambda: GaussianSensor(std=0.1, state_dim=2).measure(torch.zeros(3, 2)),
        ValueError,
        "generator= or noise=",
    ),
    (
        lambda: GaussianSensor(std=0.1, state_dim=2).expected(torch.zeros(3, 3)),
        ValueError,
        r"x must have shape \[\.\.\., 2\]",
    ),
    (
        lambda: GaussianSensor(std=0.1, state_dim=2).measure(
            torch.zeros(3, 2), noise=torch.zeros(3, 2).double()
        ),
        TypeError,
        "noise has dtype torch.float64",
    ),  # fmt: skip
    (
        lambda: RangeBearing([[1.0, 0.0]], 0.1, 0.1).expected(torch.zeros(3, 2)),
        ValueError,
        r"x must have shape \[\.\.\., n\] with n > 2",
    ),
    (
        lambda: FunctionSensor(lambda x: x, std=[0.1], output_dim=1).expected(torch.zeros(3, 2)),
        ValueError,
        r"fn\(x\) must return \[\.\.\., 1\]",
    ),
    (
        lambda: classification_loss(torch.zeros(4), torch.zeros(5, dtype=torch.bool)),
        ValueError,
        "h and safe must have the same shape",
    ),
    (
        lambda: closed_loop_loss(
            type(
                "T",
                (),
                {"x": torch.zeros(2, 3), "u": torch.zeros(2, 2, 2), "u_nom": torch.zeros(2, 2, 2)},
            )()
        ),
        ValueError,
        "trajectory must hold",
    ),  # fmt: skip
    (lambda: uniform_box([1.0, 1.0], [0.0, 0.0], 10), ValueError, "high must exceed low"),
    (lambda: uniform_box([math.nan, 0.0], [1.0, 1.0], 10), ValueError, "low must not contain"),
    (lambda: uniform_box([0.0, 0.0], [1.0, 1.0], 0), ValueError, "num"),
    (lambda: MLP(2, low=[-1.0, -1.0, -1.0], high=1.0), ValueError, r"low must .* in_dim = 2"),
]


@pytest.mark.parametrize(
    "build, error, pattern", CASES, ids=[f"{i}-{c[2][:30]}" for i, c in enumerate(CASES)]
)
def test_bad_argument_is_named(build, error, pattern):
    with pytest.raises(error, match=pattern):
        build()


def test_arm_and_roadmap_arguments():
    pytest.importorskip("pytorch_kinematics")
    from torchcbf.barriers import JointLimitBarrier, LinkSphereBarrier
    from torchcbf.dynamics import Manipulator
    from torchcbf.roadmap import sample_free_configurations, segment_clearance

    with pytest.raises(ValueError, match="urdf 'nope' is neither"):
        Manipulator("nope")
    with pytest.raises(ValueError, match="control must be"):
        Manipulator("planar3", control="torque")
    arm = Manipulator("planar3")
    with pytest.raises(ValueError, match=r"unknown links \['nolink'\]"):
        LinkSphereBarrier(arm, ["nolink"], 0.1, [0.0, 0.0, 0.0], 0.1)
    with pytest.raises(ValueError, match="obstacle_center must not contain NaN"):
        LinkSphereBarrier(arm, ["link2"], 0.1, [math.nan, 0.0, 0.0], 0.1)
    with pytest.raises(ValueError, match="margin must be .*finite"):
        JointLimitBarrier(arm, margin=math.inf)
    # the obstacle covers the whole workspace: rejection sampling gives up with a clear error
    blocked = LinkSphereBarrier(arm, ["link1"], 0.05, [0.0, 0.0, 0.0], 5.0)
    gen = torch.Generator().manual_seed(0)
    with pytest.raises(RuntimeError, match="lower the clearance"):
        sample_free_configurations(
            arm, blocked, 4, 0.0, gen, torch.float64, torch.device("cpu"), max_rounds=3
        )
    q = torch.zeros(2, 3, dtype=torch.float64)
    clear = LinkSphereBarrier(arm, ["link1"], 0.05, [5.0, 5.0, 0.0], 0.1).double()
    assert segment_clearance(clear, q, q + 0.1).shape == (2,)
    # an IK target with NaN is reported per row (not converged), the other rows solve
    target = torch.tensor([[math.nan, 0.5, 0.0], [0.5, 0.5, 0.0]], dtype=torch.float64)
    res = arm.double().inverse_kinematics(target, iters=50)
    assert res.converged.tolist() == [False, True]
