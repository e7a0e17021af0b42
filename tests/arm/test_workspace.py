"""Workspace barriers: values against hand-computed geometry, Lie derivatives through the
kinematics against finite differences (both arms, both control modes), batching."""

from __future__ import annotations

import pytest
import torch

pytest.importorskip("pytorch_kinematics")

from _arm_reference import fd_jacobian, planar_fk  # noqa: E402

from torchcbf.barriers import Ball, rectify  # noqa: E402
from torchcbf.barriers.workspace import (  # noqa: E402
    EndEffectorBoxBarrier,
    JointLimitBarrier,
    JointVelocityBarrier,
    LinkBoxBarrier,
    LinkSphereBarrier,
    PointBarrier,
    box_signed_distance,
)
from torchcbf.dynamics.manipulator import Manipulator  # noqa: E402


def _tol(dtype: torch.dtype) -> float:
    return 1e-6 if dtype == torch.float64 else 5e-5


@pytest.fixture(scope="module")
def planar() -> Manipulator:
    return Manipulator("planar3")


def _states(arm: Manipulator, num: int, seed: int, dtype=torch.float64) -> torch.Tensor:
    gen = torch.Generator().manual_seed(seed)
    q = arm.random_configurations(num, generator=gen, dtype=dtype)
    if arm.control == "acceleration":
        qd = torch.randn(num, arm.dof, generator=gen, dtype=dtype)
        return torch.cat([q, qd], -1)
    return q


def test_link_spheres_match_hand_geometry(planar: Manipulator, dtype: torch.dtype) -> None:
    centers = [[0.6, 0.3, 0.0], [-0.2, -0.7, 0.1]]
    radii = [0.05, 0.08, 0.04]
    b = LinkSphereBarrier(planar, ["link2", "link3", "ee"], radii, centers, [0.15, 0.2]).to(dtype)
    bsq = LinkSphereBarrier(
        planar, ["link2", "link3", "ee"], radii, centers, [0.15, 0.2], squared=True
    ).to(dtype)
    q = _states(planar, 40, 0, dtype)
    p = planar_fk(q)[:, 1:]  # link2, link3, ee
    c = torch.tensor(centers, dtype=dtype)
    dist = (p[:, :, None] - c).norm(dim=-1)  # [B, 3, 2]
    clear = torch.tensor(radii, dtype=dtype)[:, None] + torch.tensor([0.15, 0.2], dtype=dtype)
    torch.testing.assert_close(b(q), (dist - clear).flatten(1), atol=_tol(dtype), rtol=0)
    torch.testing.assert_close(bsq(q), (dist**2 - clear**2).flatten(1), atol=_tol(dtype), rtol=0)
    assert b(q[0]).shape == (6,) and b(q.reshape(4, 10, 3)).shape == (4, 10, 6)


def test_link_sphere_offsets(planar: Manipulator) -> None:
    # a sphere 0.2 m along link2 sits midway between the link2 and link3 origins
    b = LinkSphereBarrier(
        planar, ["link2"], 0.0, [0.0, 0.0, 0.0], 0.1, offsets=[[0.2, 0.0, 0.0]]
    ).double()
    q = _states(planar, 20, 1)
    p = planar_fk(q)
    mid = 0.5 * (p[:, 1] + p[:, 2])
    torch.testing.assert_close(b(q)[:, 0], mid.norm(dim=-1) - 0.1, atol=1e-6, rtol=0)


def test_box_signed_distance_reference() -> None:
    gen = torch.Generator().manual_seed(2)
    p = torch.rand(500, 3, generator=gen, dtype=torch.float64) * 4 - 2
    c = torch.tensor([0.3, -0.2, 0.1], dtype=torch.float64)
    e = torch.tensor([0.5, 0.3, 0.8], dtype=torch.float64)
    sd = box_signed_distance(p, c, e)
    closest = torch.maximum(torch.minimum(p, c + e), c - e)
    inside = ((p - c).abs() <= e).all(-1)
    depth = (e - (p - c).abs()).amin(-1)
    ref = torch.where(inside, -depth, (p - closest).norm(dim=-1))
    torch.testing.assert_close(sd, ref, atol=1e-8, rtol=0)
    assert bool(inside.any() and (~inside).any())


@pytest.mark.parametrize("name", ["planar3", "arm7"])
def test_lie_derivatives_match_finite_differences(name: str) -> None:
    arm = Manipulator(name)
    links = arm.links[1:]
    center = [0.4, 0.3, 0.0] if name == "planar3" else [0.3, 0.2, 0.7]
    barriers = [
        LinkSphereBarrier(arm, links, 0.05, center, 0.15),
        LinkBoxBarrier(arm, links, 0.05, center, [0.1, 0.15, 0.2]),
        EndEffectorBoxBarrier(arm, [-1.0, -1.0, -1.0], [1.0, 1.0, 1.2]),
        PointBarrier(arm, Ball(center, 0.2, index=(0, 1, 2))),
        JointLimitBarrier(arm, margin=0.05),
    ]
    x = _states(arm, 24, 3)
    for b in barriers:
        b = b.double()
        terms = b.lie(x, arm)
        dhdx = fd_jacobian(lambda xx, b=b: b(xx).reshape(xx.shape[0], -1), x)
        k = dhdx.shape[1]
        assert terms.dhdx.reshape(24, k, -1).shape == dhdx.shape
        torch.testing.assert_close(terms.dhdx.reshape(24, k, -1), dhdx, atol=1e-6, rtol=0)
        # velocity control: L_f h = 0 and L_g h = dh/dq
        torch.testing.assert_close(terms.lfh, torch.zeros_like(terms.h))
        torch.testing.assert_close(terms.lgh.reshape(24, k, -1), dhdx, atol=1e-6, rtol=0)


def test_lie_derivatives_batch_equals_loop(planar: Manipulator, dtype: torch.dtype) -> None:
    b = LinkSphereBarrier(planar, planar.links, 0.05, [0.4, 0.3, 0.0], 0.15).to(dtype)
    x = _states(planar, 6, 4, dtype).reshape(2, 3, 3)
    terms = b.lie(x, planar)
    assert terms.lgh.shape == (2, 3, 4, 3)
    tol = 1e-12 if dtype == torch.float64 else 1e-5
    for i in range(2):
        for j in range(3):
            single = b.lie(x[i, j], planar)
            torch.testing.assert_close(terms.h[i, j], single.h, atol=tol, rtol=0)
            torch.testing.assert_close(terms.lgh[i, j], single.lgh, atol=tol, rtol=0)


def test_hessian_trace_with_diffusion() -> None:
    # tr(sigma' H sigma) through the kinematics, against a finite-difference Hessian
    arm = Manipulator("planar3", sigma=0.1)
    b = LinkSphereBarrier(arm, ["ee"], 0.05, [0.4, 0.3, 0.0], 0.15).double()
    x = _states(arm, 8, 5)
    terms = b.lie(x, arm)
    H = fd_jacobian(lambda xx: b.lie(xx, arm).dhdx[:, 0, :], x, eps=1e-5)  # [B, n, n]
    ref = 0.01 * torch.diagonal(H, dim1=-2, dim2=-1).sum(-1)
    torch.testing.assert_close(terms.hess_trace[:, 0], ref, atol=1e-5, rtol=0)


@pytest.mark.parametrize("name", ["planar3", "arm7"])
def test_acceleration_control_rectified_barrier(name: str) -> None:
    """Exponential CBF ``h_e = dh/dq qdot + k h`` through the kinematics, second order."""
    arm = Manipulator(name, control="acceleration")
    center = [0.4, 0.3, 0.0] if name == "planar3" else [0.3, 0.2, 0.7]
    h = LinkSphereBarrier(arm, arm.links[-2:], 0.05, center, 0.15).double()
    he = rectify(h, arm, form="exponential", gains=2.0)
    x = _states(arm, 10, 6)
    q, qd = x[:, : arm.dof], x[:, arm.dof :]
    # dh/dq by finite differences in q, then h_e = J_h qdot + k h
    Jh = fd_jacobian(lambda qq: h(torch.cat([qq, qd], -1)), q)  # [B, k, dof]
    val = he(x)
    ref_k = (val - (Jh @ qd[..., None])[..., 0]) / h(x)
    assert bool((ref_k > 0).all())  # the rectifier adds a positive multiple of h
    terms = he.lie(x, arm)
    # L_g h_e = dh_e/dqdot = dh/dq (the qdot enters h_e linearly)
    torch.testing.assert_close(terms.lgh, Jh, atol=1e-6, rtol=0)
    # L_f h_e = dh_e/dq qdot: finite differences of h_e along (qdot, 0)
    eps = 1e-6
    step = torch.cat([qd, torch.zeros_like(qd)], -1)
    lfh = (he(x + eps * step) - he(x - eps * step)) / (2 * eps)
    torch.testing.assert_close(terms.lfh, lfh, atol=1e-5, rtol=1e-6)
    vb = JointVelocityBarrier(arm, scale=0.5).double()
    vmax = 0.5 * arm.velocity_limit
    torch.testing.assert_close(vb(x), torch.cat([qd + vmax, vmax - qd], -1))
    eye = torch.eye(arm.dof, dtype=torch.float64)
    torch.testing.assert_close(vb.lie(x, arm).lgh, torch.cat([eye, -eye]).expand(10, -1, -1))
    exact = vb.lie(x, arm, method="analytic")
    torch.testing.assert_close(exact.lgh, vb.lie(x, arm).lgh)
    torch.testing.assert_close(exact.lfh, torch.zeros_like(exact.h))


def test_joint_limits_and_ee_box_values(planar: Manipulator) -> None:
    x = _states(planar, 10, 7)
    jl = JointLimitBarrier(planar, margin=0.1)
    lo = planar.q_min + 0.1
    hi = planar.q_max - 0.1
    torch.testing.assert_close(jl(x), torch.cat([x - lo, hi - x], -1))
    assert jl.lower_joints == [0, 1, 2] and jl.upper_joints == [0, 1, 2]
    auto, exact = jl.lie(x, planar), jl.lie(x, planar, method="analytic")
    for name in ("h", "lfh", "lgh", "dhdt", "dhdx"):
        torch.testing.assert_close(getattr(auto, name), getattr(exact, name))
    box = EndEffectorBoxBarrier(planar, [-0.5, -0.6, -0.1], [0.7, 0.8, 0.1], margin=0.02).double()
    ee = planar_fk(x)[:, -1]
    lo = torch.tensor([-0.48, -0.58, -0.08], dtype=torch.float64)
    hi = torch.tensor([0.68, 0.78, 0.08], dtype=torch.float64)
    torch.testing.assert_close(box(x), torch.cat([ee - lo, hi - ee], -1), atol=1e-6, rtol=0)
    keep_in = PointBarrier(planar, Ball([0.0, 0.0, 0.0], 1.0, index=(0, 1, 2), keep_in=True))
    torch.testing.assert_close(keep_in.double()(x), 1.0 - (ee**2).sum(-1), atol=1e-6, rtol=0)


def test_bad_arguments(planar: Manipulator) -> None:
    with pytest.raises(TypeError, match="Manipulator"):
        LinkSphereBarrier(object(), ["ee"], 0.1, [0, 0, 0], 0.1)  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="radii"):
        LinkSphereBarrier(planar, ["ee", "link2"], [0.1, 0.1, 0.1], [0, 0, 0], 0.1)
    with pytest.raises(ValueError, match="obstacle_center"):
        LinkSphereBarrier(planar, ["ee"], 0.1, [0, 0], 0.1)
    with pytest.raises(ValueError, match="obstacle_radius"):
        LinkSphereBarrier(planar, ["ee"], 0.1, [0, 0, 0], -0.1)
    with pytest.raises(ValueError, match="unknown links"):
        LinkSphereBarrier(planar, ["hand"], 0.1, [0, 0, 0], 0.1)
    with pytest.raises(ValueError, match="box_half_extents"):
        LinkBoxBarrier(planar, ["ee"], 0.1, [0, 0, 0], [0.1, 0.1])
    with pytest.raises(ValueError, match="acceleration"):
        JointVelocityBarrier(planar)
    with pytest.raises(ValueError, match="margin"):
        JointLimitBarrier(planar, margin=3.0)
