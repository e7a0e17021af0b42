"""Batched inverse kinematics of a :class:`~torchcbf.dynamics.manipulator.Manipulator` for
point targets: projected Levenberg-Marquardt with random restarts, one batch ``[B * R]``.

Each restart minimises ``|p* - ee(q)|^2 + (w sum_k relu(c + b - h_k(q)))^2`` over ``q``
inside the joint limits (``w`` the penalty weight, ``c`` the required clearance, ``b`` a small
buffer, ``h_k`` the workspace barriers), with the damped step ``dq = J' (J J' + lambda^2
I)^-1 r`` of the stacked residual ``r`` (position error, then the penalty as one residual),
projected onto the limit box (joints at a limit that the step would push outward are
frozen for that step). The damping ``lambda`` adapts per row: a step is accepted
where it lowers the objective (``lambda /= 2``), otherwise rejected (``lambda *= 4``).
Every row runs the same fixed iteration schedule; the only host synchronisation is an
optional "all rows done" test every ``check_every`` iterations.
"""

from __future__ import annotations

import math
import numbers
from collections.abc import Callable, Sequence
from typing import Literal, NamedTuple, Protocol, runtime_checkable

import torch
from torch import Tensor

from torchcbf._autograd import recordable, recording
from torchcbf._checks import (
    broadcast_shapes,
    check_int,
    check_number,
    check_positive,
    check_tensor,
)


@runtime_checkable
class Barrier(Protocol):
    """A workspace barrier as the solver sees it (a :class:`~torchcbf.barriers.Barrier` is
    one): ``x [N, n] -> h [N]`` or ``[N, k]``, with Lie derivatives."""

    def __call__(self, x: Tensor) -> Tensor: ...

    def lie(self, *args: object, **kwargs: object) -> object: ...


class Manipulator(Protocol):
    """What the solver needs of an arm (a :class:`~torchcbf.dynamics.Manipulator` has it)."""

    dof: int
    control: str
    q_min: Tensor
    q_max: Tensor

    def end_effector_and_jacobian(self, x: Tensor) -> tuple[Tensor, Tensor]: ...


_LAMBDA_MIN = 1e-3  # lambda^2 = 1e-6 keeps J J' + lambda^2 I invertible in float32
_LAMBDA_MAX = 1e4


class IKResult(NamedTuple):
    """Output of :meth:`Manipulator.inverse_kinematics` (batch shape ``[...]`` of the target).

    ``q [..., dof]``: the chosen configuration (inside the joint limits); ``converged
    [...]`` (bool): its position error is ``<= tol`` and, with barriers, every barrier value
    is ``>= clearance``; ``error [...]``: its end-effector position error (m).
    """

    q: Tensor
    converged: Tensor
    error: Tensor


def _limits(arm: Manipulator, margin: float, like: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Clamp bounds (``+-inf`` for unlimited joints) and sampling bounds (``[-pi, pi]``)."""
    lo = arm.q_min.to(like) + margin
    hi = arm.q_max.to(like) - margin
    if bool((lo > hi).any()):  # a locked joint (q_min = q_max) keeps its one value
        raise ValueError(f"limit_margin {margin} leaves an empty range for some joint")
    s_lo = torch.where(torch.isfinite(lo), lo, torch.full_like(lo, -math.pi))
    s_hi = torch.where(torch.isfinite(hi), hi, torch.full_like(hi, math.pi))
    return lo, hi, s_lo, s_hi


class _Objective:
    """Residual ``r [N, m (+1)]`` and its Jacobian ``[N, m (+1), dof]`` at ``q [N, dof]``."""

    def __init__(
        self,
        arm: Manipulator,
        target: Tensor,
        barriers: Sequence[Barrier],
        level: float,
        weight: float,
    ) -> None:
        self.arm = arm
        self.target = target  # [N, m]
        self.m = target.shape[-1]
        self.barriers = list(barriers)
        self.level = level
        self.weight = weight

    def _state(self, q: Tensor) -> Tensor:
        if self.arm.control == "velocity":
            return q
        return torch.cat([q, torch.zeros_like(q)], -1)

    def clearance(self, q: Tensor) -> Tensor:
        """Smallest barrier value ``[N]`` (``inf`` without barriers)."""
        if not self.barriers:
            return torch.full_like(q[:, 0], math.inf)
        x = self._state(q)
        return torch.cat([b(x).reshape(q.shape[0], -1) for b in self.barriers], -1).amin(-1)

    def __call__(self, q: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """``(r, J, error)`` with ``error [N]`` the position error."""
        ee, J = self.arm.end_effector_and_jacobian(q)
        e = self.target - ee[:, : self.m]
        J = J[:, : self.m]
        error = e.norm(dim=-1)
        if not self.barriers:
            return e, J, error
        with recording():  # under inference mode too
            qg = recordable(q).detach().requires_grad_(True)
            x = self._state(qg)
            h = torch.cat([b(x).reshape(q.shape[0], -1) for b in self.barriers], -1)
            pen = self.weight * torch.relu(self.level - h).sum(-1)  # [N]
            (grad,) = torch.autograd.grad(pen.sum(), qg, allow_unused=True)
        if grad is None:
            grad = torch.zeros_like(q)
        # Gauss-Newton solves J dq = r: e(q + dq) ~ e - J dq for the position residual, and
        # pen(q + dq) ~ pen + grad dq for the penalty, whose row is therefore (grad, -pen)
        r = torch.cat([e, -pen.detach().unsqueeze(-1)], -1)
        Jr = torch.cat([J, grad.detach().unsqueeze(-2)], -2)
        return r, Jr, error


def inverse_kinematics(
    arm: Manipulator,
    target: Tensor,
    q_init: Tensor | None = None,
    *,
    restarts: int = 8,
    iters: int = 100,
    tol: float = 1e-4,
    damping: float = 1e-2,
    barriers: Sequence[Barrier] = (),
    clearance: float = 0.0,
    penalty_weight: float = 1.0,
    penalty_buffer: float = 1e-3,
    limit_margin: float = 0.0,
    prefer: Literal["nearest", "error"] = "nearest",
    check_every: int = 10,
    reseed_every: int = 25,
    generator: torch.Generator | None = None,
    seed: int = 0,
) -> IKResult:
    """Configurations whose end effector reaches point targets (see the module docstring).

    Args:
        arm: the :class:`~torchcbf.dynamics.manipulator.Manipulator`.
        target: ``[..., 3]``, or ``[..., 2]`` for a planar arm (only ``x, y`` are matched; an
            arm whose end effector also moves in z refuses it).
        q_init: initial guess ``[..., dof]`` (broadcast against the target's batch): the
            first restart starts there, the others uniformly inside the joint limits (joints
            without limits in ``[-pi, pi]``); ``None``: all restarts random.
        restarts: ``R >= 1`` starts per target, solved together as one batch ``[B * R]``.
        iters: Levenberg-Marquardt iterations (a fixed schedule).
        tol: position error (m) below which a solution counts as converged.
        damping: initial ``lambda > 0`` (m).
        barriers: workspace barriers of the arm (e.g. a
            :class:`~torchcbf.barriers.workspace.LinkSphereBarrier`) evaluated at ``q``
            (zero joint velocity under acceleration control); a solution must keep every
            value ``>= clearance``, and the objective penalises values below
            ``clearance + penalty_buffer`` with weight ``penalty_weight``.
        limit_margin: keep this far (rad or m) inside the URDF position limits.
        prefer: among the valid solutions of a target (converged and clear), the one
            ``"nearest"`` to ``q_init`` in joint space (smallest error without ``q_init``),
            or the one with the smallest ``"error"``. Without a valid one: the smallest
            objective.
        check_every: test every this many iterations whether to stop early (one host sync
            per test): when every target has a valid solution, or, for ``prefer="nearest"``
            with ``q_init``, when every restart has one; ``0`` runs all ``iters``.
        reseed_every: every this many iterations, restarts still short of a valid solution
            start again at a new random configuration (not in the last ``reseed_every``
            iterations); ``0``: never.
        generator: random restarts (on the target's device); else ``seed``.

    Returns:
        :class:`IKResult` ``(q [..., dof], converged [...], error [...])``, in the target's
        dtype and device. The solve is not differentiated (the outputs carry no gradient).
        A row whose target is not finite is not converged (its error not finite); a start
        ``q_init`` with entries that are not finite takes random values there. The restarts
        are drawn for the whole batch, and every row iterates until all are done: a row's
        answer (which of its valid solutions) may change with the other rows.
    """
    check_tensor("target", target)
    if not target.is_floating_point():
        raise TypeError(f"target must be a floating tensor, got {target.dtype}")
    if target.dim() == 0 or target.shape[-1] not in (2, 3):
        raise ValueError(f"target must have shape [..., 3] or [..., 2], got {tuple(target.shape)}")
    if target.shape[-1] == 2 and not arm.is_planar():
        raise ValueError(
            "target [..., 2] is for a planar arm (its end effector moves in the x-y plane); "
            "this arm's also moves in z: give targets [..., 3]"
        )
    restarts = check_int("restarts", restarts, low=1)
    iters = check_int("iters", iters, low=1)
    check_every = check_int("check_every", check_every, low=0)
    reseed_every = check_int("reseed_every", reseed_every, low=0)
    if generator is None and (isinstance(seed, bool) or not isinstance(seed, numbers.Integral)):
        raise TypeError(f"seed must be an int, got {seed!r}")
    clearance = check_number("clearance", clearance)
    if prefer not in ("nearest", "error"):
        raise ValueError(f"prefer must be 'nearest' or 'error', got {prefer!r}")
    tol = check_positive("tol", tol)
    damping = check_positive("damping", damping)
    penalty_weight = check_positive("penalty_weight", penalty_weight)
    if not penalty_buffer >= 0 or not limit_margin >= 0:
        raise ValueError(
            f"penalty_buffer and limit_margin must be >= 0, got {penalty_buffer}, {limit_margin}"
        )
    barriers = list(barriers)
    for i, b in enumerate(barriers):
        if not isinstance(b, Barrier):
            raise TypeError(f"barriers[{i}] must be a Barrier (x -> h), got {type(b).__name__}")
    dof, dtype, device = arm.dof, target.dtype, target.device
    batch = tuple(target.shape[:-1])
    if q_init is not None:
        check_tensor("q_init", q_init)
        if q_init.dim() == 0 or q_init.shape[-1] != dof:
            raise ValueError(f"q_init must have shape [..., {dof}], got {tuple(q_init.shape)}")
        try:
            shape = broadcast_shapes(batch, tuple(q_init.shape[:-1]))
        except RuntimeError:
            raise ValueError(
                f"batch dimensions of target {tuple(target.shape)} and q_init "
                f"{tuple(q_init.shape)} do not broadcast"
            ) from None
        if shape != batch:
            raise ValueError(
                f"q_init {tuple(q_init.shape)} must broadcast to the target's batch {batch}"
            )
    lo, hi, s_lo, s_hi = _limits(arm, float(limit_margin), target)
    flat = target.detach().reshape(-1, target.shape[-1])
    B, R = flat.shape[0], restarts
    if generator is None:
        generator = torch.Generator(device=device).manual_seed(int(seed))
    u = torch.rand(B, R, dof, generator=generator, dtype=dtype, device=device)
    q = s_lo + u * (s_hi - s_lo)
    ref: Tensor | None = None
    if q_init is not None:
        ref = q_init.detach().to(target).expand(*batch, dof).reshape(B, dof)
        # a start that is not finite keeps its random draw there: q stays inside the limits
        q[:, 0] = torch.where(ref.isfinite(), torch.maximum(torch.minimum(ref, hi), lo), q[:, 0])
    q = q.reshape(B * R, dof)
    level = float(clearance) + float(penalty_buffer)
    obj = _Objective(arm, flat.repeat_interleave(R, 0), barriers, level, penalty_weight)
    with torch.no_grad():
        early = "restart" if prefer == "nearest" and ref is not None else "target"

        def sample(n: int) -> Tensor:
            u = torch.rand(n, dof, generator=generator, dtype=dtype, device=device)
            return s_lo + u * (s_hi - s_lo)

        q = _levenberg_marquardt(
            obj, q, lo, hi, damping, iters, check_every, tol, R, early, sample, reseed_every
        )
        r, _, error = obj(q)
        clear = obj.clearance(q)
        # a restart whose objective is not finite (a barrier's NaN) is the last choice
        cost = torch.nan_to_num((r * r).sum(-1), nan=math.inf)
        valid = (error <= tol) & (clear >= clearance)
        q, error, clear, valid, cost = (
            t.reshape(B, R, *t.shape[1:]) for t in (q, error, clear, valid, cost)
        )
        if prefer == "nearest" and ref is not None:
            score = (q - ref[:, None]).norm(dim=-1)
        else:
            score = error
        key = torch.where(valid, score, torch.full_like(score, math.inf))
        best_valid = key.argmin(-1)
        best_any = cost.argmin(-1)
        idx = torch.where(valid.any(-1), best_valid, best_any)  # [B]
        pick = idx[:, None]
        q_out = q.gather(1, pick[:, :, None].expand(B, 1, dof))[:, 0]
        conv = valid.gather(1, pick)[:, 0]
        err = error.gather(1, pick)[:, 0]
    return IKResult(q_out.reshape(*batch, dof), conv.reshape(batch), err.reshape(batch))


def _levenberg_marquardt(
    obj: _Objective,
    q: Tensor,
    lo: Tensor,
    hi: Tensor,
    damping: float,
    iters: int,
    check_every: int,
    tol: float,
    restarts: int,
    early: Literal["restart", "target"],
    sample: Callable[[int], Tensor],
    reseed_every: int,
) -> Tensor:
    """Projected LM with per-row adaptive damping (see the module docstring): ``[N, dof]``.

    Every ``check_every`` iterations it stops when every restart (``early="restart"``) or
    every target (one of its ``restarts`` consecutive rows, ``"target"``) is within ``tol``
    with a zero penalty. Every ``reseed_every`` iterations (not in the last
    ``reseed_every``), the rows not yet there restart at ``sample(N)``."""
    q = torch.maximum(torch.minimum(q, hi), lo)
    r, J, error = obj(q)
    cost = (r * r).sum(-1)
    lam = torch.full_like(cost, damping)
    k = r.shape[-1]
    eye = torch.eye(k, dtype=q.dtype, device=q.device)
    for it in range(iters):
        step = _damped_step(J, r, lam, eye)
        # joints at a limit that the step pushes outward are frozen, and the step recomputed
        # without them (otherwise the projection wastes it and the row stalls at the limit)
        blocked = ((q <= lo) & (step < 0)) | ((q >= hi) & (step > 0))
        step = _damped_step(J * (~blocked)[:, None, :], r, lam, eye)
        q_new = torch.maximum(torch.minimum(q + step, hi), lo)
        r_new, J_new, err_new = obj(q_new)
        cost_new = (r_new * r_new).sum(-1)
        ok = cost_new < cost  # NaN rows are rejected and keep their last finite iterate
        q = torch.where(ok[:, None], q_new, q)
        r = torch.where(ok[:, None], r_new, r)
        J = torch.where(ok[:, None, None], J_new, J)
        cost = torch.where(ok, cost_new, cost)
        error = torch.where(ok, err_new, error)
        lam = torch.where(ok, lam * 0.5, lam * 4.0).clamp(_LAMBDA_MIN, _LAMBDA_MAX)
        if reseed_every and (it + 1) % reseed_every == 0 and it + 1 + reseed_every <= iters:
            stuck = (error > tol) | (r[:, obj.m :] != 0).any(-1)
            q = torch.where(stuck[:, None], sample(q.shape[0]), q)
            r_new, J_new, err_new = obj(q)
            r = torch.where(stuck[:, None], r_new, r)
            J = torch.where(stuck[:, None, None], J_new, J)
            error = torch.where(stuck, err_new, error)
            cost = torch.where(stuck, (r_new * r_new).sum(-1), cost)
            lam = torch.where(stuck, torch.full_like(lam, damping), lam)
        if check_every and (it + 1) % check_every == 0:
            done = (error <= tol) & (r[:, obj.m :] == 0).all(-1)
            if early == "target":
                done = done.reshape(-1, restarts).any(-1)
            if bool(done.all()):
                break
    return q


def _damped_step(J: Tensor, r: Tensor, lam: Tensor, eye: Tensor) -> Tensor:
    """``J' (J J' + lambda^2 I)^-1 r``: ``J [N, k, dof]``, ``r [N, k]``, ``lam [N]`` ->
    ``[N, dof]``."""
    A = J @ J.mT + (lam * lam)[:, None, None] * eye
    sol, _ = torch.linalg.solve_ex(A, r.unsqueeze(-1))  # a failed row gives NaN: rejected
    return (J.mT @ sol).squeeze(-1)
