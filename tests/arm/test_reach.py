"""Closed loop (torchcbf.scenarios.arm_reach): the filtered planar arm reaches targets past
a ball obstacle without a collision sphere ever entering it: point targets through IK,
roadmap and deadlock escape; target configurations; and the Cartesian resolved-rate
baseline."""

from __future__ import annotations

import dataclasses
import importlib.util

import pytest
import torch

pytest.importorskip("pytorch_kinematics")

from torchcbf.roadmap import Roadmap, RoadmapController  # noqa: E402
from torchcbf.scenarios import arm_reach  # noqa: E402

# 1,000 scenarios (seed 0, 300 steps), see the slow tests for the measured figures
JOINT_MIN_REACH = 0.99
IK_MIN_REACH = 0.99  # of the reachable targets
IK_MIN_REACH_FAST = 1.0  # 40 scenarios, seed 1
ARM7_MIN_REACH = 0.99
ESCAPE_MIN_DEADLOCKS_WITHOUT = 8  # measured 16 of 17
ESCAPE_MAX_DEADLOCKS_WITH = 0
ESCAPE_MIN_GAIN = 0.3  # measured 0.059 -> 0.529


def _backend() -> str:
    # proxsuite solves these small QPs fastest on CPU; the default backend otherwise
    return "proxsuite" if importlib.util.find_spec("proxsuite") else "torch"


def _check(result: dict, min_reach: float, max_non_solved: float = 0.0) -> None:
    # safety on the true geometry: every sphere, every step
    assert result["min_clearance"] >= -1e-6
    assert result["safe_rate"] == 1.0
    assert result["failed"] == 0
    assert result["non_solved_steps"] <= max_non_solved
    # reach rate: Cartesian nominal 0.694 (1,000 scenarios, seed 0), misses are
    # deadlocks at the obstacle or at a joint limit; joint nominal with waypoints: see
    # JOINT_MIN_REACH
    assert result["reach_rate"] >= min_reach
    reached = result["reached"]
    assert bool(reached.any())


@pytest.fixture(scope="module")
def ik_scenario() -> arm_reach.ArmReachScenario:
    """Point targets through the IK pipeline, 40 scenarios (seed 1), built once."""
    return arm_reach.build("planar3", 40, seed=1, qp_backend=_backend(), nominal="ik")


def test_reach_past_obstacle_is_safe() -> None:
    """Cartesian resolved-rate nominal (target as a point)."""
    sc = arm_reach.build(
        "planar3", 40, seed=1, qp_backend=_backend(), nominal="cartesian", plan_paths=False
    )
    # every start is collision-free and every target is away from the obstacle
    assert bool((sc.collision(sc.q0) > 0).all())
    result = arm_reach.run(sc, steps=200, dt=0.02)
    _check(result, min_reach=0.5)
    # the reached ones converge: final error well under the 2 cm tolerance
    err = (result["ee"][:, -1] - sc.target).norm(dim=-1)
    assert bool((err[result["reached"]] < 0.02).all())


@pytest.mark.slow
def test_joint_nominal_reaches_target_configurations() -> None:
    """Joint-space CLF nominal along roadmap paths toward the generating configurations:
    safe, and reaches every target (measured 24/24)."""
    sc = arm_reach.build("planar3", 24, seed=1, qp_backend=_backend(), nominal="joint")
    # the target configurations generate the target points and are valid with margin
    assert torch.allclose(sc.arm.end_effector(sc.q_target), sc.target, atol=1e-9)
    assert bool((sc.collision(sc.q_target) > 0.05).all())
    result = arm_reach.run(sc, steps=300, dt=0.02)
    _check(result, min_reach=1.0)
    # the final configuration is the target one (not another IK branch)
    q_err = (result["x"][:, -1] - sc.q_target).norm(dim=-1)
    assert bool((q_err[result["reached"]] < 0.02).all())


@pytest.mark.slow
def test_roadmap_paths_are_clear(ik_scenario: arm_reach.ArmReachScenario) -> None:
    """Every planned waypoint path ends at the goal configuration and keeps its segments
    clear on a finer check (128 points per segment) than the planner's; the controller's
    first waypoint is the path's."""
    sc = ik_scenario
    wps, has_via, found = sc.waypoints, sc.has_via, sc.path_found
    roadmap = sc.nominal.roadmap
    assert torch.equal(wps[:, -1], sc.q_goal)
    # rows without a via go straight to the goal; the controller's first waypoint agrees
    assert bool((wps[~has_via] == sc.q_goal[~has_via, None]).all())
    assert bool((roadmap.first[~has_via] == -1).all())
    assert torch.equal(roadmap.nodes[roadmap.first[has_via]], wps[has_via, 0])
    prev = sc.q0
    worst = torch.full_like(sc.q0[:, 0], float("inf"))
    for j in range(wps.shape[1]):
        s = torch.linspace(0, 1, 128, dtype=prev.dtype)[:, None, None]
        seg = prev + s * (wps[:, j] - prev)
        worst = torch.minimum(worst, sc.collision(seg).amin(-1).amin(0))
        prev = wps[:, j]
    assert bool(found.all()) and bool(has_via.any())
    # the planner checks 3 cm at 32 points; between samples the clearance may dip a little
    assert float(worst.min()) > 0.0


@pytest.mark.slow
def test_ik_goals_solve_the_point_targets(ik_scenario: arm_reach.ArmReachScenario) -> None:
    """The IK pipeline's goal configurations put the end effector on the target point,
    clear the obstacle by the path clearance and stay inside the joint limits."""
    sc = ik_scenario
    assert bool(sc.reachable.all())  # every target is reachable by construction
    err = (sc.arm.end_effector(sc.q_goal) - sc.target).norm(dim=-1)
    assert float(err.max()) < 1e-4
    assert float(sc.collision(sc.q_goal).amin()) >= 0.03
    lo, hi = sc.arm.q_min.to(sc.q_goal), sc.arm.q_max.to(sc.q_goal)
    assert bool(((sc.q_goal >= lo + 0.06 - 1e-9) & (sc.q_goal <= hi - 0.06 + 1e-9)).all())
    # "nearest to the start": typically nearer than the generating configuration
    near = (sc.q_goal - sc.q0).norm(dim=-1).median()
    assert float(near) < float((sc.q_target - sc.q0).norm(dim=-1).median())


@pytest.mark.slow
def test_ik_pipeline_reaches_point_targets(ik_scenario: arm_reach.ArmReachScenario) -> None:
    """Point targets through IK, roadmap and filter: safe, and every reachable target is
    reached (measured 40/40)."""
    result = arm_reach.run(ik_scenario, steps=300, dt=0.02)
    _check(result, min_reach=IK_MIN_REACH_FAST)
    assert result["reachable_rate"] == 1.0
    assert result["reach_rate_reachable"] >= IK_MIN_REACH_FAST
    assert result["missed_at_joint_limit"] == 0.0


def _via_rows(
    sc: arm_reach.ArmReachScenario,
) -> tuple[arm_reach.ArmReachScenario, Roadmap]:
    """The scenarios whose direct C-space segment is blocked, sent straight toward their
    goal configuration (no roadmap path: the first waypoint is the goal)."""
    rows = sc.has_via.nonzero()[:, 0]
    rm = sc.nominal.roadmap
    roadmap = dataclasses.replace(
        rm, to_target=rm.to_target[rows], exit=rm.exit[rows],
        cost_to_go=rm.cost_to_go[rows], first=torch.full_like(rm.first[rows], -1),
    )  # fmt: skip
    fields = ("q0", "target", "q_target", "q_goal", "reachable", "path_found", "has_via")
    sub = dataclasses.replace(sc, **{f: getattr(sc, f)[rows] for f in fields}, waypoints=None)
    return sub, roadmap


@pytest.mark.slow
def test_escape_resolves_deadlocks(ik_scenario: arm_reach.ArmReachScenario) -> None:
    """Rows sent straight toward their goal configuration where the straight C-space
    segment is blocked: without the escape the filter holds some of them in front of the
    obstacle (measured: 16 of 17 deadlocked, 1 reached); the re-planning escape frees every
    one of them (0 deadlocks, 9 reached within 300 steps, the rest still on their detour)."""
    sub, roadmap = _via_rows(ik_scenario)
    out = {}
    for escape in (False, True):
        ctrl = RoadmapController(sub.arm, roadmap, sub.collision, sub.q_goal, sub.q0, escape=escape)
        out[escape] = arm_reach.run(dataclasses.replace(sub, nominal=ctrl), steps=300)
        _check(out[escape], min_reach=0.0)
    stuck, freed = out[False], out[True]
    assert stuck["deadlocks"] >= ESCAPE_MIN_DEADLOCKS_WITHOUT
    assert freed["deadlocks"] <= ESCAPE_MAX_DEADLOCKS_WITH
    assert freed["reach_rate"] >= stuck["reach_rate"] + ESCAPE_MIN_GAIN
    assert freed["rows_replanned"] > 0 and stuck["rows_replanned"] == 0


def test_unfiltered_baseline_collides() -> None:
    """Without the filter the Cartesian nominal drives spheres into the obstacle (the test
    can fail): the safety comes from the filter."""
    sc = arm_reach.build(
        "planar3", 40, seed=1, qp_backend=_backend(), nominal="cartesian", plan_paths=False
    )
    from torchcbf.sim import simulate

    with torch.no_grad():
        traj = simulate(sc.arm, sc.q0, 100, 0.02, nominal=sc.nominal, progress=False)
    assert float(sc.collision(traj.x).amin()) < -0.01


@pytest.mark.slow
def test_reach_1000_scenarios_ik() -> None:
    """Point targets: 1,000 random targets and starts."""
    sc = arm_reach.build("planar3", 1000, seed=0, qp_backend=_backend(), nominal="ik")
    result = arm_reach.run(sc, steps=300, dt=0.02)
    _check(result, min_reach=IK_MIN_REACH, max_non_solved=1e-5)
    assert result["reachable_rate"] == 1.0
    assert result["reach_rate_reachable"] >= IK_MIN_REACH


@pytest.mark.slow
def test_reach_200_scenarios_ik_arm7() -> None:
    sc = arm_reach.build("arm7", 200, seed=0, qp_backend=_backend(), nominal="ik")
    result = arm_reach.run(sc, steps=300, dt=0.02)
    _check(result, min_reach=ARM7_MIN_REACH, max_non_solved=1e-4)
    assert result["reachable_rate"] == 1.0


@pytest.mark.slow
def test_reach_1000_scenarios_joint() -> None:
    sc = arm_reach.build("planar3", 1000, seed=0, qp_backend=_backend(), nominal="joint")
    result = arm_reach.run(sc, steps=300, dt=0.02)
    _check(result, min_reach=JOINT_MIN_REACH, max_non_solved=1e-5)


@pytest.mark.slow
def test_reach_1000_scenarios_cartesian() -> None:
    sc = arm_reach.build(
        "planar3", 1000, seed=0, qp_backend=_backend(), nominal="cartesian", plan_paths=False
    )
    result = arm_reach.run(sc, steps=300, dt=0.02)
    _check(result, min_reach=0.65)  # measured 0.694


def test_roadmap_helpers_take_a_barrier_with_one_output() -> None:
    """A barrier giving ``[...]`` (a point barrier around one ball): the helpers reduce over
    its outputs, not over the batch (they returned [5, 20, 3] configurations and one
    clearance for two segments)."""
    from torchcbf.barriers import Ball, PointBarrier
    from torchcbf.dynamics import Manipulator
    from torchcbf.roadmap import sample_free_configurations, segment_clearance

    f64 = torch.float64
    arm = Manipulator("planar3")
    point = PointBarrier(arm, Ball([0.6, 0.0, 0.0], 0.3, index=(0, 1, 2))).double()
    gen = torch.Generator().manual_seed(0)
    q = sample_free_configurations(arm, point, 5, 0.0, gen, f64, torch.device("cpu"))
    assert q.shape == (5, 3) and bool((point(q) > 0).all())
    qa = torch.tensor([[0.0, 0.0, 0.0], [1.5, 0.0, 0.0]], dtype=f64)
    qb = torch.tensor([[0.0, 2.0, 0.0], [1.6, 0.0, 0.0]], dtype=f64)
    both = segment_clearance(point, qa, qb)
    one = [segment_clearance(lambda z: point(z)[..., None], qa[i : i + 1], qb[i : i + 1])
           for i in range(2)]  # fmt: skip
    torch.testing.assert_close(both, torch.cat(one))


def test_roadmap_inputs_are_checked(ik_scenario: arm_reach.ArmReachScenario) -> None:
    from torchcbf.dynamics import Manipulator
    from torchcbf.roadmap import roadmap_paths, segment_clearance

    sc = ik_scenario
    q0, qt, gen = sc.q0[:2], sc.q_goal[:2], torch.Generator().manual_seed(0)
    dof = sc.arm.dof
    with pytest.raises(ValueError, match="samples must be an int >= 2"):
        segment_clearance(sc.collision, q0, qt, samples=1)
    for bad, message in (
        ((q0[0], qt[0]), rf"q0 must have shape \[B, {dof}\]"),
        ((q0, qt[:1]), "must have the same shape"),
        ((q0[:, :2], qt), rf"q0 must have shape \[B, {dof}\]"),
    ):
        with pytest.raises(ValueError, match=message):
            roadmap_paths(sc.arm, sc.collision, *bad, 0.03, gen)
    with pytest.raises(ValueError, match="nodes must be a positive int"):
        roadmap_paths(sc.arm, sc.collision, q0, qt, 0.03, gen, nodes=0)
    with pytest.raises(ValueError, match="clearance must be a finite number"):
        roadmap_paths(sc.arm, sc.collision, q0, qt, float("nan"), gen)
    none = q0[:0]
    waypoints, found, _, _ = roadmap_paths(sc.arm, sc.collision, none, none, 0.03, gen, nodes=8)
    assert waypoints.shape[0] == 0 and waypoints.shape[-1] == dof and found.shape == (0,)
    accel = Manipulator("planar3", control="acceleration")
    with pytest.raises(ValueError, match="needs an arm with control='velocity'"):
        RoadmapController(accel, sc.nominal.roadmap, sc.collision, sc.q_goal, sc.q0)


def test_a_rows_problem_is_its_seeds_whatever_the_batch_and_dtype() -> None:
    """Row ``i`` is drawn from seed ``seed + i`` alone, in float64: the first rows of a
    larger batch, and the same rows in float32, are the same starts and targets."""
    kw = {"seed": 3, "nominal": "cartesian", "plan_paths": False}
    two = arm_reach.build("planar3", 2, **kw)
    four = arm_reach.build("planar3", 4, **kw)
    single = arm_reach.build("planar3", 32, **kw, dtype=torch.float32)
    assert torch.equal(two.q0, four.q0[:2]) and torch.equal(two.target, four.target[:2])
    torch.testing.assert_close(single.q0[:2], two.q0.float())
    torch.testing.assert_close(single.target[:2], two.target.float())
    late = arm_reach.build("planar3", 1, **{**kw, "seed": 4})
    assert torch.equal(late.q0, four.q0[1:2])
