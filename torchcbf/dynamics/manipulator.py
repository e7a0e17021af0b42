"""Robot arms from a URDF: kinematic joint-space models with batched, differentiable FK.

:class:`Manipulator` is a control-affine model of a serial arm in joint space, with the
forward kinematics of :mod:`pytorch_kinematics` (an optional dependency: ``pip install
"torchcbf[arm]"``). Two control modes:

- ``control="velocity"``: state ``q [dof]``, control ``qdot [dof]`` (``f = 0``, ``g = I``).
  The URDF velocity limits become ``u_min = -v_max``, ``u_max = v_max``.
- ``control="acceleration"``: state ``(q, qdot) [2 dof]``, control ``qddot [dof]``
  (``f = (qdot, 0)``, ``g = (0, I)``). A URDF has no acceleration limits: ``accel_limit``
  (or ``u_min``/``u_max``) sets them, otherwise the control is unbounded. The URDF velocity
  limits then act on the state: enforce them with
  :class:`~torchcbf.barriers.workspace.JointVelocityBarrier`.

Joint position limits are read from the URDF too; enforce them with
:class:`~torchcbf.barriers.workspace.JointLimitBarrier` (relative degree one under velocity
control, two under acceleration control: wrap it in :func:`~torchcbf.barriers.rectify`).
Effort limits are stored (``effort_limit``) for reference only: these are kinematic models
without an inertia matrix, so torques are not modelled.

Point targets become configurations with :meth:`Manipulator.inverse_kinematics`: batched
damped least squares (Levenberg-Marquardt) inside the joint limits, with random restarts
solved in one batch and an optional clearance penalty from workspace barriers.

Small arm descriptions ship with torchcbf: ``asset_path("planar3")`` (three revolute joints
about ``z``, links 0.5, 0.4, 0.3 m) and ``asset_path("arm7")`` (seven joints, axes ``z y z y
z y z``).
"""

from __future__ import annotations

import copy
import importlib
import importlib.resources
import math
import os
from collections.abc import Sequence
from pathlib import Path
from types import ModuleType
from typing import Any, Literal
from xml.etree import ElementTree

import torch
from torch import Tensor, nn

from torchcbf._checks import as_tensor, broadcast_shapes, check_number, check_tensor
from torchcbf.dynamics._ik import inverse_kinematics as _inverse_kinematics
from torchcbf.dynamics.base import ControlAffine, LimitSpec, SigmaSpec

ControlMode = Literal["velocity", "acceleration"]
ASSETS = ("planar3", "arm7")
_INSTALL_HINT = 'the arm models need pytorch-kinematics: pip install "torchcbf[arm]"'


def _pk() -> ModuleType:
    """Import :mod:`pytorch_kinematics` lazily, with an install hint when it is missing."""
    try:
        return importlib.import_module("pytorch_kinematics")
    except ImportError as err:
        raise ImportError(_INSTALL_HINT) from err


def asset_path(name: str) -> Path:
    """Path of a URDF shipped with torchcbf: ``"planar3"`` or ``"arm7"`` (``.urdf`` optional)."""
    stem = name[:-5] if name.endswith(".urdf") else name
    if stem not in ASSETS:
        raise ValueError(f"name must be one of {list(ASSETS)}, got {name!r}")
    return Path(str(importlib.resources.files("torchcbf") / "assets" / f"{stem}.urdf"))


def _read_urdf(source: str | bytes | os.PathLike[str]) -> str:
    """URDF XML from a path, an asset name, XML text or bytes."""
    if isinstance(source, bytes):
        return source.decode()
    if isinstance(source, os.PathLike):
        return Path(source).read_text()
    if not isinstance(source, str):
        raise TypeError(
            "urdf must be a path, an asset name, or URDF XML (str/bytes), "
            f"got {type(source).__name__}"
        )
    if source.lstrip().startswith("<"):
        return source
    if source in ASSETS or (source.removesuffix(".urdf") in ASSETS and not Path(source).is_file()):
        return asset_path(source).read_text()
    path = Path(source)
    if not path.is_file():
        raise ValueError(
            f"urdf {source!r} is neither URDF XML, an asset name {list(ASSETS)}, nor a file"
        )
    return path.read_text()


def _continuous_joints(urdf: str | bytes) -> set[str]:
    """The names of the URDF's ``continuous`` joints (no position limits)."""
    root = ElementTree.fromstring(urdf)
    return {j.get("name", "") for j in root.iter("joint") if j.get("type") == "continuous"}


#: the joint types of an arm (a floating or planar joint is a mobile base, not modelled)
_JOINT_TYPES = ("revolute", "continuous", "prismatic", "fixed")


def _check_limits_given(urdf: str | bytes) -> None:
    """A joint of another type than :data:`_JOINT_TYPES`, or a ``revolute`` or
    ``prismatic`` one without its required ``<limit>`` (the parser would read it as fixed at
    0 with a velocity limit of 0), is a ``ValueError`` naming it."""
    for j in ElementTree.fromstring(urdf).iter("joint"):
        if j.get("type") not in _JOINT_TYPES:
            raise ValueError(
                f"urdf: joint {j.get('name')!r} is of type {j.get('type')!r}; an arm's joints "
                f"are {', '.join(_JOINT_TYPES)}"
            )
        if j.get("type") in ("revolute", "prismatic") and j.find("limit") is None:
            raise ValueError(
                f"urdf: {j.get('type')} joint {j.get('name')!r} has no <limit> (URDF requires "
                "one; a joint without position limits is type='continuous')"
            )


def _limits(values: Sequence[float], fallback: float) -> list[float]:
    return [fallback if v is None or not math.isfinite(v) else float(v) for v in values]


class Manipulator(ControlAffine):
    """A serial robot arm in joint space, kinematics from a URDF (see the module docstring).

    Args:
        urdf: a path, an asset name (``"planar3"``, ``"arm7"``), or the URDF XML (str/bytes).
        end_link: the end-effector link (default: the only leaf link of the URDF tree).
        control: ``"velocity"`` (state ``q``) or ``"acceleration"`` (state ``(q, qdot)``).
        links: the links whose frame origins :meth:`fk` returns by default (default: every
            link moved by a joint, in chain order, ending with ``end_link``).
        root_link: the base link of the chain (default: the URDF root).
        accel_limit: ``|qddot| <= accel_limit`` for acceleration control, scalar or
            ``[dof]`` (for the sides ``u_min``/``u_max`` leave open).
        sigma, u_min, u_max, disturbance_bound, disturbance_matrix: as for
            :class:`~torchcbf.dynamics.ControlAffine`; ``u_min``/``u_max`` override the
            limits read from the URDF, each side on its own (a side not given keeps them).

    Buffers (float64, ``[dof]``): ``q_min``, ``q_max`` (position limits, ``+-inf`` for a
    joint without), ``velocity_limit`` and ``effort_limit`` (``inf`` where absent).

    The pytorch-kinematics chain is not a module: the model keeps one copy per
    ``(dtype, device)`` it has seen, converted lazily, so the FK follows its input's dtype
    and device (and ``.to()`` of the module is enough). Note that pytorch-kinematics parses
    URDF origins in float32, so link offsets carry float32 rounding (~1e-8 m) even in float64.
    """

    def __init__(
        self,
        urdf: str | bytes | os.PathLike[str],
        end_link: str | None = None,
        *,
        control: ControlMode = "velocity",
        links: Sequence[str] | None = None,
        root_link: str = "",
        accel_limit: LimitSpec = None,
        sigma: SigmaSpec = None,
        u_min: LimitSpec = None,
        u_max: LimitSpec = None,
        disturbance_bound: LimitSpec = None,
        disturbance_matrix: Tensor | None = None,
    ) -> None:
        if control not in ("velocity", "acceleration"):
            raise ValueError(f"control must be 'velocity' or 'acceleration', got {control!r}")
        pk = _pk()
        text = _read_urdf(urdf)
        try:
            ElementTree.fromstring(text)
        except ElementTree.ParseError as err:
            raise ValueError(f"urdf is not well-formed XML: {err}") from None
        _check_limits_given(text)
        parse_error = importlib.import_module(
            "pytorch_kinematics.urdf_parser_py.xml_reflection.core"
        ).ParseError
        try:
            tree = pk.build_chain_from_urdf(text)
        except parse_error as err:  # a required attribute missing, say
            raise ValueError(f"urdf is not a valid URDF: {err}") from None
        except KeyError as err:  # a joint between links the file does not define
            raise ValueError(f"urdf names a link it does not define: {err.args[0]!r}") from None
        if end_link is None:
            end_link = _leaf_link(tree)
        try:
            chain = pk.build_serial_chain_from_urdf(text, end_link, root_link)
        except (KeyError, ValueError) as err:
            raise ValueError(f"end_link {end_link!r} / root_link {root_link!r}: {err}") from err
        dof = int(chain.n_joints)
        if dof < 1:
            raise ValueError(
                f"the chain from {root_link or 'the root'} to {end_link!r} has no joint"
            )
        lo, hi = chain.get_joint_limits()
        # pytorch-kinematics reads a continuous joint as a revolute one with the limits the
        # URDF parser fills in (0, 0): it has none
        continuous = _continuous_joints(text)
        for i, name in enumerate(chain.get_joint_parameter_names()):
            if name in continuous:
                lo[i], hi[i] = -math.inf, math.inf
        _, vel = chain.get_joint_velocity_limits()
        _, eff = chain.get_joint_effort_limits()
        vel_lim = _limits(vel, math.inf)
        if control == "velocity":
            state_dim = dof
            # a side not given keeps the URDF's limit
            if u_min is None:
                u_min = [-v for v in vel_lim]
            if u_max is None:
                u_max = list(vel_lim)
        else:
            state_dim = 2 * dof
            if (u_min is None or u_max is None) and accel_limit is not None:
                a = as_tensor("accel_limit", accel_limit, dtype=torch.float64)
                if bool((a <= 0).any()):
                    raise ValueError(f"accel_limit must be positive, got {a.tolist()}")
                u_min = -a if u_min is None else u_min
                u_max = a if u_max is None else u_max
        super().__init__(
            state_dim,
            dof,
            sigma=sigma,
            u_min=u_min,
            u_max=u_max,
            disturbance_bound=disturbance_bound,
            disturbance_matrix=disturbance_matrix,
        )
        self.control = control
        self.dof = dof
        self.urdf = text
        self.end_link = end_link
        self.joint_names: list[str] = list(chain.get_joint_parameter_names())
        self._frame_index: dict[str, int] = dict(chain.frame_to_idx)
        self.link_names: list[str] = sorted(self._frame_index, key=self._frame_index.__getitem__)
        moving = [f.link.name for f in chain._serial_frames if f.joint.joint_type != "fixed"]
        if moving[-1] != end_link:
            moving.append(end_link)
        self.links: list[str] = self.check_links(moving if links is None else links)
        self._planar: bool | None = None  # is_planar(), found on first use
        f64 = torch.float64
        self.register_buffer("q_min", torch.tensor(_limits(lo, -math.inf), dtype=f64))
        self.register_buffer("q_max", torch.tensor(_limits(hi, math.inf), dtype=f64))
        self.register_buffer("velocity_limit", torch.tensor(vel_lim, dtype=f64))
        self.register_buffer("effort_limit", torch.tensor(_limits(eff, math.inf), dtype=f64))
        self._chain = chain
        self._chains: dict[tuple[torch.dtype, torch.device], Any] = {}

    @classmethod
    def from_urdf(
        cls,
        urdf: str | bytes | os.PathLike[str],
        end_link: str | None = None,
        *,
        control: ControlMode = "velocity",
        **kwargs: Any,
    ) -> Manipulator:
        """Build from a URDF path, asset name or XML (same arguments as the constructor)."""
        return cls(urdf, end_link, control=control, **kwargs)

    # -- dynamics --------------------------------------------------------------------------
    def f(self, x: Tensor) -> Tensor:
        """Drift ``[..., n] -> [..., n]``: zero (velocity control) or ``(qdot, 0)``."""
        if self.control == "velocity":
            return torch.zeros_like(x)
        return torch.cat([x[..., self.dof :], torch.zeros_like(x[..., self.dof :])], -1)

    def g(self, x: Tensor) -> Tensor:
        """Control matrix ``[..., n] -> [..., n, dof]``: ``I`` or ``(0, I)`` stacked."""
        eye = torch.eye(self.dof, dtype=x.dtype, device=x.device)
        if self.control == "acceleration":
            eye = torch.cat([torch.zeros_like(eye), eye], 0)
        return eye.expand(*x.shape[:-1], *eye.shape)

    def xdot(self, x: Tensor, u: Tensor) -> Tensor:
        """``f(x) + g(x) u`` in closed form: ``u`` or ``(qdot, u)``."""
        if self.control == "velocity":
            # a copy, not a view of u: a caller may write into the rate it gets
            return u.expand(broadcast_shapes(x.shape, u.shape)).clone()
        qd = x[..., self.dof :]
        shape = broadcast_shapes(qd.shape, u.shape)
        return torch.cat([qd.expand(shape), u.expand(shape)], -1)

    # -- kinematics ------------------------------------------------------------------------
    def joint_positions(self, x: Tensor) -> Tensor:
        """Joint angles ``q [..., dof]`` of a state ``[..., n]`` (or of ``q`` itself)."""
        check_tensor("x", x)
        if x.dim() == 0 or x.shape[-1] not in (self.dof, self.state_dim):
            raise ValueError(
                f"x must have shape [..., {self.dof}] (q) or [..., {self.state_dim}] (state), "
                f"got {tuple(x.shape)}"
            )
        return x[..., : self.dof]

    def chain(self, dtype: torch.dtype, device: torch.device | str) -> Any:
        """The pytorch-kinematics serial chain converted to ``dtype``/``device`` (cached)."""
        key = (dtype, torch.device(device))
        cached = self._chains.get(key)
        if cached is None:
            cached = copy.deepcopy(self._chain).to(dtype=dtype, device=key[1])
            self._chains[key] = cached
        return cached

    def _transforms(self, x: Tensor) -> tuple[Tensor, tuple[int, ...]]:
        """World transforms of every frame ``[F, B, 4, 4]`` and the batch shape of ``x``."""
        q = self.joint_positions(x)
        if not q.is_floating_point():
            raise TypeError(f"q must be a floating tensor, got {q.dtype}")
        batch = tuple(q.shape[:-1])
        flat = q.reshape(-1, self.dof)
        # analytical_grad=False: pytorch-kinematics' analytical backward is first-order only;
        # plain autograd keeps Hessians and nested Lie derivatives (rectify) exact.
        T = self.chain(q.dtype, q.device).forward_kinematics_tensor(flat, analytical_grad=False)
        return T, batch

    def check_links(self, links: Sequence[str] | str) -> list[str]:
        """The link names ``links`` as a list, checked against the chain (``ValueError``
        naming the unknown ones); a single name is a list of one."""
        if isinstance(links, str):
            links = [links]
        links = list(links)
        if not links:
            raise ValueError("links must name at least one link")
        unknown = [name for name in links if name not in self._frame_index]
        if unknown:
            raise ValueError(f"unknown links {unknown}; the chain has {self.link_names}")
        return links

    def link_poses(self, x: Tensor, links: Sequence[str] | None = None) -> Tensor:
        """Homogeneous world poses of links: ``x [..., dof or n] -> [..., L, 4, 4]``."""
        names = self.links if links is None else self.check_links(links)
        T, batch = self._transforms(x)
        sel = torch.stack([T[self._frame_index[name]] for name in names], 1)  # [B, L, 4, 4]
        return sel.reshape(*batch, len(names), 4, 4)

    def fk(
        self,
        x: Tensor,
        links: Sequence[str] | None = None,
        offsets: Tensor | None = None,
    ) -> Tensor:
        """World positions of link points: ``x [..., dof or n] -> [..., L, 3]``.

        Args:
            x: joint angles ``[..., dof]`` or a full state ``[..., n]``.
            links: ``L`` link names (default ``self.links``); a name may repeat.
            offsets: points in the link frames ``[L, 3]`` (default: the frame origins).
        """
        names = self.links if links is None else self.check_links(links)
        poses = self.link_poses(x, names)
        p = poses[..., :3, 3]
        if offsets is not None:
            off = as_tensor("offsets", offsets, dtype=x.dtype, device=x.device)
            if off.shape != (len(names), 3):
                raise ValueError(
                    f"offsets must have shape [{len(names)}, 3] (one point per link), "
                    f"got {tuple(off.shape)}"
                )
            p = p + (poses[..., :3, :3] @ off.unsqueeze(-1)).squeeze(-1)
        return p

    def end_effector(self, x: Tensor) -> Tensor:
        """End-effector position: ``x [..., dof or n] -> [..., 3]``."""
        return self.fk(x, [self.end_link])[..., 0, :]

    def is_planar(self) -> bool:
        """Whether the end effector moves in the x-y plane only (no joint moves it in z at a
        few random configurations; found once)."""
        if self._planar is None:
            gen = torch.Generator().manual_seed(0)
            q = self.random_configurations(4, generator=gen, dtype=torch.float64)
            J = self.jacobian(q.to(self.q_min.device))
            self._planar = bool(J[..., 2, :].abs().amax() <= 1e-9 * (1.0 + J.abs().amax()))
        return self._planar

    def jacobian(self, x: Tensor) -> Tensor:
        """Positional end-effector Jacobian ``d ee / d q``: ``x [..., dof or n] -> [..., 3, dof]``.

        The geometric Jacobian of pytorch-kinematics (closed form from the joint axes,
        independent of autograd), differentiable w.r.t. ``q``.
        """
        return self.end_effector_and_jacobian(x)[1]

    def end_effector_and_jacobian(self, x: Tensor) -> tuple[Tensor, Tensor]:
        """End-effector position ``[..., 3]`` and Jacobian ``[..., 3, dof]`` from one FK pass."""
        T, batch = self._transforms(x)
        q = self.joint_positions(x)
        chain = self.chain(q.dtype, q.device)
        J = chain.jacobian_tensor(q.reshape(-1, self.dof), all_transforms=T)
        ee = T[self._frame_index[self.end_link], :, :3, 3]
        return ee.reshape(*batch, 3), J[:, :3, :].reshape(*batch, 3, self.dof)

    def random_configurations(
        self,
        num: int,
        *,
        generator: torch.Generator | None = None,
        margin: float | Tensor = 0.0,
        dtype: torch.dtype | None = None,
        device: torch.device | str | None = None,
    ) -> Tensor:
        """Joint angles uniform within the position limits shrunk by ``margin`` (a number or
        ``[dof]``): ``[num, dof]``.

        Joints without a finite limit are drawn in ``[-pi, pi]``. Deterministic given the
        ``generator`` (which must live on ``device``). A margin that leaves a joint no room
        raises ``ValueError``.
        """
        dtype = dtype or self.q_min.dtype
        device = torch.device(device) if device is not None else self.q_min.device
        lo, hi = self.position_range()
        lo, hi = lo.to(device, dtype), hi.to(device, dtype)
        m = torch.as_tensor(margin, dtype=dtype, device=device)
        if not bool((m >= 0).all()):
            raise ValueError(f"margin must be >= 0 (it shrinks the limits), got {margin}")
        room = hi - lo - 2 * m
        if bool((room < 0).any()):
            bad = (room < 0).nonzero().flatten().tolist()
            raise ValueError(
                f"margin {margin} leaves no room in joint(s) {bad} (position ranges "
                f"{(hi - lo)[bad].tolist()})"
            )
        r = torch.rand(num, self.dof, generator=generator, dtype=dtype, device=device)
        return lo + m + r * room

    def position_range(self) -> tuple[Tensor, Tensor]:
        """The position limits ``q_min, q_max [dof]``, ``[-pi, pi]`` for a joint without
        finite ones (a continuous joint)."""
        lo = torch.where(torch.isfinite(self.q_min), self.q_min, -math.pi)
        hi = torch.where(torch.isfinite(self.q_max), self.q_max, math.pi)
        return lo, hi

    #: ``arm.inverse_kinematics(target, q_init=None, *, restarts=8, ...) -> IKResult``: joint
    #: angles whose end effector reaches point targets (projected Levenberg-Marquardt inside
    #: the joint limits, restarts in one batch, optional barrier clearance); one definition,
    #: :func:`torchcbf.dynamics._ik.inverse_kinematics`, documents every argument.
    inverse_kinematics = _inverse_kinematics

    def extra_repr(self) -> str:
        return (
            f"dof={self.dof}, control={self.control!r}, end_link={self.end_link!r}, "
            f"links={self.links}"
        )


class _JointVelocityNominal(nn.Module):
    """Shared part of the arm's nominal controllers: a target buffer, a joint velocity
    ``qdot*`` (written by subclasses in :meth:`joint_velocity`), its uniform scaling into the
    velocity limits, and ``qddot = k_v (qdot* - qdot)`` under acceleration control."""

    def __init__(
        self,
        arm: Manipulator,
        target: Tensor | Sequence[float],
        target_dim: int | None,
        gain: float,
        velocity_gain: float,
        saturate: bool,
    ) -> None:
        super().__init__()
        if not isinstance(arm, Manipulator):
            raise TypeError(f"arm must be a Manipulator, got {type(arm).__name__}")
        self.arm = arm
        target_dim = arm.dof if target_dim is None else target_dim  # None: a configuration
        # a list stays exact (float64) until a state's dtype reads it
        exact = None if isinstance(target, Tensor) else torch.float64
        t = as_tensor("target", target, dtype=exact).detach().clone()
        if t.dim() == 0 or t.shape[-1] != target_dim:
            raise ValueError(
                f"target must have shape [{target_dim}] or [B, {target_dim}], got {tuple(t.shape)}"
            )
        self.register_buffer("target", t)
        self.gain = check_number("gain", gain, low=0.0, strict=True)
        self.velocity_gain = check_number("velocity_gain", velocity_gain, low=0.0, strict=True)
        self.saturate = bool(saturate)

    def joint_velocity(self, x: Tensor) -> Tensor:
        raise NotImplementedError

    def _saturated(self, qd: Tensor) -> Tensor:
        if not self.saturate:
            return qd
        limit = self.arm.velocity_limit.to(qd)
        moves = limit > 0  # a joint whose limit is zero stays still; the others scale
        qd = torch.where(moves, qd, 0.0)
        ratio = torch.where(moves, qd.abs() / limit.clamp_min(torch.finfo(qd.dtype).tiny), 0.0)
        return qd / ratio.amax(-1, keepdim=True).clamp_min(1.0)

    def forward(self, x: Tensor, t: Tensor | float | None = None) -> Tensor:
        """Nominal control ``u [..., dof]`` at ``x [..., n]``."""
        qd = self.joint_velocity(x)
        if self.arm.control == "velocity":
            return qd
        return self.velocity_gain * (qd - x[..., self.arm.dof :])


class ResolvedRateController(_JointVelocityNominal):
    """Resolved-rate (damped least-squares) end-effector controller, a CLF-based nominal.

    With ``e = target - ee(q)`` and ``J`` the positional Jacobian, the joint velocity
    ``qdot* = J' (J J' + lambda^2 I)^{-1} k e`` decreases ``V = |e|^2`` (``dV/dt =
    -2 k e' J J' (J J' + lambda^2 I)^{-1} e <= 0``) away from singularities. Under
    acceleration control the output is ``qddot = k_v (qdot* - qdot)``. A redundant arm
    may add a secondary task in the null space of ``J``: ``k_0 (I - J^+ J)(q_mid - q)``
    pulls the joints toward the middle of their ranges (away from the limits) without
    moving the end effector (to first order; ``J^+`` the exact pseudo-inverse, not the
    damped one of the primary task, whose projector would move the end effector). With
    ``saturate=True`` the velocity ``qdot*`` is scaled down uniformly (keeping its
    direction) to fit the arm's velocity limits; a joint whose limit is zero stays still.

    Args:
        arm: the :class:`Manipulator`.
        target: end-effector target ``[3]`` or one per scenario ``[B, 3]`` (broadcast against
            the batch of states).
        gain: ``k > 0`` (1/s).
        damping: ``lambda >= 0`` (m), regularises singular configurations.
        velocity_gain: ``k_v > 0`` for acceleration control (1/s).
        null_space_gain: ``k_0 >= 0`` of the joint-centring secondary task (1/s; joints
            without finite limits are not centred).
        saturate: respect the velocity limits by uniform scaling.

    ``forward(x [..., n], t=None) -> u [..., dof]``; ``target`` is a buffer that may be
    reassigned between runs.
    """

    def __init__(
        self,
        arm: Manipulator,
        target: Tensor | Sequence[float],
        *,
        gain: float = 1.0,
        damping: float = 0.05,
        velocity_gain: float = 5.0,
        null_space_gain: float = 0.0,
        saturate: bool = True,
    ) -> None:
        super().__init__(arm, target, 3, gain, velocity_gain, saturate)
        self.damping = check_number("damping", damping, low=0.0)
        self.null_space_gain = check_number("null_space_gain", null_space_gain, low=0.0)

    def joint_velocity(self, x: Tensor) -> Tensor:
        """The resolved-rate joint velocity ``qdot* [..., dof]`` at ``x [..., n]``."""
        self.arm.check_inputs(x)
        ee, J = self.arm.end_effector_and_jacobian(x)  # [..., 3], [..., 3, dof]
        e = self.target.to(x) - ee
        eye = torch.eye(3, dtype=x.dtype, device=x.device)
        JJt = J @ J.mT + (self.damping**2) * eye
        w = torch.linalg.solve(JJt, (self.gain * e).unsqueeze(-1))
        qd = (J.mT @ w).squeeze(-1)
        if self.null_space_gain > 0:
            q = self.arm.joint_positions(x)
            lo, hi = self.arm.q_min.to(x), self.arm.q_max.to(x)
            finite = torch.isfinite(lo) & torch.isfinite(hi)
            mid = torch.where(finite, 0.5 * (lo + hi), q)
            z = (self.null_space_gain * (mid - q)).unsqueeze(-1)
            # (I - J^+ J) z with the exact pseudo-inverse (singular values below sqrt(eps)
            # of the largest count as zero: a planar arm's z row): the damped one of the
            # primary task leaks lambda^2 (J J' + lambda^2 I)^-1 J z into the end effector's
            # motion, which stops it centimetres short of its target. The projector jumps
            # where a singular value crosses that threshold (at a singular pose), and its
            # gradient grows as 1/sigma on the way there
            rtol = torch.finfo(x.dtype).eps ** 0.5
            qd = qd + (z - torch.linalg.pinv(J, rtol=rtol) @ (J @ z)).squeeze(-1)
        return self._saturated(qd)


class JointSpaceController(_JointVelocityNominal):
    """Joint-space CLF nominal toward a target configuration: ``qdot* = -k (q - q*)``.

    It decreases ``V = |q - q*|^2`` (``dV/dt = -2 k V``), also after the uniform scaling
    of ``saturate=True`` (which keeps the direction, so ``dV/dt < 0`` away from ``q*``).
    The straight joint-space path stays inside the joint-limit box when ``q`` and ``q*``
    are inside it (the box is convex), so unlike a Cartesian resolved-rate law it never
    stalls at a joint limit; it does not avoid obstacles (leave that to a safety filter).
    Under acceleration control the output is ``qddot = k_v (qdot* - qdot)``.

    Args:
        arm: the :class:`Manipulator`.
        target: target configuration ``[dof]`` or one per scenario ``[B, dof]``.
        gain: ``k > 0`` (1/s).
        velocity_gain: ``k_v > 0`` for acceleration control (1/s).
        saturate: respect the velocity limits by uniform scaling.

    ``forward(x [..., n], t=None) -> u [..., dof]``; ``target`` is a buffer that may be
    reassigned between runs.
    """

    def __init__(
        self,
        arm: Manipulator,
        target: Tensor | Sequence[float],
        *,
        gain: float = 1.0,
        velocity_gain: float = 5.0,
        saturate: bool = True,
    ) -> None:
        super().__init__(arm, target, None, gain, velocity_gain, saturate)

    def joint_velocity(self, x: Tensor) -> Tensor:
        """The joint velocity ``qdot* [..., dof]`` at ``x [..., n]``."""
        self.arm.check_inputs(x)
        q = self.arm.joint_positions(x)
        qd = -self.gain * (q - self.target.to(x))
        return self._saturated(qd)


def _leaf_link(chain: Any) -> str:
    """The only leaf link of a pytorch-kinematics chain (raise if the tree branches)."""
    leaves: list[str] = []
    stack = [chain._root]
    while stack:
        frame = stack.pop()
        if frame.children:
            stack.extend(frame.children)
        else:
            leaves.append(frame.link.name)
    if len(leaves) != 1:
        raise ValueError(f"the URDF has several leaf links {sorted(leaves)}: pass end_link=")
    return leaves[0]
