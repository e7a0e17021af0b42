"""Manipulator: URDF parsing, limits, FK against hand-written planar kinematics, Jacobians
against finite differences, batching, dtype/device, and the optional-dependency error."""

from __future__ import annotations

import math
import subprocess
import sys
from pathlib import Path

import pytest
import torch

pytest.importorskip("pytorch_kinematics")

from _arm_reference import LENGTHS, fd_jacobian, planar_fk  # noqa: E402
from _devices import device_matches_cpu  # noqa: E402

from torchcbf.dynamics.manipulator import (  # noqa: E402
    JointSpaceController,
    Manipulator,
    ResolvedRateController,
    asset_path,
)


def _tol(dtype: torch.dtype) -> float:
    # pytorch-kinematics parses URDF origins in float32: ~1e-8 m even in float64.
    return 1e-6 if dtype == torch.float64 else 2e-5


def planar_jacobian(q: torch.Tensor) -> torch.Tensor:
    """Hand-written planar end-effector Jacobian ``[..., 3, 3]``."""
    angles = torch.cumsum(q, -1)
    cols = []
    for j in range(3):
        dx = sum(-LENGTHS[i] * torch.sin(angles[..., i]) for i in range(j, 3))
        dy = sum(LENGTHS[i] * torch.cos(angles[..., i]) for i in range(j, 3))
        cols.append(torch.stack([dx, dy, torch.zeros_like(dx)], -1))
    return torch.stack(cols, -1)


@pytest.fixture(scope="module")
def planar() -> Manipulator:
    return Manipulator.from_urdf("planar3")


@pytest.fixture(scope="module")
def arm7() -> Manipulator:
    return Manipulator.from_urdf(asset_path("arm7"), "ee")


def test_assets_and_limits(planar: Manipulator, arm7: Manipulator) -> None:
    assert asset_path("planar3").is_file() and asset_path("arm7.urdf").is_file()
    with pytest.raises(ValueError, match="planar3"):
        asset_path("nope")
    assert planar.dof == 3 and planar.state_dim == 3 and planar.control_dim == 3
    assert planar.joint_names == ["joint1", "joint2", "joint3"]
    assert planar.links == ["link1", "link2", "link3", "ee"]
    torch.testing.assert_close(planar.q_min, torch.tensor([-3.0, -2.6, -2.6], dtype=torch.float64))
    torch.testing.assert_close(planar.q_max, torch.tensor([3.0, 2.6, 2.6], dtype=torch.float64))
    torch.testing.assert_close(planar.u_max, torch.tensor([1.5, 2.0, 2.5], dtype=torch.float64))
    torch.testing.assert_close(planar.u_min, -planar.u_max)
    torch.testing.assert_close(planar.effort_limit, torch.tensor([20.0, 12.0, 6.0]).double())
    assert arm7.dof == 7 and len(arm7.links) == 8
    acc = Manipulator("arm7", control="acceleration", accel_limit=4.0)
    assert acc.state_dim == 14 and acc.control_dim == 7
    torch.testing.assert_close(acc.u_max, torch.full((7,), 4.0, dtype=torch.float64))
    torch.testing.assert_close(acc.velocity_limit, arm7.velocity_limit)
    assert Manipulator("arm7", control="acceleration").u_max is None
    # user limits override the URDF's
    assert float(Manipulator("planar3", u_min=-0.5, u_max=0.5).u_max[0]) == 0.5


def test_sources_and_errors(tmp_path: Path) -> None:
    text = asset_path("planar3").read_text()
    for src in (text, text.encode(), asset_path("planar3"), str(asset_path("planar3"))):
        assert Manipulator(src).dof == 3
    with pytest.raises(ValueError, match="control"):
        Manipulator("planar3", control="torque")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="neither"):
        Manipulator(str(tmp_path / "missing.urdf"))
    with pytest.raises(TypeError, match="urdf"):
        Manipulator(3)  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="unknown links"):
        Manipulator("planar3", links=["link9"])
    # a branching tree needs end_link
    branched = text.replace(
        "</robot>",
        '<link name="tool"/><joint name="tj" type="fixed"><parent link="link2"/>'
        '<child link="tool"/></joint></robot>',
    )
    with pytest.raises(ValueError, match="end_link"):
        Manipulator(branched)
    assert Manipulator(branched, end_link="tool").dof == 2
    arm = Manipulator("planar3")
    with pytest.raises(ValueError, match=r"\[\.\.\., 3\]"):
        arm.fk(torch.zeros(4, 5))
    with pytest.raises(ValueError, match="offsets"):
        arm.fk(torch.zeros(3), ["ee"], torch.zeros(2, 3))


def test_planar_fk_matches_hand_written(
    planar: Manipulator, dtype: torch.dtype, device: torch.device
) -> None:
    gen = torch.Generator(device=device).manual_seed(0)
    q = planar.random_configurations(64, generator=gen, dtype=dtype, device=device)
    p = planar.fk(q)
    assert p.shape == (64, 4, 3) and p.dtype == dtype and p.device.type == device.type
    torch.testing.assert_close(p, planar_fk(q), atol=_tol(dtype), rtol=0)
    torch.testing.assert_close(
        planar.end_effector(q), planar_fk(q)[:, -1], atol=_tol(dtype), rtol=0
    )
    torch.testing.assert_close(planar.jacobian(q), planar_jacobian(q), atol=_tol(dtype), rtol=0)
    # a point offset in the link frame: 0.2 m along link2 is 0.2/0.4 of the way to link3
    mid = planar.fk(q, ["link2"], torch.tensor([[0.2, 0.0, 0.0]], dtype=dtype, device=device))
    ref = planar_fk(q)
    torch.testing.assert_close(mid[:, 0], 0.5 * (ref[:, 1] + ref[:, 2]), atol=_tol(dtype), rtol=0)


@pytest.mark.parametrize("name", ["planar3", "arm7"])
def test_jacobian_matches_finite_differences(name: str) -> None:
    arm = Manipulator(name)
    gen = torch.Generator().manual_seed(1)
    q = arm.random_configurations(16, generator=gen, dtype=torch.float64)
    J = arm.jacobian(q)
    J_fd = fd_jacobian(arm.end_effector, q)
    ee, J2 = arm.end_effector_and_jacobian(q)
    torch.testing.assert_close(ee, arm.end_effector(q))
    torch.testing.assert_close(J2, J)
    torch.testing.assert_close(J, J_fd, atol=1e-7, rtol=0)
    # autograd through pytorch-kinematics agrees too (every link, batched): rows are
    # independent, so the gradient of a column sum is every row's gradient.
    qr = q.clone().requires_grad_()
    p = arm.fk(qr).flatten(-2)  # [B, 3L]
    Ja = torch.stack(
        [torch.autograd.grad(p[:, c].sum(), qr, retain_graph=True)[0] for c in range(p.shape[1])], 1
    )
    Jfd_all = fd_jacobian(lambda qq: arm.fk(qq).flatten(-2), q)
    torch.testing.assert_close(Ja, Jfd_all, atol=1e-7, rtol=0)


@pytest.mark.parametrize("name", ["planar3", "arm7"])
def test_batch_equals_loop(name: str, dtype: torch.dtype) -> None:
    arm = Manipulator(name)
    gen = torch.Generator().manual_seed(2)
    q = arm.random_configurations(12, generator=gen, dtype=dtype).reshape(3, 4, arm.dof)
    batched = arm.fk(q)
    assert batched.shape == (3, 4, len(arm.links), 3)
    loop = torch.stack([torch.stack([arm.fk(q[i, j]) for j in range(4)]) for i in range(3)])
    assert arm.fk(q[0, 0]).shape == (len(arm.links), 3)
    torch.testing.assert_close(
        batched, loop, atol=1e-12 if dtype == torch.float64 else 1e-6, rtol=0
    )
    J = arm.jacobian(q)
    assert J.shape == (3, 4, 3, arm.dof)
    torch.testing.assert_close(J[1, 2], arm.jacobian(q[1, 2]))


def test_dtype_device_and_module_to(planar: Manipulator) -> None:
    arm = Manipulator("planar3")
    q32 = torch.tensor([0.3, -0.2, 0.5])
    q64 = q32.double()
    assert arm.fk(q32).dtype == torch.float32 and arm.fk(q64).dtype == torch.float64
    assert set(arm._chains) == {
        (torch.float32, torch.device("cpu")),
        (torch.float64, torch.device("cpu")),
    }
    arm.to(torch.float32)
    assert arm.u_max.dtype == torch.float32 and arm.q_min.dtype == torch.float32
    torch.testing.assert_close(arm.fk(q64), planar_fk(q64), atol=1e-6, rtol=0)
    # the chain cache is per instance: another arm is unaffected
    assert (torch.float32, torch.device("cpu")) not in Manipulator("planar3")._chains


@pytest.mark.parametrize("name", ["planar3", "arm7"])
def test_device_answers_equal_cpu_answers(name: str, dtype: torch.dtype, device) -> None:
    """Forward kinematics, the end effector and its Jacobian on a device module give the
    CPU's answers (and the hand-written planar kinematics)."""
    gen = torch.Generator().manual_seed(4)
    q = Manipulator(name).random_configurations(32, generator=gen, dtype=torch.float64)

    def run(dev: torch.device):
        arm = Manipulator(name).to(dev)
        qd = q.to(device=dev, dtype=dtype)
        ee, J = arm.end_effector_and_jacobian(qd)
        return arm.fk(qd), ee, J

    fk, _, J = device_matches_cpu(run, device, dtype, rtol=0, atol=_tol(dtype))
    assert fk.dtype == dtype
    if name == "planar3":
        torch.testing.assert_close(fk.cpu().double(), planar_fk(q), atol=_tol(dtype), rtol=0)
        want = planar_jacobian(q)
        torch.testing.assert_close(J.cpu().double(), want, atol=_tol(dtype), rtol=0)


def test_control_affine_structure(dtype: torch.dtype) -> None:
    gen = torch.Generator().manual_seed(3)
    vel = Manipulator("arm7")
    x = torch.randn(5, 7, generator=gen, dtype=dtype)
    u = torch.randn(5, 7, generator=gen, dtype=dtype)
    torch.testing.assert_close(vel(x, u), u)
    torch.testing.assert_close(vel.f(x) + (vel.g(x) @ u[..., None])[..., 0], u)
    before = u.clone()
    vel(x, u).mul_(2.0)  # the rate is a copy: u stays as given
    assert torch.equal(u, before)
    acc = Manipulator("arm7", control="acceleration")
    xa = torch.randn(2, 5, 14, generator=gen, dtype=dtype)
    ua = torch.randn(2, 5, 7, generator=gen, dtype=dtype)
    xdot = acc(xa, ua)
    torch.testing.assert_close(xdot, torch.cat([xa[..., 7:], ua], -1))
    torch.testing.assert_close(xdot, acc.f(xa) + (acc.g(xa) @ ua[..., None])[..., 0])
    assert acc.g(xa).shape == (2, 5, 14, 7)
    # fk accepts the full state
    torch.testing.assert_close(acc.fk(xa), vel.fk(xa[..., :7]))
    with pytest.raises(ValueError, match=r"\[\.\.\., 14\]"):
        acc(xa[..., :7], ua)


def test_random_configurations_within_limits() -> None:
    arm = Manipulator("arm7")
    q = arm.random_configurations(500, generator=torch.Generator().manual_seed(0), margin=0.1)
    assert bool(
        (q >= arm.q_min.float() + 0.1 - 1e-6).all() and (q <= arm.q_max.float() - 0.1 + 1e-6).all()
    )
    q2 = arm.random_configurations(500, generator=torch.Generator().manual_seed(0), margin=0.1)
    torch.testing.assert_close(q, q2)


def test_resolved_rate_decreases_distance(planar: Manipulator) -> None:
    gen = torch.Generator().manual_seed(4)
    q = planar.random_configurations(32, generator=gen, dtype=torch.float64)
    target = torch.tensor([0.6, 0.5, 0.0], dtype=torch.float64)
    ctrl = ResolvedRateController(planar, target, gain=2.0, damping=0.05)
    u = ctrl(q)
    assert u.shape == (32, 3)
    vmax = planar.velocity_limit
    assert bool((u.abs() <= vmax + 1e-12).all())
    # dV/dt = -2 e' J u < 0 wherever the error is not in the Jacobian's null space
    e = target - planar.end_effector(q)
    vdot = -2 * (e * (planar.jacobian(q) @ u[..., None])[..., 0]).sum(-1)
    assert bool((vdot < 0).all())
    # acceleration control: qddot = k_v (qdot* - qdot)
    acc = Manipulator("planar3", control="acceleration")
    ctrl_a = ResolvedRateController(acc, target, gain=2.0, velocity_gain=3.0)
    x = torch.cat([q, torch.zeros_like(q)], -1)
    torch.testing.assert_close(ctrl_a(x), 3.0 * u)
    with pytest.raises(ValueError, match="target"):
        ResolvedRateController(planar, [1.0, 2.0])


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_joint_space_controller(planar: Manipulator, dtype: torch.dtype) -> None:
    gen = torch.Generator().manual_seed(5)
    q = planar.random_configurations(16, generator=gen, dtype=dtype)
    qt = planar.random_configurations(16, generator=gen, dtype=dtype)
    ctrl = JointSpaceController(planar, qt, gain=2.0)
    u = ctrl(q)
    assert u.shape == (16, 3) and u.dtype == dtype
    vmax = planar.velocity_limit.to(dtype)
    # reference, row by row: -k e, scaled down uniformly when a joint exceeds its limit
    for b in range(16):
        ref = -2.0 * (q[b] - qt[b])
        ref = ref / max(1.0, float((ref.abs() / vmax).max()))
        torch.testing.assert_close(u[b], ref)
    assert bool((u.abs() <= vmax * (1 + 1e-6)).all())
    # V = |q - q*|^2 decreases: dV/dt = 2 (q - q*)' u < 0
    assert bool((((q - qt) * u).sum(-1) < 0).all())
    # an unsaturated near-target row equals the plain law; one target broadcasts
    single = JointSpaceController(planar, qt[0], gain=2.0)
    torch.testing.assert_close(single(qt[0] + 0.01), torch.full((3,), -0.02, dtype=dtype))
    # acceleration control: qddot = k_v (qdot* - qdot)
    acc = Manipulator("planar3", control="acceleration")
    ctrl_a = JointSpaceController(acc, qt, gain=2.0, velocity_gain=3.0)
    x = torch.cat([q, 0.1 * torch.ones_like(q)], -1)
    torch.testing.assert_close(ctrl_a(x), 3.0 * (u - 0.1))
    with pytest.raises(ValueError, match="target"):
        JointSpaceController(planar, [1.0, 2.0])
    with pytest.raises(ValueError, match="gain"):
        JointSpaceController(planar, qt, gain=0.0)
    with pytest.raises(TypeError, match="arm"):
        JointSpaceController("planar3", qt)  # type: ignore[arg-type]


def test_missing_pytorch_kinematics_raises_clear_error(monkeypatch: pytest.MonkeyPatch) -> None:
    # simulates the optional dependency not installed (an import of it then fails)
    monkeypatch.setitem(sys.modules, "pytorch_kinematics", None)
    with pytest.raises(ImportError, match=r'pip install "torchcbf\[arm\]"'):
        Manipulator("planar3")


def test_import_without_pytorch_kinematics() -> None:
    code = (
        "import sys; sys.modules['pytorch_kinematics'] = None\n"
        "import torchcbf, torchcbf.dynamics, torchcbf.barriers\n"
        "import torchcbf.dynamics.manipulator as m, torchcbf.barriers.workspace as w\n"
        "assert m.asset_path('arm7').is_file()\n"
        "try:\n"
        "    m.Manipulator('arm7')\n"
        "except ImportError as e:\n"
        "    assert 'torchcbf[arm]' in str(e), e\n"
        "    print('ok')\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "ok"


_SLIDE_URDF = """<robot name="g"><link name="base"/><link name="l1"/><link name="finger"/>
<link name="tip"/>
<joint name="j1" type="continuous"><parent link="base"/><child link="l1"/>
 <axis xyz="0 0 1"/><limit effort="10" velocity="2.0"/></joint>
<joint name="slide" type="prismatic"><parent link="l1"/><child link="finger"/>
 <origin xyz="0.3 0 0"/><axis xyz="1 0 0"/>
 <limit lower="0.0" upper="0.1" effort="1" velocity="0.1"/></joint>
<joint name="jt" type="fixed"><parent link="finger"/><child link="tip"/>
 <origin xyz="0.1 0 0"/></joint></robot>"""


def test_a_continuous_joint_has_no_position_limits_and_a_short_joint_keeps_its_room() -> None:
    """A continuous joint (no lower/upper in the URDF) is unlimited, not pinned at [0, 0];
    a margin wider than a joint's range is refused; roadmap nodes stay inside the limits
    of a 0.1 m slide (the fixed 0.15 margin drew half of them outside)."""
    from torchcbf.barriers import JointLimitBarrier, LinkSphereBarrier
    from torchcbf.roadmap import sample_free_configurations

    arm = Manipulator(_SLIDE_URDF).double()
    assert arm.q_min.tolist() == [-float("inf"), 0.0] and arm.q_max.tolist() == [float("inf"), 0.1]
    gen = torch.Generator().manual_seed(0)
    q = arm.random_configurations(500, generator=gen)
    assert q[:, 0].std() > 1.0 and bool(((q[:, 1] >= 0.0) & (q[:, 1] <= 0.1)).all())
    with pytest.raises(ValueError, match=r"no room in joint\(s\) \[1\]"):
        arm.random_configurations(5, margin=0.15)
    JointLimitBarrier(arm)  # the continuous joint leaves no empty range
    ball = LinkSphereBarrier(arm, ["tip"], 0.02, [5.0, 5.0, 0.0], 0.1).double()
    nodes = sample_free_configurations(arm, ball, 100, 0.0, gen, torch.float64,
                                       torch.device("cpu"))  # fmt: skip
    assert bool(((nodes >= arm.q_min) & (nodes <= arm.q_max)).all())


@pytest.mark.parametrize("name", ["planar3", "arm7"])
def test_the_null_space_task_leaves_the_end_effector_still(name: str) -> None:
    """``k_0 (I - J^+ J)(q_mid - q)`` adds no end-effector velocity: with the damped
    pseudo-inverse of the primary task it would (and the arm would stop short)."""
    arm = Manipulator(name).double()
    gen = torch.Generator().manual_seed(2)
    q = arm.random_configurations(64, generator=gen, margin=0.3, dtype=torch.float64)
    target = arm.end_effector(arm.random_configurations(64, generator=gen, margin=0.3))
    kw = {"gain": 2.0, "damping": 0.05, "saturate": False}
    plain = ResolvedRateController(arm, target, **kw)(q)
    centred = ResolvedRateController(arm, target, null_space_gain=1.0, **kw)(q)
    extra = centred - plain
    assert bool((extra.norm(dim=-1) > 1e-3).any())  # the task does move the joints
    moved = (arm.jacobian(q) @ extra.unsqueeze(-1)).squeeze(-1).norm(dim=-1)
    assert float(moved.max()) < 1e-9 * (1.0 + float(extra.norm(dim=-1).max()))


def test_limits_given_on_one_side_and_a_joint_that_cannot_move() -> None:
    arm = Manipulator("planar3", u_min=-1.0)
    assert arm.u_min.tolist() == [-1.0] * 3 and arm.u_max.tolist() == [1.5, 2.0, 2.5]
    acc = Manipulator("planar3", control="acceleration", accel_limit=4.0, u_max=2.0)
    assert acc.u_min.tolist() == [-4.0] * 3 and acc.u_max.tolist() == [2.0] * 3
    assert Manipulator("planar3.urdf").dof == 3
    with pytest.raises(ValueError, match="not well-formed XML"):
        Manipulator("<robot name='x'><link name='a'></robot>")
    no_effort = (
        '<robot name="r"><link name="a"/><link name="b"/><joint name="j" type="revolute">'
        '<parent link="a"/><child link="b"/><limit lower="-1" upper="1" velocity="1"/>'
        "</joint></robot>"
    )
    with pytest.raises(ValueError, match="(?s)not a valid URDF: .*effort"):
        Manipulator(no_effort)
    no_limit = no_effort.replace('<limit lower="-1" upper="1" velocity="1"/>', "")
    with pytest.raises(ValueError, match="revolute joint 'j' has no <limit>"):
        Manipulator(no_limit)
    assert Manipulator(no_limit.replace("revolute", "continuous")).q_max.tolist() == [math.inf]
    with pytest.raises(ValueError, match="margin must be >= 0"):
        arm.random_configurations(4, margin=-0.5)
    # a joint whose velocity limit is zero stays still; the others still move
    urdf = asset_path("planar3").read_text().replace('velocity="2.0"', 'velocity="0"', 1)
    frozen = Manipulator(urdf).double()
    assert frozen.velocity_limit.tolist()[1] == 0.0
    q = torch.tensor([[0.3, 0.2, -0.1]], dtype=torch.float64)
    at_target = JointSpaceController(frozen, q[0])(q)
    assert torch.equal(at_target, torch.zeros_like(q))
    away = JointSpaceController(frozen, torch.zeros(3, dtype=torch.float64))(q)
    assert away[0, 1] == 0.0 and bool((away[0, [0, 2]] != 0).all())


def test_a_floating_joint_and_controller_gains_that_are_not_finite_are_refused() -> None:
    floating = (
        '<robot name="r"><link name="a"/><link name="b"/><joint name="j" type="floating">'
        '<parent link="a"/><child link="b"/></joint></robot>'
    )
    with pytest.raises(ValueError, match="joint 'j' is of type 'floating'"):
        Manipulator(floating)
    missing = floating.replace('type="floating"', 'type="continuous"').replace(
        'parent link="a"', 'parent link="nope"'
    )
    with pytest.raises(ValueError, match="urdf names a link it does not define"):
        Manipulator(missing)
    arm = Manipulator("planar3")
    for kwargs in ({"gain": math.inf}, {"velocity_gain": math.nan}, {"damping": math.inf}):
        with pytest.raises(ValueError, match="must be a finite number"):
            ResolvedRateController(arm, [0.5, 0.5, 0.0], **kwargs)
    with pytest.raises(ValueError, match="gain must be a finite number > 0"):
        JointSpaceController(arm, [0.1, 0.2, 0.3], gain=math.inf)
    # a target given as numbers stays exact for a float64 state
    ctrl = JointSpaceController(arm, [0.1, 0.2, 0.3])
    q = torch.tensor([0.1, 0.2, 0.3], dtype=torch.float64)
    assert float(ctrl.joint_velocity(q).abs().max()) == 0.0
