"""Batched inverse kinematics (torchcbf/dynamics/_ik.py): FK of the solution against the
target (hand-written planar FK for planar3), limits, obstacle clearance, batch against a
loop over rows, an analytic unreachable case, and the error paths."""

from __future__ import annotations

import pytest
import torch

pytest.importorskip("pytorch_kinematics")

from _arm_reference import planar_fk  # noqa: E402

from torchcbf.barriers.workspace import LinkSphereBarrier  # noqa: E402
from torchcbf.dynamics import IKResult, Manipulator  # noqa: E402

TOL = 1e-4  # the IK's default position tolerance (m)
# planar3 collision spheres and the ball obstacle of torchcbf.scenarios.arm_reach
SPHERES = (["link1", "link2", "link3", "ee"], [0.05, 0.05, 0.05, 0.04])
OBSTACLE = ((0.6, 0.45, 0.0), 0.15)


@pytest.fixture(scope="module")
def planar() -> Manipulator:
    return Manipulator("planar3")


@pytest.fixture(scope="module")
def arm7() -> Manipulator:
    return Manipulator("arm7")


def _spheres(arm: Manipulator) -> LinkSphereBarrier:
    return LinkSphereBarrier(arm, SPHERES[0], SPHERES[1], *OBSTACLE)


def _within_limits(arm: Manipulator, q: torch.Tensor, margin: float = 0.0) -> bool:
    lo, hi = arm.q_min.to(q) + margin, arm.q_max.to(q) - margin
    slack = 1e-6 if q.dtype == torch.float32 else 1e-12
    return bool(((q >= lo - slack) & (q <= hi + slack)).all())


def test_planar_ik_hits_targets(
    planar: Manipulator, dtype: torch.dtype, device: torch.device
) -> None:
    arm = planar.to(device)
    gen = torch.Generator(device=device).manual_seed(0)
    q_gen = arm.random_configurations(48, generator=gen, dtype=dtype, device=device)
    target = planar_fk(q_gen)[:, -1]  # hand-written FK: an independent reference
    res = arm.inverse_kinematics(target, restarts=4, limit_margin=0.02)
    assert isinstance(res, IKResult)
    q, ok, err = res
    assert q.shape == (48, 3) and q.dtype == dtype and q.device.type == device.type
    assert ok.dtype == torch.bool and bool(ok.all())
    hit = (planar_fk(q)[:, -1] - target).norm(dim=-1)
    slack = 2e-6 if dtype == torch.float32 else 1e-7  # FK rounding (float32 URDF origins)
    assert float(hit.max()) <= TOL + slack
    torch.testing.assert_close(err, hit, atol=slack, rtol=0)
    assert _within_limits(arm, q, 0.02)


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_arm7_ik_hits_targets(arm7: Manipulator, dtype: torch.dtype) -> None:
    gen = torch.Generator().manual_seed(1)
    q_gen = arm7.random_configurations(32, generator=gen, dtype=dtype)
    target = arm7.end_effector(q_gen)
    q, ok, err = arm7.inverse_kinematics(target, restarts=4, tol=1e-5, prefer="error")
    assert bool(ok.all())
    assert float((arm7.end_effector(q) - target).norm(dim=-1).max()) <= 1e-5 + 1e-7
    assert float(err.max()) <= 1e-5
    assert _within_limits(arm7, q)
    with pytest.raises(ValueError, match=r"target \[\.\.\., 2\] is for a planar arm"):
        arm7.inverse_kinematics(target[:, :2].to(dtype))


def test_obstacle_clearance(planar: Manipulator, dtype: torch.dtype) -> None:
    """With the sphere barriers every solution clears the obstacle by ``clearance``; the
    same targets without them give colliding solutions (so the test can fail)."""
    arm = planar.to(dtype)
    spheres = _spheres(arm).to(dtype)
    # targets beside the obstacle: many IK branches pass a link through it
    angle = torch.linspace(0.2, 1.2, 40, dtype=dtype)
    target = torch.stack([0.95 * angle.cos(), 0.95 * angle.sin(), 0 * angle], -1)
    target = target[(target - torch.tensor(OBSTACLE[0], dtype=dtype)).norm(dim=-1) > 0.25]
    q_plain, ok_plain, _ = arm.inverse_kinematics(target, restarts=8, prefer="error", seed=3)
    assert bool(ok_plain.all())
    assert float(spheres(q_plain).amin()) < 0  # some unconstrained solutions collide
    q, ok, err = arm.inverse_kinematics(
        target, restarts=8, barriers=[spheres], clearance=0.03, seed=3
    )
    assert bool(ok.all())
    assert float(spheres(q).amin()) >= 0.03
    assert float((planar_fk(q)[:, -1] - target).norm(dim=-1).max()) <= TOL + 1e-6
    assert float(err.max()) <= TOL


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_batch_equals_loop(planar: Manipulator, dtype: torch.dtype) -> None:
    """One deterministic start per row (``q_init``, no random restarts): the batched solve
    equals solving row by row."""
    arm = planar.to(dtype)
    spheres = _spheres(arm).to(dtype)
    gen = torch.Generator().manual_seed(4)
    target = arm.end_effector(arm.random_configurations(10, generator=gen, dtype=dtype))
    q_init = arm.random_configurations(10, generator=gen, dtype=dtype)
    kw = dict(restarts=1, iters=60, check_every=0, reseed_every=0, barriers=[spheres])
    q, ok, err = arm.inverse_kinematics(target, q_init, **kw)
    rows = [arm.inverse_kinematics(target[i], q_init[i], **kw) for i in range(10)]
    atol = 1e-9 if dtype == torch.float64 else 1e-4
    torch.testing.assert_close(q, torch.stack([r.q for r in rows]), atol=atol, rtol=0)
    assert torch.equal(ok, torch.stack([r.converged for r in rows]))
    torch.testing.assert_close(err, torch.stack([r.error for r in rows]), atol=atol, rtol=0)
    assert rows[0].q.shape == (3,) and rows[0].converged.shape == ()


def test_batch_shapes_and_planar_targets(planar: Manipulator) -> None:
    gen = torch.Generator().manual_seed(5)
    q_gen = planar.random_configurations(6, generator=gen, dtype=torch.float64)
    target = planar.end_effector(q_gen).reshape(2, 3, 3)
    q, ok, err = planar.inverse_kinematics(target, restarts=2)
    assert q.shape == (2, 3, 3) and ok.shape == (2, 3) and err.shape == (2, 3)
    assert bool(ok.all())
    # a 2-d target matches x, y only: a z offset in the 3-d version makes it unreachable
    xy = target[..., :2]
    q2, ok2, _ = planar.inverse_kinematics(xy, restarts=2)
    assert bool(ok2.all())
    lifted = target + torch.tensor([0.0, 0.0, 0.1], dtype=torch.float64)
    _, ok3, err3 = planar.inverse_kinematics(lifted, restarts=2)
    assert not bool(ok3.any())
    torch.testing.assert_close(err3, torch.full_like(err3, 0.1), atol=1e-6, rtol=0)


def test_unreachable_target_error_is_the_distance_to_the_workspace(planar: Manipulator) -> None:
    """A point beyond the stretched arm (1.2 m): not converged, and the best error is the
    analytic ``|p| - 1.2`` (the arm stretched toward it)."""
    target = torch.tensor([[2.0, 0.0, 0.0], [0.0, -1.5, 0.0]], dtype=torch.float64)
    q, ok, err = planar.inverse_kinematics(target, restarts=4, iters=200)
    assert not bool(ok.any())
    expected = torch.tensor([0.8, 0.3], dtype=torch.float64)
    torch.testing.assert_close(err, expected, atol=1e-6, rtol=0)
    torch.testing.assert_close(q[:, 1:], torch.zeros(2, 2, dtype=torch.float64), atol=1e-3, rtol=0)


def test_prefer_nearest_returns_the_initial_solution(planar: Manipulator) -> None:
    """``q_init`` already solves the target: "nearest" keeps it (other IK branches exist)."""
    gen = torch.Generator().manual_seed(6)
    q_gen = planar.random_configurations(16, generator=gen, dtype=torch.float64, margin=0.1)
    target = planar.end_effector(q_gen)
    q, ok, _ = planar.inverse_kinematics(target, q_gen, restarts=8)
    assert bool(ok.all())
    torch.testing.assert_close(q, q_gen, atol=1e-6, rtol=0)


def test_acceleration_control_arm(dtype: torch.dtype) -> None:
    arm = Manipulator("planar3", control="acceleration").to(dtype)
    spheres = _spheres(arm).to(dtype)
    target = torch.tensor([[0.3, 0.9, 0.0], [1.0, 0.1, 0.0]], dtype=dtype)
    q, ok, _ = arm.inverse_kinematics(target, barriers=[spheres], clearance=0.02)
    assert q.shape == (2, 3) and bool(ok.all())
    x = torch.cat([q, torch.zeros_like(q)], -1)
    assert float(spheres(x).amin()) >= 0.02


def test_errors(planar: Manipulator) -> None:
    t = torch.tensor([0.5, 0.5, 0.0], dtype=torch.float64)
    with pytest.raises(TypeError, match="target"):
        planar.inverse_kinematics([0.5, 0.5, 0.0])  # type: ignore[arg-type]
    with pytest.raises(TypeError, match="floating"):
        planar.inverse_kinematics(torch.tensor([1, 1, 0]))
    with pytest.raises(ValueError, match=r"target must have shape \[\.\.\., 3\]"):
        planar.inverse_kinematics(torch.zeros(4, dtype=torch.float64))
    with pytest.raises(ValueError, match="q_init must have shape"):
        planar.inverse_kinematics(t, torch.zeros(2, dtype=torch.float64))
    with pytest.raises(ValueError, match="do not broadcast"):
        planar.inverse_kinematics(t.expand(4, 3), torch.zeros(3, 3, dtype=torch.float64))
    with pytest.raises(ValueError, match="must broadcast to the target"):
        planar.inverse_kinematics(t, torch.zeros(2, 3, dtype=torch.float64))
    for kw, msg in [
        ({"restarts": 0}, "restarts"),
        ({"iters": 0}, "iters"),
        ({"check_every": -1}, "check_every"),
        ({"reseed_every": -1}, "reseed_every"),
        ({"prefer": "best"}, "prefer"),
        ({"tol": 0.0}, "tol"),
        ({"damping": -1.0}, "damping"),
        ({"limit_margin": 3.0}, "limit_margin"),
        ({"limit_margin": -1.0}, "limit_margin"),
    ]:
        with pytest.raises(ValueError, match=msg):
            planar.inverse_kinematics(t, **kw)  # type: ignore[arg-type]
    with pytest.raises(TypeError, match=r"barriers\[0\]"):
        planar.inverse_kinematics(t, barriers=[lambda x: x])  # type: ignore[list-item]
    nan = float("nan")
    with pytest.raises(ValueError, match="clearance must be a finite number"):
        planar.inverse_kinematics(t, clearance=nan)
    with pytest.raises(TypeError, match="check_every must be an int >= 0"):
        planar.inverse_kinematics(t, check_every=True)
    with pytest.raises(TypeError, match="seed must be an int"):
        planar.inverse_kinematics(t, seed=1.5)  # type: ignore[arg-type]


def test_a_start_that_is_not_finite_is_the_last_choice(planar: Manipulator) -> None:
    """A NaN start (a row's own trouble, reported per row as a NaN target is) never wins
    over the finite restarts, even where no restart reaches the target."""
    nan = float("nan")
    far = torch.tensor([[5.0, 5.0, 0.0], [0.5, 0.5, 0.0]], dtype=torch.float64)
    start = torch.tensor([[nan, 0.0, 0.0], [nan, 0.0, 0.0]], dtype=torch.float64)
    res = planar.inverse_kinematics(far, start, iters=50)
    assert bool(torch.isfinite(res.q).all()) and res.converged.tolist() == [False, True]


def test_a_locked_joint_and_a_start_that_is_not_finite() -> None:
    """A revolute joint whose <limit> gives no range (lower = upper = 0) keeps its value;
    a start with NaN entries starts from random values there, inside the limits."""
    urdf = (
        '<robot name="r"><link name="base"/><link name="l1"/><link name="l2"/>'
        '<link name="tip"/><joint name="j1" type="revolute"><parent link="base"/>'
        '<child link="l1"/><axis xyz="0 0 1"/>'
        '<limit lower="-2" upper="2" velocity="1" effort="1"/></joint>'
        '<joint name="j2" type="revolute"><parent link="l1"/><child link="l2"/>'
        '<origin xyz="0.5 0 0"/><axis xyz="0 0 1"/><limit velocity="1" effort="1"/></joint>'
        '<joint name="jt" type="fixed"><parent link="l2"/><child link="tip"/>'
        '<origin xyz="0.3 0 0"/></joint></robot>'
    )
    arm = Manipulator(urdf)
    target = arm.end_effector(torch.tensor([0.4, 0.0], dtype=torch.float64))
    out = arm.inverse_kinematics(target)
    assert bool(out.converged) and float(out.q[1]) == 0.0
    planar = Manipulator("planar3")
    goal = planar.end_effector(torch.tensor([0.3, -0.4, 0.2], dtype=torch.float64))
    start = torch.tensor([float("nan"), 0.0, 0.0], dtype=torch.float64)
    res = planar.inverse_kinematics(goal, q_init=start, restarts=1)
    assert bool(torch.isfinite(res.q).all())
    assert bool(((res.q >= planar.q_min) & (res.q <= planar.q_max)).all())


def test_barriers_under_inference_mode() -> None:
    """The barrier penalty's gradient is taken outside inference mode."""
    arm = Manipulator("planar3")
    wall = _spheres(arm)
    goal = arm.end_effector(torch.tensor([0.3, -0.4, 0.2], dtype=torch.float64))
    want = arm.inverse_kinematics(goal, barriers=[wall])
    with torch.inference_mode():
        got = arm.inverse_kinematics(goal, barriers=[wall])
    torch.testing.assert_close(got.q, want.q)
