"""Closed loop (scripts/arm_reach.py): the filtered planar arm reaches targets past a ball
obstacle without a collision sphere ever entering it."""

from __future__ import annotations

import importlib.util
import sys
from collections.abc import Iterator
from pathlib import Path
from types import ModuleType

import pytest
import torch

pytest.importorskip("pytorch_kinematics")

# joint nominal, 1,000 scenarios (seed 0, 300 steps): measured reach 0.976 (misses: 2.4% stopped
# in front of the obstacle although a roadmap path was found); asserted with a margin
JOINT_MIN_REACH = 0.95
SCRIPT = Path(__file__).resolve().parents[2] / "scripts" / "arm_reach.py"


@pytest.fixture(scope="module")
def arm_reach() -> Iterator[ModuleType]:
    """The example script as a module (its dataclass needs it in ``sys.modules``)."""
    spec = importlib.util.spec_from_file_location("arm_reach", SCRIPT)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules["arm_reach"] = module
    try:
        spec.loader.exec_module(module)
        yield module
    finally:
        sys.modules.pop("arm_reach", None)


def _backend() -> str:
    # proxsuite solves these small QPs fastest on CPU; the default backend otherwise
    return "proxsuite" if importlib.util.find_spec("proxsuite") else "torch"


def _check(result: dict, min_reach: float, max_non_solved: float = 0.0) -> None:
    # safety on the true geometry: every sphere, every step
    assert result["min_clearance"] >= -1e-6
    assert result["safe_rate"] == 1.0
    assert result["failed"] == 0
    assert result["non_solved_steps"] <= max_non_solved
    # reach rate: Cartesian nominal 0.70 (64 scenarios) to 0.713 (1,000), misses are
    # deadlocks at the obstacle or at a joint limit; joint nominal with waypoints: see
    # JOINT_MIN_REACH
    assert result["reach_rate"] >= min_reach
    reached = result["reached"]
    assert bool(reached.any())


def test_reach_past_obstacle_is_safe(arm_reach: ModuleType) -> None:
    """Cartesian resolved-rate nominal (target as a point)."""
    sc = arm_reach.build("planar3", 40, seed=1, qp_backend=_backend(), nominal="cartesian")
    # every start is collision-free and every target is away from the obstacle
    assert bool((sc.collision(sc.q0) > 0).all())
    result = arm_reach.run(sc, steps=200, dt=0.02)
    _check(result, min_reach=0.5)
    # the reached ones converge: final error well under the 2 cm tolerance
    err = (result["ee"][:, -1] - sc.target).norm(dim=-1)
    assert bool((err[result["reached"]] < 0.02).all())


def test_joint_nominal_reaches_target_configurations(arm_reach: ModuleType) -> None:
    """Joint-space CLF nominal along roadmap waypoints: safe, and reaches every target
    whose path was found (measured 40/40)."""
    sc = arm_reach.build("planar3", 40, seed=1, qp_backend=_backend(), nominal="joint")
    # the target configurations generate the target points and are valid with margin
    assert torch.allclose(sc.arm.end_effector(sc.q_target), sc.target, atol=1e-9)
    assert bool((sc.collision(sc.q_target) > 0.05).all())
    result = arm_reach.run(sc, steps=300, dt=0.02)
    _check(result, min_reach=0.9)
    assert result["missed_at_joint_limit"] == 0.0
    assert result["path_found_rate"] >= 0.9
    assert result["reach_rate_path_found"] >= 0.95
    # the final configuration is the target one (not another IK branch)
    q_err = (result["x"][:, -1] - sc.q_target).norm(dim=-1)
    assert bool((q_err[result["reached"]] < 0.02).all())


def test_roadmap_paths_are_clear(arm_reach: ModuleType) -> None:
    """Every planned waypoint path ends at the target configuration, starts near q0 and
    keeps its segments clear on a finer check (128 points per segment) than the planner's."""
    sc = arm_reach.build("planar3", 40, seed=2, nominal="joint")
    wps = sc.nominal.waypoints  # [B, W, dof]
    assert torch.equal(wps[:, -1], sc.q_target)
    # rows without a via go straight to the target
    assert bool((wps[~sc.has_via] == sc.q_target[~sc.has_via, None]).all())
    prev = sc.q0
    worst = torch.full_like(sc.q0[:, 0], float("inf"))
    for j in range(wps.shape[1]):
        s = torch.linspace(0, 1, 128, dtype=prev.dtype)[:, None, None]
        seg = prev + s * (wps[:, j] - prev)
        worst = torch.minimum(worst, sc.collision(seg).amin(-1).amin(0))
        prev = wps[:, j]
    found = sc.path_found
    assert bool(found.any())
    # the planner checks 3 cm at 32 points; between samples the clearance may dip a little
    assert float(worst[found].min()) > 0.0


def test_unfiltered_baseline_collides(arm_reach: ModuleType) -> None:
    """Without the filter the Cartesian nominal drives spheres into the obstacle (the test
    can fail): the safety comes from the filter."""
    sc = arm_reach.build("planar3", 40, seed=1, qp_backend=_backend(), nominal="cartesian")
    from torchcbf.sim import simulate

    with torch.no_grad():
        traj = simulate(sc.arm, sc.q0, 100, 0.02, nominal=sc.nominal, progress=False)
    assert float(sc.collision(traj.x).amin()) < -0.01


@pytest.mark.slow
def test_reach_1000_scenarios_joint(arm_reach: ModuleType) -> None:
    sc = arm_reach.build("planar3", 1000, seed=0, qp_backend=_backend(), nominal="joint")
    result = arm_reach.run(sc, steps=300, dt=0.02)
    # measured: 1 RELAXED/FALLBACK filter step of 300,000 (safety still held)
    _check(result, min_reach=JOINT_MIN_REACH, max_non_solved=1e-5)


@pytest.mark.slow
def test_reach_1000_scenarios_cartesian(arm_reach: ModuleType) -> None:
    sc = arm_reach.build("planar3", 1000, seed=0, qp_backend=_backend(), nominal="cartesian")
    result = arm_reach.run(sc, steps=300, dt=0.02)
    _check(result, min_reach=0.65)  # measured 0.713
