"""Workspace barriers of a robot arm: collision spheres, end-effector regions, joint limits.

Every barrier here takes a :class:`~torchcbf.dynamics.manipulator.Manipulator` and a state
``x [..., n]`` of it (``q`` for velocity control, ``(q, qdot)`` for acceleration control),
evaluates the forward kinematics, and returns ``h [..., k]`` (``k`` constraints at once).
The Lie derivatives go through the kinematics by batched autograd (``barrier.lie(x, arm)``),
so no hand-written Jacobian is involved. Under acceleration control, position-based
barriers have relative degree two: wrap them in :func:`~torchcbf.barriers.rectify`.

Collision geometry is a set of spheres fixed to links (centre = link frame origin plus an
offset in the link frame, radius ``r_s``) against obstacles that are balls or
axis-aligned boxes.
"""

from __future__ import annotations

import functools
from collections.abc import Sequence
from typing import TYPE_CHECKING

import torch
from torch import Tensor

from torchcbf._checks import behaves_as, check_number
from torchcbf._constants import DerivedConstants, reshape
from torchcbf.barriers.base import Barrier
from torchcbf.barriers.lie import AnalyticDerivatives, FollowsTime, LieFunction

if TYPE_CHECKING:
    from torchcbf.dynamics.manipulator import Manipulator

# Smoothing of the Euclidean norm at zero: keeps gradients finite (no 0/0) at the centre of
# an obstacle, and changes distances by at most this much.
_EPS = 1e-9


def _check_arm(arm: object) -> None:
    from torchcbf.dynamics.manipulator import Manipulator

    if not isinstance(arm, Manipulator):
        raise TypeError(f"arm must be a torchcbf Manipulator, got {type(arm).__name__}")


def _expanded(t: Tensor, size: int) -> Tensor:
    """A scalar as ``[size]``."""
    return t.expand(size).clone()


def _one_row(t: Tensor) -> Tensor:
    """``[d]`` as ``[1, d]``."""
    return t.unsqueeze(0)


def _norm(v: Tensor) -> Tensor:
    """``|v|`` over the last axis, smoothed at zero."""
    return torch.sqrt((v * v).sum(-1) + _EPS**2)


class _Shaped(Barrier, DerivedConstants):
    """A barrier whose constants :func:`~torchcbf._constants.reshape` shapes (a parameter is
    kept and shaped at each read, so that it trains)."""


class _LinkSpheres(_Shaped):
    """Shared part of the sphere barriers: ``S`` spheres on links of ``arm``."""

    def __init__(
        self,
        arm: Manipulator,
        links: Sequence[str],
        radii: Tensor | float | Sequence[float],
        offsets: Tensor | Sequence[Sequence[float]] | None,
    ) -> None:
        super().__init__()
        _check_arm(arm)
        self.arm = arm
        self.links = arm.check_links(links)
        s = len(self.links)
        r = self.register_constant("radii", radii)
        if r.dim() == 0:
            reshape(self, "radii", functools.partial(_expanded, size=s))
        elif r.shape != (s,):
            raise ValueError(
                f"radii must be a scalar or [{s}] (one per link), got {tuple(r.shape)}"
            )
        if bool((self.radii.detach() < 0).any()):
            raise ValueError(f"radii must be >= 0, got {self.radii.detach().tolist()}")
        self.register_buffer("offsets", None)
        if offsets is not None:
            off = self.register_constant("offsets", offsets)
            if off.shape != (s, 3):
                raise ValueError(f"offsets must have shape [{s}, 3], got {tuple(off.shape)}")

    @property
    def num_spheres(self) -> int:
        """Number of collision spheres ``S``."""
        return len(self.links)

    def centers(self, x: Tensor) -> Tensor:
        """Sphere centres in the world: ``x [..., n] -> [..., S, 3]``."""
        off = None if self.offsets is None else self.offsets.to(x)
        return self.arm.fk(x, self.links, off)


def _obstacles(module: Barrier, center: object) -> int:
    """Register obstacle centres ``obstacle_center [O, 3]``; return ``O``."""
    c = module.register_constant("obstacle_center", center)
    if c.dim() == 1:
        reshape(module, "obstacle_center", _one_row)
    if module.obstacle_center.dim() != 2 or module.obstacle_center.shape[-1] != 3:
        raise ValueError(f"obstacle_center must have shape [3] or [O, 3], got {tuple(c.shape)}")
    return module.obstacle_center.shape[0]


class LinkSphereBarrier(_LinkSpheres):
    """Collision spheres on links against ball obstacles: ``h [..., S * O]``.

    ``h[s * O + o] = |p_s - c_o| - (r_s + R_o)`` (distance form, 1-Lipschitz in the sphere
    centre), or ``|p_s - c_o|^2 - (r_s + R_o)^2`` with ``squared=True``.

    Args:
        arm: the :class:`~torchcbf.dynamics.manipulator.Manipulator`.
        links: ``S`` link names (a link may carry several spheres: repeat its name).
        radii: sphere radii, scalar or ``[S]``.
        obstacle_center: ``[3]`` or ``[O, 3]`` (world frame).
        obstacle_radius: ``R > 0``, scalar or ``[O]``.
        offsets: sphere centres in their link frames ``[S, 3]`` (default: frame origins).
        squared: use the squared-distance form.
    """

    def __init__(
        self,
        arm: Manipulator,
        links: Sequence[str],
        radii: Tensor | float | Sequence[float],
        obstacle_center: Tensor | Sequence[float] | Sequence[Sequence[float]],
        obstacle_radius: Tensor | float | Sequence[float],
        *,
        offsets: Tensor | Sequence[Sequence[float]] | None = None,
        squared: bool = False,
    ) -> None:
        super().__init__(arm, links, radii, offsets)
        o = _obstacles(self, obstacle_center)
        rad = self.register_constant("obstacle_radius", obstacle_radius)
        if rad.dim() == 0:
            reshape(self, "obstacle_radius", functools.partial(_expanded, size=o))
        elif rad.shape != (o,):
            raise ValueError(f"obstacle_radius must be a scalar or [{o}], got {tuple(rad.shape)}")
        if bool((self.obstacle_radius.detach() <= 0).any()):
            raise ValueError(
                f"obstacle_radius must be > 0, got {self.obstacle_radius.detach().tolist()}"
            )
        self.squared = bool(squared)

    def forward(self, x: Tensor, t: Tensor | float | None = None) -> Tensor:
        """``x [..., n] -> h [..., S * O]``."""
        p = self.centers(x)  # [..., S, 3]
        diff = p.unsqueeze(-2) - self.obstacle_center.to(x)  # [..., S, O, 3]
        clearance = self.radii.to(x)[:, None] + self.obstacle_radius.to(x)  # [S, O]
        if self.squared:
            h = (diff * diff).sum(-1) - clearance**2
        else:
            h = _norm(diff) - clearance
        return h.flatten(-2)

    def extra_repr(self) -> str:
        return f"links={self.links}, obstacles={self.obstacle_center.shape[0]}"


def box_signed_distance(p: Tensor, center: Tensor, half_extents: Tensor) -> Tensor:
    """Signed distance of points to axis-aligned boxes (negative inside).

    ``p [..., 3]`` against ``center, half_extents [3]`` (broadcasting) ``-> [...]``.
    Outside the box this is the Euclidean distance, continuously differentiable (its
    gradient is the unit vector from the closest box point); inside it is minus the distance
    to the nearest face. The norm is smoothed at zero by ``1e-9`` so gradients stay finite.
    """
    d = (p - center).abs() - half_extents
    outside = torch.sqrt((d.clamp_min(0) ** 2).sum(-1) + _EPS**2) - _EPS
    inside = d.amax(-1).clamp_max(0)
    return outside + inside


class LinkBoxBarrier(_LinkSpheres):
    """Collision spheres on links against axis-aligned box obstacles: ``h [..., S * O]``.

    ``h[s * O + o] = sd_o(p_s) - r_s`` with ``sd_o`` the signed distance to box ``o``
    (:func:`box_signed_distance`): exact Euclidean clearance, continuously differentiable
    wherever the sphere centre is outside the box (everywhere on the safe set).

    Args:
        arm, links, radii, offsets: as for :class:`LinkSphereBarrier`.
        box_center: ``[3]`` or ``[O, 3]``.
        box_half_extents: positive, ``[3]`` or ``[O, 3]``.
    """

    def __init__(
        self,
        arm: Manipulator,
        links: Sequence[str],
        radii: Tensor | float | Sequence[float],
        box_center: Tensor | Sequence[float] | Sequence[Sequence[float]],
        box_half_extents: Tensor | Sequence[float] | Sequence[Sequence[float]],
        *,
        offsets: Tensor | Sequence[Sequence[float]] | None = None,
    ) -> None:
        super().__init__(arm, links, radii, offsets)
        o = _obstacles(self, box_center)
        e = self.register_constant("half_extents", box_half_extents)
        if e.dim() == 1:
            reshape(self, "half_extents", _one_row)
        if self.half_extents.shape != (o, 3):
            raise ValueError(
                f"box_half_extents must have shape [3] or [{o}, 3], got {tuple(e.shape)}"
            )
        if bool((self.half_extents.detach() <= 0).any()):
            raise ValueError(
                f"box_half_extents must be > 0, got {self.half_extents.detach().tolist()}"
            )

    def forward(self, x: Tensor, t: Tensor | float | None = None) -> Tensor:
        """``x [..., n] -> h [..., S * O]``."""
        p = self.centers(x).unsqueeze(-2)  # [..., S, 1, 3]
        sd = box_signed_distance(p, self.obstacle_center.to(x), self.half_extents.to(x))
        return (sd - self.radii.to(x)[:, None]).flatten(-2)

    def extra_repr(self) -> str:
        return f"links={self.links}, boxes={self.obstacle_center.shape[0]}"


class EndEffectorBoxBarrier(Barrier):
    """Keep a link point (the end effector by default) inside a box: ``h [..., 6]``.

    ``h = (p - low - r, high - r - p)``: one smooth constraint per face (better for a
    CBF-QP than their minimum), ``r`` a margin (e.g. a tool radius).

    Args:
        arm: the manipulator.
        low, high: box corners ``[3]``, ``low + 2 r < high``.
        link: the link (default ``arm.end_link``); ``offset`` a point in its frame ``[3]``.
        margin: ``r >= 0``.
    """

    def __init__(
        self,
        arm: Manipulator,
        low: Tensor | Sequence[float],
        high: Tensor | Sequence[float],
        *,
        link: str | None = None,
        offset: Tensor | Sequence[float] | None = None,
        margin: float = 0.0,
    ) -> None:
        super().__init__()
        _check_arm(arm)
        self.arm = arm
        self.link = arm.check_links([link or arm.end_link])[0]
        lo = self.register_constant("low", low)
        hi = self.register_constant("high", high)
        if lo.shape != (3,) or hi.shape != (3,):
            raise ValueError(
                f"low and high must have shape [3], got {tuple(lo.shape)}, {tuple(hi.shape)}"
            )
        margin = check_number("margin", margin, low=0.0)
        if bool((lo.detach() + 2 * margin >= hi.detach()).any()):
            raise ValueError(
                f"low {lo.detach().tolist()} + 2 margin must be below high {hi.detach().tolist()}"
            )
        self.margin = float(margin)
        _register_offset(self, offset)

    def forward(self, x: Tensor, t: Tensor | float | None = None) -> Tensor:
        """``x [..., n] -> h [..., 6]``."""
        p = _point(self.arm, x, self.link, self.offset)
        lo = self.low.to(x) + self.margin
        hi = self.high.to(x) - self.margin
        return torch.cat([p - lo, hi - p], -1)


def _register_offset(module: Barrier, offset: Tensor | Sequence[float] | None) -> None:
    """The buffer ``module.offset``: a point ``[3]`` in the link frame, or ``None``."""
    module.register_buffer("offset", None)
    if offset is not None:
        off = module.register_constant("offset", offset)
        if off.shape != (3,):
            raise ValueError(f"offset must have shape [3], got {tuple(off.shape)}")


def _point(arm: Manipulator, x: Tensor, link: str, offset: Tensor | None) -> Tensor:
    off = None if offset is None else offset.to(x).unsqueeze(0)
    return arm.fk(x, [link], off)[..., 0, :]


class PointBarrier(Barrier):
    """Any position-space barrier applied to a link point: ``h(x) = shape(p(x))``.

    ``shape`` is a barrier on a 3-vector "state" ``p [..., 3]`` (e.g.
    ``Ball(center, r, index=(0, 1, 2))`` to keep the end effector out of a ball,
    ``Ball(..., keep_in=True)`` to keep it in, ``HalfSpace``, ``Box``, their unions and
    intersections); the output shape is the shape's (``[...]`` or ``[..., k]``).

    Args:
        arm: the manipulator.
        shape: the position-space barrier (time-varying shapes receive ``t``).
        link: the link (default ``arm.end_link``); ``offset`` a point in its frame ``[3]``.
    """

    time_varying = FollowsTime(lambda self: self.shape.time_varying)

    def __init__(
        self,
        arm: Manipulator,
        shape: LieFunction,
        *,
        link: str | None = None,
        offset: Tensor | Sequence[float] | None = None,
    ) -> None:
        super().__init__()
        _check_arm(arm)
        if not isinstance(shape, LieFunction):
            raise TypeError(f"shape must be a Barrier, got {type(shape).__name__}")
        self.arm = arm
        self.shape = shape
        self.link = arm.check_links([link or arm.end_link])[0]
        _register_offset(self, offset)

    def forward(self, x: Tensor, t: Tensor | float | None = None) -> Tensor:
        """``x [..., n] -> h [...]`` (or ``[..., k]``)."""
        return self.shape(_point(self.arm, x, self.link, self.offset), t)


class JointLimitBarrier(Barrier):
    """Joint position limits from the URDF: ``h = (q - q_min - m, q_max - m - q)``.

    Joints without a finite limit are left out, so ``h [..., k]`` has ``k <= 2 dof``
    entries (``k = 2 dof`` when every joint is limited): first the lower bounds of the
    limited joints, then the upper ones (``lower_joints``/``upper_joints`` name them).
    Relative degree one under velocity control, two under acceleration control.

    Args:
        arm: the manipulator.
        margin: ``m >= 0`` kept from each limit (radians or metres).
    """

    def __init__(self, arm: Manipulator, margin: float = 0.0) -> None:
        super().__init__()
        _check_arm(arm)
        margin = check_number("margin", margin, low=0.0)
        self.arm = arm
        self.margin = float(margin)
        lo_ok = torch.isfinite(arm.q_min)
        hi_ok = torch.isfinite(arm.q_max)
        if not bool(lo_ok.any() or hi_ok.any()):
            raise ValueError("the arm has no finite joint position limit")
        if bool((arm.q_min + 2 * margin >= arm.q_max).any()):
            raise ValueError(f"margin {margin} leaves an empty range for some joint")
        self.lower_joints = [i for i in range(arm.dof) if bool(lo_ok[i])]
        self.upper_joints = [i for i in range(arm.dof) if bool(hi_ok[i])]

    def forward(self, x: Tensor, t: Tensor | float | None = None) -> Tensor:
        """``x [..., n] -> h [..., k]``."""
        q = self.arm.joint_positions(x)
        lo = self.arm.q_min.to(x)[self.lower_joints] + self.margin
        hi = self.arm.q_max.to(x)[self.upper_joints] - self.margin
        return torch.cat([q[..., self.lower_joints] - lo, hi - q[..., self.upper_joints]], -1)

    @property
    def has_analytic(self) -> bool:
        # the closed form is of the built-in joint map: an arm whose class rewrites it (a
        # gear ratio, an offset) is differentiated by autograd
        from torchcbf.dynamics.manipulator import Manipulator

        return behaves_as(self.arm, Manipulator, ("joint_positions",))

    def derivatives(self, x: Tensor, t: Tensor) -> AnalyticDerivatives:
        h = self(x)
        eye = torch.eye(x.shape[-1], dtype=x.dtype, device=x.device)
        rows = torch.cat([eye[self.lower_joints], -eye[self.upper_joints]], 0)  # [k, n]
        return _linear_derivatives(h, rows)


class JointVelocityBarrier(Barrier):
    """URDF velocity limits as a barrier on the state of an acceleration-controlled arm.

    ``h = (qdot + s v_max, s v_max - qdot)`` over the joints with a finite limit
    (``h [..., k]``, ``k <= 2 dof``; lower bounds first), relative degree one.

    Args:
        arm: a manipulator with ``control="acceleration"``.
        scale: ``s > 0``, a fraction of the URDF limit to enforce.
    """

    def __init__(self, arm: Manipulator, scale: float = 1.0) -> None:
        super().__init__()
        _check_arm(arm)
        if arm.control != "acceleration":
            raise ValueError(
                "JointVelocityBarrier needs control='acceleration' (under velocity control the "
                "limits are u_min/u_max)"
            )
        scale = check_number("scale", scale, low=0.0, strict=True)
        self.arm = arm
        self.scale = float(scale)
        ok = torch.isfinite(arm.velocity_limit)
        if not bool(ok.any()):
            raise ValueError("the arm has no finite joint velocity limit")
        self.joints = [i for i in range(arm.dof) if bool(ok[i])]

    def forward(self, x: Tensor, t: Tensor | float | None = None) -> Tensor:
        """``x [..., 2 dof] -> h [..., k]``."""
        self.arm.check_inputs(x)
        qd = x[..., self.arm.dof :][..., self.joints]
        v = self.arm.velocity_limit.to(x)[self.joints] * self.scale
        return torch.cat([qd + v, v - qd], -1)

    @property
    def has_analytic(self) -> bool:
        return True

    def derivatives(self, x: Tensor, t: Tensor) -> AnalyticDerivatives:
        h = self(x)
        eye = torch.eye(x.shape[-1], dtype=x.dtype, device=x.device)[self.arm.dof :]
        rows = torch.cat([eye[self.joints], -eye[self.joints]], 0)  # [k, n]
        return _linear_derivatives(h, rows)


def _linear_derivatives(h: Tensor, rows: Tensor) -> AnalyticDerivatives:
    """Derivatives of ``h = rows x + const`` (``h [..., k]``, ``rows [k, n]``)."""

    def quad(s: Tensor) -> Tensor:
        return torch.zeros_like(h)

    dhdx = rows.expand(*h.shape, rows.shape[-1])
    return AnalyticDerivatives(h, dhdx, torch.zeros_like(h), quad)
